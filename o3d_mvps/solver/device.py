"""Which device solves: ``"cpu"`` (NumPy/SciPy), or ``"cuda[:N]"`` once the CUDA path exists.

Names follow Open3D's (``"CPU:0"``, ``"CUDA:0"``, or an ``o3d.core.Device``) and PyTorch's
(``"cpu"``, ``"cuda"``, ``"cuda:1"``), case-insensitively. A CUDA device is checked before any
work: CuPy importable, the GPU visible to it.
"""

from __future__ import annotations

import re

from ..errors import DeviceError

ON_CPU = "solve on the CPU instead (device='cpu', --device cpu)"
CUDA_INSTALL = ("pip install o3d-mvps[cuda] (CuPy for CUDA 12; for CUDA 13 run pip install cupy-cuda13x "
                "instead)")
DEVICE_HELP = ("where the solver runs: cpu (default); cuda[:N] needs CuPy (pip install o3d-mvps[cuda]) and a CUDA "
               "solver path, which this version does not have yet")
_NAME = re.compile(r"(cpu|cuda)(?::(\d+))?")


def check_device(device) -> str:
    """The device as ``"cpu"`` when the solver can run there.

    ValueError for a name that is not cpu/cuda[:N]; DeviceError for a CUDA device: CuPy missing
    (how to install it), CuPy seeing no such GPU, or (both present) no CUDA solver path in this
    version.
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
    raise DeviceError(f"device {name!r}: CuPy and the GPU are there, but this version of o3d_mvps has no CUDA "
                      f"solver path yet; {ON_CPU}")
