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

import numpy as np

from controllers.base import Controller, Measurement
from cosim.binding import PlantBinding
from cosim.errors import ConfigError, ControllerError, PlantError, RunInterrupted, WorkbenchError
from cosim.fmu_plant import FmuPlant
from cosim.results import COLUMNS, RunResult, run_metadata
from cosim.scenarios import Scenario

CONTROL, RECORD, EVENT = 1, 2, 4
#: instants closer than this are one instant [s]; far below any period, far above float rounding
MERGE_TOLERANCE = 1e-12
MAX_INSTANTS = 20_000_000


class RunFailed(WorkbenchError):
    """A run stopped early; ``partial`` holds the rows recorded so far (metadata: complete = false)."""

    def __init__(self, message: str, partial: RunResult, cause: WorkbenchError):
        super().__init__(message)
        self.partial = partial
        self.exit_code = cause.exit_code


@dataclass(frozen=True)
class Timeline:
    """Merged instants in plant time (seconds since the start of the settle interval)."""

    times: np.ndarray
    flags: np.ndarray
    settle: float  # [s] plant time of scenario t = 0

    @property
    def size(self) -> int:
        return len(self.times)


def _grid(period: float, end: float) -> np.ndarray:
    count = int(math.floor(end / period * (1 + 1e-12) + 1e-9))
    return np.arange(count + 1) * period


def build_timeline(scenario: Scenario, control_period: float, record_period: float) -> Timeline:
    """Merge control samples, recording points and plant events into one sorted grid."""
    for label, value in (("control period", control_period), ("record period", record_period)):
        if not (value > 0 and math.isfinite(value)):
            raise ConfigError(f"{label} = {value} s is invalid: expected a finite value > 0")
    settle_periods = math.ceil(scenario.settle / control_period - 1e-9)
    settle = settle_periods * control_period
    end = settle + scenario.duration
    expected = end / control_period + scenario.duration / record_period
    if expected > MAX_INSTANTS:
        raise ConfigError(
            f"scenario {scenario.name}: {expected:.3g} instants for {scenario.duration} s at control period "
            f"{control_period} s and record period {record_period} s; the limit is {MAX_INSTANTS:.0e}"
        )
    control = _grid(control_period, end)
    record = settle + _grid(record_period, scenario.duration)
    events = np.array([settle + e.time for e in scenario.events
                       if any(k != "reference" for k in e.changes)], dtype=float)
    times = np.concatenate([control, record, events])
    flags = np.concatenate([np.full(len(control), CONTROL), np.full(len(record), RECORD),
                            np.full(len(events), EVENT)]).astype(np.int8)
    priority = np.concatenate([np.zeros(len(control)), np.ones(len(record)), np.full(len(events), 2)])
    order = np.lexsort((priority, times))
    times, flags = times[order], flags[order]
    new_group = np.concatenate([[True], np.diff(times) > MERGE_TOLERANCE])
    group = np.cumsum(new_group) - 1
    merged_times = times[new_group]  # first of each group: the control instant when there is one
    merged_flags = np.zeros(len(merged_times), dtype=np.int8)
    np.bitwise_or.at(merged_flags, group, flags)
    keep = merged_times <= end + MERGE_TOLERANCE
    return Timeline(times=merged_times[keep], flags=merged_flags[keep], settle=settle)


def _signal_at(timeline: Timeline, schedule: list[tuple[float, float]]) -> np.ndarray:
    """Value of a piecewise-constant scenario signal at every instant (events take effect at their time)."""
    event_times = np.array([timeline.settle + t for t, _ in schedule])
    values = np.array([v for _, v in schedule])
    index = np.searchsorted(event_times, timeline.times + MERGE_TOLERANCE, side="right") - 1
    index[index < 0] = 0  # the settle interval runs at the initial values
    return values[index]


def check_plant_supports(binding: PlantBinding, scenario: Scenario) -> None:
    """Refuse, before anything runs, a scenario that needs a role the plant binding lacks."""
    for role in sorted(scenario.required_roles()):
        if not binding.has(role):
            raise ConfigError(
                f"scenario {scenario.name} changes {role}, but {binding.origin} binds no variable to the "
                f"role {role!r}"
            )


