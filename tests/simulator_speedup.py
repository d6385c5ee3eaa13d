"""numba's CUDA simulator made cheaper for the suite (tests/conftest.py calls
:func:`speed_up_the_simulator` when the simulator is on): the same semantics, a fraction of the
CPU time. Written against numba-cuda 0.30's simulator internals; where they differ it changes
nothing."""

import numpy as np


def speed_up_the_simulator() -> None:
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
