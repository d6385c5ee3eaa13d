"""The reference views as Dask tasks: a local cluster of processes by default, or the user's.

Each task refines one reference view (:func:`.views.run_view`) in its own worker process with
one BLAS thread (the solver's BLAS calls are small; threads only contend). A view's frames go
to the workers by ``client.scatter``, not inside the task graph (no "Sending large graph"
warnings, and the graph stays small). A task that fails is reported and the others kept; a
task whose worker died is retried once, and said so. Every wait ends: a scheduler address is
checked before connecting, a connection gives up after ``timeout`` seconds, and views that
have had no worker to run on for ``timeout`` seconds fail, naming the address. Results are
identical whatever the number of workers: each view is computed by the same single-threaded
code from the same inputs.
"""

from __future__ import annotations

import logging
import os
import re
import time
import warnings
from contextlib import contextmanager
from dataclasses import replace

from tqdm.auto import tqdm

from ..errors import MVPSError
from .views import run_view

#: Environment of the local workers: one thread for every BLAS/OpenMP pool and numba's kernels.
SINGLE_THREAD_ENV = {name: "1" for name in (
    "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}
#: Seconds to wait for a scheduler to answer, or for a worker to run the views on (--scheduler-timeout).
SCHEDULER_TIMEOUT = 60.0
#: ``[tcp|tls|ws|wss|ucx]://HOST:PORT`` (HOST a name, IPv4 or [IPv6]); Dask's own parser accepts anything.
_ADDRESS = re.compile(r"^(?:(tcp|tls|ws|wss|ucx)://)?(\[[0-9a-fA-F:]+\]|[A-Za-z0-9._-]+):(\d{1,5})$")
#: Seconds between the checks of a wait for results.
_POLL = 0.2


class SchedulerError(MVPSError, RuntimeError):
    """A Dask scheduler cannot be reached, has no workers, or lost them for good."""


def check_scheduler_address(address: str) -> str:
    """``address`` if it reads ``tcp://HOST:PORT`` (or ``tls://``, or ``HOST:PORT``); else
    SchedulerError naming it and the expected form (Dask would fail later with an ``int()`` error)."""
    if address.startswith("inproc://"):  # a scheduler in this process (LocalCluster(processes=False))
        return address
    match = _ADDRESS.match(address.strip())
    if match is None or not 0 < int(match.group(3)) < 65536:
        raise SchedulerError(f"scheduler address {address!r} is not of the form tcp://HOST:PORT (e.g. "
                             "tcp://10.0.0.5:8786, the address `dask scheduler` prints); fix --scheduler")
    return address.strip()


def quiet_open3d() -> None:
    """Only errors from Open3D's log (no INFO or WARNING lines)."""
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)


def quiet_dask() -> None:
    """Only errors from Dask's loggers (no socket, large-graph or shutdown notices)."""
    for name in ("distributed", "dask", "bokeh", "tornado"):
        logging.getLogger(name).setLevel(logging.ERROR)


@contextmanager
def dask_client(client=None, scheduler: str | None = None, workers: int | None = None, *,
                timeout: float = SCHEDULER_TIMEOUT, quiet: bool = False):
    """Yield a ``dask.distributed.Client``: ``client`` as given, one connected to ``scheduler``
    (``tcp://HOST:PORT``; SchedulerError naming it when it does not answer within ``timeout``
    seconds), or a new ``LocalCluster`` of ``workers`` single-threaded processes (default: the
    CPU count), closed on exit. ``quiet``: Dask logs errors only."""
    if quiet:
        quiet_dask()
    from dask.distributed import Client, LocalCluster

    if client is not None:
        yield client
        return
    if scheduler is not None:
        address = check_scheduler_address(scheduler)
        try:
            connected = Client(address, timeout=f"{timeout}s")
        except (OSError, TimeoutError) as error:
            raise SchedulerError(f"cannot reach the Dask scheduler at {address} within {timeout:g} s ({error}); "
                                 "check that `dask scheduler` runs there and the port, raise --scheduler-timeout, "
                                 "or leave out --scheduler for a local cluster") from None
        with connected:
            yield connected
        return
    n = workers if workers is not None else os.cpu_count() or 1
    # the scheduler serves HTTP even without a dashboard, on port 8787 unless told: a free local
    # port instead (no "Port 8787 is already in use" warning when another cluster runs)
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0",
                      env=SINGLE_THREAD_ENV, silence_logs=logging.ERROR if quiet else logging.WARNING) as cluster, \
            Client(cluster) as local:
        yield local


