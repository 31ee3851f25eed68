"""The sweep file: what a sweep runs, read and checked like scenario and binding files.

Every mistake is one :class:`~cosim.base.errors.ConfigError` naming the file, the key and its
line, the value and what was expected. The format (docs/guide/sweeps.md)::

    name = "tolerance"              # letters, digits, _ - . (default: the file's stem)
    description = "L, C +-20 %, ESR, DCR"
    scenarios = ["startup", "load_change"]   # shipped names or scenario files (relative to this file)
    controllers = ["pi", "nnpc", "mpc-nominal"]  # or [[controllers]] tables with settings (below)
    control_period = 1e-3           # [s] (or "1/75e3"); default 1e-3
    record_period = 1e-5            # [s] recording step, what the metrics see; default 1e-5
    samples = 200                   # random draws (required with a random axis)
    seed = 1                        # of the draws; default 0
    keep_traces = false             # also write every run's full table (DIR/traces/); default false
    batch_size = 10                 # runs per dask task (one FMU instance); default: automatic
    implementation = "c"            # the controllers' C twins (default) or "python"

    [plant]                         # the built-in FMU ...
    mode = "switched"               # "averaged" (default) or "switched"
    variant = "nominal"             # "nominal" (Table II, default) or "mismatch"
    # binding = "my_plant.toml"     # ... or an external FMU through a binding file

    [parameters]                    # FMU parameters, each a grid or a distribution
    inductance = { tolerance = 0.2 }                    # uniform, nominal x (1 +- 0.2)
    capacitance = { tolerance = [-0.3, 0.1] }           # uniform, nominal x (1 - 0.3 ... 1 + 0.1): ageing
    capacitor_esr = { low = 0.0, high = 0.1 }           # uniform [Ohm]
    inductor_resistance = { distribution = "log-normal", median = 0.05, sigma = 0.4 }
    switching_frequency = { values = [60e3, 75e3, 90e3] }   # a grid

    [operating_point]               # the scenarios' supply, load and reference, scaled run by run
    input_voltage = { distribution = "normal", tolerance = 0.1 }
    load_resistance = { values = [4.0, 6.0, 12.0] }     # the initial load [Ohm]; later steps scale alike
    reference = { values = [5.0, 12.0], anchor = "final" }  # [V] the value after the last step; earlier scale alike

    [spec]                          # the yield: share of runs meeting every threshold
    overshoot_pct = 5.0             # metric <= value (signed steady-state errors: |metric| <= value)
    settling_time_ms = 2.0
    steady_state_error_pct = 0.5

Distributions: ``uniform`` (``low``/``high``, or ``tolerance = t`` for nominal x (1 +- t), or
``tolerance = [lo, hi]``), ``normal`` (``mean``/``std``, or ``tolerance = t`` with t = 3 sigma
relative to the nominal), ``log-normal`` (``median``/``sigma`` of ln x, or ``tolerance = t``: median
the nominal, 3 sigma = a factor 1 + t). ``distribution`` defaults to ``uniform``. Grid axes combine
as a full factorial; the random axes are drawn ``samples`` times and every grid point, scenario
and controller sees the same draws (paired comparisons). Each axis draws from its own stream,
seeded by ``seed`` and the axis's name, so adding an axis leaves the others' draws unchanged.

``controllers`` entries (a name, or a table with ``kind`` and settings): ``pi`` (``kp`` [1/V] and
``ki`` [1/(V s)], else tuned on the nominal plant), ``nnpc`` / ``nnpc-paper`` (``model`` = a model
file, else identified on the nominal plant with ``samples`` (default 10 000) and ``seed``),
``mpc-nominal`` (the nominal plant's circuit model), ``fmu`` (``path`` = a controller FMU, e.g.
from ``buck-cosim export-controller``, or a controller-binding file naming one; its sample period
must be ``control_period``; default name ``<stem> (FMU)``, or a binding file's ``label``); ``name``
renames any of them. "Nominal" is the plant without any axis applied: the controllers are designed
once, for the plant on paper, and the sweep asks how they fare on the units that get built.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cosim.base.errors import ConfigError
from cosim.base.toml_files import TomlLocator, parse_toml
from cosim.design.vocabulary import (
    CONTROLLERS,
    DEFAULT_IMPLEMENTATION,
    IMPLEMENTATIONS,
    PAPER_PERIOD,
    PLANT_VARIANTS,
    PREDICTIVE_CONTROLLERS,
    SENSORS,
)
from cosim.metrics import METRIC_COLUMNS, WALLCLOCK_METRICS
from cosim.scenarios import Scenario, load_scenario

SHIPPED_DIR = Path(__file__).parent / "studies"
TOP_KEYS = {"name", "description", "plant", "parameters", "operating_point", "samples", "seed", "scenarios",
            "controllers", "control_period", "record_period", "keep_traces", "batch_size", "implementation", "spec"}
PLANT_KEYS = {"mode", "variant", "sensor", "binding"}
PLANT_MODES = ("averaged", "switched")
DISTRIBUTIONS = ("uniform", "normal", "log-normal")
AXIS_KEYS = {"values", "distribution", "tolerance", "low", "high", "mean", "std", "median", "sigma", "anchor"}
#: what an operating-point axis's value is: the signal's initial value (default; later values scale alike) or
#: its final value (the value after the scenario's last change of it; earlier values scale alike)
ANCHORS = ("initial", "final")
#: the keys each distribution takes (``tolerance`` is the relative form of each)
DISTRIBUTION_KEYS = {"uniform": {"tolerance", "low", "high"}, "normal": {"tolerance", "mean", "std"},
                     "log-normal": {"tolerance", "median", "sigma"}}
#: operating-point axes: the scenario signals a sweep may scale, with their units
OPERATING_POINT = {"input_voltage": "V", "load_resistance": "Ohm", "reference": "V"}
#: controller kinds a sweep designs once on the nominal plant (``fmu``: a given controller FMU, run as it is)
CONTROLLER_KINDS = ("pi", "nnpc", "nnpc-paper", "mpc-nominal", "fmu", "mpc-oracle", "nnpc-explicit", "current-mode",
                    "type-iii", "pi-envelope")
CONTROLLER_KEYS = {"kind", "name", "kp", "ki", "model", "samples", "seed", "path", "policy", "design", "settle",
                   "optimizer", "rti"}
KIND_KEYS = {"pi": {"kp", "ki"}, "nnpc": {"model", "samples", "seed", "policy"}, "nnpc-paper": {"model", "samples", "seed"},
             "mpc-nominal": set(), "fmu": {"path"}, "mpc-oracle": set(), "nnpc-explicit": {"policy"},
             "current-mode": {"design"}, "type-iii": {"design"}, "pi-envelope": {"kp", "ki"}}
#: the predictive kinds' optimizer (the RTI or the search) and its RTI settings
OPTIMIZER_KEYS = {"optimizer", "rti"}
KIND_KEYS = {kind: keys | {"settle"} | (OPTIMIZER_KEYS if kind in PREDICTIVE_CONTROLLERS else set())
             for kind, keys in KIND_KEYS.items()}
#: what ``path`` of an ``fmu`` controller may name
CONTROLLER_FILE_SUFFIXES = (".fmu", ".toml")
#: how closely a controller FMU's sample period must match the sweep's control period (relative)
PERIOD_MATCH = 1e-9
#: metrics a [spec] threshold may bound (not the wall-clock ones: a yield must not depend on the machine)
SPEC_METRICS = tuple(m for m in METRIC_COLUMNS if m not in WALLCLOCK_METRICS)
#: signed metrics: a threshold bounds their magnitude
SIGNED_METRICS = ("steady_state_error_V", "steady_state_error_pct")
MAX_RUNS = 1_000_000
NAME = re.compile(r"[A-Za-z0-9_.-]+")


@dataclass(frozen=True)
class Axis:
    """One swept quantity: a grid of values or a distribution.

    ``relative``: the draws are factors on the nominal value (``tolerance``), else values in the
    quantity's unit. ``group`` is ``parameters`` (an FMU parameter) or ``operating_point``.
    """

    name: str
    group: str
    kind: str  # "grid" or one of DISTRIBUTIONS
    relative: bool = False
    values: tuple = ()  # grid values
    settings: tuple[tuple[str, float], ...] = ()  # distribution settings (absolute, or factors if relative)
    place: str = ""  # file:line of the axis, for messages
    anchor: str = "initial"  # operating-point axes: the value is the signal's initial or final one (ANCHORS)

    @property
    def random(self) -> bool:
        return self.kind != "grid"

    @property
    def key(self) -> str:
        return f"{self.group}.{self.name}"

    def setting(self, name: str) -> float:
        return dict(self.settings)[name]

    def draw(self, seed: int, count: int) -> np.ndarray:
        """``count`` draws of a random axis (factors if relative), from its own seeded stream."""
        stream = np.random.default_rng(np.random.SeedSequence([seed, _stable_int(self.key)]))
        s = dict(self.settings)
        if self.kind == "uniform":
            return stream.uniform(s["low"], s["high"], count)
        if self.kind == "normal":
            return stream.normal(s["mean"], s["std"], count)
        return stream.lognormal(math.log(s["median"]), s["sigma"], count)

    def describe(self, unit: str = "") -> str:
        """``uniform, nominal x (1 +- 0.2)`` / ``grid 60000, 75000 Hz`` for the summary."""
        u = f" {unit}" if unit else ""
        if self.kind == "grid":
            return "grid " + ", ".join(f"{v:g}" for v in self.values) + u
        s = dict(self.settings)
        if self.relative:
            if self.kind == "uniform":
                return f"uniform, nominal x [{s['low']:g}, {s['high']:g}]"
            if self.kind == "normal":
                return f"normal, nominal x (1 +- {3 * s['std']:g} at 3 sigma)"
            return f"log-normal, median = nominal, sigma(ln) {s['sigma']:.3g}"
        if self.kind == "uniform":
            return f"uniform [{s['low']:g}, {s['high']:g}]{u}"
        if self.kind == "normal":
            return f"normal, mean {s['mean']:g}{u}, std {s['std']:g}{u}"
        return f"log-normal, median {s['median']:g}{u}, sigma(ln) {s['sigma']:g}"


@dataclass(frozen=True)
class PlantChoice:
    """The built-in FMU (mode, variant, sensor) or an external one through a binding file."""

    mode: str = "averaged"
    variant: str = "nominal"
    sensor: str = "average"
    binding: Path | None = None
    place: str = ""


@dataclass(frozen=True)
class ControllerEntry:
    """One controller of the sweep, as the file gives it (designed later, once, on the nominal plant)."""

    kind: str
    name: str
    kp: float | None = None  # [1/V]
    ki: float | None = None  # [1/(V s)]
    model: Path | None = None
    samples: int = 10_000  # identification samples (nnpc)
    seed: int = 0  # identification seed (nnpc)
    path: Path | None = None  # fmu: the controller FMU or controller-binding file given
    fmu: Path | None = None  # fmu: the controller FMU itself (``path``, or the FMU a binding file names)
    place: str = ""
    origin: str = ""  # how given gains or a given model were made, for the summary (set by code, not the file)
    policy: Path | None = None  # nnpc-explicit: a distilled policy file
    design: Path | None = None  # current-mode / type-iii: a design file (results/tuning/), else designed here
    settle: float | None = None  # [s] this controller's closed-loop operation before t = 0 (else the scenarios')
    optimizer: str | None = None  # predictive kinds: "rti" or "search" (else the kind's own: own_optimizer)
    rti: tuple[tuple[str, object], ...] = ()  # predictive kinds: RtiSettings fields changed, (name, value) pairs

    def describe(self) -> dict:
        described = {"kind": self.kind, "name": self.name, "kp": self.kp, "ki": self.ki,
                     "model": str(self.model) if self.model else None, "samples": self.samples, "seed": self.seed}
        for key in ("policy", "design", "settle", "optimizer"):
            if getattr(self, key) is not None:  # only then: the ids of sweeps that give none stay what they were
                described[key] = str(getattr(self, key)) if key != "settle" else self.settle
        if self.rti:
            described["rti"] = dict(self.rti)
        if self.kind == "fmu":
            described["path"] = str(self.path)
        return described


@dataclass(frozen=True)
class Threshold:
    """``metric <= limit`` (or ``|metric| <= limit`` for a signed metric): one line of the spec."""

    metric: str
    limit: float

    @property
    def signed(self) -> bool:
        return self.metric in SIGNED_METRICS

    def text(self) -> str:
        return f"|{self.metric}| <= {self.limit:g}" if self.signed else f"{self.metric} <= {self.limit:g}"


@dataclass(frozen=True)
class SweepSpec:
    name: str
    description: str
    plant: PlantChoice
    axes: tuple[Axis, ...]
    scenarios: tuple[Scenario, ...]
    controllers: tuple[ControllerEntry, ...]
    samples: int = 1
    seed: int = 0
    control_period: float = PAPER_PERIOD  # [s]
    record_period: float = 1e-5  # [s]
    keep_traces: bool = False
    batch_size: int | None = None
    implementation: str = DEFAULT_IMPLEMENTATION
    thresholds: tuple[Threshold, ...] = ()
    path: Path | None = None
    places: dict = field(default_factory=dict, compare=False)  # key -> file:line, for later checks

    @property
    def random_axes(self) -> tuple[Axis, ...]:
        return tuple(a for a in self.axes if a.random)

    @property
    def grid_axes(self) -> tuple[Axis, ...]:
        return tuple(a for a in self.axes if not a.random)

    @property
    def grid_points(self) -> int:
        return math.prod(len(a.values) for a in self.grid_axes)

    @property
    def run_count(self) -> int:
        return self.grid_points * self.samples * len(self.scenarios) * len(self.controllers)

    def place(self, key: str) -> str:
        return self.places.get(key) or str(self.path or "<sweep>")


def _stable_int(text: str) -> int:
    """A seed component from a name, the same in every process (``hash()`` is salted per process)."""
    import hashlib

    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little")


# ---------------------------------------------------------------------------------------------
# Parsing


class _Reader:
    """Locates keys and formats messages for one sweep file."""

    def __init__(self, path: Path | None, locator: TomlLocator):
        self.path, self.loc = path, locator
        self.name = str(path) if path else "<sweep>"

    def at(self, key: str | None, table: str | None = None, index: int | None = None) -> str:
        """``file:line`` of a key (or of a ``[table.key]`` sub-table written instead), else the file."""
        line = self.loc.line_of(key, table, index)
        if line is None and key is not None and table is not None:
            line = self.loc.line_of(None, f"{table}.{key}")
        return f"{self.name}:{line}" if line else self.name

    def fail(self, place: str, message: str):
        raise ConfigError(f"{place}: {message}")

    def number(self, value, label: str, place: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(place, f"{label} = {value!r} has the wrong type: expected a number")
        if not math.isfinite(float(value)):
            self.fail(place, f"{label} = {value} is not finite")
        return float(value)

    def integer(self, value, label: str, place: str, low: int, high: int | None = None) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(place, f"{label} = {value!r} has the wrong type: expected a whole number")
        if value < low or (high is not None and value > high):
            bound = f">= {low}" if high is None else f"{low} ... {high}"
            self.fail(place, f"{label} = {value} is invalid: expected {bound}")
        return value

    def period(self, value, label: str, place: str) -> float:
        """Seconds as a number or a fraction in text (``"1/75e3"``), > 0."""
        if isinstance(value, str):
            try:
                numerator, _, denominator = value.partition("/")
                seconds = float(numerator) / float(denominator) if denominator else float(numerator)
            except (ValueError, ZeroDivisionError):
                self.fail(place, f"{label} = {value!r} is not a period in seconds (e.g. 1e-3 or \"1/75e3\")")
        else:
            seconds = self.number(value, label, place)
        if not (seconds > 0 and math.isfinite(seconds)):
            self.fail(place, f"{label} = {value} s is invalid: expected a finite value > 0")
        return seconds

    def text(self, value, label: str, place: str) -> str:
        if not isinstance(value, str):
            self.fail(place, f"{label} has the wrong type: expected text")
        return value

    def choice(self, value, label: str, place: str, options) -> str:
        self.text(value, label, place)
        if value not in options:
            self.fail(place, f"{label} = {value!r} is unknown: expected one of {', '.join(options)}")
        return value

    def table(self, value, label: str, place: str) -> dict:
        if not isinstance(value, dict):
            self.fail(place, f"{label} must be a table")
        return value

    def unknown(self, table: dict, allowed: set[str], label: str, table_name: str | None, index=None) -> None:
        for key in table:
            if key not in allowed:
                self.fail(self.at(key, table_name, index), f"unknown key '{label}.{key}': expected one of "
                                                           f"{', '.join(sorted(allowed))}")


def parse_sweep(text: str, path: Path | None = None) -> SweepSpec:
    """Parse and check a sweep file's text (``path`` resolves relative files and names errors).
    The plant-dependent checks (parameters exist, nominal values) are :func:`cosim.design.sweeps.plan`'s."""
    data, loc = parse_toml(text, path, TOP_KEYS, unnamed="<sweep>")
    r = _Reader(path, loc)
    places: dict[str, str] = {}
    base = path.parent if path else Path.cwd()

    name = data.get("name", path.stem if path else "sweep")
    r.text(name, "name", r.at("name"))
    if not NAME.fullmatch(name):
        r.fail(r.at("name"), f"name = {name!r} is invalid: expected letters, digits, _ - . only")
    description = r.text(data.get("description", ""), "description", r.at("description"))

    plant = _plant(r, data.get("plant", {}), base)
    places["plant"] = plant.place

    axes = []
    for group in ("parameters", "operating_point"):
        table = r.table(data.get(group, {}), group, r.at(group))
        for axis_name, entry in table.items():
            if group == "operating_point" and axis_name not in OPERATING_POINT:
                r.fail(r.at(axis_name, group), f"unknown key 'operating_point.{axis_name}': expected one of "
                                                f"{', '.join(OPERATING_POINT)} (FMU parameters go under [parameters])")
            axes.append(_axis(r, group, axis_name, entry))
            places[f"{group}.{axis_name}"] = r.at(axis_name, group)

    random = [a for a in axes if a.random]
    if "samples" in data:
        samples = r.integer(data["samples"], "samples", r.at("samples"), 1, MAX_RUNS)
        if not random:
            r.fail(r.at("samples"), f"samples = {samples} but no axis is random: give the grid axes only, or a "
                                    "distribution to draw from")
    elif random:
        r.fail(f"{r.name}", f"missing required key 'samples': the random axes ({', '.join(a.key for a in random)}) "
                            "need a sample count")
    else:
        samples = 1
    seed = r.integer(data.get("seed", 0), "seed", r.at("seed"), 0)

    if "scenarios" not in data:
        r.fail(r.name, "missing required key 'scenarios' (shipped scenario names or scenario files, e.g. "
                       "[\"startup\", \"load_change\"])")
    scenarios_list = data["scenarios"]
    if not isinstance(scenarios_list, list) or not scenarios_list or not all(isinstance(s, str) for s in scenarios_list):
        r.fail(r.at("scenarios"), "scenarios must be a non-empty list of scenario names or files")
    scenarios = []
    converter = _plant_spec(plant)
    for entry in scenarios_list:
        candidate = base / entry
        source = candidate if entry.endswith(".toml") or candidate.is_file() else entry
        try:
            scenario = load_scenario(source, converter, warn=True)
        except ConfigError as error:
            r.fail(r.at("scenarios"), f"scenarios: {error}")
        if scenario.name in {s.name for s in scenarios}:
            r.fail(r.at("scenarios"), f"scenario {scenario.name!r} is listed twice")
        for axis in (a for a in axes if a.group == "parameters"):  # an event of the scenario would replace the value
            event = next((e for e in scenario.parameter_events if axis.name in e.parameters), None)
            if event is not None:
                r.fail(places[axis.key], f"{axis.key} is swept, but scenario {scenario.name} sets {axis.name} at "
                                         f"t = {event.time:g} s ({event.where or scenario.place('events')}): the "
                                         "event would replace the swept value -- sweep it on another scenario, or "
                                         "drop the axis")
        scenarios.append(scenario)

    control_period = r.period(data.get("control_period", PAPER_PERIOD), "control_period", r.at("control_period"))
    for key in ("control_period", "record_period"):  # for the plan's check of the periods against the scenarios
        if key in data:
            places[key] = r.at(key)
    controllers = _controllers(r, data, base, control_period)
    record_period = r.period(data.get("record_period", 1e-5), "record_period", r.at("record_period"))
    keep_traces = data.get("keep_traces", False)
    if not isinstance(keep_traces, bool):
        r.fail(r.at("keep_traces"), f"keep_traces = {keep_traces!r} has the wrong type: expected true or false")
    batch_size = None
    if "batch_size" in data:
        batch_size = r.integer(data["batch_size"], "batch_size", r.at("batch_size"), 1, 10_000)
    implementation = r.choice(data.get("implementation", "c"), "implementation", r.at("implementation"),
                              IMPLEMENTATIONS)

    thresholds = []
    spec_table = r.table(data.get("spec", {}), "spec", r.at("spec"))
    for metric, limit in spec_table.items():
        if metric not in SPEC_METRICS:
            r.fail(r.at(metric, "spec"), f"unknown key 'spec.{metric}': expected one of {', '.join(SPEC_METRICS)}")
        value = r.number(limit, f"spec.{metric}", r.at(metric, "spec"))
        if metric != "rise_time_ms" and value < 0:
            r.fail(r.at(metric, "spec"), f"spec.{metric} = {value:g} is invalid: expected >= 0 (an upper bound)")
        thresholds.append(Threshold(metric, value))

    spec = SweepSpec(name=name, description=description, plant=plant, axes=tuple(axes), scenarios=tuple(scenarios),
                     controllers=tuple(controllers), samples=samples, seed=seed, control_period=control_period,
                     record_period=record_period, keep_traces=keep_traces, batch_size=batch_size,
                     implementation=implementation, thresholds=tuple(thresholds), path=path, places=places)
    if spec.run_count > MAX_RUNS:
        r.fail(r.name, f"the sweep has {spec.run_count} runs ({spec.grid_points} grid points x {samples} samples x "
                       f"{len(scenarios)} scenarios x {len(controllers)} controllers): expected at most {MAX_RUNS}")
    return spec


