"""The co-simulation master: a multi-rate loop of plant steps, sampled controllers and a recorder.

Time line. The plant runs on one merged grid of instants: controller samples (every control
period), recording points (every record period, finer, e.g. 10 us so figures show the LC ringing
inside a control period) and the exact times of load and input-voltage events. The two periods
need not divide each other: the grids are merged, and a row is recorded at every control sample
as well, so no compute time is lost. Between instants the FMU is stepped with its inputs held
(zero-order hold of the duty cycle).

Order at an instant t: (1) step the plant to t; (2) apply load / input-voltage events due at t;
(3) at a control sample, measure, call the controller, set the new duty; (4) at a recording
point, record outputs with the inputs now in effect. Reference changes reach the controller at
its first sample at or after the event time.
"""

from __future__ import annotations

import math
import time as wallclock
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from controllers.base import Controller, Measurement
from cosim.base.errors import ConfigError, ControllerError, PlantError, RunInterrupted, WorkbenchError
from cosim.fmi.binding import PlantBinding
from cosim.fmi.plant import FmuPlant
from cosim.results import COLUMNS, RunResult, RunStream, run_metadata
from cosim.scenarios import Scenario

CONTROL, RECORD, EVENT = 1, 2, 4
#: instants closer than this are one instant [s]; far below any period, far above float rounding
MERGE_TOLERANCE = 1e-12
MAX_INSTANTS = 200_000_000  # a sanity limit; memory stays bounded below it (windows)
STREAM_CHUNK = 16_384  # rows held in memory between writes when streaming
WINDOW_INSTANTS = 16_384  # instants generated at a time
WHOLE_TIMELINE_LIMIT = 5_000_000  # build_timeline() refuses more (the master itself iterates windows)


class RunFailed(WorkbenchError):
    """A run stopped early; ``partial`` holds the rows recorded so far (metadata: complete = false)."""

    def __init__(self, message: str, partial: RunResult, cause: WorkbenchError):
        super().__init__(message)
        self.partial = partial
        self.cause = cause
        self.exit_code = cause.exit_code

    def __reduce__(self):  # so a failure crosses from a worker process to the reproduction
        return RunFailed, (str(self), self.partial, self.cause)


@dataclass(frozen=True)
class Timeline:
    """Merged instants in plant time (seconds since the start of the settle interval)."""

    times: np.ndarray
    flags: np.ndarray
    settle: float  # [s] plant time of scenario t = 0

    @property
    def size(self) -> int:
        return len(self.times)


@dataclass(frozen=True)
class TimelinePlan:
    """The three grids of a run, generated a window at a time so long runs stay in bounded memory."""

    control_period: float
    record_period: float
    settle: float  # [s] plant time of scenario t = 0 (a whole number of control periods)
    end: float  # [s] plant time at the end
    control_count: int  # control instants k = 0 .. control_count - 1 at k * control_period
    record_count: int  # recording instants j = 0 .. record_count - 1 at settle + j * record_period
    events: np.ndarray  # plant-event times (load, supply)

    @property
    def instants(self) -> int:
        return self.control_count + self.record_count

    def _record_index(self, t: float) -> int:
        """Number of recording instants strictly before t - tolerance (a window's half-open edge)."""
        if math.isinf(t):
            return self.record_count
        return max(0, min(self.record_count, math.ceil((t - MERGE_TOLERANCE - self.settle) / self.record_period)))

    def window(self, k0: int, k1: int) -> Timeline:
        """Merged instants from control sample k0 up to (not including) sample k1; the last window
        also holds everything after the last control sample."""
        last = k1 >= self.control_count
        k1 = min(k1, self.control_count)
        lo, hi = k0 * self.control_period, math.inf if last else k1 * self.control_period
        control = np.arange(k0, k1) * self.control_period
        record = self.settle + np.arange(self._record_index(lo), self._record_index(hi)) * self.record_period
        events = self.events[(self.events >= lo - MERGE_TOLERANCE) & (self.events < hi - MERGE_TOLERANCE)]
        times = np.concatenate([control, record, events])
        flags = np.concatenate([np.full(len(control), CONTROL), np.full(len(record), RECORD),
                                np.full(len(events), EVENT)]).astype(np.int8)
        priority = np.concatenate([np.zeros(len(control)), np.ones(len(record)), np.full(len(events), 2)])
        order = np.lexsort((priority, times))
        times, flags = times[order], flags[order]
        if not len(times):
            return Timeline(times=times, flags=flags, settle=self.settle)
        new_group = np.concatenate([[True], np.diff(times) > MERGE_TOLERANCE])
        group = np.cumsum(new_group) - 1
        merged_times = times[new_group]  # first of each group: the control instant when there is one
        merged_flags = np.zeros(len(merged_times), dtype=np.int8)
        np.bitwise_or.at(merged_flags, group, flags)
        keep = merged_times <= self.end + MERGE_TOLERANCE
        return Timeline(times=merged_times[keep], flags=merged_flags[keep], settle=self.settle)

    def windows(self, size: int = WINDOW_INSTANTS):
        """Consecutive windows of about ``size`` instants covering the run."""
        per_control = 1 + self.control_period / self.record_period
        step = max(1, int(size / per_control))
        for k0 in range(0, self.control_count, step):
            yield self.window(k0, k0 + step)


