"""The benchmark suite: speed claims measured as medians, p99 and same-run ratios.

``buck-cosim bench`` writes ``results/benchmarks.md`` and ``results/benchmarks.csv``. Absolute
times drift on shared machines, so every comparison is a ratio measured within one run, with
interleaved repetitions. ``--quick`` runs each benchmark once on a tiny size (the CI smoke test).
"""

from __future__ import annotations

import os
import platform
import shutil
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from cosim.results import atomic_write, atomic_write_text, package_versions


@dataclass
class BenchRow:
    benchmark: str
    median: float
    p99: float | None
    unit: str
    target: str = ""
    meets_target: bool | None = None
    note: str = ""
    extra: dict = field(default_factory=dict)


def machine_info() -> dict[str, str]:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": str(os.cpu_count()), "system": f"{platform.system()} {platform.release()}",
            "python": platform.python_version()}


def _p99(values) -> float:
    return float(np.percentile(values, 99))


# ---------------------------------------------------------------------------------------------
# 1. plant FMU doStep cost


class _RawSlave:
    """The built-in FMU through fmpy's public API only: the floor the master is compared with."""

    def __init__(self, start_values: dict):
        import fmpy
        from fmpy.fmi2 import FMU2Slave

        from plant_fmu import fmu_path

        path = str(fmu_path())
        self.md = fmpy.read_model_description(path)
        self.vr = {v.name: v.valueReference for v in self.md.modelVariables}
        self.unzipdir = fmpy.extract(path)
        self.fmu = FMU2Slave(guid=self.md.guid, unzipDirectory=self.unzipdir,
                             modelIdentifier=self.md.coSimulation.modelIdentifier)
        self.fmu.instantiate()
        self.fmu.setupExperiment(startTime=0.0)
        for name, value in start_values.items():
            if name == "plant_mode":
                self.fmu.setInteger([self.vr[name]], [value])
            else:
                self.fmu.setReal([self.vr[name]], [value])
        self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()

    def close(self):
        self.fmu.terminate()
        self.fmu.freeInstance()
        shutil.rmtree(self.unzipdir, ignore_errors=True)


def _time_do_steps(mode: int, step: float, count: int) -> np.ndarray:
    slave = _RawSlave({"plant_mode": mode, "duty_cycle": 0.25})
    do_step = slave.fmu.dll.fmi2DoStep  # the C function itself: the FMU's cost, not Python's
    component = slave.fmu.component
    times = np.empty(count)
    t = 0.0
    try:
        for i in range(count):
            start = time.perf_counter_ns()
            do_step(component, t, step, 1)
            times[i] = time.perf_counter_ns() - start
            t = (i + 1) * step
    finally:
        slave.close()
    return times * 1e-9


def bench_plant(quick: bool) -> list[BenchRow]:
    n = 3 if quick else 400
    periods_per_ms = 75
    switched = _time_do_steps(1, 1e-3, n) / periods_per_ms
    single = _time_do_steps(1, 1 / 75e3, n * 10)
    averaged = _time_do_steps(0, 1e-3, n)
    return [
        BenchRow("plant doStep, switched mode, per simulated switching period (1 ms steps / 75)",
                 float(np.median(switched)) * 1e6, _p99(switched) * 1e6, "us",
                 "<= 1 us per switching period", bool(np.median(switched) <= 1e-6),
                 "exact piecewise solution: 2 closed-form intervals per period"),
        BenchRow("plant doStep, switched mode, one switching period per call (incl. ctypes call)",
                 float(np.median(single)) * 1e6, _p99(single) * 1e6, "us"),
        BenchRow("plant doStep, averaged mode, per 1 ms step (incl. ctypes call)",
                 float(np.median(averaged)) * 1e6, _p99(averaged) * 1e6, "us"),
    ]


# ---------------------------------------------------------------------------------------------
# 2. master overhead against the raw fmpy floor


class _Constant:
    name = "constant"
    duty_limits = (0.0, 1.0)

    def __init__(self, period):
        self.sample_period = period

    def reset(self):
        pass

    def step(self, measurement):
        return 0.25

    def describe(self):
        return {"type": "constant", "name": self.name, "duty_limits": [0.0, 1.0]}


