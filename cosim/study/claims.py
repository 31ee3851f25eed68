"""Comparisons the report states, computed from every identification seed's numbers.

A network identified from another seed's data is another controller: its start-up overshoot can
move by tens of per cent, and an IAE ratio near 1 can fall on either side. So the report states a
comparison ("the NNPC beats the PI", "adaptation helps") only when it holds for *every* seed, and
otherwise says that the difference is within the seed-to-seed spread, giving the spread. One
:class:`Spread` is the values of one quantity over the seeds; :func:`verdict` and
:func:`comparison` turn it into the report's words. The targets table's rows are built by
:func:`target_row`, which also records how close each measured value sits to its limit (the
*margin*), so a reader sees which targets are coin flips.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass

#: verdicts of :func:`verdict`
BELOW, ABOVE, EQUAL, WITHIN = "below", "above", "equal", "within"
#: ratios within this of 1 for every seed are called equal (IAE differences below 1 % are not a ranking)
EQUAL_TOLERANCE = 0.01


@dataclass(frozen=True)
class Spread:
    """One quantity over the identification seeds: ``{seed: value}`` (NaN: not measured for that seed)."""

    by_seed: dict[int, float]

    @property
    def values(self) -> list[float]:
        return [v for v in self.by_seed.values() if not math.isnan(v)]

    @property
    def count(self) -> int:
        return len(self.values)

    @property
    def minimum(self) -> float:
        return min(self.values) if self.values else math.nan

    @property
    def median(self) -> float:
        return statistics.median(self.values) if self.values else math.nan

    @property
    def maximum(self) -> float:
        return max(self.values) if self.values else math.nan

    def worst_seed(self, higher_is_worse: bool = True) -> int | None:
        """The seed of the worst value (NaN counts as the worst: a seed that was not measured)."""
        if not self.by_seed:
            return None
        sign = 1 if higher_is_worse else -1
        return max(self.by_seed, key=lambda s: math.inf if math.isnan(self.by_seed[s]) else sign * self.by_seed[s])

    def text(self, spec: str = ".2f", unit: str = "") -> str:
        """``0.42 (0.40-0.45)``: the median, and min-max over the seeds; one value alone when there is one seed."""
        if self.count == 0:
            return "n/a"
        if self.count == 1:
            return f"{self.values[0]:{spec}}{unit}"
        return f"{self.median:{spec}}{unit} ({self.minimum:{spec}}-{self.maximum:{spec}})"

    def long_text(self, spec: str = ".2f", unit: str = "") -> str:
        """``min 0.40 / median 0.42 / max 0.45 over 5 seeds``."""
        if self.count < 2:
            return f"{self.text(spec, unit)} ({self.count} seed{'s' if self.count != 1 else ''})"
        return (f"min {self.minimum:{spec}}{unit} / median {self.median:{spec}}{unit} / max {self.maximum:{spec}}{unit} "
                f"over {self.count} seeds")


def plural(count: int, noun: str) -> str:
    """``1 seed``, ``5 seeds``."""
    return f"{count} {noun}{'' if count == 1 else 's'}"


def spread(by_seed: dict[int, float]) -> Spread:
    return Spread({int(k): float(v) for k, v in sorted(by_seed.items())})


def pooled(spreads) -> Spread:
    """Several spreads (e.g. one per scenario) as one: each seed's worst (largest) value over them."""
    seeds = sorted({s for sp in spreads for s in sp.by_seed})
    out = {}
    for seed in seeds:
        values = [sp.by_seed.get(seed, math.nan) for sp in spreads]
        out[seed] = math.nan if any(math.isnan(v) for v in values) else max(values)
    return Spread(out)


def pooled_min(spreads) -> Spread:
    """Each seed's smallest value over several spreads."""
    seeds = sorted({s for sp in spreads for s in sp.by_seed})
    return Spread({s: min(sp.by_seed.get(s, math.nan) for sp in spreads) for s in seeds})


def verdict(values, threshold: float = 1.0, tolerance: float | None = None) -> str:
    """:data:`EQUAL` when ``tolerance`` is given and every value (every seed, every spread given) is
    within ``tolerance`` (relative) of ``threshold``; else :data:`BELOW` when every value is below
    ``threshold``, :data:`ABOVE` when every one is above, and otherwise :data:`WITHIN` (the threshold
    is inside the spread, or a value is missing: a comparison not measured everywhere is not claimed)."""
    flat = []
    for v in values:
        flat += v.by_seed.values() if isinstance(v, Spread) else [v]
    if not flat or any(math.isnan(v) for v in flat):
        return WITHIN
    if tolerance is not None and all(abs(v - threshold) <= tolerance * abs(threshold) for v in flat):
        return EQUAL
    if all(v < threshold for v in flat):
        return BELOW
    if all(v > threshold for v in flat):
        return ABOVE
    return WITHIN


def comparison(spreads: dict[str, Spread], first: str, second: str, quantity: str = "IAE",
               tolerance: float = EQUAL_TOLERANCE) -> str:
    """The words for the ratios ``first / second`` of ``quantity`` (lower is better), one spread over the
    seeds per scenario, grouped by verdict: "NNPC's IAE is lower than PI's for every seed in startup,
    reference_up; within the seed-to-seed spread in load_change"."""
    groups: dict[str, list[str]] = {}
    for scenario, values in spreads.items():
        groups.setdefault(verdict([values], tolerance=tolerance), []).append(scenario)
    seeds = max((s.count for s in spreads.values()), default=0)
    every = "for every seed" if seeds > 1 else "(one seed: no spread measured)"
    words = {BELOW: f"lower than {second}'s {every}", ABOVE: f"higher than {second}'s {every}",
             EQUAL: f"equal to {second}'s within {100 * tolerance:g} % {every}",
             WITHIN: "not ranked: the ratio's seed-to-seed spread includes 1" if seeds > 1 else
             "not ranked (a value is missing)"}
    parts = [f"{words[v]} in {', '.join(groups[v])}" for v in (BELOW, EQUAL, ABOVE, WITHIN) if v in groups]
    if not parts:
        return f"{first} / {second}: n/a"
    return f"{first}'s {quantity} is " + "; ".join(parts)


def per_scenario_text(spreads: dict[str, Spread], spec: str = ".2f") -> str:
    """``startup 0.19 (0.14-0.19), load_change ...``: each scenario's median and min-max over the seeds."""
    return ", ".join(f"{scenario} {s.text(spec)}" for scenario, s in spreads.items())


# ---------------------------------------------------------------------------------------------
# Targets


#: the targets table's columns (targets.csv and the report's table)
TARGET_COLUMNS = ["target", "measured", "margin", "met", "note"]


def target_row(target: str, measured: str, met: bool, note: str = "", *, value: float | None = None,
               limit: float | None = None) -> dict:
    """A row of the targets table. ``value`` / ``limit``: the measured number the verdict rests on
    (the worst seed's, the worst scenario's) and the threshold it is held to; their ratio is the
    *margin* (e.g. 0.97 for an upper limit met with 3 % to spare, 1.02 for one missed by 2 %; for a
    lower limit -- a share >= 60 % -- a margin above 1 is met). Targets without one number (a count)
    leave it empty."""
    margin = ""
    if value is not None and limit is not None and not math.isnan(value) and limit != 0:
        margin = f"{value / limit:.3f}"
    elif value is not None and math.isnan(value):
        margin = "n/a"
    return {"target": target, "measured": measured, "margin": margin, "met": "yes" if met else "**no**", "note": note}
