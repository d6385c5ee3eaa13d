"""Rendering frames: ray casting, normals, albedo and shading at colour resolution, then the sensors."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from ..capture import GroundTruth, image_from_array
from .camera import camera_rays, subpixel_offsets
from .scene import SyntheticScene, apply_matrix, random_stream
from .sensor import resolve_sensor


@dataclass
class FrameRender:
    """Noise-free buffers of one frame at colour resolution (H, W), camera-frame quantities.

    ``mask`` (H, W) bool on the object; ``hit`` (H, W) bool on any surface (the object, and in
    scene mode the table and wall); ``depth`` (H, W) float64 z metres; ``points`` (H, W, 3)
    camera-frame hit points; ``normals`` (H, W, 3) unit normals, camera frame, pointing to the
    camera; ``albedo`` (H, W, 3) linear RGB; ``color`` (H, W, 3) linear RGB ``albedo * shading``
    (not clipped). Zero where nothing was hit.
    """

    mask: np.ndarray
    hit: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    color: np.ndarray

    @property
    def object_depth(self) -> np.ndarray:
        """``depth`` (H, W) on the object, 0 elsewhere (the ground truth's depth)."""
        return np.where(self.mask, self.depth, 0.0)


def render_frame(scene: SyntheticScene, pose: np.ndarray, light, color_samples: int = 1) -> FrameRender:
    """Ray-cast one frame with ``pose`` (4, 4) reference -> frame; one ray per pixel centre.

    ``light`` is a :class:`PointLight`, :class:`DirectionalLight` or :class:`RoomLight` (see
    :func:`make_light`); it shades every surface hit. ``color_samples`` s > 1: the colour is the
    mean of s x s rays spread over each pixel's area (:func:`~.camera.subpixel_offsets`, a box
    filter, as a sensor's pixel integrates the light falling on it: an albedo edge or the
    silhouette inside a pixel gives a mixed value); the geometry buffers (mask, depth, normals,
    albedo: the ground truth) stay at the pixel centres. Costs about s^2 times the s = 1 render.
    """
    check_color_samples(color_samples)
    frame = _cast(scene, pose, light, scene.rays)
    if color_samples > 1:
        centre = frame.color
        frame.color = np.zeros_like(centre)
        for offset in subpixel_offsets(color_samples):  # an odd s's middle sample is the centre's ray
            if offset == (0.0, 0.0):
                frame.color += centre
                continue
            frame.color += _cast(scene, pose, light, camera_rays(scene.K, scene.size, offset).reshape(-1, 3)).color
        frame.color /= color_samples**2
    return frame


def check_color_samples(color_samples) -> None:
    """ValueError unless ``color_samples`` is an integer >= 1 (subpixel rays per pixel side)."""
    if isinstance(color_samples, bool) or not isinstance(color_samples, (int, np.integer)) or color_samples < 1:
        raise ValueError(f"color_samples must be an integer >= 1 (subpixel rays per pixel side), got "
                         f"{color_samples!r}; pass e.g. 2 (2 x 2 rays per pixel) or 1 (the pixel centre only)")


def _cast(scene: SyntheticScene, pose: np.ndarray, light, d_cam: np.ndarray) -> FrameRender:
    """The buffers of one frame for the unit rays ``d_cam`` (H*W, 3), camera frame, row-major."""
    W, H = scene.size
    R_c2r = pose[:3, :3].T
    C = -R_c2r @ pose[:3, 3]
    rays = np.empty((H * W, 6), dtype=np.float32)
    rays[:, :3] = C
    rays[:, 3:] = apply_matrix(R_c2r.astype(np.float32), d_cam.astype(np.float32))
    hit = scene.raycaster.cast_rays(o3d.core.Tensor(rays), nthreads=0)
    t = hit["t_hit"].numpy()  # distance along the unit ray
    index = np.flatnonzero(np.isfinite(t))
    geometry = hit["geometry_ids"].numpy()[index].astype(np.int64)
    on_object = geometry == scene.object_id
    d_hit = d_cam[index]
    points = t[index, None].astype(np.float64) * d_hit
    points_scene = apply_matrix(R_c2r, points) + C
    normals_scene = np.empty_like(points)
    albedo = np.empty_like(points)
    normals_scene[on_object] = scene.smooth_normals(hit["primitive_ids"].numpy()[index[on_object]].astype(np.int64),
                                                    hit["primitive_uvs"].numpy()[index[on_object]].astype(np.float64))
    albedo[on_object] = scene.albedo(scene.object_coordinates(points_scene[on_object]))
    if scene.surroundings is not None:
        room = ~on_object
        normals_scene[room] = scene.surroundings.normals(geometry[room])
        albedo[room] = scene.surroundings.albedo(geometry[room], points_scene[room])
    normals = apply_matrix(R_c2r.T, normals_scene)
    normals *= np.where(np.einsum("ij,ij->i", normals, d_hit) > 0, -1.0, 1.0)[:, None]  # face the camera

    def image(values: np.ndarray) -> np.ndarray:
        out = np.zeros((H * W,) + values.shape[1:])
        out[index] = values
        return out.reshape((H, W) + values.shape[1:])

    mask, any_hit = np.zeros(H * W, dtype=bool), np.zeros(H * W, dtype=bool)
    mask[index[on_object]] = True
    any_hit[index] = True
    frame = FrameRender(
        mask=mask.reshape(H, W),
        hit=any_hit.reshape(H, W),
        depth=image(points[:, 2]),
        points=image(points),
        normals=image(normals),
        albedo=image(albedo),
        color=np.zeros((H, W, 3)),
    )
    frame.color[frame.hit] = albedo * light.shading(scene, pose, frame)[:, None]
    return frame


@dataclass
class SensorFrames:
    """What the cameras recorded: ``color`` n (H, W, 3) float32 images (8-bit sRGB values,
    linearised), ``depth`` n (h, w, 1) float32 images (metres, 1 mm steps), ``masks`` n (H, W, 1)
    uint8 images of the object or None, the reference frame's noise-free ``reference``, and the
    sensor profile's ``sensor`` description with its per-frame draws ``frames`` (e.g. the D415
    profile's exposure gain and white balance)."""

    color: list
    depth: list
    masks: list | None
    reference: FrameRender
    sensor: dict | None = None
    frames: list | None = None

    def groundtruth(self, poses: np.ndarray, light: dict, mesh_to_reference: np.ndarray) -> GroundTruth:
        """The reference frame's ground truth on the object (zero on the table and wall), with the
        capture's ``poses`` (n, 4, 4; frame 0 -> frame i), ``light`` parameters and placement."""
        frame, on_object = self.reference, self.reference.mask[..., None]
        return GroundTruth(depth=frame.object_depth.astype(np.float32),
                           normals=np.where(on_object, frame.normals, 0.0).astype(np.float32),
                           albedo=np.where(on_object, frame.albedo, 0.0).astype(np.float32),
                           poses=poses, light=light, mesh_to_reference=mesh_to_reference)

    def sensor_metadata(self) -> dict:
        """``{"sensor": {...profile, "frames": [...]}}`` for capture.json's metadata.synthetic."""
        return {"sensor": {**(self.sensor or {}), **({"frames": self.frames} if any(self.frames or []) else {})}}


def render_sensor_frames(scene: SyntheticScene, poses: np.ndarray, light, scale_factor: int, *, seed: int = 0,
                         noise: bool = True, sensor: str | None = None, masks: bool = True,
                         progress: bool = False, color_samples: int | None = None) -> SensorFrames:
    """Render every pose (n, 4, 4; scene frame -> camera) and simulate the colour and depth sensors.

    ``light``: one light for every frame, or a sequence of n (one per frame). ``sensor``: the
    profile (:data:`~o3d_mvps.synthetic.sensor.SENSORS`; None: "gaussian", or "none" when not
    ``noise``); its noise is drawn from ``seed``'s colour and depth streams. ``masks=False``
    leaves the object masks out (what a user's capture without a ``mask/`` folder looks like).
    ``color_samples``: subpixel samples per side of the colour's box filter (:func:`render_frame`);
    None: the profile's (``color_samples`` of the sensor: 1 for "gaussian" and "none", the
    paper's point-sampled protocol; 2 for "d415", a real camera's pixel area).
    """
    profile = resolve_sensor(sensor, noise)
    samples = profile.color_samples if color_samples is None else color_samples
    check_color_samples(samples)
    lights = list(light) if isinstance(light, (list, tuple)) else [light] * len(poses)
    if len(lights) != len(poses):
        raise ValueError(f"{len(lights)} lights for {len(poses)} poses; give one light, or one per frame")
    color_rng, depth_rng = random_stream(seed, "color"), random_stream(seed, "depth")
    color, depth, object_masks, reference, draws = [], [], [], None, []
    for pose, frame_light in _progress(list(zip(poses, lights)), progress):
        frame = render_frame(scene, pose, frame_light, samples)
        reference = frame if reference is None else reference
        image, drawn = profile.color(frame.color, color_rng)
        color.append(image_from_array(image))
        draws.append(drawn)
        z = profile.depth(frame.depth, scale_factor, depth_rng)
        depth.append(image_from_array(z.astype(np.float32)[:, :, None]))
        object_masks.append(image_from_array((frame.mask * np.uint8(255))[:, :, None]))
    described = {**profile.describe(), "color_samples": int(samples)}
    return SensorFrames(color, depth, object_masks if masks else None, reference, described, draws)


def _progress(iterable, enabled: bool):
    """Wrap ``iterable`` in a tqdm bar when ``enabled``."""
    if not enabled:
        return iterable
    from tqdm.auto import tqdm

    return tqdm(iterable, desc="rendering", unit="frame")