def _plant_spec(plant: PlantChoice):
    """The converter spec the sweep's scenarios are resolved against: the binding file's, or the built-in plant's."""
    if plant.binding is not None:
        from cosim.fmi.binding_file import load_binding

        return load_binding(plant.binding).converter
    from cosim.fmi.binding import BUILTIN_SPEC

    return BUILTIN_SPEC


def _plant(r: _Reader, table, base: Path) -> PlantChoice:
    r.table(table, "plant", r.at("plant"))
    r.unknown(table, PLANT_KEYS, "plant", "plant")
    place = r.at(None, "plant")
    if "binding" in table:
        builtin = [k for k in ("mode", "variant", "sensor") if k in table]
        if builtin:
            r.fail(r.at(builtin[0], "plant"), f"plant.{builtin[0]} applies to the built-in FMU, but plant.binding "
                                              "names an external one: give one or the other")
        binding = base / r.text(table["binding"], "plant.binding", r.at("binding", "plant"))
        if not binding.is_file():
            r.fail(r.at("binding", "plant"), f"plant.binding = {table['binding']!r}: binding file {binding} does "
                                             "not exist")
        return PlantChoice(binding=binding, place=r.at("binding", "plant"))
    mode = r.choice(table.get("mode", "averaged"), "plant.mode", r.at("mode", "plant"), PLANT_MODES)
    variant = r.choice(table.get("variant", "nominal"), "plant.variant", r.at("variant", "plant"), tuple(PLANT_VARIANTS))
    sensor = r.choice(table.get("sensor", "average"), "plant.sensor", r.at("sensor", "plant"), SENSORS)
    return PlantChoice(mode=mode, variant=variant, sensor=sensor, place=place)


