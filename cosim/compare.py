"""Overlay runs written anywhere -- by ``buck-cosim run``, the reproduction, a sweep's traces, or a
Python controller's ``write_run`` -- in one figure, with their metrics side by side
(``buck-cosim plot`` and ``buck-cosim compare``).

A run is read from its ``.parquet`` or its ``.csv`` (with the ``.json`` beside it) by
:func:`cosim.results.read_run_file`; every file is read and checked before anything is drawn. Runs that
share a controller name are told apart by the folder (and file) they come from.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

from cosim.base.errors import ConfigError
from cosim.metrics import metrics_table
from cosim.plots import Styles, plot_scenario
from cosim.results import RunResult, read_run_file


def load_runs(paths: list[str | Path]) -> list[RunResult]:
    """The runs of ``paths`` (each a run's .parquet or .csv), checked: each a readable workbench run
    with rows. A mistake is one :class:`ConfigError` line naming the file."""
    if not paths:
        raise ConfigError("no run given: expected one or more run files (.parquet, or .csv with its .json)")
    results = []
    for text in paths:
        path = Path(text)
        result = read_run_file(path)
        if result.streamed or not len(result.frame):
            raise ConfigError(f"{path}: the run has no rows to draw")
        results.append(result)
    return results


def unlike_runs(results: list[RunResult]) -> str | None:
    """Why the runs are not a comparison of controllers alone -- they ran on different plants, scenarios or control
    periods (``"on different plants: A; B"``) -- or None."""
    differences = []
    for what, values in (("plants", [r.info.plant for r in results]), ("scenarios", [r.info.scenario for r in results]),
                         ("control periods", [f"{r.info.control_period:.6g} s" for r in results])):
        distinct = list(dict.fromkeys(values))
        if len(distinct) > 1:
            differences.append(f"on different {what}: {'; '.join(distinct)}")
    return ", ".join(differences) or None


def run_labels(results: list[RunResult], paths: list[str | Path]) -> list[str]:
    """How each run is named in the legend and the table: its controller, with its folder (and file
    stem) where several runs share a controller name."""
    names = [r.info.controller for r in results]
    labels = []
    for name, path in zip(names, paths):
        if names.count(name) == 1:
            labels.append(name)
            continue
        path = Path(path).resolve()
        folder = path.parent.parent.name if path.parent.name == "runs" else path.parent.name
        labels.append(f"{name} ({folder})")
    if len(set(labels)) < len(labels):  # same controller and folder name: the file names tell them apart
        labels = [f"{label} [{Path(p).stem}]" if labels.count(label) > 1 else label for label, p in zip(labels, paths)]
    return labels


def overlay(paths: list[str | Path], out: Path, title: str | None = None, styles: Styles | None = None) -> list[Path]:
    """The runs of ``paths`` overlaid in the run figure (:func:`cosim.plots.scenario_figure`) at ``out``
    (``out.png`` and ``out.svg``; a .png or .svg ending of ``out`` stands for the pair). Returns the written files."""
    results = load_runs(paths)
    unlike = unlike_runs(results)
    if unlike:  # the figure is drawn (its title names them), but its differences are not the controllers' alone
        print(f"warning: the runs overlaid are {unlike}: their differences are not the controllers' alone",
              file=sys.stderr)
    labels = run_labels(results, paths)
    relabelled = [relabel(r, label) for r, label in zip(results, labels)]
    if title is None:
        scenarios = sorted({r.info.scenario for r in results})
        plants = sorted({r.info.plant for r in results})
        title = f"{', '.join(scenarios)}\n{'; '.join(plants)}"
    stem = Path(out)
    stem = stem.with_suffix("") if stem.suffix.lower() in (".png", ".svg") else stem
    return plot_scenario(relabelled, stem, title=title, styles=styles)


def comparison_table(paths: list[str | Path]) -> pd.DataFrame:
    """The metrics of the runs of ``paths`` side by side, one row per run (``run``: its label, ``file``)."""
    results = load_runs(paths)
    table = metrics_table(results)
    table.insert(0, "run", run_labels(results, paths))
    table.insert(1, "file", [str(p) for p in paths])
    return table


def relabel(result: RunResult, label: str) -> RunResult:
    """The same run named ``label`` (figures name runs by their controller)."""
    from dataclasses import replace

    if label == result.info.controller:
        return result
    return RunResult(frame=result.frame, info=replace(result.info, controller=label), complete=result.complete,
                     error=result.error, details=result.details)
