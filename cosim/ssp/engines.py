"""Running an SSP of the loop with three engines; each result is a workbench run table.

* ``workbench`` -- the workbench's own master (:func:`cosim.master.simulate`) on what the archive
  holds: the plant FMU with the roles its connections give (the unconnected, recorded outputs
  from the workbench annotation) and its ``.ssv`` parameters, the controller FMU through the
  controller adapter (:class:`cosim.fmi.controller.FmuController`), the scenario file the
  scenario FMU was generated from (checked against that FMU's GUID). The master is
  Gauss-Seidel at a control sample: the plant is stepped to t_k, the controller reads y(t_k) and
  its duty acts from t_k. Recording period: the communication step.

* ``fmpy`` -- fmpy's SSP simulation (:mod:`fmpy.ssp`). Its documented algorithm
  (``fmpy.ssp.simulation.simulate_ssp``) is fixed-step **Jacobi**: at each communication point
  every component sets its inputs from the connector values, steps, and reads its outputs; only
  then are the connections applied. :func:`fmpy.ssp.simulation.simulate_ssp` itself cannot run
  this loop, and records wrongly; three defects (see ``DEVIATIONS``) -- every connector starts at
  0.0 (the plant refuses ``load_resistance = 0``), each row is stamped with the start of the step
  whose end values it holds, and the SSD's parameter bindings and linear transformations are
  never applied. This engine is therefore fmpy's reader (``read_ssd``, ``get_connections``),
  fmpy's per-component step (``fmpy.ssp.simulation.do_step``) and parameter setter
  (``set_parameters``) in ``simulate_ssp``'s loop with exactly those three things corrected.

* ``libcosim`` -- libcosim through libcosimpy (``CosimExecution.from_ssp_file``), its fixed-step
  algorithm (``fixed_step_algorithm``: all simulators step in parallel from t to t + h, then the
  outputs are transferred to the connected inputs -- **Jacobi** -- after an initialisation that
  iterates the transfers N times to propagate initial values), observed with a time-series
  observer. libcosimpy 0.0.6's ``time_series_real_samples`` drops the last sample when the
  first one is step 0 (it counts step numbers equal to 0 as unfilled); the samples are read with
  the C function it wraps, trimmed by the count that function returns.

Expected difference (both Jacobi engines): a communication point t exchanges the outputs each FMU
had *before* any input at t was set. The scenario's outputs and the plant's voltages and currents
depend on their state only, so they arrive undelayed (not the plant's load current vo/R, which
depends on its load input directly: at a load step the controller's sample sees the old one, at
any h); the controller's duty depends directly on its inputs, so the duty read at a sample t_k is computed from the inputs of t_k - h. The plant therefore runs
[t_k, t_k + h) on that stale duty and gets the workbench's duty d_k from t_k + h on: one
communication step h of delay on the measurement-to-duty path, which shrinks with h (the
controller's own state is committed with the inputs of t_k, as in the workbench). The switched
plant latches the duty once per PWM period, so there the stale duty holds for the whole first
PWM period at any h below one PWM period.

Columns the engines cannot provide: ``controller_compute_time`` (NaN: neither engine times the
controller alone). Everything else is read at each communication point from the FMUs' outputs
(``duty_cycle``: the controller output the plant takes from that point on).
"""

from __future__ import annotations

import importlib
import math
import platform
import shutil
import tempfile
import zipfile
from ctypes import c_double, c_int, c_int64, c_size_t, c_uint32
from pathlib import Path, PurePosixPath
from xml.etree import ElementTree

import fmpy
import numpy as np

from cosim.base.digests import file_sha256
from cosim.base.errors import ConfigError, WorkbenchError
from cosim.base.labels import period_label, slug
from cosim.fmi.binding import CONTROLLER_INPUT_ROLES, PlantBinding, RoleMap
from cosim.fmi.controller import ControllerBinding, FmuController
from cosim.master import simulate
from cosim.recorder import COLUMNS, DESCRIPTIONS, SCHEMA, UNITS
from cosim.results import RUN_FORMAT, RunInfo, RunResult, json_ready, package_versions
from cosim.ssp.package import (
    COMPONENTS,
    CONTROLLER,
    PLANT,
    SCENARIO,
    Loop,
    SspError,
    check_step,
    plant_mode_name,
    read_ssp,
)
from cosim.ssp.scenario_source import scenario_sources

