"""Plant FMUs stepped by fmpy in this process: one plant interface, one small class per FMI interface (FMI 2.0
here, FMI 3.0 in :mod:`cosim.fmi.plant_fmi3`; :func:`cosim.fmi.plant.open_plant` picks by the archive's
fmiVersion, and runs them in a child process instead when asked, :mod:`cosim.fmi.isolation`).

* :class:`CoSimulationPlant` -- the FMU's own solver through ``fmi2DoStep`` (fmpy's
  ``FMU2Slave``), steps subdivided to the binding's ``max_step``;
* :class:`ModelExchangePlant` -- the FMU's equations integrated by fmpy's CVode (``FMU2Model``),
  with time events (e.g. PWM edges) and state events (e.g. the diode blocking).

Both inherit :class:`FmuPlant`, the plumbing they share: the archive checks, the roles resolved
to value references (:func:`cosim.fmi.binding.resolve_roles`), the value buffers, the log, the
life cycle and the FMU state. :func:`cosim.fmi.isolation.open_in_process` picks the class for an
interface. The master sees only the methods of :class:`FmuPlant`.

The hot path (set inputs, step, get outputs) calls the C functions that fmpy loaded with their
prototypes, on value-reference and value buffers allocated once, so a macro step allocates no
Python objects beyond what ctypes needs.
"""

from __future__ import annotations

import math
import shutil
import sys
from collections import deque
from ctypes import c_double, c_uint
from dataclasses import replace
from typing import Mapping, Sequence

import fmpy
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import FMU2Model, FMU2Slave, fmi2True

from cosim.base.errors import ConfigError, PlantError
from cosim.fmi.archive import CheckedFmu
from cosim.fmi.binding import (
    INPUT_ROLES,
    OUTPUT_ROLES,
    BindingMismatch,
    PlantBinding,
    apply_parameters,
    is_float,
    resolve_parameters,
    resolve_roles,
)
from cosim.fmi.communication import CommunicationStep, communication_step, grid_index
from cosim.fmi.fmu_log import STATUS_NAMES, callbacks_for, release

FATAL_STATUS = 4
FATAL_REFUSAL = "the FMU reported fmi2Fatal earlier and cannot be used again (FMI 2.0 forbids any further call)"
_ABANDONED_AFTER_FATAL: list = []  # FMU objects that reported fmi2Fatal; never called or unloaded again
CO_SIMULATION = "co-simulation"
MODEL_EXCHANGE = "model-exchange"
INTERFACE_ALIASES = {"cs": CO_SIMULATION, "co-simulation": CO_SIMULATION,
                     "me": MODEL_EXCHANGE, "model-exchange": MODEL_EXCHANGE}


def normalise_interface(name: str | None) -> str | None:
    if name is None:
        return None
    try:
        return INTERFACE_ALIASES[name.lower()]
    except KeyError:
        raise ConfigError(f"interface {name!r} is unknown: expected 'co-simulation' (cs) or 'model-exchange' (me)") from None


def choose_interface(checked: CheckedFmu, wanted: str | None, origin: str) -> str:
    """The interface to use: ``wanted`` if the FMU offers it here, else co-simulation if offered."""
    if wanted is None:
        return CO_SIMULATION if CO_SIMULATION in checked.interfaces else checked.interfaces[0]
    if wanted not in checked.interfaces:
        raise ConfigError(f"{origin}: interface {wanted!r} is not available for this platform "
                          f"(the FMU offers: {', '.join(checked.interfaces)})")
    return wanted


def plant_signals(binding: PlantBinding, model_description) -> tuple[tuple[str, ...], tuple[str, ...], dict[str, bool]]:
    """The bound input roles and output roles (in the workbench's order) and, per input role,
    whether setting it can change a bound output at the same instant (feedthrough).

    Feedthrough is read from the ModelStructure dependencies; an output without declared
    dependencies depends on everything. The master re-reads outputs after an input change only if so.
    """
    inputs = tuple(r for r in INPUT_ROLES if binding.has(r))
    outputs = tuple(r for r in OUTPUT_ROLES if binding.has(r))
    dependencies = {u.variable.name: u.dependencies for u in model_description.outputs}
    output_variables = [binding.roles[r].variable for r in outputs]
    feedthrough = {}
    for role in inputs:
        name = binding.roles[role].variable
        feedthrough[role] = any(dependencies.get(o) is None or any(d.name == name for d in dependencies[o])
                                for o in output_variables)
    return inputs, outputs, feedthrough


