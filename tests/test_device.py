"""o3d_mvps.solver.device: ``auto`` picks the GPU when it can solve and says why not otherwise;
a numba-cuda that does not work with the installed NumPy gives a DeviceError naming the
versions and the fix, not a traceback (simulated: no GPU here). The missing-package messages
are tested in tests/test_saved_problem.py."""

import os
import subprocess
import sys
import textwrap
import types

import numpy as np
import pytest

from o3d_mvps.cli import build_parser
from o3d_mvps.errors import DeviceError
from o3d_mvps.reconstruct import ReconstructOptions
from o3d_mvps.solver import __main__ as solver_main
from o3d_mvps.solver import device

FAKE_CUPY = ("types.SimpleNamespace(cuda=types.SimpleNamespace(runtime=types.SimpleNamespace("
             "getDeviceCount=lambda: {count})))")


def fake_cupy(count: int):
    """A ``cupy`` module whose runtime sees ``count`` GPUs."""
    return eval(FAKE_CUPY.format(count=count))  # noqa: S307 - the same text serves the subprocess below


@pytest.fixture(autouse=True)
def fresh_auto_choice():
    """auto_device is asked once a process: forget its answer around each test."""
    device._auto_device.cache_clear()
    yield
    device._auto_device.cache_clear()


def test_auto_solves_on_the_cpu_without_cupy_and_says_why(monkeypatch):
    monkeypatch.setitem(sys.modules, "cupy", None)
    assert device.check_device("auto") == "cpu"
    name, line = device.resolve_device("AUTO")
    assert name == "cpu"
    assert line.startswith("device: cpu (auto: device 'cuda:0' needs CuPy, which is not installed: pip install "
                           "o3d-mvps[cuda]")
    assert "or solve on the CPU" not in line
    assert device.resolve_device("CPU:0") == ("cpu", "device: cpu")


def test_auto_takes_the_gpu_when_cupy_sees_one_and_numba_cuda_works(monkeypatch):
    monkeypatch.setitem(sys.modules, "cupy", fake_cupy(2))
    numba_cuda = types.SimpleNamespace(config=types.SimpleNamespace(ENABLE_CUDASIM=False), is_available=lambda: True)
    monkeypatch.setattr(device, "_import_numba_cuda", lambda name: numba_cuda)
    assert device.resolve_device("auto") == ("cuda:0", "device: cuda:0 (auto: CuPy sees a GPU and numba-cuda works)")
    assert device.check_device("cuda:1") == "cuda:1"


def test_numba_cuda_failing_on_numpy_gives_versions_and_fix(monkeypatch):
    """numba-cuda's typing failing as it did with NumPy 2.5 on a GPU (a KeyError from its ufunc
    table): a DeviceError with the versions and the fix; auto then solves on the CPU."""
    monkeypatch.setitem(sys.modules, "cupy", fake_cupy(1))

    def broken(name):
        raise KeyError(np.multiply)

    monkeypatch.setattr(device, "import_module", broken)
    with pytest.raises(DeviceError) as caught:
        device.check_device("cuda:0")
    message = str(caught.value)
    assert message.startswith(f"device 'cuda:0': numba-cuda does not work with the installed packages (numpy "
                              f"{np.__version__}, numba ")
    assert "KeyError: <ufunc 'multiply'>" in message
    assert "pip install 'numpy<2.5' 'numba-cuda>=0.30.4' (what o3d-mvps[cuda] pins), or solve on the CPU" in message
    assert device.auto_device() == ("cpu", message.replace("; or solve on the CPU instead (device='cpu', --device cpu)",
                                                           "").replace(", or solve on the CPU instead (device='cpu', "
                                                                       "--device cpu)", ""))


def test_numpy_without_row_stack_gives_a_device_error_not_a_traceback():
    """NumPy 2.5 removed ``row_stack``, which numba-cuda 0.30.4 registers: simulated in a fresh
    process (numba-cuda loads its NumPy typing once) by deleting it before numba-cuda loads."""
    script = textwrap.dedent(f"""
        import sys, types
        import numpy
        from o3d_mvps.errors import DeviceError
        from o3d_mvps.solver.device import auto_device, check_device
        assert "numba.cuda.np.arrayobj" not in sys.modules
        del numpy.row_stack  # as in NumPy 2.5
        sys.modules["cupy"] = {FAKE_CUPY.format(count=1)}
        try:
            check_device("cuda:0")
        except DeviceError as error:
            print(error)
        print(auto_device()[0])
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                          cwd=os.getcwd())
    assert done.returncode == 0, done.stderr
    error, choice = done.stdout.strip().splitlines()
    assert "numba-cuda does not work with the installed packages (numpy" in error
    assert "AttributeError: module 'numpy' has no attribute 'row_stack'" in error
    assert "pip install 'numpy<2.5'" in error
    assert choice == "cpu"


def test_auto_is_the_default_device_of_every_command():
    parser = build_parser()
    assert parser.parse_args(["refine", "capture", "out"]).device == "auto"
    assert parser.parse_args(["demo"]).device == "auto"
    assert parser.parse_args(["reconstruct", "capture", "out"]).device == "auto"
    assert solver_main.build_parser().parse_args(["problem.npz", "out.npz"]).device == "auto"
    assert ReconstructOptions().device == "auto"


def test_reconstruct_options_check_the_device_name():
    with pytest.raises(ValueError, match="device 'gpu' is not a device name; pass 'auto', 'cpu'"):
        ReconstructOptions(device="gpu")
    assert device.check_device_name("CUDA") == "cuda:0" and device.check_device_name("Auto") == "auto"


def test_compile_notice_when_the_kernel_cache_is_empty(monkeypatch):
    """The notice reads numba's cache index of each cached kernel (a private API: if numba
    changes it, _in_cache gives None and this test fails rather than the notice going quiet)."""
    from o3d_mvps.solver import kernels

    assert isinstance(device._in_cache(kernels.accumulate_frame), bool)
    assert device._in_cache(kernels.accumulate_pixel) is None  # inlined, not cached of its own
    monkeypatch.setattr(device, "_in_cache", lambda kernel: False)
    assert device.compile_notice(device.CPU) == "compiling the solver's kernels (first run only, ~15 s) ..."
    monkeypatch.setattr(device, "_in_cache", lambda kernel: True)
    assert device.compile_notice(device.CPU) is None