ENGINES = ("workbench", "fmpy", "libcosim")
TIME_TOLERANCE = 1e-9  # relative to the step: a communication point on the control grid
ALGORITHMS = {
    "workbench": "the workbench master: multi-rate, Gauss-Seidel at control samples (plant stepped to t_k, "
                 "controller reads y(t_k), its duty acts from t_k)",
    "fmpy": "fmpy.ssp: fixed-step Jacobi (every FMU sets its inputs, steps and reads its outputs; then the "
            "connections are applied)",
    "libcosim": "libcosim fixed_step_algorithm: fixed-step Jacobi (all simulators step in parallel, then outputs are "
                "transferred to inputs), initial values propagated by N transfer iterations",
}
#: where the fmpy engine departs from fmpy.ssp.simulation.simulate_ssp, and why
DEVIATIONS = (
    "connectors start at the values the FMUs hold after initialisation, propagated through the connections, "
    "instead of 0.0 (simulate_ssp sets every input to 0.0 at the first step: the plant refuses "
    "load_resistance = 0)",
    "each row is stamped with the communication point its values belong to (simulate_ssp stamps the values "
    "read at t + h with t) and the initial point is recorded",
    "the components' parameter bindings (.ssv) and the connections' linear transformations are applied "
    "(simulate_ssp applies neither)",
    "communication points are start + k h (simulate_ssp accumulates t += h)",
)


#: the engines that cannot run FMI 3.0 components, and why (found by running an FMI 3.0 loop with each)
FMI2_ONLY_ENGINES = {
    "fmpy": "fmpy 0.3.32's SSP simulation instantiates every component with FMU2Slave and looks for an FMI 2.0 "
            "binary",
    "libcosim": "libcosimpy 0.0.6's libcosim refuses FMI 3.0 FMUs: 'Unsupported FMI version'",
}


class EngineError(WorkbenchError):
    """An engine failed while running an SSP (one line, exit code 3)."""

    exit_code = 3


def engine_module(engine: str):
    """Import what an engine needs, or refuse in one line if it is not installed here."""
    if engine not in ENGINES:
        raise ConfigError(f"engine {engine!r} is unknown: expected one of {', '.join(ENGINES)}")
    needs = {"workbench": (), "fmpy": ("fmpy.ssp.ssd", "fmpy.ssp.simulation"),
             "libcosim": ("libcosimpy.CosimExecution",)}[engine]
    package = {"fmpy": "fmpy", "libcosim": "libcosimpy==0.0.6"}.get(engine)
    modules = []
    for name in needs:
        try:
            modules.append(importlib.import_module(name))
        except (ImportError, OSError) as error:
            raise ConfigError(f"engine {engine}: {name.split('.')[0]} is not installed or does not load here "
                              f"({type(error).__name__}: {' '.join(str(error).split())}); install it with "
                              f"pip install '{package}'") from None
    return modules


# ---------------------------------------------------------------------------------------------
# The archive as the workbench sees it


