"""The closed loop as an SSP 1.0 archive: writing it, validating it and reading it back.

An archive written by :func:`export_ssp` (``buck-cosim export-ssp``) holds::

    SystemStructure.ssd          the system: three components, their connectors and connections,
                                 units, a default experiment (start, stop, communication step)
    resources/<scenario>.fmu     the scenario as a signal source (cosim.ssp.scenario_source)
    resources/<controller>.fmu   the controller FMU (buck-cosim export-controller, or the one given)
    resources/<plant>.fmu        the plant FMU (the built-in BuckConverter, or a binding file's FMU)
    resources/plant.ssv          the plant's parameter values (an SSP 1.0 parameter set)
    resources/controller.ssv     the controller's parameter values (its sample period, limits, gains)
    resources/scenario.toml      the scenario file the scenario FMU was generated from

Connections: scenario -> controller (``reference``, ``input_voltage``) and plant
(``load_resistance``, ``input_voltage``); the plant's sensors -> controller
(``measured_output_voltage``, ``measured_inductor_current``, ``measured_load_current``);
controller ``duty_cycle`` -> plant. A binding's unit conversion (``fmu = scale * workbench +
offset``) becomes an ``ssc:LinearTransformation`` on the connection. Time in the archive is plant
time: 0 at the start of the scenario's settle interval (rounded to whole control periods), the
scenario's t = 0 at ``settle``; the default experiment stops at ``settle + duration``.

The communication step lands on every control sample and event instant. It is written twice:
in the ``com.opensimulationplatform`` annotation libcosim reads (``osp:FixedStepAlgorithm
baseStepSize``; SSP 1.0 has no step-size attribute of its own) and in the workbench's own
annotation (``urn:buck-cosim:ssp``), which also carries what only the workbench needs to run the
archive in its own master (the control period, the settle time and the plant's recorded roles).

Hand-written with lxml rather than fmpy.ssp: fmpy reads SSDs (:func:`fmpy.ssp.ssd.read_ssd`) but
has no writer; the XML is validated against the SSP 1.0 schemas fmpy ships
(``fmpy/ssp/schema``, BSD-licensed by the Modelica Association) before anything is written, and
again by :func:`read_ssp`. The archive is written atomically, with fixed member dates, so the same
command twice gives the same bytes.
"""

from __future__ import annotations

import functools
import math
import tempfile
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePosixPath

import fmpy.ssp
from lxml import etree

from cosim.base.errors import ConfigError, WorkbenchError
from cosim.base.files import atomic_write
from cosim.fmi.archive import CheckedFmu, _member_problem, check_fmu
from cosim.fmi.binding import (
    CONTROLLER_INPUT_ROLES,
    INPUT_ROLES,
    PLANT_MODE_CODES,
    PlantBinding,
    RoleMap,
    is_float,
    is_integer,
)
from cosim.fmi.communication import CommunicationStep
from cosim.fmi.controller import builtin_controller_binding
from cosim.master import check_plant_supports, communication_of
from cosim.scenarios import Scenario, parse_scenario
from cosim.ssp.scenario_source import OUTPUTS as SCENARIO_OUTPUTS
from cosim.ssp.scenario_source import scenario_fmu, scenario_toml, settle_time
from cosim.timeline import plan_timeline
from plant_fmu.build import ZIP_DATE

SSD = "http://ssp-standard.org/SSP1/SystemStructureDescription"
SSC = "http://ssp-standard.org/SSP1/SystemStructureCommon"
SSV = "http://ssp-standard.org/SSP1/SystemStructureParameterValues"
OSP = "http://opensimulationplatform.com/SSP/OSPAnnotations"
BC = "urn:buck-cosim:ssp"
#: libcosim reads the SSD with a namespace-blind parser: these exact prefixes are required
NSMAP = {"ssd": SSD, "ssc": SSC, "ssv": SSV, "osp": OSP, "bc": BC}
SCHEMA_DIR = Path(fmpy.ssp.__file__).parent / "schema"
SSD_NAME = "SystemStructure.ssd"
SCENARIO, CONTROLLER, PLANT = "scenario", "controller", "plant"
COMPONENTS = (SCENARIO, CONTROLLER, PLANT)
SCENARIO_FILE = "resources/scenario.toml"
OSP_ANNOTATION = "com.opensimulationplatform"
BC_ANNOTATION = "org.buck-cosim.loop"
#: default communication step [s]: the workbench's default recording period
DEFAULT_STEP = 1e-5
GRID_TOLERANCE = 1e-9  # relative: a period or an instant "lands on" the step grid within this
#: base units (SI exponents) of the units the connectors and parameters use
UNITS = {"V": {"kg": "1", "m": "2", "s": "-3", "A": "-1"}, "A": {"A": "1"}, "Ohm": {"kg": "1", "m": "2", "s": "-3", "A": "-2"},
         "s": {"s": "1"}, "1": {}, "H": {"kg": "1", "m": "2", "s": "-2", "A": "-2"},
         "F": {"kg": "-1", "m": "-2", "s": "4", "A": "2"}, "Hz": {"s": "-1"},
         "1/V": {"kg": "-1", "m": "-2", "s": "3", "A": "1"}, "1/(V.s)": {"kg": "-1", "m": "-2", "s": "2", "A": "1"}}
