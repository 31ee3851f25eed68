"""The workbench's master against two engines nobody here wrote: the loop as an SSP, rerun.

For the paper's four scenarios, with the PI and the NNPC, on the nominal averaged and switched
plants at 1 ms, each loop is exported as an SSP archive (:func:`cosim.ssp.package.export_ssp`)
and run by the three engines of :mod:`cosim.ssp.engines` at the archive's communication step
(10 us):

1. **The workbench's master on the SSP equals its normal run** (the controllers' C twins,
   :func:`cosim.master.simulate`): the largest difference of any recorded column, expected 0
   (<= 1e-12 V, A).
2. **fmpy and libcosim agree with each other**: both are fixed-step Jacobi; their documented
   algorithms differ only in how they count time (t = k h in double vs. whole nanoseconds).
3. **Their difference from the workbench is the Jacobi delay.** Expected from the algorithms
   (:mod:`cosim.ssp.engines`): at a control sample t_k the controller's duty is read before its
   inputs of t_k are set, so the plant runs [t_k, t_k + h) on the duty computed from the inputs of
   t_k - h and takes the workbench's duty from t_k + h: the duty response arrives tau = h late on
   the averaged plant; the switched plant latches the duty at PWM period starts, so there
   tau = ceil(h / T_pwm) T_pwm (one PWM period, 13.33 us, for any h up to it). Where the
   controller drives the transient (start-up, reference steps) the predicted difference is the
   workbench's own trajectory shifted by tau: dvo(t) = vo(t) - vo(t - tau), first order in h
   (max |dvo| ~ tau max |dvo/dt|). Checked over a ladder of communication steps.
4. The metrics from all three engines side by side, and an overlay figure.

:func:`run_loops` runs one controller's loops on one plant (the reproduction runs the four as tasks on
its cluster, beside its jobs); :func:`write_section` merges them, writes the tables (``ssp/*.csv``)
and figures (``figures/ssp_*.png``) under the output folder and returns the report section (Markdown);
:func:`agreement_section` does both in one process; :func:`append_to_report` is the reproduction's hook.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd
from fmpy.fmi2 import fmi2True

from controllers.base import Measurement
from cosim.base.errors import ControllerError
from cosim.base.files import atomic_write, atomic_write_text
from cosim.design.experiments import implemented, nnpc, scenarios_for
from cosim.design.plants import plant_binding
from cosim.design.vocabulary import NNPC, PAPER_PERIOD, PI, SWITCHING_PERIOD, pipeline_tag, plant_tag
from cosim.fmi.controller import FmuController, builtin_controller_binding
from cosim.master import simulate
from cosim.metrics import metrics_table
from cosim.scenarios import PAPER_SCENARIOS
from cosim.ssp.engines import ENGINES, run_ssp
from cosim.ssp.package import export_ssp
from cosim.study.vocabulary import PAPER_SPEC

PLANT_MODES = ("averaged", "switched")
#: the reproduction's pipelines whose PI and NNPC the study runs as FMUs: it is part of a reproduction that runs both
SOURCE_PIPELINES = tuple(pipeline_tag(plant_tag("nominal", mode), PAPER_PERIOD) for mode in PLANT_MODES)
CONTROLLER_NAMES = (PI, NNPC)
#: the communication steps of the convergence ladder [s], and the scenario it is run on
LADDER = (1e-3, 1e-4, 5e-5, 2e-5, 1e-5, 5e-6, 2e-6, 1e-6)
QUICK_LADDER = (2e-5, 1e-5)
QUICK_SCENARIOS = ("reference_up",)  # the quick profile (the test suite runs it three times)
OVERLAY_SCENARIO = "reference_up"  # the scenario of the overlay figure (the engines' trajectories)
#: where the whole duty response is delayed (a reference step: the controller's input jumps at the
#: sample), the predicted difference is the workbench's trajectory shifted by the delay
SHIFTED = ("reference_up", "reference_down")
FINE_STEP = 1e-6  # [s] the workbench's recording step for the ladder's reference runs
EQUALITY_COLUMNS = ("output_voltage", "inductor_current", "measured_output_voltage", "measured_inductor_current",
                    "measured_load_current", "load_current", "duty_cycle", "reference", "load_resistance",
                    "input_voltage")
METRICS = {"rise_time_ms": "rise [ms]", "overshoot_pct": "overshoot [%]", "settling_time_ms": "settling [ms]",
           "steady_state_error_pct": "SSE [%]", "iae_Vs": "IAE [V s]"}


@dataclass(frozen=True)
class Case:
    scenario: str
    mode: str  # averaged or switched
    controller: str  # PI or NNPC
    ssp: Path
    controller_fmu: Path | None = None  # for the one-sample-delay prediction


def delay_of(mode: str, step: float) -> float:
    """[s] the delay the Jacobi engines add to the duty: h (averaged), whole PWM periods (switched)."""
    if mode == "switched":
        return math.ceil(step / SWITCHING_PERIOD - 1e-9) * SWITCHING_PERIOD
    return step


def controllers_for(out_dir: Path, mode: str, quick: bool = False) -> dict:
    """The reproduction's PI (tuned gains) and NNPC (trained network) for the nominal ``mode`` plant at 1 ms, read
    from ``out_dir``, where its pipeline (:data:`SOURCE_PIPELINES`) wrote them (the PI read with the reproduction's
    tuning settings -- ``quick``: the quick profile's -- so its design key matches)."""
    from controllers.nn_model import load_model
    from cosim.design.design_cache import pi_file
    from cosim.design.pi_tuning import load_or_tune

    binding = plant_binding("nominal", mode)
    pi = load_or_tune(pi_file(out_dir, binding.tag, PAPER_PERIOD), binding, PAPER_PERIOD,
                      quick=quick).controller()
    model = load_model(out_dir / "models" / f"{pipeline_tag(binding.tag, PAPER_PERIOD)}__nnpc.pt",
                       expect_period=PAPER_PERIOD)
    return {PI: pi, NNPC: nnpc(model, PAPER_PERIOD, NNPC)}


class PreviousSampleController(FmuController):
    """A controller FMU in the workbench's master in the order a Jacobi engine uses it at a
    communication step of one control period: at a sample t_k the duty is read *before* the
    measurement of t_k is set, i.e. computed from the previous sample's measurement (the state
    is committed with each measurement, as the engines do); the first sample reads its own
    measurement, as both engines propagate initial values. The prediction for h = Ts: a
    one-sample delay inside the feedback loop."""

    def step(self, measurement: Measurement) -> float:
        t = measurement.time
        first = not self._initialized
        if first:
            self._initialize(t)
        elif t > self.time:
            if self._do_step(self._component, self.time, t - self.time, fmi2True) > 1:
                raise ControllerError(f"{self.binding.origin}: fmi2DoStep failed at t = {t:.9g} s")
            self.time = t
        if not first:
            self._get_real(self._component, self._out_vr, 1, self._out_value)  # from the previous inputs
        buffer = self._in_value
        for i, (name, (scale, offset)) in enumerate(zip(self._fields, self._in_maps)):
            buffer[i] = scale * getattr(measurement, name) + offset
        self._set_real(self._component, self._in_vr, len(buffer), buffer)
        if first:
            self._get_real(self._component, self._out_vr, 1, self._out_value)
        scale, offset = self._duty_map
        return (self._out_value[0] - offset) / scale


class OldLoadCurrentAtLoadStep:
    """A controller whose sample at a load step reads the load current of the *old* load (vo / R
    before the step), as the Jacobi engines hand it over: the averaged plant's load_current output
    depends directly on its load input, which changes at that communication point. Everything
    else as ``inner``: the prediction of case (iii)."""

    def __init__(self, inner, scenario):
        self.inner, self.name = inner, inner.name
        self.sample_period, self.duty_limits = inner.sample_period, inner.duty_limits
        schedule = scenario.schedule("load_resistance")
        self.steps = [(t, before) for (t, _), (_, before) in zip(schedule[1:], schedule[:-1])]

    def reset(self) -> None:
        self.inner.reset()

    def describe(self) -> dict:
        return self.inner.describe()

    def step(self, m: Measurement) -> float:
        for time, old in self.steps:
            if abs(m.time - time) <= 1e-12:
                m = replace(m, load_current=m.output_voltage / old)
        return self.inner.step(m)


def _max_difference(a: pd.DataFrame, b: pd.DataFrame, columns) -> float:
    worst = 0.0
    for column in columns:
        x, y = a[column].to_numpy(), b[column].to_numpy()
        both = ~(np.isnan(x) & np.isnan(y))
        worst = max(worst, float(np.max(np.abs(x[both] - y[both]))) if both.any() else 0.0)
    return worst


def _on_grid(fine: pd.DataFrame, times: np.ndarray, column: str) -> np.ndarray:
    """A fine-grid workbench column at ``times`` (the engines' grid is a subset of the fine one)."""
    return np.interp(times, fine["time"].to_numpy(), fine[column].to_numpy())


def prediction(case: Case, step: float, tau: float, fine: pd.DataFrame, binding, scenario, controllers,
               cache: dict):
    """(model name, f(times, column) -> predicted engine-minus-workbench difference) for a
    communication step, from the engines' algorithm; (model, None) where only the order is
    predicted (second order in h: the controller's inputs move by O(h) within a step)."""
    if math.isclose(step, PAPER_PERIOD, rel_tol=1e-9) and case.controller_fmu is not None:
        # h = Ts: every duty is computed from the previous sample's measurement
        controller = PreviousSampleController(builtin_controller_binding(case.controller_fmu))
        try:
            delayed = simulate(binding, controller, scenario, record_period=FINE_STEP).frame
        finally:
            controller.close()
        return "one-sample loop delay", lambda t, c: _on_grid(delayed, t, c) - _on_grid(fine, t, c)
    if case.scenario in SHIFTED:
        return "shift by tau", lambda t, c: _on_grid(fine, t, c) - _on_grid(fine, t - tau, c)
    if case_of(case.scenario, case.mode, case.controller) == "(iii)":
        if "old load" not in cache:
            controller = OldLoadCurrentAtLoadStep(implemented(controllers[case.mode][case.controller]), scenario)
            cache["old load"] = simulate(binding, controller, scenario, record_period=FINE_STEP).frame
        late = cache["old load"]
        return "old load current at the step", lambda t, c: _on_grid(late, t, c) - _on_grid(fine, t, c)
    return "second order in h", None


def run_cases(cases: list[Case], controllers: dict, work: Path, ladder: tuple[float, ...],
              ladder_scenarios: tuple[str, ...] = PAPER_SCENARIOS) -> dict:
    """Every case with every engine, the equality and agreement checks, and the ladder."""
    rows, equality, convergence, frames = [], [], [], {}
    for case in cases:
        [scenario] = scenarios_for(PAPER_PERIOD, [case.scenario], spec=PAPER_SPEC)
        binding = plant_binding("nominal", case.mode)
        normal = simulate(binding, implemented(controllers[case.mode][case.controller]), scenario)
        runs = {engine: run_ssp(case.ssp, engine) for engine in ENGINES}
        frames[case] = runs
        table = metrics_table(list(runs.values()))
        table["engine"], table["plant"], table["controller"] = list(runs), case.mode, case.controller
        rows.append(table)
        wb, fm, lc = (runs[e].frame for e in ENGINES)
        equality.append({
            "scenario": case.scenario, "plant": case.mode, "controller": case.controller,
            "workbench_ssp_vs_normal": _max_difference(wb, normal.frame, EQUALITY_COLUMNS),
            "fmpy_vs_libcosim": _max_difference(fm, lc, ("output_voltage", "inductor_current", "duty_cycle")),
            "fmpy_vo_V": _max_difference(fm, wb, ("output_voltage",)),
            "libcosim_vo_V": _max_difference(lc, wb, ("output_voltage",)),
            "libcosim_iL_A": _max_difference(lc, wb, ("inductor_current",))})
        if case.scenario in ladder_scenarios and ladder:
            fine = run_ssp(case.ssp, "workbench", FINE_STEP).frame
            late = {}
            for step in ladder:
                tau = delay_of(case.mode, step)
                model, predicted = prediction(case, step, tau, fine, binding, scenario, controllers, late)
                for engine in (("libcosim", "fmpy") if step >= 5e-6 else ("libcosim",)):
                    frame = run_ssp(case.ssp, engine, step).frame
                    t = frame["time"].to_numpy()
                    row = {"scenario": case.scenario, "plant": case.mode, "controller": case.controller,
                           "engine": engine, "step_s": step, "predicted_delay_s": tau, "model": model}
                    for column, label in (("output_voltage", "dvo_V"), ("inductor_current", "diL_A")):
                        measured = np.abs(frame[column].to_numpy() - _on_grid(fine, t, column))
                        row[f"max_{label}"] = float(measured.max())
                        row[f"predicted_{label}"] = float(np.max(np.abs(predicted(t, column)))) if predicted else math.nan
                    convergence.append(row)
    metrics = pd.concat(rows, ignore_index=True)
    columns = ["scenario", "plant", "controller", "engine", *METRICS]
    return {"metrics": metrics[columns], "equality": pd.DataFrame(equality), "convergence": pd.DataFrame(convergence),
            "frames": frames}


# ---------------------------------------------------------------------------------------------
# Figures


def _overlay_figure(frames: dict, path: Path, scenario: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = [c for c in frames if c.scenario == scenario and c.controller in CONTROLLER_NAMES]
    cases.sort(key=lambda c: (PLANT_MODES.index(c.mode), CONTROLLER_NAMES.index(c.controller)))
    fig, axes = plt.subplots(2, len(cases), figsize=(3.6 * len(cases), 5.5), sharex=True, squeeze=False,
                             constrained_layout=True)
    styles = {"workbench": ("k", "-", 2.2), "fmpy": ("tab:orange", "--", 1.4), "libcosim": ("tab:blue", ":", 1.6)}
    for j, case in enumerate(cases):
        for engine, result in frames[case].items():
            f = result.frame
            window = (f["time"] >= 4.9e-3) & (f["time"] <= 5.6e-3)
            color, style, width = styles[engine]
            axes[0, j].plot(f["time"][window] * 1e3, f["output_voltage"][window], color=color, linestyle=style,
                            linewidth=width, label=engine)
            axes[1, j].plot(f["time"][window] * 1e3, f["inductor_current"][window], color=color, linestyle=style,
                            linewidth=width, label=engine)
        axes[0, j].set_title(f"{case.controller}, {case.mode} plant", fontsize=10)
        axes[1, j].set_xlabel("time [ms]")
    axes[0, 0].set_ylabel("output voltage vo [V]")
    axes[1, 0].set_ylabel("inductor current iL [A]")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"{scenario}: workbench master vs fmpy vs libcosim on the same SSP (h = 10 us)", fontsize=11)
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110, metadata={"Software": None}))
    plt.close(fig)
    return path


