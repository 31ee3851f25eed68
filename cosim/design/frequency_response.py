"""``buck-cosim frequency-response``: the loop gain, margins and output impedance of a controller on the
plant FMU in closed loop, measured by injection and correlation (what PLECS's and SIMBA's AC sweeps do
on the switching model), each frequency an independent run on the sweep engine.

One run per frequency: the closed loop settles at the operating point from rest (``settle``), a small
sine is injected from t = 0 (:class:`controllers.injection.InjectedController`) -- at the duty (the
loop gain T = -U/D, U the controller's output, D the duty applied), at the reference (the closed-loop
response Vo/R) or, through the scenario, at the load (R(t) = R0 / (1 + e sin w t) changed at every
sample: the output impedance -Vo/Io of the converter, the load itself excluded) -- and after
``discard_cycles`` injection periods (at least ``discard`` seconds) the signals are correlated over a
whole number of periods (at least ``cycles`` and ``window`` seconds). Frequencies are log-spaced from
``low`` to ``high`` and moved onto the window's DFT bins (an integer number of cycles in an integer
number of samples), so nothing leaks.

The runs go through the sweep engine's plan, worker and dataset (:mod:`cosim.design.sweeps`): on a dask
cluster from the command line, or in-process (the same worker code, one run after another) inside a
reproduction job. Beside each measured point stands the **closed form** of the averaged small-signal
model (:mod:`controllers.small_signal`) for the controllers that have one (the PI, the current-mode
controller, the Type-III), and the margins: measured (interpolated between the points in log f) and
closed-form (on a fine grid). Outputs in ``OUT``: ``frequency_response.csv``, ``margins.json``,
``bode.png`` (and ``.svg``), the sweep dataset under ``dataset/``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from cosim.base.digests import canonical, digest
from cosim.base.errors import ConfigError
from cosim.base.files import atomic_write, atomic_write_text, json_text
from cosim.design.sweeps import dataset
from cosim.design.sweeps.designs import build, design, injected_recipe
from cosim.design.sweeps.plan import PlannedRun, batch_key
from cosim.design.sweeps.recipes import PlantRecipe
from cosim.design.vocabulary import DEFAULT_IMPLEMENTATION
from cosim.scenarios import Scenario, ScenarioEvent

INJECTIONS = ("duty", "reference", "load")
#: default amplitudes: duty [1], reference [V], load [relative change of the load conductance]
DEFAULT_AMPLITUDE = {"duty": 0.01, "reference": 0.1, "load": 0.05}
QUANTITY = {"duty": ("loop gain T = -U/D", ""), "reference": ("closed-loop reference response Vo/R", ""),
            "load": ("closed-loop output impedance -Vo/Io", "Ohm")}
RESULT_COLUMNS = ("correlated_samples", "u_re", "u_im", "d_re", "d_im", "injection_re", "injection_im", "vo_re",
                  "vo_im", "il_re", "il_im", "io_re", "io_im")
FORMAT = "buck-cosim frequency response 1"


@dataclass(frozen=True)
class ResponseSettings:
    """What a frequency response measures and how (SI units)."""

    injection: str = "duty"
    low: float = 100.0  # [Hz]
    high: float = 30e3  # [Hz]
    points: int = 16
    amplitude: float | None = None  # default: DEFAULT_AMPLITUDE[injection]
    reference: float = 12.0  # [V] the operating point
    load: float = 6.0  # [Ohm]
    input_voltage: float = 48.0  # [V]
    settle: float = 15e-3  # [s] closed loop from rest before the injection starts
    discard_cycles: int = 3  # injection periods after t = 0 before the window
    discard: float = 1e-3  # [s] at least
    cycles: int = 4  # periods in the window, at least
    window: float = 1e-3  # [s] at least

    @property
    def injection_amplitude(self) -> float:
        return DEFAULT_AMPLITUDE[self.injection] if self.amplitude is None else self.amplitude

    def check(self, sample_period: float) -> None:
        if self.injection not in INJECTIONS:
            raise ConfigError(f"injection {self.injection!r} is unknown: expected one of {', '.join(INJECTIONS)}")
        nyquist = 0.5 / sample_period
        if not 0 < self.low < self.high < nyquist:
            raise ConfigError(f"frequencies {self.low:g} ... {self.high:g} Hz are invalid: expected 0 < low < high < "
                              f"the Nyquist frequency {nyquist:g} Hz of the control period")
        if not 2 <= self.points <= 200:
            raise ConfigError(f"points = {self.points} is invalid: expected 2 ... 200")
        a = self.injection_amplitude
        if not (math.isfinite(a) and a > 0) or (self.injection in ("duty", "load") and a >= 0.5):
            raise ConfigError(f"amplitude {a:g} is invalid: expected > 0 (and < 0.5 for the duty or the load)")
        if not (self.reference > 0 and self.load > 0 and self.input_voltage > self.reference):
            raise ConfigError(f"operating point {self.reference:g} V, {self.load:g} Ohm, {self.input_voltage:g} V is "
                              "invalid: expected a reference > 0 below the supply and a load > 0")


@dataclass(frozen=True)
class Point:
    index: int
    frequency: float  # [Hz] on a DFT bin of the window
    samples: int  # window length
    start: float  # [s] window start (scenario time)


def plan_points(settings: ResponseSettings, sample_period: float) -> list[Point]:
    """The frequencies, each moved to the nearest bin of its window (distinct, ascending)."""
    points, seen = [], set()
    for f in np.geomspace(settings.low, settings.high, settings.points):
        samples = max(round(settings.cycles / (f * sample_period)), round(settings.window / sample_period))
        cycles = max(1, round(f * samples * sample_period))
        frequency = cycles / (samples * sample_period)
        if round(frequency, 6) in seen:
            continue
        seen.add(round(frequency, 6))
        discard = max(settings.discard_cycles / frequency, settings.discard)
        start = math.ceil(discard / sample_period) * sample_period
        points.append(Point(len(points), frequency, samples, start))
    return points


def point_scenario(settings: ResponseSettings, point: Point, sample_period: float) -> Scenario:
    """The run of one point: the operating point, and for a load injection the load at every sample."""
    duration = point.start + (point.samples + 1) * sample_period
    events = ()
    if settings.injection == "load":
        e = settings.injection_amplitude
        steps = int(round(duration / sample_period))
        events = tuple(ScenarioEvent(k * sample_period, {"load_resistance": settings.load / (
            1 + e * math.sin(2 * math.pi * point.frequency * k * sample_period))}) for k in range(steps)
            if k * sample_period < duration)
    return Scenario(name=f"frequency_response_{point.index:03d}", description=f"{settings.injection} injection at "
                    f"{point.frequency:.6g} Hz", duration=duration, settle=settings.settle,
                    initial={"reference": settings.reference, "load_resistance": settings.load,
                             "input_voltage": settings.input_voltage}, events=events, analysis_start=0.0)


def result_schema() -> pa.Schema:
    extra = [pa.field("frequency_hz", pa.float64(), metadata={"unit": "Hz"})]
    extra += [pa.field(c, pa.float64()) for c in RESULT_COLUMNS]
    return dataset.row_schema([], tuple(extra))


def _ratio(row, injection: str) -> complex:
    def phasor(name):
        return complex(row[f"{name}_re"], row[f"{name}_im"])

    if injection == "duty":
        return -phasor("u") / phasor("d")
    if injection == "reference":
        return phasor("vo") / phasor("injection")
    return -phasor("vo") / phasor("io")


def closed_form(controller, parameters, settings: ResponseSettings, sample_period: float, sensor: str,
                frequencies, modulator: str = "zoh") -> np.ndarray | None:
    """The averaged small-signal model's value of the measured quantity at ``frequencies`` (None for a
    controller without a linear model, e.g. the predictive ones)."""
    from controllers.small_signal import Loop, OperatingPoint, discrete_plant, unit_circle

    linear = getattr(controller, "linear_model", None)
    if linear is None:
        return None
    op = OperatingPoint(settings.reference, settings.load, settings.input_voltage)
    loop = Loop(discrete_plant(parameters, op, sample_period, sensor, modulator), linear(settings.input_voltage))
    z = unit_circle(frequencies, sample_period)
    if settings.injection == "duty":
        return loop.loop_gain(z)
    if settings.injection == "reference":
        return loop.reference_to_output(z)
    return loop.output_impedance(z)


def interpolated_margins(frequencies: np.ndarray, values: np.ndarray) -> dict:
    """Crossover, phase and gain margins of a loop gain known at a few points: |T| and the unwrapped
    phase interpolated linearly in log f between them (the same definitions as
    :func:`controllers.small_signal.margins`)."""
    f = np.log(np.asarray(frequencies, dtype=float))
    magnitude = np.log(np.abs(values))
    phase = np.unwrap(np.angle(values))
    crossings = []
    for i in np.nonzero(np.sign(magnitude[:-1]) != np.sign(magnitude[1:]))[0]:
        w = magnitude[i] / (magnitude[i] - magnitude[i + 1])
        angle = math.degrees(phase[i] + w * (phase[i + 1] - phase[i]))
        crossings.append((math.exp(f[i] + w * (f[i + 1] - f[i])), (angle + 360.0) % 360.0 - 180.0, magnitude[i] > 0))
    gm = math.inf
    turns = np.floor((phase + np.pi) / (2 * np.pi))
    for i in np.nonzero(turns[:-1] != turns[1:])[0]:
        boundary = max(turns[i], turns[i + 1]) * 2 * np.pi - np.pi
        w = (boundary - phase[i]) / (phase[i + 1] - phase[i])
        level = magnitude[i] + w * (magnitude[i + 1] - magnitude[i])
        if level < 0:
            gm = min(gm, -20 * level / math.log(10))
    down = [c[0] for c in crossings if c[2]]
    return {"crossover_hz": max(down) if down else None,
            "phase_margin_deg": min(c[1] for c in crossings) if crossings else None,
            "gain_margin_db": gm if math.isfinite(gm) else None, "gain_crossovers_hz": [c[0] for c in crossings]}


def _runs(points, plant: PlantRecipe, recipes, scenarios) -> list[PlannedRun]:
    runs = []
    for point, recipe, scenario in zip(points, recipes, scenarios):
        payload = {"format": FORMAT, "plant": plant.identity(), "controller": recipe.digest,
                   "scenario": canonical(scenario.describe())}
        runs.append(PlannedRun(digest(canonical(payload))[:20], point.index, 0, (), (), scenario.name, recipe.name))
    return runs


def measure(binding, entry, control_period: float, settings: ResponseSettings, out_dir: Path, *, client=None,
            implementation: str = DEFAULT_IMPLEMENTATION, progress: bool = False,
            record_period: float | None = None) -> pd.DataFrame:
    """Measure one controller's response (module docstring); returns the points table (also written)."""
    from cosim.design.controller_factory import nominal_circuit, true_parameters
    from cosim.design.sweeps.execute import SweepExecution, execute
    from cosim.design.sweeps.plan import BatchTask
    from cosim.design.sweeps.worker import RunSettings, run_batch

    settings.check(control_period)
    out_dir = Path(out_dir)
    points = plan_points(settings, control_period)
    [base] = design([entry], binding, control_period, out_dir, progress)
    point = "none" if settings.injection == "load" else settings.injection
    recipes = [injected_recipe(base, f"{base.name} @ {p.frequency:.6g} Hz", p.frequency, settings.injection_amplitude,
                               point, p.start, p.samples, implementation) for p in points]
    scenarios = [point_scenario(settings, p, control_period) for p in points]
    plant = PlantRecipe.of(binding)
    runs = _runs(points, plant, recipes, scenarios)
    schema = result_schema()
    tasks = [BatchTask(batch_key((r,)), r.controller, r.scenario, (r,)) for r in runs]
    run_settings = RunSettings(record_period or control_period, implementation)
    frequency_of = {r.run_id: p.frequency for r, p in zip(runs, points)}
    if client is None:  # in-process: the same worker code, one run after another
        for task in tasks:
            result = run_batch(plant, next(x for x in recipes if x.name == task.controller),
                               next(s for s in scenarios if s.name == task.scenario), task.runs, run_settings)
            dataset.write_part(out_dir, task.controller, task.scenario, task.key, result.rows, schema)
    else:
        execution = SweepExecution(tasks, plant, {r.name: r for r in recipes}, {s.name: s for s in scenarios},
                                   run_settings, schema, out_dir, progress=progress, label="frequency response")
        execute(execution, client, lambda counts: f"frequency response interrupted after {counts.runs} of "
                                                  f"{len(runs)} points; run it again")
    rows = dataset.read_rows(out_dir, schema)
    rows = rows[rows["run_id"].isin(frequency_of)].copy()
    rows["frequency_hz"] = rows["run_id"].map(frequency_of)
    rows = rows.sort_values("frequency_hz").reset_index(drop=True)
    failed = rows[rows["status"] != "ok"]
    if len(failed):
        raise ConfigError(f"{len(failed)} of {len(rows)} frequency-response runs failed: {failed['error'].iloc[0]}")
    measured = np.array([_ratio(row, settings.injection) for _, row in rows.iterrows()])
    python = build(base, binding, "python")
    parameters = true_parameters(binding) if binding.source is None else \
        nominal_circuit(binding, "the closed-form loop gain (the nominal circuit)")
    targets = _targets(binding, control_period)
    sensor, modulator = targets.sensor, targets.modulator
    model = closed_form(python, parameters, settings, control_period, sensor, rows["frequency_hz"].to_numpy(),
                        modulator)
    table = pd.DataFrame({"controller": base.name, "injection": settings.injection,
                          "frequency_hz": rows["frequency_hz"].to_numpy(),
                          "magnitude_db": 20 * np.log10(np.abs(measured)),
                          "phase_deg": np.degrees(np.unwrap(np.angle(measured))),
                          "correlated_samples": rows["correlated_samples"].to_numpy()})
    if model is not None:
        table["closed_form_magnitude_db"] = 20 * np.log10(np.abs(model))
        table["closed_form_phase_deg"] = np.degrees(np.unwrap(np.angle(model)))
        wrap = (table["phase_deg"] - table["closed_form_phase_deg"] + 180) % 360 - 180
        table["magnitude_error_db"] = table["magnitude_db"] - table["closed_form_magnitude_db"]
        table["phase_error_deg"] = wrap
        table["phase_deg"] = table["closed_form_phase_deg"] + wrap  # the same branch as the closed form
    summary = {"format": FORMAT, "controller": base.name, "controller_settings": base.settings,
               "plant": binding.label, "sensor_model": sensor, "modulator_model": modulator,
               "control_period_s": control_period,
               "settings": asdict(settings), "amplitude": settings.injection_amplitude,
               "quantity": QUANTITY[settings.injection][0]}
    if settings.injection == "duty":
        summary["measured"] = interpolated_margins(table["frequency_hz"].to_numpy(), measured)
        if model is not None:
            from controllers.small_signal import Loop, OperatingPoint, discrete_plant

            op = OperatingPoint(settings.reference, settings.load, settings.input_voltage)
            loop = Loop(discrete_plant(parameters, op, control_period, sensor, modulator),
                        python.linear_model(op.input_voltage))
            summary["closed_form"] = loop.margins().describe()
    if model is not None:
        limit = 0.2 / control_period  # fsw / 5 at one sample per PWM period
        near = table[table["frequency_hz"] <= limit]
        summary["agreement_up_to_fsw_over_5"] = {
            "up_to_hz": limit, "max_magnitude_error_db": float(near["magnitude_error_db"].abs().max()),
            "max_phase_error_deg": float(near["phase_error_deg"].abs().max())}
    table.attrs["summary"] = summary
    if model is not None:  # the closed form on a dense grid, for the figure
        dense = np.geomspace(settings.low, min(settings.high * 1.2, 0.499 / control_period), 400)
        values = closed_form(python, parameters, settings, control_period, sensor, dense, modulator)
        table.attrs["dense"] = (dense, 20 * np.log10(np.abs(values)), np.degrees(np.unwrap(np.angle(values))))
    return table


