"""The paper reproduction: every experiment, end to end, into ``results/``.

One pipeline per plant (nominal averaged, nominal switched, mismatch-study switched) and control
rate (1 ms, one switching period). Each pipeline, all seeded:

1. tunes the PI on that plant at that rate (:mod:`cosim.study.pi_tuning`);
2. collects the NN training data with that PI (:mod:`cosim.study.data_collection`, 10 000 samples);
3. trains the paper's 3-7-2 network and the workbench's NNPC network (+ load conductance);
4. runs the four paper scenarios with PI, NNPC, the paper's NNPC, the oracle MPC (the exact
   averaged model of that plant) and the mismatched MPC (nominal model on the mismatch plant;
   on the nominal plant, the mismatch plant's parameters);
5. writes runs, metrics and figures as it goes.

Pipelines are independent and run as dask tasks on a LocalCluster (:mod:`cosim.study.cluster`,
one single-threaded worker process each); files are written atomically, so an interrupted
reproduction keeps what finished, and ``--resume`` skips finished pipelines. Once the nominal
switched 1 ms pipeline has finished, the tolerance study (:mod:`cosim.study.tolerance_study`) runs
its controllers on production units through the sweep engine, on the same cluster.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import pandas as pd

from cosim.base.errors import PlantError, WorkbenchError
from cosim.base.files import atomic_write_text, remove_temporary_files
from cosim.batch import Batch, write_metrics
from cosim.batch import run_batch as batch_runs
from cosim.metrics import WALLCLOCK_METRICS
from cosim.scenarios import PAPER_SCENARIOS
from cosim.study import tolerance_study
from cosim.study.data_collection import collect, save_samples
from cosim.study.experiments import (collection_settings, implemented, model_mpc, nn_configs, nnpc, plant_binding,
                                    scenarios_for)
from cosim.study.pi_tuning import load_or_tune
from cosim.study.report import write_report
from cosim.study.timings import write_timings
from cosim.study.vocabulary import (
    CONTROLLER_STYLES,
    MISMATCH,
    MPC_MISMATCHED,
    MPC_NOMINAL,
    MPC_ORACLE,
    MPC_ORACLE_AVERAGED,
    MPC_ORACLE_SYNC,
    NNPC,
    NNPC_PAPER,
    NOMINAL,
    PAPER_PERIOD,
    PLANT_VARIANTS,
    STUDY_PERIODS,
    horizon_variant,
    pipeline_tag,
    plant_tag,
    seed_variant,
    transient_within_sample,
)


@dataclass(frozen=True)
class Profile:
    """Sizes of the reproduction; ``quick`` is the CI smoke profile (tiny, meaningless numbers)."""

    samples: int = 10_000
    scenarios: tuple[str, ...] = PAPER_SCENARIOS
    ablations: bool = True  # horizon N = 3 at 1 ms; at 13.33 us the oracle with eq. 3, and a synchronous sample
    seed_study: tuple[int, ...] = (1, 2)  # at 13.33 us on the nominal switched plant: NNPC identified again
    # with these seed offsets (data and training), to show how much the NNPC depends on its data
    quick: bool = False
    pipelines: tuple[str, ...] | None = None  # tags to run (default: all)
    tolerance_samples: int | None = None  # units of the tolerance study (default: its sweep file's)


FULL = Profile()
QUICK = Profile(samples=400, scenarios=("startup", "load_change"), quick=True, seed_study=(1,), tolerance_samples=3,
                pipelines=("nominal-averaged__1ms", "nominal-switched__1ms", "mismatch-switched__1ms",
                           "nominal-switched__13p33us"))


@dataclass(frozen=True)
class Pipeline:
    variant: str  # "nominal", "mismatch", or "bound" (an external FMU through ``binding_file``)
    mode: str  # "averaged" or "switched" (built-in plants)
    control_period: float
    binding_file: str | None = None

    @property
    def plant_tag(self) -> str:
        return self.binding().tag if self.binding_file else plant_tag(self.variant, self.mode)

    def binding(self):
        if self.binding_file:
            from cosim.fmi.binding_file import load_binding

            return load_binding(self.binding_file)
        return plant_binding(self.variant, self.mode)

    @property
    def tag(self) -> str:
        return pipeline_tag(self.plant_tag, self.control_period)


PIPELINES = tuple(Pipeline(variant, mode, period)
                  for period in STUDY_PERIODS
                  for variant, mode in (("nominal", "averaged"), ("nominal", "switched"), ("mismatch", "switched")))


@dataclass
class PipelineOutput:
    pipeline: Pipeline
    metrics: pd.DataFrame
    pi: dict
    models: dict[str, dict]  # name -> metadata (held-out RMSE, training)
    timings: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> str:
        """The summary written to ``pipelines/<tag>.json`` (no wall-clock figures: those are
        ``pipelines/<tag>.timings.json``, not committed, and ``timings.md``)."""
        return json.dumps({"pipeline": asdict(self.pipeline), "pi": self.pi, "models": self.models},
                          indent=2, sort_keys=True, default=str)


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run_pipeline(pipeline: Pipeline, out_dir: Path, profile: Profile, seed: int,
                 implementation: str = "c") -> PipelineOutput:
    import torch

    from controllers.nn_model import TrainingSettings, save_model, train

    torch.set_num_threads(1)  # two pipelines share two cores
    timings: dict[str, float] = {}
    tag, period = pipeline.tag, pipeline.control_period
    binding = pipeline.binding()

    start = time.perf_counter()
    pi = load_or_tune(out_dir / "tuning" / f"pi__{tag}.json", binding, period, record_period=2e-5,
                      quick=profile.quick)
    timings["pi_tuning_s"] = time.perf_counter() - start
    log(f"  {tag}: PI Kp = {pi.kp:.4g} 1/V, Ki = {pi.ki:.4g} 1/(V s) ({pi.evaluations} simulations, "
        f"{timings['pi_tuning_s']:.1f} s)")

    start = time.perf_counter()
    data = collect(binding, pi.controller(), collection_settings(period, profile.samples, seed))
    data.attrs["metadata"]["seed"] = seed
    data_path = out_dir / "data" / f"{tag}.parquet"
    save_samples(data, data_path)
    timings["data_collection_s"] = time.perf_counter() - start

    models, model_meta = {}, {}
    for name, config in nn_configs(period).items():
        start = time.perf_counter()
        model = train(data, config, TrainingSettings(seed=seed),
                      metadata={"control_period_s": period, "plant": binding.label,
                                "data_file": f"data/{tag}.parquet", "seed": seed})
        timings[f"training_{name}_s"] = time.perf_counter() - start
        save_model(model, out_dir / "models" / f"{tag}__{name}.pt")
        models[name] = model
        model_meta[name] = {"architecture": config.label, **model.metadata}
        rmse = model.metadata["held_out_rmse"]
        log(f"  {tag}: {name} {config.label}: one-step RMSE {rmse['one_step_rmse_voltage_V'] * 1e3:.1f} mV, "
            f"{rmse['one_step_rmse_current_A'] * 1e3:.1f} mA ({timings[f'training_{name}_s']:.1f} s)")

    controllers = [pi.controller(), nnpc(models["nnpc"], period, NNPC),
                   nnpc(models["nnpc-paper"], period, NNPC_PAPER)]
    if pipeline.binding_file:  # an external plant: only the Table II model is known
        controllers.append(model_mpc(NOMINAL, period, MPC_NOMINAL, binding=binding))
    else:
        true_parameters = PLANT_VARIANTS[pipeline.variant]
        wrong_parameters = NOMINAL if pipeline.variant == "mismatch" else MISMATCH
        wrong_name = MPC_NOMINAL if pipeline.variant == "mismatch" else MPC_MISMATCHED
        controllers += [model_mpc(true_parameters, period, MPC_ORACLE, binding=binding),
                        model_mpc(wrong_parameters, period, wrong_name, binding=binding)]
    scenarios = []
    for scenario in scenarios_for(period, profile.scenarios):
        missing = scenario.required_roles() - set(binding.roles)
        if missing:
            log(f"  {tag}: skipping {scenario.name}: {binding.origin} binds no {', '.join(sorted(missing))}")
        else:
            scenarios.append(scenario)
    batch = Batch(binding, scenarios)
    def run_batch(batch, controllers, out_dir, **options):  # every run with the chosen implementation
        return batch_runs(batch, [implemented(c, implementation) for c in controllers], out_dir, **options)

    start = time.perf_counter()
    output = run_batch(batch, controllers, out_dir, seed=seed, styles=CONTROLLER_STYLES,
                       extra_metadata={"pipeline": asdict(pipeline)})
    metrics = output.metrics
    if profile.ablations and pipeline.variant == "nominal" and pipeline.mode == "switched":
        if transient_within_sample(period):  # does a longer horizon change anything at 1 ms?
            ablation = run_batch(batch, [nnpc(models["nnpc"], period, horizon_variant(NNPC, 3), horizon=3)],
                                 out_dir, seed=seed, figures=False)
        else:  # the oracle blind to the sensor (eq. 3), and a synchronous point sample instead of the mean
            blind = run_batch(batch, [model_mpc(true_parameters, period, MPC_ORACLE_AVERAGED)], out_dir, seed=seed,
                              figures=False)
            synchronous = Batch(plant_binding(pipeline.variant, pipeline.mode, sensor="synchronous"), scenarios)
            ablation = run_batch(synchronous, [model_mpc(true_parameters, period, MPC_ORACLE_SYNC,
                                                         binding=synchronous.binding)],
                                 out_dir, seed=seed, figures=False)
            studies = [blind.metrics, ablation.metrics]
            for offset in profile.seed_study:  # the same NNPC identified from other seeded data
                other = seed + offset
                data = collect(binding, pi.controller(), collection_settings(period, profile.samples, other))
                model = train(data, nn_configs(period)["nnpc"], TrainingSettings(seed=other),
                              metadata={"control_period_s": period, "plant": binding.label, "seed": other})
                studies.append(run_batch(batch, [nnpc(model, period, seed_variant(NNPC, other))], out_dir,
                                         seed=other, figures=False).metrics)
            ablation.metrics = pd.concat(studies, ignore_index=True)
        ablation.metrics["plant_tag"] = pipeline.plant_tag
        metrics = pd.concat([metrics, ablation.metrics], ignore_index=True)
    timings["runs_s"] = time.perf_counter() - start
    metrics.insert(0, "pipeline", tag)
    log(f"  {tag}: {len(metrics)} runs ({timings['runs_s']:.1f} s)")
    output = PipelineOutput(pipeline=pipeline, metrics=metrics, pi=json.loads(pi.to_json()), models=model_meta,
                            timings=timings)
    write_metrics(metrics, out_dir / "metrics" / f"metrics__{tag}")
    atomic_write_text(out_dir / "pipelines" / f"{tag}.timings.json", json.dumps(timings, indent=2, sort_keys=True) + "\n")
    atomic_write_text(out_dir / "pipelines" / f"{tag}.json", output.to_json() + "\n")
    return output


@dataclass
class _Failed:
    """A pipeline's fault, returned (not raised) by its task: the workbench reports it in one line,
    where a raised exception would have dask print the task's traceback first."""

    error: WorkbenchError


