"""The closed loop as an SSP package: the scenario FMU, the SSP 1.0 archive, and the three engines
that run it (the workbench's master, fmpy's SSP simulation, libcosim)."""

from __future__ import annotations

import re
import subprocess
import sys
import zipfile
from pathlib import Path

import fmpy
import fmpy.validation
import numpy as np
import pytest
from conftest import cli
from fmpy.fmi2 import FMU2Slave
from lxml import etree

from controllers.pi import PIController
from cosim.base.errors import ConfigError
from cosim.design.experiments import implemented, scenarios_for
from cosim.design.plants import plant_binding
from cosim.fmi.controller_export import export_controller
from cosim.master import simulate
from cosim.scenarios import load_scenario, parse_scenario
from cosim.ssp.engines import ENGINES, run_ssp
from cosim.ssp.package import SCHEMA_DIR, export_ssp, read_ssp
from cosim.ssp.scenario_source import OUTPUTS, scenario_fmu, scenario_toml, settle_time
from cosim.study.vocabulary import PAPER_SPEC

# ------------------------------------------------------------------ the scenario FMU


def _sample_scenario_fmu(path: Path, times: list[float]) -> np.ndarray:
    """The scenario FMU's outputs at each of ``times`` (stepped from one to the next with raw fmpy)."""
    md = fmpy.read_model_description(str(path))
    unzipdir = fmpy.extract(str(path))
    fmu = FMU2Slave(guid=md.guid, unzipDirectory=unzipdir, modelIdentifier=md.coSimulation.modelIdentifier,
                    instanceName="scenario")
    fmu.instantiate()
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    values, now = [], 0.0
    for t in times:
        if t > now:
            fmu.doStep(now, t - now)
            now = t
        values.append(fmu.getReal([0, 1, 2]))
    fmu.terminate()
    fmu.freeInstance()
    return np.array(values)


@pytest.mark.parametrize("name", ["supply_dip", "reference_up"])
def test_the_scenario_fmu_follows_the_events_as_the_master_applies_them(name):
    from cosim.timeline import build_timeline, signal_at

    scenario = load_scenario(name, PAPER_SPEC)
    path = scenario_fmu(scenario, 1e-3)
    assert fmpy.validation.validate_fmu(str(path)) == []
    md = fmpy.read_model_description(str(path))
    assert [v.name for v in md.modelVariables] == list(OUTPUTS)
    assert all(v.causality == "output" for v in md.modelVariables)
    timeline = build_timeline(scenario, 1e-3, 1e-4)  # control samples, recording points and events
    expected = np.column_stack([signal_at(timeline, scenario.schedule(s)) for s in OUTPUTS])
    got = _sample_scenario_fmu(path, timeline.times.tolist())
    assert np.array_equal(got, expected)  # every instant, including each event instant itself


def test_the_scenario_is_rounded_to_whole_control_periods_and_survives_its_toml_form():
    [scenario] = scenarios_for(1e-3, ["load_change"], spec=PAPER_SPEC)
    assert settle_time(scenario, 1e-3) == pytest.approx(0.015)
    assert settle_time(scenario, 0.4e-3) == pytest.approx(0.0152)  # 38 control periods
    again = parse_scenario(scenario_toml(scenario), spec=PAPER_SPEC)
    assert (again.initial, again.events, again.duration, again.settle) == \
        (scenario.initial, scenario.events, scenario.duration, scenario.settle)


# ------------------------------------------------------------------ the archive

#: short versions of the paper's scenario kinds (a settled loop, then a step): fast to run
SHORT = {
    "ref_step": 'name = "ref_step"\nduration = 0.006\nsettle = 0.015\n[initial]\nreference = 12.0\n'
                "[[events]]\ntime = 0.002\nreference = 15.0\n",
    "load_step": 'name = "load_step"\nduration = 0.006\nsettle = 0.002\n[initial]\nreference = 12.0\n'
                 "[[events]]\ntime = 0.002\nload_resistance = 5.0\n",
}
GAINS = (0.0015, 15.6)


def short(name: str):
    return parse_scenario(SHORT[name], spec=PAPER_SPEC)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("ssp")


@pytest.fixture(scope="module")
def pi_fmu(work) -> Path:
    return export_controller(PIController(*GAINS, 1e-3), work / "PI.fmu")[0]


