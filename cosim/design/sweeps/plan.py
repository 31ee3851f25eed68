"""A sweep file against its plant, expanded into runs: values, run ids and the tasks that run them.

Checked here, before anything runs: every ``[parameters]`` axis names a parameter the FMU has
(causality parameter, of a type the values fit), a relative tolerance has a nominal value to be
relative to, every value lies within the FMU's declared min/max, an operating-point axis has its
role in the binding, every scenario's events have the roles they need, the control and record
periods suit every scenario (as ``buck-cosim run`` checks them), and no planned run puts the
reference above the input voltage in effect (as a scenario file is checked when read).

Each run's id is a SHA-256 of its full spec -- the plant (FMU bytes, roles, nominal parameters),
every swept value, the scenario's content, the controller's recipe (gains, model bytes), the
rates and the implementation -- so the same run always has the same id: ``--resume`` skips the
ids already in the dataset, and a rerun with the same seed gives the same rows.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from cosim.base.digests import canonical, digest
from cosim.base.errors import ConfigError
from cosim.design.sweeps.recipes import ControllerRecipe, PlantRecipe
from cosim.design.sweeps.spec import OPERATING_POINT, Axis, SweepSpec
from cosim.fmi.archive import check_fmu
from cosim.fmi.binding import BindingMismatch, PlantBinding, is_float, is_integer, resolve_parameters
from cosim.fmi.communication import grid_index
from cosim.master import check_communication_step, check_plant_supports, communication_of, record_period_of
from cosim.scenarios import Scenario, reference_above_supply, unreachable_text

RUN_ID_FORMAT = "buck-cosim sweep run 1"
RUN_ID_LENGTH = 20  # hex digits of the SHA-256 (80 bits)
#: runs per task when the sweep file gives no batch_size: about 8 tasks per controller and
#: scenario (so the workers finish together), at most this many (so a task stays short)
MAX_AUTO_BATCH = 20
TASKS_PER_PARTITION = 8


@dataclass(frozen=True)
class AxisInfo:
    """What the plant says about an axis: unit, nominal value, type and declared bounds."""

    axis: Axis
    unit: str
    nominal: float | None  # None for operating-point axes (per scenario) and parameters without one
    integer: bool = False
    minimum: float | None = None
    maximum: float | None = None


@dataclass(frozen=True)
class PlannedRun:
    run_id: str
    point: int  # index of the grid point (0 without grid axes)
    sample: int  # index of the random draw (0 without random axes)
    parameters: tuple[tuple[str, float | int], ...]  # FMU parameter -> value set for this run
    operating_point: tuple[tuple[str, float], ...]  # scenario signal -> initial value for this run
    scenario: str
    controller: str
    anchors: tuple[tuple[str, str], ...] = ()  # operating-point signal -> "final" where its value is the final one

    @property
    def values(self) -> dict[str, float | int]:
        return {**dict(self.parameters), **dict(self.operating_point)}


@dataclass(frozen=True)
class BatchTask:
    """Runs of one controller on one scenario, in one dask task with one reused FMU instance;
    they become one part file of the dataset, named by ``key``."""

    key: str
    controller: str
    scenario: str
    runs: tuple[PlannedRun, ...]

#: a swept value further than this factor from the parameter's nominal value (either way) is taken for a unit slip
#: (200 for 200 uH: 9e5 x the nominal 220 uH; a tolerance study spans a few x, a design space a few decades)
UNIT_SLIP_RATIO = 1e4


def nominal_binding(spec: SweepSpec) -> PlantBinding:
    """The sweep's plant without any axis applied."""
    if spec.plant.binding is not None:
        from cosim.fmi.binding_file import load_binding

        return load_binding(spec.plant.binding)
    from cosim.design.plants import plant_binding

    return plant_binding(spec.plant.variant, spec.plant.mode, spec.plant.sensor)


def _attribute(variable, name: str):
    value = getattr(variable, name, None)
    if value is None and getattr(variable, "declaredType", None) is not None:
        value = getattr(variable.declaredType, name, None)
    return value


def _float(text) -> float | None:
    try:
        return float(text) if text not in (None, "") else None
    except (TypeError, ValueError):
        return None


