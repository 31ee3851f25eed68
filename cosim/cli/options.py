"""What several commands share: argument types that refuse bad input at once (folders, files, periods,
seeds, bounded numbers), the parser that ends a usage mistake in one line, and the option groups (plant,
implementation, PI gains and duty limits, controller design, FMI version) with the helpers that read them.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

from cosim.base.errors import ConfigError
from cosim.base.labels import MIN_PERIOD, period_too_short
from cosim.design.data_collection import MIN_SAMPLES
from cosim.design.vocabulary import (
    DEFAULT_IMPLEMENTATION,
    EXPORTABLE_CONTROLLERS,
    IMPLEMENTATIONS,
    ON_DEMAND_SAMPLES,
    OPTIMIZERS,
    PLANT_VARIANTS,
    PREDICTIVE_CONTROLLERS,
    SENSORS,
)
from cosim.fmi.binding import PLANT_MODE_CODES

DEFAULT_RESULTS = Path("results")


class OneLineParser(argparse.ArgumentParser):
    """Usage mistakes end in one line on stderr (exit code 2), like every other user error; an option that takes one
    value is refused when given twice (argparse keeps the last silently: ``--control-period 1e-3 --control-period
    1/75e3`` ran at 13.33 us)."""

    def error(self, message: str):
        self.exit(2, f"error: {self.prog}: {message} (see {self.prog} --help)\n")

    def parse_known_args(self, args=None, namespace=None):
        if self._subparsers is None:  # a command's own options (the top level only dispatches)
            self._refuse_repeated_options(list(sys.argv[1:] if args is None else args))
        return super().parse_known_args(args, namespace)

    def _refuse_repeated_options(self, tokens: list[str]) -> None:
        single = {option: action for action in self._actions if isinstance(action, argparse._StoreAction)
                  for option in action.option_strings}  # options with a value (flags repeated are harmless)
        seen: dict[argparse.Action, str] = {}
        index = 0
        while index < len(tokens):
            token = tokens[index]
            index += 1
            if token == "--":
                break
            name = token.split("=", 1)[0]
            if not name.startswith("--") or " " in name:  # a value (a title "--out=x y" is text, not an option)
                continue
            matches = {single[o] for o in single if o == name} or {single[o] for o in single if o.startswith(name)}
            if len(matches) != 1:  # another kind of option, or an ambiguous abbreviation argparse itself refuses
                continue
            action = matches.pop()
            if "=" not in token and action.nargs is None and index < len(tokens):  # "--option value": skip the value
                token = f"{token} {tokens[index]}"
                index += 1
            if action in seen:
                self.error(f"argument {'/'.join(action.option_strings)}: given twice ({seen[action]} and {token}): "
                           "give it once")
            seen[action] = token


#: endings of the files the workbench reads and writes: a new output folder named with one is taken for a file name
FILE_SUFFIXES = (".csv", ".parquet", ".json", ".md", ".txt", ".png", ".svg", ".pdf", ".pt", ".pth", ".fmu", ".ssp",
                 ".toml")


def output_dir(text: str | None) -> Path | None:
    """A folder results go to: refused at once if it cannot be one (not after hours of work)."""
    if text is None:
        return None
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"output folder {path} is an existing file: expected a folder")
    if not path.exists() and path.suffix.lower() in FILE_SUFFIXES:  # export --out run.csv made a folder run.csv/
        raise ConfigError(f"output folder {path} is named like a {path.suffix[1:].upper()} file, but the results are a "
                          "folder of files: give a folder name (an existing folder of that name is used as it is)")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ConfigError(f"cannot create output folder {path}: {error.strerror}") from None
    if not os.access(path, os.W_OK):
        raise ConfigError(f"output folder {path} is not writable")
    return path


def cache_dir(text: str) -> Path:
    """A folder designs are cached in: refused at once if it cannot be one, but created only when
    something is written there (an export with given gains leaves no empty folder behind)."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"output folder {path} is an existing file: expected a folder")
    existing = next((p for p in (path, *path.parents) if p.exists()), Path("."))
    if not existing.is_dir() or not os.access(existing, os.W_OK):
        raise ConfigError(f"output folder {path} cannot be created: {existing} is not a writable folder")
    return path


