"""Accuracy metrics of a refinement against synthetic ground truth (the paper's MAE and RMSE,
its section 5.1; docs/benchmarks.md).

- MAE: mean angle in degrees between estimated and true unit normals.
- RMSE: root-mean-square depth error in millimetres (depths are given in metres).

:func:`evaluate` compares a :class:`~o3d_mvps.refinement.Refinement` with a
:class:`~o3d_mvps.capture.GroundTruth` over the same pixels for every method, so that the
numbers of different methods (ours, bicubic, guided, ...) can be put side by side.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

#: Pixels removed from the ground-truth object silhouette before evaluation (see :func:`evaluate`).
SILHOUETTE_MARGIN_PX = 2


def _check_mask(mask: np.ndarray, shape: tuple[int, int], what: str) -> np.ndarray:
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != shape:
        raise ValueError(f"{what}: mask has shape {mask.shape} but the images are {shape}; pass an (H, W) boolean mask")
    return mask


def _nonempty(mask: np.ndarray, what: str) -> None:
    if not mask.any():
        raise ValueError(
            f"{what}: no pixel to evaluate (the mask is empty where both inputs are valid); "
            "check that the estimate and the ground truth overlap and that the mask selects the object"
        )


def normal_mae_deg(normals_est: np.ndarray, normals_true: np.ndarray, mask: np.ndarray) -> float:
    """Mean angle in degrees between two normal fields over a mask.

    Parameters
    ----------
    normals_est, normals_true : (H, W, 3) array
        Unit normals (any common frame); a pixel whose normal is all zero is invalid.
    mask : (H, W) bool array
        Pixels to evaluate; only those where both normals are valid (nonzero) are used.

    Returns
    -------
    float
        Mean angle in degrees, computed with ``atan2(|a x b|, a . b)`` (accurate for small angles).

    Raises
    ------
    ValueError
        On a shape mismatch or when no pixel is left to evaluate.
    """
    a = np.asarray(normals_est, dtype=np.float64)
    b = np.asarray(normals_true, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(
            f"normal_mae_deg: normal fields must both be (H, W, 3), got {a.shape} and {b.shape}; "
            "compare normals at the same (colour) resolution"
        )
    mask = _check_mask(mask, a.shape[:2], "normal_mae_deg")
    valid = mask & np.any(a != 0, axis=2) & np.any(b != 0, axis=2)
    _nonempty(valid, "normal_mae_deg")
    a, b = a[valid], b[valid]
    angle = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
    return float(np.degrees(angle).mean())


def depth_rmse_mm(depth_est: np.ndarray, depth_true: np.ndarray, mask: np.ndarray) -> float:
    """Root-mean-square depth error in millimetres over a mask.

    Parameters
    ----------
    depth_est, depth_true : (H, W) array
        Depth in metres. Unlike :func:`normal_mae_deg`, zero depth is not excluded here: the
        caller's mask decides (a hole inside the mask counts as an error of the full depth).
    mask : (H, W) bool array
        Pixels to evaluate.

    Returns
    -------
    float
        RMSE in millimetres.

    Raises
    ------
    ValueError
        On a shape mismatch or an empty mask.
    """
    a = np.asarray(depth_est, dtype=np.float64)
    b = np.asarray(depth_true, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(
            f"depth_rmse_mm: depth maps must both be (H, W), got {a.shape} and {b.shape}; "
            "compare depth at the same (colour) resolution"
        )
    mask = _check_mask(mask, a.shape, "depth_rmse_mm")
    _nonempty(mask, "depth_rmse_mm")
    return float(np.sqrt(np.mean((a[mask] - b[mask]) ** 2)) * 1000.0)


def _groundtruth_arrays(groundtruth, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """GT depth (H, W) metres and normals (H, W, 3), checked against the refinement's (H, W)."""
    if getattr(groundtruth, "groundtruth", None) is not None:  # a Capture
        groundtruth = groundtruth.groundtruth
    depth = np.asarray(groundtruth.depth, dtype=np.float64)
    normals = np.asarray(groundtruth.normals, dtype=np.float64)
    if depth.shape[:2] != shape or normals.shape != shape + (3,):
        raise ValueError(
            f"evaluate: the refinement is {shape} but the ground truth depth/normals are "
            f"{depth.shape}/{normals.shape}; evaluate at the colour resolution of the capture"
        )
    return depth.reshape(shape), normals


