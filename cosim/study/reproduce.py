"""The paper reproduction: every experiment, end to end, into ``results/``.

One pipeline per plant (nominal averaged, nominal switched, mismatch-study switched) and control
rate (1 ms, one switching period). Each pipeline, all seeded:

1. tunes the PI on that plant at that rate (:mod:`cosim.design.pi_tuning`);
2. identifies the workbench's NNPC network by the recipe of :mod:`cosim.design.identification`
   (PI data, one-step then simulation-error training over the horizon) and trains the paper's
   3-7-2 network on the PI data;
3. runs the four paper scenarios with PI, NNPC, the paper's NNPC, the oracle MPC (the exact
   model of that plant) and the mismatched MPC (nominal model on the mismatch plant -- also
   without its disturbance estimate; on the nominal plant, the mismatch plant's parameters);
4. writes runs, metrics and figures as it goes.

Beside the pipelines (seed 0), *seed jobs* identify the NNPC again from the data of every other
study seed on the built-in plants (nominal and mismatch) at both rates and run it (with the
identification ablation on the nominal switched plant at one switching period), and the *drift
jobs* run the drift study on the mismatch-study plant, one per study seed (the report states a
comparison only where it holds for every seed: :mod:`cosim.study.claims`). Everything runs as dask tasks on a LocalCluster
(:mod:`cosim.design.cluster`, one single-threaded worker process each): the tuned PI gains first
(all pipelines in parallel), then every job, longest first. Once the nominal switched 1 ms
pipeline has finished, the tolerance study (:mod:`cosim.study.tolerance_study`) runs its
controllers on production units through the sweep engine, on the same cluster. Files are
written atomically, so an interrupted reproduction keeps what finished, and ``--resume`` skips
finished jobs.
"""

from __future__ import annotations

import json
import math
import sys
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from cosim.base.errors import PlantError, WorkbenchError
from cosim.base.files import atomic_write_json, atomic_write_text, json_text, remove_temporary_files
from cosim.batch import Batch, write_metrics
from cosim.batch import run_batch as batch_runs
from cosim.design import classical_design, frequency_response
from cosim.design.controller_factory import external_controllers, external_name, nominal_circuit
from cosim.design.data_collection import collect, save_samples
from cosim.design.design_cache import data_file, model_file, pi_file, seed_model_file
from cosim.design.experiments import (
    PAPER_NNPC_OPTIMIZER,
    adaptive_nnpc,
    collection_settings,
    default_optimizer,
    default_region,
    implemented,
    model_mpc,
    multiply_accumulates,
    network_region,
    nn_configs,
    nnpc,
    scenarios_for,
    small_network,
)
from cosim.design.identification import (
    ONE_STEP,
    Recipe,
    closed_loop_round,
    identify,
    network_design,
    write_identification_figure,
)
from cosim.design.pi_tuning import load_or_tune
from cosim.design.plants import plant_binding
from cosim.design.vocabulary import (
    CLOSED_LOOP_SAMPLES,
    DEFAULT_IMPLEMENTATION,
    MISMATCH,
    MPC_MISMATCHED,
    MPC_NOMINAL,
    MPC_ORACLE,
    MULTI_STEP_ITERATIONS,
    NNPC,
    NNPC_ADAPTIVE,
    NNPC_PAPER,
    NOMINAL,
    PAPER_PERIOD,
    PLANT_VARIANTS,
    SWITCHING_PERIOD,
    pipeline_tag,
    plant_tag,
    seed_variant,
    transient_within_sample,
)
from cosim.metrics import WALLCLOCK_METRICS
from cosim.scenarios import PAPER_SCENARIOS, load_scenario
from cosim.study import envelope, explicit, optimizer_ablation, ssp_agreement, tolerance_study
from cosim.study.envelope_identification import coverage
from cosim.study.report import write_report
from cosim.study.summaries import transient_and_steady_iae
from cosim.study.timings import write_timings
from cosim.study.vocabulary import (
    ABLATION_SCENARIOS,
    DRIFT_CAPACITANCE_FACTOR,
    DRIFT_RESISTANCE_FACTOR,
    DRIFT_SCENARIO,
    DRIFT_STUDY,
    MPC_NOMINAL_NO_ESTIMATE,
    MPC_ORACLE_AVERAGED,
    MPC_ORACLE_SYNC,
    NNPC_CLOSED_LOOP,
    NNPC_DRIFTED,
    NNPC_ONE_STEP,
    NNPC_SMALL_ONE_STEP,
    PAPER_SPEC,
    STUDY_PERIODS,
    STUDY_SEEDS,
    STUDY_STYLES,
    horizon_variant,
)


@dataclass(frozen=True)
class Profile:
    """Sizes of the reproduction; ``quick`` is the CI smoke profile (tiny, meaningless numbers)."""

    samples: int = 10_000
    scenarios: tuple[str, ...] = PAPER_SCENARIOS
    ablations: bool = True  # horizon N = 3 at 1 ms; at 13.33 us the oracle with eq. 3, a synchronous sample,
    # and the identification ablation (each stage of the recipe, and the 7-hidden network)
    seeds: tuple[int, ...] = STUDY_SEEDS  # the NNPC identified from each seed's data on the nominal plants
    drift: bool = True  # the drift study (mismatch-study plant at one switching period)
    closed_loop_samples: int = CLOSED_LOOP_SAMPLES  # per NNPC-in-the-loop identification round
    multi_step_iterations: int = MULTI_STEP_ITERATIONS  # per simulation-error training stage, at most
    drift_duration: float | None = None  # [s] shorten the drift scenario (quick profile)
    quick: bool = False
    pipelines: tuple[str, ...] | None = None  # tags to run (default: all)
    tolerance_samples: int | None = None  # units of the tolerance study (default: its sweep file's)


