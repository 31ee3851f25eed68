"""Reliability: bad inputs end in one line, faults keep what was recorded, interrupts leave nothing
half-written, the same command gives the same bytes, and long or repeated runs stay in bounded memory."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import replace

import pyarrow.parquet as pq
import pytest
from conftest import (
    cli,
    faulty_binding,
    interrupt_on,
    message_lines,
    no_temporary_files,
    one_line_error,
    role_named_binding,
)

from cosim.results import read_run
from cosim.study.vocabulary import PAPER_SPEC


def ends_in_one_line_error(done, code: int, message: str) -> None:
    """Progress lines may come first; the failure itself is one ``error:`` line, and the last."""
    assert done.returncode == code, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert [line for line in lines if line.startswith("error: ")] == lines[-1:], done.stderr
    assert message in lines[-1] and "Traceback" not in done.stderr, done.stderr


# ------------------------------------------------------------------------------------------ bad inputs


@pytest.mark.parametrize("parameters,message", [
    ("inductance = -1e-6", "inductance = -1e-06 H is invalid: expected a finite value > 0"),
    ("capacitance = 0.0", "capacitance = 0 F is invalid: expected a finite value > 0"),
    ("switching_frequency = 0.0", "switching_frequency = 0 Hz is invalid"),
    ("plant_mode = 7", "plant_mode = 7 is invalid: expected 0 (averaged) or 1 (switched)"),
])
def test_non_physical_plant_parameters_are_refused(tmp_path, buck_fmu, parameters, message):
    binding = tmp_path / "plant.toml"
    binding.write_text(role_named_binding(buck_fmu, parameters=parameters))
    one_line_error(cli("run", "startup", "--plant", str(binding), "--kp", "0", "--ki", "14", "--out", str(tmp_path)),
                   2, message)


@pytest.mark.parametrize("text,message", [
    ('name = "x"\nduration = 0.02\n[initial]\nreference = 12.0\nload_resistance = 0.0\n',
     "bad.toml:5: initial.load_resistance = 0.0 Ohm is invalid: expected > 0"),
    ('name = "x"\nduration = 0.02\n[initial]\nreference = 12.0\n[[events]]\ntime = 0.05\nreference = 9.0\n',
     "bad.toml:6: events[0].time = 0.05 s is at or after the end of the scenario"),
    ('name = "x"\nduration = -0.02\n[initial]\nreference = 12.0\n', "bad.toml:2: duration = -0.02 s is invalid"),
    ('name = "x"\nduration = 0.02\nstart = 0\n[initial]\nreference = 12.0\n', "bad.toml:3: unknown key 'start'"),
])
def test_scenario_mistakes_via_the_command_line(tmp_path, text, message):
    (tmp_path / "bad.toml").write_text(text)
    one_line_error(cli("run", "bad.toml", "--kp", "0", "--ki", "14", "--out", str(tmp_path / "out"), cwd=tmp_path),
                   2, message)


def test_runs_whose_files_would_overwrite_each_other_are_refused_before_any_run(tmp_path):
    """A run's files are named after its scenario and its controller: a scenario of another file with the same name,
    a scenario or a controller given twice would overwrite runs (the table showed both, the folder one), so the
    batch refuses them, naming both places."""
    from controllers.pi import PIController
    from cosim.base.errors import ConfigError
    from cosim.batch import Batch, run_batch
    from cosim.design.plants import plant_binding
    from cosim.scenarios import load_scenario

    shipped = load_scenario("startup", PAPER_SPEC)
    (tmp_path / "mine.toml").write_text(shipped.source.read_text().replace("load_resistance = 6.0",
                                                                           "load_resistance = 10.0"))
    binding = plant_binding("nominal", "averaged")
    with pytest.raises(ConfigError, match=r"^\S*mine.toml:\d+: scenario name 'startup' is the name of "
                                          r"\S*startup.toml:\d+ too: the runs' files are named after it"):
        Batch(binding, [shipped, load_scenario(str(tmp_path / "mine.toml"), PAPER_SPEC)])
    with pytest.raises(ConfigError, match=r"^scenario \S*startup.toml is given twice$"):
        Batch(binding, [shipped, load_scenario("startup", PAPER_SPEC)])
    pi = [PIController(0.01, 14.0, 1e-3), PIController(0.02, 14.0, 1e-3)]
    with pytest.raises(ConfigError, match=r"^controller PI is given twice$"):
        run_batch(Batch(binding, [shipped]), pi, tmp_path / "out")
    assert not (tmp_path / "out" / "runs").exists()
    one_line_error(cli("run", "startup", str(tmp_path / "mine.toml"), "--kp", "0.01", "--ki", "14", "--out",
                       str(tmp_path / "cli")), 2, "scenario name 'startup' is the name of")


@pytest.mark.parametrize("args,message", [
    (["run", "bad.toml", "--kp", "0", "--ki", "14", "--out", "out"], "bad.toml:2: duration = -0.02 s is invalid"),
    (["train", "data.parquet", "--activation", "swish", "--out", "m.pt"], "activation 'swish' is unknown"),
    (["train", "missing.parquet", "--out", "m.pt"], "missing.parquet"),
    (["collect-data", "--plant", "missing.toml", "--out", "d.parquet"], "missing.toml"),
    (["reproduce", "--plant", "missing.toml", "--out", "r"], "missing.toml"),
])
def test_a_refused_command_is_answered_before_torch_or_matplotlib_load(tmp_path, args, message):
    """The checks of ``run``, ``train``, ``collect-data`` and ``reproduce --plant`` (scenario, plant, rates, network,
    files) come before the controllers', the network's and the figures' libraries are imported: a typo is answered in
    about a second, not after the 2-5 s torch and matplotlib take to load (controllers/nn_config.py holds what train
    checks)."""
    (tmp_path / "bad.toml").write_text('name = "x"\nduration = -0.02\n[initial]\nreference = 12.0\n')
    probe = ("import sys; from cosim.cli import main; "
             f"code = main(['--no-progress', *{args!r}]); "
             "print(code, sorted(m for m in ('torch', 'matplotlib', 'scipy.optimize') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert message in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert done.stdout.split("\n")[0] == "2 []", done.stdout


def test_a_pi_run_loads_no_torch(tmp_path):
    """A PI-only run needs no network: torch (seconds to load) stays out of it (and matplotlib, without figures)."""
    probe = ("import sys; from cosim.cli import main; "
             "code = main(['--no-progress', 'run', 'startup', '--kp', '0.01', '--ki', '14', '--out', 'out', "
             "'--no-figures']); "
             "print(code, sorted(m for m in ('torch', 'matplotlib') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert done.stdout.strip().splitlines()[-1] == "0 []", done.stdout + done.stderr
    assert (tmp_path / "out" / "runs" / "startup__pi__nominal-averaged__1ms.parquet").is_file()


def test_a_period_the_fmu_cannot_honour_is_refused(tmp_path, fixed_step_fmu):
    """The built-in FMU declared fixed-step: its DefaultExperiment stepSize (1 ms) is its one communication step; a
    record period off that grid is refused before any run, and without one the runs record every 1 ms."""
    binding = tmp_path / "plant.toml"
    binding.write_text(role_named_binding(fixed_step_fmu, parameters=""))
    one_line_error(cli("run", "startup", "--plant", str(binding), "--kp", "0", "--ki", "14", "--record-period",
                       "3e-4", "--out", str(tmp_path / "a")), 2,
                   "the FMU steps by one fixed communication step of 0.001 s (the FMU's DefaultExperiment stepSize), "
                   "but the record period 0.0003 s is not a whole number of steps: use multiples of 0.001 s")
    done = cli("run", "startup", "--plant", str(binding), "--kp", "0", "--ki", "14", "--out", str(tmp_path / "b"),
               "--no-figures")
    assert done.returncode == 0, done.stderr
    [run] = (tmp_path / "b" / "runs").glob("*.json")
    assert json.loads(run.read_text())["rates"]["record_period_s"] == 1e-3


def test_a_model_file_for_other_inputs_is_refused(tmp_path):
    import numpy as np
    import pandas as pd

    from controllers.nn_config import NNConfig, TrainingSettings
    from controllers.nn_model import save_model, train

    n = 300
    frame = pd.DataFrame({"measured_inductor_current": np.linspace(0, 2, n), "measured_output_voltage":
                          np.linspace(0, 12, n), "duty_cycle": np.full(n, 0.25)})
    model = train(frame, NNConfig(), TrainingSettings(max_iterations=20), metadata={"control_period_s": 1e-3})
    save_model(model, tmp_path / "paper.pt")
    one_line_error(cli("run", "startup", "--controller", "nnpc", "--model", str(tmp_path / "paper.pt"),
                       "--control-period", "1/75e3", "--out", str(tmp_path)), 2,
                   "was trained at a control period of 1000 us; the controller samples every 13.33 us")


# ------------------------------------------------------------------------------------------ faults in a run


@pytest.mark.parametrize("kind,message", [
    (1, "fmi2DoStep failed (discard) at t = 0.0103"),
    (2, "fmi2DoStep failed (fatal) at t = 0.0103"),
    (3, "plant output became non-finite at t = 0.0104 s (output_voltage = nan)"),
])
def test_a_failing_plant_stops_the_run_and_keeps_the_rows(tmp_path, faulty_fmu, kind, message):
    binding = tmp_path / "faulty.toml"
    binding.write_text(faulty_binding(faulty_fmu, kind))
    done = cli("run", "startup", "--plant", str(binding), "--kp", "0", "--ki", "14", "--record-period", "1e-4",
               "--out", str(tmp_path / "out"))
    one_line_error(done, 3, message)
    stem = tmp_path / "out" / "runs" / "startup__pi__bound-faulty__1ms"
    meta = json.loads(stem.with_suffix(".json").read_text())
    assert meta["complete"] is False and message.split(" at ")[0] in meta["error"]
    run = read_run(stem.with_suffix(".parquet"))
    assert run.metadata["complete"] is False
    assert 0.0095 < run.frame["time"].max() < 0.0104  # the rows up to the fault
    no_temporary_files(tmp_path / "out")


FATAL_REUSE = """
import gc, sys
from controllers.pi import PIController
from cosim.fmi.binding_file import load_binding
from cosim.base.errors import PlantError
from cosim.fmi.plant import open_plant
from cosim.master import RunFailed, run
from cosim.scenarios import parse_scenario

