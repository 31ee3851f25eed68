"""Rewrite an FMU archive so that the same sources give the same bytes: ``python scripts/reproducible_fmu.py X.fmu``.

Exporting tools stamp every build: pythonfmu writes a fresh time-based ``guid`` (uuid1) and the build time
(``generationDateAndTime``) into modelDescription.xml, and the zip archive stores each member's modification time.
The workbench keys its cached designs and every result file on the FMU's SHA-256, so an FMU rebuilt by
``make examples`` would rewrite every committed result of its study although nothing in it changed. This rewrites the
archive in place: the members in name order, stored (no compressor version can change the bytes), with a fixed time
stamp and permissions; the ``guid`` replaced by a name-based UUID (uuid5) of the other members' contents; the
generation time dropped (FMI 2.0 and 3.0 make it optional). zipfile and re.sub do it; no library offers it.
"""

from __future__ import annotations

import hashlib
import re
import sys
import uuid
import zipfile
from pathlib import Path

FIXED_TIME = (1980, 1, 1, 0, 0, 0)


def reproducible(path: Path) -> str:
    """Rewrite ``path`` in place; returns its new guid."""
    with zipfile.ZipFile(path) as archive:
        members = {info.filename: archive.read(info) for info in archive.infolist() if not info.is_dir()}
    description = members["modelDescription.xml"].decode("utf-8")
    content = hashlib.sha256()
    for name in sorted(members):
        if name != "modelDescription.xml":
            content.update(name.encode() + b"\0" + hashlib.sha256(members[name]).digest())
    stripped = re.sub(r'\s(guid|instantiationToken)="[^"]*"', "", description, count=1)
    stripped = re.sub(r'\sgenerationDateAndTime="[^"]*"', "", stripped, count=1)
    content.update(stripped.encode())
    guid = "{" + str(uuid.uuid5(uuid.NAMESPACE_URL, content.hexdigest())) + "}"
    description = re.sub(r'((?:guid|instantiationToken)=")[^"]*(")', rf"\g<1>{guid}\g<2>", description, count=1)
    members["modelDescription.xml"] = re.sub(r'\sgenerationDateAndTime="[^"]*"', "", description, count=1).encode()
    temporary = path.with_name(path.name + ".tmp")
    with zipfile.ZipFile(temporary, "w", compression=zipfile.ZIP_STORED) as archive:
        for name in sorted(members):
            info = zipfile.ZipInfo(name, date_time=FIXED_TIME)
            info.compress_type = zipfile.ZIP_STORED
            info.external_attr = 0o644 << 16
            archive.writestr(info, members[name])
    temporary.replace(path)
    return guid


if __name__ == "__main__":
    if len(sys.argv) != 2 or not Path(sys.argv[1]).is_file():
        sys.exit("usage: python scripts/reproducible_fmu.py FMU (an existing FMU archive)")
    print(f"{sys.argv[1]}: guid {reproducible(Path(sys.argv[1]))}")
