"""The ``bench`` command: the benchmark suite of :mod:`cosim.benchmarks`."""

from __future__ import annotations

from pathlib import Path

from cosim.base.errors import ConfigError
from cosim.cli.options import DEFAULT_RESULTS, output_dir


def cmd_bench(args) -> int:
    from cosim.benchmarks import BENCHMARKS, run_benchmarks

    unknown = [name for name in args.only or [] if name not in BENCHMARKS]
    if unknown:
        raise ConfigError(f"unknown benchmark(s) {', '.join(unknown)}: expected {', '.join(BENCHMARKS)}")
    output_dir(args.out)
    command = "buck-cosim bench" + "".join(f" --only {n}" for n in args.only or [])
    models = Path(args.models) if args.models else None
    if models is not None and not models.is_dir():
        raise ConfigError(f"--models {args.models}: no such folder (expected the models folder of a reproduction)")
    md_path, csv_path = run_benchmarks(Path(args.out), quick=args.quick, only=args.only, command=command,
                                       models_dir=models)
    print(md_path.read_text())
    print(f"wrote {md_path} and {csv_path}")
    return 0


def add_bench_parser(sub) -> None:
    p = sub.add_parser("bench", help="run the benchmark suite; write results/benchmarks.md and .csv",
                       description="Measure plant, master and controller costs as medians, p99 and same-run "
                                   "ratios; write benchmarks.md and benchmarks.csv.")
    p.add_argument("--quick", action="store_true",
                   help="run each benchmark once on a tiny size (smoke test; writes benchmarks-quick.*)")
    p.add_argument("--only", action="append", metavar="NAME", help="run only this benchmark (repeatable)")
    p.add_argument("--out", default=str(DEFAULT_RESULTS), metavar="DIR", help="output folder (default: results)")
    p.add_argument("--models", metavar="DIR", default=None,
                   help="the reproduction's trained models to time (default: OUT/models, beside the tables written)")
    p.set_defaults(func=cmd_bench)
