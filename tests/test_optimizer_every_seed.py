"""The every-seed evaluation's files (results/optimizer-every-seed.csv and .md) and its command's checks."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
from conftest import script, script_refusal

from cosim.study.optimizer_every_seed import REPORT_NAME, TABLE_NAME, report, table, write_tables

ROOT = Path(__file__).resolve().parents[1]


def row(pipeline, seed, controller, scenario, ratio, overshoot=0.0, excess=(-0.5, 0.02), search_cost=0.01):
    excess = np.array(excess, dtype=float)
    return {"scenario": scenario, "controller": controller, "samples": 100, "iae_search_Vs": 1e-3,
            "iae_rti_Vs": 1e-3 * ratio, "iae_ratio": ratio, "closed_loop_cost_search_Vs": 2e-3,
            "closed_loop_cost_rti_Vs": 2e-3, "overshoot_search_pct": 1.0, "overshoot_rti_pct": 1.0 + overshoot,
            "overshoot_difference_points": overshoot, "plan_cost_rti_mean": 0.1,
            "cost_excess_median": float(np.median(excess)) if len(excess) else math.nan,
            "cost_excess_worst": float(np.max(excess)) if len(excess) else math.nan,
            "search_cost_at_worst": search_cost if len(excess) else math.nan, "cost_excess": excess,
            "search_samples": 4, "fallbacks": {"start-up": 3, "cold start": 1}, "qp_iterations_max": 5,
            "pipeline": pipeline, "seed": seed}


def test_the_tables_give_each_run_a_line_and_each_pipeline_and_controller_its_spread_and_verdict(tmp_path):
    rows = [row("p13", 0, "NNPC", "startup", 0.98, overshoot=0.3, excess=(-0.9, -0.2, 3.0), search_cost=2e-15),
            row("p13", 1, "NNPC", "startup", 1.01, excess=(-0.4, 0.0)),
            row("p13", 2, "NNPC", "reference_up", 1.00),
            row("p13", 0, "MPC-oracle", "startup", 1.03, overshoot=0.7)]
    write_tables(tmp_path, rows, complete=True, command="scripts/optimizer_every_seed.py --out results")
    csv = pd.read_csv(tmp_path / TABLE_NAME)
    assert list(csv.columns[:4]) == ["pipeline", "seed", "controller", "scenario"]
    assert "cost_excess" not in csv.columns  # the per-sample array stays out
    assert len(csv) == 4 and csv["iae_ratio"].tolist() == [0.98, 1.01, 1.0, 1.03]
    assert json.loads(csv["fallbacks"][0]) == {"cold start": 1, "start-up": 3}
    lines = (tmp_path / REPORT_NAME).read_text().splitlines()
    assert lines[0] == "# The RTI against the search on every seed"
    assert "Command: `scripts/optimizer_every_seed.py --out results`" in lines[2]
    table_lines = [line for line in lines if line.startswith(("| p13", "| **all**"))]
    # the NNPC: IAE ratio min / median / max over its three runs, the worst overshoot increase, the excess pooled
    # over its 7 RTI samples (median -0.2, worst 3.0 where the search's plan cost 2e-15), 12 of 300 samples searched
    assert table_lines[0] == ("| p13 | NNPC | 0, 1, 2 | 3 | 0.9800 / 1.0000 / 1.0100 | +0.30 | -20.00 / 300.0 "
                              "(the search's plan: 2e-15) | 4.0 | yes |")
    assert table_lines[1].startswith("| p13 | MPC-oracle | 0 | 1 | 1.0300 / 1.0300 / 1.0300 | +0.70 |")
    assert table_lines[1].endswith("| **no** |")  # IAE 1.03 > 1.02 and +0.7 points > 0.5
    assert table_lines[2].startswith("| **all** | all | 0, 1, 2 | 4 | 0.9800 / 1.0050 / 1.0300 | +0.70 |")
    assert table_lines[2].endswith("| **no** |")


def test_an_unfinished_or_unaudited_evaluation_says_so():
    rows = [row("p1", 0, "NNPC", "startup", 1.0, excess=())]
    text = report(rows, complete=False, command="c")
    assert text.splitlines()[0] == "# The RTI against the search on every seed (INCOMPLETE: the run was stopped)"
    assert "| p1 | NNPC | 0 | 1 | 1.0000 / 1.0000 / 1.0000 | +0.00 | not audited | 4.0 | yes (IAE, overshoot) |" in text
    assert table([]).empty


def run_script(argv, capsys):
    return script_refusal("optimizer_every_seed", argv, capsys)


def test_the_command_refuses_bad_arguments_in_one_line_before_any_simulation(tmp_path, capsys):
    assert run_script(["--seeds", "0,7"], capsys) == (
        2, "optimizer_every_seed.py: error: --seeds: '7' is not a study seed (expected some of 0, 1, 2, 3, 4)")
    code, line = run_script(["--pipelines", "nominal-averaged__2ms"], capsys)
    assert code == 2 and line.startswith("optimizer_every_seed.py: error: --pipelines: 'nominal-averaged__2ms' is not "
                                         "a pipeline of the reproduction (expected one of nominal-averaged__1ms, ")
    assert run_script(["--results", str(tmp_path)], capsys) == (
        2, f"optimizer_every_seed.py: error: --results {tmp_path}: no models folder there (run make reproduce first)")
    assert run_script(["--rti", "iterations=4"], capsys) == (
        2, "optimizer_every_seed.py: error: --rti iterations=4: RTI iterations = 4 is invalid: expected 1, 2 or 3 (a "
           "fixed count per sample)")


def test_one_pipeline_of_the_committed_results_evaluates_and_meets_the_targets(tmp_path):
    """The committed reproduction's 1 ms averaged-plant models, seed 0, audited: 12 runs (the NNPC and both MPC
    baselines, four scenarios), written as they come and complete at the end."""
    optimizer_every_seed = script("optimizer_every_seed")
    assert optimizer_every_seed.main(["--results", str(ROOT / "results"), "--pipelines", "nominal-averaged__1ms",
                                      "--seeds", "0", "--out", str(tmp_path)]) == 0
    csv = pd.read_csv(tmp_path / TABLE_NAME)
    assert len(csv) == 12 and set(csv["controller"]) == {"NNPC", "MPC-oracle", "MPC-mismatched"}
    assert (csv["iae_ratio"] <= 1.02).all() and (csv["samples"] > 0).all()
    text = (tmp_path / REPORT_NAME).read_text()
    assert "INCOMPLETE" not in text
    assert text.splitlines()[-1].startswith("| **all** | all | 0 | 12 |") and text.splitlines()[-1].endswith("| yes |")


def test_every_built_in_pipeline_is_evaluated_on_every_study_seed_and_an_external_plant_on_seed_0():
    from cosim.study.reproduce import FULL, PIPELINES, Pipeline

    assert FULL.seeds == (0, 1, 2, 3, 4)
    assert {p.study_seeds for p in PIPELINES} == {FULL.seeds}
    external = Pipeline("bound", "switched", 1e-3, binding_file=str(ROOT / "no-such-binding.toml"))
    assert external.study_seeds == (0,)


def test_a_seed_network_the_reproduction_saved_is_loaded_not_identified_again(tmp_path, monkeypatch):
    """The drift study's and the envelope map's plants at one switching period: a seed's network is the one the
    reproduction's seed job saved in models/ (the same weights a new identification gives), so the evaluation reads
    it instead of identifying it into its cache."""
    import shutil

    from cosim.design import identification
    from cosim.study.optimizer_every_seed import seed_model
    from cosim.study.reproduce import DRIFT_PIPELINE, SEED_MODEL_PIPELINES

    def never(*args, **kwargs):
        raise AssertionError("identified again")

    monkeypatch.setattr(identification, "identify", never)
    name = f"{DRIFT_PIPELINE.tag}__nnpc__seed2.pt"
    (tmp_path / "models").mkdir()
    shutil.copy(ROOT / "results" / "models" / name, tmp_path / "models" / name)
    assert DRIFT_PIPELINE.tag in SEED_MODEL_PIPELINES
    model = seed_model(DRIFT_PIPELINE, 2, tmp_path, tmp_path / "cache")
    assert model.metadata["seed"] == 2 and model.metadata["design"]["key"]
    assert not (tmp_path / "cache").exists()