def _run_job(job) -> PipelineOutput | _Failed:
    try:
        return run_pipeline(*job)
    except WorkbenchError as error:
        return _Failed(error)


def _pipeline_output(future, tag: str, out_dir: Path) -> PipelineOutput:
    """A finished pipeline task's output; its fault, or its worker's death, raised here."""
    from distributed.scheduler import KilledWorker

    if future.status != "finished":
        error = future.exception()
        if isinstance(error, KilledWorker):
            raise PlantError(f"a reproduction worker process died twice running pipeline {tag} (a plant FMU "
                             f"crashed it?); pipelines that finished are in {out_dir}/pipelines -- rerun with "
                             "--resume to continue") from None
        raise error
    output = future.result()
    if isinstance(output, _Failed):
        raise output.error
    return output


def _load_finished(out_dir: Path, pipeline: Pipeline) -> PipelineOutput | None:
    """A pipeline whose summary and metrics were written by an earlier (interrupted) run."""
    summary = out_dir / "pipelines" / f"{pipeline.tag}.json"
    metrics = out_dir / "metrics" / f"metrics__{pipeline.tag}.csv"
    if not (summary.is_file() and metrics.is_file()):
        return None
    data = json.loads(summary.read_text(encoding="utf-8"))
    table = pd.read_csv(metrics)
    timing = metrics.with_name(f"{metrics.stem}.timing.csv")
    if timing.is_file():  # the wall-clock metrics, in the same row order
        for column in WALLCLOCK_METRICS:
            table[column] = pd.read_csv(timing)[column].to_numpy()
    timings_file = summary.with_name(f"{pipeline.tag}.timings.json")
    timings = json.loads(timings_file.read_text(encoding="utf-8")) if timings_file.is_file() else {}
    return PipelineOutput(pipeline=pipeline, metrics=table, pi=data["pi"], models=data["models"], timings=timings)


