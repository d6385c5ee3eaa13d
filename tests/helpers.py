"""Helpers shared by the test files: a small solver problem, perturbed starts for the solver,
finite-difference checks and an analytic scene.

The analytic scene is rendered here from closed-form geometry with the model's own shading
(:mod:`o3d_mvps.model.shading`), without :mod:`o3d_mvps.synthetic`, so a solver test on it does
not share a renderer's conventions (or bugs) with the code under test.
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from o3d_mvps.capture import Capture, GroundTruth, default_depth_intrinsic, image_from_array
from o3d_mvps.model import se3
from o3d_mvps.metrics import reprojection_error_px
from o3d_mvps.model.camera import backproject, pixel_grid
from o3d_mvps.model.normals import masked_grid, perspective_normals
from o3d_mvps.model.resampling import block_average
from o3d_mvps.model.shading import led_vectors
from o3d_mvps.solver.pose import update_pose
from o3d_mvps.solver.problem import Estimate, LevelProblem
from o3d_mvps.solver.pyramid import Level, depth_prior
from o3d_mvps.synthetic import D415Sensor

#: LED offset error handed to the solver by accuracy tests (metres, camera frame): 1.5 cm off.
LED_OFFSET_ERROR = np.array([0.012, -0.009, 0.0])


def with_led_offset_error(capture: Capture, error=LED_OFFSET_ERROR) -> Capture:
    """A copy of a rendered capture whose metadata's LED offset (what ``refine`` starts from) is
    ``error`` (3,) metres away from the offset it was rendered with."""
    offset = np.asarray(capture.metadata["led_offset"], dtype=np.float64) + error
    return dataclasses.replace(capture, metadata={**capture.metadata, "led_offset": offset.tolist()})


def kicked_poses(poses: np.ndarray, seed: int = 2, metres: float = 0.003, degrees: float = 0.4) -> np.ndarray:
    """Poses (n, 4, 4) with every non-reference pose kicked by ~``metres`` and ~``degrees`` per axis."""
    rng = np.random.default_rng(seed)
    start = np.array(poses, dtype=np.float64, copy=True)
    for i in range(1, len(start)):
        kick = np.concatenate([rng.normal(0, metres, 3), np.radians(rng.normal(0, degrees, 3))])
        start[i] = se3.exp(kick) @ start[i]
    return start


# ------------------------------------------------------------------------------------------
# A small level problem on a bump (K, SIZE) for derivative checks
# ------------------------------------------------------------------------------------------
K = np.array([[120.0, 0, 31.5], [0, 120.0, 23.5], [0, 0, 1]])
SIZE = (48, 64)


def bump_depth(size=SIZE, K=K, depth=0.6, height=0.04):
    u, v = pixel_grid(*size)
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    return depth - height * np.exp(-(x**2 + y**2) / 0.02)


def smooth_image(size=SIZE):
    u, v = pixel_grid(*size)
    return np.stack([0.5 + 0.3 * np.sin(u / 7.0) * np.cos(v / 9.0), 0.4 + 0.2 * np.cos(u / 5.0 + v / 11.0),
                     0.5 + 0.25 * np.sin((u + v) / 8.0)], -1).astype(np.float64)


def make_problem(n_frames=2, tau=1.0):
    z = bump_depth()
    mask = np.zeros(SIZE, bool)
    mask[6:-6, 8:-8] = True
    grid = masked_grid(mask)
    images = [smooth_image() for _ in range(n_frames)]
    z0 = z.reshape(SIZE[0] // 2, 2, SIZE[1] // 2, 2).mean(axis=(1, 3))
    level = Level(0, grid, K, SIZE, images, [None] * n_frames, depth_prior(grid, z0, 2.0))
    problem = LevelProblem(level, tau, 0.04)
    rng = np.random.default_rng(1)
    poses = np.stack([np.eye(4)] + [se3.exp([0.01, -0.005, 0.002, 0.01, -0.02, 0.005])] * (n_frames - 1))
    lights = np.array([[0.2, 0.1, -0.1, -1.0], [0.1, -0.2, 0.05, -0.9]])[:n_frames]
    est = Estimate(grid.gather(z) + rng.normal(0, 1e-3, grid.size), 0.5 + 0.1 * rng.random((grid.size, 3)), lights,
                   poses)
    return problem, est


def assert_gradient_at_random_pixels(energy, grad, z, rng, count=25, h=1e-7):
    """Central differences of ``energy`` at ``count`` random entries of z match ``grad``."""
    for k in rng.choice(z.size, count, replace=False):
        d = np.zeros(z.size)
        d[k] = h
        fd = (energy(z + d) - energy(z - d)) / (2 * h)
        assert fd == pytest.approx(grad[k], rel=1e-4, abs=1e-6 * np.abs(grad).max())


def perturb_and_refine_poses(problem, est, true_poses, points, normals, seed=7):
    """Kick frames 1.. of ``est`` off the true poses (~2 mm, ~0.25 deg) and refine each with the
    pose step; returns the reprojection errors (px) before and after, each (n - 1,)."""
    rng = np.random.default_rng(seed)
    before, after = [], []
    K = problem.level.K
    for i in range(1, problem.n_frames):
        kick = np.concatenate([rng.normal(0, 0.002, 3), np.radians(rng.normal(0, 0.25, 3))])
        est.poses[i] = se3.exp(kick) @ true_poses[i]
        before.append(reprojection_error_px(est.poses[i], true_poses[i], points, K))
        refined = update_pose(problem, est, i, points, normals, iterations=10)
        after.append(reprojection_error_px(refined, true_poses[i], points, K))
    return np.array(before), np.array(after)


# ------------------------------------------------------------------------------------------
# An analytic relief: z = DISTANCE + AMPLITUDE sin(2 pi x / PERIOD) cos(2 pi y / PERIOD)
# ------------------------------------------------------------------------------------------
DISTANCE, AMPLITUDE, PERIOD = 0.5, 0.004, 0.08  # metres; steepest slope 17 degrees
LED = np.array([0.03, -0.02, 0.0])  # metres, camera frame
LED_AMBIENT, LED_INTENSITY = 0.05, 0.8 * DISTANCE**2


def relief_depth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Depth z (metres) of the relief at reference-frame lateral coordinates x, y (metres)."""
    k = 2 * np.pi / PERIOD
    return DISTANCE + AMPLITUDE * np.sin(k * x) * np.cos(k * y)


