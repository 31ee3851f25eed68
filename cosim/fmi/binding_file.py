"""Plant-binding files: drive an externally authored FMU (Simulink, Modelica, PLECS, pythonfmu...).

A binding is a small TOML file next to (or pointing at) the FMU::

    fmu = "MyBuck.fmu"              # path; relative paths are relative to this file
    interface = "co-simulation"     # or "model-exchange"; default: what the FMU offers, preferring CS
    max_step = 1e-5                 # [s] optional: the largest step the FMU accepts; longer ones are split
    step = 1e-5                     # [s] optional, co-simulation: the one communication step the master steps the
                                    # FMU by (a fixed-step FMU's step; default: its DefaultExperiment stepSize
                                    # if it cannot vary its step, cosim.fmi.communication)
    label = "My buck (Modelica)"    # optional: how runs and figures name this plant
    isolate = true                  # optional (default true): step the FMU in a child process, so a crash
                                    # in it ends the run with an error instead of the workbench
    step_timeout = 30.0             # [s] optional, isolated only: a step of the FMU that takes longer
                                    # (wall time) is stopped and the run fails; default 30 s + 1000 x
                                    # the step's simulated length
    memory_limit = 2000             # [MB] optional, isolated only: the FMU's process is stopped (the run
                                    # fails) above this resident memory; default half the machine's

    [roles.duty_cycle]              # required; an input
    variable = "D"
    scale = 100.0                   # fmu_value = scale * workbench_value + offset: here duty in percent
    offset = 0.0

    [roles.output_voltage]          # required; an output [V]
    variable = "Vout"

    [roles.inductor_current]        # needed by NNPC and by the cost of eq. 23; an output [A]
    variable = "IL_mA"
    scale = 1000.0                  # the FMU reports mA

    # optional: load_resistance and input_voltage (inputs, needed by load and supply steps),
    # load_current (output, lets predictive controllers estimate the load), and
    # measured_output_voltage / measured_inductor_current / measured_load_current (what the
    # controller's sensors read; sample all three alike, or the load estimate io/vo is skewed)

    [parameters]                    # parameter overrides and start values, set before initialisation
    L = 220e-6

Everything is checked when the file is loaded -- keys, types, the FMU archive itself, that each
variable exists with a fitting causality -- and a mistake names the file, key and line.
"""

from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Mapping

from cosim.base.errors import ConfigError, FmuArchiveError
from cosim.base.files import atomic_write_text
from cosim.base.labels import MIN_PERIOD, did_you_mean, period_too_short
from cosim.base.toml_files import TomlLocator, finite_number, parse_toml, where
from cosim.converter_spec import ConverterSpec, parse_converter_table
from cosim.fmi.archive import check_fmu
from cosim.fmi.binding import (
    CONTROLLER_ROLES,
    INPUT_ROLES,
    REQUIRED_ROLES,
    ROLE_DESCRIPTIONS,
    ROLES,
    BindingMismatch,
    PlantBinding,
    RoleMap,
    array_shape,
    is_float,
    resolve_parameters,
    resolve_roles,
)
from cosim.fmi.communication import can_vary_step, declared_step
from cosim.fmi.plant_fmi2 import normalise_interface

TOP_KEYS = {"fmu", "interface", "max_step", "step", "label", "isolate", "step_timeout", "memory_limit", "roles",
            "parameters", "converter"}
ROLE_KEYS = {"variable", "scale", "offset"}


def _isolation_limit(data: dict, path: Path, loc: TomlLocator, key: str, unit: str, isolate: bool) -> float | None:
    """An optional limit of the isolated plant process (``step_timeout``, ``memory_limit``): > 0, isolated only."""
    if key not in data:
        return None
    value = finite_number(data[key], key, where(path, loc, key))
    if not value > 0:
        raise ConfigError(f"{where(path, loc, key)}: {key} = {value:g} {unit} is invalid: expected > 0")
    if not isolate:
        raise ConfigError(f"{where(path, loc, key)}: {key} needs isolate = true (the workbench cannot stop an FMU "
                          "running in its own process)")
    return value