#: dask priorities (higher first): the tolerance study's source pipeline, then the pipelines longest
#: first (so the workers finish together), the study's tasks whenever no pipeline waits for a worker
SOURCE_PRIORITY, STUDY_PRIORITY = 100, -10


def _run_on_cluster(todo: list[Pipeline], outputs: dict, out_dir: Path, profile: Profile, seed: int,
                    implementation: str, workers: int, resume: bool, study_wanted: bool):
    """The pipelines as dask tasks on a LocalCluster (longest first, so the workers finish together),
    and the tolerance study's tasks as soon as its source pipeline is done; returns the study and its
    execution counts (or None, None).
    On a fault or an interrupt the cluster is closed at once (its worker processes end with it)."""
    from distributed import as_completed

    from cosim.study.cluster import dask_client

    with dask_client(workers=max(1, workers), worker_saturation=1.0) as client:
        futures, submitted = {}, []
        # submitted in the order they should start (idle workers take the first ones at once; the
        # rest wait in the scheduler's queue by priority)
        order = sorted(todo, key=lambda p: (p.tag != tolerance_study.SOURCE_PIPELINE, _expected_length(p)))
        for rank, p in enumerate(order):
            priority = SOURCE_PRIORITY if p.tag == tolerance_study.SOURCE_PIPELINE else len(todo) - rank
            future = client.submit(_run_job, (p, out_dir, profile, seed, implementation), pure=False,
                                   key=f"buck-cosim-pipeline-{p.tag}", priority=priority)
            futures[future.key] = p
            submitted.append(future)
        queue = as_completed(submitted, loop=client.loop)
        study, execution = None, None

        def start_study():
            nonlocal study, execution
            study = tolerance_study.start(out_dir, resume, profile.tolerance_samples)
            execution = study.execution()
            log(f"  {study.describe_start('the same cluster')}")
            for future in execution.submit(client, priority=STUDY_PRIORITY):
                queue.add(future)

        if study_wanted and tolerance_study.ready(p.tag for p in outputs):
            start_study()
        try:
            done = 0
            for future in queue:
                if execution is not None and execution.owns(future):
                    for new in execution.handle(future):
                        queue.add(new)
                    continue
                pipeline = futures.pop(future.key)
                output = _pipeline_output(future, pipeline.tag, out_dir)
                outputs[pipeline] = output
                done += 1
                log(f"[{done}/{len(todo)}] {pipeline.tag} finished in {sum(output.timings.values()):.1f} s")
                if study_wanted and study is None and tolerance_study.ready(p.tag for p in outputs):
                    start_study()
        except BaseException:
            if execution is not None:
                execution.cancel()
            raise
        if execution is None:
            return None, None
        execution.close()
        log(f"  tolerance study: {execution.counts.runs} run(s) written ({execution.counts.failed} failed)")
        return study, execution.counts


