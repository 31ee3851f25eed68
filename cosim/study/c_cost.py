"""What the NNPC costs in C, per rate: the report's section (deterministic counts only).

The reproduction's NNPC of the nominal switched plant runs the paper's scenarios as its C twin
(the controller FMU's step); after every step the candidate evaluations the optimizer made are
read off its state, turned into operations (:mod:`controllers.cost_model`, exact for the code
paths of ``controllers/c``) and into cycles on a 170 MHz Cortex-M4F under the stated cost model.
Nanoseconds on this machine are wall-clock figures: they live in ``benchmarks.md`` (group
``c-controllers``), not here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from controllers.cost_model import CORTEX_M4F, cortex_m4f_cycles, operation_counts, rti_operation_counts
from controllers.nn_model import load_model
from cosim.base.labels import period_text
from cosim.design.experiments import implemented, nnpc, scenarios_for
from cosim.design.plants import plant_binding
from cosim.design.vocabulary import NNPC, pipeline_tag, plant_tag
from cosim.master import simulate


class _CountingTwin:
    """The NNPC's C twin, keeping the optimizer's candidate evaluations of every step."""

    def __init__(self, twin):
        self.twin = twin
        self.name, self.sample_period, self.duty_limits = twin.name, twin.sample_period, twin.duty_limits
        self.evaluations: list[int] = []
        self.rti: list[bool] = []
        self.qp_iterations: list[int] = []
        self.reweighted: list[int] = []

    def reset(self):
        self.twin.reset()

    def step(self, measurement):
        duty = self.twin.step(measurement)
        state = self.twin.state
        self.evaluations.append(int(state.evaluations))
        self.rti.append(self.twin.last_solver == "rti")
        self.qp_iterations.append(int(state.qp_iterations))
        self.reweighted.append(int(state.reweighted))
        return duty

    def describe(self):
        return self.twin.describe()


def count_nnpc_operations(model_path: Path, period: float, scenario_names) -> dict[str, np.ndarray]:
    """Per control sample of the NNPC (``model_path``, at ``period`` [s], with its default optimizer: the search at
    one switching period, the RTI at 1 ms) over ``scenario_names`` on the nominal switched plant: rollouts
    (candidate evaluations), MACs, tanh calls, square roots and Cortex-M4F cycles."""
    controller = nnpc(load_model(model_path, expect_period=period), period, NNPC)
    counting = _CountingTwin(implemented(controller, "c"))
    binding = plant_binding("nominal", "switched")
    for scenario in scenarios_for(period, scenario_names, spec=binding.converter):
        simulate(binding, counting, scenario, record_period=period)
    if controller.rti is not None:
        counts = rti_operation_counts(controller, np.array(counting.rti), np.array(counting.qp_iterations),
                                      np.array(counting.evaluations), np.array(counting.reweighted))
    else:
        counts = operation_counts(controller, np.array(counting.evaluations))
    counts["cycles"] = cortex_m4f_cycles(counts)
    return counts


def section(out_dir: Path, periods, scenario_names) -> list[str]:
    """The report's "What the NNPC costs in C" lines, for the nominal switched pipelines' NNPC."""
    m = CORTEX_M4F
    rows, verdicts = [], []
    for period in periods:
        path = out_dir / "models" / f"{pipeline_tag(plant_tag('nominal', 'switched'), period)}__nnpc.pt"
        if not path.is_file():
            continue
        counts = count_nnpc_operations(path, period, scenario_names)
        budget = CORTEX_M4F.clock_hz * period
        cells = [period_text(period), f"{len(counts['candidates'])}"]
        for key in ("candidates", "macs", "tanh"):
            cells.append(f"{np.median(counts[key]):.0f} / {np.max(counts[key]):.0f}")
        p99, worst = np.percentile(counts["cycles"], 99), np.max(counts["cycles"])
        cells += [f"{p99:.4g} / {worst:.4g}", f"{budget:.0f}", f"{p99 / budget:.3g} / {worst / budget:.3g}",
                  "yes" if worst <= budget else "**no**"]
        rows.append("| " + " | ".join(cells) + " |")
        verdicts.append(f"at {period_text(period)} its worst step needs {worst / budget:.3g} x the period "
                        + ("(it fits)" if worst <= budget else
                           f"(it does not fit: {np.max(counts['macs']):.0f} MACs where about "
                           f"{budget / m.mac:.0f} would fill the period alone)"))
    if not rows:
        return []
    return [
        "The NNPC's step as the controller FMU runs it (the C twins of `controllers/c`), on the paper's "
        "scenarios and the nominal switched plant: operations counted per control sample from the "
        "optimizer's candidate evaluations (exact for the C code paths; `controllers/cost_model.py`), and "
        f"cycles on a {m.clock_hz / 1e6:.0f} MHz Cortex-M4F for a float32 port under a cost model: "
        f"{m.mac:g} cycles per multiply-accumulate and {m.tanh:g} per tanh (the float32 build's buckc_tanhf), "
        "calibrated on the explicit NNPC's forward pass measured on an emulated Cortex-M4F, "
        f"{m.sqrt:g} per square root (VSQRT.F32), {m.candidate:g} per "
        f"candidate (lattice, clipping, compare: assumed) and {m.interrupt:g} per sample for ADC, PWM and the "
        "interrupt. "
        "Nanoseconds per step on this machine (C harness vs Python) are wall-clock figures: "
        "[benchmarks.md](benchmarks.md), group `c-controllers`. These cycles are the cost model's estimate, kept "
        "because it prices every sample of these runs; the float32 builds themselves -- the online NNPC's with the "
        "real-time iteration and its search fallback, and the PI, the explicit NNPC, the current-mode controller, "
        "the Type-III -- are measured on an emulated Cortex-M4F, with the model's prediction against the "
        "measurement: [benchmarks.md](benchmarks.md), group `embedded` (rows \"cost-model prediction / measured\": "
        "below 1 for every controller, the model leaves out loop and call overheads and the bookkeeping around "
        "the network -- read these figures as a lower bound).",
        "",
        "| rate | samples | candidates p50 / max | MACs p50 / max | tanh p50 / max | M4F cycles p99 / max "
        "| cycles in a period | fraction of the period p99 / max | fits |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "On the Cortex-M4F, " + "; ".join(verdicts) + ".",
    ]
