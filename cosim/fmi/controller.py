"""Controller FMUs in the master: one adapter that implements the controller protocol over an FMU.

:class:`FmuController` is a controller like any other for the master (``sample_period``,
``duty_limits``, ``reset()``, ``step(measurement)``, ``describe()``): at each sample it advances
the FMU to the sample instant (``fmi2DoStep`` from the previous one: the controller's state
advances), sets the measurement as inputs and reads the duty. The master never learns a second
kind of controller.

Which FMU variable plays which role is a :class:`ControllerBinding`: for the workbench's own
controller FMUs (``buck-cosim export-controller``) the variables carry the role names and the
binding is read off the FMU (:func:`builtin_controller_binding`); for an externally authored one
(Simulink, a Modelica tool, pythonfmu) a **controller-binding file** names them::

    fmu = "MyPI.fmu"                 # relative to this file
    label = "PI (Simulink)"          # optional: how runs and figures name it
    sample_period = 1e-3             # [s] optional if [roles.sample_period] names a parameter
    duty_limits = [0.0, 1.0]         # optional (default: duty_min / duty_max of the FMU, else 0..1)

    [roles.reference]                # required (FMU input, V)
    variable = "Vref"
    [roles.measured_output_voltage]  # required (FMU input, V)
    variable = "Vo_meas"
    [roles.duty_cycle]               # required (FMU output)
    variable = "D"
    scale = 100.0                    # fmu_value = scale * workbench_value + offset: duty in percent
    # optional: [roles.measured_inductor_current], [roles.measured_load_current], [roles.input_voltage]
    # (FMU inputs), [roles.sample_period] (a parameter holding the FMU's own sample period)

    [parameters]                     # parameter values set before initialisation
    Kp = 0.0015

It is checked like a plant-binding file before anything runs (keys, types, the FMU archive, each
variable's existence and causality, the parameters' types, the sample period), every mistake
named with file, key and line.

FMI 3.0: ``FmuController(binding)`` of an FMI 3.0 archive makes an :class:`FmuController3` (below, beside
the class it specialises, so the dispatch and the subclass do not import each other): the same sampling,
roles, scales and checks, with fmpy's ``FMU3Slave`` and the FMI 3.0 calls -- ``fmi3Get/SetFloat64`` (with
the value count FMI 3.0 adds), ``fmi3EnterInitializationMode`` with the start time, ``fmi3DoStep`` with its
flags handled as for plants (:class:`cosim.fmi.plant_fmi3.Fmi3DoStep`). A controller FMU is instantiated
without event mode: it samples on its own time base inside ``fmi3DoStep``, as an FMI 2.0 one does, and one
that declares FMI 3.0 clocks (which need event mode) is refused with one line.
"""

from __future__ import annotations

import math
import shutil
import sys
from collections import deque
from ctypes import c_double, c_uint
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Mapping

import fmpy
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import FMU2Slave, fmi2True
from fmpy.fmi3 import FMU3Slave

from controllers.base import Measurement, check_duty_limits
from cosim.base.errors import ConfigError, ControllerError, FmuArchiveError
from cosim.base.toml_files import finite_number, parse_toml, where
from cosim.fmi.archive import CheckedFmu, check_fmu
from cosim.fmi.binding import (
    CONTROLLER_INPUT_ROLES,
    CONTROLLER_PARAMETER_ROLES,
    CONTROLLER_ROLES,
    REQUIRED_CONTROLLER_ROLES,
    ROLES,
    BindingMismatch,
    RoleMap,
    apply_parameters,
    resolve_parameters,
    resolve_roles,
)
from cosim.fmi.binding_file import (
    PARAMETER,
    TOGETHER,
    check_against,
    checked_fmu_of,
    fmu_path_of,
    locate_refusal,
    parse_parameters,
    parse_roles,
    read_binding_text,
)
from cosim.fmi.fmu_log import STATUS_NAMES, callbacks_for, release
from cosim.fmi.plant_fmi3 import Fmi3DoStep, clock_refusal

TOP_KEYS = {"fmu", "label", "sample_period", "duty_limits", "roles", "parameters"}


