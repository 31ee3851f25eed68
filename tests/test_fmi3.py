"""FMI 3.0: the built-in plant and the controller FMUs as FMI 3.0 editions, FMI 3.0 plants from outside
(pythonfmu3), their checks, fmi3DoStep's flags, and the reliability corpus for FMI 3.0 archives."""

from __future__ import annotations

import shutil
import zipfile
from ctypes import CFUNCTYPE, POINTER, c_bool, c_double, c_int, c_void_p
from dataclasses import replace
from pathlib import Path

import fmpy
import numpy as np
import pytest
from conftest import CORPUS, cli, faulty_binding, no_temporary_files, one_line_error, role_named_binding
from fmpy.validation import validate_fmu

from cosim.base.errors import ConfigError, FmuArchiveError, PlantError
from cosim.fmi.archive import check_fmu
from cosim.fmi.binding import builtin_binding
from cosim.fmi.binding_file import load_binding
from cosim.master import simulate
from cosim.results import read_run
from cosim.scenarios import load_scenario
from cosim.study.vocabulary import PAPER_SPEC

PI_GAINS = (0.0017, 15.6)  # a stable 1 ms PI on the built-in plant and the pythonfmu bucks


def pi():
    from controllers.pi import PIController

    return PIController(*PI_GAINS, 1e-3)


@pytest.fixture(scope="session")
def buck_fmu3() -> Path:
    from plant_fmu import fmu_path

    return fmu_path(fmi_version=3)


@pytest.fixture(scope="session")
def faulty_fmu3(tmp_path_factory) -> Path:
    from pythonfmu3.builder import FmuBuilder

    out = tmp_path_factory.mktemp("faulty3")
    return Path(FmuBuilder.build_FMU(CORPUS / "faulty_buck3.py", dest=out,
                                     canHandleVariableCommunicationStepSize=True))


BUCK2 = """\
fmu = "{fmu}"
isolate = false
[roles.duty_cycle]
variable = "D"
scale = 100.0
[roles.output_voltage]
variable = "Vout"
[roles.inductor_current]
variable = "IL_mA"
scale = 1000.0
[roles.load_resistance]
variable = "Rload"
[roles.input_voltage]
variable = "Vin"
[roles.load_current]
variable = "Iout"
[parameters]
rL = 0.15
"""

BUCK3 = """\
fmu = "{fmu}"
isolate = false
[roles.duty_cycle]
variable = "duty_pct"
scale = 100.0
[roles.output_voltage]
variable = "v_out"
[roles.inductor_current]
variable = "i_l_mA"
scale = 1000.0
[roles.load_resistance]
variable = "r_load"
[roles.input_voltage]
variable = "v_supply"
[roles.load_current]
variable = "i_out"
[parameters]
r_winding = 0.15
max_substep_us = 10
diode = true
{extra}"""


def bound(tmp_path: Path, template: str, fmu: Path, name: str, extra: str = "") -> Path:
    path = tmp_path / name
    text = template.format(fmu=fmu, extra=extra)
    if "[converter]" not in text:  # the converter its runs resolve the shipped scenarios against, at the end
        text = f"{text.rstrip()}\n[converter]\noutput_voltage = 12.0\n"
    path.write_text(text)
    return path


def numeric_difference(a, b) -> float:
    columns = [c for c in a.columns if c != "controller_compute_time" and a[c].dtype.kind in "fb"]
    assert list(a["time"]) == list(b["time"])
    return float(np.max(np.abs(a[columns].to_numpy(float) - b[columns].to_numpy(float))))


# ------------------------------------------------------------------------------------------ the built-in plant


