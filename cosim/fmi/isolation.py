"""Where a plant FMU runs: in this process (:func:`open_in_process`, the FMI 2.0 or 3.0 adapter), or in
a child process (:class:`IsolatedPlant`), so that an FMU that crashes (a segfault in foreign code) or
hangs (a step that exceeds its wall-time limit, :func:`step_time_limit`) ends the run with a one-line
error, the rows recorded up to the fault kept, instead of killing or blocking the workbench.

:class:`IsolatedPlant` offers the methods of :class:`cosim.fmi.plant_fmi2.FmuPlant`; a child process
(started with ``spawn``: nothing of the parent's threads or loaded libraries is inherited) holds
the real plant. Calls are batched: ``set_inputs`` and ``advance_to`` are queued and travel with the
next call that needs an answer (``outputs``, ``initialize``, ``reset``, the FMU state), so an
instant of the master's loop costs one round trip through a pipe. The parent decides where the
FMU is extracted and deletes that folder in every ending, the child's crash included.

Why not a library: the standard library's ``multiprocessing`` pipe is all this needs; a process
pool (concurrent.futures, dask) would add scheduling per call, and no fmpy facility runs an FMU
out of process.
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import signal
import tempfile
import time
from dataclasses import replace
from typing import Mapping, Sequence

from cosim.base.errors import ConfigError, FmuArchiveError, PlantError, WorkbenchError
from cosim.fmi.archive import CheckedFmu, check_fmu
from cosim.fmi.binding import PlantBinding, is_float
from cosim.fmi.communication import CommunicationStep, communication_step
from cosim.fmi.plant_fmi2 import (
    CO_SIMULATION,
    FATAL_REFUSAL,
    CoSimulationPlant,
    FmuPlant,
    ModelExchangePlant,
    choose_interface,
    plant_signals,
)

#: how long the child may take to start [s]
START_TIMEOUT = 60.0
#: a step's default wall-time limit: this much [s] ...
STEP_TIME_FLOOR = 30.0
#: ... plus this many wall seconds per simulated second of the step: an FMU may run 1000 times slower
#: than real time (the built-in plant steps 1 ms in ~4 us averaged, ~0.1 ms switched) and a loaded
#: machine may stall a process for seconds, but a 1 ms step that takes 30 s is hung
STEP_TIME_PER_SIMULATED_SECOND = 1000.0
#: how often [s] the parent looks at the plant process's resident memory (while it waits, and between calls)
MEMORY_CHECK_INTERVAL = 0.1
_ERRORS = {cls.__name__: cls for cls in (ConfigError, FmuArchiveError, PlantError, WorkbenchError)}


def isolation_possible() -> bool:
    """Whether this process may start the plant's child process: not a daemonic one (dask's default
    worker; the workbench's LocalCluster turns that off, cosim/design/cluster.py)."""
    return not multiprocessing.current_process().daemon


def step_time_limit(binding: PlantBinding, simulated: float) -> float:
    """The wall-time limit [s] for the plant process to step ``simulated`` seconds of simulated time:
    the binding's ``step_timeout`` if set, else :data:`STEP_TIME_FLOOR` + :data:`STEP_TIME_PER_SIMULATED_SECOND`
    x ``simulated``."""
    if binding.step_timeout is not None:
        return binding.step_timeout
    return STEP_TIME_FLOOR + STEP_TIME_PER_SIMULATED_SECOND * max(simulated, 0.0)


def memory_limit_bytes(binding: PlantBinding) -> int | None:
    """The plant process's resident-memory limit [bytes]: the binding's ``memory_limit`` (MB) if set, else half
    the machine's physical memory (one runaway FMU must not take the machine); None where unknown."""
    if binding.memory_limit is not None:
        return int(binding.memory_limit * 1e6)
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2
    except (ValueError, OSError, AttributeError):
        return None