def evaluation_mask(refinement, groundtruth, mask: np.ndarray | None = None,
                    margin: int = SILHOUETTE_MARGIN_PX) -> np.ndarray:
    """The (H, W) bool mask :func:`evaluate` uses.

    It is the refinement's mask, intersected with the ground-truth object (GT depth > 0)
    eroded by ``margin`` pixels (3x3 structuring element, so the margin is measured in the
    chessboard metric), with pixels where both normal fields are valid, and with ``mask``.
    The erosion keeps silhouette pixels, whose finite-difference normals and mixed depth are
    ill-defined for every method, from dominating the comparison. The image border does not
    count as a silhouette.
    """
    shape = refinement.depth_array().shape
    gt_depth, gt_normals = _groundtruth_arrays(groundtruth, shape)
    gt_object = gt_depth > 0
    if margin > 0:
        gt_object = ndimage.binary_erosion(gt_object, structure=np.ones((3, 3), bool), iterations=margin,
                                           border_value=1)
    out = refinement.mask_array() & gt_object
    out &= np.any(refinement.normals_array() != 0, axis=2) & np.any(gt_normals != 0, axis=2)
    if mask is not None:
        out &= _check_mask(mask, shape, "evaluate")
    return out


def evaluate(refinement, groundtruth, mask: np.ndarray | None = None, *,
             margin: int = SILHOUETTE_MARGIN_PX) -> dict:
    """Normal MAE and depth RMSE of a refinement against ground truth, on common pixels.

    Parameters
    ----------
    refinement : Refinement
        Depth (H, W) in metres and its perspective normals (H, W, 3), colour resolution.
    groundtruth : GroundTruth or Capture
        Ground truth at the same resolution (given a Capture, its ``groundtruth`` is used).
        Its normals are in the reference camera frame, like the refinement's.
    mask : (H, W) bool array, optional
        Further restricts the evaluated pixels.
    margin : int
        Silhouette erosion in pixels (default 2); see :func:`evaluation_mask`.

    Returns
    -------
    dict
        ``{"mae_deg": float, "rmse_mm": float, "pixels": int}``; both metrics use the same
        ``pixels`` pixels (:func:`evaluation_mask`).

    Raises
    ------
    ValueError
        When sizes differ or no pixel is left to evaluate.
    """
    depth = refinement.depth_array()
    gt_depth, gt_normals = _groundtruth_arrays(groundtruth, depth.shape)
    common = evaluation_mask(refinement, groundtruth, mask, margin)
    return {
        "mae_deg": normal_mae_deg(refinement.normals_array(), gt_normals, common),
        "rmse_mm": depth_rmse_mm(depth, gt_depth, common),
        "pixels": int(common.sum()),
    }


def reprojection_error_px(T_est: np.ndarray, T_true: np.ndarray, points_ref: np.ndarray, K: np.ndarray) -> float:
    """Median image distance in pixels between reference points seen with two poses of a frame.

    ``points_ref`` (N, 3) metres in the reference camera frame, ``T_est``, ``T_true`` (4, 4)
    reference -> frame, ``K`` (3, 3). Unlike rotation and translation errors, this weighs a
    pose error by what it does to the warp: a small object seen from ~0.6 m barely constrains a
    rotation about its own centre combined with the matching translation.
    """
    from .model.camera import project, transform

    u1, v1, _ = project(transform(T_est, points_ref), K)
    u2, v2, _ = project(transform(T_true, points_ref), K)
    return float(np.median(np.hypot(u1 - u2, v1 - v2)))


#: Gaussian scale (colour pixels) of the low-pass shape difference (issue 32: 20 px).
LOWPASS_SIGMA_PX = 20.0


def _masked_lowpass(values: np.ndarray, mask: np.ndarray, sigma_px: float) -> np.ndarray:
    """``values`` (H, W) low-passed over ``mask`` (H, W) bool with a Gaussian of ``sigma_px``
    pixels (:func:`o3d_mvps.model.resampling.masked_gaussian`: only masked pixels count); (K,) at
    the masked pixels."""
    from .model.resampling import masked_gaussian

    return masked_gaussian(values, mask, sigma_px)[0][mask]


