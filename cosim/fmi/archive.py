"""Checks on an FMU archive before anything is extracted or loaded.

Loading an FMU runs its native code in this process, so an archive is refused early, with one
line naming the problem, if it is not a zip, has members that would land outside the extraction
folder, would expand to an unreasonable size, has a member whose bytes do not match their CRC-32 (a damaged
file), is neither FMI 2.0 nor FMI 3.0, or has no binary for this
platform (FMI 2.0 keeps it under ``binaries/linux64/``, FMI 3.0 under ``binaries/x86_64-linux/``).
"""

from __future__ import annotations

import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from xml.etree import ElementTree

import fmpy
from fmpy.model_description import ModelDescription

from cosim.base.errors import FmuArchiveError

MAX_UNCOMPRESSED_BYTES = 1 << 30  # 1 GiB: far above any plant model, far below a zip bomb
SUPPORTED = "FMI 2.0 and FMI 3.0 (model exchange or co-simulation)"
SHARED_LIBRARY_SUFFIX = {"linux64": ".so", "darwin64": ".dylib", "win64": ".dll", "win32": ".dll"}


@dataclass(frozen=True)
class CheckedFmu:
    """An FMU that passed the checks: its path and parsed model description."""

    path: Path
    model_description: ModelDescription
    interfaces: tuple[str, ...]  # "co-simulation" and/or "model-exchange" with a binary for this platform
    platforms: tuple[str, ...]

    @property
    def fmi_major(self) -> int:
        """2 or 3: which adapter drives the FMU (the archive's fmiVersion)."""
        return 3 if self.model_description.fmiVersion.startswith("3.") else 2


def _member_problem(name: str) -> str | None:
    if name.startswith(("/", "\\")) or (len(name) > 1 and name[1] == ":"):
        return "is an absolute path"
    parts = PurePosixPath(name.replace("\\", "/")).parts
    if ".." in parts:
        return "climbs out of the archive with '..'"
    return None


#: archives whose members' bytes were verified, by (path, size, modification time): a file that changes is read again
_VERIFIED: set[tuple[str, int, int]] = set()


def _check_member_bytes(path: Path, archive: zipfile.ZipFile) -> None:
    """Every member's bytes against the CRC-32 its zip directory records (``ZipFile.testzip``), so a damaged member --
    a shared library corrupted on disk or in transfer -- is refused naming it before anything is extracted or loaded
    (fmpy's extraction would fail half-way, leaving a partly unpacked FMU behind). Done once per unchanged file."""
    stat = path.stat()
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    if key in _VERIFIED:
        return
    try:
        damaged = archive.testzip()
    except zipfile.BadZipFile as error:
        raise FmuArchiveError(f"FMU {path} is a damaged zip archive ({error})") from None
    except (EOFError, OSError, zlib.error, NotImplementedError) as error:
        raise FmuArchiveError(f"FMU {path} has a member that cannot be read ({type(error).__name__}: {error})") from None
    if damaged is not None:
        raise FmuArchiveError(f"FMU {path} is damaged: member {damaged!r} does not match its CRC-32 checksum (the "
                              "archive was corrupted on disk or in transfer): copy or build the FMU again")
    _VERIFIED.add(key)


def _binary_platforms(names: list[str]) -> tuple[str, ...]:
    platforms = {
        parts[1]
        for parts in (n.split("/") for n in names)
        if len(parts) >= 3 and parts[0] == "binaries" and parts[2]
    }
    return tuple(sorted(platforms))


def check_fmu(path: str | Path, max_uncompressed_bytes: int = MAX_UNCOMPRESSED_BYTES) -> CheckedFmu:
    """Validate an FMU archive without extracting it; raise :class:`FmuArchiveError` naming the problem."""
    path = Path(path)
    if path.is_dir():
        raise FmuArchiveError(f"FMU {path} is a folder: expected a .fmu file (a zip archive)")
    if not path.is_file():
        raise FmuArchiveError(f"FMU {path} does not exist (expected a .fmu file)")
    if not zipfile.is_zipfile(path):
        raise FmuArchiveError(f"FMU {path} is not a zip archive (an FMU is a zip file with modelDescription.xml)")
    try:
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
            names = [info.filename for info in infos]
            for name in names:
                problem = _member_problem(name)
                if problem:
                    raise FmuArchiveError(f"FMU {path}: member {name!r} {problem}; refusing to extract it")
            total = sum(info.file_size for info in infos)
            if total > max_uncompressed_bytes:
                raise FmuArchiveError(
                    f"FMU {path} would expand to {total / 2**20:.0f} MiB, "
                    f"more than the limit of {max_uncompressed_bytes / 2**20:.0f} MiB"
                )
            if "modelDescription.xml" not in names:
                raise FmuArchiveError(f"FMU {path} has no modelDescription.xml at the top level")
            _check_member_bytes(path, archive)
            xml = archive.read("modelDescription.xml")
    except zipfile.BadZipFile as error:
        raise FmuArchiveError(f"FMU {path} is a damaged zip archive ({error})") from None
    except (EOFError, OSError) as error:
        raise FmuArchiveError(f"FMU {path} is truncated or unreadable ({error})") from None
    try:
        root = ElementTree.fromstring(xml)
    except ElementTree.ParseError as error:
        raise FmuArchiveError(f"FMU {path}: modelDescription.xml is not well-formed XML ({error})") from None
    version = root.get("fmiVersion")
    if version is None:
        raise FmuArchiveError(f"FMU {path}: modelDescription.xml has no fmiVersion attribute")
    if version != "2.0" and not version.startswith("3.0"):
        raise FmuArchiveError(f"FMU {path} is FMI {version}; the workbench supports {SUPPORTED}")
    try:
        model_description = fmpy.read_model_description(str(path), validate=False)
    except Exception as error:  # fmpy raises plain Exceptions for malformed descriptions
        message = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise FmuArchiveError(f"FMU {path}: malformed modelDescription.xml ({message})") from None
    platforms = _binary_platforms(names)
    suffix = SHARED_LIBRARY_SUFFIX.get(fmpy.platform, ".so")
    platform = fmpy.platform if version == "2.0" else fmpy.platform_tuple  # linux64 / x86_64-linux
    interfaces = []
    for label, interface in (("co-simulation", model_description.coSimulation),
                             ("model-exchange", model_description.modelExchange)):
        if interface is not None:
            if f"binaries/{platform}/{interface.modelIdentifier}{suffix}" in names:
                interfaces.append(label)
    if not interfaces and getattr(model_description, "scheduledExecution", None) is not None and not (
            model_description.coSimulation or model_description.modelExchange):
        raise FmuArchiveError(f"FMU {path} offers only Scheduled Execution (FMI 3.0), which the workbench does not "
                              "drive: expected co-simulation or model exchange")
    if not interfaces:
        declared = [label for label, i in (("co-simulation", model_description.coSimulation),
                                           ("model-exchange", model_description.modelExchange)) if i]
        have = ", ".join(platforms) if platforms else "none"
        raise FmuArchiveError(
            f"FMU {path} has no {platform} binary for its interfaces ({', '.join(declared) or 'none declared'}); "
            f"binaries present: {have}"
        )
    return CheckedFmu(path=path, model_description=model_description, interfaces=tuple(interfaces),
                      platforms=platforms)