def _axis(r: _Reader, group: str, name: str, entry) -> Axis:
    label = f"{group}.{name}"
    place = r.at(name, group)
    if not isinstance(entry, dict):
        r.fail(place, f"{label} = {entry!r} is invalid: expected a table such as {{ tolerance = 0.2 }}, "
                      "{ low = 0.0, high = 0.1 } or { values = [1.0, 2.0] }")
    for key in entry:
        if key not in AXIS_KEYS:
            r.fail(place, f"unknown key '{label}.{key}': expected one of {', '.join(sorted(AXIS_KEYS))}")
    anchor = "initial"
    if "anchor" in entry:
        if group != "operating_point":
            r.fail(place, f"{label}.anchor applies to [operating_point] axes only")
        anchor = r.choice(entry["anchor"], f"{label}.anchor", place, ANCHORS)
        entry = {k: v for k, v in entry.items() if k != "anchor"}
    if "values" in entry:
        others = [k for k in entry if k != "values"]
        if others:
            r.fail(place, f"{label}: values (a grid) and {others[0]} (a distribution) exclude each other")
        values = entry["values"]
        if not isinstance(values, list) or not values:
            r.fail(place, f"{label}.values must be a non-empty list of numbers")
        for value in values:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                r.fail(place, f"{label}.values: {value!r} is invalid: expected finite numbers")
        if len(set(values)) != len(values):
            twice = next(v for v in values if values.count(v) > 1)
            r.fail(place, f"{label}.values lists {twice!r} twice")
        return Axis(name, group, "grid", values=tuple(values), place=place, anchor=anchor)

    kind = r.choice(entry.get("distribution", "uniform"), f"{label}.distribution", place, DISTRIBUTIONS)
    allowed = DISTRIBUTION_KEYS[kind] | {"distribution"}
    for key in entry:
        if key not in allowed:
            r.fail(place, f"{label}: {key} does not apply to a {kind} distribution: expected "
                          f"{', '.join(sorted(DISTRIBUTION_KEYS[kind]))}")
    if "tolerance" in entry:
        absolute = [k for k in entry if k not in ("tolerance", "distribution")]
        if absolute:
            r.fail(place, f"{label}: tolerance (relative to the nominal value) and {absolute[0]} (absolute) "
                          "exclude each other")
        return Axis(name, group, kind, relative=True, settings=_relative(r, label, place, kind, entry["tolerance"]),
                    place=place, anchor=anchor)
    if kind == "uniform":
        if "low" not in entry or "high" not in entry:
            r.fail(place, f"{label}: a uniform distribution needs low and high (or tolerance)")
        low = r.number(entry["low"], f"{label}.low", place)
        high = r.number(entry["high"], f"{label}.high", place)
        if not low < high:
            r.fail(place, f"{label}: low = {low:g} and high = {high:g} are invalid: expected low < high")
        settings = (("low", low), ("high", high))
    elif kind == "normal":
        if "std" not in entry:
            r.fail(place, f"{label}: a normal distribution needs std (and mean; or tolerance)")
        if "mean" not in entry:
            r.fail(place, f"{label}: a normal distribution with std needs mean too (or tolerance, relative to the "
                          "nominal value)")
        mean = r.number(entry["mean"], f"{label}.mean", place)
        std = r.number(entry["std"], f"{label}.std", place)
        if not std > 0:
            r.fail(place, f"{label}.std = {std:g} is invalid: expected > 0")
        settings = (("mean", mean), ("std", std))
    else:
        if "median" not in entry or "sigma" not in entry:
            r.fail(place, f"{label}: a log-normal distribution needs median and sigma (of ln x; or tolerance)")
        median = r.number(entry["median"], f"{label}.median", place)
        sigma = r.number(entry["sigma"], f"{label}.sigma", place)
        if not median > 0:
            r.fail(place, f"{label}.median = {median:g} is invalid: expected > 0 (a log-normal quantity is positive)")
        if not sigma > 0:
            r.fail(place, f"{label}.sigma = {sigma:g} is invalid: expected > 0")
        settings = (("median", median), ("sigma", sigma))
    return Axis(name, group, kind, settings=settings, place=place, anchor=anchor)


