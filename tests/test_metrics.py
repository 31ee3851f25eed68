"""Metrics against signals whose metrics are known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from cosim.metrics import METRIC_COLUMNS, run_metrics, signal_metrics
from cosim.recorder import COLUMNS
from cosim.results import RunInfo, RunResult

TAU = 1e-3
T = np.arange(0, 0.04 + 1e-12, 1e-6)


def test_first_order_step():
    y = 12.0 * (1 - np.exp(-T / TAU))
    m = signal_metrics(T, y, np.full_like(T, 12.0))
    assert m["rise_time_ms"] == pytest.approx(TAU * math.log(9) * 1e3, rel=1e-4)
    assert m["settling_time_ms"] == pytest.approx(TAU * math.log(50) * 1e3, rel=1e-3)
    assert m["overshoot_pct"] == 0.0 and m["undershoot_pct"] == 0.0
    assert m["iae_Vs"] == pytest.approx(12 * TAU, rel=1e-6)
    assert m["ise_V2s"] == pytest.approx(144 * TAU / 2, rel=1e-6)
    assert m["itae_Vs2"] == pytest.approx(12 * TAU**2, rel=1e-5)
    assert m["steady_state_error_V"] == pytest.approx(0.0, abs=1e-9)


def test_rise_time_ends_where_the_output_stays_above_90_percent():
    """A staircase, as a 1 ms loop's start-up: the first sample's LC ring crosses 90 % within 0.1 ms, the output
    falls back to 77 % and then rises for milliseconds. The rise time ends at the 90 % crossing after which it stays
    above -- not at the ring's first crossing."""
    tau, t1 = 1e-3, 0.2e-3
    ring = np.interp(T, [0.0, 0.1e-3, t1], [0.0, 0.95 * 12, 0.77 * 12])
    y = np.where(T < t1, ring, 12 * (0.77 + 0.23 * (1 - np.exp(-(T - t1) / tau))))
    m = signal_metrics(T, y, np.full_like(T, 12.0))
    t10 = 0.1e-3 * 1.2 / (0.95 * 12)
    assert m["rise_time_ms"] == pytest.approx((t1 + tau * math.log(0.23 / 0.10) - t10) * 1e3, rel=1e-4)
    assert m["rise_time_ms"] > 1.0  # python-control's first crossing would say 0.09 ms
    short = signal_metrics(T, np.minimum(y, 10.0), np.full_like(T, 12.0))
    assert math.isnan(short["rise_time_ms"])  # never stays above 90 %: no rise time


def test_second_order_overshoot_matches_the_damping_formula():
    zeta, wn = 0.39, 2 * math.pi * 3390
    wd = wn * math.sqrt(1 - zeta**2)
    y = 12 * (1 - np.exp(-zeta * wn * T) * (np.cos(wd * T) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * T)))
    m = signal_metrics(T, y, np.full_like(T, 12.0))
    assert m["overshoot_pct"] == pytest.approx(100 * math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2)), rel=1e-4)
    assert 0.3 < m["settling_time_ms"] < 0.6  # the LC transient settles in ~0.5 ms


def test_negative_step_with_undershoot_and_offset():
    t0 = 0.005
    y = np.where(T < t0, 12.0, 9.1 + 2.9 * np.exp(-(T - t0) / TAU))
    y[(T > t0 + 1e-5) & (T < t0 + 1e-4)] = 12.3  # goes the wrong way first: 0.3 V of a 2.9 V step
    r = np.where(T < t0, 12.0, 9.0)
    m = signal_metrics(T, y, r, t0)
    assert m["undershoot_pct"] == pytest.approx(0.3 / 3.0 * 100, rel=1e-9)
    assert m["overshoot_pct"] == 0.0
    assert m["steady_state_error_V"] == pytest.approx(-0.1, rel=1e-6)
    assert m["steady_state_error_pct"] == pytest.approx(-0.1 / 9 * 100, rel=1e-6)
    assert math.isnan(m["settling_time_ms"]) is False


def test_regulation_run_uses_percent_of_reference_and_no_rise_time():
    y = 12.0 - 0.6 * np.exp(-T / TAU) * (T > 0)
    m = signal_metrics(T, y, np.full_like(T, 12.0))
    assert math.isnan(m["rise_time_ms"])
    assert m["undershoot_pct"] == pytest.approx(5.0, rel=1e-3)
    assert m["settling_time_ms"] == pytest.approx(TAU * math.log(0.6 / 0.24) * 1e3, rel=1e-3)


def test_unsettled_signal_has_nan_settling_time():
    m = signal_metrics(T, 12.0 * (1 - np.exp(-T / 0.1)), np.full_like(T, 12.0))
    assert math.isnan(m["settling_time_ms"])


def test_run_metrics_saturation_and_compute_percentiles():
    n = 1001
    t = np.linspace(0, 0.01, n)
    data = np.zeros((n, len(COLUMNS)))
    frame = pd.DataFrame(data, columns=list(COLUMNS))
    frame["time"] = t
    frame["reference"] = 12.0
    frame["output_voltage"] = 12.0
    frame["inductor_current"] = 2.0 + (t > 0.005)
    frame["duty_cycle"] = np.where(t < 0.002, 1.0, 0.25)  # saturated for the first 2 ms
    frame["control_sample"] = np.arange(n) % 100 == 0
    frame["controller_compute_time"] = np.where(frame["control_sample"], np.arange(n) * 1e-8, np.nan)
    info = RunInfo(scenario="s", description="", metrics_start=0.0, controller="c", control_period=1e-3,
                   record_period=1e-5, duty_limits=(0.0, 1.0), plant="p", plant_mode=None, interface="co-simulation")
    result = RunResult(frame, info, complete=True)
    m = run_metrics(result)
    assert list(m) == list(METRIC_COLUMNS)
    assert m["duty_saturation_ms"] == pytest.approx(2.0, abs=0.011)
    assert m["peak_inductor_current_A"] == 3.0
    samples = np.arange(0, n, 100) * 1e-8
    assert m["controller_p50_us"] == pytest.approx(np.percentile(samples, 50) * 1e6)
    assert m["controller_p99_us"] == pytest.approx(np.percentile(samples, 99) * 1e6)


def test_steady_state_error_uses_the_regular_grid_only():
    fsw = 75e3
    regular = np.arange(0, 0.01, 1e-5)
    extra = np.arange(0, 0.01, 1 / fsw)  # control samples, always at the same PWM phase
    extra = extra[np.abs(extra / 1e-5 - np.round(extra / 1e-5)) > 1e-6]  # the master merges coincident ones
    t = np.sort(np.concatenate([regular, extra]))
    y = 12.0 + 0.05 * np.cos(2 * np.pi * fsw * t)  # the extra rows all sit on the ripple's crest
    on_grid = np.abs(t / 1e-5 - np.round(t / 1e-5)) < 1e-6
    m = signal_metrics(t, y, np.full_like(t, 12.0), regular=on_grid)
    assert abs(m["steady_state_error_V"]) < 5e-4  # a partial 40 us phase cycle at most
    assert abs(np.mean(12.0 - y[t >= 0.005])) > 1e-2  # all rows would report a 10+ mV error
