"""First-order spherical-harmonics shading (paper Sec. 3.2).

``m(n) = [1, n_x, n_y, n_z]``; frame i's shading of a unit normal n is ``<l_i, m(n)>``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .arrays import array_module, contiguous, like

#: Pixels per chunk of the compiled loops over frames x pixels arrays (n, N, ...) (here and in
#: :mod:`o3d_mvps.solver.kernels`): each thread takes a chunk and runs through it frame after
#: frame, reading each frame's rows of the chunk as contiguous runs, where a loop over the frames
#: inside the pixel loop touched every frame's row for each pixel (at 2 MP and 20 frames 3-7x
#: slower, the same numbers).
FRAME_CHUNK = 4096


#: Chunks that a frames x pixels loop over fewer pixels is cut into at least (:func:`frame_chunk`).
MIN_FRAME_CHUNKS = 4


@numba.njit(inline="always")
def frame_chunk(n_pixels):  # pragma: no cover - compiled
    """Pixels per chunk of a frames x pixels loop over ``n_pixels`` pixels: :data:`FRAME_CHUNK`,
    or fewer (down to 1024) to give the loop :data:`MIN_FRAME_CHUNKS` chunks, so that each
    thread has one (the joint step's 4096-pixel assembly blocks ran as one chunk, on one
    thread). Not from the thread count, which numba would not let a cached function read.
    Each pixel's values do not depend on it."""
    return max(1024, min(FRAME_CHUNK, -(-n_pixels // MIN_FRAME_CHUNKS)))

#: Initial lighting of every frame: a little ambient plus frontal light (normals point to -z).
INITIAL_LIGHT = (0.2, 0.0, 0.0, -1.0)


def sh_basis(normals: np.ndarray) -> np.ndarray:
    """m(n): (..., 4) first-order SH basis of unit normals (..., 3)."""
    xp = array_module(normals)
    return xp.concatenate([xp.ones(normals.shape[:-1] + (1,), dtype=normals.dtype), normals], axis=-1)


def shading(normals: np.ndarray, light: np.ndarray) -> np.ndarray:
    """<l, m(n)>: (...) shading of unit normals (..., 3) under SH light (4,) (NumPy or CuPy
    normals; the light on the host or the device)."""
    return light[0] + normals @ like(light[1:], normals, dtype=normals.dtype)


def led_vectors(points: np.ndarray, light_position: np.ndarray) -> np.ndarray:
    """Irradiance vectors (N, 3) of a unit point light at ``light_position`` (3,) on points (N, 3);
    (m, N, 3) for m positions (m, 3).

    ``v = (s - X) / |s - X|^3`` (1/m^2): the light's shading of a unit normal n at X is
    ``max(0, <n, v>)`` per unit intensity (inverse-square falloff, Lambertian). Points and the
    light share one frame, in metres.
    """
    d = like(light_position, points, dtype=np.float64)[..., None, :] - points
    r2 = np.einsum("...j,...j->...", d, d)
    return d / (r2 * np.sqrt(r2))[..., None]


def led_irradiances(normals: np.ndarray, points: np.ndarray, light_positions: np.ndarray,
                    kernel=None) -> np.ndarray:
    """``<n, v>`` (m, N) of :func:`led_vectors` for m light positions (m, 3, host) at once,
    unclamped (negative where a point faces away): unit normals and points (N, 3), one frame,
    metres. kernel: the ``led_irradiances_into(normals, points, positions, out)`` of the arrays'
    device (default: :func:`led_irradiances_into`, the CPU's, for NumPy arrays; the solver's
    ``kernels_for`` gives it)."""
    xp = array_module(points)
    out = xp.empty((len(light_positions), len(points)))
    (kernel or led_irradiances_into)(contiguous(normals, np.float64), contiguous(points, np.float64),
                                     like(light_positions, points, dtype=np.float64), out)
    return out


@numba.njit(inline="always")
def led_irradiance(normals, points, positions, i, p):  # pragma: no cover - compiled
    """<n, v> of point p under light position i: :func:`led_irradiances_into`'s element (the
    CUDA twin in :mod:`o3d_mvps.solver.cuda_kernels` calls it too)."""
    return led_irradiance_at(normals, points, positions[i, 0], positions[i, 1], positions[i, 2], p)


@numba.njit(inline="always")
def led_irradiance_at(normals, points, s0, s1, s2, p):  # pragma: no cover - compiled
    """<n, v> of point p under a light at (s0, s1, s2): :func:`led_irradiance` of one position."""
    return led_irradiance_of(normals[p, 0], normals[p, 1], normals[p, 2], points[p, 0], points[p, 1], points[p, 2],
                             s0, s1, s2)


@numba.njit(inline="always")
def led_irradiance_of(n0, n1, n2, x0, x1, x2, s0, s1, s2):  # pragma: no cover - compiled
    """<n, v> of the unit normal n = (n0, n1, n2) at the point x = (x0, x1, x2) under a light at
    s = (s0, s1, s2), metres: ``v = (s - x) / |s - x|^3`` (:func:`led_vectors`), unclamped."""
    d0 = s0 - x0
    d1 = s1 - x1
    d2 = s2 - x2
    r2 = d0 * d0 + d1 * d1 + d2 * d2
    return (n0 * d0 + n1 * d1 + n2 * d2) / (r2 * math.sqrt(r2))


@numba.njit(inline="always")
def led_position(poses, o0, o1, o2, i, c):  # pragma: no cover - compiled
    """Component c of ``R_i^T (o - t_i)``: an LED at o (camera frame, metres) in reference
    coordinates for the frame with poses[i] (4, 4) (summed as NumPy's einsum sums it, so
    :func:`led_positions_into` equals the array formula bit for bit)."""
    return ((poses[i, 0, c] * (o0 - poses[i, 0, 3]) + poses[i, 1, c] * (o1 - poses[i, 1, 3]))
            + poses[i, 2, c] * (o2 - poses[i, 2, 3]))


@numba.njit(cache=True)
def led_positions_into(poses, offset, out):  # pragma: no cover - compiled
    """out (m, 3): :func:`led_position` of every frame with poses (m, 4, 4) for the LED at
    ``offset`` (3,)."""
    for i in range(poses.shape[0]):
        for c in range(3):
            out[i, c] = led_position(poses, offset[0], offset[1], offset[2], i, c)


@numba.njit(parallel=True, cache=True)
def led_irradiances_into(normals, points, positions, out):  # pragma: no cover - compiled
    """:func:`led_irradiances` written into out (m, N): float64 normals, points (N, 3), light
    positions (m, 3)."""
    N = points.shape[0]
    for k in numba.prange(-(-N // FRAME_CHUNK)):  # chunks of pixels, a frame at a time (contiguous rows of out)
        for i in range(positions.shape[0]):
            for p in range(k * FRAME_CHUNK, min(N, (k + 1) * FRAME_CHUNK)):
                out[i, p] = led_irradiance(normals, points, positions, i, p)


@numba.njit(parallel=True, cache=True)
def led_bases_into(normals, points, positions, out):  # pragma: no cover - compiled
    """The LED bases ``[1, max(0, <n, v_i>)]`` written into out (m, N, 2) (float32 or float64)
    in one pass: float64 normals, points (N, 3), light positions (m, 3). The same values as
    :func:`led_irradiances_into` clamped and cast, without its (m, N) float64 temporary nor a
    second pass over a fresh (m, N, 2) array (at 1.1 M pixels and 20 frames 181 MB each)."""
    N = points.shape[0]
    for k in numba.prange(-(-N // FRAME_CHUNK)):
        for i in range(positions.shape[0]):
            for p in range(k * FRAME_CHUNK, min(N, (k + 1) * FRAME_CHUNK)):
                out[i, p, 0] = 1.0
                out[i, p, 1] = max(0.0, led_irradiance(normals, points, positions, i, p))


def led_vector_jacobian(points: np.ndarray, light_position: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """d<n, v>/dX (N, 3) of :func:`led_vectors`: ``-n / r^3 + 3 <n, d> d / r^5``, d = s - X;
    (m, N, 3) for m positions (m, 3).

    The derivative with respect to the light position is its negative.
    """
    d = like(light_position, points, dtype=np.float64)[..., None, :] - points
    r2 = np.einsum("...j,...j->...", d, d)
    r3 = r2 * np.sqrt(r2)
    nd = np.einsum("...j,...j->...", normals, d)
    return -normals / r3[..., None] + (3.0 * nd / (r3 * r2))[..., None] * d



@numba.njit(inline="always")
def dot3(x0, x1, x2, y0, y1, y2):  # pragma: no cover - compiled
    """<x, y> of two 3-vectors summed as NumPy's ``einsum("...j,...j->...")`` sums them here,
    ``(x0 y0 + x2 y2) + x1 y1``: the compiled LED fields below equal the array formulas (the
    GPU path's) bit for bit."""
    return (x0 * y0 + x2 * y2) + x1 * y1


@numba.njit(parallel=True, cache=True)
def led_fields_into(intensities, normals, points, positions, out):  # pragma: no cover - compiled
    """The lit LED fields ``I_i v_i`` (m, N, 3) of :func:`led_vectors` written into out, zero
    where ``<n, v_i> <= 0``: intensities (m,), float64 unit normals and points (N, 3), light
    positions (m, 3), one frame (metres); one pass, no temporaries."""
    N = points.shape[0]
    chunk = frame_chunk(N)
    for k in numba.prange(-(-N // chunk)):  # chunks of pixels, a frame at a time
        for i in range(positions.shape[0]):
            for p in range(k * chunk, min(N, (k + 1) * chunk)):
                led_field(intensities, normals, points, positions, out, i, p)


@numba.njit(inline="always")
def led_field(intensities, normals, points, positions, out, i, p):  # pragma: no cover - compiled
    """:func:`led_fields_into`'s element: out[i, p] (3,) for light i and point p (the CUDA twin
    in :mod:`o3d_mvps.solver.cuda_kernels` calls it too)."""
    out[i, p, 0], out[i, p, 1], out[i, p, 2] = led_field_of(intensities, normals, points, positions, i, p)


@numba.njit(inline="always")
def led_field_of(intensities, normals, points, positions, i, p):  # pragma: no cover - compiled
    """:func:`led_field`'s values (3 floats) for light i and point p, not stored (the evidence
    sums form them per pixel, :func:`o3d_mvps.solver.kernels.led_evidence_sums`)."""
    d0 = positions[i, 0] - points[p, 0]
    d1 = positions[i, 1] - points[p, 1]
    d2 = positions[i, 2] - points[p, 2]
    r2 = dot3(d0, d1, d2, d0, d1, d2)
    r3 = r2 * math.sqrt(r2)
    v0, v1, v2 = d0 / r3, d1 / r3, d2 / r3
    lit = intensities[i] if dot3(normals[p, 0], normals[p, 1], normals[p, 2], v0, v1, v2) > 0 else 0.0
    return v0 * lit, v1 * lit, v2 * lit


@numba.njit(inline="always")
def led_point_gradient(intensities, normals, points, positions, out, i, p):  # pragma: no cover - compiled
    """:func:`led_point_gradients_into`'s element: out[i, p] (3,) for light i and point p (the
    CUDA twin in :mod:`o3d_mvps.solver.cuda_kernels` calls it too)."""
    out[i, p, 0], out[i, p, 1], out[i, p, 2] = led_point_gradient_of(intensities, normals, points, positions, i, p)


@numba.njit(inline="always")
def led_point_gradient_of(intensities, normals, points, positions, i, p):  # pragma: no cover - compiled
    """:func:`led_point_gradient`'s values (3 floats) for light i and point p, not stored (the
    GPU's LED-offset system forms them per pixel, :func:`o3d_mvps.solver.kernels.led_offset_system`)."""
    n0, n1, n2 = normals[p, 0], normals[p, 1], normals[p, 2]
    d0 = positions[i, 0] - points[p, 0]
    d1 = positions[i, 1] - points[p, 1]
    d2 = positions[i, 2] - points[p, 2]
    r2 = dot3(d0, d1, d2, d0, d1, d2)
    r3 = r2 * math.sqrt(r2)
    nd = dot3(n0, n1, n2, d0, d1, d2)
    lit = intensities[i] if nd > 0 else 0.0
    s = 3.0 * nd / (r3 * r2)
    return (-n0 / r3 + s * d0) * lit, (-n1 / r3 + s * d1) * lit, (-n2 / r3 + s * d2) * lit


@numba.njit(parallel=True, cache=True)
def led_point_gradients_into(intensities, normals, points, positions, out):  # pragma: no cover - compiled
    """``I_i d<n, v_i>/dX`` (m, N, 3) of :func:`led_vector_jacobian` written into out, zero
    where ``<n, s_i - X> <= 0``: intensities (m,), float64 unit normals and points (N, 3),
    light positions (m, 3), one frame (metres); one pass, no temporaries."""
    N = points.shape[0]
    for k in numba.prange(-(-N // FRAME_CHUNK)):  # chunks of pixels, a frame at a time
        for i in range(positions.shape[0]):
            for p in range(k * FRAME_CHUNK, min(N, (k + 1) * FRAME_CHUNK)):
                led_point_gradient(intensities, normals, points, positions, out, i, p)


@numba.njit(inline="always")
def twist_row_into(G0, G1, G2, offset, out, i, p):  # pragma: no cover - compiled
    """``out[i, p, :6] = [G, o x G]`` for one gradient G = (G0, G1, G2) and the LED's offset o
    (3,), the cross product in NumPy's order of operations."""
    out[i, p, 0] = G0
    out[i, p, 1] = G1
    out[i, p, 2] = G2
    out[i, p, 3] = offset[1] * G2 - offset[2] * G1
    out[i, p, 4] = offset[2] * G0 - offset[0] * G2
    out[i, p, 5] = offset[0] * G1 - offset[1] * G0
