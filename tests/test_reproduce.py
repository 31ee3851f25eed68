"""The reproduction end to end on the quick profile: every artefact is written and the report is complete."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from cosim.cli import main
from cosim.study.reproduce import QUICK


@pytest.fixture(scope="module")
def reproduction(tmp_path_factory):
    out = tmp_path_factory.mktemp("results")
    assert main(["--no-progress", "reproduce", "--quick", "--out", str(out)]) == 0
    return out


def test_every_pipeline_writes_data_models_runs_metrics_and_figures(reproduction):
    for tag in QUICK.pipelines:
        assert (reproduction / "data" / f"{tag}.parquet").is_file()
        for name in ("nnpc", "nnpc-paper"):
            assert (reproduction / "models" / f"{tag}__{name}.pt").is_file()
        summary = json.loads((reproduction / "pipelines" / f"{tag}.json").read_text())
        assert summary["pi"]["kp"] >= 0 and "held_out_rmse" in summary["models"]["nnpc"]
        plant, rate = tag.split("__")
        for scenario in QUICK.scenarios:
            assert (reproduction / "figures" / f"{scenario}__{plant}__{rate}.png").is_file()
            assert (reproduction / "runs" / f"{scenario}__nnpc__{plant}__{rate}.parquet").is_file()
    metrics = pd.read_csv(reproduction / "metrics" / "metrics_all.csv")
    controllers = set(metrics["controller"])
    assert {"PI", "NNPC", "NNPC-paper", "MPC-oracle", "MPC-mismatched", "MPC-nominal", "NNPC (N=3)",
            "MPC-oracle (averaged model)", "MPC-oracle (sync. sample)", "NNPC (seed 1)"} <= controllers
    # + the ablations: N = 3 at 1 ms; eq. 3, sync. sample and an NNPC from other seeded data at 13.33 us
    assert len(metrics) == 4 * 2 * 5 + 2 + 2 + 2 + 2
    seed_study = metrics[metrics["controller"] == "NNPC (seed 1)"]
    assert set(seed_study["pipeline"]) == {"nominal-switched__13p33us"}
    assert (reproduction / "runs" / "startup__nnpc-seed-1__nominal-switched__13p33us.parquet").is_file()


def test_report_has_every_section_and_checks_the_targets(reproduction):
    report = (reproduction / "REPORT.md").read_text()
    for heading in ("## Summary", "## Targets", "## Setup", "## PI gains", "## NN identification",
                    "## Results at the paper's rate", "## Results at one switching period", "## Ablations",
                    "## Discussion", "## Reproducing"):
        assert heading in report
    assert "Quick profile" in report
    targets = pd.read_csv(reproduction / "targets.csv")
    assert set(targets["met"]) <= {"yes", "**no**"}
    timing = targets[targets["target"].str.contains("Whole reproduction")]
    assert timing["met"].tolist() == ["yes"]  # the quick profile is far below 120 s
    assert targets["target"].str.contains("NNPC IAE <= 1.10 x oracle-MPC IAE").any()
    overshoot = targets[targets["target"] == "NNPC start-up overshoot <= 5 % at 1/fsw, switched"]
    assert overshoot["note"].iloc[0].startswith("NNPC identified from other seeds' data: NNPC (seed 1): ")
    assert "**Seed sensitivity at 13.33 us**" in report
    for figure in report.split("](figures/")[1:]:
        assert (reproduction / "figures" / figure.split(")")[0]).is_file()


def test_resume_keeps_finished_pipelines(reproduction, capsys):
    assert main(["--no-progress", "reproduce", "--quick", "--resume", "--out", str(reproduction)]) == 0
    assert capsys.readouterr().err.count("finished earlier, kept (--resume)") == len(QUICK.pipelines)
