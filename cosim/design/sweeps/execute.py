"""Running a sweep's tasks on a dask cluster, writing each part as its task finishes.

* Tasks are submitted at once; dask's scheduler hands them to the workers as they free up. The
  workbench's process writes each finished task's rows as one part (a remote worker need not see
  the output folder), with a progress bar over runs.
* A worker process that dies (killed, out of memory, a crash in an FMU's native code) loses its
  task; dask runs it again elsewhere. A task that kills its worker again (``KilledWorker``) is split
  into one task per run, so the runs that are fine complete. A single run can still see
  ``KilledWorker`` without being the cause -- dask counts every task queued on a dying worker -- so
  it is submitted again, up to :data:`SINGLE_RUN_ATTEMPTS` times in all; a run that kills its worker
  every time is a ``failed`` row naming that cause. The sweep goes on either way.
* Ctrl-C / SIGTERM: the pending tasks are cancelled and the caller closes the cluster; every part
  on disk is complete (atomic writes), and ``--resume`` runs exactly the runs without a row.
* The scheduler goes away (its process ends, its machine or the network fails): dask cancels every
  pending future ("scheduler-connection-lost"). That is no fault of the runs -- nothing is written
  for them -- and the execution ends with :class:`~cosim.base.errors.ClusterLost` (exit 5): every
  finished part is kept, and ``--resume`` against a new scheduler runs exactly the rest.

:class:`SweepExecution` is the sweep as a set of futures, so the reproduction can run a tolerance
study on the same client as its pipelines, mixed into one ``as_completed`` loop.
"""

from __future__ import annotations

import sys
import time
from concurrent.futures import CancelledError
from dataclasses import dataclass

from cosim.base.errors import ClusterLost, RunInterrupted
from cosim.design.sweeps.dataset import write_part, write_timing, write_trace
from cosim.design.sweeps.plan import BatchTask, batch_key
from cosim.design.sweeps.worker import FAILED, BatchResult, RunSettings, run_batch, run_row, timing_row

#: the cause of a run whose worker died each time the scheduler ran it (twice on the local cluster;
#: a remote scheduler's distributed.scheduler.allowed-failures + 1 times)
WORKER_DIED = ("the worker process running it died each time it ran (a crash in the FMU's native code, or out of "
               "memory?); run it alone with buck-cosim run to see the cause")


#: how often a single run that met ``KilledWorker`` is submitted in all before it is a ``failed`` row (the
#: culprit kills its worker each time; a bystander queued on that worker completes on its next attempt)
SINGLE_RUN_ATTEMPTS = 3


@dataclass
class ExecutionCounts:
    runs: int = 0  # runs this execution wrote
    failed: int = 0
    parts: int = 0
    elapsed: float = 0.0  # [s] from the first submission to the last part


