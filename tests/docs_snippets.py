"""Read the code snippets of a Markdown page (README.md, docs/*.md) and what the page says about each.

A fenced block is *run* in order in one folder per page: ``bash`` blocks with ``bash -euo pipefail``
(``.venv`` of the running interpreter linked into the folder, so ``.venv/bin/buck-cosim`` works as in
a clone), ``python`` blocks with this interpreter. HTML comments just before a block change that:

* ``<!-- file: NAME -->`` -- the block is a file the page's later snippets use: written as ``NAME``;
* ``<!-- instead: CMD ; because: REASON -->`` -- ``CMD`` runs in the block's place (a command that
  needs minutes, or a set-up already done), and the reason is shown to the reader of the source;
* ``<!-- not-run: REASON -->`` -- reference examples that need the reader's own files: not run, but
  every ``buck-cosim`` command line in them is parsed by the real argument parser.

``<!-- expect: TEXT -->`` just after a block: what the block prints must contain ``TEXT``. Blocks in
other languages are data: ``toml`` blocks must parse (``tomllib``), the rest (C, text, YAML) are shown.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

DIRECTIVE = re.compile(r"<!--\s*(file|instead|not-run|expect):\s*(.*?)\s*-->")


@dataclass
class Snippet:
    page: Path
    line: int          # 1-based line of the opening fence
    language: str
    code: str
    file: str | None = None
    instead: str | None = None
    not_run: str | None = None
    expect: list[str] = field(default_factory=list)

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


def snippets(page: Path) -> list[Snippet]:
    """The fenced blocks of ``page`` with their directives, in page order."""
    lines = page.read_text(encoding="utf-8").splitlines()
    found: list[Snippet] = []
    pending: dict[str, str] = {}
    index = 0
    while index < len(lines):
        line = lines[index]
        match = DIRECTIVE.fullmatch(line.strip())
        if match:
            kind, value = match.groups()
            if kind == "expect":
                if not found:
                    raise ValueError(f"{page}:{index + 1}: 'expect' before any code block")
                found[-1].expect.append(value)
            else:
                pending[kind] = value
        elif line.startswith("```"):
            language = line[3:].strip()
            start = index
            index += 1
            body = []
            while index < len(lines) and not lines[index].startswith("```"):
                body.append(lines[index])
                index += 1
            if index == len(lines):
                raise ValueError(f"{page}:{start + 1}: code block never closed")
            snippet = Snippet(page, start + 1, language, "\n".join(body) + "\n")
            if "instead" in pending:
                command, _, reason = pending.pop("instead").partition("; because:")
                if not reason.strip():
                    raise ValueError(f"{page}:{start + 1}: 'instead' needs '; because: REASON'")
                snippet.instead = command.strip()
            snippet.file = pending.pop("file", None)
            snippet.not_run = pending.pop("not-run", None)
            found.append(snippet)
        elif line.strip():
            pending.clear()  # a directive applies to the block right after it
        index += 1
    return found


def command_lines(code: str, program: str = "buck-cosim") -> list[str]:
    """The ``program`` command lines of a shell block (continuations joined, comments kept for shlex)."""
    joined = re.sub(r"\s*\\\n\s*", " ", code)
    commands = []
    for line in joined.splitlines():
        words = line.strip().split()
        if words and Path(words[0]).name == program:
            commands.append(line.strip())
    return commands
