"""The report's comparisons over seeds (cosim/study/claims.py): stated only where they hold for every
seed, otherwise 'not ranked' with the spread; the targets' margins; the drift study over seeds."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from cosim.study.claims import (
    ABOVE,
    BELOW,
    EQUAL,
    WITHIN,
    comparison,
    pooled,
    spread,
    target_row,
    verdict,
)
from cosim.study.report import drift_conclusion
from cosim.study.summaries import drift_spreads, seed_ratio_spreads, seed_value_spread


def test_a_spread_gives_median_min_and_max_over_the_seeds():
    s = spread({3: 0.45, 0: 0.40, 1: 0.42, 2: math.nan})
    assert (s.minimum, s.median, s.maximum, s.count) == (0.40, 0.42, 0.45, 3)
    assert s.text() == "0.42 (0.40-0.45)"
    assert s.long_text(".2f", " %") == "min 0.40 % / median 0.42 % / max 0.45 % over 3 seeds"
    assert s.worst_seed() == 2  # the seed that was not measured counts as the worst
    assert spread({0: 0.5}).text() == "0.50" and spread({}).text() == "n/a"


def test_a_verdict_holds_only_when_every_seed_agrees():
    assert verdict([spread({0: 0.5, 1: 0.9})]) == BELOW
    assert verdict([spread({0: 1.2, 1: 1.01})]) == ABOVE
    assert verdict([spread({0: 0.9, 1: 1.1})]) == WITHIN  # one seed each way: no ranking
    assert verdict([spread({0: 0.9, 1: math.nan})]) == WITHIN  # a seed not measured: not claimed
    assert verdict([spread({0: 0.995, 1: 1.004})], tolerance=0.01) == EQUAL
    assert verdict([spread({0: 0.991, 1: 0.992})], tolerance=0.01) == EQUAL
    assert verdict([spread({0: 0.98, 1: 0.99})], tolerance=0.01) == BELOW
    assert verdict([spread({0: 0.5}), spread({0: 1.5})]) == WITHIN  # over scenarios too


def test_a_comparison_names_each_scenario_under_its_verdict():
    spreads = {"startup": spread({0: 0.4, 1: 0.5}), "load_change": spread({0: 0.97, 1: 1.05}),
               "reference_up": spread({0: 1.2, 1: 1.3}), "reference_down": spread({0: 1.0, 1: 1.005})}
    text = comparison(spreads, "NNPC", "PI")
    assert text == ("NNPC's IAE is lower than PI's for every seed in startup; equal to PI's within 1 % for every seed "
                    "in reference_down; higher than PI's for every seed in reference_up; not ranked: the ratio's "
                    "seed-to-seed spread includes 1 in load_change")
    one = comparison({"startup": spread({0: 0.4})}, "NNPC", "PI")
    assert one == "NNPC's IAE is lower than PI's (one seed: no spread measured) in startup"


def test_pooling_takes_each_seeds_worst_scenario():
    p = pooled([spread({0: 0.4, 1: 0.5}), spread({0: 0.6, 1: 0.3})])
    assert p.by_seed == {0: 0.6, 1: 0.5}


def test_a_target_row_carries_its_margin():
    row = target_row("x <= 150 mV", "128 mV", True, value=128.0, limit=150.0)
    assert row == {"target": "x <= 150 mV", "measured": "128 mV", "margin": "0.853", "met": "yes", "note": ""}
    assert target_row("share >= 60 %", "0 %", False, value=0.0, limit=60.0)["margin"] == "0.000"
    assert target_row("a count", "114 MACs", True)["margin"] == ""
    assert target_row("x", "n/a", False, value=math.nan, limit=1.0)["margin"] == "n/a"


def _metrics(rows):
    return pd.DataFrame([{"pipeline": p, "scenario": s, "controller": c, "iae_Vs": v, "overshoot_pct": o}
                         for p, s, c, v, o in rows])


def test_seed_spreads_are_read_from_every_seeds_controller():
    m = _metrics([("t", "startup", "PI", 2.0, 3.0), ("t", "load_change", "PI", 4.0, 0.0),
                  ("t", "startup", "NNPC", 1.0, 1.0), ("t", "load_change", "NNPC", 2.0, 0.0),
                  ("t", "startup", "NNPC (seed 1)", 1.5, 7.0), ("t", "load_change", "NNPC (seed 1)", 5.0, 0.0),
                  ("other", "startup", "NNPC (seed 2)", 9.0, 9.0)])
    spreads = seed_ratio_spreads(m, "t", "PI")
    assert list(spreads) == ["startup", "load_change"]
    assert spreads["startup"].by_seed == {0: 0.5, 1: 0.75} and spreads["load_change"].by_seed == {0: 0.5, 1: 1.25}
    assert verdict([spreads["startup"]]) == BELOW and verdict([spreads["load_change"]]) == WITHIN
    assert seed_value_spread(m, "t", "startup", "overshoot_pct").by_seed == {0: 1.0, 1: 7.0}


def test_the_drift_conclusion_follows_the_numbers_of_every_seed():
    def drift(adapted):  # offline 1.0 V s, not adapted 1.1 V s for both seeds
        rows = []
        for seed, a in enumerate(adapted):
            suffix = "" if seed == 0 else f" (seed {seed})"
            rows += [("drift", "capacitor_ageing", f"NNPC{suffix}", 1.1, 0.0),
                     ("drift", "capacitor_ageing", f"NNPC-adaptive{suffix}", a, 0.0),
                     ("drift", "capacitor_ageing", f"NNPC (identified on the drifted plant){suffix}", 1.0, 0.0)]
        return drift_spreads(_metrics(rows))

    helps = drift([1.0, 1.05])
    assert helps["adapted"].by_seed == {0: 1.0, 1: 1.05} and helps["frozen"].by_seed == {0: 1.1, 1: 1.1}
    assert drift_conclusion(helps).startswith("adaptation lowers the IAE for every seed")
    assert drift_conclusion(drift([1.2, 1.3])).startswith("adaptation raises the IAE for every seed")
    mixed = drift_conclusion(drift([1.0, 1.2]))
    assert mixed.startswith("adaptation does not help beyond the seed-to-seed spread") and "lower for 1 of 2 seeds" in mixed
    assert "one seed: no spread measured" in drift_conclusion(drift([1.0]))
    assert helps["adapted_over_frozen"].by_seed[1] == pytest.approx(1.05 / 1.1)
