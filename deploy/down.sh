#!/usr/bin/env bash
# Stop the deployment started by deploy/up.sh (through its launcher; if that had died, the services
# themselves, and the run is finished as the launcher would have: summary.json, merged recording).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
exec .venv/bin/splittag down "$@"
