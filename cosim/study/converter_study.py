"""The whole study for one converter: ``buck-cosim study --plant BINDING --out DIR``.

What ``make reproduce`` does for the paper's converter, done for the converter a binding file describes (its
``[converter]`` table, :mod:`cosim.converter_spec`): at each control period the spec names (or ``--control-period``),
one *pipeline* tunes the PI at the spec's nominal point, identifies the NNPC from seed 0's data over the spec's
ranges, trains the paper's 3-7-2 network, and runs the paper's scenarios (resolved against the spec) with PI, NNPC,
the paper's NNPC and the MPC on the spec's nominal circuit; at one switching period of the spec it also distils the
explicit NNPC and designs the current-mode controller and the Type-III from the nominal circuit (their loop gains
measured by injection). *Seed jobs* identify the NNPC again from every other seed's data and run it on the same
scenarios, so every comparison the report states holds for every seed or is said to be within the spread.

The jobs run as dask tasks on a LocalCluster (127.0.0.1), as the reproduction's do (the same job functions:
:func:`cosim.study.reproduce.run_pipeline`, :func:`~cosim.study.reproduce.run_seed`); files are written atomically
and ``resume`` keeps finished jobs. :mod:`cosim.study.converter_report` writes ``REPORT.md`` and ``targets.csv`` from
the metrics. Wall-clock figures go to ``timings.md`` / ``timings.csv`` only.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from cosim.base.errors import ConfigError
from cosim.design.vocabulary import DEFAULT_IMPLEMENTATION
from cosim.study.vocabulary import STUDY_SEEDS

if TYPE_CHECKING:  # the reproduction's machinery (pandas, dask, the designs) loads when a study runs, not for --help
    import pandas as pd

    from cosim.study.reproduce import Job, Pipeline, Profile

#: identification seeds of a study unless ``--seeds`` says otherwise (the reproduction's count)
DEFAULT_SEEDS = len(STUDY_SEEDS)
#: what ``--quick`` changes: two seeds, a third of the identification data and of the simulation-error training,
#: the small distillation and quick PI tuning -- a first look at a new converter, not its study
QUICK_SEEDS = 2
#: wall-clock budgets of a whole study on 2 cores [s]: the default and ``--quick`` (timings.md; a benchmark row each)
STUDY_BUDGET_S, QUICK_STUDY_BUDGET_S = 900.0, 180.0


@dataclass(frozen=True)
class StudyPlan:
    """One converter study, checked: the binding file, its control periods [s] and identification seeds."""

    binding_file: Path
    control_periods: tuple[float, ...]
    seeds: tuple[int, ...]
    quick: bool = False

    @property
    def pipelines(self) -> list[Pipeline]:
        from cosim.study.reproduce import Pipeline

        return [Pipeline("bound", "", period, str(self.binding_file)) for period in self.control_periods]

    @property
    def profile(self) -> Profile:
        """The reproduction's sizes for a bound plant: no ablations or drift study (they need a plant's true
        parameters), the study's seeds; ``quick``: smaller identification and distillation."""
        from cosim.study.reproduce import FULL

        profile = replace(FULL, seeds=self.seeds, ablations=False, drift=False)
        if self.quick:
            profile = replace(profile, samples=4000, multi_step_iterations=100, quick=True)
        return profile

    def jobs(self) -> list[Job]:
        """Every job: a pipeline per period (seed 0), then a seed job per other seed and period."""
        from cosim.study.reproduce import Job

        pipelines = self.pipelines
        return ([Job("pipeline", p, self.seeds[0]) for p in pipelines]
                + [Job("seed", p, s) for p in pipelines for s in self.seeds[1:]])