def relief_normals(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Unit normals (..., 3) of the relief, reference frame, pointing to the camera (-z)."""
    k = 2 * np.pi / PERIOD
    zx = AMPLITUDE * k * np.cos(k * x) * np.cos(k * y)
    zy = -AMPLITUDE * k * np.sin(k * x) * np.sin(k * y)
    n = np.stack([zx, zy, -np.ones_like(x)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def relief_albedo(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Linear RGB albedo (..., 3) in [0.3, 0.8], smooth patches on the relief."""
    return np.stack([0.55 + 0.25 * np.sin(x / 0.03), 0.55 + 0.25 * np.cos(y / 0.04),
                     0.55 + 0.25 * np.sin((x + y) / 0.05)], axis=-1)


def orbit_pose(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """(4, 4) reference -> camera pose of a camera turned about the point (0, 0, DISTANCE)."""
    a, b = np.radians(yaw_deg), np.radians(pitch_deg)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    R, c = Rx @ Ry, np.array([0.0, 0.0, DISTANCE])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, c - R @ c
    return T


def relief_capture(frames: int = 6, size=(160, 120), scale_factor: int = 4, max_angle_deg: float = 8.0) -> Capture:
    """A capture of the relief under an LED at :data:`LED` moving with the camera, ground truth included.

    Each pixel's ray is intersected with the relief by fixed-point iteration on the ray
    parameter (contracting: slopes below 0.4 along any ray); colour = albedo * (ambient +
    intensity * max(0, <n, led_vectors>)), linear float32, no noise; depth = the reference-grid
    depth block-averaged by ``scale_factor`` (an ideal sensor). The metadata's LED offset is the
    true one (use :func:`with_led_offset_error` in accuracy tests).
    """
    W, H = size
    f = 0.5 * W / np.tan(np.radians(30.0))
    K = np.array([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
    angles = np.linspace(0, 2 * np.pi, frames, endpoint=False)
    poses = np.stack([orbit_pose(max_angle_deg * np.cos(t) * (i > 0), max_angle_deg * np.sin(t) * (i > 0))
                      for i, t in enumerate(angles)])
    rays = backproject(np.ones((H, W)), K)  # (H, W, 3), z = 1
    color, depth, reference = [], [], None
    for T in poses:
        R, t = T[:3, :3], T[:3, 3]
        centre, direction = -R.T @ t, rays @ R  # reference frame: camera centre, ray directions R^T d
        s = np.full((H, W), DISTANCE)
        for _ in range(40):
            points = centre + s[..., None] * direction
            s = (relief_depth(points[..., 0], points[..., 1]) - centre[2]) / direction[..., 2]
        points = centre + s[..., None] * direction
        x, y = points[..., 0], points[..., 1]
        normals, albedo = relief_normals(x, y), relief_albedo(x, y)
        led = R.T @ (LED - t)
        irradiance = np.einsum("...k,...k->...", normals, led_vectors(points.reshape(-1, 3), led).reshape(H, W, 3))
        color.append(albedo * (LED_AMBIENT + LED_INTENSITY * np.maximum(irradiance, 0.0))[..., None])
        z_camera = (points @ R.T + t)[..., 2]
        depth.append(block_average(z_camera, scale_factor))
        if reference is None:
            reference = (z_camera, normals, albedo)
    return Capture(
        color=[image_from_array(c.astype(np.float32)) for c in color],
        depth=[image_from_array(d.astype(np.float32)[..., None]) for d in depth],
        color_intrinsic=o3d.core.Tensor(K), depth_intrinsic=o3d.core.Tensor(default_depth_intrinsic(K, scale_factor)),
        color_encoding="linear", sensor="analytic relief", light="led",
        groundtruth=GroundTruth(depth=reference[0].astype(np.float32), normals=reference[1].astype(np.float32),
                                albedo=reference[2].astype(np.float32), poses=poses, light={"model": "led"},
                                mesh_to_reference=np.eye(4)),
        metadata={"led_offset": LED.tolist()},
    )


# --- pose files of other tools -------------------------------------------------------------
def world_to_camera(truth: np.ndarray) -> np.ndarray:
    """The true poses (n, 4, 4; reference -> frame) as world-to-camera extrinsics of an arbitrary
    world (not the reference camera), as another tool would write them."""
    from scipy.spatial.transform import Rotation

    world_to_reference = np.eye(4)
    world_to_reference[:3, :3] = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    world_to_reference[:3, 3] = [0.5, -2.0, 1.2]
    return truth @ world_to_reference


def write_open3d(path, extrinsics) -> None:
    """Open3D's own writer (.json PinholeCameraTrajectory or .log camera-to-world) of (n, 4, 4) extrinsics."""
    trajectory = o3d.camera.PinholeCameraTrajectory()
    params = []
    for E in extrinsics:
        p = o3d.camera.PinholeCameraParameters()
        p.intrinsic = o3d.camera.PinholeCameraIntrinsic(160, 120, 150.0, 150.0, 79.5, 59.5)
        p.extrinsic = E
        params.append(p)
    trajectory.parameters = params
    assert o3d.io.write_pinhole_camera_trajectory(str(path), trajectory)


def write_tum(path, extrinsics, ids) -> None:
    """TUM lines ``id tx ty tz qx qy qz qw`` (camera-to-world) of (n, 4, 4) extrinsics."""
    from scipy.spatial.transform import Rotation

    lines = ["# id tx ty tz qx qy qz qw"]
    for i, E in zip(ids, extrinsics):
        C = np.linalg.inv(E)
        q = Rotation.from_matrix(C[:3, :3]).as_quat()
        lines.append(f"{i} " + " ".join(f"{v:.9f}" for v in [*C[:3, 3], *q]))
    path.write_text("\n".join(lines) + "\n")


def write_pose_file(path, truth: np.ndarray) -> None:
    """Write the true poses (n, 4, 4) to ``path`` in the format its suffix names (.json, .log, .txt, .npy)."""
    E = world_to_camera(truth)
    if path.suffix in (".json", ".log"):
        write_open3d(path, E)
    elif path.suffix == ".txt":
        write_tum(path, E, range(len(E)))
    else:
        np.save(path, E)



# ------------------------------------------------------------------------------------------
# A static camera and a hand-held light (the predecessor's setting, Peng et al. 2017): quilted
# fabric with a plaid, dark-patched albedo, rendered without o3d_mvps.synthetic
# ------------------------------------------------------------------------------------------
QUILT_DISTANCE, QUILT_AMPLITUDE, QUILT_PERIOD = 0.55, 0.002, 0.04  # metres


def quilt_depth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Depth z (metres) of a quilted sheet at lateral x, y (metres): cushions 2 mm high, 4 cm wide,
    (a smooth sin^2 profile) on a sheet tilted by 10 degrees about the vertical axis."""
    k = np.pi / QUILT_PERIOD
    return QUILT_DISTANCE + 0.18 * x + QUILT_AMPLITUDE * (np.sin(k * x) * np.sin(k * y)) ** 2


def quilt_albedo(x: np.ndarray, y: np.ndarray, seed: int = 3) -> np.ndarray:
    """Linear RGB albedo (..., 3): a plaid of light squares (0.55-0.75) crossed by dark bands
    (0.04-0.08) 6 mm wide every 3 cm, plus dark speckles (albedo 0.05) on a 4 mm grid."""
    base = np.stack([0.7 + 0.05 * np.sin(x / 0.02), 0.6 + 0.05 * np.cos(y / 0.03), 0.55 + 0.0 * x], axis=-1)
    band = (np.mod(x, 0.03) < 0.006) | (np.mod(y, 0.03) < 0.006)
    rng = np.random.default_rng(seed)
    cells = rng.random((200, 200)) < 0.25  # speckles on a 4 mm grid
    row, col = (np.clip(((c + 0.4) / 0.004).astype(int), 0, 199) for c in (y, x))
    speckle = cells[row, col]
    albedo = np.where(band[..., None], np.array([0.08, 0.05, 0.04]), base)
    return np.where(speckle[..., None], np.array([0.05, 0.05, 0.06]), albedo)


def quilt_scene(frames: int = 12, size=(320, 240), scale_factor: int = 2, light_distance: float = 0.35,
                light_height: float = 0.65, colour_noise: float = 0.005, depth_noise_mm: float = 1.5,
                seed: int = 0, sensor: str | None = None, missing_top: int = 0,
                dim_corner: float = 0.0) -> dict:
    """A static camera looking at the quilt (:func:`quilt_depth`) under a hand-held point light.

    Frame i's light sits on a circle of radius ``light_distance`` around the optical axis,
    ``light_height`` before the sheet's centre (0.1 m before the camera; 1/r^2 falloff, plus
    ambient 0.05): shading no first-order SH light describes exactly (far away, e.g. 35 and 65,
    it is a distant light, which SH does). Colour: linear float32 with Gaussian noise
    ``colour_noise`` and 8-bit quantisation; depth: the colour-grid depth block-averaged by
    ``scale_factor``, Gaussian noise of ``depth_noise_mm`` mm and 1 mm quantisation; or with
    ``sensor="d415"`` both from :class:`o3d_mvps.synthetic.D415Sensor` (exposure and white-balance
    drift, shot noise, sRGB 8 bit; disparity terraces, z^2 and low-frequency noise, speckle
    holes). ``missing_top``: this many depth rows at the top without depth in every frame
    (as where a registered depth camera's view ends short of the colour camera's). ``dim_corner``:
    the colour camera's response falls off toward the top left corner, where only ``1 -
    dim_corner`` of the light is recorded (vignetting off centre, a dark corner: the same in
    every frame). Returns a
    dict of arrays: colors (n, H, W, 3), depths (n, h, w), K, depth_K, depth (H, W), normals
    (H, W, 3), albedo (H, W, 3) (the truth).
    """
    W, H = size
    f = 0.5 * W / np.tan(np.radians(30.0))
    K = np.array([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
    rays = backproject(np.ones((H, W)), K)
    s = np.full((H, W), QUILT_DISTANCE)
    for _ in range(60):  # ray parameter t with t = z(t x, t y): contracting for slopes < 0.5
        s = quilt_depth(s * rays[..., 0], s * rays[..., 1])
    points = s[..., None] * rays
    normals, _ = perspective_normals(s, K)
    albedo = quilt_albedo(points[..., 0], points[..., 1])
    rng = np.random.default_rng(seed)
    colors = []
    for t in np.linspace(0, 2 * np.pi, frames, endpoint=False):
        light = np.array([light_distance * np.cos(t), light_distance * np.sin(t), QUILT_DISTANCE - light_height])
        to_light = led_vectors(points.reshape(-1, 3), light).reshape(H, W, 3)
        irradiance = np.einsum("...k,...k->...", normals, to_light)
        intensity = 0.9 * np.sum((light - np.array([0, 0, QUILT_DISTANCE])) ** 2)
        image = albedo * (0.05 + intensity * np.maximum(irradiance, 0.0))[..., None]
        if dim_corner:
            v, u = np.mgrid[:H, :W]
            image = image * (1 - dim_corner * ((u - 0.7 * W) ** 2 + (v - 0.7 * H) ** 2) / (0.49 * (W**2 + H**2)))[..., None]
        if sensor == "d415":
            colors.append(D415Sensor().color(image, rng)[0])
            continue
        image = image + rng.normal(0, colour_noise, image.shape)
        colors.append(np.clip(np.round(image * 255) / 255, 0, 1))
    if sensor == "d415":
        depths = [np.round(D415Sensor().depth(s, scale_factor, rng) * 1000) / 1000 for _ in range(frames)]
    else:
        low = block_average(s, scale_factor)
        depths = [np.round(low * 1000 + rng.normal(0, depth_noise_mm, low.shape)) / 1000 for _ in range(frames)]
    for d in depths:
        d[:missing_top] = 0.0
    return {"colors": np.array(colors, np.float32), "depths": np.array(depths, np.float32), "K": K,
            "depth_K": default_depth_intrinsic(K, scale_factor), "depth": s, "normals": normals, "albedo": albedo}


def snapshot(*paths) -> dict:
    """{file: sha256} of every file under the paths (a file or a folder): what a run must not change."""
    files = [f for p in paths for f in ([Path(p)] if Path(p).is_file() else sorted(Path(p).rglob("*"))) if f.is_file()]
    return {str(f): hashlib.sha256(f.read_bytes()).hexdigest() for f in files}