@pytest.fixture(scope="module")
def loops(work, pi_fmu) -> dict[str, Path]:
    made = {}
    for mode in ("averaged", "switched"):
        for name in SHORT:
            made[(name, mode)] = export_ssp(short(name), plant_binding("nominal", mode), pi_fmu,
                                            work / f"{name}-{mode}.ssp").archive
    return made


def test_the_archive_is_valid_ssp_1_0_and_holds_what_the_loop_needs(loops):
    path = loops[("ref_step", "averaged")]
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
        ssd = etree.fromstring(archive.read("SystemStructure.ssd"))
        ssvs = {n: etree.fromstring(archive.read(n)) for n in names if n.endswith(".ssv")}
    assert {"SystemStructure.ssd", "resources/Scenario_ref_step.fmu", "resources/PI.fmu",
            "resources/BuckConverter.fmu", "resources/plant.ssv", "resources/controller.ssv",
            "resources/scenario.toml"} == set(names)
    schema = etree.XMLSchema(etree.parse(str(SCHEMA_DIR / "SystemStructureDescription.xsd")))
    assert schema.validate(ssd), schema.error_log
    values = etree.XMLSchema(etree.parse(str(SCHEMA_DIR / "SystemStructureParameterValues.xsd")))
    for name, root in ssvs.items():
        assert values.validate(root), (name, values.error_log)
    ns = {"ssd": "http://ssp-standard.org/SSP1/SystemStructureDescription",
          "ssc": "http://ssp-standard.org/SSP1/SystemStructureCommon",
          "osp": "http://opensimulationplatform.com/SSP/OSPAnnotations"}
    experiment = ssd.find("ssd:DefaultExperiment", ns)
    assert float(experiment.get("stopTime")) == pytest.approx(0.021)  # settle + duration, plant time
    step = experiment.find("ssd:Annotations/ssc:Annotation/osp:Algorithm/osp:FixedStepAlgorithm", ns)
    assert float(step.get("baseStepSize")) == 1e-5
    assert {u.get("name") for u in ssd.findall("ssd:Units/ssc:Unit", ns)} >= {"V", "A", "Ohm", "s", "1"}
    loop = read_ssp(path)
    pairs = {(c.start_element, c.start_connector, c.end_element, c.end_connector) for c in loop.connections}
    assert pairs == {("scenario", "reference", "controller", "reference"),
                     ("scenario", "load_resistance", "plant", "load_resistance"),
                     ("scenario", "input_voltage", "plant", "input_voltage"),
                     ("scenario", "input_voltage", "controller", "input_voltage"),
                     ("plant", "average_output_voltage", "controller", "measured_output_voltage"),
                     ("plant", "average_inductor_current", "controller", "measured_inductor_current"),
                     ("plant", "average_load_current", "controller", "measured_load_current"),
                     ("controller", "duty_cycle", "plant", "duty_cycle")}
    assert loop.components["plant"].parameters["inductance"] == 220e-6
    assert loop.components["controller"].parameters["kp"] == GAINS[0]


def test_the_same_export_twice_gives_the_same_bytes(work, pi_fmu, loops):
    again = export_ssp(short("ref_step"), plant_binding("nominal", "averaged"), pi_fmu, work / "again.ssp").archive
    assert again.read_bytes() == loops[("ref_step", "averaged")].read_bytes()


# ------------------------------------------------------------------ the engines


@pytest.mark.parametrize("mode", ["averaged", "switched"])
def test_the_workbench_master_on_the_ssp_equals_its_normal_run(loops, mode):
    for name in SHORT:
        on_ssp = run_ssp(loops[(name, mode)], "workbench").frame
        normal = simulate(plant_binding("nominal", mode), implemented(PIController(*GAINS, 1e-3)), short(name)).frame
        assert len(on_ssp) == len(normal)
        for column in ("time", "output_voltage", "inductor_current", "measured_output_voltage", "duty_cycle",
                       "load_resistance", "reference"):
            assert np.max(np.abs(on_ssp[column].to_numpy() - normal[column].to_numpy())) <= 1e-12, (name, column)


def test_the_workbench_master_on_an_nnpc_ssp_equals_its_normal_run(work, nnpc_1ms):
    fmu = export_controller(nnpc_1ms, work / "NNPC.fmu")[0]
    path = export_ssp(short("load_step"), plant_binding("nominal", "averaged"), fmu, work / "nnpc.ssp").archive
    on_ssp = run_ssp(path, "workbench").frame
    normal = simulate(plant_binding("nominal", "averaged"), implemented(nnpc_1ms), short("load_step")).frame
    for column in ("output_voltage", "inductor_current", "duty_cycle"):
        assert np.max(np.abs(on_ssp[column].to_numpy() - normal[column].to_numpy())) <= 1e-12, column


