"""Markdown tables of numbers: the one place that formats a number for a report, a summary or a timings table."""

from __future__ import annotations

import math

import pandas as pd


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
