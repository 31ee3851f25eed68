"""Files that travel to a sweep's workers as bytes (a plant or controller FMU), written once per process.

Each worker process keeps one private folder (removed at exit) and writes each file once per digest
into it; the worker (:mod:`cosim.design.sweeps.worker`) and the controller designs
(:mod:`cosim.design.sweeps.designs`) both use it, so neither imports the other for it.
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
import threading
from pathlib import Path

_files_lock = threading.Lock()
_files: dict[str, Path] = {}
_folder: Path | None = None


def _process_folder() -> Path:
    global _folder
    if _folder is None or not _folder.is_dir():
        _folder = Path(tempfile.mkdtemp(prefix=f"buck-cosim-worker-{os.getpid()}-"))
        atexit.register(shutil.rmtree, _folder, True)
    return _folder


def process_file(name: str, blob: bytes, key: str) -> Path:
    """This process's copy of a file that travelled as bytes (``key``: their SHA-256), written once
    per digest into the process's private folder (removed at exit) under its own ``name``."""
    with _files_lock:
        path = _files.get(key)
        if path is None or not path.is_file():
            folder = _process_folder() / key[:16]
            folder.mkdir(exist_ok=True)
            path = folder / name
            tmp = folder / f".{name}.tmp"
            tmp.write_bytes(blob)
            os.replace(tmp, path)
            _files[key] = path
        return path
