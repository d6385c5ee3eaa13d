"""A moving camera's depth prior from all its frames: every frame's depth carried onto the
reference's rays and averaged where they agree (o3d_mvps.covisibility.frame_depths_on_reference_rays
/ reference_depth_mean, ``average_frames_depth="initial"``), or each frame's residual against the
current surface in its own pixels at the finest level (o3d_mvps.solver.frames_depth, "finest");
docs/fidelity.md, "The frames' mean depth for a moving camera"."""

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial.transform import Rotation

from o3d_mvps import RefineOptions, refine, synthetic
from o3d_mvps.covisibility import (frame_depths_in_reference, frame_depths_on_reference_rays, reference_depth_mean,
                                   reference_depth_outliers)
from o3d_mvps.model.camera import scale_intrinsics
from o3d_mvps.model.resampling import block_average, masked_gaussian, resample_valid
from o3d_mvps.solver.driver import frames_mean_depths
from o3d_mvps.solver.options import FramesDepth
from o3d_mvps.solver.frames_depth import frames_depth_target
from o3d_mvps.solving import problem_from_capture

K_PLANE = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
NORMAL = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
CENTRE = np.array([0.0, 0.0, 0.6])


def _plane_depth(T: np.ndarray, size=(120, 160)) -> np.ndarray:
    """(h, w) metres: the depth of the tilted plane through CENTRE seen by the camera of pose T."""
    normal, point = T[:3, :3] @ NORMAL, T[:3, :3] @ CENTRE + T[:3, 3]
    v, u = np.mgrid[0:size[0], 0:size[1]].astype(np.float64)
    rays = np.stack([(u - K_PLANE[0, 2]) / K_PLANE[0, 0], (v - K_PLANE[1, 2]) / K_PLANE[1, 1], np.ones_like(u)], -1)
    return (normal @ point) / (rays @ normal)


