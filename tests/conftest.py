"""Shared fixtures: the built plant FMU and a minimal raw-fmpy co-simulation driver for plant tests;
the faulty plant's binding file, binding files for FMUs with the role names, and the command-line helpers of the
tests of failures."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

# isort: off
import cosim  # noqa: F401  (first: pins the numeric kernels before numpy and torch load, cosim/base/numeric_env.py)
# isort: on
import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")

from cosim.study.vocabulary import PAPER_SPEC
from plant_fmu.table_ii import TABLE_II  # noqa: E402

# Params of the paper's Table II
VS, L, C, R, FSW = (TABLE_II.input_voltage, TABLE_II.inductance, TABLE_II.capacitance, TABLE_II.load_resistance,
                    TABLE_II.switching_frequency)


@pytest.fixture(scope="session")
def buck_fmu() -> Path:
    from plant_fmu import fmu_path

    return fmu_path()


#: every callbacks struct (and its Python logger) handed to fmpy's logger proxy, kept for the whole test session
#: (see raw_callbacks; an FMU also keeps the struct's address until it is freed)
_PROXIED_LOGGERS: list = []


def raw_callbacks(log: list):
    """FMI 2.0 callbacks for an FMU driven through fmpy alone, its messages appended to ``log``.

    fmpy's logger proxy (``fmpy.logging.addLoggerProxy``, which formats the FMU's variadic messages)
    keeps *one* Python logger for the whole process, the last one registered -- also for every FMU
    instantiated later with fmpy's default callbacks. A logger freed with its test would then be
    called by the next FMU that logs (a segfault in an unrelated test), so every logger registered
    here lives as long as the session. (The workbench itself registers one logger that never dies:
    cosim/fmi/fmu_log.py.)"""
    from ctypes import byref

    import fmpy
    from fmpy.fmi2 import (
        fmi2CallbackAllocateMemoryTYPE,
        fmi2CallbackFreeMemoryTYPE,
        fmi2CallbackFunctions,
        fmi2CallbackLoggerTYPE,
    )
    from fmpy.logging import addLoggerProxy

    def on_log(environment, name, status, category, message):
        log.append((status, message.decode()))

    callbacks = fmi2CallbackFunctions()
    callbacks.logger = fmi2CallbackLoggerTYPE(on_log)
    callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(fmpy.calloc)
    callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(fmpy.free)
    _PROXIED_LOGGERS.append((on_log, callbacks))
    addLoggerProxy(byref(callbacks))
    return callbacks


class RawSlave:
    """The FMU driven directly through fmpy's FMU2Slave (no workbench code), for plant tests."""

    def __init__(self, fmu: Path, start_values: dict | None = None, instance_name: str = "raw",
                 log: list | None = None, start_time: float = 0.0):
        import fmpy
        from fmpy.fmi2 import FMU2Slave

        self.md = fmpy.read_model_description(str(fmu))
        self.vr = {v.name: v.valueReference for v in self.md.modelVariables}
        self.types = {v.name: v.type for v in self.md.modelVariables}
        self.unzipdir = fmpy.extract(str(fmu))
        self.log = log if log is not None else []
        callbacks = raw_callbacks(self.log)
        self._keep = callbacks
        self.fmu = FMU2Slave(guid=self.md.guid, unzipDirectory=self.unzipdir,
                             modelIdentifier=self.md.coSimulation.modelIdentifier, instanceName=instance_name)
        self.fmu.instantiate(callbacks=callbacks)
        self.fmu.setupExperiment(startTime=start_time)
        self.set(start_values or {})
        self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()
        self.time = start_time

    def set(self, values: dict) -> None:
        for name, value in values.items():
            if self.types[name] == "Integer":
                self.fmu.setInteger([self.vr[name]], [int(value)])
            else:
                self.fmu.setReal([self.vr[name]], [float(value)])

    def get(self, *names: str) -> np.ndarray:
        return np.array(self.fmu.getReal([self.vr[n] for n in names]))

    def step_to(self, t: float) -> None:
        self.fmu.doStep(self.time, t - self.time)
        self.time = t

    def close(self) -> None:
        self.fmu.terminate()
        self.fmu.freeInstance()
        shutil.rmtree(self.unzipdir, ignore_errors=True)


