"""Scenarios: what happens to the converter and when, in a small human-editable TOML format.

Example (``cosim/scenarios/load_change.toml``)::

    name = "load_change"
    description = "Load step 6 -> 5 Ohm at 12 V (paper Fig. 9)"
    duration = 0.03      # [s] recorded time after t = 0
    settle = 0.015       # [s] closed-loop operation at the initial conditions before t = 0, not recorded

    [initial]
    reference = 12.0         # [V]  output-voltage reference
    load_resistance = 6.0    # [Ohm]
    input_voltage = 48.0     # [V]

    [[events]]
    time = 0.005             # [s]
    load_resistance = 5.0

Top-level keys: ``name`` (text), ``description`` (text), ``duration`` (> 0 s), ``settle`` (>= 0 s,
default 0, rounded to whole control periods), ``analysis_start`` (s, default: the first event
time, or 0 without events; metrics start here). ``[initial]`` keys: ``reference`` (>= 0 V),
``load_resistance`` (> 0 Ohm, default: the converter spec's nominal load), ``input_voltage`` (> 0 V, default:
the converter spec's nominal supply). A signal's value may be a template instead of a number: ``"nominal"`` (the
converter spec's nominal value, :mod:`cosim.converter_spec`; the nominal output for a reference) or ``"nominal * F"``
(F a number or a fraction a/b, computed exactly) -- the shipped scenarios are such templates, so they run any
converter at its own operating points (on the built-in plant, Table II, the paper's numbers). A description may name
the resolved values: ``{initial.reference:g}``, ``{events[0].load_resistance:g}`` (events in the file's order). Each
``[[events]]`` entry has ``time`` (0 <= time < duration) and at least one of ``reference``,
``load_resistance``, ``input_voltage``, ``parameters``. The plant starts at rest (zero current and
voltage) at the beginning of the settle interval. Reference changes reach the controller at its
next sample; load and input-voltage changes act on the plant at the exact event time.

Tunable-parameter events change plant parameters during the run, e.g. an ageing capacitor::

    [[events]]
    time = 0.02
    parameters = { capacitance = 7e-6, inductor_resistance = 0.3 }

The names are the plant FMU's own variable names (values in its units, like a binding file's
``[parameters]``); each must be a Real parameter the FMU declares ``variability="tunable"`` (the
built-in FMU: inductance, capacitance, inductor_resistance, switch_on_resistance,
diode_forward_voltage, capacitor_esr) and the value finite and within the variable's declared
min/max. The parser checks types and finiteness; :func:`check_parameter_events` checks names and
ranges against the FMU before anything runs, with the file, key and line. The master applies them
at the exact event time, between plant steps, like load steps.
"""

from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from cosim.base.errors import ConfigError
from cosim.base.toml_files import parse_toml
from cosim.base.toml_files import where as _where
from cosim.converter_spec import ConverterSpec

SHIPPED_DIR = Path(__file__).parent / "scenarios"
EVENT_SIGNALS = ("reference", "load_resistance", "input_voltage")
SIGNAL_UNITS = {"reference": "V", "load_resistance": "Ohm", "input_voltage": "V"}
TOP_KEYS = {"name", "description", "duration", "settle", "analysis_start", "initial", "events"}
INITIAL_KEYS = {"reference", "load_resistance", "input_voltage"}
EVENT_KEYS = {"time", "parameters", *EVENT_SIGNALS}
#: role each event signal needs from the plant binding (the reference is the controller's own input)
SIGNAL_ROLES = {"load_resistance": "load_resistance", "input_voltage": "input_voltage"}


