"""The time line of a run: controller samples, recording points and plant events, merged.

The plant runs on one merged grid of instants: controller samples (every control period),
recording points (every record period, finer, e.g. 10 us so figures show the LC ringing inside
a control period) and the exact times of load, input-voltage and plant-parameter events. The two periods need
not divide each other: the grids are merged (instants closer than :data:`MERGE_TOLERANCE` are
one), and each instant carries flags saying what happens there. Long runs are generated a
window at a time, so memory stays bounded however long the run.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from cosim.base.errors import ConfigError
from cosim.base.labels import MIN_PERIOD, period_too_short
from cosim.scenarios import Scenario

CONTROL, RECORD, EVENT = 1, 2, 4
#: instants closer than this are one instant [s]; far below any period, far above float rounding
MERGE_TOLERANCE = 1e-12
MAX_INSTANTS = 200_000_000  # a sanity limit; memory stays bounded below it (windows)
#: a run whose recorded part holds fewer controller samples than this is refused: with one sample
#: (a control period as long as the scenario) the controller acts once and the rest is open loop
MIN_CONTROL_SAMPLES = 2
#: the recording step of a run when none is given [s]: the LC ringing inside a control period shows in the figures
DEFAULT_RECORD_PERIOD = 1e-5
WINDOW_INSTANTS = 16_384  # instants generated at a time
WHOLE_TIMELINE_LIMIT = 5_000_000  # build_timeline() refuses more (the master itself iterates windows)


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
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ConfigError(f"{label} = {value!r} is invalid: expected a number of seconds")
        if not (value > 0 and math.isfinite(value)):
            raise ConfigError(f"{label} = {value} s is invalid: expected a finite value > 0")
        if value < MIN_PERIOD:
            raise ConfigError(period_too_short(f"{label} = {value:.6g} s"))
    settle = math.ceil(scenario.settle / control_period - 1e-9) * control_period
    end = settle + scenario.duration
    expected = end / control_period + scenario.duration / record_period
    if expected > MAX_INSTANTS:
        key = "settle" if settle / control_period > scenario.duration / record_period else "duration"
        raise ConfigError(
            f"{scenario.place(key)}: scenario {scenario.name}'s settle {scenario.settle:g} s and duration "
            f"{scenario.duration:g} s at control period {control_period:.6g} s and record period "
            f"{record_period:.6g} s make {expected:.3g} instants; the limit is {MAX_INSTANTS:.0e} (shorten {key} "
            "or use longer periods)")
    samples = int(math.floor(scenario.duration / control_period * (1 + 1e-12) + 1e-9)) + 1
    if samples < MIN_CONTROL_SAMPLES:
        raise ConfigError(
            f"{scenario.place('duration')}: scenario {scenario.name} records {scenario.duration:g} s, which holds "
            f"{samples} controller sample(s) at control period {control_period:.6g} s: expected at least "
            f"{MIN_CONTROL_SAMPLES} (a shorter control period or a longer duration)")
    control_count = int(math.floor(end / control_period * (1 + 1e-12) + 1e-9)) + 1
    record_count = int(math.floor(scenario.duration / record_period * (1 + 1e-12) + 1e-9)) + 1
    events = np.array([settle + e.time for e in scenario.events if e.plant_event], dtype=float)
    return TimelinePlan(control_period, record_period, settle, end, control_count, record_count, events)


def build_timeline(scenario: Scenario, control_period: float, record_period: float) -> Timeline:
    """All merged instants of a run at once (fine for short runs; long runs iterate windows)."""
    plan = plan_timeline(scenario, control_period, record_period)
    if plan.instants > WHOLE_TIMELINE_LIMIT:
        raise ConfigError(f"scenario {scenario.name}: {plan.instants:.3g} instants are too many to hold at once; "
                          "iterate plan_timeline(...).windows() instead")
    return plan.window(0, plan.control_count)


def signal_at(timeline: Timeline, schedule: list[tuple[float, float]]) -> np.ndarray:
    """Value of a piecewise-constant scenario signal at every instant (events take effect at their time)."""
    event_times = np.array([timeline.settle + t for t, _ in schedule])
    values = np.array([v for _, v in schedule])
    index = np.searchsorted(event_times, timeline.times + MERGE_TOLERANCE, side="right") - 1
    index[index < 0] = 0  # the settle interval runs at the initial values
    return values[index]
