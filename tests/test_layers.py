"""Imports point one way: no module imports from a layer above its own (README, *Layout*).

Layers, lowest first (a module belongs to the longest prefix that names it):

0. ``cosim.base``            errors, labels, atomic files, line-aware TOML -- everyone may use them
1. ``controllers``, ``plant_fmu``   algorithms (no FMI) and the plant FMU's sources and build
2. ``cosim.fmi``             FMU adapters, archive checks, bindings and binding files, inspect
3. ``cosim`` (the rest)      core: master, timeline, scenarios, recorder, results, metrics, plots, batch;
   ``cosim.ssp``             with the core: the scenario FMU, the SSP archive and the engines that run it
4. ``cosim.study``           the paper study: vocabulary, experiments, tuning, data, reproduction, report
5. ``cosim.cli``, ``cosim.benchmarks``, ``cosim.benchmark_harness``   entry points and the C timing harness

Every import counts, also one inside a function (the lazy imports that keep the command line
fast): a lazy upward import is still an upward dependency.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("cosim", "controllers", "plant_fmu")
LAYERS = {
    "cosim.base": 0,
    "controllers": 1,
    "plant_fmu": 1,
    "cosim.fmi": 2,
    "cosim": 3,
    "cosim.ssp": 3,
    "cosim.study": 4,
    "cosim.cli": 5,
    "cosim.benchmarks": 5,
    "cosim.benchmark_harness": 5,
}


def layer_of(module: str) -> int:
    """The layer of a module: that of the longest prefix in :data:`LAYERS` naming it."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        prefix = ".".join(parts[:n])
        if prefix in LAYERS:
            return LAYERS[prefix]
    raise KeyError(module)


def imported_modules(source: str, module: str) -> list[tuple[int, str]]:
    """(line, module) of every first-party import in a module's source, relative ones resolved."""
    found = []
    package = module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            names = [base]
        else:
            continue
        found += [(node.lineno, name) for name in names if name.split(".")[0] in PACKAGES]
    return found


def upward_imports(sources: dict[str, str]) -> list[str]:
    """Each import of a module from a layer above its own, as ``module:line imports target``."""
    problems = []
    for module, source in sorted(sources.items()):
        own = layer_of(module)
        for line, target in imported_modules(source, module):
            if layer_of(target) > own:
                problems.append(f"{module}:{line} imports {target} (layer {layer_of(target)} above {own})")
    return problems


def project_sources() -> dict[str, str]:
    sources = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            sources[module] = path.read_text(encoding="utf-8")
    return sources


def test_no_module_imports_from_a_layer_above_its_own():
    sources = project_sources()
    assert {"cosim.master", "cosim.fmi.plant", "controllers.predictive", "cosim.study.reproduce"} <= set(sources)
    assert upward_imports(sources) == []


def test_the_check_catches_an_upward_import():
    """The same check on a controller that reaches up into the study (lazily) and the CLI."""
    sources = {
        "controllers.sneaky": "import math\n\ndef f():\n    from cosim.study.vocabulary import NNPC\n    return NNPC\n",
        "cosim.fmi.sneaky": "from cosim.master import run\nfrom cosim.base.errors import ConfigError\n",
        "cosim.study.fine": "from cosim.master import run\nfrom controllers.pi import PIController\n",
        "cosim.master2": "from .cli import main\n",
    }
    assert upward_imports(sources) == [
        "controllers.sneaky:4 imports cosim.study.vocabulary (layer 4 above 1)",
        "cosim.fmi.sneaky:1 imports cosim.master (layer 3 above 2)",
        "cosim.master2:1 imports cosim.cli (layer 5 above 3)",
    ]
