"""Sweeps and Monte Carlo on dask: the sweep file, the runs and their ids, the dataset, the summary,
and the faults -- with real LocalClusters of two worker processes on the loopback interface."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from conftest import CONTROLLER_ROLES, cli, faulty_binding, no_temporary_files, role_named_binding
from conftest import one_line_error as cli_one_line_error

from cosim.base.errors import ConfigError
from cosim.cli import main
from cosim.design.sweeps import dataset
from cosim.design.sweeps.plan import SweepPlan, at_operating_point
from cosim.design.sweeps.spec import load_sweep, parse_sweep
from cosim.design.sweeps.summary import spec_mask, wilson_interval
from cosim.study.vocabulary import PAPER_SPEC

PI_GAINS = "kp = 0.0015, ki = 15.6"  # near the tuned 1 ms gains: the tests need a PI, not its tuning


@pytest.fixture(scope="module")
def cluster():
    """A LocalCluster of two worker processes, as ``dask scheduler`` + two ``dask worker`` would be."""
    import logging

    from distributed import Client, LocalCluster

    local = LocalCluster(host="127.0.0.1", n_workers=2, threads_per_worker=1, processes=True,
                         dashboard_address="127.0.0.1:0", silence_logs=logging.CRITICAL)
    client = Client(local, set_as_default=False)
    try:
        client.wait_for_workers(2, timeout=60)
        yield local, client
    finally:
        client.close()
        local.close()


@pytest.fixture(scope="module")
def nn_model(tmp_path_factory) -> Path:
    """An NNPC model identified on the nominal switched plant (small data: the sweep tests need one, not a good one)."""
    from cosim.design.controller_factory import trained_model
    from cosim.design.plants import plant_binding
    from cosim.design.vocabulary import pipeline_tag, plant_tag

    folder = tmp_path_factory.mktemp("nn")
    trained_model("nnpc", plant_binding("nominal", "switched"), 1e-3, folder, samples=1500, seed=0, model_path=None)
    return folder / "models" / f"{pipeline_tag(plant_tag('nominal', 'switched'), 1e-3)}__nnpc.pt"


def sweep_file(folder: Path, body: str, name: str = "study.toml") -> Path:
    path = folder / name
    path.write_text(textwrap.dedent(body))
    return path


def tolerance_study(folder: Path, model: Path, samples: int = 6, extra: str = "", controllers: str | None = None,
                    name: str = "study.toml") -> Path:
    controllers = controllers or f"""
        [[controllers]]
        kind = "pi"
        {PI_GAINS.replace(', ', chr(10) + '        ')}
        [[controllers]]
        kind = "nnpc"
        model = "{model}"
        [[controllers]]
        kind = "mpc-nominal"
        """
    return sweep_file(folder, f"""\
        name = "tol"
        description = "L, C +-20 %, ESR and DCR"
        scenarios = ["startup", "load_change"]
        samples = {samples}
        seed = 7
        {extra}
        [plant]
        mode = "switched"
        [parameters]
        inductance = {{ tolerance = 0.2 }}
        capacitance = {{ tolerance = 0.2 }}
        capacitor_esr = {{ low = 0.0, high = 0.1 }}
        inductor_resistance = {{ distribution = "log-normal", median = 0.05, sigma = 0.5 }}
        [spec]
        overshoot_pct = 5.0
        settling_time_ms = 4.0
        steady_state_error_pct = 0.5
        {controllers}""", name)


def one_line_error(capsys, code: int, expected_code: int, message: str) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == expected_code, err
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], err
    return lines[0]


def ends_in_one_line_error(capsys, code: int, expected_code: int, message: str) -> str:
    """Progress lines may come first; the failure is one ``error:`` line, the last, and no traceback."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == expected_code, err
    assert [line for line in lines if line.startswith("error: ")] == lines[-1:] and message in lines[-1], err
    assert "Traceback" not in err, err
    return lines[-1]


def rows_of(out: Path) -> pd.DataFrame:
    return dataset.read_rows(out).sort_values("run_id").reset_index(drop=True)


# ------------------------------------------------------------------------------------------ the sweep file


def test_the_sweep_file_gives_grids_distributions_controllers_and_a_spec(tmp_path):
    path = sweep_file(tmp_path, """\
        scenarios = ["startup"]
        controllers = ["pi", {kind = "nnpc", samples = 2000, seed = 3}, {kind = "mpc-nominal", name = "MPC"}]
        samples = 4000
        seed = 11
        control_period = "1/75e3"
        [parameters]
        inductance = { tolerance = 0.2 }
        capacitance = { tolerance = [-0.3, 0.1] }
        capacitor_esr = { distribution = "normal", mean = 0.05, std = 0.01 }
        inductor_resistance = { distribution = "log-normal", tolerance = 0.5 }
        switching_frequency = { values = [60e3, 75e3] }
        [operating_point]
        input_voltage = { distribution = "normal", tolerance = 0.1 }
        [spec]
        overshoot_pct = 5
        steady_state_error_pct = 0.5
        """)
    spec = load_sweep(path)
    assert spec.name == "study" and spec.control_period == pytest.approx(1 / 75e3)
    assert [c.kind for c in spec.controllers] == ["pi", "nnpc", "mpc-nominal"]
    assert [c.name for c in spec.controllers] == ["PI", "NNPC", "MPC"] and spec.controllers[1].samples == 2000
    assert spec.grid_points == 2 and spec.run_count == 2 * 4000 * 1 * 3
    assert [t.text() for t in spec.thresholds] == ["overshoot_pct <= 5", "|steady_state_error_pct| <= 0.5"]
    axes = {a.name: a for a in spec.axes}
    l_draw = axes["inductance"].draw(spec.seed, spec.samples)
    assert 0.8 <= l_draw.min() < 0.81 and 1.19 < l_draw.max() <= 1.2  # uniform factors on the nominal
    c_draw = axes["capacitance"].draw(spec.seed, spec.samples)
    assert 0.7 <= c_draw.min() and c_draw.max() <= 1.1 and c_draw.mean() == pytest.approx(0.9, abs=0.01)
    esr = axes["capacitor_esr"].draw(spec.seed, spec.samples)
    assert esr.mean() == pytest.approx(0.05, abs=1e-3) and esr.std() == pytest.approx(0.01, rel=0.05)
    dcr = axes["inductor_resistance"].draw(spec.seed, spec.samples)  # 3 sigma(ln) = ln 1.5, median 1
    assert np.median(dcr) == pytest.approx(1.0, abs=0.02) and np.log(dcr).std() == pytest.approx(math.log(1.5) / 3, rel=0.05)
    supply = axes["input_voltage"].draw(spec.seed, spec.samples)  # +-10 % at 3 sigma
    assert supply.std() == pytest.approx(0.1 / 3, rel=0.05)
    # the same seed gives the same draws; an axis's draws do not depend on the other axes
    alone = parse_sweep('scenarios = ["startup"]\ncontrollers = ["pi"]\nsamples = 4000\nseed = 11\n'
                        '[parameters]\ninductance = { tolerance = 0.2 }\n', tmp_path / "alone.toml")
    assert np.array_equal(alone.axes[0].draw(11, 4000), l_draw)
    assert not np.array_equal(alone.axes[0].draw(12, 4000), l_draw)


