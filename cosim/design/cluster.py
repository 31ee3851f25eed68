"""The dask cluster the study's parallel work runs on: a LocalCluster on this machine, or a running one.

* :func:`dask_client` -- ``scheduler=None``: a ``LocalCluster`` on the loopback interface, one
  worker process per core and one thread each (the FMU loops and the controllers hold the GIL, so
  threads would not run in parallel), closed on the way out whatever happens (the worker processes
  end with it); ``scheduler="tcp://HOST:PORT"``: a client of a cluster started with the standard
  ``dask scheduler`` / ``dask worker`` commands, which is left running.
* Local worker processes ignore Ctrl-C (:class:`IgnoreInterrupts`): the terminal sends SIGINT to the
  whole process group, and the workbench's own process decides what an interrupt means (cancel,
  close the cluster, keep what is done) -- without it every worker prints a KeyboardInterrupt
  traceback. The workers of a cluster the user started are left as they are.
* dask's own log lines are silenced below CRITICAL (``DASK_LOGGING__DISTRIBUTED`` set in the
  environment overrides this): the workbench reports a worker death or a failed task itself, in one
  line, and dask would print the task's traceback even for a fault the workbench handles.

* Every worker must run the numeric kernels of this process (:mod:`cosim.base.numeric_env`: local
  workers inherit them with the environment); a cluster with a worker that differs is refused with
  one line (a :class:`ConfigError`) before anything is submitted.

A crash in a task's native code (an FMU that segfaults) kills its worker process; the nanny starts
a new one and the scheduler runs the task again, up to ``allowed_failures`` times on a local
cluster, then the task's future raises ``KilledWorker`` and the caller decides.
"""

from __future__ import annotations

import logging
import os
import re
import signal
from contextlib import contextmanager
from typing import Iterator

from distributed.diagnostics.plugin import WorkerPlugin

from cosim.base.errors import ConfigError
from cosim.base.numeric_env import check_worker_environment, kernel_environment

