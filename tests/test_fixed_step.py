"""Fixed-step plant FMUs, as exporting tools make them: canHandleVariableCommunicationStepSize="false", the step in
DefaultExperiment stepSize, any other step refused (tests/corpus/fixed_step_buck.py, FMI 2.0 with pythonfmu, and
fixed_step_buck3.py, FMI 3.0 with pythonfmu3). The master steps such an FMU by its one step for the whole run; what
cannot lie on that step's grid is refused in one line before anything runs (cosim/fmi/communication.py)."""

from __future__ import annotations

from pathlib import Path

import fmpy
import pandas as pd
import pytest
from conftest import CORPUS, cli, one_line_error, role_named_binding
from test_fmi3 import BUCK2, BUCK3, bound

from controllers.pi import PIController
from cosim.base.errors import ConfigError, PlantError
from cosim.fmi.binding_file import load_binding
from cosim.fmi.communication import FROM_CONTROL_PERIOD, FROM_DEFAULT_EXPERIMENT, CommunicationStep, record_period_for
from cosim.fmi.inspect import describe_fmu
from cosim.fmi.plant import open_plant
from cosim.master import check_rates, communication_of, simulate
from cosim.scenarios import PAPER_SCENARIOS, load_scenario

STEP = 1e-5  # [s] the corpus FMUs' fixed step
PI_GAINS = (0.0017, 15.6)


def _build(tmp_path_factory, script: str, twin: str, fmi_version: int, variable: bool) -> Path:
    if fmi_version == 2:
        from pythonfmu.builder import FmuBuilder
    else:
        from pythonfmu3.builder import FmuBuilder
    out = tmp_path_factory.mktemp(f"fixed_step{fmi_version}")
    return Path(FmuBuilder.build_FMU(CORPUS / script, dest=out, project_files=[CORPUS / twin, CORPUS / "buck_math.py"],
                                     canHandleVariableCommunicationStepSize=variable))


@pytest.fixture(scope="session")
def fixed_step_buck(tmp_path_factory) -> Path:
    return _build(tmp_path_factory, "fixed_step_buck.py", "python_buck.py", 2, variable=False)


@pytest.fixture(scope="session")
def fixed_step_buck3(tmp_path_factory) -> Path:
    return _build(tmp_path_factory, "fixed_step_buck3.py", "python_buck3.py", 3, variable=False)


@pytest.fixture
def pairs(tmp_path, fixed_step_buck, fixed_step_buck3, python_buck_fmu, python_buck3_fmu):
    """Per FMI version: (the fixed-step FMU's binding, the same model's variable-step FMU stepped by `step` = 10 us)."""
    return {2: (bound(tmp_path, BUCK2, fixed_step_buck, "fixed2.toml"),
                bound(tmp_path, "step = 1e-5\n" + BUCK2, python_buck_fmu, "variable2.toml")),
            3: (bound(tmp_path, BUCK3, fixed_step_buck3, "fixed3.toml"),
                bound(tmp_path, "step = 1e-5\n" + BUCK3, python_buck3_fmu, "variable3.toml"))}


@pytest.mark.parametrize("fmi_version", [2, 3])
def test_the_corpus_fmus_declare_a_fixed_step_and_refuse_any_other(fmi_version, pairs):
    """What makes the FMUs below a test of the master: the flag false, the step declared, and a step of another
    length fails inside the FMU (stepped here without the master's fixed step)."""
    binding = load_binding(pairs[fmi_version][0])
    md = fmpy.read_model_description(str(binding.fmu_path))
    assert md.fmiVersion.startswith(str(fmi_version))
    assert md.coSimulation.canHandleVariableCommunicationStepSize is False
    assert float(md.defaultExperiment.stepSize) == STEP
    assert ("fixed step: the workbench steps it by 1e-05 s (its DefaultExperiment stepSize) unless a binding gives "
            "step") in describe_fmu(binding.fmu_path)
    with open_plant(binding) as plant:
        plant.initialize([0.25, 48.0, 6.0])
        plant.use_step(STEP)
        plant.advance_to(3 * STEP)  # three steps of 10 us
        plant.use_step(None)
        with pytest.raises(PlantError, match=rf"fmi{fmi_version}DoStep failed \(\w+\) at t = 3e-05 s: fixed-step model: "
                                             r"communication step 1\.99+\d*e-05 s at t = 3\.0+\d*e-05 s, expected 1e-05"):
            plant.advance_to(5 * STEP)


