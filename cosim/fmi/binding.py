"""Plant bindings: which FMU variable plays which role for the workbench, with unit conversion.

The workbench speaks SI units and six role names. A binding maps each role onto a variable of a
particular FMU, with ``fmu_value = scale * workbench_value + offset`` (e.g. a duty cycle in percent
has ``scale = 100``; a current in mA has ``scale = 1000``). The built-in BuckConverter FMU binds
every role to the variable of the same name; :mod:`cosim.fmi.binding_file` reads user bindings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Mapping

from cosim.base.errors import ConfigError
from cosim.base.labels import did_you_mean, slug
from cosim.converter_spec import ConverterSpec
from plant_fmu.table_ii import TABLE_II

#: the built-in plant's converter spec: the paper's Table II (the one module that reads it)
BUILTIN_SPEC: ConverterSpec = TABLE_II

INPUT_ROLES = ("duty_cycle", "input_voltage", "load_resistance")
OUTPUT_ROLES = ("output_voltage", "inductor_current", "load_current", "measured_output_voltage",
                "measured_inductor_current", "measured_load_current")
ROLES = INPUT_ROLES + OUTPUT_ROLES
REQUIRED_ROLES = ("duty_cycle", "output_voltage")
#: a controller FMU's inputs, in the order the adapter sets them (the Measurement's fields; cosim.fmi.controller)
CONTROLLER_INPUT_ROLES = ("reference", "measured_output_voltage", "measured_inductor_current",
                          "measured_load_current", "input_voltage")
CONTROLLER_OUTPUT_ROLES = ("duty_cycle",)
#: a parameter that holds the controller FMU's own sample period
CONTROLLER_PARAMETER_ROLES = ("sample_period",)
CONTROLLER_ROLES = CONTROLLER_INPUT_ROLES + CONTROLLER_OUTPUT_ROLES + CONTROLLER_PARAMETER_ROLES
REQUIRED_CONTROLLER_ROLES = ("reference", "measured_output_voltage", "duty_cycle")
ROLE_DESCRIPTIONS = {
    "duty_cycle": "duty cycle command, 0..1 (input, required)",
    "input_voltage": "input/supply voltage Vs (input, optional: needed for supply steps)",
    "load_resistance": "load resistance R (input, optional: needed for load steps)",
    "output_voltage": "output voltage vo (output, required)",
    "inductor_current": "inductor current iL (output, required by NNPC and the cost of eq. 23)",
    "load_current": "load current io (output, optional: lets predictive controllers estimate the load)",
    "measured_output_voltage": "what the controller's voltage sensor reads, e.g. a period average "
                               "(output, optional: default output_voltage)",
    "measured_inductor_current": "what the controller's current sensor reads (output, optional: default "
                                 "inductor_current)",
    "measured_load_current": "what the controller's load-current sensor reads (output, optional: default "
                             "load_current)",
}

#: the built-in FMU's Integer parameter ``plant_mode`` per mode name
PLANT_MODE_CODES = {"averaged": 0, "switched": 1}


@dataclass(frozen=True)
class RoleMap:
    """One role bound to an FMU variable: ``fmu_value = scale * workbench_value + offset``."""

    variable: str
    scale: float = 1.0
    offset: float = 0.0



@dataclass(frozen=True)
class PlantBinding:
    """Everything the master needs to drive one plant FMU."""

    fmu_path: Path
    roles: Mapping[str, RoleMap]
    interface: str | None = None  # "co-simulation", "model-exchange", or None: prefer co-simulation
    parameters: Mapping[str, float | int | bool | str] = field(default_factory=dict)
    max_step: float | None = None  # largest step the FMU accepts [s]; the master subdivides longer ones
    source: Path | None = None  # the binding file, named in error messages
    label: str = "BuckConverter (built-in)"
    tag_override: str | None = None  # short name for file names (see :attr:`tag`)
    isolate: bool = False  # step the FMU in a child process (cosim.fmi.isolation): a crash ends only the run
    #: isolated only: the wall-time limit [s] for one step of the plant process, None: derived from the
    #: step's simulated length (cosim.fmi.isolation.step_time_limit); a step over it is a fault
    step_timeout: float | None = None
    #: isolated only: the plant process's resident memory limit [MB], None: half the machine's memory
    #: (cosim.fmi.isolation.memory_limit_bytes); a plant process above it is stopped, a fault
    memory_limit: float | None = None
    #: the converter under study (:mod:`cosim.converter_spec`): a binding file's ``[converter]`` table with the FMU's
    #: start values as defaults, the built-in plant's Table II; None: none given (designs then refuse, naming the key)
    spec: ConverterSpec | None = None
    #: co-simulation only: the one communication step [s] the master steps the FMU by (a fixed-step FMU's step;
    #: :mod:`cosim.fmi.communication`), None: any step (or, for an FMU that cannot vary it, its DefaultExperiment's)
    step: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "roles", MappingProxyType(dict(self.roles)))
        object.__setattr__(self, "parameters", MappingProxyType(dict(self.parameters)))

    def __reduce__(self):  # read-only mappings do not pickle: rebuild from plain dicts (worker processes)
        return (PlantBinding, (self.fmu_path, dict(self.roles), self.interface, dict(self.parameters), self.max_step,
                               self.source, self.label, self.tag_override, self.isolate, self.step_timeout,
                               self.memory_limit, self.spec, self.step))

    def has(self, role: str) -> bool:
        return role in self.roles

    @property
    def tag(self) -> str:
        """Short name in file and table names: ``bound-<binding file stem>`` for a binding file,
        else the name the caller gave (the study's ``nominal-switched``), else the label's slug."""
        if self.tag_override:
            return self.tag_override
        if self.source is not None:
            return f"bound-{Path(self.source).stem}"
        return slug(self.label)

    @property
    def origin(self) -> str:
        """How to name this plant in a message: the binding file if any, else the FMU."""
        return f"binding file {self.source}" if self.source else f"plant FMU {self.fmu_path}"

    def describe(self) -> dict:
        """JSON-ready description for run metadata."""
        return {
            "label": self.label,
            "fmu": str(self.fmu_path),
            "binding_file": str(self.source) if self.source else None,
            "interface": self.interface,
            "roles": {r: {"variable": m.variable, "scale": m.scale, "offset": m.offset} for r, m in self.roles.items()},
            "parameters": dict(self.parameters),
            "max_step_s": self.max_step,
            "isolated": self.isolate,
            "step_timeout_s": self.step_timeout,
            "memory_limit_mb": self.memory_limit,
            **({"communication_step_s": self.step} if self.step is not None else {}),
            **({"converter": self.spec.describe()} if self.spec is not None else {}),
        }

    @property
    def converter(self) -> ConverterSpec:
        """The converter spec, or a spec that gives nothing (every design needing a value then refuses, naming it)."""
        return self.spec if self.spec is not None else ConverterSpec(label=self.label, origin=self.origin)


def builtin_binding(mode: str = "averaged", parameters: Mapping[str, float | int] | None = None,
                    interface: str | None = None) -> PlantBinding:
    """Binding for the project's own BuckConverter FMU (built on first use).

    ``mode`` is "averaged" (eq. 3 with DCM) or "switched" (ideal switch and diode with PWM);
    ``parameters`` overrides FMU parameters by name, e.g. ``{"inductance": 264e-6}``.
    """
    from plant_fmu import fmu_path

    if mode not in PLANT_MODE_CODES:
        raise ConfigError(f"plant mode {mode!r} is unknown: expected one of {', '.join(PLANT_MODE_CODES)}")
    values: dict[str, float | int] = {"plant_mode": PLANT_MODE_CODES[mode]}
    values.update(parameters or {})
    roles = {role: RoleMap(role) for role in ROLES}
    # The controller measures like an averaging ADC: the mean over the last PWM period, free of the
    # switching ripple a point sample would alias into a DC error (equal to the state when averaged).
    roles["measured_output_voltage"] = RoleMap("average_output_voltage")
    roles["measured_inductor_current"] = RoleMap("average_inductor_current")
    roles["measured_load_current"] = RoleMap("average_load_current")
    return PlantBinding(
        fmu_path=fmu_path(),
        roles=roles,
        interface=interface,
        parameters=values,
        label=f"BuckConverter (built-in, {mode})",
        spec=BUILTIN_SPEC,
    )


# ---------------------------------------------------------------------------------------------
# A binding against an FMU's model description: the one place the roles and parameters are checked


class BindingMismatch(ConfigError):
    """A role or parameter of a binding does not fit the FMU. ``kind`` ("role" or "parameter")
    and ``key`` name what, so a binding file can add its line; the plant adds the FMU's name."""

    def __init__(self, message: str, kind: str, key: str):
        super().__init__(message)
        self.kind, self.key = kind, key


@dataclass(frozen=True)
class ResolvedRole:
    """A role bound to a value reference: ``fmu_value = scale * workbench_value + offset``."""

    role: str
    value_reference: int
    scale: float
    offset: float


@dataclass(frozen=True)
class ResolvedParameter:
    """A parameter or start value to set before initialisation, typed as the FMU declares it."""

    name: str
    value_reference: int
    type: str  # FMI 2.0: "Real", "Integer", "Enumeration", "Boolean", "String"; FMI 3.0: "Float64", "Int32", ...
    value: float | int | bool | str


# ---------------------------------------------------------------------------------------------
# Variable types of both FMI versions: the one place the workbench knows them

#: the types of a signal role's variable: FMI 2.0's Real, FMI 3.0's Float64 (the workbench computes in doubles)
FLOAT_TYPES = ("Real", "Float64")
#: FMI 3.0's sized integers (and FMI 2.0's Integer, 32 bits): the values each holds
INTEGER_RANGES = {"Integer": (-2**31, 2**31 - 1), "Enumeration": (-2**31, 2**31 - 1),
                  **{f"Int{n}": (-2**(n - 1), 2**(n - 1) - 1) for n in (8, 16, 32, 64)},
                  **{f"UInt{n}": (0, 2**n - 1) for n in (8, 16, 32, 64)}}
_FLOAT_LIMITS = {"Real": float("inf"), "Float64": float("inf"), "Float32": 3.4028234663852886e38}


def is_float(variable) -> bool:
    """A Real (FMI 2.0) or Float64 (FMI 3.0) variable: what signal roles and tunable parameters can be."""
    return variable.type in FLOAT_TYPES


def is_integer(variable) -> bool:
    """An Integer (FMI 2.0) or Int8 ... UInt64 (FMI 3.0) variable (not an enumeration)."""
    return variable.type in INTEGER_RANGES and variable.type != "Enumeration"


def array_shape(variable) -> tuple[int, ...]:
    """An FMI 3.0 array variable's shape (its Dimension elements); () for a scalar (always, in FMI 2.0)."""
    if not getattr(variable, "dimensions", None):
        return ()
    return tuple(getattr(variable, "shape", None) or (len(variable.dimensions) * (0,)))


def _fits(kind: str, value) -> bool:
    if kind in _FLOAT_LIMITS:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(float(value)) \
            and abs(float(value)) <= _FLOAT_LIMITS[kind]
    if kind in INTEGER_RANGES:
        low, high = INTEGER_RANGES[kind]
        return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high
    if kind == "Boolean":
        return isinstance(value, bool)
    if kind == "String":
        return isinstance(value, str)
    return False


def _expected(kind: str) -> str:
    if kind in _FLOAT_LIMITS:
        return "a finite number" + (" within +-3.4e38" if kind == "Float32" else "")
    if kind in INTEGER_RANGES:
        low, high = INTEGER_RANGES[kind]
        return f"a whole number in [{low}, {high}]"
    return {"Boolean": "true or false", "String": "text"}.get(kind, "nothing: the workbench cannot set it")


#: fmpy's FMI 3.0 setter per type (FMI 3.0 sets enumerations as Int64)
_FMI3_SETTERS = {"Enumeration": "setInt64"}


def apply_parameters(fmu, parameters) -> None:
    """Set each :class:`ResolvedParameter` on an instance -- fmpy's ``FMU2Slave``/``FMU2Model`` (FMI 2.0) or
    ``FMU3Slave``/``FMU3Model`` (FMI 3.0) -- with the setter of its declared type, in order; before
    initialisation, as the binding's parameters and start values are set (plant and controller FMUs alike)."""
    from fmpy.fmi3 import _FMU3

    fmi3 = isinstance(fmu, _FMU3)
    for p in parameters:
        if fmi3:
            value = float(p.value) if p.type in _FLOAT_LIMITS else p.value
            getattr(fmu, _FMI3_SETTERS.get(p.type, f"set{p.type}"))([p.value_reference], [value])
        elif p.type == "Real":
            fmu.setReal([p.value_reference], [float(p.value)])
        elif p.type in ("Integer", "Enumeration"):
            fmu.setInteger([p.value_reference], [int(p.value)])
        elif p.type == "Boolean":
            fmu.setBoolean([p.value_reference], [bool(p.value)])
        else:
            fmu.setString([p.value_reference], [str(p.value)])


def resolve_roles(binding, model_description, input_roles=INPUT_ROLES) -> dict[str, ResolvedRole]:
    """Each bound role's variable: it exists, is Real, has a causality that fits the role (an
    ``input_roles`` role: input or tunable parameter -- the workbench writes it during the run -- except a controller's
    own settings, such as its sample period, any parameter; any other: output or local), and the role's scale
    is finite and non-zero. Raises :class:`BindingMismatch` naming the role. ``binding``: a plant
    or a controller binding (anything with ``roles`` and ``fmu_path``)."""
    variables = {v.name: v for v in model_description.modelVariables}
    fmu_name = Path(binding.fmu_path).name
    resolved = {}
    for role, mapping in binding.roles.items():
        variable = variables.get(mapping.variable)
        if variable is None:
            fitting = [v.name for v in model_description.modelVariables if is_float(v) and v.causality in
                       (("input", "parameter") if role in input_roles else ("output", "local"))]
            raise BindingMismatch(f"role {role!r} names variable {mapping.variable!r}, which {fmu_name} does not "
                                  f"have{did_you_mean(mapping.variable, fitting, hint_all=8)}", "role", role)
        if not is_float(variable):
            wanted_type = "Real" if variable.type in ("Integer", "Boolean", "String", "Enumeration") else "Float64"
            why = ": the workbench exchanges signals as 64-bit floats" if variable.type == "Float32" else ""
            raise BindingMismatch(f"role {role!r} needs a {wanted_type} variable, but {mapping.variable!r} is "
                                  f"{variable.type}{why}", "role", role)
        if array_shape(variable):
            raise BindingMismatch(f"role {role!r} needs a scalar variable, but {mapping.variable!r} is an FMI 3.0 array "
                                  f"(shape {list(array_shape(variable))}): a role carries one value", "role", role)
        wanted = ("input", "parameter") if role in input_roles else ("output", "local")
        if variable.causality not in wanted:
            raise BindingMismatch(f"role {role!r} needs causality {' or '.join(wanted)}, but {mapping.variable!r} "
                                  f"has causality {variable.causality}", "role", role)
        if variable.causality == "parameter" and role not in CONTROLLER_PARAMETER_ROLES \
                and variable.variability != "tunable":  # the workbench writes it during the run
            raise BindingMismatch(f"role {role!r} is set by the workbench during the run, so it needs an input or a "
                                  f"tunable parameter, but {mapping.variable!r} is a parameter with variability "
                                  f"{variable.variability} (the FMU takes it only before initialisation)", "role", role)
        if mapping.scale == 0.0 or not math.isfinite(mapping.scale) or not math.isfinite(mapping.offset):
            raise BindingMismatch(f"role {role!r} has scale {mapping.scale} / offset {mapping.offset}; expected a "
                                  "finite, non-zero scale and a finite offset", "role", role)
        resolved[role] = ResolvedRole(role, variable.valueReference, mapping.scale, mapping.offset)
    return resolved


def parameter_values(parameters: Mapping[str, object], model_description) -> dict[str, float | int | bool | str]:
    """Every scalar parameter of the FMU with the value a run starts from: the binding's override, else
    the FMU's start value, typed (a number, true/false or text). What run metadata records, so a run
    names its switching frequency, PWM carrier or component values whether or not a binding set them."""
    values = {}
    for v in model_description.modelVariables:
        if v.causality != "parameter" or array_shape(v) or v.type in ("Binary", "Clock"):
            continue
        if v.name in parameters:
            values[v.name] = parameters[v.name]
        elif v.start is not None:
            text = str(v.start)
            try:
                values[v.name] = (float(text) if v.type in _FLOAT_LIMITS else
                                  int(float(text)) if v.type in INTEGER_RANGES else
                                  text.lower() in ("true", "1") if v.type == "Boolean" else text)
            except ValueError:
                values[v.name] = text
    return values


def resolve_parameters(parameters: Mapping[str, object], model_description, fmu_name: str) -> list[ResolvedParameter]:
    """Each parameter names a scalar variable of the FMU and has a value of its type (Real, Float64, Float32:
    a finite number; Integer, Enumeration and FMI 3.0's Int8 ... UInt64: a whole number the type holds;
    Boolean true/false; String text). FMI 3.0 arrays, Binary variables and clocks cannot be set from a binding.
    Raises :class:`BindingMismatch` naming the parameter."""
    variables = {v.name: v for v in model_description.modelVariables}
    resolved = []
    for name, value in parameters.items():
        variable = variables.get(name)
        if variable is None:
            settable = [v.name for v in model_description.modelVariables if v.causality in ("parameter", "input")]
            raise BindingMismatch(f"parameter {name!r} is not a variable of {fmu_name}"
                                  f"{did_you_mean(name, settable, hint_all=12)}", "parameter", name)
        kind = variable.type
        if variable.causality in ("output", "calculatedParameter", "independent"):
            raise BindingMismatch(f"parameter {name!r} is {'an' if variable.causality[0] in 'oi' else 'a'} "
                                  f"{variable.causality} of {fmu_name}: the FMU computes it, a binding sets parameters "
                                  "and inputs only", "parameter", name)
        if array_shape(variable):
            raise BindingMismatch(f"parameter {name!r} is an FMI 3.0 array in {fmu_name} (shape "
                                  f"{list(array_shape(variable))}): a binding sets scalar parameters only; leave it at "
                                  "its start value", "parameter", name)
        if kind in ("Binary", "Clock"):
            raise BindingMismatch(f"parameter {name!r} is a {kind} variable of {fmu_name}: a binding sets numbers, "
                                  "true/false and text only", "parameter", name)
        if not _fits(kind, value):
            raise BindingMismatch(f"parameter {name!r} is {kind} in {fmu_name}, got {value!r} "
                                  f"({type(value).__name__}): expected {_expected(kind)}", "parameter", name)
        resolved.append(ResolvedParameter(name, variable.valueReference, kind, value))
    return resolved