def test_the_fmi3_edition_declares_the_fmi2_variables(buck_fmu, buck_fmu3):
    """One definition of the variables: every FMI 2.0 variable reappears with its value reference, causality,
    variability, unit, start and range; FMI 3.0 adds the independent time and the two event indicators."""
    md2 = fmpy.read_model_description(str(buck_fmu))
    md3 = fmpy.read_model_description(str(buck_fmu3))
    assert (md3.fmiVersion, md3.guid, md3.numberOfContinuousStates, md3.numberOfEventIndicators) == \
        ("3.0", md2.guid, md2.numberOfContinuousStates, md2.numberOfEventIndicators) == ("3.0", md2.guid, 4, 2)
    v3 = {v.name: v for v in md3.modelVariables}
    for v in md2.modelVariables:
        w = v3.pop(v.name)
        assert (w.valueReference, w.causality, w.variability, w.unit, w.min, w.max) == \
            (v.valueReference, v.causality, v.variability, v.unit, v.min, v.max), v.name
        assert w.type == {"Real": "Float64", "Integer": "Int32"}[v.type]
        assert float(w.start or 0) == float(v.start or 0)
        assert (w.derivative.name if w.derivative else None) == (v.derivative.name if v.derivative else None)
    assert {n: (v.causality, v.valueReference) for n, v in v3.items()} == {
        "time": ("independent", 1000), "diode_event_indicator": ("local", 1001),
        "conduction_boundary_event_indicator": ("local", 1002)}
    assert [(o.variable.name, sorted(d.name for d in o.dependencies)) for o in md3.outputs] == \
        [(o.variable.name, sorted(d.name for d in o.dependencies)) for o in md2.outputs]
    assert [d.variable.name for d in md3.derivatives] == [d.variable.name for d in md2.derivatives]


def test_the_fmi3_plant_fmus_validate_clean(buck_fmu3):
    from plant_fmu import source_fmu_path

    source = source_fmu_path(fmi_version=3)
    assert validate_fmu(str(buck_fmu3)) == [] and validate_fmu(str(source)) == []
    with zipfile.ZipFile(source) as archive:  # what a tool compiling it needs: the build description, the model
        names = set(archive.namelist())
    assert {"sources/buildDescription.xml", "sources/fmi3_glue.c", "sources/buck_fmu.c", "sources/buck_model.c",
            "sources/fmi3_variables.h", "sources/fmi2TypesPlatform.h"} <= names
    assert not any(n.startswith("binaries/") and n.endswith(".so") for n in names)


@pytest.mark.parametrize("mode,interface,scenario", [
    ("averaged", "co-simulation", "capacitor_ageing"),
    ("switched", "co-simulation", "capacitor_ageing"),
    ("averaged", "model-exchange", "capacitor_ageing"),
    ("switched", "model-exchange", "short_load_step"),
])
def test_the_fmi3_plant_equals_the_fmi2_plant_run_by_run(buck_fmu3, mode, interface, scenario):
    """The same model code behind either glue: every recorded column equal to 1e-12 (in fact bit for bit),
    tunable-parameter events (CS: set between steps, ME: in event mode) included. (The switched plant in
    model exchange, slow under CVode, runs a short start-up with a load step.)"""
    from cosim.scenarios import parse_scenario

    binding2 = builtin_binding(mode, interface=interface)
    binding3 = replace(binding2, fmu_path=buck_fmu3)
    chosen = parse_scenario('name = "short_load_step"\nduration = 0.008\n[initial]\nreference = 12.0\n'
                            '[[events]]\ntime = 0.004\nload_resistance = 5.0\n',
                            spec=PAPER_SPEC) if scenario == "short_load_step" \
        else load_scenario(scenario, PAPER_SPEC)
    runs = [simulate(b, pi(), chosen) for b in (binding2, binding3)]
    assert runs[1].metadata["plant"]["interface"] == interface
    assert numeric_difference(runs[0].frame, runs[1].frame) <= 1e-12


