"""The reference views as Dask tasks: a local cluster of processes by default, or the user's.

Each task refines one reference view (:func:`.views.run_view`) in its own worker process with
one BLAS thread (the solver's BLAS calls are small; threads only contend). A task that fails
is reported and the others kept. Results are identical whatever the number of workers: each
view is computed by the same single-threaded code from the same inputs.
"""

from __future__ import annotations

import os
from contextlib import contextmanager

from tqdm.auto import tqdm

from .views import run_view

#: Environment of the local workers: one thread for every BLAS/OpenMP pool and numba's kernels.
SINGLE_THREAD_ENV = {name: "1" for name in (
    "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}


@contextmanager
def dask_client(client=None, scheduler: str | None = None, workers: int | None = None):
    """Yield a ``dask.distributed.Client``: ``client`` as given, one connected to ``scheduler``
    (``tcp://HOST:PORT``), or a new ``LocalCluster`` of ``workers`` single-threaded processes
    (default: the CPU count), closed on exit."""
    from dask.distributed import Client, LocalCluster

    if client is not None:
        yield client
        return
    if scheduler is not None:
        with Client(scheduler) as connected:
            yield connected
        return
    n = workers or os.cpu_count() or 1
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                      env=SINGLE_THREAD_ENV) as cluster, Client(cluster) as local:
        yield local


def run_views(jobs: list, options, depth_source: str, client, progress: bool = True,
              device="auto") -> tuple[list, dict]:
    """Run the jobs on ``client``; returns (results in job order, {reference: error message} of failures)."""
    from dask.distributed import as_completed

    futures = {client.submit(run_view, job, options, depth_source, device, pure=False): job.reference for job in jobs}
    results, failed = {}, {}
    bar = tqdm(total=len(jobs), desc=f"{depth_source} views", unit="view", disable=not progress)
    for future in as_completed(futures):
        reference = futures[future]
        if future.status == "error":
            error = future.exception()
            failed[reference] = f"{type(error).__name__}: {error}"
        else:
            results[reference] = future.result()
        bar.update(1)
    bar.close()
    return [results[job.reference] for job in jobs if job.reference in results], failed