def _relative(r: _Reader, label: str, place: str, kind: str, tolerance) -> tuple[tuple[str, float], ...]:
    """Factor settings of a ``tolerance``: uniform 1 +- t (or [1 + lo, 1 + hi]), normal 3 sigma = t,
    log-normal 3 sigma(ln) = ln(1 + t)."""
    if isinstance(tolerance, list):
        if kind != "uniform":
            r.fail(place, f"{label}.tolerance = {tolerance!r}: a [low, high] tolerance applies to uniform "
                          "distributions only")
        if len(tolerance) != 2:
            r.fail(place, f"{label}.tolerance = {tolerance!r} is invalid: expected [low, high], e.g. [-0.3, 0.1]")
        low, high = (r.number(v, f"{label}.tolerance", place) for v in tolerance)
        if not -1 < low < high:
            r.fail(place, f"{label}.tolerance = {tolerance!r} is invalid: expected -1 < low < high")
        return (("low", 1 + low), ("high", 1 + high))
    t = r.number(tolerance, f"{label}.tolerance", place)
    if not 0 < t < 1:
        r.fail(place, f"{label}.tolerance = {t:g} is invalid: expected 0 < tolerance < 1 (a fraction: 0.2 is 20 %)")
    if kind == "uniform":
        return (("low", 1 - t), ("high", 1 + t))
    if kind == "normal":
        return (("mean", 1.0), ("std", t / 3))
    return (("median", 1.0), ("sigma", math.log(1 + t) / 3))


