#!/usr/bin/env bash
# Idempotent setup: a project-local virtual environment in .venv with the project and its dev tools.
# torch is pinned to the CPU wheel that lies on disk on this kind of machine *before* the project,
# so that the project's torch range is already satisfied and pip never downloads CUDA packages.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PYTHON="${PYTHON:-python3}"
VENV=.venv
STAMP="$VENV/.splittag-setup"
want="$(cat pyproject.toml deploy/setup.sh | sha256sum | cut -d' ' -f1)"
if [[ -x "$VENV/bin/python" && -f "$STAMP" && "$(cat "$STAMP")" == "$want" ]]; then
    exit 0
fi
echo "[setup] creating $VENV and installing splittag (one-time, a few minutes)" >&2
[[ -x "$VENV/bin/python" ]] || "$PYTHON" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --disable-pip-version-check --upgrade pip
"$VENV/bin/python" -m pip install -q --disable-pip-version-check "torch==2.13.0"
"$VENV/bin/python" -m pip install -q --disable-pip-version-check -e ".[dev]"
echo "$want" > "$STAMP"
echo "[setup] done" >&2
