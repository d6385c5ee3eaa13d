"""One reference view of a reconstruction: its frames, their poses re-based to it, its depth.

A :class:`ViewJob` is what a worker needs (picklable: a capture subset and poses); running it
(:func:`run_view`) refines the reference with the frames that see it, or, for ``depth="raw"``,
bicubic-upsamples its sensor depth, and returns a :class:`ViewResult` of NumPy arrays.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..covisibility import ViewSelection, frames_seeing_reference

DEPTH_SOURCES = ("refined", "raw")


@dataclass
class ViewJob:
    """Reference ``reference`` of the capture refined with ``frames`` (reference first).

    arrays: the capture's frames ``frames`` as NumPy arrays (:func:`capture_arrays`; Open3D
    images do not cross Dask's serialisation); poses: (len(frames), 4, 4) reference -> frame;
    world_to_camera: (4, 4) capture frame 0 -> reference camera; selection: why these frames;
    poses_given: the poses came from the user (refined under their trust, docs/poses-and-light.md),
    not from the registration.
    """

    reference: int
    frames: list
    arrays: dict
    poses: np.ndarray
    world_to_camera: np.ndarray
    selection: ViewSelection
    poses_given: bool = True


@dataclass
class ViewResult:
    """A reference view's depth (H, W) metres, mask (H, W) bool, albedo (H, W, 3) linear RGB
    (the colour image for raw depth), colour intrinsics K (3, 3), world_to_camera (4, 4);
    warnings: the messages of the Python warnings its refinement raised (in a Dask worker)."""

    reference: int
    frames: list
    depth: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray
    K: np.ndarray
    world_to_camera: np.ndarray
    seconds: float
    selection: dict
    warnings: list = field(default_factory=list)


def plan_view(capture, poses: np.ndarray, reference: int, *, min_covisibility: float,
              max_frames: int | None, poses_given: bool = True) -> ViewJob:
    """The job of one reference: the frames that see its surface, poses re-based onto it.

    capture: the whole capture; poses: (n, 4, 4) capture frame 0 -> frame i. The job's reference,
    frames and selection name the frames as the user knows them (:meth:`~o3d_mvps.Capture.frame_id`:
    their index in the capture given, also when registration dropped some), and so do the view's
    messages.
    """
    order = [reference] + [i for i in range(capture.n_frames) if i != reference]
    ids = [capture.frame_id(i) for i in order]
    rebased = poses[order] @ np.linalg.inv(poses[reference])
    sub = capture.select(order)
    selection = frames_seeing_reference(sub, rebased, min_covisibility=min_covisibility, max_frames=max_frames,
                                        frame_ids=ids)
    keep = [ids.index(i) for i in selection.frames]
    view = replace(sub.select(keep), frame_ids=selection.frames)
    return ViewJob(ids[0], selection.frames, capture_arrays(view), rebased[keep], poses[reference],
                   selection, poses_given)


def capture_arrays(capture) -> dict:
    """A capture as a dict of NumPy arrays and plain fields (no ground truth); :func:`capture_from_arrays` inverts it.
    The frames' file names and ids go with them, so that a view's messages name the frames as the
    user knows them (their index in the capture given, and file), not by their places in the view."""
    masks = None if capture.masks is None else [capture.mask_array(i) for i in range(capture.n_frames)]
    return {"color": [capture.color_array(i) for i in range(capture.n_frames)],
            "depth": [capture.depth_array(i) for i in range(capture.n_frames)], "masks": masks,
            "color_K": capture.color_K(), "depth_K": capture.depth_K(),
            "fields": {name: getattr(capture, name) for name in ("depth_scale", "depth_trunc", "color_encoding",
                                                                  "sensor", "light", "metadata", "frame_names",
                                                                  "frame_ids")}}


def capture_from_arrays(arrays: dict):
    """The :class:`~o3d_mvps.Capture` of :func:`capture_arrays`'s dict."""
    import open3d as o3d

    from ..capture import Capture, image_from_array

    def image(array, dtype):  # a fresh copy: arrays Dask deserialised carry a buffer format Open3D rejects
        return image_from_array(np.array(array, dtype=dtype))

    masks = arrays["masks"]
    return Capture(color=[image(c, np.float32) for c in arrays["color"]],
                   depth=[image(d[..., None], np.float32) for d in arrays["depth"]],
                   color_intrinsic=o3d.core.Tensor(np.array(arrays["color_K"], dtype=np.float64)),
                   depth_intrinsic=o3d.core.Tensor(np.array(arrays["depth_K"], dtype=np.float64)),
                   masks=None if masks is None else [None if m is None else image(m[..., None] * 255, np.uint8)
                                                     for m in masks],
                   **arrays["fields"])


def run_view(job: ViewJob, options, depth_source: str = "refined", device="auto") -> ViewResult:
    """Refine (or, for ``depth_source="raw"``, bicubic-upsample) a job's reference depth, on
    ``device`` (:func:`o3d_mvps.solver.device.check_device`)."""
    t0 = time.perf_counter()
    capture = capture_from_arrays(job.arrays)
    if depth_source == "refined":
        from ..solving import refine

        result = refine(capture, options, device, initial_poses=job.poses,
                        pose_trust=None if job.poses_given else False)
        albedo = result.albedo_array()
    else:
        from ..baselines import bicubic

        result = bicubic(capture)
        albedo = capture.color_array(0)
    depth = result.depth_array().astype(np.float64)
    mask = result.mask_array() & (depth > 0)
    return ViewResult(job.reference, job.frames, depth, mask, np.asarray(albedo, dtype=np.float32),
                      capture.color_K(), job.world_to_camera, time.perf_counter() - t0, job.selection.to_dict())
