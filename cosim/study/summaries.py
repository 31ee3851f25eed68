"""Look-ups in the reproduction's metrics table and Markdown tables, shared by the report, the
targets and the timings (the one place that formats a number for them)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from cosim.design.vocabulary import NNPC, NNPC_ADAPTIVE, is_seed_variant, seed_of
from cosim.study.claims import Spread, spread
from cosim.study.vocabulary import DRIFT_SCENARIO, DRIFT_STUDY, NNPC_DRIFTED


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


def seed_ratio_spreads(metrics, pipeline, denominator: str, base: str = NNPC) -> dict[str, Spread]:
    """{scenario: :class:`~cosim.study.claims.Spread` of ``base``'s IAE / ``denominator``'s IAE over every
    identification seed's ``base`` (``NNPC``, ``NNPC (seed 1)``, ...)} in ``pipeline``, scenarios in run order."""
    per_seed = {seed: ratio_table(metrics, pipeline, name, denominator)
                for seed, name in seed_controllers(metrics, pipeline, base).items()}
    scenarios = list(dict.fromkeys(s for r in per_seed.values() for s in r.index))
    return {scenario: spread({seed: float(r.get(scenario, math.nan)) for seed, r in per_seed.items()})
            for scenario in scenarios}


def seed_value_spread(metrics, pipeline, scenario: str, column: str, base: str = NNPC) -> Spread:
    """:class:`~cosim.study.claims.Spread` of one metric of every seed's ``base`` in one scenario."""
    return spread({seed: value(metrics, pipeline, name, scenario, column)
                   for seed, name in seed_controllers(metrics, pipeline, base).items()})


def drift_spreads(rows: pd.DataFrame) -> dict[str, Spread]:
    """The drift study over its seeds: IAE after the drift of the adapted and the non-adapted NNPC over
    that of the NNPC identified on the drifted plant, and adapted over not adapted."""
    offline = {s: value(rows, DRIFT_STUDY, n, DRIFT_SCENARIO, "iae_Vs")
               for s, n in seed_controllers(rows, DRIFT_STUDY, NNPC_DRIFTED).items()}
    adapted = {s: value(rows, DRIFT_STUDY, n, DRIFT_SCENARIO, "iae_Vs")
               for s, n in seed_controllers(rows, DRIFT_STUDY, NNPC_ADAPTIVE).items()}
    frozen = {s: value(rows, DRIFT_STUDY, n, DRIFT_SCENARIO, "iae_Vs")
              for s, n in seed_controllers(rows, DRIFT_STUDY, NNPC).items()}
    seeds = sorted(set(offline) & set(adapted) & set(frozen))
    return {"adapted": spread({s: adapted[s] / offline[s] for s in seeds}),
            "frozen": spread({s: frozen[s] / offline[s] for s in seeds}),
            "adapted_over_frozen": spread({s: adapted[s] / frozen[s] for s in seeds})}


#: [s] after each reference or load step, the *transient* part of the drift study's IAE; the rest is the steady
#: part (the output's ripple about the reference, which no controller removes)
TRANSIENT_WINDOW = 0.3e-3


def transient_and_steady_iae(frame: pd.DataFrame, start: float) -> dict[str, float]:
    """A run's IAE [V s] from ``start`` on, split into the :data:`TRANSIENT_WINDOW` after each reference or
    load step and the rest (the drift study's analysis of what adaptation can change)."""
    part = frame[frame["time"] >= start]
    t = part["time"].to_numpy()
    dt = np.diff(t, append=t[-1]) if len(t) else t
    error = np.abs(part["output_voltage"] - part["reference"]).to_numpy() * dt
    steps = t[((part["reference"].diff().abs() > 0) | (part["load_resistance"].diff().abs() > 0)).to_numpy()]
    transient = np.zeros(len(t), bool)
    for step in steps:
        transient |= (t >= step) & (t < step + TRANSIENT_WINDOW)
    return {"transient": float(error[transient].sum()), "steady": float(error[~transient].sum())}
