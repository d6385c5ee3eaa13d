"""Initial poses from Open3D ICP (o3d_mvps.odometry) on small rendered captures.

Measured on the fixture render (bunny, 8 frames, 320 x 240, SF 4, LED, noise, seed 0):
max 1.72 deg / 15.9 mm, median 0.83 deg / 7.6 mm; the inverse poses are off by up to 29 deg.
"""

import numpy as np
import pytest

from o3d_mvps.errors import OdometryError
from o3d_mvps.model.se3 import pose_error
from o3d_mvps.odometry import initial_poses
from o3d_mvps.synthetic import render_capture

MAX_DEG, MAX_M = 2.5, 0.025  # measured 1.72 deg, 15.9 mm
MEDIAN_DEG, MEDIAN_M = 1.2, 0.012  # measured 0.83 deg, 7.6 mm


@pytest.fixture(scope="module")
def capture():
    return render_capture("bunny", frames=8, scale_factor=4, size=(320, 240), light="led", seed=0)


@pytest.fixture(scope="module")
def poses(capture):
    return initial_poses(capture)


def _errors(poses, truth):
    return np.array([pose_error(poses[i], truth[i]) for i in range(1, len(truth))])


class _ReplacedDepth:
    """A capture whose depth of one frame is replaced (same interface as used by initial_poses)."""

    def __init__(self, capture, frame, depth):
        self._capture, self._frame, self._depth = capture, frame, depth
        self.n_frames = capture.n_frames

    def depth_array(self, i):
        return self._depth if i == self._frame else self._capture.depth_array(i)

    def depth_K(self):
        return self._capture.depth_K()


def test_poses_match_groundtruth(capture, poses):
    assert poses.shape == (8, 4, 4)
    np.testing.assert_array_equal(poses[0], np.eye(4))
    errors = _errors(poses, capture.groundtruth.poses)
    assert errors[:, 0].max() < MAX_DEG and errors[:, 1].max() < MAX_M, errors
    assert np.median(errors[:, 0]) < MEDIAN_DEG and np.median(errors[:, 1]) < MEDIAN_M, errors


def test_direction_is_reference_to_frame(capture, poses):
    inverse = np.linalg.inv(poses)
    errors = _errors(inverse, capture.groundtruth.poses)
    assert errors[:, 0].max() > 4 * MAX_DEG and errors[:, 1].max() > 4 * MAX_M, errors


@pytest.mark.parametrize("kind", ["far_plane", "random"])
def test_unregistrable_frame_raises_naming_it(capture, kind):
    shape = capture.depth_array(3).shape
    if kind == "far_plane":
        depth = np.full(shape, 2.5)
    else:
        depth = np.random.default_rng(0).uniform(0.3, 2.9, size=shape)
    with pytest.raises(OdometryError, match=r"frame 3\b"):
        initial_poses(_ReplacedDepth(capture, 3, depth))


def test_empty_frame_raises_naming_it(capture):
    depth = np.zeros(capture.depth_array(5).shape)
    with pytest.raises(OdometryError, match=r"frame 5\b"):
        initial_poses(_ReplacedDepth(capture, 5, depth))


def test_single_frame_is_identity():
    capture = render_capture("bunny", frames=1, scale_factor=4, size=(160, 120), light="led", seed=0)
    np.testing.assert_array_equal(initial_poses(capture), np.eye(4)[None])


def test_unknown_method(capture):
    with pytest.raises(ValueError, match="unknown method"):
        initial_poses(capture, method="hybrid")