def _roles_from_connections(loop: Loop) -> dict[str, RoleMap]:
    """The plant roles: the connected ones from the SSD's connections (their linear
    transformations as the roles' scale and offset), the others from the workbench annotation.
    Refuses a connection the workbench's master cannot reproduce."""
    roles = dict(loop.plant_roles)
    for c in loop.connections:
        pair = (c.start_element, c.end_element)
        if pair == (CONTROLLER, PLANT) and c.start_connector == "duty_cycle":
            roles["duty_cycle"] = RoleMap(c.end_connector, c.factor, c.offset)
        elif pair == (SCENARIO, PLANT) and c.start_connector in ("load_resistance", "input_voltage"):
            roles[c.start_connector] = RoleMap(c.end_connector, c.factor, c.offset)
        elif pair == (PLANT, CONTROLLER) and c.end_connector.startswith("measured_"):
            if c.factor == 0.0:
                raise SspError(f"{loop.archive}: connection {c.label} has factor 0")
            roles[c.end_connector] = RoleMap(c.start_connector, 1.0 / c.factor, -c.offset / c.factor)
        elif pair == (SCENARIO, CONTROLLER) and c.start_connector == c.end_connector and \
                c.start_connector in ("reference", "input_voltage") and (c.factor, c.offset) == (1.0, 0.0):
            pass  # the master hands the controller the scenario's reference and supply itself
        else:
            raise SspError(f"{loop.archive}: the workbench's master cannot run connection {c.label}: it connects "
                           "scenario -> controller (reference, input_voltage) and plant, plant sensors -> controller "
                           "and controller duty_cycle -> plant")
    return roles


def _extract(loop: Loop, folder: Path) -> dict[str, Path]:
    """The three FMUs of the archive, extracted (as files) into ``folder``."""
    paths = {}
    with zipfile.ZipFile(loop.archive) as archive:
        for name, component in loop.components.items():
            target = folder / f"{name}-{PurePosixPath(component.source).name}"
            target.write_bytes(archive.read(component.source))
            paths[name] = target
    return paths


def _check_scenario_fmu(loop: Loop, scenario_path: Path) -> None:
    """The archive's scenario FMU must be the one its scenario file generates (same GUID: the
    GUID is a hash of the generated data), or the workbench would run another scenario."""
    guid = fmpy.read_model_description(str(scenario_path), validate=False).guid
    md = scenario_sources(loop.scenario, loop.control_period).model_description
    expected = ElementTree.fromstring(md).get("guid")
    if guid != expected:
        raise SspError(f"{loop.archive}: the scenario FMU (GUID {guid}) was not generated from the archive's "
                       "scenario file at its control period: the archive was edited")


def _ssp_member(loop: Loop, name: str) -> str:
    return f"{Path(loop.archive).name}!{loop.components[name].source}"


def _engine_metadata(loop: Loop, engine: str, step: float) -> dict:
    versions = {"fmpy": package_versions().get("fmpy")}
    if engine == "libcosim":
        try:
            from importlib import metadata

            versions["libcosimpy"] = metadata.version("libcosimpy")
        except Exception:
            versions["libcosimpy"] = "unknown"
    meta = {"engine": {"name": engine, "algorithm": ALGORITHMS[engine], "communication_step_s": step,
                       "versions": versions,
                       "not_provided": {"controller_compute_time": "NaN: the engine does not time the controller"}
                       if engine != "workbench" else {}},
            "ssp": {"file": Path(loop.archive).name, "sha256": file_sha256(loop.archive), "name": loop.name}}
    if engine == "fmpy":
        meta["engine"]["deviations_from_simulate_ssp"] = list(DEVIATIONS)
    return meta


def prepare(path: str | Path, engine: str, step: float | None = None) -> tuple[Loop, float]:
    """Read and check the archive and the engine before anything runs; return the loop and the
    communication step [s] to use (``step``, else the archive's)."""
    engine_module(engine)
    loop = read_ssp(path)
    step = loop.step if step is None else float(step)
    binding = PlantBinding(fmu_path=Path(loop.components[PLANT].source), roles=loop.plant_roles,
                           label=loop.plant_label)
    check_step(step, loop.control_period, loop.scenario, loop.settle, binding)
    newer = [name for name in COMPONENTS if not loop.components[name].fmi_version.startswith(("1.", "2."))]
    if engine in FMI2_ONLY_ENGINES and newer:
        raise SspError(f"{path}: engine {engine} runs FMI 1.0 and 2.0 components only ({FMI2_ONLY_ENGINES[engine]}); "
                       f"{'components' if len(newer) > 1 else 'component'} {', '.join(repr(n) for n in newer)} "
                       f"{'are' if len(newer) > 1 else 'is'} FMI {loop.components[newer[0]].fmi_version}: run this "
                       "archive with --engine workbench")
    if engine == "libcosim":
        nanoseconds = step * 1e9
        if abs(nanoseconds - round(nanoseconds)) > 1e-6 * max(1.0, nanoseconds):
            raise SspError(f"engine libcosim counts time in whole nanoseconds: communication step {step:.9g} s is "
                           f"{nanoseconds:.6g} ns (choose a step that is a whole number of nanoseconds)")
    if engine == "workbench":
        _roles_from_connections(loop)
    return loop, step


