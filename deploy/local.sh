#!/usr/bin/env bash
# Start a local site: router + every service on loopback. Ctrl-C stops everything.
#   deploy/local.sh [--port 7447] [--serve | --save out.rrd] [--set mapping.scale=0.3] ...
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
exec "$here/.venv/bin/telesurg" up --config-dir "$here/deploy/local" "$@"
