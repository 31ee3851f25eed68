"""The co-simulation master: a multi-rate loop of plant steps, sampled controllers and a recorder.

The plant runs on the merged grid of :mod:`cosim.timeline` (controller samples, recording points
and plant events). Between instants the FMU is stepped with its inputs held (zero-order hold of
the duty cycle).

Order at an instant t: (1) step the plant to t; (2) apply load / input-voltage and tunable-parameter
events due at t (parameters through :meth:`~cosim.fmi.plant_fmi2.FmuPlant.set_parameters`);
(3) at a control sample, measure, call the controller, set the new duty; (4) at a recording
point, record outputs with the inputs now in effect. Reference changes reach the controller at
its first sample at or after the event time.

:func:`run` is the one place a scenario is checked against the plant (every path to a run passes
it); a :class:`_Run` carries one run through its named steps: set up, start, each window of
instants (the hot loop), each control sample, and the ending (complete, failed or interrupted).
"""

from __future__ import annotations

import math
import time as wallclock
from pathlib import Path

import numpy as np

from controllers.base import Controller, Measurement, check_duty_limits
from cosim.base.errors import ConfigError, ControllerError, PlantError, RunInterrupted, WorkbenchError
from cosim.fmi.archive import check_fmu
from cosim.fmi.binding import PlantBinding
from cosim.fmi.binding_file import PARAMETER, REST, TOGETHER, load_binding, locate_refusal
from cosim.fmi.communication import CommunicationStep, communication_step, grid_index, record_period_for
from cosim.fmi.plant import open_plant
from cosim.fmi.plant_fmi2 import FmuPlant, choose_interface, normalise_interface
from cosim.recorder import COLUMNS, MASTER_FIELDS, Recorder
from cosim.results import RunInfo, RunResult, RunStream, run_details
from cosim.scenarios import Scenario, check_parameter_events, load_scenario
from cosim.timeline import (
    CONTROL,
    DEFAULT_RECORD_PERIOD,
    EVENT,
    MERGE_TOLERANCE,
    RECORD,
    TimelinePlan,
    plan_timeline,
    signal_at,
)

STREAM_CHUNK = 16_384  # rows held in memory between writes when streaming
#: the values the loop records per row, in this order (the recorder's MASTER_FIELDS), then the
#: plant's outputs
RECORDED = ("time", "reference", "duty_cycle", "load_resistance", "input_voltage", "control_sample",
            "controller_compute_time")
assert RECORDED == MASTER_FIELDS, "the master records its values in the recorder's MASTER_FIELDS order"


class RunFailed(WorkbenchError):
    """A run stopped early; ``partial`` holds the rows recorded so far (metadata: complete = false)."""

    def __init__(self, message: str, partial: RunResult, cause: WorkbenchError):
        super().__init__(message)
        self.partial = partial
        self.cause = cause
        self.exit_code = cause.exit_code

    def __reduce__(self):  # so a failure crosses from a worker process to the reproduction
        return RunFailed, (str(self), self.partial, self.cause)


def check_communication_step(communication: CommunicationStep, plan: TimelinePlan, scenario: Scenario,
                             origin: str) -> float | None:
    """The one communication step [s] of a run of ``scenario`` on ``plan``'s grid for a plant stepped as
    ``communication`` says (None: any step) -- or a one-line :class:`ConfigError`, before anything runs, naming what
    is not a whole number of that step (the control period, the record period, the time of a load, supply or
    parameter event) and what would work. The settle interval is a whole number of control periods."""
    step = communication.for_run(plan.control_period)
    if step is None:
        return None
    misfits = []
    for label, value in (("control period", plan.control_period), ("record period", plan.record_period)):
        if not grid_index(value, step):
            misfits.append(f"the {label} {value:.6g} s")
    off_grid = [e for e in scenario.events if e.plant_event and grid_index(e.time, step) is None]
    if off_grid:
        misfits.append(f"scenario {scenario.name}'s event at t = {off_grid[0].time:.6g} s"
                       + (f" ({off_grid[0].where})" if off_grid[0].where else "")
                       + (f" and {len(off_grid) - 1} more" if len(off_grid) > 1 else ""))
    if not misfits:
        return step
    suggestion = f"multiples of {step:.6g} s"
    if misfits[0].startswith("the record period") and grid_index(plan.control_period, step):
        lower = max(1, math.floor(plan.record_period / step)) * step
        suggestion += f" (e.g. --record-period {lower:.6g})"
    raise ConfigError(f"{origin}: the FMU steps by one fixed communication step of "
                      f"{communication.describe(plan.control_period)}, "
                      f"but {', '.join(misfits)} {'is' if len(misfits) == 1 else 'are'} not a whole number of steps: "
                      f"use {suggestion}")


