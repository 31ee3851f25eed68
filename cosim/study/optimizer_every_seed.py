"""The every-seed evaluation of the real-time iteration against the search (issue 24's quality targets).

:func:`every_seed` runs :func:`cosim.study.optimizer_ablation.compare` for the NNPC of every study seed and the MPC
baselines on every pipeline of the reproduction. It builds on the reproduction's recipe and files, so it lives
beside it rather than in :mod:`cosim.study.optimizer_ablation` (which the reproduction imports): nothing in the
workbench imports this module; ``scripts/optimizer_every_seed.py`` runs it.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from cosim.base.files import atomic_write, atomic_write_text
from cosim.study.optimizer_ablation import (
    COST_EXCESS_TARGET,
    IAE_RATIO_TARGET,
    OVERSHOOT_POINTS_TARGET,
    compare,
    summary,
    verdict,
    with_rti,
)

#: the files :func:`write_tables` writes into the results folder
TABLE_NAME, REPORT_NAME = "optimizer-every-seed.csv", "optimizer-every-seed.md"


def every_seed(out_dir: Path, cache: Path, pipelines: list[str] | None = None, seeds: tuple[int, ...] | None = None,
               audit: bool = True, log: Callable[[str], None] = print, rti_changes: dict | None = None,
               on_row: Callable[[list[dict]], None] | None = None) -> list[dict]:
    """The every-seed evaluation issue 24 asks before the RTI may be the default: :func:`compare` for the NNPC
    identified from every study seed's data on each pipeline of the seed study (seed 0: the reproduction's model in
    ``out_dir/models``; the other seeds identified here with the reproduction's recipe and PI, and kept in
    ``cache``, so a rerun only simulates), and for the MPC baselines (the oracle and the mismatched model: no
    identification, seed 0) on every pipeline, both rates. Each row carries ``pipeline``, ``seed`` and its
    controller; :func:`verdict` of the rows of a pipeline or of all is the table the docs quote
    (``scripts/optimizer_every_seed.py`` prints it). ``rti_changes``: :class:`~controllers.predictive.RtiSettings`
    fields changed from each rate's defaults for the RTI runs (e.g. ``{"iterations": 2}``: a candidate default
    evaluated before it becomes one). ``on_row(rows)`` is called with the rows so far after each run (to save them
    as they come: :func:`write_tables`)."""
    from cosim.design.experiments import model_mpc, nnpc, scenarios_for
    from cosim.design.vocabulary import MISMATCH, MPC_MISMATCHED, MPC_NOMINAL, MPC_ORACLE, NNPC, NOMINAL, PLANT_VARIANTS
    from cosim.study import reproduce

    rows: list[dict] = []
    for pipeline in reproduce.PIPELINES:
        if pipelines is not None and pipeline.tag not in pipelines:
            continue
        period, binding = pipeline.control_period, pipeline.binding()
        scenarios = scenarios_for(period, spec=binding.converter)
        for seed in [s for s in pipeline.study_seeds if seeds is None or s in seeds]:
            model = seed_model(pipeline, seed, out_dir, cache)
            makers = {NNPC: lambda optimizer, model=model: nnpc(model, period, NNPC, optimizer=optimizer)}
            if seed == 0:
                wrong, wrong_name = (NOMINAL, MPC_NOMINAL) if pipeline.variant == "mismatch" else (MISMATCH,
                                                                                                   MPC_MISMATCHED)
                for name, parameters in ((MPC_ORACLE, PLANT_VARIANTS[pipeline.variant]), (wrong_name, wrong)):
                    makers[name] = (lambda optimizer, name=name, parameters=parameters:
                                    model_mpc(parameters, period, name, binding=binding, optimizer=optimizer))
            if rti_changes:
                makers = {name: (lambda optimizer, make=make: with_rti(make(optimizer), **rti_changes)
                                 if optimizer == "rti" else make(optimizer)) for name, make in makers.items()}
            for name, make in makers.items():
                for row in compare(binding, make, scenarios, audit=audit):
                    row.update(pipeline=pipeline.tag, seed=seed)
                    rows.append(row)
                    if on_row is not None:
                        on_row(rows)
                    log(f"{pipeline.tag:27s} seed {seed} {name:14s} {row['scenario']:14s} IAE {row['iae_search_Vs']:.4g} "
                        f"V s x {row['iae_ratio']:.4f}, eq. 16 x "
                        f"{row['closed_loop_cost_rti_Vs'] / row['closed_loop_cost_search_Vs']:.4f}, overshoot "
                        f"{row['overshoot_search_pct']:.2f} -> {row['overshoot_rti_pct']:.2f} %, plan cost excess "
                        f"median {100 * row['cost_excess_median']:.2f} % worst {100 * row['cost_excess_worst']:.1f} %,"
                        f" search {row['search_samples']} of {row['samples']} {row['fallbacks']}")
        verdict_line = {k: (round(v[0], 4), v[1]) for k, v in verdict([r for r in rows
                                                                       if r["pipeline"] == pipeline.tag]).items()}
        log(f"{pipeline.tag}: {verdict_line}")
    return rows


def seed_model(pipeline, seed: int, out_dir: Path, cache: Path):
    """The NNPC network of ``pipeline`` (a :class:`cosim.study.reproduce.Pipeline`) identified from study seed
    ``seed``'s data: seed 0 the reproduction's (``out_dir/models``), the other seeds of the pipelines whose seed jobs
    save their network (``reproduce.SEED_MODEL_PIPELINES``: the envelope map's plant and the drift study's at one
    switching period) the reproduction's seed jobs' files; any other identified here with the reproduction's recipe
    and tuned PI and kept in ``cache`` under a name holding the network and its data region (a cache of another
    recipe is not taken for it), so a rerun only loads it."""
    from controllers.nn_model import load_model, save_model
    from cosim.design.design_cache import seed_model_file
    from cosim.design.experiments import network_region, nn_configs
    from cosim.design.identification import identify
    from cosim.study import reproduce

    period = pipeline.control_period
    config = nn_configs(period)["nnpc"]
    if seed == 0:
        path = out_dir / "models" / f"{pipeline.tag}__nnpc.pt"
    elif pipeline.tag in reproduce.SEED_MODEL_PIPELINES:
        path = seed_model_file(out_dir, pipeline.plant_tag, period, seed)  # the reproduction's seed job wrote it
    else:
        region = network_region("nnpc", period)
        path = cache / f"{pipeline.tag}__seed{seed}__nnpc__{re.sub(r'[^A-Za-z0-9]+', '_', config.label)}__{region}.pt"
        if not path.is_file():
            pi = reproduce._tuned(pipeline, out_dir, reproduce.FULL)
            identified = identify(pipeline.binding(), pi.controller(), period, config, seed,
                                  reproduce._recipe(reproduce.FULL))
            cache.mkdir(parents=True, exist_ok=True)
            save_model(identified.model, path)
    return load_model(path, expect_period=period, expect_config=config)


def table(rows: list[dict]) -> pd.DataFrame:
    """One line per run (pipeline, seed, controller, scenario) with :func:`~cosim.study.optimizer_ablation.summary`'s
    columns; the fallback counts as JSON text."""
    if not rows:
        return pd.DataFrame()
    records = []
    for r in rows:
        record = summary(r)
        record["fallbacks"] = json.dumps(record["fallbacks"], sort_keys=True)
        records.append(record)
    frame = pd.DataFrame.from_records(records)
    first = ["pipeline", "seed", "controller", "scenario"]
    return frame[first + [c for c in frame.columns if c not in first]]


def _spread(values: list[float]) -> str:
    values = [v for v in values if math.isfinite(v)]
    if not values:
        return "--"
    return f"{min(values):.4f} / {float(np.median(values)):.4f} / {max(values):.4f}"


def report(rows: list[dict], complete: bool, command: str) -> str:
    """The markdown summary of the rows: per pipeline and controller, and over all, the spread of the IAE ratio
    (min / median / max over seeds and scenarios), the worst start-up overshoot increase, the plan-cost excess
    pooled over every RTI sample (median, worst), the search's share of the samples, and issue 24's verdict."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["pipeline"], r["controller"]), []).append(r)
    lines = [f"# The RTI against the search on every seed{'' if complete else ' (INCOMPLETE: the run was stopped)'}",
             "", f"Command: `{command}`. Per run: `{TABLE_NAME}` (one line per pipeline, seed, controller and scenario).",
             "Targets for the RTI (issue 24): closed-loop IAE at most "
             f"{IAE_RATIO_TARGET:g} x the search's on the same model, start-up overshoot at most "
             f"{OVERSHOOT_POINTS_TARGET:g} points above it, and the eq. 16 cost of the RTI's plan within "
             f"{100 * COST_EXCESS_TARGET:g} % of the best the search finds for the same problem at the median RTI "
             "sample (pooled over all RTI samples of the runs; negative: the RTI plans better); beside the worst sample's "
             "excess, the search's plan cost there (eq. 16's discounted sum [V]: near zero, a large ratio is a small "
             "difference). IAE ratios are min / median / max over the seeds and scenarios.", "",
             "| pipeline | controller | seeds | runs | IAE RTI / search | start-up overshoot increase, worst "
             "[points] | plan cost excess median / worst [%] (the search's plan cost there [V]) | samples planned by the "
             "search [%] | meets |",
             "|---|---|---|---|---|---|---|---|---|"]

    def line(pipeline: str, controller: str, subset: list[dict]) -> str:
        v = verdict(subset)
        seeds = sorted({r["seed"] for r in subset})
        startup = v["startup_overshoot_increase_points_worst"][0]
        searched = 100 * sum(r["search_samples"] for r in subset) / max(1, sum(r["samples"] for r in subset))
        audited = math.isfinite(v["cost_excess_median"][0])
        meets = all(met for met in (v["iae_ratio_worst"][1], v["startup_overshoot_increase_points_worst"][1],
                                    v["cost_excess_median"][1] or not audited))
        worst = max(subset, key=lambda r: r["cost_excess_worst"] if math.isfinite(r["cost_excess_worst"]) else -math.inf)
        cost = (f"{100 * v['cost_excess_median'][0]:+.2f} / {100 * v['cost_excess_worst'][0]:.1f} (the search's plan: "
                f"{worst['search_cost_at_worst']:.2g})" if audited else "not audited")
        return (f"| {pipeline} | {controller} | {', '.join(map(str, seeds))} | {len(subset)} | "
                f"{_spread([r['iae_ratio'] for r in subset])} | {startup:+.2f} | {cost} | {searched:.1f} | "
                f"{('yes' if audited else 'yes (IAE, overshoot)') if meets else '**no**'} |")

    for (pipeline, controller), subset in groups.items():
        lines.append(line(pipeline, controller, subset))
    if rows:
        lines.append(line("**all**", "all", rows))
    return "\n".join(lines) + "\n"


def write_tables(out_dir: Path, rows: list[dict], complete: bool, command: str) -> None:
    """``out_dir/optimizer-every-seed.csv`` and ``.md`` (atomic writes; the markdown says when the rows are
    incomplete, as after each run while the evaluation goes on)."""
    out_dir = Path(out_dir)
    frame = table(rows)
    atomic_write(out_dir / TABLE_NAME, lambda tmp: frame.to_csv(tmp, index=False, float_format="%.10g"))
    atomic_write_text(out_dir / REPORT_NAME, report(rows, complete, command))
