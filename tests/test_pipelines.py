"""pipelines/*.py: every script's --help, and refine_capture / print_scan / reconstruct_object end to end on tiny captures."""

import subprocess
import sys
from pathlib import Path

import pytest

from o3d_mvps import read_refinement, write_capture
from o3d_mvps.synthetic import render_capture

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"
SCRIPTS = ["refine_capture.py", "print_scan.py", "record_and_refine.py", "reconstruct_object.py"]
TINY_SOLVER = ["--levels", "3", "--iterations", "2", "--quiet"]


def run_script(name, *args):
    return subprocess.run([sys.executable, str(PIPELINES / name), *map(str, args)], capture_output=True, text=True, check=False,
                          timeout=120)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    path = tmp_path_factory.mktemp("pipelines") / "capture"
    write_capture(render_capture("bunny", frames=4, scale_factor=4, size=(160, 120), seed=2), path)
    return path


def test_help():
    # concurrently: each start imports Open3D, which is most of the time
    runs = {s: subprocess.Popen([sys.executable, str(PIPELINES / s), "--help"], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True) for s in SCRIPTS}
    for script, proc in runs.items():
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, f"{script}: {err}"
        assert "usage:" in out and "examples:" in out, script


def test_refine_capture(capture_dir, tmp_path):
    out = tmp_path / "out"
    result = run_script("refine_capture.py", capture_dir, out, *TINY_SOLVER)
    assert result.returncode == 0, result.stderr
    assert (out / "mesh.obj").is_file() and (out / "mesh.mtl").is_file()
    report = (out / "report.md").read_text()
    assert "| ours |" in report and "| bicubic |" in report
    refinement = read_refinement(out / "refined")
    assert refinement.depth_array().shape == (120, 160)
    again = run_script("refine_capture.py", capture_dir, out, *TINY_SOLVER)  # never over earlier output
    assert again.returncode == 1 and "pass --overwrite" in again.stderr and "overwrite=True" not in again.stderr


def test_print_scan(capture_dir, tmp_path):
    import open3d as o3d

    out = tmp_path / "scan.stl"
    result = run_script("print_scan.py", capture_dir, out, "--print", "60", *TINY_SOLVER)
    assert result.returncode == 0, result.stderr
    mesh = o3d.io.read_triangle_mesh(str(out))
    assert len(mesh.triangles) > 100
    extent = mesh.get_axis_aligned_bounding_box().get_extent()
    assert max(extent) == pytest.approx(60.0, rel=1e-3)
    usage = run_script("print_scan.py", capture_dir, tmp_path / "scan.obj")
    assert usage.returncode == 2 and "*.stl" in usage.stderr


def test_reconstruct_object(tmp_path):
    import numpy as np
    import trimesh

    from o3d_mvps.synthetic import render_ring

    ring, _ = render_ring("bunny", frames=8, size=(96, 72))
    write_capture(ring, tmp_path / "ring")
    np.save(tmp_path / "ring" / "poses.npy", ring.groundtruth.poses)
    done = run_script("reconstruct_object.py", tmp_path / "ring", tmp_path / "object", "--references", "3",
                      "--depth", "raw", "--print", "50", "--quiet")
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in (tmp_path / "object").iterdir()) == ["mesh.mtl", "mesh.obj", "mesh_albedo.png",
                                                                        "print.stl"]
    mesh = trimesh.load(tmp_path / "object" / "mesh.obj", force="mesh")
    assert len(mesh.faces) > 500 and np.asarray(mesh.visual.material.image).shape[:2] == (1024, 1024)
    solid = trimesh.load(tmp_path / "object" / "print.stl")
    assert solid.is_volume and max(solid.extents) == pytest.approx(50.0, rel=1e-4)


def test_failures_exit_1_with_the_message(tmp_path, monkeypatch, capsys):
    missing = run_script("refine_capture.py", tmp_path / "nowhere", tmp_path / "out")
    assert missing.returncode == 1 and "does not exist" in missing.stderr
    # no camera: run the script in-process with pyrealsense2's device list emptied (its boundary),
    # so the check holds whether or not a RealSense is plugged in
    import pyrealsense2 as rs

    class NoDevices:
        def query_devices(self):
            return []

    monkeypatch.setattr(rs, "context", NoDevices)
    monkeypatch.syspath_prepend(str(PIPELINES))
    import _common
    import record_and_refine

    code = _common.run_main(record_and_refine.build_parser(), record_and_refine.run, [str(tmp_path / "rec"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1 and "record_and_refine.py: error:" in err and "RealSense" in err
    assert not (tmp_path / "rec").exists()
