"""The command line: runs write tables, metrics and a figure per scenario; mistakes are one line."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from conftest import cli as command
from conftest import one_line_error

from cosim.cli import main
from cosim.results import read_run


def cli(*args, cwd=None):
    """Run ``buck-cosim`` in a subprocess, as a user would (no stdin)."""
    return subprocess.run([sys.executable, "-m", "cosim.cli", *args], capture_output=True, text=True,
                          cwd=cwd, stdin=subprocess.DEVNULL, env={**os.environ, "PYTHONWARNINGS": "ignore"})


def test_run_writes_tables_metrics_and_one_figure_per_scenario(tmp_path, capsys):
    code = main(["--no-progress", "run", "startup", "load_change", "--kp", "0", "--ki", "14", "--out", str(tmp_path)])
    assert code == 0
    for scenario in ("startup", "load_change"):
        png = tmp_path / "figures" / f"{scenario}__nominal-averaged__1ms.png"
        svg = png.with_suffix(".svg")
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
        text = svg.read_text()
        assert "output voltage" in text and "inductor current" in text and "time [ms]" in text
        run = read_run(tmp_path / "runs" / f"{scenario}__pi__nominal-averaged__1ms.parquet")
        assert run.complete and run.frame["output_voltage"].iloc[-1] == pytest.approx(12.0, rel=1e-3)
    metrics = pd.read_csv(tmp_path / "metrics" / "metrics__nominal-averaged.csv")
    assert metrics["scenario"].tolist() == ["startup", "load_change"]
    assert (metrics["steady_state_error_pct"].abs() < 0.2).all()
    assert "startup" in capsys.readouterr().out


def test_runs_into_one_folder_keep_one_metrics_table_of_all_its_runs(tmp_path):
    """A second run into the same --out replaced the metrics table, leaving the first run's files without their row;
    a run of the same scenario and controller again replaces its own row, the rest stay."""
    args = ["--no-progress", "run", "--kp", "0.01", "--ki", "14", "--no-figures", "--out", str(tmp_path)]
    table = tmp_path / "metrics" / "metrics__nominal-averaged.csv"
    assert main([*args, "startup"]) == 0
    first = pd.read_csv(table)
    assert main([*args, "load_change"]) == 0
    assert pd.read_csv(table)["scenario"].tolist() == ["startup", "load_change"]
    assert main([*args, "startup"]) == 0
    both = pd.read_csv(table)
    assert both["scenario"].tolist() == ["load_change", "startup"]
    pd.testing.assert_frame_equal(both.iloc[[1]].reset_index(drop=True), first)  # the same run, the same row
    timing = pd.read_csv(tmp_path / "metrics" / "metrics__nominal-averaged.timing.csv")
    assert timing["scenario"].tolist() == ["load_change", "startup"] and timing["controller_p99_us"].notna().all()


def test_export_converts_between_formats(tmp_path):
    main(["--no-progress", "run", "reference_down", "--kp", "0", "--ki", "14", "--out", str(tmp_path), "--no-figures"])
    source = tmp_path / "runs" / "reference_down__pi__nominal-averaged__1ms.parquet"
    assert main(["export", str(source), "--to", "csv", "--out", str(tmp_path / "exported")]) == 0
    back = read_run(tmp_path / "exported" / "reference_down__pi__nominal-averaged__1ms.csv")
    original = read_run(source)
    pd.testing.assert_frame_equal(back.frame, original.frame.drop(columns=["controller_compute_time"]))
    assert back.metadata == original.metadata
    # a "conversion" into the file it reads would replace it: refused, the file untouched
    before = source.read_bytes()
    assert main(["export", str(source), "--to", "parquet"]) == 2 and source.read_bytes() == before


def test_build_fmu_copies_binary_and_source_fmus(tmp_path):
    assert main(["build-fmu", "--output", str(tmp_path)]) == 0
    assert (tmp_path / "BuckConverter.fmu").stat().st_size > 5000
    assert (tmp_path / "BuckConverter-source.fmu").is_file()


def test_scenarios_and_inspect_print_what_they_describe(buck_fmu, capsys):
    assert main(["scenarios"]) == 0
    out = capsys.readouterr().out
    assert "load_change" in out and "5 ms: load_resistance=5" in out
    assert main(["inspect", str(buck_fmu)]) == 0
    out = capsys.readouterr().out
    assert "co-simulation, model-exchange" in out and "load_resistance" in out and "Ohm" in out


@pytest.mark.parametrize("args,message", [
    (["run", "no_such_scenario"], "error: scenario 'no_such_scenario' is neither a file nor a shipped scenario"),
    (["run", "startup", "--control-period", "0"], "error: buck-cosim run: argument --control-period: period 0 s is invalid"),
    (["run", "startup", "--control-period", "1e-9"],
     "error: buck-cosim run: argument --control-period: period 1e-9 s is invalid: expected >= 1e-07 s (one switching "
     "period of the paper's converter is 13.3 us): was it given in another unit?"),
    (["export-ssp", "startup", "--controller", "pi", "--communication-step", "1e-9", "--out", "l.ssp"],
     "argument --communication-step: period 1e-9 s is invalid: expected >= 1e-07 s"),
    (["run", "startup", "--control-period", "fast"], "'fast' is not a period in seconds"),
    (["run", "startup", "--kp", "0.1"], "error: --kp and --ki must be given together"),
    (["run", "startup", "--kp", "-1", "--ki", "3"], "argument --kp: -1 is invalid: expected a finite number >= 0"),
    (["run", "startup", "--kp", "nan", "--ki", "3"], "argument --kp: nan is invalid: expected a finite number >= 0"),
    (["run", "startup", "--kp", "0", "--ki", "inf"], "argument --ki: inf is invalid: expected a finite number >= 0"),
    (["run", "startup", "--duty-max", "1.5"], "argument --duty-max: 1.5 is invalid: expected a finite number >= 0 "
                                              "and <= 1"),
    (["run", "startup", "--duty-min", "0.6", "--duty-max", "0.5"], "error: duty limits (0.6, 0.5) are invalid"),
    (["run", "startup", "--seed", "-1"], "argument --seed: seed -1 is out of range: expected a whole number 0 .. "
                                         "4294967295"),
    (["run", "startup", "--seed", str(10**30)], "argument --seed: seed 1000000000000000000000000000000 is out of "
                                                "range"),
    (["collect-data", "--seed", "-1", "--out", "d.parquet"], "argument --seed: seed -1 is out of range"),
    (["collect-data", "--samples", "0", "--out", "d.parquet"], "argument --samples: 0 is invalid: expected a whole "
                                                               "number >= 100"),
    (["collect-data", "--excitation", "nan", "--out", "d.parquet"], "argument --excitation: nan is invalid"),
    (["train", "d.parquet", "--seed", str(2**32), "--out", "m.pt"], "argument --seed: seed 4294967296 is out of range"),
    (["train", ".", "--out", "m.pt"], "error: data file . is a folder: expected a file"),
    (["reproduce", "--workers", "0"], "argument --workers: 0 is invalid: expected a whole number >= 1"),
    (["frequency-response", "--workers", "-1", "--out", "fr"], "argument --workers: -1 is invalid: expected a whole "
                                                               "number >= 1"),
    (["export-controller", "pi", "--kp", "0.01", "--ki", "14", "--model", "m.pt", "--out", "pi.fmu"],
     "error: --model gives the network of nnpc, nnpc-paper, nnpc-adaptive or nnpc-explicit, but no controller run "
     "here uses one (controllers: pi): drop --model"),
    (["export-controller", "pi", "--kp", "0.01", "--ki", "14", "--samples", "2000", "--out", "pi.fmu"],
     "error: --samples sizes the data a network is trained on, but no controller run here trains one (controllers: "
     "pi): drop --samples"),
    (["run", "startup", "--controller", "nnpc", "--controller", "nnpc"], "error: controller nnpc is given twice"),
    (["frequency-response", "--out", "fr.csv"], "error: output folder fr.csv is named like a CSV file, but the results "
                                                 "are a folder of files"),
    (["tune-pi", "--control-period", "1e-3", "--control-period=1/75e3"],
     "error: buck-cosim tune-pi: argument --control-period: given twice (--control-period 1e-3 and "
     "--control-period=1/75e3): give it once"),
    (["train", "d.parquet", "--seed", "1", "--se", "2", "--out", "m.pt"], "argument --seed: given twice (--seed 1 and "
                                                                        "--se 2)"),
    (["tune-pi", "--plant", "p.toml", "--mode", "switched"],
     "error: --mode switched chooses a built-in plant, but --plant p.toml drives an external FMU, whose binding file "
     "chooses the model: drop --mode"),
    (["run", "startup", "--optimizer", "search"],
     "error: --optimizer search chooses the optimizer of the predictive controllers (nnpc, nnpc-paper, nnpc-adaptive, "
     "mpc-oracle, mpc-nominal), but none runs here (controllers: pi): drop --optimizer"),
    (["run", "startup", "--controller", "mpc-oracle", "--rti", "iteration=2"],
     "error: --rti iteration=2: 'iteration' is not an RTI setting (did you mean 'iterations'? expected one of "
     "iterations, line_search, "),
    (["run", "startup", "--controller", "mpc-oracle", "--rti", "iterations"],
     "error: --rti iterations: expected FIELD=VALUE (e.g. iterations=2)"),
    (["run", "startup", "--controller", "mpc-oracle", "--rti", "iterations=2", "--rti", "iterations=3"],
     "error: --rti iterations=3: iterations is given twice: give it once"),
    (["run", "startup", "--controller", "mpc-oracle", "--rti", "smoothing=-1"],
     "error: --rti smoothing=-1: RTI smoothing = -1.0 is invalid: expected eps > 0 [V]"),
    # the 1 ms RTI has the line search, which the reweightings are refused with: before the network is trained
    (["run", "startup", "--controller", "nnpc", "--rti", "reweightings=1"],
     "error: --rti reweightings=1 at the control period 1 ms: RTI reweightings = 1 with line_search is refused"),
    (["run", "startup", "--controller", "mpc-oracle", "--optimizer", "search", "--rti", "iterations=2"],
     "error: --rti iterations=2 changes the real-time iteration's settings, but no controller here plans with it "
     "(--optimizer search; controllers: mpc-oracle): drop --rti"),
    (["run", "startup", "--controller", "nnpc-paper", "--rti", "line_search=true"],
     "error: --rti line_search=true changes the real-time iteration's settings, but no controller here plans with it "
     "(nnpc-paper plans with the search unless --optimizer rti; controllers: nnpc-paper): drop --rti"),
    (["export-controller", "pi", "--kp", "0.01", "--ki", "14", "--rti", "iterations=2", "--out", "pi.fmu"],
     "error: --rti iterations=2 changes the real-time iteration's settings, but no controller here plans with it "
     "(none of nnpc, nnpc-paper, mpc-oracle, mpc-nominal runs; controllers: pi): drop --rti"),
    (["frequency-response", "--controller", "pi", "--optimizer", "search", "--out", "fr"],
     "error: --optimizer search chooses the optimizer of the predictive controllers"),
    (["frequency-response", "--controller", "mpc-oracle", "--rti", "reweightings=5", "--out", "fr"],
     "error: --rti reweightings=5: RTI reweightings = 5 is invalid: expected 0, 1, 2 or 3"),
    (["export-ssp", "startup", "--controller", "my.fmu", "--optimizer", "search", "--out", "l.ssp"],
     "error: --optimizer design a built-in controller, but --controller my.fmu is a controller FMU"),
    (["inspect", "README.md"], "is not a zip archive"),
    (["export", "missing.parquet", "--to", "csv"], "error: run file missing.parquet does not exist"),
    (["frobnicate"], "error: buck-cosim: argument COMMAND: invalid choice"),
])
def test_user_mistakes_are_one_line_errors_without_traceback(args, message, tmp_path):
    (tmp_path / "README.md").write_text("not an FMU")
    done = cli(*args, "--out", str(tmp_path)) if args[0] == "run" else cli(*args, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, done.stderr
    assert message in lines[0]
    assert "Traceback" not in done.stderr
    assert not list(tmp_path.rglob("*.pt")) and not list(tmp_path.rglob("*.parquet"))  # refused before any work


def test_help_texts_state_units():
    done = cli("run", "--help")
    assert done.returncode == 0
    assert "--control-period SECONDS" in done.stdout and "[1/V]" in done.stdout and "1/75e3" in done.stdout


def test_mpc_baselines_run_without_training(tmp_path):
    code = main(["--no-progress", "run", "reference_up", "--controller", "mpc-oracle", "--controller", "mpc-nominal",
                 "--variant", "mismatch", "--mode", "switched", "--out", str(tmp_path), "--no-figures"])
    assert code == 0
    metrics = pd.read_csv(tmp_path / "metrics" / "metrics__mismatch-switched.csv")
    assert metrics["controller"].tolist() == ["MPC-oracle", "MPC-nominal"]
    assert (metrics["steady_state_error_pct"].abs() < 0.2).all()


def test_the_predictive_controllers_optimizer_and_rti_settings_are_chosen_on_the_command_line(tmp_path):
    """--optimizer search runs the search alone; --rti FIELD=VALUE changes fields of the rate's RTI settings and
    keeps the others; the run's metadata says which optimizer planned, with its settings."""
    from dataclasses import asdict

    from cosim.design.experiments import SWITCHING_PERIOD_RTI

    common = ["--no-progress", "run", "reference_up", "--controller", "mpc-oracle", "--no-figures"]
    assert main([*common, "--optimizer", "search", "--out", str(tmp_path / "search")]) == 0
    run = read_run(tmp_path / "search" / "runs" / "reference_up__mpc-oracle__nominal-averaged__1ms.parquet")
    assert run.metadata["controller"]["optimizer"] == "search (grid + pattern search)"
    assert main([*common, "--control-period", "1/75e3", "--rti", "reweightings=0", "--rti", "iterations=2",
                 "--out", str(tmp_path / "rti")]) == 0
    run = read_run(tmp_path / "rti" / "runs" / "reference_up__mpc-oracle__nominal-averaged__13p33us.parquet")
    optimizer = run.metadata["controller"]["optimizer"]
    assert optimizer["type"].startswith("real-time iteration")
    assert {k: v for k, v in optimizer.items() if k != "type"} == \
        {**asdict(SWITCHING_PERIOD_RTI), "reweightings": 0, "iterations": 2}
    assert run.frame["output_voltage"].iloc[-1] == pytest.approx(15.0, rel=5e-3)