def test_fmpy_and_libcosim_agree_and_deliver_the_duty_one_communication_step_late(loops):
    path = loops[("ref_step", "averaged")]
    runs = {engine: run_ssp(path, engine).frame for engine in ENGINES}
    workbench, fmpy_run, libcosim = runs["workbench"], runs["fmpy"], runs["libcosim"]
    assert list(fmpy_run.columns) == list(workbench.columns) and len(fmpy_run) == len(workbench)
    assert fmpy_run["controller_compute_time"].isna().all()
    for column in ("output_voltage", "inductor_current", "duty_cycle"):  # two Jacobi engines, one algorithm
        assert np.max(np.abs(fmpy_run[column].to_numpy() - libcosim[column].to_numpy())) <= 1e-9, column
    k = int(np.flatnonzero(np.isclose(workbench["time"], 0.002))[0])  # the reference step, a control sample
    d = workbench["duty_cycle"].to_numpy()
    e = fmpy_run["duty_cycle"].to_numpy()
    assert d[k] != pytest.approx(d[k - 1], abs=1e-3)  # the workbench acts at the sample itself
    assert e[k] == pytest.approx(d[k - 1], abs=1e-6)  # the engine still applies the old duty there ...
    assert e[k + 1] == pytest.approx(d[k], abs=1e-6)  # ... and the workbench's one step (10 us) later
    assert np.max(np.abs(e[:k] - d[:k])) <= 1e-6  # before the step the loops agree


def test_the_vo_difference_shrinks_with_the_communication_step_as_a_one_step_delay_predicts(loops):
    """The duty response arrives tau late: on the averaged plant tau = h, so the difference is the
    workbench's trajectory shifted by h (first order in h); the switched plant latches the duty per
    PWM period, so below one PWM period the difference stops shrinking."""
    from cosim.study.ssp_agreement import delay_of

    def worst(path, mode, h, fine):
        frame = run_ssp(path, "libcosim", h).frame
        t, v = frame["time"].to_numpy(), frame["output_voltage"].to_numpy()
        ft, fv = fine["time"].to_numpy(), fine["output_voltage"].to_numpy()
        measured = np.max(np.abs(v - np.interp(t, ft, fv)))
        predicted = np.max(np.abs(np.interp(t, ft, fv) - np.interp(t - delay_of(mode, h), ft, fv)))
        return measured, predicted

    averaged = loops[("ref_step", "averaged")]
    fine = run_ssp(averaged, "workbench", 1e-6).frame
    (m20, p20), (m10, p10) = worst(averaged, "averaged", 2e-5, fine), worst(averaged, "averaged", 1e-5, fine)
    assert m20 / m10 == pytest.approx(2.0, rel=0.1)  # first order in h
    assert m10 == pytest.approx(p10, rel=0.05) and m20 == pytest.approx(p20, rel=0.05)  # the shift, as predicted
    switched = loops[("ref_step", "switched")]
    fine = run_ssp(switched, "workbench", 1e-6).frame
    (m5, _), (m2, _) = worst(switched, "switched", 5e-6, fine), worst(switched, "switched", 2.5e-6, fine)
    assert m5 == pytest.approx(m2, rel=0.05)  # both delayed one PWM period: no longer shrinking


# ------------------------------------------------------------------ the engines' own defects, as found


def test_fmpy_simulate_ssp_as_shipped_cannot_run_the_loop(loops, monkeypatch):
    """simulate_ssp starts every connector at 0.0 and sets the inputs from them at the first step:
    the plant refuses load_resistance = 0 (fmi2SetReal fails)."""
    import fmpy.ssp.simulation as simulation
    from fmpy.fmi1 import FMICallException

    refused = []
    set_value = simulation.set_value

    def watched(component, name, value):
        try:
            set_value(component, name, value)
        except FMICallException:
            refused.append((component.name, name, value))
            raise

    monkeypatch.setattr(simulation, "set_value", watched)
    with pytest.raises(FMICallException, match="fmi2SetReal"):
        simulation.simulate_ssp(str(loops[("ref_step", "averaged")]), stop_time=1e-4, step_size=1e-5)
    assert refused == [("plant", "load_resistance", 0.0)]


