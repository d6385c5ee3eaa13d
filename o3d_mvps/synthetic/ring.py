"""Synthetic captures that go around the object: a ring (or an arc of it) of frames, and scene mode.

Frames sit on :func:`.camera.ring_trajectory`'s ring (``arc_deg`` of it, evenly spaced),
rendered like :func:`.capture.render_capture` (8-bit sRGB colour, noisy 1 mm depth at 1/SF
resolution). The object alone comes with exact masks; in scene mode (``surroundings=True``) it
stands on a table in front of a wall (:mod:`.surroundings`) and the masks are left out, as in a
user's capture, so the automatic masks have to find it. Used by ``python -m benchmarks object``,
the reconstruction and real-capture tests, and the notebook.
"""

from __future__ import annotations

import open3d as o3d

from ..capture import Capture, default_depth_intrinsic
from ..model.se3 import relative_to_reference
from .camera import ring_trajectory
from .capture import capture_light, check_render_arguments
from .lights import PointLight, make_light
from .render import render_sensor_frames
from .scene import build_scene
from .sensor import DEPTH_SCALE


def render_ring(mesh="bunny", *, frames: int = 12, size=(160, 120), scale_factor: int = 4, arc_deg: float = 360.0,
                elevation_deg: float = 20.0, light: str = "led", surroundings: bool = False, seed: int = 0,
                noise: bool = True, sensor: str | None = None, object_size: float = 0.2, distance: float = 0.6,
                progress: bool = False, albedo: str = "patches", color_samples: int | None = None):
    """(Capture, scene): a ring capture of ``mesh`` and its :class:`~o3d_mvps.synthetic.SyntheticScene`.

    ``light``: "led", "directional" or "room" (:func:`~o3d_mvps.synthetic.make_light`; the
    capture's ``light`` says "led" or "room"). ``surroundings``: scene mode (table, wall, no
    masks). ``sensor``: the sensor profile, ``albedo`` the texture ("patches" or "speckled") and
    ``color_samples`` the colour rays per pixel side (:func:`~o3d_mvps.synthetic.render_capture`).
    ``capture.groundtruth.poses`` (n, 4, 4) map frame-0 camera -> frame-i camera (what a
    pose file gives); ground truth depth, normals and albedo cover the object only.
    ``capture.metadata["world_to_camera"]`` holds the poses from the scene's reference camera
    (the frame the scene's ray caster works in).
    """
    size = check_render_arguments(frames, scale_factor, size, None, light, object_size, distance)
    scene = build_scene(mesh, size=size, object_size=object_size, distance=distance, seed=seed,
                        surroundings=surroundings, albedo=albedo)
    world = ring_trajectory(frames, distance, elevation_deg, arc_deg)
    lighting = make_light(light, distance)
    rendered = render_sensor_frames(scene, world, lighting, scale_factor, seed=seed, noise=noise,
                                    sensor=sensor, masks=not surroundings, progress=progress,
                                    color_samples=color_samples)
    poses = relative_to_reference(world)
    gt = rendered.groundtruth(poses, lighting.parameters(poses, world[0]), world[0] @ scene.mesh_to_reference)
    K = scene.K
    offset = {"led_offset": [float(v) for v in lighting.offset]} if isinstance(lighting, PointLight) else {}
    capture = Capture(color=rendered.color, depth=rendered.depth, color_intrinsic=o3d.core.Tensor(K),
                      depth_intrinsic=o3d.core.Tensor(default_depth_intrinsic(K, scale_factor)), masks=rendered.masks,
                      depth_scale=DEPTH_SCALE, sensor="synthetic", light=capture_light(light), groundtruth=gt,
                      metadata={**offset, "world_to_camera": world.tolist(),
                                "synthetic": {**rendered.sensor_metadata(), "subdivisions": scene.subdivisions}})
    return capture, scene
