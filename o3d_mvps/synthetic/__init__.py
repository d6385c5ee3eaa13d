"""Synthetic captures: a mesh rendered by ray casting under an LED that moves with the camera,
alone or (scene mode, :func:`render_ring` with ``surroundings=True``) on a table in front of a wall.

The benchmark protocol of the paper's synthetic experiments (Sec. 5.1; docs/benchmarks.md).
Conventions (all lengths in metres):

- Reference camera (frame 0) at the origin, looking along +z, x right, y down (OpenCV /
  Open3D). The mesh (assumed y-up, Stanford style) is turned upright (180 degrees about x, so
  its +z side faces the camera), centred, scaled so its largest bounding-box extent is
  ``object_size`` and put at ``(0, 0, distance)``: ``mesh_to_reference`` (4x4 similarity).
- Colour intrinsics: a pinhole with 60 degree horizontal field of view, square pixels,
  principal point at the image centre ``((W - 1)/2, (H - 1)/2)`` (pixel centres at integer
  coordinates). Depth intrinsics: :func:`o3d_mvps.capture.default_depth_intrinsic`.
- Poses: ``poses[i]`` (4x4) maps reference-camera coordinates to frame-i camera coordinates;
  ``poses[0]`` is the identity. The cameras look at the object centre.
- Colour: linear RGB ``albedo * shading`` (+ Gaussian noise), quantised to 8-bit sRGB; the
  stored floats are exactly ``srgb_to_linear(k / 255)``. Background 0.
- Depth: z rendered at colour resolution, area-averaged over SF x SF blocks (a block is valid
  only if all its pixels hit the object), + Gaussian noise ``sigma = 1e-5 z_mm^2`` mm, 1 mm
  quantisation.
- Sensor profiles (``sensor=``, :mod:`.sensor`): "gaussian" (the two lines above, the default),
  "d415" (an active-stereo camera like the RealSense D415: disparity terraces, flying pixels,
  z^2 noise with a smooth low-frequency part, speckle holes; colour integrated over each pixel's
  area by 2 x 2 rays, with per-frame exposure and white-balance drift, shot and read noise),
  "none" (quantisation only). ``color_samples=`` sets the rays per pixel side of any profile.
- Static camera (:func:`render_static_capture`): identity poses, a hand-held point light moved
  around the camera, one position per frame (Peng et al. 2017's setting).

Lights (``groundtruth.light``):

- ``"led"``: a point light at ``offset`` in the camera frame (it moves with the camera);
  ``I = albedo * (ambient + intensity * V * max(0, n.l) / r^2)``, l the unit vector to the light,
  r its distance, V = 0 where a shadow ray toward the light is blocked.
- ``"directional"``: SH-exact, ``I = albedo * <l_i, [1, n_x, n_y, n_z]>`` with n the unit normal
  (pointing to the camera) in reference-camera coordinates and ``l_i = light["sh"][i]``;
  no clamping, no shadows (the shading is positive for every normal).
- ``"room"``: room light fixed in the scene, ``I = albedo * (ambient + sum_k s_k V_k max(0, n.d_k))``
  over three distant lights (directions d_k in reference coordinates, V_k shadow visibility);
  every frame sees the same light. A capture's ``light`` is "led" for the LED, else "room".
"""

from .camera import (HORIZONTAL_FOV_DEG, MAX_ORBIT_DEG, ORBIT_TURNS, TRAJECTORIES, camera_rays, look_at_pose,
                     orbit_trajectory, ring_trajectory, synthetic_intrinsics)
from .capture import MAX_SCALE_FACTOR, render_capture
from .lights import (LED_AMBIENT, LED_FRONTAL_IRRADIANCE, LED_OFFSET, LIGHTS, SH_AMBIENT, SH_DIRECTION, SH_STRENGTH,
                     DirectionalLight, PointLight, RoomLight, make_light)
from .render import FrameRender, SensorFrames, render_frame, render_sensor_frames
from .ring import render_ring
from .static import QUILT_DISTANCE, QUILT_SIZE, quilt_mesh, render_static_capture
from .scene import ProceduralAlbedo, SyntheticScene, build_scene, placement_transform, random_stream
from .sensor import (COLOR_NOISE_SIGMA, DEPTH_SCALE, SENSORS, SRGB8_TO_LINEAR, D415Sensor, GaussianSensor,
                     depth_noise_sigma, make_sensor, quantise_srgb8, simulate_depth_sensor)

__all__ = [
    "render_capture", "render_ring", "render_static_capture", "quilt_mesh", "QUILT_SIZE", "QUILT_DISTANCE", "SENSORS", "make_sensor", "GaussianSensor",
    "D415Sensor", "build_scene", "render_frame", "render_sensor_frames", "SensorFrames", "make_light",
    "PointLight", "DirectionalLight", "RoomLight", "FrameRender",
    "SyntheticScene", "ProceduralAlbedo", "placement_transform", "random_stream", "synthetic_intrinsics",
    "camera_rays", "look_at_pose", "orbit_trajectory", "ring_trajectory", "quantise_srgb8", "depth_noise_sigma",
    "simulate_depth_sensor", "TRAJECTORIES", "LIGHTS", "MAX_SCALE_FACTOR", "HORIZONTAL_FOV_DEG", "MAX_ORBIT_DEG",
    "ORBIT_TURNS", "COLOR_NOISE_SIGMA", "DEPTH_SCALE", "SRGB8_TO_LINEAR", "LED_OFFSET", "LED_FRONTAL_IRRADIANCE",
    "LED_AMBIENT", "SH_AMBIENT", "SH_STRENGTH", "SH_DIRECTION",
]