@pytest.mark.parametrize("body,message", [
    ('scenarios = ["startup"]\ncontrollers = ["pi"]\nsamples = 3\n[parameters]\ninductance = { tolerance = 1.5 }\n',
     "bad.toml:5: parameters.inductance.tolerance = 1.5 is invalid: expected 0 < tolerance < 1"),
    ('scenarios = ["startup"]\ncontrollers = ["pi"]\n[parameters]\ninductance = { tolerance = 0.2 }\n',
     "bad.toml: missing required key 'samples': the random axes (parameters.inductance) need a sample count"),
    ('scenarios = ["startup"]\ncontrollers = ["pi"]\nsamples = 3\n[parameters]\n'
     'capacitance = { distribution = "gamma", low = 1 }\n',
     "bad.toml:5: parameters.capacitance.distribution = 'gamma' is unknown: expected one of uniform, normal, log-normal"),
    ('scenarios = ["startup"]\ncontrollers = ["pi"]\nsamples = 3\n[parameters]\n'
     'capacitance = { distribution = "normal", low = 1e-6, high = 2e-6 }\n',
     "bad.toml:5: parameters.capacitance: low does not apply to a normal distribution: expected mean, std, tolerance"),
    ('scenarios = ["startup"]\ncontrollers = ["pi"]\n[parameters]\ninductance = { values = [1e-4, 1e-4] }\n',
     "bad.toml:4: parameters.inductance.values lists 0.0001 twice"),
    ('scenarios = ["startup"]\ncontrollers = ["pi", "fuzzy"]\n',
     "bad.toml:2: controllers[1].kind = 'fuzzy' is unknown: expected one of pi, nnpc, nnpc-paper, mpc-nominal"),
    ('scenarios = ["startup"]\n[[controllers]]\nkind = "pi"\nkp = 0.1\n',
     "bad.toml:3: controllers[0]: kp and ki go together (or neither: tuned on the nominal plant)"),
    ('scenarios = ["startup"]\ncontrollers = ["pi"]\n[spec]\novershoot = 5\n',
     "bad.toml:4: unknown key 'spec.overshoot': expected one of rise_time_ms, overshoot_pct"),
    ('scenarios = ["nowhere"]\ncontrollers = ["pi"]\n', "bad.toml:1: scenarios: scenario 'nowhere' is neither a file"),
    ('scenarios = ["startup"]\ncontrollers = ["pi"]\nsamples = 0\n', "bad.toml:3: samples = 0 is invalid: expected 1"),
    ('scenarios = ["startup"]\ncontrollers = ["pi"]\ncontrol_period = "1/0"\n',
     "bad.toml:3: control_period = '1/0' is not a period in seconds"),
    ('scenarios = ["startup"]\ncontrollers = ["pi"]\n[plant]\nmode = "switched"\nbinding = "x.toml"\n',
     "bad.toml:4: plant.mode applies to the built-in FMU, but plant.binding names an external one"),
    ('scenarios = ["startup"]\ncontrollers = ["pi"]\nworkers = 4\n',
     "bad.toml:3: unknown key 'workers': expected one of batch_size, control_period"),
    ('scenarios = ["startup"]\n[[controllers]]\nkind = "mpc-nominal"\noptimizer = "newton"\n',
     "bad.toml:4: controllers[0].optimizer = 'newton' is unknown: expected one of rti, search"),
    ('scenarios = ["startup"]\n[[controllers]]\nkind = "pi"\noptimizer = "search"\n',
     "bad.toml:4: controllers[0].optimizer does not apply to pi"),
    ('scenarios = ["startup"]\n[[controllers]]\nkind = "mpc-nominal"\nrti = { iteration = 2 }\n',
     "bad.toml:4: controllers[0].rti: 'iteration' is not an RTI setting (did you mean 'iterations'? expected one of "),
    ('scenarios = ["startup"]\n[[controllers]]\nkind = "mpc-nominal"\nrti = { line_search = 1 }\n',
     "bad.toml:4: controllers[0].rti: line_search = 1 is invalid: expected true or false"),
    ('scenarios = ["startup"]\n[[controllers]]\nkind = "mpc-nominal"\nrti = { iterations = 2.0 }\n',
     "bad.toml:4: controllers[0].rti: iterations = 2.0 is invalid: expected an integer"),
    ('scenarios = ["startup"]\n[[controllers]]\nkind = "mpc-nominal"\nrti = { smoothing = 0 }\n',
     "bad.toml:4: controllers[0].rti: RTI smoothing = 0.0 is invalid: expected eps > 0 [V]"),
    ('scenarios = ["startup"]\n[[controllers]]\nkind = "mpc-nominal"\nrti = 2\n',
     "bad.toml:4: controllers[0].rti must be a table"),
    ('scenarios = ["startup"]\n[[controllers]]\nkind = "mpc-nominal"\nrti = { reweightings = 1 }\n',
     "bad.toml:4: controllers[0].rti at the control period 0.001 s: RTI reweightings = 1 with line_search is refused"),
    ('scenarios = ["startup"]\n[[controllers]]\nkind = "nnpc-paper"\nrti = { iterations = 2 }\n',
     "bad.toml:4: controllers[0].rti changes the real-time iteration's settings, but this controller plans with the "
     "search (nnpc-paper plans with the search unless optimizer = \"rti\"): drop rti"),
    ('scenarios = ["startup"]\n[[controllers]]\nkind = "nnpc"\noptimizer = "search"\nrti = { iterations = 2 }\n',
     "bad.toml:5: controllers[0].rti changes the real-time iteration's settings, but this controller plans with the "
     "search (optimizer = \"search\"): drop rti"),
])
def test_sweep_file_mistakes_name_file_key_and_line(tmp_path, body, message):
    (tmp_path / "bad.toml").write_text(body)
    with pytest.raises(ConfigError) as caught:
        load_sweep(tmp_path / "bad.toml")
    assert message in str(caught.value).replace(str(tmp_path) + "/", "")


def test_values_outside_the_fmu_bounds_and_unknown_parameters_are_refused_before_any_work(tmp_path, capsys):
    """One line, exit 2, and nothing computed: no cluster, no tuning, no dataset."""
    def base(samples=True):
        return ('scenarios = ["startup", "load_change"]\ncontrollers = ["pi"]\n' + ("samples = 50\n" if samples else "")
                + '[plant]\nmode = "switched"\n')

    cases = [
        (base() + '[parameters]\nL = { tolerance = 0.2 }\n',
         "study.toml:7: parameters.L: BuckConverter-", "has no parameter 'L'; its parameters are capacitance, "
         "capacitor_esr, diode_forward_voltage, inductance, inductor_resistance, plant_mode, pwm_carrier, "
         "switch_on_resistance, switching_frequency"),
        (base() + '[parameters]\ninductance = { distribution = "normal", mean = 220e-6, std = 200e-6 }\n',
         "study.toml:7: parameters.inductance:", "values fall below the FMU's minimum 0 H (smallest"),
        (base(False) + '[parameters]\nload_resistance = { values = [5.0, 6.0] }\n',
         "study.toml:6: parameters.load_resistance:", "is an input of BuckConverter-"),
        (base() + '[parameters]\ncapacitor_esr = { tolerance = 0.2 }\n',
         "study.toml:7: parameters.capacitor_esr: a tolerance is relative to the nominal value, which is 0.0",
         "give absolute bounds"),
        (base(False) + '[parameters]\nplant_mode = { values = [0.5] }\n',
         "study.toml:6: parameters.plant_mode is an Integer parameter", "must be whole numbers"),
    ]
    for body, message, more in cases:
        path = sweep_file(tmp_path, body)
        out = tmp_path / "out"
        code = main(["--no-progress", "sweep", str(path), "--out", str(out)])
        line = one_line_error(capsys, code, 2, more)
        assert message in line.replace(str(tmp_path) + "/", ""), line
        assert not (out / "dataset").exists() and not (out / "tuning").exists() and not (out / "sweep.json").exists()


def nothing_ran(out: Path) -> None:
    """No cluster work, no design, no dataset: the output folder holds nothing (or does not exist)."""
    assert not out.exists() or not any(out.iterdir()), sorted(out.rglob("*"))


def plan_error(path: Path) -> str:
    with pytest.raises(ConfigError) as caught:
        SweepPlan(load_sweep(path))
    text = str(caught.value)
    assert "\n" not in text, text
    return text.replace(str(path.parent) + "/", "")