def _raw_floor(step: float, count: int) -> float:
    """Seconds per macro step of the bare loop: fmpy setReal + doStep + getReal."""
    slave = _RawSlave({"plant_mode": 0})
    vr = slave.vr
    inputs, outputs = [vr["duty_cycle"]], [vr["output_voltage"], vr["inductor_current"], vr["load_current"]]
    fmu = slave.fmu
    try:
        start = time.perf_counter()
        for i in range(count):
            fmu.setReal(inputs, [0.25])
            fmu.doStep(i * step, step)
            fmu.getReal(outputs)
        return (time.perf_counter() - start) / count
    finally:
        slave.close()


def _master_step(step: float, count: int) -> float:
    from cosim.binding import builtin_binding
    from cosim.fmu_plant import FmuPlant
    from cosim.master import run
    from cosim.scenarios import parse_scenario

    scenario = parse_scenario(f'name = "bench"\nduration = {count * step!r}\n[initial]\nreference = 12.0\n')
    with FmuPlant(builtin_binding("averaged")) as plant:
        start = time.perf_counter()
        result = run(plant, _Constant(step), scenario, record_period=step)
        elapsed = time.perf_counter() - start
    return elapsed / (len(result.frame) - 1)


def bench_master(quick: bool) -> list[BenchRow]:
    step = 1e-5
    count = 200 if quick else 20000
    repeats = 1 if quick else 5
    floors, masters = [], []
    for _ in range(repeats):  # interleaved, so drift hits both alike
        floors.append(_raw_floor(step, count))
        masters.append(_master_step(step, count))
    ratios = [m / f for m, f in zip(masters, floors)]
    ratio = statistics.median(ratios)
    return [
        BenchRow("raw fmpy floor: setReal + doStep + getReal per macro step (averaged, 10 us)",
                 statistics.median(floors) * 1e6, None, "us"),
        BenchRow("master per macro step (control + record every 10 us, constant controller)",
                 statistics.median(masters) * 1e6, None, "us"),
        BenchRow("master overhead ratio: master / raw fmpy floor (median of interleaved repeats)",
                 ratio, max(ratios), "ratio", "<= 1.5", bool(ratio <= 1.5),
                 "p99 column: worst repeat"),
    ]


# ---------------------------------------------------------------------------------------------

BENCHMARKS: dict[str, Callable[[bool], list[BenchRow]]] = {
    "plant": bench_plant,
    "master": bench_master,
}


def run_benchmarks(out_dir: Path, quick: bool = False, only: list[str] | None = None,
                   command: str = "buck-cosim bench") -> tuple[Path, Path]:
    rows: list[BenchRow] = []
    for name, function in BENCHMARKS.items():
        if only and name not in only:
            continue
        print(f"benchmark: {name} ...", file=sys.stderr)
        rows.extend(function(quick))
    return write_benchmarks(rows, Path(out_dir), quick, command)


def write_benchmarks(rows: list[BenchRow], out_dir: Path, quick: bool, command: str) -> tuple[Path, Path]:
    machine = machine_info()
    versions = package_versions()
    frame = pd.DataFrame([{k: v for k, v in asdict(r).items() if k != "extra"} for r in rows])
    frame["machine"] = f"{machine['cpu']} ({machine['cores']} cores)"
    frame["command"] = command + (" --quick" if quick else "")
    csv_path = atomic_write(out_dir / ("benchmarks-quick.csv" if quick else "benchmarks.csv"),
                            lambda tmp: frame.to_csv(tmp, index=False))
    lines = [
        "# Benchmarks" + (" (quick smoke run: sizes too small to mean anything)" if quick else ""),
        "",
        f"Command: `{command}{' --quick' if quick else ''}`  ",
        f"Machine: {machine['cpu']}, {machine['cores']} cores, {machine['system']}, Python {machine['python']}  ",
        "Packages: " + ", ".join(f"{k} {v}" for k, v in versions.items() if k != "python"),
        "",
        "Medians over repetitions; p99 where a distribution exists. Ratios are measured within this one run.",
        "",
        "| benchmark | median | p99 | unit | target | met |",
        "|---|---:|---:|---|---|---|",
    ]
    for r in rows:
        p99 = "" if r.p99 is None else f"{r.p99:.4g}"
        met = "" if r.meets_target is None else ("yes" if r.meets_target else "**no**")
        lines.append(f"| {r.benchmark} | {r.median:.4g} | {p99} | {r.unit} | {r.target} | {met} |")
    notes = [r for r in rows if r.note]
    if notes:
        lines += ["", "Notes:", ""] + [f"- {r.benchmark}: {r.note}" for r in notes]
    md_path = atomic_write_text(out_dir / ("benchmarks-quick.md" if quick else "benchmarks.md"), "\n".join(lines) + "\n")
    return md_path, csv_path