def plan_study(binding_file: str | Path, control_periods: tuple[float, ...] = (), seeds: int | None = None,
               quick: bool = False) -> StudyPlan:
    """The study of ``binding_file``'s converter, checked before any work: the binding (roles, archive, converter
    table), the nominal circuit its model-based designs need, the control periods (``control_periods``, else the
    spec's ``control_periods``) and that every scenario suits each of them. Refused in one line
    (:class:`ConfigError` and the binding's own errors) otherwise."""
    from cosim.batch import Batch
    from cosim.design.experiments import scenarios_for
    from cosim.fmi.binding_file import load_binding

    binding_file = Path(binding_file).resolve()
    binding = load_binding(binding_file)
    spec = binding.converter
    spec.circuit("the converter study (its MPC and classical baselines design with the nominal circuit)")
    periods = tuple(control_periods) or tuple(spec.control_periods or ())
    if not periods:
        raise ConfigError(f"{binding.origin}: the converter study needs its control periods: give "
                          "[converter] control_periods = [...] (s) or --control-period")
    count = seeds if seeds is not None else (QUICK_SEEDS if quick else DEFAULT_SEEDS)
    if count < 1:
        raise ConfigError(f"--seeds {count} is invalid: expected at least 1 identification seed")
    for period in periods:
        scenarios = [s for s in scenarios_for(period, spec=spec) if s.required_roles() <= set(binding.roles)]
        Batch(binding, scenarios).check_rates(period)
    return StudyPlan(binding_file, tuple(dict.fromkeys(periods)), tuple(range(count)), quick)


def run_study(plan: StudyPlan, out_dir: Path, *, workers: int = 2, resume: bool = False,
              implementation: str = DEFAULT_IMPLEMENTATION) -> Path:
    """Run every job of ``plan`` into ``out_dir`` and write its report; returns the report's path."""
    import pandas as pd

    from cosim.base.files import remove_temporary_files
    from cosim.batch import write_metrics
    from cosim.study.converter_report import write_converter_report
    from cosim.study.reproduce import log, prepare_jobs, run_on_cluster
    from cosim.study.timings import write_timings

    out_dir = Path(out_dir)
    started = time.perf_counter()
    jobs = plan.jobs()
    outputs, todo = prepare_jobs(jobs, out_dir, resume, implementation)
    binding = plan.pipelines[0].binding()
    log(f"converter study of {binding.converter.label or binding.label}: {len(todo)} job(s) on {workers} worker(s) "
        f"-> {out_dir}/" + (" [quick]" if plan.quick else ""))
    if todo:
        tunings = sorted({job.pipeline for job in todo}, key=lambda p: p.control_period)
        try:
            run_on_cluster(todo, tunings, outputs, out_dir, plan.profile, implementation, workers, resume,
                            study_wanted=False)
        finally:
            remove_temporary_files(out_dir)
    map_steps = run_envelope_map(plan, binding, out_dir, workers, resume)
    ordered = [outputs[job] for job in jobs]
    metrics = pd.concat([o.metrics for o in ordered], ignore_index=True)
    write_metrics(metrics, out_dir / "metrics" / "metrics_all")
    report = write_converter_report(out_dir, binding, plan, ordered, metrics, map_steps)
    elapsed = time.perf_counter() - started
    write_timings(out_dir, ordered, metrics, elapsed, workers, study="converter study",
                  command="buck-cosim study", targets=budget_targets(plan, elapsed, workers))
    log(f"converter study finished in {elapsed:.1f} s; report: {report}")
    return report


def map_period(plan: StudyPlan, spec) -> float | None:
    """The rate of the study's envelope map: one sample per PWM period of the converter, if the study runs it."""
    for period in plan.control_periods:
        if spec.samples_once_per_pwm_period(period):
            return period
    return None