class FmuPlant:
    """An instantiated plant FMU with the workbench's roles resolved to value references.

    Life cycle: :meth:`initialize` (resets first if the instance ran before), then
    :meth:`set_inputs` / :meth:`advance_to` / :meth:`outputs` in any order, :meth:`close` at the
    end (or use it as a context manager). Inputs and outputs are lists in the order of
    :attr:`input_roles` / :attr:`output_roles`, in workbench units.
    """

    interface: str  # CO_SIMULATION or MODEL_EXCHANGE
    _fmu_class: type

    def __init__(self, binding: PlantBinding, checked: CheckedFmu, relative_tolerance: float = 1e-8,
                 instance_name: str = "plant", unzip_dir: str | None = None):
        self.binding = binding
        self.model_description = md = checked.model_description
        self.relative_tolerance = relative_tolerance
        self.time = 0.0
        self.log: deque[tuple[str, str, str]] = deque(maxlen=500)  # (status, category, message)
        try:
            roles = resolve_roles(binding, md)
            self._parameters = resolve_parameters(binding.parameters, md, binding.fmu_path.name)
        except BindingMismatch as error:
            raise ConfigError(f"{binding.origin}: {error}") from None
        self.input_roles, self.output_roles, self.feedthrough = plant_signals(binding, md)
        inputs = [roles[r] for r in self.input_roles]
        outputs = [roles[r] for r in self.output_roles]
        self._in_vr = (c_uint * len(inputs))(*(r.value_reference for r in inputs))
        self._in_value = (c_double * len(inputs))()
        self._out_vr = (c_uint * len(outputs))(*(r.value_reference for r in outputs))
        self._out_value = (c_double * len(outputs))()
        self._in_scale = [r.scale for r in inputs]
        self._in_offset = [r.offset for r in inputs]
        self._out_identity = all(r.scale == 1.0 and r.offset == 0.0 for r in outputs)
        self._out_scale = [r.scale for r in outputs]
        self._out_offset = [r.offset for r in outputs]
        self._unzipdir = fmpy.extract(str(binding.fmu_path), unzipdir=unzip_dir)
        self._callbacks = self._make_callbacks()
        self._fmu = None
        self._initialized = False
        self._fatal = False
        try:
            self._instantiate(instance_name)
        except BaseException:
            self._remove_unzipdir()
            raise

    # ------------------------------------------------------------------ set-up
    def _make_callbacks(self):
        callbacks, self._log_handle = callbacks_for(lambda status, category, message:
                                                    self.log.append((status, category, message)))
        return callbacks

    def _model_identifier(self) -> str:
        raise NotImplementedError

    def _instantiate(self, instance_name: str) -> None:
        md = self.model_description
        self._fmu = self._fmu_class(guid=md.guid, unzipDirectory=self._unzipdir,
                                    modelIdentifier=self._model_identifier(), instanceName=instance_name)
        try:
            # logging on: an FMU may report why a call failed only then (pythonfmu, e.g., its exception)
            self._fmu.instantiate(callbacks=self._callbacks, loggingOn=True)
        except Exception:
            self._fmu.freeLibrary()
            self._fmu = None
            raise PlantError(f"{self.binding.origin}: fmi2Instantiate failed{self._last_log_suffix()}") from None
        dll = self._fmu.dll
        self._set_real = dll.fmi2SetReal
        self._get_real = dll.fmi2GetReal
        self._component = self._fmu.component

    @property
    def label(self) -> str:
        return self.binding.label

    @property
    def initialized(self) -> bool:
        """True between :meth:`initialize` and the next :meth:`reset`."""
        return self._initialized

    @property
    def communication(self) -> CommunicationStep:
        """How the master may step this plant (:mod:`cosim.fmi.communication`; model exchange: any step)."""
        return communication_step(self.binding, self.model_description, self.interface)

    def use_step(self, step: float | None) -> None:
        """Step by ``step`` [s] only, until told otherwise (None: from one instant to the next, however long): a
        fixed-step FMU's communication step for a run (model exchange has none)."""

    def _last_log_suffix(self) -> str:
        """``": <the FMU's last error, discard or warning message>"`` (on one line), or nothing."""
        for status, _, message in reversed(self.log):
            if status in ("error", "fatal", "discard", "warning"):
                return f": {' '.join(message.split())}"
        return ""

    def _fail(self, call: str, status: int | None = None, at: float | None = None) -> PlantError:
        when = self.time if at is None else at
        if status == FATAL_STATUS:
            self._fatal = True  # FMI 2.0: after fmi2Fatal no other function of the FMU may be called
        label = f" ({STATUS_NAMES[status]})" if status is not None and 0 <= status < len(STATUS_NAMES) else ""
        return PlantError(f"{self.binding.origin}: {call} failed{label} at t = {when:.9g} s{self._last_log_suffix()}")

    # ------------------------------------------------------------------ life cycle
    def initialize(self, inputs: Sequence[float], start_time: float = 0.0,
                   start_values: Mapping[str, float] | None = None) -> None:
        """Set parameters, start values and the first inputs, and leave initialization mode at
        ``start_time``; an instance that ran before is reset first, so one instance serves many runs."""
        if self._initialized:
            self.reset()
        self._refuse_if_fatal()
        try:
            extra = resolve_parameters(start_values or {}, self.model_description, self.binding.fmu_path.name)
        except BindingMismatch as error:
            raise ConfigError(f"{self.binding.origin}: {error}") from None
        try:
            self._initialization(start_time, self._parameters + extra, inputs)
        except FMICallException as error:
            # failing before the first step means the set-up was refused: a parameter, start value
            # or input the FMU does not accept (its log message names it) -- a configuration error
            failure = self._fail(error.function, error.status, at=start_time)
            if not self._fatal:  # back to instantiated (a refusal may leave it in initialisation mode): reusable
                try:
                    self._fmu.reset()
                except FMICallException:
                    pass
            raise ConfigError(str(failure)) from None
        self.time = start_time
        self._initialized = True
        self._after_initialization(start_time)

    def _initialization(self, start_time: float, parameters, inputs: Sequence[float]) -> None:
        """The FMI calls of :meth:`initialize`, from instantiated to initialised (FMI 3.0: cosim.fmi.plant_fmi3)."""
        fmu = self._fmu
        fmu.setupExperiment(startTime=start_time)
        apply_parameters(fmu, parameters)
        fmu.enterInitializationMode()
        self._write_inputs(inputs)
        fmu.exitInitializationMode()

    def _after_initialization(self, start_time: float) -> None:
        """Interface-specific start (model exchange: the solver)."""

    def replace_parameters(self, parameters: Mapping[str, float | int | bool | str]) -> None:
        """Replace the binding's parameters: they are set at the next :meth:`initialize`, so a
        sweep varies them run by run on one reused instance (never a reload per run). Checked
        like the binding's own (each names a variable of the FMU, with a value of its type).
        (:meth:`set_parameters` changes tunable parameters during a run.)"""
        binding = replace(self.binding, parameters=parameters)
        try:
            resolved = resolve_parameters(binding.parameters, self.model_description, binding.fmu_path.name)
        except BindingMismatch as error:
            raise ConfigError(f"{binding.origin}: {error}") from None
        self.binding, self._parameters = binding, resolved

    @property
    def fatal(self) -> bool:
        """True once the FMU has returned ``fmi2Fatal``: the standard allows no further call to it."""
        return self._fatal

    def _refuse_if_fatal(self) -> None:
        if self._fatal:
            raise PlantError(f"{self.binding.origin}: {FATAL_REFUSAL}")

    def reset(self) -> None:
        """Return to the instantiated state (fmi2Reset) so the same instance serves another run."""
        self._refuse_if_fatal()
        try:
            self._fmu.reset()
        except FMICallException as error:
            raise self._fail(error.function, error.status) from None
        self._initialized = False
        self.time = 0.0
        self.log.clear()

    def close(self) -> None:
        """Terminate, free the instance and delete the extracted files. Safe to call twice.

        After an ``fmi2Fatal`` status the standard forbids any further call, so the instance and
        its library are abandoned (not freed) rather than risking a crash inside the FMU.
        """
        if self._fmu is not None:
            fmu, self._fmu = self._fmu, None
            if self._fatal:
                _ABANDONED_AFTER_FATAL.append(fmu)  # keep it alive: its library must stay loaded
                self._remove_unzipdir()
                return
            if self._initialized:
                try:
                    fmu.terminate()
                except Exception:
                    pass  # already in an error state; freeing is what matters
            try:
                fmu.freeInstance()
            except Exception:
                pass
        self._remove_unzipdir()

    def _remove_unzipdir(self) -> None:
        if getattr(self, "_log_handle", None) and not self._fatal:
            release(self._log_handle)
        if getattr(self, "_unzipdir", None):
            shutil.rmtree(self._unzipdir, ignore_errors=True)
            self._unzipdir = None

    def __enter__(self) -> "FmuPlant":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):  # last resort; the master closes explicitly
        try:
            self.close()
        except Exception:
            pass

    # ------------------------------------------------------------------ signals
    def _write_inputs(self, values: Sequence[float]) -> None:
        buffer = self._in_value
        for i, value in enumerate(values):
            buffer[i] = self._in_scale[i] * value + self._in_offset[i]
        status = self._set_real(self._component, self._in_vr, len(buffer), buffer)
        if status > 1:
            raise FMICallException("fmi2SetReal", status)

    def set_inputs(self, values: Sequence[float]) -> None:
        """Set the input roles (order of :attr:`input_roles`, workbench units); held until the next call."""
        try:
            self._write_inputs(values)
        except FMICallException as error:
            raise self._fail(error.function, error.status) from None

    def outputs(self) -> list[float]:
        """Output roles (order of :attr:`output_roles`) in workbench units, as Python floats."""
        status = self._get_real(self._component, self._out_vr, len(self._out_value), self._out_value)
        if status > 1:
            raise self._fail("fmi2GetReal", status)
        values = self._out_value[:]
        if self._out_identity:
            return values
        return [(v - o) / k for v, o, k in zip(values, self._out_offset, self._out_scale)]

    def advance_to(self, t_next: float) -> None:
        """Advance the plant from :attr:`time` to ``t_next`` with the inputs held."""
        raise NotImplementedError

    # ------------------------------------------------------------------ tunable parameters
    @property
    def tunable_parameters(self) -> dict[str, int]:
        """Real parameters the FMU lets change during a run (``variability="tunable"``): name -> value reference."""
        return {v.name: v.valueReference for v in self.model_description.modelVariables
                if v.causality == "parameter" and v.variability == "tunable" and is_float(v)}

    def _write_parameters(self, values: Mapping[str, float]) -> None:
        tunable = self.tunable_parameters
        unknown = [name for name in values if name not in tunable]
        if unknown:
            raise ConfigError(f"{self.binding.origin}: {', '.join(map(repr, unknown))} is not a tunable Real parameter "
                              f"of {self.binding.fmu_path.name} (tunable: {', '.join(sorted(tunable)) or 'none'})")
        self._set_reals([tunable[name] for name in values], [float(v) for v in values.values()])

    def _set_reals(self, value_references: list[int], values: list[float]) -> None:
        self._fmu.setReal(value_references, values)

    def set_parameters(self, values: Mapping[str, float]) -> None:
        """Change tunable parameters (FMU names and units) between two steps of a run, e.g. a
        drifting capacitance; the FMU's states carry over (co-simulation: fmi2SetReal at the
        communication point; model exchange overrides this with an event)."""
        try:
            self._write_parameters(values)
        except FMICallException as error:
            raise self._fail(error.function, error.status) from None

    def trial_parameters(self, changes: Sequence[Mapping[str, float]]) -> tuple[int, str] | None:
        """Before a run: try each set of parameter values on the fresh instance, so the FMU's own
        checks refuse a bad value before the first step. Returns (position, the FMU's message) of
        the first refused set, or None; the instance is reset afterwards either way."""
        self._refuse_if_fatal()
        if self._initialized:
            self.reset()
        try:
            for position, values in enumerate(changes):
                try:
                    self._write_parameters(values)
                except FMICallException as error:
                    message = self._last_log_suffix().removeprefix(": ") or f"{error.function} failed"
                    return position, message
            return None
        finally:
            self._fmu.reset()
            self.log.clear()

    # ------------------------------------------------------------------ FMU state
    def get_state(self):
        """Snapshot of the FMU (fmi2GetFMUstate); free it with :meth:`free_state`."""
        return self._fmu.getFMUstate()

    def set_state(self, state, time: float) -> None:
        """Restore a snapshot taken at ``time``."""
        self._fmu.setFMUstate(state)
        self.time = time

    def free_state(self, state) -> None:
        self._fmu.freeFMUstate(state)