def _run_scattered(job, arrays, options, depth_source: str, quiet: bool, device="auto"):
    """:func:`.views.run_view` of ``job`` with its frames ``arrays`` (scattered to the worker) on
    ``device``; the Python warnings it raised come back on the result. ``quiet``: Open3D logs
    errors only."""
    if quiet:
        quiet_open3d()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = run_view(replace(job, arrays=arrays), options, depth_source, device)
    result.warnings = list(dict.fromkeys(str(w.message) for w in caught))
    return result


def _address(client) -> str:
    return getattr(client.scheduler, "address", None) or "the local cluster"


def run_views(jobs: list, options, depth_source: str, client, progress: bool = True, *,
              timeout: float = SCHEDULER_TIMEOUT, device="auto") -> tuple[list, dict, dict]:
    """Run the jobs on ``client``, each view refined on ``device``.

    Returns (results in job order, {reference: error message} of failures, {reference or
    "lost workers": why} of views run again because their worker died: Dask reschedules a lost
    worker's task by itself, and the lost workers are listed; a view that failed for it is
    submitted once more). Views wait at most ``timeout`` seconds while the
    scheduler has no worker (none started, or all lost): then SchedulerError names the address.
    """
    from dask.distributed import wait
    from distributed.client import FuturesCancelledError
    from distributed.scheduler import KilledWorker

    try:
        client.wait_for_workers(1, timeout=timeout)
    except TimeoutError:
        raise SchedulerError(f"the Dask scheduler at {_address(client)} has no workers after {timeout:g} s; start "
                             f"workers (`dask worker {_address(client)}`), raise --scheduler-timeout, or leave out "
                             "--scheduler for a local cluster") from None
    by_reference = {job.reference: job for job in jobs}
    seen, lost = set(client.scheduler_info().get("workers", {})), []

    def submit(job):
        [arrays] = client.scatter([job.arrays], hash=False)  # the frames travel apart from the graph
        return client.submit(_run_scattered, replace(job, arrays=None), arrays, options, depth_source, not progress,
                             device, pure=False)

    futures = {submit(job): job.reference for job in jobs}
    results, failed, retried = {}, {}, {}
    bar = tqdm(total=len(jobs), desc=f"{depth_source} views", unit="view", disable=not progress)
    pending, idle_since = set(futures), None
    while pending:
        try:
            wait(pending, timeout=_POLL, return_when="FIRST_COMPLETED")
        except (TimeoutError, FuturesCancelledError):  # nothing finished within the poll; a view cancelled
            pass
        done = {future for future in pending if future.done()}
        pending -= done
        for future in done:
            reference = futures.pop(future)
            if future.status in ("error", "cancelled", "lost"):
                error = future.exception() if future.status == "error" else None
                worker_died = error is None or isinstance(error, KilledWorker)
                if worker_died and reference not in retried:  # its worker died: once more, with its frames sent again
                    retried[reference] = f"its worker was lost ({error or future.status})"
                    again = submit(by_reference[reference])
                    futures[again] = reference
                    pending.add(again)
                    continue
                failed[reference] = f"{type(error).__name__}: {error}" if error else "its worker was lost twice"
            else:
                results[reference] = future.result()
            bar.update(1)
        workers = set(client.scheduler_info().get("workers", {}))
        lost += sorted(seen - workers - set(lost))
        seen |= workers
        if pending and not done:
            if workers:
                idle_since = None
            elif idle_since is None:
                idle_since = time.monotonic()
            elif time.monotonic() - idle_since > timeout:
                for future in pending:
                    future.cancel()
                bar.close()
                raise SchedulerError(
                    f"the Dask scheduler at {_address(client)} has had no workers for {timeout:g} s, with "
                    f"{len(pending)} of {len(jobs)} views left; start workers (`dask worker {_address(client)}`), "
                    "raise --scheduler-timeout, or leave out --scheduler for a local cluster")
    bar.close()
    if lost:
        retried["lost workers"] = (f"{', '.join(lost)} left the scheduler while views ran; Dask ran their views "
                                   "again on the other workers")
    return [results[job.reference] for job in jobs if job.reference in results], failed, retried
