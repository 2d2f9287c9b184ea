#!/usr/bin/env bash
# Start a local site: router + every service on loopback, configs from local/site.toml beside
# this script. Ctrl-C stops everything.
#   deploy/local.sh [--port 7447] [--serve | --save out.rrd] [--set mapping.scale=0.3] ...
# (telesurg site init DIR writes this script and the site folders out of an installed package.)
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
ts="$here/../.venv/bin/telesurg"          # a checkout's venv; else telesurg on the PATH
[[ -x "$ts" ]] || ts=telesurg
exec "$ts" up --config-dir "$here/local" "$@"
