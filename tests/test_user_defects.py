"""Defects found by trying the workbench as a new user would (bad inputs, faulty FMUs,
interruptions), each with the test that would have caught it. README: "What happens when things
go wrong"."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from conftest import cli, faulty_binding, interrupt_on, message_lines, one_line_error, role_named_binding

from controllers.nn_config import NNConfig, TrainingSettings
from controllers.nn_model import _checksum, load_model, save_model, train
from cosim.base.errors import ModelFileError
from cosim.results import read_run, write_parquet
from cosim.study.vocabulary import PAPER_SPEC


def strict_json(path: Path):
    """JSON as the standard has it: NaN and Infinity are not JSON."""
    def refuse(constant):
        raise AssertionError(f"{path} holds {constant}, which is not JSON")
    return json.loads(path.read_text(), parse_constant=refuse)


def small_frame(n=300, **extra) -> pd.DataFrame:
    return pd.DataFrame({"measured_inductor_current": np.linspace(0, 2, n),
                         "measured_output_voltage": np.linspace(0, 12, n), "duty_cycle": np.full(n, 0.25), **extra})


# ------------------------------------------------------------------ 1. streamed runs keep their metadata


def test_an_interrupted_streamed_run_exported_to_csv_is_still_marked_incomplete(tmp_path, faulty_fmu):
    binding = tmp_path / "faulty.toml"
    binding.write_text(faulty_binding(faulty_fmu, 1))
    one_line_error(cli("run", "startup", "--plant", str(binding), "--kp", "0", "--ki", "14", "--stream",
                       "--record-period", "1e-4", "--out", str(tmp_path / "out")), 3, "fmi2DoStep failed (discard)")
    streamed = tmp_path / "out" / "runs" / "startup__pi__bound-faulty__1ms.parquet"
    assert read_run(streamed).metadata["complete"] is False
    assert cli("export", str(streamed), "--to", "csv", "--out", str(tmp_path / "csv")).returncode == 0
    meta = strict_json(tmp_path / "csv" / "startup__pi__bound-faulty__1ms.json")
    assert meta["complete"] is False and "fmi2DoStep failed (discard) at t = 0.0103" in meta["error"]
    assert meta["streamed"] is True and meta["rows"] == len(pd.read_csv(tmp_path / "csv" /
                                                                         "startup__pi__bound-faulty__1ms.csv"))
    back = read_run(tmp_path / "csv" / "startup__pi__bound-faulty__1ms.csv")  # and back to Parquet keeps it too
    assert back.complete is False and back.error == meta["error"] and back.metadata["streamed"] is True


# ------------------------------------------------------------------ 2, 3. model files


@pytest.fixture(scope="module")
def tiny_model():
    return train(small_frame(), NNConfig(), TrainingSettings(max_iterations=10), metadata={"control_period_s": 1e-3})


def test_non_finite_weights_with_a_valid_checksum_are_refused(tiny_model, tmp_path):
    path = save_model(tiny_model, tmp_path / "good.pt")
    payload = torch.load(path, weights_only=True)
    payload["state_dict"]["layers.0.weight"][0, 0] = math.nan
    norm = [payload["normalisation"][k].numpy() for k in ("input_mean", "input_std", "output_mean", "output_std")]
    payload["checksum"] = _checksum(payload["state_dict"], norm)  # a tamperer who knows the format
    torch.save(payload, tmp_path / "nan.pt")
    with pytest.raises(ModelFileError, match=r"nan.pt has non-finite values in layers.0.weight: refused"):
        load_model(tmp_path / "nan.pt", expect_period=1e-3)
    payload = torch.load(path, weights_only=True)
    payload["normalisation"]["input_std"][1] = math.inf
    norm = [payload["normalisation"][k].numpy() for k in ("input_mean", "input_std", "output_mean", "output_std")]
    payload["checksum"] = _checksum(payload["state_dict"], norm)
    torch.save(payload, tmp_path / "inf.pt")
    with pytest.raises(ModelFileError, match=r"non-finite values in normalisation input_std"):
        load_model(tmp_path / "inf.pt")


def test_training_refuses_non_finite_data_and_saving_refuses_non_finite_weights(tiny_model, tmp_path):
    frame = small_frame()
    frame.loc[40, "measured_output_voltage"] = math.nan
    with pytest.raises(ValueError, match=r"1 of 300 samples hold NaN or infinite values in measured_inductor_current, "
                                         r"measured_output_voltage, duty_cycle \(first: row 40\)"):
        train(frame, NNConfig(), TrainingSettings(max_iterations=10))
    with torch.no_grad():
        tiny_model.network.layers[0].weight[0, 0] = math.inf
    with pytest.raises(ValueError, match=r"non-finite values in layers.0.weight .* refusing to save it"):
        save_model(tiny_model, tmp_path / "inf.pt")
    assert not (tmp_path / "inf.pt").exists()


def test_data_without_a_control_period_needs_one_and_a_model_without_one_is_refused_at_use(tmp_path):
    write_parquet(small_frame(), {}, tmp_path / "foreign.parquet")  # no workbench metadata at all
    one_line_error(cli("train", "foreign.parquet", "--out", "m.pt", cwd=tmp_path), 2,
                   "foreign.parquet has no workbench metadata naming its control period")
    assert not (tmp_path / "m.pt").exists()
    assert cli("train", "foreign.parquet", "--control-period", "1/75e3", "--out", "m.pt", cwd=tmp_path).returncode == 0
    assert load_model(tmp_path / "m.pt").metadata["control_period_s"] == pytest.approx(1 / 75e3, rel=1e-12)
    one_line_error(cli("run", "startup", "--controller", "nnpc", "--model", "m.pt", "--out", "o", cwd=tmp_path), 2,
                   "was trained at a control period of 13.33 us; the controller samples every 1000 us")
    model = train(small_frame(), NNConfig(), TrainingSettings(max_iterations=10))  # no period in its metadata
    save_model(model, tmp_path / "periodless.pt")
    one_line_error(cli("run", "startup", "--controller", "nnpc", "--model", "periodless.pt", "--out", "o",
                       cwd=tmp_path), 2, "periodless.pt names no control period")
    write_parquet(small_frame(), {"control_period_s": 1e-3}, tmp_path / "ours.parquet")
    one_line_error(cli("train", "ours.parquet", "--control-period", "2e-3", "--out", "x.pt", cwd=tmp_path), 2,
                   "was collected at a control period of 0.001 s, not the --control-period 0.002 s given")


def test_random_bytes_and_folders_are_named_for_what_they_are(tmp_path):
    (tmp_path / "noise.pt").write_bytes(os.urandom(4096))
    with pytest.raises(ModelFileError, match=r"noise.pt is not a model written by buck-cosim train \(not a torch "
                                             r"zip archive"):
        load_model(tmp_path / "noise.pt")
    with pytest.raises(ModelFileError, match=r"is a folder: expected a .pt file"):
        load_model(tmp_path)
    one_line_error(cli("export", str(tmp_path), "--to", "csv"), 2, "is a folder: expected a run's .parquet or .csv")
    one_line_error(cli("run", str(tmp_path), "--kp", "0", "--ki", "14", "--out", str(tmp_path / "o")), 2,
                   "is a folder: expected a scenario file")
    one_line_error(cli("run", "startup", "--plant", str(tmp_path), "--kp", "0", "--ki", "14"), 2,
                   "is a folder: expected a .toml file")
    one_line_error(cli("inspect", str(tmp_path)), 2, "is a folder: expected a .fmu file")


# ------------------------------------------------------------------ 5. numbers written to JSON


def test_every_json_file_a_run_writes_is_strict_json(tmp_path):
    done = cli("run", "startup", "--kp", "0", "--ki", "14", "--no-figures", "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr
    files = list(tmp_path.rglob("*.json"))
    assert files
    for path in files:
        strict_json(path)


# ------------------------------------------------------------------ 6, 7. impossible requests, work before checks


def test_a_reference_above_the_supply_is_refused_with_its_line(tmp_path):
    (tmp_path / "high.toml").write_text('name = "high"\nduration = 0.03\n[initial]\nreference = 12.0\n'
                                        '[[events]]\ntime = 0.02\ninput_voltage = 40.0\n'
                                        '[[events]]\ntime = 0.01\nreference = 45.0\n')
    one_line_error(cli("run", str(tmp_path / "high.toml"), "--kp", "0", "--ki", "14", "--out", str(tmp_path)), 2,
                   "high.toml:7: the reference 45 V at t = 0.02 s exceeds the input voltage 40 V in effect then: a "
                   "buck converter's output cannot exceed its input")  # line 7: the supply step that makes it so


def test_a_control_period_longer_than_the_scenario_is_refused_before_any_tuning(tmp_path):
    error = one_line_error(cli("run", "startup", "--control-period", "0.05", "--out", str(tmp_path)), 2,
                           "scenario startup records 0.03 s, which holds 1 controller sample(s) at control period "
                           "0.05 s: expected at least 2")
    assert "startup.toml:4:" in error  # the duration's line
    assert not (tmp_path / "tuning").exists()  # refused before the PI was tuned


def test_bad_collection_settings_are_refused_before_the_pi_is_tuned(tmp_path):
    one_line_error(cli("collect-data", "--samples", "50", "--work-dir", str(tmp_path), "--out",
                       str(tmp_path / "d.parquet")), 2, "argument --samples: 50 is invalid")
    one_line_error(cli("collect-data", "--excitation", "0.7", "--work-dir", str(tmp_path), "--out",
                       str(tmp_path / "d.parquet")), 2, "argument --excitation: 0.7 is invalid")
    assert not list(tmp_path.rglob("*.json")) and not (tmp_path / "d.parquet").exists()


def test_a_bad_model_file_is_refused_before_the_pi_is_tuned(tmp_path):
    (tmp_path / "bad.pt").write_bytes(b"junk")
    one_line_error(cli("run", "startup", "--controller", "pi", "--controller", "nnpc", "--model",
                       str(tmp_path / "bad.pt"), "--out", str(tmp_path)), 2, "bad.pt is not a model")
    assert not (tmp_path / "tuning").exists()


# ------------------------------------------------------------------ 8. messages that name the place


@pytest.mark.parametrize("parameter,message", [
    ("fault_kind = 1.5", "faulty.toml:9: parameter 'fault_kind' is Integer in FaultyBuck.fmu, got 1.5 (float)"),
    ('fault_time = "big"', "faulty.toml:10: parameter 'fault_time' is Real in FaultyBuck.fmu, got 'big' (str)"),
    ("fault_kind = true", "faulty.toml:9: parameter 'fault_kind' is Integer in FaultyBuck.fmu, got True (bool)"),
])
def test_a_wrongly_typed_binding_parameter_is_refused_with_its_line_when_the_file_loads(tmp_path, faulty_fmu,
                                                                                       parameter, message):
    from cosim.base.errors import ConfigError
    from cosim.fmi.binding_file import load_binding

    name = parameter.split(" = ")[0]
    lines = faulty_binding(faulty_fmu, 0).splitlines()
    text = "\n".join(parameter if line.startswith(f"{name} = ") else line for line in lines) + "\n"
    (tmp_path / "faulty.toml").write_text(text)
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_binding(tmp_path / "faulty.toml")  # before any FMU is opened


def test_a_binding_parameter_the_fmu_refuses_is_named_at_its_line_before_any_tuning_or_run(tmp_path, buck_fmu):
    binding = tmp_path / "plant.toml"
    binding.write_text(role_named_binding(buck_fmu, parameters="capacitance = 4.7e-6\ninductance = -1\n"))
    message = ("plant.toml:14: parameters.inductance = -1: the plant FMU refuses its set-up with this value "
               "(fmi2SetReal failed (error) at t = 0 s: fmi2SetReal: inductance = -1 H is invalid")
    for command in (["run", "startup", "--plant", str(binding), "--out", str(tmp_path / "out")],  # gains: tuned
                    ["tune-pi", "--plant", str(binding), "--out", str(tmp_path / "pi.json")],
                    ["collect-data", "--plant", str(binding), "--work-dir", str(tmp_path / "out"), "--out",
                     str(tmp_path / "d.parquet")],
                    ["inspect", str(binding)]):
        one_line_error(cli(*command), 2, message)
    assert not (tmp_path / "out" / "tuning").exists() and not (tmp_path / "out" / "runs").exists()
    assert not (tmp_path / "pi.json").exists() and not (tmp_path / "d.parquet").exists()


def test_a_refused_set_up_is_told_apart_one_value_their_combination_or_the_rest(tmp_path, buck_fmu):
    """locate_refusal, with an FMU that refuses Rload < 0 in its inputs, inductance < 0 alone, and inductance above
    1 mH together with capacitance above 1 mF (the try_set_up below plays it)."""
    from cosim.fmi.binding_file import PARAMETER, REST, TOGETHER, load_binding, locate_refusal

    def fmu(refuse_inputs=False):
        def try_set_up(parameters):
            tried.append(dict(parameters))
            together = parameters.get("inductance", 0) > 1e-3 and parameters.get("capacitance", 0) > 1e-3
            return not (refuse_inputs or parameters.get("inductance", 0) < 0 or together)
        return try_set_up

    path = tmp_path / "plant.toml"
    for values, refuse_inputs, expected in (
            ("capacitance = 4.7e-6\ninductance = -1\n", False, (PARAMETER, ":14", "inductance", -1)),
            ("capacitance = 2e-3\ninductance = 2e-3\n", False, (TOGETHER, ":12", "", None)),
            ("capacitance = 4.7e-6\n", True, (REST, "", "", None))):
        path.write_text(role_named_binding(buck_fmu, parameters=values))
        tried = []
        refusal = locate_refusal(load_binding(path), fmu(refuse_inputs))
        assert (refusal.kind, refusal.place[len(str(path)):], refusal.name, refusal.value) == expected
        assert tried[0] == {}  # first without any binding value: the inputs or the FMU's defaults are not blamed on one
    path.write_text(role_named_binding(buck_fmu, parameters=""))
    assert locate_refusal(load_binding(path), fmu(refuse_inputs=True)) is None  # no binding value to locate


def test_refused_first_inputs_are_named_as_the_scenarios_not_a_binding_value(tmp_path, buck_fmu):
    from dataclasses import replace

    from cosim.base.errors import ConfigError
    from cosim.fmi.binding_file import load_binding
    from cosim.master import check_set_up
    from cosim.scenarios import load_scenario

    (tmp_path / "plant.toml").write_text(role_named_binding(buck_fmu, parameters="capacitance = 4.7e-6\n"))
    startup = load_scenario("startup", PAPER_SPEC)
    refused = replace(startup, initial={**startup.initial, "load_resistance": -1.0})  # past the file's own checks
    with pytest.raises(ConfigError) as caught:
        check_set_up(replace(load_binding(tmp_path / "plant.toml"), isolate=False), [startup, refused])
    assert str(caught.value) == (
        f"{startup.place('initial')}: the plant FMU (binding file {tmp_path / 'plant.toml'}) refuses its set-up at the "
        "start of scenario startup (duty_cycle = 0, input_voltage = 48, load_resistance = -1), even without the binding "
        "parameters (fmi2SetReal failed (error) at t = 0 s: fmi2SetReal: load_resistance = -1 Ohm is invalid: "
        "expected a finite value > 0)")


def test_a_refused_parameter_event_stops_the_batch_before_its_first_run(tmp_path):
    (tmp_path / "zero_c.toml").write_text('name = "zero_c"\nduration = 0.03\n[initial]\nreference = 12.0\n'
                                          '[[events]]\ntime = 0.01\nparameters = { capacitance = 0.0 }\n')
    one_line_error(cli("run", "startup", str(tmp_path / "zero_c.toml"), "--kp", "0", "--ki", "14",
                       "--out", str(tmp_path / "out")), 2,
                   "zero_c.toml:7: events[0].parameters (capacitance): the plant FMU refuses the value: "
                   "fmi2SetReal: capacitance = 0 F is invalid")
    assert not (tmp_path / "out" / "runs").exists()  # not even the start-up, which comes first, was run


def test_a_pi_tuning_that_no_gains_can_run_is_refused_not_returned(tmp_path, faulty_fmu):
    from cosim.base.errors import PlantError
    from cosim.design.pi_tuning import tune_pi
    from cosim.fmi.binding_file import load_binding

    (tmp_path / "faulty.toml").write_text(faulty_binding(faulty_fmu, 3))  # NaN outputs at 10.3 ms, whatever the duty
    with pytest.raises(PlantError, match=r"faulty.toml: the PI cannot be tuned on this plant: no gains of the search "
                                         r"ran it through the tuning scenarios \(the first failure: plant output "
                                         r"became non-finite at t = 0.0103"):
        tune_pi(load_binding(tmp_path / "faulty.toml"), 1e-3, quick=True)


def test_a_huge_settle_is_refused_naming_the_file_and_the_key(tmp_path):
    (tmp_path / "huge.toml").write_text('name = "huge"\nduration = 0.03\nsettle = 1e6\n[initial]\nreference = 12.0\n')
    one_line_error(cli("run", str(tmp_path / "huge.toml"), "--kp", "0", "--ki", "14", "--out", str(tmp_path)), 2,
                   "huge.toml:3: scenario huge's settle 1e+06 s and duration 0.03 s at control period 0.001 s and "
                   "record period 1e-05 s make 1e+09 instants; the limit is 2e+08 (shorten settle")


def test_the_fmus_own_exception_text_is_in_the_message(tmp_path, faulty_fmu):
    binding = tmp_path / "faulty.toml"
    binding.write_text(faulty_binding(faulty_fmu, 2))
    one_line_error(cli("run", "startup", "--plant", str(binding), "--kp", "0", "--ki", "14", "--no-figures",
                       "--record-period", "1e-4", "--out", str(tmp_path / "out")), 3,
                   "fmi2DoStep failed (fatal) at t = 0.0103 s: Fatal py exception encountered: [doStep] "
                   "PyObject_CallMethod RuntimeError('simulated solver breakdown')")


def test_an_interrupted_data_collection_says_that_nothing_was_written(tmp_path):
    from cosim.design.controller_factory import tuned_pi
    from cosim.design.plants import plant_binding

    tuned_pi(plant_binding("nominal", "averaged"), 1e-3, tmp_path)  # cached: the command goes straight to collecting
    process = subprocess.Popen([sys.executable, "-m", "cosim.cli", "collect-data", "--samples", "300000",
                                "--work-dir", str(tmp_path), "--out", str(tmp_path / "d.parquet")],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL)
    code, err = interrupt_on(process, "step/s")  # the collection's progress bar: well into the collection
    assert code == 130
    lines = message_lines(err)
    assert len(lines) == 1 and "data collection interrupted at t = " in lines[0] and "no data file written" in \
        lines[0] and "rows kept" not in lines[0], err
    assert not (tmp_path / "d.parquet").exists()


# ------------------------------------------------------------------ 9. a crashing FMU


def test_a_crashing_fmu_ends_the_run_not_the_workbench(tmp_path, faulty_fmu):
    """A plant FMU that dereferences NULL: isolated (the default for binding files) the run ends with
    exit 3 and one line naming the FMU and the time, the rows before the crash are written and
    marked incomplete, and the extracted FMU is deleted. In-process (--no-isolate) it takes the
    whole process with it -- the reason isolation is the default for external FMUs."""
    binding = tmp_path / "crash.toml"
    binding.write_text(faulty_binding(faulty_fmu, 4))
    private_tmp = tmp_path / "tmp"  # the run's own temporary folder: another test's plants extract theirs elsewhere
    private_tmp.mkdir()
    one_line_error(cli("run", "startup", "--plant", str(binding), "--kp", "0", "--ki", "14", "--record-period", "1e-4",
                       "--out", str(tmp_path / "out"), env={**os.environ, "TMPDIR": str(private_tmp)}), 3,
                   f"binding file {binding}: the FMU crashed the plant process (signal SIGSEGV) while stepping at "
                   "t = 0.0104 s")
    run = read_run(tmp_path / "out" / "runs" / "startup__pi__bound-crash__1ms.parquet")
    assert run.complete is False and "SIGSEGV" in run.error
    assert 0.0099 < run.frame["time"].max() < 0.0104 and len(run.frame) > 90
    assert not list(private_tmp.glob("buck-cosim-fmu-*"))  # the extracted FMU is deleted
    crashed = cli("run", "startup", "--plant", str(binding), "--no-isolate", "--kp", "0", "--ki", "14",
                  "--record-period", "1e-4", "--out", str(tmp_path / "in-process"))
    assert crashed.returncode == -signal.SIGSEGV  # no message, no rows: what isolation prevents


def test_a_hanging_fmu_is_stopped_at_its_step_time_limit(tmp_path, faulty_fmu):
    """A hang is a fault like a crash: the isolated plant's doStep that never returns is stopped after the
    binding's step_timeout, the run ends with exit 3 and one line naming the FMU, the time and the limit,
    and the rows before it are written, marked incomplete. Before the watchdog the command waited forever."""
    binding = tmp_path / "hang.toml"
    binding.write_text("step_timeout = 2.0\n" + faulty_binding(faulty_fmu, 5))
    started = time.monotonic()
    one_line_error(cli("run", "startup", "--plant", str(binding), "--kp", "0", "--ki", "14", "--record-period", "1e-4",
                       "--out", str(tmp_path / "out"), timeout=120), 3,
                   f"binding file {binding}: the FMU {faulty_fmu.name} did not finish stepping from t = 0.0103 s to "
                   "0.0104 s within the step time limit of 2 s (step_timeout); its process was stopped")
    assert time.monotonic() - started < 60  # the limit, the interpreter's start and the rows before the hang
    run = read_run(tmp_path / "out" / "runs" / "startup__pi__bound-hang__1ms.parquet")
    assert run.complete is False and "step time limit of 2 s" in run.error
    assert 0.0099 < run.frame["time"].max() < 0.0104


def test_the_step_time_limit_on_the_command_line_overrides_the_binding(tmp_path, faulty_fmu):
    """--step-timeout sets the limit for one command (the binding file sets none here); it needs an isolated
    plant, so with --no-isolate it is refused before anything runs."""
    binding = tmp_path / "hang.toml"
    binding.write_text(faulty_binding(faulty_fmu, 5))
    one_line_error(cli("run", "startup", "--plant", str(binding), "--step-timeout", "1.5", "--kp", "0", "--ki", "14",
                       "--record-period", "1e-4", "--out", str(tmp_path / "out"), timeout=120), 3,
                   "did not finish stepping from t = 0.0103 s to 0.0104 s within the step time limit of 1.5 s")
    one_line_error(cli("run", "startup", "--plant", str(binding), "--no-isolate", "--step-timeout", "2",
                       "--out", str(tmp_path / "refused")), 2, "--step-timeout needs an isolated plant")
    one_line_error(cli("run", "startup", "--plant", str(binding), "--step-timeout", "0",
                       "--out", str(tmp_path / "refused")), 2, "expected a finite number >= 0.001 s")


def test_the_default_step_time_limit_grows_with_the_simulated_step(faulty_fmu, tmp_path):
    """Without step_timeout the limit is 30 s plus 1000 x the step's simulated length: a 1 ms step may take
    31 s, a 1 s step 1030 s (an FMU 1000 x slower than real time still runs; a stalled one does not)."""
    from cosim.fmi.binding_file import load_binding
    from cosim.fmi.isolation import step_time_limit

    (tmp_path / "plant.toml").write_text(faulty_binding(faulty_fmu, 0))
    default = load_binding(tmp_path / "plant.toml")
    assert default.step_timeout is None
    assert step_time_limit(default, 1e-3) == pytest.approx(31.0) and step_time_limit(default, 1.0) == 1030.0
    (tmp_path / "set.toml").write_text("step_timeout = 5\n" + faulty_binding(faulty_fmu, 0))
    assert step_time_limit(load_binding(tmp_path / "set.toml"), 1.0) == 5.0


@pytest.mark.parametrize("text,message", [
    ("step_timeout = -1\n", "step_timeout = -1 s is invalid: expected > 0"),
    ("step_timeout = \"long\"\n", "step_timeout = 'long' is invalid: expected a finite number"),
    ("isolate = false\nstep_timeout = 5\n", "step_timeout needs isolate = true"),
    ("memory_limit = 0\n", "memory_limit = 0 MB is invalid: expected > 0"),
    ("isolate = false\nmemory_limit = 500\n", "memory_limit needs isolate = true"),
])
def test_isolation_limits_in_a_binding_file_are_checked(tmp_path, faulty_fmu, text, message):
    binding = tmp_path / "limits.toml"
    binding.write_text(text + faulty_binding(faulty_fmu, 0))
    one_line_error(cli("run", "startup", "--plant", str(binding), "--out", str(tmp_path / "out")), 2, message)


def test_an_fmu_that_allocates_without_bound_is_stopped_at_its_memory_limit(tmp_path, faulty_fmu):
    """Isolated, the plant process's resident memory is watched: above the binding's memory_limit it is
    stopped and the run ends like a crash (exit 3, one line with the FMU, the memory, the limit and the time)."""
    binding = tmp_path / "hoard.toml"
    binding.write_text("memory_limit = 600\n" + faulty_binding(faulty_fmu, 6))
    line = one_line_error(cli("run", "startup", "--plant", str(binding), "--kp", "0", "--ki", "14",
                              "--record-period", "1e-4", "--out", str(tmp_path / "out"), timeout=300), 3,
                          f"binding file {binding}: the FMU {faulty_fmu.name}'s process used ")
    assert "above the memory limit of 600 MB (memory_limit), while stepping at t = " in line
    assert "its process was stopped" in line
    run = read_run(tmp_path / "out" / "runs" / "startup__pi__bound-hoard__1ms.parquet")
    assert run.complete is False and "memory limit of 600 MB" in run.error


def test_isolation_gives_the_same_run_as_in_process(tmp_path, faulty_fmu):
    from controllers.pi import PIController
    from cosim.fmi.binding_file import load_binding
    from cosim.master import simulate
    from cosim.scenarios import load_scenario

    binding = tmp_path / "plant.toml"
    binding.write_text(faulty_binding(faulty_fmu, 0))
    plant = load_binding(binding)
    assert plant.isolate is True  # binding files default to isolation
    startup = load_scenario("startup", PAPER_SPEC)
    runs = [simulate(replace_isolate(plant, isolate), PIController(0.0, 14.0, 1e-3), startup,
                     record_period=1e-4) for isolate in (True, False)]
    pd.testing.assert_frame_equal(runs[0].frame.drop(columns="controller_compute_time"),
                                  runs[1].frame.drop(columns="controller_compute_time"))
    assert runs[0].metadata["plant"]["isolated"] is True and runs[1].metadata["plant"]["isolated"] is False


def replace_isolate(binding, isolate: bool):
    from dataclasses import replace

    return replace(binding, isolate=isolate)