@dataclass(frozen=True)
class ControllerBinding:
    """Everything the adapter needs to drive one controller FMU."""

    fmu_path: Path
    roles: Mapping[str, RoleMap]
    sample_period: float | None = None  # [s] None: the FMU's sample_period role's start value
    duty_limits: tuple[float, float] | None = None  # None: the FMU's duty_min / duty_max, else 0..1
    parameters: Mapping[str, float | int | bool | str] = field(default_factory=dict)
    source: Path | None = None  # the binding file, named in messages
    label: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "roles", MappingProxyType(dict(self.roles)))
        object.__setattr__(self, "parameters", MappingProxyType(dict(self.parameters)))

    def __reduce__(self):  # read-only mappings do not pickle
        return (ControllerBinding, (self.fmu_path, dict(self.roles), self.sample_period, self.duty_limits,
                                    dict(self.parameters), self.source, self.label))

    @property
    def origin(self) -> str:
        return f"controller binding file {self.source}" if self.source else f"controller FMU {self.fmu_path}"

    def has(self, role: str) -> bool:
        return role in self.roles


def builtin_controller_binding(fmu_path: str | Path) -> ControllerBinding:
    """The binding of a controller FMU whose variables carry the role names (``export-controller``'s)."""
    checked = check_fmu(fmu_path)
    names = {v.name for v in checked.model_description.modelVariables}
    missing = [r for r in REQUIRED_CONTROLLER_ROLES + CONTROLLER_PARAMETER_ROLES if r not in names]
    if missing:
        raise ConfigError(f"controller FMU {fmu_path} has no variable {missing[0]!r}: a controller FMU without the "
                          "workbench's role names needs a controller-binding file (--controller BINDING.toml)")
    return ControllerBinding(Path(fmu_path).resolve(), {r: RoleMap(r) for r in CONTROLLER_ROLES if r in names})


def own_sample_period(binding: ControllerBinding, model_description) -> float | None:
    """The sample period [s] the FMU computes with in the parameter bound to the ``sample_period`` role: the value
    the binding's ``[parameters]`` give it, else its start value, mapped by the role's scale and offset; or None (no
    such role, or no value). (``[parameters] Ts = 2e-3`` was set on the FMU while the master stepped it at the start
    value's 1 ms.)"""
    mapping = binding.roles.get("sample_period")
    if mapping is None:
        return None
    value = binding.parameters.get(mapping.variable, _variable(model_description, mapping.variable).start)
    return None if value is None else (float(value) - mapping.offset) / mapping.scale


def _variable(model_description, name: str):
    """The model variable called ``name`` in ``model_description``, or None."""
    return next((variable for variable in model_description.modelVariables if variable.name == name), None)


def sample_period_problem(period: float | None, own: float | None) -> str | None:
    """Why a binding's ``sample_period`` cannot drive an FMU whose own sample period is ``own`` (None: fine):
    it must be a whole multiple of it, or the master would step the FMU past its sample instants."""
    if period is None or own is None:
        return None
    if not (own > 0 and math.isfinite(own)):
        return (f"the FMU's own sample period (the value of its sample_period role's parameter) is {own:g} s: "
                "expected a finite value > 0")
    ratio = period / own
    if abs(ratio - round(ratio)) > 1e-9 * ratio or round(ratio) < 1:
        return (f"sample_period = {period:.6g} s is not a whole multiple of the FMU's own sample period {own:.6g} s: "
                "the master would step the FMU past its sample instants")
    return None


_WARNED: set[str] = set()  # the warning lines this process has printed (a file may be read more than once)


def _warn_once(line: str) -> None:
    if line not in _WARNED:
        _WARNED.add(line)
        print(line, file=sys.stderr)