def test_export_controller_builds_the_fmu_with_the_optimizer_and_rti_settings_asked_for(tmp_path):
    """The controller FMU's generated header (data only) holds the RTI settings the command line chose."""
    import zipfile

    def header(*options):
        out = tmp_path / f"mpc{len(options)}.fmu"
        assert main(["--no-progress", "export-controller", "mpc-oracle", "--control-period", "1/75e3", *options,
                     "--out", str(out)]) == 0
        with zipfile.ZipFile(out.with_name(out.stem + "-source.fmu")) as source:
            return source.read("sources/controller_config.h").decode()

    assert ".rti = {.enabled = 1, .iterations = 1, .reweightings = 2," in header()
    assert ".rti = {" not in header("--optimizer", "search")  # all zero: the search alone
    assert ".rti = {.enabled = 1, .iterations = 2, .smoothing = 0.02," in header("--rti", "iterations=2", "--rti",
                                                                                 "smoothing=0.02", "--rti",
                                                                                 "reweightings=0")


def test_frequency_response_measures_the_predictive_controllers_with_the_optimizer_asked_for(tmp_path, monkeypatch):
    """--optimizer/--rti reach the controller entry frequency-response designs and measures (the measurement itself,
    minutes of a dask cluster, is tests/test_frequency_response.py's)."""
    import contextlib

    import cosim.design.cluster as cluster
    import cosim.design.frequency_response as response
    from cosim.base.errors import ConfigError

    entries = []

    def measure(binding, entry, *args, **kwargs):
        entries.append(entry)
        raise ConfigError("stopped by the test")  # the entry is what this test checks

    monkeypatch.setattr(response, "measure", measure)
    monkeypatch.setattr(cluster, "dask_client", lambda *a, **k: contextlib.nullcontext())
    assert main(["--no-progress", "frequency-response", "--controller", "mpc-oracle", "--rti", "reweightings=0",
                 "--out", str(tmp_path)]) == 2
    assert main(["--no-progress", "frequency-response", "--controller", "nnpc", "--optimizer", "search", "--out",
                 str(tmp_path)]) == 2
    assert [(e.kind, e.optimizer, dict(e.rti)) for e in entries] == \
        [("mpc-oracle", None, {"reweightings": 0}), ("nnpc", "search", {})]