class CoSimulationPlant(FmuPlant):
    """The FMU's own solver: ``fmi2DoStep`` from one instant to the next (split at ``max_step``)."""

    interface = CO_SIMULATION
    _fmu_class = FMU2Slave
    _step_call = "fmi2DoStep"  # how messages name the step

    def _model_identifier(self) -> str:
        return self.model_description.coSimulation.modelIdentifier

    _fixed_step: float | None = None  # [s] the run's one communication step (use_step), None: any

    def _instantiate(self, instance_name: str) -> None:
        super()._instantiate(instance_name)
        self._do_step = self._fmu.dll.fmi2DoStep

    def use_step(self, step: float | None) -> None:
        self._fixed_step = step

    def advance_to(self, t_next: float) -> None:
        t0 = self.time
        if t_next <= t0:
            return
        if self._fixed_step is not None:
            self._advance_fixed(t0, t_next, self._fixed_step)
        elif not self.binding.max_step:  # the common case, kept lean: one call
            status = self._do_step(self._component, t0, t_next - t0, fmi2True)
            if status > 1:
                raise self._fail(self._step_call, status, at=t0)
        else:
            self._advance_in_pieces(t0, t_next, self.binding.max_step)
        self.time = t_next

    def _advance_fixed(self, t0: float, t_next: float, step: float) -> None:
        """From ``t0`` to ``t_next`` in steps of exactly ``step`` [s], each from a multiple of it (the master checked
        before the run that every instant lies on that grid: :func:`cosim.master.check_communication_step`)."""
        first, last = grid_index(t0, step), grid_index(t_next, step)
        if first is None or last is None:
            raise PlantError(f"{self.binding.origin}: cannot step from t = {t0:.9g} s to {t_next:.9g} s in whole "
                             f"communication steps of {step:.6g} s (the FMU's fixed step)")
        for i in range(last - first):
            status = self._do_step(self._component, (first + i) * step, step, fmi2True)
            if status > 1:
                raise self._fail(self._step_call, status, at=(first + i) * step)

    def _advance_in_pieces(self, t0: float, t_next: float, max_step: float) -> None:
        h = t_next - t0
        n = math.ceil(h / max_step * (1.0 - 1e-12)) if h > max_step else 1
        for i in range(n):
            start = t0 + h * i / n if i else t0
            end = t0 + h * (i + 1) / n if i + 1 < n else t_next
            status = self._do_step(self._component, start, end - start, fmi2True)
            if status > 1:
                raise self._fail(self._step_call, status, at=start)