def test_libcosimpy_drops_the_last_time_series_sample_and_the_engine_does_not(loops):
    from libcosimpy.CosimEnums import CosimVariableType
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimObserver import CosimObserver

    from cosim.ssp.engines import _time_series

    execution = CosimExecution.from_ssp_file(str(loops[("ref_step", "averaged")]), step_size=10_000)
    observer = CosimObserver.create_time_series(buffer_size=100)
    execution.add_observer(observer)
    plant = execution.slave_index_from_instance_name("plant")
    observer.start_time_series(plant, 3, CosimVariableType.REAL)  # output_voltage
    assert execution.simulate_until(50 * 10_000)
    times, _, _ = observer.time_series_real_samples(plant, 3, from_step=0, sample_count=60)
    assert len(times) == 50 and times[-1] == 49 * 10_000  # 51 samples (steps 0..50) exist
    times, _ = _time_series(observer, plant, 3, 60)
    assert len(times) == 51 and times[-1] == 50 * 10_000


def test_a_predictive_controller_fmu_can_be_read_in_initialization_mode(work, nnpc_1ms):
    """libcosim reads every output while it iterates initial values; the NNPC FMU used to compute a
    duty there with its predictive controller not yet configured, and crashed the process."""
    path = export_controller(nnpc_1ms, work / "NNPC_init.fmu")[0]
    md = fmpy.read_model_description(str(path))
    unzipdir = fmpy.extract(str(path))
    fmu = FMU2Slave(guid=md.guid, unzipDirectory=unzipdir, modelIdentifier=md.coSimulation.modelIdentifier,
                    instanceName="nnpc")
    vr = {v.name: v.valueReference for v in md.modelVariables}
    fmu.instantiate()
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()
    fmu.setReal([vr["reference"], vr["measured_output_voltage"], vr["measured_inductor_current"],
                 vr["measured_load_current"]], [12.0, 0.0, 0.0, 0.0])
    assert fmu.getReal([vr["duty_cycle"]]) == [0.0]  # held before the controller is configured
    fmu.exitInitializationMode()
    assert fmu.getReal([vr["duty_cycle"]])[0] > 0.0  # computed once configured (start-up: full duty)
    fmu.terminate()
    fmu.freeInstance()


# ------------------------------------------------------------------ bad input: one line, exit 2, nothing written


def _rewrite(source: Path, target: Path, members: dict[str, bytes | None]) -> Path:
    """A copy of an archive with some members replaced (bytes) or left out (None)."""
    with zipfile.ZipFile(source) as old, zipfile.ZipFile(target, "w") as new:
        for info in old.infolist():
            if info.filename in members:
                if members[info.filename] is not None:
                    new.writestr(info, members[info.filename])
            else:
                new.writestr(info, old.read(info.filename))
    return target


def _ssd(path: Path) -> str:
    with zipfile.ZipFile(path) as archive:
        return archive.read("SystemStructure.ssd").decode()


@pytest.fixture(scope="module")
def bad_archives(loops, work) -> dict[str, tuple[Path, str]]:
    good = loops[("ref_step", "averaged")]
    ssd = _ssd(good)
    truncated = work / "truncated.ssp"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    junk = work / "junk.ssp"
    junk.write_text("not an archive")
    return {
        "not a zip": (junk, "is not a zip archive"),
        "truncated": (truncated, "is not a zip archive"),
        "malformed ssd": (_rewrite(good, work / "malformed.ssp", {"SystemStructure.ssd": ssd[:500].encode()}),
                          "SystemStructure.ssd is not well-formed XML"),
        "not ssp 1.0": (_rewrite(good, work / "invalid.ssp", {"SystemStructure.ssd": ssd.replace(
            'kind="output"', 'kind="sideways"', 1).encode()}), "not valid SSP 1.0"),
        "connection to a missing connector": (_rewrite(good, work / "missing-connector.ssp", {
            "SystemStructure.ssd": ssd.replace('endConnector="measured_output_voltage"',
                                               'endConnector="measured_voltage"').encode()}),
            "component 'controller' has no connector 'measured_voltage'"),
        "connector naming a missing variable": (_rewrite(good, work / "missing-variable.ssp", {
            "SystemStructure.ssd": ssd.replace('name="average_output_voltage"', 'name="avg_vo"').replace(
                'startConnector="average_output_voltage"', 'startConnector="avg_vo"').encode()}),
            "component 'plant' has a connector 'avg_vo', but BuckConverter.fmu has no such variable"),
        "FMU missing": (_rewrite(good, work / "no-fmu.ssp", {"resources/PI.fmu": None}),
                        "component 'controller' names resources/PI.fmu, which the archive does not contain"),
        "parameter set missing": (_rewrite(good, work / "no-ssv.ssp", {"resources/plant.ssv": None}),
                                  "names resources/plant.ssv, which the archive does not contain"),
        "stop time before the start": (_rewrite(good, work / "negative-stop.ssp", {"SystemStructure.ssd": re.sub(
            'stopTime="[^"]*"', 'stopTime="-1"', ssd).encode()}),
            "DefaultExperiment stopTime = -1 s: expected 0.021 s, the end of the embedded scenario 'ref_step'"),
        "stop time short of the scenario": (_rewrite(good, work / "short-stop.ssp", {
            "SystemStructure.ssd": re.sub('stopTime="[^"]*"', 'stopTime="0.01"', ssd).encode()}),
            "DefaultExperiment stopTime = 0.01 s: expected 0.021 s"),
        "start time not zero": (_rewrite(good, work / "late-start.ssp", {"SystemStructure.ssd": ssd.replace(
            'startTime="0.0"', 'startTime="0.005"').encode()}), "DefaultExperiment startTime = 0.005 s: expected 0"),
        "communication step zero": (_rewrite(good, work / "zero-step.ssp", {"SystemStructure.ssd": ssd.replace(
            'communicationStep="', 'communicationStep="0" was="').encode()}),
            "communicationStep = 0 s: expected a time > 0"),
        "settle edited": (_rewrite(good, work / "settle.ssp", {"SystemStructure.ssd": re.sub(
            'settle="[^"]*"', 'settle="0.004"', ssd).encode()}), "the buck-cosim annotation's settle = 0.004 s: expected"),
    }