def test_each_predictive_controller_plans_with_its_own_optimizer_unless_one_is_given(tmp_path):
    """nnpc-paper plans with the search as the reproduction runs the paper's network, the others with the RTI;
    --optimizer overrides both, and --rti changes only the controllers that plan with the RTI."""
    from dataclasses import replace
    from pathlib import Path

    from controllers.adaptation import AdaptiveNNPC
    from cosim.design.controller_factory import make_controllers
    from cosim.design.experiments import SWITCHING_PERIOD_RTI
    from cosim.design.plants import plant_binding
    from cosim.design.vocabulary import SWITCHING_PERIOD

    model = str(Path(__file__).parent / "fixtures" / "nnpc_nominal_averaged_13p33us.pt")
    binding = plant_binding("nominal", "averaged")

    def rti_of(name, **options):
        [controller] = make_controllers([name], binding, SWITCHING_PERIOD, tmp_path, duty_limits=(0.0, 1.0),
                                        model_path=model, **options)
        return (controller.inner if isinstance(controller, AdaptiveNNPC) else controller).rti

    assert rti_of("nnpc") == SWITCHING_PERIOD_RTI and rti_of("nnpc-paper") is None
    assert rti_of("nnpc-paper", optimizer="rti") == SWITCHING_PERIOD_RTI and rti_of("nnpc", optimizer="search") is None
    changed = rti_of("nnpc-adaptive", rti_changes={"reweightings": 1, "smoothing": 0.02})
    assert (changed.reweightings, changed.smoothing, changed.iterations) == (1, 0.02, SWITCHING_PERIOD_RTI.iterations)
    [mpc] = make_controllers(["mpc-oracle"], binding, SWITCHING_PERIOD, tmp_path, duty_limits=(0.0, 1.0),
                             rti_changes={"iterations": 2})
    assert mpc.rti == replace(SWITCHING_PERIOD_RTI, iterations=2) and rti_of("nnpc", rti_changes={"iterations": 2}) \
        == replace(SWITCHING_PERIOD_RTI, iterations=2)


