#!/usr/bin/env bash
# The whole suite twice more, with the robot's compute scaled: 2x this CPU's (real sleeps), and 0.5x
# the reference profile (shared.compute.REFERENCE_HEAD_MS_PER_TAG). A test whose scenario depends on
# how fast this CPU is fails here. Environment variables win over every TOML a test writes.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
ref="$(.venv/bin/python -c 'from shared.control.compute import REFERENCE_HEAD_MS_PER_TAG as r; print(list(r))')"
echo "[test-gamma] robot compute x2 of this CPU" >&2
SPLITTAG_ROBOT_INFER_GAMMA=2 .venv/bin/pytest "$@"
echo "[test-gamma] robot compute x0.5 of the reference profile $ref" >&2
SPLITTAG_ROBOT_INFER_GAMMA=0.5 SPLITTAG_ROBOT_INFER_EMULATED_MS_PER_TAG_BY_K="$ref" .venv/bin/pytest "$@"
