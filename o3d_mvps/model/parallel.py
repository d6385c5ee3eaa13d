"""How the package's compiled parallel loops (numba, OpenMP threading layer) wait between launches.

GNU OpenMP's worker threads spin for about 300 000 pause loops (milliseconds) after every
parallel region before they sleep, and its barrier spins too. The solver launches some 12 000
short parallel kernels per D415 refinement with serial Python between them: the spinning worker
took a core from the main thread and from other processes. With 2 numba threads on a loaded
2-core machine a D415 refinement took 71 CPU s and 250 s wall instead of 21 CPU s and 70 s, and
a loop of 2000 launches of a 90k-pixel kernel 87-112 s wall instead of 1.5-9 s. Passive waiting
(threads sleep at once, woken by the kernel: some microseconds a launch) changes no result.
"""

from __future__ import annotations

import os

#: the GNU OpenMP wait policy the package asks for, unless the user set one (or a spin count)
WAIT_POLICY = "PASSIVE"
#: environment variables by which a user chooses the waiting themselves (then left alone)
USER_SETTINGS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def configure_openmp(environ=os.environ) -> bool:
    """Ask OpenMP for passive waiting (:data:`WAIT_POLICY`) in ``environ`` (the process's);
    True where it was set, False where the user set ``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT``.

    OpenMP reads it once, when its library loads: numba loads it at the first parallel launch,
    after this runs on import of :mod:`o3d_mvps.model`. Where another package loaded OpenMP
    before, its setting stays (set ``OMP_WAIT_POLICY=PASSIVE`` before starting Python then).
    """
    if any(name in environ for name in USER_SETTINGS):
        return False
    environ["OMP_WAIT_POLICY"] = WAIT_POLICY
    return True


#: Grid pixels per compiled-kernel thread: a level with fewer object pixels than twice this runs its
#: kernels on one thread. On the D415 render's coarse levels (about 340, 1 300 and 5 400 pixels,
#: 23 of its 40 sweeps) a launch lasts tens of microseconds to a few hundred, and waking and
#: joining a second thread costs tens of microseconds (docs/performance.md, "D415 in seconds").
PIXELS_PER_THREAD = 8192


def kernel_threads(pixels: int, available: int | None = None) -> int:
    """Threads for the compiled kernels of a problem of ``pixels`` grid pixels: one per
    :data:`PIXELS_PER_THREAD` pixels, at least 1 and at most ``available`` (default: numba's
    configured count, ``NUMBA_NUM_THREADS``)."""
    if available is None:
        import numba

        available = numba.config.NUMBA_NUM_THREADS
    return int(max(1, min(available, pixels // PIXELS_PER_THREAD)))


def current_kernel_threads() -> int:
    """The thread count of this thread's numba launches (``numba.get_num_threads``)."""
    import numba

    return numba.get_num_threads()


def set_kernel_threads(threads: int) -> int:
    """Have this thread's later numba launches use ``threads`` threads; returns the count they
    used before (to restore)."""
    import numba

    previous = numba.get_num_threads()
    numba.set_num_threads(threads)
    return previous