def test_collect_train_and_run_an_nnpc(tmp_path):
    data, model = tmp_path / "data.parquet", tmp_path / "model.pt"
    assert main(["--no-progress", "collect-data", "--samples", "600", "--out", str(data),
                 "--work-dir", str(tmp_path)]) == 0
    assert main(["--no-progress", "train", str(data), "--extra", "load_conductance", "--out", str(model)]) == 0
    assert main(["--no-progress", "run", "reference_up", "--controller", "nnpc", "--model", str(model),
                 "--out", str(tmp_path / "runs")]) == 0
    run = read_run(tmp_path / "runs" / "runs" / "reference_up__nnpc__nominal-averaged__1ms.parquet")
    assert run.metadata["controller"]["predictor"]["architecture"].startswith("4-7-2 tanh")
    assert run.frame["output_voltage"].iloc[-1] == pytest.approx(15.0, rel=2e-3)


def test_collect_data_draws_over_the_region_asked_for(tmp_path):
    """``--region envelope`` at 1 ms (where the default is the paper's region): supplies drawn 36-60 V, loads up to
    100 Ohm, the binary dither; the metadata says so. ``--region paper`` keeps 48 V and 4-10 Ohm."""
    from cosim.results import read_parquet

    frames = {}
    for region in ("paper", "envelope"):
        path = tmp_path / f"{region}.parquet"
        assert main(["--no-progress", "collect-data", "--samples", "3000", "--region", region, "--out", str(path),
                     "--work-dir", str(tmp_path)]) == 0
        frames[region] = read_parquet(path)[0]
    paper, envelope = frames["paper"], frames["envelope"]
    assert set(paper["input_voltage"]) == {48.0} and (paper["output_voltage"] / paper["load_current"]).max() < 10.5
    assert envelope["input_voltage"].nunique() > 3 and 36.0 <= envelope["input_voltage"].min()
    assert envelope["input_voltage"].max() <= 60.0 and (envelope["output_voltage"] / envelope["load_current"]).max() > 20
    collection = envelope.attrs["metadata"]["collection"]
    assert collection["dither"] == "am-prbs" and list(collection["input_voltage_range"]) == [36.0, 60.0]
    assert paper.attrs["metadata"]["collection"]["dither"] == "gaussian"
    with pytest.raises(SystemExit) as refused:
        main(["--no-progress", "collect-data", "--region", "moon", "--out", str(tmp_path / "x.parquet")])
    assert refused.value.code == 2