class SweepExecution:
    """The tasks of one sweep on one client; :meth:`handle` writes a finished task's part."""

    def __init__(self, tasks: list[BatchTask], plant, controllers: dict, scenarios: dict, settings: RunSettings,
                 schema, out_dir, progress: bool = False, label: str = "sweep"):
        self.tasks, self.plant, self.controllers, self.scenarios = tasks, plant, controllers, scenarios
        self.settings, self.schema, self.out_dir = settings, schema, out_dir
        self.counts = ExecutionCounts()
        self._pending: dict[str, tuple[BatchTask, int]] = {}  # future key -> task, how often it was submitted
        self._futures: dict[str, object] = {}
        self._client, self._priority = None, 0
        self._started = None
        self._bar = None
        if progress and tasks:
            from tqdm import tqdm

            self._bar = tqdm(total=sum(len(t.runs) for t in tasks), desc=label, unit="run", file=sys.stderr,
                             mininterval=0.5, dynamic_ncols=True)

    @property
    def pending(self) -> int:
        return len(self._pending)

    def submit(self, client, priority: int = 0) -> list:
        """Every task to ``client`` (dask ``priority``: higher runs first); the futures to wait on."""
        self._client, self._priority = client, priority
        self._started = time.perf_counter()
        return [self._submit(task) for task in self.tasks]

    def _submit(self, task: BatchTask, attempt: int = 1):
        key = f"buck-cosim-sweep-{task.key}" + (f"-attempt-{attempt}" if attempt > 1 else "")
        future = self._client.submit(run_batch, self.plant, self.controllers[task.controller],
                                     self.scenarios[task.scenario], task.runs, self.settings, key=key, pure=False,
                                     retries=0, priority=self._priority)
        self._pending[future.key] = (task, attempt)
        self._futures[future.key] = future
        return future

    def owns(self, future) -> bool:
        return future.key in self._pending

    def handle(self, future) -> list:
        """Write a finished future's part (or split a task that killed its worker); new futures to wait on.
        A future cancelled by dask, not by :meth:`cancel`, means the scheduler went away: :class:`SchedulerGone`."""
        from distributed.comm.core import CommClosedError
        from distributed.scheduler import KilledWorker

        if future.status == "cancelled":  # only dask cancels a pending future: cancel() stops handling first
            raise SchedulerGone(future.key)
        if future.status == "finished":
            try:
                result = future.result()
            except (CommClosedError, CancelledError):  # finished, but the scheduler went away before the result came
                raise SchedulerGone(future.key) from None
        task, attempt = self._pending.pop(future.key)
        self._futures.pop(future.key, None)
        if future.status == "finished":
            self._write(task, result)
            return []
        try:
            error = future.exception()
        except Exception as cancelled:  # a future the scheduler cancelled has no exception to give
            error = cancelled
        if isinstance(error, KilledWorker) and len(task.runs) > 1:  # find the run that kills: one task per run
            return [self._submit(BatchTask(batch_key((run,)), task.controller, task.scenario, (run,)))
                    for run in task.runs]
        if isinstance(error, KilledWorker) and attempt < SINGLE_RUN_ATTEMPTS:  # the culprit, or a bystander
            return [self._submit(task, attempt + 1)]
        cause = WORKER_DIED if isinstance(error, KilledWorker) else \
            f"the task failed on its worker: {type(error).__name__}: {' '.join(str(error).split())}"
        self._write(task, BatchResult([run_row(r, FAILED, cause, {}) for r in task.runs],
                                      [timing_row(r, float('nan'), {}, "") for r in task.runs]))
        return []

    def _write(self, task: BatchTask, result: BatchResult) -> None:
        for run_id, frame, metadata in result.traces:
            write_trace(self.out_dir, run_id, frame, metadata)
        write_timing(self.out_dir, task.key, result.timings)
        write_part(self.out_dir, task.controller, task.scenario, task.key, result.rows, self.schema)
        self.counts.runs += len(result.rows)
        self.counts.failed += sum(row["status"] == FAILED for row in result.rows)
        self.counts.parts += 1
        self.counts.elapsed = time.perf_counter() - self._started
        if self._bar is not None:
            self._bar.update(len(result.rows))
            if self.counts.failed:
                self._bar.set_postfix_str(f"{self.counts.failed} failed", refresh=False)

    def cancel(self) -> None:
        """Cancel what has not finished (an interrupt): nothing more is written."""
        if self._client is not None and self._futures:
            try:
                self._client.cancel(list(self._futures.values()), force=True)
            except Exception:
                pass
        self._pending.clear()
        self._futures.clear()
        self.close()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


class SchedulerGone(Exception):
    """dask cancelled a pending future: the client lost its scheduler (see the module docstring)."""


def scheduler_lost(counts: ExecutionCounts) -> str:
    """The default :class:`ClusterLost` message of :func:`execute`."""
    return (f"the dask scheduler went away (the client lost its connection) after {counts.runs} run(s); what "
            "finished is kept")


def execute(execution: SweepExecution, client, interrupted_message, lost_message=scheduler_lost) -> ExecutionCounts:
    """Run ``execution`` to the end on ``client``. On Ctrl-C / SIGTERM: cancel, and raise
    :class:`RunInterrupted` with ``interrupted_message(counts)``; when the scheduler goes away, raise
    :class:`ClusterLost` with ``lost_message(counts)``."""
    from distributed import as_completed
    from distributed.comm.core import CommClosedError

    futures = execution.submit(client)
    try:
        try:
            queue = as_completed(futures, loop=client.loop)
            for future in queue:
                for new in execution.handle(future):
                    queue.add(new)
        except CommClosedError:  # the connection to the scheduler closed under a call of ours
            raise SchedulerGone() from None
    except KeyboardInterrupt:
        execution.cancel()
        raise RunInterrupted(interrupted_message(execution.counts)) from None
    except SchedulerGone:
        execution.cancel()
        raise ClusterLost(lost_message(execution.counts)) from None
    except BaseException:
        execution.cancel()
        raise
    execution.close()
    return execution.counts