#: controller inputs fed by a plant sensor: (controller input, plant roles in order of preference)
SENSOR_ROLES = {"measured_output_voltage": ("measured_output_voltage", "output_voltage"),
                "measured_inductor_current": ("measured_inductor_current", "inductor_current"),
                "measured_load_current": ("measured_load_current", "load_current")}


class SspError(ConfigError):
    """An SSP archive that cannot be written or used (one line, exit code 2)."""


@dataclass(frozen=True)
class Connector:
    name: str
    kind: str  # "input", "output" or "parameter"
    type: str  # "Real", "Integer", "Boolean" or "String"
    unit: str | None = None


@dataclass(frozen=True)
class Component:
    name: str  # scenario, controller or plant
    source: str  # member of the archive, e.g. resources/BuckConverter.fmu
    connectors: tuple[Connector, ...]
    parameters: dict = field(default_factory=dict)  # name -> value, from the component's .ssv
    parameter_source: str | None = None  # member of the archive
    fmi_version: str = "2.0"  # the component FMU's fmiVersion (read back from the archive)


@dataclass(frozen=True)
class Connection:
    start_element: str
    start_connector: str
    end_element: str
    end_connector: str
    factor: float = 1.0  # end = factor * start + offset
    offset: float = 0.0

    @property
    def label(self) -> str:
        return f"{self.start_element}.{self.start_connector} -> {self.end_element}.{self.end_connector}"


@dataclass(frozen=True)
class Loop:
    """An SSP of the closed loop, as written or read back (times in plant time, seconds)."""

    name: str
    components: dict[str, Component]
    connections: tuple[Connection, ...]
    start_time: float
    stop_time: float
    step: float  # [s] the communication step
    control_period: float  # [s]
    settle: float  # [s] plant time of the scenario's t = 0
    scenario: Scenario
    plant_roles: dict[str, RoleMap]  # every role of the plant binding (the recorded outputs too)
    plant_label: str
    plant_tag: str
    plant_binding_file: str | None = None  # the binding file the archive was made from (metadata only)
    archive: Path | None = None

    def connection_to(self, element: str, connector: str) -> Connection | None:
        return next((c for c in self.connections if (c.end_element, c.end_connector) == (element, connector)), None)


# ---------------------------------------------------------------------------------------------
# Schemas


@functools.lru_cache(maxsize=None)
def schema(name: str) -> etree.XMLSchema:
    """An SSP 1.0 schema from fmpy's copy (``SystemStructureDescription.xsd``, ...)."""
    return etree.XMLSchema(etree.parse(str(SCHEMA_DIR / name)))


def schema_problem(root, name: str) -> str | None:
    """The first violation of the SSP 1.0 schema ``name`` (one line), or None if valid."""
    checker = schema(name)
    if checker.validate(root):
        return None
    entry = checker.error_log[0]
    return f"line {entry.line}: {' '.join(entry.message.split())}"


# ---------------------------------------------------------------------------------------------
# Writing


def _q(namespace: str, tag: str) -> str:
    return f"{{{namespace}}}{tag}"


def _number(value: float) -> str:
    return repr(float(value))


def _type_element(parent, namespace: str, kind: str, value=None, unit: str | None = None) -> None:
    attributes = {}
    if value is not None:
        attributes["value"] = (("true" if value else "false") if kind == "Boolean" else
                               _number(value) if kind == "Real" else str(value))
    if unit and kind == "Real":
        attributes["unit"] = unit
    etree.SubElement(parent, _q(namespace, kind), attributes)


def _units_element(parent, namespace: str, units: set[str]) -> None:
    element = etree.SubElement(parent, _q(namespace, "Units"))
    for unit in sorted(units):
        item = etree.SubElement(element, _q(SSC, "Unit"), {"name": unit})
        etree.SubElement(item, _q(SSC, "BaseUnit"), UNITS.get(unit, {}))