def test_train_with_the_simulation_error_stage_extra_data_and_a_refinement(tmp_path, capsys):
    from controllers.nn_model import load_model

    data, more = tmp_path / "data.parquet", tmp_path / "more.parquet"
    for path, seed in ((data, "0"), (more, "1")):
        assert main(["--no-progress", "collect-data", "--samples", "500", "--seed", seed, "--out", str(path),
                     "--work-dir", str(tmp_path)]) == 0
    first, refined = tmp_path / "first.pt", tmp_path / "refined.pt"
    assert main(["--no-progress", "train", str(data), "--extra", "load_conductance", "--multi-step-horizon", "5",
                 "--multi-step-iterations", "25", "--multi-step-stride", "3", "--out", str(first)]) == 0
    stage = load_model(first).metadata["training"]["multi_step"]
    assert stage["horizon"] == 5 and stage["iterations"] <= 25 and stage["windows"] == len(range(0, 400 - 5, 3))
    assert main(["--no-progress", "train", str(data), "--extra", "load_conductance", "--extra-data", str(more),
                 "--init", str(first), "--multi-step-horizon", "5", "--multi-step-iterations", "25",
                 "--out", str(refined)]) == 0
    model = load_model(refined)
    assert model.metadata["training"]["refined_from_initial"] and model.metadata["training"]["extra_samples"] == 500
    assert model.metadata["extra_data_files"] == [str(more)]
    np.testing.assert_array_equal(model.input_mean, load_model(first).input_mean)
    # the same samples again (a copy of the data file) would train on the held-out share: refused, nothing written
    shutil.copy(data, tmp_path / "copy.parquet")
    assert main(["--no-progress", "train", str(data), "--extra-data", str(more), "--extra-data",
                 str(tmp_path / "copy.parquet"), "--out", str(tmp_path / "twice.pt")]) == 2
    assert not (tmp_path / "twice.pt").exists()
    assert f"--extra-data {tmp_path / 'copy.parquet'} holds the same samples as {data}: training on them twice " \
           "would train on the held-out share too" in capsys.readouterr().err


