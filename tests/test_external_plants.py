"""Externally authored plant FMUs through binding files, and every refusal of a bad FMU or binding."""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from conftest import CORPUS, PLANT_CONVERTER, cli, one_line_error, role_named_binding

from cosim.base.errors import ConfigError, FmuArchiveError, WorkbenchError
from cosim.cli import main
from cosim.fmi.archive import check_fmu
from cosim.fmi.binding_file import guess_roles, load_binding
from cosim.master import simulate
from cosim.metrics import run_metrics
from cosim.results import read_run
from cosim.scenarios import load_scenario
from cosim.study.vocabulary import PAPER_SPEC

PYTHON_BINDING = """\
fmu = "{fmu}"
label = "PyBuck (pythonfmu)"

[roles.duty_cycle]
variable = "D"
scale = 100.0          # the FMU takes percent

[roles.output_voltage]
variable = "Vout"

[roles.inductor_current]
variable = "IL_mA"
scale = 1000.0         # the FMU reports mA

[roles.load_resistance]
variable = "Rload"

[roles.input_voltage]
variable = "Vin"

[roles.load_current]
variable = "Iout"

[parameters]
rL = 0.15

""" + PLANT_CONVERTER + """[converter.circuit]
inductance = "L"
capacitance = "C"
inductor_resistance = "rL"
capacitor_esr = "rC"
"""

ME_BINDING = """\
fmu = "{fmu}"
interface = "model-exchange"

[roles.duty_cycle]
variable = "duty_cycle"

[roles.output_voltage]
variable = "output_voltage"

[roles.inductor_current]
variable = "inductor_current"

[parameters]
plant_mode = 0

""" + PLANT_CONVERTER