def run(plant: FmuPlant, controller: Controller, scenario: Scenario, *, record_period: float = 1e-5,
        seed: int | None = None, progress: bool = False, extra_metadata: dict | None = None) -> RunResult:
    """Run one closed-loop scenario; return every recorded row as a :class:`RunResult`.

    The plant instance is reset and re-initialised here, so one instance serves many runs.
    On a plant or controller fault, or Ctrl-C, raises :class:`RunFailed` / :class:`RunInterrupted`
    carrying the rows recorded so far.
    """
    check_plant_supports(plant.binding, scenario)
    control_period = controller.sample_period
    timeline = build_timeline(scenario, control_period, record_period)
    reference = _signal_at(timeline, scenario.schedule("reference"))
    load = _signal_at(timeline, scenario.schedule("load_resistance"))
    supply = _signal_at(timeline, scenario.schedule("input_voltage"))

    roles_in = plant.input_roles
    roles_out = plant.output_roles
    i_vo = roles_out.index("output_voltage")
    i_il = roles_out.index("inductor_current") if "inductor_current" in roles_out else -1
    i_io = roles_out.index("load_current") if "load_current" in roles_out else -1
    # the controller reads its sensors: the measured roles where bound, else the plain outputs
    i_mv = roles_out.index("measured_output_voltage") if "measured_output_voltage" in roles_out else i_vo
    i_mi = roles_out.index("measured_inductor_current") if "measured_inductor_current" in roles_out else i_il
    inputs = {"duty_cycle": 0.0, "input_voltage": supply[0], "load_resistance": load[0]}
    # after a duty change alone, outputs need re-reading only if the FMU declares a feedthrough
    duty_feedthrough = plant.feedthrough.get("duty_cycle", True)

    recorded = (timeline.flags & RECORD) != 0
    recorded |= ((timeline.flags & CONTROL) != 0) & (timeline.times >= timeline.settle - MERGE_TOLERANCE)
    rows: list[tuple] = []
    metadata = run_metadata(scenario=scenario, controller=controller, plant=plant, control_period=control_period,
                            record_period=record_period, seed=seed, extra=extra_metadata)
    nan = math.nan

    def result(complete: bool, error: str | None = None) -> RunResult:
        data = np.array(rows, dtype=float).reshape(len(rows), len(COLUMNS))
        return RunResult.from_array(data, metadata, complete=complete, error=error)

    if plant._initialized:
        plant.reset()
    bar = _progress_bar(progress, timeline.size, f"{scenario.name} / {controller.name}")
    t = 0.0
    settle = timeline.settle
    try:
        plant.initialize([inputs[r] for r in roles_in], start_time=0.0)
        controller.reset()
        duty = 0.0
        # plain lists: indexing them is several times cheaper than numpy scalars in this loop
        times, flags = timeline.times.tolist(), timeline.flags.tolist()
        references, loads, supplies, record_flags = reference.tolist(), load.tolist(), supply.tolist(), recorded.tolist()
        last_load, last_supply = loads[0], supplies[0]
        advance, outputs, set_inputs, step = plant.advance_to, plant.outputs, plant.set_inputs, controller.step
        append, clock = rows.append, wallclock.perf_counter_ns
        for i in range(timeline.size):
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
                _check_finite(y, roles_out, t - settle)
                measurement = Measurement(t - settle, references[i], y[i_mv], y[i_mi] if i_mi >= 0 else nan,
                                          y[i_io] if i_io >= 0 else nan, last_supply)
                start = clock()
                try:
                    duty = step(measurement)
                except WorkbenchError:
                    raise
                except Exception as error:
                    raise ControllerError(
                        f"controller {controller.name} raised {type(error).__name__} at t = {t - settle:.9g} s: {error}"
                    ) from None
                compute = (clock() - start) * 1e-9
                if not (isinstance(duty, (int, float, np.floating)) and math.isfinite(duty)):
                    raise ControllerError(
                        f"controller {controller.name} returned duty cycle {duty!r} at t = {t - settle:.9g} s: "
                        "expected a finite number"
                    )
                duty = float(duty)
                inputs["duty_cycle"] = duty
                set_inputs([inputs[r] for r in roles_in])
                if duty_feedthrough:
                    y = None
            if record_flags[i]:
                if y is None:
                    y = outputs()
                    _check_finite(y, roles_out, t - settle)
                append((t - settle, references[i], y[i_vo], y[i_il] if i_il >= 0 else nan, y[i_mv],
                        y[i_mi] if i_mi >= 0 else nan, y[i_io] if i_io >= 0 else nan, duty, last_load,
                        last_supply, 1.0 if flag & CONTROL else 0.0, compute))
            if bar is not None and i % 2048 == 0:
                bar.update(min(2048, timeline.size - bar.n))
    except KeyboardInterrupt:
        partial = result(False, f"interrupted at t = {t - timeline.settle:.9g} s")
        raise RunInterrupted(f"run {scenario.name} / {controller.name} interrupted at t = "
                             f"{t - timeline.settle:.6g} s; {len(rows)} rows kept", partial) from None
    except (PlantError, ControllerError) as error:
        partial = result(False, str(error))
        raise RunFailed(str(error), partial, error) from None
    finally:
        if bar is not None:
            bar.close()
    return result(True)


def _check_finite(values: list[float], roles: tuple[str, ...], t: float) -> None:
    if sum(values) * 0.0 != 0.0:  # NaN or +-inf anywhere (cheaper than a per-element test)
        bad = [f"{r} = {v}" for r, v in zip(roles, values) if not math.isfinite(v)]
        raise PlantError(f"plant output became non-finite at t = {t:.9g} s ({', '.join(bad)})")


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


