"""The renderer's sensor profiles (o3d_mvps.synthetic.sensor): the D415-like profile's statistics
match its documented parameters, every profile is seeded, and the default stays the paper's."""

import json

import numpy as np
import pytest
from scipy import ndimage

from o3d_mvps import read_capture, synthetic
from o3d_mvps.capture import write_capture
from o3d_mvps.cli import main
from o3d_mvps.colour import srgb_to_linear
from o3d_mvps.synthetic.sensor import EDGE_JUMP, D415Sensor, make_sensor, simulate_depth_sensor

D415 = D415Sensor()
SF = 2


@pytest.fixture(scope="module")
def d415_capture():
    """A D415-like bunny capture: 320x240 colour, SF 2, 6 frames."""
    return synthetic.render_capture("bunny", frames=6, scale_factor=SF, size=(320, 240), sensor="d415", seed=3)


def plane_depth(z, size=(240, 320), tilt=0.0):
    """Colour-resolution depth (H, W) of a plane at z metres, optionally tilted (m per pixel along u)."""
    H, W = size
    return np.full((H, W), float(z)) + tilt * (np.arange(W) - W / 2)[None, :]


def test_documented_d415_figures():
    """The class docstring's numbers: 1.13 mm terraces and 1.45 mm white noise at 1 m, 0.41 mm at 0.6 m."""
    assert D415.depth_step(1.0) * 1000 == pytest.approx(1.131, abs=0.002)
    assert D415.depth_step(0.6) * 1000 == pytest.approx(0.407, abs=0.002)
    assert D415.depth_sigma(1.0) * 1000 == pytest.approx(1.448, abs=0.002)
    assert D415.describe()["depth_step_at_1m_mm"] == pytest.approx(1.131, abs=0.002)


def test_terrace_step_at_one_metre():
    """Depth comes in terraces: on a tilted plane around 1 m the distinct values are one disparity
    step apart, 1.13 mm (specified; within 20 %), "about 1 mm"; at 0.5 m four times finer."""
    for z, expected in ((1.0, D415.depth_step(1.0)), (0.5, D415.depth_step(0.5))):
        out = D415.depth(plane_depth(z, tilt=2e-5), SF, np.random.default_rng(0))
        values = np.unique(out[out > 0])
        steps = np.diff(values[np.abs(values - z) < 0.01])
        assert steps.size > 5
        assert np.median(steps) == pytest.approx(expected, rel=0.2)
        assert np.all(steps > 0.5 * expected)  # nothing between the terraces
    assert D415.depth_step(1.0) == pytest.approx(1e-3, rel=0.2)


def test_depth_noise_grows_with_depth_squared_and_is_partly_smooth():
    """A fronto-parallel plane at 0.5 and 1 m: the error's std grows 4x (z^2, within 15 %); at 1 m it
    is the white and low-frequency parts together, sqrt(1.45^2 + 2.90^2) = 3.24 mm, plus the
    terraces' 1.13/sqrt(12) mm (within 15 %); smoothed over 4 px the white part averages out and
    the low-frequency part, 2.90 mm, stays (within 20 %)."""
    stds = {}
    for z in (0.5, 1.0):
        out = D415.depth(plane_depth(z), SF, np.random.default_rng(1))
        valid = out > 0
        stds[z] = (out[valid] - z).std()
        if z == 1.0:
            error = np.where(valid, out - z, 0.0)
            smooth = ndimage.gaussian_filter(error, 4) / np.maximum(ndimage.gaussian_filter(valid * 1.0, 4), 1e-9)
            lowfreq = D415.lowfreq_sigma * 1.0 / (D415.focal_px * D415.baseline)
            assert smooth[valid].std() == pytest.approx(lowfreq, rel=0.2)
    white, lowfreq = D415.depth_sigma(1.0), D415.depth_sigma(1.0) * D415.lowfreq_sigma / D415.disparity_sigma
    expected = np.sqrt(white**2 + lowfreq**2 + D415.depth_step(1.0) ** 2 / 12)
    assert stds[1.0] == pytest.approx(expected, rel=0.15)
    assert stds[1.0] / stds[0.5] == pytest.approx(4.0, rel=0.15)


def test_speckle_holes_are_a_few_percent_in_clusters(d415_capture):
    """3 % (specified) of the object's depth pixels are holes (0), away from edges too, within 1
    point; they come in clusters (more than 1.5 pixels each on average)."""
    gt = d415_capture.groundtruth.depth
    clean = simulate_depth_sensor(gt, SF, None, depth_scale=None) > 0
    inner = ndimage.binary_erosion(clean, iterations=2)
    z = d415_capture.depth_array(0)
    holes = inner & (z == 0)
    assert inner.sum() > 1000
    assert holes.mean() / inner.mean() == pytest.approx(D415.hole_fraction, abs=0.01)
    clusters = ndimage.label(holes)[1]
    assert holes.sum() / clusters > 1.5


