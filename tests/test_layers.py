"""Imports point one way: no module imports from a layer above its own (README, *Layout*).

Layers, lowest first (a module belongs to the longest prefix that names it):

0. ``cosim.base``            errors, labels, atomic files, line-aware TOML -- everyone may use them
1. ``controllers``, ``plant_fmu``   algorithms (no FMI) and the plant FMU's sources and build;
   ``cosim.converter_spec``  the converter under study (Table II is the built-in plant's)
2. ``cosim.fmi``             FMU adapters, archive checks, bindings and binding files, inspect
3. ``cosim`` (the rest)      core: master, timeline, scenarios, recorder, results, metrics, plots, batch;
   ``cosim.ssp``             with the core: the scenario FMU, the SSP archive and the engines that run it
4. ``cosim.design``          the design steps: vocabulary, controllers by name, PI tuning, data collection,
   identification, classical design, distillation, frequency response, design cache, sweeps
5. ``cosim.study``           the studies built on them: the paper's reproduction, report, claims, targets,
   ablations, every-seed evaluations, and a converter's study
6. ``cosim.cli``, ``cosim.api``, ``cosim.benchmarks``, ``cosim.benchmark_harness``   entry points (the command line,
   the design steps' Python API) and the C timing harness

Every import counts, also one inside a function (the lazy imports that keep the command line
fast): a lazy upward import is still an upward dependency.

Inside a layer imports point one way too: no module reaches itself through the modules it imports
(an import circle, lazy or not -- e.g. the isolated plant and the plant opener, or the sweep worker
and the controller designs, once did).
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
    "cosim.converter_spec": 1,
    "cosim.fmi": 2,
    "cosim": 3,
    "cosim.ssp": 3,
    "cosim.design": 4,
    "cosim.study": 5,
    "cosim.cli": 6,
    "cosim.benchmarks": 6,
    "cosim.benchmark_harness": 6,
    "cosim.api": 6,
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


def import_graph(sources: dict[str, str]) -> dict[str, set[str]]:
    """Module -> the project modules it imports. ``from package import name`` imports the module
    ``package.name`` if there is one (else the package); a package's own ``__init__`` counts as the
    package."""
    graph = {}
    for module, source in sources.items():
        targets = set()
        tree = ast.parse(source)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                base = _from_base(node, module)
                for alias in node.names:
                    candidate = f"{base}.{alias.name}"
                    targets.add(candidate if candidate in sources else base)
            elif isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names)
        graph[module] = {t for t in targets if t in sources and t != module}
    return graph


def _from_base(node: ast.ImportFrom, module: str) -> str:
    """The module a ``from ... import`` names, relative imports resolved."""
    package = module.rsplit(".", 1)[0]
    base = node.module or ""
    if node.level:
        anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
        base = ".".join(anchor + ([base] if base else []))
    return base


def import_circles(sources: dict[str, str]) -> list[list[str]]:
    """Every set of modules that import each other in a circle (strongly connected, Tarjan), sorted."""
    graph = import_graph(sources)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for target in sorted(graph[module]):
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            members = []
            while True:
                member = stack.pop()
                members.append(member)
                if member == module:
                    break
            if len(members) > 1:
                circles.append(sorted(members))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return sorted(circles)


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
    assert {"cosim.master", "cosim.fmi.plant", "controllers.predictive", "cosim.design.pi_tuning",
            "cosim.study.reproduce"} <= set(sources)
    assert upward_imports(sources) == []


def test_the_check_catches_an_upward_import():
    """The same check on a controller that reaches up into the study (lazily), the CLI, and a design step that
    reaches up into the paper's study."""
    sources = {
        "controllers.sneaky": "import math\n\ndef f():\n    from cosim.study.vocabulary import NNPC\n    return NNPC\n",
        "cosim.fmi.sneaky": "from cosim.master import run\nfrom cosim.base.errors import ConfigError\n",
        "cosim.study.fine": "from cosim.master import run\nfrom controllers.pi import PIController\n",
        "cosim.master2": "from .cli import main\n",
        "cosim.design.sneaky": "from cosim.study.reproduce import reproduce\n",
    }
    assert upward_imports(sources) == [
        "controllers.sneaky:4 imports cosim.study.vocabulary (layer 5 above 1)",
        "cosim.design.sneaky:1 imports cosim.study.reproduce (layer 5 above 4)",
        "cosim.fmi.sneaky:1 imports cosim.master (layer 3 above 2)",
        "cosim.master2:1 imports cosim.cli (layer 6 above 3)",
    ]


def test_no_modules_import_each_other_in_a_circle():
    sources = project_sources()
    assert {"cosim.fmi.isolation", "cosim.fmi.plant", "cosim.design.sweeps.worker"} <= set(sources)
    assert import_circles(sources) == []


def test_the_circle_check_catches_lazy_and_indirect_circles():
    """The two circles issue 26 untied, as they were (the lazy half of each inside a function), and a
    circle of three; a package's ``from package import module`` is an import of that module."""
    sources = {
        "cosim.fmi.plant": "def open_plant():\n    from cosim.fmi.isolation import IsolatedPlant\n",
        "cosim.fmi.isolation": "from cosim.fmi.plant import FATAL_REFUSAL, plant_signals\n",
        "cosim.design.sweeps.worker": "from cosim.design.sweeps.designs import build\n",
        "cosim.design.sweeps.designs": "def f():\n    from cosim.design.sweeps.worker import process_file\n",
        "cosim.a": "import cosim.b\n", "cosim.b": "from cosim import c\n", "cosim.c": "from .a import x\n",
        "plant_fmu": "from plant_fmu.build import fmu_path\n", "plant_fmu.build": "from plant_fmu import fmi3\n",
        "plant_fmu.fmi3": "import math\n",
    }
    assert import_circles(sources) == [["cosim.a", "cosim.b", "cosim.c"],
                                       ["cosim.design.sweeps.designs", "cosim.design.sweeps.worker"],
                                       ["cosim.fmi.isolation", "cosim.fmi.plant"]]
