"""Atomic file writes: a crash, a full disk or Ctrl-C never leaves a half-written file behind.

Every file the workbench writes goes through :func:`atomic_write`: written under a temporary
name in the target folder, then renamed onto the target (``os.replace`` is atomic within one
file system), so a reader sees either the old file or the complete new one.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Callable

#: temporary names look like ``.<name>.tmp-<pid>``; stale ones can be swept with this glob
TEMPORARY_GLOB = ".*.tmp-*"


def temporary_name(path: Path) -> Path:
    """The temporary sibling ``path`` is written under before the rename."""
    path = Path(path)
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def atomic_write(path: Path, write: Callable[[Path], object]) -> Path:
    """Call ``write(tmp_path)`` and rename the result onto ``path`` (same folder, so the rename is atomic)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def atomic_write_text(path: Path, text: str) -> Path:
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def remove_temporary_files(folder: Path) -> None:
    """Delete the temporary files of writes that a terminated process left unfinished."""
    for stale in Path(folder).rglob(TEMPORARY_GLOB):
        stale.unlink(missing_ok=True)


def _finite(value):
    """``value`` with every non-finite float replaced by None (JSON null): JSON has no NaN or
    Infinity, and a file that contains them is not JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def _plain(value):
    """What ``json`` cannot write itself: numpy scalars, paths, sets, tuples (anything else as text)."""
    if hasattr(value, "item") and callable(value.item):  # numpy scalars
        return value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (set, tuple)):
        return list(value)
    return str(value)


def json_text(value, indent: int | None = 2) -> str:
    """``value`` as strict JSON text (keys sorted): NaN and infinities become null, numpy scalars
    and paths plain values. The one way the workbench writes JSON."""
    plain = json.loads(json.dumps(value, default=_plain))  # numpy, paths, tuples -> plain JSON types
    return json.dumps(_finite(plain), indent=indent, sort_keys=True, allow_nan=False)


def atomic_write_json(path: Path, value) -> Path:
    return atomic_write_text(path, json_text(value) + "\n")