def check_rates(binding: PlantBinding, scenarios, control_period: float, record_period: float | None = None,
                interface: str | None = None) -> None:
    """Refuse, before any work, periods no run of ``scenarios`` on ``binding``'s plant could use: too many instants
    or too few controller samples (:func:`cosim.timeline.plan_timeline`), or a grid a fixed-step FMU cannot follow
    (:func:`check_communication_step`). ``record_period`` None: what :func:`run` records at by default."""
    communication = communication_of(binding, interface)
    if record_period is None:
        record_period = record_period_for(communication, DEFAULT_RECORD_PERIOD, control_period)
    for scenario in scenarios:
        check_communication_step(communication, plan_timeline(scenario, control_period, record_period), scenario,
                                 binding.origin)


def communication_of(binding: PlantBinding, interface: str | None = None) -> CommunicationStep:
    """How a run may step ``binding``'s plant (:mod:`cosim.fmi.communication`), read off its archive: through
    ``interface``, else the binding's, else co-simulation where offered -- as :func:`cosim.fmi.plant.open_plant`
    chooses."""
    checked = check_fmu(binding.fmu_path)
    chosen = choose_interface(checked, normalise_interface(interface or binding.interface), binding.origin)
    return communication_step(binding, checked.model_description, chosen)


def record_period_of(binding: PlantBinding, wanted: float, control_period: float,
                     interface: str | None = None) -> float:
    """:func:`cosim.fmi.communication.record_period_for` of ``binding``'s plant: ``wanted`` [s], or the nearest whole
    number of a fixed-step FMU's steps -- for a period the workbench chooses itself, never one a user gives."""
    return record_period_for(communication_of(binding, interface), wanted, control_period)


def check_plant_supports(binding: PlantBinding, scenario: Scenario, model_description=None) -> None:
    """Refuse, before anything runs, a scenario that needs a role the plant binding lacks, or a
    parameter event the FMU cannot take during a run (:func:`cosim.scenarios.check_parameter_events`)."""
    for role in sorted(scenario.required_roles()):
        if not binding.has(role):
            raise ConfigError(
                f"scenario {scenario.name} changes {role}, but {binding.origin} binds no variable to the "
                f"role {role!r}"
            )
    if scenario.parameter_events:
        if model_description is None:
            model_description = check_fmu(binding.fmu_path).model_description
        check_parameter_events(scenario, model_description, binding.origin)


def run(plant: FmuPlant, controller: Controller, scenario: Scenario, *, record_period: float | None = None,
        seed: int | None = None, progress: bool = False, extra_metadata: dict | None = None,
        stream_to: Path | None = None) -> RunResult:
    """Run one closed-loop scenario; return every recorded row as a :class:`RunResult`.

    The scenario is checked against the plant's binding first (:func:`check_plant_supports`);
    :func:`run_checked` is the same run for a caller that has checked it already (a batch checks
    all its scenarios before the first run). The plant instance is (re-)initialised here, so one
    instance serves many runs. On a plant or controller fault, or Ctrl-C, raises
    :class:`RunFailed` / :class:`RunInterrupted` carrying the rows recorded so far.

    ``record_period`` [s]: None -- :data:`cosim.timeline.DEFAULT_RECORD_PERIOD`, or the nearest multiple of a
    fixed-step FMU's communication step (:func:`cosim.fmi.communication.record_period_for`); a given one must lie
    on that FMU's grid (:func:`check_communication_step`), as must the control period and the plant events.

    ``stream_to``: write the rows to this Parquet file in chunks while running (memory stays
    bounded however long the run); the returned result then has an empty frame and the file's
    metadata, complete or not.
    """
    check_plant_supports(plant.binding, scenario, plant.model_description)
    return run_checked(plant, controller, scenario, record_period=record_period, seed=seed, progress=progress,
                       extra_metadata=extra_metadata, stream_to=stream_to)


