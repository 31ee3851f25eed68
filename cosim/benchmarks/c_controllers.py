"""Group c-controllers: the C controllers, Python out of the loop."""

from __future__ import annotations

import numpy as np

from cosim.base.labels import period_text
from cosim.benchmarks.common import (
    REPLAY_PASSES,
    BenchRow,
    _c_and_python_step_us,
    _p99,
    instruction_row,
    per_sample_median_row,
)
from cosim.benchmarks.subjects import _benchmark_pi, _mixed_scenario, _nn_model
from cosim.design.vocabulary import MPC_ORACLE, NNPC, NOMINAL, PAPER_PERIOD, SWITCHING_PERIOD, transient_within_sample


def bench_c_controllers(quick: bool) -> list[BenchRow]:
    """ns per step of the C PI and NNPC (the FMU's sources, controllers/c + the generated header)
    replaying recorded closed-loop measurements, next to the Python controller on the same inputs (the C steps of
    one rate's controllers timed pass by pass in turn: replay_interleaved); the NNPC's operations counted and a
    Cortex-M4F cycle estimate (cosim.benchmark_harness)."""
    from cosim.benchmark_harness import (
        CORTEX_M4F,
        cortex_m4f_cycles,
        operation_counts,
        record_measurements,
        replay_interleaved,
        rti_operation_counts,
    )
    from cosim.design.experiments import implemented, model_mpc, nnpc
    from cosim.design.plants import plant_binding
    from cosim.study.optimizer_ablation import TWO_STEPS

    binding = plant_binding("nominal", "switched")
    rows = []
    for period in (PAPER_PERIOD, SWITCHING_PERIOD):
        label = period_text(period, ascii_only=True)
        samples = 40 if quick else (3000 if transient_within_sample(period) else 600)
        scenario = _mixed_scenario(period, samples)
        model, origin = _nn_model("nnpc", period, quick)
        controllers = [_benchmark_pi(period), nnpc(model, period, NNPC),  # the default: the RTI
                       nnpc(model, period, f"{NNPC} (search)", optimizer="search")]
        if not transient_within_sample(period):
            controllers.append(model_mpc(NOMINAL, period, MPC_ORACLE, binding=binding))
            # the ablation's variant (cosim.study.optimizer_ablation.TWO_STEPS): what a second Gauss-Newton step costs
            controllers.append(nnpc(model, period, f"{NNPC} (rti, two steps)", optimizer="rti", rti_changes=TWO_STEPS))
            # the study's step without its reweightings (RtiSettings.reweightings): what they cost where they run
            controllers.append(nnpc(model, period, f"{NNPC} (rti, no reweightings)", optimizer="rti",
                                    rti_changes={"reweightings": 0}))
            # the option the study does not take (RtiSettings.reuse_jacobian): a second step whose trial is rolled out
            # with the first step's sensitivities, not linearised again
            controllers.append(nnpc(model, period, f"{NNPC} (rti, two steps, reused Jacobian)", optimizer="rti",
                                    rti_changes={**TWO_STEPS, "reuse_jacobian": True}))
        # each controller's own closed loop, then their C steps timed pass by pass in turn (replay_interleaved: the
        # variants' ratios under the same machine conditions)
        recorded = [(controller, record_measurements(binding, implemented(controller), scenario))
                    for controller in controllers]
        replays = replay_interleaved(recorded, 1 if quick else REPLAY_PASSES)
        for (controller, measurements), result in zip(recorded, replays):
            c_p50, c_p99, py_p50, py_p99 = _c_and_python_step_us(controller, measurements, result)
            budget = period * 1e6
            online = controller.name.startswith(NNPC)
            rti = getattr(controller, "rti", None) is not None
            note = f"NN: {origin}" if online else ""
            if rti:  # issue 24's targets, on the online NNPC's RTI steps; the search's fallback steps apart
                per_pass = result.ns.reshape(-1, len(measurements)) * 1e-3
                rti_us, search_us = per_pass[:, result.rti], per_pass[:, ~result.rti]
                rti_p99, fallbacks = _p99(rti_us), int(np.count_nonzero(~result.rti))
                limit = 2.0 if transient_within_sample(period) else budget
                rows.append(BenchRow(
                    f"C RTI step, {controller.name}, {label} (the {int(result.rti.sum())} of {len(measurements)} "
                    f"samples the RTI planned, {100 * rti_p99 / budget:.3g} % of the period at p99)",
                    float(np.median(rti_us)), rti_p99, "us", f"p99 <= {limit:.3g} us" if online else "",
                    rti_p99 <= limit if online else None,
                    f"{note + '; ' if note else ''}the search planned the other {fallbacks} (the cold start and the "
                    f"fallback rule: start-up region, reference steps): p50 {float(np.median(search_us)):.4g} us, max "
                    f"{float(np.max(search_us)):.4g} us -- the next row is every step"))
                rows.append(per_sample_median_row(
                    f"C RTI step, {controller.name}, {label}", per_pass, result.rti, limit if online else None,
                    "the row above is every pass's steps as timed, with the interrupts and preemptions of a "
                    "non-real-time OS"))
                if not quick or controller.name == NNPC:  # the smoke test counts the default's (callgrind: ~50 x)
                    rows.append(instruction_row(f"x86-64 instructions per C RTI step, {controller.name}, {label}",
                                                controller, measurements, result.rti))
                note += (f"{'; ' if note else ''}every step, the search's {fallbacks} included "
                         f"({100 * fallbacks / len(measurements):.2g} % of the samples: the p99 is theirs at 1 % or more)")
            rows.append(BenchRow(f"C step, {controller.name}, {label} ({len(measurements)} replayed samples, "
                                 f"{100 * c_p99 / budget:.3g} % of the period at p99)", c_p50, c_p99, "us", note=note))
            rows.append(BenchRow(f"Python step, {controller.name}, {label} (same inputs)", py_p50, py_p99, "us"))
            rows.append(BenchRow(f"speed-up of C over Python, {controller.name}, {label} (p50)", py_p50 / c_p50, None,
                                 "ratio"))
            if not online:
                continue
            if rti:
                counts = rti_operation_counts(controller, result.rti, result.qp_iterations, result.evaluations,
                                              result.reweighted)
            else:
                counts = operation_counts(controller, result.evaluations)
            cycles = cortex_m4f_cycles(counts)
            if rti:  # the estimate's target on the RTI's steps, as the timing's
                cycles = cycles[result.rti]
                counts = {key: value[result.rti] for key, value in counts.items()}
            quantities = [("candidates", "candidate evaluations (rollouts)"), ("macs", "multiply-accumulates"),
                          ("tanh", "tanh calls")] + ([("qp_iterations", "box-QP iterations")] if rti else [])
            for key, what in quantities:
                rows.append(BenchRow(f"{controller.name} {label} per {'RTI ' if rti else ''}step: {what} (counted)",
                                     float(np.median(counts[key])), float(np.percentile(counts[key], 99)), "count"))
            fraction = float(np.percentile(cycles, 99)) / (CORTEX_M4F.clock_hz * period)
            rows.append(BenchRow(
                f"{controller.name} {label} per {'RTI ' if rti else ''}step on a 170 MHz Cortex-M4F (float32 port, "
                "estimated cycles)",
                float(np.median(cycles)), float(np.percentile(cycles, 99)), "cycles",
                f"fits {CORTEX_M4F.clock_hz * period:.0f} cycles", fraction <= 1.0,
                f"p99 is {fraction:.3g} x the period; cost model: {CORTEX_M4F.mac:g} cycles/MAC and "
                f"{CORTEX_M4F.tanh:g}/tanh (calibrated: group embedded), {CORTEX_M4F.sqrt:g}/sqrt, "
                f"{CORTEX_M4F.candidate:g}/candidate (assumed), {CORTEX_M4F.interrupt:g} per sample for ADC/PWM/ISR "
                "(controllers/cost_model.py); the float32 build with the RTI is measured on an emulated Cortex-M4F "
                "in group embedded, which replaces this estimate (the model's prediction / the measurement there)"))
    return rows
