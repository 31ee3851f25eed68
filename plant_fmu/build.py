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

The archives are reproducible (:func:`zip_folder`): the same sources and toolchain give the same
FMU bytes on every build and machine, so the SHA-256 of the plant FMU that the design keys and the
runs' metadata record is the same in a fresh clone as in the committed results.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import fmpy
import fmpy.build

from plant_fmu.fmi3 import fmi3_edition
from plant_fmu.fmu_sources import (
    CMAKE_OPTIONS,
    MODEL_DESCRIPTION,
    SOURCE_DIR,
    FmuSources,
    glue_files,
    read_files,
)

MODEL_IDENTIFIER = "BuckConverter"
PLANT_FILES = ("buck_model.c", "buck_model.h", "buck_variables.h", "buck_fmu.c")
#: the FMI versions the workbench builds its FMUs for (one glue layer each: glue/fmi2_glue.c, glue/fmi3_glue.c)
FMI_VERSIONS = (2, 3)
#: the plant's event indicators (buck_event_indicators in buck_model.c), named for FMI 3.0, which makes them variables
PLANT_EVENT_INDICATORS = (
    ("diode_event_indicator", "Diode zero crossing: iL while the diode conducts, the unblocking margin while it "
                              "blocks"),
    ("conduction_boundary_event_indicator", "CCM/DCM boundary of the averaged model (1 in switched mode)"),
)


#: every member of a workbench archive (FMU, SSP) gets this date, so the same content gives the same bytes
ZIP_DATE = (1980, 1, 1, 0, 0, 0)


class PlantBuildError(RuntimeError):
    """An FMU could not be compiled; the message names the log with the compiler output."""


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


def zip_folder(folder: Path, target: Path) -> None:
    """Zip ``folder``'s tree into ``target`` reproducibly: members in sorted order, folders before the files
    in them, each dated :data:`ZIP_DATE` with fixed permissions (0755 folders, 0644 files, the execute bit
    kept), deflated at zlib's default level.

    Hand-written rather than ``fmpy.util.create_zip_archive``, which stamps each member with its file's
    modification time and takes a folder's files in ``os.walk`` order: every build of the same sources gave
    another archive, so the plant FMU's SHA-256 -- part of the PI tuning's design key and of every run's
    metadata -- differed in each fresh clone from the committed results' (measured: two builds of the plant
    in two folders, member bytes identical, archives not)."""
    folder = Path(folder)
    with zipfile.ZipFile(target, "w") as archive:
        for path in sorted(folder.rglob("*"), key=lambda p: p.relative_to(folder).parts):
            name = path.relative_to(folder).as_posix()
            if path.is_dir():
                info = zipfile.ZipInfo(name + "/", ZIP_DATE)
                info.external_attr = (0o40755 << 16) | 0x10  # a folder (MS-DOS directory flag too)
                archive.writestr(info, b"")
            elif path.is_file():
                info = zipfile.ZipInfo(name, ZIP_DATE)
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = (0o100755 if os.access(path, os.X_OK) else 0o100644) << 16
                archive.writestr(info, path.read_bytes())


def _zip_into(unzipdir: Path, target: Path, compile_first: bool, identifier: str) -> Path:
    """Optionally compile a staged FMU folder (fmpy's CMake build), then zip it atomically to ``target``."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=".build-") as tmp:
        tmp_path = Path(tmp)
        if compile_first:
            _compile(Path(unzipdir), tmp_path / "build", target.parent / f"{target.stem}.build.log", identifier)
        staged = tmp_path / "staged.fmu"
        zip_folder(Path(unzipdir), staged)
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