def parameter_set_xml(name: str, parameters: list[tuple[str, str, object, str | None]]) -> bytes:
    """An SSP 1.0 parameter set (``.ssv``): ``parameters`` are (name, type, value, unit)."""
    root = etree.Element(_q(SSV, "ParameterSet"), {"version": "1.0", "name": name}, nsmap={"ssv": SSV, "ssc": SSC})
    values = etree.SubElement(root, _q(SSV, "Parameters"))
    for pname, kind, value, unit in parameters:
        element = etree.SubElement(values, _q(SSV, "Parameter"), {"name": pname})
        _type_element(element, SSV, kind, value, unit)
    units = {unit for _, kind, _, unit in parameters if unit and kind == "Real"}
    if units:
        _units_element(root, SSV, units)
    problem = schema_problem(root, "SystemStructureParameterValues.xsd")
    if problem:  # a defect of this writer, not of the user's input
        raise AssertionError(f"{name}.ssv violates the SSP 1.0 schema: {problem}")
    return etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True)


def ssd_xml(loop: Loop, description: str) -> bytes:
    """``SystemStructure.ssd`` of a loop, checked against the SSP 1.0 schema."""
    root = etree.Element(_q(SSD, "SystemStructureDescription"),
                         {"version": "1.0", "name": loop.name, "generationTool": "buck-cosim export-ssp"},
                         nsmap=NSMAP)
    system = etree.SubElement(root, _q(SSD, "System"), {"name": "loop", "description": description})
    elements = etree.SubElement(system, _q(SSD, "Elements"))
    units = set()
    for name in COMPONENTS:
        component = loop.components[name]
        element = etree.SubElement(elements, _q(SSD, "Component"),
                                   {"name": name, "type": "application/x-fmu-sharedlibrary",
                                    "source": component.source})
        connectors = etree.SubElement(element, _q(SSD, "Connectors"))
        for c in component.connectors:
            connector = etree.SubElement(connectors, _q(SSD, "Connector"), {"name": c.name, "kind": c.kind})
            _type_element(connector, SSC, c.type, unit=c.unit)
            if c.unit and c.type == "Real":
                units.add(c.unit)
        if component.parameter_source:
            bindings = etree.SubElement(element, _q(SSD, "ParameterBindings"))
            etree.SubElement(bindings, _q(SSD, "ParameterBinding"),
                             {"type": "application/x-ssp-parameter-set", "source": component.parameter_source})
    connections = etree.SubElement(system, _q(SSD, "Connections"))
    for c in loop.connections:
        connection = etree.SubElement(connections, _q(SSD, "Connection"), {
            "startElement": c.start_element, "startConnector": c.start_connector,
            "endElement": c.end_element, "endConnector": c.end_connector})
        if c.factor != 1.0 or c.offset != 0.0:
            etree.SubElement(connection, _q(SSC, "LinearTransformation"),
                             {"factor": _number(c.factor), "offset": _number(c.offset)})
    annotations = etree.SubElement(system, _q(SSD, "Annotations"))
    annotation = etree.SubElement(annotations, _q(SSC, "Annotation"), {"type": BC_ANNOTATION})
    workbench = etree.SubElement(annotation, _q(BC, "Loop"), {
        "scenario": SCENARIO_FILE, "controlPeriod": _number(loop.control_period), "settle": _number(loop.settle),
        "plantLabel": loop.plant_label, "plantTag": loop.plant_tag,
        **({"plantBindingFile": loop.plant_binding_file} if loop.plant_binding_file else {})})
    for role, mapping in loop.plant_roles.items():
        etree.SubElement(workbench, _q(BC, "PlantRole"), {"role": role, "variable": mapping.variable,
                                                          "scale": _number(mapping.scale),
                                                          "offset": _number(mapping.offset)})
    _units_element(root, SSD, units)
    experiment = etree.SubElement(root, _q(SSD, "DefaultExperiment"),
                                  {"startTime": _number(loop.start_time), "stopTime": _number(loop.stop_time)})
    annotations = etree.SubElement(experiment, _q(SSD, "Annotations"))
    osp = etree.SubElement(annotations, _q(SSC, "Annotation"), {"type": OSP_ANNOTATION})
    algorithm = etree.SubElement(osp, _q(OSP, "Algorithm"))
    etree.SubElement(algorithm, _q(OSP, "FixedStepAlgorithm"), {"baseStepSize": _number(loop.step)})
    ours = etree.SubElement(annotations, _q(SSC, "Annotation"), {"type": BC_ANNOTATION})
    etree.SubElement(ours, _q(BC, "Experiment"), {"communicationStep": _number(loop.step)})
    problem = schema_problem(root, "SystemStructureDescription.xsd")
    if problem:
        raise AssertionError(f"{SSD_NAME} violates the SSP 1.0 schema: {problem}")
    return etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True)


