"""Against depth fusion (issue #32 item 7): the TSDF-fusion baseline, and ours against it and
bicubic on a noisy, dark-speckled, wide-baseline render (docs/fidelity.md, "Against depth fusion").
"""

import numpy as np
import open3d as o3d
import pytest
from scipy import ndimage

from o3d_mvps.baselines import tsdf_fusion
from o3d_mvps.capture import Capture, default_depth_intrinsic
from o3d_mvps.covisibility import reference_depth_outliers
from o3d_mvps.synthetic.camera import look_at_pose, synthetic_intrinsics

from benchmarks.peers import (METHODS, SMOOTHED, error_sources, frames_seeing, light_rows, render, selected_methods,
                             sensor_like_normals, smoothed_depth)


def _plane_capture(size=(320, 240), sf=2):
    """A plane tilted 30 degrees about the vertical axis, 0.5 m away, seen from 5 frames 2 cm apart;
    exact (unquantised) depth by ray-plane intersection at each frame's depth pixels."""
    W, H = size
    K = synthetic_intrinsics(W, H)
    K_lr = default_depth_intrinsic(K, sf)
    normal = np.array([np.sin(np.radians(30)), 0.0, -np.cos(np.radians(30))])  # points to the camera
    point = np.array([0.0, 0.0, 0.5])
    target = point
    poses = [np.eye(4)] + [look_at_pose(np.array([0.02 * x, 0.02 * y, 0.0]), target)
                           for x, y in ((-1, 0), (1, 0), (0, -1), (0, 1))]
    depth = []
    for T in poses:
        v, u = np.mgrid[0:H // sf, 0:W // sf].astype(np.float64)
        rays = np.stack([(u - K_lr[0, 2]) / K_lr[0, 0], (v - K_lr[1, 2]) / K_lr[1, 1], np.ones_like(u)], -1)
        R, t = T[:3, :3], T[:3, 3]
        n_cam, p_cam = R @ normal, R @ point + t  # the plane in the frame's camera
        z = (n_cam @ p_cam) / (rays @ n_cam)
        depth.append(o3d.t.geometry.Image(o3d.core.Tensor(z[..., None].astype(np.float32))))
    colour = [o3d.t.geometry.Image(o3d.core.Tensor(np.full((H, W, 3), 0.5, np.float32))) for _ in poses]
    capture = Capture(color=colour, depth=depth, color_intrinsic=o3d.core.Tensor(K),
                      depth_intrinsic=o3d.core.Tensor(K_lr), light="room")
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    truth = (normal @ point) / (rays @ normal)
    return capture, np.stack(poses), truth


def test_fusion_round_trips_a_plane():
    """Five exact depth maps of a tilted plane, fused and ray cast into the reference colour view."""
    capture, poses, truth = _plane_capture()
    fused = tsdf_fusion(capture, 0.004, poses=poses)
    depth, mask = fused.depth_array(), fused.mask_array()
    inner = mask.copy()
    inner[:8], inner[-8:], inner[:, :8], inner[:, -8:] = False, False, False, False
    error = np.abs(depth - truth)[inner]
    assert fused.method == "tsdf fusion" and fused.info["tsdf_fusion"]["voxel_mm"] == 4.0
    assert fused.info["tsdf_fusion"]["missed_fraction"] < 0.05  # measured 0.033: the border only some frames see
    rmse_mm = 1000 * np.sqrt(np.mean(error**2))
    assert rmse_mm < 0.35, rmse_mm  # measured 0.24 mm (nearest depth pixel of 3.6 mm on a 30-degree slope)
    with pytest.raises(ValueError, match=r"poses must be \(5, 4, 4\).*\(2, 4, 4\)"):
        tsdf_fusion(capture, 0.004, poses=poses[:2])
    with pytest.raises(ValueError, match="voxel must be.*-1"):
        tsdf_fusion(capture, -1, poses=poses)


@pytest.fixture(scope="module")
def room_study():
    """The benchmark's capture, small: room light, 320x240, SF 4, 8 frames to 30 degrees; the
    rows of bicubic, TSDF 4 mm and ours (given poses) and the error study's arrays."""
    rows, _, arrays = light_rows({"size": (320, 240), "scale_factor": 4, "frames": 8}, "room",
                                 selected_methods("bicubic,tsdf4,ours-given"))
    return {row["method"]: row for row in rows}, arrays


@pytest.fixture(scope="module")
def room_case(room_study):
    rows = room_study[0]
    return {"bicubic": rows["bicubic"], "tsdf": rows["tsdf 4 mm"], "ours": rows["ours, given poses"]}


def test_ours_beats_bicubic_and_fusion_on_a_noisy_speckled_room_lit_capture(room_case):
    """Measured (object 4 px inside, true poses): ours 2.20 mm / 11.6 deg (dark quarter 10.2,
    against the true depth smoothed by 4 px 12.0); TSDF 4 mm 4.17 / 17.0 (16.9, 14.7); bicubic
    8.19 / 23.1. Before the reference's flying pixels were left out of the prior ours was 7.38 mm /
    16.8 deg: worse than the fusion in depth."""
    ours, fusion, cubic = room_case["ours"], room_case["tsdf"], room_case["bicubic"]
    assert ours["rmse_mm"] < 0.8 * fusion["rmse_mm"], room_case
    assert ours["mae_deg"] < 0.75 * fusion["mae_deg"], room_case
    assert ours["mae_dark_deg"] < 0.8 * fusion["mae_dark_deg"], room_case
    assert ours["mae_sensor_like_deg"] < 0.85 * fusion["mae_sensor_like_deg"], room_case
    assert ours["rmse_mm"] < 0.5 * cubic["rmse_mm"] and ours["mae_deg"] < 0.6 * cubic["mae_deg"], room_case
    assert fusion["rmse_mm"] < 0.6 * cubic["rmse_mm"], room_case  # the fusion does average the frames' noise


def test_the_reference_s_flying_pixels_are_found_by_the_other_frames():
    """Exact plane depth in 5 frames; 40 reference pixels moved 3 cm back (flying pixels) are
    flagged and nothing else; a 2 mm error (sensor noise) is not."""
    capture, poses, _ = _plane_capture()
    depths = np.stack([capture.depth_array(i) for i in range(capture.n_frames)]).astype(np.float64)
    rng = np.random.default_rng(0)
    h, w = depths.shape[1:]
    flat = rng.choice(np.arange(h * w).reshape(h, w)[10:-10, 10:-10].ravel(), 80, replace=False)
    flying, noisy = flat[:40], flat[40:]
    depths[0].ravel()[flying] += 0.03
    depths[0].ravel()[noisy] += 0.002
    found = reference_depth_outliers(depths, poses, capture.depth_K())
    assert set(np.flatnonzero(found)) == set(flying)


def test_methods_are_chosen_by_key_and_a_wrong_key_is_named():
    assert selected_methods("all") == list(METHODS.values())
    assert selected_methods("ours-given, tsdf4") == ["tsdf 4 mm", "ours, given poses"]  # the tables' order
    with pytest.raises(ValueError, match=r"--methods 'tsdf4,tsdf9'.*\['tsdf9'\].*bicubic, tsdf4"):
        selected_methods("tsdf4,tsdf9")
    with pytest.raises(ValueError, match="tsdf4-refined.*add ours-registered"):
        selected_methods("tsdf4-refined")


@pytest.fixture(scope="module")
def small_capture():
    return render({"size": (160, 120), "scale_factor": 4, "frames": 6}, "room")


def test_the_true_depth_smoothed_is_the_sensor_like_surface(small_capture):
    """The sensor-like normals are the normals of the true depth smoothed by smoothed_depth."""
    truth = np.asarray(small_capture.groundtruth.depth, np.float64)
    smooth = smoothed_depth(truth, truth > 0)
    from o3d_mvps.model.normals import perspective_normals
    normals = perspective_normals(smooth, small_capture.color_K(), smooth > 0)[0]
    np.testing.assert_allclose(normals, sensor_like_normals(small_capture), atol=1e-12)


def test_frames_seeing_counts_the_reference_and_the_frames_that_face_a_pixel(small_capture):
    """6 frames on an orbit to 30 degrees: every object pixel is seen by the reference, most by all;
    pixels off the object by none; the rim band (turned away from the orbit's far frames) by fewer."""
    truth = np.asarray(small_capture.groundtruth.depth, np.float64)
    seen = frames_seeing(small_capture)
    mask = truth > 0
    assert seen[~mask].max() == 0 and seen[mask].min() >= 1 and seen.max() <= 6
    assert np.median(seen[mask]) == 6
    rim = mask & (ndimage.distance_transform_edt(mask) <= 3)
    assert seen[rim].mean() < seen[mask & ~rim].mean() - 0.2, (seen[rim].mean(), seen[mask & ~rim].mean())


def test_no_region_is_noisier_than_the_smoothed_sensor_and_colour_does_not_become_relief(room_study):
    """The error study on the small room case (320x240, SF 4, 8 frames). Against the true normals,
    ours (given poses) in every region below 0.8 x the smoothed sensor's (bicubic smoothed by 4 px):
    measured all 11.6 / 22.3 deg, rim band 12.7 / 27.8, inner 10.3 / 16.0 (the largest ratio,
    0.65), darkest albedo quarter 10.2 / 21.6, steepest albedo 10.9 / 20.8, seen by fewer frames
    than the median 16.5 / 26.8. The high-frequency part (ours against its own smoothing) does not
    follow the albedo: correlation with its gradient -0.066, with its darkness -0.041 (bound
    0.15)."""
    _, arrays = room_study
    study, maps = error_sources(arrays)
    ours = study["methods"]["ours, given poses"]
    for region, sensor in study["smoothed_sensor_mae_deg"].items():
        assert ours["by_region"][region]["true"] < 0.8 * sensor, (region, ours["by_region"][region], sensor)
    assert abs(ours["high_vs_albedo_gradient"]) < 0.15 and abs(ours["high_vs_albedo_darkness"]) < 0.15, ours
    assert {"true normals vs sensor-like", "ours, given poses: vs truth"} <= set(maps)
    assert all(m.shape == arrays["pixels"].shape and np.isnan(m[~arrays["pixels"]]).all() for m in maps.values())


def test_the_sensor_like_metric_penalises_true_detail(room_study):
    """The true depth itself is 15.3 deg off the sensor-like normals, above the 4 mm fusion (14.7)
    and ours (12.0): the metric's floor for a method that keeps all true detail is the truth's
    own distance from its smoothing, not 0. With the detail smoothed away from both (4 px, as the
    reference is made) ours is 3.2 deg off, the fusion 11.1: bound 0.5 x."""
    rows, _ = room_study
    truth, fusion, ours = rows["true depth"], rows["tsdf 4 mm"], rows["ours, given poses"]
    assert truth["rmse_mm"] == 0.0 and truth["mae_deg"] < 2.0, truth  # the depth's normals against the mesh's: 1.85
    assert truth["mae_sensor_like_deg"] > fusion["mae_sensor_like_deg"] > ours["mae_sensor_like_deg"], rows
    assert rows["ours, given poses" + SMOOTHED]["mae_sensor_like_deg"] < 0.5 * rows["tsdf 4 mm" + SMOOTHED]["mae_sensor_like_deg"], rows