def test_a_control_period_too_long_for_a_scenario_is_refused_before_any_work(tmp_path):
    """The check ``run --control-period`` makes (too few controller samples in a scenario's recorded time),
    made on the sweep file before a cluster starts -- not found by the runs failing on the workers."""
    path = sweep_file(tmp_path, f"""\
        name = "mini"
        scenarios = ["startup", "load_change"]
        samples = 2
        control_period = 0.05
        record_period = 1e-5
        controllers = [{{ kind = "pi", {PI_GAINS} }}]
        [parameters]
        inductance = {{ tolerance = 0.2 }}
        """)
    out = tmp_path / "out"
    done = cli("sweep", str(path), "--out", str(out), "--workers", "1")
    line = cli_one_line_error(done, 2, "scenario startup records 0.03 s, which holds 1 controller sample(s) at control "
                                       "period 0.05 s: expected at least 2 (a shorter control period or a longer "
                                       "duration)")
    assert line.startswith(f"error: {path}:4: control_period = 0.05 s: "), line
    assert "cosim/scenarios/startup.toml:4: scenario startup" in line, line  # the scenario's own file and line
    nothing_ran(out)
    assert done.stdout == ""
    # the same check names the key that is at fault: a record period too fine for a scenario ...
    path.write_text(path.read_text().replace("control_period = 0.05", "control_period = 1e-3")
                    .replace("record_period = 1e-5", "record_period = 1e-10"))
    assert plan_error(path).startswith("study.toml:5: record_period = 1e-10 s: ")
    # ... a controller's own settle time (the runs of that controller only) ...
    path.write_text(path.read_text().replace("record_period = 1e-10", "record_period = 1e-5")
                    .replace("control_period = 1e-3", "control_period = 1e-5")
                    .replace(" }]", f' }}, {{ kind = "pi", name = "slow", settle = 2000.0, {PI_GAINS} }}]'))
    text = plan_error(path)
    assert text.startswith("study.toml:4: control_period = 1e-05 s with controllers[1].settle = 2000 s: ") and \
        "scenario startup's settle 2000 s and duration 0.03 s" in text and "the limit is 2e+08" in text, text
    # ... and the default control period against a scenario file of the user's
    (tmp_path / "short.toml").write_text('name = "short"\nduration = 0.0009\n[initial]\nreference = 12.0\n')
    path = sweep_file(tmp_path, 'scenarios = ["short.toml"]\ncontrollers = ["pi"]\n')
    assert plan_error(path) == ("study.toml: control_period = 0.001 s (the default): short.toml:2: scenario short "
                                "records 0.0009 s, which holds 1 controller sample(s) at control period 0.001 s: "
                                "expected at least 2 (a shorter control period or a longer duration)")


def test_a_reference_above_the_input_voltage_is_refused_before_any_work(tmp_path):
    """The scenario file's check ("exceeds the input voltage"), made on every run the sweep plans: each
    scenario as the operating-point axes move it."""
    path = sweep_file(tmp_path, f"""\
        scenarios = ["startup"]
        controllers = [{{ kind = "pi", {PI_GAINS} }}]
        [operating_point]
        reference = {{ values = [60.0] }}
        """)
    out = tmp_path / "out"
    done = cli("sweep", str(path), "--out", str(out), "--workers", "1")
    line = cli_one_line_error(done, 2, "")
    assert line == (f"error: {path}:4: operating_point.reference: 1 of 1 values in scenario startup put the reference "
                    "above the input voltage (e.g. the reference 60 V at t = 0 s exceeds the input voltage 48 V in "
                    "effect then: a buck converter's output cannot exceed its input): expected a reference <= the "
                    "input voltage"), line
    nothing_ran(out)
    assert done.stdout == ""

    def study(axes: str, scenarios: str = '"startup"', samples: str = "") -> Path:
        return sweep_file(tmp_path, f'scenarios = [{scenarios}]\ncontrollers = ["pi"]\n{samples}[operating_point]\n{axes}')

    # a reference axis against a supply axis: every pair the full factorial draws, the reference's line named
    text = plan_error(study("reference = { values = [10.0, 20.0, 40.0] }\ninput_voltage = { values = [24.0, 36.0, 48.0] }\n"))
    assert text.startswith("study.toml:4: operating_point.reference with operating_point.input_voltage (study.toml:5): "
                           "2 of 9 (reference, input voltage) pairs in scenario startup put the reference above the "
                           "input voltage (e.g. the reference 40 V at t = 0 s exceeds the input voltage 24 V"), text
    SweepPlan(load_sweep(study("reference = { values = [10.0, 20.0, 24.0] }\ninput_voltage = { values = [24.0, 48.0] }\n")))
    # later in the run: the reference step of reference_up scales with the axis (12 -> 15 V becomes 40 -> 50 V) ...
    text = plan_error(study("reference = { values = [12.0, 40.0] }\n", '"startup", "reference_up"'))
    assert text.startswith("study.toml:4: operating_point.reference: 1 of 2 values in scenario reference_up put the "
                           "reference above the input voltage (e.g. the reference 50 V at t = 0.005 s exceeds the input "
                           "voltage 48 V in effect then: a buck converter's output cannot exceed its input)"), text
    # ... but not anchored at its final value (32 -> 40 V)
    SweepPlan(load_sweep(study('reference = { values = [12.0, 40.0], anchor = "final" }\n', '"startup", "reference_up"')))
    # a random supply axis alone, run by run: exactly the draws below the scenario's 12 V
    path = study('input_voltage = { distribution = "uniform", low = 10.0, high = 48.0 }\n', samples="samples = 50\n")
    drawn = load_sweep(path).axes[0].draw(0, 50)
    text = plan_error(path)
    assert text.startswith(f"study.toml:5: operating_point.input_voltage: {int((drawn < 12.0).sum())} of 50 values in "
                           "scenario startup put the reference above the input voltage"), text
    assert (drawn < 12.0).sum() > 0


def test_a_binding_value_the_fmu_refuses_is_refused_before_any_cluster_starts(tmp_path, buck_fmu):
    (tmp_path / "plant.toml").write_text(role_named_binding(buck_fmu, ("duty_cycle", "output_voltage", "inductor_current"),
                                                            parameters="inductance = -1\n"))
    path = sweep_file(tmp_path, 'scenarios = ["startup"]\ncontrollers = ["pi"]\nsamples = 2\n[plant]\n'
                                'binding = "plant.toml"\n[parameters]\ncapacitance = { tolerance = 0.2 }\n')
    out = tmp_path / "out"
    done = cli("sweep", str(path), "--out", str(out), "--workers", "1")
    cli_one_line_error(done, 2, "plant.toml:9: parameters.inductance = -1: the plant FMU refuses its set-up with this "
                                "value (fmi2SetReal failed (error) at t = 0 s: fmi2SetReal: inductance = -1 H is invalid")
    nothing_ran(out)


def test_an_axis_anchored_where_the_scenario_is_zero_is_refused_before_any_work(tmp_path):
    (tmp_path / "from_zero.toml").write_text('name = "from_zero"\nduration = 0.03\n[initial]\nreference = 0.0\n'
                                             '[[events]]\ntime = 0.01\nreference = 12.0\n')
    axis = "reference = {{ values = [10.0, 12.0]{} }}\n"
    path = sweep_file(tmp_path, 'scenarios = ["from_zero.toml"]\ncontrollers = ["pi"]\n[operating_point]\n'
                      + axis.format(""))
    assert plan_error(path) == ("study.toml:4: operating_point.reference: scenario from_zero's initial reference is 0, "
                                "which the axis cannot scale (it multiplies the scenario's reference by value / "
                                "anchored value): expected a scenario whose anchored value is not 0, or the other anchor")
    path.write_text(path.read_text().replace(axis.format(""), axis.format(', anchor = "final"')))
    plan = SweepPlan(load_sweep(path))  # anchored at its final 12 V: 0 -> 10 V and 0 -> 12 V
    scenario = plan.spec.scenarios[0]
    moved = at_operating_point(scenario, plan.values(scenario, 0, 0)[1], (("reference", "final"),))
    assert moved.initial["reference"] == 0.0 and moved.events[0].changes["reference"] == 10.0


def test_a_parameter_the_scenario_changes_during_the_run_is_not_swept(tmp_path):
    """capacitor_ageing sets the capacitance itself (its ageing events): a sweep of capacitance on it ran three
    identical units labelled 5, 10 and 20 uF. Refused, naming the axis, the scenario and the event's line."""
    path = sweep_file(tmp_path, 'scenarios = ["capacitor_ageing"]\ncontrollers = ["pi"]\n[parameters]\n'
                      'capacitance = { values = [5e-6, 10e-6, 20e-6] }\n')
    text = plan_error(path)
    assert text.startswith("study.toml:4: parameters.capacitance is swept, but scenario capacitor_ageing sets "
                           "capacitance at t = 0.00675 s (") and "capacitor_ageing.toml:" in text, text
    assert text.endswith("the event would replace the swept value -- sweep it on another scenario, or drop the axis")


def test_a_swept_value_orders_of_magnitude_off_its_nominal_is_taken_for_a_unit_slip(tmp_path):
    """inductance = 200 meant 200 uH: it ran at 200 H with 99.7 % steady-state error, the only hint in SWEEP.md."""
    path = sweep_file(tmp_path, 'scenarios = ["startup"]\ncontrollers = ["pi"]\n[parameters]\n'
                      'inductance = { values = [200, 220] }\n')
    text = plan_error(path)
    assert text.startswith("study.toml:4: parameters.inductance = 200 H is 9.1e+05 x its nominal 0.00022 H in ") and \
        text.endswith("expected values within 10000 x of it -- was it given in another unit?"), text
    path.write_text(path.read_text().replace("[200, 220]", "[200e-6, 220e-6]"))
    SweepPlan(load_sweep(path))  # the same study in henries plans