def _controllers(r: _Reader, data: dict, base: Path, control_period: float) -> list[ControllerEntry]:
    if "controllers" not in data:
        r.fail(r.name, f"missing required key 'controllers' (e.g. [\"pi\", \"nnpc\", \"mpc-nominal\"]; kinds: "
                       f"{', '.join(CONTROLLER_KINDS)})")
    entries = data["controllers"]
    if not isinstance(entries, list) or not entries:
        r.fail(r.at("controllers"), "controllers must be a non-empty list of controller kinds or [[controllers]] "
                                    "tables")
    tables = all(isinstance(e, dict) for e in entries) and r.loc.line_of(None, "controllers", 0) is not None
    controllers: list[ControllerEntry] = []
    for index, entry in enumerate(entries):
        place = r.at("kind", "controllers", index) if tables else r.at("controllers")
        if isinstance(entry, str):
            entry = {"kind": entry}
        if not isinstance(entry, dict):
            r.fail(place, f"controllers[{index}] = {entry!r} is invalid: expected a kind ({', '.join(CONTROLLER_KINDS)}) "
                          "or a table with 'kind'")
        for key in entry:
            if key not in CONTROLLER_KEYS:
                r.fail(r.at(key, "controllers", index) if tables else place,
                       f"unknown key 'controllers[{index}].{key}': expected one of {', '.join(sorted(CONTROLLER_KEYS))}")
        if "kind" not in entry:
            r.fail(place, f"controllers[{index}] has no kind: expected one of {', '.join(CONTROLLER_KINDS)}")
        kind = entry["kind"]
        if kind not in CONTROLLER_KINDS:
            hint = ""
            r.fail(place, f"controllers[{index}].kind = {kind!r} is unknown: expected one of "
                          f"{', '.join(CONTROLLER_KINDS)}{hint}")
        for key in entry:
            if key not in KIND_KEYS[kind] | {"kind", "name"}:
                r.fail(r.at(key, "controllers", index) if tables else place,
                       f"controllers[{index}].{key} does not apply to {kind}: expected "
                       f"{', '.join(sorted(KIND_KEYS[kind] | {'name'}))}")

        def at(key):
            return r.at(key, "controllers", index) if tables else place

        path = fmu = None
        default_name = CONTROLLERS.get(kind)
        if kind == "fmu":
            if "path" not in entry:
                r.fail(place, f"controllers[{index}]: kind \"fmu\" needs path = \"NAME.fmu\" (a controller FMU, e.g. "
                              "from buck-cosim export-controller, or a controller-binding .toml naming one)")
            path, fmu, default_name = _controller_fmu(r, index, entry["path"], at("path"), base, control_period,
                                                      r.at("control_period") if "control_period" in data else None)
        name = r.text(entry.get("name", default_name), f"controllers[{index}].name", at("name"))
        if not name.strip() or "/" in name or "=" in name:
            r.fail(at("name"), f"controllers[{index}].name = {name!r} is invalid: expected a label without / or =")
        if name in {c.name for c in controllers}:
            r.fail(at("name") if "name" in entry else place,
                   f"controller name {name!r} is used twice: give the second one a name = \"...\"")
        kp = ki = model = None
        if kind in ("pi", "pi-envelope") and ("kp" in entry or "ki" in entry):
            if "kp" not in entry or "ki" not in entry:
                r.fail(place, f"controllers[{index}]: kp and ki go together (or neither: tuned on the nominal plant)")
            kp = r.number(entry["kp"], f"controllers[{index}].kp", at("kp"))
            ki = r.number(entry["ki"], f"controllers[{index}].ki", at("ki"))
            if kp < 0 or ki < 0:
                r.fail(at("kp"), f"controllers[{index}]: PI gains kp = {kp:g}, ki = {ki:g} are invalid: expected >= 0")
        if "model" in entry:
            model = base / r.text(entry["model"], f"controllers[{index}].model", at("model"))
            if not model.is_file():
                r.fail(at("model"), f"controllers[{index}].model: model file {model} does not exist")
        files = {}
        for key in ("policy", "design"):
            if key in entry:
                files[key] = base / r.text(entry[key], f"controllers[{index}].{key}", at(key))
                if not files[key].is_file():
                    r.fail(at(key), f"controllers[{index}].{key}: file {files[key]} does not exist")
        settle = None
        if "settle" in entry:
            settle = r.number(entry["settle"], f"controllers[{index}].settle", at("settle"))
            if settle < 0:
                r.fail(at("settle"), f"controllers[{index}].settle = {settle:g} s is invalid: expected >= 0")
        samples = r.integer(entry.get("samples", 10_000), f"controllers[{index}].samples", at("samples"), 200)
        seed = r.integer(entry.get("seed", 0), f"controllers[{index}].seed", at("seed"), 0)
        optimizer, rti = _optimizer(r, index, kind, entry, at, control_period)
        controllers.append(ControllerEntry(kind=kind, name=name, kp=kp, ki=ki, model=model, samples=samples,
                                           seed=seed, path=path, fmu=fmu, place=place, policy=files.get("policy"),
                                           design=files.get("design"), settle=settle, optimizer=optimizer,
                                           rti=tuple(rti.items())))
    return controllers