def run_checked(plant: FmuPlant, controller: Controller, scenario: Scenario, *, record_period: float | None = None,
                seed: int | None = None, progress: bool = False, extra_metadata: dict | None = None,
                stream_to: Path | None = None) -> RunResult:
    """:func:`run` for a scenario already checked against ``plant.binding``."""
    limits = getattr(controller, "duty_limits", None)
    if limits is not None:  # a duty in percent, (0, 100), would drive the plant at full duty without a word
        try:
            check_duty_limits(tuple(limits), f"controller {getattr(controller, 'name', type(controller).__name__)}")
        except (TypeError, ValueError) as error:
            raise ConfigError(str(error) if isinstance(error, ValueError) else
                              f"controller duty_limits = {limits!r}: expected (min, max)") from None
    communication = plant.communication
    if record_period is None:
        record_period = record_period_for(communication, DEFAULT_RECORD_PERIOD, controller.sample_period)
    plan = plan_timeline(scenario, controller.sample_period, record_period)
    plant.use_step(check_communication_step(communication, plan, scenario, plant.binding.origin))
    return _Run(plant, controller, scenario, plan, seed, extra_metadata, stream_to).execute(progress)


def start_inputs(scenario: Scenario) -> dict[str, float]:
    """The plant's inputs at t = 0 by role (workbench units): duty 0, the scenario's first load and supply."""
    return {"duty_cycle": 0.0, "input_voltage": scenario.schedule("input_voltage")[0][1],
            "load_resistance": scenario.schedule("load_resistance")[0][1]}


def _parameter_events(scenario: Scenario) -> list[tuple[float, dict, str | None, int]]:
    """(scenario time [s], values, where in its file, index in events) of each tunable-parameter event."""
    return [(e.time, dict(e.parameters), e.where, i) for i, e in enumerate(scenario.events) if e.parameters]


def refuse_parameter_events(plant: FmuPlant, scenario: Scenario) -> None:
    """Try ``scenario``'s parameter events on the FMU itself (its own checks), so a value it refuses -- e.g. a
    capacitance of 0 -- is a :class:`ConfigError` naming the event before any step."""
    events = _parameter_events(scenario)
    if not events:
        return
    refused = plant.trial_parameters([values for _, values, _, _ in events])
    if refused is not None:
        position, message = refused
        _, values, where, index = events[position]
        raise ConfigError(f"{where or scenario.name}: events[{index}].parameters ({', '.join(values)}): the plant "
                          f"FMU refuses the value: {message}")


def preflight(plant: FmuPlant, scenario: Scenario) -> None:
    """Ask the plant, before any run, what a run's start asks of it: the scenario's parameter events tried on the
    FMU, then the set-up -- the binding's parameters and the scenario's first inputs, initialised at t = 0. A
    refusal is a :class:`ConfigError` naming what is refused where it can be told apart
    (:func:`cosim.fmi.binding_file.locate_refusal`): one ``[parameters]`` value at its line of the binding file,
    their combination, or the scenario's first inputs. The next initialisation resets the instance, so the runs
    that follow see it as if it were fresh."""
    refuse_parameter_events(plant, scenario)
    inputs = start_inputs(scenario)
    values = [inputs[r] for r in plant.input_roles]
    try:
        plant.initialize(values, start_time=0.0)
    except ConfigError as error:
        raise ConfigError(_refusal_text(plant, scenario, inputs, values, error)) from None


