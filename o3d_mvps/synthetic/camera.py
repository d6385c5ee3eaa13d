"""Synthetic cameras: intrinsics, pixel rays and the trajectories of the rendered frames (metres)."""

from __future__ import annotations

import numpy as np

TRAJECTORIES = ("orbit", "orbit-translate")
HORIZONTAL_FOV_DEG = 60.0
MAX_ORBIT_DEG = 15.0
ORBIT_TURNS = 1.5


def synthetic_intrinsics(width: int, height: int, fov_deg: float = HORIZONTAL_FOV_DEG) -> np.ndarray:
    """(3, 3) pinhole K of a ``width`` x ``height`` camera with horizontal FOV ``fov_deg``.

    Square pixels, principal point at the image centre ``((W - 1)/2, (H - 1)/2)``.
    """
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def look_at_pose(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) reference -> camera transform of a camera at ``centre`` looking at ``target``.

    No roll: the camera's x axis is horizontal in the reference frame (y down stays "down").
    """
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)  # camera -> reference rotation (columns: camera axes)
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ centre
    return T


def orbit_trajectory(
    frames: int, distance: float, kind: str = "orbit", max_angle_deg: float = MAX_ORBIT_DEG
) -> np.ndarray:
    """Camera poses (frames, 4, 4), reference -> frame i; ``poses[0]`` is the identity.

    ``"orbit"``: an outward spiral (``ORBIT_TURNS`` turns) of yaw/pitch offsets around the
    object centre ``(0, 0, distance)``, radius growing linearly to ``max_angle_deg``, at
    constant distance, always looking at the centre. ``"orbit-translate"`` adds a distance
    change of up to +-5 cm and a sideways camera shift of up to 3 cm (x) and 2 cm (y).
    """
    if kind not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory {kind!r}; choose one of {list(TRAJECTORIES)}")
    target = np.array([0.0, 0.0, distance])
    poses = np.empty((frames, 4, 4))
    for i in range(frames):
        t = i / (frames - 1) if frames > 1 else 0.0
        radius = np.radians(max_angle_deg) * t
        phase = 2 * np.pi * ORBIT_TURNS * t
        yaw, pitch = radius * np.cos(phase), radius * np.sin(phase)
        d = distance
        if kind == "orbit-translate":
            d = distance - 0.05 * np.sin(2 * np.pi * t)
        direction = np.array([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
        centre = target - d * direction
        T = look_at_pose(centre, target)
        if kind == "orbit-translate":  # a sideways shift in the camera's own frame
            shift = np.array([0.03 * np.sin(3 * np.pi * t), 0.02 * np.sin(2 * np.pi * t), 0.0])
            T[:3, 3] -= shift
        poses[i] = T
    poses[0] = np.eye(4)
    return poses


def ring_trajectory(frames: int, distance: float, elevation_deg: float = 15.0, arc_deg: float = 360.0) -> np.ndarray:
    """Camera poses (frames, 4, 4) evenly around the object, reference -> frame i.

    The cameras sit at ``distance`` from the object centre ``(0, 0, distance)`` (reference
    frame), ``elevation_deg`` above it (toward -y, image up), looking at the centre without
    roll, at azimuths about the vertical axis through the centre: ``360 * i / frames`` degrees
    for a full ring, else evenly over ``arc_deg`` degrees centred on azimuth 0 (both ends
    included). Unlike :func:`orbit_trajectory`, ``poses[0]`` is the identity only for
    ``elevation_deg=0`` (and a full ring): the reference frame stays the level camera the object
    was placed for (:func:`build_scene`).
    """
    target = np.array([0.0, 0.0, distance])
    elevation = np.radians(elevation_deg)
    full = arc_deg >= 360.0
    step = 360.0 / frames if full else arc_deg / max(int(frames) - 1, 1)
    start = 0.0 if full else -arc_deg / 2
    poses = np.empty((int(frames), 4, 4))
    for i in range(int(frames)):
        azimuth = np.radians(start + step * i)
        direction = np.array([np.sin(azimuth) * np.cos(elevation), np.sin(elevation),
                              np.cos(azimuth) * np.cos(elevation)])  # camera -> centre
        poses[i] = look_at_pose(target - distance * direction, target)
    return poses


def camera_rays(K: np.ndarray, size: tuple[int, int], offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Unit ray directions (H, W, 3) through the pixel centres, camera frame; ``offset`` (du, dv)
    pixels moves every ray to ``(u + du, v + dv)`` (a subpixel sample, :func:`subpixel_offsets`)."""
    W, H = size
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    u, v = u + offset[0], v + offset[1]
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def subpixel_offsets(samples: int) -> list[tuple[float, float]]:
    """The ``samples`` x ``samples`` (du, dv) offsets (pixels) of a box filter over the pixel area:
    cell centres ``(k + 1/2) / samples - 1/2``, k = 0..samples-1 (samples 1: the pixel centre only)."""
    steps = (np.arange(int(samples)) + 0.5) / int(samples) - 0.5
    return [(float(du), float(dv)) for dv in steps for du in steps]
