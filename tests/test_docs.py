"""The documentation site builds with --strict, and every snippet of the docs and the README does what the
page says (tests/docs_snippets.py: the rules a page's HTML comments set)."""

from __future__ import annotations

import os
import re
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


LINK = re.compile(r"(?<!!)\[[^\]\n]*\]\(([^)\s]+)\)")
CODE = re.compile(r"```.*?```|`[^`\n]*`", re.S)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_of_a_page_leads_to_a_file(page):
    """A link's target exists (a file or folder of the repository, or a page of the site); Markdown outside code
    reads ``[iL, vc, d](k-1)`` as a link to a page "k-1" that does not exist."""
    text = CODE.sub("", page.read_text(encoding="utf-8"))
    dead = []
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:|#", target):  # a URL, an anchor on the page
            continue
        path = (page.parent / target.split("#")[0]).resolve()
        site = [ROOT / "docs" / target.split("#")[0], ROOT / target.split("#")[0]]  # the site's results/ pages
        if not path.exists() and not any(p.exists() for p in site):
            dead.append(target)
    assert not dead, f"{page.relative_to(ROOT)}: links to nothing: {dead}"


def test_the_sites_navigation_has_plain_unique_titles_and_a_guide_overview():
    """Navigation titles are shown as written (no Markdown): no backticks, no two alike; the guide has an overview
    page that links every guide page."""
    import yaml

    class Loader(yaml.SafeLoader):  # mkdocs.yml's !!python tags are the theme's business, not the nav's
        pass

    Loader.add_multi_constructor("tag:yaml.org,2002:python/", lambda loader, suffix, node: None)
    nav = yaml.load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"), Loader=Loader)["nav"]
    titles = []

    def walk(entries):
        for entry in entries:
            for title, value in entry.items():
                titles.append(title)
                if isinstance(value, list):
                    walk(value)

    walk(nav)
    assert not [t for t in titles if "`" in t], titles
    assert len(titles) == len(set(titles)), sorted(t for t in titles if titles.count(t) > 1)
    overview = (ROOT / "docs" / "guide" / "index.md").read_text(encoding="utf-8")
    missing = [p.name for p in (ROOT / "docs" / "guide").glob("*.md") if p.name != "index.md" and
               f"({p.name})" not in overview]
    assert not missing, missing


def test_following_the_docs_in_the_clone_leaves_git_status_clean():
    """Every folder or file the README, the quick start and the tutorials tell a reader to write in the clone
    (``--out``, ``--draft-binding``, the files they save) is ignored by git."""
    written = set()
    for page in [ROOT / "README.md", ROOT / "docs" / "quickstart.md", *(ROOT / "docs" / "tutorials").glob("*.md")]:
        text = page.read_text(encoding="utf-8")
        written |= set(re.findall(r"--(?:out|draft-binding) ([a-z][a-z0-9_.-]*)", text))
        written |= {"BuckConverter.fmu", "BuckConverter-source.fmu"} if "build-fmu --output ." in text else set()
        written |= {snippet.file for snippet in snippets(page) if snippet.file}
    assert {"quickstart", "own", "tiny.toml"} <= written
    done = subprocess.run(["git", "check-ignore", "--no-index", *sorted(written)], cwd=ROOT, capture_output=True,
                          text=True)
    ignored = set(done.stdout.split())
    assert ignored == written, sorted(written - ignored)


def test_bootstrap_skips_the_debian_packages_when_asked(tmp_path):
    """As root with apt-get, ``make bootstrap`` installs the embedded toolchain's Debian packages unless
    BUCK_COSIM_NO_APT is set (a fake apt-get records whether it was called; the .venv is already installed)."""
    fake = tmp_path / "bin"
    fake.mkdir()
    for name, body in (("apt-get", f'echo "$@" >> {tmp_path}/apt.log'), ("dpkg-query", "exit 1"), ("id", "echo 0")):
        (fake / name).write_text(f"#!/bin/sh\n{body}\n")
        (fake / name).chmod(0o755)
    env = {**os.environ, "PATH": f"{fake}{os.pathsep}{os.environ['PATH']}"}
    for skip, called in (("1", False), ("", True)):
        (tmp_path / "apt.log").unlink(missing_ok=True)
        done = subprocess.run(["bash", "scripts/bootstrap.sh"], cwd=ROOT, capture_output=True, text=True,
                              env={**env, "BUCK_COSIM_NO_APT": skip}, timeout=600)
        assert done.returncode == 0, done.stderr
        assert (tmp_path / "apt.log").exists() == called, (skip, done.stdout)


def test_the_readme_is_one_screen_and_its_duration_is_the_results():
    """The README is for a visitor: short, no measurement history; the reproduction's duration it states agrees
    with the committed wall-clock files (the paper's study and the two converter studies make reproduce runs),
    within a factor of two (they are wall-clock figures of one machine)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 80
    assert not re.search(r"\b(earlier|the run before|before it)\b", text, re.IGNORECASE)
    stated = float(re.search(r"make reproduce .*: about (\d+) minutes on two cores", text).group(1))
    seconds = [float(re.search(r"Whole reproduction: ([\d.]+) s", (ROOT / "results" / "timings.md").read_text()).group(1))]
    seconds += [float(re.search(r"Whole converter study: ([\d.]+) s", (ROOT / "results" / name / "timings.md")
                                .read_text()).group(1)) for name in ("pol-buck", "pol-buck-pythonfmu")]
    assert stated / 2 <= sum(seconds) / 60 <= stated * 2, (stated, seconds)
