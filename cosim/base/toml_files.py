"""Line numbers for keys of a TOML file, so every configuration error can name file, key and line.

``tomllib`` parses without positions; this scans the text for the table headers and ``key =``
lines, which is enough for the small, hand-written files the workbench reads.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

from cosim.base.errors import ConfigError


class TomlLocator:
    """Finds the line of a key in a TOML text (tables, arrays of tables, dotted position)."""

    def __init__(self, text: str):
        self.lines = text.splitlines()

    def line_of(self, key: str, table: str | None = None, index: int | None = None) -> int | None:
        current, count = None, -1
        for number, raw in enumerate(self.lines, start=1):
            line = raw.split("#", 1)[0].strip()
            header = re.fullmatch(r"\[\[\s*([\w.-]+)\s*\]\]", line) or re.fullmatch(r"\[\s*([\w.-]+)\s*\]", line)
            if header:
                name = header.group(1)
                if line.startswith("[[") and name == table:
                    count += 1
                current = name
                if key is None and name == table and (index is None or count == index):
                    return number
                continue
            in_place = current == table and (index is None or count == index)
            if key is not None and in_place and re.match(rf"{re.escape(key)}\s*=", line):
                return number
        return None


def finite_number(value, label: str, place: str) -> float:
    """A configuration value that must be a finite number (not a bool, not text), as a float; else a one-line
    :class:`ConfigError` at ``place`` (``file:line``) naming ``label``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise ConfigError(f"{place}: {label} = {value!r} is invalid: expected a finite number")
    return float(value)


def where(path: Path | None, locator: TomlLocator, key: str, table: str | None = None, index: int | None = None) -> str:
    name = str(path) if path else "<text>"
    line = locator.line_of(key, table, index)
    return f"{name}:{line}" if line else name


def parse_toml(text: str, path: Path | None, allowed_keys: set[str], unnamed: str = "<text>") -> tuple[dict, TomlLocator]:
    """Parse a configuration file's text; invalid TOML or an unknown top-level key is a
    :class:`ConfigError` naming the file (``unnamed`` for text without one) and the key's line. A byte-order mark,
    which Windows editors put before UTF-8 text and tomllib refuses ("invalid statement at line 1"), is skipped."""
    text = text.removeprefix("\ufeff")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path if path else unnamed}: invalid TOML: {error}") from None
    locator = TomlLocator(text)
    for key in data:
        if key not in allowed_keys:
            raise ConfigError(f"{where(path, locator, key)}: unknown key {key!r}: expected one of "
                              f"{', '.join(sorted(allowed_keys))}")
    return data, locator
