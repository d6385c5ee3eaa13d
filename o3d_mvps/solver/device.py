"""Which device solves, and the array device the solver's code runs on there.

Names follow Open3D's (``"CPU:0"``, ``"CUDA:0"``, or an ``o3d.core.Device``) and PyTorch's
(``"cpu"``, ``"cuda"``, ``"cuda:1"``), case-insensitively, plus ``"auto"``: the first GPU when it
can solve, else the CPU (:func:`auto_device`). A CUDA device is checked before any work: CuPy
importable, the GPU visible to it, numba's CUDA target present and working with the installed
NumPy (:func:`check_device`).

The solver is one code for both. An :class:`ArrayDevice` says where the per-pixel arrays live
(NumPy or CuPy, SciPy's or CuPy's sparse matrices); the code that runs on them follows from the
arrays: the per-pixel kernels (numba on the CPU, :mod:`.cuda_kernels` on CUDA:
:func:`kernels_for`) and the linear solver (pyamg's AMG on the CPU, the array-generic multigrid
of :mod:`.krylov` on CUDA: :func:`on_gpu`). Small arrays (lights, poses, the 6x6 pose systems)
stay NumPy arrays on the host.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from importlib import import_module, metadata
from types import ModuleType

import numpy as np
import scipy.sparse

from ..errors import DeviceError
from ..model.arrays import array_module

ON_CPU = "solve on the CPU instead (device='cpu', --device cpu)"
CUDA_INSTALL = ("pip install o3d-mvps[cuda] (CuPy and numba-cuda for CUDA 12; for CUDA 13: pip install "
                "o3d-mvps[cuda13])")
#: the NumPy versions the numba-cuda of the ``cuda`` extras compiles kernels with (numba-cuda
#: 0.30.4, the newest, registers NumPy's ``row_stack``, which NumPy 2.5 removed)
CUDA_NUMPY = "numpy<2.5"
DEVICE_HELP = ("where the solver runs: auto (default: the first GPU when CuPy sees one and numba-cuda works, "
               "else the CPU), cpu, or cuda[:N] (needs CuPy and numba-cuda: pip install o3d-mvps[cuda])")
_NAME = re.compile(r"(auto|cpu|cuda)(?::(\d+))?")

#: :attr:`ArrayDevice.residual_dtype` on CUDA
CUDA_RESIDUAL_DTYPE = np.float32

#: :attr:`ArrayDevice.min_level_pixels` on CUDA. A GPU's cost per array operation (a kernel
#: launch or a small copy, 5-20 us from Python) does not shrink with the level, and a sweep makes
#: hundreds: on 20-frame LED problems (``python -m benchmarks.gpu count``, docs/gpu.md) 400-650
#: launches and 50-80 copies per joint sweep (1600-2300 operations before issue 33's item 4),
#: i.e. some 5-20 ms. This machine's 2 cores take 0.4 s for a joint sweep of 22400 pixels x 20
#: frames, so a GPU machine's 16 about 50 ms: below some 20000 pixels the CPU was as fast at the
#: earlier counts (with today's, the threshold may be lower). An estimate from counts and CPU
#: times, not a GPU measurement.
CUDA_MIN_LEVEL_PIXELS = 20000


@dataclass(frozen=True)
class ArrayDevice:
    """Where the solver's per-pixel arrays live: name "cpu" or "cuda:N", xp numpy or cupy,
    sparse scipy.sparse or cupyx.scipy.sparse. The code that runs on them follows from the
    arrays themselves (:func:`kernels_for`).

    residual_dtype: of the largest arrays, the per-frame residuals (n, N, 3) and shading (n, N)
    of an evaluation: float32 (every sum over them is float64, in the kernels' registers). On
    CUDA the sweeps that read them are bound by memory traffic; on the CPU float32 halves an
    evaluation's largest arrays (some 300 MB at 2 megapixels and 20 frames).

    min_level_pixels: pyramid levels with fewer object pixels are solved on the CPU (:data:`CPU`).
    """

    name: str
    xp: ModuleType
    sparse: ModuleType
    residual_dtype: type = np.float32
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


def to_host_together(*arrays) -> list:
    """``arrays`` (float64, any shapes) as NumPy arrays of the same shapes; from the GPU in one
    copy (one synchronisation; raveled, concatenated, copied and split), on the host themselves."""
    if all(array_module(a) is np for a in arrays):
        return list(arrays)
    xp = array_module(arrays[0])
    flat = to_host(xp.concatenate([a.reshape(-1) for a in arrays]))
    ends = np.cumsum([a.size for a in arrays])
    return [part.reshape(a.shape) for part, a in zip(np.split(flat, ends[:-1]), arrays)]


class DeviceCopies:
    """The device copies of the last ``kept`` small host arrays (newest first; for the kernels'
    inputs, never written): :meth:`copy` of values equal to a kept one's gives that copy again
    (no copy), else copies (one ``asarray``) and keeps it."""

    def __init__(self, kept: int):
        self.kept, self.entries = kept, []  # (host values, array module, device, device array)

    def copy(self, host: np.ndarray, reference):
        """``host`` as a C-contiguous array of ``reference``'s module and device."""
        xp, device = array_module(reference), getattr(reference, "device", None)
        for values, module, where, copied in self.entries:
            if module is xp and where == device and values.shape == host.shape and np.array_equal(values, host):
                return copied
        copied = xp.asarray(host, order="C")
        self.entries.insert(0, (host, xp, device, copied))
        del self.entries[self.kept:]
        return copied

    def copy_many(self, hosts: list, reference, extra: tuple = ()) -> tuple[list, list]:
        """:meth:`copy` of several host arrays (1-d) in one ``asarray`` (views of one device
        array), keeping each; those equal to a kept one give that copy, and none is copied
        where all are kept and there is no ``extra``: further host arrays (1-d) copied in the
        same copy, not kept. Returns (the copies of ``hosts``, those of ``extra``)."""
        found = [self.copy(host, reference) if self._kept(host, reference) else None for host in hosts]
        missing = [k for k, got in enumerate(found) if got is None]
        extra = list(extra)
        if missing or extra:
            xp, device = array_module(reference), getattr(reference, "device", None)
            parts = [hosts[k] for k in missing] + extra
            packed = xp.asarray(np.concatenate(parts))
            ends = np.cumsum([0] + [len(part) for part in parts])
            views = [packed[start:stop] for start, stop in zip(ends[:-1], ends[1:])]
            for k, view in zip(missing, views):
                found[k] = view
                self.entries.insert(0, (hosts[k], xp, device, view))
            del self.entries[max(self.kept, len(missing)):]
            return found, views[len(missing):]
        return found, []

    def _kept(self, host: np.ndarray, reference) -> bool:
        xp, device = array_module(reference), getattr(reference, "device", None)
        return any(module is xp and where == device and values.shape == host.shape and np.array_equal(values, host)
                   for values, module, where, _ in self.entries)

    def clear(self) -> None:
        self.entries.clear()


def check_device_name(device) -> str:
    """The device's name spelled ``"auto"``, ``"cpu"`` or ``"cuda:N"``, without asking whether it
    can run (options check names when made); ValueError for a name that is none of these."""
    name = str(device)
    match = _NAME.fullmatch(name.strip().lower())
    if match is None or (match[1] in ("cpu", "auto") and match[2] not in (None, "0")):
        raise ValueError(f"device {name!r} is not a device name; pass 'auto', 'cpu' (or 'CPU:0') or 'cuda:N'")
    return match[1] if match[1] != "cuda" else f"cuda:{int(match[2] or 0)}"


def check_device(device) -> str:
    """The device's name, ``"cpu"`` or ``"cuda:N"``, when the solver can run there; ``"auto"``
    gives :func:`auto_device`'s choice.

    ValueError for a name that is not auto/cpu/cuda[:N]; DeviceError for a CUDA device that
    cannot run: CuPy or numba-cuda missing (how to install them), CuPy seeing no such GPU, or a
    numba-cuda that does not work with the installed NumPy (the versions, and the fix).
    """
    name, canonical = str(device), check_device_name(device)
    if canonical == "auto":
        return auto_device()[0]
    if canonical == "cpu":
        return "cpu"
    index = int(canonical.split(":")[1])
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
    numba_cuda = _import_numba_cuda(name)
    if numba_cuda.config.ENABLE_CUDASIM:
        raise DeviceError(f"device {name!r}: numba's CUDA simulator is on (NUMBA_ENABLE_CUDASIM=1), which runs "
                          f"kernels on the CPU; unset it to solve on the GPU, or {ON_CPU}")
    if not numba_cuda.is_available():
        raise DeviceError(f"device {name!r}: CuPy sees the GPU but numba's CUDA target does not (numba-cuda needs "
                          f"the CUDA toolkit's NVVM: {CUDA_INSTALL}); or {ON_CPU}")
    return f"cuda:{index}"


def auto_device() -> tuple[str, str]:
    """``("cuda:0", why)`` when the first GPU can solve (:func:`check_device`), else ``("cpu",
    why not)``: the reason is :func:`check_device`'s DeviceError message. Asked once a process."""
    return _auto_device()


@functools.lru_cache(maxsize=1)
def _auto_device() -> tuple[str, str]:
    try:
        name = check_device("cuda:0")
    except DeviceError as error:
        return "cpu", str(error).replace(f"; or {ON_CPU}", "").replace(f", or {ON_CPU}", "")
    return name, "CuPy sees a GPU and numba-cuda works"


def resolve_device(device) -> tuple[str, str]:
    """(:func:`check_device`'s name, a line for a run's output saying where it solves and, for
    ``"auto"``, why), e.g. ``("cpu", "device: cpu (auto: device 'cuda:0' needs CuPy, ...)")``."""
    name = check_device(device)
    if check_device_name(device) == "auto":
        return name, f"device: {name} (auto: {auto_device()[1]})"
    return name, f"device: {name}"


#: seconds the kernels' first compile takes, roughly (numba's CPU kernels: 11 s of CPU time on
#: this project's 2-core machine; the CUDA kernels: 16-30 s on an H100 machine, issue 33)
COMPILE_SECONDS = {"cpu": 15, "cuda": 30}


def compile_notice(device: ArrayDevice) -> str | None:
    """A line to print before a solve on ``device`` that will compile kernels (their on-disk
    cache holds nothing for this source: a first run, or the code changed), else None. Cheap:
    reads the caches' indexes; None too where that cannot be told."""
    from . import kernels

    modules = [kernels]
    if device.name.startswith("cuda"):
        from . import cuda_kernels

        modules.append(cuda_kernels)
    cached = [_in_cache(kernel) for module in modules for kernel in vars(module).values()]
    if False not in cached:
        return None
    seconds = COMPILE_SECONDS["cuda" if len(modules) > 1 else "cpu"]
    return f"compiling the solver's kernels (first run only, ~{seconds} s) ..."


def _in_cache(kernel) -> bool | None:
    """Whether numba's on-disk cache of a ``cache=True`` kernel holds compiled code for its
    current source; None for anything else (not a cached kernel, numba's internals changed)."""
    cache_file = getattr(getattr(kernel, "_cache", None), "_cache_file", None)
    if cache_file is None:
        return None
    try:
        return bool(cache_file._load_index())  # {} when the index is missing or of older source
    except Exception:  # noqa: BLE001 - a private API of numba: no notice rather than a failure
        return None


def package_versions() -> str:
    """The installed versions of the CUDA path's packages, e.g. "numpy 2.4.6, numba 0.68.1,
    numba-cuda 0.30.4, cupy-cuda12x 14.2.0" (those installed)."""
    names = ("numpy", "numba", "numba-cuda", "cupy-cuda12x", "cupy-cuda13x", "cupy")
    found = []
    for package in names:
        try:
            found.append(f"{package} {metadata.version(package)}")
        except metadata.PackageNotFoundError:
            pass
    return ", ".join(found)


def _import_numba_cuda(name: str) -> ModuleType:
    """``numba.cuda``, its NumPy typing loaded (what every kernel compiles with): DeviceError when
    it is not installed, or does not work with the installed NumPy (numba-cuda 0.30 with NumPy
    2.5: AttributeError for ``np.row_stack``) -- the versions and the fix, not a traceback."""
    try:
        import numba.cuda

        import_module("numba.cuda.np.arrayobj")  # NumPy's array functions, as a compile loads them
    except ImportError as error:
        if getattr(error, "name", "") in ("numba", "numba.cuda"):
            raise DeviceError(f"device {name!r} needs numba's CUDA target (numba-cuda), which is not installed: "
                              f"{CUDA_INSTALL}; or {ON_CPU}") from None
        raise _incompatible(name, error) from None
    except Exception as error:  # noqa: BLE001 - any failure to load is reported with the versions
        raise _incompatible(name, error) from None
    return numba.cuda


def _incompatible(name: str, error: Exception) -> DeviceError:
    return DeviceError(f"device {name!r}: numba-cuda does not work with the installed packages ({package_versions()}): "
                       f"{type(error).__name__}: {error}. Install versions that work together: "
                       f"pip install '{CUDA_NUMPY}' 'numba-cuda>=0.30.4' (what o3d-mvps[cuda] pins), or {ON_CPU}")


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