def test_a_folder_given_as_the_sweep_file_is_called_a_folder(tmp_path):
    folder = tmp_path / "d.toml"
    folder.mkdir()
    out = tmp_path / "out"
    done = cli("sweep", str(folder), "--out", str(out))
    line = cli_one_line_error(done, 2, "")
    assert line == f"error: sweep file {folder} is a folder: expected a file", line  # as run, export, ... say it
    assert not out.exists() and done.stdout == ""


def test_an_unreachable_or_malformed_scheduler_is_refused_before_any_work(tmp_path, capsys):
    import socket

    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    path = sweep_file(tmp_path, 'scenarios = ["startup"]\ncontrollers = ["pi"]\n[parameters]\n'
                                'inductance = { values = [200e-6, 240e-6] }\n')
    out = tmp_path / "out"
    code = main(["--no-progress", "sweep", str(path), "--out", str(out), "--scheduler", f"tcp://127.0.0.1:{port}",
                 "--scheduler-timeout", "1"])
    one_line_error(capsys, code, 2, f"cannot reach the dask scheduler at tcp://127.0.0.1:{port} within 1 s")
    assert not (out / "tuning").exists() and not (out / "dataset").exists()
    code = main(["--no-progress", "sweep", str(path), "--out", str(out), "--scheduler", "127.0.0.1:8786"])
    one_line_error(capsys, code, 2, "--scheduler '127.0.0.1:8786' is not a dask scheduler address: expected "
                                    "tcp://HOST:PORT")
    code = main(["--no-progress", "sweep", str(path), "--out", str(out), "--scheduler", "tcp://127.0.0.1:1",
                 "--workers", "2"])
    one_line_error(capsys, code, 2, "--workers sizes the local cluster")


def test_operating_point_axes_move_the_scenario_and_run_ids_hash_the_whole_run(tmp_path):
    from cosim.design.sweeps.recipes import ControllerRecipe
    from cosim.scenarios import load_scenario

    moved = at_operating_point(load_scenario("load_change", PAPER_SPEC),
                               {"load_resistance": 12.0, "input_voltage": 40.0})
    assert moved.initial["load_resistance"] == 12.0 and moved.initial["input_voltage"] == 40.0
    assert moved.events[0].changes == {"load_resistance": 10.0}  # 6 -> 5 Ohm becomes 12 -> 10 Ohm
    spec = parse_sweep('scenarios = ["startup", "load_change"]\ncontrollers = ["pi"]\nsamples = 3\n'
                       '[parameters]\ninductance = { tolerance = 0.2 }\nplant_mode = { values = [0, 1] }\n'
                       '[operating_point]\nload_resistance = { values = [6.0, 12.0] }\n'
                       'input_voltage = { tolerance = 0.1 }\n', tmp_path / "s.toml")
    plan = SweepPlan(spec)
    pi = ControllerRecipe("pi", "PI", 1e-3, '{"kp_per_V": 0.0015, "ki_per_V_s": 15.6, "tuning": {}}')
    runs = plan.runs([pi])
    assert len(runs) == 2 * 2 * 3 * 2 and len({r.run_id for r in runs}) == len(runs)
    assert {r.values["plant_mode"] for r in runs} == {0, 1} and all(isinstance(r.values["plant_mode"], int) for r in runs)
    assert {r.values["load_resistance"] for r in runs} == {6.0, 12.0}
    supplies = {r.values["input_voltage"] for r in runs}
    assert len(supplies) == 3 and all(43.2 <= v <= 52.8 for v in supplies)  # 48 V +- 10 %
    assert [r.run_id for r in SweepPlan(spec).runs([pi])] == [r.run_id for r in runs]  # the same spec, the same ids
    other = ControllerRecipe("pi", "PI", 1e-3, '{"kp_per_V": 0.0016, "ki_per_V_s": 15.6, "tuning": {}}')
    assert not {r.run_id for r in plan.runs([other])} & {r.run_id for r in runs}  # other gains, other runs
    tasks = plan.batches(runs)
    assert sorted(r.run_id for t in tasks for r in t.runs) == sorted(r.run_id for r in runs)
    assert all(len({(r.controller, r.scenario) for r in t.runs}) == 1 for t in tasks)


@pytest.mark.parametrize("name,runs", [("tolerance", 8000), ("tolerance-reproduction", 600), ("tolerance-fast", 1200)])
def test_the_shipped_studies_are_valid_against_the_built_in_plant(name, runs):
    from cosim.design.sweeps.spec import shipped_studies

    assert name in shipped_studies()
    spec = load_sweep(name)  # by name, like shipped scenarios
    plan = SweepPlan(spec)  # every axis against the FMU, every draw within its bounds
    assert spec.run_count == runs and spec.thresholds and plan.binding.tag == "nominal-switched"


