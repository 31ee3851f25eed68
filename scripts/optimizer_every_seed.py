"""The every-seed evaluation of the real-time iteration against the search (issue 24's quality targets).

Runs :func:`cosim.study.optimizer_every_seed.every_seed`: the NNPC of every study seed and the MPC baselines on
every pipeline of the seed study, both rates, each with the search and with the RTI (its C twins, as the
study runs them), and prints one line per run and the targets' verdict per pipeline and over all; with --out,
writes ``optimizer-every-seed.csv`` (one line per run) and ``optimizer-every-seed.md`` (the verdict with the
spread over seeds) there, after every run (marked incomplete until the last). Needs the reproduction's models
and PI tunings in RESULTS (``make reproduce``); the seeds' models are identified once and kept in CACHE. About
three minutes on two cores with the audit, the seeds' identification on a first run included; run it niced.
``make every-seed`` runs it on everything and writes results/.

    nice ./.venv/bin/python scripts/optimizer_every_seed.py [--results results] [--cache ~/.cache/buck-cosim/every-seed]
        [--pipelines TAG,...] [--seeds 0,1,...] [--no-audit] [--out DIR] [--rti FIELD=VALUE ...]

Exit codes: 0 done, 2 bad arguments (one line, before any simulation).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cosim  # noqa: F401  (first: pins the numeric kernels before numpy and torch load)


def main(argv: list[str]) -> int:
    from controllers.native import cache_dir
    from cosim.design.experiments import rti_changes
    from cosim.study.optimizer_ablation import verdict
    from cosim.study.optimizer_every_seed import every_seed, write_tables

    parser = argparse.ArgumentParser(prog="optimizer_every_seed.py", description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, default=Path("results"),
                        help="the reproduction's results folder: its models/ and PI tunings (default: results)")
    parser.add_argument("--cache", type=Path, default=cache_dir() / "every-seed",
                        help="where the seeds' identified networks are kept between runs")
    parser.add_argument("--pipelines", default="", help="comma-separated pipeline tags (default: all)")
    parser.add_argument("--seeds", default="", help="comma-separated seeds (default: the study's)")
    parser.add_argument("--no-audit", action="store_true", help="skip the per-sample search (no plan-cost excess)")
    parser.add_argument("--out", type=Path, help="write optimizer-every-seed.csv and .md into this folder (after every "
                                                 "run; the .md says incomplete until the last)")
    parser.add_argument("--rti", action="append", default=[], metavar="FIELD=VALUE",
                        help="an RtiSettings field of the RTI runs changed from each rate's setting, e.g. iterations=2, "
                             "line_search=false, regularization=1e-2 (repeatable)")
    args = parser.parse_args(argv)
    from cosim.study import reproduce

    try:
        changes = rti_changes(args.rti)
    except ValueError as error:
        parser.error(str(error))
    tags = [p.tag for p in reproduce.PIPELINES]
    for tag in filter(None, args.pipelines.split(",")):
        if tag not in tags:
            parser.error(f"--pipelines: {tag!r} is not a pipeline of the reproduction (expected one of {', '.join(tags)})")
    for text in filter(None, args.seeds.split(",")):
        if not text.strip().isdigit() or int(text) not in reproduce.FULL.seeds:
            parser.error(f"--seeds: {text!r} is not a study seed (expected some of "
                         f"{', '.join(map(str, reproduce.FULL.seeds))})")
    if not (args.results / "models").is_dir():
        parser.error(f"--results {args.results}: no models folder there (run make reproduce first)")
    command = "scripts/optimizer_every_seed.py " + " ".join(argv)
    save = (lambda rows: write_tables(args.out, rows, complete=False, command=command.strip())) if args.out else None
    rows = every_seed(args.results, args.cache, pipelines=args.pipelines.split(",") if args.pipelines else None,
                      seeds=tuple(int(s) for s in args.seeds.split(",")) if args.seeds else None,
                      audit=not args.no_audit, log=lambda line: print(line, flush=True), rti_changes=changes,
                      on_row=save)
    if args.out:
        write_tables(args.out, rows, complete=True, command=command.strip())
    for key, (value, met) in verdict(rows).items():
        print(f"all: {key} = {value:.4g} ({'met' if met else 'NOT met'})")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
