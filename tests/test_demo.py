"""`o3d-mvps demo` end to end at a tiny size: every promised output is written, and re-running
replaces the demo folder as a whole."""

import pytest

from o3d_mvps import read_capture, read_refinement
from o3d_mvps.cli import main

OUTPUTS = ["capture", "refined", "report.md", "mesh.obj", "mesh.mtl", "mesh_albedo.png", "mesh.glb", "print.stl",
           "preview.png"]


def test_demo_writes_every_output(tmp_path):
    out = tmp_path / "demo"
    args = ["--quiet", "demo", "--out", str(out), "--frames", "3", "--size", "160x120", "--scale-factor", "2"]
    assert main(args) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUTS)
    assert read_capture(out / "capture").n_frames == 3
    assert read_refinement(out / "refined").depth_array().shape == (120, 160)
    report = (out / "report.md").read_text()
    assert "| ours |" in report and "| bicubic |" in report
    (out / "stale.txt").write_text("from an earlier run")
    assert main(args) == 0
    assert not (out / "stale.txt").exists()


def test_demo_rejects_a_bad_size(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["demo", "--size", "640by480"])
    assert stop.value.code == 2
    assert "WIDTHxHEIGHT" in capsys.readouterr().err