def plan_timeline(scenario: Scenario, control_period: float, record_period: float) -> TimelinePlan:
    """Validate the periods and lay out the grids of a run (see :class:`TimelinePlan`)."""
    for label, value in (("control period", control_period), ("record period", record_period)):
        if not (value > 0 and math.isfinite(value)):
            raise ConfigError(f"{label} = {value} s is invalid: expected a finite value > 0")
    settle = math.ceil(scenario.settle / control_period - 1e-9) * control_period
    end = settle + scenario.duration
    expected = end / control_period + scenario.duration / record_period
    if expected > MAX_INSTANTS:
        raise ConfigError(
            f"scenario {scenario.name}: {expected:.3g} instants for {scenario.duration} s at control period "
            f"{control_period} s and record period {record_period} s; the limit is {MAX_INSTANTS:.0e}"
        )
    control_count = int(math.floor(end / control_period * (1 + 1e-12) + 1e-9)) + 1
    record_count = int(math.floor(scenario.duration / record_period * (1 + 1e-12) + 1e-9)) + 1
    events = np.array([settle + e.time for e in scenario.events if any(k != "reference" for k in e.changes)],
                      dtype=float)
    return TimelinePlan(control_period, record_period, settle, end, control_count, record_count, events)


def build_timeline(scenario: Scenario, control_period: float, record_period: float) -> Timeline:
    """All merged instants of a run at once (fine for short runs; long runs iterate windows)."""
    plan = plan_timeline(scenario, control_period, record_period)
    if plan.instants > WHOLE_TIMELINE_LIMIT:
        raise ConfigError(f"scenario {scenario.name}: {plan.instants:.3g} instants are too many to hold at once; "
                          "iterate plan_timeline(...).windows() instead")
    return plan.window(0, plan.control_count)


def _signal_at(timeline: Timeline, schedule: list[tuple[float, float]]) -> np.ndarray:
    """Value of a piecewise-constant scenario signal at every instant (events take effect at their time)."""
    event_times = np.array([timeline.settle + t for t, _ in schedule])
    values = np.array([v for _, v in schedule])
    index = np.searchsorted(event_times, timeline.times + MERGE_TOLERANCE, side="right") - 1
    index[index < 0] = 0  # the settle interval runs at the initial values
    return values[index]


def check_step_sizes(plant: FmuPlant, plan: TimelinePlan) -> None:
    """Refuse a non-uniform grid for a co-simulation FMU that cannot vary its communication step."""
    cs = plant.model_description.coSimulation
    if plant.interface != "co-simulation" or cs is None or cs.canHandleVariableCommunicationStepSize:
        return
    low, high, previous = math.inf, 0.0, None
    for window in plan.windows():
        times = window.times if previous is None else np.concatenate([[previous], window.times])
        if len(times) > 1:
            steps = np.diff(times)
            low, high = min(low, steps.min()), max(high, steps.max())
        previous = window.times[-1] if len(window.times) else previous
    if high - low > 1e-9 * high:
        raise ConfigError(
            f"{plant.binding.origin}: the FMU cannot change its communication step size, but control period "
            f"{plan.control_period:.6g} s, record period {plan.record_period:.6g} s and the scenario's events give "
            f"steps from {low:.6g} s to {high:.6g} s: use a record period that divides the control period and "
            "events on that grid"
        )


