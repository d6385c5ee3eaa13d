"""Exceptions raised by o3d_mvps. Each message names the problem and the fix."""


class MVPSError(Exception):
    """Base class of every error o3d_mvps raises on purpose."""


class CaptureError(MVPSError, ValueError):
    """A capture (folder, frames, intrinsics, masks) is missing, malformed or inconsistent."""


class OutputExistsError(MVPSError, FileExistsError):
    """Writing would overwrite a user's earlier output; pass ``overwrite=True`` to allow it."""


class OdometryError(MVPSError, RuntimeError):
    """RGB-D odometry could not register a frame to the reference (frames do not overlap)."""


class RecordingError(MVPSError, RuntimeError):
    """A RealSense camera or recording cannot deliver what was asked for."""


class ExportError(MVPSError, ValueError):
    """A mesh or print-ready solid cannot be built or fails its checks."""


class DeviceError(MVPSError, RuntimeError):
    """The device asked for cannot run the solver (no CuPy, no GPU, or no solver path for it)."""


class OutputPathError(MVPSError, ValueError):
    """An output cannot be written where asked: its parent is a file, the folder is read-only,
    it lies inside an input, a folder stands where a file is wanted, or the disk is full."""