def _optimizer(r: _Reader, index: int, kind: str, entry: dict, at, control_period: float) -> tuple[str | None, dict]:
    """A predictive controller's ``optimizer`` ("rti" or "search") and ``rti`` table (RtiSettings fields changed),
    checked against the settings of the sweep's control period as ``run --optimizer/--rti`` checks them. The
    optimizer is written out where the file gives rti or the kind's own is not the default (nnpc-paper's search):
    the recipe and the sweep's id then say it, and no worker's default decides it; nnpc and the MPCs that give
    neither keep the ids they had."""
    if kind not in PREDICTIVE_CONTROLLERS or ("optimizer" not in entry and "rti" not in entry
                                              and kind != "nnpc-paper"):
        return None, {}
    from cosim.design.experiments import own_optimizer, rti_settings, rti_table
    from cosim.design.vocabulary import OPTIMIZERS

    label = f"controllers[{index}]"
    optimizer = r.choice(entry["optimizer"], f"{label}.optimizer", at("optimizer"), OPTIMIZERS) \
        if "optimizer" in entry else None
    if "rti" not in entry:
        return optimizer or own_optimizer(kind), {}
    table = r.table(entry["rti"], f"{label}.rti", at("rti"))
    try:
        changes = rti_table(table)
    except ValueError as error:
        r.fail(at("rti"), f"{label}.rti: {error}")
    if own_optimizer(kind, optimizer) != "rti":
        why = 'optimizer = "search"' if optimizer else f'{kind} plans with the search unless optimizer = "rti"'
        r.fail(at("rti"), f"{label}.rti changes the real-time iteration's settings, but this controller plans with "
                          f"the search ({why}): drop rti")
    try:
        rti_settings(control_period, "rti", (0.0, 1.0), changes)
    except ValueError as error:
        r.fail(at("rti"), f"{label}.rti at the control period {control_period:.6g} s: {error}")
    return "rti", changes