def run_stem(loop: Loop, engine: str) -> str:
    """``<scenario>__<controller>__<plant tag>__<period label>__<engine>``."""
    controller = loop.components[CONTROLLER].source
    return (f"{loop.scenario.name}__{slug(PurePosixPath(controller).stem)}__{loop.plant_tag}__"
            f"{period_label(loop.control_period)}__ssp-{engine}")


def run_ssp(path: str | Path, engine: str, step: float | None = None) -> RunResult:
    """Run the SSP archive ``path`` with ``engine`` (workbench, fmpy or libcosim) at communication
    step ``step`` [s] (default: the archive's); return a workbench run table (time [s] from the
    scenario's t = 0, the columns of :data:`cosim.recorder.SCHEMA`) with metadata naming the engine."""
    loop, step = prepare(path, engine, step)
    runner = {"workbench": _run_workbench, "fmpy": _run_fmpy, "libcosim": _run_libcosim}[engine]
    return runner(loop, step)


# ---------------------------------------------------------------------------------------------
# workbench


def _run_workbench(loop: Loop, step: float) -> RunResult:
    with tempfile.TemporaryDirectory(prefix="buck-cosim-ssp-") as tmp:
        paths = _extract(loop, Path(tmp))
        _check_scenario_fmu(loop, paths[SCENARIO])
        plant = loop.components[PLANT]
        binding = PlantBinding(fmu_path=paths[PLANT], roles=_roles_from_connections(loop),
                               interface="co-simulation", parameters=plant.parameters, label=loop.plant_label,
                               tag_override=loop.plant_tag)
        controller_component = loop.components[CONTROLLER]
        names = {c.name for c in controller_component.connectors}
        controller_binding = ControllerBinding(paths[CONTROLLER], {r: RoleMap(r) for r in (*CONTROLLER_INPUT_ROLES,
                                                                                          "duty_cycle", "sample_period")
                                                                  if r in names},
                                               parameters=controller_component.parameters)
        controller = FmuController(controller_binding)
        try:
            result = simulate(binding, controller, loop.scenario, record_period=step,
                              extra_metadata=_engine_metadata(loop, "workbench", step))
        finally:
            controller.close()
    # name the FMUs by their place in the archive, not the temporary folder they ran from
    result.details["plant"]["fmu"] = _ssp_member(loop, PLANT)
    result.details["controller"]["fmu"] = _ssp_member(loop, CONTROLLER)
    return result


# ---------------------------------------------------------------------------------------------
# The Jacobi engines' tables