def lowpass_difference_permille(depth: np.ndarray, reference: np.ndarray, mask: np.ndarray,
                                sigma_px: float = LOWPASS_SIGMA_PX, percentile: float = 95.0) -> float:
    """How far the coarse shape of ``depth`` departs from ``reference`` (the sensor's), per mille of depth.

    The difference ``depth - reference`` (both (H, W) metres) is low-passed over ``mask`` (H, W)
    bool with a Gaussian of ``sigma_px`` pixels (normalised convolution: only masked pixels
    count), divided by ``reference`` and its ``percentile`` of absolute values over the mask
    returned in per mille. With ``reference`` the bicubic upsampling of the sensor depth this is
    issue 32's measure of a bowl or tilt that the refinement adds to the sensor's shape (target
    <= 2 per mille). Fine detail (well below ``sigma_px``) does not count.
    """
    depth, reference = np.asarray(depth, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    mask = _check_mask(mask, depth.shape, "lowpass_difference_permille") & (reference > 0)
    _nonempty(mask, "lowpass_difference_permille")
    low = _masked_lowpass(depth - reference, mask, sigma_px)
    return float(np.percentile(np.abs(low) / reference[mask], percentile) * 1000.0)


def _relative_albedo_error(albedo: np.ndarray, albedo_true: np.ndarray, mask: np.ndarray, what: str,
                           per_channel: bool = False) -> tuple:
    """(relative error ``(s rho - rho*) / rho*`` (H, W, 3), zero where not used; used (H, W, 3)
    bool), s the median ratio ``rho* / rho`` over the masked pixels where both are positive (one
    per channel where ``per_channel``)."""
    albedo, albedo_true = np.asarray(albedo, dtype=np.float64), np.asarray(albedo_true, dtype=np.float64)
    mask = _check_mask(mask, albedo.shape[:2], what)
    use = mask[..., None] & (albedo > 0) & (albedo_true > 0)
    _nonempty(use.any(axis=2), what)
    if per_channel:
        scale = np.array([np.median(albedo_true[..., c][use[..., c]] / albedo[..., c][use[..., c]])
                          if use[..., c].any() else 1.0 for c in range(3)])
    else:
        scale = float(np.median(albedo_true[use] / albedo[use]))
    return np.where(use, (scale * albedo - albedo_true) / np.where(use, albedo_true, 1.0), 0.0), use


def albedo_error(albedo: np.ndarray, albedo_true: np.ndarray, mask: np.ndarray, per_channel: bool = False) -> float:
    """Median relative albedo error after one global scale: ``median |s rho - rho*| / rho*`` over
    the masked pixels (H, W) bool and the channels of albedos (H, W, 3), s the median ratio
    ``rho* / rho`` (an albedo is known up to the light's scale). Shading left in the albedo (a
    bright centre, a side that darkens) shows here, and so does the images' own noise (each
    pixel's albedo is its own: :func:`albedo_shading_error` leaves that out); 0 is perfect.
    per_channel: one scale per channel, the albedo known up to the light's colour. Frames whose
    white balance drifts, each divided by its balance relative to the frames' mean (refine does
    so for a static camera: :func:`o3d_mvps.capture.frame_white_balance`), leave the mean
    balance's colour in the albedo, which no image tells apart from the object's."""
    error, use = _relative_albedo_error(albedo, albedo_true, mask, "albedo_error", per_channel)
    return float(np.median(np.abs(error[use])))


#: the image-border band of :func:`border_bands` (pixels from the image's edge) and where its interior starts
BORDER_BAND_PX, BORDER_INTERIOR_PX = 2, 16


def border_bands(shape: tuple[int, int], band_px: int = BORDER_BAND_PX,
                 interior_px: int = BORDER_INTERIOR_PX) -> tuple[np.ndarray, np.ndarray]:
    """(band, interior), both (H, W) bool for an image of ``shape`` (H, W): the pixels less than
    ``band_px`` from the image's edge and those ``interior_px`` or more from it (pixel rows and
    columns counted: the chessboard distance). Issue 32's measure of bad borders compares a
    metric (:func:`evaluate`, :func:`albedo_error`) over the band with the interior's."""
    H, W = (int(v) for v in shape)
    v, u = np.mgrid[:H, :W]
    distance = np.minimum(np.minimum(u, W - 1 - u), np.minimum(v, H - 1 - v))
    return distance < band_px, distance >= interior_px


#: metres: an output pixel farther than this from the true surface is stray (:func:`stray_pixels`)
STRAY_TOLERANCE_M = 0.01


def stray_pixels(depth: np.ndarray, mask: np.ndarray, depth_true: np.ndarray,
                 tolerance: float = STRAY_TOLERANCE_M) -> int:
    """How many output pixels (``mask`` (H, W) bool, ``depth`` (H, W) metres) lie more than
    ``tolerance`` metres from the true surface (``depth_true`` (H, W) metres, 0 off the object;
    off it, from the true depth of the nearest pixel on it): fragments hanging off the surface (a
    sensor's flying pixels kept), which :func:`evaluate`'s mask (the truth's, its silhouette
    eroded) never sees, but a mesh export shows. A pixel just past the silhouette at the surface's
    depth (a depth pixel that straddles it) is not stray."""
    mask = _check_mask(mask, np.shape(depth), "stray_pixels")
    depth_true = np.asarray(depth_true, dtype=np.float64)
    if depth_true.shape != np.shape(depth):
        raise ValueError(f"stray_pixels: the true depth is {depth_true.shape} but the depth is {np.shape(depth)}; "
                         "pass both at the colour resolution (H, W)")
    on = depth_true > 0
    if not on.any():
        return int(mask.sum())
    nearest = ndimage.distance_transform_edt(~on, return_distances=False, return_indices=True)
    surface = depth_true[nearest[0], nearest[1]]
    return int((mask & (np.abs(np.asarray(depth, dtype=np.float64) - surface) > tolerance)).sum())


#: Gaussian (pixels) of :func:`albedo_shading_error`
ALBEDO_SHADING_SIGMA_PX = 8.0


def albedo_shading_error(albedo: np.ndarray, albedo_true: np.ndarray, mask: np.ndarray,
                         sigma_px: float = ALBEDO_SHADING_SIGMA_PX, per_channel: bool = False) -> float:
    """The shading left in an albedo: the log ratio ``log(rho / rho*)`` per channel, low-passed
    over the mask with a Gaussian of ``sigma_px`` pixels (normalised convolution), after one
    global scale (its median over the masked pixels and channels), as a relative error: the
    median of ``|exp(.) - 1|``. A pixel's own noise (the images' photon noise, 0.5 % on the
    D415-like bunny) averages out before the scale is taken (by about 28 times at 8 px); a bright
    centre, a side that darkens do not. albedo, albedo_true (H, W, 3), mask (H, W) bool; 0 is perfect.
    per_channel: one scale per channel, each channel's own median (as :func:`albedo_error`'s)."""
    albedo, albedo_true = np.asarray(albedo, dtype=np.float64), np.asarray(albedo_true, dtype=np.float64)
    mask = _check_mask(mask, albedo.shape[:2], "albedo_shading_error")
    use = mask[..., None] & (albedo > 0) & (albedo_true > 0)
    _nonempty(use.any(axis=2), "albedo_shading_error")
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(use, np.log(albedo / albedo_true), 0.0)
    low = [_masked_lowpass(ratio[..., c], use[..., c], sigma_px) for c in range(3) if use[..., c].any()]
    centred = (np.concatenate([channel - np.median(channel) for channel in low]) if per_channel else
               np.concatenate(low) - np.median(np.concatenate(low)))
    return float(np.median(np.abs(np.expm1(centred))))


def albedo_relief(depth: np.ndarray, K: np.ndarray, normals_true: np.ndarray, albedo: np.ndarray, mask: np.ndarray,
                  sigma_px: float = 4.0) -> dict:
    """Whether colour became relief (issue 32 item 3): the normal MAE (deg) of ``depth`` (H, W)
    metres (colour intrinsics K (3, 3)) against ``normals_true`` (H, W, 3) over ``mask`` (H, W)
    bool and over its quarter with the steepest albedo (the gradient magnitude of the mean of
    ``albedo`` (H, W, 3) or (H, W), Gaussian of 1 px: the rims of its patches and speckles), and
    the correlation over ``mask`` of the normals' high-frequency part (their angle to the normals
    of the depth low-passed by a Gaussian of ``sigma_px`` over the mask) with that gradient.
    Returns {"mae_deg", "steepest_quarter_mae_deg", "high_vs_albedo_gradient"}; the true
    depth's own correlation is the floor (a few hundredths on the rendered bunnies)."""
    from .model.normals import perspective_normals

    mask = _check_mask(mask, depth.shape, "mask") & (depth > 0)
    _nonempty(mask, "mask")
    rho = np.asarray(albedo, np.float64)
    rho = rho.mean(axis=2) if rho.ndim == 3 else rho
    gradient = np.hypot(*np.gradient(ndimage.gaussian_filter(rho, 1.0)))
    steep = np.zeros_like(mask)
    order = np.argsort(-gradient[mask], kind="stable")  # exactly a quarter, the steepest first
    steep[tuple(i[order[: max(1, order.size // 4)]] for i in np.nonzero(mask))] = True
    normals = perspective_normals(depth, K, depth > 0)[0]
    smooth = np.zeros(depth.shape)
    smooth[mask] = _masked_lowpass(depth, mask, sigma_px)
    smooth_normals = perspective_normals(smooth, K, smooth > 0)[0]
    high = np.degrees(np.arccos(np.clip(np.sum(normals * smooth_normals, axis=2), -1.0, 1.0)))
    return {"mae_deg": normal_mae_deg(normals, normals_true, mask),
            "steepest_quarter_mae_deg": normal_mae_deg(normals, normals_true, steep),
            "high_vs_albedo_gradient": float(np.corrcoef(high[mask], gradient[mask])[0, 1])}