@pytest.mark.parametrize("interface", ["co-simulation", "model-exchange"])
def test_an_fmi3_plant_refuses_a_binding_value_at_its_line_before_any_run_and_stays_usable(tmp_path, buck_fmu3,
                                                                                          interface):
    """The pre-run set-up (cosim.master.preflight) through the FMI 3.0 glue: the refused [parameters] value is
    named at its line; on the same instance, after that refusal and its location's retries, a run gives exactly
    the run of a fresh instance."""
    from cosim.fmi.plant import open_plant
    from cosim.master import check_set_up, preflight, run

    text = role_named_binding(buck_fmu3, parameters="", converter=False, interface=interface, isolate=False)
    (tmp_path / "bad.toml").write_text(text + "capacitance = 4.7e-6\ninductance = -1\n")
    with pytest.raises(ConfigError, match=r"bad.toml:16: parameters.inductance = -1: the plant FMU refuses its "
                                          r"set-up with this value \(fmi3SetFloat64 failed"):
        check_set_up(load_binding(tmp_path / "bad.toml"), [load_scenario("startup", PAPER_SPEC)])
    (tmp_path / "good.toml").write_text(text + "capacitance = 4.7e-6\n")
    good = load_binding(tmp_path / "good.toml")
    startup = load_scenario("startup", PAPER_SPEC)
    refused = replace(startup, initial={**startup.initial, "load_resistance": -1.0})
    with open_plant(good) as plant:
        with pytest.raises(ConfigError, match="refuses its set-up at the start of scenario startup"):
            preflight(plant, refused)
        after = run(plant, pi(), startup)
    fresh = simulate(good, pi(), startup)
    timed = ["controller_compute_time"]
    assert after.frame.drop(columns=timed).equals(fresh.frame.drop(columns=timed))


def test_an_fmi3_plant_state_restores(buck_fmu3):
    from cosim.fmi.plant import open_plant

    with open_plant(replace(builtin_binding("switched"), fmu_path=buck_fmu3)) as plant:
        plant.initialize([0.25, 48.0, 6.0])
        plant.advance_to(1e-4)
        state = plant.get_state()
        plant.advance_to(3e-4)
        first = plant.outputs()
        plant.set_state(state, 1e-4)
        plant.advance_to(3e-4)
        assert plant.outputs() == first and first[0] > 0.5
        plant.free_state(state)


DO_STEP = CFUNCTYPE(c_int, c_void_p, c_double, c_double, c_bool, POINTER(c_bool), POINTER(c_bool), POINTER(c_bool),
                   POINTER(c_double))


def test_fmi3_do_step_flags_are_handled_or_refused(buck_fmu3):
    """An early return that progressed is continued (the same run as without it); an early return without
    progress and a request for event mode the FMU was not given are refused with one line each. The FMU's
    fmi3DoStep is wrapped by a fake that steps it part of the way and reports what an FMU would."""
    from cosim.fmi.plant import open_plant

    binding = replace(builtin_binding("averaged"), fmu_path=buck_fmu3)

    def run(fake):
        with open_plant(binding) as plant:
            step = plant._do_step
            if fake is not None:
                real = step._call
                step._call = DO_STEP(lambda *args: fake(real, *args))
            plant.initialize([0.25, 48.0, 6.0])
            for k in range(1, 11):
                plant.advance_to(k * 1e-4)
            return plant.outputs()

    def halfway(real, instance, t, h, no_set_prior, event, terminate, early, last):
        if h < 6e-5:  # the second half
            return real(instance, t, h, no_set_prior, event, terminate, early, last)
        status = real(instance, t, h / 2, no_set_prior, event, terminate, early, last)
        early[0] = True  # last: t + h / 2, as the FMU reported it
        return status

    reference = run(None)
    assert run(halfway) == pytest.approx(reference, rel=1e-12, abs=1e-12)

    def stuck(real, instance, t, h, no_set_prior, event, terminate, early, last):
        early[0], last[0] = True, t
        return 0

    with pytest.raises(PlantError, match=r"fmi3DoStep returned early \(earlyReturn\) at lastSuccessfulTime = 0 s "
                                         r"without progress from t = 0 s"):
        run(stuck)

    def wants_events(real, instance, t, h, no_set_prior, event, terminate, early, last):
        status = real(instance, t, h, no_set_prior, event, terminate, early, last)
        event[0] = t > 4e-4
        return status

    with pytest.raises(PlantError, match=r"fmi3DoStep asked for event handling \(eventHandlingNeeded\) at "
                                         r"t = 0.0006 s, but the FMU was instantiated without event mode"):
        run(wants_events)


# ------------------------------------------------------------------------------------------ pythonfmu3 plants


