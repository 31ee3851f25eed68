"""The benchmark suite: speed claims measured as medians, p99 and same-run ratios.

``buck-cosim bench`` writes ``results/benchmarks.md`` and ``results/benchmarks.csv`` (``--out``). Absolute
times drift on shared machines, so every comparison is a ratio measured within one run, with
interleaved repetitions. ``--quick`` runs each benchmark once on a tiny size (the CI smoke test).
The groups that time the reproduction's trained models read them from the ``models`` folder of the
results folder written to (``--out``; ``--models`` names another), never from the working directory.

One module per group (its ``bench_*`` function and the helpers only it uses); :mod:`.common` holds
the row and the timing, :mod:`.subjects` what several groups time, :mod:`.suite` the group registry
and the table writing.
"""

from __future__ import annotations

from cosim.benchmarks.common import BenchRow
from cosim.benchmarks.suite import BENCHMARKS, machine_info, run_benchmarks, write_benchmarks

__all__ = ["BENCHMARKS", "BenchRow", "machine_info", "run_benchmarks", "write_benchmarks"]
