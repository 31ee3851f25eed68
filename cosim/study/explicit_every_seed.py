"""The explicit NNPC on every identification seed: its targets against the online NNPC of the same seed.

The reproduction distills the explicit NNPC from seed 0's online NNPC only (:mod:`cosim.study.explicit`), so its
targets there -- IAE within 1.05 x the online NNPC's in the paper's four scenarios, start-up overshoot <= 5 %,
steady-state error <= 0.2 % -- are one seed's. :func:`every_seed` repeats them for the NNPC identified from every
study seed's data on each pipeline at one switching period: seed 0 with the reproduction's own policy file (so its
rows are the reproduction's), every other seed distilled here with the reproduction's budget
(:data:`~cosim.design.distillation.FULL_DISTILLATION`, DAgger seed = the identification seed, as the reproduction
pairs them) and kept in a cache keyed by the expert network and the expert's optimizer, so a rerun only simulates.
With ``expert_optimizer`` other than the reproduction's (:data:`~cosim.design.distillation.FULL_DISTILLATION`'s: the
workbench's default, the RTI) every seed, 0 too, is distilled here with that optimizer labelling the states, and the
tables are named for it (``explicit-every-seed-search-labels.*``): the same targets, side by side with the
reproduction's labels. The (pipeline, seed) jobs
run as dask tasks on a LocalCluster (:mod:`cosim.design.cluster`), one job per task.

Distillation is the cost: about 40 s per plant and seed on a core (two workers; 80 s with the search's labels), so
this is not part of ``make reproduce``; ``make every-seed`` runs it (``scripts/explicit_every_seed.py``) after the
reproduction. Nothing in the workbench imports this module.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from cosim.base.files import atomic_write, atomic_write_text
from cosim.study.explicit import IAE_RATIO_TARGET, OVERSHOOT_TARGET_PCT, STEADY_STATE_TARGET_PCT, policy_path

#: the files :func:`write_tables` writes into the results folder (with the reproduction's expert optimizer;
#: :func:`file_names` for another)
TABLE_NAME, REPORT_NAME = "explicit-every-seed.csv", "explicit-every-seed.md"
#: the record period of the runs [s]: the reproduction's (cosim.batch.run_batch's default), so seed 0's rows are its
RECORD_PERIOD = 1e-5
#: one row per run: these columns first, in this order
COLUMNS = ("pipeline", "seed", "scenario", "iae_online_Vs", "iae_explicit_Vs", "iae_ratio", "overshoot_online_pct",
           "overshoot_explicit_pct", "steady_state_error_online_pct", "steady_state_error_explicit_pct",
           "settling_time_online_ms", "settling_time_explicit_ms", "policy")


def fast_pipelines(tags: list[str] | None = None) -> list:
    """The reproduction's built-in pipelines at one switching period (those it distills a policy for), or those of
    them named in ``tags``."""
    from cosim.design.vocabulary import transient_within_sample
    from cosim.study import reproduce

    return [p for p in reproduce.PIPELINES if not transient_within_sample(p.control_period)
            and (tags is None or p.tag in tags)]


def reproduction_labels(expert_optimizer: str | None) -> bool:
    """Whether ``expert_optimizer`` (None: the reproduction's) labels the states as the reproduction's do."""
    from cosim.design.distillation import FULL_DISTILLATION

    return expert_optimizer in (None, FULL_DISTILLATION.resolved().expert_optimizer)


def file_names(expert_optimizer: str | None) -> tuple[str, str]:
    """The CSV and markdown :func:`write_tables` writes: :data:`TABLE_NAME` and :data:`REPORT_NAME` with the
    reproduction's expert optimizer, ``explicit-every-seed-<optimizer>-labels.*`` with another."""
    if reproduction_labels(expert_optimizer):
        return TABLE_NAME, REPORT_NAME
    stem = f"explicit-every-seed-{expert_optimizer}-labels"
    return f"{stem}.csv", f"{stem}.md"


def cached_policy_path(cache: Path, tag: str, seed: int, expert: str, expert_optimizer: str) -> Path:
    """Where a seed's policy is kept: named by its pipeline, seed, expert network (a retrained NNPC is not
    taken for the one a cached policy imitates) and the optimizer that labelled it."""
    return Path(cache) / f"{tag}__seed{seed}__nnpc-explicit__expert-{expert}__{expert_optimizer}-labels.pt"


def seed_policy(pipeline, seed: int, model, out_dir: Path, cache: Path, log: Callable[[str], None] | None = None,
                expert_optimizer: str | None = None):
    """The explicit policy distilled from ``model`` (seed ``seed``'s NNPC on ``pipeline``) with ``expert_optimizer``
    labelling the states (None: the reproduction's) and where it comes from: seed 0 with the reproduction's labels
    the reproduction's policy file (refused if it imitates another network than ``model``), the others the cache's
    or a new distillation (then cached)."""
    from controllers.explicit_policy import load_policy, save_policy
    from cosim.base.errors import ConfigError
    from cosim.design.distillation import FULL_DISTILLATION, expert_fingerprint, settings_dict
    from cosim.design.distillation import distill as run_distillation

    expert = expert_fingerprint(model)
    settings = replace(FULL_DISTILLATION, seed=seed,
                       expert_optimizer=expert_optimizer or FULL_DISTILLATION.expert_optimizer)
    settings.check()
    settings = settings.resolved().for_converter(pipeline.binding().converter)  # as the policy's metadata records them
    if seed == 0 and reproduction_labels(expert_optimizer):
        path = policy_path(out_dir, pipeline.tag)
        if not path.is_file():
            raise ConfigError(f"{path}: no explicit policy there (run make reproduce first)")
        policy = load_policy(path, expect_period=pipeline.control_period)
        if policy.metadata.get("expert_model") != expert:
            raise ConfigError(f"{path}: distilled from another network (expert {policy.metadata.get('expert_model')}) "
                              f"than {out_dir}/models/{pipeline.tag}__nnpc.pt ({expert}): run make reproduce again")
        return policy, "reproduction"
    path = cached_policy_path(cache, pipeline.tag, seed, expert, settings.expert_optimizer)
    if path.is_file():
        policy = load_policy(path, expect_period=pipeline.control_period)
        recorded = policy.metadata.get("distillation", {})
        if {k: v for k, v in recorded.items() if k not in ("labels", "history")} == settings_dict(settings):
            return policy, "cache"
    policy = run_distillation(model, pipeline.binding(), pipeline.control_period, settings, log=log,
                              metadata={"pipeline": pipeline.tag, "identification_seed": seed})
    Path(cache).mkdir(parents=True, exist_ok=True)
    save_policy(policy, path)
    return policy, "distilled"


def check_results(out_dir: Path, pipelines: list) -> None:
    """Refuse, before any job, a results folder whose seed-0 policy of one of ``pipelines`` is missing or imitates
    another network than its NNPC file (a reproduction half-rerun): a :class:`ConfigError` naming the file."""
    from controllers.nn_model import load_model
    from cosim.design.experiments import nn_configs

    for pipeline in pipelines:
        model = load_model(Path(out_dir) / "models" / f"{pipeline.tag}__nnpc.pt", expect_period=pipeline.control_period,
                           expect_config=nn_configs(pipeline.control_period)["nnpc"])
        seed_policy(pipeline, 0, model, out_dir, Path(out_dir), log=None)  # seed 0: reads and checks, never distills


def seed_job(tag: str, seed: int, out_dir: Path, cache: Path,
             expert_optimizer: str | None = None) -> tuple[list[dict], dict]:
    """One (pipeline, seed) of :func:`every_seed`, as a dask task: the seed's NNPC (identified if not cached), its
    policy, and both on the paper's scenarios (their C twins, as the reproduction runs them). The rows (``policy``:
    "reproduction" for seed 0's file, else "distilled here"), and for the log the job's wall-clock seconds and
    where the policy came from this time ("reproduction", "cache" or "distilled")."""
    from cosim.design.experiments import explicit_nnpc, implemented, nnpc, scenarios_for
    from cosim.design.vocabulary import NNPC, NNPC_EXPLICIT
    from cosim.master import simulate
    from cosim.metrics import run_metrics
    from cosim.study.optimizer_every_seed import seed_model

    start = time.perf_counter()
    (pipeline,) = fast_pipelines([tag])
    period, binding = pipeline.control_period, pipeline.binding()
    model = seed_model(pipeline, seed, Path(out_dir), Path(cache))
    policy, origin = seed_policy(pipeline, seed, model, Path(out_dir), Path(cache), log=None,
                                 expert_optimizer=expert_optimizer)
    # the table names the policy's recipe, not whether this run took it from the cache (the same bytes on a rerun)
    recipe = "reproduction" if origin == "reproduction" else "distilled here"
    rows = []
    for scenario in scenarios_for(period, spec=binding.converter):
        online, explicit = (run_metrics(simulate(binding, implemented(controller), scenario,
                                                 record_period=RECORD_PERIOD, seed=seed))
                            for controller in (nnpc(model, period, NNPC), explicit_nnpc(policy, NNPC_EXPLICIT)))
        rows.append({"pipeline": tag, "seed": seed, "scenario": scenario.name,
                     "iae_online_Vs": online["iae_Vs"], "iae_explicit_Vs": explicit["iae_Vs"],
                     "iae_ratio": explicit["iae_Vs"] / online["iae_Vs"] if online["iae_Vs"] > 0 else math.nan,
                     "overshoot_online_pct": online["overshoot_pct"],
                     "overshoot_explicit_pct": explicit["overshoot_pct"],
                     "steady_state_error_online_pct": online["steady_state_error_pct"],
                     "steady_state_error_explicit_pct": explicit["steady_state_error_pct"],
                     "settling_time_online_ms": online["settling_time_ms"],
                     "settling_time_explicit_ms": explicit["settling_time_ms"], "policy": recipe})
    return rows, {"seconds": time.perf_counter() - start, "origin": origin}


def every_seed(out_dir: Path, cache: Path, pipelines: list[str] | None = None, seeds: tuple[int, ...] | None = None,
               workers: int | None = None, log: Callable[[str], None] = print,
               on_rows: Callable[[list[dict]], None] | None = None,
               expert_optimizer: str | None = None) -> list[dict]:
    """:func:`seed_job` for every fast pipeline (or those in ``pipelines``) and every study seed (or those in
    ``seeds``) on a LocalCluster of ``workers`` processes (default: one per core). ``on_rows(rows)`` gets the rows so
    far after each job (to save them as they come); the rows come back in (pipeline, seed, scenario) order, whatever
    order the jobs finished in. ``expert_optimizer``: the optimizer labelling the distillation's states (None: the
    reproduction's)."""
    from distributed import as_completed

    from cosim.design.cluster import dask_client

    jobs = [(p.tag, seed) for p in fast_pipelines(pipelines) for seed in p.study_seeds if seeds is None or seed in seeds]
    check_results(Path(out_dir), [p for p in fast_pipelines(pipelines)])
    done: dict[tuple[str, int], list[dict]] = {}

    def ordered() -> list[dict]:
        return [row for job in jobs if job in done for row in done[job]]

    with dask_client(workers=workers, worker_saturation=1.0) as client:
        futures = {client.submit(seed_job, tag, seed, Path(out_dir), Path(cache), expert_optimizer, pure=False):
                   (tag, seed)
                   for tag, seed in jobs}
        for future in as_completed(list(futures), loop=client.loop):
            tag, seed = futures[future]
            rows, info = future.result()
            done[(tag, seed)] = rows
            worst = max(rows, key=lambda r: r["iae_ratio"])
            startup = next((r for r in rows if r["scenario"] == "startup"), None)
            log(f"[{len(done)}/{len(jobs)}] {tag} seed {seed} (policy: {info['origin']}, {info['seconds']:.0f} s): "
                f"worst IAE explicit / online {worst['iae_ratio']:.3f} ({worst['scenario']})"
                + (f", start-up overshoot {startup['overshoot_explicit_pct']:.2f} % (online "
                   f"{startup['overshoot_online_pct']:.2f} %)" if startup else ""))
            if on_rows is not None:
                on_rows(ordered())
    return ordered()


# ---------------------------------------------------------------------------------------------
# The verdict and the tables


def _per_seed(rows: list[dict]) -> dict[int, dict]:
    """Per seed: the worst IAE ratio and its scenario, the start-up overshoots, the largest |steady-state error|."""
    out = {}
    for seed in sorted({r["seed"] for r in rows}):
        mine = [r for r in rows if r["seed"] == seed]
        worst = max(mine, key=lambda r: r["iae_ratio"] if math.isfinite(r["iae_ratio"]) else math.inf)
        startup = next((r for r in mine if r["scenario"] == "startup"), None)
        error = max(mine, key=lambda r: abs(r["steady_state_error_explicit_pct"]))
        out[seed] = {"iae_ratio": worst["iae_ratio"], "iae_scenario": worst["scenario"],
                     "overshoot": startup["overshoot_explicit_pct"] if startup else math.nan,
                     "overshoot_online": startup["overshoot_online_pct"] if startup else math.nan,
                     "steady_state_error": abs(error["steady_state_error_explicit_pct"]),
                     "steady_state_scenario": error["scenario"]}
    return out


def verdict(rows: list[dict]) -> list[dict]:
    """One line per target of the explicit NNPC (those of :mod:`cosim.study.explicit`) over the seeds of ``rows``
    (one pipeline): the value per seed, its spread (min / median / max over the seeds), the seeds that miss the
    limit, and whether it holds for every seed."""
    per_seed = _per_seed(rows)
    lines = []
    for key, target, limit, unit in (
            ("iae_ratio", f"IAE <= {IAE_RATIO_TARGET:.2f} x online NNPC, every scenario (worst scenario)",
             IAE_RATIO_TARGET, ""),
            ("overshoot", f"start-up overshoot <= {OVERSHOOT_TARGET_PCT:g} %", OVERSHOOT_TARGET_PCT, " %"),
            ("steady_state_error", f"steady-state error <= {STEADY_STATE_TARGET_PCT:g} %, every scenario",
             STEADY_STATE_TARGET_PCT, " %")):
        values = {seed: v[key] for seed, v in per_seed.items()}
        missed = [seed for seed, value in values.items() if not value <= limit]
        finite = [v for v in values.values() if math.isfinite(v)]
        lines.append({"target": target, "key": key, "limit": limit, "unit": unit, "values": values,
                      "spread": (min(finite), float(np.median(finite)), max(finite)) if finite else (math.nan,) * 3,
                      "missed": missed, "met": not missed and bool(values)})
    return lines


def report(rows: list[dict], complete: bool, command: str, expert_optimizer: str | None = None) -> str:
    """The markdown summary: per pipeline, each target's verdict over the seeds with its spread and the value of
    every seed; then the online NNPC's start-up overshoot per seed beside the explicit's (the comparison the
    overshoot target is read against). ``expert_optimizer``: what labelled the states (None: the reproduction's)."""
    from cosim.design.distillation import FULL_DISTILLATION

    table_name = file_names(expert_optimizer)[0]
    names = {"rti": "RTI"}  # the optimizers as the prose names them
    default = names.get(FULL_DISTILLATION.resolved().expert_optimizer, FULL_DISTILLATION.resolved().expert_optimizer)
    if reproduction_labels(expert_optimizer):
        title, recipe = "", (
            "Seed 0's policy is the reproduction's (`models/<pipeline>__nnpc-explicit.pt`), so its rows are those of "
            "`REPORT.md`; every other seed's NNPC is identified from that seed's data with the reproduction's recipe "
            "and distilled with the reproduction's budget (DAgger seed = identification seed), the online NNPC with "
            f"the {default} labelling the states.")
    else:
        other = names.get(expert_optimizer, expert_optimizer)
        title, recipe = f", its labels from the {other}", (
            f"Every seed's policy, seed 0's too, is distilled here with the online NNPC planned by the "
            f"{other} labelling the states instead of the reproduction's {default}, with the reproduction's "
            "budget (DAgger seed = identification seed); each seed's NNPC is the reproduction's recipe's, so the "
            "online columns are those of "
            f"`{TABLE_NAME}`.")
    lines = [f"# The explicit NNPC on every seed{title}{'' if complete else ' (INCOMPLETE: the run was stopped)'}",
             "", f"Command: `{command}`. Per run: `{table_name}` (one line per pipeline, seed and scenario: the online "
             "NNPC and the explicit NNPC distilled from it, their C twins, on the paper's four scenarios). " + recipe +
             " A target holds only if it holds for every seed; spreads are min / median / max over the seeds.", "",
             "| pipeline | target | every seed | min / median / max | per seed | seeds that miss it |",
             "|---|---|---|---|---|---|"]
    pipelines = list(dict.fromkeys(r["pipeline"] for r in rows))
    for tag in pipelines:
        mine = [r for r in rows if r["pipeline"] == tag]
        for line in verdict(mine):
            digits = ".2f" if line["key"] == "overshoot" else ".3f"
            spread = " / ".join(f"{v:{digits}}" for v in line["spread"])
            per_seed = "; ".join(f"{seed}: {value:{digits}}" for seed, value in line["values"].items())
            missed = ", ".join(map(str, line["missed"])) or "--"
            met = "yes" if line["met"] else "**no**"
            lines.append(f"| {tag} | {line['target']} | {met} | {spread}{line['unit']} | {per_seed} | {missed} |")
    lines += ["", "Start-up overshoot per seed [%], explicit (online NNPC of the same seed):", "",
              "| pipeline | " + " | ".join(f"seed {s}" for s in sorted({r['seed'] for r in rows})) + " |",
              "|---|" + "---|" * len({r["seed"] for r in rows})]
    all_seeds = sorted({r["seed"] for r in rows})
    for tag in pipelines:
        per_seed = _per_seed([r for r in rows if r["pipeline"] == tag])
        cells = [f"{per_seed[s]['overshoot']:.2f} ({per_seed[s]['overshoot_online']:.2f})" if s in per_seed else "--"
                 for s in all_seeds]
        lines.append(f"| {tag} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def table(rows: list[dict]) -> pd.DataFrame:
    """One line per run, :data:`COLUMNS` in order."""
    return pd.DataFrame.from_records(rows, columns=list(COLUMNS))


def write_tables(out_dir: Path, rows: list[dict], complete: bool, command: str,
                 expert_optimizer: str | None = None) -> None:
    """``out_dir/explicit-every-seed.csv`` and ``.md`` (:func:`file_names`: another name for another
    ``expert_optimizer``; atomic writes; the markdown says when the rows are incomplete, as after each job while the
    evaluation goes on)."""
    out_dir = Path(out_dir)
    frame = table(rows)
    table_name, report_name = file_names(expert_optimizer)
    atomic_write(out_dir / table_name, lambda tmp: frame.to_csv(tmp, index=False, float_format="%.10g"))
    atomic_write_text(out_dir / report_name, report(rows, complete, command, expert_optimizer))
