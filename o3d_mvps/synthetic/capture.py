"""The synthetic capture: argument checks and :func:`render_capture`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from ..capture import Capture, default_depth_intrinsic
from .camera import MAX_ORBIT_DEG, TRAJECTORIES, orbit_trajectory
from .lights import LIGHTS, PointLight, make_light
from .render import render_sensor_frames
from .scene import build_scene
from .sensor import DEPTH_SCALE

MAX_SCALE_FACTOR = 16


def check_render_arguments(frames, scale_factor, size, trajectory, light, object_size, distance) -> tuple[int, int]:
    """Validate the renderers' arguments (``trajectory`` None: a ring, nothing to check); returns (W, H)."""
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
    if trajectory is not None and trajectory not in TRAJECTORIES:
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
    sensor: str | None = None,
    object_size: float = 0.2,
    distance: float = 0.6,
    progress: bool = False,
    albedo: str = "patches",
    orbit_deg: float = MAX_ORBIT_DEG,
    color_samples: int | None = None,
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
    light : {"led", "directional", "room"}
        Point LED with shadows, the SH-exact directional light, or room light (ambient plus
        distant lights fixed in the scene, with shadows); see the module docstring.
    seed : int
        Seeds the albedo texture and the noise; equal seeds give identical captures.
    noise : bool
        Colour (sigma 0.005 linear) and depth (sigma 1e-5 z_mm^2 mm) noise; quantisation always.
        False is ``sensor="none"``.
    sensor : {"gaussian", "d415", "none"} or None
        Sensor profile (:data:`~o3d_mvps.synthetic.sensor.SENSORS`): the paper's Gaussian noise,
        a RealSense-D415-like sensor (disparity terraces, flying pixels, holes, exposure and
        white-balance drift, shot noise) or none; None: "gaussian", or "none" when not ``noise``.
    object_size, distance : float
        Largest bounding-box extent of the object and its distance to the reference camera (m).
    progress : bool
        Show a tqdm progress bar over frames.
    albedo : {"patches", "speckled"}
        The surface texture: coloured patches, or a pale stone with dark speckles
        (:class:`~o3d_mvps.synthetic.scene.SpeckledAlbedo`).
    orbit_deg : float
        The orbit's largest angle from the reference (degrees, 15 by default; 30: a wide baseline).
    color_samples : int or None
        Colour rays per pixel side, averaged (a box filter over the pixel's area, as a camera
        integrates; costs about ``color_samples**2`` times the point-sampled render); None: the
        sensor profile's (1 for "gaussian" and "none", 2 for "d415").

    Returns
    -------
    Capture
        Colour (H, W, 3) linear floats of 8-bit sRGB values, depth (h, w, 1) metres in 1 mm
        steps, masks (H, W, 1) uint8 255 on the object, and :class:`GroundTruth`.
    """
    W, H = check_render_arguments(frames, scale_factor, size, trajectory, light, object_size, distance)
    scene = build_scene(mesh, size=(W, H), object_size=object_size, distance=distance, seed=seed, albedo=albedo)
    if not (np.isfinite(orbit_deg) and 0 <= orbit_deg < 90):
        raise ValueError(f"orbit_deg must be an angle in [0, 90) degrees, got {orbit_deg!r}; e.g. 15 or 30")
    poses = orbit_trajectory(int(frames), distance, trajectory, float(orbit_deg))
    lighting = make_light(light, distance)
    rendered = render_sensor_frames(scene, poses, lighting, scale_factor, seed=seed, noise=noise, sensor=sensor,
                                    progress=progress, color_samples=color_samples)
    K = scene.K
    gt = rendered.groundtruth(poses, lighting.parameters(poses), scene.mesh_to_reference)
    return Capture(
        color=rendered.color,
        depth=rendered.depth,
        color_intrinsic=o3d.core.Tensor(K),
        depth_intrinsic=o3d.core.Tensor(default_depth_intrinsic(K, scale_factor)),
        masks=rendered.masks,
        depth_scale=DEPTH_SCALE,
        depth_trunc=3.0,
        color_encoding="srgb",
        sensor="synthetic",
        light=capture_light(light),
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
                "albedo": albedo,
                "orbit_deg": float(orbit_deg),
                "subdivisions": scene.subdivisions,
                **rendered.sensor_metadata(),
            }
        },
    )


def capture_light(light: str) -> str:
    """capture.json's ``light`` of a rendered light: "led" for the LED, "room" for the others (distant
    lights, which the first-order SH model describes)."""
    return "led" if light == "led" else "room"
