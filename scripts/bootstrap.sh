#!/usr/bin/env bash
# Create .venv (once) and install the project with exactly the tested dependency versions.
# Re-runs are cheap: the install is skipped while pyproject.toml and constraints.txt are unchanged.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python3}"

# The Cortex-M4F cross toolchain and emulator of the embedded tests and benchmarks
# (cosim/benchmark_harness/cortex_m4.py): Debian packages, installed here when this runs as root with
# apt-get; elsewhere (or if the install fails) the embedded tests are deselected with one line saying why.
# qemu-user: qemu-x86_64 runs one process on another x86-64 CPU model, for the test that the trained
# networks are the same bytes on other CPUs (cosim/benchmark_harness/cpu_emulation.py). valgrind: callgrind
# counts the C steps' instructions on the host (cosim/benchmark_harness/instruction_count.py).
# BUCK_COSIM_NO_APT=1 skips the Debian packages (the tests that need them then deselect themselves).
embedded_packages="gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm qemu-user valgrind"
if [ -z "${BUCK_COSIM_NO_APT:-}" ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && command -v dpkg-query >/dev/null 2>&1; then
  missing=""
  for package in $embedded_packages; do
    dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "ok installed" || missing="$missing $package"
  done
  if [ -n "$missing" ]; then
    echo "bootstrap: installing the Cortex-M4F toolchain, the emulators and valgrind (Debian packages:$missing)"
    log=$(mktemp)
    # shellcheck disable=SC2086  # the package list is meant to split
    if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
           $missing; } >"$log" 2>&1; then
      tail -n 5 "$log"
      echo "bootstrap: warning: apt-get could not install$missing; the embedded, emulated-CPU and instruction-count tests and benchmarks are skipped"
    fi
    rm -f "$log"
  fi
fi
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
.venv/bin/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[test,docs,bench]"
echo "$want" > "$stamp"
