"""Group c-controllers: the C controllers, Python out of the loop."""

from __future__ import annotations

import numpy as np

from cosim.benchmarks.common import BenchRow, _c_and_python_step_us
from cosim.benchmarks.subjects import _benchmark_pi, _mixed_scenario, _nn_model
from cosim.study.vocabulary import MPC_ORACLE, NNPC, NOMINAL, PAPER_PERIOD, SWITCHING_PERIOD, transient_within_sample


def bench_c_controllers(quick: bool) -> list[BenchRow]:
    """ns per step of the C PI and NNPC (the FMU's sources, controllers/c + the generated header)
    replaying recorded closed-loop measurements, next to the Python controller on the same inputs;
    the NNPC's operations counted and a Cortex-M4F cycle estimate (cosim.benchmark_harness)."""
    from cosim.benchmark_harness import CORTEX_M4F, cortex_m4f_cycles, operation_counts, record_measurements, replay
    from cosim.study.experiments import implemented, model_mpc, nnpc, plant_binding

    binding = plant_binding("nominal", "switched")
    rows = []
    for period, label in ((PAPER_PERIOD, "1 ms"), (SWITCHING_PERIOD, "13.33 us")):
        samples = 40 if quick else (3000 if transient_within_sample(period) else 600)
        scenario = _mixed_scenario(period, samples)
        model, origin = _nn_model("nnpc", period, quick)
        controllers = [_benchmark_pi(period), nnpc(model, period, NNPC)]
        if not transient_within_sample(period):
            controllers.append(model_mpc(NOMINAL, period, MPC_ORACLE, binding=binding))
        for controller in controllers:
            measurements = record_measurements(binding, implemented(controller), scenario)
            result = replay(controller, measurements, repeats=1 if quick else 3)
            c_p50, c_p99, py_p50, py_p99 = _c_and_python_step_us(controller, measurements, result)
            budget = period * 1e6
            target, met = "", None
            if controller.name == NNPC:
                target, met = ("p99 <= 5 us", c_p99 <= 5.0) if transient_within_sample(period) else \
                    ("p99 <= 13.3 us (stretch)", c_p99 <= budget)
            rows.append(BenchRow(f"C step, {controller.name}, {label} ({len(measurements)} replayed samples, "
                                 f"{100 * c_p99 / budget:.3g} % of the period at p99)", c_p50, c_p99, "us", target, met,
                                 f"NN: {origin}" if controller.name == NNPC else ""))
            rows.append(BenchRow(f"Python step, {controller.name}, {label} (same inputs)", py_p50, py_p99, "us"))
            rows.append(BenchRow(f"speed-up of C over Python, {controller.name}, {label} (p50)", py_p50 / c_p50, None,
                                 "ratio"))
            if controller.name != NNPC:
                continue
            counts = operation_counts(controller, result.evaluations)
            cycles = cortex_m4f_cycles(counts)
            for key, what in (("candidates", "candidate evaluations"), ("macs", "multiply-accumulates"),
                              ("tanh", "tanh calls")):
                rows.append(BenchRow(f"NNPC {label} per step: {what} (counted)", float(np.median(counts[key])),
                                     float(np.percentile(counts[key], 99)), "count"))
            fraction = float(np.percentile(cycles, 99)) / (CORTEX_M4F.clock_hz * period)
            rows.append(BenchRow(
                f"NNPC {label} per step on a 170 MHz Cortex-M4F (float32 port, estimated cycles)",
                float(np.median(cycles)), float(np.percentile(cycles, 99)), "cycles",
                f"fits {CORTEX_M4F.clock_hz * period:.0f} cycles", fraction <= 1.0,
                f"p99 is {fraction:.3g} x the period; cost model: {CORTEX_M4F.mac} cycles/MAC, {CORTEX_M4F.tanh}/tanh, "
                f"{CORTEX_M4F.sqrt}/sqrt, {CORTEX_M4F.candidate}/candidate, {CORTEX_M4F.interrupt} per sample for "
                "ADC/PWM/ISR (cosim/benchmark_harness); the twins compute in double precision, which the M4F "
                "emulates in software -- a float32 port is assumed"))
    return rows
