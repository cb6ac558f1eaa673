#!/usr/bin/env bash
# Stop the deployment started by deploy/up.sh (SIGINT to each service's process group).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
exec .venv/bin/splittag down "$@"