def _communication_step(data: dict, path: Path, loc: TomlLocator, interface: str | None,
                        max_step: float | None) -> float | None:
    """The optional ``step`` key [s]: > 0, co-simulation only, not with ``max_step`` (which splits steps)."""
    if "step" not in data:
        return None
    step = finite_number(data["step"], "step", where(path, loc, "step"))
    if not step > 0:
        raise ConfigError(f"{where(path, loc, 'step')}: step = {step:g} s is invalid: expected > 0 (the one "
                          "communication step the master steps the FMU by)")
    if step < MIN_PERIOD:
        raise ConfigError(f"{where(path, loc, 'step')}: {period_too_short(f'step = {step:g} s')}")
    if interface == "model-exchange":
        raise ConfigError(f"{where(path, loc, 'step')}: step is a co-simulation FMU's communication step, but "
                          "interface = \"model-exchange\" (CVode chooses its own steps): drop one of them")
    if max_step is not None:
        raise ConfigError(f"{where(path, loc, 'step')}: step (one fixed communication step) and max_step (split longer "
                          "steps) exclude each other: keep one")
    return step


def _check_fixed_step(binding: PlantBinding, checked, loc: TomlLocator) -> None:
    """``step`` needs the co-simulation interface; ``max_step`` splits the master's steps into shorter ones: refused for
    a co-simulation FMU that cannot vary its communication step (its ``step`` is what it needs instead)."""
    uses_cs = binding.interface != "model-exchange" and "co-simulation" in checked.interfaces
    if binding.step is not None and not uses_cs:
        raise ConfigError(f"{where(binding.source, loc, 'step')}: step is a co-simulation FMU's communication step, "
                          f"but {binding.fmu_path.name} offers only model exchange here (CVode chooses its own "
                          "steps): drop step")
    if binding.max_step is None or not uses_cs or can_vary_step(checked.model_description):
        return
    declared = declared_step(checked.model_description)
    hint = f" (its DefaultExperiment says {declared:g} s)" if declared else ""
    raise ConfigError(f"{where(binding.source, loc, 'max_step')}: max_step splits steps into shorter ones, but "
                      f"{binding.fmu_path.name} cannot vary its communication step (canHandleVariableCommunicationStep"
                      f"Size = false): give its fixed step as step = ... instead{hint}")


def fmu_path_of(data: dict, path: Path, loc: TomlLocator) -> Path:
    """The required ``fmu`` key: a path, relative to the binding file unless absolute."""
    if "fmu" not in data:
        raise ConfigError(f"{path}: missing required key 'fmu' (the FMU file this binding drives)")
    if not isinstance(data["fmu"], str):
        raise ConfigError(f"{where(path, loc, 'fmu')}: fmu has the wrong type: expected a path as text")
    fmu_path = Path(data["fmu"])
    return fmu_path if fmu_path.is_absolute() else (path.parent / fmu_path).resolve()


def parse_roles(data: dict, path: Path, loc: TomlLocator, allowed: tuple[str, ...],
                other: tuple[str, tuple[str, ...]] = ("", ())) -> dict[str, RoleMap]:
    """The ``[roles.<name>]`` tables: each a variable with an optional finite, non-zero scale and offset. ``other``:
    the other kind of binding and its roles, to say so when a file of that kind is given here."""
    roles_table = data.get("roles", {})
    if not isinstance(roles_table, dict):
        raise ConfigError(f"{where(path, loc, 'roles')}: 'roles' must be a table of [roles.<name>] tables")
    roles: dict[str, RoleMap] = {}
    for role, entry in roles_table.items():
        table = f"roles.{role}"
        if role not in allowed and role in other[1]:
            expected = "plant" if other[0] == "controller" else "controller"
            raise ConfigError(f"{where(path, loc, None, table)}: role {role!r} is a {other[0]} role: this is a "
                              f"{other[0]} binding file, given where a {expected} binding is expected")
        if role not in allowed:
            hint = did_you_mean(role, allowed)
            raise ConfigError(f"{where(path, loc, None, table)}: unknown role {role!r}"
                              + (hint if hint else f": expected one of {', '.join(allowed)}"))
        if not isinstance(entry, dict):
            raise ConfigError(f"{where(path, loc, role, 'roles')}: role {role!r} must be a table with 'variable'")
        for key in entry:
            if key not in ROLE_KEYS:
                raise ConfigError(f"{where(path, loc, key, table)}: unknown key '{table}.{key}': expected one of "
                                  f"{', '.join(sorted(ROLE_KEYS))}")
        variable = entry.get("variable")
        if not isinstance(variable, str) or not variable:
            raise ConfigError(f"{where(path, loc, 'variable', table)}: '{table}.variable' must name an FMU variable")
        scale = finite_number(entry.get("scale", 1.0), f"{table}.scale", where(path, loc, "scale", table))
        offset = finite_number(entry.get("offset", 0.0), f"{table}.offset", where(path, loc, "offset", table))
        if scale == 0:
            raise ConfigError(f"{where(path, loc, 'scale', table)}: {table}.scale = 0 is invalid: expected a "
                              "non-zero factor")
        roles[role] = RoleMap(variable=variable, scale=scale, offset=offset)
    return roles