def _convergence_figure(convergence: pd.DataFrame, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True, sharey=True)
    for ax, mode in zip(axes, PLANT_MODES):
        part = convergence[(convergence["plant"] == mode) & (convergence["engine"] == "libcosim")
                           & (convergence["max_dvo_V"] > NOISE)]  # rounding-level rows would squash the scale
        for (scenario, controller), rows in part.groupby(["scenario", "controller"], sort=True):
            line = ax.loglog(rows["step_s"] * 1e6, rows["max_dvo_V"], "o-", label=f"{scenario}, {controller}")[0]
            ax.loglog(rows["step_s"] * 1e6, rows["predicted_dvo_V"], "x", color=line.get_color(), markersize=8)
        fm = convergence[(convergence["plant"] == mode) & (convergence["engine"] == "fmpy")
                         & (convergence["max_dvo_V"] > NOISE)]
        ax.loglog(fm["step_s"] * 1e6, fm["max_dvo_V"], "s", markerfacecolor="none", color="gray", label="fmpy")
        if mode == "switched":
            ax.axvline(SWITCHING_PERIOD * 1e6, color="gray", linewidth=0.8, linestyle="--")
            ax.text(SWITCHING_PERIOD * 1e6 * 1.1, ax.get_ylim()[0] * 2, "one PWM period", fontsize=8, color="gray")
        ax.set_title(f"{mode} plant (o libcosim, x predicted, squares fmpy)", fontsize=10)
        ax.set_xlabel("communication step h [us]")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("max |vo(engine) - vo(workbench)| [V]")
    axes[0].legend(fontsize=7)
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110, metadata={"Software": None}))
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------------------
# The report section


