"""Smoke test: every benchmark runs once on a tiny size, so the suite cannot rot."""

from __future__ import annotations

import pandas as pd

from cosim.benchmark_harness.cortex_m4 import toolchain_problem
from cosim.benchmark_harness.instruction_count import problem as counting_problem
from cosim.benchmarks import BENCHMARKS
from cosim.cli import main


def test_every_benchmark_runs_quickly_and_writes_both_files(tmp_path, capsys):
    assert main(["bench", "--quick", "--out", str(tmp_path)]) == 0
    table = pd.read_csv(tmp_path / "benchmarks-quick.csv")
    markdown = (tmp_path / "benchmarks-quick.md").read_text()
    assert len(table) >= len(BENCHMARKS)
    measured = ~table["benchmark"].str.contains(": not measured")  # the embedded group without its toolchain
    growth = table["benchmark"].str.contains("resident memory growth")  # may shrink: a difference, not a cost
    # the sweep's overhead per run is a difference too (1-worker sweep / the same runs without dask - 1): on a busy
    # machine the quick size's few runs measured it at -74 %
    overhead = table["benchmark"].str.startswith("sweep overhead per run")
    assert overhead.sum() == 1 and table.loc[overhead, "median"].notna().all()
    assert (table.loc[measured & ~growth & ~overhead, "median"] > 0).all()
    assert table.loc[growth, "median"].notna().all() and growth.sum() == 2
    assert "| benchmark | median | p99 |" in markdown and "## What profiling changed" in markdown
    for row in ("plant doStep, switched mode", "master overhead ratio",
                "controller compute per step, NNPC, 1 ms, C twin",
                "controller compute per step, NNPC, 1 ms, Python reference",
                "controller compute per step, MPC-mismatched, 13.33 us, C twin", "data collection, 500 samples",
                "NN training, 3-7-2", "speed-up of numpy over torch", "end-to-end reproduction",
                "quick converter study of the second converter (buck-cosim study --quick, smoke size",
                "reproduction time with the RTI / with the search (same run)",
                "floor of the RTI / search ratio, an optimizer that took no time anywhere",
                "worker time where a predictive controller plans, the search the default",
                "floor of the RTI / search ratio, a default optimizer that took no time",
                "worker time with the RTI / with the search, the parts issue 24's target names in parentheses",
                "share of the wall time the 2 workers were busy, the RTI the default",
                "x86-64 instructions per C RTI step, load_change" + (": not measured" if counting_problem() else ""),
                "NNPC IAE / oracle-MPC IAE, startup", "C step, NNPC, 1 ms", "speed-up of C over Python, NNPC",
                "NNPC 1 ms per RTI step on a 170 MHz Cortex-M4F", "NNPC 13.33 us per RTI step: tanh calls",
                "NNPC (search) 13.33 us per step: tanh calls", "C step, NNPC-explicit, 13.33 us",
                # the default optimizer (the RTI at both rates), the search beside it, and the two-step variants
                "C RTI step, NNPC, 1 ms", "C RTI step, NNPC, 13.33 us", "C step, NNPC (search), 13.33 us",
                "C step, NNPC (search), 1 ms", "NNPC 13.33 us per RTI step: box-QP iterations (counted)",
                "C RTI step, NNPC (rti, two steps), 13.33 us",
                "C RTI step, NNPC (rti, two steps, reused Jacobian), 13.33 us",
                # the same steps, each sample's median over the passes (the OS's interruptions left out)
                "C RTI step, NNPC, 13.33 us, each sample's median over the", "C RTI step, NNPC, 1 ms, each sample's",
                "C RTI NNPC step, startup",
                "do-mpc (IPOPT) step on the same problem, load_change", "do-mpc step / C RTI step, startup",
                "closed-loop IAE, C RTI / do-mpc, load_change", "NNPC-explicit 13.33 us per step: multiply-accumulates (counted)",
                "NNPC-explicit 13.33 us per step on a 170 MHz Cortex-M4F",
                "sweep throughput on a LocalCluster of 2 workers", "sweep overhead per run",
                "plant doStep, averaged DCM at d = 1e-07", "averaged DCM cost spread over d",
                "soak: worker resident memory growth", "soak: the workbench's own process",
                "C step, NNPC-adaptive (RLS + RTI, controllers/c/adaptation.c), 13.33 us: the",
                "C step, NNPC-adaptive (RLS + RTI, controllers/c/adaptation.c), 13.33 us: the RTI samples, each sample's median",
                # each RTI step's x86-64 instructions (callgrind), where valgrind is installed
                "x86-64 instructions per C RTI step, NNPC, 13.33 us" + (": not measured" if counting_problem() else ""),
                "x86-64 instructions per C step, NNPC-explicit, 13.33 us"
                + (": not measured" if counting_problem() else " (callgrind; every one of the 40 samples"),
                "x86-64 instructions per C step, NNPC-adaptive (RLS + RTI, controllers/c/adaptation.c), 13.33 us"
                + (": not measured" if counting_problem() else ""),
                "Cortex-M4F measurements (QEMU mps2-an386)" if toolchain_problem() else
                "NNPC-explicit 13.33 us on a Cortex-M4F (float32, QEMU mps2-an386): max cycles per step",
                "Cortex-M4F measurements (QEMU mps2-an386)" if toolchain_problem() else
                "online NNPC (RTI, 4-7-2) 1 ms on a Cortex-M4F (float32, QEMU mps2-an386): cycles per RTI step"):
        assert table["benchmark"].str.startswith(row).any(), row
    # the 1 ms NNPC's p99 target is on both implementations' rows, each judged on its own p99
    compute = table[table["benchmark"].str.startswith("controller compute per step, NNPC, 1 ms, ")]
    assert len(compute) == 2 and (compute["target"] == "p99 <= 100 us").all()
    assert (compute["meets_target"].astype(bool) == (compute["p99"] <= 100)).all(), compute[["benchmark", "p99"]]
    # and they time two different steps: the C twin's (ctypes call included) far below numpy's on the same problem
    c_twin, python = (compute.loc[compute["benchmark"].str.contains(name), "median"].item()
                      for name in ("C twin", "Python reference"))
    assert 10 * c_twin < python, (c_twin, python)
    assert table["command"].iloc[0] == "buck-cosim bench --quick"
    assert " cores), Linux " in table["machine"].iloc[0] and table["machine"].nunique() == 1
    # rerunning one group replaces only its rows; the others keep their values and their command
    assert main(["bench", "--quick", "--only", "plant", "--out", str(tmp_path)]) == 0
    merged = pd.read_csv(tmp_path / "benchmarks-quick.csv")
    assert list(merged["benchmark"]) == list(table["benchmark"])
    plant = merged["group"] == "plant"
    assert set(merged.loc[plant, "command"]) == {"buck-cosim bench --only plant --quick"}
    pd.testing.assert_frame_equal(merged[~plant].reset_index(drop=True),
                                  table[table["group"] != "plant"].reset_index(drop=True))
    header = (tmp_path / "benchmarks-quick.md").read_text().splitlines()[2]
    assert header.startswith("Commands: ") and "`buck-cosim bench --only plant --quick` (plant)" in header
    assert "`buck-cosim bench --quick` (master, controllers," in header
    # a group rerun on another machine: the kept rows keep the machine that measured them, the header names both
    merged.loc[~plant, "machine"] = "Other CPU (8 cores), Linux 5.0, Python 3.11.0"
    merged.to_csv(tmp_path / "benchmarks-quick.csv", index=False)
    assert main(["bench", "--quick", "--only", "plant", "--out", str(tmp_path)]) == 0
    remerged = pd.read_csv(tmp_path / "benchmarks-quick.csv")
    assert set(remerged.loc[remerged["group"] != "plant", "machine"]) == {"Other CPU (8 cores), Linux 5.0, Python 3.11.0"}
    assert set(remerged.loc[remerged["group"] == "plant", "machine"]) == set(table["machine"])
    machines = (tmp_path / "benchmarks-quick.md").read_text().splitlines()[3]
    assert machines.startswith(f"Machines: {table['machine'].iloc[0]} (plant); Other CPU (8 cores), Linux 5.0, "
                               "Python 3.11.0 (master, controllers,")