def test_nnpc_trains_on_demand_and_reuses_its_model(tmp_path):
    args = ["--no-progress", "run", "startup", "--controller", "nnpc", "--samples", "500", "--out", str(tmp_path),
            "--no-figures"]  # the PI that collects the data is tuned (--kp/--ki set the gains of a pi run only)
    assert main(args) == 0
    model = next((tmp_path / "models").glob("*__nnpc.pt"))
    mtime = model.stat().st_mtime_ns
    assert main(args) == 0
    assert model.stat().st_mtime_ns == mtime  # reused, not retrained


@pytest.mark.parametrize("make,args,message", [
    (None, ["train", "missing.parquet", "--out", "m.pt"], "error: data file missing.parquet does not exist"),
    ("garbage", ["run", "startup", "--controller", "nnpc", "--model", "bad.pt"], "model file bad.pt is not a model written by buck-cosim train"),
    (None, ["train", "x.parquet", "--activation", "swish", "--out", "m.pt"], "activation 'swish' is unknown"),
    (None, ["train", "x.parquet", "--multi-step-horizon", "0", "--out", "m.pt"],
     "argument --multi-step-horizon: 0 is invalid: expected a whole number >= 1"),
])
def test_nnpc_mistakes_are_one_line_errors(tmp_path, make, args, message):
    if make == "garbage":
        (tmp_path / "bad.pt").write_bytes(b"not a model at all")
    (tmp_path / "x.parquet").write_bytes(b"")
    done = cli(*args, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], done.stderr