def parse_parameters(data: dict, path: Path, loc: TomlLocator) -> dict:
    """The ``[parameters]`` table: names and values (numbers, true/false or text) set before initialisation."""
    parameters = data.get("parameters", {})
    if not isinstance(parameters, dict):
        raise ConfigError(f"{where(path, loc, 'parameters')}: 'parameters' must be a table")
    for name, value in parameters.items():
        if not isinstance(value, (bool, int, float, str)):
            raise ConfigError(f"{where(path, loc, name, 'parameters')}: parameter {name!r} = {value!r} is invalid: "
                              "expected a number, true/false or text")
    return parameters


def checked_fmu_of(fmu_path: Path, path: Path, loc: TomlLocator):
    """The archive checks of the bound FMU (nothing is extracted or loaded before this), located at ``fmu``."""
    try:
        return check_fmu(fmu_path)
    except FmuArchiveError as error:
        raise FmuArchiveError(f"{where(path, loc, 'fmu')}: {error}") from None


def check_against(binding, checked, loc: TomlLocator, input_roles: tuple[str, ...],
                  settings: tuple[str, ...] = ()) -> None:
    """A binding's roles and parameters against its FMU, each mistake located at its key's line; then that every
    role of ``input_roles`` (the workbench sets its variable) has a variable of its own: two values written into one
    would overwrite each other, and a value written where another is read would be read back as the other (roles the
    workbench only reads may share one, e.g. the output voltage and its measurement). A ``[parameters]`` value may
    not set a role's variable (the workbench sets it at every step), except for the roles of ``settings``: the FMU's
    own settings the workbench reads, such as a controller's sample period."""
    try:
        resolve_roles(binding, checked.model_description, input_roles)
        resolve_parameters(binding.parameters, checked.model_description, binding.fmu_path.name)
    except BindingMismatch as error:
        place = where(binding.source, loc, "variable", f"roles.{error.key}") if error.kind == "role" else \
            where(binding.source, loc, error.key, "parameters")
        raise ConfigError(f"{place}: {error}") from None
    bound = {mapping.variable: role for role, mapping in binding.roles.items() if role not in settings}
    for name in binding.parameters:  # a role's variable is set by the workbench at every step: a value here is lost
        if name in bound:
            raise ConfigError(f"{where(binding.source, loc, name, 'parameters')}: parameter {name!r} is the variable "
                              f"of role {bound[name]!r}, which the workbench sets itself (from the scenario or the "
                              f"controller): its value here would be replaced -- drop it (a scenario sets the "
                              f"{bound[name]} of a run)")
    named: dict[str, str] = {}
    for role, mapping in binding.roles.items():  # in the file's order: the second of two is the one named
        other = named.setdefault(mapping.variable, role)
        if other != role and input_roles and (role in input_roles or other in input_roles):
            written = role if role in input_roles else other
            raise ConfigError(f"{where(binding.source, loc, 'variable', f'roles.{role}')}: role {role!r} names "
                              f"variable {mapping.variable!r}, which role {other!r} names too: the workbench writes "
                              f"{written} into it, so the two would overwrite each other -- give each its own variable")


