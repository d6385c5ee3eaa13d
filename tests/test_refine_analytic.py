"""refine() end to end on an analytic relief rendered without o3d_mvps.synthetic (tests/helpers.py)."""

import numpy as np

from helpers import kicked_poses, relief_capture, with_led_offset_error
from o3d_mvps import RefineOptions, refine
from o3d_mvps.baselines import bicubic
from o3d_mvps.metrics import evaluate


def test_refine_recovers_the_relief_from_a_wrong_led_offset_and_kicked_poses():
    """6 frames of a 4 mm sinusoidal relief at 0.5 m, 160x120, SF 4, LED offset 1.5 cm off,
    poses kicked by ~3 mm / 0.4 deg, like a registration's (refined freely: pose_trust=False; held
    at the default 2 mm / 0.2 deg trust the MAE is 0.64 deg). Measured: normal MAE 0.40 deg, depth RMSE 0.102 mm
    (bicubic 2.05 deg, 0.286 mm); bounds 0.6 deg and 0.15 mm (50 % margin)."""
    capture = relief_capture()
    start = evaluate(bicubic(capture), capture.groundtruth)
    assert start["mae_deg"] > 1.5 and start["rmse_mm"] > 0.25  # the bounds below are not met by the input
    result = refine(with_led_offset_error(capture), RefineOptions(progress=False, levels=3, max_iterations=4),
                    initial_poses=kicked_poses(capture.groundtruth.poses), pose_trust=False)
    got = evaluate(result, capture.groundtruth)
    assert got["mae_deg"] < 0.6, got
    assert got["rmse_mm"] < 0.15, got
    assert np.isfinite(result.albedo_array()).all()