#: dask settings of the local workers, for FMU loops and controllers that hold the GIL and allocate
#: many small numpy arrays: no statistical profiler (it samples every thread's stack every 10 ms
#: under the GIL; measured at 15-40 % of a 1 ms sweep's run time), and glibc's own heap trimming
#: instead of the nanny's MALLOC_TRIM_THRESHOLD_=65536 (measured: a 13.33 us pipeline ran 20-30 %
#: slower with it). For one's own ``dask worker`` processes docs/guide/sweeps.md gives the same as dask YAML.
#: ``daemon`` off: a worker steps a binding file's plant FMU in a child process of its own
#: (:mod:`cosim.fmi.isolation`), which a daemonic process may not start; the nanny still ends its
#: worker, and the plant process ends when its pipe closes
WORKER_SETTINGS = {"distributed.worker.profile.enabled": False, "distributed.worker.daemon": False,
                   "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}
#: how long to try to reach a scheduler before refusing the address [s]
CONNECT_TIMEOUT = 10.0
#: a task whose worker died running it is run again this many times, then reported as killed
ALLOWED_FAILURES = 1
#: on a fault or an interrupt, a local worker gets this long [s] to stop before it is killed
KILL_TIMEOUT = 0.5
LOOPBACK = "127.0.0.1"
_ADDRESS = re.compile(r"(tcp|tls)://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})")


def local_cores() -> int:
    """Cores this process may use (the default number of local workers)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def check_address(address: str) -> str:
    """A scheduler address ``tcp://HOST:PORT`` (or ``tls://``), refused with one line otherwise."""
    match = _ADDRESS.fullmatch(address.strip())
    if not match or not 0 < int(match.group(3)) < 65536:
        raise ConfigError(f"--scheduler {address!r} is not a dask scheduler address: expected tcp://HOST:PORT "
                          "(what `dask scheduler` prints as 'Scheduler at:')")
    return address.strip()


def _log_level() -> int:
    """dask's log level for this process and its local workers: CRITICAL unless the user set one."""
    configured = os.environ.get("DASK_LOGGING__DISTRIBUTED", "")
    level = logging.getLevelName(configured.upper()) if configured else logging.CRITICAL
    return level if isinstance(level, int) else logging.WARNING


class IgnoreInterrupts(WorkerPlugin):
    """Local worker processes leave Ctrl-C to the workbench's process (set up on every worker, restarted ones too)."""

    name = "buck-cosim-ignore-interrupts"

    def setup(self, worker) -> None:
        try:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        except ValueError:  # not the main thread of the process (a threaded worker's setup)
            pass


@contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None, *,
                connect_timeout: float = CONNECT_TIMEOUT, allowed_failures: int = ALLOWED_FAILURES,
                worker_saturation: float | None = None) -> Iterator:
    """A dask ``Client``: of a new LocalCluster (``workers`` processes, default one per core) or of
    the running scheduler at ``scheduler``. An unreachable scheduler is a :class:`ConfigError`
    raised before anything is submitted. The local cluster is always closed on the way out.

    ``worker_saturation`` (local cluster): tasks in flight per worker thread; 1.0 keeps every task
    not yet running in the scheduler's queue, in priority order -- right for a few long tasks of
    very different lengths (the reproduction's pipelines); dask's default (1.1, so one task waits on
    each worker) suits many short ones (a sweep's batches)."""
    import dask
    from distributed import Client, LocalCluster

    level = _log_level()
    # dask's logging configuration gives some children their own level (distributed.client: warning, whose
    # reconnect loop logs a traceback when a lost scheduler's client is closed): set them all
    children = [name for name in logging.Logger.manager.loggerDict if name.startswith(("distributed.", "tornado."))]
    for name in ("distributed", "tornado", "distributed.client", *children):
        logging.getLogger(name).setLevel(level)
    cluster = None
    if scheduler is not None:
        address = check_address(scheduler)
        try:
            client = Client(address, timeout=connect_timeout, set_as_default=False)
        except (OSError, TimeoutError) as error:
            reason = " ".join(str(error).split()) or type(error).__name__
            raise ConfigError(f"cannot reach the dask scheduler at {address} within {connect_timeout:g} s ({reason}): "
                              "start one with `dask scheduler` and workers with `dask worker "
                              f"{address}`, or leave out --scheduler to use this machine") from None
        try:
            client.wait_for_workers(1, timeout=connect_timeout)
        except (OSError, TimeoutError):
            client.close()
            raise ConfigError(f"the dask scheduler at {address} has no workers (waited {connect_timeout:g} s): start "
                              f"some with `dask worker {address}`") from None
    else:
        workers = workers or local_cores()
        settings = {"distributed.scheduler.allowed-failures": allowed_failures, **WORKER_SETTINGS}
        if worker_saturation is not None:
            settings["distributed.scheduler.worker-saturation"] = worker_saturation
        with dask.config.set(settings):
            cluster = LocalCluster(host=LOOPBACK, n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=f"{LOOPBACK}:0", silence_logs=level)
        client = Client(cluster, set_as_default=False)
    stopping = False
    try:
        mismatch = check_worker_environment(client.run(kernel_environment))
        if mismatch:  # their models would not be this machine's bytes (cosim/base/numeric_env.py)
            raise ConfigError(mismatch)
        if cluster is not None:  # our own workers only: a user's `dask worker` keeps its Ctrl-C
            client.register_plugin(IgnoreInterrupts())
        yield client
    except BaseException:
        stopping = True  # a fault or an interrupt: the local workers end now, not after their tasks
        raise
    finally:
        try:
            client.close(timeout=10)
        finally:
            if cluster is not None:
                if stopping:
                    cluster.sync(_kill_workers, cluster, KILL_TIMEOUT)
                cluster.close(timeout=20)


async def _kill_workers(cluster, timeout: float) -> None:
    """``Nanny.kill`` every local worker with a short timeout: a closing cluster otherwise waits
    seconds for each running task (an FMU loop does not stop for a close request)."""
    import asyncio

    await asyncio.gather(*(worker.kill(timeout=timeout) for worker in list(cluster.workers.values())),
                         return_exceptions=True)


def cluster_text(client) -> str:
    """``a LocalCluster of 2 workers`` / ``the cluster at tcp://host:8786 (4 workers)`` for log lines."""
    workers = len(client.scheduler_info().get("workers", {}))
    address = client.scheduler.address
    if address.startswith(f"tcp://{LOOPBACK}:") and getattr(client, "cluster", None) is not None:
        return f"a LocalCluster of {workers} worker process(es)"
    return f"the cluster at {address} ({workers} worker(s))"