def _refusal_text(plant: FmuPlant, scenario: Scenario, inputs: dict, values: list[float], error: ConfigError) -> str:
    """The message of a refused :func:`preflight` set-up, naming the refused part."""
    binding = plant.binding
    detail = str(error).removeprefix(f"{binding.origin}: ")

    def try_set_up(parameters) -> bool:
        plant.replace_parameters(parameters)
        try:
            plant.initialize(values, start_time=0.0)
        except ConfigError:
            return False
        return True

    try:
        refusal = locate_refusal(binding, try_set_up)
    except WorkbenchError:  # the FMU cannot be set up again: its first message stands
        refusal = None
    finally:
        plant.replace_parameters(binding.parameters)
    first = ", ".join(f"{role} = {inputs[role]:g}" for role in plant.input_roles)
    if refusal is None or refusal.kind == REST:
        return (f"{scenario.place('initial')}: the plant FMU ({binding.origin}) refuses its set-up at the start of "
                f"scenario {scenario.name} ({first}){', even without the binding parameters' if refusal else ''} "
                f"({detail})")
    if refusal.kind == PARAMETER:
        return (f"{refusal.place}: parameters.{refusal.name} = {refusal.value!r}: the plant FMU refuses its set-up "
                f"with this value ({detail})")
    assert refusal.kind == TOGETHER
    return (f"{refusal.place}: the plant FMU refuses its set-up with these [parameters] together, though with each "
            f"alone ({detail})")


def check_set_up(binding: PlantBinding, scenarios, interface: str | None = None) -> None:
    """:func:`preflight` of each of ``scenarios`` on one instance of ``binding``'s plant, opened for the check
    (``interface`` as the runs will use it): everything the plant itself can refuse, refused before any run."""
    with open_plant(binding, interface=interface) as plant:
        for scenario in scenarios:
            preflight(plant, scenario)