def parse_binding(text: str, path: Path) -> PlantBinding:
    """Parse and check a binding file's text (``path`` locates the FMU and names errors)."""
    data, loc = parse_toml(text, path, TOP_KEYS)
    fmu_path = fmu_path_of(data, path, loc)
    interface = data.get("interface")
    if interface is not None:
        if not isinstance(interface, str):
            raise ConfigError(f"{where(path, loc, 'interface')}: interface has the wrong type: expected text")
        try:
            interface = normalise_interface(interface)
        except ConfigError as error:
            raise ConfigError(f"{where(path, loc, 'interface')}: {error}") from None
    max_step = None
    if "max_step" in data:
        max_step = finite_number(data["max_step"], "max_step", where(path, loc, "max_step"))
        if max_step <= 0:
            raise ConfigError(f"{where(path, loc, 'max_step')}: max_step = {max_step} s is invalid: expected > 0")
    step = _communication_step(data, path, loc, interface, max_step)
    label = data.get("label", f"{fmu_path.stem} (bound by {path.name})")
    if not isinstance(label, str):
        raise ConfigError(f"{where(path, loc, 'label')}: label has the wrong type: expected text")
    isolate = data.get("isolate", True)
    if not isinstance(isolate, bool):
        raise ConfigError(f"{where(path, loc, 'isolate')}: isolate = {isolate!r} has the wrong type: expected true or "
                          "false")
    step_timeout = _isolation_limit(data, path, loc, "step_timeout", "s", isolate)
    memory_limit = _isolation_limit(data, path, loc, "memory_limit", "MB", isolate)

    roles = parse_roles(data, path, loc, ROLES, other=("controller", CONTROLLER_ROLES))
    for role in REQUIRED_ROLES:
        if role not in roles:
            raise ConfigError(f"{path}: missing role [roles.{role}] ({ROLE_DESCRIPTIONS[role]})")
    if "measured_output_voltage" in roles and "load_current" in roles and "measured_load_current" not in roles:
        print(f"warning: {path}: [roles.measured_output_voltage] is bound but [roles.measured_load_current] is not: "
              "predictive controllers will estimate the load from a measured vo and the plain load_current; "
              "bind both alike", file=sys.stderr)

    parameters = parse_parameters(data, path, loc)

    checked = checked_fmu_of(fmu_path, path, loc)
    binding = PlantBinding(fmu_path=fmu_path, roles=roles, interface=interface, parameters=parameters,
                           max_step=max_step, source=path, label=label, isolate=isolate, step_timeout=step_timeout,
                           memory_limit=memory_limit, step=step)
    _check_variables(binding, checked, loc)
    binding = replace(binding, spec=converter_spec(data.get("converter"), binding, checked.model_description, loc))
    problems = unit_problems(binding, checked.model_description)
    if problems:
        print(f"warning: {path}: implausible binding: {'; '.join(problems)} "
              "(fmu_value = scale * workbench_value + offset)", file=sys.stderr)
    return binding


