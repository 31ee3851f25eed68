"""Build the workbench's FMUs from C sources with fmpy's own compile (CMake + the C compiler).

Every FMU -- the buck plant, the controllers, the scenario sources -- is the shared FMI 2.0 glue
(``plant_fmu/glue``) plus one model, described by an :class:`FmuSources`: its model identifier,
its ``modelDescription.xml`` and its source files. Its FMI 3.0 edition (:func:`fmi3_edition`,
``plant_fmu/fmi3.py``) is the same model behind the FMI 3.0 glue, its description derived from the
FMI 2.0 one. :func:`build` stages them in an FMU folder,
compiles them with ``fmpy.build.build_platform_binary`` (warnings on, warnings as errors) and
zips the result; :func:`build_source_fmu` zips the same folder without compiling, for tools that
compile FMUs themselves. Both are cached under a name that holds a hash of everything that
determines the binary (sources, model description, fmpy version, platform, flags), so editing a
source file triggers exactly one rebuild and users and tests never build by hand.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from xml.etree import ElementTree

import fmpy
import fmpy.build
import fmpy.util

PACKAGE_DIR = Path(__file__).parent
GLUE_DIR = PACKAGE_DIR / "glue"
SOURCE_DIR = PACKAGE_DIR / "sources"
MODEL_IDENTIFIER = "BuckConverter"
GLUE_FILES = ("fmi2_glue.c", "fmu_model.h")
#: the model interface's Integer and model-exchange functions for a co-simulation-only model with Real
#: variables only (the controller and scenario FMUs): compiled beside the glue and the model
REAL_CO_SIMULATION_ONLY = "real_co_simulation_only.c"
PLANT_FILES = ("buck_model.c", "buck_model.h", "buck_variables.h", "buck_fmu.c")
MODEL_DESCRIPTION = "modelDescription.xml"
#: the FMI versions the workbench builds its FMUs for (one glue layer each: glue/fmi2_glue.c, glue/fmi3_glue.c)
FMI_VERSIONS = (2, 3)
#: the plant's event indicators (buck_event_indicators in buck_model.c), named for FMI 3.0, which makes them variables
PLANT_EVENT_INDICATORS = (
    ("diode_event_indicator", "Diode zero crossing: iL while the diode conducts, the unblocking margin while it "
                              "blocks"),
    ("conduction_boundary_event_indicator", "CCM/DCM boundary of the averaged model (1 in switched mode)"),
)
#: warnings as errors; no fused multiply-add (the C twins must round like the Python references)
CMAKE_OPTIONS = {"CMAKE_COMPILE_WARNING_AS_ERROR:BOOL": "ON", "CMAKE_C_FLAGS:STRING": "-ffp-contract=off"}


class PlantBuildError(RuntimeError):
    """An FMU could not be compiled; the message names the log with the compiler output."""


@dataclass(frozen=True)
class FmuSources:
    """What an FMU is built from: ``files`` are (name, contents) pairs staged under ``sources/``."""

    identifier: str
    model_description: str
    files: tuple[tuple[str, bytes], ...]

    def digest(self) -> str:
        """Hash of everything that determines the binary: sources, fmpy version, platform, flags."""
        h = hashlib.sha256()
        h.update(f"fmpy {fmpy.__version__} {fmpy.platform} {sys.platform} {sorted(CMAKE_OPTIONS.items())}".encode())
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


def plant_sources(fmi_version: int = 2) -> FmuSources:
    """The buck converter plant FMU: FMI 2.0, or its FMI 3.0 edition (the same model code, the FMI 3.0 glue)."""
    sources = FmuSources(MODEL_IDENTIFIER, (SOURCE_DIR / MODEL_DESCRIPTION).read_text(encoding="utf-8"),
                         glue_files() + read_files(SOURCE_DIR, PLANT_FILES))
    return sources if check_fmi_version(fmi_version) == 2 else fmi3_edition(sources, PLANT_EVENT_INDICATORS)


def check_fmi_version(fmi_version: int) -> int:
    """``fmi_version`` if the workbench builds FMUs of that FMI version (2 or 3), else a ValueError."""
    if fmi_version not in FMI_VERSIONS:
        raise ValueError(f"FMI version {fmi_version!r} is not built: expected one of {', '.join(map(str, FMI_VERSIONS))}")
    return fmi_version


def fmi3_edition(sources: FmuSources, event_indicators=()) -> FmuSources:
    """:func:`plant_fmu.fmi3.fmi3_edition`: the FMI 3.0 edition of an FMU's sources."""
    from plant_fmu import fmi3

    return fmi3.fmi3_edition(sources, event_indicators)


def cache_dir() -> Path:
    """Folder for built FMUs: ``$BUCK_COSIM_CACHE`` or ``~/.cache/buck-cosim``."""
    configured = os.environ.get("BUCK_COSIM_CACHE")
    return Path(configured) if configured else Path.home() / ".cache" / "buck-cosim"


