"""Shared fixtures; helpers shared by several test files live in tests/helpers.py (importable as
``helpers``: pytest puts this folder on sys.path). Keep renders small: the suite must stay fast
on a 2-core machine.

First of all: without a GPU, numba's CUDA kernels (tests/test_cuda_kernels.py) run in numba's
CUDA simulator, which numba.cuda picks at its first import from NUMBA_ENABLE_CUDASIM; so that is
set here, before any test module imports numba. A GPU counts when ``nvidia-smi -L`` lists one
(the driver's tool: no CUDA library is loaded to ask). NUMBA_ENABLE_CUDASIM set by the caller
(1: simulate even with a GPU) is left as it is. With the simulator on, its array wrappers and its
block manager's polling are made cheaper (:func:`_speed_up_the_simulator`; the same semantics).
"""

import os
import shutil
import subprocess


def _nvidia_gpu_listed() -> bool:
    """Whether ``nvidia-smi -L`` runs and lists a GPU."""
    smi = shutil.which("nvidia-smi")
    if smi is None:
        return False
    try:
        listed = subprocess.run([smi, "-L"], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return False
    return listed.returncode == 0 and "GPU" in listed.stdout


if not _nvidia_gpu_listed():
    os.environ.setdefault("NUMBA_ENABLE_CUDASIM", "1")


def _speed_up_the_simulator() -> None:
    """numba's CUDA simulator, the same semantics at a fraction of the CPU time (the suite's
    simulated kernels: tests/test_cuda_kernels.py, the CUDA path's tests, benchmarks.gpu's test).

    Measured on benchmarks.gpu's 64x48 problem (tests/test_benchmarks.py), whose device multigrid
    set-up inverts its 226-unknown coarsest level by Gauss-Jordan, 226 barriers over 51076 entries
    each: 105 of the test's 131 CPU seconds. Two costs, neither the kernels' own:

    - a kernel's array access went through two Python wrappers (FakeWithinKernelCUDAArray ->
      FakeCUDAArray -> ndarray; ``a.shape`` built a FakeShape through both ``__getattr__``): one
      Gauss-Jordan entry 3.0 us, 1.4 us with the ndarray indexed at once. The same objects come
      back (an ndarray or record is wrapped as before, a scalar is the ndarray's scalar);
    - the block's manager polled its 128 threads in a loop that never waits, taking the GIL from
      the threads it waits for. Here each thread says when it reaches a barrier or ends, and the
      manager sleeps until all have (a 10 ms timeout falls back to the original polling). A
      barrier still releases the block only when every live thread is blocked in it.

    Left as numba has them where its internals are not the ones this was written against
    (numba-cuda 0.30).
    """
    import threading

    from numba.cuda.simulator import kernel
    from numba.cuda.simulator.cudadrv import devicearray

    fake, manager, thread = devicearray.FakeWithinKernelCUDAArray, kernel.BlockManager, kernel.BlockThread
    if not all(hasattr(c, a) for c, a in ((devicearray, "FakeCUDAArray"), (devicearray, "FakeShape"),
                                          (thread, "syncthreads"), (manager, "run"))):
        return
    wrapped = (np.ndarray, np.void)

    def getitem(self, idx):
        item = self._item
        value = item._ary[idx]
        if type(value) in wrapped:
            return fake(devicearray.FakeCUDAArray(value, stream=item.stream))
        return value

    def setitem(self, idx, value):
        self._item._ary[idx] = value

    fake.__getitem__, fake.__setitem__ = getitem, setitem
    fake.shape = property(lambda self: devicearray.FakeShape(self._item._ary.shape))

    class Arrivals:
        """The threads of one block blocked at a barrier or ended (``ready``: all of them)."""

        def __init__(self, threads: int):
            self.lock, self.ready, self.blocked, self.alive = threading.Lock(), threading.Event(), 0, threads

        def change(self, blocked: int = 0, alive: int = 0) -> None:
            with self.lock:
                self.blocked += blocked
                self.alive += alive
                if self.blocked >= self.alive:
                    self.ready.set()
                else:
                    self.ready.clear()

    thread_run = thread.run

    def run_thread(self):
        try:
            thread_run(self)
        finally:
            arrivals = getattr(self._manager, "arrivals", None)
            if arrivals is not None:
                arrivals.change(alive=-1)

    def syncthreads(self):
        if self.abort:
            raise RuntimeError("abort flag set on syncthreads call")
        self.syncthreads_blocked = True
        arrivals = getattr(self._manager, "arrivals", None)
        if arrivals is not None:
            arrivals.change(blocked=1)
        self.syncthreads_event.wait()
        self.syncthreads_event.clear()
        if self.abort:
            raise RuntimeError("abort flag set on syncthreads clear")

    def run_block(self, grid_point, *args):  # BlockManager.run, waiting where it polled
        points = list(np.ndindex(*self._block_dim))
        self.arrivals = arrivals = Arrivals(len(points))
        threads, livethreads, blockedthreads = set(), set(), set()
        for block_point in points:

            def target():
                self._f(*args)

            t = thread(target, self, grid_point, block_point, self._debug)
            t.start()
            threads.add(t)
            livethreads.add(t)
        while livethreads:
            arrivals.ready.wait(0.01)
            for t in livethreads:
                if t.syncthreads_blocked:
                    blockedthreads.add(t)
                elif t.exception:
                    for t_other in threads:
                        t_other.abort = True
                        t_other.syncthreads_blocked = False
                        t_other.syncthreads_event.set()
                    raise t.exception[0].with_traceback(t.exception[1])
            if livethreads == blockedthreads:
                arrivals.change(blocked=-len(blockedthreads))
                for t in blockedthreads:
                    t.syncthreads_blocked = False
                    t.syncthreads_event.set()
                blockedthreads = set()
            livethreads = set([t for t in livethreads if t.is_alive()])
        for t in threads:
            if t.exception:
                raise t.exception[0].with_traceback(t.exception[1])

    thread.run, thread.syncthreads, manager.run = run_thread, syncthreads, run_block

import numpy as np  # noqa: E402 - after the simulator's switch
import pytest  # noqa: E402

if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
    _speed_up_the_simulator()


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def tiny_capture():
    """The bunny rendered small: 3 frames, colour 80x60, depth 40x30 (SF 2), seed 1 (the capture of
    the command-line tests). One object for the whole session: never modify it."""
    from o3d_mvps.synthetic import render_capture

    return render_capture("bunny", frames=3, scale_factor=2, size=(80, 60), seed=1, progress=False)


@pytest.fixture(scope="session")
def capture_dir(tiny_capture, tmp_path_factory):
    """``tiny_capture`` as a capture folder, shared by every test file of the session: read it,
    never write into it (a test that needs a changed capture copies it first). Checked at the end
    of the session: a test that changed it fails the run, naming this fixture."""
    from helpers import snapshot

    from o3d_mvps import write_capture

    path = tmp_path_factory.mktemp("shared") / "capture"
    write_capture(tiny_capture, path)
    before = snapshot(path)
    yield path
    assert snapshot(path) == before, f"a test wrote into the shared capture_dir {path}; copy it first"
