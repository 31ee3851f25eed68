"""Run tables: CSV and Parquet round trips, metadata and units inside the files, atomic writes."""

from __future__ import annotations

import json

import pandas as pd
import pyarrow.parquet as pq
import pytest

from controllers.pi import PIController
from cosim.fmi.binding import builtin_binding
from cosim.master import simulate
from cosim.recorder import COLUMNS
from cosim.results import read_run, write_run
from cosim.scenarios import load_scenario
from cosim.study.vocabulary import PAPER_SPEC


@pytest.fixture(scope="module")
def result():
    scenario = load_scenario("reference_up", PAPER_SPEC)
    return simulate(builtin_binding("switched"), PIController(0.0, 14.0, 1e-3), scenario, seed=7)


def test_frame_has_the_documented_columns_and_metadata(result):
    assert list(result.frame.columns) == list(COLUMNS)
    meta = result.metadata
    assert meta["complete"] is True and meta["seed"] == 7
    assert meta["scenario"]["name"] == "reference_up"
    assert meta["controller"]["type"] == "PI" and meta["controller"]["ki_per_V_s"] == 14.0
    assert meta["plant"]["parameters"]["plant_mode"] == 1 and meta["plant"]["interface"] == "co-simulation"
    assert meta["rates"] == {"control_period_s": 1e-3, "record_period_s": 1e-5}
    assert {"fmpy", "numpy", "pandas", "torch", "python"} <= set(meta["versions"])
    assert meta["units"]["output_voltage"] == "V"


@pytest.mark.parametrize("kind", ["parquet", "csv"])
def test_round_trip_gives_the_same_frame_and_metadata(result, tmp_path, kind):
    paths = write_run(result, tmp_path, "run")
    back = read_run(paths[kind])
    pd.testing.assert_frame_equal(back.frame, result.frame, check_exact=True)
    assert back.metadata == result.metadata


def test_a_stem_given_with_a_run_files_ending_names_the_run_without_it(result, tmp_path):
    paths = write_run(result, tmp_path, "startup.parquet")  # was startup.parquet.parquet, .csv, ...
    assert sorted(p.name for p in tmp_path.iterdir()) == ["startup.csv", "startup.json", "startup.parquet",
                                                          "startup.timing.csv"]
    assert paths["parquet"] == tmp_path / "startup.parquet"


def test_parquet_carries_units_per_field_and_metadata_in_the_schema(result, tmp_path):
    path = write_run(result, tmp_path, "run")["parquet"]
    schema = pq.read_schema(path)
    assert schema.field("output_voltage").metadata[b"unit"] == b"V"
    assert schema.field("inductor_current").metadata[b"unit"] == b"A"
    assert json.loads(schema.metadata[b"buck_cosim"])["scenario"]["name"] == "reference_up"
    assert "controller_compute_time" not in schema.names  # wall clock lives in the timing file


def test_csv_has_a_json_sidecar_and_the_values_as_text(result, tmp_path):
    paths = write_run(result, tmp_path, "run")
    header = paths["csv"].read_text().splitlines()[0].split(",")
    assert header == [c for c in COLUMNS if c != "controller_compute_time"]
    assert json.loads(paths["json"].read_text())["complete"] is True
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.csv", "run.json", "run.parquet", "run.timing.csv"]


def test_same_run_twice_gives_byte_identical_tables(tmp_path):
    pi = PIController(0.0, 14.0, 1e-3)
    for folder in ("a", "b"):
        r = simulate(builtin_binding("averaged"), pi, load_scenario("load_change", PAPER_SPEC), seed=1)
        write_run(r, tmp_path / folder, "run")
    for name in ("run.csv", "run.parquet", "run.json"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
