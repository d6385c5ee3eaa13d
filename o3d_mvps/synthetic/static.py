"""Static-camera, moving-light captures (the setting of Peng et al. 2017 and its public data): the
camera stays at the reference pose while a light is moved by hand around it, one position per frame.

Rendered like :func:`.capture.render_capture` (same scene, sensors and ground truth); the poses
are all the identity, the light is a point light per frame at :func:`.lights.handheld_offsets`
(0.3-0.5 m from the optical axis, in the camera's plane, 1/r^2, shadows), and capture.json says
``"camera": "static"`` (no "light": refine then uses per-frame SH,
:func:`o3d_mvps.solving.with_light_model`). Used by ``o3d-mvps render --static-camera``, the
static-camera tests and ``python -m benchmarks static``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from ..capture import Capture, default_depth_intrinsic
from .capture import check_render_arguments
from .lights import HANDHELD_RADIUS, handheld_lights, handheld_parameters
from .render import render_sensor_frames
from .scene import build_scene
from .sensor import DEPTH_SCALE


def render_static_capture(mesh="bunny", *, frames: int = 20, scale_factor: int = 2, size=(1280, 960),
                          light_radius=HANDHELD_RADIUS, seed: int = 0, sensor: str | None = None, noise: bool = True,
                          object_size: float = 0.2, distance: float = 0.6, shadows: bool = True,
                          albedo: str = "patches", masks: bool = True, progress: bool = False,
                          color_samples: int | None = None) -> Capture:
    """Render a static-camera capture of ``mesh`` lit by a hand-held light, with ground truth.

    Parameters
    ----------
    mesh : o3d.t.geometry.TriangleMesh, o3d.geometry.TriangleMesh, str or Path
        The object (as :func:`~o3d_mvps.synthetic.render_capture`).
    frames : int
        Number of frames n >= 1 (Peng et al.'s data: about 20).
    scale_factor : int
        Depth grid = colour size / SF (Peng et al.'s data: 1280x960 colour, 640x480 depth, SF 2).
    size : (int, int)
        Colour resolution (W, H) in pixels.
    light_radius : (float, float)
        The light's distance range from the optical axis (m).
    seed : int
        Seeds the albedo texture and the noise.
    sensor : {"gaussian", "d415", "none"} or None
        Sensor profile (:data:`~o3d_mvps.synthetic.sensor.SENSORS`); None: "gaussian", or
        "none" when not ``noise``.
    noise : bool
        False: quantisation only (``sensor="none"``).
    object_size, distance : float
        Largest extent of the object and its distance to the camera (m).
    shadows : bool
        Cast shadows (a shadow ray toward the light per pixel; False: every surface facing the
        light is lit, as the ``point`` light model assumes).
    albedo : {"patches", "speckled"}
        The surface texture (:data:`~o3d_mvps.synthetic.scene.ALBEDOS`).
    masks : bool
        False: no object masks (a user's capture without ``mask/``, refined as ``--mask none``).
    progress : bool
        Show a progress bar over frames.
    color_samples : int or None
        Colour rays per pixel side, averaged over the pixel's area (as
        :func:`~o3d_mvps.synthetic.render_capture`); None: the sensor profile's.

    Returns
    -------
    Capture
        ``camera == "static"``, ``light`` None; ground truth poses all the identity and
        ``light["positions"]`` the n light positions (reference frame, m).
    """
    # the camera stands still in front of the object: a sheet wider than its distance (a quilt) is fine
    W, H = check_render_arguments(frames, scale_factor, size, None, "led", object_size, 2 * object_size + 1)
    if not (np.isfinite(distance) and distance > 0):
        raise ValueError(f"distance must be a positive length in metres, got {distance!r}; e.g. 0.6")
    radius = tuple(float(r) for r in light_radius)
    if len(radius) != 2 or not 0 <= radius[0] <= radius[1] or not np.isfinite(radius).all():
        raise ValueError(f"light_radius must be (near, far) metres with 0 <= near <= far, got {light_radius!r}; "
                         "e.g. (0.3, 0.5)")
    scene = build_scene(mesh, size=(W, H), object_size=object_size, distance=distance, seed=seed, albedo=albedo)
    poses = np.tile(np.eye(4), (int(frames), 1, 1))
    lights = handheld_lights(int(frames), distance, radius, shadows)
    rendered = render_sensor_frames(scene, poses, lights, scale_factor, seed=seed, noise=noise, sensor=sensor,
                                    masks=masks, progress=progress, color_samples=color_samples)
    gt = rendered.groundtruth(poses, handheld_parameters(lights), scene.mesh_to_reference)
    K = scene.K
    return Capture(
        color=rendered.color, depth=rendered.depth, color_intrinsic=o3d.core.Tensor(K),
        depth_intrinsic=o3d.core.Tensor(default_depth_intrinsic(K, scale_factor)), masks=rendered.masks,
        depth_scale=DEPTH_SCALE, depth_trunc=3.0, color_encoding="srgb", sensor="synthetic", camera="static",
        groundtruth=gt,
        metadata={"synthetic": {
            "mesh": str(mesh) if isinstance(mesh, (str, Path)) else type(mesh).__name__, "frames": int(frames),
            "scale_factor": int(scale_factor), "size": [W, H], "camera": "static", "light": "handheld",
            "light_radius": list(radius), "seed": int(seed), "object_size": float(object_size),
            "distance": float(distance), "subdivisions": scene.subdivisions, **rendered.sensor_metadata()}},
    )


#: the quilt's size (m): wider than a 60-degree camera's view at 0.55 m (0.64 m), a little
#: shorter than its height (0.48 m), so the sheet's top and bottom edges lie inside the frame
QUILT_SIZE = (0.8, 0.44)
#: the quilt's distance from the camera (m): the real quilt capture of issue 32
QUILT_DISTANCE = 0.55


def quilt_mesh(size=QUILT_SIZE, cushion_m: float = 0.04, height_m: float = 0.002, tilt_deg: float = 10.0,
               step_m: float = 0.002) -> o3d.geometry.TriangleMesh:
    """A quilted sheet (the predecessor's quilt captures): a grid mesh ``size`` (width, height) m
    with sin^2 cushions ``cushion_m`` wide and ``height_m`` high toward +z, tilted by ``tilt_deg``
    about the vertical axis, vertices every ``step_m``; y up, +z toward the camera, as
    :func:`~o3d_mvps.synthetic.scene.placement_transform` expects. Give
    :func:`render_static_capture` ``object_size=size[0]`` to keep it at these metres."""
    w, h = (float(v) for v in size)
    x, y = np.meshgrid(np.linspace(-w / 2, w / 2, int(round(w / step_m)) + 1),
                       np.linspace(-h / 2, h / 2, int(round(h / step_m)) + 1))
    k = np.pi / cushion_m
    z = height_m * (np.sin(k * x) * np.sin(k * y)) ** 2 - np.tan(np.radians(tilt_deg)) * x
    rows, cols = x.shape
    index = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel()
    triangles = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])  # counter-clockwise seen from +z
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.stack([x, y, z], -1).reshape(-1, 3)),
                                     o3d.utility.Vector3iVector(triangles.astype(np.int32)))
    return mesh