def input_file(text: str, what: str, hint: str = "") -> Path:
    """A file to read: refused at once, in one line, if it is missing or a folder."""
    path = Path(text)
    if path.is_dir():
        raise ConfigError(f"{what} {path} is a folder: expected a file")
    if not path.is_file():
        raise ConfigError(f"{what} {path} does not exist" + (f" ({hint})" if hint else ""))
    return path


def output_file(text: str | None, suffixes: tuple[str, ...] = (), what: str = "", option: str = "--out") -> Path | None:
    """A file a result goes to: its folder must be creatable and writable, and it must not be a folder.

    ``suffixes`` (e.g. ``(".parquet",)``): the endings its name may have, case aside -- where a command writes one
    format, a file named for another (samples written as Parquet into ``data.csv``) would be a silent surprise, so
    the name is refused, saying what is written (``what``); ``option`` names the option in the message."""
    if text is None:
        return None
    path = Path(text)
    if path.is_dir():
        raise ConfigError(f"output file {path} is a folder: expected a file name")
    if suffixes and path.suffix.lower() not in suffixes:
        endings = " or ".join(suffixes)
        raise ConfigError(f"{option} {path} is invalid: expected a file name ending in {endings}"
                          + (f" ({what})" if what else ""))
    output_dir(str(path.parent))
    return path


def parse_period(text: str) -> float:
    """A period in seconds: ``1e-3``, ``0.001`` or a fraction such as ``1/75e3``; at least
    :data:`cosim.timeline.MIN_PERIOD` (100 ns: a shorter one is taken for a unit slip)."""
    try:
        if "/" in text:
            numerator, denominator = text.split("/", 1)
            value = float(numerator) / float(denominator)
        else:
            value = float(text)
    except (ValueError, ZeroDivisionError):
        raise argparse.ArgumentTypeError(f"{text!r} is not a period in seconds (e.g. 1e-3 or 1/75e3)") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"period {text} s is invalid: expected a finite value > 0")
    if value < MIN_PERIOD:
        raise argparse.ArgumentTypeError(period_too_short(f"period {text} s"))
    return value


#: seeds are 32-bit: numpy's and torch's generators take them, and so does any tool a user repeats a run with
SEED_MAX = 2**32 - 1