def test_the_trained_models_are_read_beside_the_output_not_from_the_working_directory(tmp_path, monkeypatch):
    """The groups that time the reproduction's models read OUT/models (or --models), whatever the working
    directory: before, they read ./results/models while writing to --out, so a bench run from another
    folder, or into another results folder, silently trained a model of its own."""
    import shutil
    from pathlib import Path

    import cosim.benchmarks.suite as suite
    import cosim.design.data_collection as data_collection
    from cosim.benchmarks import BenchRow, run_benchmarks
    from cosim.benchmarks.subjects import _nn_model
    from cosim.design.vocabulary import PAPER_PERIOD

    name = "nominal-switched__1ms__nnpc.pt"
    shutil.copy(Path(__file__).resolve().parents[1] / "results" / "models" / name, (tmp_path / "models").mkdir() or
                tmp_path / "models" / name)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)

    def must_not_train(*args, **kwargs):
        raise AssertionError("the model was not found, so the benchmark collected data to train one")

    monkeypatch.setattr(data_collection, "collect", must_not_train)
    monkeypatch.setattr(suite, "BENCHMARKS", {"probe": lambda quick: [
        BenchRow("probe", 0.0, None, "", note=_nn_model("nnpc", PAPER_PERIOD, False)[1])]})
    run_benchmarks(tmp_path, only=["probe"])
    table = pd.read_csv(tmp_path / "benchmarks.csv")
    assert table.loc[0, "note"] == str(tmp_path / "models" / name)
    other = tmp_path / "other"
    (other / "models").mkdir(parents=True)
    shutil.copy(tmp_path / "models" / name, other / "models" / name)
    run_benchmarks(tmp_path / "out2", only=["probe"], models_dir=other / "models")
    assert pd.read_csv(tmp_path / "out2" / "benchmarks.csv").loc[0, "note"] == str(other / "models" / name)