def converter_spec(table, binding: PlantBinding, model_description, loc: TomlLocator) -> ConverterSpec:
    """The binding file's ``[converter]`` table (:mod:`cosim.converter_spec`) with the FMU's defaults: the nominal
    supply and load are the start values of the variables bound to input_voltage and load_resistance (in workbench
    units, through the role's scale and offset) where the table does not give them; a circuit value given as an FMU
    parameter's name is the binding's ``[parameters]`` value, else that parameter's start value."""
    path = binding.source
    variables = {v.name: v for v in model_description.modelVariables}
    defaults = {}
    for role in ("input_voltage", "load_resistance"):
        mapping = binding.roles.get(role)
        variable = variables.get(mapping.variable) if mapping is not None else None
        try:
            value = (float(variable.start) - mapping.offset) / mapping.scale
        except (AttributeError, TypeError, ValueError):  # no variable, no start value, or not a number
            continue
        if value > 0:  # a start value of 0 (a placeholder in many exported FMUs) is no nominal value: not given
            defaults[role] = (value, f"the start value of {mapping.variable!r}, bound to {role}")

    def parameter_value(name: str, scale: float, at: str) -> float:
        variable = variables.get(name)
        if variable is None or variable.causality != "parameter" or not is_float(variable):
            choices = sorted(v.name for v in model_description.modelVariables
                             if v.causality == "parameter" and is_float(v))
            raise ConfigError(f"{at}: {binding.fmu_path.name} has no Real parameter {name!r} (its Real parameters: "
                              f"{', '.join(choices) or 'none'})")
        value = binding.parameters.get(name)
        if value is None:  # the FMU's start value (the model description's text)
            try:
                value = float(variable.start)
            except (TypeError, ValueError):
                value = None
        if value is None or isinstance(value, (bool, str)):
            raise ConfigError(f"{at}: the FMU parameter {name!r} has no numeric value: set it under [parameters] or "
                              "give the circuit value as a number")
        return float(value) / scale

    def place(key, table):
        return where(path, loc, key, table) if key is not None else where(path, loc, "converter")

    return parse_converter_table(table, f"binding file {path}", place, defaults, parameter_value,
                                 label=binding.label)


#: the quantity of each role's workbench value (SI; the duty 0..1)
ROLE_QUANTITIES = {
    "duty_cycle": "duty", "input_voltage": "voltage", "output_voltage": "voltage", "measured_output_voltage": "voltage",
    "load_resistance": "resistance", "inductor_current": "current", "load_current": "current",
    "measured_inductor_current": "current", "measured_load_current": "current",
}
#: units an FMU may declare for each quantity, with the binding scale each one needs
UNIT_SCALES = {
    "duty": {"1": 1.0, "%": 100.0},
    "voltage": {"V": 1.0, "mV": 1e3, "kV": 1e-3},
    "current": {"A": 1.0, "mA": 1e3, "uA": 1e6, "kA": 1e-3},
    "resistance": {"Ohm": 1.0, "ohm": 1.0, "Ω": 1.0, "mOhm": 1e3, "kOhm": 1e-3},
}


def unit_problems(binding: PlantBinding, model_description) -> list[str]:
    """Roles whose FMU variable declares a unit that contradicts them: another quantity (a current
    bound as a voltage), or a known unit with another scale than it needs (a duty in % with
    scale 1). Variables without a declared unit cannot be checked here (a run's results can:
    :func:`cosim.metrics.implausible_runs`)."""
    variables = {v.name: v for v in model_description.modelVariables}
    problems = []
    for role, mapping in binding.roles.items():
        variable = variables.get(mapping.variable)
        unit = _unit_of(variable) if variable is not None else ""
        quantity = ROLE_QUANTITIES.get(role)
        if not unit or quantity is None:
            continue
        if unit in UNIT_SCALES[quantity]:
            needed = UNIT_SCALES[quantity][unit]
            if not math.isclose(mapping.scale, needed, rel_tol=1e-9):
                problems.append(f"{role} is {mapping.variable!r} in {unit} with scale = {mapping.scale:g} "
                                f"(a {quantity} in {unit} needs scale = {needed:g})")
        else:
            other = next((q for q, units in UNIT_SCALES.items() if unit in units and q != quantity), None)
            if other is not None:
                what = "dimensionless" if unit == "1" else f"a {other}"
                problems.append(f"{role} is {mapping.variable!r} in {unit}, {what}, not a {quantity}")
    return problems


def _check_variables(binding: PlantBinding, checked, loc: TomlLocator) -> None:
    """The roles and parameters against the FMU (the plant's own checks, :func:`check_against`),
    and the interface."""
    check_against(binding, checked, loc, INPUT_ROLES)
    _check_fixed_step(binding, checked, loc)
    wanted_interface = binding.interface
    if wanted_interface is not None and wanted_interface not in checked.interfaces:
        raise ConfigError(f"{where(binding.source, loc, 'interface')}: interface {wanted_interface!r} is not "
                          f"available (the FMU offers: {', '.join(checked.interfaces)})")