def write(tmp_path: Path, text: str, name: str = "plant.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.fixture
def python_binding(tmp_path, python_buck_fmu):
    shutil.copy(python_buck_fmu, tmp_path / "PyBuck.fmu")
    return write(tmp_path, PYTHON_BINDING.format(fmu="PyBuck.fmu"))


def pi(period=1e-3):
    from controllers.pi import PIController

    return PIController(0.0, 0.7 / (48 * period), period)


# ------------------------------------------------------------------------------------------ running


def test_pi_start_up_settles_on_the_pythonfmu_plant(python_binding):
    binding = load_binding(python_binding)
    assert binding.interface is None and binding.roles["duty_cycle"].scale == 100.0
    result = simulate(binding, pi(), load_scenario("startup", PAPER_SPEC))
    metrics = run_metrics(result)
    assert abs(metrics["steady_state_error_pct"]) < 0.1 and metrics["settling_time_ms"] < 10
    assert result.metadata["plant"]["binding_file"] == str(python_binding.resolve())
    assert result.frame["inductor_current"].iloc[-1] == pytest.approx(2.0, rel=0.01)  # mA converted to A


def test_pi_start_up_settles_on_the_model_exchange_only_fmu(tmp_path, me_only_fmu):
    binding = load_binding(write(tmp_path, ME_BINDING.format(fmu=me_only_fmu)))
    result = simulate(binding, pi(), load_scenario("startup", PAPER_SPEC))
    assert result.metadata["plant"]["interface"] == "model-exchange"
    assert abs(run_metrics(result)["steady_state_error_pct"]) < 0.1


def test_nnpc_collects_trains_and_runs_on_the_pythonfmu_plant(python_binding, tmp_path):
    out = tmp_path / "out"
    code = main(["--no-progress", "run", "reference_up", "load_change", "--plant", str(python_binding),
                 "--controller", "pi", "--controller", "nnpc", "--samples", "1500", "--out", str(out), "--no-figures"])
    assert code == 0
    assert list((out / "data").glob("*.parquet")) and list((out / "models").glob("*__nnpc.pt"))
    for scenario in ("reference_up", "load_change"):
        run = read_run(out / "runs" / f"{scenario}__nnpc__bound-plant__1ms.parquet")
        assert run.complete and abs(run.frame["output_voltage"].iloc[-1] / run.frame["reference"].iloc[-1] - 1) < 0.01


def test_reproduce_runs_its_pipeline_on_a_bound_plant(python_binding, tmp_path):
    out = tmp_path / "results"
    assert main(["--no-progress", "reproduce", "--quick", "--plant", str(python_binding), "--out", str(out)]) == 0
    report = (out / "REPORT.md").read_text()
    assert "bound-plant__1ms" in report and "MPC-nominal" in report
    assert (out / "models" / "bound-plant__1ms__nnpc.pt").is_file()


def test_draft_binding_guesses_roles_from_names_and_units(python_buck_fmu, buck_fmu, tmp_path):
    guesses = {role: g[0] for role, g in guess_roles(check_fmu(python_buck_fmu).model_description).items()}
    assert guesses == {"duty_cycle": "D", "input_voltage": "Vin", "load_resistance": "Rload", "output_voltage": "Vout",
                       "inductor_current": "IL_mA", "load_current": "Iout"}
    shutil.copy(buck_fmu, tmp_path / "Buck.fmu")
    assert main(["inspect", str(tmp_path / "Buck.fmu"), "--draft-binding", str(tmp_path / "draft.toml")]) == 0
    draft = load_binding(tmp_path / "draft.toml")  # a draft of our own FMU loads as it is
    assert draft.roles["inductor_current"].variable == "inductor_current"
    assert draft.roles["duty_cycle"].variable == "duty_cycle"
    # a binding edited by hand is never replaced by a new draft, and a draft is named as the TOML it is
    edited = (tmp_path / "draft.toml").read_text().replace("label =", "# my edit\nlabel =")
    (tmp_path / "draft.toml").write_text(edited)
    one_line_error(cli("inspect", str(tmp_path / "Buck.fmu"), "--draft-binding", str(tmp_path / "draft.toml")), 2,
                   f"--draft-binding {tmp_path / 'draft.toml'} exists: a draft never replaces a file")
    assert (tmp_path / "draft.toml").read_text() == edited
    one_line_error(cli("inspect", str(tmp_path / "Buck.fmu"), "--draft-binding", str(tmp_path / "draft.json")), 2,
                   "--draft-binding " + str(tmp_path / "draft.json") + " is invalid: expected a file name ending in "
                   ".toml (a plant-binding file is TOML)")
    assert not (tmp_path / "draft.json").exists()


# ------------------------------------------------------------------------------------------ refusals


@pytest.mark.parametrize("edit,message", [
    (("label =", "lable ="), r"plant.toml:2: unknown key 'lable'"),
    (("[roles.load_current]", "[roles.load_currnt]"), r"plant.toml:\d+: unknown role 'load_currnt'"),
    (('variable = "D"\nscale = 100.0          # the FMU takes percent\n', ""), r"role 'duty_cycle' must be a table|missing role|variable"),
    (('variable = "Vout"', 'variable = "V_out"'), r"plant.toml:9: role 'output_voltage' names variable 'V_out', which PyBuck.fmu does not have"),
    (('[roles.input_voltage]\nvariable = "Vin"\n\n[roles.load_current]\nvariable = "Iout"\n',
      '[roles.input_voltage]\nvariable = "Iout"\n'),
     r"role 'input_voltage' needs causality input or parameter, but 'Iout' has causality output"),
    # a variable the workbench writes must be the role's own (the supply dip was written into Rload and lost)
    (('variable = "Vin"', 'variable = "Rload"'), r"plant.toml:\d+: role 'input_voltage' names variable 'Rload', "
                                                 r"which role 'load_resistance' names too: the workbench writes "
                                                 r"input_voltage into it"),
    (("scale = 1000.0", "scale = 0"), r"plant.toml:13: roles.inductor_current.scale = 0 is invalid"),
    (("rL = 0.15", "Lf = 0.15"), r"plant.toml:\d+: parameter 'Lf' is not a variable of PyBuck.fmu"),
    # [parameters] sets what the FMU takes and the workbench leaves alone: not an output, not a role's variable
    (("rL = 0.15", "Vout = 5.0"), r"plant.toml:\d+: parameter 'Vout' is an output of PyBuck.fmu: the FMU computes it"),
    (("rL = 0.15", "Rload = 3.0"), r"plant.toml:\d+: parameter 'Rload' is the variable of role 'load_resistance', "
                                   r"which the workbench sets itself"),
    (('fmu = "PyBuck.fmu"', 'fmu = "Nope.fmu"'), r"plant.toml:1: FMU .*Nope.fmu does not exist"),
    (('label = "PyBuck (pythonfmu)"', 'interface = "model-exchange"'), r"plant.toml:2: interface 'model-exchange' is not available \(the FMU offers: co-simulation\)"),
    (('label = "PyBuck (pythonfmu)"', 'interface = "cosim"'), r"interface 'cosim' is unknown"),
])
def test_binding_mistakes_name_file_key_and_line(python_binding, edit, message):
    text = python_binding.read_text().replace(*edit, 1)
    with pytest.raises(WorkbenchError, match=message):
        load_binding(write(python_binding.parent, text))


def test_an_fmu_or_a_controller_binding_given_as_the_plant_binding_is_named_as_what_it_is(python_binding, tmp_path,
                                                                                        buck_fmu):
    with pytest.raises(ConfigError, match=r"^\S+\.fmu is an FMU, not a binding file: a binding file \(\.toml\) names "
                                          r"the FMU and its variables' roles -- draft one with buck-cosim inspect "):
        load_binding(buck_fmu)
    text = python_binding.read_text().replace("[roles.output_voltage]", "[roles.reference]")
    with pytest.raises(ConfigError, match=r"plant.toml:\d+: role 'reference' is a controller role: this is a "
                                          r"controller binding file, given where a plant binding is expected$"):
        load_binding(write(python_binding.parent, text))
    from cosim.fmi.controller import load_controller_binding

    with pytest.raises(ConfigError, match=r"plant.toml:\d+: \[converter\] is a plant binding's table: this is a plant "
                                          r"binding file, given where a controller binding is expected$"):
        load_controller_binding(python_binding)


def test_missing_required_role_is_refused(python_binding):
    text = python_binding.read_text().replace("[roles.duty_cycle]\nvariable = \"D\"\nscale = 100.0          # the FMU takes percent\n", "")
    with pytest.raises(ConfigError, match=r"plant.toml: missing role \[roles.duty_cycle\]"):
        load_binding(write(python_binding.parent, text))


def test_a_scenario_needing_a_missing_role_is_refused_before_the_run(tmp_path, me_only_fmu):
    path = write(tmp_path, ME_BINDING.format(fmu=me_only_fmu))
    with pytest.raises(ConfigError, match=r"scenario load_change changes load_resistance, but binding file .*plant.toml "
                                          r"binds no variable to the role 'load_resistance'"):
        simulate(load_binding(path), pi(), load_scenario("load_change", PAPER_SPEC))
    done = subprocess.run([sys.executable, "-m", "cosim.cli", "run", "load_change", "--plant", str(path), "--kp", "0",
                           "--ki", "14", "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
    assert "binds no variable to the role 'load_resistance'" in done.stderr
    assert not (tmp_path / "out" / "runs").exists()  # nothing ran


def _fmu_with(tmp_path: Path, name: str, members: dict[str, bytes]) -> Path:
    path = tmp_path / name
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for member, data in members.items():
            z.writestr(member, data)
    return path


def damaged_copy(fmu: Path, path: Path) -> Path:
    """``fmu`` with one byte of its shared library's data flipped: the zip directory, modelDescription.xml and every
    header sound, the library's bytes no longer matching their CRC-32 (a file damaged on disk or in transfer)."""
    with zipfile.ZipFile(fmu) as source, zipfile.ZipFile(path, "w") as target:
        for info in source.infolist():  # stored, not deflated: the flipped byte stays a readable byte
            target.writestr(info.filename, source.read(info.filename), zipfile.ZIP_STORED)
    with zipfile.ZipFile(path) as archive:
        info = next(i for i in archive.infolist() if i.filename.endswith(".so"))
    data = bytearray(path.read_bytes())
    name_length, extra_length = struct.unpack("<HH", data[info.header_offset + 26:info.header_offset + 30])
    middle = info.header_offset + 30 + name_length + extra_length + info.file_size // 2
    data[middle] ^= 0xFF
    path.write_bytes(bytes(data))
    return path


MD = '<?xml version="1.0"?><fmiModelDescription fmiVersion="{v}" modelName="x" guid="{{1}}"/>'


def _crafted(tmp_path: Path, buck_fmu: Path, kind: str) -> Path:
    if kind == "not a zip":
        path = tmp_path / "text.fmu"
        path.write_text("this is not an FMU")
        return path
    if kind == "truncated":
        path = tmp_path / "truncated.fmu"
        path.write_bytes(buck_fmu.read_bytes()[:4000])
        return path
    if kind == "absolute member":
        return _fmu_with(tmp_path, "abs.fmu", {"modelDescription.xml": MD.format(v="2.0"), "/etc/evil": b"x"})
    if kind == "climbing member":
        return _fmu_with(tmp_path, "climb.fmu", {"modelDescription.xml": MD.format(v="2.0"), "../../evil.so": b"x"})
    if kind == "huge":  # a zip bomb's header: the central directory claims 4 GiB uncompressed
        path = _fmu_with(tmp_path, "huge.fmu", {"modelDescription.xml": MD.format(v="2.0"), "big.bin": b"0" * 100})
        data = bytearray(path.read_bytes())
        entry = data.rfind(b"PK\x01\x02")  # central directory header of the last member
        data[entry + 24:entry + 28] = struct.pack("<I", 0xFFFFFFF0)
        path.write_bytes(bytes(data))
        return path
    if kind == "damaged member":
        return damaged_copy(buck_fmu, tmp_path / "damaged.fmu")
    if kind == "fmi1":
        return _fmu_with(tmp_path, "fmi1.fmu", {"modelDescription.xml": MD.format(v="1.0")})
    if kind == "fmi4":
        return _fmu_with(tmp_path, "fmi4.fmu", {"modelDescription.xml": MD.format(v="4.0")})
    if kind == "no binary":
        from plant_fmu import source_fmu_path

        path = tmp_path / "source.fmu"
        shutil.copy(source_fmu_path(), path)
        return path
    if kind == "no description":
        return _fmu_with(tmp_path, "nodesc.fmu", {"binaries/linux64/x.so": b"x"})
    if kind == "malformed description":
        return _fmu_with(tmp_path, "bad.fmu", {"modelDescription.xml": "<fmiModelDescription fmiVersion='2.0'"})
    raise ValueError(kind)


@pytest.mark.parametrize("kind,message", [
    ("not a zip", r"text.fmu is not a zip archive"),
    ("truncated", r"truncated.fmu is (not a zip archive|a damaged zip archive|truncated)"),
    ("absolute member", r"member '/etc/evil' is an absolute path; refusing to extract it"),
    ("climbing member", r"member '../../evil.so' climbs out of the archive"),
    ("huge", r"huge.fmu would expand to 4096 MiB, more than the limit of 1024 MiB"),
    ("damaged member", r"damaged.fmu is damaged: member 'binaries/linux64/BuckConverter.so' does not match its "
                       r"CRC-32 checksum \(the archive was corrupted on disk or in transfer\)"),
    ("fmi1", r"fmi1.fmu is FMI 1.0; the workbench supports FMI 2.0"),
    ("fmi4", r"fmi4.fmu is FMI 4.0; the workbench supports FMI 2.0 and FMI 3.0"),
    ("no binary", r"source.fmu has no linux64 binary for its interfaces \(co-simulation, model-exchange\); binaries present: none"),
    ("no description", r"nodesc.fmu has no modelDescription.xml"),
    ("malformed description", r"bad.fmu: modelDescription.xml is not well-formed XML"),
])
def test_bad_fmu_archives_are_refused_before_extraction(tmp_path, buck_fmu, kind, message):
    path = _crafted(tmp_path, buck_fmu, kind)
    with pytest.raises(FmuArchiveError, match=message):
        check_fmu(path)
    done = subprocess.run([sys.executable, "-m", "cosim.cli", "inspect", str(path)], capture_output=True, text=True)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and done.stderr.startswith("error: FMU")


def test_a_measured_voltage_without_a_measured_load_current_is_warned_about(python_binding, capsys):
    """vo read as a period mean but io as a point sample skews the load estimate vo/io in every
    transient (the mistake that made the 13.33 us start-up overshoot 60 %): say so at load time."""
    text = python_binding.read_text() + '\n[roles.measured_output_voltage]\nvariable = "Vout"\n'
    load_binding(write(python_binding.parent, text))
    warning = capsys.readouterr().err
    assert "plant.toml: [roles.measured_output_voltage] is bound but [roles.measured_load_current] is not" in warning
    load_binding(write(python_binding.parent, text + '\n[roles.measured_load_current]\nvariable = "Iout"\n'))
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("isolate", ["--isolate", "--no-isolate"])
def test_a_damaged_fmu_is_refused_in_one_line_and_nothing_is_left_behind(tmp_path, buck_fmu, isolate):
    """A member whose bytes fail their CRC: refused at the binding's fmu line, exit 2, before anything is extracted
    (no partly unpacked FMU in the temporary folder), with the plant process or without."""
    fmu = damaged_copy(buck_fmu, tmp_path / "Damaged.fmu")
    binding = write(tmp_path, role_named_binding(fmu, parameters=""), "damaged.toml")
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    done = cli("run", "startup", "--plant", str(binding), isolate, "--kp", "0", "--ki", "14", "--out",
               str(tmp_path / "out"), env={**os.environ, "TMPDIR": str(scratch)})
    line = one_line_error(done, 2, f"damaged.toml:1: FMU {fmu} is damaged: member 'binaries/linux64/BuckConverter.so' "
                                   "does not match its CRC-32 checksum")
    assert str(binding) in line
    assert list(scratch.iterdir()) == [] and not (tmp_path / "out" / "runs").exists()


def test_an_input_role_bound_to_a_fixed_parameter_is_refused_at_its_line(python_binding, tmp_path):
    """The duty written into the capacitance (a fixed parameter: the FMU takes it only before initialisation) would
    run silently on a lax FMU: refused when the binding is read, at the role's variable line, exit 2."""
    text = python_binding.read_text().replace('[roles.duty_cycle]\nvariable = "D"', '[roles.duty_cycle]\nvariable = "C"')
    write(tmp_path, text)
    done = cli("run", "startup", "--plant", str(python_binding), "--kp", "0", "--ki", "14", "--out",
               str(tmp_path / "out"))
    one_line_error(done, 2, f"{python_binding}:5: role 'duty_cycle' is set by the workbench during the run, so it needs "
                            "an input or a tunable parameter, but 'C' is a parameter with variability fixed (the FMU "
                            "takes it only before initialisation)")
    assert not (tmp_path / "out" / "runs").exists()


def test_a_draft_binding_guesses_from_declared_units_where_names_say_nothing(tmp_path):
    """An FMI 3.0 FMU with opaque names and declared units (% V Ohm V mA): every role its units single out is
    guessed, with the scale its unit implies, and the command says which guesses came from units alone."""
    from pythonfmu3.builder import FmuBuilder

    fmu = Path(FmuBuilder.build_FMU(CORPUS / "unit_named_buck3.py", dest=tmp_path,
                                    project_files=[CORPUS / "buck_math.py"], canHandleVariableCommunicationStepSize=True))
    done = cli("inspect", str(fmu), "--draft-binding", str(tmp_path / "draft.toml"))
    assert done.returncode == 0, done.stderr
    assert ("guessed from the declared units alone (no name matched): duty_cycle = command (scale 100), input_voltage "
            "= rail, load_resistance = sink, output_voltage = terminal, inductor_current = winding (scale 1000)"
            in done.stdout)
    text = (tmp_path / "draft.toml").read_text()
    assert "[roles.duty_cycle]   # guessed from unit % alone (the only input in a duty unit" in text
    draft = load_binding(tmp_path / "draft.toml")
    assert {r: (m.variable, m.scale) for r, m in draft.roles.items()} == {
        "duty_cycle": ("command", 100.0), "input_voltage": ("rail", 1.0), "load_resistance": ("sink", 1.0),
        "output_voltage": ("terminal", 1.0), "inductor_current": ("winding", 1000.0)}
    assert "warning" not in done.stderr  # every guessed role declares its unit: no unitless-scale warning
