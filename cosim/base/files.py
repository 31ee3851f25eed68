"""Atomic file writes: a crash, a full disk or Ctrl-C never leaves a half-written file behind.

Every file the workbench writes goes through :func:`atomic_write`: written under a temporary
name in the target folder, then renamed onto the target (``os.replace`` is atomic within one
file system), so a reader sees either the old file or the complete new one.
"""

from __future__ import annotations

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