class _NoInput:
    """fmpy's CVode wrapper re-applies inputs at root checks; the master holds them instead."""

    def apply(self, time, continuous=True, discrete=True, after_event=False):
        return None


class ModelExchangePlant(FmuPlant):
    """The FMU's equations integrated by fmpy's CVode, with time and state events."""

    interface = MODEL_EXCHANGE
    _fmu_class = FMU2Model
    _derivatives = "getDerivatives"  # fmpy's name for the derivatives call

    def __init__(self, binding: PlantBinding, checked: CheckedFmu, relative_tolerance: float = 1e-8,
                 instance_name: str = "plant", unzip_dir: str | None = None):
        self._solver = None
        self._inputs_changed = False
        self._next_event_time: float | None = None
        self._needs_completed_step = bool(checked.model_description.modelExchange.needsCompletedIntegratorStep)
        super().__init__(binding, checked, relative_tolerance, instance_name, unzip_dir)

    def _model_identifier(self) -> str:
        return self.model_description.modelExchange.modelIdentifier

    def _after_initialization(self, start_time: float) -> None:
        from fmpy.sundials import CVodeSolver

        fmu = self._fmu
        self._event_update()
        fmu.enterContinuousTimeMode()
        md = self.model_description
        self._solver = CVodeSolver(
            nx=md.numberOfContinuousStates,
            nz=md.numberOfEventIndicators,
            get_x=fmu.getContinuousStates,
            set_x=fmu.setContinuousStates,
            get_dx=getattr(fmu, self._derivatives),
            get_z=fmu.getEventIndicators,
            get_nominals=fmu.getNominalsOfContinuousStates,
            set_time=fmu.setTime,
            input=_NoInput(),
            startTime=start_time,
            maxStep=self.binding.max_step or float("inf"),
            relativeTolerance=self.relative_tolerance,
            maxNumSteps=1_000_000,
        )
        self._inputs_changed = False

    def reset(self) -> None:
        super().reset()
        self._solver = None

    def close(self) -> None:
        self._solver = None
        super().close()

    def set_inputs(self, values: Sequence[float]) -> None:
        super().set_inputs(values)
        self._inputs_changed = True  # inputs may change discrete states (e.g. the diode unblocks)

    def _event_update(self) -> None:
        fmu = self._fmu
        needed, terminate = True, False
        while needed and not terminate:
            needed, terminate, _, _, defined, next_time = fmu.newDiscreteStates()
        if terminate:
            raise PlantError(f"{self.binding.origin}: the FMU asked to terminate at t = {self.time:.9g} s"
                             f"{self._last_log_suffix()}")
        self._next_event_time = next_time if defined else None

    def _handle_event(self, time: float) -> None:
        fmu = self._fmu
        fmu.enterEventMode()
        self._event_update()
        fmu.enterContinuousTimeMode()
        self._solver.reset(time)

    def advance_to(self, t_next: float) -> None:
        if t_next <= self.time:
            return
        fmu, solver = self._fmu, self._solver
        t = self.time
        try:
            if self._inputs_changed:
                fmu.setTime(t)
                self._handle_event(t)
                self._inputs_changed = False
            while t < t_next:
                target = t_next
                time_event = False
                if self._next_event_time is not None and self._next_event_time <= t_next:
                    target, time_event = max(self._next_event_time, t), True
                if target - t <= 8 * sys.float_info.epsilon * max(abs(t), abs(target), 1e-300):
                    state_event, t_reached = False, target  # CVode cannot take so short a step
                else:
                    state_event, _, t_reached = solver.step(t, target)
                fmu.setTime(t_reached)
                step_event = False
                if self._needs_completed_step:
                    step_event, terminate = fmu.completedIntegratorStep()
                    if terminate:
                        raise PlantError(f"{self.binding.origin}: the FMU asked to terminate at t = {t_reached:.9g} s")
                reached_target = t_reached >= target - 1e-13 * max(1.0, abs(target))
                if state_event or step_event or (time_event and reached_target):
                    self._handle_event(t_reached)
                if reached_target and target == t_next:
                    break
                t = t_reached
        except FMICallException as error:
            raise self._fail(error.function, error.status, at=t) from None
        except RuntimeError as error:  # CVode failure
            raise PlantError(f"{self.binding.origin}: the model-exchange solver failed at t = {t:.9g} s ({error})") from None
        self.time = t_next

    def set_parameters(self, values: Mapping[str, float]) -> None:
        """Tunable parameters change in event mode (FMI 2.0): enter it, set, update the discrete
        states (e.g. the diode) and restart the solver from the same state."""
        fmu = self._fmu
        try:
            fmu.setTime(self.time)
            fmu.enterEventMode()
            self._write_parameters(values)
            self._event_update()
            fmu.enterContinuousTimeMode()
        except FMICallException as error:
            raise self._fail(error.function, error.status) from None
        self._solver.reset(self.time)

    def set_state(self, state, time: float) -> None:
        """Restore a snapshot taken at ``time``; the discrete part (the next PWM edge) is re-derived
        by an event update and the solver restarts there."""
        super().set_state(state, time)
        if self._solver is not None:
            self._fmu.setTime(time)
            self._handle_event(time)
            self._inputs_changed = False