def resident_bytes(pid: int) -> int | None:
    """A process's resident memory [bytes] (Linux /proc), or None where it cannot be read."""
    try:
        with open(f"/proc/{pid}/statm", encoding="ascii") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def open_in_process(binding: PlantBinding, checked: CheckedFmu, interface: str, relative_tolerance: float = 1e-8,
                    instance_name: str = "plant", unzip_dir: str | None = None) -> FmuPlant:
    """The adapter for the checked FMU's FMI version and the chosen interface, in this process."""
    if checked.fmi_major == 3:  # the FMI 3.0 adapters, beneath the same interface
        from cosim.fmi.plant_fmi3 import CoSimulationPlant3, ModelExchangePlant3

        cls = CoSimulationPlant3 if interface == CO_SIMULATION else ModelExchangePlant3
    else:
        cls = CoSimulationPlant if interface == CO_SIMULATION else ModelExchangePlant
    return cls(binding, checked, relative_tolerance=relative_tolerance, instance_name=instance_name,
               unzip_dir=unzip_dir)


def _serve(connection, binding: PlantBinding, interface: str, relative_tolerance: float, instance_name: str,
           unzip_dir: str) -> None:
    """The child: open the plant and answer the parent's requests until it says close -- or goes
    away (its end of the pipe closes): then the child closes the FMU and ends quietly."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    plant = None
    try:
        try:
            checked = check_fmu(binding.fmu_path)
            plant = open_in_process(binding, checked, choose_interface(checked, interface, binding.origin),
                                    relative_tolerance, instance_name, unzip_dir)
            connection.send(("ok", None))
        except WorkbenchError as error:  # opening failed
            connection.send(("error", type(error).__name__, str(error), False))
            return
        states: dict[int, object] = {}
        while True:
            request = connection.recv()
            if request[0] == "close":
                break
            try:
                connection.send(("ok", _answer_request(plant, states, request)))
            except WorkbenchError as error:
                connection.send(("error", type(error).__name__, str(error), plant.fatal))
    except (EOFError, OSError):  # the parent went away (it ended, or it was terminated)
        pass
    except Exception as error:  # a bug here, not the FMU's: report it rather than vanish
        try:
            connection.send(("error", "PlantError", f"{type(error).__name__}: {error}", False))
        except OSError:
            pass
    finally:
        if plant is not None:
            plant.close()
        connection.close()


def _answer_request(plant, states: dict, request: tuple):
    kind = request[0]
    if kind == "ops":
        result = None
        for op in request[1]:
            if op[0] == "set":
                plant.set_inputs(op[1])
            elif op[0] == "advance":
                plant.advance_to(op[1])
            elif op[0] == "parameters":
                plant.set_parameters(op[1])
            else:
                result = plant.outputs()
        return result
    if kind == "initialize":
        return plant.initialize(request[1], request[2], request[3])
    if kind == "reset":
        return plant.reset()
    if kind == "use_step":
        return plant.use_step(request[1])
    if kind == "replace_parameters":
        return plant.replace_parameters(request[1])
    if kind == "trial_parameters":
        return plant.trial_parameters(request[1])
    if kind == "get_state":
        handle = len(states) + 1
        states[handle] = plant.get_state()
        return handle
    if kind == "set_state":
        return plant.set_state(states[request[1]], request[2])
    if kind == "free_state":
        return plant.free_state(states.pop(request[1]))
    raise PlantError(f"unknown request {kind!r} to the plant process")


class IsolatedPlant:
    """A plant FMU in a child process, with the interface of :class:`cosim.fmi.plant_fmi2.FmuPlant`."""

    def __init__(self, binding: PlantBinding, checked: CheckedFmu, interface: str, relative_tolerance: float = 1e-8,
                 instance_name: str = "plant"):
        self.binding = binding
        self.model_description = checked.model_description
        self.interface = interface
        self.relative_tolerance = relative_tolerance
        self.input_roles, self.output_roles, self.feedthrough = plant_signals(binding, checked.model_description)
        self.time = 0.0
        self._child_time = 0.0  # where the plant process has stepped to (self.time runs ahead of the queue)
        self._memory_limit = memory_limit_bytes(binding)
        self._next_memory_check = 0.0
        self._initialized = False
        self._fatal = False  # fmi2Fatal, or the process died
        self._crash: str | None = None  # how the process died
        self._queue: list[tuple] = []
        self._unzip_dir = tempfile.mkdtemp(prefix="buck-cosim-fmu-")
        context = multiprocessing.get_context("spawn")
        self._connection, child = context.Pipe()
        self._process = context.Process(target=_serve, name=f"plant FMU {binding.fmu_path.name}", daemon=True,
                                        args=(child, binding, interface, relative_tolerance, instance_name,
                                              self._unzip_dir))
        try:
            self._process.start()
            child.close()
            if not self._connection.poll(START_TIMEOUT):
                raise PlantError(f"{binding.origin}: the plant process did not start within {START_TIMEOUT:g} s")
            self._answer("opening the FMU", START_TIMEOUT)
        except BaseException:
            self._stop()
            raise

    # ------------------------------------------------------------------ the pipe
    def _answer(self, doing: str, limit: float, steps: tuple[float, float] | None = None):
        """The child's reply, waiting at most ``limit`` seconds (``steps``: the simulated interval the
        request steps, for the message); a child that does not answer in time, or that grows past its
        memory limit meanwhile, is stopped."""
        try:
            deadline = time.monotonic() + limit
            while not self._connection.poll(max(0.0, min(deadline - time.monotonic(), MEMORY_CHECK_INTERVAL))):
                self._check_memory(doing)
                if time.monotonic() >= deadline:
                    raise self._hung(doing, limit, steps)
            reply = self._connection.recv()
        except (EOFError, OSError):
            raise self._crashed(doing) from None
        if time.monotonic() >= self._next_memory_check:
            self._check_memory(doing)
        if reply[0] == "ok":
            return reply[1]
        _, name, message, fatal = reply
        self._fatal = self._fatal or fatal
        raise _ERRORS.get(name, PlantError)(message)

    def _crashed(self, doing: str) -> PlantError:
        self._process.join(timeout=5)
        code = self._process.exitcode
        how = f"signal {signal.Signals(-code).name}" if code is not None and code < 0 else f"exit code {code}"
        if code == -signal.SIGKILL:
            how += ": killed from outside, e.g. by the kernel's out-of-memory killer"
        self._fatal, self._crash = True, how
        return PlantError(f"{self.binding.origin}: the FMU crashed the plant process ({how}) while {doing} "
                          f"at t = {self.time:.9g} s")

    def _check_memory(self, doing: str) -> None:
        self._next_memory_check = time.monotonic() + MEMORY_CHECK_INTERVAL
        if self._memory_limit is None or self._process is None:
            return
        used = resident_bytes(self._process.pid)
        if used is not None and used > self._memory_limit:
            self._kill()
            self._fatal, self._crash = True, f"stopped at {used / 1e6:.0f} MB, above its memory limit"
            raise PlantError(f"{self.binding.origin}: the FMU {self.binding.fmu_path.name}'s process used "
                             f"{used / 1e6:.0f} MB, above the memory limit of {self._memory_limit / 1e6:.0f} MB "
                             f"(memory_limit), while {doing} at t = {self.time:.9g} s; its process was stopped")

    def _kill(self) -> None:
        process = self._process
        if process is not None and process.is_alive():
            process.kill()
            process.join(timeout=5)

    def _hung(self, doing: str, limit: float, steps: tuple[float, float] | None) -> PlantError:
        """Stop a child that exceeded its wall-time limit: a hang is a fault like a crash."""
        self._kill()
        what = (f"stepping from t = {steps[0]:.9g} s to {steps[1]:.9g} s" if steps is not None and steps[1] > steps[0]
                else f"{doing} at t = {self._child_time:.9g} s")
        self._fatal, self._crash = True, f"stopped after {limit:g} s without an answer"
        return PlantError(f"{self.binding.origin}: the FMU {self.binding.fmu_path.name} did not finish {what} within "
                          f"the step time limit of {limit:g} s (step_timeout); its process was stopped")

    def _setup_limit(self) -> float:
        return max(START_TIMEOUT, step_time_limit(self.binding, 0.0))

    def _call(self, doing: str, *request):
        self._flush_into(None)
        try:
            self._connection.send(request)
        except (BrokenPipeError, OSError):
            raise self._crashed(doing) from None
        return self._answer(doing, self._setup_limit())

    def _flush_into(self, final: tuple | None):
        ops, self._queue = self._queue, []
        if final is not None:
            ops.append(final)
        if not ops:
            return None
        start = self._child_time
        end = max([op[1] for op in ops if op[0] == "advance"], default=start)
        try:
            self._connection.send(("ops", ops))
        except (BrokenPipeError, OSError):
            raise self._crashed("stepping") from None
        result = self._answer("stepping", step_time_limit(self.binding, end - start), (start, end))
        self._child_time = end
        return result

    # ------------------------------------------------------------------ the plant interface
    @property
    def label(self) -> str:
        return self.binding.label

    @property
    def initialized(self) -> bool:
        return self._initialized

    @property
    def fatal(self) -> bool:
        return self._fatal

    def _refuse_if_dead(self) -> None:
        if self._crash:
            raise PlantError(f"{self.binding.origin}: the FMU crashed its process earlier ({self._crash}) and cannot "
                             "be used again")
        if self._fatal:
            raise PlantError(f"{self.binding.origin}: {FATAL_REFUSAL}")

    def initialize(self, inputs: Sequence[float], start_time: float = 0.0,
                   start_values: Mapping[str, float] | None = None) -> None:
        self._refuse_if_dead()
        self._queue.clear()
        self._call("initialising", "initialize", list(inputs), start_time, dict(start_values or {}))
        self.time = self._child_time = start_time
        self._initialized = True

    def reset(self) -> None:
        self._refuse_if_dead()
        self._queue.clear()
        self._call("resetting", "reset")
        self._initialized = False
        self.time = self._child_time = 0.0

    @property
    def communication(self) -> CommunicationStep:
        """As :attr:`cosim.fmi.plant_fmi2.FmuPlant.communication` (read off the binding and model description)."""
        return communication_step(self.binding, self.model_description, self.interface)

    def use_step(self, step: float | None) -> None:
        self._refuse_if_dead()
        self._queue.clear()  # a run starts here: nothing of an earlier, interrupted one is sent under the new step
        self._call("setting the communication step", "use_step", step)

    def set_inputs(self, values: Sequence[float]) -> None:
        self._queue.append(("set", list(values)))

    def advance_to(self, t_next: float) -> None:
        if t_next > self.time:
            self._queue.append(("advance", t_next))
            self.time = t_next

    def outputs(self) -> list[float]:
        return self._flush_into(("outputs",))

    @property
    def tunable_parameters(self) -> dict[str, int]:
        """As :attr:`cosim.fmi.plant_fmi2.FmuPlant.tunable_parameters` (read off the model description)."""
        return {v.name: v.valueReference for v in self.model_description.modelVariables
                if v.causality == "parameter" and v.variability == "tunable" and is_float(v)}

    def set_parameters(self, values: Mapping[str, float]) -> None:
        """As :meth:`cosim.fmi.plant_fmi2.FmuPlant.set_parameters`, in order with the queued steps."""
        self._queue.append(("parameters", dict(values)))

    def replace_parameters(self, parameters: Mapping[str, float | int | bool | str]) -> None:
        """As :meth:`cosim.fmi.plant_fmi2.FmuPlant.replace_parameters`, in the plant process."""
        self._refuse_if_dead()
        self._call("replacing the parameters", "replace_parameters", dict(parameters))
        self.binding = replace(self.binding, parameters=dict(parameters))

    def trial_parameters(self, changes: Sequence[Mapping[str, float]]):
        """As :meth:`cosim.fmi.plant_fmi2.FmuPlant.trial_parameters`, in the plant process."""
        self._refuse_if_dead()
        self._queue.clear()
        result = self._call("trying the parameter events", "trial_parameters", [dict(c) for c in changes])
        self._initialized = False
        return None if result is None else tuple(result)

    def get_state(self):
        return self._call("saving the FMU state", "get_state")

    def set_state(self, state, time: float) -> None:
        self._call("restoring the FMU state", "set_state", state, time)
        self.time = self._child_time = time

    def free_state(self, state) -> None:
        self._call("freeing the FMU state", "free_state", state)

    def close(self) -> None:
        """Ask the child to close the FMU, then stop it and delete the extracted files (every ending)."""
        if self._process is not None and self._process.is_alive() and not self._fatal:
            try:
                self._queue.clear()
                self._connection.send(("close",))
            except (BrokenPipeError, OSError):
                pass
        self._stop()

    def _stop(self) -> None:
        process, self._process = self._process, None
        if process is not None and process.pid is not None:  # started (a failed start leaves nothing to join)
            process.join(timeout=10)
            if process.is_alive():
                process.kill()
                process.join(timeout=5)
        self._connection.close()
        if self._unzip_dir:
            shutil.rmtree(self._unzip_dir, ignore_errors=True)
            self._unzip_dir = None

    def __enter__(self) -> "IsolatedPlant":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

