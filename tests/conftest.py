"""Shared fixtures; helpers shared by several test files live in tests/helpers.py (importable as
``helpers``: pytest puts this folder on sys.path). Keep renders small: the suite must stay fast
on a 2-core machine.

First of all: without a GPU, numba's CUDA kernels (tests/test_cuda_kernels.py) run in numba's
CUDA simulator, which numba.cuda picks at its first import from NUMBA_ENABLE_CUDASIM; so that is
set here, before any test module imports numba. A GPU counts when ``nvidia-smi -L`` lists one
(the driver's tool: no CUDA library is loaded to ask). NUMBA_ENABLE_CUDASIM set by the caller
(1: simulate even with a GPU) is left as it is. With the simulator on, its array wrappers and its
block manager's polling are made cheaper (tests/simulator_speedup.py; the same semantics).
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

if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
    from simulator_speedup import speed_up_the_simulator

    speed_up_the_simulator()


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
