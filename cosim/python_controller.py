"""A user's own Python controller for ``buck-cosim run --controller module:Class`` (or ``path.py:Class``).

``module:Class`` imports ``module`` (the current folder first on the import path, as ``python -m``
does); ``path.py:Class`` imports the file. ``Class`` is any callable returning a controller -- a
class or a factory function. It is called with the keywords it accepts of ``sample_period`` [s]
(``--control-period``) and ``duty_limits`` (``--duty-min``, ``--duty-max``), none if it takes none.
The object must have the protocol of :class:`controllers.base.Controller`: ``name``,
``sample_period`` [s], ``duty_limits``, ``reset()``, ``step(measurement) -> duty`` and
``describe()``. It runs at its own ``sample_period``, like a controller FMU.

Everything is checked before any run: the file or module, the name in it, the call, the members
and their values. Each mistake is one :class:`~cosim.base.errors.ConfigError` line naming the spec.
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import math
import re
import sys
from pathlib import Path

from cosim.base.errors import ConfigError
from cosim.base.labels import did_you_mean

#: ``module:Name`` or ``path/to/file.py:Name``
SPEC = re.compile(r"^(?P<source>[^:]+):(?P<name>[A-Za-z_][A-Za-z0-9_]*)$")
MEMBERS = ("name", "sample_period", "duty_limits", "reset", "step", "describe")


def is_python_controller(text: str) -> bool:
    """Whether ``--controller text`` names a Python controller (``module:Class``, ``file.py:Class``)."""
    return SPEC.match(text) is not None


def _module(source: str, spec: str):
    if source.endswith(".py"):
        path = Path(source)
        if not path.is_file():
            raise ConfigError(f"--controller {spec}: {path} does not exist" if not path.exists() else
                              f"--controller {spec}: {path} is a folder: expected a Python file")
        name = f"buck_cosim_user_{re.sub(r'[^A-Za-z0-9_]', '_', path.stem)}"
        loader = importlib.util.spec_from_file_location(name, path.resolve())
        module = importlib.util.module_from_spec(loader)
        sys.modules[name] = module  # dataclasses and pickling look their module up
        run = lambda: loader.loader.exec_module(module)  # noqa: E731
    else:
        module = None
        run = None
    added = str(Path.cwd())
    sys.path.insert(0, added)
    try:
        if run is not None:
            run()
            return module
        return importlib.import_module(source)
    except ModuleNotFoundError as error:
        if run is None and error.name == source.split(".")[0]:
            raise ConfigError(f"--controller {spec}: no module named {source!r} (expected module:Class with the module "
                              "importable from the current folder, or path/to/file.py:Class)") from None
        raise ConfigError(f"--controller {spec}: importing {source} failed: {error}") from None
    except Exception as error:
        raise ConfigError(f"--controller {spec}: importing {source} raised {type(error).__name__}: "
                          f"{str(error).splitlines()[0] if str(error) else ''}") from None
    finally:
        sys.path.remove(added)


def load_python_controller(spec: str, *, sample_period: float, duty_limits: tuple[float, float]):
    """The controller ``spec`` names, built and checked (module docstring)."""
    match = SPEC.match(spec)
    if match is None:
        raise ConfigError(f"--controller {spec}: expected module:Class or path/to/file.py:Class")
    module = _module(match["source"], spec)
    name = match["name"]
    factory = getattr(module, name, None)
    if factory is None:
        public = [n for n in vars(module) if not n.startswith("_") and callable(getattr(module, n))]
        raise ConfigError(f"--controller {spec}: {match['source']} has no {name!r}{did_you_mean(name, public)}")
    if not callable(factory):
        raise ConfigError(f"--controller {spec}: {name} is a {type(factory).__name__}, not a class or function")
    try:
        accepted = inspect.signature(factory).parameters
    except (TypeError, ValueError):
        accepted = {}
    keywords = {k: v for k, v in (("sample_period", sample_period), ("duty_limits", tuple(duty_limits)))
                if k in accepted or any(p.kind is p.VAR_KEYWORD for p in accepted.values())}
    try:
        controller = factory(**keywords)
    except Exception as error:
        raise ConfigError(f"--controller {spec}: {name}({', '.join(f'{k}={v!r}' for k, v in keywords.items())}) "
                          f"raised {type(error).__name__}: {error}") from None
    missing = [m for m in MEMBERS if not hasattr(controller, m)]
    if missing:
        raise ConfigError(f"--controller {spec}: the controller lacks {', '.join(missing)} (a controller has name, "
                          "sample_period [s], duty_limits, reset(), step(measurement) -> duty and describe())")
    check_controller(controller, spec)
    return controller


def check_controller(controller, spec: str) -> None:
    """The protocol's values: a name, a finite sample period > 0 and duty limits 0 <= min < max <= 1."""
    from controllers.base import check_duty_limits

    if not isinstance(controller.name, str) or not controller.name:
        raise ConfigError(f"--controller {spec}: name = {controller.name!r}: expected non-empty text")
    try:
        period = float(controller.sample_period)
    except (TypeError, ValueError):
        period = math.nan
    if not (period > 0 and math.isfinite(period)):
        raise ConfigError(f"--controller {spec}: sample_period = {controller.sample_period!r}: expected a finite "
                          "number of seconds > 0")
    try:
        check_duty_limits(tuple(controller.duty_limits), f"--controller {spec}")
    except (TypeError, ValueError) as error:
        raise ConfigError(str(error) if isinstance(error, ValueError) else f"--controller {spec}: duty_limits = "
                          f"{controller.duty_limits!r}: expected (min, max)") from None
    for method in ("reset", "step", "describe"):
        if not callable(getattr(controller, method)):
            raise ConfigError(f"--controller {spec}: {method} is not a method")
