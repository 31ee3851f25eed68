"""FMI 3.0 plant FMUs stepped by fmpy (``FMU3Slave``, ``FMU3Model``), beneath the plant interface of
:class:`cosim.fmi.plant_fmi2.FmuPlant`: the master sees the same methods for either FMI version.

Each class here is its FMI 2.0 sibling with the FMI calls replaced (:func:`cosim.fmi.isolation.open_in_process`
picks them by the archive's fmiVersion); the roles, scales, checks, buffers, life cycle and the model-
exchange event loop are shared. What FMI 3.0 changes:

* variables are typed by size: signal roles need ``Float64`` scalars (``fmi3Get/SetFloat64`` with the
  value count FMI 3.0 adds for arrays); parameters take any scalar type (:mod:`cosim.fmi.binding`);
* the log callback has no variable arguments: each instance gets its own Python callback (no logger proxy);
* initialisation has no ``setupExperiment``: the start time goes with ``fmi3EnterInitializationMode``;
* ``fmi3DoStep`` reports three flags. The workbench instantiates co-simulation FMUs without event mode and
  without early return (an FMU then handles its internal events itself), so

  - ``terminateSimulation`` ends the run with a :class:`PlantError` naming the time;
  - ``earlyReturn`` with progress (``lastSuccessfulTime`` inside the step) is handled: the step continues
    from there to the communication point; an early return without progress is refused;
  - ``eventHandlingNeeded`` is refused (an FMU must not ask for event mode it was not given);
* model exchange: ``fmi3UpdateDiscreteStates`` instead of ``fmi2NewDiscreteStates`` (same results, same
  order), ``fmi3GetContinuousStateDerivatives`` instead of ``fmi2GetDerivatives``.

Clocks (FMI 3.0's synchronous clocks) need event mode; the workbench's roles carry values, not clock
ticks, so a plant that declares clocks is refused when it is opened.
"""

from __future__ import annotations

from ctypes import byref, c_bool, c_double
from typing import Callable, Sequence

from fmpy.fmi1 import FMICallException
from fmpy.fmi3 import FMU3Model, FMU3Slave

from cosim.base.errors import ConfigError, PlantError
from cosim.fmi.binding import apply_parameters
from cosim.fmi.fmu_log import STATUS_NAMES
from cosim.fmi.plant_fmi2 import CoSimulationPlant, FmuPlant, ModelExchangePlant


def clock_refusal(model_description, origin: str) -> str | None:
    """The one-line refusal of an FMI 3.0 FMU with clocks (which need event mode), or None."""
    clocks = [v.name for v in model_description.modelVariables if v.type == "Clock"]
    if not clocks:
        return None
    return (f"{origin}: the FMU declares clocks ({', '.join(clocks[:3])}{', ...' if len(clocks) > 3 else ''}); "
            "FMI 3.0 clocks need event mode, which the workbench does not drive for plants")


class _Fmi3Plant(FmuPlant):
    """The FMI 3.0 calls shared by both interfaces (mixed into the FMI 2.0 classes' logic)."""

    def _make_callbacks(self):
        self._log_handle = None  # FMI 3.0 logging needs no proxy and no handle
        log = self.log

        def on_message(environment, status, category, message) -> None:
            try:
                label = STATUS_NAMES[status] if 0 <= status < len(STATUS_NAMES) else str(status)
                log.append((label, category.decode("utf-8", "replace") if category else "",
                            message.decode("utf-8", "replace") if message else ""))
            except Exception:  # never let an exception cross the C boundary
                pass

        return on_message

    def _instantiate_fmu(self, fmu) -> None:
        raise NotImplementedError

    def _instantiate(self, instance_name: str) -> None:
        md = self.model_description
        refusal = clock_refusal(md, self.binding.origin)
        if refusal:
            raise ConfigError(refusal)
        self._fmu = self._fmu_class(guid=md.guid, unzipDirectory=self._unzipdir,
                                    modelIdentifier=self._model_identifier(), instanceName=instance_name)
        try:
            self._instantiate_fmu(self._fmu)
        except Exception:
            self._fmu.freeLibrary()
            self._fmu = None
            kind = "CoSimulation" if self._fmu_class is FMU3Slave else "ModelExchange"
            raise PlantError(f"{self.binding.origin}: fmi3Instantiate{kind} failed{self._last_log_suffix()}") from None
        dll = self._fmu.dll
        self._set_real = dll.fmi3SetFloat64
        self._get_real = dll.fmi3GetFloat64
        self._component = self._fmu.component

    def _initialization(self, start_time: float, parameters, inputs: Sequence[float]) -> None:
        fmu = self._fmu
        apply_parameters(fmu, parameters)  # FMI 3.0: parameters and start values are set while instantiated
        fmu.enterInitializationMode(startTime=start_time)
        self._write_inputs(inputs)
        fmu.exitInitializationMode()

    # ------------------------------------------------------------------ signals (the hot path)
    def _write_inputs(self, values: Sequence[float]) -> None:
        buffer = self._in_value
        for i, value in enumerate(values):
            buffer[i] = self._in_scale[i] * value + self._in_offset[i]
        n = len(buffer)
        status = self._set_real(self._component, self._in_vr, n, buffer, n)
        if status > 1:
            raise FMICallException("fmi3SetFloat64", status)

    def outputs(self) -> list[float]:
        n = len(self._out_value)
        status = self._get_real(self._component, self._out_vr, n, self._out_value, n)
        if status > 1:
            raise self._fail("fmi3GetFloat64", status)
        values = self._out_value[:]
        if self._out_identity:
            return values
        return [(v - o) / k for v, o, k in zip(values, self._out_offset, self._out_scale)]

    def _set_reals(self, value_references: list[int], values: list[float]) -> None:
        self._fmu.setFloat64(value_references, values)

    # ------------------------------------------------------------------ FMU state
    def get_state(self):
        return self._fmu.getFMUState()

    def set_state(self, state, time: float) -> None:
        self._fmu.setFMUState(state)
        self.time = time

    def free_state(self, state) -> None:
        self._fmu.freeFMUState(state)