@dataclass(frozen=True)
class ScenarioEvent:
    time: float  # [s]
    changes: dict[str, float]  # signal -> new value
    parameters: dict[str, float] = field(default_factory=dict)  # plant FMU parameter -> new value
    #: "file:line" of the event's parameters (else of its time), for errors found later; not part of what it is
    where: str | None = field(default=None, compare=False)

    @property
    def plant_event(self) -> bool:
        """Does it act on the plant at its exact time (load, supply or parameters)?"""
        return bool(self.parameters) or any(k != "reference" for k in self.changes)


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    duration: float  # [s]
    initial: dict[str, float]
    events: tuple[ScenarioEvent, ...] = ()
    settle: float = 0.0  # [s]
    analysis_start: float | None = None  # [s]
    source: Path | None = None
    key_places: Mapping[str, str] = field(default_factory=dict, compare=False)  # key -> "file:line"

    def place(self, key: str) -> str:
        """Where a top-level key of the scenario is (``file:line``), to name it in a message."""
        return self.key_places.get(key) or (str(self.source) if self.source else f"scenario {self.name}")

    @property
    def metrics_start(self) -> float:
        """Start of the metrics window: ``analysis_start``, else the first event, else 0."""
        if self.analysis_start is not None:
            return self.analysis_start
        return self.events[0].time if self.events else 0.0

    def schedule(self, signal: str) -> list[tuple[float, float]]:
        """Piecewise-constant schedule ``[(time, value), ...]`` of one signal, starting at t = 0."""
        points = [(0.0, self.initial[signal])]
        for event in self.events:
            if signal in event.changes:
                points.append((event.time, event.changes[signal]))
        return points

    @property
    def parameter_events(self) -> tuple[ScenarioEvent, ...]:
        return tuple(e for e in self.events if e.parameters)

    def required_roles(self) -> set[str]:
        """Plant roles this scenario needs because it changes them during the run."""
        return {SIGNAL_ROLES[s] for e in self.events for s in e.changes if s in SIGNAL_ROLES}

    def describe(self) -> dict:
        return {
            "name": self.name,
            "description": self.description,
            "duration_s": self.duration,
            "settle_s": self.settle,
            "metrics_start_s": self.metrics_start,
            "initial": dict(self.initial),
            "events": [{"time_s": e.time, **e.changes, **({"parameters": dict(e.parameters)} if e.parameters else {})}
                       for e in self.events],
            "source": str(self.source) if self.source else None,
        }


# ---------------------------------------------------------------------------------------------
# Parsing with messages that name file, key and line