def test_the_communication_step_comes_from_the_binding_then_the_fmu_then_the_control_period(pairs, fixed_step_fmu,
                                                                                          tmp_path):
    fixed, variable = pairs[2]
    assert communication_of(load_binding(fixed)) == CommunicationStep(True, STEP, FROM_DEFAULT_EXPERIMENT)
    stepped = communication_of(load_binding(variable))
    assert stepped.fixed and stepped.step == STEP and "the binding's step" in stepped.source
    assert not communication_of(load_binding(bound(tmp_path, BUCK2, load_binding(variable).fmu_path, "v.toml"))).fixed
    # an FMU that cannot vary its step and declares none: the control period of the run
    undeclared = CommunicationStep(True, None, FROM_CONTROL_PERIOD)
    assert undeclared.for_run(1e-3) == 1e-3
    assert record_period_for(undeclared, 1e-5, 1e-3) == 1e-3
    # periods the workbench chooses are moved onto the grid, to the nearest whole number of steps
    assert record_period_for(CommunicationStep(True, 1e-4, ""), 1e-5, 1e-3) == pytest.approx(1e-4)
    assert record_period_for(CommunicationStep(True, 3e-6, ""), 1e-5, 1e-3) == pytest.approx(9e-6)
    assert record_period_for(CommunicationStep(True, 1e-6, ""), 2e-5, 1e-3) == 2e-5
    assert record_period_for(CommunicationStep(), 1.234e-5, 1e-3) == 1.234e-5


@pytest.mark.parametrize("fmi_version", [2, 3])
def test_a_fixed_step_fmu_runs_the_papers_scenarios_as_the_same_model_does_with_a_variable_step(
        fmi_version, pairs, nnpc_1ms):
    """PI and NNPC, every paper scenario: the fixed-step FMU (the master honours its 10 us; any other step would fail
    the run) gives what the same model's variable-step FMU gives at that step, within 1e-6 V (here: exactly)."""
    fixed, variable = (load_binding(p) for p in pairs[fmi_version])
    for controller in (PIController(*PI_GAINS, 1e-3), nnpc_1ms):
        for name in PAPER_SCENARIOS:
            scenario = load_scenario(name, fixed.converter)
            a = simulate(fixed, controller, scenario)
            b = simulate(variable, controller, scenario)
            assert a.metadata["complete"] and a.metadata["rates"]["record_period_s"] == STEP
            assert len(a.frame) == len(b.frame) > 1000
            assert (a.frame["output_voltage"] - b.frame["output_voltage"]).abs().max() <= 1e-6, (name, controller.name)
            assert (a.frame["duty_cycle"] - b.frame["duty_cycle"]).abs().max() <= 1e-9


@pytest.mark.parametrize("args,message", [
    (["--record-period", "2.5e-5"], "the FMU steps by one fixed communication step of 1e-05 s (the FMU's "
                                    "DefaultExperiment stepSize), but the record period 2.5e-05 s is not a whole "
                                    "number of steps: use multiples of 1e-05 s (e.g. --record-period 2e-05)"),
    (["--control-period", "1.5e-5"], "but the control period 1.5e-05 s is not a whole number of steps"),
    (["--control-period", "1/75e3"], "but the control period 1.33333e-05 s is not a whole number of steps"),
])
def test_a_grid_the_fixed_step_cannot_follow_is_refused_in_one_line_before_anything_runs(tmp_path, pairs, args,
                                                                                       message):
    out = tmp_path / "out"
    one_line_error(cli("run", "startup", "--plant", str(pairs[2][0]), "--kp", "0.0017", "--ki", "15.6", *args,
                       "--out", str(out)), 2, message)
    assert not (out / "runs").exists()


def test_an_event_off_the_fixed_steps_grid_is_named_with_its_line(tmp_path, pairs):
    scenario = tmp_path / "odd.toml"
    scenario.write_text('name = "odd"\nduration = 0.01\nsettle = 0.003\n[initial]\nreference = 12.0\n'
                        'load_resistance = 6.0\n[[events]]\ntime = 0.0050005\nload_resistance = 5.0\n')
    one_line_error(cli("run", str(scenario), "--plant", str(pairs[2][0]), "--kp", "0.0017", "--ki", "15.6",
                       "--out", str(tmp_path / "out")), 2,
                   f"but scenario odd's event at t = 0.0050005 s ({scenario}:8) is not a whole number of steps")
    binding = load_binding(pairs[2][0])
    with pytest.raises(ConfigError, match="the record period 1.5e-05 s, scenario odd's event at t = 0.0050005 s"):
        check_rates(binding, [load_scenario(scenario, binding.converter)], 1e-3, 1.5e-5)