def simulate_raw(fmu: Path, t_end: float, step: float, start_values: dict | None = None,
                 input_changes: dict[float, dict] | None = None,
                 outputs=("inductor_current", "output_voltage")) -> tuple[np.ndarray, np.ndarray]:
    """Step ``t_end`` in communication steps of ``step``; apply ``input_changes[t]`` at grid time t.

    Times are n * step (not accumulated), as a careful importer computes them.
    """
    slave = RawSlave(fmu, start_values)
    n = int(round(t_end / step))
    times = np.arange(n + 1) * step
    changes = {int(round(t / step)): v for t, v in (input_changes or {}).items()}
    values = np.empty((n + 1, len(outputs)))
    try:
        for k, t in enumerate(times):
            if k:
                slave.step_to(t)
            if k in changes:
                slave.set(changes[k])
            values[k] = slave.get(*outputs)
    finally:
        slave.close()
    return times, values


@pytest.fixture
def raw_slave_factory(buck_fmu):
    made = []

    def make(start_values=None, **kwargs):
        slave = RawSlave(buck_fmu, start_values, **kwargs)
        made.append(slave)
        return slave

    yield make
    for slave in made:
        try:
            slave.close()
        except Exception:
            pass


# ------------------------------------------------------------------ the Cortex-M4F tests (marker: embedded)


#: the lines saying which tests were deselected and why (pytest_terminal_summary prints them)
_DESELECTED = pytest.StashKey[list]()


def _deselect(config, items, marker: str, problem: str | None, what: str) -> None:
    """Deselect the tests marked ``marker`` when ``problem`` says why they cannot run here (one line, kept
    for the summary)."""
    marked = [item for item in items if item.get_closest_marker(marker)]
    if not marked or problem is None:
        return
    items[:] = [item for item in items if not item.get_closest_marker(marker)]
    config.hook.pytest_deselected(items=marked)
    config.stash.setdefault(_DESELECTED, []).append(f"{len(marked)} {what} deselected: {problem}")


def _tool_checks() -> list[tuple[str, str, Callable[[], str | None]]]:
    """(marker, what, the check saying why such tests cannot run here or None) of each kind of test that needs
    a tool; a check runs only where its tests are (the toolchain's runs the cross compiler)."""
    from cosim.benchmark_harness import cpu_emulation, instruction_count
    from cosim.benchmark_harness.cortex_m4 import toolchain_problem

    return [("embedded", "embedded tests", toolchain_problem),
            ("emulated", "emulated-CPU tests", cpu_emulation.problem),
            ("counted", "instruction-count tests", instruction_count.problem)]


def pytest_collection_modifyitems(config, items):
    """Without the cross toolchain and QEMU (``make`` installs them when run as root), deselect the tests
    marked ``embedded``; without QEMU's user-mode x86-64 emulator, those marked ``emulated``; without valgrind,
    those marked ``counted``."""
    for marker, what, check in _tool_checks():
        if any(item.get_closest_marker(marker) for item in items):
            _deselect(config, items, marker, check(), what)


def pytest_terminal_summary(terminalreporter, config):
    """One line per kind of test deselected for a missing tool, saying which tool. Under pytest-xdist (``make
    test``) the workers collect and their output goes nowhere, so its controller says it from the tools alone."""
    if config.pluginmanager.hasplugin("dsession"):  # pytest-xdist's controller
        lines = [f"{what} deselected: {problem}" for _, what, check in _tool_checks() if (problem := check())]
    else:
        lines = config.stash.get(_DESELECTED, [])
    for line in lines:
        terminalreporter.write_line(line)


