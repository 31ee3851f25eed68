"""The every-seed evaluation of the real-time iteration against the search (issue 24's quality targets).

:func:`every_seed` runs :func:`cosim.study.optimizer_ablation.compare` for the NNPC of every study seed and the MPC
baselines on every pipeline of the reproduction. It builds on the reproduction's recipe and files, so it lives
beside it rather than in :mod:`cosim.study.optimizer_ablation` (which the reproduction imports): nothing in the
workbench imports this module; ``scripts/optimizer_every_seed.py`` runs it.
"""

from __future__ import annotations

import re
from dataclasses import fields
from pathlib import Path
from typing import Callable

from controllers.predictive import RtiSettings
from cosim.study.optimizer_ablation import compare, verdict, with_rti


def every_seed(out_dir: Path, cache: Path, pipelines: list[str] | None = None, seeds: tuple[int, ...] | None = None,
               audit: bool = True, log: Callable[[str], None] = print, rti_changes: dict | None = None) -> list[dict]:
    """The every-seed evaluation issue 24 asks before the RTI may be the default: :func:`compare` for the NNPC
    identified from every study seed's data on the nominal plants (seed 0: the reproduction's model in
    ``out_dir/models``; the other seeds identified here with the reproduction's recipe and PI, and kept in
    ``cache``, so a rerun only simulates), and for the MPC baselines (the oracle and the mismatched model: no
    identification, seed 0) on every pipeline, both rates. Each row carries ``pipeline``, ``seed`` and its
    controller; :func:`verdict` of the rows of a pipeline or of all is the table the docs quote
    (``scripts/optimizer_every_seed.py`` prints it). ``rti_changes``: :class:`~controllers.predictive.RtiSettings`
    fields changed from each rate's defaults for the RTI runs (e.g. ``{"iterations": 2}``: a candidate default
    evaluated before it becomes one)."""
    from controllers.nn_model import load_model, save_model
    from cosim.study import envelope, reproduce
    from cosim.study.experiments import model_mpc, network_region, nn_configs, nnpc, scenarios_for
    from cosim.study.identification import identify
    from cosim.study.vocabulary import MISMATCH, MPC_MISMATCHED, MPC_NOMINAL, MPC_ORACLE, NNPC, NOMINAL, PLANT_VARIANTS

    rows: list[dict] = []
    for pipeline in reproduce.PIPELINES:
        if pipelines is not None and pipeline.tag not in pipelines:
            continue
        period, binding = pipeline.control_period, pipeline.binding()
        scenarios = scenarios_for(period)
        study_seeds = reproduce.FULL.seeds if pipeline.seed_study else (0,)
        for seed in [s for s in study_seeds if seeds is None or s in seeds]:
            config = nn_configs(period)["nnpc"]
            if seed == 0:
                path = out_dir / "models" / f"{pipeline.tag}__nnpc.pt"
            elif pipeline.tag == envelope.pipeline_tag(envelope.MAP_PLANT, envelope.SWITCHING_PERIOD):
                path = envelope.seed_model_path(out_dir, seed)  # the reproduction's seed job wrote it
            else:  # named by the network and its data region, so a cache of another recipe is not taken for it
                region = network_region("nnpc", period)
                path = cache / f"{pipeline.tag}__seed{seed}__nnpc__{re.sub(r'[^A-Za-z0-9]+', '_', config.label)}__{region}.pt"
                if not path.is_file():
                    pi = reproduce._tuned(pipeline, out_dir, reproduce.FULL)
                    identified = identify(binding, pi.controller(), period, config, seed,
                                          reproduce._recipe(reproduce.FULL))
                    cache.mkdir(parents=True, exist_ok=True)
                    save_model(identified.model, path)
            model = load_model(path, expect_period=period, expect_config=config)
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


def rti_changes(items: list[str]) -> dict:
    """``["iterations=2", "line_search=false"]`` -> ``{"iterations": 2, "line_search": False}``, each value of its
    :class:`~controllers.predictive.RtiSettings` field's type; ValueError names a field or value that is not."""
    types = {f.name: type(getattr(RtiSettings(), f.name)) for f in fields(RtiSettings)}
    changes = {}
    for item in items:
        name, _, text = item.partition("=")
        if name not in types:
            raise ValueError(f"--rti {item}: {name!r} is not an RTI setting (expected one of {', '.join(types)})")
        kind = types[name]
        if kind is bool:
            if text.lower() not in ("true", "false"):
                raise ValueError(f"--rti {item}: expected true or false")
            changes[name] = text.lower() == "true"
        else:
            try:
                changes[name] = kind(text)
            except ValueError:
                raise ValueError(f"--rti {item}: expected {'an integer' if kind is int else 'a number'}") from None
    RtiSettings(**changes)  # its own checks (ranges), before any simulation
    return changes