def _targets(binding, control_period: float):
    """The sensor and modulator of the closed form: those the classical designs assume for this plant."""
    from dataclasses import replace

    from cosim.design.classical_design import targets_for

    try:
        return targets_for(binding, control_period)
    except ValueError:  # another rate: the sensor and modulator alone
        period = 1.0 / binding.converter.require("switching_frequency", "the closed-form loop gain's modulator")
        return replace(targets_for(binding, period), sample_period=control_period)


def write_outputs(tables: list[pd.DataFrame], out_dir: Path, stem: str = "frequency_response",
                  vector: bool = True) -> list[Path]:
    """``<stem>.csv`` (every point of every table), ``<stem>.json`` (each table's summary and margins)
    and the Bode plot ``<stem>.png`` with the margins marked."""
    out_dir = Path(out_dir)
    frame = pd.concat(tables, ignore_index=True)
    files = [atomic_write(out_dir / f"{stem}.csv", lambda tmp: frame.to_csv(tmp, index=False, float_format="%.10g"))]
    files.append(atomic_write_text(out_dir / f"{stem}.json", json_text([t.attrs["summary"] for t in tables]) + "\n"))
    files += bode_figure(tables, out_dir / stem, vector)
    return files


def bode_figure(tables: list[pd.DataFrame], stem: Path, vector: bool = True) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cosim.design.vocabulary import CONTROLLER_STYLES
    from cosim.plots import save_figure

    fig, (mag, ph) = plt.subplots(2, 1, figsize=(8.5, 6.8), sharex=True)
    for table in tables:
        s = table.attrs["summary"]
        name = s["controller"]
        colour = CONTROLLER_STYLES.get(name, ("black", "-"))[0]
        f = table["frequency_hz"]
        mag.semilogx(f, table["magnitude_db"], "o", color=colour, label=f"{name}: measured on the FMU")
        ph.semilogx(f, table["phase_deg"], "o", color=colour)
        if "dense" in table.attrs:
            fd, md, pd_ = table.attrs["dense"]
            shift = 360.0 * np.round((table["closed_form_phase_deg"].iloc[0] - np.interp(f.iloc[0], fd, pd_)) / 360.0)
            mag.semilogx(fd, md, "-", color=colour, lw=1.2, label=f"{name}: averaged small-signal closed form")
            ph.semilogx(fd, pd_ + shift, "-", color=colour, lw=1.2)
        measured = s.get("measured")
        if measured and measured.get("crossover_hz"):
            fc, pm = measured["crossover_hz"], measured["phase_margin_deg"]
            mag.axvline(fc, color=colour, ls=":", lw=1)
            ph.axvline(fc, color=colour, ls=":", lw=1)
            ph.annotate(f"PM {pm:.0f} deg at {fc:.0f} Hz", (fc, -180 + pm), color=colour, fontsize=8,
                        xytext=(4, 4), textcoords="offset points")
            ph.plot([fc, fc], [-180, -180 + pm], color=colour, lw=2.5, alpha=0.6)
            gm = measured.get("gain_margin_db")
            if gm is not None:
                mag.annotate(f"GM {gm:.1f} dB", (f.max(), -gm), color=colour, fontsize=8, ha="right")
    quantity, unit = QUANTITY[tables[0].attrs["summary"]["settings"]["injection"]]
    mag.axhline(0, color="grey", lw=0.8)
    ph.axhline(-180, color="grey", lw=0.8)
    mag.set_ylabel(f"|{quantity.split(' ')[-1]}| [dB{' ' + unit if unit else ''}]")
    ph.set_ylabel("phase [deg]")
    ph.set_xlabel("frequency [Hz]")
    s = tables[0].attrs["summary"]
    limit = 0.2 / s["control_period_s"]
    for ax in (mag, ph):
        ax.axvspan(limit, ax.get_xlim()[1], color="grey", alpha=0.08)
        ax.grid(True, which="both", alpha=0.3)
    mag.legend(fontsize=8)
    mag.set_title(f"{quantity} on {s['plant']} at {s['settings']['reference']:g} V, {s['settings']['load']:g} Ohm, "
                  f"{s['settings']['input_voltage']:g} V (shaded: above fsw/5)", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, stem)