def seed_value(text: str) -> int:
    """A random seed: a whole number 0 .. 2**32 - 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a seed: expected a whole number 0 .. {SEED_MAX}") from None
    if not 0 <= value <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"seed {text} is out of range: expected a whole number 0 .. {SEED_MAX}")
    return value


def bounded(kind=float, low: float | None = None, high: float | None = None, *, below_high: bool = False,
            unit: str = ""):
    """An argparse type: a finite number (``kind`` int or float) with ``low <= value`` and
    ``value <= high`` (``value < high`` with ``below_high``); NaN and infinities are refused."""
    name = "whole number" if kind is int else "finite number"
    limits = [f">= {low:g}" if low is not None else "", (f"< {high:g}" if below_high else f"<= {high:g}")
              if high is not None else ""]
    expected = f"a {name} {' and '.join(x for x in limits if x)}".strip() + (f" {unit}" if unit else "")

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is invalid: expected {expected}") from None
        ok = math.isfinite(value) and (low is None or value >= low) and \
            (high is None or (value < high if below_high else value <= high))
        if not ok:
            raise argparse.ArgumentTypeError(f"{text} is invalid: expected {expected}")
        return value

    return parse


def _plant_binding(args):
    from dataclasses import replace

    built_in = {option: getattr(args, option[2:], None) for option in BUILT_IN_PLANT_OPTIONS}
    if getattr(args, "plant", None):
        from cosim.fmi.binding_file import load_binding

        given = next((f"{option} {value}" for option, value in built_in.items() if value is not None), None)
        if given:  # the binding file chooses the plant: the option would be dropped silently
            raise ConfigError(f"{given} chooses a built-in plant, but --plant {args.plant} drives an external FMU, "
                              f"whose binding file chooses the model: drop {given.split()[0]}")
        binding = load_binding(args.plant)
    else:
        from cosim.design.plants import plant_binding

        variant, mode, sensor = (value or BUILT_IN_PLANT_OPTIONS[option] for option, value in built_in.items())
        binding = plant_binding(variant, mode, sensor)
    isolate = getattr(args, "isolate", None)
    binding = binding if isolate is None else replace(binding, isolate=isolate)
    limits = {key: value for key, value in (("step_timeout", getattr(args, "step_timeout", None)),
                                            ("memory_limit", getattr(args, "memory_limit", None))) if value is not None}
    if limits and not binding.isolate:
        option = "--" + next(iter(limits)).replace("_", "-")
        raise ConfigError(f"{option} needs an isolated plant (--isolate, or a binding file's default): the workbench "
                          "cannot stop an FMU running in its own process")
    return replace(binding, **limits) if limits else binding


def _check_duty_limits(args) -> None:
    """Refuse --duty-min/--duty-max unless 0 <= min < max <= 1, before any other work."""
    if not (0.0 <= args.duty_min < args.duty_max <= 1.0):
        raise ConfigError(f"duty limits ({args.duty_min}, {args.duty_max}) are invalid: expected 0 <= min < max <= 1")


#: the options that choose the built-in plant, with their defaults (None in the parser: an option given with --plant
#: is refused, not dropped)
BUILT_IN_PLANT_OPTIONS = {"--variant": "nominal", "--mode": "averaged", "--sensor": "average"}


def _add_plant_options(parser) -> None:
    parser.add_argument("--mode", choices=list(PLANT_MODE_CODES), default=None,
                        help="built-in plant: averaged model (eq. 3, with DCM) or switched (PWM, ideal switch and "
                             "diode) (default: averaged)")
    parser.add_argument("--variant", choices=list(PLANT_VARIANTS), default=None,
                        help="built-in plant parameters: Table II, or L +20 %%, C -20 %% with parasitics "
                             "(default: nominal)")
    parser.add_argument("--sensor", choices=list(SENSORS), default=None,
                        help="what controllers measure: the mean over the last PWM period (default), or a point "
                             "sample at mid off-time with centre-aligned PWM")
    parser.add_argument("--plant", metavar="BINDING.toml",
                        help="drive an external FMU through a plant-binding file instead of the built-in plant "
                             "(--mode/--variant/--sensor, which choose the built-in one, are refused with it); its "
                             "[converter] table says which converter it is, and the scenarios and designs work at "
                             "its operating points (docs/guide/external-plants.md)")
    isolation = parser.add_mutually_exclusive_group()
    isolation.add_argument("--isolate", dest="isolate", action="store_true", default=None,
                           help="step the plant FMU in a child process: a crash inside it ends the run with an error "
                                "(exit 3, rows kept) instead of the workbench (default for binding-file plants; costs "
                                "one pipe round trip per step, see benchmarks.md)")
    isolation.add_argument("--no-isolate", dest="isolate", action="store_false",
                           help="step the plant FMU in this process (default for the built-in plant)")
    parser.add_argument("--step-timeout", type=bounded(float, 1e-3, unit="s"), default=None, metavar="SECONDS",
                        help="isolated plant: a step that takes longer (wall time) is stopped and the run fails "
                             "(exit 3) (default: the binding file's step_timeout, else 30 s + 1000 x the step's "
                             "simulated length)")
    parser.add_argument("--memory-limit", type=bounded(float, 1.0, unit="MB"), default=None, metavar="MB",
                        help="isolated plant: its process is stopped (the run fails, exit 3) above this resident "
                             "memory (default: the binding file's memory_limit, else half the machine's)")
    parser.add_argument("--interface", choices=["cs", "me"], default=None,
                        help="FMI interface: cs = co-simulation (fmi2DoStep), me = model exchange with fmpy's CVode "
                             "(default: the binding's choice, else co-simulation)")


def _add_implementation_option(parser) -> None:
    parser.add_argument("--implementation", choices=list(IMPLEMENTATIONS), default=DEFAULT_IMPLEMENTATION,
                        help="run the PI and predictive controllers as their C twins (controllers/c: the same duty "
                             "at every sample; the predictive ones 100-400 x faster per step with the RTI, the PI "
                             "about as cheap: its ctypes call) or as the Python references (default: %(default)s)")


def _add_optimizer_options(parser, offered: tuple[str, ...] = PREDICTIVE_CONTROLLERS) -> None:
    """--optimizer and --rti FIELD=VALUE (the predictive controllers' optimizer and its RTI settings), read by
    :func:`optimizer_options`; ``offered``: the predictive controllers the command offers (named in the help)."""
    parser.add_argument("--optimizer", choices=list(OPTIMIZERS), default=None,
                        help=f"the optimizer of the predictive controllers ({', '.join(offered)}): rti, "
                             "the real-time iteration (Gauss-Newton steps on the blocked duties from the last plan, "
                             "the search as its fallback at a cold start and at large steps), or search, the grid + "
                             "pattern search alone (the reference). Default: "
                             + ("each one's own -- the search for nnpc-paper (as the reproduction runs the paper's "
                                "network), the RTI for the others" if "nnpc-paper" in offered else "the RTI"))
    parser.add_argument("--rti", action="append", default=[], metavar="FIELD=VALUE",
                        help="change one of the RTI settings of the control period's default (repeat for several), "
                             "e.g. --rti reweightings=0 --rti iterations=2; fields and units: "
                             "docs/guide/controllers.md (controllers.predictive.RtiSettings); refused where no "
                             "controller plans with the RTI")


#: the predictive controllers export-controller and export-ssp offer (the adaptive NNPC has no C twin to export)
EXPORTED_PREDICTIVE = tuple(k for k in PREDICTIVE_CONTROLLERS if k in EXPORTABLE_CONTROLLERS)


def optimizer_options(args) -> tuple[str | None, dict]:
    """(--optimizer, the --rti changes parsed: :func:`cosim.design.experiments.rti_changes`); a bad item is a
    ConfigError naming it."""
    from cosim.design.experiments import rti_changes

    try:
        return args.optimizer, rti_changes(args.rti)
    except ValueError as error:
        raise ConfigError(str(error)) from None


def _add_pi_and_duty_options(parser, gains_default: str) -> None:
    """--kp/--ki (the PI's gains; ``gains_default`` says what happens without them) and --duty-min/--duty-max (every
    built-in controller's duty limits), checked together by :func:`_check_duty_limits`."""
    parser.add_argument("--kp", type=bounded(float, 0.0),
                        help=f"PI proportional gain [1/V] (default: {gains_default})")
    parser.add_argument("--ki", type=bounded(float, 0.0),
                        help=f"PI integral gain [1/(V s)] (default: {gains_default})")
    parser.add_argument("--duty-min", type=bounded(float, 0.0, 1.0), default=0.0,
                        help="lower duty limit [1] (default: 0)")
    parser.add_argument("--duty-max", type=bounded(float, 0.0, 1.0), default=1.0,
                        help="upper duty limit [1] (default: 1)")


def _add_controller_design_options(parser) -> None:
    """What export-controller and export-ssp need to design a built-in controller on the plant (read by
    :func:`_design_controller`): the PI's gains and the duty limits, the predictive controllers' optimizer and RTI
    settings, the samples and seed of an NN plant model
    trained on demand, and the folder the tuned gains and trained networks are cached in."""
    _add_pi_and_duty_options(parser, gains_default="tuned on the plant")
    _add_optimizer_options(parser, EXPORTED_PREDICTIVE)
    parser.add_argument("--samples", type=bounded(int, MIN_SAMPLES), default=None,
                        help=f"samples of PI data an NNPC's network is identified from when trained on demand"
                        f" (>= {MIN_SAMPLES}; default: {ON_DEMAND_SAMPLES}); refused where none is")
    parser.add_argument("--seed", type=seed_value, default=0, help=f"random seed, 0 .. {SEED_MAX} (default: 0)")
    parser.add_argument("--work-dir", default=str(DEFAULT_RESULTS / "runs-cli"), metavar="DIR",
                        help="where tuned gains and trained networks are cached, created only when one is "
                             "(default: results/runs-cli, relative to the current folder)")


def _add_fmi_version_option(p, whose: str) -> None:
    p.add_argument("--fmi-version", type=int, choices=(2, 3), default=2, metavar="{2,3}",
                   help=f"{whose} FMI version: 2 (FMI 2.0, the default) or 3 (FMI 3.0)")
