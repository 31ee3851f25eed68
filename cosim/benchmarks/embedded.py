"""Group embedded: the float32 controllers on a Cortex-M4F (QEMU), measured."""

from __future__ import annotations

import math

import numpy as np

from cosim.benchmarks.common import BenchRow
from cosim.benchmarks.subjects import _benchmark_pi, _explicit_policy, _mixed_scenario
from cosim.study.vocabulary import PAPER_PERIOD, SWITCHING_PERIOD


def _embedded_controllers(quick: bool):
    """What the embedded group measures at 13.33 us: (controller, its operation counts for the cost model,
    where it comes from). A controller with a float32 build and a row in cortex_m4.EMBEDDED_CONTROLLERS
    is one more entry here."""
    from controllers.cost_model import (
        compensator_operation_counts,
        current_mode_operation_counts,
        pi_operation_counts,
        policy_operation_counts,
    )
    from cosim.study.classical_design import design_current_mode, design_type_iii, targets_for
    from cosim.study.experiments import explicit_nnpc, plant_binding
    from cosim.study.vocabulary import NNPC_EXPLICIT, NOMINAL

    policy, origin = _explicit_policy(quick)
    pi = _benchmark_pi(SWITCHING_PERIOD)
    targets = targets_for(plant_binding("nominal", "switched"), SWITCHING_PERIOD)
    current_mode = design_current_mode(NOMINAL, targets).controller
    type_iii = design_type_iii(NOMINAL, targets).controller
    designed = "designed for the nominal switched plant as make reproduce designs it"
    return [(pi, pi_operation_counts(), "the benchmark PI gains"),
            (explicit_nnpc(policy, NNPC_EXPLICIT), policy_operation_counts(policy.config), f"policy: {origin}"),
            (current_mode, current_mode_operation_counts(), designed),
            (type_iii, compensator_operation_counts(type_iii.coefficients.order), designed)]


