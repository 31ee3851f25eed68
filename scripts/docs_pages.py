"""Pages of the documentation site generated at build time (mkdocs-gen-files runs this from mkdocs.yml).

* ``reference/cli.md`` -- every command's ``--help`` text, from the argparse parser itself, so the CLI
  reference cannot drift from the command line;
* ``reference/fmu-variables.md`` -- the built-in plant FMU's variables (FMI 2.0 and 3.0), read by fmpy
  from the modelDescription.xml of the FMU as built here;
* ``results/...`` -- the committed reproduction (REPORT.md, benchmarks, timings, figures, tables) as
  ``make reproduce`` wrote it; run files and data (Parquet, models) stay out of the site.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import mkdocs_gen_files

ROOT = Path(__file__).resolve().parents[1]
RESULT_SUFFIXES = {".md", ".png", ".svg", ".csv", ".json"}
RESULT_FOLDERS_LEFT_OUT = {"runs", "data", "runs-cli", "models"}


def cli_reference() -> str:
    os.environ["COLUMNS"] = "100"  # argparse wraps at the terminal width: fix it so the page is stable
    from cosim.cli import build_parser

    parser = build_parser()
    parser.prog = "buck-cosim"
    lines = ["# Command line", "", "Generated from the parser of `buck-cosim` (`cosim/cli/`): what `--help` prints.",
             "", "```text", parser.format_help().rstrip(), "```", ""]
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001
    for name, sub in commands.choices.items():
        lines += [f"## `buck-cosim {name}`", "", "```text", sub.format_help().rstrip(), "```", ""]
    return "\n".join(lines)


def _cell(value) -> str:
    return "" if value is None else str(value).replace("|", "\\|").replace("\n", " ")


def fmu_variables() -> str:
    from fmpy import read_model_description

    from plant_fmu import fmu_path

    lines = ["# FMU variables", "",
             "The built-in plant FMU's variables, read by fmpy from the modelDescription.xml of the FMU as "
             "built by `buck-cosim build-fmu` (one FMU for the averaged and the switched model, chosen by "
             "its parameters).", ""]
    for version in (2, 3):
        description = read_model_description(str(fmu_path(fmi_version=version)))
        interfaces = [kind for kind, present in (("co-simulation", description.coSimulation),
                                                 ("model exchange", description.modelExchange)) if present]
        lines += [f"## FMI {version}.0 (`{description.modelName}`, {', '.join(interfaces)})", "",
                  "| name | causality | variability | type | unit | start | description |",
                  "|---|---|---|---|---|---|---|"]
        for variable in description.modelVariables:
            lines.append("| " + " | ".join(_cell(v) for v in (
                f"`{variable.name}`", variable.causality, variable.variability, variable.type,
                variable.unit or (variable.declaredType.unit if variable.declaredType else None),
                variable.start, variable.description)) + " |")
        lines.append("")
    return "\n".join(lines)


def copy_results() -> None:
    results = ROOT / "results"
    for path in sorted(results.rglob("*")):
        relative = path.relative_to(results)
        if (path.is_file() and path.suffix in RESULT_SUFFIXES
                and not RESULT_FOLDERS_LEFT_OUT.intersection(relative.parts[:-1])):
            with mkdocs_gen_files.open(f"results/{relative.as_posix()}", "wb") as target:
                target.write(path.read_bytes())


with mkdocs_gen_files.open("reference/cli.md", "w") as page:
    page.write(cli_reference())
with mkdocs_gen_files.open("reference/fmu-variables.md", "w") as page:
    page.write(fmu_variables())
copy_results()