def test_a_pythonfmu3_plant_runs_pi_and_nnpc_like_its_fmi2_twin(tmp_path, python_buck_fmu, python_buck3_fmu,
                                                                 nnpc_1ms):
    twin2 = load_binding(bound(tmp_path, BUCK2, python_buck_fmu, "buck2.toml"))
    twin3 = load_binding(bound(tmp_path, BUCK3, python_buck3_fmu, "buck3.toml"))
    assert check_fmu(twin3.fmu_path).fmi_major == 3 and check_fmu(twin2.fmu_path).fmi_major == 2
    for controller, scenario in ((pi(), "startup"), (nnpc_1ms, "reference_up"), (nnpc_1ms, "load_change")):
        controller.reset()
        run2 = simulate(twin2, controller, load_scenario(scenario, PAPER_SPEC))
        controller.reset()
        run3 = simulate(twin3, controller, load_scenario(scenario, PAPER_SPEC))
        assert numeric_difference(run2.frame, run3.frame) <= 1e-12, (controller.name, scenario)
        final = run3.frame.iloc[-1]
        assert abs(final["output_voltage"] / final["reference"] - 1) < 0.01, (controller.name, scenario)
    assert run3.metadata["plant"]["fmu"] == str(python_buck3_fmu)


@pytest.mark.parametrize("extra,message", [
    ('[roles.measured_output_voltage]\nvariable = "states"\n',
     "role 'measured_output_voltage' needs a scalar variable, but 'states' is an FMI 3.0 array "
     "(shape [2]): a role carries one value"),
    ('[roles.measured_load_current]\nvariable = "max_substep_us"\n',
     "role 'measured_load_current' needs a Float64 variable, but 'max_substep_us' is Int32"),
    ("loss_table = 0.1\n", "parameter 'loss_table' is an FMI 3.0 array in PyBuck3.fmu (shape [3])"),
    ("r_esr = true\n", "parameter 'r_esr' is Float64 in PyBuck3.fmu, got True (bool): expected a "
                       "finite number"),
])
def test_fmi3_bindings_are_checked_like_fmi2_ones(tmp_path, python_buck3_fmu, extra, message):
    text = BUCK3.format(fmu=python_buck3_fmu, extra="")
    if extra.startswith("[roles"):
        text = text.replace("[parameters]", extra + "[parameters]")
    else:
        text += extra
    path = tmp_path / "buck3.toml"
    path.write_text(text)
    line = text.splitlines().index(extra.splitlines()[-1]) + 1  # the key the message must point at
    with pytest.raises(ConfigError) as error:
        load_binding(path)
    assert f"buck3.toml:{line}: {message}" in str(error.value)


def test_fmi3_integer_parameters_are_range_checked(tmp_path, python_buck3_fmu):
    path = bound(tmp_path, BUCK3, python_buck3_fmu, "buck3.toml").read_text()
    (tmp_path / "b.toml").write_text(path.replace("max_substep_us = 10", "max_substep_us = 3000000000"))
    with pytest.raises(ConfigError, match=r"b.toml:19: parameter 'max_substep_us' is Int32 in PyBuck3.fmu, got "
                                          r"3000000000 \(int\): expected a whole number in \[-2147483648, 2147483647\]"):
        load_binding(tmp_path / "b.toml")


