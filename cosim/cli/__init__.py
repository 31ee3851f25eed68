"""``buck-cosim``: the workbench's command line.

Every user mistake ends in one line ``error: ...`` on stderr and a non-zero exit code:
2 bad input or configuration, 3 a plant or controller fault during a run, 4 the FMU build
failed, 5 a sweep's dask scheduler went away, 130 interrupted (Ctrl-C or SIGTERM). Completed runs are kept on disk in every case.
``--debug`` (or ``BUCK_COSIM_DEBUG=1``) prints the whole traceback after that line.

One module per command group (run, export, design, studies, bench), each with its commands and
their parsers; the options several commands share are in :mod:`cosim.cli.options`. The parser
and the dispatch (signals, one-line errors, exit codes) are here, in one place.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys

from cosim.base.errors import WorkbenchError
from cosim.cli import bench, design, export, run, studies
from cosim.cli.options import OneLineParser

#: every command's parser, in the order ``buck-cosim --help`` lists them
PARSERS = (run.add_scenarios_parser, run.add_run_parser, design.add_collect_data_parser, design.add_train_parser,
           design.add_distill_parser, export.add_export_controller_parser, export.add_export_ssp_parser,
           export.add_run_ssp_parser, run.add_inspect_parser, run.add_export_parser, run.add_plot_parser,
           run.add_compare_parser, export.add_build_fmu_parser,
           design.add_tune_pi_parser, studies.add_reproduce_parser, studies.add_study_parser, studies.add_sweep_parser,
           studies.add_frequency_response_parser, bench.add_bench_parser)


#: an environment variable that asks for tracebacks as --debug does (for commands started by other programs)
DEBUG_VARIABLE = "BUCK_COSIM_DEBUG"
#: a token that is a number, negative or with an exponent (argparse takes "-1e-3" for an option)
NUMBER = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|nan)$", re.IGNORECASE)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("buck-cosim")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _numbers_as_values(parser: argparse.ArgumentParser, argv: list[str]) -> list[str]:
    """``--control-period -1e-3`` as ``--control-period=-1e-3``: argparse takes a token starting with "-" for an
    option unless it looks like a plain negative number, and would answer "expected one argument" instead of the
    option's own message about the value. Only options that take one value are joined."""
    valued = {option for action in _actions(parser) if action.option_strings and action.nargs is None
              and not isinstance(action, (argparse._StoreConstAction, argparse._StoreTrueAction,
                                          argparse._StoreFalseAction, argparse._CountAction,
                                          argparse._HelpAction, argparse._VersionAction))
              for option in action.option_strings}
    joined, i = [], 0
    while i < len(argv):
        if argv[i] in valued and i + 1 < len(argv) and NUMBER.match(argv[i + 1]):
            joined.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            joined.append(argv[i])
            i += 1
    return joined


def _actions(parser: argparse.ArgumentParser):
    """Every action of ``parser`` and of its sub-commands' parsers."""
    for action in parser._actions:
        yield action
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _actions(sub)


def _print_traceback(error: BaseException) -> None:
    """The whole story of ``error`` for --debug: its traceback, and that of the fault it carries (a failed run's
    cause, a controller's own exception)."""
    import traceback

    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        traceback.print_exception(error, file=sys.stderr)
        error = getattr(error, "cause", None)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="buck-cosim",
        description="FMU co-simulation workbench for a 48 V -> 12 V buck converter: PI, NNPC and MPC controllers "
                    "driving an FMI 2.0 or 3.0 plant through fmpy. Units: seconds, volts, amperes, ohms.")
    parser.add_argument("--no-progress", dest="progress", action="store_false",
                        help="hide progress bars (shown by default on long runs)")
    parser.add_argument("--debug", action="store_true",
                        help=f"after the one-line error, print the whole traceback (also: {DEBUG_VARIABLE}=1)")
    parser.add_argument("--version", action="version", version=f"buck-cosim {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add_parser in PARSERS:
        add_parser(sub)
    return parser


def _quiet_half_built_dask_objects(unraisable) -> None:
    """``sys.unraisablehook`` once the user has interrupted: drop the AttributeError that a half-built dask
    ``Future``'s finalizer raises, report every other unraisable exception as Python does.

    An interrupt lands wherever the main thread is; in a sweep that may be inside distributed's ``Future``
    constructor, which then leaves an object without its ``_client`` whose ``__del__`` fails when it is collected
    after the one-line "interrupted" -- Python prints that as "Exception ignored in ... Traceback", a traceback for an
    interrupt the workbench handled (seen in the interrupted-reproduction test, by the timing of the signal)."""
    finalizer = getattr(unraisable, "object", None)
    module = getattr(finalizer, "__module__", None) or ""
    if isinstance(unraisable.exc_value, AttributeError) and module.split(".")[0] == "distributed":
        return
    sys.__unraisablehook__(unraisable)


def _interrupted() -> None:
    sys.unraisablehook = _quiet_half_built_dask_objects


def _raise_interrupt(signum, frame):
    _interrupted()
    raise KeyboardInterrupt


def _stdout_closed() -> bool:
    """Is stdout a pipe whose reader has gone? (Polling its descriptor reports an error condition then.)"""
    import select

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(event & select.POLLERR for _, event in poller.poll(0))
    except (OSError, ValueError, AttributeError):  # no descriptor (a captured stream): not a closed pipe
        return False


def _discard_stdout() -> None:
    """Point stdout at /dev/null: Python flushes it again at exit, which would fail on the closed pipe once more."""
    try:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(_numbers_as_values(parser, list(sys.argv[1:] if argv is None else argv)))
    debug = args.debug or os.environ.get(DEBUG_VARIABLE, "") not in ("", "0")
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        return args.func(args) or 0
    except WorkbenchError as error:
        print(f"error: {' '.join(str(error).split())}", file=sys.stderr)
        if debug:
            _print_traceback(error)
        return error.exit_code
    except KeyboardInterrupt:
        _interrupted()
        print("error: interrupted; files already complete were kept and none is half-written", file=sys.stderr)
        return 130
    except BrokenPipeError as error:
        if _stdout_closed():  # the reader of the output went away (``| head``): a normal end, not an error
            _discard_stdout()
            return 0
        print(f"error: {error.strerror or error}", file=sys.stderr)  # another pipe (a process, a socket)
        return 2
    except OSError as error:  # a file system refusal (disk full, permissions): one line, not a traceback
        where = f"{error.filename}: " if error.filename else ""
        print(f"error: {where}{error.strerror or error}", file=sys.stderr)
        return 2
    except Exception as error:
        from plant_fmu import PlantBuildError

        if isinstance(error, PlantBuildError):
            print(f"error: {str(error).splitlines()[0]}", file=sys.stderr)
            return 4
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
