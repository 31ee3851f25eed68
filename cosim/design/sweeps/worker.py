"""What a dask worker does with a task: run a batch of runs on one reused FMU instance.

The fmpy ``parameter_variation`` pattern: the FMU is instantiated once per worker thread and
reset between runs (``cosim.master.run`` re-initialises it with the run's parameters, set by
:meth:`~cosim.fmi.plant_fmi2.FmuPlant.replace_parameters`), never reloaded per run. Plants and controllers
are kept per thread across tasks, so a worker pays for extracting the FMU, loading the model and
building the C twins once. An FMU that reported ``fmi2Fatal`` is dropped and a fresh instance
serves the next run.

A run that fails (the FMU errors or discards a step, an output turns NaN, the controller fails, the
FMU refuses a parameter value) is a row with status ``failed`` and the cause; the batch goes on.
Wall-clock figures (the run's duration, the controller's compute time) come back apart from the
rows, so the dataset stays byte-identical when the sweep is repeated.
"""

from __future__ import annotations

import atexit
import itertools
import math
import os
import socket
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from cosim.base.errors import WorkbenchError
from cosim.design.sweeps.designs import build
from cosim.design.sweeps.plan import PlannedRun, at_operating_point
from cosim.design.sweeps.process_files import process_file
from cosim.design.sweeps.recipes import ControllerRecipe, PlantRecipe
from cosim.design.vocabulary import DEFAULT_IMPLEMENTATION
from cosim.fmi.isolation import resident_bytes
from cosim.master import RunFailed, run_checked
from cosim.metrics import METRIC_COLUMNS, WALLCLOCK_METRICS, run_metrics
from cosim.scenarios import Scenario

OK, FAILED = "ok", "failed"
DETERMINISTIC_METRICS = tuple(m for m in METRIC_COLUMNS if m not in WALLCLOCK_METRICS)


@dataclass(frozen=True)
class RunSettings:
    record_period: float  # [s]
    implementation: str = DEFAULT_IMPLEMENTATION
    keep_traces: bool = False


@dataclass
class BatchResult:
    rows: list[dict]  # one per run: run id, indices, values, status, error, metrics
    timings: list[dict]  # one per run: run id, wall time, controller compute p50/p99, worker
    traces: list[tuple[str, object, dict]] = field(default_factory=list)  # (run id, frame, metadata)


# ---------------------------------------------------------------------------------------------
# per-process files and per-thread instances

_local = threading.local()


def fmu_file(recipe: PlantRecipe) -> Path:
    """This process's copy of the recipe's FMU (written once per digest)."""
    return process_file(recipe.fmu_name, recipe.fmu_bytes, recipe.fmu_digest)


def _cache() -> dict:
    if not hasattr(_local, "cache"):
        _local.cache = {}
        atexit.register(_close_all, _local.cache)
    return _local.cache


def _close_all(cache: dict) -> None:
    for value in list(cache.values()):
        close = getattr(value, "close", None)
        if close is not None:
            try:
                close()
            except Exception:
                pass
    cache.clear()


def _plant_key(recipe: PlantRecipe) -> tuple:
    return ("plant", recipe.fmu_digest, recipe.roles, recipe.parameters, recipe.interface, recipe.max_step, recipe.step)


def _plant(recipe: PlantRecipe):
    """This thread's instance of the recipe's plant (and its binding), opened on first use."""
    from cosim.fmi.plant import open_plant

    cache = _cache()
    entry = cache.get(_plant_key(recipe))
    if entry is None or entry[0].fatal:
        if entry is not None:
            entry[0].close()  # abandoned, not freed, as FMI 2.0 demands after fmi2Fatal
        plant = open_plant(recipe.binding(fmu_file(recipe)))
        # the plant's binding says what runs: in a daemonic worker an isolated binding is stepped in process
        entry = cache[_plant_key(recipe)] = _OpenPlant(plant, plant.binding)
    return entry


def _recover(recipe: PlantRecipe, plant) -> None:
    """After a failed run: back to the instantiated state for the next run, or a fresh instance
    next time if the FMU can no longer be reset."""
    if plant.fatal:
        return  # :func:`_plant` replaces it
    try:
        plant.reset()
    except WorkbenchError:
        _cache().pop(_plant_key(recipe), None)
        plant.close()


class _OpenPlant(tuple):
    """(plant, binding), closed together at exit."""

    def __new__(cls, plant, binding):
        return super().__new__(cls, (plant, binding))

    def close(self) -> None:
        self[0].close()


