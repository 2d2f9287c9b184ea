#!/usr/bin/env bash
# Console site: the web surgeon console (its page is the master: mouse and keyboard, phone,
# gamepad) or, with --master scripted / --tui, master_capture and the terminal console, on this
# machine, connected to a slave site over mutual TLS. Ctrl-C, SIGTERM or quitting stops all.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"   # this script's folder, beside the site folders
# a checkout's venv; else the Python beside telesurg on the PATH (an installed package)
py="$here/../.venv/bin/python"
if [[ ! -x "$py" ]]; then
    ts="$(command -v telesurg || true)"
    if [[ -z "$ts" ]]; then
        echo "console.sh: telesurg not found (no ../.venv beside $here, none on the PATH): activate the venv it is installed in" >&2
        exit 2
    fi
    py="$([[ -x "$(dirname "$ts")/python" ]] && echo "$(dirname "$ts")/python" || echo python3)"
fi

usage() {
    cat <<USAGE
usage: deploy/console.sh SLAVE_HOST [options]

Connects to the slave site's router at tls/SLAVE_HOST:7447 (deploy/slave-site.sh there) with
this machine's certificate and starts, by default, the web surgeon console (telesurg console
--web; open the URL it prints; the page is the master m1). With --master scripted: master_capture
(the site file's scripted or serial device) and the terminal console (telesurg console) in the
foreground. Configs from console/site.toml beside this script. Guide: docs/deploy.md,
docs/console.md.

options:
  --port N             the slave site's TLS port (default: 7447)
  --protocol P         tls or quic (default: tls; quic needs --listen quic/... on the slave site)
  --datagram N         send the master's pose, joints and buttons best effort to the slave
                       site's UDP port N (deploy/slave-site.sh --datagram-port N): a lost packet
                       costs one sample instead of stalling the stream; for a lossy WAN
  --site ID            site id, as on the slave site (default: lab)
  --certs DIR          ca.pem and IDENTITY.pem/.key (default: certs; telesurg certs)
  --identity NAME      certificate common name (default: console; console-mapping with --mapping)
  --keyring DIR        this machine's keyring: master_capture, console (console-mapping with
                       --mapping) and the link to the site, from `telesurg keys export ...
                       --to console` on the slave site
                       (default: $TELESURG_KEYS or ~/.local/state/telesurg/SITE/keys)
  --config-dir DIR     site folder: DIR/site.toml, a table per service (default: console/
                       beside this script)
  --mapping            also run the mapping here (the slave site runs with --no-mapping)
  --master M           web (default: the web console's page is the master) or scripted
                       (master_capture with the site file's device, and the terminal console)
  --web-port N         the web console's port (default 8470; the page is served on 127.0.0.1
                       unless --set console.web.host=0.0.0.0)
  --no-console         --master scripted without the terminal UI: run master_capture until
                       Ctrl-C / SIGTERM
  --log-dir DIR        service logs (default: stderr; out/console-logs under the console UI)
  --set SERVICE.KEY=VALUE
                       override a config key of master_capture, mapping or console,
                       e.g. --set master_capture.scripted.radius=0.02
  -h, --help           this help
USAGE
}

host=""
port=7447
protocol=tls
site=lab
certs=certs
identity=""
config_dir="$here/console"
mapping=0
datagram=""
ui=1
master=web
web_port=8470
log_dir=""
keyring=""
declare -A sets=([master_capture]="" [mapping]="" [console]="")
while [[ $# -gt 0 ]]; do
    case "$1" in
        -h|--help) usage; exit 0 ;;
        --port) port="$2"; shift 2 ;;
        --protocol) protocol="$2"; shift 2 ;;
        --datagram) datagram="$2"; shift 2 ;;
        --site) site="$2"; shift 2 ;;
        --certs) certs="$2"; shift 2 ;;
        --identity) identity="$2"; shift 2 ;;
        --config-dir) config_dir="$2"; shift 2 ;;
        --mapping) mapping=1; shift ;;
        --no-console) ui=0; master=scripted; shift ;;
        --master) master="$2"; shift 2 ;;
        --web-port) web_port="$2"; shift 2 ;;
        --log-dir) log_dir="$2"; shift 2 ;;
        --keyring) keyring="$2"; shift 2 ;;
        --set)
            svc="${2%%.*}"
            if [[ -z "${sets[$svc]+x}" || "$2" != *.*=* ]]; then
                echo "deploy/console.sh: --set $2: expected master_capture|mapping|console.KEY=VALUE" >&2
                exit 2
            fi
            sets[$svc]+="${2#*.}"$'\n'
            shift 2 ;;
        -*) echo "deploy/console.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
        *) if [[ -n "$host" ]]; then echo "deploy/console.sh: one SLAVE_HOST only" >&2; exit 2; fi
           host="$1"; shift ;;
    esac
done
if [[ -z "$host" ]]; then usage >&2; exit 2; fi
case "$protocol" in tls|quic) ;; *) echo "deploy/console.sh: --protocol tls or quic" >&2; exit 2 ;; esac
case "$master" in web|scripted) ;; *) echo "deploy/console.sh: --master web or scripted" >&2; exit 2 ;; esac
[[ -z "$identity" ]] && identity=$([[ $mapping == 1 ]] && echo console-mapping || echo console)
for f in ca.pem "$identity.pem" "$identity.key"; do
    if [[ ! -f "$certs/$f" ]]; then
        echo "deploy/console.sh: $certs/$f missing (copy it from where telesurg certs ran)" >&2
        exit 2
    fi
