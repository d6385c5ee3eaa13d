"""Bicubic and guided-filter depth upsampling baselines."""

import cv2
import numpy as np
import open3d as o3d
import pytest

from o3d_mvps.baselines import bicubic, guided, upsample_bicubic
from o3d_mvps.model.resampling import block_average
from o3d_mvps.capture import Capture, default_depth_intrinsic, image_from_array
from o3d_mvps.errors import CaptureError
from o3d_mvps.model.camera import pixel_grid
from o3d_mvps.refinement import Refinement

SF = 4
h, w = 16, 24
H, W = h * SF, w * SF
K = np.array([[80.0, 0.0, (W - 1) / 2], [0.0, 80.0, (H - 1) / 2], [0.0, 0.0, 1.0]])


def make_capture(depth_lr, color=None, mask=None) -> Capture:
    """A one-frame capture from an (h, w) depth in metres, (H, W, 3) colour and (H, W) mask."""
    color = np.full((H, W, 3), 0.5, np.float32) if color is None else color
    masks = None if mask is None else [image_from_array((mask.astype(np.uint8) * 255)[..., None])]
    return Capture(
        color=[image_from_array(color.astype(np.float32))],
        depth=[image_from_array(depth_lr.astype(np.float32)[..., None])],
        color_intrinsic=o3d.core.Tensor(K),
        depth_intrinsic=o3d.core.Tensor(default_depth_intrinsic(K, SF)),
        masks=masks,
    )


def hr_to_lr_coordinate(x):
    """Low-resolution coordinate of high-resolution coordinate x (centre of LR j at SF j + (SF-1)/2)."""
    return (x - (SF - 1) / 2) / SF


def smooth_depth(u, v):
    """A smooth (quadratic) depth field in metres, u, v in low-resolution pixels."""
    return 0.6 + 0.004 * u - 0.003 * v + 2e-4 * u * u - 1e-4 * u * v + 3e-4 * v * v


def test_opencv_inter_cubic_uses_the_same_centres_but_does_not_reproduce_ramps():
    """Why baselines does not use cv2.resize: same centre alignment, but a = -0.75 ripples."""
    ramp = np.tile(np.arange(w, dtype=np.float32), (h, 1))
    x = hr_to_lr_coordinate(np.arange(W))
    cv = cv2.resize(ramp, (W, H), interpolation=cv2.INTER_CUBIC)[0, 2 * SF:-2 * SF]
    ours = upsample_bicubic(ramp, SF)[0]
    assert np.abs(cv - x[2 * SF:-2 * SF]).mean() < 0.05  # centred: the ripple averages out...
    assert np.abs(cv - x[2 * SF:-2 * SF]).max() > 0.03  # ...but it is there
    assert np.abs(ours - x).max() < 1e-12  # linear fields exactly, up to the border


@pytest.mark.parametrize("factor", [1, 2, 3, 4, 8])
def test_upsample_bicubic_reproduces_quadratics_at_pixel_centres(factor):
    j, i = np.meshgrid(np.arange(7), np.arange(5))
    x, y = pixel_grid(5 * factor, 7 * factor)
    to_lr = lambda c: (c - (factor - 1) / 2) / factor  # noqa: E731
    up = upsample_bicubic(smooth_depth(j, i), factor)
    truth = smooth_depth(to_lr(x), to_lr(y))
    inner = (slice(2 * factor, -2 * factor or None),) * 2
    assert np.abs(up - truth)[inner].max() < 1e-12


def test_bicubic_reproduces_a_smooth_depth_field():
    j, i = np.meshgrid(np.arange(w), np.arange(h))
    refinement = bicubic(make_capture(smooth_depth(j, i)))
    x, y = pixel_grid(H, W)
    truth = smooth_depth(hr_to_lr_coordinate(x), hr_to_lr_coordinate(y))
    error = np.abs(refinement.depth_array() - truth)
    inner = error[2 * SF:-2 * SF, 2 * SF:-2 * SF]  # quadratic terms are extrapolated linearly at the border
    assert inner.max() < 1e-6  # float32 storage of ~0.6 m
    assert error.max() < 1e-3
    assert refinement.method == "bicubic"


