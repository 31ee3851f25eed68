"""Group explicit: the explicit NNPC, what one forward pass costs."""

from __future__ import annotations

import numpy as np

from cosim.base.labels import period_text
from cosim.benchmarks.common import BenchRow, _c_and_python_step_us, instruction_row
from cosim.benchmarks.subjects import _explicit_policy, _mixed_scenario, _nn_model
from cosim.design.vocabulary import NNPC, SWITCHING_PERIOD


def bench_explicit(quick: bool) -> list[BenchRow]:
    """The explicit NNPC's C step (the FMU's sources) replaying closed-loop measurements, next to its
    Python step and the online NNPC's C step on the same inputs; operations counted and the
    Cortex-M4F cycle estimate (cosim.benchmark_harness, the c-controllers group's cost model)."""
    from cosim.benchmark_harness import (
        CORTEX_M4F,
        cortex_m4f_cycles,
        policy_operation_counts,
        record_measurements,
        replay,
    )
    from cosim.design.experiments import explicit_nnpc, implemented, nnpc
    from cosim.design.plants import plant_binding
    from cosim.design.vocabulary import NNPC_EXPLICIT

    period = SWITCHING_PERIOD
    label = period_text(period, ascii_only=True)
    binding = plant_binding("nominal", "switched")
    policy, origin = _explicit_policy(quick)
    controller = explicit_nnpc(policy, NNPC_EXPLICIT)
    samples = 40 if quick else 3000
    measurements = record_measurements(binding, implemented(controller), _mixed_scenario(period, samples))
    result = replay(controller, measurements, repeats=1 if quick else 20)
    c_p50, c_p99, py_p50, py_p99 = _c_and_python_step_us(controller, measurements, result)
    model, _ = _nn_model("nnpc", period, quick)
    online = replay(nnpc(model, period, NNPC), measurements[:40 if quick else 600], repeats=1)
    online_p50 = float(np.median(online.ns)) * 1e-3
    counts = policy_operation_counts(policy.config)
    cycles = float(cortex_m4f_cycles(counts))
    budget = CORTEX_M4F.clock_hz * period
    note = f"policy: {origin}"
    return [
        BenchRow(f"C step, {NNPC_EXPLICIT}, {label} ({len(measurements)} replayed samples x "
                 f"{1 if quick else 20} passes, {100 * c_p99 / (period * 1e6):.3g} % of the period at p99)",
                 c_p50, c_p99, "us", "p99 <= 0.5 us", c_p99 <= 0.5,
                 f"{note}; the time's verdict is the VM's draw (its speed steps between two levels), the instructions "
                 "below are the step's work"),
        instruction_row(f"x86-64 instructions per C step, {NNPC_EXPLICIT}, {label}", controller, measurements),
        BenchRow(f"Python step, {NNPC_EXPLICIT}, {label} (same inputs)", py_p50, py_p99, "us"),
        BenchRow(f"C step time, online NNPC / {NNPC_EXPLICIT}, {label} (same inputs, p50)", online_p50 / c_p50, None,
                 "ratio"),
        BenchRow(f"{NNPC_EXPLICIT} {label} per step: multiply-accumulates (counted)", counts["macs"], None, "count",
                 "<= 300", counts["macs"] <= 300, f"{policy.config.label}: layers + G r + (Ki Ts) e"),
        BenchRow(f"{NNPC_EXPLICIT} {label} per step: tanh calls (counted)", counts["tanh"], None, "count"),
        BenchRow(f"{NNPC_EXPLICIT} {label} per step on a 170 MHz Cortex-M4F: the cost model's prediction (superseded by "
                 "the measurement of the embedded group)", cycles, None, "cycles",
                 note=f"{cycles / budget:.3g} x the period; cost model: {CORTEX_M4F.mac:g} cycles/MAC, "
                      f"{CORTEX_M4F.tanh:g}/tanh, {CORTEX_M4F.division:g}/division, {CORTEX_M4F.candidate:g} for the "
                      f"features, clip and integral, {CORTEX_M4F.interrupt:g} per sample for ADC/PWM/ISR "
                      "(controllers/cost_model.py); measured on the emulated Cortex-M4F: group embedded"),
    ]
