"""The synthetic capture: argument checks and :func:`render_capture`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from ..capture import Capture, GroundTruth, default_depth_intrinsic, image_from_array
from .camera import TRAJECTORIES, orbit_trajectory
from .lights import LIGHTS, PointLight, make_light
from .render import render_frame
from .scene import build_scene, random_stream
from .sensor import DEPTH_SCALE, quantise_srgb8, simulate_depth_sensor

MAX_SCALE_FACTOR = 16


def _check_arguments(frames, scale_factor, size, trajectory, light, object_size, distance) -> tuple[int, int]:
    """Validate render_capture's arguments; returns (W, H)."""
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise ValueError(
            f"frames must be an integer >= 1 (the reference is frame 0), got {frames!r}; pass e.g. frames=20"
        )
    if (
        isinstance(scale_factor, bool)
        or not isinstance(scale_factor, (int, np.integer))
        or not 1 <= scale_factor <= MAX_SCALE_FACTOR
    ):
        raise ValueError(
            f"scale_factor must be an integer in 1..{MAX_SCALE_FACTOR}, got {scale_factor!r}; pass e.g. scale_factor=4"
        )
    try:
        W, H = (int(s) for s in size)
        if (W, H) != tuple(size):
            raise ValueError
    except (TypeError, ValueError):
        raise ValueError(f"size must be (width, height) in pixels, got {size!r}; pass e.g. size=(640, 480)") from None
    if W < 8 or H < 8:
        raise ValueError(f"size {W}x{H} is too small; give at least 8x8 pixels, e.g. size=(640, 480)")
    if W % scale_factor or H % scale_factor:
        raise ValueError(
            f"scale_factor {scale_factor} does not divide the size {W}x{H}; choose a size whose width and "
            f"height are multiples of {scale_factor} (e.g. {W - W % scale_factor}x{H - H % scale_factor})"
        )
    if trajectory not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory {trajectory!r}; choose one of {list(TRAJECTORIES)}")
    if light not in LIGHTS:
        raise ValueError(f"unknown light {light!r}; choose one of {list(LIGHTS)}")
    if not (np.isfinite(object_size) and object_size > 0):
        raise ValueError(f"object_size must be a positive length in metres, got {object_size!r}; e.g. 0.2")
    if not (np.isfinite(distance) and distance > object_size):
        raise ValueError(
            f"distance ({distance!r} m) must exceed object_size ({object_size!r} m) so the camera is outside "
            "the object; e.g. distance=0.6 with object_size=0.2"
        )
    return W, H


# --------------------------------------------------------------------------------------
# The capture
# --------------------------------------------------------------------------------------
def render_capture(
    mesh,
    *,
    frames: int = 20,
    scale_factor: int = 4,
    size=(640, 480),
    trajectory: str = "orbit",
    light: str = "led",
    seed: int = 0,
    noise: bool = True,
    object_size: float = 0.2,
    distance: float = 0.6,
    progress: bool = False,
) -> Capture:
    """Render a synthetic LED-lit RGB-D capture of ``mesh`` with ground truth.

    Parameters
    ----------
    mesh : o3d.t.geometry.TriangleMesh, o3d.geometry.TriangleMesh, str or Path
        The object; ``"bunny"``, ``"armadillo"`` or a mesh file load via :mod:`o3d_mvps.datasets`.
    frames : int
        Number of frames n >= 1; frame 0 is the reference (pose identity).
    scale_factor : int
        Super-resolution factor SF (1..16) dividing both image sides; depth is (H/SF, W/SF).
    size : (int, int)
        Colour resolution (W, H) in pixels.
    trajectory : {"orbit", "orbit-translate"}
        See :func:`orbit_trajectory`.
    light : {"led", "directional"}
        Point LED with shadows, or the SH-exact directional light (module docstring).
    seed : int
        Seeds the albedo texture and the noise; equal seeds give identical captures.
    noise : bool
        Colour (sigma 0.005 linear) and depth (sigma 1e-5 z_mm^2 mm) noise; quantisation always.
    object_size, distance : float
        Largest bounding-box extent of the object and its distance to the reference camera (m).
    progress : bool
        Show a tqdm progress bar over frames.

    Returns
    -------
    Capture
        Colour (H, W, 3) linear floats of 8-bit sRGB values, depth (h, w, 1) metres in 1 mm
        steps, masks (H, W, 1) uint8 255 on the object, and :class:`GroundTruth`.
    """
    W, H = _check_arguments(frames, scale_factor, size, trajectory, light, object_size, distance)
    scene = build_scene(mesh, size=(W, H), object_size=object_size, distance=distance, seed=seed)
    poses = orbit_trajectory(int(frames), distance, trajectory)
    lighting = make_light(light, distance)
    color_rng = random_stream(seed, "color") if noise else None
    depth_rng = random_stream(seed, "depth") if noise else None

    color, depth, masks = [], [], []
    reference = None
    for i in _progress(range(int(frames)), progress):
        frame = render_frame(scene, poses[i], lighting)
        reference = frame if i == 0 else reference
        color.append(image_from_array(quantise_srgb8(frame.color, color_rng).astype(np.float32)))
        z = simulate_depth_sensor(frame.depth, scale_factor, depth_rng)
        depth.append(image_from_array(z.astype(np.float32)[:, :, None]))
        masks.append(image_from_array((frame.mask * np.uint8(255))[:, :, None]))

    K = scene.K
    gt = GroundTruth(
        depth=reference.depth.astype(np.float32),
        normals=reference.normals.astype(np.float32),
        albedo=reference.albedo.astype(np.float32),
        poses=poses,
        light=lighting.parameters(poses),
        mesh_to_reference=scene.mesh_to_reference,
    )
    return Capture(
        color=color,
        depth=depth,
        color_intrinsic=o3d.core.Tensor(K),
        depth_intrinsic=o3d.core.Tensor(default_depth_intrinsic(K, scale_factor)),
        masks=masks,
        depth_scale=DEPTH_SCALE,
        depth_trunc=3.0,
        color_encoding="srgb",
        sensor="synthetic",
        groundtruth=gt,
        metadata={
            # what a user measures with a ruler and writes into capture.json (read by refine)
            **({"led_offset": [float(v) for v in lighting.offset]} if isinstance(lighting, PointLight) else {}),
            "synthetic": {
                "mesh": str(mesh) if isinstance(mesh, (str, Path)) else type(mesh).__name__,
                "frames": int(frames),
                "scale_factor": int(scale_factor),
                "size": [W, H],
                "trajectory": trajectory,
                "light": light,
                "seed": int(seed),
                "noise": bool(noise),
                "object_size": float(object_size),
                "distance": float(distance),
            }
        },
    )


def _progress(iterable, enabled: bool):
    """Wrap ``iterable`` in a tqdm bar when ``enabled``."""
    if not enabled:
        return iterable
    from tqdm.auto import tqdm

    return tqdm(iterable, desc="rendering", unit="frame")