def _turned(degrees: float) -> np.ndarray:
    """The pose of a camera turned about the y axis through CENTRE."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", degrees, degrees=True).as_matrix()
    T[:3, 3] = CENTRE - T[:3, :3] @ CENTRE
    return T


@pytest.fixture(scope="module")
def plane():
    poses = np.stack([np.eye(4), _turned(15.0), _turned(-25.0), _turned(8.0), _turned(-10.0)])
    return np.stack([_plane_depth(T) for T in poses]), poses


def test_a_plane_is_carried_onto_the_reference_rays_exactly(plane):
    """Each frame's exact depth of a tilted plane, carried onto the reference's rays, is the
    reference's depth to 9e-6 m (the bilinear interpolation of a plane's depth, not linear in the
    pixels; bound 2e-5 m, about 1/30 of a millimetre), over at least 79 % of the pixels (the rest
    outside the frame). The z-buffered splat keeps the nearest sample in a pixel: up to 1.8 mm off
    the same plane."""
    depths, poses = plane
    carried = frame_depths_on_reference_rays(depths, poses, K_PLANE)
    splat = frame_depths_in_reference(depths, poses, K_PLANE)
    for k in range(len(poses) - 1):
        seen = carried[k] > 0
        assert seen.mean() > 0.75
        assert np.abs(carried[k] - depths[0])[seen].max() < 2e-5
    assert max(np.abs(splat[k] - depths[0])[splat[k] > 0].max() for k in range(len(poses) - 1)) > 1e-3


def test_frames_that_agree_are_their_own_mean(plane):
    """Frames that measure the same surface leave the reference depth as it is (to the carrying's
    9e-6 m), and every pixel four frames measure takes the mean."""
    depths, poses = plane
    mean, averaged = reference_depth_mean(depths, poses, K_PLANE)
    assert averaged.mean() > 0.6
    assert np.abs(mean - depths[0]).max() < 2e-5


def test_a_frame_that_disagrees_is_left_out_of_the_mean(plane):
    """A frame whose depth lies 3 cm behind the others' (an occluded view, a wrong pose) is outside
    the outlier tolerance of their median: the mean of the four others is still the reference's
    depth."""
    depths, poses = plane
    depths = depths.copy()
    depths[2] += 0.03
    mean, averaged = reference_depth_mean(depths, poses, K_PLANE)
    assert averaged.mean() > 0.6
    assert np.abs(mean - depths[0]).max() < 2e-5


@pytest.fixture(scope="module")
def d415():
    """The speckled, room-lit bunny with the D415-like sensor (a low-frequency depth error of about
    1 mm at 0.6 m, new in every frame), 320x240, SF 2, 8 frames orbiting to 30 degrees."""
    return synthetic.render_capture("bunny", frames=8, size=(320, 240), scale_factor=2, light="room", sensor="d415",
                                    albedo="speckled", orbit_deg=30.0, seed=1, progress=False)


def test_the_mean_averages_the_frames_low_frequency_error(d415):
    """With the true poses, the frames' mean is nearer the true depth than frame 0 alone over the
    object (its depth pixels fully on the object, 2 px inside, frame 0's flying pixels left out):
    the error's low frequencies (a Gaussian of 4 depth pixels) 1.19 -> 0.23 mm, its RMS 1.37 -> 0.65
    mm, its mean -1.18 -> 0.07 mm. Bounds: half of frame 0's, and 0.25 mm for the mean."""
    truth = np.asarray(d415.groundtruth.depth, np.float64)
    true_depth, on_object = resample_valid(truth, truth > 0, d415.depth_size, min_valid_fraction=1.0)
    depths = np.stack([d415.depth_array(i) for i in range(d415.n_frames)]).astype(np.float64)
    K, poses = np.asarray(d415.depth_K(), np.float64), np.asarray(d415.groundtruth.poses, np.float64)
    flying, noise = reference_depth_outliers(depths, poses, K, return_noise=True)
    mean, averaged = reference_depth_mean(depths, poses, K, noise)
    pixels = ndimage.binary_erosion(on_object & (depths[0] > 0) & ~flying, iterations=2)
    assert averaged[pixels].mean() > 0.8

    def errors(depth):
        error = np.where(pixels, depth - true_depth, 0.0)
        low, _ = masked_gaussian(error, pixels, 4.0)
        return np.sqrt(np.mean(low[pixels] ** 2)), np.sqrt(np.mean(error[pixels] ** 2)), error[pixels].mean()

    (low0, rms0, bias0), (low, rms, bias) = errors(depths[0]), errors(mean)
    assert low < 0.5 * low0 and rms < 0.6 * rms0
    assert abs(bias) < 0.25e-3 < abs(bias0)


def test_the_option_ties_the_depth_to_the_frames_mean_and_says_how_much(d415):
    """``average_frames_depth="initial"``: the solver ties the depth to the frames' mean at the given
    poses (:func:`o3d_mvps.solver.driver.frames_mean_depths`; the saved problem keeps the sensor's
    own depth), and the run report counts the pixels it averaged: 929 of frame 0's 1402 depth
    pixels (the rest along the silhouette or seen by fewer than four frames; bound 60 %), and its
    input checks say so. Off (the default), or without a measured depth noise, frame 0's depth
    stays as it is (the input's own array, not a copy) and nothing is counted."""
    depths = np.stack([d415.depth_array(i) for i in range(d415.n_frames)]).astype(np.float64)
    problem, _ = problem_from_capture(d415, RefineOptions(progress=False, average_frames_depth="initial"),
                                      initial_poses=d415.groundtruth.poses)
    assert problem.depth_noise > 0
    tied = frames_mean_depths(problem, problem.options.average_frames_depth)
    row = problem.report["reference_depth_outliers"]
    assert row["averaged"] > 0.6 * int((depths[0] > 0).sum())
    changed = np.abs(tied[0] - problem.depths[0]) > 1e-4
    assert changed.sum() > 0.5 * row["averaged"]
    np.testing.assert_array_equal(tied[1:], problem.depths[1:])
    said = [c for c in problem.report["inputs"]["checks"] if c["name"] == "frames' mean depth"]
    assert len(said) == 1 and said[0]["detail"].startswith(f"{row['averaged']} of the reference's")
    unmeasured = replace(problem, depth_noise=None)
    for mode in ("initial", "finest"):  # asked for, but no noise to judge the frames by: said, not silent
        with pytest.warns(UserWarning, match=f"average_frames_depth='{mode}' needs 4 frames or more.*not measured"):
            assert frames_mean_depths(unmeasured, FramesDepth(mode)) is unmeasured.depths
    default, _ = problem_from_capture(d415, RefineOptions(progress=False), initial_poses=d415.groundtruth.poses)
    assert frames_mean_depths(default, default.options.average_frames_depth) is default.depths
    assert "averaged" not in default.report["reference_depth_outliers"]
    assert not [c for c in default.report["inputs"]["checks"] if c["name"] == "frames' mean depth"]
    flying = reference_depth_outliers(depths, np.asarray(d415.groundtruth.poses, np.float64),
                                      np.asarray(d415.depth_K(), np.float64))
    assert np.array_equal(default.depths[0][~flying], depths[0][~flying])


def test_finest_with_the_poses_held_says_it_is_not_made(d415):
    """"finest" compares the frames at the poses the solve refines: with the poses held it is not
    made, and the solve says so (naming "initial" instead) rather than tying the depth to frame 0
    without a word; the result is the default's."""
    options = dict(progress=False, refine_poses=False, levels=2, max_iterations=2)
    with pytest.warns(UserWarning, match="'finest' compares the frames at the poses the solve refines.*'initial'"):
        held = refine(d415, RefineOptions(average_frames_depth="finest", **options),
                      initial_poses=d415.groundtruth.poses)
    assert "frames_depth" not in held.info
    default = refine(d415, RefineOptions(**options), initial_poses=d415.groundtruth.poses)
    np.testing.assert_array_equal(held.depth_array(), default.depth_array())


def test_the_cli_flag_is_the_option():
    """``o3d-mvps refine --average-frames-depth finest|initial|off`` is the option; "off" without it."""
    from o3d_mvps.cli import build_parser
    from o3d_mvps.cli.refine import options_from_args

    parse = build_parser().parse_args
    for value in ("initial", "off", "finest"):
        args = parse(["refine", "in", "out", "--average-frames-depth", value])
        assert options_from_args(args).model.average_frames_depth == value
    assert options_from_args(parse(["refine", "in", "out"])).model.average_frames_depth == "off"
    with pytest.raises(ValueError, match="average_frames_depth must be one of"):
        RefineOptions(average_frames_depth=True)


# ------------------------------------------------------------------------------------------
# The finest level's target from every frame's residual (o3d_mvps.solver.frames_depth)
# ------------------------------------------------------------------------------------------

SF = 2


def _plane_capture(noise_m: float = 0.0, seed: int = 0):
    """The tilted plane on a 160x120 colour grid (K_PLANE) seen by 7 cameras turned about its centre,
    each frame's depth the block average of its colour-grid depth over SF x SF pixels (an ideal
    sensor), plus white noise of ``noise_m`` metres: (reference colour depth, depths (7, 60, 80),
    poses, depth intrinsics)."""
    poses = np.stack([np.eye(4), _turned(10.0), _turned(-12.0), _turned(6.0), _turned(-8.0), _turned(14.0),
                      _turned(-5.0)])
    depths = np.stack([block_average(_plane_depth(T), SF) for T in poses])
    depths += np.random.default_rng(seed).normal(0.0, noise_m, depths.shape)
    return _plane_depth(poses[0]), depths, poses, scale_intrinsics(K_PLANE, 1 / SF, 1 / SF)


def test_the_frames_residuals_leave_an_exact_surface_where_frame_0_has_it():
    """At the true surface an ideal sensor's frames have no residual: the target is frame 0's depth
    to 3e-5 m on 90 % of the pixels (median 4e-6 m; at most 5e-4 m, where a frame's depth pixel is
    only partly seen), and 96 % of the pixels are averaged."""
    z, depths, poses, K_depth = _plane_capture()
    target, averaged = frames_depth_target(z, z > 0, K_PLANE, K_depth, SF, depths, poses, 0.0, depths[0])
    error = np.abs(target - depths[0])[averaged]
    assert averaged.mean() > 0.9
    assert np.percentile(error, 90) < 1e-4 and error.max() < 1e-3


def test_the_frames_residuals_average_the_noise_and_not_a_pose_that_is_off():
    """With 1 mm of white noise in every frame, the target is 0.29 mm RMS off the noise-free depth
    where frame 0 is 1.00 mm off (bound: 0.4 of it). A frame whose pose is 3 mm off along its axis
    moves it by its rigid part alone, which frame 0's replaces: still 0.29 mm, its mean error that of
    frame 0's noise (-0.008 mm; bound 0.05 mm)."""
    z, exact, poses, K_depth = _plane_capture()
    _, noisy, _, _ = _plane_capture(noise_m=0.001)
    target, averaged = frames_depth_target(z, z > 0, K_PLANE, K_depth, SF, noisy, poses, 0.0, noisy[0])
    rms0 = np.sqrt(np.mean((noisy[0] - exact[0])[averaged] ** 2))
    assert np.sqrt(np.mean((target - exact[0])[averaged] ** 2)) < 0.4 * rms0
    off = poses.copy()
    off[3, 2, 3] += 0.003
    target, averaged = frames_depth_target(z, z > 0, K_PLANE, K_depth, SF, noisy, off, 0.0, noisy[0])
    assert np.sqrt(np.mean((target - exact[0])[averaged] ** 2)) < 0.4 * rms0
    assert abs(np.mean((target - exact[0])[averaged]) - np.mean((noisy[0] - exact[0])[averaged])) < 5e-5


@pytest.fixture(scope="module")
def demo_render():
    """``make demo``'s capture: the LED bunny in coloured patches, 640x480, SF 4, 20 frames on a 15
    degree orbit, Gaussian sensor noise (:func:`o3d_mvps.synthetic.render_capture`'s defaults)."""
    return synthetic.render_capture("bunny", frames=20, size=(640, 480), scale_factor=4, light="led", seed=0,
                                    progress=False)


def test_finest_re_makes_the_finest_prior_and_the_normals_gain(demo_render):
    """``average_frames_depth="finest"`` on ``make demo``'s capture: normal MAE 2.155 -> 1.558 deg
    (bound 0.85 of "off"), depth RMSE 0.975 -> 0.866 mm (bound: not worse); ``info["frames_depth"]``
    counts the averaged pixels (1271 of frame 0's 1310 depth pixels; bound 80 %), "off" has none."""
    import warnings

    from o3d_mvps import refine
    from o3d_mvps.metrics import evaluate

    got = {}
    for mode in ("off", "finest"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = refine(demo_render, RefineOptions(progress=False, average_frames_depth=mode))
        got[mode] = (evaluate(result, demo_render), result.info.get("frames_depth"))
    (off, none), (finest, counted) = got["off"], got["finest"]
    assert none is None
    assert counted["averaged"] > 0.8 * counted["of"]
    assert finest["mae_deg"] < 0.85 * off["mae_deg"], got
    assert finest["rmse_mm"] <= off["rmse_mm"], got


def test_a_retargeted_prior_on_the_device_scores_its_new_target():
    """``DepthPrior.retarget`` on a prior moved to the GPU (or, where numba's CUDA simulator is on,
    the CuPy stand-in, which refuses host arrays as CuPy does): the new target is copied there and
    the device's cached -z0 is formed anew, so its energy is the host prior's with that target (to
    1e-12 relative), not the old one's (the old target scores 1.0, the new 0.25)."""
    import numba
    import scipy.sparse as sp

    from o3d_mvps.solver.pyramid import DepthPrior

    z, old, new = np.full(4, 0.5), np.full(4, 1.0), np.full(4, 0.75)
    host = DepthPrior(sp.identity(4, format="csr"), new)
    if numba.config.ENABLE_CUDASIM:
        import cupy_emulation

        with cupy_emulation.installed():
            energy = _retargeted_energy(cupy_emulation.array_device(), old, new, z)
    else:
        from o3d_mvps.solver.device import array_device

        energy = _retargeted_energy(array_device("cuda:0"), old, new, z)
    assert energy[0] == pytest.approx(1.0, rel=1e-12)
    assert energy[1] == pytest.approx(host.energy(z, 1.0, 0.0), rel=1e-12) == pytest.approx(0.25, rel=1e-12)


def _retargeted_energy(device, old: np.ndarray, new: np.ndarray, z: np.ndarray) -> tuple[float, float]:
    """The energy (tau 1, no smoothness) of a device prior at z before and after its target goes
    from ``old`` to ``new``."""
    import scipy.sparse as sp

    from o3d_mvps.solver.pyramid import DepthPrior

    moved = DepthPrior(sp.identity(4, format="csr"), old).on_device(device)
    z_device = device.asarray(z)
    before = moved.energy(z_device, 1.0, 0.0)
    moved.retarget(new)
    return before, moved.energy(z_device, 1.0, 0.0)