def _controller(recipe: ControllerRecipe, binding, implementation: str):
    cache = _cache()
    key = ("controller", recipe.digest, implementation)
    if key not in cache:
        cache[key] = build(recipe, binding, implementation)
    return cache[key]


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


# ---------------------------------------------------------------------------------------------
# the task


def run_batch(plant_recipe: PlantRecipe, controller_recipe: ControllerRecipe, scenario: Scenario,
              runs: tuple[PlannedRun, ...], settings: RunSettings) -> BatchResult:
    """Run every run of a batch; never raises for a run that fails (that is a row)."""
    import torch

    torch.set_num_threads(1)  # one worker process per core
    result = BatchResult([], [])
    nominal_parameters = dict(plant_recipe.parameters)
    name = worker_name()
    try:
        plant, binding = _plant(plant_recipe)
        controller = _controller(controller_recipe, binding, settings.implementation)
    except WorkbenchError as error:  # the worker cannot set up what every run needs: each run says why
        for run in runs:
            result.rows.append(run_row(run, FAILED, f"setting up on worker {name}: {error}", {}))
            result.timings.append(timing_row(run, math.nan, {}, name))
        return result
    settle = controller_recipe.settings.get("settle_s")  # a controller's own closed-loop time before t = 0
    if settle is not None:
        scenario = replace(scenario, settle=float(settle))
    for run in runs:
        if plant.fatal or _plant_key(plant_recipe) not in _cache():
            plant, binding = _plant(plant_recipe)
        start = time.perf_counter()
        metrics, status, error, trace = {}, OK, None, None
        try:
            plant.replace_parameters({**nominal_parameters, **dict(run.parameters)})
            outcome = run_checked(plant, controller, at_operating_point(scenario, dict(run.operating_point), run.anchors),
                                  record_period=settings.record_period,
                                  extra_metadata={"sweep_run": {"run_id": run.run_id, "point": run.point,
                                                                "sample": run.sample, "values": run.values}})
            metrics = run_metrics(outcome)
            results = getattr(controller, "run_results", None)  # what a measuring controller found (frequency response)
            if results is not None:
                metrics.update(results())
            trace = outcome
        except RunFailed as failure:
            status, error, trace = FAILED, str(failure), failure.partial
        except WorkbenchError as failure:  # refused before the first step, e.g. a parameter value
            status, error = FAILED, str(failure)
        except Exception as failure:  # a fault outside the workbench's own checks: still a row, with its cause
            status, error = FAILED, f"{type(failure).__name__}: {failure}"
        if status == FAILED:
            _recover(plant_recipe, plant)
        elapsed = time.perf_counter() - start
        result.rows.append(run_row(run, status, error, metrics))
        result.timings.append(timing_row(run, elapsed, metrics, name, next(_runs_here), _resident_mb()))
        if settings.keep_traces and trace is not None:
            result.traces.append((run.run_id, trace.frame.drop(columns=["controller_compute_time"], errors="ignore"),
                                  trace.metadata))
    return result


def run_row(run: PlannedRun, status: str, error: str | None, metrics: dict) -> dict:
    """A run's row: ids, values, status and every deterministic metric, plus what a measuring
    controller's ``run_results()`` reported (columns of the dataset's schema beyond the metrics)."""
    row = {"run_id": run.run_id, "point": run.point, "sample": run.sample, **run.values, "status": status,
           "error": " ".join(error.split()) if error else None}
    for column in DETERMINISTIC_METRICS:
        row[column] = float(metrics.get(column, math.nan))
    for column, value in metrics.items():
        if column not in row and column not in WALLCLOCK_METRICS:
            row[column] = value
    return row


def timing_row(run: PlannedRun, elapsed: float, metrics: dict, worker: str, worker_run: int | None = None,
               rss_mb: float = math.nan) -> dict:
    return {"run_id": run.run_id, "wall_time_s": elapsed,
            **{c: float(metrics.get(c, math.nan)) for c in WALLCLOCK_METRICS}, "worker": worker,
            "worker_run": worker_run, "worker_rss_mb": rss_mb}


_runs_here = itertools.count(1)  # this worker process's runs, in order


def _resident_mb() -> float:
    used = resident_bytes(os.getpid())
    return math.nan if used is None else used / 1e6


def worker_facts() -> dict:
    """What the workbench checks on every worker before it sends work: the FMI platform it can
    load binaries for, and the Python it runs."""
    import platform

    import fmpy

    return {"platform": fmpy.platform, "python": platform.python_version(), "host": socket.gethostname()}