def _on_grid(value: float, step: float) -> bool:
    ratio = value / step
    return abs(ratio - round(ratio)) <= GRID_TOLERANCE * max(1.0, abs(ratio))


def check_step(step: float, control_period: float, scenario: Scenario, settle: float, binding: PlantBinding,
               communication: CommunicationStep | None = None) -> None:
    """Refuse a communication step that misses a control sample or an event instant, or that the
    plant FMU cannot take in one step (its binding's ``max_step``, or, given the plant's ``communication``, another
    than a fixed-step FMU's own, :mod:`cosim.fmi.communication`)."""
    if not (step > 0 and math.isfinite(step)):
        raise SspError(f"communication step {step} s is invalid: expected a finite value > 0")
    if step > control_period * (1 + GRID_TOLERANCE) or not _on_grid(control_period, step):
        raise SspError(f"communication step {step:.6g} s does not divide the control period {control_period:.6g} s: "
                       "the engines exchange values only at communication points, so every control sample must be "
                       "one (use --communication-step with a divisor of the control period)")
    for event in scenario.events:
        if not _on_grid(settle + event.time, step):
            raise SspError(f"scenario {scenario.name}: the event at t = {event.time:.9g} s (plant time "
                           f"{settle + event.time:.9g} s) is not on the grid of communication step {step:.6g} s: "
                           "an engine would apply it late (use --communication-step with a divisor of the event time)")
    fixed = communication.for_run(control_period) if communication is not None else None
    if fixed is not None and not math.isclose(step, fixed, rel_tol=GRID_TOLERANCE):
        raise SspError(f"{binding.origin}: the plant FMU steps only by its fixed communication step "
                       f"{communication.describe(control_period)}, but the communication step is {step:.6g} s: use "
                       f"--communication-step {fixed:.6g}")
    if binding.max_step is not None and step > binding.max_step * (1 + GRID_TOLERANCE):
        raise SspError(f"{binding.origin}: communication step {step:.6g} s is longer than the plant's max_step "
                       f"{binding.max_step:.6g} s (engines step the FMU once per communication step)")


def _real_parameter_unit(checked: CheckedFmu, name: str) -> str | None:
    variable = next(v for v in checked.model_description.modelVariables if v.name == name)
    return variable.unit or (variable.declaredType.unit if variable.declaredType is not None else None)


def _connector(checked: CheckedFmu, name: str, kind: str) -> Connector:
    variable = next((v for v in checked.model_description.modelVariables if v.name == name), None)
    if variable is None:
        raise SspError(f"FMU {checked.path.name} has no variable {name!r}")
    kind_type = ssp_type(variable)
    return Connector(name, kind, kind_type, _real_parameter_unit(checked, name) if kind_type == "Real" else None)


def ssp_type(variable) -> str:
    """The SSP 1.0 connector type of an FMU variable: SSP 1.0 knows FMI 2.0's types only, so an FMI 3.0
    Float64 connects as Real and an Int8 ... UInt64 as Integer (as enumerations do)."""
    if is_float(variable):
        return "Real"
    if variable.type == "Enumeration" or is_integer(variable):
        return "Integer"
    return variable.type