@pytest.mark.parametrize("case", ["not a zip", "truncated", "malformed ssd", "not ssp 1.0",
                                  "connection to a missing connector", "connector naming a missing variable",
                                  "FMU missing", "parameter set missing", "stop time before the start",
                                  "stop time short of the scenario", "start time not zero",
                                  "communication step zero", "settle edited"])
def test_a_bad_archive_is_refused_in_one_line(bad_archives, case):
    path, message = bad_archives[case]
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_ssp(path)


@pytest.mark.parametrize("case", ["truncated", "connection to a missing connector", "FMU missing",
                                  "stop time before the start"])
def test_run_ssp_refuses_a_bad_archive_with_exit_2_and_writes_nothing(bad_archives, case, tmp_path):
    path, message = bad_archives[case]
    result = cli("run-ssp", str(path), "--engine", "fmpy", "--out", str(tmp_path / "out"))
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0]
    assert not (tmp_path / "out").exists()


def test_an_engine_that_is_not_installed_is_refused_before_anything_runs(loops, tmp_path):
    shim = tmp_path / "shim" / "libcosimpy"
    shim.mkdir(parents=True)
    (shim / "__init__.py").write_text("raise ImportError('no libcosimpy here')\n")
    import os

    env = {**os.environ, "PYTHONPATH": str(shim.parent)}
    result = subprocess.run([sys.executable, "-m", "cosim.cli", "run-ssp", str(loops[("ref_step", "averaged")]),
                             "--engine", "libcosim", "--out", str(tmp_path / "out")], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parents[1], env=env, timeout=300)
    assert result.returncode == 2
    assert result.stderr.strip() == ("error: engine libcosim: libcosimpy is not installed or does not load here "
                                     "(ImportError: no libcosimpy here); install it with pip install "
                                     "'libcosimpy==0.0.6'")
    assert not (tmp_path / "out").exists()


def test_export_ssp_refuses_a_step_off_the_control_grid_and_writes_nothing(pi_fmu, tmp_path):
    target = tmp_path / "loop.ssp"
    result = cli("export-ssp", "reference_up", "--controller", str(pi_fmu), "--communication-step", "3e-4",
                 "--out", str(target))
    assert result.returncode == 2
    assert "communication step 0.0003 s does not divide the control period 0.001 s" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not target.exists()
    result = cli("export-ssp", "reference_up", "--controller", "nonsense", "--out", str(target))
    assert result.returncode == 2 and "expected pi, nnpc" in result.stderr and not target.exists()
    # a controller FMU brings its own gains and limits: the options that design a built-in one are refused, not ignored
    result = cli("export-ssp", "reference_up", "--controller", str(pi_fmu), "--kp", "0.002", "--ki", "10",
                 "--duty-max", "0.5", "--out", str(target))
    assert result.returncode == 2 and not target.exists()
    assert f"--kp, --ki, --duty-min/--duty-max design a built-in controller, but --controller {pi_fmu} is a " \
           "controller FMU, which brings its own" in result.stderr, result.stderr