def check_axes(spec: SweepSpec, binding: PlantBinding) -> list[AxisInfo]:
    """Each axis against the plant (module docstring); a :class:`ConfigError` naming the axis's line."""
    md = check_fmu(binding.fmu_path).model_description
    variables = {v.name: v for v in md.modelVariables}
    fmu = Path(binding.fmu_path).name
    infos = []
    for axis in spec.axes:
        if axis.group == "operating_point":
            role = axis.name
            if role != "reference" and not binding.has(role):
                raise ConfigError(f"{axis.place}: operating_point.{axis.name}: {binding.origin} binds no variable to "
                                  f"the role {role!r}, so the scenarios cannot change it")
            infos.append(AxisInfo(axis, OPERATING_POINT[axis.name], None, minimum=0.0))
            continue
        variable = variables.get(axis.name)
        if variable is None:
            names = sorted(v.name for v in md.modelVariables if v.causality == "parameter")
            raise ConfigError(f"{axis.place}: parameters.{axis.name}: {fmu} has no parameter {axis.name!r}; its "
                              f"parameters are {', '.join(names) or 'none'}")
        if variable.causality != "parameter":
            raise ConfigError(f"{axis.place}: parameters.{axis.name}: {axis.name!r} is a{'n' if variable.causality[0] in 'aeiou' else ''} "
                              f"{variable.causality} of {fmu}, not a parameter"
                              + (" (sweep the scenario's supply and load under [operating_point])"
                                 if axis.name in OPERATING_POINT else ""))
        if not (is_float(variable) or is_integer(variable)):  # Real/Integer (FMI 2.0), Float64/Int32 ... (FMI 3.0)
            raise ConfigError(f"{axis.place}: parameters.{axis.name} is {variable.type} in {fmu}: a sweep varies "
                              "Real and Integer parameters")
        integer = is_integer(variable)
        if integer and axis.random:
            raise ConfigError(f"{axis.place}: parameters.{axis.name} is an Integer parameter of {fmu}: give a grid "
                              "(values = [...]), not a distribution")
        if integer and not all(isinstance(v, int) for v in axis.values):
            raise ConfigError(f"{axis.place}: parameters.{axis.name} is an Integer parameter of {fmu}: its values "
                              f"{list(axis.values)} must be whole numbers")
        nominal = binding.parameters.get(axis.name)
        nominal = _float(nominal) if nominal is not None else _float(variable.start)
        if axis.relative and not nominal:
            raise ConfigError(f"{axis.place}: parameters.{axis.name}: a tolerance is relative to the nominal value, "
                              f"which is {nominal if nominal is not None else 'not given'} for {fmu}: give absolute "
                              "bounds (low/high, mean/std, median/sigma)")
        if axis.relative and nominal < 0:
            raise ConfigError(f"{axis.place}: parameters.{axis.name}: a tolerance on a negative nominal value "
                              f"({nominal:g}) is ambiguous: give absolute bounds")
        unit = _attribute(variable, "unit") or ""
        if nominal and not axis.relative and not integer:  # 200 for 200 uH is 200 H: a unit slip, not a study
            far = next((v for v in axis.values if v and not 1 / UNIT_SLIP_RATIO <= abs(v / nominal) <= UNIT_SLIP_RATIO),
                       None)
            if far is not None:
                raise ConfigError(f"{axis.place}: parameters.{axis.name} = {far:g} {unit} is "
                                  f"{abs(far / nominal):.2g} x its nominal {nominal:g} {unit} in {fmu}: expected "
                                  f"values within {UNIT_SLIP_RATIO:g} x of it -- was it given in another unit?")
        try:  # the plant's own check (existence, type), with a representative value
            resolve_parameters({axis.name: (axis.values[0] if axis.values else float(nominal or 0.0))}, md, fmu)
        except BindingMismatch as error:
            raise ConfigError(f"{axis.place}: parameters.{axis.name}: {error}") from None
        infos.append(AxisInfo(axis, unit, nominal, integer, _float(_attribute(variable, "min")),
                              _float(_attribute(variable, "max"))))
    for scenario in spec.scenarios:
        try:
            check_plant_supports(binding, scenario)
        except ConfigError as error:
            raise ConfigError(f"{spec.place('plant')}: {error}") from None
    return infos