def _markdown(frame: pd.DataFrame, formats: dict[str, str] | None = None) -> list[str]:
    formats = formats or {}
    header = "| " + " | ".join(frame.columns) + " |"
    lines = [header, "|" + "---|" * len(frame.columns)]
    for _, row in frame.iterrows():
        cells = []
        for column, value in row.items():
            if isinstance(value, float):
                cells.append("n/a" if math.isnan(value) else format(value, formats.get(column, ".4g")))
            else:
                cells.append(str(value))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


#: [V] differences below this are rounding (the FMUs' last bits), not the algorithm
NOISE = 1e-9


def case_of(scenario: str, mode: str, controller: str) -> str:
    """(i): the reference jumps at the sample (the duty response is delayed by tau, first order);
    (iii): the load steps at a sample and the controller reads the load current, which the
    averaged plant's output changes with the load at once (feedthrough): the controller's sample
    there sees the old load, at any h; (ii): the inputs move smoothly within a step (second order)."""
    if scenario in SHIFTED:
        return "(i)"
    if scenario in ("load_change", "supply_dip") and controller == NNPC and mode == "averaged":
        return "(iii)"
    return "(ii)"


def _slopes(convergence: pd.DataFrame) -> pd.DataFrame:
    """The order of the vo difference in h between consecutive ladder steps."""
    rows = []
    part = convergence[convergence["engine"] == "libcosim"]
    for (scenario, mode, controller), g in part.groupby(["scenario", "plant", "controller"], sort=True):
        g = g.sort_values("step_s")
        s, v = g["step_s"].to_numpy(), g["max_dvo_V"].to_numpy()
        rows.append({"scenario": scenario, "plant": mode, "controller": controller,
                     "case": case_of(scenario, mode, controller),
                     **{f"{s[i] * 1e6:g}-{s[i + 1] * 1e6:g} us": (
                         float(np.log(v[i + 1] / v[i]) / np.log(s[i + 1] / s[i])) if min(v[i], v[i + 1]) > NOISE
                         else math.nan) for i in range(len(s) - 1)}})
    return pd.DataFrame(rows)