def map_entries(out_dir: Path, plant_tag: str, period: float, seeds: tuple[int, ...], settle: float) -> tuple:
    """The map's controllers, from the pipeline's files at ``period``: the online NNPC of seed 0 (the explicit policy
    in shadow), the explicit NNPC, the nominal-model MPC, the current-mode controller, the Type-III and the PI, and
    the online NNPC of every other seed (``settle`` [s]: the predictive controllers' operation before the steps)."""
    import json

    from cosim.design.classical_design import design_files
    from cosim.design.design_cache import model_file, pi_file, seed_model_file
    from cosim.design.sweeps.spec import ControllerEntry
    from cosim.design.vocabulary import (
        CURRENT_MODE,
        MPC_NOMINAL,
        NNPC,
        NNPC_EXPLICIT,
        PI,
        TYPE_III,
        pipeline_tag,
        seed_variant,
    )

    tag = pipeline_tag(plant_tag, period)
    pi = json.loads(pi_file(out_dir, plant_tag, period).read_text(encoding="utf-8"))
    model, policy = model_file(out_dir, plant_tag, period, "nnpc"), model_file(out_dir, plant_tag, period,
                                                                               "nnpc-explicit")
    designs = design_files(out_dir, tag)
    return (ControllerEntry("nnpc", NNPC, model=model, policy=policy, settle=settle,
                            origin=f"identified by the study (models/{model.name}), the explicit policy in shadow"),
            ControllerEntry("nnpc-explicit", NNPC_EXPLICIT, policy=policy,
                            origin=f"distilled by the study (models/{policy.name})"),
            ControllerEntry("mpc-nominal", MPC_NOMINAL, settle=settle),
            ControllerEntry("current-mode", CURRENT_MODE, design=designs["current-mode"],
                            origin=f"designed by the study (tuning/{designs['current-mode'].name})"),
            ControllerEntry("type-iii", TYPE_III, design=designs["type-iii"],
                            origin=f"designed by the study (tuning/{designs['type-iii'].name})"),
            ControllerEntry("pi", PI, kp=pi["kp"], ki=pi["ki"], origin=f"tuned by the study ({pi['method']})"),
            *(ControllerEntry("nnpc", seed_variant(NNPC, s), settle=settle,
                              model=seed_model_file(out_dir, plant_tag, period, s),
                              origin=f"identified by the study's seed job {s}") for s in seeds[1:]))


def run_envelope_map(plan: StudyPlan, binding, out_dir: Path, workers: int, resume: bool):
    """The envelope map over the spec's ranges at one sample per PWM period (the paper's map, on this converter: a
    reference step 0.8 r -> r and a load step 1.25 R -> R at every point, scored against overshoot <= 5 % and 2 %
    settling within 0.5 ms), on the sweep engine; ``envelope/`` tables and ``figures/envelope_map.png``. Returns the
    map's steps table (None where the study has no such rate)."""
    import shutil

    from cosim.base.labels import period_text
    from cosim.design.sweeps.spec import PlantChoice
    from cosim.master import record_period_of
    from cosim.study import envelope
    from cosim.study.reproduce import log

    spec = binding.converter
    period = map_period(plan, spec)
    if period is None:
        return None
    settings = envelope.MapSettings.for_converter(spec, plan.quick)
    folder = out_dir / envelope.ENVELOPE_DIR / "sweep"
    if not resume and folder.exists():
        shutil.rmtree(folder)
    entries = map_entries(out_dir, binding.tag, period, plan.seeds, settings.settle_predictive)
    log(f"  envelope map: {settings.points} points x 2 steps x {len(entries)} controllers at {period_text(period)}")
    steps = envelope.run_entries(entries, folder, settings, workers, plant=PlantChoice(binding=plan.binding_file),
                                 control_period=period,
                                 record_period=record_period_of(binding, period / 4, period))
    envelope.write_tables(steps, out_dir)
    envelope.figures(steps, out_dir, where=f"{binding.label} at {period_text(period, ascii_only=True)}",
                     nominal_supply=settings.nominal[2])
    return steps


def budget(plan: StudyPlan) -> float:
    """The study's wall-clock budget on 2 cores [s]."""
    return QUICK_STUDY_BUDGET_S if plan.quick else STUDY_BUDGET_S


def budget_targets(plan: StudyPlan, elapsed: float, workers: int) -> pd.DataFrame:
    """The timing target of a study (``timings.md``): its whole wall time against :func:`budget`."""
    import pandas as pd

    from cosim.study.claims import TARGET_COLUMNS, target_row

    limit = budget(plan)
    row = target_row(f"Whole {'quick ' if plan.quick else ''}study <= {limit / 60:g} min on 2 cores",
                     f"{elapsed:.1f} s on {workers} worker process(es)", elapsed <= limit, value=elapsed, limit=limit)
    return pd.DataFrame([row], columns=TARGET_COLUMNS)
