"""The explicit NNPC on every identification seed (its targets: IAE <= 1.05 x the online NNPC's, start-up overshoot
<= 5 %, steady-state error <= 0.2 %).

Runs :func:`cosim.study.explicit_every_seed.every_seed`: for each pipeline at one switching period and each study
seed, the NNPC identified from that seed's data and the explicit NNPC distilled from it (seed 0: the reproduction's
policy; the others distilled here with the reproduction's budget -- about a minute per plant and seed on an idle core
(55-65 s in results/timings.md), about 2.5 min on a shared one -- and kept in CACHE), both on the paper's four
scenarios; prints a line per (pipeline, seed) and writes, with --out, ``explicit-every-seed.csv`` (one line per
run) and ``explicit-every-seed.md`` (each target over the seeds, with the spread) after every job (marked incomplete
until the last). With ``--expert-optimizer search`` the search's plans label the states instead of the RTI's (the
reproduction's), every seed (0 too) is distilled here and the tables are ``explicit-every-seed-search-labels.*``:
the labels' A/B. Needs the
reproduction's results in RESULTS (``make reproduce``). About 16 minutes on two cores on a first run (twelve
distillations), under a minute after. ``make every-seed`` runs it and writes results/.

    nice ./.venv/bin/python scripts/explicit_every_seed.py [--results results] [--cache ~/.cache/buck-cosim/every-seed]
        [--pipelines TAG,...] [--seeds 0,1,...] [--workers N] [--expert-optimizer {rti,search}] [--out DIR]

Exit codes: 0 done, 2 bad arguments or results (one line, before any simulation).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cosim  # noqa: F401  (first: pins the numeric kernels before numpy and torch load)


def main(argv: list[str]) -> int:
    from controllers.native import cache_dir
    from cosim.base.errors import ConfigError
    from cosim.design.vocabulary import OPTIMIZERS
    from cosim.study.explicit_every_seed import every_seed, fast_pipelines, file_names, verdict, write_tables

    parser = argparse.ArgumentParser(prog="explicit_every_seed.py", description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, default=Path("results"),
                        help="the reproduction's results folder: its models/ (networks, seed 0's policies) and PI "
                             "tunings (default: results)")
    parser.add_argument("--cache", type=Path, default=cache_dir() / "every-seed",
                        help="where the seeds' identified networks and distilled policies are kept between runs")
    parser.add_argument("--pipelines", default="", help="comma-separated pipeline tags at one switching period "
                                                        "(default: all)")
    parser.add_argument("--seeds", default="", help="comma-separated seeds (default: the study's)")
    parser.add_argument("--workers", type=int, default=None, help="local worker processes (default: one per core)")
    parser.add_argument("--expert-optimizer", choices=OPTIMIZERS, default=None,
                        help="the optimizer of the online NNPC that labels the distillation's states (default: the "
                             "reproduction's, the RTI; another distills every seed, 0 too, and names the tables "
                             "explicit-every-seed-<optimizer>-labels.*)")
    parser.add_argument("--out", type=Path, help=f"write {file_names(None)[1]} and its CSV into this folder (after "
                                                 "every job; the .md says incomplete until the last)")
    args = parser.parse_args(argv)
    tags = [p.tag for p in fast_pipelines()]
    chosen = [t.strip() for t in args.pipelines.split(",") if t.strip()] or None
    for tag in chosen or []:
        if tag not in tags:
            parser.error(f"--pipelines: {tag!r} is not a pipeline of the reproduction at one switching period "
                         f"(expected one of {', '.join(tags)})")
    study_seeds = sorted({s for p in fast_pipelines() for s in p.study_seeds})
    seeds = None
    if args.seeds:
        seeds = []
        for text in args.seeds.split(","):
            if not text.strip().isdigit() or int(text) not in study_seeds:
                parser.error(f"--seeds: {text!r} is not a study seed (expected some of "
                             f"{', '.join(map(str, study_seeds))})")
            seeds.append(int(text))
        seeds = tuple(seeds)
    if args.workers is not None and args.workers < 1:
        parser.error(f"--workers {args.workers}: expected at least 1")
    for pipeline in fast_pipelines(chosen):
        for name in (f"{pipeline.tag}__nnpc.pt", f"{pipeline.tag}__nnpc-explicit.pt"):
            if not (args.results / "models" / name).is_file():
                parser.error(f"--results {args.results}: no models/{name} there (run make reproduce first)")
    command = ("scripts/explicit_every_seed.py " + " ".join(argv)).strip()
    save = (lambda rows: write_tables(args.out, rows, complete=False, command=command,
                                      expert_optimizer=args.expert_optimizer)) if args.out else None
    try:
        rows = every_seed(args.results, args.cache, pipelines=chosen, seeds=seeds, workers=args.workers,
                          log=lambda line: print(line, flush=True), on_rows=save,
                          expert_optimizer=args.expert_optimizer)
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if args.out:
        write_tables(args.out, rows, complete=True, command=command, expert_optimizer=args.expert_optimizer)
    for tag in dict.fromkeys(r["pipeline"] for r in rows):
        for line in verdict([r for r in rows if r["pipeline"] == tag]):
            print(f"{tag}: {line['target']}: {'met' if line['met'] else 'NOT met'} for every seed "
                  f"(min / median / max {' / '.join(f'{v:.3g}' for v in line['spread'])}"
                  + (f"; missed by seed {', '.join(map(str, line['missed']))})" if line["missed"] else ")"))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
