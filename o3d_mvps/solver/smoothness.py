"""The smoothness term ``mu ||S z||^2`` (not in the paper): its rows S and, under room light, its weight.

S takes the depth's second differences along rows and columns (:func:`second_differences`);
under room light each row is weighted down where the sensor's surface is steep
(:func:`slope_weights`), and the weight mu~ follows the sensor depth's roughness and the
colour pixels' footprint (:func:`auto_smoothness`). Fourth-difference rows that see the depth
alternating from pixel to pixel, which the central-difference normals do not (:func:`grid_mode_rows`,
:func:`with_grid_modes`), can be added below S; :func:`grid_mode_weight` says where (by light model, frames and level size).
"""

from __future__ import annotations

import cv2
import numpy as np
import scipy.sparse as sp

from ..model.normals import MaskedGrid
from ..model.resampling import fill_nearest_valid


#: the taps of a :func:`second_differences` row, on its columns in ascending order
SECOND_DIFFERENCE_TAPS = (1.0, -2.0, 1.0)


def second_differences(grid: MaskedGrid) -> sp.csr_matrix:
    """S (K, N): the second differences z[p-1] - 2 z[p] + z[p+1] along rows and along columns, at
    every masked pixel whose two neighbours in that direction are masked (metres for z in metres)."""
    own = np.arange(grid.size)
    centres = [own[inner] for inner in grid.interior()]
    return _stencil_rows([[bwd[both], both, fwd[both]] for both, fwd, bwd in
                          zip(centres, (grid.fwd_u, grid.fwd_v), (grid.bwd_u, grid.bwd_v))],
                         np.array(SECOND_DIFFERENCE_TAPS), grid.size)


def unweighted_second_differences(S: sp.csr_matrix) -> sp.csr_matrix:
    """The smoothness matrix (K, N) of :func:`second_differences` (and :func:`with_grid_modes`'
    rows below it) again from ``S``, the same rows weighted in place (each row's entries scaled by
    its weight, the columns kept in order; the grid-mode rows, of 5 entries, by exactly 1): the
    taps :data:`SECOND_DIFFERENCE_TAPS` put back in every 3-entry row, the other rows as they are.
    The same matrix bit for bit as the one built, sharing ``S``'s index arrays (a new data array
    only). Not for slope-weighted rows (:func:`smoothness_rows`), whose values are not taps."""
    data = S.data.copy()
    counts = np.diff(S.indptr)
    starts = S.indptr[:-1][counts == 3]
    for k, tap in enumerate(SECOND_DIFFERENCE_TAPS):
        data[starts + k] = tap
    return sp.csr_matrix((data, S.indices, S.indptr), shape=S.shape)


def _stencil_rows(columns: list, taps: np.ndarray, n: int) -> sp.csr_matrix:
    """CSR rows (K, n) of one stencil: for each direction's list of tap columns (t arrays (k,),
    ascending per row: the masked index grows along rows and columns), k rows holding ``taps``
    (t,) there, the directions' rows one after the other. Built as CSR directly (t entries a
    row), the same matrix as from COO triplets without coo_tocsr's pass and sort."""
    cols = np.concatenate([np.stack(c, axis=1) for c in columns]).ravel()
    K = cols.size // taps.size
    return sp.csr_matrix((np.tile(taps, K), cols, np.arange(0, cols.size + 1, taps.size)), shape=(K, n))


#: weight of :func:`grid_mode_rows` in the smoothness, relative to the second differences' (their
#: rows are scaled by its square root), where :func:`grid_mode_weight` turns them on. At 1000 (LED,
#: D415 render, 20 frames) the normal MAE fell 1.337 -> 1.292 deg and a mesh's (forward-difference)
#: normals' 3.29 -> 1.72 deg, the grid mode's median amplitude 8.3 -> 2.2 um, for a depth RMSE
#: 0.516 -> 0.521 mm (+1.1 %, at the ear's depth steps, which the rows straddle; docs/method.md,
#: "Grid modes").
GRID_MODE_WEIGHT = 1000.0
#: the LED's grid-mode rows need at least this many frames: with fewer (an 8-frame ring whose
#: reference 3 frames see, tests/test_grain.py) the solver leans on the sensor depth and the
#: rows, relative to its 10x larger smoothness, flattened the normals (12.5 deg against a bound of 10.5)
GRID_MODE_MIN_FRAMES = 4