def parse_controller_binding(text: str, path: Path) -> ControllerBinding:
    """Parse and check a controller-binding file's text (``path`` locates the FMU and names errors)."""
    data, loc = parse_toml(text, path, TOP_KEYS | {"converter"})
    if "converter" in data:  # a plant binding's converter spec: say what the file is, not that the key is unknown
        raise ConfigError(f"{where(path, loc, None, 'converter')}: [converter] is a plant binding's table: this is a "
                          "plant binding file, given where a controller binding is expected")
    fmu_path = fmu_path_of(data, path, loc)
    label = data.get("label", f"{fmu_path.stem} (bound by {path.name})")
    if not isinstance(label, str):
        raise ConfigError(f"{where(path, loc, 'label')}: label has the wrong type: expected text")
    period = None
    if "sample_period" in data:
        period = finite_number(data["sample_period"], "sample_period", where(path, loc, "sample_period"))
        if period <= 0:
            raise ConfigError(f"{where(path, loc, 'sample_period')}: sample_period = {period} s is invalid: "
                              "expected > 0")
    limits = None
    if "duty_limits" in data:
        raw = data["duty_limits"]
        place = where(path, loc, "duty_limits")
        if not (isinstance(raw, list) and len(raw) == 2):
            raise ConfigError(f"{place}: duty_limits = {raw!r} is invalid: expected [min, max]")
        limits = (finite_number(raw[0], "duty_limits[0]", place), finite_number(raw[1], "duty_limits[1]", place))
        if not 0.0 <= limits[0] < limits[1] <= 1.0:
            raise ConfigError(f"{place}: duty_limits = [{limits[0]:g}, {limits[1]:g}] is invalid: expected 0 <= min < "
                              "max <= 1")
    roles = parse_roles(data, path, loc, CONTROLLER_ROLES, other=("plant", ROLES))
    for role in REQUIRED_CONTROLLER_ROLES:
        if role not in roles:
            raise ConfigError(f"{path}: missing role [roles.{role}] (the controller FMU's {role})")
    if period is None and "sample_period" not in roles:
        raise ConfigError(f"{path}: no sample period: give sample_period = <seconds> or [roles.sample_period] "
                          "naming the FMU's parameter that holds it")
    parameters = parse_parameters(data, path, loc)
    checked = checked_fmu_of(fmu_path, path, loc)
    binding = ControllerBinding(fmu_path, roles, period, limits, parameters, path, label)
    check_against(binding, checked, loc, CONTROLLER_INPUT_ROLES + CONTROLLER_PARAMETER_ROLES,
                  settings=CONTROLLER_PARAMETER_ROLES)
    problem = sample_period_problem(period, own_sample_period(binding, checked.model_description))
    if problem:
        key = "sample_period" if "sample_period" in data else "variable"
        raise ConfigError(f"{where(path, loc, key, None if key == 'sample_period' else 'roles.sample_period')}: "
                          f"{problem}")
    unbound = _variable(checked.model_description, "sample_period")
    own = binding.parameters.get("sample_period", None if unbound is None else unbound.start)  # as [parameters] set it
    if period is not None and "sample_period" not in roles and unbound is not None \
            and unbound.causality == "parameter" and own is not None and float(own) != period:
        _warn_once(f"warning: {where(path, loc, 'sample_period')}: sample_period = {period:.6g} s, but the FMU's "
                   f"parameter 'sample_period' is {float(own):.6g} s and is not bound "
                   "([roles.sample_period]): the FMU may compute with its own period while the master steps it at "
                   "this one")
    if "co-simulation" not in checked.interfaces:
        raise ConfigError(f"{where(path, loc, 'fmu')}: {fmu_path.name} offers no co-simulation for this platform "
                          "(a controller FMU is stepped with fmi2DoStep / fmi3DoStep)")
    return binding


def load_controller_binding(path: str | Path) -> ControllerBinding:
    """Read and check a controller-binding file; raise :class:`ConfigError` (one line) on any problem."""
    text, resolved = read_binding_text(path, "controller binding file")
    return parse_controller_binding(text, resolved)


def controller_binding(text: str) -> ControllerBinding:
    """What ``--controller`` names: a controller FMU (the workbench's role names) or a binding file."""
    path = Path(text)
    if path.suffix.lower() == ".toml":
        return load_controller_binding(path)
    if path.is_dir() or not path.is_file():
        raise ConfigError(f"controller {text!r} is neither a built-in controller, a controller FMU (.fmu) nor a "
                          "controller-binding file (.toml)" if not path.exists() else
                          f"controller {text} is a folder: expected a .fmu or .toml file")
    return builtin_controller_binding(path)


