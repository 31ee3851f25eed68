"""Group numeric-env: what the same bytes on every CPU cost, and whether they hold on another CPU.

The workbench pins the numeric kernels (cosim/base/numeric_env.py: one thread, AVX2 kernels, MKL's
compatible path) and trains with a line search whose square root is exact (controllers/lbfgs.py). Timed
here, each training in a process of its own (cosim/benchmark_harness/training_job.py, the NNPC's 1 ms
network, a fixed number of L-BFGS iterations), alternating so a busy machine slows all alike:
* the workbench as it is: pinned kernels, exact line search;
* the libraries' native kernels (``BUCK_COSIM_NUMERIC_ENV=native``: their own ISA and thread count)
  with torch's line search -- the training before issue 22;
* pinned kernels with torch's line search: the line search's own cost.
And, where QEMU's user-mode emulator is installed, the same training on an emulated CPU of another kind
(cosim/benchmark_harness/cpu_emulation.py): the weights' SHA-256 against the host's, with the exact line
search (must be equal) and with torch's (differed before: why the fix exists).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from cosim.benchmarks.common import BenchRow
from cosim.benchmarks.subjects import _benchmark_pi
from cosim.design.vocabulary import PAPER_PERIOD

JOB = "cosim.benchmark_harness.training_job"


def _environment(native: bool) -> dict:
    from cosim.base import numeric_env

    env = {k: v for k, v in os.environ.items() if k not in (*numeric_env.PINNED, numeric_env.ESCAPE)}
    if native:
        env[numeric_env.ESCAPE] = numeric_env.NATIVE
    return env


def _train(data: Path, out: Path, native: bool, line_search: str, iterations: int, emulated: str | None = None,
           timeout: float = 1800) -> dict:
    from cosim.benchmark_harness import cpu_emulation

    argv = [sys.executable, "-m", JOB, str(data), str(out), "--line-search", line_search, "--iterations",
            str(iterations)]
    if emulated:
        argv = cpu_emulation.command(argv, emulated)
    done = subprocess.run(argv, env=_environment(native), capture_output=True, text=True, timeout=timeout)
    if done.returncode != 0:
        raise RuntimeError(f"training job failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(out.read_text())


def bench_numeric_env(quick: bool) -> list[BenchRow]:
    from cosim.benchmark_harness import cpu_emulation
    from cosim.design.data_collection import CollectionSettings, collect
    from cosim.design.plants import plant_binding

    samples, iterations, repeats = (2000, 50, 1) if quick else (10_000, 200, 3)
    configurations = {"pinned kernels, exact line search (the workbench)": (False, "exact"),
                      "native kernels, torch's line search (before issue 22)": (True, "torch"),
                      "pinned kernels, torch's line search": (False, "torch")}
    times: dict[str, list[float]] = {name: [] for name in configurations}
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="buck-cosim-numeric-env-") as folder:
        data = Path(folder) / "data.parquet"
        collect(plant_binding("nominal", "averaged"), _benchmark_pi(PAPER_PERIOD),
                CollectionSettings(samples=samples)).to_parquet(data)
        for repeat in range(repeats):
            for name, (native, search) in configurations.items():
                result = _train(data, Path(folder) / "out.json", native, search, iterations)
                times[name].append(result["seconds"] / max(1, result["iterations"]) * 1e3)
                results[name] = result
        workbench, before = (next(iter(configurations)), list(configurations)[1])
        rows = [BenchRow(f"NN training ({samples} samples, {iterations} L-BFGS iterations, 4-10-2 network at 1 ms): "
                         f"ms per iteration, {name}", float(np.median(times[name])), None, "ms",
                         note=f"{repeats} run(s), alternating; {results[name]['threads']} torch thread(s)")
                for name in configurations]
        ratio = float(np.median(times[workbench]) / np.median(times[before]))
        rows.append(BenchRow("what the same bytes on every CPU cost: training time, the workbench / before issue 22",
                             ratio, None, "x", note="pinned kernels and exact line search against the native "
                                                     "kernels and torch's line search; medians of the rows above"))
        problem = cpu_emulation.problem()
        if problem:
            rows.append(BenchRow("the same weights on an emulated CPU of another kind", float("nan"), None, "",
                                 note=f"not measured: {problem}"))
            return rows
        model = cpu_emulation.contrasting_model()
        short = 5 if quick else min(iterations, 50)  # the emulator is 20-50 x slower
        # --quick (the suite's smoke test) runs the row with a target only: tests/test_numeric_env.py checks the same
        # property on a full training, and each emulated process spends most of a minute loading torch
        searches = (("exact", True),) if quick else (("exact", True), ("torch", None))
        for search, expected in searches:
            host = _train(data, Path(folder) / "host.json", False, search, short)
            there = _train(data, Path(folder) / "emulated.json", False, search, short, emulated=model)
            same = host["weights_sha256"] == there["weights_sha256"]
            rows.append(BenchRow(f"the same weights on an emulated {cpu_emulation.DESCRIPTIONS[model]}, pinned "
                                 f"kernels, {'the exact' if search == 'exact' else 'torch' + chr(39) + 's'} line search "
                                 f"({short} iterations): 1 = identical", float(same), None, "",
                                 "identical" if expected else "", same if expected else None,
                                 f"weights SHA-256 {there['weights_sha256'][:12]} there, {host['weights_sha256'][:12]} "
                                 f"here; emulated training {there['seconds']:.0f} s"
                                 + ("" if expected else " -- torch's line search takes torch.sqrt, whose last bits "
                                                        "depend on the CPU (controllers/lbfgs.py)")))
    return rows