def test_the_sweep_help_states_units_and_exit_codes(capsys):
    with pytest.raises(SystemExit) as done:
        main(["sweep", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert done.value.code == 0
    for phrase in ("--scheduler-timeout SECONDS", "tcp://HOST:PORT", "one per core", "SI: s, V, A, Ohm, H, F, Hz",
                   "Exit 2 on a mistake, before any work; 3 if some runs failed", "130 if interrupted"):
        assert phrase in text, phrase


def test_wilson_interval_and_the_spec_mask():
    assert wilson_interval(0, 12) == (0.0, pytest.approx(0.2425, abs=1e-4))
    low, high = wilson_interval(10, 20)
    assert low == pytest.approx(0.2993, abs=1e-4) and high == pytest.approx(0.7007, abs=1e-4)
    assert wilson_interval(20, 20)[1] == 1.0
    from cosim.design.sweeps.spec import Threshold

    rows = pd.DataFrame({"status": ["ok", "ok", "ok", "failed"], "overshoot_pct": [1.0, 6.0, 2.0, np.nan],
                         "settling_time_ms": [1.0, 1.0, np.nan, np.nan], "steady_state_error_pct": [-0.4, 0, 0, 0]})
    mask = spec_mask(rows, [Threshold("overshoot_pct", 5.0), Threshold("settling_time_ms", 2.0),
                            Threshold("steady_state_error_pct", 0.5)])
    assert mask.tolist() == [True, False, False, False]  # too much overshoot; never settles; failed


# ------------------------------------------------------------------------------------------ runs on clusters


def test_one_and_two_workers_give_the_same_rows_and_summary(tmp_path, nn_model, cluster, capsys):
    """1 worker (the command's own LocalCluster) and 2 (an existing cluster, as --scheduler): same
    rows, same parts, same summary; and the rows, the yield and the worst case say what they should."""
    local, client = cluster
    path = tolerance_study(tmp_path, nn_model, samples=5, extra="keep_traces = true")
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(["--no-progress", "sweep", str(path), "--out", str(one), "--workers", "1"]) == 0
    assert main(["--no-progress", "sweep", str(path), "--out", str(two), "--scheduler", local.scheduler_address]) == 0
    err = capsys.readouterr().err
    assert "on a LocalCluster of 1 worker process(es)" in err and f"the cluster at {local.scheduler_address} (2" in err
    a, b = rows_of(one), rows_of(two)
    pd.testing.assert_frame_equal(a, b)
    parts = sorted(p.relative_to(one) for p in (one / "dataset").rglob("*.parquet"))
    assert parts == sorted(p.relative_to(two) for p in (two / "dataset").rglob("*.parquet"))
    for part in parts:
        assert (one / part).read_bytes() == (two / part).read_bytes(), part
    for name in ("SWEEP.md", "yield.csv", "sweep.json", "figures/yield.png"):
        assert (one / name).read_bytes() == (two / name).read_bytes(), name

    # one row per run: 3 controllers x 2 scenarios x 5 units, partitioned by controller and scenario
    assert len(a) == 30 and a["run_id"].is_unique and set(a["status"]) == {"ok"} and a["error"].isna().all()
    assert {p.parts[1] for p in parts} == {"controller=PI", "controller=NNPC", "controller=MPC-nominal"}
    assert {p.parts[2] for p in parts} == {"scenario=startup", "scenario=load_change"}
    units = a.groupby(["point", "sample"])[["inductance", "capacitance", "capacitor_esr"]].nunique()
    assert (units == 1).all().all()  # every controller and scenario saw the same five units
    assert a["inductance"].between(176e-6, 264e-6).all() and a["capacitor_esr"].between(0, 0.1).all()
    schema = pq.read_schema(one / parts[0])
    assert schema.field("inductance").metadata == {b"unit": b"H"} and "controller" not in schema.names
    assert not any(c.startswith("controller_p") or c.startswith("wall") for c in a.columns)  # wall clock: timing/
    timing = dataset.read_timing(one)
    assert set(timing["run_id"]) == set(a["run_id"]) and (timing["wall_time_s"] > 0).all()
    # traces: the full table of each run, with its values in the metadata
    from cosim.results import read_run

    run = a[(a["controller"] == "PI") & (a["scenario"] == "startup")].iloc[0]
    trace = read_run(one / "traces" / f"{run['run_id']}.parquet")
    assert trace.complete and trace.metadata["sweep_run"]["values"]["inductance"] == run["inductance"]
    assert trace.metadata["plant"]["parameters"]["inductance"] == run["inductance"]

    # the yield table is the share of rows meeting every threshold, per unit over both scenarios too
    table = pd.read_csv(one / "yield.csv")
    spec = load_sweep(path)
    for controller in ("PI", "NNPC", "MPC-nominal"):
        mine = a[a["controller"] == controller].assign(meets=lambda f: spec_mask(f, spec.thresholds))
        for scenario in ("startup", "load_change"):
            row = table[(table["controller"] == controller) & (table["scenario"] == scenario)].iloc[0]
            assert row["meet_spec"] == mine.loc[mine["scenario"] == scenario, "meets"].sum()
        per_unit = mine.groupby(["point", "sample"])["meets"].all()
        row = table[(table["controller"] == controller) & (table["scenario"] == "all scenarios (per unit)")].iloc[0]
        assert row["runs"] == 5 and row["meet_spec"] == per_unit.sum()
    text = (one / "SWEEP.md").read_text()
    for heading in ("## What was swept", "## Yield", "## Distributions", "## Most influential parameter",
                    "## Worst case", "## Failed runs"):
        assert heading in text
    # the worst NNPC start-up is its run with the largest overshoot / 5 % (the binding threshold)
    nn = a[(a["controller"] == "NNPC") & (a["scenario"] == "startup")]
    worst = nn.loc[nn["overshoot_pct"].idxmax()]
    assert f"| startup | NNPC | {worst['run_id']} | ok |" in text
    for figure in ("yield", "distributions__startup", "influence__load_change"):
        assert (one / "figures" / f"{figure}.png").read_bytes()[:4] == b"\x89PNG"

    # the folder holds this sweep, complete: a second start is a no-op (no cluster, no run, the same summary);
    # another sweep is refused there, a changed spec cannot resume it, and resuming the same sweep runs nothing again
    before = {p: p.stat().st_mtime_ns for p in (one / "dataset").rglob("*.parquet")}
    summary = (one / "SWEEP.md").read_bytes()
    assert main(["--no-progress", "sweep", str(path), "--out", str(one), "--workers", "1"]) == 0
    assert "all 30 runs are in" in capsys.readouterr().err and (one / "SWEEP.md").read_bytes() == summary
    assert {p: p.stat().st_mtime_ns for p in (one / "dataset").rglob("*.parquet")} == before
    changed = tolerance_study(tmp_path, nn_model, samples=6, extra="keep_traces = true", name="changed.toml")
    code = main(["--no-progress", "sweep", str(changed), "--out", str(one)])
    one_line_error(capsys, code, 2, f"{one} already holds another sweep (id ")
    code = main(["--no-progress", "sweep", str(changed), "--out", str(one), "--resume"])
    one_line_error(capsys, code, 2, "(changed: samples): resume with the original file, or choose another --out")
    assert main(["--no-progress", "sweep", str(path), "--out", str(one), "--resume", "--scheduler",
                 local.scheduler_address]) == 0
    assert "30 done earlier, kept (--resume); running 0 in 0 task(s)" in capsys.readouterr().err
    assert {p: p.stat().st_mtime_ns for p in (one / "dataset").rglob("*.parquet")} == before


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(parent, []).append(int(entry.name))
    found, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.add(child)
            todo.append(child)
    return found


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}").exists() and "Z" not in (Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1][:3])


def _dask_cluster(folder: Path) -> tuple[str, list[subprocess.Popen]]:
    """``dask scheduler`` and one ``dask worker`` on the loopback interface, each in its own session; the
    scheduler's address. The scheduler picks its own port (0) and writes it to a scheduler file in ``folder``:
    a port probed free here could be taken by another process (make test runs two) before the scheduler binds it."""
    import json

    dask = str(Path(sys.executable).with_name("dask"))
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "stdin": subprocess.DEVNULL,
             "start_new_session": True}
    folder.mkdir(parents=True, exist_ok=True)
    file = folder / "scheduler.json"
    scheduler = subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                  "--scheduler-file", str(file)], **quiet)
    address, deadline = None, time.time() + 60
    while address is None:
        try:
            address = json.loads(file.read_text())["address"]
        except (OSError, ValueError, KeyError):  # not written yet, or half-written
            if time.time() > deadline or scheduler.poll() is not None:
                _stop([scheduler])
                raise RuntimeError(f"the dask scheduler wrote no address to {file} within 60 s") from None
            time.sleep(0.05)
    worker = subprocess.Popen([dask, "worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                               "--host", "127.0.0.1"], **quiet)
    return address, [scheduler, worker]


def _stop(processes: list[subprocess.Popen]) -> None:
    for process in processes:
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        process.wait(timeout=30)


def long_startup_sweep(tmp_path, duration: float, samples: int):
    """A sweep file of ``samples`` PI start-ups of ``duration`` [s] on the switched plant with L +-20 %, two runs a
    task: long enough to be interrupted part-way."""
    (tmp_path / "long_startup.toml").write_text(f'name = "long_startup"\nduration = {duration}\n[initial]\n'
                                                'reference = 12.0\n')
    return sweep_file(tmp_path, f"""\
        scenarios = ["long_startup.toml"]
        samples = {samples}
        batch_size = 2
        [[controllers]]
        kind = "pi"
        {PI_GAINS.replace(', ', chr(10) + '        ')}
        [plant]
        mode = "switched"
        [parameters]
        inductance = {{ tolerance = 0.2 }}
        """)


def test_a_scheduler_that_dies_mid_sweep_keeps_every_part_and_resume_finishes_on_a_new_one(tmp_path):
    """A sweep on a cluster of one's own (``dask scheduler`` + ``dask worker``) whose scheduler is killed
    after the first parts: one line saying so, how many runs are in and how to finish, exit 5 -- and no
    run written as failed (dask cancels the pending tasks; that is no fault of theirs). ``--resume`` against
    a new scheduler runs exactly the rest: every run in the dataset once, none computed twice."""
    path = long_startup_sweep(tmp_path, duration=0.02, samples=24)
    out = tmp_path / "out"
    address, cluster = _dask_cluster(tmp_path / "cluster")
    assert address.startswith("tcp://127.0.0.1:")
    try:
        sweep = subprocess.Popen([sys.executable, "-m", "cosim.cli", "--no-progress", "sweep", str(path), "--out",
                                  str(out), "--scheduler", address, "--scheduler-timeout", "60"],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL)
        deadline = time.time() + 180
        while not list((out / "dataset").rglob("part-*.parquet")) and time.time() < deadline and sweep.poll() is None:
            time.sleep(0.05)
        assert sweep.poll() is None, "the sweep ended before the scheduler died"
        _stop(cluster[:1])  # the scheduler dies; its worker is left looking for it
        _, err = sweep.communicate(timeout=120)
    finally:
        _stop(cluster)
    lines = [line for line in err.splitlines() if line.strip()]
    assert sweep.returncode == 5, err
    assert [line for line in lines if line.startswith("error:")] == lines[-1:] and "Traceback" not in err, err
    kept = dataset.done_run_ids(out)
    assert 1 <= len(kept) < 24
    assert lines[-1].startswith(f"error: sweep stopped: the dask scheduler (the cluster at {address} "
                                f"(1 worker(s))) went away; {len(kept)} of 24 runs are in {out}/dataset (every part "
                                "complete); start a scheduler and workers again and run the same command with "
                                f"--resume (--scheduler ADDRESS for a new address) to finish the other {24 - len(kept)}")
    assert (dataset.read_rows(out)["status"] == "ok").all()  # the cancelled tasks left no rows
    no_temporary_files(out)
    before = {p: p.stat().st_mtime_ns for p in (out / "dataset").rglob("part-*.parquet")}
    address, cluster = _dask_cluster(tmp_path / "new-cluster")
    try:
        done = subprocess.run([sys.executable, "-m", "cosim.cli", "--no-progress", "sweep", str(path), "--out",
                               str(out), "--resume", "--scheduler", address, "--scheduler-timeout", "60"],
                              capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=300)
    finally:
        _stop(cluster)
    assert done.returncode == 0, done.stderr
    rows = dataset.read_rows(out)
    assert len(rows) == rows["run_id"].nunique() == 24 and (rows["status"] == "ok").all()
    assert all(p.stat().st_mtime_ns == t for p, t in before.items())  # the kept parts were not rewritten


@pytest.mark.parametrize("interrupt", ["SIGTERM to the process", "Ctrl-C: SIGINT to the process group"])
def test_an_interrupt_shuts_the_cluster_down_and_resume_finishes_without_recomputing(tmp_path, cluster, interrupt):
    """SIGTERM (a batch system) or Ctrl-C (the terminal signals every process of the group, the
    workers too): exit 130 in one line, no worker outlives the sweep, only complete parts; --resume
    runs exactly the rest and writes nothing that was done."""
    local, _ = cluster
    path = long_startup_sweep(tmp_path, duration=0.1, samples=40)
    out = tmp_path / "out"
    group = interrupt.startswith("Ctrl-C")
    process = subprocess.Popen([sys.executable, "-m", "cosim.cli", "--no-progress", "sweep", str(path), "--out",
                                str(out), "--workers", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               stdin=subprocess.DEVNULL, start_new_session=group,
                               preexec_fn=(lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)) if group else None)
    deadline = time.time() + 120
    while not list((out / "dataset").rglob("part-*.parquet")) and time.time() < deadline:
        time.sleep(0.05)
    workers = _descendants(process.pid)
    assert process.poll() is None and len(workers) >= 2, "the sweep ended before the interrupt"
    if group:
        os.killpg(process.pid, signal.SIGINT)
    else:
        process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines[-1].startswith("error: sweep interrupted: ") and "run the same command with --resume to finish the other" \
        in lines[-1] and "Traceback" not in err, err
    assert [line for line in lines if line.startswith("error:")] == lines[-1:]
    deadline = time.time() + 20
    while any(_alive(pid) for pid in workers) and time.time() < deadline:
        time.sleep(0.1)
    assert not [pid for pid in workers if _alive(pid)], "worker processes outlived the interrupted sweep"
    no_temporary_files(out)
    done = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in (out / "dataset").rglob("part-*.parquet")}
    kept = len(dataset.done_run_ids(out))
    assert 1 <= kept < 40 and f"{kept} of 40 runs are in" in lines[-1]

    from cosim.design.sweeps.sweep import run_sweep

    outcome = run_sweep(path, out, scheduler=local.scheduler_address, resume=True)
    assert outcome.done_before == kept and outcome.computed == 40 - kept and outcome.failed == 0
    for part, (content, mtime) in done.items():  # nothing done was written again
        assert part.read_bytes() == content and part.stat().st_mtime_ns == mtime
    rows = dataset.read_rows(out)
    ids = [i for p in (out / "dataset").rglob("part-*.parquet") for i in pq.read_table(p).column("run_id").to_pylist()]
    assert len(ids) == len(set(ids)) == len(rows) == 40 and set(rows["status"]) == {"ok"}


def test_a_worker_killed_mid_sweep_loses_and_duplicates_no_run(tmp_path, cluster):
    local, client = cluster
    path = sweep_file(tmp_path, f"""\
        scenarios = ["startup", "load_change"]
        samples = 24
        batch_size = 2
        [[controllers]]
        kind = "pi"
        {PI_GAINS.replace(', ', chr(10) + '        ')}
        [plant]
        mode = "switched"
        [parameters]
        capacitance = {{ tolerance = 0.2 }}
        """)
    out = tmp_path / "out"
    killed = []

    def kill_a_busy_worker():  # as an OOM killer or a crash would: SIGKILL, while it runs a task
        deadline = time.time() + 120
        while not list((out / "dataset").rglob("part-*.parquet")) and time.time() < deadline:
            time.sleep(0.01)
        pids = client.run(os.getpid)
        busy = [address for address, keys in client.processing().items() if keys]
        if busy:
            os.kill(pids[busy[0]], signal.SIGKILL)
            killed.append(busy[0])

    from cosim.design.sweeps.sweep import run_sweep

    killer = threading.Thread(target=kill_a_busy_worker)
    killer.start()
    outcome = run_sweep(path, out, scheduler=local.scheduler_address)
    killer.join()
    assert killed, "no worker was busy when the first part landed"
    assert outcome.computed == outcome.planned == 48 and outcome.failed == 0
    ids = [i for p in (out / "dataset").rglob("part-*.parquet") for i in pq.read_table(p).column("run_id").to_pylist()]
    assert len(ids) == len(set(ids)) == 48
    client.wait_for_workers(2, timeout=60)  # the nanny started a new worker


@pytest.mark.parametrize("isolate", [True, False])
def test_failing_runs_are_rows_with_their_cause_and_the_exit_code_says_so(tmp_path, faulty_fmu, capsys, isolate):
    """The FMU dereferences NULL, discards a step, its output turns NaN: each is one failed row with the
    cause, and the other runs -- one of them after the crash in the same batch -- complete; the command
    exits 3. Isolated (a binding file's default) the crash is the plant process's: the row names the
    signal and the time and the worker goes on. In-process it kills the worker: dask reruns the task,
    the task is split into single runs, and the crashing one is a row saying the worker died."""
    (tmp_path / "faulty.toml").write_text(("" if isolate else "isolate = false\n") + faulty_binding(faulty_fmu))
    (tmp_path / "short.toml").write_text('name = "short"\nduration = 0.02\n[initial]\nreference = 12.0\n')
    path = sweep_file(tmp_path, """\
        scenarios = ["short.toml"]
        record_period = 1e-4
        batch_size = 4
        controllers = [{ kind = "pi", kp = 0.0, ki = 14.0 }]
        [plant]
        binding = "faulty.toml"
        [parameters]
        fault_kind = { values = [4, 0, 1, 3] }
        fault_time = { values = [0.0103] }
        """)
    out = tmp_path / "out"
    code = main(["--no-progress", "sweep", str(path), "--out", str(out), "--workers", "2"])
    ends_in_one_line_error(capsys, code, 3, f"3 of 4 runs failed (status 'failed' in {out}/dataset, causes in {out}/SWEEP.md); "
                                    "the other 1 runs and the summary are complete")
    rows = dataset.read_rows(out).set_index("fault_kind").sort_index()
    assert rows.loc[0, "status"] == "ok" and pd.isna(rows.loc[0, "error"])
    assert rows.loc[0, "steady_state_error_pct"] == pytest.approx(0.0, abs=0.5)
    assert "fmi2DoStep failed (discard) at t = 0.0103" in rows.loc[1, "error"]
    assert "plant output became non-finite at t = 0.0104 s (output_voltage = nan)" in rows.loc[3, "error"]
    if isolate:
        assert "the FMU crashed the plant process (signal SIGSEGV) while stepping at t = 0.0104 s" in rows.loc[4, "error"]
    else:
        assert rows.loc[4, "error"].startswith("the worker process running it died each time it ran")
    assert rows.loc[rows["status"] == "failed", "iae_Vs"].isna().all()
    text = (out / "SWEEP.md").read_text()
    assert "3 run(s) failed" in text and "fmi2DoStep failed (discard)" in text
    no_temporary_files(out)


def test_a_hanging_run_and_a_run_out_of_memory_are_rows_and_the_rest_complete(tmp_path, faulty_fmu, capsys):
    """Isolated plants with limits: a doStep that never returns is stopped at the binding's step_timeout, a
    plant process that allocates without bound at its memory_limit; each is one failed row naming the FMU,
    the time and the limit, and the other runs (a fault time after the run's end: no fault), in the same
    batches, complete (exit 3)."""
    (tmp_path / "faulty.toml").write_text("step_timeout = 2.0\nmemory_limit = 600\n" + faulty_binding(faulty_fmu))
    (tmp_path / "short.toml").write_text('name = "short"\nduration = 0.02\n[initial]\nreference = 12.0\n')
    path = sweep_file(tmp_path, """\
        scenarios = ["short.toml"]
        record_period = 1e-4
        batch_size = 3
        controllers = [{ kind = "pi", kp = 0.0, ki = 14.0 }]
        [plant]
        binding = "faulty.toml"
        [parameters]
        fault_kind = { values = [5, 0, 6] }
        fault_time = { values = [0.0103, 1.0] }
        """)
    out = tmp_path / "out"
    code = main(["--no-progress", "sweep", str(path), "--out", str(out), "--workers", "2"])
    ends_in_one_line_error(capsys, code, 3, "2 of 6 runs failed")
    rows = dataset.read_rows(out).set_index(["fault_kind", "fault_time"]).sort_index()
    failed = rows[rows["status"] == "failed"]
    assert list(failed.index) == [(5, 0.0103), (6, 0.0103)]
    hang, hoard = failed["error"]
    assert (f"the FMU {faulty_fmu.name} did not finish stepping from t = 0.0103 s to 0.0104 s within the step time "
            "limit of 2 s (step_timeout); its process was stopped") in hang
    assert f"the FMU {faulty_fmu.name}'s process used " in hoard and "above the memory limit of 600 MB" in hoard
    complete = rows[rows["status"] == "ok"]
    assert len(complete) == 4 and complete["steady_state_error_pct"].abs().max() < 0.5
    no_temporary_files(out)


def _plant_kind(recipe, queue) -> None:
    from controllers.pi import PIController
    from cosim.design.sweeps.worker import _plant
    from cosim.master import run
    from cosim.scenarios import parse_scenario

    plant, binding = _plant(recipe)
    scenario = parse_scenario('name = "s"\nduration = 0.002\n[initial]\nreference = 12.0\n', spec=PAPER_SPEC)
    metadata = run(plant, PIController(0.0, 14.0, 1e-3), scenario).metadata
    queue.put((type(plant).__name__, binding.isolate, metadata["plant"]["isolated"]))
    plant.close()


def test_a_daemonic_worker_steps_an_isolated_binding_in_process(tmp_path, faulty_fmu):
    """dask's default workers are daemonic and cannot start the isolated plant's process: there the
    plant runs in the worker (the workbench's own LocalCluster is non-daemonic and keeps isolation), and
    the run's metadata says so: "isolated" states what was run, not what the binding asked for."""
    import multiprocessing

    from cosim.design.sweeps.recipes import PlantRecipe
    from cosim.fmi.binding_file import load_binding

    (tmp_path / "plant.toml").write_text(faulty_binding(faulty_fmu, 0))
    recipe = PlantRecipe.of(load_binding(tmp_path / "plant.toml"))
    assert recipe.isolate is True and recipe.binding(faulty_fmu).isolate is True
    kinds = {}
    for daemon in (True, False):
        queue = multiprocessing.get_context("fork").Queue()
        process = multiprocessing.get_context("fork").Process(target=_plant_kind, args=(recipe, queue), daemon=daemon)
        process.start()
        kinds[daemon] = queue.get(timeout=60)
        process.join(timeout=60)
    assert kinds == {True: ("CoSimulationPlant", False, False),  # in the worker process, and said so
                     False: ("IsolatedPlant", True, True)}  # in its own


# ------------------------------------------------------------------------------------------ controller FMUs


PI_KP, PI_KI = 0.0015, 15.6


def bound_pi(fmu: str) -> str:
    """A controller-binding file for the exported PI ``fmu``, its sample period bound to the FMU's own."""
    return role_named_binding(fmu, CONTROLLER_ROLES + ("sample_period",), label="PI (bound)")


@pytest.fixture(scope="module")
def pi_fmu(tmp_path_factory) -> Path:
    """The PI of PI_GAINS exported as a controller FMU at 1 ms, as a user would export it."""
    folder = tmp_path_factory.mktemp("pi-fmu")
    assert main(["--no-progress", "export-controller", "pi", "--kp", str(PI_KP), "--ki", str(PI_KI),
                 "--control-period", "1e-3", "--out", str(folder / "my_pi.fmu"), "--work-dir", str(folder / "work")]) == 0
    return folder / "my_pi.fmu"


def fmu_study(folder: Path, fmu: Path, extra: str = "", controllers: str | None = None) -> Path:
    """A small tolerance study of the built-in PI (PI_GAINS) next to controller FMUs in ``folder``."""
    import shutil

    if fmu.parent != folder:
        shutil.copy(fmu, folder / fmu.name)
    (folder / "bound.toml").write_text(bound_pi(fmu.name))
    controllers = controllers if controllers is not None else f"""
        [[controllers]]
        kind = "pi"
        {PI_GAINS.replace(', ', chr(10) + '        ')}
        [[controllers]]
        kind = "fmu"
        path = "{fmu.name}"
        [[controllers]]
        kind = "fmu"
        path = "bound.toml"
        """
    return sweep_file(folder, f"""\
        scenarios = ["startup", "load_change"]
        samples = 3
        seed = 5
        {extra}
        [plant]
        mode = "switched"
        [parameters]
        inductance = {{ tolerance = 0.2 }}
        capacitance = {{ tolerance = 0.2 }}
        [operating_point]
        input_voltage = {{ tolerance = 0.1 }}
        {controllers}""")


def test_a_controller_fmu_travels_as_bytes_and_is_rebuilt_from_them(tmp_path, pi_fmu):
    """The recipe holds the FMU's bytes (and a binding file's content), no path of this machine; the
    digest covers the bytes; the build needs only the recipe, and the C-twin step leaves the FMU as it is."""
    import pickle

    from cosim.design.sweeps.designs import build, design
    from cosim.design.sweeps.recipes import ControllerRecipe
    from cosim.fmi.controller import FmuController

    path = fmu_study(tmp_path, pi_fmu)
    spec = load_sweep(path)
    assert [(c.kind, c.name) for c in spec.controllers] == [("pi", "PI"), ("fmu", "my_pi (FMU)"), ("fmu", "PI (bound)")]
    plan = SweepPlan(spec)
    _, given, bound = design(spec.controllers, plan.binding, spec.control_period, tmp_path / "out")
    blob = (tmp_path / "my_pi.fmu").read_bytes()
    assert given.blob == bound.blob == blob and given.settings["binding"] is None
    assert bound.settings["binding"]["label"] == "PI (bound)" and bound.settings["binding"]["file"] == "bound.toml"
    for recipe in (given, bound):
        assert str(tmp_path).encode() not in pickle.dumps(recipe)
    other = ControllerRecipe(given.kind, given.name, given.control_period, given.settings_json, blob + b"\0")
    assert other.digest != given.digest  # the digest covers the bytes
    assert given.describe()["fmu_sha256"] == given.blob_digest
    (tmp_path / "my_pi.fmu").unlink()  # as on a worker that never saw the file
    for recipe in (given, bound):
        for implementation in ("c", "python"):
            controller = build(recipe, plan.binding, implementation)
            try:
                assert isinstance(controller, FmuController) and controller.name == recipe.name
                assert controller.sample_period == 1e-3 and not str(controller.binding.fmu_path).startswith(str(tmp_path))
            finally:
                controller.close()
    from cosim.design.sweeps.worker import process_file

    assert process_file("my_pi.fmu", blob, given.blob_digest) == process_file("my_pi.fmu", blob, given.blob_digest)


def test_a_swept_pi_fmu_gives_the_built_in_pis_metrics_unit_by_unit(tmp_path, pi_fmu, cluster):
    """The PI given by gains and the same PI exported as an FMU (directly and through a binding
    file): per unit and scenario the same metrics, on a cluster of two worker processes."""
    from cosim.design.sweeps.sweep import run_sweep
    from cosim.design.sweeps.worker import DETERMINISTIC_METRICS

    local, _ = cluster
    path = fmu_study(tmp_path, pi_fmu)
    out = tmp_path / "out"
    outcome = run_sweep(path, out, scheduler=local.scheduler_address)
    assert outcome.planned == outcome.computed == 18 and outcome.failed == 0
    rows = dataset.read_rows(out)
    assert set(rows["status"]) == {"ok"} and set(rows["controller"]) == {"PI", "my_pi (FMU)", "PI (bound)"}
    key = ["scenario", "point", "sample"]
    pi = rows[rows["controller"] == "PI"].set_index(key).sort_index()
    for name in ("my_pi (FMU)", "PI (bound)"):
        fmu = rows[rows["controller"] == name].set_index(key).sort_index()
        assert fmu.index.equals(pi.index) and len(fmu) == 6
        for column in ("inductance", "capacitance", "input_voltage"):  # the same units
            np.testing.assert_array_equal(fmu[column], pi[column])
        for metric in DETERMINISTIC_METRICS:  # duty equal to 1e-9: metrics equal to far below their resolution
            np.testing.assert_allclose(fmu[metric], pi[metric], rtol=1e-6, atol=1e-9, err_msg=f"{name}: {metric}")
    text = (out / "SWEEP.md").read_text()
    assert "*my_pi (FMU)* (fmu): controller FMU my_pi.fmu (SHA-256 " in text
    assert "through controller-binding file bound.toml" in text
    no_temporary_files(out)


@pytest.mark.parametrize("controllers,message", [
    ('[[controllers]]\nkind = "fmu"\npath = "nowhere.fmu"\n',
     "study.toml:4: controllers[0].path = 'nowhere.fmu': controller FMU {tmp}/nowhere.fmu does not exist"),
    ('[[controllers]]\nkind = "fmu"\npath = "nowhere.toml"\n',
     "study.toml:4: controllers[0].path = 'nowhere.toml': controller-binding file {tmp}/nowhere.toml does not exist"),
    ('[[controllers]]\nkind = "fmu"\npath = "plain.fmu"\n',
     "study.toml:4: controllers[0].path = 'plain.fmu': FMU {tmp}/plain.fmu is not a zip archive"),
    ('[[controllers]]\nkind = "fmu"\npath = "plant.fmu"\n',
     "study.toml:4: controllers[0].path = 'plant.fmu': controller FMU {tmp}/plant.fmu has no variable 'reference': "
     "a controller FMU without the workbench's role names needs a controller-binding file"),
    ('[[controllers]]\nkind = "fmu"\npath = "wrong.toml"\n',
     "study.toml:4: controllers[0].path = 'wrong.toml': {tmp}/wrong.toml:4: role 'reference' names variable 'Vref', "
     "which my_pi.fmu does not have"),
    ('[[controllers]]\nkind = "fmu"\npath = "my_pi.zip"\n',
     "study.toml:4: controllers[0].path = 'my_pi.zip' is invalid: expected a controller FMU (.fmu) or a "
     "controller-binding file (.toml)"),
    ('control_period = 2e-3\n[[controllers]]\nkind = "fmu"\npath = "my_pi.fmu"\n',
     "study.toml:5: controllers[0].path = 'my_pi.fmu': the controller FMU's sample period is 0.001 s, but the "
     "sweep's control_period = 0.002 s (study.toml:2): a sweep runs every controller at its control_period"),
    ('[[controllers]]\nkind = "fmu"\n', 'study.toml:3: controllers[0]: kind "fmu" needs path = "NAME.fmu"'),
    ('controllers = ["fmu"]\n', 'study.toml:2: controllers[0]: kind "fmu" needs path = "NAME.fmu"'),
    ('[[controllers]]\nkind = "fmu"\npath = "my_pi.fmu"\nkp = 0.1\n',
     "study.toml:5: controllers[0].kp does not apply to fmu: expected name, path"),
    ('[[controllers]]\nkind = "fmu"\npath = "my_pi.fmu"\nmodel = "nn.pt"\n',
     "study.toml:5: controllers[0].model does not apply to fmu: expected name, path"),
    ('[[controllers]]\nkind = "pi"\npath = "my_pi.fmu"\n',
     "study.toml:4: controllers[0].path does not apply to pi: expected ki, kp, name"),
    ('[[controllers]]\nkind = "fmu"\npath = "my_pi.fmu"\n[[controllers]]\nkind = "fmu"\npath = "my_pi.fmu"\n',
     "study.toml:6: controller name 'my_pi (FMU)' is used twice: give the second one a name"),
])
def test_controller_fmu_mistakes_name_file_key_and_line(tmp_path, pi_fmu, buck_fmu, controllers, message):
    import shutil

    shutil.copy(pi_fmu, tmp_path / "my_pi.fmu")
    shutil.copy(buck_fmu, tmp_path / "plant.fmu")
    (tmp_path / "plain.fmu").write_text("not a zip archive\n")
    (tmp_path / "wrong.toml").write_text(bound_pi("my_pi.fmu").replace('variable = "reference"',
                                                                                   'variable = "Vref"'))
    path = sweep_file(tmp_path, 'scenarios = ["startup"]\n' + controllers)
    with pytest.raises(ConfigError) as caught:
        load_sweep(path)
    text = str(caught.value)
    assert "\n" not in text and message.format(tmp=tmp_path) in text.replace(f"{tmp_path}/study.toml", "study.toml"), text


def test_a_controller_fmu_mistake_stops_the_sweep_before_any_work(tmp_path, pi_fmu, capsys):
    path = fmu_study(tmp_path, pi_fmu, extra='control_period = "1/75e3"')
    out = tmp_path / "out"
    code = main(["--no-progress", "sweep", str(path), "--out", str(out), "--workers", "1"])
    one_line_error(capsys, code, 2, "controllers[1].path = 'my_pi.fmu': the controller FMU's sample period is 0.001 "
                                    "s, but the sweep's control_period = 1.33333e-05 s")
    assert not out.exists()


def test_a_sweep_file_chooses_a_predictive_controllers_optimizer_and_rti_settings(tmp_path):
    """optimizer and rti = { ... } of a [[controllers]] table reach the controller each worker builds (through the
    recipe), and leave the recipes of the controllers that give none as they were."""
    from dataclasses import replace

    from cosim.design.experiments import SWITCHING_PERIOD_RTI
    from cosim.design.sweeps.designs import build, design

    path = sweep_file(tmp_path, """\
        scenarios = ["startup"]
        control_period = "1/75e3"
        [[controllers]]
        kind = "mpc-nominal"
        name = "MPC (search)"
        optimizer = "search"
        [[controllers]]
        kind = "mpc-nominal"
        name = "MPC (plain RTI step)"
        rti = { reweightings = 0, smoothing = 0.02 }
        [[controllers]]
        kind = "mpc-nominal"
        """)
    spec = load_sweep(path)
    assert [(c.optimizer, dict(c.rti)) for c in spec.controllers] == \
        [("search", {}), ("rti", {"reweightings": 0, "smoothing": 0.02}), (None, {})]
    plan = SweepPlan(spec)
    recipes = design(spec.controllers, plan.binding, spec.control_period, tmp_path / "out")
    built = [build(recipe, plan.binding, "python") for recipe in recipes]
    assert built[0].rti is None
    assert built[1].rti == replace(SWITCHING_PERIOD_RTI, reweightings=0, smoothing=0.02)
    assert built[2].rti == SWITCHING_PERIOD_RTI and set(recipes[2].settings) == {"circuit"}
    # the C twin each worker runs by default gets them too
    twins = [build(recipe, plan.binding, "c").config.rti for recipe in recipes]
    assert twins[0].enabled == 0
    assert (twins[1].enabled, twins[1].reweightings, twins[1].smoothing) == (1, 0, 0.02)
    assert (twins[2].reweightings, twins[2].smoothing) == (SWITCHING_PERIOD_RTI.reweightings, 0.05)
    assert spec.controllers[1].describe()["rti"] == {"reweightings": 0, "smoothing": 0.02}
    assert "optimizer" not in spec.controllers[2].describe() and "rti" not in spec.controllers[2].describe()


def test_a_swept_nnpc_plans_with_the_optimizer_its_key_has_on_the_command_line():
    """nnpc-paper plans with the search in a sweep as in the reproduction and `run` (the paper's network), nnpc with
    the rate's RTI (cosim.design.experiments.own_optimizer)."""
    from cosim.design.experiments import SWITCHING_PERIOD_RTI
    from cosim.design.plants import plant_binding
    from cosim.design.sweeps.designs import build
    from cosim.design.sweeps.recipes import ControllerRecipe
    from cosim.design.vocabulary import SWITCHING_PERIOD

    blob = (Path(__file__).parent / "fixtures" / "nnpc_nominal_averaged_13p33us.pt").read_bytes()
    binding = plant_binding("nominal", "averaged")
    built = {kind: build(ControllerRecipe(kind, kind, SWITCHING_PERIOD, "{}", blob), binding, "python")
             for kind in ("nnpc", "nnpc-paper")}
    assert built["nnpc"].rti == SWITCHING_PERIOD_RTI and built["nnpc-paper"].rti is None
    # a sweep file's nnpc-paper says so in its description (the sweep's id), nnpc keeps the description it had
    spec = parse_sweep('scenarios = ["startup"]\ncontrollers = ["nnpc", "nnpc-paper"]\n', Path("study.toml"))
    assert [c.describe().get("optimizer") for c in spec.controllers] == [None, "search"]