def _expected_length(pipeline: Pipeline) -> tuple:
    """Sort key, longest first: the fast rate, and there the nominal switched plant (the switched
    oracle and its ablations)."""
    return (pipeline.control_period, not (pipeline.variant == "nominal" and pipeline.mode == "switched"))


def _study_timing(study, counts) -> dict | None:
    """The tolerance study's wall-clock figures for timings.md: its runs' worker time, and when its
    last part landed (its tasks share the cluster with the pipelines, so neither is its added cost)."""
    if study is None:
        return None
    from cosim.study.sweeps.dataset import read_timing

    worker_time = float(read_timing(study.out_dir)["wall_time_s"].astype(float).sum())
    return {"runs": counts.runs if counts else 0, "worker_s": worker_time, "last_part_s": counts.elapsed if counts else 0.0}


def reproduce(out_dir: Path = Path("results"), workers: int = 2, resume: bool = False, seed: int = 0,
              implementation: str = "c",
              profile: Profile = FULL, binding_file: str | None = None,
              control_periods: tuple[float, ...] = ()) -> Path:
    """Run every pipeline and write ``REPORT.md``; returns the report path.

    With ``binding_file``, the pipeline runs on that external plant at ``control_periods``
    (default 1 ms) instead of the built-in plants. ``implementation``: the controllers' C twins
    ("c", equivalent at every sample and faster) or their Python references ("python").
    """
    from plant_fmu import fmu_path

    out_dir = Path(out_dir)
    started = time.perf_counter()
    fmu_path()  # build once, before workers start
    if implementation == "c":
        from controllers.native import library

        library()  # the C twins too
    if not resume:  # a fresh reproduction recomputes everything, tuned gains included
        for stale in [*(out_dir / "tuning").glob("pi__*.json"), *(out_dir / "pipelines").glob("*.json")]:
            stale.unlink()
    outputs: dict[Pipeline, PipelineOutput] = {}
    todo = []
    if binding_file:
        selected = [Pipeline("bound", "", period, str(Path(binding_file).resolve()))
                    for period in (control_periods or (PAPER_PERIOD,))]
    else:
        selected = [p for p in PIPELINES if profile.pipelines is None or p.tag in profile.pipelines]
    for pipeline in selected:
        finished = _load_finished(out_dir, pipeline) if resume else None
        if finished is not None:
            outputs[pipeline] = finished
            log(f"  {pipeline.tag}: finished earlier, kept (--resume)")
        else:
            todo.append(pipeline)
    log(f"reproduction: {len(todo)} pipeline(s) on {workers} worker(s) -> {out_dir}/"
        + (" [quick profile: tiny sizes]" if profile.quick else ""))
    study_wanted = not binding_file and tolerance_study.SOURCE_PIPELINE in {p.tag for p in selected}
    study = study_counts = None
    if todo or study_wanted:
        try:
            study, study_counts = _run_on_cluster(todo, outputs, out_dir, profile, seed, implementation, workers,
                                                  resume, study_wanted)
        finally:
            remove_temporary_files(out_dir)  # what unfinished writes left, once the workers are gone
    ordered = [outputs[p] for p in selected]
    metrics = pd.concat([o.metrics for o in ordered], ignore_index=True)
    write_metrics(metrics, out_dir / "metrics" / "metrics_all")
    # PNG only: the report links PNGs, and results/ commits no SVG
    tolerance = study.summarise(vector=False) if study is not None else None
    elapsed = time.perf_counter() - started
    report = write_report(out_dir, ordered, metrics, profile=profile, seed=seed, tolerance=tolerance)
    write_timings(out_dir, ordered, metrics, elapsed, workers, tolerance=_study_timing(study, study_counts))
    log(f"reproduction finished in {elapsed:.1f} s; report: {report}")
    return report

