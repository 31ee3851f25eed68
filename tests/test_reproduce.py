"""The reproduction end to end on the quick profile: every artefact is written and the report is complete."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from conftest import no_temporary_files

from cosim.cli import main
from cosim.study.reproduce import QUICK


@pytest.fixture(scope="module")
def controller_fmu(tmp_path_factory) -> Path:
    """A PI exported as an FMU (1 ms): the reproduction runs it next to its own controllers."""
    out = tmp_path_factory.mktemp("fmus") / "my_pi.fmu"
    assert main(["--no-progress", "export-controller", "pi", "--kp", "0.0015", "--ki", "15.6", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def reproduction(tmp_path_factory, controller_fmu):
    out = tmp_path_factory.mktemp("results")
    assert main(["--no-progress", "reproduce", "--quick", "--out", str(out), "--controller", str(controller_fmu)]) == 0
    return out


def test_every_pipeline_writes_data_models_runs_metrics_and_figures(reproduction):
    for tag in QUICK.pipelines:
        assert (reproduction / "data" / f"{tag}.parquet").is_file()
        for name in ("nnpc", "nnpc-paper"):
            assert (reproduction / "models" / f"{tag}__{name}.pt").is_file()
            assert (reproduction / "models" / f"{tag}__{name}.identification.png").read_bytes()[:4] == b"\x89PNG"
        summary = json.loads((reproduction / "pipelines" / f"{tag}.json").read_text())
        tuning = json.loads((reproduction / "tuning" / f"pi__{tag}.json").read_text())
        assert summary["pi"]["design"]["key"] == tuning["design"]["key"]  # the gains name what they were tuned for
        assert summary["models"]["nnpc"]["design_key"] and "design" not in summary["models"]["nnpc"]
        assert summary["pi"]["kp"] >= 0 and "held_out_rmse" in summary["models"]["nnpc"]
        plant, rate = tag.split("__")
        for scenario in QUICK.scenarios:
            assert (reproduction / "figures" / f"{scenario}__{plant}__{rate}.png").is_file()
            assert (reproduction / "runs" / f"{scenario}__nnpc__{plant}__{rate}.parquet").is_file()
    metrics = pd.read_csv(reproduction / "metrics" / "metrics_all.csv")
    controllers = set(metrics["controller"])
    assert {"PI", "NNPC", "NNPC-paper", "MPC-oracle", "MPC-mismatched", "MPC-nominal", "NNPC (N=3)",
            "MPC-oracle (averaged model)", "MPC-oracle (sync. sample)", "NNPC (seed 1)",
            "MPC-nominal (no disturbance estimate)", "NNPC (7 hidden, one-step)", "NNPC (+ closed-loop round)",
            "NNPC (+ closed-loop round) (seed 1)", "NNPC-adaptive", "NNPC (identified on the drifted plant)",
            "NNPC-explicit", "CMC", "Type-III", "PI-envelope"} <= controllers
    # 4 pipelines x 2 scenarios x 5 controllers, + the no-estimate MPC on the mismatch plant, + the
    # ablations (N = 3 at 1 ms; eq. 3 and sync. sample at 13.33 us, and two identification variants
    # there on the start-up), + seed 1 on the four pipelines (with its identification variants on the
    # nominal switched plant at 13.33 us), + the drift study for seeds 0 and 1, + the controller FMU in
    # the three 1 ms pipelines, + the explicit NNPC at 13.33 us (with its policy), + the current-mode
    # controller, the Type-III and the envelope PI there
    assert len(metrics) == 4 * 2 * 5 + 2 + 2 + 2 + 2 + 2 + 2 + 2 + 2 + (2 + 2) + 2 * 3 + 3 * 2 + 2 + 3 * 2
    fmu = metrics[metrics["controller"] == "my_pi (FMU)"]
    assert set(fmu["pipeline"]) == {t for t in QUICK.pipelines if t.endswith("__1ms")} and len(fmu) == 3 * 2
    assert fmu["iae_Vs"].notna().all() and (fmu["iae_Vs"] > 0).all()
    assert (reproduction / "runs" / "startup__my-pi-fmu__nominal-switched__1ms.parquet").is_file()
    assert set(metrics.loc[metrics["controller"] == "NNPC-explicit", "pipeline"]) == {"nominal-switched__13p33us"}
    assert (reproduction / "models" / "nominal-switched__13p33us__nnpc-explicit.pt").is_file()
    for kind in ("current-mode", "current-mode-no-delay", "type-iii", "pi-envelope", "pi-margins"):  # with their margins
        design = json.loads((reproduction / "tuning" / f"{kind}__nominal-switched__13p33us.json").read_text())
        assert design["loops"]["duty"]["closed_loop_stable"]
    # the envelope map on the sweep engine: every point, step and controller; its shares from its table
    steps = pd.read_csv(reproduction / "envelope" / "map.csv")
    # eight controllers and the online NNPC of every other identification seed (QUICK: seed 1)
    assert len(steps) == 4 * 2 * (8 + 1) and set(steps["controller"]) >= {"NNPC", "NNPC (seed 1)", "MPC-oracle", "CMC",
                                                                        "CMC (no delay)", "PI-envelope"}
    assert (reproduction / "models" / "nominal-switched__13p33us__nnpc__seed1.pt").is_file()
    shares = pd.read_csv(reproduction / "envelope" / "shares.csv")
    overall = shares[shares["input_voltage_V"] == "all"].set_index("controller")["share_pct"]
    points = pd.read_csv(reproduction / "envelope" / "points.csv")
    assert overall.to_dict() == pytest.approx((100 * points.groupby("controller")["meets"].mean()).to_dict())
    assert steps.loc[steps["controller"] == "NNPC", "first_move_samples"].gt(0).all()
    # the frequency responses: loop gains and output impedances against the closed form
    loop = pd.read_csv(reproduction / "frequency-response" / "loop_gain.csv")
    assert set(loop["controller"]) == {"PI", "CMC", "Type-III"} and loop["phase_error_deg"].abs().max() <= 5
    seed_study = metrics[metrics["controller"] == "NNPC (seed 1)"]
    assert set(seed_study["pipeline"]) == {*QUICK.pipelines, "drift"}  # nominal and mismatch plants, the drift study
    assert (reproduction / "runs" / "startup__nnpc-seed-1__nominal-switched__13p33us.parquet").is_file()
    drift = metrics[metrics["pipeline"] == "drift"]
    assert set(drift["scenario"]) == {"capacitor_ageing"} and len(drift) == 2 * 3  # every study seed (QUICK: 0, 1)
    assert {"NNPC-adaptive (seed 1)", "NNPC (identified on the drifted plant) (seed 1)"} <= set(drift["controller"])
    assert (reproduction / "figures" / "capacitor_ageing__mismatch-switched__13p33us.png").is_file()
    summary = json.loads((reproduction / "pipelines" / "drift.json").read_text())
    assert summary["study"]["adaptation"]["samples"] > 0
    assert set(summary["study"]["prediction_after_drift"]) == {"NNPC", "NNPC-adaptive",
                                                              "NNPC (identified on the drifted plant)"}
    other = json.loads((reproduction / "pipelines" / "drift__seed1.json").read_text())
    assert other["study"]["seed"] == 1 and "NNPC-adaptive (seed 1)" in other["study"]["prediction_after_drift"]
    seed = json.loads((reproduction / "pipelines" / "nominal-switched__13p33us__seed1.json").read_text())
    assert {"nnpc (seed 1)", "nnpc (one-step) (seed 1)", "nnpc (+ closed-loop round) (seed 1)"} <= set(seed["models"])
    assert seed["models"]["nnpc (seed 1)"]["identification"]["stage"] == "multi-step"
    assert seed["models"]["nnpc (+ closed-loop round) (seed 1)"]["identification"]["stage"] == "closed-loop 1"


def test_report_has_every_section_and_checks_the_targets(reproduction):
    report = (reproduction / "REPORT.md").read_text()
    for heading in ("## Summary", "## Targets", "## Setup", "## PI gains", "## NN identification",
                    "## Results at the paper's rate", "## Results at one switching period",
                    "## What the NNPC costs in C", "## Seeds", "## Ablations",
                    "## Model mismatch", "## Drift and online adaptation", "## Discussion", "## Reproducing"):
        assert heading in report
    assert "Quick profile" in report
    targets = pd.read_csv(reproduction / "targets.csv", keep_default_na=False)
    assert list(targets.columns) == ["target", "measured", "margin", "met", "note"]
    assert set(targets["met"]) <= {"yes", "**no**"}
    # the margin is the measured value over the limit: met upper limits sit at or below 1
    rmse = targets[targets["target"].str.startswith("NNPC 10-step held-out vo RMSE <= 150 mV at 1/fsw, switched")]
    assert float(rmse["margin"].iloc[0]) == pytest.approx(float(rmse["measured"].iloc[0].split()[0]) / 150, abs=0.01)
    assert all(float(m) <= 1 for m, met, t in zip(targets["margin"], targets["met"], targets["target"])
               if m not in ("", "n/a") and met == "yes" and " <= " in t and " >= " not in t)
    assert not targets["target"].str.contains("Whole reproduction|compute per step").any()  # wall clock: timings
    assert targets["target"].str.contains("NNPC IAE <= 1.10 x oracle-MPC IAE").any()
    overshoot = targets[targets["target"] == "NNPC start-up overshoot <= 5 % at 1/fsw, switched, every seed"]
    assert overshoot["note"].iloc[0].startswith("seed 0: ") and "seed 1: " in overshoot["note"].iloc[0]
    assert overshoot["measured"].iloc[0].endswith(")")  # the worst seed named
    assert targets["target"].str.contains("10-step held-out vo RMSE <= 150 mV").any()
    assert targets["target"].str.contains("Under mismatch: NNPC IAE <= 1.05 x oracle-MPC IAE").any()
    assert not targets["target"].str.contains("0.8 x nominal-model MPC").any()  # withdrawn
    drift = targets[targets["target"].str.startswith("Drift: adapted NNPC IAE")]
    assert drift["note"].iloc[0].startswith("seed 0: ") and "seed 1: " in drift["note"].iloc[0]
    summary = report.split("## Summary")[1].split("\n## ")[0]
    assert "median (min-max) over 2 seeds" in summary  # spreads beside the headline ratios
    assert "adapted / not adapted" in summary
    assert "**Identification** (nominal switched plant" in report
    ablation_section = report.split("Old vs new optimizer on the same models")[1]
    ablation = next(block for block in ablation_section.split("\n\n") if block.startswith("| pipeline |")).splitlines()[2:]
    pipelines = {line.split(" | ")[0].lstrip("| ") for line in ablation}
    assert pipelines == set(QUICK.pipelines)  # every built-in pipeline: the NNPC and the oracle MPC, each scenario
    assert {"NNPC", "MPC-oracle"} == {line.split(" | ")[1] for line in ablation}
    assert len(ablation) == len(QUICK.pipelines) * 2 * len(QUICK.scenarios)
    cost = report.split("## What the NNPC costs in C")[1].split("\n## ")[0]
    rows = [line for line in cost.splitlines() if line.startswith(("| 1 ms |", "| 13.33 µs |"))]
    assert len(rows) == 2 and rows[0].endswith("| yes |")  # the 1 ms NNPC fits a Cortex-M4F, counted
    assert "## Explicit NNPC" in report and "## Control quality over the operating envelope" in report
    assert targets["target"].str.startswith("Envelope map: current-mode controller (CMC) share >= 60 %").any()
    assert targets["target"].str.contains("x current-mode (CMC) IAE, every paper scenario and seed", regex=False).any()
    assert "**Against the best-designed classical controller at the nominal point**" in report
    assert targets["target"].str.startswith("NNPC-explicit IAE <= 1.05 x online NNPC IAE").any()
    for figure in report.split("](figures/")[1:]:
        assert (reproduction / "figures" / figure.split(")")[0]).is_file()


def test_the_tolerance_study_runs_the_pipelines_controllers_on_production_units(reproduction):
    """The nominal switched 1 ms pipeline's own PI and NNPC (and the nominal MPC) on QUICK's units,
    through the sweep engine; its yield table and figures in the report."""
    import hashlib

    from cosim.design.sweeps.dataset import read_rows

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
    jobs = 2 * len(QUICK.pipelines) + 2  # the pipelines, seed 1 of each, the drift study for seeds 0 and 1
    err = capsys.readouterr().err
    assert err.count("finished earlier, kept (--resume)") == jobs
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
    ssp = timings[timings["kind"] == "ssp agreement"].set_index("what")["value"]  # its parts ran on the cluster
    assert list(ssp.index) == ["4 parts: worker time", "tables, figures and report section"] and (ssp > 0).all()
    assert "The SSP agreement's 4 parts took" in text
    metrics = pd.read_csv(reproduction / "metrics" / "metrics_all.csv")
    assert not any(c.startswith("controller_p") for c in metrics.columns)
    wall = pd.read_csv(reproduction / "metrics" / "metrics_all.timing.csv")
    assert {"controller_p50_us", "controller_p99_us"} <= set(wall.columns) and len(wall) == len(metrics)
    report = (reproduction / "REPORT.md").read_text()
    assert "ctrl p99" not in report and "Wall time" not in report and "[timings.md](timings.md)" in report
    summary = json.loads((reproduction / "pipelines" / f"{QUICK.pipelines[0]}.json").read_text())
    assert "timings" not in summary


def test_the_ssp_agreement_run_on_the_cluster_equals_one_run_in_this_process(reproduction, tmp_path):
    """The reproduction runs the SSP agreement's four (plant, controller) parts as tasks beside its jobs and merges
    them: its tables and report section are the ones the study writes when it runs here, part after part."""
    import shutil

    from cosim.study.ssp_agreement import agreement_section

    for folder in ("tuning", "models"):  # the designs the study exports as FMUs
        shutil.copytree(reproduction / folder, tmp_path / folder)
    section = agreement_section(tmp_path, quick=True)
    for name in ("metrics", "equality", "convergence"):
        table = pd.read_csv(tmp_path / "ssp" / f"ssp_{name}.csv")
        assert len(table) and (tmp_path / "ssp" / f"ssp_{name}.csv").read_bytes() == (
            reproduction / "ssp" / f"ssp_{name}.csv").read_bytes(), name
    assert set(pd.read_csv(tmp_path / "ssp" / "ssp_equality.csv")[["plant", "controller"]].itertuples(
        index=False, name=None)) == {(m, c) for m in ("averaged", "switched") for c in ("PI", "NNPC")}
    assert section.startswith("## The loop as an SSP") and section in (reproduction / "REPORT.md").read_text()


def test_each_drift_seed_reuses_the_nnpc_its_mismatch_seed_job_identified(tmp_path, monkeypatch):
    """The drift study of every seed runs after the mismatch plant's job of that seed at 1/fsw and reads the NNPC
    that job saved (one identification fewer per seed), the same network as identified again: same summary. A file
    identified for other settings (another design key) is identified again rather than reused."""
    from dataclasses import replace

    from cosim.design.design_cache import seed_model_file
    from cosim.study import reproduce
    from cosim.study.reproduce import DRIFT_PIPELINE, FULL, plan_jobs, run_drift, run_seed

    drift = {job.seed: job.after for job in plan_jobs(list(reproduce.PIPELINES), FULL, 0, None) if job.kind == "drift"}
    assert drift == {0: DRIFT_PIPELINE.tag, **{s: f"{DRIFT_PIPELINE.tag}__seed{s}" for s in FULL.seeds[1:]}}
    alone = plan_jobs([p for p in reproduce.PIPELINES if p != DRIFT_PIPELINE], FULL, 0, None)
    assert {job.after for job in alone if job.kind == "drift"} == {None}  # nothing to reuse: identified there

    profile = replace(QUICK, scenarios=("startup",), ablations=False)
    identified = []
    identify = reproduce.identify
    monkeypatch.setattr(reproduce, "identify", lambda binding, *a, **k: identified.append(binding.tag)
                        or identify(binding, *a, **k))
    seed_job = run_seed(DRIFT_PIPELINE, tmp_path, profile, 1)
    saved = seed_model_file(tmp_path, DRIFT_PIPELINE.plant_tag, DRIFT_PIPELINE.control_period, 1)
    assert saved.is_file() and identified == [DRIFT_PIPELINE.plant_tag]
    identified.clear()
    reused = run_drift(tmp_path, profile, 1, reuse=True, first=False)
    assert identified == [f"{DRIFT_PIPELINE.plant_tag}-drifted"]  # the drifted plant's only
    assert reused.models["nnpc (seed 1)"] == seed_job.models["nnpc (seed 1)"]
    identified.clear()
    run_drift(tmp_path, replace(profile, samples=profile.samples + 1), 1, reuse=True, first=False)
    assert identified == [DRIFT_PIPELINE.plant_tag, f"{DRIFT_PIPELINE.plant_tag}-drifted"]


def test_the_1ms_compute_target_reads_the_c_twins_benchmark_row_not_the_python_references(tmp_path):
    """The workbench runs the C twin by default: the timing target takes its row's p99, whichever row comes
    first in the table, and says so; the Python reference's row stays in the benchmark table beside it."""
    from cosim.study.targets import TimingTargets

    rows = [("controller compute per step, NNPC, 1 ms, Python reference (3000 samples, ...)", 206.0, 302.0),
            ("controller compute per step, NNPC, 1 ms, C twin (3000 samples, ...)", 2.9, 11.4)]
    pd.DataFrame(rows, columns=["benchmark", "median", "p99"]).to_csv(tmp_path / "benchmarks.csv", index=False)
    metrics = pd.DataFrame({"controller": ["NNPC"], "pipeline": ["nominal-switched__1ms"], "controller_p99_us": [18.0]})
    row = TimingTargets(metrics, 500.0, tmp_path).frame().iloc[0]
    assert row["target"] == "NNPC compute per step p99 <= 100 us at 1 ms"
    assert row["measured"] == "worst run p99 18 us; benchmark suite: p99 11 us" and row["met"] == "yes"
    assert "C twin" in row["note"]
    pd.DataFrame(rows[:1], columns=["benchmark", "median", "p99"]).to_csv(tmp_path / "benchmarks.csv", index=False)
    row = TimingTargets(metrics, 500.0, tmp_path).frame().iloc[0]  # no C twin row: the runs' own p99 decides
    assert row["measured"] == "worst run p99 18 us" and row["met"] == "yes"