def grid_mode_weight(light: str, frames: int, level_pixels: int, lamp_level_pixels: int = 0) -> float:
    """The weight of a level's :func:`grid_mode_rows` (0: none), the one place that decides where
    they are on: :data:`GRID_MODE_WEIGHT` for the LED (``light`` "led") with at least
    :data:`GRID_MODE_MIN_FRAMES` ``frames``, and for point lights ("point", a static camera) on
    the levels of more than ``lamp_level_pixels`` object pixels (``level_pixels``), those that no
    longer place the lamps (the driver's ``POINT_FIT_MAX_PIXELS``: on the lamp-placing levels the
    rows held the bend of a quilt a few pixels across and the lamps went out, 98 -> 501 mm off);
    none under room light ("room", "sh": with its large smoothness they flattened the normals,
    a speckled room render's 16.1 deg against a bound of 12.8; docs/method.md, "Grid modes")."""
    if light == "led" and frames >= GRID_MODE_MIN_FRAMES:
        return GRID_MODE_WEIGHT
    if light == "point" and level_pixels > lamp_level_pixels:
        return GRID_MODE_WEIGHT
    return 0.0


def grid_mode_rows(grid: MaskedGrid, weight: float) -> sp.csr_matrix:
    """Rows (K, N) that see the grid modes: the depth that alternates from pixel to pixel along
    rows or columns (a (-1)^u, a (-1)^v, a (-1)^(u+v)), which central-difference normals do not
    see (z[p+1] - z[p-1] = 0). Each row is ``sqrt(weight) (z[p-2] - 4 z[p-1] + 6 z[p] - 4 z[p+1]
    + z[p+2]) / 4`` along rows and along columns, at every masked pixel whose four neighbours in
    that direction have both their neighbours masked. A mode of amplitude a gives 4 a sqrt(weight)
    (a second difference's 4 a); a smooth surface of frequency omega (rad/pixel) 4 sin^4(omega/2)
    times its amplitude, its curvature (omega^2) times omega^2 / 4."""
    own = np.arange(grid.size)
    taps = np.sqrt(weight) * np.array([1.0, -4.0, 6.0, -4.0, 1.0]) / 4.0
    columns = []
    for fwd, bwd, inner in zip((grid.fwd_u, grid.fwd_v), (grid.bwd_u, grid.bwd_v), grid.interior()):
        both = own[inner & inner[fwd] & inner[bwd]]
        columns.append([bwd[bwd[both]], bwd[both], both, fwd[both], fwd[fwd[both]]])
    return _stencil_rows(columns, taps, grid.size)