#: what the reproduction measures on the nominal switched plant at one sample per PWM period:
#: (injection, controller names)
REPRODUCTION = (("duty", ("PI", "CMC", "Type-III")), ("load", ("PI", "CMC")))
REPRODUCTION_DIR = "frequency-response"


def in_pipeline(pipeline, binding, controllers, out_dir: Path, quick: bool = False, timings: dict | None = None,
                log=None) -> None:
    """The study's hook: at one sample per PWM period, on the paper's nominal switched plant or a bound plant (its
    classical designs are there), the loop gain of the PI, the current-mode controller and the Type-III and the
    output impedance of the PI and the current-mode controller at the converter's nominal point from 100 Hz to 2/5
    of its switching frequency, in-process (the job already runs on a dask worker), into ``frequency-response/``."""
    import time

    from cosim.design.sweeps.spec import ControllerEntry
    from cosim.design.vocabulary import pipeline_tag

    spec = binding.converter  # measured at its nominal point, up to 2/5 of its switching frequency
    if not (pipeline.binding_file or pipeline.plant_tag == "nominal-switched") \
            or not spec.samples_once_per_pwm_period(pipeline.control_period):
        return
    start = time.perf_counter()
    switching_frequency = spec.switching_frequency
    purpose = "the frequency response's operating point"
    operating_point = {"reference": spec.require("output_voltage", purpose),
                       "load": spec.require("load_resistance", purpose),
                       "input_voltage": spec.require("input_voltage", purpose)}
    folder = Path(out_dir) / REPRODUCTION_DIR
    by_name = {c.name: c for c in controllers}
    for injection, names in REPRODUCTION:
        settings = ResponseSettings(injection=injection, points=5 if quick else 16, high=2 * switching_frequency / 5,
                                    **operating_point)
        tables = []
        for name in names:
            controller = by_name[name]
            if name == "PI":
                entry = ControllerEntry("pi", name, kp=controller.kp, ki=controller.ki, origin="the pipeline's PI")
            else:
                design_dir = Path(out_dir) / "tuning"
                kind = "current-mode" if name == "CMC" else "type-iii"
                tag = pipeline_tag(pipeline.plant_tag, pipeline.control_period)
                entry = ControllerEntry(kind, name, design=design_dir / f"{kind}__{tag}.json",
                                        origin="the pipeline's design")
            tables.append(measure(binding, entry, pipeline.control_period, settings, folder / f"{injection}-{name}"))
        write_outputs(tables, folder, stem=f"{'loop_gain' if injection == 'duty' else 'output_impedance'}")
        if log is not None:
            for t in tables:
                a = t.attrs["summary"].get("agreement_up_to_fsw_over_5", {})
                log(f"  frequency response ({injection}) {t.attrs['summary']['controller']}: within "
                    f"{a.get('max_magnitude_error_db', float('nan')):.2f} dB, {a.get('max_phase_error_deg', float('nan')):.2f} "
                    "deg of the closed form up to fsw/5")
    if timings is not None:
        timings["frequency_response_s"] = time.perf_counter() - start
