"""x86-64 instructions per C controller step, counted by callgrind: the host's measure of a step's cost that does
not move with the machine's speed.

The step's time on this shared VM steps between two levels (the same binary's 13.33 us RTI step measured 5 or
10 us p50 by the minute on some days, from one ~10 ms pass to the next on others; hardware performance counters
are not exposed to it), so a change to
the C code cannot be judged by its time across two benchmark runs, and a time target's verdict is partly the
run's draw. The instructions a step executes are a property of the code and its inputs: the same in every run
on the same machine (with another CPU, only where glibc picks another variant of a libm function, e.g. exp with
or without FMA, or memcpy). :func:`instruction_counts` replays recorded measurements through the harness built with
``-DHARNESS_COUNT_INSTRUCTIONS`` (``controller_step.c``: each step's instructions collected alone and dumped)
under ``valgrind --tool=callgrind`` and returns every step's count. It takes ~50 x the step's time; valgrind is
Debian's ``valgrind`` package, which ``make`` installs when run as root.

Hand-written around valgrind rather than through a library: no maintained Python package reads callgrind's
per-dump totals, and the one line read here (``totals:``) is the format's documented summary.
"""

from __future__ import annotations

import functools
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from controllers.native import NativeBuildError, compiler
from cosim.benchmark_harness import harness
from cosim.benchmark_harness.cpu_emulation import not_x86_64

VALGRIND = "valgrind"
PACKAGES = ("valgrind",)


class InstructionCountError(RuntimeError):
    """valgrind could not count the replay (its message and log tail)."""


def problem() -> str | None:
    """Why the steps' instructions cannot be counted here (None: they can): not x86-64, no valgrind, or no
    ``<valgrind/callgrind.h>`` for the harness (some distributions ship it apart, e.g. Fedora's valgrind-devel)."""
    if not_x86_64():
        return not_x86_64()
    if shutil.which(VALGRIND) is None:
        return (f"{VALGRIND} is not installed (Debian package {' '.join(PACKAGES)}; `make` installs it when run as "
                "root)")
    return _header_problem()


@functools.lru_cache(maxsize=1)
def _header_problem() -> str | None:
    try:
        done = subprocess.run([*compiler(), "-E", "-x", "c", "-"], input="#include <valgrind/callgrind.h>\n",
                              capture_output=True, text=True, timeout=60, check=False)
    except (OSError, subprocess.TimeoutExpired, NativeBuildError) as error:
        return f"the C compiler cannot be run to find <valgrind/callgrind.h>: {error}"
    if done.returncode != 0:
        return ("the C compiler finds no <valgrind/callgrind.h>, which the counting harness includes (Debian's "
                "valgrind package has it; elsewhere a valgrind-devel package)")
    return None


def instruction_counts(controller, measurements: np.ndarray) -> np.ndarray:
    """Instructions executed by each step of ``controller``'s C step replaying ``measurements`` once from a reset
    (int64, one per row; the clock reads around the step are outside the count). Raises
    :class:`InstructionCountError` when valgrind is missing or fails."""
    reason = problem()
    if reason:
        raise InstructionCountError(f"cannot count instructions: {reason}")
    executable = harness(controller, count_instructions=True)
    with tempfile.TemporaryDirectory(prefix="buck-cosim-callgrind-") as tmp:
        data, out = Path(tmp) / "measurements.bin", Path(tmp) / "steps.out"
        np.ascontiguousarray(measurements, dtype="<f8").tofile(data)
        argv = [VALGRIND, "--tool=callgrind", "--collect-atstart=no", "--dump-instr=no", "--dump-line=no",
                f"--callgrind-out-file={out}", str(executable), str(data), "1"]
        try:
            done = subprocess.run(argv, capture_output=True, text=True, timeout=3600, check=False)
        except (OSError, subprocess.TimeoutExpired) as error:
            raise InstructionCountError(f"callgrind failed: {error}") from None
        if done.returncode != 0:
            tail = " | ".join(done.stderr.strip().splitlines()[-3:]) or "no message"
            raise InstructionCountError(f"callgrind's replay failed (exit {done.returncode}): {tail}")
        # one dump per step, numbered from 1 in step order (the file without a number is what followed the last)
        dumps = {int(p.suffix[1:]) for p in Path(tmp).glob(f"{out.name}.*") if p.suffix[1:].isdigit()}
        if dumps != set(range(1, len(measurements) + 1)):
            missing = sorted(set(range(1, len(measurements) + 1)) - dumps)
            raise InstructionCountError(
                f"callgrind wrote {len(dumps)} step profiles for {len(measurements)} steps"
                + (f" (the first missing: step {missing[0]})" if missing else " (more than the steps)"))
        counts = [_totals(out.with_name(f"{out.name}.{k}")) for k in range(1, len(measurements) + 1)]
    return np.array(counts, dtype=np.int64)


def _totals(dump: Path) -> int:
    try:
        text = dump.read_text(encoding="utf-8", errors="replace")
    except OSError as error:
        raise InstructionCountError(f"callgrind wrote no profile {dump.name}: {error}") from None
    found = re.search(r"^totals:\s+(\d+)", text, flags=re.MULTILINE) or re.search(r"^summary:\s+(\d+)", text, flags=re.MULTILINE)
    if found is None:
        raise InstructionCountError(f"callgrind's profile {dump.name} has no totals line")
    return int(found.group(1))