class _Run:
    """One run of :func:`run`, step by step."""

    def __init__(self, plant: FmuPlant, controller: Controller, scenario: Scenario, plan: TimelinePlan,
                 seed: int | None, extra_metadata: dict | None, stream_to: Path | None):
        self.plant, self.controller, self.scenario, self.plan = plant, controller, scenario, plan
        self.schedules = [scenario.schedule(s) for s in ("reference", "load_resistance", "input_voltage")]
        roles = plant.output_roles
        # the controller reads its sensors: the measured roles where bound, else the plain outputs
        self.i_vo = self._index(roles, "measured_output_voltage", "output_voltage")
        self.i_il = self._index(roles, "measured_inductor_current", "inductor_current")
        self.i_io = self._index(roles, "measured_load_current", "load_current")
        self.inputs = start_inputs(scenario)
        # after a duty change alone, outputs need re-reading only if the FMU declares a feedthrough
        self.duty_feedthrough = plant.feedthrough.get("duty_cycle", True)
        self.details = run_details(scenario=scenario, controller=controller, plant=plant,
                                   control_period=plan.control_period, record_period=plan.record_period, seed=seed,
                                   extra=extra_metadata)
        self.info = RunInfo.from_metadata(self.details)
        self.recorder = Recorder(roles)
        self.stream = RunStream(stream_to) if stream_to is not None else None
        self.stream_to = stream_to
        # tunable-parameter events in plant time, applied in order (the timeline has an EVENT instant for each)
        self.parameter_events = [(plan.settle + time, values, where, i)
                                 for time, values, where, i in _parameter_events(scenario)]
        self.next_parameter_event = 0
        self.t = 0.0  # plant time reached [s]
        self.duty = 0.0  # in effect
        self.load, self.supply = self.inputs["load_resistance"], self.inputs["input_voltage"]

    @staticmethod
    def _index(roles: tuple[str, ...], *preferred: str) -> int:
        return next((roles.index(r) for r in preferred if r in roles), -1)

    # ------------------------------------------------------------------ steps
    def start(self) -> None:
        """Initialise the plant at rest with the first inputs (a refusal is a configuration
        error) and reset the controller. Parameter events are first tried on the FMU itself, so a
        value it refuses (e.g. a capacitance of 0) stops the run before its first step."""
        refuse_parameter_events(self.plant, self.scenario)
        self.plant.initialize([self.inputs[r] for r in self.plant.input_roles], start_time=0.0)
        self.controller.reset()
        self.next_parameter_event = 0

    def apply_parameter_events(self, t: float) -> None:
        """Set every tunable-parameter event due at plant time ``t`` (between plant steps)."""
        events = self.parameter_events
        while self.next_parameter_event < len(events) and events[self.next_parameter_event][0] <= t + MERGE_TOLERANCE:
            self.plant.set_parameters(events[self.next_parameter_event][1])
            self.next_parameter_event += 1

    def execute(self, progress: bool) -> RunResult:
        bar = _progress_bar(progress, self.plan.instants, f"{self.scenario.name} / {self.controller.name}")
        self.start()
        try:
            for window in self.plan.windows():
                self.window(window)
                if self.stream is not None and len(self.recorder) >= STREAM_CHUNK:
                    self.stream.write(self.recorder.take())
                if bar is not None:
                    bar.update(window.size)
        except KeyboardInterrupt:
            partial = self.finish(False, f"interrupted at t = {self.t - self.plan.settle:.9g} s")
            raise RunInterrupted(f"run {self.scenario.name} / {self.controller.name} interrupted at t = "
                                 f"{self.t - self.plan.settle:.6g} s; {partial.metadata['rows']} rows kept",
                                 partial) from None
        except WorkbenchError as error:  # plant or controller faults: keep the rows, name the cause
            partial = self.finish(False, str(error))
            raise RunFailed(str(error), partial, error) from None
        except BaseException as error:  # anything else (a bug, a full disk): no stream left half-written
            if self.stream is not None:
                try:
                    self.finish(False, f"{type(error).__name__}: {error}")
                except Exception:
                    pass
            raise
        finally:
            if bar is not None:
                bar.close()
        return self.finish(True)

    def window(self, window) -> None:
        """Every instant of one window: the hot loop (locals, plain lists and bound methods: they
        are several times cheaper than attributes and numpy scalars here)."""
        plant, settle = self.plant, self.plan.settle
        times, flags = window.times.tolist(), window.flags.tolist()
        references, loads, supplies = (signal_at(window, schedule).tolist() for schedule in self.schedules)
        recorded = (window.flags & RECORD) != 0
        recorded |= ((window.flags & CONTROL) != 0) & (window.times >= settle - MERGE_TOLERANCE)
        record_flags = recorded.tolist()
        advance, outputs, set_inputs = plant.advance_to, plant.outputs, plant.set_inputs
        parameter_events = bool(self.parameter_events)
        roles_in, roles_out, inputs = plant.input_roles, plant.output_roles, self.inputs
        record = self.recorder.record
        control_sample, duty_feedthrough = self._control_sample(), self.duty_feedthrough
        origin = plant.binding.origin
        t, duty, load, supply = self.t, self.duty, self.load, self.supply
        nan = math.nan
        try:
            for i in range(window.size):
                t = times[i]
                flag = flags[i]
                advance(t)
                y = None
                if loads[i] != load or supplies[i] != supply:
                    load, supply = loads[i], supplies[i]
                    inputs["load_resistance"], inputs["input_voltage"] = load, supply
                    set_inputs([inputs[r] for r in roles_in])
                if parameter_events and flag & EVENT:
                    self.apply_parameter_events(t)
                compute = nan
                if flag & CONTROL:
                    y = outputs()
                    _check_finite(y, roles_out, t - settle, origin)
                    duty, compute = control_sample(t - settle, references[i], y, supply)
                    if duty_feedthrough:
                        y = None
                if record_flags[i]:
                    if y is None:
                        y = outputs()
                        _check_finite(y, roles_out, t - settle, origin)
                    record((t - settle, references[i], duty, load, supply, 1.0 if flag & CONTROL else 0.0, compute,
                            *y))
        finally:
            self.t, self.duty, self.load, self.supply = t, duty, load, supply

    def _control_sample(self):
        """The step at a control sample, as a closure over what it needs (the hot path: free
        variables are cheaper than attribute look-ups): measure, call the controller, check and
        apply its duty; it returns the duty and the controller's compute time [s]."""
        controller, plant, inputs = self.controller, self.plant, self.inputs
        step, set_inputs, roles_in, name = controller.step, plant.set_inputs, plant.input_roles, controller.name
        i_vo, i_il, i_io = self.i_vo, self.i_il, self.i_io
        clock, nan, isfinite = wallclock.perf_counter_ns, math.nan, math.isfinite

        def control_sample(t: float, reference: float, y: list[float], supply: float) -> tuple[float, float]:
            measurement = Measurement(t, reference, y[i_vo], y[i_il] if i_il >= 0 else nan,
                                      y[i_io] if i_io >= 0 else nan, supply)
            start = clock()
            try:
                duty = step(measurement)
            except WorkbenchError as error:
                raise ControllerError(f"controller {name} failed at t = {t:.9g} s: {error}") from None
            except Exception as error:  # the raising line named; the exception kept for --debug
                raise ControllerError(f"controller {name} raised {type(error).__name__} at t = {t:.9g} s "
                                      f"({raising_line(error)}): {error}") from error
            compute = (clock() - start) * 1e-9
            if not (isinstance(duty, (int, float, np.floating)) and isfinite(duty)):
                raise ControllerError(f"controller {name} returned duty cycle {duty!r} at t = {t:.9g} s: "
                                      "expected a finite number")
            duty = inputs["duty_cycle"] = float(duty)
            set_inputs([inputs[r] for r in roles_in])
            return duty, compute

        return control_sample

    def finish(self, complete: bool, error: str | None = None) -> RunResult:
        """The run's result, complete or not; a stream is closed with the final metadata."""
        if self.stream is None:
            return RunResult.from_table(self.recorder.take(), self.info, self.details, complete, error)
        self.stream.write(self.recorder.take())
        result = RunResult.from_table(np.empty((0, len(COLUMNS))), self.info, self.details,
                                      complete, error)
        self.stream.close(result.metadata)
        result.rows, result.streamed, result.streamed_to = self.stream.rows, True, str(self.stream_to)
        return result


