"""Groups reproduction (end to end with the C and the Python controllers, and the quality ratios of that very run)
and reproduction-optimizer (end to end with the RTI and with the search as the predictive controllers' default)."""

from __future__ import annotations

import time
from pathlib import Path

import pandas as pd

from cosim.benchmarks.common import BenchRow
from cosim.study.vocabulary import MPC_ORACLE, NNPC, PAPER_PERIOD, PI

#: what --quick names in the rows: the suite's smoke test runs one 1 ms pipeline of the quick profile
SMOKE_SCOPE = ", smoke profile: one 1 ms pipeline of --quick"


def _profile(quick: bool):
    """The reproduction's profile for a bench run: the full one, or with --quick (the suite's smoke test) one 1 ms
    pipeline of the quick profile, no seed jobs, ablations or drift study (the rows exist and are computed; the
    numbers mean nothing)."""
    from dataclasses import replace

    from cosim.study.reproduce import FULL, QUICK

    return replace(QUICK, pipelines=("nominal-averaged__1ms",), seeds=(0,), drift=False,
                   ablations=False) if quick else FULL


#: --quick's reproductions by their effective options: the smoke test's groups reproduction and
#: reproduction-optimizer both time the default reproduction (C controllers, the RTI), which then runs once
_QUICK_RUNS: dict[tuple, tuple[float, pd.DataFrame]] = {}


def _timed_reproduction(quick: bool, read_metrics: bool = False, **options) -> tuple[float, pd.DataFrame | None]:
    """Seconds of one whole reproduction (2 workers, into a temporary folder, ``options`` to ``reproduce``), and its
    metrics table if asked for (read before the folder goes). With ``quick`` a reproduction with the same effective
    options as an earlier one in this process is not run again (its numbers mean nothing there; the smoke test
    checks that the rows are computed); a full bench run times every reproduction it reports."""
    import tempfile

    from cosim.study.experiments import DEFAULT_OPTIMIZER
    from cosim.study.reproduce import reproduce
    from cosim.study.vocabulary import DEFAULT_IMPLEMENTATION

    key = (options.get("implementation", DEFAULT_IMPLEMENTATION), options.get("optimizer", DEFAULT_OPTIMIZER),
           tuple(sorted((k, v) for k, v in options.items() if k not in ("implementation", "optimizer"))))
    if quick and key in _QUICK_RUNS:
        elapsed, metrics = _QUICK_RUNS[key]
        return elapsed, metrics if read_metrics else None
    with tempfile.TemporaryDirectory(prefix="buck-bench-") as tmp:
        start = time.perf_counter()
        reproduce(Path(tmp), workers=2, profile=_profile(quick), **options)
        elapsed = time.perf_counter() - start
        metrics = pd.read_csv(Path(tmp) / "metrics" / "metrics_all.csv")
    if quick:
        _QUICK_RUNS[key] = (elapsed, metrics)
    return elapsed, metrics if read_metrics else None


def bench_reproduction(quick: bool) -> list[BenchRow]:
    from cosim.base.labels import period_label

    # the same reproduction, controllers in Python and in C
    times = {"python": _timed_reproduction(quick, implementation="python")[0]}
    times["c"], metrics = _timed_reproduction(quick, read_metrics=True, implementation="c")
    elapsed = times["c"]
    ratio = times["c"] / times["python"]
    command = "buck-cosim reproduce"
    scope = SMOKE_SCOPE if quick else ""
    rows = [BenchRow(f"end-to-end reproduction ({command}{scope}), 2 workers, controllers as their C twins (the "
                     "default)", elapsed, None, "s", "<= 120 s on 2 cores", elapsed <= 120.0),
            BenchRow(f"end-to-end reproduction ({command} --implementation python{scope}), 2 workers",
                     times["python"], None, "s"),
            BenchRow("reproduction time with the C controllers / with the Python controllers (same run)", ratio, None,
                     "ratio", "<= 0.4", ratio <= 0.4,
                     "with the real-time iteration the predictive controllers' default, the controllers are a small "
                     "part of either run, whose time goes mostly to what both share: the identification and "
                     "distillation trainings (torch; stages per job: timings.md; per-step costs: group "
                     "c-controllers)")]
    for pipeline in sorted(set(metrics["pipeline"]), key=lambda p: (("13p33us" in p), p)):
        if not pipeline.startswith("nominal"):
            continue
        m = metrics[metrics["pipeline"] == pipeline]
        for scenario in dict.fromkeys(m["scenario"]):
            iae = m[m["scenario"] == scenario].set_index("controller")["iae_Vs"]
            if {NNPC, MPC_ORACLE, PI} <= set(iae.index):
                rate = pipeline.split("__")[1]
                slow = rate == period_label(PAPER_PERIOD)
                target = "<= 1.10" if slow else ""
                ratio = iae[NNPC] / iae[MPC_ORACLE]
                rows.append(BenchRow(f"NNPC IAE / oracle-MPC IAE, {scenario}, {pipeline}", ratio, None, "ratio",
                                     target, ratio <= 1.10 if target else None))
                ratio = iae[NNPC] / iae[PI]
                target = "<= 0.6" if not slow else ""
                rows.append(BenchRow(f"NNPC IAE / PI IAE, {scenario}, {pipeline}", ratio, None, "ratio", target,
                                     ratio <= 0.6 if target else None))
    return rows


def bench_reproduction_optimizer(quick: bool) -> list[BenchRow]:
    """Issue 24's "make reproduce with the new optimizer <= 0.5 x its time with the old one, in one bench run": the
    reproduction (C controllers, 2 workers, into a temporary folder) with the RTI as the predictive controllers'
    default and again with the search as their default (``reproduce(optimizer=...)``), one after the other."""
    times = {optimizer: _timed_reproduction(quick, optimizer=optimizer)[0] for optimizer in ("rti", "search")}
    scope = SMOKE_SCOPE if quick else ""
    ratio = times["rti"] / times["search"]
    return [BenchRow(f"end-to-end reproduction, the RTI the predictive controllers' default (as make reproduce){scope}",
                     times["rti"], None, "s"),
            BenchRow(f"end-to-end reproduction, the search the predictive controllers' default{scope}",
                     times["search"], None, "s",
                     note="controllers given an optimizer of their own keep it either way: the optimizer ablation's "
                          "pairs, the paper's 3-7-2 NNPC (the search), the distillation's expert (the search)"),
            BenchRow("reproduction time with the RTI / with the search (same run)", ratio, None, "ratio", "<= 0.5",
                     ratio <= 0.5, "issue 24's target; the runs of both are the same jobs, seeds and sizes")]