# ---------------------------------------------------------------------------------------------
# The adapter


class FmuController:
    """A controller FMU with the controller protocol of :mod:`controllers.base`.

    ``FmuController(binding)`` of an FMI 3.0 FMU makes a :class:`FmuController3`
    (the FMI 3.0 calls beneath the same protocol): callers do not learn the FMU's version."""

    #: how messages name the FMI calls of :meth:`step`
    _calls = {"step": "fmi2DoStep", "set": "fmi2SetReal", "get": "fmi2GetReal", "reset": "fmi2Reset",
              "instantiate": "fmi2Instantiate"}

    def __new__(cls, binding: ControllerBinding, checked: CheckedFmu | None = None, name: str | None = None):
        if cls is FmuController:
            checked = checked or check_fmu(binding.fmu_path)
            if checked.fmi_major == 3:
                cls = FmuController3
        return super().__new__(cls)

    def __init__(self, binding: ControllerBinding, checked: CheckedFmu | None = None, name: str | None = None):
        checked = checked or check_fmu(binding.fmu_path)
        if "co-simulation" not in checked.interfaces:
            raise FmuArchiveError(f"{binding.origin}: the FMU offers no co-simulation for this platform")
        self.binding = binding
        self.model_description = md = checked.model_description
        try:
            roles = resolve_roles(binding, md, CONTROLLER_INPUT_ROLES + CONTROLLER_PARAMETER_ROLES)
            self._parameters = resolve_parameters(binding.parameters, md, binding.fmu_path.name)
        except BindingMismatch as error:
            raise ConfigError(f"{binding.origin}: {error}") from None
        self.name = name or binding.label or md.modelName
        self.log: deque[tuple[str, str]] = deque(maxlen=100)
        variables = {v.name: v for v in md.modelVariables}
        self.sample_period = self._sample_period(binding)
        self.duty_limits = self._duty_limits(binding, variables)
        self.input_roles = tuple(r for r in CONTROLLER_INPUT_ROLES if r in roles)
        self._fields = tuple(_MEASUREMENT_FIELDS[r] for r in self.input_roles)
        self._in_vr = (c_uint * len(self.input_roles))(*(roles[r].value_reference for r in self.input_roles))
        self._in_value = (c_double * len(self.input_roles))()
        self._in_maps = [(roles[r].scale, roles[r].offset) for r in self.input_roles]
        duty = roles["duty_cycle"]
        self._out_vr = (c_uint * 1)(duty.value_reference)
        self._out_value = (c_double * 1)()
        self._duty_map = (duty.scale, duty.offset)
        self._unzipdir = fmpy.extract(str(binding.fmu_path))
        self._callbacks = self._make_callbacks()
        self._fmu = None
        try:
            self._instantiate(md)
        except Exception as error:
            if self._fmu is not None:
                self._fmu.freeLibrary()
                self._fmu = None
            shutil.rmtree(self._unzipdir, ignore_errors=True)
            if isinstance(error, ConfigError):
                raise
            raise ConfigError(f"{binding.origin}: {self._calls['instantiate']} failed{self._last_log()}") from None
        self._component = self._fmu.component
        self._initialized = False
        self.time = 0.0
        self._try_initialization()  # a parameter the FMU refuses is a configuration error, found now

    # ------------------------------------------------------------------ set-up
    def _instantiate(self, md) -> None:
        """Load and instantiate the FMU; set the C calls of :meth:`step` (FMI 2.0's signatures)."""
        self._fmu = FMU2Slave(guid=md.guid, unzipDirectory=self._unzipdir,
                              modelIdentifier=md.coSimulation.modelIdentifier, instanceName="controller")
        self._fmu.instantiate(callbacks=self._callbacks, loggingOn=True)
        dll = self._fmu.dll
        self._set_real, self._get_real, self._do_step = dll.fmi2SetReal, dll.fmi2GetReal, dll.fmi2DoStep

    def _sample_period(self, binding: ControllerBinding) -> float:
        own = own_sample_period(binding, self.model_description)
        period = binding.sample_period if binding.sample_period is not None else own
        if period is None or not (period > 0 and math.isfinite(period)):
            raise ConfigError(f"{binding.origin}: the controller FMU declares no valid sample period "
                              f"(got {period!r}): give sample_period in a controller-binding file")
        problem = sample_period_problem(binding.sample_period, own)
        if problem:
            raise ConfigError(f"{binding.origin}: {problem}")
        return period

    @staticmethod
    def _duty_limits(binding: ControllerBinding, variables) -> tuple[float, float]:
        if binding.duty_limits is not None:
            return tuple(binding.duty_limits)
        low, high = variables.get("duty_min"), variables.get("duty_max")
        if low is not None and high is not None and low.start is not None and high.start is not None:
            return check_duty_limits((float(low.start), float(high.start)), binding.origin)
        return 0.0, 1.0

    def _make_callbacks(self):
        callbacks, self._log_handle = callbacks_for(lambda status, category, message:
                                                    self.log.append((status, message)))
        return callbacks

    def _last_log(self) -> str:
        for status, message in reversed(self.log):
            if status in ("error", "fatal", "discard", "warning"):
                return f": {' '.join(message.split())}"
        return ""

    def _initialize(self, start_time: float) -> None:
        fmu = self._fmu
        fmu.setupExperiment(startTime=start_time)
        apply_parameters(fmu, self._parameters)
        fmu.enterInitializationMode()
        fmu.exitInitializationMode()
        self._initialized = True
        self.time = start_time

    def _try_initialization(self) -> None:
        try:
            self._initialize(0.0)
            self._fmu.reset()
        except FMICallException as error:
            refusal = f"({error.function} failed){self._last_log()}"
            located = self._locate_refusal()
            if located is not None and located.kind == PARAMETER:
                raise ConfigError(f"{located.place}: parameters.{located.name} = {located.value!r}: the controller FMU "
                                  f"refuses its set-up with this value {refusal}") from None
            if located is not None and located.kind == TOGETHER:
                raise ConfigError(f"{located.place}: the controller FMU refuses its set-up with these [parameters] "
                                  f"together, though with each alone {refusal}") from None
            raise ConfigError(f"{self.binding.origin}: the controller FMU refuses its set-up "
                              f"{'even without the binding parameters ' if located else ''}{refusal}") from None
        self._initialized = False

    def _locate_refusal(self):
        """After a refused set-up: which part the FMU refuses (:func:`cosim.fmi.binding_file.locate_refusal`), the
        binding's parameters restored and the instance reset afterwards; None if the FMU cannot be reset."""
        md, resolved = self.model_description, self._parameters

        def try_set_up(parameters) -> bool:
            self._fmu.reset()
            self._parameters = resolve_parameters(parameters, md, self.binding.fmu_path.name)
            try:
                self._initialize(0.0)
            except FMICallException:
                return False
            return True

        try:
            located = locate_refusal(self.binding, try_set_up, TOP_KEYS)
            self._fmu.reset()
            return located
        except FMICallException:  # the FMU cannot be reset: no location
            return None
        finally:
            self._parameters = resolved

    # ------------------------------------------------------------------ the controller protocol
    def reset(self) -> None:
        """Forget everything: the FMU is reset and initialised again at the next sample's time."""
        if self._initialized:
            try:
                self._fmu.reset()
            except FMICallException:
                raise ControllerError(f"{self.binding.origin}: {self._calls['reset']} failed{self._last_log()}") from None
            self._initialized = False

    def step(self, measurement: Measurement) -> float:
        t = measurement.time
        try:
            if not self._initialized:
                self._initialize(t)
            elif t > self.time:
                status = self._do_step(self._component, self.time, t - self.time, fmi2True)
                if status > 1:
                    raise FMICallException(self._calls["step"], status)
                self.time = t
            buffer = self._in_value
            for i, (name, (scale, offset)) in enumerate(zip(self._fields, self._in_maps)):
                buffer[i] = scale * getattr(measurement, name) + offset
            status = self._set_real(self._component, self._in_vr, len(buffer), buffer)
            if status > 1:
                raise FMICallException(self._calls["set"], status)
            status = self._get_real(self._component, self._out_vr, 1, self._out_value)
            if status > 1:
                raise FMICallException(self._calls["get"], status)
        except FMICallException as error:
            label = STATUS_NAMES[error.status] if 0 <= error.status < len(STATUS_NAMES) else str(error.status)
            raise ControllerError(f"{self.binding.origin}: {error.function} failed ({label}) at t = {t:.9g} s"
                                  f"{self._last_log()}") from None
        scale, offset = self._duty_map
        return (self._out_value[0] - offset) / scale

    def describe(self) -> dict:
        md = self.model_description
        return {"type": "controller FMU", "name": self.name, "fmu": str(self.binding.fmu_path),
                "binding_file": str(self.binding.source) if self.binding.source else None,
                "model_name": md.modelName, "guid": md.guid, "description": md.description,
                "sample_period_s": self.sample_period, "duty_limits": list(self.duty_limits),
                "roles": {r: {"variable": m.variable, "scale": m.scale, "offset": m.offset}
                          for r, m in self.binding.roles.items()},
                "parameters": dict(self.binding.parameters)}

    def close(self) -> None:
        if self._fmu is not None:
            fmu, self._fmu = self._fmu, None
            try:
                if self._initialized:
                    fmu.terminate()
            except Exception:
                pass
            try:
                fmu.freeInstance()
            except Exception:
                pass
        if getattr(self, "_log_handle", None):
            release(self._log_handle)
        if getattr(self, "_unzipdir", None):
            shutil.rmtree(self._unzipdir, ignore_errors=True)
            self._unzipdir = None

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


