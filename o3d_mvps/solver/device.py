"""Which device solves, and the array device the solver's code runs on there.

Names follow Open3D's (``"CPU:0"``, ``"CUDA:0"``, or an ``o3d.core.Device``) and PyTorch's
(``"cpu"``, ``"cuda"``, ``"cuda:1"``), case-insensitively. A CUDA device is checked before any
work: CuPy importable, the GPU visible to it, numba's CUDA target present.

The solver is one code for both. An :class:`ArrayDevice` says where the per-pixel arrays live
(NumPy or CuPy, SciPy's or CuPy's sparse matrices); the code that runs on them follows from the
arrays: the per-pixel kernels (numba on the CPU, :mod:`.cuda_kernels` on CUDA:
:func:`kernels_for`) and the linear solver (pyamg's AMG on the CPU, the array-generic multigrid
of :mod:`.krylov` on CUDA: :func:`on_gpu`). Small arrays (lights, poses, the 6x6 pose systems)
stay NumPy arrays on the host.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from types import ModuleType

import numpy as np
import scipy.sparse

from ..errors import DeviceError
from ..model.arrays import array_module

ON_CPU = "solve on the CPU instead (device='cpu', --device cpu)"
CUDA_INSTALL = ("pip install o3d-mvps[cuda] (CuPy and numba-cuda for CUDA 12; for CUDA 13 run pip install "
                "cupy-cuda13x numba-cuda[cu13] instead)")
DEVICE_HELP = "where the solver runs: cpu (default), or cuda[:N] (needs CuPy and numba-cuda: pip install o3d-mvps[cuda])"
_NAME = re.compile(r"(cpu|cuda)(?::(\d+))?")

#: :attr:`ArrayDevice.residual_dtype` on CUDA
CUDA_RESIDUAL_DTYPE = np.float32

#: :attr:`ArrayDevice.min_level_pixels` on CUDA. A GPU's cost per array operation (a kernel
#: launch or a small copy, 5-20 us from Python) does not shrink with the level, and a sweep makes
#: thousands: on 20-frame LED problems (``python -m benchmarks.gpu count``) 1600-2300 per joint
#: sweep, about 5000 per sweep of the coarser levels' separate pose and depth steps, i.e. some
#: 20-100 ms. This machine's 2 cores take 0.4 s for a joint sweep of 22400 pixels x 20 frames,
#: so a GPU machine's 16 about 50 ms: below some 20000 pixels the CPU is as fast. An estimate
#: from counts and CPU times, not a GPU measurement.
CUDA_MIN_LEVEL_PIXELS = 20000


@dataclass(frozen=True)
class ArrayDevice:
    """Where the solver's per-pixel arrays live: name "cpu" or "cuda:N", xp numpy or cupy,
    sparse scipy.sparse or cupyx.scipy.sparse. The code that runs on them follows from the
    arrays themselves (:func:`kernels_for`).

    residual_dtype: of the largest arrays, the per-frame residuals (n, N, 3) and shading (n, N)
    of an evaluation. float32 on CUDA, where the sweeps that read them are bound by memory
    traffic (every sum over them is float64, in the kernels' registers); float64 on the CPU.

    min_level_pixels: pyramid levels with fewer object pixels are solved on the CPU (:data:`CPU`).
    """

    name: str
    xp: ModuleType
    sparse: ModuleType
    residual_dtype: type = np.float64
    min_level_pixels: int = 0

    def asarray(self, a, dtype=None):
        """``a`` (a NumPy array, or already one of this device's) as an array of this device."""
        return self.xp.asarray(a, dtype=dtype)

    def sparse_matrix(self, matrix):
        """A SciPy sparse matrix as a CSR matrix of this device."""
        return self.sparse.csr_matrix(matrix)


CPU = ArrayDevice("cpu", np, scipy.sparse)

def on_gpu(x) -> bool:
    """Whether arrays like ``x`` take the CUDA path: CuPy arrays (or a stand-in's: its module's
    name starts with "cupy", see :func:`o3d_mvps.model.arrays.array_module`)."""
    return array_module(x) is not np


def kernels_for(x) -> ModuleType:
    """The per-pixel kernels for arrays like ``x``: :mod:`.cuda_kernels` on the CUDA path
    (:func:`on_gpu`), else the CPU's :mod:`.kernels` (the same functions)."""
    if on_gpu(x):
        from . import cuda_kernels

        return cuda_kernels
    from . import kernels

    return kernels


def to_host(a):
    """``a`` as a NumPy array (copied from the GPU; itself on the host); None stays None."""
    return a if a is None or array_module(a) is np else a.get()


def check_device(device) -> str:
    """The device's name, ``"cpu"`` or ``"cuda:N"``, when the solver can run there.

    ValueError for a name that is not cpu/cuda[:N]; DeviceError for a CUDA device that cannot
    run: CuPy or numba-cuda missing (how to install them), or CuPy seeing no such GPU.
    """
    name = str(device)
    match = _NAME.fullmatch(name.strip().lower())
    if match is None or (match[1] == "cpu" and match[2] not in (None, "0")):
        raise ValueError(f"device {name!r} is not a device name; pass 'cpu' (or 'CPU:0') or 'cuda:N'")
    if match[1] == "cpu":
        return "cpu"
    index = int(match[2] or 0)
    try:
        import cupy
    except ImportError:
        raise DeviceError(f"device {name!r} needs CuPy, which is not installed: {CUDA_INSTALL}; or {ON_CPU}") from None
    try:
        count = cupy.cuda.runtime.getDeviceCount()
    except Exception:  # CUDARuntimeError without a driver or GPU
        count = 0
    if index >= count:
        seen = "no GPU" if count == 0 else f"{count} GPU(s), cuda:0 to cuda:{count - 1}"
        raise DeviceError(f"device {name!r}: CuPy sees {seen}; check the NVIDIA driver (nvidia-smi) and that the "
                          f"CuPy package matches its CUDA version, pick a listed GPU, or {ON_CPU}")
    try:
        import numba.cuda
    except ImportError:
        raise DeviceError(f"device {name!r} needs numba's CUDA target (numba-cuda), which is not installed: "
                          f"{CUDA_INSTALL}; or {ON_CPU}") from None
    if numba.config.ENABLE_CUDASIM:
        raise DeviceError(f"device {name!r}: numba's CUDA simulator is on (NUMBA_ENABLE_CUDASIM=1), which runs "
                          f"kernels on the CPU; unset it to solve on the GPU, or {ON_CPU}")
    if not numba.cuda.is_available():
        raise DeviceError(f"device {name!r}: CuPy sees the GPU but numba's CUDA target does not (numba-cuda needs "
                          f"the CUDA toolkit's NVVM: {CUDA_INSTALL}); or {ON_CPU}")
    return f"cuda:{index}"


def array_device(device) -> ArrayDevice:
    """The :class:`ArrayDevice` of a device name (:func:`check_device`), or ``device`` itself
    when it is one.

    On CUDA, the GPU is made the current device of CuPy and of numba's CUDA target.
    """
    if isinstance(device, ArrayDevice):
        return device
    name = check_device(device)
    if name == "cpu":
        return CPU
    import cupy
    import cupyx.scipy.sparse
    from numba import cuda

    index = int(name.split(":")[1])
    cupy.cuda.Device(index).use()
    cuda.select_device(index)
    return ArrayDevice(name, cupy, cupyx.scipy.sparse, CUDA_RESIDUAL_DTYPE, CUDA_MIN_LEVEL_PIXELS)