@pytest.mark.parametrize("text,message", [
    ("step = 0.0\n", "step = 0 s is invalid: expected > 0"),
    ("step = 1e-5\nmax_step = 1e-5\n", "step (one fixed communication step) and max_step (split longer steps) "
                                       "exclude each other: keep one"),
    ('step = 1e-5\ninterface = "model-exchange"\n', "step is a co-simulation FMU's communication step, but interface "
                                                    '= "model-exchange"'),
])
def test_bad_step_keys_are_refused_at_their_line(tmp_path, python_buck_fmu, text, message):
    path = bound(tmp_path, text + BUCK2, python_buck_fmu, "b.toml")
    with pytest.raises(ConfigError, match=r"b.toml:\d+: ") as refused:
        load_binding(path)
    assert message in str(refused.value)


def test_max_step_on_a_fixed_step_fmu_is_refused_with_its_step(tmp_path, fixed_step_buck):
    with pytest.raises(ConfigError) as refused:
        load_binding(bound(tmp_path, "max_step = 1e-5\n" + BUCK2, fixed_step_buck, "b.toml"))
    assert ("max_step splits steps into shorter ones, but FixedStepBuck.fmu cannot vary its communication step "
            "(canHandleVariableCommunicationStepSize = false): give its fixed step as step = ... instead (its "
            "DefaultExperiment says 1e-05 s)") in str(refused.value)


def test_tuning_data_collection_and_identification_work_on_a_fixed_step_fmu(tmp_path, fixed_step_fmu):
    """The built-in plant declared fixed-step (its DefaultExperiment says 1 ms): every automatic recording moves to
    1 ms, where the PI tuning recorded at 10 us before and was refused."""
    from controllers.nn_config import NNConfig, TrainingSettings
    from controllers.nn_model import train
    from cosim.design.data_collection import collect
    from cosim.design.experiments import collection_settings
    from cosim.design.pi_tuning import tune_pi

    path = tmp_path / "fixed.toml"
    path.write_text(f'fmu = "{fixed_step_fmu}"\nisolate = false\n'
                    + "".join(f'[roles.{r}]\nvariable = "{r}"\n' for r in ("duty_cycle", "input_voltage",
                                                                          "load_resistance", "output_voltage",
                                                                          "inductor_current", "load_current"))
                    + "[converter]\noutput_voltage = 12.0\ninput_voltage_range = [36.0, 60.0]\n"
                      "output_voltage_range = [3.0, 20.0]\nload_resistance_range = [4.0, 100.0]\n")
    binding = load_binding(path)
    tuning = tune_pi(binding, 1e-3, quick=True)
    assert tuning.design["inputs"]["settings"]["record_period_s"] == 1e-3
    assert 0 < tuning.kp < 0.01 and 1 < tuning.ki < 100 and tuning.worst_overshoot_pct < 20
    data = collect(binding, tuning.controller(), collection_settings(1e-3, samples=400, seed=2, spec=binding.converter))
    assert len(data) == 400 and data["measured_output_voltage"].between(0, 25).all()
    model = train(data, NNConfig(), TrainingSettings(seed=2, max_iterations=30), metadata={"control_period_s": 1e-3})
    assert model is not None
    result = simulate(binding, tuning.controller(), "startup")
    assert result.metadata["rates"]["record_period_s"] == 1e-3
    assert abs(result.frame["output_voltage"].iloc[-1] - 12.0) < 0.1