def run_loops(out_dir: Path, mode: str, controller: str, quick: bool = False) -> dict:
    """One controller's loops on one plant (``mode``), every scenario: its FMU exported from the reproduction's
    design in ``out_dir``, an SSP per scenario, each run by every engine (:func:`run_cases`). The reproduction runs
    the four (mode, controller) parts as tasks on its cluster, next to its jobs, once the source pipelines have
    written the designs; :func:`write_section` merges them. Returns :func:`run_cases`' tables, and its frames of
    :data:`OVERLAY_SCENARIO` only (the overlay figure's; the others would only travel back to be dropped)."""
    from cosim.fmi.controller_export import export_controller

    out_dir = Path(out_dir)
    scenarios = QUICK_SCENARIOS if quick else PAPER_SCENARIOS
    controllers = {mode: controllers_for(out_dir, mode, quick)}
    binding = plant_binding("nominal", mode)
    with tempfile.TemporaryDirectory(prefix="buck-cosim-ssp-study-") as tmp:
        work = Path(tmp)
        fmu = export_controller(controllers[mode][controller], work / f"{controller}.fmu")[0]
        cases = []
        for scenario in scenarios_for(PAPER_PERIOD, scenarios, spec=PAPER_SPEC):
            path = work / f"{scenario.name}__{controller}__{mode}.ssp"
            export_ssp(scenario, binding, fmu, path)
            cases.append(Case(scenario.name, mode, controller, path, work / f"{controller}-{mode}.fmu"))
        fmu.rename(work / f"{controller}-{mode}.fmu")
        results = run_cases(cases, controllers, work, QUICK_LADDER if quick else LADDER, scenarios)
    results["frames"] = {case: runs for case, runs in results["frames"].items() if case.scenario == OVERLAY_SCENARIO}
    return results


