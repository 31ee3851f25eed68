"""The documentation site builds with --strict, and every snippet of the docs and the README does what the
page says (tests/docs_snippets.py: the rules a page's HTML comments set)."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from docs_snippets import command_lines, snippets

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
VENV = Path(sys.executable).parent.parent


def test_the_site_builds_strict_with_the_generated_references(tmp_path):
    site = tmp_path / "site"
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "-d", str(site)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    cli = (site / "reference" / "cli" / "index.html").read_text(encoding="utf-8")
    assert "buck-cosim export-controller" in cli and "--control-period" in cli
    variables = (site / "reference" / "fmu-variables" / "index.html").read_text(encoding="utf-8")
    assert "output_voltage" in variables and "FMI 3.0" in variables
    api = (site / "reference" / "api" / "index.html").read_text(encoding="utf-8")
    assert "simulate" in api and "Measurement" in api
    assert (site / "results" / "REPORT" / "index.html").is_file()


def test_every_page_has_its_blocks_closed_and_its_directives_in_place():
    for page in PAGES:
        for snippet in snippets(page):
            if snippet.language == "bash" and snippet.instead is None and snippet.not_run is None:
                assert "make reproduce" not in snippet.code, f"{snippet.where}: runs the whole reproduction"


@pytest.mark.parametrize("page", PAGES,
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_the_snippets_of_a_page_run_as_written(page, tmp_path):
    (tmp_path / ".venv").symlink_to(VENV)
    env = {**os.environ, "PATH": f"{VENV / 'bin'}{os.pathsep}{os.environ['PATH']}", "MPLBACKEND": "Agg"}
    for snippet in snippets(page):
        if snippet.file:
            (tmp_path / snippet.file).write_text(snippet.code, encoding="utf-8")
            output = ""
        elif snippet.not_run is not None:
            _parse_every_command(snippet)
            continue
        elif snippet.instead is not None:
            output = _run(["bash", "-euo", "pipefail", "-c", snippet.instead], snippet, tmp_path, env)
        elif snippet.language == "bash":
            output = _run(["bash", "-euo", "pipefail", "-c", snippet.code], snippet, tmp_path, env)
        elif snippet.language == "python":
            output = _run([sys.executable, "-c", snippet.code], snippet, tmp_path, env)
        elif snippet.language == "toml":
            tomllib.loads(snippet.code)  # data: it must at least be TOML
            output = ""
        else:
            continue
        for text in snippet.expect:
            assert text in output, f"{snippet.where}: expected {text!r} in what it printed:\n{output[-2000:]}"


def _run(command, snippet, folder, env) -> str:
    done = subprocess.run(command, cwd=folder, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"{snippet.where} failed ({done.returncode}):\n{done.stderr[-3000:]}"
    return done.stdout + done.stderr


def _parse_every_command(snippet) -> None:
    from cosim.cli import build_parser

    for line in command_lines(snippet.code):
        words = shlex.split(line, comments=True)[1:]
        try:
            build_parser().parse_args(words)
        except SystemExit as exit_:
            assert exit_.code == 0, f"{snippet.where}: the parser refuses `{line}`"


def test_the_rules_catch_a_stale_command_line_and_a_wrong_expectation(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("<!-- not-run: example -->\n```bash\nbuck-cosim run startup --controller pi \\\n"
                    "    --no-such-option 3   # comment\n```\n\n```bash\necho hello\n```\n"
                    "<!-- expect: goodbye -->\n", encoding="utf-8")
    stale, echo = snippets(page)
    assert stale.not_run == "example" and command_lines(stale.code) == [
        "buck-cosim run startup --controller pi --no-such-option 3   # comment"]
    with pytest.raises(AssertionError, match="the parser refuses"):
        _parse_every_command(stale)
    assert echo.expect == ["goodbye"] and echo.line == 7
