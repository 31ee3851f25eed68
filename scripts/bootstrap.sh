#!/usr/bin/env bash
# Create .venv (once) and install the project with exactly the tested dependency versions.
# Re-runs are cheap: the install is skipped while pyproject.toml and constraints.txt are unchanged.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python3}"
stamp=.venv/.installed
want=$(cat pyproject.toml constraints.txt | sha256sum | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
if [ ! -x .venv/bin/python ]; then
  echo "bootstrap: creating .venv with $($PYTHON --version)"
  "$PYTHON" -m venv .venv
fi
echo "bootstrap: installing dependencies (torch==2.13.0 CPU, fmpy, pandas, ...)"
.venv/bin/python -m pip install --quiet --disable-pip-version-check --upgrade "pip>=24"
# torch first and alone, pinned: pip takes the local CPU build of exactly this version.
.venv/bin/python -m pip install --quiet --disable-pip-version-check -c constraints.txt "torch==2.13.0"
.venv/bin/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[test]"
echo "$want" > "$stamp"