def check_rates(spec: SweepSpec, binding: PlantBinding) -> None:
    """The sweep's control and record periods against every scenario, with each controller's own settle
    time: the check ``buck-cosim run`` makes (:meth:`cosim.batch.Batch.check_rates`: enough controller
    samples in the recorded time, not too many instants: :func:`cosim.timeline.plan_timeline`), before any work
    rather than in every run on a worker; and the grid against a fixed-step plant FMU's communication step
    (:func:`cosim.master.check_communication_step`). The message names the sweep's key and line, then the
    scenario's own cause."""
    from cosim.timeline import plan_timeline

    communication = communication_of(binding)

    settles: dict[float | None, int] = {}  # a settle time the runs use (None: the scenarios' own) -> its controller
    for index, controller in enumerate(spec.controllers):
        settles.setdefault(controller.settle, index)
    for settle, index in settles.items():
        for scenario in spec.scenarios:
            run_as = scenario if settle is None else replace(scenario, settle=settle)
            try:
                timeline = plan_timeline(run_as, spec.control_period, spec.record_period)
            except ConfigError as error:
                try:  # the control period alone, at the fewest instants a record period can give
                    plan_timeline(run_as, spec.control_period, run_as.duration)
                    key, value = "record_period", spec.record_period
                except ConfigError:
                    key, value = "control_period", spec.control_period
                given = "" if key in spec.places else " (the default)"
                own = "" if settle is None else f" with controllers[{index}].settle = {settle:g} s"
                raise ConfigError(f"{spec.place(key)}: {key} = {value:.6g} s{given}{own}: {error}") from None
            try:
                check_communication_step(communication, timeline, run_as, binding.origin)
            except ConfigError as error:  # named at the first key that misses the grid (the plant's step otherwise)
                step = communication.for_run(spec.control_period)
                key = next((k for k in ("control_period", "record_period")
                            if k in spec.places and grid_index(getattr(spec, k), step) is None), "plant")
                raise ConfigError(f"{spec.place(key)}: {error}") from None


def anchor_value(scenario: Scenario, signal: str, anchor: str = "initial") -> float:
    """The value of ``signal`` an operating-point axis sets: its initial one, or its final one (after the
    scenario's last change of it)."""
    return scenario.schedule(signal)[-1][1] if anchor == "final" else scenario.initial[signal]


def at_operating_point(scenario: Scenario, values: dict[str, float], anchors=()) -> Scenario:
    """``scenario`` with its supply, load and/or reference moved: the anchored value (the initial one,
    or the final one for signals ``anchors`` names "final") becomes the run's, and every other value of
    that signal is scaled by the same factor (a 6 -> 5 Ohm step at 12 Ohm initial load becomes 12 -> 10
    Ohm; a reference step 9.6 -> 12 V anchored at its final value 5 V becomes 4 -> 5 V)."""
    if not values:
        return scenario
    anchored = dict(anchors)
    factors = {signal: value / anchor_value(scenario, signal, anchored.get(signal, "initial"))
               for signal, value in values.items()}
    initial = {**scenario.initial, **{k: values[k] if anchored.get(k, "initial") == "initial"
                                      else scenario.initial[k] * f for k, f in factors.items()}}
    events = tuple(replace(e, changes={k: (v * factors[k] if k in factors else v) for k, v in e.changes.items()})
                   for e in scenario.events)
    return replace(scenario, initial=initial, events=events)


def scenario_identity(scenario: Scenario) -> dict:
    """What decides a run's result (not where the file is, nor its prose)."""
    return {k: v for k, v in scenario.describe().items() if k not in ("source", "description")}


