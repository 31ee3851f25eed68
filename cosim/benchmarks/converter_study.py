"""Group converter-study: ``buck-cosim study`` of the second converter (examples/pol_buck/, on the workbench's C plant)
end to end, the default study and ``--quick``, each against its wall-clock budget on 2 cores."""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

from cosim.benchmarks.common import BenchRow

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "pol_buck" / "pol_builtin.toml"


def _timed_study(folder: Path, quick: bool, **plan_options) -> tuple[float, int]:
    """One study of the example into ``folder``/study (the FMU its binding names built there), timed: its wall time
    [s] and the runs it made."""
    import pandas as pd

    from cosim.study.converter_study import plan_study, run_study
    from plant_fmu import fmu_path

    binding = folder / EXAMPLE.name
    if not binding.is_file():
        shutil.copy(EXAMPLE, binding)
        (folder / "build").mkdir(exist_ok=True)
        shutil.copy(fmu_path(), folder / "build" / "BuckConverter.fmu")
    out = folder / ("quick" if quick else "default")
    start = time.perf_counter()
    run_study(plan_study(binding, quick=quick, **plan_options), out, workers=2)
    elapsed = time.perf_counter() - start
    return elapsed, len(pd.read_csv(out / "metrics" / "metrics_all.csv"))


def bench_converter_study(quick: bool) -> list[BenchRow]:
    """The default study (both of the spec's rates, five seeds) and the quick one (two seeds, smaller sizes); with
    ``quick`` (the suite's smoke test) only the quick one, at one switching period and one seed."""
    from cosim.study.converter_study import QUICK_STUDY_BUDGET_S, STUDY_BUDGET_S

    rows = []
    with tempfile.TemporaryDirectory(prefix="buck-bench-study-") as tmp:
        folder = Path(tmp)
        if not quick:
            seconds, runs = _timed_study(folder, quick=False)
            rows.append(BenchRow("converter study of the second converter (buck-cosim study --plant "
                                 "examples/pol_buck/pol_builtin.toml), 2 workers", seconds, None, "s",
                                 f"<= {STUDY_BUDGET_S:g} s on 2 cores", seconds <= STUDY_BUDGET_S,
                                 f"{runs} runs: both rates, 5 seeds"))
        options = {"control_periods": (1e-5,), "seeds": 1} if quick else {}
        seconds, runs = _timed_study(folder, True, **options)
        scope = ", smoke size: one rate, one seed" if quick else ""
        rows.append(BenchRow(f"quick converter study of the second converter (buck-cosim study --quick{scope}), "
                             "2 workers", seconds, None, "s", f"<= {QUICK_STUDY_BUDGET_S:g} s on 2 cores",
                             seconds <= QUICK_STUDY_BUDGET_S, f"{runs} runs"))
    return rows
