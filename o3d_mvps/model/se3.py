"""SE(3) exponential and logarithm maps on twists xi = (v, w) in R^6 (translation first).

A pose T (4x4) maps reference-camera coordinates to frame-i camera coordinates.
Pose updates are left-multiplicative: T <- exp(dxi) @ T.
"""

from __future__ import annotations

import numpy as np


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric 3x3 matrix [w]_x with hat(w) @ x == cross(w, x)."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _so3_coefficients(theta: float) -> tuple[float, float, float]:
    """(sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3) with Taylor series near 0."""
    if theta < 1e-4:
        t2 = theta * theta
        return 1.0 - t2 / 6.0, 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    s, c = np.sin(theta), np.cos(theta)
    return s / theta, (1.0 - c) / theta**2, (theta - s) / theta**3


def exp(xi: np.ndarray) -> np.ndarray:
    """4x4 rigid transform of the twist xi = (v, w), shape (6,)."""
    xi = np.asarray(xi, dtype=np.float64)
    v, w = xi[:3], xi[3:]
    theta = float(np.linalg.norm(w))
    a, b, c = _so3_coefficients(theta)
    W = hat(w)
    W2 = W @ W
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + a * W + b * W2
    T[:3, 3] = (np.eye(3) + b * W + c * W2) @ v
    return T


def log(T: np.ndarray) -> np.ndarray:
    """Twist (6,) of a 4x4 rigid transform; inverse of :func:`exp` for rotation angles < pi."""
    R, t = T[:3, :3], T[:3, 3]
    cos_theta = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos_theta))
    if theta < 1e-4:
        w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    else:
        w = theta / (2.0 * np.sin(theta)) * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    a, b, _ = _so3_coefficients(theta)
    W = hat(w)
    # V^-1 = I - W/2 + (1 - a / (2 b)) / theta^2 * W^2
    if theta < 1e-4:
        k = 1.0 / 12.0
    else:
        k = (1.0 - a / (2.0 * b)) / theta**2
    V_inv = np.eye(3) - 0.5 * W + k * (W @ W)
    return np.concatenate([V_inv @ t, w])


def rotation_angle_deg(R: np.ndarray) -> float:
    """Rotation angle of a 3x3 rotation matrix in degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) between two 4x4 poses."""
    D = T_est @ np.linalg.inv(T_true)
    return rotation_angle_deg(D[:3, :3]), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))


def camera_movement(T_from: np.ndarray, T_to: np.ndarray) -> tuple[float, float]:
    """How far a camera moved between two poses (4, 4), reference -> camera: (rotation in
    degrees, distance between the camera centres in metres, in reference coordinates)."""
    centre = lambda T: -T[:3, :3].T @ T[:3, 3]  # noqa: E731
    return rotation_angle_deg(T_to[:3, :3] @ T_from[:3, :3].T), float(np.linalg.norm(centre(T_to) - centre(T_from)))


def relative_to_reference(world_to_camera: np.ndarray) -> np.ndarray:
    """(n, 4, 4) world-to-camera transforms E_i -> T_i = E_i E_0^-1 (reference -> frame i);
    poses already relative to some frame re-base onto frame 0 the same way."""
    E = np.asarray(world_to_camera, dtype=np.float64)
    return E @ np.linalg.inv(E[0])
