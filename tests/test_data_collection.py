"""Identification data: the paper's experiment, seeded, with the documented statistics."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.base import Measurement
from controllers.pi import PIController
from cosim.base.errors import ConfigError
from cosim.fmi.binding import builtin_binding
from cosim.results import read_parquet
from cosim.study.data_collection import SAMPLE_COLUMNS, CollectionSettings, collect, random_scenario

PI = PIController(0.003, 14.0, 1e-3)


@pytest.fixture(scope="module")
def samples():
    return collect(builtin_binding("averaged"), PI, CollectionSettings(samples=600, seed=4))


def test_one_row_per_control_sample_with_the_documented_columns(samples):
    assert len(samples) == 600 and list(samples.columns) == list(SAMPLE_COLUMNS)
    assert np.allclose(np.diff(samples["time"]), 1e-3)
    meta = samples.attrs["metadata"]
    assert meta["control_period_s"] == 1e-3 and meta["collection"]["seed"] == 4
    ok = samples["measured_output_voltage"] > 0.05
    np.testing.assert_allclose(samples.loc[ok, "load_conductance"],
                               samples.loc[ok, "measured_load_current"] / samples.loc[ok, "measured_output_voltage"])


def test_random_levels_are_held_for_the_documented_intervals():
    settings = CollectionSettings(samples=5000, seed=1, rest_probability=0.2)
    scenario = random_scenario(settings, 1e-3)
    for signal, (lo, hi) in (("reference", (0.0, 20.0)), ("load_resistance", (4.0, 10.0))):
        schedule = scenario.schedule(signal)
        times = np.array([t for t, _ in schedule])
        holds = np.round(np.diff(times) / 1e-3).astype(int)
        assert holds.min() >= 5 and holds.max() <= 40
        values = np.array([v for _, v in schedule])
        assert values.min() >= lo and values.max() <= hi
    references = np.array([v for _, v in scenario.schedule("reference")])
    assert 0.1 < np.mean(references == 0.0) < 0.3  # repeated start-ups from rest


def test_same_seed_same_data_other_seed_other_data(samples):
    again = collect(builtin_binding("averaged"), PI, CollectionSettings(samples=600, seed=4))
    assert again.equals(samples)
    other = collect(builtin_binding("averaged"), PI, CollectionSettings(samples=600, seed=5))
    assert not other["reference"].equals(samples["reference"])


def test_without_dither_the_duty_is_the_pis_own():
    data = collect(builtin_binding("averaged"), PI, CollectionSettings(samples=300, excitation=0.0))
    pi = PIController(0.003, 14.0, 1e-3)
    replay = [pi.step(Measurement(t, r, v)) for t, r, v in
              zip(data["time"], data["reference"], data["measured_output_voltage"])]
    np.testing.assert_allclose(data["duty_cycle"], replay, rtol=1e-12)


def test_saved_samples_keep_their_metadata(samples, tmp_path):
    from cosim.study.data_collection import save_samples

    save_samples(samples, tmp_path / "data.parquet")
    frame, meta = read_parquet(tmp_path / "data.parquet")
    assert frame.equals(samples.reset_index(drop=True)) and meta["plant"] == "BuckConverter (built-in, averaged)"


@pytest.mark.parametrize("kwargs,message", [
    ({"samples": 10}, "samples = 10 is too few"), ({"load_range": (5.0, 2.0)}, r"load range \(5.0, 2.0\) Ohm"),
    ({"hold_range": (0, 3)}, r"hold range \(0, 3\) periods"), ({"excitation": 0.9}, "excitation = 0.9"),
])
def test_invalid_settings_are_refused(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        collect(builtin_binding("averaged"), PI, CollectionSettings(**kwargs))


#: measured: 80 us per sample (5 000 samples at a 0 V reference in 0.39 s, averaged plant); 50 000
#: samples take ~4 s plus the interpreter's start. 20x that for a loaded machine. Before the averaged
#: plant's DCM current was solved algebraically, a 2 000 000-sample collection failed at t = 401 s (the
#: dithered PI commanded d = 1e-9) and duties of 1e-9 .. 1e-7 could hang a single step for minutes.
ZERO_REFERENCE_BOUND = 120.0


def test_a_collection_at_a_0_v_reference_finishes_in_bounded_time():
    """The dithered PI at a (mostly) 0 V reference drives the averaged plant through the tiniest duties
    (its integrator unwinding, the dither clipped at 0) in DCM, for 50 s of simulated time."""
    import json
    import subprocess
    import sys

    code = """
import json
import cosim
from controllers.pi import PIController
from cosim.fmi.binding import builtin_binding
from cosim.study.data_collection import CollectionSettings, collect
frame = collect(builtin_binding("averaged"), PIController(0.0017, 15.6, 1e-3),
                CollectionSettings(samples=50_000, rest_probability=0.95, seed=3))
duty = frame["duty_cycle"]
print(json.dumps({"rows": len(frame), "zero_reference": float((frame["reference"] == 0).mean()),
                  "smallest": float(duty[duty > 0].min()), "below_1e-4": int(((duty > 0) & (duty < 1e-4)).sum())}))
"""
    try:
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=ZERO_REFERENCE_BOUND)
    except subprocess.TimeoutExpired:
        pytest.fail(f"a 50 000-sample collection at a 0 V reference took more than {ZERO_REFERENCE_BOUND:g} s")
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["rows"] == 50_000 and result["zero_reference"] > 0.9
    assert result["smallest"] < 1e-5 and result["below_1e-4"] > 10  # the regime the issue is about was visited