def test_flying_pixels_only_near_edges(d415_capture):
    """Flying pixels (depth far from the clean area average, or depth where the sensor had none)
    exist, about half (specified: 50 %) of the silhouette's partly covered pixels, and lie only
    within one depth pixel of a silhouette or a jump of more than 2 cm."""
    gt = d415_capture.groundtruth.depth
    clean = simulate_depth_sensor(gt, SF, None, depth_scale=None)
    z = d415_capture.depth_array(0).astype(np.float64)
    tolerance = 6 * D415.depth_sigma(clean) * (D415.lowfreq_sigma + D415.disparity_sigma) / D415.disparity_sigma
    flying = (z > 0) & ((clean == 0) | (np.abs(z - clean) > tolerance + 1e-3))
    jump = np.zeros_like(clean, dtype=bool)
    for axis in (0, 1):
        d = np.abs(np.diff(clean, axis=axis)) > EDGE_JUMP
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        jump[tuple(lo)] |= d
        jump[tuple(hi)] |= d
    edges = ndimage.binary_dilation((clean == 0) | jump, structure=np.ones((3, 3), bool)) & \
        ndimage.binary_dilation(clean > 0, structure=np.ones((3, 3), bool))
    partly = (clean == 0) & (np.add.reduceat(np.add.reduceat(gt > 0, np.arange(0, gt.shape[0], SF), 0),
                                              np.arange(0, gt.shape[1], SF), 1) > 0)
    assert flying.sum() > 50
    assert not (flying & ~edges).any()
    assert np.mean(z[partly] > 0) == pytest.approx(D415.flying_fraction * (1 - D415.hole_fraction), abs=0.12)


def test_colour_gain_white_balance_and_shot_noise():
    """A flat grey (linear 0.3) frame: its mean per channel is 0.3 x exposure gain x white balance
    (within 1 %), the drawn gains lie in the specified ranges (exposure 1 +- 10 %, red and blue
    1 +- 4 %, green 1), and the pixel noise is the shot and read noise (plus 8-bit rounding)
    within 15 %."""
    rng = np.random.default_rng(5)
    grey = np.full((120, 160, 3), 0.3)
    gains = []
    for _ in range(12):
        image, drawn = D415.color(grey, rng)
        gain, balance = drawn["gain"], np.array(drawn["white_balance"])
        gains.append(gain)
        assert 1 / 1.1 <= gain <= 1.1 and balance[1] == 1.0 and np.all(np.abs(np.log(balance)) <= np.log(1.04))
        np.testing.assert_allclose(image.mean(axis=(0, 1)), 0.3 * gain * balance, rtol=0.01)
        shot = np.sqrt(D415.full_well * gain * 0.3 + D415.read_noise**2) / D415.full_well * balance[1]
        code = np.rint(((0.3 * gain) ** (1 / 2.4) * 1.055 - 0.055) * 255)
        step = srgb_to_linear(np.array([(code + 1) / 255]))[0] - srgb_to_linear(np.array([code / 255]))[0]
        assert image[..., 1].std() == pytest.approx(np.sqrt(shot**2 + step**2 / 12), rel=0.15)
    assert max(gains) - min(gains) > 0.05  # the exposure drifts between frames


def test_profiles_are_seeded_and_the_default_is_unchanged():
    """Equal seeds give identical D415 captures, another seed another; sensor=None is "gaussian"
    (the paper's protocol, as before), noise=False is "none", and noise=False with a noisy profile
    is refused."""
    kw = dict(frames=2, scale_factor=2, size=(160, 120))
    a, b = (synthetic.render_capture("bunny", sensor="d415", seed=7, **kw) for _ in range(2))
    c = synthetic.render_capture("bunny", sensor="d415", seed=8, **kw)
    for i in range(2):
        np.testing.assert_array_equal(a.depth_array(i), b.depth_array(i))
        np.testing.assert_array_equal(a.color_array(i), b.color_array(i))
    assert not np.array_equal(a.depth_array(1), c.depth_array(1))
    assert a.metadata["synthetic"]["sensor"] == b.metadata["synthetic"]["sensor"]
    default, gaussian = (synthetic.render_capture("bunny", **kw, **extra) for extra in ({}, {"sensor": "gaussian"}))
    none, off = (synthetic.render_capture("bunny", **kw, **extra) for extra in ({"sensor": "none"}, {"noise": False}))
    for i in range(2):
        np.testing.assert_array_equal(default.depth_array(i), gaussian.depth_array(i))
        np.testing.assert_array_equal(default.color_array(i), gaussian.color_array(i))
        np.testing.assert_array_equal(none.depth_array(i), off.depth_array(i))
        np.testing.assert_array_equal(none.color_array(i), off.color_array(i))
    with pytest.raises(ValueError, match="noise=False contradicts sensor='d415'"):
        synthetic.render_capture("bunny", noise=False, sensor="d415", **kw)
    with pytest.raises(ValueError, match="unknown sensor 'kinect'.*'gaussian', 'd415', 'none'"):
        make_sensor("kinect")