class FmuController3(FmuController):
    """An FMI 3.0 co-simulation controller FMU with the controller protocol of :mod:`controllers.base`."""

    _calls = {"step": "fmi3DoStep", "set": "fmi3SetFloat64", "get": "fmi3GetFloat64", "reset": "fmi3Reset",
              "instantiate": "fmi3InstantiateCoSimulation"}

    def _make_callbacks(self):
        self._log_handle = None  # FMI 3.0 logging needs no proxy
        log = self.log

        def on_message(environment, status, category, message) -> None:
            try:
                label = STATUS_NAMES[status] if 0 <= status < len(STATUS_NAMES) else str(status)
                log.append((label, message.decode("utf-8", "replace") if message else ""))
            except Exception:  # never let an exception cross the C boundary
                pass

        return on_message

    def _instantiate(self, md) -> None:
        refusal = clock_refusal(md, self.binding.origin)
        if refusal:
            raise ConfigError(refusal)
        self._fmu = FMU3Slave(guid=md.guid, unzipDirectory=self._unzipdir,
                              modelIdentifier=md.coSimulation.modelIdentifier, instanceName="controller")
        self._fmu.instantiate(loggingOn=True, eventModeUsed=False, earlyReturnAllowed=False,
                              logMessage=self._callbacks)
        dll = self._fmu.dll
        set_float, get_float = dll.fmi3SetFloat64, dll.fmi3GetFloat64
        # the calls of FmuController.step, with FMI 2.0's signatures (FMI 3.0 adds the value count)
        self._set_real = lambda instance, vr, n, values: set_float(instance, vr, n, values, n)
        self._get_real = lambda instance, vr, n, values: get_float(instance, vr, n, values, n)
        self._do_step = Fmi3DoStep(self._fmu, self.binding.origin, self._last_log, ControllerError)

    def _initialize(self, start_time: float) -> None:
        fmu = self._fmu
        apply_parameters(fmu, self._parameters)  # FMI 3.0: parameters are set while instantiated
        fmu.enterInitializationMode(startTime=start_time)
        fmu.exitInitializationMode()
        self._initialized = True
        self.time = start_time


_MEASUREMENT_FIELDS = {"reference": "reference", "measured_output_voltage": "output_voltage",
                       "measured_inductor_current": "inductor_current", "measured_load_current": "load_current",
                       "input_voltage": "input_voltage"}


def open_controller(text: str, name: str | None = None) -> FmuController:
    """The adapter for what ``--controller`` names: a controller FMU or a controller-binding file."""
    binding = controller_binding(text)
    return FmuController(binding, name=name)