def _controller_fmu(r: _Reader, index: int, value, place: str, base: Path, control_period: float,
                    period_place: str | None) -> tuple[Path, Path, str]:
    """An ``fmu`` controller's ``path``, checked as ``reproduce --controller`` checks one (the archive,
    the roles, the parameters, an instance that initialises) and against the sweep's control period.
    Returns the file given, the FMU itself and the default name."""
    from cosim.base.errors import WorkbenchError
    from cosim.design.controller_factory import external_name
    from cosim.fmi.controller import FmuController, controller_binding

    label = f"controllers[{index}].path"
    text = r.text(value, label, place)
    path = base / text
    if path.suffix.lower() not in CONTROLLER_FILE_SUFFIXES:
        r.fail(place, f"{label} = {text!r} is invalid: expected a controller FMU (.fmu) or a controller-binding file "
                      "(.toml)")
    what = "controller FMU" if path.suffix.lower() == ".fmu" else "controller-binding file"
    if path.is_dir():
        r.fail(place, f"{label} = {text!r}: {path} is a folder: expected a {what}")
    if not path.is_file():
        r.fail(place, f"{label} = {text!r}: {what} {path} does not exist")
    try:
        binding = controller_binding(str(path))
        controller = FmuController(binding, name=external_name(str(path)))
    except WorkbenchError as error:
        r.fail(place, f"{label} = {text!r}: {error}")
    try:
        period = controller.sample_period
        name = controller.name
    finally:
        controller.close()
    if abs(period - control_period) > PERIOD_MATCH * control_period:
        given = f"control_period = {control_period:.6g} s ({period_place})" if period_place else \
            f"control_period is {control_period:.6g} s (the default)"
        r.fail(place, f"{label} = {text!r}: the controller FMU's sample period is {period:.6g} s, but the sweep's "
                      f"{given}: a sweep runs every controller at its control_period (export the FMU with "
                      "--control-period, or set control_period)")
    return path, Path(binding.fmu_path), name


def shipped_studies() -> list[str]:
    return sorted(p.stem for p in SHIPPED_DIR.glob("*.toml"))


def load_sweep(name_or_path: str | Path) -> SweepSpec:
    """Read a sweep file, or a shipped study by name (``buck-cosim sweep tolerance``)."""
    path = Path(name_or_path)
    if not path.is_file() and not str(name_or_path).endswith(".toml") and (SHIPPED_DIR / f"{name_or_path}.toml").is_file():
        path = SHIPPED_DIR / f"{name_or_path}.toml"
    if path.is_dir():  # the wording of every command's file arguments (cosim.cli.options.input_file)
        raise ConfigError(f"sweep file {path} is a folder: expected a file")
    if not path.is_file():
        shipped = ", ".join(shipped_studies()) or "none"
        raise ConfigError(f"sweep file {name_or_path} does not exist (shipped studies: {shipped})")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(f"{path}: cannot read sweep file ({error})") from None
    return parse_sweep(text, path)
