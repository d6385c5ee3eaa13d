"""Reference views of a capture that goes around an object, and how far around it goes.

World frame: the capture's frame-0 camera; ``poses[i]`` (4, 4) maps it to camera i.
"""

from __future__ import annotations

import numpy as np

#: Azimuth span (degrees) from which a capture counts as going around the object.
FULL_TURN_DEG = 300.0


def camera_centres(poses: np.ndarray) -> np.ndarray:
    """Camera centres (n, 3) in the world frame of poses (n, 4, 4) world -> camera."""
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    return -np.einsum("nji,nj->ni", R, t)


def viewing_directions(poses: np.ndarray) -> np.ndarray:
    """Unit optical axes (n, 3) of the cameras in the world frame."""
    return poses[:, 2, :3] / np.linalg.norm(poses[:, 2, :3], axis=1, keepdims=True)


#: When the fitted cone axis counts as 'up' (see :func:`up_direction`): the viewing directions
#: make at least this angle (degrees) with it ...
MIN_CONE_ANGLE_DEG = 45.0
#: ... or the cameras' image-up vectors lean toward it by at least this much on average (cosine;
#: a ring at elevation e gives cos(e), so rings up to 75 degrees above the object qualify).
MIN_UP_ALONG_AXIS = float(np.cos(np.radians(75.0)))


def up_direction(poses: np.ndarray) -> np.ndarray:
    """World 'up' (3,): the axis of the cone the viewing directions lie on (the normal of the plane
    through their tips, for a ring or an arc at one elevation), signed along the cameras' mean
    image-up (-y); that mean itself when the directions do not span a plane (fewer than 3 views)
    or the axis is not an up axis: the directions hug it (cone narrower than
    :data:`MIN_CONE_ANGLE_DEG`) while the image-ups stay square to it (below
    :data:`MIN_UP_ALONG_AXIS`). That is an orbit in front of the object (yaw/pitch within
    +-15 degrees): its tips also lie near a plane, but the plane's normal is the mean viewing
    direction, about which the directions would seem to go all round."""
    ups = -poses[:, 1, :3]
    mean_up = ups.mean(axis=0)
    tips = viewing_directions(poses)
    if len(tips) >= 3:
        _, singular, vt = np.linalg.svd(tips - tips.mean(axis=0))
        axis = vt[2] * np.sign(vt[2] @ mean_up or 1.0)
        cone_deg = np.degrees(np.arccos(min(abs(float(np.mean(tips @ axis))), 1.0)))
        up_along = float(np.mean(ups @ axis)) / max(float(np.mean(np.linalg.norm(ups, axis=1))), 1e-12)
        if singular[1] > 1e-3 * max(singular[0], 1e-12) and (cone_deg >= MIN_CONE_ANGLE_DEG
                                                              or up_along >= MIN_UP_ALONG_AXIS):
            return axis
    return mean_up / np.linalg.norm(mean_up)


def azimuths_deg(poses: np.ndarray) -> np.ndarray:
    """Each camera's viewing direction as an angle (n,) degrees about :func:`up_direction`."""
    up = up_direction(poses)
    d = viewing_directions(poses)
    flat = d - np.outer(d @ up, up)
    e1 = flat[0] / max(np.linalg.norm(flat[0]), 1e-12)
    e2 = np.cross(up, e1)
    return np.degrees(np.arctan2(flat @ e2, flat @ e1))


def azimuth_span_deg(poses: np.ndarray) -> float:
    """Degrees of the circle the viewing directions cover: 360 minus the largest gap between them."""
    a = np.sort(np.mod(azimuths_deg(poses), 360.0))
    gaps = np.diff(np.concatenate([a, a[:1] + 360.0]))
    return float(360.0 - gaps.max()) if len(a) > 1 else 0.0


def choose_references(poses: np.ndarray, k: int) -> list[int]:
    """``k`` frame indices whose viewing directions are spread out (greedy farthest point from frame 0).

    Raises ValueError when k is not in 1..n.
    """
    n = len(poses)
    if not 1 <= k <= n:
        raise ValueError(f"references={k} must be between 1 and the {n} frames of the capture; pass fewer")
    d = viewing_directions(poses)
    chosen = [0]
    nearest = 1.0 - d @ d[0]
    for _ in range(k - 1):
        i = int(np.argmax(nearest))
        chosen.append(i)
        nearest = np.minimum(nearest, 1.0 - d @ d[i])
    return sorted(chosen)
