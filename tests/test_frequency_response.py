"""buck-cosim frequency-response: loop gain and output impedance measured by injection on the plant FMU,
against the averaged small-signal closed form (1 dB / 5 deg up to fsw/5) for the PI and the current-mode
design; the points run through the sweep engine (in-process here, on dask through the command line)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from conftest import cli, one_line_error

from cosim.design.frequency_response import ResponseSettings, interpolated_margins, measure, plan_points
from cosim.design.plants import plant_binding
from cosim.design.sweeps.spec import ControllerEntry
from cosim.design.vocabulary import SWITCHING_PERIOD

TS = SWITCHING_PERIOD
PI_ENTRY = ControllerEntry("pi", "PI", kp=0.007026878992716469, ki=172.92168103154324)
CMC_ENTRY = ControllerEntry("current-mode", "CMC")


def test_points_sit_on_whole_cycles_of_their_window():
    points = plan_points(ResponseSettings(points=12), TS)
    for p in points:
        cycles = p.frequency * p.samples * TS
        assert cycles == pytest.approx(round(cycles), abs=1e-9) and cycles >= 4
        assert p.start * p.frequency >= 3 - 1e-9
    assert [p.frequency for p in points] == sorted(p.frequency for p in points)


@pytest.mark.parametrize("entry", [PI_ENTRY, CMC_ENTRY], ids=["PI", "CMC"])
def test_loop_gain_on_the_switched_plant_matches_the_closed_form(entry, tmp_path):
    settings = ResponseSettings(points=7, low=200.0, high=15e3)
    table = measure(plant_binding("nominal", "switched"), entry, TS, settings, tmp_path)
    assert len(table) == 7 and (table["correlated_samples"] >= 75).all()
    assert table["magnitude_error_db"].abs().max() <= 1.0
    assert table["phase_error_deg"].abs().max() <= 5.0
    summary = table.attrs["summary"]
    assert summary["agreement_up_to_fsw_over_5"]["max_phase_error_deg"] <= 5.0
    # the loop crosses over inside the band and the measured margins bracket the closed form's
    measured, model = summary["measured"], summary["closed_form"]
    assert measured["crossover_hz"] == pytest.approx(model["crossover_hz"], rel=0.15)
    assert measured["phase_margin_deg"] == pytest.approx(model["phase_margin_deg"], abs=8.0)
    # the points are rows of a sweep dataset
    rows = pd.read_parquet(next(tmp_path.glob("dataset/**/part-*.parquet")))
    assert {"run_id", "status", "frequency_hz", "u_re", "d_im"} <= set(rows.columns)


def test_output_impedance_matches_the_closed_form(tmp_path):
    settings = ResponseSettings(injection="load", points=4, low=300.0, high=10e3)
    table = measure(plant_binding("nominal", "switched"), CMC_ENTRY, TS, settings, tmp_path)
    assert table["magnitude_error_db"].abs().max() <= 1.0
    assert table["phase_error_deg"].abs().max() <= 5.0


def test_interpolated_margins_of_a_sampled_integrator():
    """L = 1000/(j f) e^(-j 2 pi f 1e-4): crossover 1 kHz, PM = 90 - 36 = 54 deg, phase -180 at 2.5 kHz."""
    f = np.geomspace(100, 1e4, 60)
    values = 1000 / (1j * f) * np.exp(-2j * np.pi * f * 1e-4)
    m = interpolated_margins(f, values)
    assert m["crossover_hz"] == pytest.approx(1000, rel=1e-3)
    assert m["phase_margin_deg"] == pytest.approx(54.0, abs=0.2)
    assert m["gain_margin_db"] == pytest.approx(20 * math.log10(2.5), abs=0.1)


def test_command_line_refuses_frequencies_above_nyquist(tmp_path):
    done = cli("frequency-response", "--high", "40e3", "--out", str(tmp_path / "fr"))
    one_line_error(done, 2, "expected 0 < low < high < the Nyquist frequency 37500 Hz")
    assert not (tmp_path / "fr").exists()