def test_a_cached_network_is_reused_only_for_the_same_identification_settings(tmp_path, monkeypatch):
    """trained_model caches per plant, rate and network; a changed seed (or sample count, or dither
    rule) must retrain instead of silently reusing a model identified differently."""
    import cosim.design.controller_factory as factory
    from cosim.fmi.binding import builtin_binding

    calls = []
    real_collect = factory.collect
    monkeypatch.setattr(factory, "collect", lambda *a, **k: calls.append(a[2]) or real_collect(*a, **k))
    binding = builtin_binding("averaged")
    first = factory.trained_model("nnpc", binding, 1e-3, tmp_path, samples=300, seed=1, model_path=None)
    again = factory.trained_model("nnpc", binding, 1e-3, tmp_path, samples=300, seed=1, model_path=None)
    assert len(calls) == 1 and again.metadata["collection"] == first.metadata["collection"]
    other = factory.trained_model("nnpc", binding, 1e-3, tmp_path, samples=300, seed=2, model_path=None)
    assert len(calls) == 2 and other.metadata["collection"]["seed"] == 2
    assert calls[0].excitation == 0.01 and calls[0].hold_range == (5, 40)  # the 1 ms identification rule


class _FailingFinalizer:
    def __del__(self):
        raise AttributeError("a finalizer of the workbench's own")


def test_after_an_interrupt_a_half_built_dask_future_is_not_reported_and_other_finalizer_errors_are(capsys,
                                                                                                     monkeypatch):
    """An interrupt inside distributed's Future constructor leaves a Future without its client, whose __del__ fails
    when collected: Python prints that as "Exception ignored ... Traceback" after the one-line "interrupted". Once
    interrupted, the command line drops exactly that report (cosim.cli._quiet_half_built_dask_objects); any other
    finalizer's error is still reported."""
    import gc

    import distributed

    from cosim import cli

    monkeypatch.setattr(sys, "unraisablehook", sys.__unraisablehook__)
    half_built = distributed.Future.__new__(distributed.Future)  # what an interrupted constructor leaves
    del half_built
    gc.collect()
    assert "AttributeError" in capsys.readouterr().err  # Python's own report: the noise the test removes
    cli._interrupted()
    half_built = distributed.Future.__new__(distributed.Future)
    del half_built
    gc.collect()
    assert capsys.readouterr().err == ""
    other = _FailingFinalizer()
    del other
    gc.collect()
    assert "a finalizer of the workbench's own" in capsys.readouterr().err


def test_a_reader_that_closes_the_pipe_ends_the_command_quietly(monkeypatch, capsys, buck_fmu):
    """``buck-cosim inspect X.fmu | head``: the pipe closes after the first lines -- a normal end (exit 0, nothing on
    stderr), not "error: Broken pipe"."""
    read, write = os.pipe()
    os.close(read)  # the reader is gone before the first line
    closed = os.fdopen(write, "w", buffering=1)  # line-buffered: the first line already meets the closed pipe
    monkeypatch.setattr(sys, "stdout", closed)
    assert main(["inspect", str(buck_fmu)]) == 0
    assert capsys.readouterr().err == ""


def test_a_broken_pipe_that_is_not_the_output_is_an_error(monkeypatch, capsys, buck_fmu):
    """Only the reader of stdout going away is a normal end: a pipe to another process breaking is one error line."""
    import cosim.fmi.inspect

    def broken(path):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(cosim.fmi.inspect, "describe_fmu", broken)
    assert main(["inspect", str(buck_fmu)]) == 2
    assert capsys.readouterr().err == "error: Broken pipe\n"