def bench_embedded(quick: bool) -> list[BenchRow]:
    """The float32 builds cross-compiled for a Cortex-M4F (-O2, hard float) and executed in QEMU's
    mps2-an386, replaying recorded closed-loop measurements of the nominal switched plant at 13.33 us:
    duties against the host's float32 build, instructions per step from the execution trace, cycles from
    the executed instruction mix with the Cortex-M4 TRM's table (cosim/benchmark_harness/cortex_m4.py), flash
    and RAM, the stack; the cost model's prediction against the measurement, and its network constants
    calibrated (the tanh probe and the explicit NNPC's forward pass)."""
    from controllers.base import Measurement
    from controllers.cost_model import CORTEX_M4F, calibrated, cortex_m4f_cycles
    from controllers.explicit_policy import N_FEATURES
    from controllers.native import native_twin
    from cosim.benchmark_harness import record_measurements
    from cosim.benchmark_harness.cortex_m4 import (
        CLOCK_HZ,
        CYCLE_TABLE,
        EXCEPTION_FRAME_BYTES,
        ISR_ALLOWANCE,
        measure,
        measure_tanh,
        toolchain_problem,
    )
    from cosim.study.experiments import plant_binding
    from cosim.study.vocabulary import NNPC_EXPLICIT

    problem = toolchain_problem()
    if problem:
        return [BenchRow("Cortex-M4F measurements (QEMU mps2-an386): not measured", math.nan, None, "", note=problem)]
    period, label = SWITCHING_PERIOD, "13.33 us"
    budget, slow_budget = CLOCK_HZ * period, CLOCK_HZ * PAPER_PERIOD
    binding = plant_binding("nominal", "switched")
    samples = 40 if quick else 600
    scenario = _mixed_scenario(period, samples)
    probe = measure_tanh()
    tanh_cycles = float(np.median(probe.cycles))
    rows = [BenchRow("buckc_tanhf (the float32 build's tanh) on a Cortex-M4F: cycles per call, inlined in a loop "
                     f"({len(probe.cycles)} batches of {len(probe.values) // len(probe.cycles)}; p99 column: max)",
                     tanh_cycles, float(probe.cycles.max()), "cycles",
                     note=f"lower TRM reading {np.median(probe.cycles_low):.1f}; the target's values within "
                          f"{np.max(np.abs(probe.values - np.tanh(probe.arguments))):.3g} of tanh on [-4.5, 4.5) "
                          "(cortex_m4/tanh_probe.c; newlib's tanhf measured ~210 a call)")]
    for controller, counts, origin in _embedded_controllers(quick):
        measurements = record_measurements(binding, native_twin(controller), scenario)
        measured = measure(controller, measurements)
        run, size = measured.replay, measured.footprint
        n = len(measurements)
        host = native_twin(controller, "float32")
        host.reset()
        duties = np.array([host.step(Measurement(*row)) for row in measurements])
        identical = float(np.mean(duties == run.duty)) * 100
        name = f"{controller.name} {label} on a Cortex-M4F (float32, QEMU mps2-an386)"
        worst = float(run.cycles.max())
        predicted = float(cortex_m4f_cycles(counts)) - CORTEX_M4F.interrupt
        library = sum(c for f, c in run.functions.items() if not f.startswith("buckc_")) / n
        table = (f"TRM cycle table, upper reading (P = {CYCLE_TABLE.refill:g}, no load/store pipelining, SDIV "
                 f"{CYCLE_TABLE.divide:g}, VDIV 14); the lower reading (P = 1, pipelined loads) gives p50 "
                 f"{np.median(run.cycles_low):.0f} / max {run.cycles_low.max():.0f}")
        targeted = controller.name == NNPC_EXPLICIT
        rows += [
            BenchRow(f"{name}: instructions executed per step ({n} replayed samples; p99 column: max)",
                     float(np.median(run.instructions)), float(run.instructions.max()), "count", note=origin),
            BenchRow(f"{name}: cycles per step from the executed instruction mix (p99 column: max)",
                     float(np.median(run.cycles)), worst, "cycles", note=table),
            BenchRow(f"{name}: max cycles per step + {ISR_ALLOWANCE:.0f}-cycle ISR allowance, 170 MHz", worst
                     + ISR_ALLOWANCE, None, "cycles", f"<= {budget:.0f} (13.33 us)", worst + ISR_ALLOWANCE <= budget,
                     f"{(worst + ISR_ALLOWANCE) / budget:.3g} x the switching period; library functions (libm) "
                     f"take {library:.0f} cycles per step on average"),
            BenchRow(f"{name}: the same against a 1 ms sample", worst + ISR_ALLOWANCE, None, "cycles",
                     f"<= {slow_budget:.0f} (1 ms)", worst + ISR_ALLOWANCE <= slow_budget,
                     f"{(worst + ISR_ALLOWANCE) / slow_budget:.3g} x the 1 ms sample"),
            BenchRow(f"{name}: flash the controller adds (code, configuration, library functions)", size.flash,
                     None, "bytes", "<= 16384" if targeted else "", size.flash <= 16384 if targeted else None,
                     f"text {size.text}, data {size.data} (arm-none-eabi-size of a minimal firmware with and "
                     f"without it); controller.o alone: text {size.object_sizes['text']}, data "
                     f"{size.object_sizes['data']}, bss {size.object_sizes['bss']}"),
            BenchRow(f"{name}: RAM the controller needs (state + stack + exception frame)", size.ram + run.stack_bytes
                     + EXCEPTION_FRAME_BYTES, None, "bytes", "<= 2048" if targeted else "",
                     size.ram + run.stack_bytes + EXCEPTION_FRAME_BYTES <= 2048 if targeted else None,
                     f".data + .bss {size.ram}, deepest stack of a step {run.stack_bytes} (painted stack; "
                     f"-fstack-usage frames: " + ", ".join(f"{k} {v}" for k, v in sorted(measured.stack_usage.items())
                                                          if v) + f"), FP exception frame {EXCEPTION_FRAME_BYTES}"),
            BenchRow(f"{name}: duties equal to the host's float32 build, bit for bit", identical, None, "%",
                     "100 %", identical == 100.0,
                     f"max |difference| {np.max(np.abs(duties - run.duty)):.3g} (the same float operations on "
                     "both: no libm in the steps, -ffp-contract=off)"),
            BenchRow(f"{name}: cost-model prediction / measured max cycles per step", predicted / worst, None,
                     "ratio", note=f"prediction {predicted:.0f} cycles (controllers/cost_model.py: "
                                   f"{CORTEX_M4F.mac:g} per MAC, {CORTEX_M4F.tanh:g} per tanh, {CORTEX_M4F.division:g} "
                                   f"per division, {CORTEX_M4F.candidate:g} for the step's bookkeeping) against "
                                   f"{worst:.0f} measured; the measurement replaces it"),
        ]
        if counts["tanh"]:
            widths = [N_FEATURES, *controller.policy.config.hidden, 1]
            layer_macs = sum(a * b for a, b in zip(widths[:-1], widths[1:]))
            forward = run.functions.get("buckc_policy_forward", 0.0) / n
            model = calibrated(CORTEX_M4F, tanh_cycles, forward, layer_macs, counts["tanh"])
            for what, value, committed, how in (
                    ("multiply-accumulate", model.mac, CORTEX_M4F.mac,
                     f"the explicit NNPC's forward pass ({forward:.0f} cycles a step: {layer_macs} layer MACs, "
                     f"{counts['tanh']:.0f} tanh) less its tanh at the probe's {tanh_cycles:.1f}, per MAC"),
                    ("tanh", model.tanh, CORTEX_M4F.tanh, "the tanh probe's median (above)")):
                rows.append(BenchRow(f"cost model calibrated on the Cortex-M4F: cycles per {what}", value, None,
                                     "cycles", f"controllers/cost_model.py's {committed:g} within 5 %",
                                     abs(committed / value - 1) <= 0.05,
                                     f"{how}; the online NNPC's estimate (no float32 build) uses it"))
    return rows
