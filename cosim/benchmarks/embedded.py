"""Group embedded: the float32 controllers on a Cortex-M4F (QEMU), measured."""

from __future__ import annotations

import math

import numpy as np

from cosim.base.labels import period_text
from cosim.benchmarks.common import BenchRow
from cosim.benchmarks.subjects import _benchmark_pi, _explicit_policy, _mixed_scenario
from cosim.design.vocabulary import PAPER_PERIOD, SWITCHING_PERIOD


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
    from cosim.design.classical_design import design_current_mode, design_type_iii, targets_for
    from cosim.design.experiments import explicit_nnpc
    from cosim.design.plants import plant_binding
    from cosim.design.vocabulary import NNPC_EXPLICIT, NOMINAL

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
    from cosim.design.plants import plant_binding
    from cosim.design.vocabulary import NNPC_EXPLICIT

    problem = toolchain_problem()
    if problem:
        return [BenchRow("Cortex-M4F measurements (QEMU mps2-an386): not measured", math.nan, None, "", note=problem)]
    period = SWITCHING_PERIOD
    label, slow = period_text(period, ascii_only=True), period_text(PAPER_PERIOD, ascii_only=True)
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
                     + ISR_ALLOWANCE, None, "cycles", f"<= {budget:.0f} ({label})", worst + ISR_ALLOWANCE <= budget,
                     f"{(worst + ISR_ALLOWANCE) / budget:.3g} x the switching period; library functions (libm) "
                     f"take {library:.0f} cycles per step on average"),
            BenchRow(f"{name}: the same against a {slow} sample", worst + ISR_ALLOWANCE, None, "cycles",
                     f"<= {slow_budget:.0f} ({slow})", worst + ISR_ALLOWANCE <= slow_budget,
                     f"{(worst + ISR_ALLOWANCE) / slow_budget:.3g} x the {slow} sample"),
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
                     (f"the explicit NNPC's forward pass ({forward:.0f} cycles a step: {layer_macs} layer MACs, "
                      f"{counts['tanh']:.0f} tanh) less its tanh at the probe's {tanh_cycles:.1f}, per MAC")),
                    ("tanh", model.tanh, CORTEX_M4F.tanh, "the tanh probe's median (above)")):
                rows.append(BenchRow(f"cost model calibrated on the Cortex-M4F: cycles per {what}", value, None,
                                     "cycles", f"controllers/cost_model.py's {committed:g} within 5 %",
                                     abs(committed / value - 1) <= 0.05,
                                     f"{how}; the online NNPC's prediction (below) uses it"))
    for period in (PAPER_PERIOD, SWITCHING_PERIOD):
        rows += _online_nnpc_rows(period, quick)
    return rows


def _steady_reference(scenario):
    """``scenario`` with its reference held at the initial value (loads and supplies still change)."""
    from dataclasses import replace

    events = tuple(replace(e, changes={k: v for k, v in e.changes.items() if k != "reference"})
                   for e in scenario.events)
    return replace(scenario, events=tuple(e for e in events if e.changes or e.parameters))


def _online_nnpc_replay(controller, period: float, samples: int) -> np.ndarray:
    """Recorded measurements for the online NNPC with the real-time iteration: the rate's mixed scenario
    (transients and steady state over the rate's identification region) driven by its double twin, on the
    nominal switched plant. At 13.33 us the reference is held (the loads and supplies still step) and the replay
    starts once the start-up has come within the RTI's start-up region: the search then plans the replay's cold
    start only -- a search step executes 2e7 instructions on the Cortex-M4F, which QEMU's trace takes 10-15 s
    and 250 MB to log -- and at a reference step the search would plan (RtiSettings.reference_step). At 1 ms the
    RTI plans every sample but the cold start, reference steps included, so the scenario is kept whole."""
    from controllers.native import native_twin
    from cosim.benchmark_harness import record_measurements
    from cosim.design.plants import plant_binding

    binding = plant_binding("nominal", "switched")
    if controller.rti.reference_step == 0.0:
        return record_measurements(binding, native_twin(controller), _mixed_scenario(period, samples))
    lead, settled = 400, 10  # samples the start-up may take (5.3 ms at 13.33 us); how long it must stay inside
    scenario = _steady_reference(_mixed_scenario(period, samples + lead))
    recorded = record_measurements(binding, native_twin(controller), scenario)
    inside = np.abs(recorded[:, 1] - recorded[:, 2]) <= controller.rti.startup_region / 2
    stays = np.convolve(inside, np.ones(settled), "valid") == settled  # inside from here for `settled` samples
    return recorded[int(np.argmax(stays)):][:samples]