CORPUS = Path(__file__).parent / "corpus"


@pytest.fixture(scope="session")
def python_buck_fmu(tmp_path_factory) -> Path:
    """An outside-authored plant: built here with pythonfmu (co-simulation only, its own names/units; its physics,
    tests/corpus/buck_math.py, bundled with it)."""
    from pythonfmu.builder import FmuBuilder

    out = tmp_path_factory.mktemp("pythonfmu")
    return Path(FmuBuilder.build_FMU(CORPUS / "python_buck.py", dest=out, project_files=[CORPUS / "buck_math.py"]))


@pytest.fixture(scope="session")
def python_buck3_fmu(tmp_path_factory) -> Path:
    """The FMI 3.0 twin of the pythonfmu plant, with its own names (tests/corpus/python_buck3.py)."""
    from pythonfmu3.builder import FmuBuilder

    out = tmp_path_factory.mktemp("pythonfmu3")
    return Path(FmuBuilder.build_FMU(CORPUS / "python_buck3.py", dest=out, project_files=[CORPUS / "buck_math.py"],
                                     canHandleVariableCommunicationStepSize=True))


@pytest.fixture(scope="session")
def me_only_fmu(tmp_path_factory) -> Path:
    """The built-in sources packaged with only the model-exchange interface, under another identifier."""
    import re

    from plant_fmu.build import compile_fmu, stage_sources

    out = tmp_path_factory.mktemp("me_only")
    unzipdir = out / "BuckME"
    stage_sources(unzipdir)
    xml_path = unzipdir / "modelDescription.xml"
    xml = xml_path.read_text()
    xml = re.sub(r"\s*<CoSimulation.*?</CoSimulation>", "", xml, flags=re.S)
    xml = xml.replace('modelIdentifier="BuckConverter"', 'modelIdentifier="BuckConverterME"')
    xml_path.write_text(xml)
    return compile_fmu(unzipdir, out / "BuckConverterME.fmu")


@pytest.fixture(scope="session")
def faulty_fmu(tmp_path_factory) -> Path:
    """A pythonfmu plant that fails on purpose at fault_time (discard, error or NaN by fault_kind)."""
    from pythonfmu.builder import FmuBuilder

    out = tmp_path_factory.mktemp("faulty")
    return Path(FmuBuilder.build_FMU(CORPUS / "faulty_buck.py", dest=out))


#: the ``[converter]`` table of the test corpus's plants (the paper's 48 V -> 12 V at 6 Ohm), appended to their
#: binding files' texts (at the end: the line numbers the tests name stay where they are)
PLANT_CONVERTER = ("[converter]\noutput_voltage = 12.0\ninput_voltage = 48.0\nload_resistance = 6.0\n"
                   "output_voltage_range = [3.0, 20.0]\ninput_voltage_range = [36.0, 60.0]\n"
                   "load_resistance_range = [4.0, 100.0]\n")

#: the nominal circuit the faulty plant's converter table gives the model-based designs (its own model has none)
FAULTY_CIRCUIT = "[converter.circuit]\ninductance = 220e-6\ncapacitance = 10e-6\n"

FAULTY_BINDING = """\
fmu = "{fmu}"
[roles.duty_cycle]
variable = "duty"
[roles.output_voltage]
variable = "Vout"
[roles.inductor_current]
variable = "IL"
[parameters]
{fault_kind}fault_time = 0.0103
{converter}"""


def faulty_binding(fmu: Path, kind: int | None = None) -> str:
    """The text of a plant-binding file for :func:`faulty_fmu` (its names bound to the workbench's roles)
    that fails at t = 0.0103 s, just after a 1 ms control sample, in the way ``kind`` selects
    (tests/corpus/faulty_buck.py: 0 none, 1 discard, 2 error, 3 NaN, 4 SIGSEGV, 5 hang, 6 memory without
    bound); without ``kind`` it leaves fault_kind to the FMU's default or to a sweep. fault_kind is on line 9,
    fault_time on the last line."""
    return FAULTY_BINDING.format(fmu=fmu, fault_kind="" if kind is None else f"fault_kind = {kind}\n",
                                 converter=PLANT_CONVERTER + FAULTY_CIRCUIT)


