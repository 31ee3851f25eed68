"""What an FMU of the workbench is built from: the shared FMI 2.0 glue, a model's files and its
``modelDescription.xml`` (:class:`FmuSources`), and the helpers that generate a description.

Below both :mod:`plant_fmu.build` (compiles and caches) and :mod:`plant_fmu.fmi3` (derives the FMI 3.0
edition), which each import it and not each other's internals.
"""

from __future__ import annotations

import hashlib
import sys
from dataclasses import dataclass
from pathlib import Path
from xml.etree import ElementTree

import fmpy

PACKAGE_DIR = Path(__file__).parent
GLUE_DIR = PACKAGE_DIR / "glue"
SOURCE_DIR = PACKAGE_DIR / "sources"
GLUE_FILES = ("fmi2_glue.c", "fmu_model.h")
#: the model interface's Integer and model-exchange functions for a co-simulation-only model with Real
#: variables only (the controller and scenario FMUs): compiled beside the glue and the model
REAL_CO_SIMULATION_ONLY = "real_co_simulation_only.c"
MODEL_DESCRIPTION = "modelDescription.xml"
#: warnings as errors; no fused multiply-add (the C twins must round like the Python references)
#: how plant_fmu.build.zip_folder lays an archive out; in the cache key, so FMUs zipped another way are rebuilt
ARCHIVE_LAYOUT = "zip: members sorted, dated 1980-01-01, fixed permissions, deflated"
CMAKE_OPTIONS = {"CMAKE_COMPILE_WARNING_AS_ERROR:BOOL": "ON", "CMAKE_C_FLAGS:STRING": "-ffp-contract=off"}


@dataclass(frozen=True)
class FmuSources:
    """What an FMU is built from: ``files`` are (name, contents) pairs staged under ``sources/``."""

    identifier: str
    model_description: str
    files: tuple[tuple[str, bytes], ...]

    def digest(self) -> str:
        """Hash of everything that determines the archive: sources, fmpy version, platform, flags and the archive's
        layout (:data:`ARCHIVE_LAYOUT`)."""
        h = hashlib.sha256()
        h.update(f"fmpy {fmpy.__version__} {fmpy.platform} {sys.platform} {sorted(CMAKE_OPTIONS.items())}".encode())
        h.update(ARCHIVE_LAYOUT.encode())
        h.update(self.identifier.encode())
        h.update(self.model_description.encode())
        for name, contents in sorted(self.files):
            h.update(name.encode())
            h.update(contents)
        return h.hexdigest()[:16]

    def stage(self, unzipdir: Path) -> None:
        """Write ``modelDescription.xml`` and ``sources/`` into an FMU folder layout."""
        unzipdir = Path(unzipdir)
        (unzipdir / "sources").mkdir(parents=True)
        (unzipdir / MODEL_DESCRIPTION).write_text(self.model_description, encoding="utf-8")
        for name, contents in self.files:
            (unzipdir / "sources" / name).write_bytes(contents)


def read_files(folder: Path, names: tuple[str, ...]) -> tuple[tuple[str, bytes], ...]:
    return tuple((name, (Path(folder) / name).read_bytes()) for name in names)


def glue_files() -> tuple[tuple[str, bytes], ...]:
    """The shared FMI 2.0 glue every FMU of the workbench is compiled with."""
    return read_files(GLUE_DIR, GLUE_FILES)


def real_co_simulation_only_files() -> tuple[tuple[str, bytes], ...]:
    """:data:`REAL_CO_SIMULATION_ONLY`, for the sources of a co-simulation-only model with Real variables only
    (list it in the model description's SourceFiles too)."""
    return read_files(GLUE_DIR, (REAL_CO_SIMULATION_ONLY,))


#: what the shared glue implements for co-simulation: every FMU built on it declares these capabilities
GLUE_CO_SIMULATION_CAPABILITIES = {"canHandleVariableCommunicationStepSize": "true",
                                   "canNotUseMemoryManagementFunctions": "true", "canGetAndSetFMUstate": "true",
                                   "canSerializeFMUstate": "true"}


def co_simulation_description_root(identifier: str, guid: str, description: str, generation_tool: str,
                                   compiled: tuple[str, ...]) -> ElementTree.Element:
    """The start of a generated ``modelDescription.xml`` of a co-simulation-only FMU built on the shared glue:
    ``fmiModelDescription`` (FMI 2.0, model name ``identifier``, structured names, no event indicators) holding
    its ``CoSimulation`` element (the glue's capabilities; ``compiled``, the files compiled, as its SourceFiles).
    The caller adds units, variables and the model structure, then writes it with :func:`model_description_text`."""
    root = ElementTree.Element("fmiModelDescription", {
        "fmiVersion": "2.0", "modelName": identifier, "guid": guid, "description": description,
        "generationTool": generation_tool, "variableNamingConvention": "structured",
        "numberOfEventIndicators": "0"})
    cs = ElementTree.SubElement(root, "CoSimulation", {"modelIdentifier": identifier,
                                                       **GLUE_CO_SIMULATION_CAPABILITIES})
    files = ElementTree.SubElement(cs, "SourceFiles")
    for file in compiled:
        ElementTree.SubElement(files, "File", {"name": file})
    return root


def model_description_text(root: ElementTree.Element) -> str:
    """A model description's element tree as the text of ``modelDescription.xml`` (UTF-8 declaration,
    indented by two spaces, a final newline)."""
    ElementTree.indent(root, space="  ")
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ElementTree.tostring(root, encoding="unicode") + "\n"
