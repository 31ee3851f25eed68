"""Look-ups in the reproduction's metrics table and Markdown tables, shared by the report, the
targets and the timings (the one place that formats a number for them)."""

from __future__ import annotations

import math

import pandas as pd

from cosim.study.vocabulary import NNPC, is_seed_variant, seed_of


def fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and (math.isnan(value) or math.isinf(value))):
        return "n/a"
    if isinstance(value, str):
        return value
    if isinstance(value, (bool,)):
        return "yes" if value else "no"
    if abs(value) >= 1e4 or (abs(value) < 1e-3 and value != 0):
        return f"{value:.{digits}e}"
    return f"{value:.{digits}g}"


def markdown_table(frame: pd.DataFrame, columns: list[str], headers: list[str] | None = None, digits: int = 3) -> list[str]:
    headers = headers or columns
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    for _, row in frame[columns].iterrows():
        lines.append("| " + " | ".join(fmt(v, digits) if not isinstance(v, str) else v for v in row) + " |")
    return lines


def ratio_table(metrics: pd.DataFrame, pipeline: str, numerator: str, denominator: str) -> pd.DataFrame:
    m = metrics[metrics["pipeline"] == pipeline]
    a = m[m["controller"] == numerator].set_index("scenario")["iae_Vs"]
    b = m[m["controller"] == denominator].set_index("scenario")["iae_Vs"]
    return (a / b).rename(f"{numerator}/{denominator}")


def seed_study(metrics, pipeline) -> list[str]:
    """Names of the seed-study NNPCs of a pipeline ("NNPC (seed 1)", ...)."""
    names = metrics.loc[metrics["pipeline"] == pipeline, "controller"]
    return sorted(n for n in set(names) if is_seed_variant(n))


def value(metrics, pipeline, controller, scenario, column):
    rows = metrics[(metrics["pipeline"] == pipeline) & (metrics["controller"] == controller)
                   & (metrics["scenario"] == scenario)]
    return float(rows[column].iloc[0]) if len(rows) else math.nan


def seed_controllers(metrics, pipeline, base: str = NNPC) -> dict[int, str]:
    """The NNPC of each identification seed of a pipeline: {0: "NNPC", 1: "NNPC (seed 1)", ...}."""
    names = set(metrics.loc[metrics["pipeline"] == pipeline, "controller"])
    found = {seed_of(n, base): n for n in names}
    return {s: found[s] for s in sorted(k for k in found if k is not None)}


def model_key(name: str) -> str:
    """The key of a controller's network in a pipeline's model summaries ("NNPC (seed 2)" -> "nnpc (seed 2)")."""
    return name.lower()


def worst(values: dict) -> tuple:
    """(key, value) of the largest value of a dict (NaN counts as the worst)."""
    key = max(values, key=lambda k: math.inf if math.isnan(values[k]) else values[k])
    return key, values[key]