def _online_nnpc_rows(period: float, quick: bool) -> list[BenchRow]:
    """The online NNPC with the real-time iteration, float32 build, on the Cortex-M4F: its RTI steps' cycles
    against the switching period's and the 1 ms budget, the search fallback's cycles (the cold start), footprint,
    the duties against the host's float32 build of the same image (bit for bit) and against the double twin,
    and the cost model's prediction of the RTI step against the measurement."""
    from controllers.base import Measurement
    from controllers.cost_model import CORTEX_M4F, cortex_m4f_cycles
    from controllers.native import native_twin
    from cosim.benchmark_harness import rti_operation_counts
    from cosim.benchmark_harness.cortex_m4 import (
        CLOCK_HZ,
        EXCEPTION_FRAME_BYTES,
        ISR_ALLOWANCE,
        host_replay,
        measure,
    )
    from cosim.benchmarks.subjects import _nn_model
    from cosim.design.experiments import nnpc
    from cosim.design.vocabulary import NNPC

    label = period_text(period, ascii_only=True)
    fast, slow = period_text(SWITCHING_PERIOD, ascii_only=True), period_text(PAPER_PERIOD, ascii_only=True)
    model, origin = _nn_model("nnpc", period, quick)
    # --quick (the suite's smoke test): a 4-step horizon at 13.33 us, so the traced cold-start search is small
    horizon = 4 if quick and period == SWITCHING_PERIOD else None
    controller = nnpc(model, period, f"{NNPC} (rti)", horizon=horizon, optimizer="rti")
    measurements = _online_nnpc_replay(controller, period, 40 if quick else 600)
    n = len(measurements)
    double = native_twin(controller)
    double.reset()
    duty64, solvers = [], []
    for row in measurements:
        duty64.append(double.step(Measurement(*row)))
        solvers.append(double.last_solver)
    rti = np.array(solvers) == "rti"  # the fallback rule reads measurements only: the float32 build's choice too
    measured = measure(controller, measurements, select=rti)
    run, size = measured.replay, measured.footprint
    host = host_replay(controller, measurements)
    identical = float(np.mean(host == run.duty)) * 100
    budget, slow_budget = CLOCK_HZ * SWITCHING_PERIOD, CLOCK_HZ * PAPER_PERIOD
    cycles, search = run.cycles[rti], run.cycles[~rti]
    worst = float(cycles.max())
    counts = rti_operation_counts(controller, rti, *_rti_diagnostics(controller, measurements))
    predicted = cortex_m4f_cycles({k: v[rti] for k, v in counts.items()}) - CORTEX_M4F.interrupt
    arch = "-".join(str(w) for w in (model.config.n_inputs, *model.config.hidden, 2))

    def own(rate: float, cycles_budget: float):
        """(target, met): a target against the controller's own rate's budget, none against the other's."""
        if rate != period:
            return "", None
        return f"<= {cycles_budget:.0f} ({period_text(rate, ascii_only=True)})", worst + ISR_ALLOWANCE <= cycles_budget
    name = f"online NNPC (RTI, {arch}) {label} on a Cortex-M4F (float32, QEMU mps2-an386)"
    note = (f"NN: {origin}; the {int(rti.sum())} of {n} replayed samples the RTI planned (the search planned the "
            f"other {int((~rti).sum())}: the cold start)")
    total = sum(run.functions.values())
    parts = {"the network's sensitivity pass (nn_model.c)": ("buckc_nn_sensitivities", "dense"),
             "the Gauss-Newton model": ("rti_model",), "the box QP": ("buckc_box_qp",),
             "the plan's rollout and costs": ("buckc_nn_shared_rollout", "buckc_nn_forward", "buckc_nn_rollout",
                                              "rti_costs"),
             "copies (memmove, memcpy, memset)": ("memmove", "memcpy", "memset")}
    split = ", ".join(f"{what} {100 * sum(run.functions.get(f, 0.0) for f in names) / total:.0f} %"
                      for what, names in parts.items())
    rows = [
        BenchRow(f"{name}: instructions executed per RTI step (p99 column: max)", float(np.median(run.instructions[rti])),
                 float(run.instructions[rti].max()), "count", note=note),
        BenchRow(f"{name}: cycles per RTI step from the executed instruction mix (p99 column: max)",
                 float(np.median(cycles)), worst, "cycles",
                 note=f"TRM cycle table, upper reading; the lower reading gives p50 "
                      f"{np.median(run.cycles_low[rti]):.0f} / max {run.cycles_low[rti].max():.0f}; where they go: "
                      f"{split}"),
        BenchRow(f"{name}: max cycles per RTI step + {ISR_ALLOWANCE:.0f}-cycle ISR allowance, 170 MHz, against a "
                 f"{fast} period", worst + ISR_ALLOWANCE, None, "cycles", *own(SWITCHING_PERIOD, budget),
                 f"{(worst + ISR_ALLOWANCE) / budget:.3g} x the switching period"),
        BenchRow(f"{name}: the same against a {slow} sample", worst + ISR_ALLOWANCE, None, "cycles",
                 *own(PAPER_PERIOD, slow_budget), f"{(worst + ISR_ALLOWANCE) / slow_budget:.3g} x the {slow} "
                 "sample"),
        BenchRow(f"{name}: cycles of the search's fallback step (the cold start)", float(search.max()), None,
                 "cycles", note=f"{search.max() / CLOCK_HZ * 1e3:.3g} ms at 170 MHz ({search.max() / budget:.3g} x the "
                                "switching period): the search is the RTI's fallback, not a real-time step"),
        BenchRow(f"{name}: flash the controller adds (code, configuration, library functions)", size.flash, None,
                 "bytes", note=f"text {size.text}, data {size.data}; the search's code included (the fallback)"),
        BenchRow(f"{name}: RAM the controller needs (state + stack + exception frame)",
                 size.ram + run.stack_bytes + EXCEPTION_FRAME_BYTES, None, "bytes",
                 note=f".data + .bss {size.ram}, deepest stack of a step {run.stack_bytes} (the RTI's Jacobian and "
                      f"Hessian live on the stack), FP exception frame {EXCEPTION_FRAME_BYTES}"),
        BenchRow(f"{name}: duties equal to the host's float32 build of the same image, bit for bit", identical, None,
                 "%", "100 %", identical == 100.0,
                 f"max |difference| {np.max(np.abs(host - run.duty)):.3g} (sqrtf and floorf are correctly rounded and "
                 "exact in both libms; the discount's powers are products, not powf)"),
        BenchRow(f"{name}: max |float32 duty - double twin's duty| over the replay", float(np.max(np.abs(
                 run.duty - np.array(duty64)))), None, "duty", note="the same measurements into both builds"),
        BenchRow(f"{name}: cost-model prediction / measured max cycles per RTI step", float(np.max(predicted)) / worst,
                 None, "ratio", note=f"prediction {np.max(predicted):.0f} cycles (controllers/cost_model.py with the "
                                     "RTI's counted operations) against the measured; the measurement replaces it"),
    ]
    return rows


def _rti_diagnostics(controller, measurements):
    """(box-QP iterations, candidate evaluations, reweighted box QPs) per step of the double C twin on
    ``measurements``."""
    from cosim.benchmark_harness import replay

    result = replay(controller, measurements, repeats=1)
    return result.qp_iterations, result.evaluations, result.reweighted