def build_loop(scenario: Scenario, binding: PlantBinding, controller: CheckedFmu, scenario_source: CheckedFmu,
               control_period: float, step: float) -> Loop:
    """The loop's structure: components, connectors, connections and experiment."""
    settle = settle_time(scenario, control_period)
    plan = plan_timeline(scenario, control_period, step)
    plant = check_fmu(binding.fmu_path)
    if "co-simulation" not in plant.interfaces:
        raise SspError(f"{binding.origin}: the plant FMU offers no co-simulation for this platform (an SSP's "
                       "engines step every FMU with fmi2DoStep or fmi3DoStep)")
    check_step(step, control_period, scenario, settle, binding, communication_of(binding, "co-simulation"))
    roles = dict(binding.roles)
    # plant connectors: every bound role's variable (inputs and outputs), then the parameters
    plant_connectors, seen = [], set()
    for role, mapping in roles.items():
        if mapping.variable not in seen:
            seen.add(mapping.variable)
            plant_connectors.append(_connector(plant, mapping.variable, "input" if role in INPUT_ROLES else "output"))
    plant_parameters = dict(binding.parameters)
    for name in plant_parameters:
        plant_connectors.append(_connector(plant, name, "parameter"))
    controller_md = controller.model_description
    controller_variables = {v.name: v for v in controller_md.modelVariables}
    controller_inputs = [r for r in CONTROLLER_INPUT_ROLES if r in controller_variables]
    controller_parameters = {v.name: float(v.start) for v in controller_md.modelVariables
                             if v.causality == "parameter" and v.start is not None and is_float(v)}
    controller_connectors = [_connector(controller, r, "input") for r in controller_inputs]
    controller_connectors.append(_connector(controller, "duty_cycle", "output"))
    controller_connectors += [_connector(controller, name, "parameter") for name in controller_parameters]
    scenario_connectors = [_connector(scenario_source, s, "output") for s in SCENARIO_OUTPUTS]

    connections = [Connection(SCENARIO, "reference", CONTROLLER, "reference")]
    for signal in ("load_resistance", "input_voltage"):
        if signal in roles:
            m = roles[signal]
            connections.append(Connection(SCENARIO, signal, PLANT, m.variable, m.scale, m.offset))
    for controller_input, candidates in SENSOR_ROLES.items():
        role = next((r for r in candidates if r in roles), None)
        if role is not None and controller_input in controller_inputs:
            m = roles[role]  # workbench = (fmu - offset) / scale
            connections.append(Connection(PLANT, m.variable, CONTROLLER, controller_input, 1.0 / m.scale,
                                          -m.offset / m.scale))
    if "input_voltage" in controller_inputs:
        connections.append(Connection(SCENARIO, "input_voltage", CONTROLLER, "input_voltage"))
    duty = roles["duty_cycle"]
    connections.append(Connection(CONTROLLER, "duty_cycle", PLANT, duty.variable, duty.scale, duty.offset))

    components = {
        SCENARIO: Component(SCENARIO, f"resources/{scenario_source.model_description.coSimulation.modelIdentifier}.fmu", tuple(scenario_connectors)),
        CONTROLLER: Component(CONTROLLER, f"resources/{controller_md.coSimulation.modelIdentifier}.fmu",
                              tuple(controller_connectors), controller_parameters, "resources/controller.ssv"),
        PLANT: Component(PLANT, f"resources/{plant.model_description.coSimulation.modelIdentifier}.fmu",
                         tuple(plant_connectors), plant_parameters,
                         "resources/plant.ssv" if plant_parameters else None),
    }
    if len({c.source for c in components.values()}) != 3:
        raise SspError("the scenario, controller and plant FMUs have the same model identifier: rename one")
    return Loop(name=f"{scenario.name}__{controller_md.modelName}", components=components,
                connections=tuple(connections), start_time=0.0, stop_time=plan.end, step=step,
                control_period=control_period, settle=settle, scenario=scenario, plant_roles=roles,
                plant_label=binding.label, plant_tag=binding.tag,
                plant_binding_file=str(binding.source.name) if binding.source else None)


def _ssv_entries(checked: CheckedFmu, parameters: dict) -> list[tuple[str, str, object, str | None]]:
    entries = []
    for name, value in parameters.items():
        connector = _connector(checked, name, "parameter")
        entries.append((name, connector.type, value, connector.unit))
    return entries


def controller_sample_period(controller: CheckedFmu) -> float:
    """The sample period [s] a workbench controller FMU declares (its ``sample_period`` start value)."""
    variable = next((v for v in controller.model_description.modelVariables if v.name == "sample_period"), None)
    if variable is None or variable.start is None:
        raise SspError(f"controller FMU {controller.path} declares no sample_period")
    return float(variable.start)


def export_ssp(scenario: Scenario, binding: PlantBinding, controller_fmu: Path, out: Path, *,
               step: float | None = None) -> Loop:
    """Write the loop of ``scenario`` on ``binding``'s plant with the controller FMU (the
    workbench's role names, e.g. from ``export-controller``) as an SSP 1.0 archive ``out``.
    The scenario FMU is of the controller FMU's FMI version (2.0 or 3.0); the plant's is its own.

    ``step``: the communication step [s] (default: 10 us, the workbench's recording period); it
    must divide the controller's sample period and land on every event. Everything is checked and
    the XML validated before the archive is written (atomically, fixed member dates).
    """
    builtin_controller_binding(controller_fmu)  # the workbench's role names, or a one-line refusal
    controller = check_fmu(controller_fmu)
    if "co-simulation" not in controller.interfaces:
        raise SspError(f"controller FMU {controller_fmu} offers no co-simulation for this platform")
    check_plant_supports(binding, scenario)
    control_period = controller_sample_period(controller)
    if step is None:  # 10 us, or a fixed-step plant's own step
        step = communication_of(binding, "co-simulation").for_run(control_period) or DEFAULT_STEP
    source = check_fmu(scenario_fmu(scenario, control_period, fmi_version=controller.fmi_major))
    loop = build_loop(scenario, binding, controller, source, control_period, step)
    description = (f"buck-cosim closed loop: scenario {scenario.name} ({scenario.description}), controller "
                   f"{controller.model_description.modelName} sampled every {control_period:.6g} s, plant "
                   f"{binding.label}; plant time, the scenario's t = 0 at {loop.settle:.9g} s")
    members = {SSD_NAME: ssd_xml(loop, description)}
    plant = check_fmu(binding.fmu_path)
    for name, fmu in ((SCENARIO, source.path), (CONTROLLER, controller.path), (PLANT, plant.path)):
        members[loop.components[name].source] = Path(fmu).read_bytes()
    for name, checked in ((CONTROLLER, controller), (PLANT, plant)):
        component = loop.components[name]
        if component.parameter_source:
            members[component.parameter_source] = parameter_set_xml(name, _ssv_entries(checked, component.parameters))
    members[SCENARIO_FILE] = scenario_toml(scenario).encode()

    def write(tmp: Path) -> None:
        with zipfile.ZipFile(tmp, "w") as archive:
            for member, data in members.items():
                info = zipfile.ZipInfo(member, ZIP_DATE)
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = 0o644 << 16
                archive.writestr(info, data)

    atomic_write(Path(out), write)
    return Loop(**{**loop.__dict__, "archive": Path(out)})


