"""Build ``BuckConverter.fmu`` from the C sources with fmpy's own compile (CMake + the C compiler).

The built FMU is cached under a name that contains a hash of the sources, the fmpy version and
the platform, so editing a source file triggers exactly one rebuild and users and tests never
build by hand. A source-only FMU (no binaries) is written beside it for tools that compile FMUs
themselves.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import fmpy
import fmpy.build
import fmpy.util

SOURCE_DIR = Path(__file__).parent / "sources"
MODEL_IDENTIFIER = "BuckConverter"
C_SOURCES = ("buck_model.c", "buck_model.h", "buck_variables.h", "fmi2_functions.c")
MODEL_DESCRIPTION = "modelDescription.xml"


class PlantBuildError(RuntimeError):
    """The FMU could not be compiled; the message names the log with the compiler output."""


def cache_dir() -> Path:
    """Folder for built FMUs: ``$BUCK_COSIM_CACHE`` or ``~/.cache/buck-cosim``."""
    configured = os.environ.get("BUCK_COSIM_CACHE")
    return Path(configured) if configured else Path.home() / ".cache" / "buck-cosim"


def source_digest() -> str:
    """Hash of everything that determines the binary: sources, fmpy version, platform."""
    digest = hashlib.sha256()
    digest.update(f"fmpy {fmpy.__version__} {fmpy.platform} {sys.platform}".encode())
    for name in (MODEL_DESCRIPTION, *C_SOURCES):
        digest.update(name.encode())
        digest.update((SOURCE_DIR / name).read_bytes())
    return digest.hexdigest()[:16]


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


def _stage_sources(unzipdir: Path) -> None:
    (unzipdir / "sources").mkdir(parents=True)
    shutil.copy2(SOURCE_DIR / MODEL_DESCRIPTION, unzipdir / MODEL_DESCRIPTION)
    for name in C_SOURCES:
        shutil.copy2(SOURCE_DIR / name, unzipdir / "sources" / name)


def _compile(unzipdir: Path, build_dir: Path, log_path: Path) -> None:
    """fmpy's compile with all warnings on and warnings as errors."""
    build_dir.mkdir()
    # fmpy calls `cmake`; pip installs it next to this interpreter, which may not be on PATH.
    path = os.environ.get("PATH", "")
    os.environ["PATH"] = str(Path(sys.executable).parent) + os.pathsep + path
    try:
        with _output_to(log_path):
            fmpy.build.build_platform_binary(
                unzipdir,
                build_dir=build_dir,
                all_warnings=True,
                cmake_options={"CMAKE_COMPILE_WARNING_AS_ERROR:BOOL": "ON"},
            )
    except (subprocess.CalledProcessError, OSError) as error:
        tail = log_path.read_text(errors="replace").strip().splitlines()[-15:]
        raise PlantBuildError(
            f"compiling {MODEL_IDENTIFIER}.fmu failed ({error}); compiler log: {log_path}\n" + "\n".join(tail)
        ) from None
    finally:
        os.environ["PATH"] = path


def stage_sources(unzipdir: Path) -> None:
    """Copy modelDescription.xml and sources/ into an FMU folder layout (to build or to adapt)."""
    _stage_sources(Path(unzipdir))


def _zip_into(unzipdir: Path, target: Path, compile_first: bool) -> Path:
    """Optionally compile a staged FMU folder (fmpy's CMake build), then zip it atomically to ``target``."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=".build-") as tmp:
        tmp_path = Path(tmp)
        if compile_first:
            _compile(Path(unzipdir), tmp_path / "build", target.parent / f"{target.stem}.build.log")
        staged = tmp_path / "staged.fmu"
        fmpy.util.create_zip_archive(staged, unzipdir)
        os.replace(staged, target)  # atomic: a concurrent build writes the same bytes
    return target


def compile_fmu(unzipdir: Path, target: Path) -> Path:
    """Compile a staged FMU folder with fmpy's CMake build and zip it atomically to ``target``."""
    return _zip_into(unzipdir, target, compile_first=True)


def _cached(suffix: str, compile_first: bool, force: bool) -> Path:
    target = cache_dir() / f"{MODEL_IDENTIFIER}-{source_digest()}{suffix}.fmu"
    if target.is_file() and not force:
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=".stage-") as tmp:
        unzipdir = Path(tmp) / MODEL_IDENTIFIER
        _stage_sources(unzipdir)
        return _zip_into(unzipdir, target, compile_first)


def fmu_path(force: bool = False) -> Path:
    """Path of the compiled BuckConverter FMU (model exchange + co-simulation), building it if needed."""
    return _cached("", compile_first=True, force=force)


def source_fmu_path(force: bool = False) -> Path:
    """Path of a source-only FMU (modelDescription.xml + sources/) that other tools can compile."""
    return _cached("-source", compile_first=False, force=force)


def export_fmus(output_dir: Path, force: bool = False) -> tuple[Path, Path]:
    """Copy the compiled and the source FMU to ``output_dir`` as BuckConverter.fmu / BuckConverter-source.fmu."""
    output_dir.mkdir(parents=True, exist_ok=True)
    binary = output_dir / f"{MODEL_IDENTIFIER}.fmu"
    source = output_dir / f"{MODEL_IDENTIFIER}-source.fmu"
    shutil.copyfile(fmu_path(force), binary)
    shutil.copyfile(source_fmu_path(force), source)
    return binary, source