class SweepPlan:
    """The spec checked against its plant, and every run's values (drawn once, here)."""

    def __init__(self, spec: SweepSpec, binding: PlantBinding | None = None):
        self.binding = binding or nominal_binding(spec)
        if "record_period" not in spec.places:  # the default 10 us, or the nearest multiple of a fixed-step FMU's step
            spec = replace(spec, record_period=record_period_of(self.binding, spec.record_period, spec.control_period))
        self.spec = spec
        self.axes = check_axes(spec, self.binding)
        check_rates(spec, self.binding)
        oracle = next((c for c in spec.controllers if c.kind == "mpc-oracle"), None)
        if oracle is not None and any(a.group == "parameters" for a in spec.axes):
            raise ConfigError(f"{oracle.place}: mpc-oracle knows the nominal plant's circuit only, and [parameters] "
                              "axes change the circuit unit by unit: use mpc-nominal (the robustness question) or "
                              "sweep the operating point only")
        self.plant = PlantRecipe.of(self.binding)
        self._points = list(itertools.product(*(a.values for a in spec.grid_axes))) or [()]
        draws = {a.key: a.draw(spec.seed, spec.samples) for a in spec.random_axes}
        self._draws = draws
        self._check_anchors()
        self._check_bounds()
        self._check_reachable()

    @property
    def scenarios(self) -> dict[str, Scenario]:
        return {s.name: s for s in self.spec.scenarios}

    def info(self, key: str) -> AxisInfo:
        return next(i for i in self.axes if i.axis.key == key)

    def _values(self, info: AxisInfo, scenario: Scenario, point: int, sample: int) -> float | int:
        axis = info.axis
        if not axis.random:
            grid = [a.key for a in self.spec.grid_axes]
            value = self._points[point][grid.index(axis.key)]
            return int(value) if info.integer else float(value)
        drawn = float(self._draws[axis.key][sample])
        if not axis.relative:
            return drawn
        nominal = info.nominal if axis.group == "parameters" else anchor_value(scenario, axis.name, axis.anchor)
        return nominal * drawn

    def values(self, scenario: Scenario, point: int, sample: int) -> tuple[dict, dict]:
        """(FMU parameters, operating point) of one run."""
        parameters, operating = {}, {}
        for info in self.axes:
            value = self._values(info, scenario, point, sample)
            (parameters if info.axis.group == "parameters" else operating)[info.axis.name] = value
        return parameters, operating

    def _column(self, info: AxisInfo, scenario: Scenario) -> np.ndarray:
        """An axis's value in every run of a scenario (one controller), ordered grid point, sample."""
        return np.array([self._values(info, scenario, p, s) for p in range(len(self._points))
                         for s in range(self.spec.samples)], dtype=float)

    def _check_bounds(self) -> None:
        """Every value within the FMU's declared min/max, a supply and a load > 0, before any run."""
        for info in self.axes:
            operating = info.axis.group == "operating_point"
            unit = f" {info.unit}" if info.unit else ""
            for scenario in self.spec.scenarios if operating else self.spec.scenarios[:1]:
                values = self._column(info, scenario)
                if operating:
                    low, bad, bound = 0.0, values <= 0, "0 (a supply or a load must be > 0)"
                else:
                    low = info.minimum
                    bad = values < low if low is not None else np.zeros(len(values), dtype=bool)
                    bound = f"the FMU's minimum {low:g}{unit}" if low is not None else ""
                if bad.any():
                    where = f" in scenario {scenario.name}" if operating else ""
                    raise ConfigError(f"{info.axis.place}: {info.axis.key}: {int(bad.sum())} of {len(values)} values"
                                      f"{where} fall below {bound} (smallest {values.min():.4g}{unit}): narrow the "
                                      "distribution or bound it with low/high")
                if info.maximum is not None and (values > info.maximum).any():
                    raise ConfigError(f"{info.axis.place}: {info.axis.key}: {int((values > info.maximum).sum())} of "
                                      f"{len(values)} values exceed the FMU's maximum {info.maximum:g}{unit} (largest "
                                      f"{values.max():.4g}{unit})")

    def _check_anchors(self) -> None:
        """An operating-point axis scales each scenario's values of its signal by value / anchor
        (:func:`at_operating_point`): a scenario whose anchored value is 0 (a reference at rest) cannot be moved."""
        for info in self.axes:
            if info.axis.group != "operating_point":
                continue
            for scenario in self.spec.scenarios:
                axis = info.axis
                if anchor_value(scenario, axis.name, axis.anchor) == 0:
                    raise ConfigError(f"{axis.place}: {axis.key}: scenario {scenario.name}'s {axis.anchor} {axis.name} "
                                      f"is 0, which the axis cannot scale (it multiplies the scenario's {axis.name} by "
                                      "value / anchored value): expected a scenario whose anchored value is not 0, or "
                                      "the other anchor")

    def _check_reachable(self) -> None:
        """No planned run puts the reference above the input voltage in effect, at t = 0 or after any event:
        each run's scenario as the worker will run it (:func:`at_operating_point`), checked by the rule scenario
        files are checked by when read (:func:`cosim.scenarios.reference_above_supply`)."""
        swept = {i.axis.name: i for i in self.axes if i.axis.group == "operating_point"
                 and i.axis.name in ("reference", "input_voltage")}
        if not swept:
            return
        anchors = tuple((a.name, a.anchor) for a in self.spec.axes
                        if a.group == "operating_point" and a.anchor != "initial")
        count = len(self._points) * self.spec.samples
        for scenario in self.spec.scenarios:
            bad, first = 0, None
            for point in range(len(self._points)):
                for sample in range(self.spec.samples):
                    _, operating = self.values(scenario, point, sample)
                    moved = at_operating_point(scenario, operating, anchors)  # anchors are not 0 (_check_anchors)
                    found = reference_above_supply(moved.initial, list(enumerate(moved.events)))
                    if found is not None:
                        bad += 1
                        first = first or found
            if first is None:
                continue
            axis = (swept.get("reference") or swept["input_voltage"]).axis
            what = (f"{axis.key} with operating_point.input_voltage ({swept['input_voltage'].axis.place}): {bad} of "
                    f"{count} (reference, input voltage) pairs") if len(swept) == 2 else \
                f"{axis.key}: {bad} of {count} values"
            raise ConfigError(f"{axis.place}: {what} in scenario {scenario.name} put the reference above the input "
                              f"voltage (e.g. {unreachable_text(*first[:3])}): expected a reference <= the input "
                              "voltage")

    # ------------------------------------------------------------------ runs
    def runs(self, controllers: list[ControllerRecipe], implementation: str | None = None) -> list[PlannedRun]:
        """Every run, ordered controller, scenario, grid point, sample; ids hash each run's full spec."""
        spec = self.spec
        implementation = implementation or spec.implementation
        plant = self.plant.identity()
        anchors = tuple((a.name, a.anchor) for a in spec.axes if a.group == "operating_point" and a.anchor != "initial")
        runs = []
        for controller in controllers:
            for scenario in spec.scenarios:
                identity = scenario_identity(scenario)
                for point in range(len(self._points)):
                    for sample in range(spec.samples):
                        parameters, operating = self.values(scenario, point, sample)
                        payload = {"format": RUN_ID_FORMAT, "plant": plant, "parameters": parameters,
                                   "operating_point": operating, "scenario": identity,
                                   "controller": controller.digest, "control_period_s": spec.control_period,
                                   "record_period_s": spec.record_period, "implementation": implementation}
                        if anchors:  # only then: the ids of sweeps without anchored axes stay what they were
                            payload["anchors"] = dict(anchors)
                        run_id = digest(canonical(payload))[:RUN_ID_LENGTH]
                        runs.append(PlannedRun(run_id, point, sample, tuple(parameters.items()),
                                               tuple(operating.items()), scenario.name, controller.name, anchors))
        return runs

    def batch_size(self, runs_per_partition: int) -> int:
        if self.spec.batch_size:
            return self.spec.batch_size
        return max(1, min(MAX_AUTO_BATCH, math.ceil(runs_per_partition / TASKS_PER_PARTITION)))

    def batches(self, runs: list[PlannedRun]) -> list[BatchTask]:
        """Consecutive runs of one controller and scenario per task, interleaved across
        partitions (so every worker starts with different work)."""
        partitions: dict[tuple[str, str], list[PlannedRun]] = {}
        for run in runs:
            partitions.setdefault((run.controller, run.scenario), []).append(run)
        per_partition = []
        for (controller, scenario), members in partitions.items():
            size = self.batch_size(len(members))
            chunks = [tuple(members[i:i + size]) for i in range(0, len(members), size)]
            per_partition.append([BatchTask(batch_key(c), controller, scenario, c) for c in chunks])
        return [task for group in itertools.zip_longest(*per_partition) for task in group if task is not None]

    def identity(self, controllers: list[dict] | None = None) -> dict:
        """The sweep's identity (its id hashes it): everything that decides its runs; not the name,
        the description, the thresholds (they only decide the summary) or the batching."""
        s = self.spec
        axes = [{"key": a.key, "kind": a.kind, "relative": a.relative, "values": list(a.values),
                 "settings": dict(a.settings), **({"anchor": a.anchor} if a.anchor != "initial" else {})}
                for a in s.axes]
        return {"plant": self.plant.identity(), "axes": axes, "samples": s.samples, "seed": s.seed,
                "scenarios": [scenario_identity(x) for x in s.scenarios],
                "controllers": controllers if controllers is not None else [_entry_identity(c) for c in s.controllers],
                "control_period_s": s.control_period, "record_period_s": s.record_period,
                "keep_traces": s.keep_traces, "implementation": s.implementation}

    def sweep_id(self) -> str:
        return digest(canonical(self.identity()))[:16]


def _entry_identity(entry) -> dict:
    """A controller entry as the sweep id sees it: a given model file, controller FMU or
    controller-binding file (with the FMU it names) by its content, not its path."""
    described = entry.describe()
    if entry.model is not None:
        described["model"] = digest(Path(entry.model).read_bytes())
    for key in ("policy", "design"):  # by content, like the model
        if getattr(entry, key, None) is not None:
            described[key] = digest(Path(getattr(entry, key)).read_bytes())
    if entry.path is not None:
        files = [entry.path, entry.fmu] if Path(entry.path).suffix.lower() == ".toml" else [entry.path]
        described["path"] = digest(*(Path(f).read_bytes() for f in files))
    return described


def batch_key(runs) -> str:
    return digest(*(r.run_id for r in runs))[:16]
