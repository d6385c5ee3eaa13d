"""README.md's fenced Python blocks run as written, in a folder holding a small rendered
capture at capture/ (the path the snippets use)."""

import re
from pathlib import Path

import numpy as np
import pytest

from o3d_mvps import read_capture, write_capture
from o3d_mvps.synthetic import render_capture

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"^```python\n(.*?)^```", README.read_text(), flags=re.S | re.M)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    root = tmp_path_factory.mktemp("readme")
    write_capture(render_capture("bunny", frames=4, scale_factor=4, size=(160, 120), seed=0, progress=False),
                  root / "capture")
    return root


def run_block(index: int, workdir, monkeypatch, capfd) -> dict:
    """Execute README's Python block ``index`` in ``workdir``; its namespace afterwards."""
    monkeypatch.chdir(workdir)
    namespace = {"__name__": "__readme__"}
    exec(compile(BLOCKS[index], f"README.md python block {index}", "exec"), namespace)
    printed = capfd.readouterr()
    assert "WARNING" not in printed.out + printed.err  # Open3D prints its warnings to stdout
    return namespace


def test_readme_has_the_two_python_blocks():
    assert len(BLOCKS) == 2 and "refine_rgbd" in BLOCKS[1]


def test_python_api_block(workdir, monkeypatch, capfd):
    ns = run_block(0, workdir, monkeypatch, capfd)
    assert ns["result"].depth_array().shape == (120, 160)
    assert ns["result"].lighting.shape == (4, 2)  # the documented (n, 2) LED lighting
    assert (workdir / "refined" / "depth.npy").is_file()
    assert (workdir / "scan.glb").stat().st_size > 1000 and (workdir / "scan.stl").stat().st_size > 1000


def test_open3d_loop_block(workdir, monkeypatch, capfd):
    ns = run_block(1, workdir, monkeypatch, capfd)
    points = ns["cloud"].point.positions.numpy()
    assert len(points) > 1000  # one integration of the 160x120 refined depth
    sensor = read_capture(workdir / "capture").depth_array(0)
    near, far = sensor[sensor > 0].min(), sensor.max()
    voxel = 0.002  # the snippet's voxel size; fused points lie within the TSDF truncation (8 voxels)
    assert near - 8 * voxel < points[:, 2].min() and points[:, 2].max() < far + 8 * voxel
    assert np.array_equal(ns["poses"][0], np.eye(4))
