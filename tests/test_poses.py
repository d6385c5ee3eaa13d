"""Pose files of other tools (o3d_mvps.capture.poses) against a rendered capture's true poses, and refine --poses."""

import json

import numpy as np
import pytest

from o3d_mvps.capture import read_capture_poses, write_capture
from o3d_mvps.cli import main
from o3d_mvps.errors import CaptureError
from o3d_mvps.synthetic import render_capture

from helpers import world_to_camera, write_open3d, write_pose_file, write_tum

N = 4


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("poses") / "cap"
    write_capture(render_capture("bunny", frames=N, scale_factor=4, size=(160, 120), light="led", seed=0), path)
    return path


@pytest.fixture(scope="module")
def truth(folder):
    return np.load(folder / "groundtruth" / "poses.npy")


@pytest.mark.parametrize("name", ["poses.json", "poses.log", "poses.txt", "poses.npy"])
def test_each_format_round_trips_the_true_poses(folder, truth, tmp_path, name):
    path = tmp_path / name
    write_pose_file(path, truth)
    poses, read_from = read_capture_poses(folder, path)
    assert read_from == path
    tolerance = 1e-6  # .log and TUM files hold 8-9 decimals
    np.testing.assert_allclose(poses, truth, rtol=0, atol=tolerance)


def test_folder_pose_file_is_used_and_ambiguity_refused(folder, truth):
    assert read_capture_poses(folder) is None
    np.save(folder / "poses.npy", truth)
    try:
        poses, path = read_capture_poses(folder)
        assert path == folder / "poses.npy"
        np.testing.assert_allclose(poses, truth, rtol=0, atol=1e-12)
        write_tum(folder / "poses.txt", truth, range(N))
        with pytest.raises(CaptureError, match=r"several pose files \(poses.npy, poses.txt\); keep one"):
            read_capture_poses(folder)
    finally:
        for name in ("poses.npy", "poses.txt"):
            (folder / name).unlink(missing_ok=True)


def test_pose_count_mismatch_names_both_counts(folder, truth, tmp_path):
    write_open3d(tmp_path / "t.log", world_to_camera(truth)[:3])
    with pytest.raises(CaptureError, match=r"t.log holds 3 poses but the capture folder has 4 frames"):
        read_capture_poses(folder, tmp_path / "t.log")


def test_pose_ids_mismatch(folder, truth, tmp_path):
    write_tum(tmp_path / "t.txt", world_to_camera(truth), [5, 6, 7, 8])
    with pytest.raises(CaptureError, match=r"the pose ids 5..8 do not match the 4 frames 000000..000003"):
        read_capture_poses(folder, tmp_path / "t.txt")


def test_bad_pose_files(folder, tmp_path):
    (tmp_path / "p.csv").write_text("1,2")
    with pytest.raises(CaptureError, match=r"unknown pose file format '.csv'"):
        read_capture_poses(folder, tmp_path / "p.csv")
    (tmp_path / "p.json").write_text(json.dumps({"parameters": [{"intrinsic": {}}]}))
    with pytest.raises(CaptureError, match="not an Open3D PinholeCameraTrajectory JSON"):
        read_capture_poses(folder, tmp_path / "p.json")
    np.save(tmp_path / "p.npy", np.tile(2 * np.eye(4), (N, 1, 1)))
    with pytest.raises(CaptureError, match="pose 0 is not a rigid transform"):
        read_capture_poses(folder, tmp_path / "p.npy")


def test_refine_cli_takes_poses_from_a_file(folder, truth, tmp_path, capsys):
    write_open3d(tmp_path / "trajectory.log", world_to_camera(truth))
    out = tmp_path / "out"
    code = main(["refine", str(folder), str(out), "--poses", str(tmp_path / "trajectory.log"), "--levels", "2",
                 "--iterations", "1", "--no-pose-refinement"])
    assert code == 0
    assert f"poses: from {tmp_path / 'trajectory.log'}" in capsys.readouterr().out
    np.testing.assert_allclose(np.load(out / "poses.npy"), truth, rtol=0, atol=1e-6)  # kept: no pose refinement
    assert json.loads((out / "report.json").read_text())["info"]["frames"] == list(range(N))
