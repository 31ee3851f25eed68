"""Digests: the SHA-256 of bytes, of files, and of JSON-ready data in a canonical form.

They identify what a result depends on (a sweep run's recipes, a cached design's inputs), so the
same inputs always give the same hex string on every machine.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path


def digest(*parts: bytes | str) -> str:
    """SHA-256 (hex) of the parts; of one part, the plain SHA-256 of its bytes (what ``sha256sum`` prints)."""
    h = hashlib.sha256()
    for i, part in enumerate(parts):
        if i:
            h.update(b"\0")  # a separator, so ("ab", "c") and ("a", "bc") differ
        h.update(part.encode() if isinstance(part, str) else part)
    return h.hexdigest()


def canonical(value) -> str:
    """JSON text with sorted keys: the same data always hashes the same (floats as Python's repr)."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)


_FILE_DIGESTS: dict[tuple[str, int, int], str] = {}


def file_sha256(path: Path) -> str:
    """The SHA-256 (hex) of a file's bytes, what ``sha256sum`` prints. Remembered per process for
    the same path, size and modification time, so asking again costs one ``stat``."""
    path = Path(path).resolve()
    stat = os.stat(path)
    key = (str(path), stat.st_size, stat.st_mtime_ns)
    if key not in _FILE_DIGESTS:
        h = hashlib.sha256()
        with open(path, "rb") as file:
            for block in iter(lambda: file.read(1 << 20), b""):
                h.update(block)
        _FILE_DIGESTS[key] = h.hexdigest()
    return _FILE_DIGESTS[key]
