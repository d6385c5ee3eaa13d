"""The Capture type: n RGB-D frames of one object, frame 0 the reference, and its ground truth."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import open3d as o3d

from ..colour import codes_to_linear
from ..model.camera import as_intrinsic_matrix, scale_intrinsics
from ..model.sensor import choose_scale_factor


def integer_scale_factor(color_size, depth_size) -> int:
    """The capture's scale-factor rule: SF = H / h = W / w, an integer >= 1 (color_size (H, W),
    depth_size (h, w) in pixels); :func:`o3d_mvps.model.sensor.choose_scale_factor` with exact
    grids, whose CaptureError names the mismatch and the fix."""
    return choose_scale_factor(color_size, depth_size, exact=True)


@dataclass
class GroundTruth:
    """Ground truth of a synthetic capture (reference frame 0, colour resolution).

    depth: (H, W) float32 metres, 0 off the object. normals: (H, W, 3) float32, reference
    camera frame, unit, pointing to the camera, 0 off the object. albedo: (H, W, 3) float32
    linear RGB. poses: (n, 4, 4) float64 mapping reference-camera coordinates to frame-i
    coordinates. light: JSON-serialisable light parameters (``"model"``: ``"led"`` or
    ``"directional"`` or ``"room"``; the directional model stores ``"sh"``: n x 4 first-order SH
    vectors in reference coordinates). mesh_to_reference: (4, 4) float64 mesh -> reference camera.
    """

    depth: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    poses: np.ndarray
    light: dict
    mesh_to_reference: np.ndarray


@dataclass
class Capture:
    """n RGB-D frames; frame 0 is the reference.

    color: n images (H, W, 3): float32 linear RGB in [0, 1], or the uint8/uint16 codes of the
    files they were read from (all of one dtype; :meth:`color_array` decodes them by
    ``color_encoding``: a quarter of the memory for 8-bit files).
    depth: n images (h, w, 1) float32 metres, 0 = no measurement; h = H/SF, w = W/SF.
    color_intrinsic, depth_intrinsic: (3, 3) float64 tensors (pixels).
    masks: None, or n entries each None or an (H, W, 1) uint8 image (nonzero = object).
    depth_scale: depth PNG units per metre (1000 = mm). depth_trunc: metres.
    color_encoding: how colour PNGs are encoded on disk ("srgb" or "linear").
    light: what lit the frames (capture.json's "light"): "led" (the LED on the camera), "room"
    (room light) or "point" (a lamp moved by hand, one position per frame); None when the capture does not say.
    camera: capture.json's "camera": "static" (a fixed camera, a light moved between frames:
    :mod:`o3d_mvps.capture.static`), "moving", or None when the capture does not say.
    frame_names: the colour file of each frame (read from a folder), or None; folder: the
    capture folder it was read from, or None; both used in messages and reports. frame_ids: each
    frame's index in the capture the user gave, where this one holds some of its frames (a
    reconstruction's view), or None (its own indices): messages name frames by it.
    """

    color: list
    depth: list
    color_intrinsic: o3d.core.Tensor
    depth_intrinsic: o3d.core.Tensor
    masks: list | None = None
    depth_scale: float = 1000.0
    depth_trunc: float = 3.0
    color_encoding: str = "srgb"
    sensor: str = "unknown"
    groundtruth: GroundTruth | None = None
    metadata: dict = field(default_factory=dict)
    light: str | None = None
    camera: str | None = None
    frame_names: list | None = None
    folder: str | None = None
    frame_ids: list | None = None

    # --- sizes -------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return len(self.color)

    @property
    def color_size(self) -> tuple[int, int]:
        """(H, W) of the colour frames."""
        return (self.color[0].rows, self.color[0].columns)

    @property
    def depth_size(self) -> tuple[int, int]:
        """(h, w) of the depth frames."""
        return (self.depth[0].rows, self.depth[0].columns)

    @property
    def scale_factor(self) -> int:
        """Integer super-resolution factor SF = H / h = W / w (CaptureError when there is none)."""
        return integer_scale_factor(self.color_size, self.depth_size)

    # --- numpy views (what the solver works on) ----------------------------------------
    def color_array(self, i: int) -> np.ndarray:
        """Frame i colour, (H, W, 3) float32 linear RGB (integer codes decoded: a new array)."""
        codes = self.color_codes(i)
        if codes is not None:
            return codes_to_linear(codes, srgb=self.color_encoding == "srgb")
        return np.asarray(to_host(self.color[i].as_tensor()), dtype=np.float32).reshape(*self.color_size, 3)

    def color_codes(self, i: int) -> np.ndarray | None:
        """Frame i's colour codes, (H, W, 3) uint8/uint16 (the image's own memory on the CPU), or
        None where the frame holds floats."""
        pixels = to_host(self.color[i].as_tensor())
        if pixels.dtype not in (np.uint8, np.uint16):
            return None
        return pixels.reshape(*self.color_size, 3)

    def depth_array(self, i: int) -> np.ndarray:
        """Frame i depth, (h, w) float32 metres, 0 = missing."""
        return np.asarray(to_host(self.depth[i].as_tensor()), dtype=np.float32).reshape(self.depth_size)

    def mask_array(self, i: int) -> np.ndarray | None:
        """Frame i object mask, (H, W) bool, or None when the frame has none."""
        if self.masks is None or self.masks[i] is None:
            return None
        return to_host(self.masks[i].as_tensor()).reshape(self.color_size) > 0

    def color_K(self) -> np.ndarray:
        """Colour intrinsics as a (3, 3) float64 numpy array."""
        return as_intrinsic_matrix(to_host(self.color_intrinsic))

    def depth_K(self) -> np.ndarray:
        """Depth intrinsics as a (3, 3) float64 numpy array."""
        return as_intrinsic_matrix(to_host(self.depth_intrinsic))

    def select(self, frames) -> "Capture":
        """A capture of the listed frame indices; the first one becomes the reference.

        Ground truth is kept only when the reference stays frame 0 (poses are re-indexed).
        """
        frames = [int(i) for i in frames]
        pick = lambda seq: None if seq is None else [seq[i] for i in frames]  # noqa: E731
        gt = self.groundtruth
        if gt is not None:
            gt = replace(gt, poses=gt.poses[frames]) if frames[0] == 0 else None
        return replace(self, color=pick(self.color), depth=pick(self.depth), masks=pick(self.masks), groundtruth=gt,
                       frame_names=pick(self.frame_names), frame_ids=pick(self.frame_ids))

    def reference_only(self) -> "Capture":
        """This capture with the reference frame's images only (colour, depth, mask, name, id):
        for what reads frame 0 alone once the frames are solved (baselines, report figures), so
        that the other frames' arrays can be freed. Unlike ``select([0])`` the ground truth is kept
        whole (its poses still index every frame of this capture)."""
        first = lambda seq: None if seq is None else list(seq[:1])  # noqa: E731
        return replace(self, color=first(self.color), depth=first(self.depth), masks=first(self.masks),
                       frame_names=first(self.frame_names), frame_ids=first(self.frame_ids))

    def frame_id(self, i: int) -> int:
        """Frame i's index in the capture the user gave (:attr:`frame_ids`, default i)."""
        return i if self.frame_ids is None else int(self.frame_ids[i])

    def frame_label(self, i: int) -> str:
        """'frame i' or 'frame i (file)' for messages, i as the user knows it (:meth:`frame_id`)."""
        name = f"frame {self.frame_id(i)}"
        return name if self.frame_names is None else f"{name} ({self.frame_names[i]})"


def to_host(value):
    """An o3d.core.Tensor on any device as a NumPy array in host memory (a CUDA tensor is copied;
    a CPU one shared); any other value unchanged. The CPU solver needs host arrays; handing CUDA
    tensors over without a copy (DLPack) belongs to a GPU solver path."""
    return value.cpu().numpy() if isinstance(value, o3d.core.Tensor) else value


def default_depth_intrinsic(color_K: np.ndarray, scale_factor: int) -> np.ndarray:
    """Depth intrinsics of a depth grid that area-averages SF x SF colour pixels."""
    return scale_intrinsics(color_K, 1.0 / scale_factor)


def image_from_array(array: np.ndarray) -> o3d.t.geometry.Image:
    """An o3d.t.geometry.Image holding a contiguous copy of an (H, W) or (H, W, C) array."""
    return o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(array)))
