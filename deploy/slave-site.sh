#!/usr/bin/env bash
# Slave site: a zenoh router on a TLS endpoint (mutual TLS + access control) and the slave-side
# services, all on this machine. Ctrl-C or SIGTERM stops everything cleanly (telesurg up).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"   # this script's folder, beside the site folders
# a checkout's venv; else the Python beside telesurg on the PATH (an installed package)
py="$here/../.venv/bin/python"
if [[ ! -x "$py" ]]; then
    ts="$(command -v telesurg || true)"
    if [[ -z "$ts" ]]; then
        echo "slave-site.sh: telesurg not found (no ../.venv beside $here, none on the PATH): activate the venv it is installed in" >&2
        exit 2
    fi
    py="$([[ -x "$(dirname "$ts")/python" ]] && echo "$(dirname "$ts")/python" || echo python3)"
fi

usage() {
    cat <<USAGE
usage: deploy/slave-site.sh [options] [-- telesurg up options]

Starts the router (listening on --listen with mutual TLS and the access-control rules, plus a
mutual-TLS listener on 127.0.0.1:--local-port for this machine's services, each with its own
certificate made at every start), then watchdog,
slave_control and mapping (and the mirror with --mirror), configs from slave-site/site.toml
beside this script.
Consoles connect with deploy/console.sh SLAVE_HOST. Guide: docs/deploy.md.

options:
  --site ID            site id, key prefix telesurg/ID/... (default: lab)
  --listen ENDPOINT    TLS endpoint for consoles, repeatable (default: tls/0.0.0.0:7447)
  --local-port N       loopback port of the site's services (default: 7448; mutual TLS)
  --datagram-port N    also listen on udp/0.0.0.0:N for the consoles' datagram streams (the
                       master's pose, joints and buttons, best effort: deploy/console.sh
                       --datagram N); the ACL lets a UDP transport put those and nothing else
  --certs DIR          ca.pem, slave-site.pem, slave-site.key (default: certs; telesurg certs)
  --acl FILE           access-control rules (default: slave-site/acl.json5 beside this script)
  --config-dir DIR     site folder: DIR/site.toml, a table per service (default: slave-site/
                       beside this script)
  --no-mapping         the mapping runs on the console machine (identity console-mapping)
  --camera             also start the endoscope camera (camera/<cam>/image to the consoles; the
                       watchdog then guards the video: docs/console.md)
  --mirror             also start the mirror (rerun viewer); with --serve or --save FILE.rrd
  --serve | --save F   mirror options (imply --mirror)
  --log-dir DIR        one log file per service
  --acl-log            the router logs access-control denials only (its log: --log-dir)
  --credentials-dir D  where the local services' certificates are made at every start
                       (default: ~/.local/state/telesurg/SITE-LOCAL_PORT; files 0600)
  --allow-insecure-listen
                       let --listen take a plain tcp/ endpoint beyond loopback (development
                       only: anyone who reaches it bypasses the certificates)
  --set SERVICE.KEY=VALUE
                       override a config key, e.g. --set watchdog.latency_budget_ms=80
  -h, --help           this help
Anything after -- goes to telesurg up unchanged.
USAGE
}

site=lab
listen=()
local_port=7448
datagram_port=""
certs=certs
acl="$here/slave-site/acl.json5"
config_dir="$here/slave-site"
services=watchdog,slave_control,mapping
mirror=0
save=""
extra=()
while [[ $# -gt 0 ]]; do
    case "$1" in
        -h|--help) usage; exit 0 ;;
        --site) site="$2"; shift 2 ;;
        --listen) listen+=("$2"); shift 2 ;;
        --local-port) local_port="$2"; shift 2 ;;
        --datagram-port) datagram_port="$2"; shift 2 ;;
        --certs) certs="$2"; shift 2 ;;
        --acl) acl="$2"; shift 2 ;;
        --config-dir) config_dir="$2"; shift 2 ;;
        --no-mapping) services=${services/,mapping/}; shift ;;
        --camera) services+=",camera"; shift ;;
        --mirror|--serve) mirror=1; shift ;;
        --save) mirror=1; save="$2"; shift 2 ;;
        --log-dir) extra+=(--log-dir "$2"); shift 2 ;;
        --allow-insecure-listen) extra+=(--allow-insecure-listen); shift ;;
        --acl-log) extra+=(--acl-log denied); shift ;;
        --credentials-dir) extra+=(--credentials-dir "$2"); shift 2 ;;
        --set) extra+=(--set "$2"); shift 2 ;;
        --) shift; extra+=("$@"); break ;;
        *) echo "deploy/slave-site.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
    esac
done
[[ ${#listen[@]} -eq 0 ]] && listen=(tls/0.0.0.0:7447)
if [[ -n "$datagram_port" ]]; then
    if ! [[ "$datagram_port" =~ ^[0-9]+$ ]] || (( datagram_port < 1 || datagram_port > 65535 )); then
        echo "deploy/slave-site.sh: --datagram-port $datagram_port: a UDP port number, 1-65535" >&2
        exit 2
    fi
    listen+=("udp/0.0.0.0:$datagram_port")
fi
# --mirror alone serves the viewer; with --save the mirror writes the file instead
if [[ $mirror == 1 ]]; then
    services+=",mirror"
    if [[ -n "$save" ]]; then extra=(--save "$save" ${extra[@]+"${extra[@]}"}); else extra=(--serve ${extra[@]+"${extra[@]}"}); fi
fi
for f in ca.pem slave-site.pem slave-site.key; do
    if [[ ! -f "$certs/$f" ]]; then
        echo "deploy/slave-site.sh: $certs/$f missing; make it with: telesurg certs --out $certs --host <this host>" >&2
        exit 2
    fi
done

args=(up --site "$site" --host 127.0.0.1 --port "$local_port" --config-dir "$config_dir" --services "$services")
for ep in "${listen[@]}"; do args+=(--listen "$ep"); done
args+=(--tls-ca "$certs/ca.pem" --tls-cert "$certs/slave-site.pem" --tls-key "$certs/slave-site.key")
args+=(--mtls --acl "$acl")
# exec: telesurg up gets the signals and stops the services in order
exec "$py" -m telesurg.services.cli "${args[@]}" ${extra[@]+"${extra[@]}"}
