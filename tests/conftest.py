"""Shared fixtures; helpers shared by several test files live in tests/helpers.py (importable as
``helpers``: pytest puts this folder on sys.path). Keep renders small: the suite must stay fast
on a 2-core machine.

First of all: without a GPU, numba's CUDA kernels (tests/test_cuda_kernels.py) run in numba's
CUDA simulator, which numba.cuda picks at its first import from NUMBA_ENABLE_CUDASIM; so that is
set here, before any test module imports numba. A GPU counts when ``nvidia-smi -L`` lists one
(the driver's tool: no CUDA library is loaded to ask). NUMBA_ENABLE_CUDASIM set by the caller
(1: simulate even with a GPU) is left as it is.
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

import numpy as np  # noqa: E402 - after the simulator's switch
import pytest  # noqa: E402


@pytest.fixture
def rng():
    return np.random.default_rng(0)
