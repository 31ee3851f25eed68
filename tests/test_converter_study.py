"""The converter study (``buck-cosim study``): its checks before any work, and its targets computed from the metrics
(the end-to-end study of the second converter is in test_second_converter.py)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from conftest import cli, one_line_error
from test_converter_spec import MY24, my24

from cosim.converter_spec import ConverterSpec
from cosim.study.converter_report import study_targets

TAG = "bound-x__10us"


def _metrics(rows: list[tuple[str, str, float]], overshoot: float = 2.0, error: float = 0.1) -> pd.DataFrame:
    """A study's metrics: (controller, scenario, IAE [V s]) rows of one pipeline at 10 us, the PI's start-up with
    ``overshoot`` [%] and steady-state ``error`` [%]."""
    frame = pd.DataFrame([{"pipeline": TAG, "controller": c, "scenario": s, "iae_Vs": iae, "overshoot_pct": 1.0,
                           "steady_state_error_pct": 0.0} for c, s, iae in rows])
    startup = (frame["controller"] == "PI") & (frame["scenario"] == "startup")
    frame.loc[startup, ["overshoot_pct", "steady_state_error_pct"]] = overshoot, error
    return frame


SPEC = ConverterSpec(label="x", input_voltage=24.0, output_voltage=5.0, load_resistance=2.0, switching_frequency=100e3)


def _targets(tmp_path, metrics) -> dict[str, dict]:
    table = study_targets(tmp_path, SPEC, [1e-5], {1e-5: TAG}, metrics)
    return {row["target"].split(" at ")[0].split(",")[0]: row for row in table.to_dict("records")}


def test_targets_hold_when_every_seed_beats_the_pi_and_stays_near_the_mpc(tmp_path):
    """NNPC / MPC-nominal on the load change: 1.04 (seed 0) and 1.12 (seed 1), median 1.08 <= 1.10, worst 1.12 <= 1.5;
    NNPC / PI at most 0.56."""
    rows = [("PI", "startup", 1.0), ("PI", "load_change", 1.0), ("MPC-nominal", "startup", 0.5),
            ("MPC-nominal", "load_change", 0.5), ("NNPC", "startup", 0.5), ("NNPC", "load_change", 0.52),
            ("NNPC (seed 1)", "startup", 0.53), ("NNPC (seed 1)", "load_change", 0.56)]
    targets = _targets(tmp_path, _metrics(rows))
    assert [t["met"] for t in targets.values()] == ["yes"] * 5, targets
    pi = targets["NNPC IAE < PI IAE"]
    assert pi["measured"] == "worst NNPC / PI 0.560 (load_change, seed 1)" and pi["margin"] == "0.560"
    median, worst = (t for t in targets.values() if "nominal-model MPC" in t["target"])
    assert median["measured"] == "1.080 (load_change)" and median["margin"] == "0.982"
    assert "startup: 1.030 (1.000-1.060)" in median["note"]
    assert worst["measured"] == "1.120 (load_change, seed 1)"
    assert targets["PI start-up"]["measured"] == "overshoot 2.00 %, steady-state error +0.100 %"


def test_one_seed_worse_than_the_pi_fails_the_target_and_names_the_seed_and_scenario(tmp_path):
    rows = [("PI", "startup", 1.0), ("PI", "load_change", 1.0), ("MPC-nominal", "startup", 1.0),
            ("MPC-nominal", "load_change", 1.0), ("NNPC", "startup", 0.5), ("NNPC", "load_change", 0.5),
            ("NNPC (seed 1)", "startup", 0.5), ("NNPC (seed 1)", "load_change", 1.6)]
    targets = _targets(tmp_path, _metrics(rows, overshoot=6.0))
    assert targets["NNPC IAE < PI IAE"]["met"] == "**no**"
    assert targets["NNPC IAE < PI IAE"]["measured"] == "worst NNPC / PI 1.600 (load_change, seed 1)"
    worst = [t for name, t in targets.items() if "worst seed" in t["target"]][0]
    assert worst["met"] == "**no**" and worst["measured"] == "1.600 (load_change, seed 1)"
    assert targets["PI start-up"]["met"] == "**no**" and "overshoot 6.00 %" in targets["PI start-up"]["measured"]


def test_a_run_outside_the_networks_data_fails_its_target(tmp_path):
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / f"startup__nnpc__{TAG}.json").write_text(
        '{"complete": true, "controller": "NNPC", "outside_data_domain": [{"signal": "input_voltage", "value": 40.0, '
        '"unit": "V", "range": [18.0, 32.0]}]}')  # a run's metadata file, as run_batch writes it
    targets = _targets(tmp_path, _metrics([("PI", "startup", 1.0), ("NNPC", "startup", 0.5)]))
    domain = targets["No NNPC run leaves its identification data's ranges (supply"]
    assert domain["met"] == "**no**" and domain["measured"] == "1 run(s) outside"
    assert "input_voltage 40 outside [18.0, 32.0]" in domain["note"]


def test_a_study_without_control_periods_or_a_nominal_circuit_is_refused_before_any_work(tmp_path, python_buck_fmu):
    binding = my24(tmp_path, python_buck_fmu)  # a circuit, no control_periods
    done = cli("study", "--plant", str(binding), "--out", str(tmp_path / "out"))
    one_line_error(done, 2, "the converter study needs its control periods: give [converter] control_periods = [...] "
                            "(s) or --control-period")
    assert not (tmp_path / "out").exists()
    no_circuit = my24(tmp_path, python_buck_fmu, text=MY24.format(fmu=python_buck_fmu, extra="control_periods = "
                                                                  "[1e-3]\n").split("[converter.circuit]")[0])
    done = cli("study", "--plant", str(no_circuit), "--out", str(tmp_path / "out"))
    one_line_error(done, 2, "my24.toml: the converter study (its MPC and classical baselines design with the nominal "
                            "circuit) needs inductance")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("args,message", [
    (["--seeds", "0"], "argument --seeds: 0 is invalid: expected a whole number >= 1 and <= 20"),
    (["--control-period", "1e-9"], "argument --control-period: period 1e-9 s is invalid: expected >= 1e-07 s"),
])
def test_bad_study_options_are_refused_in_one_line(tmp_path, python_buck_fmu, args, message):
    binding = my24(tmp_path, python_buck_fmu, extra="control_periods = [1e-3]\n")
    done = cli("study", "--plant", str(binding), "--out", str(tmp_path / "out"), *args)
    one_line_error(done, 2, message)
    assert not Path(tmp_path / "out").exists()