@pytest.mark.parametrize("method", [bicubic, guided])
def test_result_is_a_refinement_at_colour_resolution(method):
    j, i = np.meshgrid(np.arange(w), np.arange(h))
    mask = np.zeros((H, W), bool)
    mask[8:56, 10:80] = True
    rng = np.random.default_rng(0)
    refinement = method(make_capture(smooth_depth(j, i), rng.uniform(0.2, 0.8, (H, W, 3)), mask))
    assert isinstance(refinement, Refinement)
    assert refinement.depth_array().shape == (H, W) and refinement.depth_array().dtype == np.float32
    assert np.array_equal(refinement.mask_array(), mask)
    normals = refinement.normals_array()
    assert normals.shape == (H, W, 3)
    np.testing.assert_allclose(np.linalg.norm(normals[mask], axis=1), 1.0, atol=1e-5)
    assert np.all(normals[~mask] == 0) and np.all(refinement.depth_array()[~mask] == 0)
    assert np.all(normals[mask][:, 2] < 0)  # pointing to the camera
    assert refinement.albedo is None
    np.testing.assert_allclose(refinement.intrinsic_matrix(), K)


@pytest.mark.parametrize("method", [bicubic, guided])
def test_missing_depth_is_not_blended_into_valid_depth(method):
    depth = np.full((h, w), 0.6)
    depth[5:8, 9:13] = 0.0  # a hole inside the object
    depth[:, :3] = 0.0  # background strip, outside the object
    mask = np.ones((H, W), bool)
    mask[:, :3 * SF] = False
    result = method(make_capture(depth, mask=mask)).depth_array()
    assert np.abs(result[mask] - 0.6).max() < 1e-6  # the hole is filled, the border is not dragged to 0
    # without a mask the result covers the valid low-resolution pixels, SF x SF each
    unmasked = method(make_capture(depth))
    expected = np.kron(depth > 0, np.ones((SF, SF), bool))
    assert np.array_equal(unmasked.mask_array(), expected)
    assert np.abs(unmasked.depth_array()[expected] - 0.6).max() < 1e-6


def test_guided_sharpens_a_depth_step_aligned_with_a_colour_edge():
    edge = 46  # first high-resolution column of the far side; inside LR column 11 (44..47), a mixed pixel
    x, _ = pixel_grid(H, W)
    depth_hr = np.where(x < edge, 0.50, 0.55)
    color = np.repeat(np.where(x < edge, 0.2, 0.7)[..., None], 3, axis=2)
    rng = np.random.default_rng(1)
    color += rng.normal(0, 0.005, color.shape)  # a little sensor noise
    capture = make_capture(block_average(depth_hr, SF), color)
    near = np.abs(x + 0.5 - edge) <= 2 * SF  # within two LR pixels of the edge

    def edge_error(refinement):
        return np.abs(refinement.depth_array() - depth_hr)[near].mean()

    def transition_width(refinement):  # columns between 10 % and 90 % of the step, middle row
        row = (refinement.depth_array()[H // 2] - 0.50) / 0.05
        return int(np.sum((row > 0.1) & (row < 0.9)))

    b, g, g_default = bicubic(capture), guided(capture, eps=0.01), guided(capture)
    # measured (bicubic, eps 0.01, default eps 0.3): mean error near the edge 6.2, 0.28, 5.1 mm;
    # 10-90 % width 6, 0, 8 columns (small eps: a clean step; the default only half follows the
    # colour edge, a = var / (var + eps) ~ 0.4, and trades edges for less texture copying)
    assert edge_error(g) < 0.1 * edge_error(b)
    assert transition_width(b) >= SF and transition_width(g) == 0
    assert np.abs(g.depth_array() - depth_hr).max() < 0.1 * 0.05  # no overshoot anywhere
    assert edge_error(g_default) < edge_error(b)


def test_no_valid_depth_raises():
    with pytest.raises(CaptureError, match="no valid depth"):
        bicubic(make_capture(np.zeros((h, w))))


def test_guided_rejects_bad_parameters():
    capture = make_capture(np.full((h, w), 0.6))
    with pytest.raises(ValueError, match="radius"):
        guided(capture, radius=0)
    with pytest.raises(ValueError, match="eps"):
        guided(capture, eps=0.0)
