"""The FMI 3.0 edition of an FMU the workbench builds: its ``modelDescription.xml``, ``buildDescription.xml``
and the generated ``fmi3_variables.h``, all derived from the FMI 2.0 edition's model description.

The variables of each FMU are defined once -- the plant's hand-written FMI 2.0 ``modelDescription.xml``,
the controller's and scenario's tables in Python -- and :func:`fmi3_model_description` translates that
description into FMI 3.0: ``ScalarVariable``/``Real`` becomes ``Float64``, ``Integer`` becomes ``Int32``,
``SimpleType``s become ``Float64Type``/``Int32Type``, ``guid`` becomes ``instantiationToken``, the capability
flags take their FMI 3.0 names, the model structure refers to value references instead of indices, and
the two kinds of variable FMI 3.0 requires that FMI 2.0 does without are added: the independent
variable ``time`` and one ``Float64`` variable per event indicator, served by the FMI 3.0 glue
(``glue/fmi3_glue.c``) under the value references of :data:`TIME_VALUE_REFERENCE` and
:data:`FIRST_EVENT_INDICATOR_VALUE_REFERENCE`.

Why hand-written: fmpy can write an FMI 3.0 description from its objects
(``fmpy.model_description.write_model_description``), but it drops the variables' ``min``, ``max``,
``nominal`` and ``reinit`` attributes, which the workbench's checks (tunable-parameter ranges) and other
importers rely on; this translation keeps every attribute.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence
from xml.etree import ElementTree

import fmpy

from plant_fmu.fmu_sources import GLUE_DIR, FmuSources, model_description_text, read_files

#: value references the FMI 3.0 glue owns (a model's own value references stay below 1000)
TIME_VALUE_REFERENCE = 1000
FIRST_EVENT_INDICATOR_VALUE_REFERENCE = 1001
MODEL_VALUE_REFERENCE_LIMIT = 1000
#: files staged in an FMI 3.0 FMU's sources/ beside the model's
BUILD_DESCRIPTION = "buildDescription.xml"
VARIABLES_HEADER = "fmi3_variables.h"
FMI2_GLUE, FMI3_GLUE = "fmi2_glue.c", "fmi3_glue.c"
#: the FMI 2.0 standard's headers, for the model interface's scalar types (fmu_model.h), from fmpy's copy:
#: staged with the sources so that a tool compiling the source FMU with its FMI 3.0 headers finds them
FMI2_TYPE_HEADERS = ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h")

_TYPES = {"Real": "Float64", "Integer": "Int32", "Boolean": "Boolean", "String": "String",
          "Enumeration": "Enumeration"}
#: FMI 2.0 capability flags -> FMI 3.0 names (None: no FMI 3.0 counterpart, dropped)
_CAPABILITIES = {
    "modelIdentifier": "modelIdentifier", "needsExecutionTool": "needsExecutionTool",
    "canBeInstantiatedOnlyOncePerProcess": "canBeInstantiatedOnlyOncePerProcess",
    "canGetAndSetFMUstate": "canGetAndSetFMUState", "canSerializeFMUstate": "canSerializeFMUState",
    "providesDirectionalDerivative": "providesDirectionalDerivative",
    "canHandleVariableCommunicationStepSize": "canHandleVariableCommunicationStepSize",
    "maxOutputDerivativeOrder": "maxOutputDerivativeOrder", "canInterpolateInputs": "canInterpolateInputs",
    "completedIntegratorStepNotNeeded": None, "canNotUseMemoryManagementFunctions": None,
    "canRunAsynchronuously": None,
}
_VARIABLE_ATTRIBUTES = ("name", "valueReference", "description", "causality", "variability", "initial",
                        "canHandleMultipleSetPerTimeInstant")
_TYPE_ATTRIBUTES = ("declaredType", "quantity", "unit", "displayUnit", "relativeQuantity", "min", "max", "nominal",
                    "unbounded", "start", "reinit")


def _interface(element: ElementTree.Element, tag: str) -> ElementTree.Element:
    interface = ElementTree.Element(tag)
    for name, value in element.attrib.items():
        if name not in _CAPABILITIES:
            raise ValueError(f"{tag} attribute {name!r} has no known FMI 3.0 counterpart")
        if _CAPABILITIES[name] is not None:
            interface.set(_CAPABILITIES[name], value)
    if tag == "ModelExchange" and element.get("completedIntegratorStepNotNeeded") != "true":
        interface.set("needsCompletedIntegratorStep", "true")
    return interface


def _type_definition(simple: ElementTree.Element) -> ElementTree.Element:
    (kind,) = list(simple)
    element = ElementTree.Element(f"{_TYPES[kind.tag]}Type", {"name": simple.get("name"), **kind.attrib})
    if simple.get("description"):
        element.set("description", simple.get("description"))
    for item in kind.findall("Item"):
        ElementTree.SubElement(element, "Item", item.attrib)
    return element


def fmi3_model_description(fmi2_text: str, event_indicators: Sequence[tuple[str, str]] = ()) -> str:
    """The FMI 3.0 ``modelDescription.xml`` of the FMU whose FMI 2.0 description is ``fmi2_text``.

    ``event_indicators``: (name, description) of each event indicator, in the model's order (as many as
    the FMI 2.0 description's ``numberOfEventIndicators``); they become local Float64 variables.
    """
    old = ElementTree.fromstring(fmi2_text)
    if old.get("fmiVersion") != "2.0":
        raise ValueError(f"expected an FMI 2.0 model description, got fmiVersion={old.get('fmiVersion')!r}")
    expected = int(old.get("numberOfEventIndicators", "0"))
    if len(event_indicators) != expected:
        raise ValueError(f"the model has {expected} event indicators, {len(event_indicators)} named")
    root = ElementTree.Element("fmiModelDescription", {"fmiVersion": "3.0"})
    for name in ("modelName", "description", "author", "version", "copyright", "license", "generationTool",
                 "generationDateAndTime", "variableNamingConvention"):
        if old.get(name) is not None:
            root.set(name, old.get(name))
    root.set("instantiationToken", old.get("guid"))
    for tag in ("ModelExchange", "CoSimulation"):
        element = old.find(tag)
        if element is not None:
            root.append(_interface(element, tag))
    for tag in ("UnitDefinitions", "TypeDefinitions", "LogCategories", "DefaultExperiment"):  # the schema's order
        element = old.find(tag)
        if element is None:
            continue
        if tag == "TypeDefinitions":
            types = ElementTree.SubElement(root, tag)
            for simple in element.findall("SimpleType"):
                types.append(_type_definition(simple))
        else:
            root.append(element)  # the same in both versions

    scalars = old.findall("ModelVariables/ScalarVariable")
    references = [int(v.get("valueReference")) for v in scalars]  # by FMI 2.0 index - 1
    if any(r >= MODEL_VALUE_REFERENCE_LIMIT for r in references):
        raise ValueError(f"value references from {MODEL_VALUE_REFERENCE_LIMIT} on belong to the FMI 3.0 glue")
    variables = ElementTree.SubElement(root, "ModelVariables")
    ElementTree.SubElement(variables, "Float64", {
        "name": "time", "valueReference": str(TIME_VALUE_REFERENCE), "causality": "independent",
        "variability": "continuous", "description": "Simulation time"})
    for scalar in scalars:
        (kind,) = [child for child in scalar if child.tag in _TYPES]
        element = ElementTree.SubElement(variables, _TYPES[kind.tag])
        for name in _VARIABLE_ATTRIBUTES:
            if scalar.get(name) is not None:
                element.set(name, scalar.get(name))
        for name in _TYPE_ATTRIBUTES:
            value = kind.get(name)
            if value is None:
                continue
            if kind.tag == "String" and name == "start":
                ElementTree.SubElement(element, "Start", {"value": value})
            else:
                element.set(name, value)
        if kind.get("derivative") is not None:
            element.set("derivative", str(references[int(kind.get("derivative")) - 1]))
    for i, (name, description) in enumerate(event_indicators):
        ElementTree.SubElement(variables, "Float64", {
            "name": name, "valueReference": str(FIRST_EVENT_INDICATOR_VALUE_REFERENCE + i), "causality": "local",
            "variability": "continuous", "initial": "calculated", "description": description})

    structure = ElementTree.SubElement(root, "ModelStructure")
    for group, tag in (("Outputs", "Output"), ("Derivatives", "ContinuousStateDerivative"),
                       ("InitialUnknowns", "InitialUnknown")):
        for unknown in old.findall(f"ModelStructure/{group}/Unknown"):
            element = ElementTree.SubElement(structure, tag,
                                             {"valueReference": str(references[int(unknown.get("index")) - 1])})
            if unknown.get("dependencies") is not None:
                element.set("dependencies", " ".join(str(references[int(i) - 1])
                                                     for i in unknown.get("dependencies").split()))
            if unknown.get("dependenciesKind") is not None:
                element.set("dependenciesKind", unknown.get("dependenciesKind"))
    for i in range(len(event_indicators)):
        ElementTree.SubElement(structure, "EventIndicator",
                               {"valueReference": str(FIRST_EVENT_INDICATOR_VALUE_REFERENCE + i)})
    return model_description_text(root)


def build_description(identifier: str, compiled: Sequence[str]) -> str:
    """``sources/buildDescription.xml``: the files to compile, in order (FMI 3.0 lists them here rather than
    in modelDescription.xml). No language is declared: the compiler's default, as for the FMI 2.0 edition,
    so both editions compute with the same flags."""
    root = ElementTree.Element("fmiBuildDescription", {"fmiVersion": "3.0"})
    configuration = ElementTree.SubElement(root, "BuildConfiguration", {"modelIdentifier": identifier})
    files = ElementTree.SubElement(configuration, "SourceFileSet")
    for name in compiled:
        ElementTree.SubElement(files, "SourceFile", {"name": name})
    return model_description_text(root)


def source_files_of(fmi2_text: str) -> tuple[str, ...]:
    """The files an FMI 2.0 description compiles (its first interface's SourceFiles), in order."""
    root = ElementTree.fromstring(fmi2_text)
    for tag in ("CoSimulation", "ModelExchange"):
        element = root.find(tag)
        if element is not None:
            return tuple(f.get("name") for f in element.findall("SourceFiles/File"))
    return ()


def variables_header() -> bytes:
    """``fmi3_variables.h``: the value references the FMI 3.0 glue serves itself."""
    return (
        "/* Generated by plant_fmu/fmi3.py: the value references the FMI 3.0 glue (fmi3_glue.c) serves itself,\n"
        " * as modelDescription.xml declares them. */\n"
        "#ifndef FMI3_VARIABLES_H\n#define FMI3_VARIABLES_H\n\n"
        f"#define FMU3_TIME_VALUE_REFERENCE {TIME_VALUE_REFERENCE}u\n"
        f"#define FMU3_FIRST_EVENT_INDICATOR_VALUE_REFERENCE {FIRST_EVENT_INDICATOR_VALUE_REFERENCE}u\n\n"
        "#endif\n"
    ).encode()


def fmi3_edition(sources: FmuSources, event_indicators: Sequence[tuple[str, str]] = ()) -> FmuSources:
    """The FMI 3.0 edition of an FMU described by its FMI 2.0 ``sources``: the same model files and model
    identifier, the FMI 3.0 glue instead of the FMI 2.0 one, the translated description
    (:func:`fmi3_model_description`), ``buildDescription.xml`` and ``fmi3_variables.h``."""
    compiled = tuple(FMI3_GLUE if name == FMI2_GLUE else name for name in source_files_of(sources.model_description))
    if FMI3_GLUE not in compiled:
        raise ValueError(f"{sources.identifier}: its model description does not compile {FMI2_GLUE}")
    files = tuple((name, contents) for name, contents in sources.files if name != FMI2_GLUE)
    files += read_files(GLUE_DIR, (FMI3_GLUE,)) + read_files(Path(fmpy.__file__).parent / "c-code", FMI2_TYPE_HEADERS)
    files += ((VARIABLES_HEADER, variables_header()),
              (BUILD_DESCRIPTION, build_description(sources.identifier, compiled).encode()))
    return FmuSources(sources.identifier, fmi3_model_description(sources.model_description, event_indicators), files)