def row_centres(S) -> np.ndarray:
    """The column (K,) of each row's centre pixel in a smoothness matrix S (K, N) whose rows are
    symmetric stencils along a row or a column of the grid (the -2 of a second difference, the 6 of
    :func:`grid_mode_rows`): with the columns in ascending order, each row's middle entry (the masked
    index grows along rows and columns). S on the host or a GPU; the pixel whose weight each row
    takes."""
    if not getattr(S, "has_sorted_indices", True):
        S = S.copy()
        S.sort_indices()
    return S.indices[(S.indptr[:-1] + S.indptr[1:]) // 2]


def grid_mode_row_flags(S) -> np.ndarray:
    """Whether each row (K,) bool of a smoothness matrix S (K, N) on the host is a
    :func:`grid_mode_rows` row (5 entries; a second difference has 3)."""
    return np.diff(S.indptr) > 3


#: exponent of the smoothness rows' slope weights ``(1 + |grad z|^2)^(-SLOPE_EXPONENT / 2)``: with
#: 3/2 the squared rows penalise the curvature of a graph surface, z'' / (1 + z'^2)^(3/2)
SLOPE_EXPONENT = 1.5


def slope_weights(grid: MaskedGrid, S: sp.csr_matrix, z0: np.ndarray, K: np.ndarray, level_factor: float) -> np.ndarray:
    """Weights (K,) of the second-difference rows S (K, N): ``(1 + |grad z|^2)^(-3/4)`` at each
    row's centre pixel, |grad z| the metric slope (depth change per metre across the image) of
    the sensor depth z0 (h, w) metres, filled, upsampled to the level and blurred over
    ``level_factor`` = SF / 2^level pixels (the sensor's steps are not slopes); K: (3, 3) level
    intrinsics.

    Unweighted, ``||S z||^2`` penalises image-space second differences, which grow without bound
    toward a silhouette where the surface turns away (z changes by millimetres per pixel there
    on a smooth ball): it flattened the rim. On a room-lit bunny (640x480, SF 4) the smooth fit's
    normal error at the rim fell 28.9 -> 23.4 deg with the weights (SLOPE_EXPONENT 1.5). With the
    LED, whose small smoothness only holds the pixels no other frame sees, the weights freed them
    at the rims: the LED table scene's RMSE rose 1.64 -> 4.11 mm, so the LED model goes without.
    """
    H, W = grid.shape
    filled = fill_nearest_valid(z0.astype(np.float64), z0 > 0)
    surface = cv2.resize(filled, (W, H), interpolation=cv2.INTER_CUBIC)
    surface = cv2.GaussianBlur(surface, (0, 0), max(1.0, level_factor))
    dz_dv, dz_du = np.gradient(surface)
    z = np.maximum(grid.gather(surface), 1e-6)
    slope2 = (grid.gather(dz_du) * K[0, 0] / z) ** 2 + (grid.gather(dz_dv) * K[1, 1] / z) ** 2
    centre = row_centres(S)
    return (1.0 + slope2[centre]) ** (-SLOPE_EXPONENT / 2)


def smoothness_rows(grid: MaskedGrid, z0: np.ndarray, K: np.ndarray, level_factor: float) -> sp.csr_matrix:
    """The smoothness term's S (K, N): :func:`second_differences` weighted by :func:`slope_weights`."""
    S = second_differences(grid)
    return sp.csr_matrix(sp.diags(slope_weights(grid, S, z0, K, level_factor)) @ S)


def with_grid_modes(grid: MaskedGrid, S: sp.csr_matrix, z0: np.ndarray, K: np.ndarray,
                    level_factor: float, weight: float) -> sp.csr_matrix:
    """S (K, N) with :func:`grid_mode_rows` of ``weight`` (:func:`grid_mode_weight`) below
    it, each weighted by :func:`slope_weights` (the sensor surface's slope at its centre pixel, as
    for the second differences under room light: a rim's legitimate fourth differences are
    large); S itself where the weight is 0. z0, K, level_factor: as :func:`slope_weights`. The
    evidence weights leave these rows alone (:meth:`.pyramid.DepthPrior.weigh_smoothness`)."""
    if weight <= 0:
        return S
    M = grid_mode_rows(grid, weight)
    weights = slope_weights(grid, M, z0, K, level_factor)
    M = sp.csr_matrix(sp.diags(weights) @ M)
    return sp.csr_matrix(sp.vstack([S, M]))




#: the least roughness :func:`sensor_roughness` reports (metres), for a depth with none to measure
#: (a plane facing the camera): a 1 mm depth unit's rounding noise, 1 mm / sqrt(12)
MIN_ROUGHNESS = 0.3e-3
#: mu~ / tau~ of a sensor depth 1 mm rough seen by colour pixels 1 mm wide (see :func:`auto_smoothness`)
ROUGHNESS_RATIO = 40.0
#: the least mu~ / tau~ :func:`auto_smoothness` gives: the stereo's own pixel-to-pixel noise needs
#: smoothing that the sensor's roughness does not measure. 24 (mu~ 240) is the weight measured
#: best on noiseless 640x480 scenes; on a noiseless 320x240 room bunny the formula alone gave
#: mu~ 36 and 13.02 deg / 3.53 mm, the floor 12.57 deg / 2.76 mm.
STEREO_RATIO = 24.0


def _object_depth_pixels(z0: np.ndarray, mask: np.ndarray, scale_factor: int) -> np.ndarray:
    """(h, w) bool: valid depth pixels whose SF x SF block of the (H, W) mask is all inside."""
    h, w = z0.shape
    blocks = mask[:h * scale_factor, :w * scale_factor].reshape(h, scale_factor, w, scale_factor)
    return blocks.all(axis=(1, 3)) & (z0 > 0)


def sensor_roughness(z0: np.ndarray, mask: np.ndarray, scale_factor: int) -> float:
    """The sensor depth's noise (metres): 1.4826 x the median absolute deviation of its second
    differences along rows and columns, over the depth pixels whose SF x SF block lies inside
    the colour-resolution ``mask`` (H, W), divided by sqrt(6) (a second difference of
    independent noise has 6 times its variance). z0 (h, w) metres, 0 = missing. The surface's
    own curvature adds to it; not below :data:`MIN_ROUGHNESS`."""
    inside = _object_depth_pixels(z0, mask, scale_factor)
    differences = []
    for z, ok in ((z0, inside), (z0.T, inside.T)):
        both = ok[:, :-2] & ok[:, 1:-1] & ok[:, 2:]
        differences.append((z[:, :-2] - 2 * z[:, 1:-1] + z[:, 2:])[both])
    d = np.concatenate(differences)
    if d.size < 20:
        return MIN_ROUGHNESS
    return max(MIN_ROUGHNESS, 1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(6.0))


def auto_smoothness(tau_tilde: float, z0: np.ndarray, mask: np.ndarray, scale_factor: int, K: np.ndarray) -> float:
    """mu~ for room light: ``tau~ max(24, 40 (sigma / 1 mm)^2 (1 mm / h)^4)``, sigma the sensor
    depth's roughness (:func:`sensor_roughness`), h = median(z0) / f_x the width (metres) of a
    colour pixel on the object; 24 is :data:`STEREO_RATIO`. z0 (h, w) metres; mask (H, W) bool;
    K (3, 3) colour intrinsics.

    Noise needs smoothing in proportion to its variance, and finer pixels need more: against
    the sensor's fixed blocks, a curvature's squared second differences summed over the pixels
    shrink as h^4 (the same scaling as the pyramid levels' 16^level). The factor 40 is measured:
    on six rendered room scenes (320x240 to 2 MP, noiseless and with D415-like noise, sigma
    0.6-4.2 mm, h 0.5-2 mm) the formula's normal error was within 1.4 deg of the best of a sweep
    of mu~ (the best lay within 5x of the formula), where a fixed mu~ 240 was 100x too small on
    a noisy 2 MP bunny (28.4 deg normal error; with the formula 12.1).
    """
    return max(tau_tilde * STEREO_RATIO, sensor_noise_smoothness(tau_tilde, z0, mask, scale_factor, K))


def sensor_noise_smoothness(tau_tilde: float, z0: np.ndarray, mask: np.ndarray, scale_factor: int,
                            K: np.ndarray) -> float:
    """mu~ the sensor's own noise calls for: ``tau~ 40 (sigma / 1 mm)^2 (1 mm / h)^4``
    (:func:`auto_smoothness` without its floor for the stereo's noise, :data:`STEREO_RATIO`);
    same arguments. The smooth fit of the sensor alone (:func:`o3d_mvps.baselines.smooth_fit`)
    on a D415-like 320x240 bunny (sigma 0.65 mm, h 2 mm: mu~ 11 at tau~ 10) had normals 7.8-8.0
    deg off at 0.05-0.1 x auto_smoothness's 240, 10.4 at 240 (bicubic 9.8)."""
    sigma = sensor_roughness(z0, mask, scale_factor)
    inside = _object_depth_pixels(z0, mask, scale_factor)
    depth = z0[inside] if inside.any() else z0[z0 > 0]
    footprint = float(np.median(depth)) / float(K[0, 0]) if depth.size else 1e-3
    return tau_tilde * ROUGHNESS_RATIO * (sigma / 1e-3) ** 2 * (1e-3 / footprint) ** 4
