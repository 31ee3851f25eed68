"""The suite: its groups in table order, running some or all of them, and writing benchmarks.md and
benchmarks.csv (a group rerun alone replaces only its own rows)."""

from __future__ import annotations

import math
import os
import platform
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Callable

import pandas as pd

from cosim.base.files import atomic_write, atomic_write_text
from cosim.benchmarks.adaptation import bench_adaptation
from cosim.benchmarks.c_controllers import bench_c_controllers
from cosim.benchmarks.common import BenchRow
from cosim.benchmarks.controller_compute import bench_controllers
from cosim.benchmarks.converter_study import bench_converter_study
from cosim.benchmarks.dompc import bench_dompc
from cosim.benchmarks.embedded import bench_embedded
from cosim.benchmarks.explicit import bench_explicit
from cosim.benchmarks.inference import bench_inference
from cosim.benchmarks.master import bench_master
from cosim.benchmarks.numeric_env import bench_numeric_env
from cosim.benchmarks.plant import bench_plant
from cosim.benchmarks.reproduction import bench_reproduction, bench_reproduction_optimizer
from cosim.benchmarks.soak import bench_soak
from cosim.benchmarks.subjects import reading_models_from
from cosim.benchmarks.sweep import bench_sweep
from cosim.benchmarks.training import bench_training
from cosim.results import package_versions

BENCHMARKS: dict[str, Callable[[bool], list[BenchRow]]] = {
    "plant": bench_plant,
    "master": bench_master,
    "controllers": bench_controllers,
    "c-controllers": bench_c_controllers,
    "adaptation": bench_adaptation,
    "do-mpc": bench_dompc,
    "explicit": bench_explicit,
    "embedded": bench_embedded,
    "training": bench_training,
    "numeric-env": bench_numeric_env,
    "inference": bench_inference,
    "reproduction": bench_reproduction,
    "reproduction-optimizer": bench_reproduction_optimizer,
    "converter-study": bench_converter_study,
    "sweep": bench_sweep,
    "soak": bench_soak,
}


def run_benchmarks(out_dir: Path, quick: bool = False, only: list[str] | None = None,
                   command: str = "buck-cosim bench", models_dir: Path | None = None) -> tuple[Path, Path]:
    """Run the benchmarks (``only``: some of them) and write the table. With ``only``, the other
    groups' rows of the existing table are kept as they were measured, each with its own command.
    Trained models are read from ``models_dir`` (default: ``out_dir/models``)."""
    command += " --quick" if quick else ""
    out_dir = Path(out_dir)
    rows: list[BenchRow] = []
    with reading_models_from(Path(models_dir) if models_dir is not None else out_dir / "models"):
        for name, function in BENCHMARKS.items():
            if only and name not in only:
                continue
            print(f"benchmark: {name} ...", file=sys.stderr)
            for row in function(quick):
                row.group, row.command, row.machine = name, command, machine_label()
                rows.append(row)
    if only:
        kept = [r for r in _read_rows(out_dir / ("benchmarks-quick.csv" if quick else "benchmarks.csv"))
                if r.group not in only]
        order = list(BENCHMARKS)
        rows = sorted(kept + rows, key=lambda r: order.index(r.group))  # stable: measured order kept
    return write_benchmarks(rows, out_dir, quick)


def _read_rows(path: Path) -> list[BenchRow]:
    """Rows of an earlier table that can be merged (those with a known group), else none."""
    try:
        frame = pd.read_csv(path, keep_default_na=False)
    except (OSError, ValueError):
        return []
    if not {"group", "command", "benchmark", "median"} <= set(frame.columns):
        return []

    def optional(value, kind):
        return None if value in ("", None) else kind(value)

    rows = []
    for r in frame.to_dict("records"):
        if r["group"] not in BENCHMARKS:
            continue
        met = r.get("meets_target")
        median = optional(r["median"], float)  # empty: a "not measured" row's NaN
        rows.append(BenchRow(str(r["benchmark"]), math.nan if median is None else median,
                             optional(r.get("p99"), float), str(r["unit"]),
                             str(r.get("target", "")), None if met in ("", None) else str(met) == "True",
                             str(r.get("note", "")), group=r["group"], command=str(r["command"]),
                             machine=str(r.get("machine", ""))))
    return rows


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


def machine_label() -> str:
    """The machine a row was measured on, as the table's ``machine`` column keeps it: CPU, cores, kernel, Python
    (the kernel tells two cloud machines with the same CPU label apart; they differed 2x in speed)."""
    machine = machine_info()
    return f"{machine['cpu']} ({machine['cores']} cores), {machine['system']}, Python {machine['python']}"


def write_benchmarks(rows: list[BenchRow], out_dir: Path, quick: bool) -> tuple[Path, Path]:
    """Write the table; each row keeps the machine that measured it (a group rerun on another machine is
    named as such in the header, whose ratios hold only within one command's rows)."""
    versions = package_versions()
    for r in rows:
        r.machine = r.machine or machine_label()
    frame = pd.DataFrame([{k: v for k, v in asdict(r).items() if k != "extra"} for r in rows])
    machines = list(dict.fromkeys(r.machine for r in rows))
    csv_path = atomic_write(out_dir / ("benchmarks-quick.csv" if quick else "benchmarks.csv"),
                            lambda tmp: frame.to_csv(tmp, index=False))
    commands = list(dict.fromkeys(r.command for r in rows))
    lines = [
        "# Benchmarks" + (" (quick smoke run: sizes too small to mean anything)" if quick else ""),
        "",
        (f"Command: `{commands[0]}`  " if len(commands) == 1 else
         "Commands: " + "; ".join(f"`{c}` ({', '.join(dict.fromkeys(r.group for r in rows if r.command == c))})"
                                  for c in commands) + " -- ratios only within one command's rows  "),
        (f"Machine: {machines[0]}  " if len(machines) == 1 else
         "Machines: " + "; ".join(f"{m} ({', '.join(dict.fromkeys(r.group for r in rows if r.machine == m))})"
                                  for m in machines) + " -- times compare only within one machine  "),
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
    lines += ["", "## What profiling changed", "",
              ("When this profiling was done, before the real-time iteration (issue 24), the end-to-end "
               "reproduction was dominated by the predictive controllers' search at one switching period (a "
               "23-step horizon, thousands of samples; where its time goes now: timings.md, written by make "
               "reproduce). cProfile showed the time in the NN rollout, the optimizer's array set-up and the model "
               "discretisation; the rows above measure each fix against the code path it replaced, in this run:"),
              "",
              "- NN inference in numpy with the normalisation folded into the weights, not torch "
              "(`speed-up of numpy over torch`);",
              "- a rollout that computes the measured history's share of the first layer once for all "
              "candidates (`speed-up of the shared-history rollout`);",
              "- the 2x2 matrix exponential in closed form instead of scipy's Pade (`speed-up of the "
              "closed-form matrix exponential`);",
              "- in the optimizer, refinement that starts from the warm start's fine lattice when the warm "
              "start wins, so steady samples take one or two batched passes (NNPC p50 vs p99 above);",
              "- in the master, outputs read as Python floats from a reused ctypes buffer and one finiteness "
              "test per row instead of numpy calls, and outputs not re-read after a duty change the FMU "
              "declares no feedthrough for (`master overhead ratio`)."]
    md_path = atomic_write_text(out_dir / ("benchmarks-quick.md" if quick else "benchmarks.md"), "\n".join(lines) + "\n")
    return md_path, csv_path