#: the study's parts in the order their rows appear in its tables: every (mode, controller)
PARTS = tuple((mode, controller) for mode in PLANT_MODES for controller in CONTROLLER_NAMES)


def write_section(out_dir: Path, parts: list[dict], quick: bool = False) -> str:
    """Merge :func:`run_loops`' ``parts`` (in :data:`PARTS`' order), write the tables (``ssp/*.csv``) and
    figures (``figures/ssp_*.png``) under ``out_dir`` and return the report section (Markdown)."""
    out_dir = Path(out_dir)
    results = {name: pd.concat([part[name] for part in parts if len(part[name])], ignore_index=True)
               for name in ("metrics", "equality", "convergence")}
    results["frames"] = {case: runs for part in parts for case, runs in part["frames"].items()}
    tables = out_dir / "ssp"
    for name in ("metrics", "equality", "convergence"):
        frame = results[name]
        atomic_write(tables / f"ssp_{name}.csv", lambda tmp, frame=frame: frame.to_csv(tmp, index=False))
    overlay = _overlay_figure(results["frames"], out_dir / "figures" / "ssp_overlay.png", OVERLAY_SCENARIO)
    converge = _convergence_figure(results["convergence"], out_dir / "figures" / "ssp_convergence.png")
    return _section_text(results, overlay.relative_to(out_dir), converge.relative_to(out_dir), quick)