def check_plant_supports(binding: PlantBinding, scenario: Scenario) -> None:
    """Refuse, before anything runs, a scenario that needs a role the plant binding lacks."""
    for role in sorted(scenario.required_roles()):
        if not binding.has(role):
            raise ConfigError(
                f"scenario {scenario.name} changes {role}, but {binding.origin} binds no variable to the "
                f"role {role!r}"
            )


def run(plant: FmuPlant, controller: Controller, scenario: Scenario, *, record_period: float = 1e-5,
        seed: int | None = None, progress: bool = False, extra_metadata: dict | None = None,
        stream_to: Path | None = None) -> RunResult:
    """Run one closed-loop scenario; return every recorded row as a :class:`RunResult`.

    The plant instance is reset and re-initialised here, so one instance serves many runs.
    On a plant or controller fault, or Ctrl-C, raises :class:`RunFailed` / :class:`RunInterrupted`
    carrying the rows recorded so far.

    ``stream_to``: write the rows to this Parquet file in chunks while running (memory stays
    bounded however long the run); the returned result then has an empty frame and the file's
    metadata, complete or not.
    """
    check_plant_supports(plant.binding, scenario)
    control_period = controller.sample_period
    plan = plan_timeline(scenario, control_period, record_period)
    check_step_sizes(plant, plan)
    schedules = [scenario.schedule(s) for s in ("reference", "load_resistance", "input_voltage")]

    roles_in = plant.input_roles
    roles_out = plant.output_roles
    i_vo = roles_out.index("output_voltage")
    i_il = roles_out.index("inductor_current") if "inductor_current" in roles_out else -1
    i_io = roles_out.index("load_current") if "load_current" in roles_out else -1
    # the controller reads its sensors: the measured roles where bound, else the plain outputs
    i_mv = roles_out.index("measured_output_voltage") if "measured_output_voltage" in roles_out else i_vo
    i_mi = roles_out.index("measured_inductor_current") if "measured_inductor_current" in roles_out else i_il
    i_mo = roles_out.index("measured_load_current") if "measured_load_current" in roles_out else i_io
    inputs = {"duty_cycle": 0.0, "input_voltage": schedules[2][0][1], "load_resistance": schedules[1][0][1]}
    # after a duty change alone, outputs need re-reading only if the FMU declares a feedthrough
    duty_feedthrough = plant.feedthrough.get("duty_cycle", True)

    rows: list[tuple] = []
    metadata = run_metadata(scenario=scenario, controller=controller, plant=plant, control_period=control_period,
                            record_period=record_period, seed=seed, extra=extra_metadata)
    nan = math.nan
    stream = RunStream(stream_to) if stream_to is not None else None

    def flush() -> None:
        stream.write(np.array(rows, dtype=float).reshape(len(rows), len(COLUMNS)))
        rows.clear()

    def result(complete: bool, error: str | None = None) -> RunResult:
        data = np.array(rows, dtype=float).reshape(len(rows), len(COLUMNS))
        if stream is None:
            return RunResult.from_array(data, metadata, complete=complete, error=error)
        flush()
        empty = RunResult.from_array(np.empty((0, len(COLUMNS))), metadata, complete=complete, error=error)
        stream.close(empty.metadata)
        empty.metadata.update({"rows": stream.rows, "streamed_to": str(stream_to)})
        return empty

    if plant._initialized:
        plant.reset()
    bar = _progress_bar(progress, plan.instants, f"{scenario.name} / {controller.name}")
    t = 0.0
    settle = plan.settle
    plant.initialize([inputs[r] for r in roles_in], start_time=0.0)  # a refusal here is a configuration error
    controller.reset()
    try:
        duty = 0.0
        last_load, last_supply = inputs["load_resistance"], inputs["input_voltage"]
        advance, outputs, set_inputs, step = plant.advance_to, plant.outputs, plant.set_inputs, controller.step
        append, clock = rows.append, wallclock.perf_counter_ns
        for window in plan.windows():
            # plain lists: indexing them is several times cheaper than numpy scalars in this loop
            times, flags = window.times.tolist(), window.flags.tolist()
            references, loads, supplies = (_signal_at(window, schedule).tolist() for schedule in schedules)
            recorded = (window.flags & RECORD) != 0
            recorded |= ((window.flags & CONTROL) != 0) & (window.times >= settle - MERGE_TOLERANCE)
            record_flags = recorded.tolist()
            for i in range(window.size):
                t = times[i]
                flag = flags[i]
                advance(t)
                y = None
                if loads[i] != last_load or supplies[i] != last_supply:
                    last_load, last_supply = loads[i], supplies[i]
                    inputs["load_resistance"], inputs["input_voltage"] = last_load, last_supply
                    set_inputs([inputs[r] for r in roles_in])
                compute = nan
                if flag & CONTROL:
                    y = outputs()
                    _check_finite(y, roles_out, t - settle, plant.binding.origin)
                    measurement = Measurement(t - settle, references[i], y[i_mv], y[i_mi] if i_mi >= 0 else nan,
                                              y[i_mo] if i_mo >= 0 else nan, last_supply)
                    start = clock()
                    try:
                        duty = step(measurement)
                    except WorkbenchError as error:
                        raise ControllerError(f"controller {controller.name} failed at t = {t - settle:.9g} s: "
                                              f"{error}") from None
                    except Exception as error:
                        raise ControllerError(f"controller {controller.name} raised {type(error).__name__} at "
                                              f"t = {t - settle:.9g} s: {error}") from None
                    compute = (clock() - start) * 1e-9
                    if not (isinstance(duty, (int, float, np.floating)) and math.isfinite(duty)):
                        raise ControllerError(f"controller {controller.name} returned duty cycle {duty!r} at "
                                              f"t = {t - settle:.9g} s: expected a finite number")
                    duty = float(duty)
                    inputs["duty_cycle"] = duty
                    set_inputs([inputs[r] for r in roles_in])
                    if duty_feedthrough:
                        y = None
                if record_flags[i]:
                    if y is None:
                        y = outputs()
                        _check_finite(y, roles_out, t - settle, plant.binding.origin)
                    append((t - settle, references[i], y[i_vo], y[i_il] if i_il >= 0 else nan, y[i_mv],
                            y[i_mi] if i_mi >= 0 else nan, y[i_io] if i_io >= 0 else nan,
                            y[i_mo] if i_mo >= 0 else nan, duty, last_load,
                            last_supply, 1.0 if flag & CONTROL else 0.0, compute))
            if stream is not None and len(rows) >= STREAM_CHUNK:
                flush()
            if bar is not None:
                bar.update(window.size)
    except KeyboardInterrupt:
        partial = result(False, f"interrupted at t = {t - settle:.9g} s")
        raise RunInterrupted(f"run {scenario.name} / {controller.name} interrupted at t = "
                             f"{t - settle:.6g} s; {partial.metadata['rows']} rows kept", partial) from None
    except WorkbenchError as error:  # plant or controller faults: keep the rows, name the cause
        partial = result(False, str(error))
        raise RunFailed(str(error), partial, error) from None
    except BaseException as error:  # anything else (a bug, a full disk): no stream left half-written
        if stream is not None:
            try:
                result(False, f"{type(error).__name__}: {error}")
            except Exception:
                pass
        raise
    finally:
        if bar is not None:
            bar.close()
    return result(True)


def _check_finite(values: list[float], roles: tuple[str, ...], t: float, origin: str) -> None:
    if sum(values) * 0.0 != 0.0:  # NaN or +-inf anywhere (cheaper than a per-element test)
        bad = [f"{r} = {v}" for r, v in zip(roles, values) if not math.isfinite(v)]
        raise PlantError(f"{origin}: plant output became non-finite at t = {t:.9g} s ({', '.join(bad)})")


def _progress_bar(enabled: bool, total: int, label: str):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=label, unit="step", leave=False, mininterval=0.5, delay=1.0)


def simulate(binding: PlantBinding, controller: Controller, scenario: Scenario, *, interface: str | None = None,
             record_period: float = 1e-5, seed: int | None = None, progress: bool = False,
             relative_tolerance: float = 1e-8, extra_metadata: dict | None = None) -> RunResult:
    """Open the plant, run one scenario, and always free the FMU, even on error."""
    check_plant_supports(binding, scenario)
    with FmuPlant(binding, interface=interface, relative_tolerance=relative_tolerance) as plant:
        return run(plant, controller, scenario, record_period=record_period, seed=seed, progress=progress,
                   extra_metadata=extra_metadata)