done
# this machine's keyring (it signs and verifies every message): one line saying what to do
if ! why="$("$py" - "$site" "$keyring" 2>&1 <<'PY'
import sys
from pathlib import Path

from telesurg.shared.auth import check_keyring_dir, default_keys_dir
from telesurg.shared.errors import ConfigError

site, given = sys.argv[1], sys.argv[2]
d = Path(given) if given else default_keys_dir(site)
try:
    check_keyring_dir(d)
except ConfigError as exc:
    if d.exists() or d.is_symlink():
        sys.exit(f"keyring: {exc}")
    sys.exit(
        f"no keyring at {d}: on the slave site run `telesurg keys export master_capture console "
        f"--to console --site {site} --out console-keys`, copy console-keys/ here, then pass "
        f"--keyring console-keys (or `telesurg keys import console-keys --site {site}`)"
    )
PY
)"; then
    echo "deploy/console.sh: ${why##*$'\n'}" >&2
    exit 2
fi
[[ "$host" == *:* && "$host" != \[* ]] && host="[$host]"   # IPv6 literal
bus=(--site "$site" --connect "$protocol/$host:$port" --tls-ca "$certs/ca.pem" --mtls
     --tls-cert "$certs/$identity.pem" --tls-key "$certs/$identity.key")
[[ -n "$keyring" ]] && bus+=(--keyring "$keyring")
if [[ -n "$datagram" ]]; then
    if ! [[ "$datagram" =~ ^[0-9]+$ ]] || (( datagram < 1 || datagram > 65535 )); then
        echo "deploy/console.sh: --datagram $datagram: a UDP port number, 1-65535" >&2
        exit 2
    fi
    bus+=(--datagram "udp/$host:$datagram")
fi

has_console=0
if [[ $ui == 1 ]] && "$py" -c 'import importlib.util as u, sys; sys.exit(u.find_spec("telesurg.services.console") is None)' 2>/dev/null; then
    has_console=1
    [[ -z "$log_dir" ]] && log_dir="$PWD/out/console-logs"
fi
[[ -n "$log_dir" ]] && mkdir -p "$log_dir"

pids=()
stop_all() {
    trap - INT TERM EXIT
    local pid
    for pid in "${pids[@]}"; do kill -INT "$pid" 2>/dev/null || true; done   # master first
    for pid in "${pids[@]}"; do wait "$pid" 2>/dev/null || true; done
}
trap 'stop_all; exit 0' INT TERM
trap stop_all EXIT

if [[ ! -f "$config_dir/site.toml" ]]; then
    echo "deploy/console.sh: site file $config_dir/site.toml not found (--config-dir)" >&2
    exit 2
fi

start() {  # start SERVICE (cli name) in the background with its table of the site file, overrides
    local name="$1" cli="$2" args=(--config "$config_dir/site.toml" --table "$1")
    while IFS= read -r item; do [[ -n "$item" ]] && args+=(--set "$item"); done <<< "${sets[$name]}"
    if [[ -n "$log_dir" ]]; then
        "$py" -m telesurg.services.cli "$cli" "${bus[@]}" ${args[@]+"${args[@]}"} >>"$log_dir/$name.log" 2>&1 &
    else
        "$py" -m telesurg.services.cli "$cli" "${bus[@]}" ${args[@]+"${args[@]}"} &
    fi
    pids+=($!)
    echo "console.sh: started $name (pid $!) -> $protocol/$host:$port as $identity" >&2
}

if [[ $master == web ]]; then
    # the web console is the master (its node master_capture publishes master/m1/*) and the console
    [[ $mapping == 1 ]] && start mapping mapping
    args=(--config "$config_dir/site.toml" --port "$web_port")
    while IFS= read -r item; do [[ -n "$item" ]] && args+=(--set "$item"); done <<< "${sets[console]}"
    echo "console.sh: web surgeon console on http://127.0.0.1:$web_port/ -> $protocol/$host:$port as $identity" >&2
    "$py" -m telesurg.services.cli console --web "${bus[@]}" ${args[@]+"${args[@]}"} &
    pids+=($!)
    wait "${pids[-1]}" || { rc=$?; echo "console.sh: the web console exited with code $rc" >&2; exit "$rc"; }
    exit 0
fi
start master_capture master-capture
[[ $mapping == 1 ]] && start mapping mapping

if [[ $has_console == 1 ]]; then
    args=(--config "$config_dir/site.toml")
    while IFS= read -r item; do [[ -n "$item" ]] && args+=(--set "$item"); done <<< "${sets[console]}"
    "$py" -m telesurg.services.cli console \
        "${bus[@]}" --log-file "$log_dir/console.log" ${args[@]+"${args[@]}"} || true
else
    [[ $ui == 1 ]] && echo "console.sh: telesurg console is not installed; running master_capture only" >&2
    wait "${pids[0]}" || { rc=$?; echo "console.sh: master_capture exited with code $rc" >&2; exit "$rc"; }
fi