def test_inspect_and_draft_binding_read_fmi3(tmp_path, python_buck3_fmu):
    shutil.copy(python_buck3_fmu, tmp_path / "PyBuck3.fmu")
    done = cli("inspect", "PyBuck3.fmu", "--draft-binding", "draft.toml", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "(FMI 3.0, generated by PythonFMU3" in done.stdout and "platforms        x86_64-linux" in done.stdout
    assert any(line.split()[:4] == ["loss_table", "parameter", "fixed", "Float64[3]"] for line in done.stdout.splitlines())
    draft = (tmp_path / "draft.toml").read_text()
    for role, variable in (("duty_cycle", "duty_pct"), ("output_voltage", "v_out"), ("inductor_current", "i_l_mA"),
                           ("load_resistance", "r_load"), ("input_voltage", "v_supply"), ("load_current", "i_out")):
        assert f'[roles.{role}]   # guessed from name {variable!r}' in draft and f'variable = "{variable}"' in draft
    assert "scale = 1000.0" in draft and "loss_table" not in draft and "# max_substep_us = 10" in draft
    binding = load_binding(tmp_path / "draft.toml")
    assert binding.roles["inductor_current"].scale == 1000.0


# ------------------------------------------------------------------------------------------ the reliability corpus


def _rezipped(source: Path, target: Path, rename=None, drop=(), replace_members=None) -> Path:
    with zipfile.ZipFile(source) as old, zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as new:
        for info in old.infolist():
            if any(info.filename.startswith(d) for d in drop):
                continue
            data = (replace_members or {}).get(info.filename, old.read(info.filename))
            name = rename(info.filename) if rename else info.filename
            new.writestr(name, data)
    return target


@pytest.mark.parametrize("kind,message", [
    ("truncated", r"truncated3.fmu is (not a zip archive|a damaged zip archive|truncated)"),
    ("no binary", r"source3.fmu has no x86_64-linux binary for its interfaces \(co-simulation, model-exchange\); "
                  r"binaries present: none"),
    ("wrong platform", r"mac3.fmu has no x86_64-linux binary for its interfaces \(co-simulation, model-exchange\); "
                       r"binaries present: aarch64-darwin"),
    ("FMI 2.0 layout", r"layout3.fmu has no x86_64-linux binary .*binaries present: linux64"),
    ("malformed description", r"bad3.fmu: modelDescription.xml is not well-formed XML"),
    ("scheduled execution", r"se3.fmu offers only Scheduled Execution \(FMI 3.0\), which the workbench does not drive"),
])
def test_bad_fmi3_archives_are_refused_before_extraction(tmp_path, buck_fmu3, kind, message):
    from plant_fmu import source_fmu_path

    if kind == "truncated":
        path = tmp_path / "truncated3.fmu"
        path.write_bytes(buck_fmu3.read_bytes()[:4000])
    elif kind == "no binary":
        path = shutil.copy(source_fmu_path(fmi_version=3), tmp_path / "source3.fmu")
    elif kind == "wrong platform":
        path = _rezipped(buck_fmu3, tmp_path / "mac3.fmu",
                         rename=lambda n: n.replace("x86_64-linux", "aarch64-darwin").replace(".so", ".dylib"))
    elif kind == "FMI 2.0 layout":
        path = _rezipped(buck_fmu3, tmp_path / "layout3.fmu", rename=lambda n: n.replace("x86_64-linux", "linux64"))
    elif kind == "malformed description":
        path = _rezipped(buck_fmu3, tmp_path / "bad3.fmu",
                         replace_members={"modelDescription.xml": b"<fmiModelDescription fmiVersion='3.0'"})
    else:
        xml = zipfile.ZipFile(buck_fmu3).read("modelDescription.xml").decode()
        start, end = xml.index("<ModelExchange"), xml.index("<UnitDefinitions")
        xml = xml[:start] + '<ScheduledExecution modelIdentifier="BuckConverter"/>\n  ' + xml[end:]
        path = _rezipped(buck_fmu3, tmp_path / "se3.fmu", replace_members={"modelDescription.xml": xml.encode()})
    with pytest.raises(FmuArchiveError, match=message):
        check_fmu(path)


def test_an_fmi3_variable_of_the_wrong_causality_is_refused(tmp_path, buck_fmu3):
    path = tmp_path / "plant.toml"
    path.write_text(f'fmu = "{buck_fmu3}"\n[roles.duty_cycle]\nvariable = "output_voltage"\n'
                    '[roles.output_voltage]\nvariable = "output_voltage"\n')
    with pytest.raises(ConfigError, match=r"plant.toml:3: role 'duty_cycle' needs causality input or parameter, but "
                                          r"'output_voltage' has causality output"):
        load_binding(path)


def test_a_crashing_fmi3_plant_ends_the_run_not_the_workbench(tmp_path, faulty_fmu3):
    """The faulty plant's FMI 3.0 twin segfaults in its process (isolated, the binding files' default): exit 3,
    one line, the rows before the crash written and marked incomplete."""
    binding = tmp_path / "crash.toml"
    binding.write_text(faulty_binding(faulty_fmu3, 4))
    one_line_error(cli("run", "startup", "--plant", str(binding), "--kp", "0", "--ki", "14", "--record-period", "1e-4",
                       "--out", str(tmp_path / "out")), 3,
                   f"binding file {binding}: the FMU crashed the plant process (signal SIGSEGV) while stepping at "
                   "t = 0.0104 s")
    run = read_run(tmp_path / "out" / "runs" / "startup__pi__bound-crash__1ms.parquet")
    assert run.complete is False and 0.0099 < run.frame["time"].max() < 0.0104 and len(run.frame) > 90
    no_temporary_files(tmp_path / "out")


@pytest.mark.parametrize("kind,message", [
    (5, "the FMU asked to terminate the simulation (fmi3DoStep's terminateSimulation) at t = 0.0104 s"),
    (2, "fmi3DoStep failed (fatal) at t = 0.0103 s: Fatal py exception encountered: [doStep] PyObject_CallMethod "
        "RuntimeError('simulated solver breakdown')"),
])
def test_a_failing_fmi3_plant_ends_the_run_and_keeps_the_rows(tmp_path, faulty_fmu3, kind, message):
    from cosim.master import RunFailed

    binding = tmp_path / "faulty.toml"
    binding.write_text("isolate = false\n" + faulty_binding(faulty_fmu3, kind))
    with pytest.raises(RunFailed) as failure:
        simulate(load_binding(binding), pi(), load_scenario("startup", PAPER_SPEC), record_period=1e-4)
    assert message in str(failure.value) and failure.value.exit_code == 3
    partial = failure.value.partial
    assert partial.metadata["complete"] is False and 0.0099 < partial.frame["time"].max() < 0.0104


# ------------------------------------------------------------------------------------------ controller FMUs


def test_fmi3_controller_fmus_equal_their_fmi2_editions(tmp_path, nnpc_1ms):
    """export-controller --fmi-version 3: validate_fmu clean, read through the same adapter protocol (a plain
    FMU and a controller-binding file), the same duties as the FMI 2.0 FMU to the bit, PI and NNPC."""
    from cosim.fmi.controller import FmuController, builtin_controller_binding, open_controller
    from cosim.fmi.controller_export import export_controller

    first = {}
    for name, controller, scenario in (("pi", pi(), "reference_up"), ("nnpc", nnpc_1ms, "load_change")):
        runs = []
        for version in (2, 3):
            binary, source = export_controller(controller, tmp_path / f"{name}{version}.fmu", fmi_version=version)
            assert validate_fmu(str(binary)) == [] and validate_fmu(str(source)) == []
            assert check_fmu(binary).fmi_major == version
            adapter = FmuController(builtin_controller_binding(binary))
            assert type(adapter).__name__ == ("FmuController" if version == 2 else "FmuController3")
            try:
                runs.append(simulate(builtin_binding("averaged"), adapter, load_scenario(scenario, PAPER_SPEC)).frame)
            finally:
                adapter.close()
        assert numeric_difference(runs[0], runs[1]) == 0.0, name
        first[name] = runs[0]
    (tmp_path / "pi3.toml").write_text('fmu = "pi3.fmu"\n[roles.reference]\nvariable = "reference"\n'
                                       '[roles.measured_output_voltage]\nvariable = "measured_output_voltage"\n'
                                       '[roles.duty_cycle]\nvariable = "duty_cycle"\n'
                                       '[roles.sample_period]\nvariable = "sample_period"\n')
    bound_pi = open_controller(str(tmp_path / "pi3.toml"))
    try:
        assert bound_pi.sample_period == 1e-3
        run = simulate(builtin_binding("averaged"), bound_pi, load_scenario("reference_up", PAPER_SPEC)).frame
        assert numeric_difference(run, first["pi"]) == 0.0
    finally:
        bound_pi.close()


def test_build_fmu_and_export_controller_take_fmi_version_3(tmp_path):
    done = cli("build-fmu", "--fmi-version", "3", "--output", str(tmp_path / "plant"))
    assert done.returncode == 0, done.stderr
    assert "FMI 3.0 co-simulation + model exchange FMU" in done.stdout
    assert check_fmu(tmp_path / "plant" / "BuckConverter.fmu").fmi_major == 3
    done = cli("export-controller", "pi", "--kp", str(PI_GAINS[0]), "--ki", str(PI_GAINS[1]), "--fmi-version", "3",
               "--out", str(tmp_path / "pi.fmu"))
    assert done.returncode == 0, done.stderr
    assert "as an FMI 3.0 co-simulation FMU" in done.stdout
    assert fmpy.read_model_description(str(tmp_path / "pi.fmu")).fmiVersion == "3.0"


# ------------------------------------------------------------------------------------------ SSP


def test_an_ssp_loop_of_fmi3_components_runs_in_the_workbench_engine_only(tmp_path, buck_fmu3):
    """export-ssp's loop with an FMI 3.0 controller, scenario source and plant: the workbench's engine runs it
    to the FMI 2.0 loop's bits; fmpy's SSP simulation and libcosim run FMI 2.0 components only, refused in one
    line before anything runs."""
    from cosim.fmi.controller_export import export_controller
    from cosim.ssp.engines import run_ssp
    from cosim.ssp.package import SspError, export_ssp, read_ssp

    runs = {}
    for version, binding in ((2, builtin_binding("averaged")),
                             (3, replace(builtin_binding("averaged"), fmu_path=buck_fmu3))):
        controller, _ = export_controller(pi(), tmp_path / f"pi{version}.fmu", fmi_version=version)
        export_ssp(load_scenario("reference_up", PAPER_SPEC), binding, controller, tmp_path / f"loop{version}.ssp")
        runs[version] = run_ssp(tmp_path / f"loop{version}.ssp", "workbench").frame
    loop = read_ssp(tmp_path / "loop3.ssp")
    assert {name: c.fmi_version for name, c in loop.components.items()} == \
        {"scenario": "3.0", "controller": "3.0", "plant": "3.0"}
    assert numeric_difference(runs[2], runs[3]) == 0.0
    for engine, why in (("fmpy", "instantiates every component with FMU2Slave"),
                        ("libcosim", "refuses FMI 3.0 FMUs: 'Unsupported FMI version'")):
        with pytest.raises(SspError, match=f"engine {engine} runs FMI 1.0 and 2.0 components only .*{why}.*; "
                                           "components 'scenario', 'controller', 'plant' are FMI 3.0: run this "
                                           "archive with --engine workbench"):
            run_ssp(tmp_path / "loop3.ssp", engine)


@pytest.mark.parametrize("version", [2, 3])
def test_export_ssp_builds_a_named_controller_in_the_fmi_version_asked_for(tmp_path, version):
    """``export-ssp --controller pi --fmi-version N``: the PI is exported as an FMI N.0 FMU beside the scenario source
    and the built-in plant of the same version (the version was once passed as the C build's precision: the command
    failed with 'precision 2 is unknown')."""
    from cosim.ssp.package import read_ssp

    done = cli("export-ssp", "reference_up", "--controller", "pi", "--fmi-version", str(version),
               "--out", "loop.ssp", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    loop = read_ssp(tmp_path / "loop.ssp")
    assert {name: c.fmi_version for name, c in loop.components.items()} == \
        {"scenario": f"{version}.0", "controller": f"{version}.0", "plant": f"{version}.0"}


def test_the_fmi3_edition_names_fmi3_functions_in_its_messages(buck_fmu3):
    """The model is written against the FMI 2.0 API; its FMI 3.0 edition's messages name what the caller called."""
    from fmpy.fmi1 import FMICallException
    from fmpy.fmi3 import FMU3Slave

    md = fmpy.read_model_description(str(buck_fmu3))
    messages = []
    unzipped = fmpy.extract(str(buck_fmu3))
    fmu = FMU3Slave(guid=md.guid, unzipDirectory=unzipped, modelIdentifier=md.coSimulation.modelIdentifier,
                    instanceName="names")
    fmu.instantiate(loggingOn=True, logMessage=lambda env, status, category, message: messages.append(message.decode()))
    try:
        fmu.enterInitializationMode()
        fmu.exitInitializationMode()
        frequency = next(v.valueReference for v in md.modelVariables if v.name == "switching_frequency")
        with pytest.raises(FMICallException):
            fmu.setFloat64([frequency], [1e5])
    finally:
        fmu.freeInstance()
        shutil.rmtree(unzipped, ignore_errors=True)
    assert messages[-1] == "fmi3SetFloat64: switching_frequency can only be set before fmi3ExitInitializationMode"
    assert not any("fmi2" in m for m in messages)
