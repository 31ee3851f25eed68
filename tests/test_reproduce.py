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
    assert not targets["target"].str.contains("Whole reproduction|compute per step").any()  # wall clock: timings
    assert targets["target"].str.contains("NNPC IAE <= 1.10 x oracle-MPC IAE").any()
    overshoot = targets[targets["target"] == "NNPC start-up overshoot <= 5 % at 1/fsw, switched"]
    assert overshoot["note"].iloc[0].startswith("NNPC identified from other seeds' data: NNPC (seed 1): ")
    assert "**Seed sensitivity at 13.33 us**" in report
    for figure in report.split("](figures/")[1:]:
        assert (reproduction / "figures" / figure.split(")")[0]).is_file()


def test_the_tolerance_study_runs_the_pipelines_controllers_on_production_units(reproduction):
    """The nominal switched 1 ms pipeline's own PI and NNPC (and the nominal MPC) on QUICK's units,
    through the sweep engine; its yield table and figures in the report."""
    import hashlib

    from cosim.study.sweeps.dataset import read_rows

    study = reproduction / "tolerance-study"
    rows = read_rows(study)
    units = QUICK.tolerance_samples
    assert len(rows) == 3 * 2 * units and set(rows["status"]) == {"ok"}
    assert set(rows["controller"]) == {"PI", "NNPC", "MPC-nominal"} and set(rows["scenario"]) == {"startup",
                                                                                                   "load_change"}
    assert rows["inductance"].between(176e-6, 264e-6).all() and rows["capacitance"].between(8e-6, 12e-6).all()
    manifest = json.loads((study / "sweep.json").read_text())
    designed = {c["name"]: c for c in manifest["controllers"]}
    tuned = json.loads((reproduction / "tuning" / "pi__nominal-switched__1ms.json").read_text())
    assert designed["PI"]["settings"]["kp_per_V"] == tuned["kp"] and designed["PI"]["settings"]["ki_per_V_s"] == tuned["ki"]
    model = (reproduction / "models" / "nominal-switched__1ms__nnpc.pt").read_bytes()
    assert designed["NNPC"]["model_sha256"] == hashlib.sha256(model).hexdigest()
    report = (reproduction / "REPORT.md").read_text()
    section = report.split("## Tolerance study")[1].split("\n## ")[0]
    assert f"on {units} production units" in section and "| PI | all scenarios (per unit) | " in section
    for figure in section.split("](tolerance-study/")[1:]:
        assert (study / figure.split(")")[0]).is_file()
    assert (study / "SWEEP.md").is_file() and (study / "yield.csv").is_file()


def test_resume_keeps_finished_pipelines(reproduction, capsys):
    assert main(["--no-progress", "reproduce", "--quick", "--resume", "--out", str(reproduction)]) == 0
    err = capsys.readouterr().err
    assert err.count("finished earlier, kept (--resume)") == len(QUICK.pipelines)
    assert f"{3 * 2 * QUICK.tolerance_samples} done earlier, kept (--resume); running 0" in err  # the study's rows too


def test_wall_clock_figures_live_in_the_timings_files_only(reproduction):
    """REPORT.md, targets.csv and the metrics tables hold no wall-clock figure; timings.md/.csv do."""
    timings = pd.read_csv(reproduction / "timings.csv")
    whole = timings[timings["kind"] == "reproduction"]
    assert len(whole) == 1 and 0 < whole["value"].iloc[0] < 600
    assert {"stage", "controller p50", "controller p99"} <= set(timings["kind"])
    text = (reproduction / "timings.md").read_text()
    assert "## Timing targets" in text and "Whole reproduction <= 120 s on 2 cores" in text
    assert "| yes |" in text.split("Whole reproduction <= 120 s on 2 cores")[1].splitlines()[0]  # quick: far below
    metrics = pd.read_csv(reproduction / "metrics" / "metrics_all.csv")
    assert not any(c.startswith("controller_p") for c in metrics.columns)
    wall = pd.read_csv(reproduction / "metrics" / "metrics_all.timing.csv")
    assert {"controller_p50_us", "controller_p99_us"} <= set(wall.columns) and len(wall) == len(metrics)
    report = (reproduction / "REPORT.md").read_text()
    assert "ctrl p99" not in report and "Wall time" not in report and "[timings.md](timings.md)" in report
    summary = json.loads((reproduction / "pipelines" / f"{QUICK.pipelines[0]}.json").read_text())
    assert "timings" not in summary


def test_a_second_reproduction_writes_the_same_bytes(reproduction, tmp_path):
    """Everything committed from results/ is byte-identical when the reproduction runs again
    (the wall-clock files aside): tuned gains, models, pipeline summaries, metrics, targets,
    figures and the report."""
    again = tmp_path / "again"
    assert main(["--no-progress", "reproduce", "--quick", "--out", str(again)]) == 0
    committed = [p.relative_to(again) for p in sorted(again.rglob("*")) if p.is_file()
                 and p.parts[len(again.parts)] not in ("data", "runs")
                 and not p.name.startswith("timings.") and ".timing" not in p.name and p.suffix != ".svg"]
    assert {"REPORT.md", "targets.csv"} <= {str(p) for p in committed} and len(committed) > 30
    for relative in committed:
        assert (again / relative).read_bytes() == (reproduction / relative).read_bytes(), relative
