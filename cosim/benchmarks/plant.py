"""Group plant: the plant FMU's doStep cost."""

from __future__ import annotations

import time

import numpy as np

from cosim.benchmarks.common import BenchRow, _p99
from cosim.benchmarks.subjects import _RawSlave
from cosim.study.vocabulary import PAPER_PERIOD, SWITCHING_PERIOD


def _time_do_steps(mode: int, step: float, count: int) -> np.ndarray:
    slave = _RawSlave({"plant_mode": mode, "duty_cycle": 0.25})
    do_step = slave.fmu.dll.fmi2DoStep  # the C function itself: the FMU's cost, not Python's
    component = slave.fmu.component
    times = np.empty(count)
    t = 0.0
    try:
        for i in range(count):
            start = time.perf_counter_ns()
            do_step(component, t, step, 1)
            times[i] = time.perf_counter_ns() - start
            t = (i + 1) * step
    finally:
        slave.close()
    return times * 1e-9


def bench_plant(quick: bool) -> list[BenchRow]:
    n = 3 if quick else 400
    periods_per_ms = 75
    switched = _time_do_steps(1, PAPER_PERIOD, n) / periods_per_ms
    single = _time_do_steps(1, SWITCHING_PERIOD, n * 10)
    averaged = _time_do_steps(0, PAPER_PERIOD, n)
    return [
        BenchRow("plant doStep, switched mode, per simulated switching period (1 ms steps / 75)",
                 float(np.median(switched)) * 1e6, _p99(switched) * 1e6, "us",
                 "<= 1 us per switching period", bool(np.median(switched) <= 1e-6),
                 "exact piecewise solution: 2 closed-form intervals per period"),
        BenchRow("plant doStep, switched mode, one switching period per call (incl. ctypes call)",
                 float(np.median(single)) * 1e6, _p99(single) * 1e6, "us"),
        BenchRow("plant doStep, averaged mode, per 1 ms step (incl. ctypes call)",
                 float(np.median(averaged)) * 1e6, _p99(averaged) * 1e6, "us"),
    ]
