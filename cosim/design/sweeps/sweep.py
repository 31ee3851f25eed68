"""``buck-cosim sweep``: a sweep file to a dataset and a summary, on a local or a remote dask cluster.

Order of work, so that every mistake is refused before anything runs: the sweep file (keys,
types, values), the plant (parameters exist, values within bounds, roles for the scenarios), the
output folder (a finished or different sweep is not overwritten), the cluster (the scheduler
answers, its workers can load this FMU); then the controllers are designed on the nominal plant
(cached in the output folder), the runs not yet in the dataset are run, and the summary is written.

Exit codes (``cosim.cli``): 0 every run complete; 2 a mistake in the sweep file, the plant, the
output folder or ``--scheduler``; 3 the sweep finished but some runs failed (their rows say why);
5 the dask scheduler went away mid-sweep (``--resume`` against a new one finishes the rest);
130 interrupted (``--resume`` finishes the rest).
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from cosim.base.errors import ConfigError, WorkbenchError
from cosim.base.files import atomic_write_text, remove_temporary_files
from cosim.design.sweeps import dataset
from cosim.design.sweeps.designs import describe, design
from cosim.design.sweeps.execute import SweepExecution, execute
from cosim.design.sweeps.plan import SweepPlan
from cosim.design.sweeps.spec import SweepSpec, load_sweep
from cosim.design.sweeps.summary import SweepSummary, summarise
from cosim.design.sweeps.worker import RunSettings, worker_facts
from cosim.fmi.archive import check_fmu
from cosim.master import check_set_up

MANIFEST_FORMAT = "buck-cosim sweep 1"
TIMINGS = "timings.json"


class RunsFailed(WorkbenchError):
    """The sweep finished, but some runs failed (each is a row with status ``failed`` and its cause)."""

    exit_code = 3


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@dataclass
class SweepOutcome:
    out_dir: Path
    sweep_id: str
    planned: int
    done_before: int
    computed: int
    failed: int  # failed rows among the planned runs (this time or before)
    elapsed: float  # [s] wall clock of the runs this time (cluster up, controllers designed)
    summary: SweepSummary
    cluster: str = ""

    @property
    def runs_per_second(self) -> float:
        return self.computed / self.elapsed if self.elapsed > 0 else float("nan")


def check_output(plan: SweepPlan, out_dir: Path, resume: bool) -> bool:
    """Refuse to mix sweeps in one folder: without ``--resume`` the folder must hold no sweep, or this
    very sweep complete (then the command is a no-op: True is returned); with it, the same sweep
    (same id: the same plant, axes, samples, seed, scenarios, controllers, rates)."""
    manifest = dataset.read_manifest(out_dir)
    exists = manifest is not None or dataset.has_rows(out_dir)
    if not exists:
        return False
    held = manifest.get("sweep_id", "unknown") if manifest else "unknown"
    same = manifest is not None and held == plan.sweep_id()
    if not resume and same and len(dataset.done_run_ids(out_dir)) >= int(manifest.get("runs", -1)) >= 0:
        return True  # every planned run has its row: nothing to do
    if not resume:
        raise ConfigError(f"{out_dir} already holds a sweep (id {held}), not complete: pass --resume to finish it, "
                          "or choose another --out" if same else
                          f"{out_dir} already holds another sweep (id {held}): choose another --out (or pass "
                          "--resume with its sweep file)")
    if not same:
        changed = []
        if manifest is not None:
            old, new = manifest.get("identity", {}), plan.identity()
            changed = [key for key in new if old.get(key) != json.loads(json.dumps(new[key], default=str))]
        raise ConfigError(f"--resume: {out_dir} holds sweep {held}, but {plan.spec.path or 'the sweep file'} describes "
                          f"sweep {plan.sweep_id()}" + (f" (changed: {', '.join(changed)})" if changed else "")
                          + ": resume with the original file, or choose another --out")
    return False


def check_workers(client, plan: SweepPlan) -> None:
    """Every worker can import the workbench and load the plant's and the controller FMUs' binaries,
    before any work is sent."""
    try:
        facts = client.run(worker_facts)
    except Exception as error:
        raise ConfigError(f"the dask workers cannot run the workbench ({type(error).__name__}: {error}): install "
                          "buck-cosim (same version) in every worker's environment") from None
    if not facts:
        raise ConfigError("the dask cluster has no workers")
    fmus = [Path(plan.binding.fmu_path)] + [Path(c.fmu) for c in plan.spec.controllers if c.fmu is not None]
    for fmu in fmus:  # the plant's and the controller FMUs'
        checked = check_fmu(fmu)
        for address, fact in sorted(facts.items()):
            if fact["platform"] not in checked.platforms:
                raise ConfigError(f"worker {address} ({fact['host']}) runs platform {fact['platform']}, but "
                                  f"{fmu.name} has binaries for {', '.join(checked.platforms)} only: the FMU binary "
                                  "must suit the workers' platform")


class PreparedSweep:
    """A sweep with its controllers designed and its remaining runs grouped into tasks."""

    def __init__(self, plan: SweepPlan, out_dir: Path, recipes, progress: bool = False, extra_columns=()):
        self.plan, self.spec, self.out_dir, self.recipes = plan, plan.spec, Path(out_dir), recipes
        self.runs = plan.runs(recipes)
        done = dataset.done_run_ids(self.out_dir)
        self.todo = [r for r in self.runs if r.run_id not in done]
        self.done_before = len(self.runs) - len(self.todo)
        self.tasks = plan.batches(self.todo)
        self.schema = dataset.row_schema([(i.axis.name, i.unit, i.integer) for i in plan.axes], tuple(extra_columns))
        self.progress = progress
        self.sweep_id = plan.sweep_id()

    def write_manifest(self) -> None:
        spec = self.spec
        manifest = {"format": MANIFEST_FORMAT, "sweep_id": self.sweep_id, "name": spec.name,
                    "description": spec.description, "sweep_file": spec.path.name if spec.path else None,
                    "identity": self.plan.identity(), "controllers": describe(self.recipes),
                    "runs": len(self.runs), "thresholds": [t.text() for t in spec.thresholds]}
        dataset.write_manifest(self.out_dir, json.loads(json.dumps(manifest, default=str)))

    def execution(self) -> SweepExecution:
        settings = RunSettings(self.spec.record_period, self.spec.implementation, self.spec.keep_traces)
        return SweepExecution(self.tasks, self.plan.plant, {r.name: r for r in self.recipes}, self.plan.scenarios,
                              settings, self.schema, self.out_dir, progress=self.progress, label=self.spec.name)

    def describe_start(self, where: str) -> str:
        s = self.spec
        shape = f"{s.grid_points} grid point(s) x {s.samples} sample(s) x {len(s.scenarios)} scenario(s) x " \
                f"{len(s.controllers)} controller(s)"
        earlier = f"; {self.done_before} done earlier, kept (--resume)" if self.done_before else ""
        return (f"sweep {s.name} ({self.sweep_id}): {len(self.runs)} runs = {shape}{earlier}; running "
                f"{len(self.todo)} in {len(self.tasks)} task(s) on {where} -> {self.out_dir}/")

    def summarise(self, vector: bool = True) -> SweepSummary:
        """SWEEP.md and the figures from the rows of the planned runs (``vector``: SVG besides PNG)."""
        rows = dataset.read_rows(self.out_dir, self.schema)
        planned = {r.run_id for r in self.runs}
        rows = rows[rows["run_id"].isin(planned)]
        order = {r.run_id: i for i, r in enumerate(self.runs)}
        rows = rows.assign(_order=rows["run_id"].map(order)).sort_values("_order").drop(columns="_order")
        return summarise(self.spec, self.plan, self.recipes, rows.reset_index(drop=True), self.out_dir, self.sweep_id,
                         vector)


def interrupted(out_dir: Path, planned: int, done_before: int):
    def message(counts) -> str:
        done = done_before + counts.runs
        return (f"sweep interrupted: {done} of {planned} runs are in {out_dir}/{dataset.DATASET_DIR} (every part "
                f"complete); run the same command with --resume to finish the other {planned - done}")
    return message


def scheduler_lost(out_dir: Path, planned: int, done_before: int, where: str):
    def message(counts) -> str:
        done = done_before + counts.runs
        return (f"sweep stopped: the dask scheduler ({where}) went away; {done} of {planned} runs are in "
                f"{out_dir}/{dataset.DATASET_DIR} (every part complete); start a scheduler and workers again and run "
                f"the same command with --resume (--scheduler ADDRESS for a new address) to finish the other "
                f"{planned - done}")
    return message


def run_sweep(spec: SweepSpec | str | Path, out_dir: Path, *, scheduler: str | None = None, workers: int | None = None,
              resume: bool = False, progress: bool = False, connect_timeout: float | None = None) -> SweepOutcome:
    """Run a sweep (module docstring); returns what happened, the summary included. Failed runs do not
    raise here (the caller decides: the command line exits 3)."""
    from cosim.design.cluster import CONNECT_TIMEOUT, cluster_text, dask_client

    spec = spec if isinstance(spec, SweepSpec) else load_sweep(spec)
    out_dir = Path(out_dir)
    plan = SweepPlan(spec)
    check_set_up(plan.binding, spec.scenarios)  # what the FMU refuses (binding parameters, events), before any cluster
    if check_output(plan, out_dir, resume):  # this sweep, complete: nothing to run, no cluster
        recipes = design(spec.controllers, plan.binding, spec.control_period, out_dir, progress)
        prepared = PreparedSweep(plan, out_dir, recipes, progress)
        if not prepared.todo:
            summary = prepared.summarise()
            log(f"sweep {spec.name} ({prepared.sweep_id}): all {len(prepared.runs)} runs are in {out_dir}/ already: "
                f"nothing to run (summary: {out_dir / 'SWEEP.md'})")
            return SweepOutcome(out_dir, prepared.sweep_id, len(prepared.runs), prepared.done_before, 0,
                                summary.counts["failed"], 0.0, summary, "none (nothing to run)")
        resume = True  # rows of the same sweep id, yet runs missing (the controllers' designs changed): finish them
    if scheduler is not None and workers is not None:
        raise ConfigError("--workers sizes the local cluster; with --scheduler the cluster's own workers run the sweep")
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers {workers} is invalid: expected >= 1")
    from plant_fmu import fmu_path

    fmu_path()  # the built-in FMU exists before workers start
    if spec.implementation == "c":
        from controllers.native import library

        library()  # and the C twins, built once here rather than by every local worker
    with dask_client(scheduler, workers, connect_timeout=connect_timeout or CONNECT_TIMEOUT) as client:
        check_workers(client, plan)
        where = cluster_text(client)
        recipes = design(spec.controllers, plan.binding, spec.control_period, out_dir, progress)
        prepared = PreparedSweep(plan, out_dir, recipes, progress)
        prepared.write_manifest()
        log(prepared.describe_start(where))
        started = time.perf_counter()
        try:
            counts = execute(prepared.execution(), client,
                             interrupted(out_dir, len(prepared.runs), prepared.done_before),
                             scheduler_lost(out_dir, len(prepared.runs), prepared.done_before, where))
        finally:
            remove_temporary_files(out_dir)
        elapsed = time.perf_counter() - started
    summary = prepared.summarise()
    outcome = SweepOutcome(out_dir, prepared.sweep_id, len(prepared.runs), prepared.done_before, counts.runs,
                           summary.counts["failed"], elapsed, summary, where)
    write_timings(outcome)
    log(f"sweep {spec.name}: {outcome.computed} run(s) in {elapsed:.1f} s ({outcome.runs_per_second:.1f} runs/s) on "
        f"{where}; {summary.counts['ok']} of {outcome.planned} complete, {outcome.failed} failed; "
        f"summary: {out_dir / 'SWEEP.md'}")
    return outcome


def write_timings(outcome: SweepOutcome) -> Path:
    """``timings.json``: the wall-clock figures of the sweep (never in SWEEP.md or the dataset)."""
    timing = dataset.read_timing(outcome.out_dir)
    durations = timing["wall_time_s"].astype(float).dropna()
    figures = {"runs_computed": outcome.computed, "elapsed_s": outcome.elapsed,
               "runs_per_second": outcome.runs_per_second, "cluster": outcome.cluster,
               "run_wall_time_median_s": float(durations.median()) if len(durations) else None,
               "run_wall_time_p99_s": float(durations.quantile(0.99)) if len(durations) else None}
    return atomic_write_text(outcome.out_dir / TIMINGS, json.dumps(figures, indent=2, sort_keys=True) + "\n")


def raise_if_failed(outcome: SweepOutcome) -> None:
    if outcome.failed:
        ok = outcome.summary.counts["ok"]
        raise RunsFailed(f"{outcome.failed} of {outcome.planned} runs failed (status 'failed' in "
                         f"{outcome.out_dir}/{dataset.DATASET_DIR}, causes in {outcome.out_dir}/SWEEP.md); the other "
                         f"{ok} runs and the summary are complete")
