"""Synthetic captures that go around the object: a ring (or an arc of it) of LED-lit frames.

Frames sit on :func:`.camera.ring_trajectory`'s ring (``arc_deg`` of it, evenly spaced),
rendered like :func:`.capture.render_capture` (8-bit sRGB colour, noisy 1 mm depth at 1/SF
resolution, exact masks). Used by ``python -m benchmarks object``, the reconstruction tests and
the notebook.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from ..capture import Capture, GroundTruth, default_depth_intrinsic, image_from_array
from ..model.se3 import relative_to_reference
from .camera import ring_trajectory
from .lights import make_light
from .render import render_frame
from .scene import build_scene, random_stream
from .sensor import DEPTH_SCALE, quantise_srgb8, simulate_depth_sensor


def render_ring(mesh="bunny", *, frames: int = 12, size=(160, 120), scale_factor: int = 4, arc_deg: float = 360.0,
                elevation_deg: float = 20.0, seed: int = 0, object_size: float = 0.2, distance: float = 0.6):
    """(Capture, scene): a ring capture of ``mesh`` and its :class:`~o3d_mvps.synthetic.SyntheticScene`.

    ``capture.groundtruth.poses`` (n, 4, 4) map frame-0 camera -> frame-i camera (what a pose
    file gives); ``capture.metadata["world_to_camera"]`` holds the poses from the scene's
    reference camera (the frame the scene's ray caster works in).
    """
    scene = build_scene(mesh, size=size, object_size=object_size, distance=distance, seed=seed)
    world = ring_trajectory(frames, distance, elevation_deg, arc_deg)
    light = make_light("led", distance)
    color_rng, depth_rng = random_stream(seed, "color"), random_stream(seed, "depth")
    color, depth, masks, renders = [], [], [], []
    for pose in world:
        frame = render_frame(scene, pose, light)
        color.append(image_from_array(quantise_srgb8(frame.color, color_rng).astype(np.float32)))
        z = simulate_depth_sensor(frame.depth, scale_factor, depth_rng)
        depth.append(image_from_array(z.astype(np.float32)[:, :, None]))
        masks.append(image_from_array((frame.mask * np.uint8(255))[:, :, None]))
        renders.append(frame)
    poses = relative_to_reference(world)
    gt = GroundTruth(depth=renders[0].depth.astype(np.float32), normals=renders[0].normals.astype(np.float32),
                     albedo=renders[0].albedo.astype(np.float32), poses=poses, light=light.parameters(poses),
                     mesh_to_reference=world[0] @ scene.mesh_to_reference)
    K = scene.K
    capture = Capture(color=color, depth=depth, color_intrinsic=o3d.core.Tensor(K),
                      depth_intrinsic=o3d.core.Tensor(default_depth_intrinsic(K, scale_factor)), masks=masks,
                      depth_scale=DEPTH_SCALE, sensor="synthetic", groundtruth=gt,
                      metadata={"led_offset": [float(v) for v in light.offset], "world_to_camera": world.tolist()})
    return capture, scene
