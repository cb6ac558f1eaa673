#!/usr/bin/env bash
# Start camera, robot_infer, edge_infer and slam (and the controller with --controller) as separate processes; Ctrl-C / SIGINT stops them all.
# Usage: deploy/up.sh [--config deploy/local.toml] [--duration SECS]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
bash deploy/setup.sh
exec .venv/bin/splittag up "$@"