def test_an_interrupted_and_resumed_reproduction_writes_the_same_bytes_as_one_run_through(reproduction, controller_fmu,
                                                                                          tmp_path, capsys):
    """A second reproduction, stopped by SIGTERM once a pipeline has finished and others still run, keeps the
    finished pipelines (exit 130, one line, nothing half-written); ``--resume`` completes it, and everything committed
    from results/ is then byte-identical to the fixture's uninterrupted run (the wall-clock files aside): tuned gains,
    models, pipeline summaries, metrics, targets, figures and the report. (One test for both properties: each on its
    own cost a quick reproduction of its own.)"""
    again = tmp_path / "again"
    process = subprocess.Popen([sys.executable, "-m", "cosim.cli", "--no-progress", "reproduce", "--quick", "--out",
                                str(again), "--controller", str(controller_fmu)], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL)
    deadline = time.monotonic() + 600  # a loaded machine: the first pipeline of a quick reproduction took 60-120 s

    def finished() -> list[str]:
        return sorted(p.stem for p in (again / "pipelines").glob("*.json") if not p.name.endswith(".timings.json"))

    while not finished() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)  # interrupt once a pipeline has finished and others still run
    assert process.poll() is None, "the reproduction ended before the interrupt"
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130 and "Traceback" not in err, err
    no_temporary_files(again)
    kept = finished()
    jobs = 2 * len(QUICK.pipelines) + 2  # the pipelines, seed 1 of each, the drift study for seeds 0 and 1
    assert 1 <= len(kept) < jobs, kept
    assert main(["--no-progress", "reproduce", "--quick", "--resume", "--out", str(again), "--controller",
                 str(controller_fmu)]) == 0
    assert capsys.readouterr().err.count("finished earlier, kept (--resume)") == len(kept)
    committed = [p.relative_to(again) for p in sorted(again.rglob("*")) if p.is_file()
                 and p.parts[len(again.parts)] not in ("data", "runs")
                 and not p.name.startswith("timings.") and ".timing" not in p.name and p.suffix != ".svg"]
    assert {"REPORT.md", "targets.csv"} <= {str(p) for p in committed} and len(committed) > 30
    for relative in committed:
        assert (again / relative).read_bytes() == (reproduction / relative).read_bytes(), relative


