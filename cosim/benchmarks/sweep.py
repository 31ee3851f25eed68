"""Group sweep: sweeps on dask, throughput on 1 and 2 workers, against the same runs without dask."""

from __future__ import annotations

import statistics
import time
from pathlib import Path

from cosim.benchmarks.common import BenchRow
from cosim.benchmarks.subjects import _benchmark_pi, _nn_model
from cosim.design.vocabulary import NNPC, PAPER_PERIOD, PI

SWEEP_SAMPLES = 100  # x 2 controllers (PI, NNPC) x start-up = the 200-run sweep of the benchmark


def _sweep_setup(quick: bool):
    """A 200-run tolerance sweep at 1 ms (L, C +-20 % on the switched plant; PI and NNPC, start-up):
    its plan, its controllers' recipes and its runs."""
    import tempfile

    from controllers.nn_model import save_model
    from cosim.base.digests import canonical
    from cosim.design.sweeps.plan import SweepPlan
    from cosim.design.sweeps.recipes import ControllerRecipe
    from cosim.design.sweeps.spec import parse_sweep

    samples = 4 if quick else SWEEP_SAMPLES
    spec = parse_sweep(f'scenarios = ["startup"]\ncontrollers = ["pi", "nnpc"]\nsamples = {samples}\nseed = 1\n'
                       '[plant]\nmode = "switched"\n[parameters]\ninductance = { tolerance = 0.2 }\n'
                       'capacitance = { tolerance = 0.2 }\n', None)
    plan = SweepPlan(spec)
    pi = _benchmark_pi(PAPER_PERIOD)
    model, _ = _nn_model("nnpc", PAPER_PERIOD, quick)
    with tempfile.TemporaryDirectory() as folder:  # the model as a worker receives it: a file's bytes
        blob = save_model(model, Path(folder) / "nnpc.pt").read_bytes()
    recipes = [ControllerRecipe("pi", PI, PAPER_PERIOD, canonical({"kp_per_V": pi.kp, "ki_per_V_s": pi.ki,
                                                                    "tuning": {"method": "benchmark gains"}})),
               ControllerRecipe("nnpc", NNPC, PAPER_PERIOD, canonical({"network": model.config.label}), blob)]
    return plan, recipes, plan.runs(recipes)


def _plain_runs(plan, recipes, runs) -> float:
    """Seconds for the runs in this process without dask: one plant, each controller built once,
    parameters set and the run and its metrics computed -- the work a sweep distributes."""
    from cosim.design.sweeps.designs import build
    from cosim.fmi.plant import open_plant
    from cosim.master import run_checked
    from cosim.metrics import run_metrics

    binding = plan.binding
    controllers = {r.name: build(r, binding, "c") for r in recipes}
    scenarios = plan.scenarios
    nominal = dict(binding.parameters)
    with open_plant(binding) as plant:
        plant.replace_parameters({**nominal, **dict(runs[0].parameters)})  # warm: first initialisation
        run_checked(plant, controllers[runs[0].controller], scenarios[runs[0].scenario], record_period=1e-5)
        start = time.perf_counter()
        for r in runs:
            plant.replace_parameters({**nominal, **dict(r.parameters)})
            run_metrics(run_checked(plant, controllers[r.controller], scenarios[r.scenario], record_period=1e-5))
        return time.perf_counter() - start


def _sweep_on(client, plan, recipes, runs, folder: Path) -> tuple[float, float]:
    """Seconds for the same runs through the sweep machinery on ``client`` (tasks, transfer, the
    workers' runs, every part written; the workers warmed up first: imports, FMU, C twins), and the
    runs' own seconds as the workers timed them (summed)."""
    from cosim.design.sweeps import dataset
    from cosim.design.sweeps.execute import SweepExecution, execute
    from cosim.design.sweeps.worker import RunSettings, run_batch

    settings = RunSettings(1e-5, "c", False)
    controllers = {r.name: r for r in recipes}
    tasks = plan.batches(runs)
    warm = [client.submit(run_batch, plan.plant, controllers[t.controller], plan.scenarios[t.scenario], t.runs[:1],
                          settings, workers=[address], pure=False)
            for address in client.scheduler_info()["workers"] for t in tasks[:2]]
    client.gather(warm)
    schema = dataset.row_schema([(i.axis.name, i.unit, i.integer) for i in plan.axes])
    execution = SweepExecution(tasks, plan.plant, controllers, plan.scenarios, settings, schema, folder)
    start = time.perf_counter()
    execute(execution, client, lambda counts: "interrupted")
    elapsed = time.perf_counter() - start
    return elapsed, float(dataset.read_timing(folder)["wall_time_s"].sum())


def bench_sweep(quick: bool) -> list[BenchRow]:
    import tempfile

    from cosim.design.cluster import dask_client

    plan, recipes, runs = _sweep_setup(quick)
    repeats = 1 if quick else 5
    plain, on, machinery = [], {1: [], 2: []}, []
    starts = {}
    with tempfile.TemporaryDirectory(prefix="buck-bench-sweep-") as tmp:
        for workers in (1, 2):
            start = time.perf_counter()
            with dask_client(workers=workers) as client:
                client.wait_for_workers(workers, timeout=120)
                starts[workers] = time.perf_counter() - start
                for repeat in range(repeats):  # interleaved with the plain runs, so drift hits both alike
                    if workers == 1:
                        plain.append(_plain_runs(plan, recipes, runs))
                    elapsed, runs_own = _sweep_on(client, plan, recipes, runs, Path(tmp) / f"{workers}-{repeat}")
                    on[workers].append(elapsed)
                    if workers == 1:  # one worker: the runs' own time is the sweep's minus the machinery's
                        machinery.append(1 - runs_own / elapsed)
    n = len(runs)
    rate = {w: n / statistics.median(t) for w, t in on.items()}
    plain_rate = n / statistics.median(plain)
    scaling = rate[2] / rate[1]
    overhead = statistics.median(on[1]) / statistics.median(plain) - 1
    label = f"{n}-run sweep at 1 ms (PI and NNPC, start-up, switched plant, L and C +-20 %)"
    return [
        BenchRow(f"sweep throughput without dask: the same runs in one process, {label}", plain_rate, None, "runs/s"),
        BenchRow(f"sweep throughput on a LocalCluster of 1 worker, {label}", rate[1], n / max(on[1]), "runs/s",
                 note="p99 column: the slowest repeat; workers warmed up (imports, FMU, C twins) before timing"),
        BenchRow(f"sweep throughput on a LocalCluster of 2 workers, {label}", rate[2], n / max(on[2]), "runs/s",
                 note="p99 column: the slowest repeat"),
        BenchRow("sweep scaling: 2 workers / 1 worker (median runs/s)", scaling, None, "ratio", ">= 1.8 on 2 cores",
                 scaling >= 1.8, "the workbench's process (scheduler, part writing) shares the 2 cores"),
        BenchRow("sweep overhead per run: 1-worker sweep / the same runs without dask - 1", overhead * 100, None, "%",
                 "<= 5 %", overhead <= 0.05, "tasks, transfer, one Parquet part per task, progress; measured "
                 "against runs in another process at another moment, so the shared machine's drift is in it"),
        BenchRow("sweep machinery share of a 1-worker sweep: 1 - (the runs' own time on the worker) / (sweep time)",
                 statistics.median(machinery) * 100, max(machinery) * 100, "%", note="the same sweep timed from "
                 "both sides (no drift between two measurements); p99 column: the worst repeat"),
        BenchRow("LocalCluster start-up, 2 worker processes (until both are ready)", starts[2], None, "s"),
    ]