def test_render_cli_writes_the_profile(tmp_path, capsys):
    """`o3d-mvps render --sensor d415` writes the profile and each frame's gains into capture.json;
    --no-noise with --sensor d415 is refused before anything is written."""
    out = tmp_path / "cap"
    assert main(["render", "bunny", str(out), "--frames", "2", "--size", "160x120", "--scale-factor", "2",
                 "--sensor", "d415", "--quiet"]) == 0
    sensor = json.loads((out / "capture.json").read_text())["metadata"]["synthetic"]["sensor"]
    assert sensor["name"] == "d415" and sensor["baseline"] == pytest.approx(0.055)
    assert len(sensor["frames"]) == 2 and set(sensor["frames"][0]) == {"gain", "white_balance"}
    assert read_capture(out).depth_array(0).max() > 0
    bad = tmp_path / "bad"
    assert main(["render", "bunny", str(bad), "--no-noise", "--sensor", "d415", "--quiet"]) == 1
    assert "--no-noise contradicts --sensor d415" in capsys.readouterr().err
    assert not bad.exists()


def test_d415_capture_round_trips(d415_capture, tmp_path):
    """A D415-like capture writes and reads back: depth in 1 mm units, colour 8-bit codes."""
    write_capture(d415_capture, tmp_path / "c")
    back = read_capture(tmp_path / "c")
    np.testing.assert_allclose(back.depth_array(1), np.rint(d415_capture.depth_array(1) * 1000) / 1000, atol=1e-6)
    np.testing.assert_allclose(back.color_array(1), d415_capture.color_array(1), atol=1e-6)


def test_colour_integrates_over_the_pixel_area():
    """``color_samples`` s averages s x s rays per pixel (a box filter): on a speckled bunny
    (160x120, directional light) the silhouette's pixels mix the object with the black background
    (none outside the mask is lit point-sampled, 52 are with 2 x 2: bound 30), and 2 x 2 lies
    near the 8 x 8 limit where the point sample does not (image total 0.12 % off against 1.1 %:
    bound 0.3 %; mean |difference| on the object 0.0126 against 0.0393: bound 0.5 x). The D415
    profile integrates (2 x 2), the paper's protocol does not; a bad count names the value."""
    scene = synthetic.build_scene("bunny", size=(160, 120), albedo="speckled")
    light = synthetic.make_light("directional", scene.distance)
    frames = {s: synthetic.render_frame(scene, np.eye(4), light, color_samples=s) for s in (1, 2, 8)}
    point, box, limit = (frames[s].color for s in (1, 2, 8))
    outside = ~frames[1].mask
    assert not point[outside].any() and (box[outside].sum(axis=1) > 0.01).sum() > 30
    assert box.sum() == pytest.approx(limit.sum(), rel=3e-3) and point.sum() != pytest.approx(limit.sum(), rel=3e-3)
    on = frames[1].mask
    assert np.abs(box - limit)[on].mean() < 0.5 * np.abs(point - limit)[on].mean()
    for s in (2, 8):  # the geometry (ground truth) stays at the pixel centres
        np.testing.assert_array_equal(frames[s].depth, frames[1].depth)
        np.testing.assert_array_equal(frames[s].albedo, frames[1].albedo)
    kw = dict(frames=1, scale_factor=2, size=(64, 48))
    d415, paper = (synthetic.render_capture("bunny", sensor=s, **kw) for s in ("d415", "gaussian"))
    assert d415.metadata["synthetic"]["sensor"]["color_samples"] == 2
    assert paper.metadata["synthetic"]["sensor"]["color_samples"] == 1
    with pytest.raises(ValueError, match="color_samples must be an integer >= 1.*got 0"):
        synthetic.render_capture("bunny", color_samples=0, **kw)
