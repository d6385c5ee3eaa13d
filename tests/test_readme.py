"""README.md's fenced Python block runs as written, in a folder holding a small rendered capture
at dataset/ with its true poses as the trajectory Open3D's reconstruction system would write
(dataset/scene/trajectory.log), the paths the snippet uses; the README stays short; and the
Python block of docs/getting-started.md runs on the same capture (as capture/)."""

import re
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from o3d_mvps import write_capture
from o3d_mvps.synthetic import render_capture

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
PYTHON_BLOCK = r"^```python\n(.*?)^```"
BLOCKS = re.findall(PYTHON_BLOCK, README.read_text(), flags=re.S | re.M)
GETTING_STARTED = re.findall(PYTHON_BLOCK, (REPO / "docs" / "getting-started.md").read_text(), flags=re.S | re.M)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    root = tmp_path_factory.mktemp("readme")
    capture = render_capture("bunny", frames=4, scale_factor=4, size=(160, 120), seed=0, progress=False)
    write_capture(capture, root / "dataset")
    trajectory = o3d.camera.PinholeCameraTrajectory()
    intrinsic = o3d.io.read_pinhole_camera_intrinsic(str(root / "dataset" / "intrinsic.json"))
    for pose in capture.groundtruth.poses:  # world = the reference camera: extrinsic = T_i
        parameters = o3d.camera.PinholeCameraParameters()
        parameters.intrinsic, parameters.extrinsic = intrinsic, pose
        trajectory.parameters = [*trajectory.parameters, parameters]
    (root / "dataset" / "scene").mkdir()
    assert o3d.io.write_pinhole_camera_trajectory(str(root / "dataset" / "scene" / "trajectory.log"), trajectory)
    return root, capture.groundtruth


def test_readme_is_short_and_has_one_python_block():
    assert len(README.read_text().splitlines()) <= 150
    assert len(BLOCKS) == 1 and "trajectory.log" in BLOCKS[0]


def run_block(code: str, name: str, folder, monkeypatch, capfd) -> dict:
    """Execute ``code`` in ``folder``; its namespace afterwards. Nothing may warn."""
    monkeypatch.chdir(folder)
    namespace = {"__name__": "__readme__"}
    exec(compile(code, name, "exec"), namespace)
    printed = capfd.readouterr()
    assert "WARNING" not in printed.out + printed.err  # Open3D prints its warnings to stdout
    return namespace


def test_open3d_trajectory_block(workdir, monkeypatch, capfd):
    root, groundtruth = workdir
    namespace = run_block(BLOCKS[0], "README.md python block", root, monkeypatch, capfd)
    # the .log round trip gives the true poses back (Open3D writes 8 decimals)
    assert np.allclose(namespace["E"] @ np.linalg.inv(namespace["E"][0]), groundtruth.poses, atol=1e-6)
    result = namespace["result"]
    assert result.depth_array().shape == (120, 160)
    assert (root / "refined" / "normals.png").is_file() and (root / "refined" / "depth.npy").is_file()
    assert (root / "refined.png").stat().st_size > 1000
    # started at the truth, the refined poses stay near it: 4 frames at 160x120 (a colour pixel
    # is about 3 mm on the object) moved at most 8.9 mm; bound 15 mm
    moved_mm = 1000 * np.linalg.norm(result.poses.numpy()[:, :3, 3] - groundtruth.poses[:, :3, 3], axis=1)
    assert moved_mm[0] == 0.0 and moved_mm.max() < 15.0, moved_mm


def test_getting_started_python_block(workdir, monkeypatch, capfd):
    root, _ = workdir
    folder = root / "getting_started"
    folder.mkdir()
    (folder / "capture").symlink_to(root / "dataset")
    assert len(GETTING_STARTED) == 1
    namespace = run_block(GETTING_STARTED[0], "docs/getting-started.md python block", folder, monkeypatch, capfd)
    assert namespace["result"].depth_array().shape == (120, 160)
    assert namespace["result"].lighting.shape == (4, 2)  # the documented (n, 2) LED lighting
    assert (folder / "refined" / "depth.npy").is_file()
    assert (folder / "scan.glb").stat().st_size > 1000 and (folder / "scan.stl").stat().st_size > 1000