class Fmi3DoStep:
    """``fmi3DoStep`` with the shape of the FMI 2.0 call the adapters' stepping loops make --
    ``(instance, t, h, noSetFMUStatePriorToCurrentPoint) -> status`` -- and its three flags handled for an
    instance made without event mode and without early return: ``terminateSimulation`` and
    ``eventHandlingNeeded`` raise ``error`` (a one-line message naming the time), an early return that
    progressed continues from ``lastSuccessfulTime``, one that did not is refused."""

    def __init__(self, fmu, origin: str, last_log: Callable[[], str], error: type = PlantError):
        self._call = fmu.dll.fmi3DoStep
        self._origin, self._last_log, self._error = origin, last_log, error
        self._event, self._terminate, self._early = c_bool(), c_bool(), c_bool()
        self._last = c_double()
        self._flags = (byref(self._event), byref(self._terminate), byref(self._early), byref(self._last))

    def __call__(self, instance, t0: float, h: float, no_set_prior=True) -> int:
        t, end = t0, t0 + h
        while True:
            self._event.value = self._terminate.value = self._early.value = False  # not every FMU writes them
            self._last.value = end
            status = self._call(instance, t, end - t, True, *self._flags)
            if status > 1:
                return status
            if self._terminate.value:
                raise self._error(f"{self._origin}: the FMU asked to terminate the simulation (fmi3DoStep's "
                                  f"terminateSimulation) at t = {self._last.value:.9g} s{self._last_log()}")
            if self._event.value:
                raise self._error(f"{self._origin}: fmi3DoStep asked for event handling (eventHandlingNeeded) at "
                                  f"t = {self._last.value:.9g} s, but the FMU was instantiated without event mode "
                                  "(eventModeUsed = false); it must handle its events itself")
            if not self._early.value:
                return status
            last = self._last.value
            if not t < last < end:
                raise self._error(f"{self._origin}: fmi3DoStep returned early (earlyReturn) at lastSuccessfulTime = "
                                  f"{last:.9g} s without progress from t = {t:.9g} s towards {end:.9g} s, although "
                                  "early return was not allowed")
            t = last  # an early return that progressed: continue from where it stopped


class CoSimulationPlant3(_Fmi3Plant, CoSimulationPlant):
    """An FMI 3.0 co-simulation plant: ``fmi3DoStep`` from one instant to the next (split at ``max_step``)."""

    _fmu_class = FMU3Slave
    _step_call = "fmi3DoStep"

    def _instantiate_fmu(self, fmu) -> None:
        fmu.instantiate(loggingOn=True, eventModeUsed=False, earlyReturnAllowed=False, logMessage=self._callbacks)

    def _instantiate(self, instance_name: str) -> None:
        _Fmi3Plant._instantiate(self, instance_name)
        # the FMI 2.0 stepping loop calls _do_step(instance, t, h, noSetFMUStatePrior): FMI 3.0's, flags handled
        self._do_step = Fmi3DoStep(self._fmu, self.binding.origin, self._last_log_suffix)


class ModelExchangePlant3(_Fmi3Plant, ModelExchangePlant):
    """An FMI 3.0 model-exchange plant: its equations integrated by fmpy's CVode, with time and state events."""

    _fmu_class = FMU3Model
    _derivatives = "getContinuousStateDerivatives"

    def _instantiate_fmu(self, fmu) -> None:
        fmu.instantiate(loggingOn=True, logMessage=self._callbacks)

    def _event_update(self) -> None:
        fmu = self._fmu
        needed, terminate = True, False
        while needed and not terminate:
            needed, terminate, _, _, defined, next_time = fmu.updateDiscreteStates()
        if terminate:
            raise PlantError(f"{self.binding.origin}: the FMU asked to terminate at t = {self.time:.9g} s"
                             f"{self._last_log_suffix()}")
        self._next_event_time = next_time if defined else None


__all__ = ["CoSimulationPlant3", "Fmi3DoStep", "ModelExchangePlant3", "clock_refusal"]