def _details(loop: Loop, engine: str, step: float, guids: dict[str, str], names: dict[str, str]) -> dict:
    controller = loop.components[CONTROLLER]
    params = controller.parameters
    plant = loop.components[PLANT]
    meta = {
        "format": RUN_FORMAT,
        "scenario": loop.scenario.describe(),
        "controller": {"type": "controller FMU", "name": names[CONTROLLER], "fmu": _ssp_member(loop, CONTROLLER),
                       "guid": guids[CONTROLLER], "sample_period_s": loop.control_period,
                       "duty_limits": [params.get("duty_min", 0.0), params.get("duty_max", 1.0)],
                       "parameters": dict(params)},
        "plant": {"label": loop.plant_label, "fmu": _ssp_member(loop, PLANT), "binding_file": loop.plant_binding_file,
                  "interface": "co-simulation", "parameters": dict(plant.parameters),
                  "roles": {r: {"variable": m.variable, "scale": m.scale, "offset": m.offset}
                            for r, m in loop.plant_roles.items()},
                  "model_name": names[PLANT], "guid": guids[PLANT],
                  "fmu_file": PurePosixPath(plant.source).name},
        "rates": {"control_period_s": loop.control_period, "record_period_s": step},
        "seed": None,
        "versions": package_versions(),
        "platform": {"machine": platform.machine(), "system": platform.system()},
        "units": dict(UNITS),
        "descriptions": dict(DESCRIPTIONS),
        **_engine_metadata(loop, engine, step),
    }
    if plant_mode_name(loop) is None:  # RunInfo reads the built-in FMU's mode from plant_mode
        meta["plant"]["parameters"].pop("plant_mode", None)
    return json_ready(meta)


def _table(loop: Loop, step: float, times: np.ndarray, value_of) -> np.ndarray:
    """The run table from an engine's samples: ``value_of(element, connector)`` gives that
    connector's value at every communication point ``times`` [s, plant time]."""
    keep = times >= loop.settle - TIME_TOLERANCE * step
    times = times[keep]
    roles = loop.plant_roles

    def plant_role(*candidates):
        for role in candidates:
            if role in roles:
                m = roles[role]
                return (value_of(PLANT, m.variable)[keep] - m.offset) / m.scale
        return np.full(len(times), math.nan)

    k = times / loop.control_period
    control = np.abs(k - np.round(k)) <= TIME_TOLERANCE * loop.control_period / step * np.maximum(1.0, k) + 1e-9
    columns = {
        "time": _scenario_time(times, loop.settle, step),
        "reference": value_of(SCENARIO, "reference")[keep],
        "output_voltage": plant_role("output_voltage"),
        "inductor_current": plant_role("inductor_current"),
        "measured_output_voltage": plant_role("measured_output_voltage", "output_voltage"),
        "measured_inductor_current": plant_role("measured_inductor_current", "inductor_current"),
        "load_current": plant_role("load_current"),
        "measured_load_current": plant_role("measured_load_current", "load_current"),
        "duty_cycle": value_of(CONTROLLER, "duty_cycle")[keep],
        "load_resistance": value_of(SCENARIO, "load_resistance")[keep],
        "input_voltage": value_of(SCENARIO, "input_voltage")[keep],
        "control_sample": control.astype(float),
        "controller_compute_time": np.full(len(times), math.nan),
    }
    assert tuple(columns) == COLUMNS == tuple(c.name for c in SCHEMA)
    return np.column_stack([columns[c] for c in COLUMNS])


def _scenario_time(times: np.ndarray, settle: float, step: float) -> np.ndarray:
    """Scenario time [s] of communication points: j * step for the j-th point after ``settle``
    (exactly the grid, free of the rounding of plant time minus settle)."""
    j = np.round((times - settle) / step)
    exact = np.abs((times - settle) / step - j) <= 1e-6
    return np.where(exact, j * step, times - settle)


def _result(loop: Loop, engine: str, step: float, table: np.ndarray, guids, names) -> RunResult:
    details = _details(loop, engine, step, guids, names)
    return RunResult.from_table(table, RunInfo.from_metadata(details), details, True)


def _steps(loop: Loop, step: float) -> int:
    n = (loop.stop_time - loop.start_time) / step
    return int(round(n)) if abs(n - round(n)) <= 1e-6 * max(1.0, n) else int(math.ceil(n))


# ---------------------------------------------------------------------------------------------
# fmpy


