"""Smoke test: every benchmark runs once on a tiny size, so the suite cannot rot."""

from __future__ import annotations

import pandas as pd

from cosim.benchmarks import BENCHMARKS
from cosim.cli import main


def test_every_benchmark_runs_quickly_and_writes_both_files(tmp_path, capsys):
    assert main(["bench", "--quick", "--out", str(tmp_path)]) == 0
    table = pd.read_csv(tmp_path / "benchmarks-quick.csv")
    markdown = (tmp_path / "benchmarks-quick.md").read_text()
    assert len(table) >= len(BENCHMARKS)
    assert (table["median"] > 0).all()
    assert "master overhead ratio" in markdown and "| benchmark | median | p99 |" in markdown
    assert table["command"].iloc[0] == "buck-cosim bench --quick"