def test_a_controller_fmu_at_no_pipelines_rate_is_refused_before_any_work(tmp_path, capsys):
    fast = tmp_path / "pi_2ms.fmu"
    assert main(["--no-progress", "export-controller", "pi", "--kp", "0.0015", "--ki", "15.6", "--control-period",
                 "2e-3", "--out", str(fast)]) == 0
    capsys.readouterr()
    assert main(["--no-progress", "reproduce", "--quick", "--out", str(tmp_path / "r"), "--controller", str(fast)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"error: {fast}: sample period 0.002 s matches no pipeline of the "
                   "reproduction (expected one of 1 ms, 13.33 µs)")
    assert not (tmp_path / "r" / "pipelines").exists()


def test_a_controller_fmu_named_like_a_built_in_controller_is_refused(tmp_path, capsys):
    clash = tmp_path / "binding.toml"
    fmu = tmp_path / "pi.fmu"
    assert main(["--no-progress", "export-controller", "pi", "--kp", "0.0015", "--ki", "15.6", "--out", str(fmu)]) == 0
    clash.write_text(f'fmu = "{fmu.name}"\nlabel = "NNPC"\n'
                     + "".join(f'[roles.{r}]\nvariable = "{r}"\n' for r in ("reference", "measured_output_voltage",
                                                                           "duty_cycle", "sample_period")))
    capsys.readouterr()
    assert main(["--no-progress", "reproduce", "--quick", "--out", str(tmp_path / "r"), "--controller", str(clash)]) == 2
    assert capsys.readouterr().err.strip() == (f"error: {clash}: the controller name 'NNPC' is taken (by a built-in "
                                               "controller): give it a 'label' in a controller-binding file")