def _run_fmpy(loop: Loop, step: float) -> RunResult:
    from fmpy.fmi1 import FMICallException
    from fmpy.fmi2 import FMU2Slave
    from fmpy.ssp.simulation import add_path, do_step, get_value, set_parameters, set_value
    from fmpy.ssp.ssd import Parameter, ParameterSet, find_components, find_connectors, get_connections, read_ssd

    from cosim.fmi.fmu_log import callbacks_for, release

    ssd = read_ssd(str(loop.archive))  # fmpy's reader (it validates against the SSP 1.0 schema too)
    add_path(ssd.system)
    components = find_components(ssd.system)
    connectors = find_connectors(ssd.system)
    connections = get_connections(ssd.system)
    transformations = {(c.end_element, c.end_connector): (c.factor, c.offset) for c in loop.connections}
    parameter_set = ParameterSet(parameters=[
        Parameter(name=f"{component.name}.{p.name}", type=p.type, value=p.value)
        for component in components for binding in component.parameterBindings
        for values in binding.parameterValues for p in values.parameters])
    unzipdir = Path(fmpy.extract(str(loop.archive)))
    log: list[tuple[str, str]] = []
    handles, started = [], []
    guids, names = {}, {}
    failing = "the engine"

    def last_error() -> str:
        for owner, message in reversed(log):
            return f": {owner}: {' '.join(message.split())}"
        return ""

    try:
        for component in components:  # fmpy.ssp.simulation.instantiate_fmu, with a logger per instance
            failing = component.name
            md = fmpy.read_model_description(str(unzipdir / component.source), validate=False)
            guids[component.name], names[component.name] = md.guid, md.modelName
            component.unzipdir = fmpy.extract(str(unzipdir / component.source))
            component.variables = {v.name: v for v in md.modelVariables}
            component.fmu = FMU2Slave(guid=md.guid, unzipDirectory=component.unzipdir,
                                      modelIdentifier=md.coSimulation.modelIdentifier, instanceName=component.name)
            callbacks, handle = callbacks_for(
                lambda status, category, message, owner=component.name:
                log.append((owner, message)) if status in ("warning", "error", "fatal", "discard") else None)
            handles.append(handle)
            component.fmu.instantiate(callbacks=callbacks)
            started.append(component)
            component.fmu.setupExperiment(startTime=loop.start_time)
            set_parameters(component, parameter_set)
            component.fmu.enterInitializationMode()
            component.fmu.exitInitializationMode()
        def apply_connections():
            for start, end in connections:
                factor, offset = transformations.get((end.parent.name, end.name), (1.0, 0.0))
                end.value = factor * start.value + offset

        # initial values: what the FMUs hold after initialisation, propagated through the connections
        failing = "initialisation"
        for connector in connectors:
            if connector.kind in ("input", "output"):
                connector.value = get_value(connector.parent, connector.name)
        for _ in range(len(components)):
            apply_connections()
            for connector in connectors:
                if connector.kind == "input":
                    set_value(connector.parent, connector.name, connector.value)
            for connector in connectors:
                if connector.kind == "output":
                    connector.value = get_value(connector.parent, connector.name)
        apply_connections()
        recorded = [c for c in connectors if c.kind == "output"]
        n = _steps(loop, step)
        values = np.empty((n + 1, len(recorded)))
        values[0] = [c.value for c in recorded]
        for k in range(n):
            t = loop.start_time + k * step
            for component in components:
                failing = f"{component.name} at t = {t:.9g} s"
                do_step(component, t, step)  # fmpy: set inputs, fmi2DoStep, get outputs
            apply_connections()
            values[k + 1] = [c.value for c in recorded]
        times = loop.start_time + np.arange(n + 1) * step
    except FMICallException as error:
        raise EngineError(f"engine fmpy: {failing}: {error}{last_error()}") from None
    finally:
        for component in started:
            try:
                component.fmu.terminate()
            except Exception:
                pass
            try:
                component.fmu.freeInstance()
            except Exception:
                pass
            shutil.rmtree(getattr(component, "unzipdir", ""), ignore_errors=True)
        for handle in handles:
            release(handle)
        shutil.rmtree(unzipdir, ignore_errors=True)
    column = {c.path: i for i, c in enumerate(recorded)}

    def value_of(element, connector):
        return values[:, column[f"{element}.{connector}"]]

    return _result(loop, "fmpy", step, _table(loop, step, times, value_of), guids, names)