def test_the_per_sample_median_drops_one_pass_interruptions_and_keeps_what_the_data_costs():
    """Interrupts that land in one pass of a sample leave its median; a sample that is slow in every pass (a costly
    input: the QP's iterations) stays slow -- so the p99 of the medians is the data's worst case, where the raw p99
    over every pass is the interruptions'."""
    import numpy as np

    from cosim.benchmarks.common import _p99, per_sample_median

    passes = np.full((5, 200), 10.0)
    passes[2, :20] = 60.0  # 2 % of all steps interrupted, one pass each
    passes[[0, 3], 150] = 40.0  # interrupted in two of five passes: still the majority's cost
    passes[:, 190:] = [[14.0], [14.5], [15.0], [14.2], [30.0]]  # ten costly samples (5 %), one pass interrupted
    typical = per_sample_median(passes)
    assert typical.shape == (200,)
    assert (typical[:190] == 10.0).all() and (typical[190:] == 14.5).all()
    assert _p99(passes.ravel()) == 60.0 and _p99(typical) == 14.5


def test_the_reproductions_worker_time_is_split_by_whether_an_optimizer_plans_in_it():
    """bench_reproduction_optimizer's floor: the stages of timings.csv summed into where a predictive controller
    plans (with the tolerance study's and the envelope map's worker time, not their wall-clock spans) and where no
    optimizer enters; a stage in neither list is refused by name rather than left out of both."""
    import pytest

    from cosim.benchmarks.reproduction import worker_seconds

    rows = [("reproduction", "", "wall time on 2 worker process(es)", 500.0),
            ("tolerance study", "", "600 runs: worker time", 10.0),
            ("tolerance study", "", "last part written after its first task", 400.0),
            ("envelope map", "", "1800 runs: worker time", 50.0),
            ("envelope map", "", "last part written after its first task", 90.0),
            ("envelope map", "", "tables and figures", 3.0),
            ("ssp agreement", "", "4 parts: worker time", 40.0),
            ("ssp agreement", "", "tables, figures and report section", 5.0),
            ("stage", "a", "identification_nnpc_s", 100.0), ("stage", "a", "runs_s", 20.0),
            ("stage", "a", "distillation_episodes_s", 30.0), ("stage", "a", "distillation_training_s", 40.0),
            ("stage", "b", "identification_nnpc_s", 7.0), ("stage", "b", "optimizer_ablation_s", 2.0),
            ("controller p50", "a", "startup / NNPC", 5.0)]
    table = pd.DataFrame(rows, columns=["kind", "pipeline", "what", "value"]).assign(unit="s")
    table.loc[len(table)] = ["stage", "b", "identification_ablation_s", 4.0, "s"]
    assert worker_seconds(table) == {"planning": 10.0 + 50.0 + 40.0 + 20.0 + 30.0 + 2.0, "optimizer_free": 147.0,
                                     "mixed": 4.0, "search_by_design": 2.0, "named": 20.0 + 30.0 + 50.0}
    table.loc[len(table)] = ["stage", "b", "new_study_s", 1.0, "s"]
    with pytest.raises(ValueError, match="new_study_s in none of PLANNING_STAGES, OPTIMIZER_FREE_STAGES and "
                                         "MIXED_STAGES"):
        worker_seconds(table)


def test_a_jobs_stages_are_disjoint_so_that_its_worker_time_adds_up(tmp_path, monkeypatch):
    """The runs' stage of a pipeline job is timed without the ablations inside it (before, runs_s held the
    optimizer ablation and the identification ablation, which the worker-time split then counted twice): on the
    quick profile's 1 ms pipeline, its optimizer ablation made 3 s longer, the job's stages add up to no more than
    its wall time."""
    import time
    from dataclasses import replace

    from cosim.study import optimizer_ablation
    from cosim.study.reproduce import PIPELINES, QUICK, run_pipeline

    compare = optimizer_ablation.compare

    def slow_compare(*args, **kwargs):
        time.sleep(3.0)
        return compare(*args, **kwargs)

    monkeypatch.setattr(optimizer_ablation, "compare", slow_compare)
    pipeline = next(p for p in PIPELINES if p.tag == "nominal-switched__1ms")
    start = time.perf_counter()
    output = run_pipeline(pipeline, tmp_path, replace(QUICK, ablations=True), 0)
    elapsed = time.perf_counter() - start
    assert {"runs_s", "optimizer_ablation_s", "identification_nnpc_s"} <= set(output.timings)
    assert output.timings["optimizer_ablation_s"] >= 2 * 3.0  # NNPC and MPC-oracle, each compared once
    assert 0 < output.timings["runs_s"] and sum(output.timings.values()) <= elapsed, (output.timings, elapsed)
