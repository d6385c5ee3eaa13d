"""OpenMP wait policy of the compiled parallel loops (o3d_mvps.model.parallel)."""

import os
import subprocess
import sys
from pathlib import Path

from o3d_mvps.model.parallel import (PIXELS_PER_THREAD, WAIT_POLICY, configure_openmp, current_kernel_threads,
                                     kernel_threads, set_kernel_threads)

ROOT = Path(__file__).resolve().parent.parent


def test_passive_unless_the_user_chose():
    environ = {}
    assert configure_openmp(environ) is True and environ == {"OMP_WAIT_POLICY": WAIT_POLICY}
    for name, value in (("OMP_WAIT_POLICY", "active"), ("GOMP_SPINCOUNT", "10000")):
        environ = {name: value}
        assert configure_openmp(environ) is False and environ == {name: value}


def test_set_before_openmp_loads():
    """In a fresh process the policy is in the environment before numba's first parallel launch
    loads libgomp (which reads it once), and that launch then runs with it."""
    code = ("import os, numpy as np\n"
            "from o3d_mvps.solver.kernels import log1p_square_sum  # sets the threading layer: OpenMP first\n"
            "maps = open('/proc/self/maps').read()\n"
            "assert 'libgomp' not in maps, 'OpenMP loaded on import'\n"
            "assert os.environ['OMP_WAIT_POLICY'] == 'PASSIVE'\n"
            "assert abs(log1p_square_sum(np.ones(100000), 1.0) - 100000 * np.log(2.0)) < 1e-2\n"
            "import numba; print(numba.threading_layer())\n")
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env["PYTHONPATH"] = str(ROOT)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "omp"


def test_kernel_threads_by_size():
    """The D415 render's levels (object pixels 340, 1 300, 5 400, 21 000, 86 000) on 2 threads: the
    three coarse ones on one, the two fine ones on both; never more than available, never 0."""
    assert [kernel_threads(p, 2) for p in (0, 340, 1300, 5400, 21000, 86000)] == [1, 1, 1, 1, 2, 2]
    assert kernel_threads(86000, 1) == 1 and kernel_threads(100 * PIXELS_PER_THREAD, 16) == 16
    assert kernel_threads(3 * PIXELS_PER_THREAD, 16) == 3


def test_set_kernel_threads_returns_the_count_before():
    before = current_kernel_threads()
    try:
        assert set_kernel_threads(1) == before and current_kernel_threads() == 1
    finally:
        set_kernel_threads(before)
    assert current_kernel_threads() == before