def test_a_sweep_and_the_quick_study_run_on_a_fixed_step_fmu(tmp_path, pairs):
    """The converter study at 1 ms (one seed, quick) and a sweep over the load, on the FMI 2.0 fixed-step FMU in its
    own plant processes on the workers: every run stepped by 10 us (any other step would have failed it)."""
    binding = pairs[2][0]
    text = binding.read_text()
    assert text.endswith("[converter]\noutput_voltage = 12.0\n")
    text += ("input_voltage = 48.0\nload_resistance = 6.0\ninput_voltage_range = [36.0, 60.0]\n"
             "output_voltage_range = [6.0, 18.0]\nload_resistance_range = [4.0, 50.0]\ncontrol_periods = [1e-3]\n"
             "inductor_current_limit = 8.0\n[converter.circuit]\ninductance = \"L\"\ncapacitance = \"C\"\n"
             "inductor_resistance = \"rL\"\ncapacitor_esr = \"rC\"\nswitching_frequency = 75e3\n")
    binding.write_text(text)
    study = tmp_path / "study"
    done = cli("study", "--plant", str(binding), "--quick", "--seeds", "1", "--out", str(study))
    assert done.returncode == 0, done.stderr
    runs = sorted((study / "runs").glob("*.parquet"))
    assert len(runs) == 16  # 4 scenarios x PI, NNPC, NNPC-paper, MPC-nominal, each recorded every 10 us
    assert all(pd.read_parquet(r, columns=["time"])["time"].diff().dropna().round(12).eq(STEP).all() for r in runs)
    report = (study / "REPORT.md").read_text()
    assert "# Study of FixedStepBuck" in report and "2 of 2 met" in report
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'scenarios = ["load_change"]\ncontrollers = [{{ kind = "pi", kp = {PI_GAINS[0]}, ki = '
                     f'{PI_GAINS[1]} }}]\n[plant]\nbinding = "{binding}"\n[operating_point]\n'
                     "load_resistance = { values = [6.0, 12.0] }\n")
    done = cli("sweep", str(sweep), "--out", str(tmp_path / "swept"), "--workers", "1")
    assert done.returncode == 0, done.stderr
    from cosim.design.sweeps import dataset

    rows = dataset.read_rows(tmp_path / "swept")
    assert list(rows["status"]) == ["ok", "ok"] and rows["iae_Vs"].gt(0).all()
    sweep.write_text(sweep.read_text().replace('scenarios = ["load_change"]\n',
                                               'scenarios = ["load_change"]\nrecord_period = 2.5e-5\n'))
    line = one_line_error(cli("sweep", str(sweep), "--out", str(tmp_path / "refused"), "--workers", "1"), 2,
                          "but the record period 2.5e-05 s is not a whole number of steps")
    assert line.startswith(f"error: {sweep}:2: ")  # at the record_period line


def test_every_instant_of_a_long_run_lies_on_the_fixed_steps_grid():
    """Far into a run (200 s of plant time), the instants the master steps between still count as whole steps of a
    10 us grid, though their float rounding (about 3e-14 s) exceeds a billionth of the step."""
    from cosim.fmi.communication import grid_index
    from cosim.scenarios import Scenario
    from cosim.timeline import plan_timeline

    plan = plan_timeline(Scenario("long", "", 250.0, {"reference": 12.0, "load_resistance": 6.0,
                                                      "input_voltage": 48.0}, settle=0.015), 1e-3, STEP)
    times = plan.window(200_000, 200_010).times
    indices = [grid_index(t, STEP) for t in times]
    assert None not in indices and len(times) == 10 * 100  # ten control periods, each 100 steps
    assert all(b - a == 1 for a, b in zip(indices, indices[1:]))
    assert grid_index(200.0 + STEP / 2, STEP) is None and grid_index(200.0 + 1e-9, STEP) is None


def test_a_binding_step_needs_the_co_simulation_interface_and_a_sensible_size(tmp_path, me_only_fmu, python_buck_fmu):
    with pytest.raises(ConfigError, match=r"b.toml:\d+: step is a co-simulation FMU's communication step, but "
                                          r"BuckConverterME.fmu offers only model exchange here"):
        load_binding(bound(tmp_path, "step = 1e-5\n" + role_named_binding(me_only_fmu, parameters=""), me_only_fmu,
                           "b.toml"))
    with pytest.raises(ConfigError, match=r"c.toml:1: step = 1e-12 s is invalid: expected >= 1e-07 s"):
        load_binding(bound(tmp_path, "step = 1e-12\n" + BUCK2, python_buck_fmu, "c.toml"))


def test_an_ssp_of_a_fixed_step_plant_takes_its_step(tmp_path, pairs):
    """export-ssp steps a fixed-step plant by its own step by default, and refuses another."""
    from cosim.fmi.controller_export import export_controller
    from cosim.ssp.package import SspError, export_ssp

    controller_fmu_2 = export_controller(PIController(*PI_GAINS, 1e-3), tmp_path / "PI.fmu")[0]
    binding = load_binding(pairs[2][0])
    scenario = load_scenario("startup", binding.converter)
    with pytest.raises(SspError, match=r"the plant FMU steps only by its fixed communication step 1e-05 s \(the FMU's "
                                       r"DefaultExperiment stepSize\), but the communication step is 2e-05 s: use "
                                       r"--communication-step 1e-05"):
        export_ssp(scenario, binding, controller_fmu_2, tmp_path / "a.ssp", step=2e-5)
    loop = export_ssp(scenario, binding, controller_fmu_2, tmp_path / "b.ssp")
    assert (tmp_path / "b.ssp").is_file() and loop.step == STEP
