"""Errors the workbench reports to users as one line (the CLI prints ``error: <message>`` and exits non-zero).

Every message names the culprit (file, key, line, variable or value) and what was expected.
"""

from __future__ import annotations


class WorkbenchError(Exception):
    """A user-facing problem: bad input, a refused configuration or a failed run."""

    exit_code = 2


class ConfigError(WorkbenchError):
    """A scenario, binding or settings file (or a command-line value) is invalid."""


class FmuArchiveError(WorkbenchError):
    """An FMU file cannot be used (not a zip, unsafe members, wrong FMI version, no binary...)."""


class PlantError(WorkbenchError):
    """The plant FMU failed or produced non-finite values during a run."""

    exit_code = 3


class ControllerError(WorkbenchError):
    """A controller raised or returned a non-finite duty cycle."""

    exit_code = 3


class BuildError(WorkbenchError):
    """Compiling generated or shipped C failed (a cross build; the FMU builds raise PlantBuildError)."""

    exit_code = 4


class ModelFileError(WorkbenchError):
    """A trained-model file is missing, truncated, tampered with or made for other inputs."""


class ClusterLost(WorkbenchError):
    """The dask scheduler went away in the middle of the work (its process ended, its machine or the
    network failed); every part finished before is kept, and ``--resume`` against a new one finishes it."""

    exit_code = 5


class RunInterrupted(WorkbenchError):
    """The user interrupted a run (Ctrl-C / SIGTERM); ``partial`` holds what was recorded."""

    exit_code = 130

    def __init__(self, message: str, partial=None):
        super().__init__(message)
        self.partial = partial
