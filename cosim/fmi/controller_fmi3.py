"""FMI 3.0 controller FMUs beneath the controller protocol of :class:`cosim.fmi.controller.FmuController`.

``FmuController(binding)`` of an FMI 3.0 archive makes an :class:`FmuController3`: the same sampling, roles,
scales and checks, with fmpy's ``FMU3Slave`` and the FMI 3.0 calls -- ``fmi3Get/SetFloat64`` (with the
value count FMI 3.0 adds), ``fmi3EnterInitializationMode`` with the start time, ``fmi3DoStep`` with its
flags handled as for plants (:class:`cosim.fmi.plant_fmi3.Fmi3DoStep`). A controller FMU is instantiated
without event mode: it samples on its own time base inside ``fmi3DoStep``, as an FMI 2.0 one does, and one
that declares FMI 3.0 clocks (which need event mode) is refused with one line.
"""

from __future__ import annotations

from fmpy.fmi3 import FMU3Slave

from cosim.base.errors import ConfigError, ControllerError
from cosim.fmi.binding import apply_parameters
from cosim.fmi.controller import FmuController
from cosim.fmi.fmu_log import STATUS_NAMES
from cosim.fmi.plant_fmi3 import Fmi3DoStep, clock_refusal


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