def agreement_section(out_dir: Path, quick: bool = False) -> str:
    """Run the agreement study into ``out_dir`` (tables ``ssp/*.csv``, figures
    ``figures/ssp_*.png``) in this process, one part after the other, and return its report section (Markdown)."""
    return write_section(out_dir, [run_loops(out_dir, mode, controller, quick) for mode, controller in PARTS], quick)


def _section_text(results: dict, overlay: Path, converge: Path, quick: bool) -> str:
    equality, convergence, metrics = results["equality"], results["convergence"], results["metrics"]
    worst_equal = float(equality["workbench_ssp_vs_normal"].max())
    worst_engines = float(equality["fmpy_vs_libcosim"].max())
    lines = ["## The loop as an SSP, rerun by fmpy and libcosim", ""]
    if quick:
        lines += ["*(quick profile: one scenario and a short ladder; the numbers check the pipeline, not the "
                  "engines)*", ""]
    lines += [
        "Each loop (scenario FMU -> controller FMU <-> plant FMU, the nominal averaged and switched plants, PI and "
        "NNPC at 1 ms) is exported as an SSP 1.0 archive (`buck-cosim export-ssp`) and run by three engines at the "
        "archive's communication step h = 10 us (`buck-cosim run-ssp --engine ...`).", "",
        "**Expected, from each engine's documented algorithm.** The workbench's master is Gauss-Seidel at a control "
        "sample: it steps the plant to t_k, hands the controller y(t_k) and applies its duty from t_k. fmpy.ssp "
        "(`simulate_ssp`: every component sets its inputs, steps, reads its outputs; then the connections are "
        "applied) and libcosim (`fixed_step_algorithm`: all simulators step in parallel, then outputs are "
        "transferred) are fixed-step **Jacobi**: a communication point passes on the outputs each FMU had before "
        "any input at that point was set. The scenario's outputs and the plant's voltages and currents depend on "
        "their state only and arrive undelayed; the controller's duty depends directly on its inputs, so at t_k "
        "the plant receives the duty computed from the inputs of t_k - h and runs [t_k, t_k + h) on it: **one "
        "communication step of delay on the measurement-to-duty path**, tau = h. The switched plant latches the "
        "duty at each PWM period start, so there tau = ceil(h / T_pwm) T_pwm. Both engines propagate initial "
        "values before the first step (libcosim iterates its transfers; the fmpy engine does the same), so the "
        "first sample is not delayed. What that does to vo and iL depends on how far the controller's inputs "
        "move within [t_k - h, t_k]:", "",
        "- (i) an input *jumps* at the sample -- the reference at a reference step: the plant runs tau on the old "
        "duty, the whole duty response is delayed, and the difference is the workbench's own trajectory shifted "
        "by tau, vo(t) - vo(t - tau): **first order in h** (max |dvo| ~ tau max |dvo/dt|);",
        "- (ii) the inputs move by O(h) within h (start-up after the first sample, the load step for the PI, "
        "which does not read the load current): **second order in h**;",
        "- (iii) one plant output is not a state: the load current vo/R depends directly on the load input, so it "
        "crosses a Jacobi connection one step late too -- at the sample that coincides with the load step the "
        "controller gets the old load current, **whatever h is**. Only the NNPC reads it, and only on the "
        "averaged plant does it move at that instant (the switched plant's sensor is the mean over the last "
        "completed PWM period): there the difference does not shrink with h;",
        "- on the switched plant the duty is latched and the sensor updated once per PWM period: below h = 13.33 "
        "us a stale duty is held a whole period and computed from the previous period's reading, so no case "
        "shrinks any more;",
        "- at h = Ts every duty is computed from the previous sample's measurement: a one-sample delay *inside* "
        "the feedback loop, a different closed loop.", "",
        f"**Workbench master on the SSP vs its normal run**: largest difference of any recorded column over all "
        f"{len(equality)} loops: **{worst_equal:.3g}** (required <= 1e-12).", "",
        f"**fmpy vs libcosim**: largest difference in vo, iL or duty: **{worst_engines:.3g}** -- the same Jacobi "
        "algorithm; they differ only in the clock (t = k h in double vs libcosim's whole nanoseconds), which moves "
        "the FMUs' last bits.", "",
        "Largest differences from the workbench at h = 10 us (V, A):", "",
    ]
    lines += _markdown(equality.rename(columns={"workbench_ssp_vs_normal": "workbench(SSP) - normal",
                                                "fmpy_vs_libcosim": "fmpy - libcosim",
                                                "fmpy_vo_V": "fmpy vo", "libcosim_vo_V": "libcosim vo",
                                                "libcosim_iL_A": "libcosim iL"}),
                       {"workbench(SSP) - normal": ".2g", "fmpy - libcosim": ".2g"})
    libcosim = convergence[convergence["engine"] == "libcosim"]

    def ladder_table(rows: pd.DataFrame) -> list[str]:
        shown = rows[["scenario", "plant", "controller", "step_s", "predicted_delay_s", "model", "max_dvo_V",
                      "predicted_dvo_V", "max_diL_A", "predicted_diL_A"]].copy()
        shown["step_s"] = shown["step_s"] * 1e6
        shown["predicted_delay_s"] = shown["predicted_delay_s"] * 1e6
        shown = shown.rename(columns={"step_s": "h [us]", "predicted_delay_s": "tau [us]",
                                      "max_dvo_V": "max|dvo| [V]", "predicted_dvo_V": "predicted [V]",
                                      "max_diL_A": "max|diL| [A]", "predicted_diL_A": "predicted [A]"})
        return _markdown(shown, {"h [us]": "g", "tau [us]": ".4g"})

    lines += ["", "**The difference against the communication step** (libcosim; fmpy gives the same to ~1e-11 at "
              "every h it ran, all rows in `ssp/ssp_convergence.csv`). 'predicted' is the engine-minus-workbench "
              "difference the algorithm predicts: *shift by tau* -- the workbench's own trajectory delayed by tau; "
              "*one-sample loop delay* (h = Ts) -- the workbench's master with every duty computed from the previous "
              "sample's measurement (`PreviousSampleController`); *old load current at the step* -- the workbench's "
              "master with the controller's sample at the load step reading vo / R_old (`OldLoadCurrentAtLoadStep`). "
              "Reference step up (on the switched plant the shift also moves the iL ripple, which stays on the PWM "
              "grid in the engines: the shift model overstates diL there; vo's ripple is small):", ""]
    lines += ladder_table(libcosim[libcosim["scenario"] == "reference_up"])
    late = libcosim[libcosim["model"] == "old load current at the step"]
    if len(late):
        lines += ["", "Case (iii), the NNPC on the averaged plant at the load step (the plant's load_current "
                  "output depends directly on its load_resistance input, so at the sample that coincides with the "
                  "load step the engines hand the controller the old load current, at every h):", ""]
        lines += ladder_table(late)
    whole = libcosim[np.isclose(libcosim["step_s"], PAPER_PERIOD)]
    if len(whole):
        lines += ["", "h = Ts = 1 ms, every scenario: each duty is computed from the previous sample's measurement, a "
                  "one-sample delay inside the feedback loop -- a different closed loop, predicted by the "
                  "workbench's master with the same delay:", ""]
        lines += ladder_table(whole)
    slopes = _slopes(convergence)
    if len(slopes):
        lines += ["", "Order of max|dvo| in h between consecutive steps, every scenario (libcosim; 1 = first order, "
                  "2 = second, 0 = not shrinking; expected on the averaged plant for h < Ts: (i) 1, (ii) 2, (iii) 0; "
                  "on the switched plant below one PWM period (13.33 us): 0; n/a: the differences "
                  "are rounding, below 1e-9 V):", ""]
        lines += _markdown(slopes, {c: ".2f" for c in slopes.columns})
    lines += ["", f"![engines overlaid]({overlay.as_posix()})", "", f"![difference vs step]({converge.as_posix()})",
              "", "**Metrics from the three engines** (h = 10 us):", ""]
    wide = metrics.rename(columns=METRICS)
    lines += _markdown(wide)
    lines += ["", "**Defects found** (none in the workbench's master: it matches its normal run to the bit):", "",
              "- fmpy 0.3.32 `fmpy.ssp.simulation.simulate_ssp` cannot run the loop: it starts every connector at "
              "0.0 and sets inputs from them at the first step, so the plant receives load_resistance = 0 and "
              "refuses it (fmi2Error). It also stamps each row with the start t of the step whose end values "
              "(t + h) it holds, never applies the SSD's parameter bindings (.ssv) or connection transformations, "
              "and accumulates time (t += h); its command `python -m fmpy.ssp.simulate` ignores the SSD's default "
              "experiment (stop 1 s, step 1 % of it, past the controller's sample instants). The `fmpy` engine is fmpy's reader and per-component step "
              "(`read_ssd`, `get_connections`, `do_step`, `set_parameters`) in `simulate_ssp`'s loop with these "
              "four things corrected (listed in each run's metadata).",
              "- libcosimpy 0.0.6 `CosimObserver.time_series_real_samples` drops the last sample: it trims the "
              "result by counting step numbers equal to 0, and the first sample is step 0. The `libcosim` engine "
              "reads the samples with libcosimc's own function and the count it returns.",
              "- libcosim found one in the workbench's controller FMUs (not in its master): reading duty_cycle in "
              "Initialization Mode -- which libcosim does while it iterates initial values -- computed a duty with "
              "the controller not yet configured, and the predictive one (NNPC) crashed the process. Fixed in "
              "`controller_fmu.c`: the duty reads 0 until initialisation ends.", ""]
    return "\n".join(lines)


def append_to_report(out_dir: Path, report: Path, quick: bool = False, parts: list[dict] | None = None) -> Path:
    """The reproduction's hook: insert the study's section into ``report`` before "## Reproducing" (or at the
    end), from :func:`run_loops`' ``parts`` (in :data:`PARTS`' order) where the reproduction's cluster ran them,
    else running the study here."""
    section = write_section(out_dir, parts, quick) if parts is not None else agreement_section(out_dir, quick=quick)
    text = Path(report).read_text(encoding="utf-8")
    marker = "\n## Reproducing"
    text = text.replace(marker, "\n" + section + marker, 1) if marker in text else text.rstrip("\n") + "\n\n" + section
    return atomic_write_text(Path(report), text)