def raising_line(error: BaseException) -> str:
    """``file:line`` of the innermost frame of ``error``'s traceback: where a user's controller raised."""
    import traceback

    frames = traceback.extract_tb(error.__traceback__)
    return f"{frames[-1].filename}:{frames[-1].lineno}" if frames else "no traceback"


def _check_finite(values: list[float], roles: tuple[str, ...], t: float, origin: str) -> None:
    if sum(values) * 0.0 != 0.0:  # NaN or +-inf anywhere (cheaper than a per-element test)
        bad = [f"{r} = {v}" for r, v in zip(roles, values) if not math.isfinite(v)]
        raise PlantError(f"{origin}: plant output became non-finite at t = {t:.9g} s ({', '.join(bad)})")


def _progress_bar(enabled: bool, total: int, label: str):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=label, unit="step", leave=False, mininterval=0.5, delay=1.0)


def simulate(binding: PlantBinding | str | Path, controller: Controller, scenario: Scenario | str | Path, *,
             interface: str | None = None,
             record_period: float | None = None, seed: int | None = None, progress: bool = False,
             relative_tolerance: float = 1e-8, extra_metadata: dict | None = None) -> RunResult:
    """Open the plant, run one scenario, and always free the FMU, even on error. ``binding`` may be a binding file's
    path and ``scenario`` a shipped scenario's name or a scenario file's path, as the command line takes them (resolved
    against the plant's converter spec, :mod:`cosim.converter_spec`)."""
    if isinstance(binding, (str, Path)):
        binding = load_binding(binding)
    if isinstance(scenario, (str, Path)):
        scenario = load_scenario(scenario, binding.converter, warn=True)
    if isinstance(controller, type):
        raise TypeError(f"controller {controller.__name__} is a class: pass an instance, {controller.__name__}(...)")
    from cosim.data_domain import checked_metadata

    extra_metadata = checked_metadata(controller, scenario, extra_metadata)
    with open_plant(binding, interface=interface, relative_tolerance=relative_tolerance) as plant:
        return run(plant, controller, scenario, record_period=record_period, seed=seed, progress=progress,
                   extra_metadata=extra_metadata)