def _number(value, path, locator, key, label, table=None, index=None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(
            f"{_where(path, locator, key, table, index)}: {label} = {value!r} has the wrong type: expected a number"
        )
    value = float(value)
    if not math.isfinite(value):
        raise ConfigError(f"{_where(path, locator, key, table, index)}: {label} = {value} is not finite")
    return value


def _signal_value(raw, path, loc, key, label, table, index, spec: ConverterSpec | None) -> float:
    """A signal's value: a number, or a template (``"nominal"``, ``"nominal * 5/6"``) resolved against ``spec``."""
    if isinstance(raw, str):
        at = _where(path, loc, key, table, index)
        if spec is None:
            raise ConfigError(f"{at}: {label} = {raw!r} is relative to a converter's nominal value, but no converter "
                              "spec is given (a plant binding's [converter] table)")
        return spec.resolve(raw, key, f"{at}: {label}")
    return _number(raw, path, loc, key, label, table, index)


def _nominal(key: str, path, loc, spec: ConverterSpec | None) -> float:
    """An initial load or supply a scenario leaves out: the converter's nominal one."""
    at = _where(path, loc, None, "initial")
    if spec is None:
        raise ConfigError(f"{at}: initial.{key} is not given and no converter spec gives a nominal {key}: give "
                          f"initial.{key} in {SIGNAL_UNITS[key]}")
    return float(spec.require(key, f"{at} (initial.{key}, not given)"))


def _describe(template: str, initial: dict, events: list, path, loc) -> str:
    """The description with its placeholders filled: ``{initial.reference:g}``, ``{events[0].load_resistance:g}``
    (the values in the file's order of events), so a template's text names the numbers it resolved to."""
    if "{" not in template:
        return template
    from types import SimpleNamespace

    try:
        return template.format(initial=SimpleNamespace(**initial),
                               events=[SimpleNamespace(**e.changes) for e in events])
    except (KeyError, IndexError, AttributeError, ValueError) as error:
        raise ConfigError(f"{_where(path, loc, 'description')}: description placeholder {error} names no value: "
                          "expected {initial.<signal>} or {events[N].<signal>}") from None


def warn_outside(scenario: "Scenario", spec: ConverterSpec | None) -> list[str]:
    """One warning line on stderr per scenario value outside the converter spec's ranges (its output, supply and load
    envelope); returns the lines. A scenario outside the envelope still runs -- the designs were made inside it."""
    if spec is None:
        return []
    found = []
    for when, values in [("initially", scenario.initial),
                         *((f"at t = {e.time:g} s", e.changes) for e in scenario.events)]:
        for signal, value in values.items():
            text = spec.outside(signal, value)
            if text is not None:
                found.append(f"warning: {scenario.place('name')}: {text} ({when})")
    for line in dict.fromkeys(found):
        print(line, file=sys.stderr)
    return found


def parse_scenario(text: str, path: Path | None = None, spec: ConverterSpec | None = None) -> Scenario:
    """Parse and validate scenario TOML; raise :class:`ConfigError` naming file, key and line. ``spec``: the converter
    a template's values (``"nominal * F"``) and a left-out initial load or supply are resolved against."""
    name_for_errors = str(path) if path else "<scenario>"
    data, loc = parse_toml(text, path, TOP_KEYS, unnamed=name_for_errors)
    for key in ("name", "duration", "initial"):
        if key not in data:
            raise ConfigError(f"{name_for_errors}: missing required key {key!r}")
    name = data["name"]
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
        raise ConfigError(
            f"{_where(path, loc, 'name')}: name = {name!r} is invalid: expected letters, digits, '_', '-' or '.'"
        )
    description = data.get("description", "")
    if not isinstance(description, str):
        raise ConfigError(f"{_where(path, loc, 'description')}: description has the wrong type: expected text")
    duration = _number(data["duration"], path, loc, "duration", "duration")
    if duration <= 0:
        raise ConfigError(f"{_where(path, loc, 'duration')}: duration = {duration} s is invalid: expected > 0")
    settle = _number(data.get("settle", 0.0), path, loc, "settle", "settle")
    if settle < 0:
        raise ConfigError(f"{_where(path, loc, 'settle')}: settle = {settle} s is negative: expected >= 0")

    initial_table = data["initial"]
    if not isinstance(initial_table, dict):
        raise ConfigError(f"{_where(path, loc, 'initial')}: 'initial' must be a table ([initial])")
    for key in initial_table:
        if key not in INITIAL_KEYS:
            raise ConfigError(
                f"{_where(path, loc, key, 'initial')}: unknown key 'initial.{key}': "
                f"expected one of {', '.join(sorted(INITIAL_KEYS))}"
            )
    if "reference" not in initial_table:
        raise ConfigError(f"{_where(path, loc, None, 'initial')}: missing required key 'initial.reference'")
    initial = {}
    for key in ("reference", "load_resistance", "input_voltage"):
        if key in initial_table:
            initial[key] = _signal_value(initial_table[key], path, loc, key, f"initial.{key}", "initial", None, spec)
        else:  # the converter's nominal load and supply: never a number of the paper's
            initial[key] = _nominal(key, path, loc, spec)
        _check_signal(key, initial[key], path, loc, f"initial.{key}", key, "initial", None)

    raw_events = data.get("events", [])
    if not isinstance(raw_events, list) or not all(isinstance(e, dict) for e in raw_events):
        raise ConfigError(f"{_where(path, loc, 'events')}: 'events' must be an array of tables ([[events]])")
    events = []
    for i, entry in enumerate(raw_events):
        label = f"events[{i}]"
        for key in entry:
            if key not in EVENT_KEYS:
                raise ConfigError(
                    f"{_where(path, loc, key, 'events', i)}: unknown key '{label}.{key}': "
                    f"expected one of {', '.join(sorted(EVENT_KEYS))}"
                )
        if "time" not in entry:
            raise ConfigError(f"{_where(path, loc, None, 'events', i)}: {label} has no 'time'")
        time = _number(entry["time"], path, loc, "time", f"{label}.time", "events", i)
        if time < 0:
            raise ConfigError(f"{_where(path, loc, 'time', 'events', i)}: {label}.time = {time} s is negative: expected >= 0")
        if time >= duration:
            raise ConfigError(
                f"{_where(path, loc, 'time', 'events', i)}: {label}.time = {time} s is at or after the end "
                f"of the scenario (duration = {duration} s)"
            )
        changes = {}
        for key in EVENT_SIGNALS:
            if key in entry:
                value = _signal_value(entry[key], path, loc, key, f"{label}.{key}", "events", i, spec)
                _check_signal(key, value, path, loc, f"{label}.{key}", key, "events", i)
                changes[key] = value
        parameters = _parameters(entry.get("parameters"), path, loc, label, i) if "parameters" in entry else {}
        if not changes and not parameters:
            raise ConfigError(
                f"{_where(path, loc, None, 'events', i)}: {label} changes nothing: "
                f"expected at least one of {', '.join((*EVENT_SIGNALS, 'parameters'))}"
            )
        at = _where(path, loc, "parameters", "events", i) if parameters else _where(path, loc, "time", "events", i)
        if ":" not in at:  # a [events.parameters] sub-table: name the event's own line
            at = _where(path, loc, None, "events", i)
        events.append(ScenarioEvent(time=time, changes=changes, parameters=parameters, where=at))
    indexed = list(enumerate(events))  # the file's order, for messages
    setting: dict[tuple[float, str], int] = {}
    for i, event in indexed:  # two changes of one signal at one instant: the run would take one and drop the other
        for key in (*event.changes, *(f"parameters.{name}" for name in event.parameters)):
            first = setting.setdefault((event.time, key), i)
            if first != i:
                raise ConfigError(
                    f"{_where(path, loc, 'time', 'events', i)}: events[{i}] sets {key} at t = {event.time} s, as "
                    f"events[{first}] does: one of the two would be dropped -- merge them or give them different times")
    description = _describe(description, initial, events, path, loc)
    events.sort(key=lambda e: e.time)

    analysis_start = None
    if "analysis_start" in data:
        analysis_start = _number(data["analysis_start"], path, loc, "analysis_start", "analysis_start")
        if not 0 <= analysis_start < duration:
            raise ConfigError(
                f"{_where(path, loc, 'analysis_start')}: analysis_start = {analysis_start} s is outside "
                f"[0, duration = {duration} s)"
            )
    _check_reachable(initial, sorted(indexed, key=lambda pair: pair[1].time), path, loc)
    places = {key: _where(path, loc, key) for key in ("duration", "settle", "name") if key in data}
    return Scenario(name=name, description=description, duration=duration, initial=initial,
                    events=tuple(events), settle=settle, analysis_start=analysis_start, source=path,
                    key_places=places)


def reference_above_supply(initial: dict, events) -> tuple[float, float, float, int | None, "ScenarioEvent | None"] | None:
    """The first instant a buck converter cannot follow: the reference above the input voltage in effect, as
    (time [s], reference [V], input voltage [V], the event's index, the event) -- index and event None at t = 0 --
    or None. ``events`` are (index, event) in time order. The one rule: scenario files are checked with it when
    read, and a sweep's runs as its operating-point axes move them."""
    reference, supply = initial["reference"], initial["input_voltage"]
    points = [(0.0, None, None)] + [(event.time, index, event) for index, event in events]
    for time, index, event in points:
        if event is not None:
            reference = event.changes.get("reference", reference)
            supply = event.changes.get("input_voltage", supply)
        if reference > supply:
            return time, reference, supply, index, event
    return None


def unreachable_text(time: float, reference: float, supply: float) -> str:
    """How a message says :func:`reference_above_supply`'s finding."""
    return (f"the reference {reference:g} V at t = {time:g} s exceeds the input voltage {supply:g} V in effect then: "
            "a buck converter's output cannot exceed its input")


def _check_reachable(initial: dict, events: list[tuple[int, "ScenarioEvent"]], path, loc) -> None:
    """Refuse a reference a buck converter cannot reach (:func:`reference_above_supply`), at its line."""
    found = reference_above_supply(initial, events)
    if found is None:
        return
    time, reference, supply, index, event = found
    if event is None:
        place = _where(path, loc, "reference", "initial")
    else:
        key = "reference" if "reference" in event.changes else "input_voltage"
        place = _where(path, loc, key, "events", index)
    raise ConfigError(f"{place}: {unreachable_text(time, reference, supply)}")


def _parameters(table, path, loc, label, index) -> dict[str, float]:
    """An event's ``parameters`` table: names to finite numbers (the FMU check comes later)."""
    at = _where(path, loc, "parameters", "events", index)
    if ":" not in at:
        at = _where(path, loc, None, "events", index)
    if not isinstance(table, dict):
        raise ConfigError(f"{at}: {label}.parameters = {table!r} has the wrong type: expected a table of "
                          "parameter names and values, e.g. parameters = {{ capacitance = 7e-6 }}")
    if not table:
        raise ConfigError(f"{at}: {label}.parameters is empty: name at least one tunable plant parameter")
    values = {}
    for name, value in table.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{at}: {label}.parameters.{name} = {value!r} has the wrong type: expected a number")
        if not math.isfinite(float(value)):
            raise ConfigError(f"{at}: {label}.parameters.{name} = {value} is not finite")
        values[name] = float(value)
    return values


def check_parameter_events(scenario: Scenario, model_description, origin: str) -> None:
    """Refuse, before anything runs, a parameter event the plant FMU cannot take during a run:
    a name that is not a Real parameter with ``variability="tunable"``, or a value outside the
    variable's declared min/max. Messages name the scenario file, the key and its line."""
    from cosim.fmi.binding import is_float

    variables = {v.name: v for v in model_description.modelVariables}
    real = "Float64" if str(model_description.fmiVersion).startswith("3") else "Real"  # the FMI version's name
    tunable = sorted(v.name for v in model_description.modelVariables
                     if v.causality == "parameter" and v.variability == "tunable" and is_float(v))
    choices = ", ".join(tunable) if tunable else f"none: the FMU declares no tunable {real} parameter"
    for i, event in enumerate(scenario.events):
        if not event.parameters:
            continue
        at = event.where or (str(scenario.source) if scenario.source else f"scenario {scenario.name}")
        label = f"events[{i}].parameters"
        for name, value in event.parameters.items():
            variable = variables.get(name)
            if variable is None:
                raise ConfigError(f"{at}: {label}.{name}: {origin} has no variable {name!r} (tunable: {choices})")
            if variable.causality != "parameter" or variable.variability != "tunable" or not is_float(variable):
                kind = f"a {variable.variability} {variable.causality}" + ("" if is_float(variable) else
                                                                           f" of type {variable.type}")
                raise ConfigError(f"{at}: {label}.{name}: {name!r} is {kind}; only tunable {real} parameters can "
                                  f"change during a run (tunable: {choices})")
            low, high = _declared_range(variable)
            if (low is not None and value < low) or (high is not None and value > high):
                unit = _declared_unit(variable)
                raise ConfigError(f"{at}: {label}.{name} = {value:g}{unit} is outside the range the FMU declares "
                                  f"[{'-inf' if low is None else f'{low:g}'}, {'inf' if high is None else f'{high:g}'}]")


def _declared_range(variable) -> tuple[float | None, float | None]:
    declared = variable.declaredType
    low = variable.min if variable.min is not None else (declared.min if declared is not None else None)
    high = variable.max if variable.max is not None else (declared.max if declared is not None else None)
    return (None if low is None else float(low)), (None if high is None else float(high))


def _declared_unit(variable) -> str:
    unit = variable.unit or (variable.declaredType.unit if variable.declaredType is not None else None)
    return f" {unit}" if unit else ""


def _check_signal(signal, value, path, loc, label, key, table, index) -> None:
    if signal == "reference" and value < 0:
        raise ConfigError(f"{_where(path, loc, key, table, index)}: {label} = {value} V is negative: expected >= 0")
    if signal in ("load_resistance", "input_voltage") and value <= 0:
        raise ConfigError(
            f"{_where(path, loc, key, table, index)}: {label} = {value} {SIGNAL_UNITS[signal]} is invalid: expected > 0"
        )


def load_scenario(name_or_path: str | Path, spec: ConverterSpec | None = None, warn: bool = False) -> Scenario:
    """Load a scenario file, or a shipped scenario by name (see :func:`shipped_scenarios`), resolved against the
    converter ``spec`` (the shipped scenarios are templates: start-up to the nominal output, a load step to 5/6 of
    the nominal load, ...). ``warn``: a line on stderr for each value outside the spec's ranges."""
    path = Path(name_or_path)
    if path.is_dir():
        raise ConfigError(f"scenario {path} is a folder: expected a scenario file (.toml) or a shipped scenario name")
    if not path.is_file():
        shipped = SHIPPED_DIR / f"{name_or_path}.toml"
        if shipped.is_file():
            path = shipped
        else:
            names = ", ".join(shipped_scenario_names())
            raise ConfigError(f"scenario {str(name_or_path)!r} is neither a file nor a shipped scenario ({names})")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(f"{path}: cannot read scenario file ({error})") from None
    scenario = parse_scenario(text, path, spec)
    if warn:
        warn_outside(scenario, spec)
    return scenario


def shipped_scenario_names() -> list[str]:
    return sorted(p.stem for p in SHIPPED_DIR.glob("*.toml"))


#: the paper's four scenarios, in the order of its figures
PAPER_SCENARIOS = ("startup", "load_change", "reference_up", "reference_down")


def shipped_scenarios(spec: ConverterSpec) -> list[Scenario]:
    """Every shipped scenario resolved against ``spec``."""
    return [load_scenario(name, spec) for name in shipped_scenario_names()]


def set_up_scenario(binding) -> Scenario:
    """A scenario at rest (reference 0 V) at the plant's nominal load and supply, its converter spec's (for a binding
    file: the ``[converter]`` table's, else the FMU's start values): what ``inspect`` sets the FMU up with to check a
    binding, needing no output reference. A load or supply the plant binds and no spec gives is refused, naming the key;
    one it does not bind is never written to the FMU (1 stands in for it)."""
    spec = binding.converter
    initial = {"reference": 0.0}
    for key in ("load_resistance", "input_voltage"):
        value = getattr(spec, key)
        if value is None:
            if binding.has(key):
                spec.require(key, "setting the FMU up")
            value = 1.0
        initial[key] = float(value)
    return Scenario(name="set_up", description="the plant at rest, set up as a run's", duration=1e-3, initial=initial)
