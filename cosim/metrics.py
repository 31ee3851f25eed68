"""Control-quality metrics of a run, with the definitions a control engineer expects.

The metrics window starts at the scenario's ``metrics_start`` (t0: the first event, or 0 for
start-up) and ends with the run. y is the output voltage, r the reference in effect, e = r - y,
y0 = y(t0), r_f = the reference at the end of the run. A run is a *step* when
|r_f - y0| > 2 % of r_f (start-up, reference changes) and a *regulation* run otherwise (load or
supply disturbances at constant reference).

* ``rise_time_ms`` -- step only: time from first reaching y0 + 10 % (r_f - y0) to the crossing of
  y0 + 90 % (r_f - y0) after which the output stays beyond it to the end of the window -- the rise an engineer reads
  off the trace. (python-control's ``RiseTime`` takes the *first* 90 % crossing: at a 1 ms sample period the LC
  ring of the first sample crosses it within 0.1 ms before the output falls back to 77 % and rises for
  milliseconds.) NaN for regulation runs, and where the output ends short of 90 %.
* ``overshoot_pct`` -- step: largest excursion beyond r_f in the direction of the step, in % of
  |r_f - y0|; regulation: largest excursion above r, in % of r.
* ``undershoot_pct`` -- step: largest excursion from y0 *against* the step direction, in % of
  |r_f - y0|; regulation: largest excursion below r, in % of r.
* ``settling_time_ms`` -- time after t0 at which |y - r_f| last leaves a band of 2 % of r_f;
  0 if it never leaves, NaN if it is outside the band at the end.
* ``steady_state_error_V`` / ``_pct`` -- mean of e over the uniform recording grid in the last
  quarter of the window, at most 5 ms (375 PWM periods; rows added only for control samples are
  left out, as they all sit at one PWM phase), in volts and in % of r_f.
* ``iae_Vs``, ``ise_V2s``, ``itae_Vs2`` -- integrals of |e|, e^2 and (t - t0)|e| over the window
  (trapezoidal rule on the recording grid).
* ``peak_inductor_current_A`` -- largest inductor current in the window.
* ``output_voltage_ripple_mV`` / ``inductor_current_ripple_A`` -- peak to peak of the instantaneous
  vo and iL (``output_voltage``, ``inductor_current``) over the steady-state window of the
  steady-state error, every recorded row: the switching ripple plus what is left of the transient.
  As the recording grid resolves it: record at 1/20 of a PWM period or finer
  (``--record-period 6.67e-7`` at 75 kHz) for the true ripple; the default 10 us grid lands on four
  phases of a 13.33 us period only. 0 on an averaged plant in steady state.
* ``duty_saturation_ms`` -- time in the window with the duty at either controller limit.
* ``controller_p50_us`` / ``controller_p99_us`` -- median and 99th percentile of the controller's
  wall-clock compute time per sample over the recorded run.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from cosim.results import RunResult

SETTLING_BAND = 0.02
STEP_THRESHOLD = 0.02
STEADY_STATE_WINDOW = 5e-3  # [s]

METRIC_COLUMNS = (
    "rise_time_ms",
    "overshoot_pct",
    "undershoot_pct",
    "settling_time_ms",
    "steady_state_error_V",
    "steady_state_error_pct",
    "iae_Vs",
    "ise_V2s",
    "itae_Vs2",
    "peak_inductor_current_A",
    "output_voltage_ripple_mV",
    "inductor_current_ripple_A",
    "duty_saturation_ms",
    "controller_p50_us",
    "controller_p99_us",
)
#: metrics that are wall-clock measurements: they differ from run to run, so tables written to
#: files keep them apart (``<stem>.timing.csv``) from the byte-comparable ones
WALLCLOCK_METRICS = ("controller_p50_us", "controller_p99_us")
#: the columns of :func:`metrics_table` that identify a run
LABEL_COLUMNS = ("scenario", "controller", "plant", "interface", "control_period_us", "complete")


def _first_crossing(t: np.ndarray, y: np.ndarray, level: float, rising: bool) -> float:
    reached = y >= level if rising else y <= level
    index = int(np.argmax(reached))
    if not reached[index]:
        return math.nan
    if index == 0:
        return float(t[0])
    y0, y1 = y[index - 1], y[index]  # linear interpolation between samples
    fraction = (level - y0) / (y1 - y0) if y1 != y0 else 1.0
    return float(t[index - 1] + fraction * (t[index] - t[index - 1]))


def _final_entry(t: np.ndarray, y: np.ndarray, level: float) -> float:
    """When ``y`` reaches ``level`` for the last time, staying at or above it to the end (linear interpolation
    between samples); NaN if it ends below, ``t[0]`` if it never is below."""
    below = y < level
    if below[-1]:
        return math.nan
    if not below.any():
        return float(t[0])
    last = int(np.nonzero(below)[0][-1])
    y0, y1 = y[last], y[last + 1]
    fraction = (level - y0) / (y1 - y0) if y1 != y0 else 1.0
    return float(t[last] + fraction * (t[last + 1] - t[last]))


def _trapezoid(t: np.ndarray, values: np.ndarray) -> float:
    return float(np.trapezoid(values, t)) if len(t) > 1 else 0.0


def signal_metrics(t: np.ndarray, y: np.ndarray, r: np.ndarray, t0: float = 0.0,
                   regular: np.ndarray | None = None) -> dict[str, float]:
    """Step/regulation metrics of output ``y`` against reference ``r`` on the window ``t >= t0``.

    ``regular`` marks the rows of the uniform recording grid; the steady-state error averages over
    those only (extra rows at control samples all sit at one PWM phase and would bias it).
    """
    window = t >= t0 - 1e-12
    t, y, r = t[window], y[window], r[window]
    regular = np.ones(len(t), dtype=bool) if regular is None else np.asarray(regular)[window]
    y0, r_final = float(y[0]), float(r[-1])
    e = r - y
    step = abs(r_final - y0) > STEP_THRESHOLD * abs(r_final)
    out: dict[str, float] = {}
    if step:
        delta = r_final - y0
        sign = 1.0 if delta > 0 else -1.0
        t10 = _first_crossing(t, sign * y, sign * (y0 + 0.1 * delta), rising=True)
        t90 = _final_entry(t, sign * y, sign * (y0 + 0.9 * delta))
        out["rise_time_ms"] = (t90 - t10) * 1e3
        out["overshoot_pct"] = max(0.0, float(np.max(sign * (y - r_final)))) / abs(delta) * 100
        out["undershoot_pct"] = max(0.0, float(np.max(sign * (y0 - y)))) / abs(delta) * 100
    else:
        scale = abs(r_final) if r_final else 1.0
        out["rise_time_ms"] = math.nan
        out["overshoot_pct"] = max(0.0, float(np.max(y - r))) / scale * 100
        out["undershoot_pct"] = max(0.0, float(np.max(r - y))) / scale * 100
    band = SETTLING_BAND * abs(r_final)
    outside = np.abs(y - r_final) > band
    if not outside.any():
        out["settling_time_ms"] = 0.0
    elif outside[-1]:
        out["settling_time_ms"] = math.nan
    else:
        last = int(np.nonzero(outside)[0][-1])
        out["settling_time_ms"] = (t[last + 1] - t0) * 1e3
    window_length = min(STEADY_STATE_WINDOW, 0.25 * (t[-1] - t0))
    tail = (t >= t[-1] - window_length + 1e-12) & regular
    sse = float(np.mean(e[tail])) if tail.any() else float(e[-1])
    out["steady_state_error_V"] = sse
    out["steady_state_error_pct"] = sse / abs(r_final) * 100 if r_final else math.nan
    out["iae_Vs"] = _trapezoid(t, np.abs(e))
    out["ise_V2s"] = _trapezoid(t, e * e)
    out["itae_Vs2"] = _trapezoid(t, (t - t0) * np.abs(e))
    return out


def run_metrics(result: RunResult) -> dict[str, float]:
    """All metrics of one run (see the module docstring for the definitions)."""
    frame, info = result.frame, result.info
    t0 = info.metrics_start
    t = frame["time"].to_numpy()
    regular = None
    if info.record_period > 0:
        phase = t / info.record_period
        regular = np.abs(phase - np.round(phase)) < 1e-6
    out = signal_metrics(t, frame["output_voltage"].to_numpy(), frame["reference"].to_numpy(), t0, regular)
    window = t >= t0 - 1e-12
    current = frame["inductor_current"].to_numpy()[window]
    out["peak_inductor_current_A"] = float(np.nanmax(current)) if np.isfinite(current).any() else math.nan
    end = float(t[-1]) if len(t) else t0
    tail = t >= end - min(STEADY_STATE_WINDOW, 0.25 * (end - t0)) - 1e-12  # the steady-state error's window
    for column, name, factor in (("output_voltage", "output_voltage_ripple_mV", 1e3),
                                 ("inductor_current", "inductor_current_ripple_A", 1.0)):
        values = frame[column].to_numpy()[tail]
        values = values[np.isfinite(values)]
        out[name] = float(np.ptp(values)) * factor if len(values) else math.nan
    low, high = info.duty_limits
    duty = frame["duty_cycle"].to_numpy()[window]
    tw = t[window]
    saturated = (duty <= low + 1e-9) | (duty >= high - 1e-9)
    out["duty_saturation_ms"] = float(np.sum(np.diff(tw) * saturated[:-1])) * 1e3 if len(tw) > 1 else 0.0
    compute = frame.loc[frame["control_sample"], "controller_compute_time"].to_numpy() \
        if "controller_compute_time" in frame else np.array([])
    compute = compute[np.isfinite(compute)]
    out["controller_p50_us"] = float(np.percentile(compute, 50)) * 1e6 if len(compute) else math.nan
    out["controller_p99_us"] = float(np.percentile(compute, 99)) * 1e6 if len(compute) else math.nan
    return {name: out[name] for name in METRIC_COLUMNS}


#: a run looks implausible -- a binding with wrong units or signs, a controller far off -- when its
#: duty sits at a limit for this share of the metrics window or more ...
IMPLAUSIBLE_SATURATION = 0.5
#: ... or its steady state is this far from the reference [% of the final reference] or more
IMPLAUSIBLE_ERROR_PCT = 10.0
#: an inductor current averaging this many times the load current vo / R over the run's last fifth is implausible:
#: there the two agree (the capacitor's mean current is ~0), and a current read in mA bound without scale = 1000
#: reads 1000 x (the start-up's peak is no measure: it charges the capacitor, 22 x a 200 Ohm load's current)
IMPLAUSIBLE_CURRENT_RATIO = 20.0


def implausible_runs(results: list[RunResult], table: pd.DataFrame) -> list[str]:
    """What looks wrong in each complete run of ``results`` (``table``: their :func:`metrics_table`,
    same order): the duty at a limit for at least :data:`IMPLAUSIBLE_SATURATION` of the metrics
    window, a steady-state error of at least :data:`IMPLAUSIBLE_ERROR_PCT` % -- a duty in percent
    bound without ``scale = 100`` shows both -- or an inductor current averaging above
    :data:`IMPLAUSIBLE_CURRENT_RATIO` times the load current at the end of the run (a current in mA bound without
    ``scale = 1000``). One phrase per run, e.g. ``"startup with PI: duty at a
    limit for 83 % of the window, steady state 96 % below the reference"``."""
    found = []
    for result, (_, row) in zip(results, table.iterrows()):
        if not result.complete or result.streamed or not len(result.frame):
            continue
        window_ms = (float(result.frame["time"].iloc[-1]) - result.info.metrics_start) * 1e3
        share = row["duty_saturation_ms"] / window_ms if window_ms > 0 else 0.0
        error = row["steady_state_error_pct"]
        signs = []
        if share >= IMPLAUSIBLE_SATURATION:
            signs.append(f"duty at a limit for {share * 100:.0f} % of the window")
        if math.isfinite(error) and abs(error) >= IMPLAUSIBLE_ERROR_PCT:
            signs.append(f"steady state {abs(error):.0f} % {'below' if error > 0 else 'above'} the reference")
        frame = result.frame
        if "inductor_current" in frame:  # over the last fifth of the run the mean inductor current is the load's
            start, end = float(frame["time"].iloc[0]), float(frame["time"].iloc[-1])
            tail = frame[frame["time"] >= start + 0.8 * (end - start)]
            load = float((tail["output_voltage"] / tail["load_resistance"]).mean())
            current = float(tail["inductor_current"].mean())
            if load > 0 and abs(current) > IMPLAUSIBLE_CURRENT_RATIO * load:
                signs.append(f"inductor current {current:.4g} A on average over the run's last fifth, "
                             f"{abs(current) / load:.0f} x the load current vo/R ({load:.3g} A)")
        if signs:
            found.append(f"{result.info.scenario} with {result.info.controller}: {', '.join(signs)}")
    return found


def run_label(result: RunResult) -> dict[str, object]:
    """Identifying columns of a run for metrics tables."""
    info = result.info
    return {
        "scenario": info.scenario,
        "controller": info.controller,
        "plant": info.plant,
        "interface": info.interface,
        "control_period_us": info.control_period * 1e6,
        "complete": result.complete,
    }


def metrics_table(results: list[RunResult]) -> pd.DataFrame:
    """One row per run: identifying columns, then :data:`METRIC_COLUMNS`."""
    rows = [{**run_label(r), **run_metrics(r)} for r in results]
    return pd.DataFrame(rows)