#: the roles the workbench's own plant FMU names its variables after (a binding file binds each to itself)
PLANT_ROLES = ("duty_cycle", "output_voltage", "inductor_current", "load_resistance", "input_voltage")
#: the same for a controller FMU the workbench exported (``buck-cosim export-controller``)
CONTROLLER_ROLES = ("reference", "measured_output_voltage", "duty_cycle")


def role_named_binding(fmu, roles: tuple[str, ...] = PLANT_ROLES, parameters: str | None = None,
                       converter: bool = True, **keys) -> str:
    """The text of a binding file for an FMU whose variables carry the workbench's role names (its own plant FMU,
    an exported controller FMU): line 1 ``fmu``, then a line per ``keys`` item in order (strings quoted, booleans
    as TOML's, numbers as Python writes them), two lines per role (``[roles.R]``, ``variable = "R"``), then, where
    ``parameters`` is given, ``[parameters]`` and that text. With k keys and r roles ``[parameters]`` is on line
    2 + k + 2 r and its first key on the next. A plant binding (``output_voltage`` among the roles) ends with the
    test corpus's ``[converter]`` table (:data:`PLANT_CONVERTER`) unless ``converter`` is false (a text more
    ``[parameters]`` lines are appended to)."""
    def value(item):
        if isinstance(item, (str, Path)):
            return f'"{item}"'
        return str(item).lower() if isinstance(item, bool) else repr(item)

    text = f'fmu = "{fmu}"\n' + "".join(f"{key} = {value(item)}\n" for key, item in keys.items())
    text += "".join(f'[roles.{role}]\nvariable = "{role}"\n' for role in roles)
    text = text if parameters is None else f"{text}[parameters]\n{parameters}"
    if converter and "output_voltage" in roles:  # a plant binding: the converter of its scenarios
        text = f"{text.rstrip()}\n{PLANT_CONVERTER}"
    return text


# ------------------------------------------------------------------ the command line, as a user runs it


def cli(*args, cwd=None, timeout=600, env=None) -> subprocess.CompletedProcess:
    """Run ``buck-cosim --no-progress ARGS`` in a subprocess (no stdin), its output captured as text; ``env``:
    its environment (default: this process's)."""
    return subprocess.run([sys.executable, "-m", "cosim.cli", "--no-progress", *args], capture_output=True,
                          text=True, cwd=cwd, stdin=subprocess.DEVNULL, timeout=timeout, env=env)


def one_line_error(done: subprocess.CompletedProcess, code: int, message: str) -> str:
    """The command exited with ``code`` and wrote one line to stderr, ``error: ...`` holding ``message``
    and no traceback; that line."""
    assert done.returncode == code, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in done.stderr, done.stderr
    assert message in lines[0], lines[0]
    return lines[0]


def script(name: str):
    """The module of ``scripts/<name>.py`` (the project's scripts are not a package), imported once."""
    import importlib

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.pop(0)


def script_refusal(name: str, argv: list[str], capsys) -> tuple[int, str]:
    """Run ``scripts/<name>.py ARGV`` in this process, expecting argparse's refusal: its exit code and the last
    line it wrote to stderr."""
    with pytest.raises(SystemExit) as stopped:
        script(name).main(argv)
    return stopped.value.code, capsys.readouterr().err.strip().splitlines()[-1]