def read_binding_text(path: str | Path, what: str = "binding file") -> tuple[str, Path]:
    """A binding file's text and resolved path; a missing file, a folder or unreadable text is a
    one-line :class:`ConfigError`."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{what} {path} is a folder: expected a .toml file")
    if not path.is_file():
        raise ConfigError(f"{what} {path} does not exist")
    if path.suffix.lower() == ".fmu":  # read as text it would be "cannot decode byte 0x.."
        raise ConfigError(f"{path} is an FMU, not a {what}: a binding file (.toml) names the FMU and its variables' "
                          f"roles -- draft one with buck-cosim inspect {path} --draft-binding binding.toml")
    try:
        return path.read_text(encoding="utf-8"), path.resolve()
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(f"{path}: cannot read {what} ({error})") from None


@dataclass(frozen=True)
class Refusal:
    """Which part of a refused set-up the FMU refuses (:func:`locate_refusal`)."""

    kind: str  # PARAMETER: one [parameters] value alone; TOGETHER: only their combination; REST: the set-up without any
    place: str = ""  # file:line of the value's key (PARAMETER) or of the [parameters] table (TOGETHER)
    name: str = ""
    value: object = None


PARAMETER, TOGETHER, REST = "parameter", "together", "rest"


def locate_refusal(binding, try_set_up: Callable[[Mapping[str, object]], bool], top_keys: set[str] = TOP_KEYS
                   ) -> Refusal | None:
    """After an FMU refused its set-up with ``binding``'s ``[parameters]``: which part it refuses. ``try_set_up``
    sets the FMU up afresh with exactly the given binding parameters (the FMU's own defaults for the rest) and
    says whether it was accepted. First without any (refused: REST -- the inputs or the FMU's defaults, not the
    binding), then each value alone (the first refused: PARAMETER, at its line of the binding file), else TOGETHER.
    None without a binding file or parameters. Plant and controller bindings alike (``top_keys``: the file kind's
    keys); the caller restores its own parameters."""
    if binding.source is None or not binding.parameters:
        return None
    if not try_set_up({}):
        return Refusal(REST)
    text, path = read_binding_text(binding.source)
    _, loc = parse_toml(text, path, top_keys)
    for name, value in binding.parameters.items():
        if not try_set_up({name: value}):
            return Refusal(PARAMETER, where(path, loc, name, "parameters"), name, value)
    return Refusal(TOGETHER, where(path, loc, None, "parameters"))


def load_binding(path: str | Path) -> PlantBinding:
    """Read and check a plant-binding file; raise :class:`ConfigError` (one line) on any problem."""
    text, resolved = read_binding_text(path)
    return parse_binding(text, resolved)


# ---------------------------------------------------------------------------------------------
# Draft bindings: guess roles from names and units

_PATTERNS = {
    "duty_cycle": (r"duty|^d$|^dc$|^u$|pwm", ("1", "%", "")),
    "input_voltage": (r"v_?in|v_?s$|vs\b|v_?source|supply|input_?voltage|vdc|u_?in", ("V", "mV", "")),
    "load_resistance": (r"r_?load|load_?res|^r$|rl?oad|resistance", ("Ohm", "ohm", "Ω", "")),
    "output_voltage": (r"v_?out|v_?o$|^vo\b|output_?voltage|v_?c$|vcap|v_?load|u_?out", ("V", "mV", "")),
    "inductor_current": (r"i_?l\b|i_?l_|^il|inductor.*i|i_?ind|l\.i$|inductor_?current", ("A", "mA", "")),
    "load_current": (r"i_?out|i_?o$|i_?load|load_?current", ("A", "mA", "")),
}
#: an FMI quantity (the variable's or its declared type's ``quantity``) -> the workbench quantity it measures
_QUANTITIES = {"electricpotential": "voltage", "voltage": "voltage", "electriccurrent": "current", "current": "current",
               "resistance": "resistance", "electricresistance": "resistance", "dutycycle": "duty", "duty": "duty"}


def _unit_of(variable) -> str:
    unit = variable.unit or (getattr(variable.declaredType, "unit", None) if variable.declaredType else None)
    return unit or ""


def _quantity_of(variable) -> str | None:
    """The workbench quantity (:data:`ROLE_QUANTITIES`' values) the variable's declared unit or FMI quantity names,
    or None."""
    unit = _unit_of(variable)
    found = next((q for q, units in UNIT_SCALES.items() if unit in units), None)
    if found is not None:
        return found
    declared = variable.quantity or (getattr(variable.declaredType, "quantity", None) if variable.declaredType else None)
    return _QUANTITIES.get(re.sub(r"[^a-z]", "", (declared or "").lower()))


def guess_roles(model_description) -> dict[str, tuple[str, float, str]]:
    """Role -> (variable, scale, reason) guessed from names, causality and units: first by name (a declared unit must
    fit the role), then, for a role still unguessed, the one variable of the right causality whose declared unit or
    FMI quantity measures the role's quantity (a current output only if it is the only one left: inductor or load
    current cannot be told apart by unit). The scale is the one the unit implies (``%`` -> 100, ``mA`` -> 1000)."""
    guesses: dict[str, tuple[str, float, str]] = {}
    taken: set[str] = set()

    def candidates(role: str):
        wanted = ("input",) if role in INPUT_ROLES else ("output",)
        return [v for v in model_description.modelVariables if is_float(v) and not array_shape(v)
                and v.causality in wanted and v.name not in taken]

    for role, (pattern, units) in _PATTERNS.items():
        for variable in candidates(role):
            unit = _unit_of(variable)
            if re.search(pattern, variable.name, re.IGNORECASE) and (unit in units or not units):
                scale = UNIT_SCALES[ROLE_QUANTITIES[role]].get(unit, 1.0)
                if not unit:  # no declared unit: hints in the name, e.g. IL_mA or duty_pct
                    if re.search(r"(^|_)mA($|_)", variable.name):
                        scale = 1000.0
                    elif re.search(r"pct|percent", variable.name, re.IGNORECASE):
                        scale = 100.0
                reason = f"name {variable.name!r}" + (f", unit {unit}" if unit else ", no unit declared")
                guesses[role] = (variable.name, scale, reason)
                taken.add(variable.name)
                break
    for role in _PATTERNS:
        if role in guesses:
            continue
        quantity = ROLE_QUANTITIES[role]
        fitting = [v for v in candidates(role) if _quantity_of(v) == quantity]
        if len(fitting) != 1:  # none, or several the units cannot tell apart: left to the user
            continue
        variable = fitting[0]
        unit = _unit_of(variable)
        scale = UNIT_SCALES[quantity].get(unit, 1.0)
        reason = (f"unit {unit} alone (the only {'input' if role in INPUT_ROLES else 'output'} in a {quantity} unit; "
                  f"the name {variable.name!r} says nothing)" if unit else
                  f"quantity {variable.quantity or variable.declaredType.quantity} alone")
        guesses[role] = (variable.name, scale, reason)
        taken.add(variable.name)
    return guesses


def unitless_guesses(fmu_path: str | Path) -> list[str]:
    """The draft's guessed roles whose variables declare no unit (``"D (duty_cycle)"``) and whose name
    gives no hint either: their scale is a guess of 1 a user must check."""
    md = check_fmu(fmu_path).model_description
    variables = {v.name: v for v in md.modelVariables}
    return [f"{name} ({role})" for role, (name, scale, _) in guess_roles(md).items()
            if not _unit_of(variables[name]) and scale == 1.0]


def draft_binding_text(fmu_path: Path, binding_path: Path) -> str:
    checked = check_fmu(fmu_path)
    md = checked.model_description
    guesses = guess_roles(md)
    try:
        relative = Path(fmu_path).resolve().relative_to(binding_path.resolve().parent)
    except ValueError:
        relative = Path(fmu_path).resolve()
    interface = "co-simulation" if "co-simulation" in checked.interfaces else checked.interfaces[0]
    lines = [
        f"# Draft plant binding for {Path(fmu_path).name}, written by 'buck-cosim inspect --draft-binding'.",
        "# Roles were GUESSED from variable names and units: check every one before use.",
        "# fmu_value = scale * workbench_value + offset (workbench units: V, A, Ohm, duty 0..1).",
        f'fmu = "{relative.as_posix()}"',
        f'interface = "{interface}"   # this FMU offers: {", ".join(checked.interfaces)}',
        f'label = "{md.modelName} (external)"',
        "",
    ]
    for role in ROLES:
        if role in guesses:
            name, scale, reason = guesses[role]
            lines += [f"[roles.{role}]   # guessed from {reason}", f'variable = "{name}"']
            if scale != 1.0:
                lines.append(f"scale = {scale}")
            lines.append("")
        else:
            lines += [f"# [roles.{role}]   # not found: {ROLE_DESCRIPTIONS[role]}", '# variable = "..."', ""]
    parameters = [v for v in md.modelVariables if v.causality == "parameter" and v.start is not None
                  and not array_shape(v) and v.type not in ("Binary", "Clock")]  # what a binding can set
    if parameters:
        lines.append("[parameters]   # current start values; edit to override")
        for v in parameters:
            value = v.start
            if v.type == "Boolean":
                value = "true" if str(value).lower() in ("true", "1") else "false"
            elif v.type == "String":
                value = f'"{value}"'
            name = v.name if re.fullmatch(r"[A-Za-z0-9_-]+", v.name) else f'"{v.name}"'
            lines.append(f"# {name} = {value}")
    lines += ["", *_draft_converter(md, guesses)]
    return "\n".join(lines) + "\n"


def _draft_converter(model_description, guesses) -> list[str]:
    """The draft's ``[converter]`` table (:mod:`cosim.converter_spec`), every key commented out: the nominal supply
    and load default to the start values of their guessed variables; the output, the ranges and the circuit are the
    user's to give."""
    variables = {v.name: v for v in model_description.modelVariables}
    parameters = [v for v in model_description.modelVariables if v.causality == "parameter" and is_float(v)]

    def circuit(key: str, pattern: str, example: str, unit: str) -> str:
        found = next((v for v in parameters if re.fullmatch(pattern, v.name, re.IGNORECASE)), None)
        if found is None:
            return f"# {key} = {example:<24} # [{unit}] a number, or the name of the FMU parameter that holds it"
        quoted = f'"{found.name}"'
        return f"# {key} = {quoted:<24} # [{unit}] the FMU parameter {found.name} (start {found.start})"

    def start(role: str) -> str:
        name = guesses.get(role, (None,))[0]
        value = variables[name].start if name in variables else None
        return f"default: the start value of {name}, {value}" if value is not None else "no start value to default to"

    return [
        "# The converter under study: the shipped scenarios, the PI tuning, the NNPC's identification data and the",
        "# classical and MPC designs work at these operating points (docs/guide/external-plants.md). Give at least",
        "# output_voltage; the ranges (the operating envelope) are needed by the identification, the envelope designs",
        "# and the map; the circuit by the model-based designs (mpc-nominal, current-mode, type-iii).",
        "[converter]",
        "# output_voltage = 12.0                # [V] nominal output, the regulated reference (required)",
        f"# input_voltage = 48.0                 # [V] nominal supply ({start('input_voltage')})",
        f"# load_resistance = 6.0                # [Ohm] nominal load ({start('load_resistance')})",
        "# output_voltage_range = [3.0, 20.0]   # [V] references",
        "# input_voltage_range = [36.0, 60.0]   # [V] supplies",
        "# load_resistance_range = [4.0, 100.0] # [Ohm] loads",
        "# control_periods = [1e-3]             # [s]",
        "# inductor_current_limit = 8.0         # [A]",
        "# [converter.circuit]                  # the nominal circuit: numbers in SI, or an FMU parameter's name",
        circuit("inductance", r"l|ind\w*|l_\w+", "100e-6", "H"),
        circuit("capacitance", r"c|cap\w*|c_\w+", "47e-6", "F"),
        circuit("switching_frequency", r"f_?sw|fs|f_?s|sw\w*_?freq\w*|switching_?frequency", "100e3", "Hz"),
    ]


def write_draft_binding(fmu_path: str | Path, out_path: str | Path) -> Path:
    out_path = Path(out_path)
    return atomic_write_text(out_path, draft_binding_text(Path(fmu_path), out_path))
