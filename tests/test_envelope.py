"""The envelope map's definition and bookkeeping: its sweep (grid axes anchored where the steps land), the
share of the grid meeting the spec from its table, the worst points, the IAE ratios."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from cosim.study.envelope import (
    FULL_MAP,
    iae_ratios,
    point_results,
    share_of,
    shares,
    step_scenarios,
    worst_points,
)
from cosim.study.sweeps.plan import at_operating_point

COLUMNS = ["reference_V", "load_Ohm", "input_voltage_V", "step", "controller", "status", "overshoot_pct",
           "settling_time_ms", "iae_Vs"]


def _steps() -> pd.DataFrame:
    return pd.DataFrame([
        # point (5 V, 6 Ohm): NNPC meets both; the explicit one overshoots 6 % in the load step
        (5, 6, 48, "reference_step", "NNPC", "ok", 1.0, 0.1, 1e-4), (5, 6, 48, "load_step", "NNPC", "ok", 4.9, 0.5, 2e-4),
        (5, 6, 48, "reference_step", "NNPC-explicit", "ok", 1.0, 0.1, 1e-4),
        (5, 6, 48, "load_step", "NNPC-explicit", "ok", 6.0, 0.1, 1e-4),
        # point (15 V, 60 Ohm): the NNPC never settles in one step; the explicit one meets both
        (15, 60, 48, "reference_step", "NNPC", "ok", 0.0, math.nan, 4e-4),
        (15, 60, 48, "load_step", "NNPC", "ok", 0.0, 0.1, 1e-4),
        (15, 60, 48, "reference_step", "NNPC-explicit", "ok", 5.0, 0.49, 2e-4),
        (15, 60, 48, "load_step", "NNPC-explicit", "failed", 0.0, 0.0, math.nan),
    ], columns=COLUMNS)


def test_the_share_needs_both_steps_within_overshoot_and_settling():
    steps = _steps()
    assert share_of(steps) == {"NNPC": 50.0, "NNPC-explicit": 0.0}  # a failed run fails its point
    points = point_results(steps).set_index(["controller", "reference_V"])
    assert points.loc[("NNPC", 15), "settling_time_ms"] == math.inf
    assert not points.loc[("NNPC-explicit", 5), "meets"] and not points.loc[("NNPC-explicit", 15), "meets"]
    assert points.loc[("NNPC", 5), "excess"] == pytest.approx(1.0)  # overshoot 4.9/5 vs settling 0.5/0.5
    per_supply = shares(steps, by_supply=True)
    assert list(per_supply["input_voltage_V"]) == [48, 48] and list(per_supply["points"]) == [2, 2]
    worst = worst_points(steps, 1).set_index("controller")
    assert worst.loc["NNPC", "reference_V"] == 15 and worst.loc["NNPC-explicit", "reference_V"] == 15
    ratios = iae_ratios(steps, "NNPC", "NNPC-explicit")
    assert ratios.loc[(48, 5, 6, "load_step")] == pytest.approx(2.0) and len(ratios) == 3  # NaN IAE dropped


def test_steps_land_on_the_grid_point():
    """The axes are anchored at the final value: the reference step ends at r, the load step at R."""
    reference_step, load_step = step_scenarios(FULL_MAP)
    anchors = (("reference", "final"), ("load_resistance", "final"))
    values = {"reference": 20.0, "load_resistance": 100.0, "input_voltage": 36.0}
    moved = at_operating_point(reference_step, values, anchors)
    assert moved.initial["reference"] == pytest.approx(16.0) and moved.events[-1].changes["reference"] == pytest.approx(20)
    assert moved.initial["load_resistance"] == pytest.approx(100.0) and moved.initial["input_voltage"] == 36.0
    moved = at_operating_point(load_step, values, anchors)
    assert moved.initial["load_resistance"] == pytest.approx(125.0)
    assert moved.events[-1].changes["load_resistance"] == pytest.approx(100.0)
    assert moved.initial["reference"] == pytest.approx(20.0)
    # without anchors (the tolerance studies), the value is the initial one, exactly as before
    assert at_operating_point(load_step, {"load_resistance": 12.0}).initial["load_resistance"] == 12.0


def test_sweep_files_take_anchored_reference_axes_and_refuse_the_oracle_beside_parameter_axes(tmp_path):
    from cosim.base.errors import ConfigError
    from cosim.study.sweeps.plan import SweepPlan
    from cosim.study.sweeps.spec import load_sweep

    body = ('scenarios = ["reference_up"]\ncontrollers = ["mpc-oracle", "current-mode"]\ncontrol_period = "1/75e3"\n'
            '[plant]\nmode = "switched"\n'
            '[operating_point]\nreference = { values = [5.0, 20.0], anchor = "final" }\n')
    (tmp_path / "map.toml").write_text(body)
    plan = SweepPlan(load_sweep(tmp_path / "map.toml"))
    assert plan.spec.axes[0].anchor == "final"
    (tmp_path / "bad.toml").write_text(body + '[parameters]\ninductance = { values = [2e-4, 2.4e-4] }\n')
    with pytest.raises(ConfigError, match="mpc-oracle knows the nominal plant's circuit only"):
        SweepPlan(load_sweep(tmp_path / "bad.toml"))
    (tmp_path / "bad2.toml").write_text(body.replace('anchor = "final"', 'anchor = "middle"'))
    with pytest.raises(ConfigError, match="anchor = 'middle' is unknown: expected one of initial, final"):
        load_sweep(tmp_path / "bad2.toml")