# ---------------------------------------------------------------------------------------------
# Reading


def _parse(data: bytes, what: str, where: str):
    try:
        return etree.fromstring(data, parser=etree.XMLParser(resolve_entities=False, no_network=True))
    except etree.XMLSyntaxError as error:
        raise SspError(f"{where}: {what} is not well-formed XML ({' '.join(str(error).split())})") from None


def _float(text: str | None, what: str, where: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise SspError(f"{where}: {what} = {text!r} is not a number") from None
    if not math.isfinite(value):
        raise SspError(f"{where}: {what} = {text} is not finite")
    return value


def _positive(text: str | None, what: str, where: str) -> float:
    value = _float(text, what, where)
    if value <= 0:
        raise SspError(f"{where}: {what} = {text} s: expected a time > 0")
    return value


def _check_experiment(start_time: float, stop_time: float, step: float, control_period: float, settle: float,
                      scenario: Scenario, where: str) -> None:
    """The DefaultExperiment every engine runs: from rest at t = 0 to the end of the embedded scenario (its settle
    time and duration at the archive's control period, as export-ssp writes it), and the annotation's settle time
    the scenario's. The workbench engine runs the scenario's own timeline; fmpy and libcosim run
    startTime..stopTime and keep the rows from the annotated settle time on: an archive whose experiment differs
    from the scenario would give three engines three different runs."""
    if start_time != 0.0:
        raise SspError(f"{where}: DefaultExperiment startTime = {start_time:g} s: expected 0 (the loop starts at rest "
                       "at t = 0, the scenario's settle time first)")
    try:
        plan = plan_timeline(scenario, control_period, step)
    except ConfigError as error:
        raise SspError(f"{where}: {error}") from None
    end = plan.end
    if not math.isclose(settle, plan.settle, rel_tol=1e-9, abs_tol=1e-12):
        raise SspError(f"{where}: the buck-cosim annotation's settle = {settle:g} s: expected {plan.settle:.9g} s, the "
                       f"embedded scenario {scenario.name!r}'s settle time at control period {control_period:.6g} s")
    if not math.isclose(stop_time, end, rel_tol=1e-9, abs_tol=1e-12):
        raise SspError(f"{where}: DefaultExperiment stopTime = {stop_time:g} s: expected {end:.9g} s, the end of the "
                       f"embedded scenario {scenario.name!r} (its settle time and {scenario.duration:g} s at control "
                       f"period {control_period:.6g} s) -- to run another length, export the archive again with "
                       "another scenario")


def _typed(element, where: str):
    """(type, value) of an ssv:Real/Integer/Boolean/String element."""
    kind = etree.QName(element).localname
    text = element.get("value")
    if kind == "Real":
        return kind, _float(text, "a Real parameter", where)
    if kind in ("Integer", "Enumeration"):
        return "Integer", int(text)
    if kind == "Boolean":
        return kind, text in ("true", "1")
    return kind, text


def _member(archive: zipfile.ZipFile, name: str, path: Path, what: str) -> bytes:
    try:
        return archive.read(name)
    except KeyError:
        raise SspError(f"{path}: {what} names {name}, which the archive does not contain") from None


def read_ssp(path: str | Path) -> Loop:
    """Read and check an SSP archive of the loop: a zip with safe member names, an SSD valid
    against the SSP 1.0 schema, the three components with their FMUs and parameter sets present,
    every connector a variable of its FMU with a fitting causality, every connection between
    declared connectors (output to input), and the workbench's annotations. Raises
    :class:`SspError` (one line) naming the problem."""
    path = Path(path)
    if path.is_dir():
        raise SspError(f"SSP {path} is a folder: expected an .ssp file (a zip archive)")
    if not path.is_file():
        raise SspError(f"SSP {path} does not exist (write one with buck-cosim export-ssp)")
    if not zipfile.is_zipfile(path):
        raise SspError(f"SSP {path} is not a zip archive (an SSP is a zip file with {SSD_NAME}); truncated?")
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            for name in names:
                problem = _member_problem(name)
                if problem:
                    raise SspError(f"SSP {path}: member {name!r} {problem}; refusing to read it")
            if SSD_NAME not in names:
                raise SspError(f"SSP {path} has no {SSD_NAME} at the top level")
            return _read_loop(archive, path)
    except zipfile.BadZipFile as error:
        raise SspError(f"SSP {path} is a damaged zip archive ({error})") from None
    except (EOFError, OSError) as error:
        raise SspError(f"SSP {path} is truncated or unreadable ({error})") from None


def _read_loop(archive: zipfile.ZipFile, path: Path) -> Loop:
    where = f"{path}!{SSD_NAME}"
    root = _parse(archive.read(SSD_NAME), SSD_NAME, str(path))
    problem = schema_problem(root, "SystemStructureDescription.xsd")
    if problem:
        raise SspError(f"{where}: not valid SSP 1.0 ({problem})")
    ns = {"ssd": SSD, "ssc": SSC, "ssv": SSV, "osp": OSP, "bc": BC}
    system = root.find("ssd:System", ns)
    components: dict[str, Component] = {}
    fmus: dict[str, CheckedFmu] = {}
    for element in system.findall("ssd:Elements/ssd:Component", ns):
        name, source = element.get("name"), element.get("source")
        connectors = tuple(Connector(c.get("name"), c.get("kind"),
                                     etree.QName(c[0]).localname if len(c) and etree.QName(c[0]).namespace == SSC
                                     else "Real", c[0].get("unit") if len(c) else None)
                           for c in element.findall("ssd:Connectors/ssd:Connector", ns))
        parameters, parameter_source = {}, None
        for binding in element.findall("ssd:ParameterBindings/ssd:ParameterBinding", ns):
            parameter_source = binding.get("source")
            if parameter_source is None:
                raise SspError(f"{where}: component {name!r} has a parameter binding without a source (.ssv file)")
            ssv_where = f"{path}!{parameter_source}"
            ssv = _parse(_member(archive, parameter_source, path, f"component {name!r}'s parameter binding"),
                         parameter_source, str(path))
            problem = schema_problem(ssv, "SystemStructureParameterValues.xsd")
            if problem:
                raise SspError(f"{ssv_where}: not a valid SSP 1.0 parameter set ({problem})")
            for parameter in ssv.findall("ssv:Parameters/ssv:Parameter", ns):
                kind, value = _typed(parameter[0], ssv_where)
                parameters[parameter.get("name")] = value
        components[name] = Component(name, source, connectors, parameters, parameter_source)
    missing = [c for c in COMPONENTS if c not in components]
    if missing:
        raise SspError(f"{where}: no component named {missing[0]!r} (a buck-cosim loop has the components "
                       f"{', '.join(COMPONENTS)})")
    with tempfile.TemporaryDirectory(prefix="buck-cosim-ssp-") as tmp:
        for name in COMPONENTS:
            component = components[name]
            data = _member(archive, component.source, path, f"component {name!r}")
            target = Path(tmp) / PurePosixPath(component.source).name
            target.write_bytes(data)
            try:
                fmus[name] = check_fmu(target)
            except WorkbenchError as error:
                raise SspError(f"{path}!{component.source}: {str(error).split(': ', 1)[-1]}") from None
            components[name] = replace(component, fmi_version=fmus[name].model_description.fmiVersion)
        _check_connectors(components, fmus, where)
    connections = []
    declared = {(c.name, k.name): k for c in components.values() for k in c.connectors}
    for element in system.findall("ssd:Connections/ssd:Connection", ns):
        start = (element.get("startElement"), element.get("startConnector"))
        end = (element.get("endElement"), element.get("endConnector"))
        transformation = element.find("ssc:LinearTransformation", ns)
        factor = _float(transformation.get("factor", "1"), "factor", where) if transformation is not None else 1.0
        offset = _float(transformation.get("offset", "0"), "offset", where) if transformation is not None else 0.0
        connection = Connection(*start, *end, factor, offset)
        for (element_name, connector_name), side, kind in ((start, "start", "output"), (end, "end", "input")):
            if element_name not in components:
                raise SspError(f"{where}: connection {connection.label}: no component {element_name!r}")
            connector = declared.get((element_name, connector_name))
            if connector is None:
                raise SspError(f"{where}: connection {connection.label}: component {element_name!r} has no connector "
                               f"{connector_name!r}")
            if connector.kind != kind:
                raise SspError(f"{where}: connection {connection.label}: its {side} {element_name}.{connector_name} "
                               f"is an {connector.kind}, expected an {kind}")
        connections.append(connection)
    ends = [(c.end_element, c.end_connector) for c in connections]
    if len(set(ends)) != len(ends):
        twice = next(e for e in ends if ends.count(e) > 1)
        raise SspError(f"{where}: input {twice[0]}.{twice[1]} is the end of more than one connection")
    experiment = root.find("ssd:DefaultExperiment", ns)
    if experiment is None or experiment.get("stopTime") is None:
        raise SspError(f"{where}: no DefaultExperiment with a stopTime")
    ours = system.find(f"ssd:Annotations/ssc:Annotation[@type='{BC_ANNOTATION}']/bc:Loop", ns)
    step_element = experiment.find(f"ssd:Annotations/ssc:Annotation[@type='{BC_ANNOTATION}']/bc:Experiment", ns)
    if ours is None or step_element is None:
        raise SspError(f"{where}: no buck-cosim annotations ({BC_ANNOTATION}): not written by buck-cosim export-ssp "
                       "(the workbench needs its control period, settle time and plant roles)")
    scenario_text = _member(archive, ours.get("scenario", SCENARIO_FILE), path, "the buck-cosim annotation")
    try:
        scenario = parse_scenario(scenario_text.decode("utf-8"), Path(f"{path}!{ours.get('scenario')}"))
    except UnicodeDecodeError:
        raise SspError(f"{path}!{ours.get('scenario')}: not UTF-8 text") from None
    roles = {r.get("role"): RoleMap(r.get("variable"), _float(r.get("scale"), "scale", where),
                                    _float(r.get("offset"), "offset", where))
             for r in ours.findall("bc:PlantRole", ns)}
    for role in ("duty_cycle", "output_voltage"):
        if role not in roles:
            raise SspError(f"{where}: the buck-cosim annotation binds no plant variable to the role {role!r}")
    plant_variables = {k.name for k in components[PLANT].connectors}
    for role, mapping in roles.items():
        if mapping.variable not in plant_variables:
            raise SspError(f"{where}: the plant role {role!r} names {mapping.variable!r}, which is not a connector "
                           "of the component 'plant'")
    start_time = _float(experiment.get("startTime", "0"), "startTime", where)
    stop_time = _float(experiment.get("stopTime"), "stopTime", where)
    step = _positive(step_element.get("communicationStep"), "communicationStep", where)
    control_period = _positive(ours.get("controlPeriod"), "controlPeriod", where)
    settle = _float(ours.get("settle"), "settle", where)
    _check_experiment(start_time, stop_time, step, control_period, settle, scenario, where)
    return Loop(name=root.get("name"), components=components, connections=tuple(connections),
                start_time=start_time, stop_time=stop_time, step=step, control_period=control_period,
                settle=settle, scenario=scenario, plant_roles=roles,
                plant_label=ours.get("plantLabel", "plant"), plant_tag=ours.get("plantTag", "ssp-plant"),
                plant_binding_file=ours.get("plantBindingFile"), archive=path)


def _check_connectors(components: dict[str, Component], fmus: dict[str, CheckedFmu], where: str) -> None:
    """Every connector (and parameter) names a variable of its FMU with a fitting causality."""
    for name, component in components.items():
        checked = fmus[name]
        variables = {v.name: v for v in checked.model_description.modelVariables}
        fmu_name = PurePosixPath(component.source).name
        for connector in component.connectors:
            variable = variables.get(connector.name)
            if variable is None:
                raise SspError(f"{where}: component {name!r} has a connector {connector.name!r}, but {fmu_name} has no "
                               "such variable")
            wanted = {"input": ("input",), "output": ("output",), "parameter": ("parameter", "input")}.get(
                connector.kind, (connector.kind,))
            if variable.causality not in wanted:
                raise SspError(f"{where}: connector {name}.{connector.name} is an {connector.kind}, but {fmu_name}'s "
                               f"variable has causality {variable.causality}")
        for parameter in component.parameters:
            if parameter not in variables:
                raise SspError(f"{where}: the parameter set {component.parameter_source} of component {name!r} sets "
                               f"{parameter!r}, which {fmu_name} does not have")


def plant_mode_name(loop: Loop) -> str | None:
    """``averaged`` or ``switched`` for the built-in plant (its ``plant_mode`` parameter), else None."""
    code = loop.components[PLANT].parameters.get("plant_mode")
    return {v: k for k, v in PLANT_MODE_CODES.items()}.get(code)
