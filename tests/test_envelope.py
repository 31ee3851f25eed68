"""The envelope map's definition and bookkeeping: its sweep (grid axes anchored where the steps land), the
share of the grid meeting the spec from its table, the worst points, the IAE ratios."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from cosim.design.sweeps.plan import at_operating_point
from cosim.study.envelope import (
    FULL_MAP,
    iae_ratios,
    point_results,
    share_of,
    shares,
    step_scenarios,
    worst_points,
)

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
    from cosim.design.sweeps.plan import SweepPlan
    from cosim.design.sweeps.spec import load_sweep

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


def test_the_map_has_the_delay_free_current_mode_row_from_its_own_design_file(tmp_path):
    """The like-for-like row: the current-mode controller designed without the computation delay, read from
    ``tuning/current-mode-no-delay__<pipeline>.json`` (the reproduction writes it) and built with no delay;
    the targets table reports its share beside the delayed design's, and it is not "the best classical design"
    (no microcontroller computes in zero time)."""
    import json

    from cosim.design.classical_design import design_current_mode_no_delay, targets_for, write_design
    from cosim.design.plants import plant_binding
    from cosim.design.sweeps.designs import build, design
    from cosim.design.vocabulary import CURRENT_MODE, CURRENT_MODE_NO_DELAY, NOMINAL, SWITCHING_PERIOD
    from cosim.study.envelope import best_classical, controllers_of, pipeline_files, target_rows

    files = pipeline_files(tmp_path)
    files["pi"].parent.mkdir(parents=True)
    files["pi"].write_text(json.dumps({"kp": 0.01, "ki": 50.0, "method": "test"}))
    files["pi-envelope"].write_text(json.dumps({"controller": {"kp_per_V": 0.02, "ki_per_V_s": 60.0}}))
    binding = plant_binding("nominal", "switched")
    write_design(design_current_mode_no_delay(NOMINAL, targets_for(binding, SWITCHING_PERIOD), CURRENT_MODE_NO_DELAY),
                 files["current-mode-no-delay"])
    entries = {e.name: e for e in controllers_of(tmp_path)}
    assert entries[CURRENT_MODE_NO_DELAY].design == files["current-mode-no-delay"]
    assert entries[CURRENT_MODE].design == files["current-mode"]
    recipe, = design([entries[CURRENT_MODE_NO_DELAY]], binding, SWITCHING_PERIOD, tmp_path)
    controller = build(recipe, binding, implementation="python")
    assert controller.name == CURRENT_MODE_NO_DELAY and controller.gains.computation_delay == 0

    rows = []
    for controller, overshoot in ((CURRENT_MODE, 20.0), (CURRENT_MODE_NO_DELAY, 1.0)):
        for step in ("reference_step", "load_step"):
            rows.append((5, 6, 48, step, controller, "ok", overshoot, 0.3, 1e-4))
    steps = pd.DataFrame(rows, columns=COLUMNS)
    assert share_of(steps) == {CURRENT_MODE: 0.0, CURRENT_MODE_NO_DELAY: 100.0}
    assert best_classical(steps) == CURRENT_MODE
    folder = tmp_path / "envelope"
    folder.mkdir()
    steps.assign(steady_state_error_pct=0.0).to_csv(folder / "map.csv", index=False)
    measured = {r["target"]: r for r in target_rows(pd.DataFrame(columns=["pipeline", "controller"]), tmp_path)}
    row = next(r for t, r in measured.items() if "without the computation delay" in t)
    assert row["measured"] == "100 % (with the delay 0 %)"


def test_the_oracle_diagnosis_names_ripple_horizon_or_model_per_point():
    """A point fails by ripple when the period mean of vo meets the spec, by the horizon when the longer horizon
    meets it, else by the model; both steps of a point count."""
    from cosim.study.oracle_limits import verdicts

    def row(r, step, overshoot, mean, settle, long_overshoot, long_settle):
        return {"reference_V": r, "load_Ohm": 100.0, "input_voltage_V": 48.0, "step": step, "overshoot_pct": overshoot,
                "overshoot_of_mean_pct": mean, "settling_time_ms": settle, "overshoot_pct_long": long_overshoot,
                "settling_time_ms_long": long_settle}

    frame = pd.DataFrame([
        row(3, "reference_step", 6.0, 4.0, 0.1, 6.0, 0.1), row(3, "load_step", 1.0, 0.5, 0.1, 1.0, 0.1),  # ripple
        row(7, "reference_step", 9.0, 8.0, 0.2, 4.0, 0.3), row(7, "load_step", 1.0, 0.5, 0.1, 1.0, 0.2),  # horizon
        row(11, "reference_step", 9.0, 8.0, 0.2, 4.0, math.nan),  # the long horizon never settles: model
        row(11, "load_step", 1.0, 0.5, 0.1, 1.0, 0.1),
        row(15, "reference_step", 2.0, 1.0, 0.2, 2.0, 0.2), row(15, "load_step", 1.0, 0.5, 0.7, 1.0, 0.2),  # settling
    ])
    verdict = verdicts(frame).drop_duplicates("reference_V").set_index("reference_V")["verdict"]
    assert verdict.to_dict() == {3: "ripple", 7: "horizon", 11: "model", 15: "horizon"}


def test_a_given_network_runs_on_the_map_with_the_inputs_it_was_trained_for(tmp_path):
    """The side studies map networks of another recipe (the NNPC identified before the supply voltage was an
    input): a sweep's given model file is designed and built with the file's own inputs."""
    from pathlib import Path

    from controllers.base import Measurement
    from cosim.design.experiments import nn_configs
    from cosim.design.plants import plant_binding
    from cosim.design.sweeps.designs import build, design
    from cosim.design.sweeps.spec import ControllerEntry
    from cosim.design.vocabulary import SWITCHING_PERIOD

    path = Path(__file__).parent / "fixtures" / "nnpc_nominal_averaged_13p33us.pt"
    binding = plant_binding("nominal", "switched")
    recipe, = design([ControllerEntry("nnpc", "NNPC (earlier recipe)", model=path)], binding, SWITCHING_PERIOD, tmp_path)
    assert "input_voltage" in nn_configs(SWITCHING_PERIOD)["nnpc"].extra_signals
    assert recipe.settings["network"] == "7-7-2 tanh, 2 delay(s), +load_conductance"
    controller = build(recipe, binding, implementation="python")
    assert controller.predictor.model.config.extra_signals == ("load_conductance",)
    assert 0.0 <= controller.step(Measurement(0.0, 12.0, 0.0, inductor_current=0.0, load_current=0.0,
                                              input_voltage=48.0)) <= 1.0