# ---------------------------------------------------------------------------------------------
# libcosim


def _time_series(observer, slave: int, reference: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    """All of a real variable's samples from a time-series observer: (times [ns], values), read
    with libcosimc's own function and trimmed by the count it returns (libcosimpy 0.0.6's
    ``time_series_real_samples`` drops the last sample when the first is step 0)."""
    from ctypes import POINTER

    from libcosimpy._internal import libcosimc, wrap_function
    from libcosimpy.CosimObserver import CosimObserver

    get = wrap_function(lib=libcosimc(), funcname="cosim_observer_slave_get_real_samples", restype=c_int64,
                        argtypes=[POINTER(CosimObserver), c_int, c_uint32, c_int64, c_size_t, c_double * count,
                                  c_int64 * count, c_int64 * count])
    samples, steps, times = (c_double * count)(), (c_int64 * count)(), (c_int64 * count)()
    got = get(observer.ptr(), slave, reference, 0, count, samples, steps, times)
    if got < 0:
        raise EngineError(f"engine libcosim: reading the samples of variable {reference} of slave {slave} failed")
    return np.frombuffer(times, dtype=np.int64, count=got).copy(), np.frombuffer(samples, count=got).copy()


def _run_libcosim(loop: Loop, step: float) -> RunResult:
    from libcosimpy._internal import get_last_error_message
    from libcosimpy.CosimEnums import CosimVariableType
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    from libcosimpy.CosimObserver import CosimObserver

    log_output_level(CosimLogLevel.FATAL)  # its log goes to the console; errors are read back instead
    step_ns = int(round(step * 1e9))
    n = _steps(loop, step)
    try:
        execution = CosimExecution.from_ssp_file(str(loop.archive), step_size=step_ns)
    except AssertionError:
        raise EngineError(f"engine libcosim: cannot load {loop.archive} ({get_last_error_message()})") from None
    guids, names, references, slaves = {}, {}, {}, {}
    with zipfile.ZipFile(loop.archive) as archive:
        for name, component in loop.components.items():
            with tempfile.TemporaryDirectory(prefix="buck-cosim-md-") as tmp:
                target = Path(tmp) / "m.fmu"
                target.write_bytes(archive.read(component.source))
                md = fmpy.read_model_description(str(target), validate=False)
            guids[name], names[name] = md.guid, md.modelName
            references[name] = {v.name: v.valueReference for v in md.modelVariables}
            slaves[name] = execution.slave_index_from_instance_name(name)
    observer = CosimObserver.create_time_series(buffer_size=n + 16)
    execution.add_observer(observer)
    wanted = [(SCENARIO, s) for s in ("reference", "load_resistance", "input_voltage")] + [(CONTROLLER, "duty_cycle")]
    wanted += sorted({(PLANT, m.variable) for r, m in loop.plant_roles.items() if r != "duty_cycle" and
                      r not in ("load_resistance", "input_voltage")})
    for element, variable in wanted:
        observer.start_time_series(slaves[element], references[element][variable], CosimVariableType.REAL)
    if not execution.simulate_until(step_ns * n):
        raise EngineError(f"engine libcosim: the simulation failed ({' '.join(get_last_error_message().split())})")
    series = {}
    times_ns = None
    for element, variable in wanted:
        t, v = _time_series(observer, slaves[element], references[element][variable], n + 16)
        if len(t) != n + 1:
            raise EngineError(f"engine libcosim: {len(t)} samples of {element}.{variable}, expected {n + 1}")
        if times_ns is None:
            times_ns = t
        series[(element, variable)] = v
    execution.stop()
    del execution
    times = times_ns * 1e-9  # libcosim's clock [ns] as seconds

    def value_of(element, connector):
        return series[(element, connector)]

    return _result(loop, "libcosim", step, _table(loop, step, times, value_of), guids, names)
