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
    from cosim.benchmark_harness import (
        CORTEX_M4F,
        cortex_m4f_cycles,
        operation_counts,
        record_measurements,
        replay,
        rti_operation_counts,
    )
    from cosim.study.experiments import default_optimizer, implemented, model_mpc, nnpc, plant_binding

    binding = plant_binding("nominal", "switched")
    rows = []
    for period, label in ((PAPER_PERIOD, "1 ms"), (SWITCHING_PERIOD, "13.33 us")):
        samples = 40 if quick else (3000 if transient_within_sample(period) else 600)
        scenario = _mixed_scenario(period, samples)
        model, origin = _nn_model("nnpc", period, quick)
        default = default_optimizer(period)
        other = "search" if default == "rti" else "rti"
        controllers = [_benchmark_pi(period), nnpc(model, period, NNPC), nnpc(model, period, f"{NNPC} ({other})",
                                                                              optimizer=other)]
        if not transient_within_sample(period):
            controllers.append(model_mpc(NOMINAL, period, MPC_ORACLE, binding=binding))
        for controller in controllers:
            measurements = record_measurements(binding, implemented(controller), scenario)
            result = replay(controller, measurements, repeats=1 if quick else 3)
            c_p50, c_p99, py_p50, py_p99 = _c_and_python_step_us(controller, measurements, result)
            budget = period * 1e6
            target, met = "", None
            online = controller.name.startswith(NNPC)
            rti = getattr(controller, "rti", None) is not None
            if online and rti:  # issue 24's targets for the online NNPC with the real-time iteration
                target, met = ("p99 <= 2 us", c_p99 <= 2.0) if transient_within_sample(period) else \
                    ("p99 <= 13.3 us", c_p99 <= budget)
            fallbacks = int(np.count_nonzero(~result.rti)) if rti else 0
            note = f"NN: {origin}" if online else ""
            if rti:
                note += (f"; {fallbacks} of {len(measurements)} steps planned by the search (the cold start"
                         f"{' and the fallback rule' if fallbacks > 1 else ''}); RTI steps alone: p99 "
                         f"{float(np.percentile(result.ns.reshape(-1, len(measurements))[:, result.rti], 99)) * 1e-3:.3g} "
                         "us, max " f"{float(np.max(result.ns)) * 1e-3:.4g} us (all steps)")
            rows.append(BenchRow(f"C step, {controller.name}, {label} ({len(measurements)} replayed samples, "
                                 f"{100 * c_p99 / budget:.3g} % of the period at p99)", c_p50, c_p99, "us", target, met,
                                 note))
            rows.append(BenchRow(f"Python step, {controller.name}, {label} (same inputs)", py_p50, py_p99, "us"))
            rows.append(BenchRow(f"speed-up of C over Python, {controller.name}, {label} (p50)", py_p50 / c_p50, None,
                                 "ratio"))
            if not online:
                continue
            if rti:
                counts = rti_operation_counts(controller, result.rti, result.qp_iterations, result.evaluations)
            else:
                counts = operation_counts(controller, result.evaluations)
            cycles = cortex_m4f_cycles(counts)
            quantities = [("candidates", "candidate evaluations (rollouts)"), ("macs", "multiply-accumulates"),
                          ("tanh", "tanh calls")] + ([("qp_iterations", "box-QP iterations")] if rti else [])
            for key, what in quantities:
                rows.append(BenchRow(f"{controller.name} {label} per step: {what} (counted)",
                                     float(np.median(counts[key])), float(np.percentile(counts[key], 99)), "count"))
            fraction = float(np.percentile(cycles, 99)) / (CORTEX_M4F.clock_hz * period)
            rows.append(BenchRow(
                f"{controller.name} {label} per step on a 170 MHz Cortex-M4F (float32 port, estimated cycles)",
                float(np.median(cycles)), float(np.percentile(cycles, 99)), "cycles",
                f"fits {CORTEX_M4F.clock_hz * period:.0f} cycles", fraction <= 1.0,
                f"p99 is {fraction:.3g} x the period; cost model: {CORTEX_M4F.mac:g} cycles/MAC and "
                f"{CORTEX_M4F.tanh:g}/tanh (calibrated: group embedded), {CORTEX_M4F.sqrt:g}/sqrt, "
                f"{CORTEX_M4F.candidate:g}/candidate (assumed), {CORTEX_M4F.interrupt:g} per sample for ADC/PWM/ISR "
                "(controllers/cost_model.py); the online NNPC's optimizer computes in double only -- a float32 "
                "port is assumed"))
    return rows
