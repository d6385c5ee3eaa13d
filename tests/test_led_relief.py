"""Colour must never become relief (issue 32 item 3) under the LED: on a speckled bunny with the
D415-like sensor the normals at the speckles' rims are worse than elsewhere and their
high-frequency part follows the albedo's gradient (docs/fidelity.md, "Albedo edges under the
LED"). These tests hold the measured figures with a stated margin, so that a change that makes
the relief worse fails, and check :func:`o3d_mvps.metrics.albedo_relief` on a plane whose relief
is known.
"""

import warnings

import numpy as np
import pytest
from scipy import ndimage

from o3d_mvps import RefineOptions, refine, synthetic
from o3d_mvps.metrics import albedo_relief


def _plane(bump_at_step: bool):
    """A fronto-parallel plane at 0.5 m (64 x 64, f = 100 px), albedo 0.6 left of column 32 and
    0.1 right of it; a 0.5 mm Gaussian ridge (2 px wide) along the step or along column 23."""
    H = W = 64
    K = np.array([[100.0, 0.0, 32.0], [0.0, 100.0, 32.0], [0.0, 0.0, 1.0]])
    u = np.arange(W)[None, :].repeat(H, axis=0).astype(float)
    albedo = np.where(u < 32, 0.6, 0.1)
    centre = 31.5 if bump_at_step else 23.0
    depth = 0.5 - 5e-4 * np.exp(-0.5 * ((u - centre) / 2.0) ** 2)
    return depth, K, np.dstack([np.zeros((H, W)), np.zeros((H, W)), -np.ones((H, W))]), albedo


def test_albedo_relief_sees_a_ridge_along_the_albedo_step_only():
    """The ridge on the step: its quarter of steepest albedo (the step's columns) is far worse
    than the mean and the high-pass follows the gradient (measured 2.6 x and 0.40: bounds 2 x and 0.3); the same ridge
    elsewhere: the step's quarter better than the mean (0.03 against 0.39 deg), correlation below 0 (-0.18)."""
    mask = np.zeros((64, 64), bool)
    mask[4:-4, 20:44] = True  # the step's 6-8 columns of steep albedo a quarter of them
    on = albedo_relief(*_plane(True), mask)
    off = albedo_relief(*_plane(False), mask)
    assert on["steepest_quarter_mae_deg"] > 2.0 * on["mae_deg"] and on["high_vs_albedo_gradient"] > 0.3, on
    assert off["steepest_quarter_mae_deg"] < off["mae_deg"] and off["high_vs_albedo_gradient"] < 0.0, off
    with pytest.raises(ValueError, match=r"mask: mask has shape \(3, 3\).*\(64, 64\)"):
        albedo_relief(*_plane(True), np.ones((3, 3), bool))


#: measured on the render below (480x360, SF 4, 12 frames, 30 deg orbit, LED, D415-like sensor,
#: speckled stone, colour integrated over 2 x 2 rays per pixel, given poses) by :func:`albedo_relief`
#: over the pixels 6 px inside the silhouette: all 4.53 deg, steepest albedo quarter 7.52,
#: correlation 0.041 (the true depth's 0.001); when the test was written 4.62 / 8.45 / 0.071
#: (point-sampled colour then: 4.69 / 9.10 / 0.108)
MEASURED = {"mae_deg": 4.53, "steepest_quarter_mae_deg": 7.52, "high_vs_albedo_gradient": 0.041}


def test_speckles_under_the_led_make_no_more_relief_than_measured():
    """Bounds 5 % above the measured figures (and a correlation 0.03 above): the speckles' rims
    at most 1.75 x the mean normal error (measured 1.66 x). The render's D415-like depth has flying
    pixels: they are replaced (the default); kept (``drop_depth_outliers=False``), the mean error is
    8.3 deg (rims 12.9). These figures move by several per cent under small changes of the solver
    (docs/fidelity.md, "Albedo edges under the LED": weighting the warped samples by their
    interpolation error): measure them again when a change moves them."""
    capture = synthetic.render_capture("bunny", frames=12, size=(480, 360), scale_factor=4, light="led",
                                       sensor="d415", albedo="speckled", orbit_deg=30.0, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = refine(capture, RefineOptions(progress=False), initial_poses=capture.groundtruth.poses)
    gt = capture.groundtruth
    depth, truth = result.depth_array().astype(np.float64), np.asarray(gt.depth, np.float64)
    inner = ndimage.distance_transform_edt((truth > 0) & (depth > 0)) > 6
    got = albedo_relief(depth, capture.color_K(), np.asarray(gt.normals, np.float64), np.asarray(gt.albedo), inner)
    floor = albedo_relief(truth, capture.color_K(), np.asarray(gt.normals, np.float64), np.asarray(gt.albedo), inner)
    print(got, floor)
    assert got["mae_deg"] < 1.05 * MEASURED["mae_deg"], got
    assert got["steepest_quarter_mae_deg"] < 1.05 * MEASURED["steepest_quarter_mae_deg"], got
    assert got["steepest_quarter_mae_deg"] < 1.75 * got["mae_deg"], got
    assert got["high_vs_albedo_gradient"] < MEASURED["high_vs_albedo_gradient"] + 0.03, got
    assert abs(floor["high_vs_albedo_gradient"]) < 0.05 and floor["mae_deg"] < 2.0, floor  # forward differences: 1.38