def interrupt_on(process: subprocess.Popen, marker: str, timeout: float = 300.0, times: int = 2) -> tuple[int, str]:
    """Send SIGTERM to ``process`` once ``marker`` has shown ``times`` times on its stderr -- the event the test is
    about, e.g. ``step/s``: the progress bar of a run that has been stepping for a second -- not after a fixed time,
    which a busy machine outruns; then wait for it to end. Returns (exit code, everything it wrote to stderr). Too few
    markers within ``timeout`` seconds (or an end before them) fail the test, naming what it wrote.

    Twice by default: tqdm notes that it has drawn a bar only after drawing it, so an interrupt right after the first
    drawing finds a bar it believes was never shown and leaves it on the line, before the one-line error."""
    import threading

    chunks: list[str] = []
    seen = threading.Event()

    def pump() -> None:  # stderr as it comes: tqdm ends its updates with "\r", not a newline
        while data := os.read(process.stderr.fileno(), 4096):
            chunks.append(data.decode("utf-8", "replace"))
            if "".join(chunks).count(marker) >= times:
                seen.set()
        seen.set()

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    seen.wait(timeout)
    if process.poll() is not None or "".join(chunks).count(marker) < times:
        process.kill()
        process.wait(timeout=60)
        raise AssertionError(f"no {marker!r} on stderr within {timeout:g} s (exit {process.returncode}): "
                             f"{''.join(chunks)[-2000:]}")
    process.send_signal(signal.SIGTERM)
    process.wait(timeout=120)
    reader.join(timeout=30)
    return process.returncode, "".join(chunks)


def message_lines(stderr: str) -> list[str]:
    """The non-blank lines of ``stderr`` that are not progress bars (tqdm's, which hold ``/s``, or its clearing)."""
    return [line for line in stderr.replace("\r", "\n").splitlines()
            if line.strip() and not re.search(r"(step|it|eval|run)/s\]|\|\s*\d+/\d+", line)]


def no_temporary_files(folder: Path) -> None:
    """No half-written file (the workbench's ``.NAME.tmp-*``) is left anywhere below ``folder``."""
    assert not list(Path(folder).rglob(".*.tmp-*")), list(Path(folder).rglob(".*.tmp-*"))


@pytest.fixture(scope="session")
def fixed_step_fmu(tmp_path_factory, buck_fmu) -> Path:
    """The built-in FMU declaring canHandleVariableCommunicationStepSize="false"."""
    import zipfile

    out = tmp_path_factory.mktemp("fixed_step") / "FixedStep.fmu"
    with zipfile.ZipFile(buck_fmu) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as target:
        for info in source.infolist():
            data = source.read(info.filename)
            if info.filename == "modelDescription.xml":
                data = data.replace(b'canHandleVariableCommunicationStepSize="true"',
                                    b'canHandleVariableCommunicationStepSize="false"')
            target.writestr(info, data)
    return out


@pytest.fixture(scope="session")
def nnpc_1ms():
    """The workbench's 1 ms NNPC on a network identified quickly (800 samples, 100 iterations)."""
    from controllers.nn_config import TrainingSettings
    from controllers.nn_model import train
    from controllers.pi import PIController
    from cosim.design.data_collection import collect
    from cosim.design.experiments import collection_settings, nn_configs, nnpc
    from cosim.design.plants import plant_binding

    data = collect(plant_binding("nominal", "averaged"), PIController(0.0017, 15.6, 1e-3),
                   collection_settings(1e-3, samples=800, seed=3, spec=PAPER_SPEC))
    model = train(data, nn_configs(1e-3)["nnpc"], TrainingSettings(seed=3, max_iterations=100),
                  metadata={"control_period_s": 1e-3})
    return nnpc(model, 1e-3)


def random_model(config, seed: int):
    """An untrained network of ``config`` (torch's initialisation from ``seed``) with random input and output
    scalings: a model whose numbers no training shaped, for checking twins and exports against each other."""
    import torch

    from controllers.nn_model import NNPlantModel, PlantNetwork

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    n = config.n_inputs
    return NNPlantModel(config, PlantNetwork(config), rng.normal(0, 3, n), rng.uniform(0.5, 5, n),
                        rng.normal(0, 5, 2), rng.uniform(0.5, 5, 2))