def test_the_commands_write_run_tables_that_read_back(pi_fmu, tmp_path):
    from cosim.results import read_run

    target = tmp_path / "loop.ssp"
    result = cli("export-ssp", str(_short_file(tmp_path)), "--controller", str(pi_fmu), "--out", str(target))
    assert result.returncode == 0, result.stderr
    for engine in ENGINES:
        result = cli("run-ssp", str(target), "--engine", engine, "--out", str(tmp_path / "out"))
        assert result.returncode == 0, result.stderr
    runs = sorted((tmp_path / "out" / "runs").glob("*.parquet"))
    assert [p.name for p in runs] == [f"ref_step__pi__nominal-averaged__1ms__ssp-{e}.parquet"
                                      for e in ("fmpy", "libcosim", "workbench")]
    for path in runs:
        run = read_run(path)
        assert run.complete and run.metadata["engine"]["name"] in ENGINES and len(run.frame) == 601
    # the same command twice writes the same bytes
    assert cli("run-ssp", str(target), "--engine", "libcosim", "--out", str(tmp_path / "again")).returncode == 0
    for path in (tmp_path / "again" / "runs").iterdir():
        if ".timing." not in path.name:  # wall clock, kept apart for exactly this reason
            assert path.read_bytes() == (tmp_path / "out" / "runs" / path.name).read_bytes(), path.name


def _short_file(folder: Path) -> Path:
    path = folder / "ref_step.toml"
    path.write_text(SHORT["ref_step"])
    return path


def test_an_external_plant_with_other_units_travels_as_linear_transformations(python_buck_fmu, pi_fmu, tmp_path):
    """A binding's unit conversion (duty in percent, current in mA) becomes ssc:LinearTransformation
    on the connections; every engine applies it and records workbench units."""
    import shutil

    from cosim.fmi.binding_file import load_binding

    shutil.copy(python_buck_fmu, tmp_path / "PyBuck.fmu")
    (tmp_path / "py.toml").write_text('fmu = "PyBuck.fmu"\nlabel = "PyBuck"\n[roles.duty_cycle]\nvariable = "D"\n'
                                      'scale = 100.0\n[roles.output_voltage]\nvariable = "Vout"\n'
                                      '[roles.inductor_current]\nvariable = "IL_mA"\nscale = 1000.0\n'
                                      '[roles.load_resistance]\nvariable = "Rload"\n[roles.load_current]\n'
                                      'variable = "Iout"\n[converter]\noutput_voltage = 12.0\ninput_voltage = 48.0\n')
    binding = load_binding(tmp_path / "py.toml")
    scenario = short("load_step")
    path = export_ssp(scenario, binding, pi_fmu, tmp_path / "py.ssp").archive
    duty = next(c for c in read_ssp(path).connections if c.end_connector == "D")
    assert (duty.factor, duty.offset) == (100.0, 0.0)
    normal = simulate(binding, PIController(*GAINS, 1e-3), scenario).frame
    for engine in ENGINES:
        frame = run_ssp(path, engine).frame
        tolerance = 1e-12 if engine == "workbench" else 1e-4  # the Jacobi engines: a delay, second order here
        for column in ("output_voltage", "inductor_current", "duty_cycle"):
            assert np.max(np.abs(frame[column].to_numpy() - normal[column].to_numpy())) <= tolerance, (engine, column)


def test_the_agreement_study_reads_the_controllers_of_two_pipelines_every_full_and_quick_reproduction_runs():
    """The SSP agreement study runs the reproduction's PI and NNPC of the nominal plants at 1 ms as FMUs, read from
    the reproduction's files (it no longer designs them itself: a profile without those pipelines, as the benchmark
    suite's one-pipeline smoke reproduction, skips the study -- it was 10 s of PI tuning and a 10 000-sample
    identification there, a third of the smoke reproduction)."""
    from cosim.study.reproduce import FULL, PIPELINES, QUICK
    from cosim.study.ssp_agreement import SOURCE_PIPELINES

    assert SOURCE_PIPELINES == ("nominal-averaged__1ms", "nominal-switched__1ms")
    assert set(SOURCE_PIPELINES) <= {p.tag for p in PIPELINES} and FULL.pipelines is None
    assert set(SOURCE_PIPELINES) <= set(QUICK.pipelines)