@pytest.mark.parametrize("option", ["--control-period", "--record-period"])
def test_a_negative_period_gets_the_periods_own_message(tmp_path, option):
    """argparse takes "-1e-3" for an option ("expected one argument"); the workbench passes it to the option."""
    done = cli("run", "startup", option, "-1e-3", "--kp", "0", "--ki", "14", "--out", str(tmp_path))
    assert done.returncode == 2 and "expected one argument" not in done.stderr, done.stderr
    assert "-1e-3" in done.stderr and "expected" in done.stderr and len(done.stderr.strip().splitlines()) == 1


def test_the_version_is_the_installed_packages():
    from importlib.metadata import version

    done = cli("--version")
    assert done.returncode == 0 and done.stdout.strip() == f"buck-cosim {version('buck-cosim')}"


def test_a_controller_exception_names_its_line_and_debug_shows_the_traceback(tmp_path):
    """A user's controller that raises: the one line names the file and line that raised; --debug (or
    BUCK_COSIM_DEBUG=1) adds the whole traceback, the controller's own frames included."""
    (tmp_path / "mine.py").write_text(
        "from controllers.base import Controller\n\n\n"
        "class Mine(Controller):\n"
        "    def __init__(self, sample_period, duty_limits=(0.0, 1.0)):\n"
        "        self.name, self.sample_period, self.duty_limits = 'Mine', sample_period, duty_limits\n\n"
        "    def reset(self):\n        pass\n\n"
        "    def step(self, measurement):\n"
        "        return 1 / 0\n")
    args = ["run", "startup", "--controller", f"{tmp_path / 'mine.py'}:Mine", "--out", str(tmp_path / "out"),
            "--no-figures"]
    line = one_line_error(command(*args), 3, f"controller Mine raised ZeroDivisionError at t = 0 s "
                                             f"({tmp_path / 'mine.py'}:12): division by zero")
    assert "Traceback" not in line
    for done in (command("--debug", *args), command(*args, env={**os.environ, "BUCK_COSIM_DEBUG": "1"})):
        assert done.returncode == 3 and done.stderr.startswith("error: controller Mine raised ZeroDivisionError")
        assert "Traceback (most recent call last)" in done.stderr and 'mine.py", line 12, in step' in done.stderr


def test_a_csv_where_samples_are_expected_and_a_metrics_table_where_a_run_is_are_named(tmp_path):
    (tmp_path / "data.csv").write_text("measured_inductor_current,measured_output_voltage,duty_cycle\n1,2,0.3\n")
    one_line_error(command("train", str(tmp_path / "data.csv"), "--out", str(tmp_path / "m.pt")), 2,
                   f"{tmp_path / 'data.csv'} is not a Parquet file (it is a CSV): expected the samples .parquet that "
                   "buck-cosim collect-data writes")
    (tmp_path / "metrics.csv").write_text("scenario,controller,plant,iae_Vs\nstartup,PI,x,0.01\n")
    one_line_error(command("compare", str(tmp_path / "metrics.csv"), "--out", str(tmp_path / "cmp")), 2,
                   f"{tmp_path / 'metrics.csv'} is a metrics table (one row of metrics per run), not a run: give the "
                   "runs' own files")


def test_compare_warns_when_the_runs_differ_in_more_than_the_controller(tmp_path):
    """Overlaying a switched-plant run on an averaged-plant run draws the figure, and one warning line says the
    differences are not the controllers' alone."""
    for mode in ("averaged", "switched"):
        assert command("run", "startup", "--mode", mode, "--kp", "0.0017155", "--ki", "15.589", "--no-figures",
                       "--out", str(tmp_path / mode)).returncode == 0
    runs = [str(tmp_path / mode / "runs" / f"startup__pi__nominal-{mode}__1ms.parquet") for mode in ("averaged",
                                                                                                     "switched")]
    done = command("compare", *runs, "--out", str(tmp_path / "cmp"))
    assert done.returncode == 0, done.stderr
    assert done.stderr.strip() == ("warning: the runs overlaid are on different plants: BuckConverter (nominal, "
                                   "averaged); BuckConverter (nominal, switched): their differences are not the "
                                   "controllers' alone")
    same = command("compare", runs[0], runs[0], "--out", str(tmp_path / "same"))
    assert same.returncode == 0 and "warning" not in same.stderr
