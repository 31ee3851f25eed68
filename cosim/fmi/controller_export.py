"""Controller FMUs: a workbench controller as an FMI 2.0 (or 3.0) co-simulation unit built from C.

:func:`controller_sources` stages what the FMU is compiled from: the shared FMI 2.0 glue of the
plant FMU (``plant_fmu/glue``), the hand-written algorithms of ``controllers/c``, the controller
model (``controller_fmu/controller_fmu.c``: variables and the sample clock) and one generated
header of data (:func:`controllers.codegen.config_header`). :func:`export_controller` builds it
with the plant's fmpy-compile helper and cache and writes ``NAME.fmu`` and ``NAME-source.fmu``.

The variables carry the workbench's role names: inputs ``reference``, ``measured_output_voltage``,
``measured_inductor_current``, ``measured_load_current``, ``input_voltage``; output
``duty_cycle`` (which depends directly on the inputs at a sample instant); parameters
``sample_period``, ``duty_min``, ``duty_max`` (and ``kp``, ``ki`` for the PI, which may be set
before initialisation; a predictive controller's are fixed by its generation).

``precision="float32"`` builds the FMU from the float32 build of the twins (``buckc_real`` =
float, ``controllers/c/buckc.h``; the PI, the explicit NNPC, the current-mode controller and the
compensator have one): the generated header holds float data, and every compiled file is a two-line
wrapper ``f32_NAME.c`` that defines ``BUCKC_FLOAT32`` and includes ``NAME.c`` (FMI 2.0 source FMUs
have no place for compiler flags, so the definition travels in a source file that any FMI tool
compiles as it is).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from xml.etree import ElementTree

from controllers.codegen import (
    KIND_ADAPTIVE,
    KIND_COMPENSATOR,
    KIND_CURRENT_MODE,
    KIND_EXPLICIT,
    KIND_PI,
    config_header,
    controller_kind,
    header_guid,
)
from controllers.native import FLOAT32_SOURCES, check_precision
from controllers.native import SOURCE_DIR as ALGORITHM_DIR
from plant_fmu.build import check_fmi_version, export
from plant_fmu.fmi3 import fmi3_edition
from plant_fmu.fmu_sources import (
    REAL_CO_SIMULATION_ONLY,
    FmuSources,
    co_simulation_description_root,
    glue_files,
    model_description_text,
    read_files,
    real_co_simulation_only_files,
)

MODEL_DIR = Path(__file__).parent / "controller_fmu"
MODEL_FILES = ("controller_fmu.c", "controller_variables.h")
ALGORITHM_FILES = ("buckc.c", "buckc.h", "buckc_pair.h", "buckc_tanh.h", "pi.c", "pi.h", "nn_model.c", "nn_model.h",
                   "predictors.c", "predictors.h", "predictive.c", "predictive.h", "load_estimate.c", "load_estimate.h",
                   "explicit_policy.c", "explicit_policy.h", "current_mode.c", "current_mode.h", "compensator.c",
                   "compensator.h", "box_qp.c", "box_qp.h",
                   "adaptation.h")  # buckc.c's struct sizes include it; the FMU does not run the adaptation
#: compiled files (the glue and its Real co-simulation-only defaults, the model, the algorithms), in
#: modelDescription.xml's SourceFiles
COMPILED = ("fmi2_glue.c", REAL_CO_SIMULATION_ONLY, "controller_fmu.c", "buckc.c", "pi.c", "nn_model.c",
            "predictors.c", "predictive.c", "load_estimate.c", "explicit_policy.c", "current_mode.c", "compensator.c",
            "box_qp.c")
#: the float32 FMU: the files with a float32 build that its controllers need, each through a
#: wrapper that defines BUCKC_FLOAT32 (the glue does not include buckc.h: compiled as it is)
FLOAT32_ALGORITHMS = tuple(f for f in ("buckc.c", "pi.c", "load_estimate.c", "explicit_policy.c",
                                       "current_mode.c", "compensator.c")
                           if f in FLOAT32_SOURCES)
FLOAT32_HEADERS = ("buckc.h", "buckc_pair.h", "buckc_tanhf.h", "pi.h", "nn_model.h", "load_estimate.h",
                   "explicit_policy.h", "current_mode.h", "compensator.h")
FLOAT32_COMPILED = ("fmi2_glue.c", REAL_CO_SIMULATION_ONLY, "f32_controller_fmu.c",
                    *(f"f32_{f}" for f in FLOAT32_ALGORITHMS))


@dataclass(frozen=True)
class Variable:
    name: str
    value_reference: int
    causality: str
    variability: str
    unit: str
    description: str
    start: str | None = None
    pi_only: bool = False


#: the controller FMUs' variables; controller_variables.h numbers them the same way (tested)
VARIABLES = (
    Variable("reference", 0, "input", "continuous", "V", "output-voltage reference", "0"),
    Variable("measured_output_voltage", 1, "input", "continuous", "V", "what the output-voltage sensor reads", "0"),
    Variable("measured_inductor_current", 2, "input", "continuous", "A", "what the inductor-current sensor reads",
             "0"),
    Variable("measured_load_current", 3, "input", "continuous", "A",
             "what the load-current sensor reads (NaN: no such sensor; the load is then estimated from iL)", "0"),
    Variable("input_voltage", 4, "input", "continuous", "V", "supply voltage", None),
    Variable("duty_cycle", 5, "output", "discrete", "1", "duty cycle in effect (held between sample instants)"),
    Variable("sample_period", 6, "parameter", "fixed", "s", "controller sample period Ts: samples at t0 + k Ts"),
    Variable("duty_min", 7, "parameter", "fixed", "1", "lower duty limit"),
    Variable("duty_max", 8, "parameter", "fixed", "1", "upper duty limit"),
    Variable("kp", 9, "parameter", "fixed", "1/V", "proportional gain", pi_only=True),
    Variable("ki", 10, "parameter", "fixed", "1/(V.s)", "integral gain", pi_only=True),
)
UNITS = {"V": {"kg": "1", "m": "2", "s": "-3", "A": "-1"}, "A": {"A": "1"}, "1": {}, "s": {"s": "1"},
         "1/V": {"kg": "-1", "m": "-2", "s": "3", "A": "1"}, "1/(V.s)": {"kg": "-1", "m": "-2", "s": "2", "A": "1"}}


def model_description(identifier: str, name: str, guid: str, description: str, start_values: dict[str, float],
                      pi: bool, compiled: tuple[str, ...] = COMPILED) -> str:
    """``modelDescription.xml`` of a controller FMU (co-simulation only)."""
    root = co_simulation_description_root(identifier, guid, description,
                                          "buck-cosim export-controller (hand-written C, generated data)", compiled)
    units = ElementTree.SubElement(root, "UnitDefinitions")
    for unit, base in UNITS.items():
        element = ElementTree.SubElement(units, "Unit", {"name": unit})
        if base:
            ElementTree.SubElement(element, "BaseUnit", base)
    # a master's default communication step: one sample period (any step works: a step spanning several
    # sample instants takes each with the inputs held, controller_fmu.c)
    ElementTree.SubElement(root, "DefaultExperiment", {"startTime": "0", "stepSize": start_values["sample_period"]})
    variables = ElementTree.SubElement(root, "ModelVariables")
    listed = [v for v in VARIABLES if pi or not v.pi_only]
    for v in listed:
        attributes = {"name": v.name, "valueReference": str(v.value_reference), "causality": v.causality,
                      "variability": v.variability, "description": v.description}
        if v.causality == "output":
            attributes["initial"] = "calculated"
        element = ElementTree.SubElement(variables, "ScalarVariable", attributes)
        real = {"unit": v.unit}
        start = start_values.get(v.name, v.start)
        if v.causality != "output" and start is not None:
            real["start"] = str(start)
        ElementTree.SubElement(element, "Real", real)
    structure = ElementTree.SubElement(root, "ModelStructure")
    outputs = ElementTree.SubElement(structure, "Outputs")
    index = {v.name: str(i + 1) for i, v in enumerate(listed)}
    inputs = " ".join(index[v.name] for v in listed if v.causality == "input")
    ElementTree.SubElement(outputs, "Unknown", {"index": index["duty_cycle"], "dependencies": inputs,
                                                "dependenciesKind": " ".join("dependent" for _ in inputs.split())})
    initial = ElementTree.SubElement(structure, "InitialUnknowns")
    ElementTree.SubElement(initial, "Unknown", {"index": index["duty_cycle"]})
    return model_description_text(root)


def controller_sources(controller, identifier: str, precision: str = "float64") -> FmuSources:
    """What the FMU of a Python PI, predictive, explicit-policy, current-mode or compensator controller is built from (``precision``:
    the build of the twins it computes with; ValueError for a controller without a float32 build)."""
    kind = controller_kind(controller)
    if kind == KIND_ADAPTIVE:
        raise ValueError(f"{controller.name} has no controller FMU: the adaptive NNPC's C twin (controllers/c/"
                         "adaptation.c) runs in the workbench and its benchmark harness, not in controller_fmu.c")
    header = config_header(controller, name=identifier, precision=check_precision(precision))
    pi = kind == KIND_PI
    low, high = controller.duty_limits
    starts = {"sample_period": repr(float(controller.sample_period)), "duty_min": repr(float(low)),
              "duty_max": repr(float(high)),
              "input_voltage": repr(float(getattr(controller, "nominal_input_voltage", 48.0)))}
    if pi:
        starts.update(kp=repr(float(controller.kp)), ki=repr(float(controller.ki)))
    algorithm = {KIND_PI: "PI", KIND_EXPLICIT: "explicit policy", KIND_CURRENT_MODE: "average-current-mode control",
                 KIND_COMPENSATOR: "discrete compensator"}.get(kind, "predictive")
    build = "" if precision == "float64" else f", {precision} build"
    description = (f"{controller.name} controller of the buck-cosim workbench, sampled every "
                   f"{controller.sample_period:.6g} s ({algorithm}; hand-written C99, generated configuration{build})")
    if precision == "float64":
        algorithms, compiled, wrappers = ALGORITHM_FILES, COMPILED, ()
    else:
        algorithms, compiled = FLOAT32_ALGORITHMS + FLOAT32_HEADERS, FLOAT32_COMPILED
        wrappers = tuple((f"f32_{name}", float32_wrapper(name).encode())
                         for name in ("controller_fmu.c", *FLOAT32_ALGORITHMS))
    md = model_description(identifier, controller.name, header_guid(header), description, starts, pi, compiled)
    files = (glue_files() + real_co_simulation_only_files() + read_files(MODEL_DIR, MODEL_FILES)
             + read_files(ALGORITHM_DIR, tuple(sorted(algorithms))) + wrappers)
    return FmuSources(identifier, md, files + (("controller_config.h", header.encode()),))


def float32_wrapper(name: str) -> str:
    """The compiled file of a float32 FMU for ``name``: the one source, with buckc_real = float."""
    return (f"/* Generated by buck-cosim (export-controller --precision float32): {name} in the float32 build. */\n"
            f'#define BUCKC_FLOAT32 1\n#include "{name}"\n')


def export_controller(controller, out: Path, force: bool = False, precision: str = "float64",
                      fmi_version: int = 2) -> tuple[Path, Path]:
    """Build the controller's FMU and write ``out`` (``NAME.fmu``) and ``NAME-source.fmu`` beside it:
    FMI 2.0, or (``fmi_version`` 3) its FMI 3.0 edition -- the same model and algorithm code, the FMI 3.0
    glue, the description translated by :func:`plant_fmu.fmi3.fmi3_model_description`
    (``precision="float32"``: from the float32 build of the twins)."""
    out = Path(out)
    identifier = _identifier(out.stem)
    sources = controller_sources(controller, identifier, precision)
    if check_fmi_version(fmi_version) == 3:
        sources = fmi3_edition(sources)
    return export(sources, out, out.with_name(f"{out.stem}-source.fmu"), force)


def _identifier(stem: str) -> str:
    """A C identifier from a file name: the FMU's model identifier names its shared library."""
    text = "".join(c if c.isalnum() or c == "_" else "_" for c in stem)
    return text if text and not text[0].isdigit() else f"controller_{text}"