def source_digest() -> str:
    """Hash of the plant FMU's sources (see :meth:`FmuSources.digest`)."""
    return plant_sources().digest()


@contextlib.contextmanager
def _output_to(log_path: Path):
    """Send this process's stdout/stderr (and its children's) to a log file for a while."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(log_path, "wb") as log:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def _compile(unzipdir: Path, build_dir: Path, log_path: Path, identifier: str) -> None:
    """fmpy's compile with all warnings on and warnings as errors."""
    build_dir.mkdir()
    # fmpy calls `cmake`; pip installs it next to this interpreter, which may not be on PATH.
    path = os.environ.get("PATH", "")
    os.environ["PATH"] = str(Path(sys.executable).parent) + os.pathsep + path
    try:
        with _output_to(log_path):
            fmpy.build.build_platform_binary(unzipdir, build_dir=build_dir, all_warnings=True,
                                             cmake_options=dict(CMAKE_OPTIONS))
    except (subprocess.CalledProcessError, OSError) as error:
        tail = log_path.read_text(errors="replace").strip().splitlines()[-15:]
        raise PlantBuildError(
            f"compiling {identifier}.fmu failed ({error}); compiler log: {log_path}\n" + "\n".join(tail)
        ) from None
    finally:
        os.environ["PATH"] = path


def _zip_into(unzipdir: Path, target: Path, compile_first: bool, identifier: str) -> Path:
    """Optionally compile a staged FMU folder (fmpy's CMake build), then zip it atomically to ``target``."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=".build-") as tmp:
        tmp_path = Path(tmp)
        if compile_first:
            _compile(Path(unzipdir), tmp_path / "build", target.parent / f"{target.stem}.build.log", identifier)
        staged = tmp_path / "staged.fmu"
        fmpy.util.create_zip_archive(staged, unzipdir)
        os.replace(staged, target)  # atomic: a concurrent build writes the same bytes
    return target


def stage_sources(unzipdir: Path) -> None:
    """The plant FMU's folder layout (modelDescription.xml and sources/), to build or to adapt."""
    plant_sources().stage(Path(unzipdir))


def compile_fmu(unzipdir: Path, target: Path, identifier: str = MODEL_IDENTIFIER) -> Path:
    """Compile a staged FMU folder with fmpy's CMake build and zip it atomically to ``target``."""
    return _zip_into(unzipdir, target, compile_first=True, identifier=identifier)


def _cached(sources: FmuSources, suffix: str, compile_first: bool, force: bool) -> Path:
    target = cache_dir() / f"{sources.identifier}-{sources.digest()}{suffix}.fmu"
    if target.is_file() and not force:
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=".stage-") as tmp:
        unzipdir = Path(tmp) / sources.identifier
        sources.stage(unzipdir)
        return _zip_into(unzipdir, target, compile_first, sources.identifier)


def build(sources: FmuSources, force: bool = False) -> Path:
    """The compiled FMU (this platform's binary + its sources) of ``sources``, from the cache or built now."""
    return _cached(sources, "", compile_first=True, force=force)


def build_source_fmu(sources: FmuSources, force: bool = False) -> Path:
    """A source-only FMU (modelDescription.xml + sources/) that other tools can compile."""
    return _cached(sources, "-source", compile_first=False, force=force)


def fmu_path(force: bool = False, fmi_version: int = 2) -> Path:
    """Path of the compiled BuckConverter FMU (model exchange + co-simulation, FMI 2.0 or 3.0), building it
    if needed."""
    return build(plant_sources(fmi_version), force)


def source_fmu_path(force: bool = False, fmi_version: int = 2) -> Path:
    """Path of the plant's source-only FMU."""
    return build_source_fmu(plant_sources(fmi_version), force)


def export(sources: FmuSources, binary: Path, source: Path, force: bool = False) -> tuple[Path, Path]:
    """Copy the compiled and the source FMU of ``sources`` to ``binary`` and ``source`` (atomically)."""
    for built, target in ((build(sources, force), binary), (build_source_fmu(sources, force), source)):
        Path(target).parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(target).with_name(f".{Path(target).name}.tmp-{os.getpid()}")
        shutil.copyfile(built, tmp)
        os.replace(tmp, target)
    return Path(binary), Path(source)


def export_fmus(output_dir: Path, force: bool = False, fmi_version: int = 2) -> tuple[Path, Path]:
    """Copy the compiled and the source plant FMU to ``output_dir`` as BuckConverter.fmu / BuckConverter-source.fmu
    (``fmi_version`` 3: the FMI 3.0 edition, under the same names)."""
    output_dir = Path(output_dir)
    return export(plant_sources(fmi_version), output_dir / f"{MODEL_IDENTIFIER}.fmu",
                  output_dir / f"{MODEL_IDENTIFIER}-source.fmu", force)
