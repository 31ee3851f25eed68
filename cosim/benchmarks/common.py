"""What every group uses to time and report: the table row, p99, the median of repeated calls, the
C twin timed against its Python reference on the same inputs, and a C step's instructions counted."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np


@dataclass
class BenchRow:
    benchmark: str
    median: float
    p99: float | None
    unit: str
    target: str = ""
    meets_target: bool | None = None
    note: str = ""
    extra: dict = field(default_factory=dict)
    group: str = ""  # the BENCHMARKS entry that measured it
    command: str = ""  # the command line that measured it
    machine: str = ""  # the machine that measured it (suite.machine_label; a merged row keeps its own)


def _p99(values) -> float:
    return float(np.percentile(values, 99))


#: passes of a replay the groups with a real-time target make (the per-sample median needs several)
REPLAY_PASSES = 5


def per_sample_median(per_pass: np.ndarray) -> np.ndarray:
    """Each sample's median over the passes of a replay (``per_pass``: passes x samples, the same inputs in every
    pass): the step's own cost on those inputs. A raw p99 over every pass's steps is set on this machine by the
    operating system -- a timer interrupt or a preemption lands in about 1 % of the ~10 us steps and adds
    microseconds -- not by the step's data: the per-sample median drops those events (they rarely hit one sample
    in most of its passes) and keeps what the inputs cost (the search's fallbacks, the QP's iterations), so its
    p99 is the data's worst case. Both are reported; neither replaces the other."""
    return np.median(np.asarray(per_pass, dtype=float), axis=0)


def per_sample_median_row(benchmark: str, per_pass: np.ndarray, planned: np.ndarray, limit_us: float | None,
                          note: str = "") -> BenchRow:
    """The row of the ``planned`` samples' per-sample medians (:func:`per_sample_median`, ``per_pass`` in us), with
    the target p99 <= ``limit_us`` (None: no target) -- beside a row of the same steps as timed."""
    typical = per_sample_median(per_pass)[planned]
    p99 = _p99(typical)
    return BenchRow(f"{benchmark}, each sample's median over the {len(per_pass)} passes (the same "
                    f"{int(np.count_nonzero(planned))} samples; the operating system's interruptions left out)",
                    float(np.median(typical)), p99, "us", f"p99 <= {limit_us:.3g} us" if limit_us is not None else "",
                    p99 <= limit_us if limit_us is not None else None,
                    "the step's own cost on these inputs, its data's worst case at p99"
                    f"{'; ' + note if note else ''} (cosim.benchmarks.common.per_sample_median)")


def _median_time(function, repeats: int) -> float:
    samples = []
    for _ in range(repeats):
        start = time.perf_counter_ns()
        function()
        samples.append(time.perf_counter_ns() - start)
    return float(np.median(samples)) * 1e-9


def _c_and_python_step_us(controller, measurements, replayed) -> tuple[float, float, float, float]:
    """The C step times of ``replayed`` (the harness's replay of ``measurements``) and the Python controller's
    on the same inputs, timed here one step at a time: (C p50, C p99, Python p50, Python p99) in us. First
    checks that the in-process C twin gives the harness's duties, so both time the same computation."""
    from controllers.base import Measurement
    from cosim.design.experiments import implemented

    twin = implemented(controller)
    twin.reset()
    assert all(twin.step(Measurement(*row)) == duty for row, duty in zip(measurements, replayed.duty)), \
        "the harness and the in-process twin disagree"
    python = []
    controller.reset()
    for row in measurements:
        start = time.perf_counter_ns()
        controller.step(Measurement(*row))
        python.append(time.perf_counter_ns() - start)
    return (float(np.median(replayed.ns)) * 1e-3, _p99(replayed.ns) * 1e-3, float(np.median(python)) * 1e-3,
            _p99(python) * 1e-3)


def instruction_row(what: str, controller, measurements: np.ndarray, planned: np.ndarray | None = None) -> BenchRow:
    """x86-64 instructions per C step of ``controller`` on the samples ``planned`` marks (the RTI's; None: every
    sample, a controller without a fallback), counted by callgrind replaying ``measurements`` once from a reset --
    the timed passes' path, each of them starting from a reset too: what the step costs whatever the machine's
    speed, so a change to the C code is judged by it across runs (:mod:`cosim.benchmark_harness.instruction_count`);
    one row saying why where valgrind is missing."""
    from controllers.native import NativeBuildError
    from cosim.benchmark_harness.instruction_count import InstructionCountError, instruction_counts, problem

    every = planned is None
    planned = np.ones(len(measurements), dtype=bool) if every else planned
    reason = problem()
    if reason is None and not planned.any():
        reason = "the RTI planned none of the replayed samples"
    if reason is None:
        try:
            counts = instruction_counts(controller, measurements)
        except (InstructionCountError, NativeBuildError) as error:
            reason = str(error)
    if reason:
        return BenchRow(f"{what}: not measured", math.nan, None, "", note=reason)
    chosen, others = counts[planned], counts[~planned]
    if every:
        return BenchRow(f"{what} (callgrind; every one of the {len(chosen)} samples of one pass; p99 column: max)",
                        float(np.median(chosen)), float(np.max(chosen)), "count",
                        note="the same in every run on this machine (another CPU may take other variants of libm's "
                             "tanh)")
    other = (f"p50 {float(np.median(others)):.4g}, max {float(np.max(others)):.4g}" if len(others) else "none")
    return BenchRow(f"{what} (callgrind; the {int(planned.sum())} RTI samples of one pass; p99 column: max)",
                    float(np.median(chosen)), float(np.max(chosen)), "count",
                    note=f"the same in every run on this machine (another CPU may take other variants of libm's exp "
                         f"and libc's copies); the search's {len(others)} fallback steps: {other}")

