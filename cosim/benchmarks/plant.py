"""Group plant: the plant FMU's doStep cost, and the averaged DCM cost per simulated second across duties."""

from __future__ import annotations

import statistics
import time

import numpy as np

from cosim.benchmarks.common import BenchRow, _p99
from cosim.benchmarks.subjects import _RawSlave
from cosim.design.vocabulary import PAPER_PERIOD, SWITCHING_PERIOD


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


#: duties of the averaged DCM cost rows: from a 13 fs on-time up (d = 0: the closed-form RC discharge)
DCM_DUTIES = (0.0, 1e-9, 1e-7, 1e-5, 1e-3, 0.1, 0.25)


def _dcm_seconds_per_simulated_second(duty: float, steps: int) -> float:
    """Wall seconds per simulated second of the averaged plant in DCM: 200 Ohm from vo = 47 V at ``duty``
    (the issue-26 case: 1 ms steps at d = 1e-7 used to take minutes each), 1 ms doSteps through the C call."""
    slave = _RawSlave({"plant_mode": 0, "duty_cycle": duty, "capacitor_voltage": 47.0, "load_resistance": 200.0})
    do_step, component = slave.fmu.dll.fmi2DoStep, slave.fmu.component
    try:
        start = time.perf_counter()
        for i in range(steps):
            do_step(component, i * PAPER_PERIOD, PAPER_PERIOD, 1)
        return (time.perf_counter() - start) / (steps * PAPER_PERIOD)
    finally:
        slave.close()


def bench_plant(quick: bool) -> list[BenchRow]:
    n = 3 if quick else 400
    periods_per_ms = 75
    switched = _time_do_steps(1, PAPER_PERIOD, n) / periods_per_ms
    single = _time_do_steps(1, SWITCHING_PERIOD, n * 10)
    averaged = _time_do_steps(0, PAPER_PERIOD, n)
    dcm_steps, repeats = (20, 1) if quick else (20_000, 5)  # 20 s of simulated time per repeat
    dcm = {d: [] for d in DCM_DUTIES}
    for _ in range(repeats):  # interleaved, so the machine's drift hits every duty alike
        for d in DCM_DUTIES:
            dcm[d].append(_dcm_seconds_per_simulated_second(d, dcm_steps))
    dcm_median = {d: statistics.median(v) for d, v in dcm.items()}
    pulsed = [dcm_median[d] for d in DCM_DUTIES if d > 0]
    spread = max(pulsed) / min(pulsed)
    dcm_rows = [BenchRow(f"plant doStep, averaged DCM at d = {d:g} (200 Ohm from vo = 47 V, 1 ms steps), per "
                         "simulated second", dcm_median[d] * 1e3, max(dcm[d]) * 1e3, "ms",
                         note="p99 column: the slowest repeat" + ("; d = 0: the diode blocks, closed-form RC "
                                                                  "discharge" if d == 0 else ""))
                for d in DCM_DUTIES]
    dcm_rows.append(BenchRow("averaged DCM cost spread over d = 1e-9 .. 0.25: max / min per simulated second", spread,
                             None, "ratio", "<= 3 (no dependence on d)", spread <= 3.0,
                             "the DCM current is algebraic (reduced-order model): only vC is integrated, and nothing "
                             "stiff is left; before, d = 1e-7 made one 1 ms step run for minutes"))
    return [
        BenchRow("plant doStep, switched mode, per simulated switching period (1 ms steps / 75)",
                 float(np.median(switched)) * 1e6, _p99(switched) * 1e6, "us",
                 "<= 1 us per switching period", bool(np.median(switched) <= 1e-6),
                 "exact piecewise solution: 2 closed-form intervals per period"),
        BenchRow("plant doStep, switched mode, one switching period per call (incl. ctypes call)",
                 float(np.median(single)) * 1e6, _p99(single) * 1e6, "us"),
        BenchRow("plant doStep, averaged mode, per 1 ms step (incl. ctypes call)",
                 float(np.median(averaged)) * 1e6, _p99(averaged) * 1e6, "us"),
        *dcm_rows,
    ]