plant = open_plant(load_binding(sys.argv[1]))
scenario = parse_scenario('name = "s"\\nduration = 0.02\\n[initial]\\nreference = 12.0\\nload_resistance = 6.0\\n'
                          'input_voltage = 48.0\\n')
try:
    run(plant, PIController(0.0, 14.0, 1e-3), scenario)
except RunFailed as error:
    print("run:", error)
try:
    plant.reset()
except PlantError as error:
    print("reset:", error)
plant.close()
gc.collect()
print("closed")
"""


def test_an_fmu_that_reported_fatal_is_never_called_again(tmp_path, faulty_fmu):
    """FMI 2.0 forbids any call after fmi2Fatal; calling fmi2FreeInstance anyway corrupts pythonfmu's heap."""
    binding = tmp_path / "faulty.toml"
    binding.write_text(faulty_binding(faulty_fmu, 2))
    done = subprocess.run([sys.executable, "-c", FATAL_REUSE, str(binding)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert "fmi2DoStep failed (fatal) at t = 0.0103" in lines[0]
    assert lines[1].endswith("the FMU reported fmi2Fatal earlier and cannot be used again "
                             "(FMI 2.0 forbids any further call)")
    assert lines[2] == "closed"
    # PI tuning scores failing gains as bad, but a fatal plant ends the tuning at once
    tuned = cli("run", "startup", "--plant", str(binding), "--out", str(tmp_path / "out"), "--no-figures")
    ends_in_one_line_error(tuned, 3, "fmi2DoStep failed (fatal) at t = 0.0103 s")


def test_a_controller_fault_in_a_batch_writes_the_partial_run(tmp_path):
    import math

    from cosim.batch import Batch, run_batch
    from cosim.fmi.binding import builtin_binding
    from cosim.master import RunFailed
    from cosim.scenarios import load_scenario

    class Broken:
        name, sample_period, duty_limits = "broken", 1e-3, (0.0, 1.0)

        def reset(self):
            self.k = 0

        def step(self, m):
            self.k += 1
            return 0.25 if self.k < 5 else math.inf

        def describe(self):
            return {"type": "broken", "name": self.name, "duty_limits": [0.0, 1.0]}

    with pytest.raises(RunFailed, match=r"controller broken returned duty cycle inf at t = 0.004 s"):
        run_batch(Batch(replace(builtin_binding("averaged"), tag_override="x"), [load_scenario("startup", PAPER_SPEC)]),
                  [Broken()], tmp_path)
    meta = json.loads((tmp_path / "runs" / "startup__broken__x__1ms.json").read_text())
    assert meta["complete"] is False and meta["rows"] > 300
    no_temporary_files(tmp_path)


# ------------------------------------------------------------------------------------------ interrupts


def _start(*args, cwd=None):
    """The command with its progress bars on stderr (the events the interrupts below wait for)."""
    return subprocess.Popen([sys.executable, "-m", "cosim.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, cwd=cwd, stdin=subprocess.DEVNULL)


def test_sigterm_during_a_run_keeps_the_rows_marked_incomplete(tmp_path):
    scenario = tmp_path / "long.toml"
    scenario.write_text('name = "long"\nduration = 500.0\n[initial]\nreference = 12.0\n')
    process = _start("run", str(scenario), "--kp", "0", "--ki", "14", "--out", str(tmp_path / "out"))
    code, err = interrupt_on(process, "step/s")  # the run's progress bar: it has been stepping for a second
    assert code == 130 and "Traceback" not in err
    [line] = message_lines(err)
    assert line.startswith("error: run long / PI interrupted at t = "), err
    run = read_run(tmp_path / "out" / "runs" / "long__pi__nominal-averaged__1ms.parquet")
    assert run.metadata["complete"] is False and run.metadata["error"].startswith("interrupted at t = ")
    assert len(run.frame) > 1000
    no_temporary_files(tmp_path)


def test_sigterm_during_data_collection_writes_no_data_file(tmp_path):
    from cosim.design.controller_factory import tuned_pi
    from cosim.design.plants import plant_binding

    tuned_pi(plant_binding("nominal", "averaged"), 1e-3, tmp_path)  # cached, so the run goes straight to collecting
    process = _start("collect-data", "--samples", "20000000", "--work-dir", str(tmp_path), "--out",
                     str(tmp_path / "data.parquet"))
    code, err = interrupt_on(process, "step/s")  # the collection's run is under way
    assert code == 130 and "interrupted" in err and "Traceback" not in err
    assert not (tmp_path / "data.parquet").exists()
    no_temporary_files(tmp_path)


def test_sigterm_during_training_writes_no_model_file(tmp_path):
    import numpy as np
    import pandas as pd

    from cosim.results import write_parquet

    rng = np.random.default_rng(0)
    n = 40_000
    frame = pd.DataFrame({"measured_inductor_current": rng.uniform(0, 3, n),
                          "measured_output_voltage": rng.uniform(0, 20, n), "duty_cycle": rng.uniform(0, 1, n)})
    write_parquet(frame, {"control_period_s": 1e-3}, tmp_path / "data.parquet")
    process = _start("train", str(tmp_path / "data.parquet"), "--hidden", "64", "64", "--out",
                     str(tmp_path / "model.pt"))
    code, err = interrupt_on(process, "it/s")  # the training's progress bar: iterations under way
    assert code == 130 and "interrupted" in err and "Traceback" not in err
    assert not (tmp_path / "model.pt").exists()
    no_temporary_files(tmp_path)


def test_a_failing_pipeline_stops_a_parallel_reproduction(tmp_path, faulty_fmu):
    binding = tmp_path / "faulty.toml"
    binding.write_text(faulty_binding(faulty_fmu, 2))
    done = cli("reproduce", "--quick", "--plant", str(binding), "--control-period", "1e-3", "--control-period",
               "2e-3", "--workers", "2", "--out", str(tmp_path / "out"), timeout=300)
    ends_in_one_line_error(done, 3, "fmi2DoStep failed (fatal)")
    no_temporary_files(tmp_path / "out")


def test_a_worker_that_dies_ends_a_parallel_reproduction_with_an_error(tmp_path, faulty_fmu):
    """A plant FMU that crashes its process (a segfault, with isolation off): dask runs the
    task again on a fresh worker, and when that one dies too the reproduction ends in one line
    (exit 3) instead of hanging on a result that never comes."""
    binding = tmp_path / "faulty.toml"
    binding.write_text("isolate = false\n" + faulty_binding(faulty_fmu, 4))  # the crash takes the worker
    started = time.monotonic()
    done = cli("reproduce", "--quick", "--plant", str(binding), "--control-period", "1e-3", "--control-period",
               "2e-3", "--workers", "2", "--out", str(tmp_path / "out"), timeout=300)
    ends_in_one_line_error(done, 3, "a reproduction worker process died twice running the PI tuning of bound-faulty__")
    assert "rerun with --resume to continue" in done.stderr
    assert time.monotonic() - started < 120  # not a hang waiting for a result that never comes
    no_temporary_files(tmp_path / "out")


@pytest.mark.parametrize("args,message", [
    (["run", "startup", "--kp", "0", "--ki", "14", "--out", "afile"], "output folder afile is an existing file"),
    (["tune-pi", "--out", "."], "output file . is a folder"),
    (["train", "small.parquet", "--control-period", "1e-3", "--out", "m.pt"],
     "small.parquet: 50 samples are too few to train on"),
    # a file named for another format than the one written: refused, saying what is written
    (["collect-data", "--out", "d.csv"],
     "--out d.csv is invalid: expected a file name ending in .parquet (the samples are written as Parquet, with their "
     "metadata)"),
    (["tune-pi", "--out", "gains.txt"], "--out gains.txt is invalid: expected a file name ending in .json"),
    (["train", "small.parquet", "--out", "m.onnx"],
     "--out m.onnx is invalid: expected a file name ending in .pt or .pth (the model is written as a torch archive)"),
    (["distill", "--model", "none.pt", "--out", "policy.bin"],
     "--out policy.bin is invalid: expected a file name ending in .pt or .pth"),
])
def test_output_and_size_mistakes_are_caught_before_the_work(tmp_path, args, message):
    import numpy as np
    import pandas as pd

    from cosim.results import write_parquet

    (tmp_path / "afile").write_text("x")
    write_parquet(pd.DataFrame({"measured_inductor_current": np.zeros(50), "measured_output_voltage": np.zeros(50),
                                "duty_cycle": np.zeros(50)}), {}, tmp_path / "small.parquet")
    one_line_error(cli(*args, cwd=tmp_path), 2, message)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "small.parquet"]  # nothing written


def test_an_output_file_may_end_in_any_of_its_formats_endings_in_either_case(tmp_path):
    from cosim.base.errors import ConfigError
    from cosim.cli.options import output_file

    for name in ("m.pt", "m.pth", "m.PTH"):
        assert output_file(str(tmp_path / name), (".pt", ".pth")) == tmp_path / name
    assert output_file(str(tmp_path / "anything.bin")) == tmp_path / "anything.bin"  # no endings given: any name
    with pytest.raises(ConfigError, match=r"^--out \S+m\.pt\.bak is invalid: expected a file name ending in \.pt or "
                                          r"\.pth$"):
        output_file(str(tmp_path / "m.pt.bak"), (".pt", ".pth"))
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------------------------------ determinism


def test_the_same_command_twice_gives_byte_identical_tables(tmp_path):
    for folder in ("a", "b"):  # the same commands, run in two folders
        cwd = tmp_path / folder
        cwd.mkdir()
        for args in (("run", "reference_up", "load_change", "--mode", "switched", "--controller", "mpc-oracle",
                      "--out", "out", "--no-figures"),
                     ("collect-data", "--samples", "1500", "--seed", "3", "--work-dir", "out", "--out", "data.parquet"),
                     ("train", "data.parquet", "--seed", "3", "--out", "model.pt")):
            done = cli(*args, cwd=cwd)
            assert done.returncode == 0, done.stderr
    names = [p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*")
             if p.is_file() and ".timing." not in p.name and p.suffix in (".csv", ".parquet", ".json", ".pt")
             and "metrics" not in p.parts]  # metrics hold compute-time percentiles (wall clock)
    assert len(names) >= 9
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name


# ------------------------------------------------------------------------------------------ long runs

MEMORY_SCRIPT = """
import os, sys
from controllers.pi import PIController
from cosim.fmi.binding import builtin_binding
from cosim.fmi.plant import open_plant
from cosim.master import run
from cosim.scenarios import parse_scenario

def rss_mb():
    return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20

scenario = parse_scenario('name = "short"\\nduration = 0.003\\n[initial]\\nreference = 12.0\\n'
                          'load_resistance = 6.0\\ninput_voltage = 48.0\\n'
                          '[[events]]\\ntime = 0.001\\nload_resistance = 5.0\\n')
binding, pi = builtin_binding("switched"), PIController(0.0, 14.0, 1e-3)
growth = {}
with open_plant(binding) as plant:  # reuse and reset: the known cure for reload crashes
    for i in range(1000):
        if i == 50:
            base = rss_mb()
        run(plant, pi, scenario, record_period=1e-4)
    growth["reuse"] = rss_mb() - base
for i in range(1000):  # a fresh instance every time
    if i == 50:
        base = rss_mb()
    with open_plant(binding) as plant:
        run(plant, pi, scenario, record_period=1e-4)
growth["reinstantiate"] = rss_mb() - base
print(growth["reuse"], growth["reinstantiate"])
"""


def test_a_thousand_runs_in_one_process_keep_memory_bounded():
    done = subprocess.run([sys.executable, "-c", MEMORY_SCRIPT], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    reuse, reinstantiate = map(float, done.stdout.split())
    assert reuse <= 50 and reinstantiate <= 50


def _peak_rss_mb(*args, cwd) -> tuple[float, str]:
    process = subprocess.Popen([sys.executable, "-m", "cosim.cli", "--no-progress", *args], cwd=cwd,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, _, usage = os.wait4(process.pid, 0)
    out = process.stdout.read()
    return usage.ru_maxrss / 1024, out


def test_a_ten_second_switched_soak_streams_in_bounded_memory(tmp_path):
    body = '[initial]\nreference = 12.0\n[[events]]\ntime = {t}\nload_resistance = 5.0\n'
    (tmp_path / "soak.toml").write_text('name = "soak"\nduration = 10.0\n' + body.format(t=4.0))
    (tmp_path / "short.toml").write_text('name = "short"\nduration = 0.2\n' + body.format(t=0.08))
    args = ["--mode", "switched", "--kp", "0", "--ki", "14", "--stream", "--record-period", "1e-5"]
    short, _ = _peak_rss_mb("run", "short.toml", *args, "--out", "short", cwd=tmp_path)
    soak, out = _peak_rss_mb("run", "soak.toml", *args, "--out", "soak", cwd=tmp_path)
    assert "streamed 1000001 rows" in out
    assert soak - short < 100  # a million rows more, yet memory barely moves
    path = tmp_path / "soak" / "runs" / "soak__pi__nominal-switched__1ms.parquet"
    assert pq.read_metadata(path).num_rows == 1_000_001
    assert json.loads(path.with_suffix(".json").read_text())["complete"] is True
