#!/usr/bin/env bash
# Start a local site: router + every service on loopback, configs from local/site.toml beside
# this script. Ctrl-C stops everything.
#   deploy/local.sh [--port 7447] [--serve | --save out.rrd] [--set mapping.scale=0.3] ...
# (telesurg site init DIR writes this script and the site folders out of an installed package.)
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
ts="$here/../.venv/bin/telesurg"          # a checkout's venv; else telesurg on the PATH
if [[ ! -x "$ts" ]]; then
    ts="$(command -v telesurg || true)"
    if [[ -z "$ts" ]]; then
        echo "local.sh: telesurg not found (no ../.venv beside $here, none on the PATH): activate the venv it is installed in" >&2
        exit 2
    fi
fi
exec "$ts" up --config-dir "$here/local" "$@"
