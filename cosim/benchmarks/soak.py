"""Group soak: a long sweep on 2 local workers, each worker's and the workbench's resident memory growth."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

from cosim.benchmarks.common import BenchRow
from cosim.benchmarks.subjects import _benchmark_pi
from cosim.design.vocabulary import PAPER_PERIOD, PI

#: the soak: this many runs on 2 local workers (the issue-26 target: <= 50 MB of growth per worker and in the
#: workbench's own process)
SOAK_RUNS = 10_000
#: a worker's memory is taken as settled after its first runs this many (FMU extracted, C twins loaded, caches warm)
SOAK_WARM_RUNS = 100
SOAK_GROWTH_TARGET_MB = 50.0


def bench_soak(quick: bool) -> list[BenchRow]:
    """A long sweep on 2 local workers, each worker's resident memory after each of its runs read from the
    sweep's timing table (``worker_rss_mb``, ``worker_run``): growth from its run SOAK_WARM_RUNS to its last;
    the workbench's own process measured before and after. PI at 1 ms, the shipped start-up on the averaged
    plant, L +-20 % (a run costs ~20 ms; 10 000 runs take a few minutes)."""
    import tempfile

    from cosim.base.digests import canonical
    from cosim.design.cluster import dask_client
    from cosim.design.sweeps import dataset
    from cosim.design.sweeps.execute import SweepExecution, execute
    from cosim.design.sweeps.plan import SweepPlan
    from cosim.design.sweeps.recipes import ControllerRecipe
    from cosim.design.sweeps.spec import parse_sweep
    from cosim.design.sweeps.worker import RunSettings, run_batch
    from cosim.fmi.isolation import resident_bytes

    runs_wanted = 2 * (SOAK_WARM_RUNS + 10) if quick else SOAK_RUNS
    spec = parse_sweep(f'scenarios = ["startup"]\ncontrollers = ["pi"]\nsamples = {runs_wanted}\nseed = 2\n'
                       'batch_size = 50\n[plant]\nmode = "averaged"\n[parameters]\n'
                       'inductance = { tolerance = 0.2 }\n', None)
    plan = SweepPlan(spec)
    pi = _benchmark_pi(PAPER_PERIOD)
    recipes = [ControllerRecipe("pi", PI, PAPER_PERIOD, canonical({"kp_per_V": pi.kp, "ki_per_V_s": pi.ki,
                                                                    "tuning": {"method": "benchmark gains"}}))]
    runs = plan.runs(recipes)
    settings = RunSettings(1e-4, "c", False)
    controllers = {r.name: r for r in recipes}
    tasks = plan.batches(runs)
    schema = dataset.row_schema([(i.axis.name, i.unit, i.integer) for i in plan.axes])
    with tempfile.TemporaryDirectory(prefix="buck-bench-soak-") as folder, dask_client(workers=2) as client:
        client.wait_for_workers(2, timeout=120)
        warm = [client.submit(run_batch, plan.plant, controllers[t.controller], plan.scenarios[t.scenario],
                              t.runs[:1], settings, workers=[address], pure=False)
                for address in client.scheduler_info()["workers"] for t in tasks[:1]]
        client.gather(warm)
        own_before = resident_bytes(os.getpid())
        execution = SweepExecution(tasks, plan.plant, controllers, plan.scenarios, settings, schema, Path(folder))
        start = time.perf_counter()
        execute(execution, client, lambda counts: "interrupted")
        elapsed = time.perf_counter() - start
        own_after = resident_bytes(os.getpid())
        timing = dataset.read_timing(Path(folder))
    growth, last = {}, {}
    for worker, rows in timing.groupby("worker"):
        rows = rows.sort_values("worker_run")
        settled = rows[rows["worker_run"] >= SOAK_WARM_RUNS]
        growth[worker] = float(settled["worker_rss_mb"].iloc[-1] - settled["worker_rss_mb"].iloc[0])
        last[worker] = float(rows["worker_rss_mb"].iloc[-1])
    worst = max(growth.values())
    own = (own_after - own_before) / 1e6 if own_before and own_after else math.nan
    label = f"{len(runs)}-run sweep on 2 workers (PI, start-up, averaged plant, L +-20 %)"
    return [
        BenchRow(f"soak: worker resident memory growth over a {label}, worst worker", worst, None, "MB",
                 f"<= {SOAK_GROWTH_TARGET_MB:g} MB", worst <= SOAK_GROWTH_TARGET_MB,
                 f"from each worker's run {SOAK_WARM_RUNS} to its last ({', '.join(f'{g:+.1f}' for g in growth.values())}"
                 f" MB; resident at the end: {', '.join(f'{v:.0f}' for v in last.values())} MB), read from the "
                 "sweep's timing table (worker_rss_mb)"),
        BenchRow(f"soak: the workbench's own process, resident memory growth over the {label}", own, None, "MB",
                 f"<= {SOAK_GROWTH_TARGET_MB:g} MB", own <= SOAK_GROWTH_TARGET_MB,
                 "scheduler, futures, parts written; from after the workers' warm-up to the end"),
        BenchRow(f"soak: throughput of the {label}", len(runs) / elapsed, None, "runs/s"),
    ]
