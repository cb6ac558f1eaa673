#!/usr/bin/env bash
# Idempotent setup: a project-local virtual environment in .venv with the project and its dev tools.
# torch is pinned to the CPU wheel that lies on disk on this kind of machine *before* the project,
# so that the project's torch range is already satisfied and pip never downloads CUDA packages.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PYTHON="${PYTHON:-python3}"
VENV=.venv
STAMP="$VENV/.splittag-setup"
want="$(cat pyproject.toml deploy/setup.sh deploy/constraints.txt | sha256sum | cut -d' ' -f1)"
if [[ -x "$VENV/bin/python" && -f "$STAMP" && "$(cat "$STAMP")" == "$want" ]]; then
    exit 0
fi
echo "[setup] creating $VENV and installing splittag (one-time, a few minutes)" >&2
# The environment takes ~2.9 GB (torch alone ~1.8). Warn plainly before pip's "[Errno 28] No space left on
# device" halfway through (a CI run once failed that way on a disk filled by old clones in /tmp).
free_kib="$(df -Pk . | awk 'NR==2 {print $4}')"
if [[ -n "$free_kib" && "$free_kib" -lt $((4 * 1024 * 1024)) ]]; then
    echo "[setup] only $((free_kib / 1024)) MiB free on $(df -P . | awk 'NR==2 {print $6}'); the environment needs ~3 GiB plus pip's" \
        "temporary files: if pip fails with 'No space left on device', free some (old clones, /tmp)" >&2
fi
[[ -x "$VENV/bin/python" ]] || "$PYTHON" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --disable-pip-version-check --upgrade pip
# Every version as deploy/constraints.txt says (the suite's): the open ranges of pyproject.toml alone let a
# new release on the registry (gtsam 4.3.0 in session 18) change what a fresh clone installs and tests.
"$VENV/bin/python" -m pip install -q --disable-pip-version-check -c deploy/constraints.txt "torch==2.13.0"
"$VENV/bin/python" -m pip install -q --disable-pip-version-check -c deploy/constraints.txt -e ".[dev]"
echo "$want" > "$STAMP"
echo "[setup] done" >&2