FULL = Profile()
QUICK = Profile(samples=400, scenarios=("startup", "load_change"), quick=True, seeds=(0, 1), closed_loop_samples=150,
                multi_step_iterations=50, drift_duration=0.009, tolerance_samples=3,
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

    @property
    def seed_study(self) -> bool:
        """The built-in plants are identified from every study seed's data (an external plant: seed 0 only)."""
        return self.variant in ("nominal", "mismatch")

    @property
    def study_seeds(self) -> tuple[int, ...]:
        """The identification seeds of this pipeline's networks: the full profile's on the built-in plants, seed 0
        only on an external plant (what the every-seed evaluations iterate over)."""
        return FULL.seeds if self.seed_study else (0,)

    @property
    def identification_ablation(self) -> bool:
        return self.variant == "nominal" and self.mode == "switched" and not transient_within_sample(self.control_period)


PIPELINES = tuple(Pipeline(variant, mode, period)
                  for period in STUDY_PERIODS
                  for variant, mode in (("nominal", "averaged"), ("nominal", "switched"), ("mismatch", "switched")))
DRIFT_PIPELINE = Pipeline("mismatch", "switched", SWITCHING_PERIOD)
DRIFT_KEY = DRIFT_STUDY  # the drift study's job key and its rows' "pipeline" in the metrics tables
#: the pipelines whose seed jobs save their NNPC (design_cache.seed_model_file) for another job: the envelope
#: map's plant at one switching period (the map runs every seed's NNPC), the drift study's (reused there)
SEED_MODEL_PIPELINES = (pipeline_tag(envelope.MAP_PLANT, SWITCHING_PERIOD), DRIFT_PIPELINE.tag)


@dataclass(frozen=True)
class Job:
    """One unit of work for a worker: a pipeline (seed 0), a seed job, or the drift study."""

    kind: str  # "pipeline", "seed" or "drift"
    pipeline: Pipeline
    seed: int = 0
    after: str | None = None  # key of a job that must finish first (the drift study reuses its model)
    controllers: tuple[str, ...] = ()  # controller FMUs / binding files run next to the built-in ones (pipelines)

    first_drift: bool = True  # a drift job: the one of the reproduction's seed (the others: ``drift__seed<s>``)

    @property
    def key(self) -> str:
        """File stem of the job's summary and metrics: the pipeline tag, ``<tag>__seed<s>``, ``drift``
        (the reproduction's seed) or ``drift__seed<s>``."""
        return {"pipeline": self.pipeline.tag, "seed": f"{self.pipeline.tag}__seed{self.seed}",
                "drift": DRIFT_KEY if self.first_drift else f"{DRIFT_KEY}__seed{self.seed}"}[self.kind]

    def cost(self) -> float:
        """A rough relative cost, so the longest jobs start first and the workers finish together."""
        fast = not transient_within_sample(self.pipeline.control_period)
        weight = {"pipeline": 4.0, "seed": 1.0, "drift": 2.5 if self.after is None else 1.5}[self.kind]
        if self.kind == "seed" and self.pipeline.identification_ablation:
            weight = 2.2
        return weight * (8.0 if fast else 1.0)


@dataclass
class PipelineOutput:
    pipeline: Pipeline
    metrics: pd.DataFrame
    pi: dict
    models: dict[str, dict]  # name -> metadata (held-out RMSE, training)
    timings: dict[str, float] = field(default_factory=dict)
    key: str = ""  # the job that wrote it (default: the pipeline tag)
    study: dict = field(default_factory=dict)  # the drift study's own figures (prediction errors, adaptation, seed)

    def __post_init__(self):
        self.key = self.key or self.pipeline.tag

    def to_json(self) -> str:
        """The summary written to ``pipelines/<key>.json`` (no wall-clock figures: those are
        ``pipelines/<key>.timings.json``, not committed, and ``timings.md``)."""
        payload = {"pipeline": asdict(self.pipeline), "pi": self.pi, "models": self.models}
        if self.study:
            payload["study"] = self.study
        return json_text(payload)


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _tuned(pipeline: Pipeline, out_dir: Path, profile: Profile):
    return load_or_tune(pi_file(out_dir, pipeline.plant_tag, pipeline.control_period), pipeline.binding(),
                        pipeline.control_period, quick=profile.quick)


def _tune_job(job) -> tuple[str, float]:
    pipeline, out_dir, profile = job
    start = time.perf_counter()
    pi = _tuned(pipeline, out_dir, profile)
    log(f"  {pipeline.tag}: PI Kp = {pi.kp:.4g} 1/V, Ki = {pi.ki:.4g} 1/(V s) ({pi.evaluations} simulations)")
    return pipeline.tag, time.perf_counter() - start


def _recipe(profile: Profile) -> Recipe:
    return Recipe(samples=profile.samples, closed_loop_samples=profile.closed_loop_samples,
                  multi_step_iterations=profile.multi_step_iterations)


def _model_summary(model, config) -> dict:
    """A model's entry in ``pipelines/<key>.json``: its metadata, the design named by its key only, without
    the learning curves (they are in the model file and its identification figure)."""
    meta = {k: v for k, v in model.metadata.items() if k != "design"}
    if "training" in meta:
        training = {k: v for k, v in meta["training"].items() if k != "history"}
        if isinstance(training.get("multi_step"), dict):
            training["multi_step"] = {k: v for k, v in training["multi_step"].items() if k != "history"}
        meta["training"] = training
    return {"architecture": config.label, "multiply_accumulates": multiply_accumulates(config), **meta,
            "design_key": (model.metadata.get("design") or {}).get("key")}


def _network_design(name: str, binding, period: float, seed: int, profile: Profile, pi) -> dict:
    """The design (key and inputs) of the pipeline's network ``name``, stored in its model file."""
    config = nn_configs(period)[name]
    if name == "nnpc":
        design = network_design(name, binding, period, config, seed, profile.samples, recipe=_recipe(profile),
                                pi_key=pi.design_key)
    else:
        design = network_design(name, binding, period, config, seed, profile.samples, training=_paper_training(seed),
                                pi_key=pi.design_key)
    return design.describe()


def _runner(implementation: str):
    def run_batch(batch, controllers, out_dir, **options):  # every run with the chosen implementation
        return batch_runs(batch, [implemented(c, implementation) for c in controllers], out_dir, **options)
    return run_batch


def _scenarios(pipeline: Pipeline, binding, profile: Profile) -> list:
    scenarios = []
    for scenario in scenarios_for(pipeline.control_period, profile.scenarios, spec=binding.converter):
        missing = scenario.required_roles() - set(binding.roles)
        if missing:
            log(f"  {pipeline.tag}: skipping {scenario.name}: {binding.origin} binds no {', '.join(sorted(missing))}")
        else:
            scenarios.append(scenario)
    return scenarios


def run_pipeline(pipeline: Pipeline, out_dir: Path, profile: Profile, seed: int,
                 implementation: str = DEFAULT_IMPLEMENTATION,
                 controller_files: tuple[str, ...] = ()) -> PipelineOutput:
    import torch

    from controllers.nn_model import save_model, train

    torch.set_num_threads(1)  # two workers share two cores
    timings: dict[str, float] = {}
    tag, period = pipeline.tag, pipeline.control_period
    binding = pipeline.binding()
    run_batch = _runner(implementation)

    start = time.perf_counter()
    pi = _tuned(pipeline, out_dir, profile)
    timings["pi_tuning_s"] = time.perf_counter() - start

    start = time.perf_counter()
    configs = nn_configs(period)
    identified = identify(binding, pi.controller(), period, configs["nnpc"], seed, _recipe(profile),
                          metadata={"data_file": f"data/{tag}.parquet",
                                    "design": _network_design("nnpc", binding, period, seed, profile, pi)})
    timings["identification_nnpc_s"] = time.perf_counter() - start
    data = identified.data
    data.attrs["metadata"]["seed"] = seed
    save_samples(data, data_file(out_dir, pipeline.plant_tag, period))
    models = {"nnpc": identified.model}
    start = time.perf_counter()
    datasets = {"nnpc": data, "nnpc-paper": data}
    paper_file = data_file(out_dir, pipeline.plant_tag, period)
    if network_region("nnpc-paper", period) != default_region(period):  # the paper's network keeps the paper's data
        region = network_region("nnpc-paper", period)
        datasets["nnpc-paper"] = collect(binding, pi.controller(),
                                         collection_settings(period, profile.samples, seed, region=region,
                                                             spec=binding.converter))
        datasets["nnpc-paper"].attrs["metadata"]["seed"] = seed
        paper_file = data_file(out_dir, pipeline.plant_tag, period, region)
        save_samples(datasets["nnpc-paper"], paper_file)
    models["nnpc-paper"] = train(datasets["nnpc-paper"], configs["nnpc-paper"], _paper_training(seed),
                                 metadata={"control_period_s": period, "plant": binding.label,
                                           "data_file": f"data/{paper_file.name}", "seed": seed,
                                           "design": _network_design("nnpc-paper", binding, period, seed, profile,
                                                                     pi)})
    timings["training_nnpc-paper_s"] = time.perf_counter() - start
    model_meta = {}
    for name, model in models.items():
        save_model(model, model_file(out_dir, pipeline.plant_tag, period, name))
        write_identification_figure(model, datasets[name], model_file(out_dir, pipeline.plant_tag, period, name))
        model_meta[name] = _model_summary(model, configs[name])
        model_meta[name]["data_coverage"] = coverage(datasets[name])  # what the data visit of the envelope
        rmse = model.metadata["held_out_rmse"]
        log(f"  {tag}: {name} {configs[name].label}: held-out RMSE one step {rmse['one_step_rmse_voltage_V'] * 1e3:.1f} mV, "
            f"10 steps {rmse.get('10_step_rmse_voltage_V', math.nan) * 1e3:.0f} mV")

    spec = binding.converter
    controllers = [pi.controller(), nnpc(models["nnpc"], period, NNPC, spec=spec),
                   nnpc(models["nnpc-paper"], period, NNPC_PAPER, optimizer=PAPER_NNPC_OPTIMIZER, spec=spec)]
    true_parameters = None
    if pipeline.binding_file:  # an external plant: the nominal circuit of its converter spec
        design_circuit = nominal_circuit(binding, "mpc-nominal")
        controllers.append(model_mpc(design_circuit, period, MPC_NOMINAL, binding=binding))
    else:
        true_parameters = PLANT_VARIANTS[pipeline.variant]
        wrong_parameters = NOMINAL if pipeline.variant == "mismatch" else MISMATCH
        wrong_name = MPC_NOMINAL if pipeline.variant == "mismatch" else MPC_MISMATCHED
        controllers += [model_mpc(true_parameters, period, MPC_ORACLE, binding=binding),
                        model_mpc(wrong_parameters, period, wrong_name, binding=binding)]
        if pipeline.variant == "mismatch":  # what the disturbance estimate buys: the paper's kind of MPC
            controllers.append(model_mpc(NOMINAL, period, MPC_NOMINAL_NO_ESTIMATE, binding=binding, offset_free=False))
        design_circuit = true_parameters
    controllers += explicit.in_pipeline(pipeline, binding, models["nnpc"], pi.controller(), out_dir, profile, seed,
                                        implementation, timings, log)  # the explicit NNPC at 1/fsw, and its map
    # the classical baselines at 1/fsw: current-mode and Type-III (on the built-in plants for their true circuit, on a
    # bound plant for its spec's nominal one), the envelope PI on the paper's nominal switched plant
    controllers += classical_design.in_pipeline(pipeline, binding, design_circuit, pi.controller(), out_dir,
                                                profile.quick, timings, log)
    frequency_response.in_pipeline(pipeline, binding, [pi.controller(), *controllers], out_dir, profile.quick,
                                   timings, log)  # loop gains and output impedances by injection
    if controller_files:  # controller FMUs the user added (reproduce --controller), checked before any work
        from cosim.fmi.controller import FmuController, controller_binding

        controllers += [FmuController(controller_binding(path), name=external_name(path)) for path in controller_files]
    scenarios = _scenarios(pipeline, binding, profile)
    batch = Batch(binding, scenarios)

    start = time.perf_counter()
    output = run_batch(batch, controllers, out_dir, seed=seed, styles=STUDY_STYLES,
                       extra_metadata={"pipeline": asdict(pipeline)})
    metrics = [output.metrics]
    if profile.ablations and true_parameters is not None:  # old vs new optimizer on the same models
        start_ablation = time.perf_counter()
        makers = {NNPC: lambda optimizer: nnpc(models["nnpc"], period, NNPC, optimizer=optimizer),
                  MPC_ORACLE: lambda optimizer: model_mpc(true_parameters, period, MPC_ORACLE, binding=binding,
                                                          optimizer=optimizer)}
        model_meta["optimizer_ablation"] = [optimizer_ablation.summary(row) for make in makers.values()
                                            for row in optimizer_ablation.compare(binding, make, scenarios)]
        timings["optimizer_ablation_s"] = time.perf_counter() - start_ablation
    if profile.ablations and pipeline.variant == "nominal" and pipeline.mode == "switched":
        if transient_within_sample(period):  # does a longer horizon change anything at 1 ms?
            metrics.append(run_batch(batch, [nnpc(models["nnpc"], period, horizon_variant(NNPC, 3), horizon=3)],
                                     out_dir, seed=seed, figures=False).metrics)
        else:  # the oracle blind to the sensor (eq. 3), and a synchronous point sample instead of the mean
            metrics.append(run_batch(batch, [model_mpc(true_parameters, period, MPC_ORACLE_AVERAGED)], out_dir,
                                     seed=seed, figures=False).metrics)
            synchronous = Batch(plant_binding(pipeline.variant, pipeline.mode, sensor="synchronous"), scenarios)
            metrics.append(run_batch(synchronous, [model_mpc(true_parameters, period, MPC_ORACLE_SYNC,
                                                             binding=synchronous.binding)],
                                     out_dir, seed=seed, figures=False).metrics)
    if profile.ablations and pipeline.identification_ablation:
        start_ablation = time.perf_counter()
        ablation, meta = _identification_ablation(identified, binding, period, seed, batch, out_dir, run_batch,
                                                   profile)
        timings["identification_ablation_s"] = time.perf_counter() - start_ablation
        metrics.append(ablation)
        model_meta.update(meta)
    metrics = _job_table(metrics, pipeline, tag)
    # the runs only: the stages of a job are disjoint, so that timings.csv's worker time adds up
    timings["runs_s"] = (time.perf_counter() - start - timings.get("optimizer_ablation_s", 0.0)
                         - timings.get("identification_ablation_s", 0.0))
    log(f"  {tag}: {len(metrics)} runs ({timings['runs_s']:.1f} s)")
    return _finish(PipelineOutput(pipeline=pipeline, metrics=metrics, pi=json.loads(pi.to_json()), models=model_meta,
                                  timings=timings), out_dir)


def _paper_training(seed: int):
    from controllers.nn_config import TrainingSettings

    return TrainingSettings(seed=seed)  # the paper's network keeps the paper's (one-step) training


def _identification_ablation(identified, binding, period, seed, batch, out_dir, run_batch,
                             profile: Profile) -> tuple[pd.DataFrame, dict]:
    """The earlier 7-hidden network with one-step training (the workbench's NNPC before this study),
    the NNPC's network after its one-step stage, and the NNPC refined on a round of data with itself
    in the loop, all from the same data; named with the seed unless it is seed 0."""
    from controllers.nn_config import TrainingSettings
    from controllers.nn_model import train

    def named(name):
        return name if seed == 0 else seed_variant(name, seed)

    small = small_network(period)
    earlier = train(identified.data, small, TrainingSettings(seed=seed),
                    metadata={"control_period_s": period, "plant": binding.label, "seed": seed})
    config = nn_configs(period)["nnpc"]
    looped = closed_loop_round(identified, binding, period, config, seed, _recipe(profile)).model
    variants = [(NNPC_SMALL_ONE_STEP, earlier, small), (NNPC_ONE_STEP, identified.stages[ONE_STEP], None),
                (NNPC_CLOSED_LOOP, looped, None)]
    # closed-loop runs for the earlier NNPC and the closed-loop round; the one-step network by its
    # RMSE only (what growing the network buys in prediction; a run each would cost the time target)
    controllers = [nnpc(model, period, named(name)) for name, model, _ in variants if name in ABLATION_RUNS]
    scenarios = [s for s in batch.scenarios if s.name in ABLATION_SCENARIOS] or list(batch.scenarios)
    metrics = run_batch(Batch(batch.binding, scenarios), controllers, out_dir, seed=seed, figures=False).metrics
    meta = {named(name).lower(): _model_summary(model, cfg or config) for name, model, cfg in variants}
    return metrics, meta


#: the identification-ablation variants run in closed loop (the others are compared by their RMSE)
ABLATION_RUNS = (NNPC_SMALL_ONE_STEP, NNPC_CLOSED_LOOP)


def run_seed(pipeline: Pipeline, out_dir: Path, profile: Profile, seed: int,
             implementation: str = DEFAULT_IMPLEMENTATION) -> PipelineOutput:
    """The NNPC identified from seed ``seed``'s data (same PI, same recipe) and run on the paper's scenarios."""
    import torch

    torch.set_num_threads(1)
    period, binding = pipeline.control_period, pipeline.binding()
    run_batch = _runner(implementation)
    timings = {}
    pi = _tuned(pipeline, out_dir, profile)
    start = time.perf_counter()
    config = nn_configs(period)["nnpc"]
    identified = identify(binding, pi.controller(), period, config, seed, _recipe(profile),
                          metadata={"design": _network_design("nnpc", binding, period, seed, profile, pi)})
    timings["identification_nnpc_s"] = time.perf_counter() - start
    name = seed_variant(NNPC, seed)
    start = time.perf_counter()
    batch = Batch(binding, _scenarios(pipeline, binding, profile))
    metrics = [run_batch(batch, [nnpc(identified.model, period, name)], out_dir, seed=seed, figures=False).metrics]
    meta = {name.lower(): _model_summary(identified.model, config)}
    if pipeline.tag in SEED_MODEL_PIPELINES or pipeline.binding_file:  # another job runs this NNPC too: the
        # envelope map (the paper's; a converter study's), the drift study
        from controllers.nn_model import save_model

        save_model(identified.model, seed_model_file(out_dir, pipeline.plant_tag, period, seed))
    if profile.ablations and pipeline.identification_ablation:
        start_ablation = time.perf_counter()
        ablation, extra = _identification_ablation(identified, binding, period, seed, batch, out_dir, run_batch,
                                                   profile)
        timings["identification_ablation_s"] = time.perf_counter() - start_ablation
        metrics.append(ablation)
        meta.update(extra)
    metrics = _job_table(metrics, pipeline, pipeline.tag)
    timings["runs_s"] = time.perf_counter() - start - timings.get("identification_ablation_s", 0.0)
    rmse = identified.model.metadata["held_out_rmse"]
    log(f"  {pipeline.tag}: {name}: 10-step RMSE {rmse.get('10_step_rmse_voltage_V', math.nan) * 1e3:.0f} mV, "
        f"{len(metrics)} runs")
    return _finish(PipelineOutput(pipeline=pipeline, metrics=metrics, pi={}, models=meta, timings=timings,
                                  key=f"{pipeline.tag}__seed{seed}"), out_dir)


def drift_scenario(profile: Profile):
    """The shipped drift scenario (shortened for the quick profile)."""
    scenario = load_scenario(DRIFT_SCENARIO, PAPER_SPEC)
    if profile.drift_duration is not None:
        end = profile.drift_duration
        scenario = replace(scenario, duration=end, events=tuple(e for e in scenario.events if e.time < end),
                           analysis_start=end / 2)
    return scenario


def drifted_binding(binding):
    """The mismatch-study plant after the drift: C -30 %, DCR doubled (bound from the start)."""
    p = binding.parameters
    parameters = {**p, "capacitance": p["capacitance"] * DRIFT_CAPACITANCE_FACTOR,
                  "inductor_resistance": p["inductor_resistance"] * DRIFT_RESISTANCE_FACTOR}
    return replace(binding, parameters=parameters, label=binding.label.replace(")", ", drifted)"),
                   tag_override=f"{binding.tag}-drifted")


def drift_names(seed: int, first: bool) -> tuple[str, str, str]:
    """The drift study's three controllers for one seed: not adapted, adapted, identified on the drifted
    plant (``NNPC``, ... for the reproduction's seed; ``NNPC (seed 2)``, ... for the others)."""
    names = (NNPC, NNPC_ADAPTIVE, NNPC_DRIFTED)
    return names if first else tuple(seed_variant(name, seed) for name in names)


def run_drift(out_dir: Path, profile: Profile, seed: int, implementation: str = DEFAULT_IMPLEMENTATION,
              reuse: bool = False, first: bool = True) -> PipelineOutput:
    """The drift study for one seed: the NNPC identified on the mismatch-study plant from that seed's
    data, without and with online adaptation, and one identified offline on the drifted plant (same
    seed), on the drift scenario.

    ``reuse``: the mismatch-study pipeline at this rate (``first``), or its seed job for ``seed``, has run in this
    reproduction, so its NNPC (the same recipe and seed) is read from its model file instead of being identified
    again (identified here after all if the file's design key is not the one wanted).
    ``first``: the reproduction's own seed (plain controller names, job key ``drift``)."""
    import torch

    from controllers.load_estimate import conductance_series
    from controllers.nn_model import build_dataset

    torch.set_num_threads(1)
    pipeline = DRIFT_PIPELINE
    period, binding = pipeline.control_period, pipeline.binding()
    run_batch = _runner(implementation)
    timings = {}
    pi = _tuned(pipeline, out_dir, profile)
    config = nn_configs(period)["nnpc"]
    start = time.perf_counter()
    design = _network_design("nnpc", binding, period, seed, profile, pi)
    before_model = None
    reused = None
    if reuse:  # the mismatch pipeline's own network (the reproduction's seed) or its seed job's
        reused = (model_file(out_dir, pipeline.plant_tag, period, "nnpc") if first
                  else seed_model_file(out_dir, pipeline.plant_tag, period, seed))
    if reused is not None and reused.is_file():
        from controllers.nn_model import load_model

        before_model = load_model(reused, expect_period=period, expect_config=config)
        if (before_model.metadata.get("design") or {}).get("key") != design["key"]:
            before_model = None  # identified for another plant or recipe: not the drift study's NNPC
    if before_model is None:
        before_model = identify(binding, pi.controller(), period, config, seed, _recipe(profile),
                                metadata={"design": design}).model
    after_binding = drifted_binding(binding)
    after = identify(after_binding, pi.controller(), period, config, seed, _recipe(profile))
    timings["identification_nnpc_s"] = time.perf_counter() - start
    scenario = drift_scenario(profile)
    final = load_scenario(DRIFT_SCENARIO, PAPER_SPEC).parameter_events[-1].parameters
    for name, value in final.items():  # the scenario ends where the offline identification's plant is
        if not math.isclose(value, after_binding.parameters[name], rel_tol=1e-6):
            raise ValueError(f"{DRIFT_SCENARIO}: {name} ends at {value}, the drifted plant has "
                             f"{after_binding.parameters[name]}")
    frozen_name, adaptive_name, drifted_name = drift_names(seed, first)
    controllers = [nnpc(before_model, period, frozen_name),
                   implemented(adaptive_nnpc(before_model, period, adaptive_name), implementation),
                   nnpc(after.model, period, drifted_name)]
    start = time.perf_counter()
    output = run_batch(Batch(binding, [scenario]), controllers, out_dir, seed=seed, styles=STUDY_STYLES,
                       extra_metadata={"pipeline": asdict(pipeline), "study": "drift"}, figures=first)
    timings["runs_s"] = time.perf_counter() - start
    adaptive = controllers[1]
    # one-step prediction error after the drift, on the non-adapting NNPC's closed-loop data
    frame = output.results[0].frame
    samples = frame[frame["control_sample"] & (frame["time"] >= scenario.metrics_start)].reset_index(drop=True)
    samples["load_conductance"] = conductance_series(samples["measured_output_voltage"].to_numpy(),
                                                     samples["measured_load_current"].to_numpy(),
                                                     samples["measured_inductor_current"].to_numpy(), initial=1 / 6)
    x, y = build_dataset(samples, config)
    adapted = adaptive.model.__class__(config, adaptive.model.network, adaptive.model.input_mean,
                                       adaptive.model.input_std, adaptive.model.output_mean, adaptive.model.output_std)
    theta = adaptive.output_weights
    adapted._weights[-1][...], adapted._biases[-1][...] = theta[:-1], theta[-1]
    prediction = {}
    for name, model in ((frozen_name, before_model), (adaptive_name, adapted), (drifted_name, after.model)):
        error = model.predict(x) - y
        prediction[name] = {"one_step_rmse_current_A": float(np.sqrt(np.mean(error[:, 0] ** 2))),
                            "one_step_rmse_voltage_V": float(np.sqrt(np.mean(error[:, 1] ** 2)))}
    metrics = _job_table([output.metrics], pipeline, DRIFT_KEY)
    windows = {r.info.controller: transient_and_steady_iae(r.frame, scenario.metrics_start) for r in output.results}
    study = {"seed": seed, "controllers": [frozen_name, adaptive_name, drifted_name], "iae_windows_Vs": windows,
             "scenario": scenario.name, "analysis_start_s": scenario.metrics_start,
             "drifted_parameters": {k: after_binding.parameters[k] for k in final},
             "prediction_after_drift": prediction, "adaptation": dict(adaptive.counters),
             "adaptation_settings": asdict(adaptive.settings)}
    models = {frozen_name.lower(): _model_summary(before_model, config),
              drifted_name.lower(): _model_summary(after.model, config)}
    key = DRIFT_KEY if first else f"{DRIFT_KEY}__seed{seed}"
    log(f"  {key}: {len(metrics)} runs ({timings['runs_s']:.1f} s); adaptation {adaptive.counters}")
    return _finish(PipelineOutput(pipeline=pipeline, metrics=metrics, pi={}, models=models, timings=timings,
                                  key=key, study=study), out_dir)


def _job_table(parts: list[pd.DataFrame], pipeline: Pipeline, key: str) -> pd.DataFrame:
    """A job's metrics rows in one table, labelled with its key (column ``pipeline``) and plant tag."""
    metrics = pd.concat(parts, ignore_index=True)
    metrics["plant_tag"] = pipeline.plant_tag
    metrics.insert(0, "pipeline", key)
    return metrics


def _finish(output: PipelineOutput, out_dir: Path) -> PipelineOutput:
    write_metrics(output.metrics, out_dir / "metrics" / f"metrics__{output.key}")
    atomic_write_json(out_dir / "pipelines" / f"{output.key}.timings.json", output.timings)
    atomic_write_text(out_dir / "pipelines" / f"{output.key}.json", output.to_json() + "\n")
    return output


def run_job(job: Job, out_dir: Path, profile: Profile, implementation: str = DEFAULT_IMPLEMENTATION) -> PipelineOutput:
    if job.kind == "pipeline":
        return run_pipeline(job.pipeline, out_dir, profile, job.seed, implementation, job.controllers)
    if job.kind == "seed":
        return run_seed(job.pipeline, out_dir, profile, job.seed, implementation)
    return run_drift(out_dir, profile, job.seed, implementation, reuse=job.after is not None, first=job.first_drift)


@dataclass
class _Failed:
    """A task's fault, returned (not raised) by the task: the workbench reports it in one line,
    where a raised exception would have dask print the task's traceback first."""

    error: WorkbenchError


def _timed(function, *args) -> tuple[object, float]:
    """``function(*args)`` and its wall time [s] (a task whose worker time timings.csv records)."""
    start = time.perf_counter()
    result = function(*args)
    return result, time.perf_counter() - start


def _guarded(function, *args):
    try:
        return function(*args)
    except WorkbenchError as error:
        return _Failed(error)


def _task_result(future, what: str, out_dir: Path):
    """A finished task's result; its fault, or its worker's death, raised here (``what``: the task, for the message)."""
    from distributed.scheduler import KilledWorker

    if future.status != "finished":
        error = future.exception()
        if isinstance(error, KilledWorker):
            raise PlantError(f"a reproduction worker process died twice running {what} (a plant FMU crashed it?); "
                             f"jobs that finished are in {out_dir}/pipelines -- rerun with --resume to continue") from None
        raise error
    result = future.result()
    if isinstance(result, _Failed):
        raise result.error
    return result


def _load_finished(out_dir: Path, job: Job) -> PipelineOutput | None:
    """A job whose summary and metrics were written by an earlier (interrupted) run."""
    summary = out_dir / "pipelines" / f"{job.key}.json"
    metrics = out_dir / "metrics" / f"metrics__{job.key}.csv"
    if not (summary.is_file() and metrics.is_file()):
        return None
    data = json.loads(summary.read_text(encoding="utf-8"))
    table = pd.read_csv(metrics)
    timing = metrics.with_name(f"{metrics.stem}.timing.csv")
    if timing.is_file():  # the wall-clock metrics, in the same row order
        for column in WALLCLOCK_METRICS:
            table[column] = pd.read_csv(timing)[column].to_numpy()
    timings_file = summary.with_name(f"{job.key}.timings.json")
    timings = json.loads(timings_file.read_text(encoding="utf-8")) if timings_file.is_file() else {}
    return PipelineOutput(pipeline=job.pipeline, metrics=table, pi=data["pi"], models=data["models"], timings=timings,
                          key=job.key, study=data.get("study", {}))


def prepare_jobs(jobs: list[Job], out_dir: Path, resume: bool,
                 implementation: str) -> tuple[dict[Job, PipelineOutput], list[Job]]:
    """Before the workers start: the plant FMU (and the C twins) built once; without ``resume`` an earlier run's
    tuned gains and job summaries removed (a fresh run recomputes everything), with it the jobs that run finished
    loaded and kept. Returns (the kept jobs' outputs, the jobs to run)."""
    from plant_fmu import fmu_path

    fmu_path()
    if implementation == "c":
        from controllers.native import library

        library()
    if not resume:
        for stale in [*(out_dir / "tuning").glob("pi__*.json"), *(out_dir / "pipelines").glob("*.json")]:
            stale.unlink()
    outputs: dict[Job, PipelineOutput] = {}
    todo = []
    for job in jobs:
        finished = _load_finished(out_dir, job) if resume else None
        if finished is not None:
            outputs[job] = finished
            log(f"  {job.key}: finished earlier, kept (--resume)")
        else:
            todo.append(job)
    return outputs, todo


def plan_jobs(selected: list[Pipeline], profile: Profile, seed: int, binding_file: str | None,
              controllers: dict[float, tuple[str, ...]] | None = None) -> list[Job]:
    """Every job of a reproduction: the pipelines (with the controller FMUs ``controllers`` maps to
    their period), the seed jobs of the built-in plants, the drift study for every study seed."""
    jobs = [Job("pipeline", p, seed, controllers=(controllers or {}).get(p.control_period, ())) for p in selected]
    if not binding_file:
        jobs += [Job("seed", p, seed + offset) for p in selected if p.seed_study for offset in profile.seeds[1:]]
        if profile.drift:  # each seed reuses the NNPC of the mismatch pipeline or its seed job (same recipe and seed)
            planned = DRIFT_PIPELINE in selected
            jobs.append(Job("drift", DRIFT_PIPELINE, seed, DRIFT_PIPELINE.tag if planned else None))
            jobs += [Job("drift", DRIFT_PIPELINE, seed + offset,
                         Job("seed", DRIFT_PIPELINE, seed + offset).key if planned else None, first_drift=False)
                     for offset in profile.seeds[1:]]
    return jobs


#: dask priorities (higher first): the tolerance study's source pipeline, then the pipelines longest
#: first (so the workers finish together), the SSP agreement's parts (a few seconds to tens of seconds each) once
#: every job has started, the studies' tasks (many, short: they fill the end) whenever no other task waits
SOURCE_PRIORITY, SSP_PRIORITY, STUDY_PRIORITY = 100, 0, -10


def _default_optimizer_plugin(optimizer: str):
    """A dask worker plugin that makes ``optimizer`` the default on every worker of the reproduction's cluster
    (set up on each, restarted ones too), as :func:`default_optimizer` does in this process."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class DefaultOptimizer(WorkerPlugin):
        name = "buck-cosim-default-optimizer"

        def setup(self, worker) -> None:
            from cosim.design import experiments

            experiments.DEFAULT_OPTIMIZER = optimizer

    return DefaultOptimizer()


def run_on_cluster(todo: list[Job], tunings: list[Pipeline], outputs: dict, out_dir: Path, profile: Profile,
                    implementation: str, workers: int, resume: bool, study_wanted: bool, map_wanted: bool = False,
                    optimizer: str | None = None, ssp_parts: dict | None = None):
    """The reproduction as dask tasks on a LocalCluster: the PI tunings first (every job of a plant
    and rate needs its gains), then the jobs (longest first, so the workers finish together; a job
    that depends on another is submitted when that one finishes), and the tolerance study's tasks as
    soon as its source pipeline is done (the envelope map's likewise). ``ssp_parts``: a dict to fill with the SSP
    agreement study's parts (:func:`cosim.study.ssp_agreement.run_loops` by (mode, controller), each with its
    worker time [s]), run as tasks once its source pipelines are done, after every job has started (None: not
    wanted). Returns the tolerance study and its execution counts (or None, None), and the envelope map and its
    execution (or None, None).
    On a fault or an interrupt the cluster is closed at once (its worker processes end with it)."""
    from distributed import as_completed

    from cosim.design.cluster import dask_client

    with dask_client(workers=max(1, workers), worker_saturation=1.0) as client:
        if optimizer is not None:
            client.register_plugin(_default_optimizer_plugin(optimizer))
        tuned = {client.submit(_guarded, _tune_job, (p, out_dir, profile), pure=False,
                               key=f"buck-cosim-tuning-{p.tag}"): p for p in tunings}
        for future in as_completed(list(tuned), loop=client.loop):
            _task_result(future, f"the PI tuning of {tuned[future].tag}", out_dir)

        keys = {job.key for job in todo}
        waiting = [job for job in todo if job.after is not None and job.after in keys]
        # submitted in the order they should start (idle workers take the first ones at once; the
        # rest wait in the scheduler's queue by priority): the study's source pipeline, then longest first
        sources = (tolerance_study.SOURCE_PIPELINE, pipeline_tag(envelope.MAP_PLANT, SWITCHING_PERIOD),
                   *(ssp_agreement.SOURCE_PIPELINES if ssp_parts is not None else ()))
        order = sorted((job for job in todo if job not in waiting),
                       key=lambda job: (job.key not in sources, -job.cost()))
        futures: dict[str, Job] = {}
        ssp_futures: dict[str, tuple[str, str]] = {}
        queue = as_completed(loop=client.loop)

        def submit(job: Job, priority: int) -> None:
            future = client.submit(_guarded, run_job, job, out_dir, profile, implementation, pure=False,
                                   key=f"buck-cosim-job-{job.key}", priority=priority)
            futures[future.key] = job
            queue.add(future)

        for rank, job in enumerate(order):
            submit(job, SOURCE_PRIORITY if job.key == tolerance_study.SOURCE_PIPELINE else len(order) - rank)
        study, execution = None, None
        envelope_map, envelope_execution = None, None

        def finished_pipelines():
            return (job.key for job in outputs if job.kind == "pipeline")

        map_seeds = [job.seed for job in todo + list(outputs) if job.kind == "seed"
                     and job.pipeline.tag == pipeline_tag(envelope.MAP_PLANT, SWITCHING_PERIOD)]

        def start_study():
            nonlocal study, execution
            study = tolerance_study.start(out_dir, resume, profile.tolerance_samples)
            execution = study.execution()
            log(f"  {study.describe_start('the same cluster')}")
            for future in execution.submit(client, priority=STUDY_PRIORITY):
                queue.add(future)

        def start_map():  # the envelope map, once the nominal switched pipeline at 1/fsw has its controllers
            nonlocal envelope_map, envelope_execution
            envelope_map = envelope.start(out_dir, quick=profile.quick, resume=resume, seeds=sorted(map_seeds))
            envelope_execution = envelope_map.execution()
            log(f"  {envelope_map.describe_start('the same cluster')}")
            for future in envelope_execution.submit(client, priority=STUDY_PRIORITY):
                queue.add(future)

        ssp_started = False

        def start_ssp():  # the SSP agreement's parts, once its source pipelines have written their designs
            nonlocal ssp_started
            ssp_started = True
            for mode, controller in ssp_agreement.PARTS:
                future = client.submit(_guarded, _timed, ssp_agreement.run_loops, out_dir, mode, controller,
                                       profile.quick, pure=False, key=f"buck-cosim-ssp-{mode}-{controller}",
                                       priority=SSP_PRIORITY)
                ssp_futures[future.key] = (mode, controller)
                queue.add(future)
            log(f"  SSP agreement: {len(ssp_agreement.PARTS)} part(s) on the same cluster")

        def maybe_start():
            if (ssp_parts is not None and not ssp_started
                    and set(ssp_agreement.SOURCE_PIPELINES) <= set(finished_pipelines())):
                start_ssp()
            if study_wanted and study is None and tolerance_study.ready(finished_pipelines()):
                start_study()
            if map_wanted and envelope_map is None and envelope.ready((job.key for job in outputs), map_seeds):
                start_map()

        maybe_start()
        try:
            done = 0
            for future in queue:
                owner = next((e for e in (execution, envelope_execution) if e is not None and e.owns(future)), None)
                if owner is not None:
                    for new in owner.handle(future):
                        queue.add(new)
                    continue
                if future.key in ssp_futures:
                    mode, controller = ssp_futures.pop(future.key)
                    ssp_parts[mode, controller] = _task_result(future, f"the SSP agreement's {controller} loops on "
                                                               f"the {mode} plant", out_dir)
                    continue
                job = futures.pop(future.key)
                what = f"pipeline {job.key}" if job.kind == "pipeline" else f"the {job.kind} job {job.key}"
                output = _task_result(future, what, out_dir)
                outputs[job] = output
                done += 1
                log(f"[{done}/{len(todo)}] {job.key} finished in {sum(output.timings.values()):.1f} s")
                for ready in [j for j in waiting if j.after == job.key]:
                    waiting.remove(ready)
                    submit(ready, SOURCE_PRIORITY)
                maybe_start()
        except BaseException:
            for e in (execution, envelope_execution):
                if e is not None:
                    e.cancel()
            raise
        if envelope_execution is not None:
            envelope_execution.close()
            log(f"  envelope map: {envelope_execution.counts.runs} run(s) written ({envelope_execution.counts.failed} "
                "failed)")
        if execution is None:
            return None, None, envelope_map, envelope_execution
        execution.close()
        log(f"  tolerance study: {execution.counts.runs} run(s) written ({execution.counts.failed} failed)")
        return study, execution.counts, envelope_map, envelope_execution


def _study_timing(study, counts) -> dict | None:
    """The tolerance study's wall-clock figures for timings.md: its runs' worker time, and when its
    last part landed (its tasks share the cluster with the pipelines, so neither is its added cost)."""
    if study is None:
        return None
    from cosim.design.sweeps.dataset import read_timing

    worker_time = float(read_timing(study.out_dir)["wall_time_s"].astype(float).sum())
    return {"runs": counts.runs if counts else 0, "worker_s": worker_time, "last_part_s": counts.elapsed if counts else 0.0}


def reproduce(out_dir: Path = Path("results"), workers: int = 2, resume: bool = False, seed: int = 0,
              implementation: str = DEFAULT_IMPLEMENTATION,
              profile: Profile = FULL, binding_file: str | None = None,
              control_periods: tuple[float, ...] = (), controller_files: tuple[str, ...] = (),
              optimizer: str | None = None) -> Path:
    """Run every job and write ``REPORT.md``; returns the report path.

    With ``binding_file``, the pipeline runs on that external plant at ``control_periods``
    (default 1 ms) instead of the built-in plants (no seed jobs, no drift study).
    ``implementation``: the controllers' C twins ("c", equivalent at every sample and faster) or
    their Python references ("python"). ``controller_files``: controller FMUs / controller-binding
    files run next to the built-in controllers in every pipeline at their sample period (checked
    before any work starts). ``optimizer`` (Python API only, a measurement switch): the default optimizer of
    the predictive controllers that have none of their own, here and on every worker
    (:func:`cosim.design.experiments.default_optimizer`; None: the study's, the RTI) -- the benchmark group
    ``reproduction-optimizer`` times the reproduction with "rti" and with "search"; the report's prose
    describes the default.
    """
    with default_optimizer(optimizer) if optimizer is not None else nullcontext():  # a bad name: refused here
        return _reproduce(out_dir, workers, resume, seed, implementation, profile, binding_file, control_periods,
                          controller_files, optimizer)


def _reproduce(out_dir: Path, workers: int, resume: bool, seed: int, implementation: str, profile: Profile,
               binding_file: str | None, control_periods: tuple[float, ...], controller_files: tuple[str, ...],
               optimizer: str | None = None) -> Path:

    out_dir = Path(out_dir)
    started = time.perf_counter()
    if binding_file:
        selected = [Pipeline("bound", "", period, str(Path(binding_file).resolve()))
                    for period in (control_periods or (PAPER_PERIOD,))]
    else:
        selected = [p for p in PIPELINES if profile.pipelines is None or p.tag in profile.pipelines]
    extra = external_controllers(list(controller_files), tuple(dict.fromkeys(p.control_period for p in selected)))
    jobs = plan_jobs(selected, profile, seed, binding_file, extra)
    outputs, todo = prepare_jobs(jobs, out_dir, resume, implementation)
    tunings = sorted({job.pipeline for job in todo}, key=lambda p: p.control_period)
    log(f"reproduction: {len(todo)} job(s) on {workers} worker(s) -> {out_dir}/"
        + (" [quick profile: tiny sizes]" if profile.quick else ""))
    study_wanted = not binding_file and tolerance_study.SOURCE_PIPELINE in {p.tag for p in selected}
    map_wanted = not binding_file and pipeline_tag(envelope.MAP_PLANT, SWITCHING_PERIOD) in {p.tag for p in selected}
    ssp_wanted = not binding_file and set(ssp_agreement.SOURCE_PIPELINES) <= {p.tag for p in selected}
    ssp_parts: dict = {}
    study = study_counts = envelope_map = map_execution = None
    if todo or study_wanted or map_wanted:
        try:
            study, study_counts, envelope_map, map_execution = run_on_cluster(
                todo, tunings, outputs, out_dir, profile, implementation, workers, resume, study_wanted, map_wanted,
                optimizer, ssp_parts if ssp_wanted else None)
        finally:
            remove_temporary_files(out_dir)  # what unfinished writes left, once the workers are gone
    map_started = time.perf_counter()
    if envelope_map is not None:
        envelope.write_outputs(envelope_map, out_dir)
    map_timing = _study_timing(envelope_map, map_execution.counts if map_execution is not None else None)
    if map_timing is not None:
        map_timing["outputs_s"] = time.perf_counter() - map_started
    ordered = [outputs[job] for job in jobs]
    metrics = pd.concat([o.metrics for o in ordered], ignore_index=True)
    write_metrics(metrics, out_dir / "metrics" / "metrics_all")
    # PNG only: the report links PNGs, and results/ commits no SVG
    tolerance = study.summarise(vector=False) if study is not None else None
    pipelines = _per_pipeline(selected, jobs, outputs)
    drift = [outputs[job] for job in jobs if job.kind == "drift"]
    report = write_report(out_dir, pipelines, metrics, profile=profile, seed=seed, drift=drift, tolerance=tolerance)
    ssp_timing = None
    if ssp_wanted:  # the loop as an SSP (issue 17): its parts ran on the cluster (here if no cluster ran)
        section_started = time.perf_counter()
        parts = [ssp_parts[part][0] for part in ssp_agreement.PARTS] if ssp_parts else None
        ssp_agreement.append_to_report(out_dir, report, quick=profile.quick, parts=parts)
        ssp_timing = {"parts": len(ssp_parts), "worker_s": sum(seconds for _, seconds in ssp_parts.values()),
                      "section_s": time.perf_counter() - section_started} if ssp_parts else None
    elapsed = time.perf_counter() - started
    write_timings(out_dir, ordered, metrics, elapsed, workers, tolerance=_study_timing(study, study_counts),
                  envelope=map_timing, ssp=ssp_timing)
    log(f"reproduction finished in {elapsed:.1f} s; report: {report}")
    return report


def _per_pipeline(selected: list[Pipeline], jobs: list[Job], outputs: dict[Job, PipelineOutput]) -> list[PipelineOutput]:
    """Each pipeline's output with its seed jobs' metrics and models merged in (for the report)."""
    merged = []
    for pipeline in selected:
        main = outputs[next(j for j in jobs if j.kind == "pipeline" and j.pipeline == pipeline)]
        parts = [main] + [outputs[j] for j in jobs if j.kind == "seed" and j.pipeline == pipeline]
        models = {}
        for part in parts:
            models.update(part.models)
        merged.append(PipelineOutput(pipeline=pipeline, metrics=pd.concat([p.metrics for p in parts], ignore_index=True),
                                     pi=main.pi, models=models, timings=main.timings))
    return merged
