#!/usr/bin/env bash
# Creates .venv in this checkout (once) and installs torchrl_tels into it,
# with the test and robotics extras.
# torch is installed first, pinned to the CPU build: a bare `torch` requirement
# on a machine without torch pulls a multi-GB CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${TELS_VENV:-.venv}
PY=${PYTHON:-python3}
stamp="$VENV/.torchrl_tels-installed"
want="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
"$VENV/bin/python" -m pip install --quiet --upgrade pip
"$VENV/bin/python" -m pip install --quiet "torch==2.13.0"
"$VENV/bin/python" -m pip install --quiet -e ".[test,robotics]"
echo "$want" > "$stamp"
