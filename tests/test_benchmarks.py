"""The benchmark entry point's --quick mode writes every result file with the documented keys."""

import json

from benchmarks.__main__ import main


def test_quick_benchmarks_write_results(tmp_path):
    assert main(["all", "--quick", "--out", str(tmp_path)]) == 0
    row_keys = {"mesh", "sf", "frames", "method", "mae_deg", "rmse_mm", "seconds"}
    accuracy = json.loads((tmp_path / "accuracy.json").read_text())
    assert {r["method"] for r in accuracy} == {"bicubic", "guided", "single_frame", "two_stage", "ours"}
    assert all(row_keys <= r.keys() for r in accuracy)
    for study, cases in (("frames", 4), ("tau", 2)):  # frames: 2 values x 2 protocols
        rows = json.loads((tmp_path / f"{study}.json").read_text())
        assert len(rows) == cases and all(row_keys | {"tau", "protocol"} <= r.keys() for r in rows)
    (speed,) = json.loads((tmp_path / "speed.json").read_text())
    assert {"color", "depth", "frames", "seconds", "peak_mb", "breakdown"} <= speed.keys()
    assert speed["peak_mb"] > 0 and speed["breakdown"]["total"] > 0
    summary = (tmp_path / "summary.md").read_text()
    assert "Speed" in summary and "tau~" in summary
    for png in ("frames_mae.png", "frames_rmse.png", "tau_mae.png", "tau_rmse.png"):
        assert (tmp_path / png).stat().st_size > 1000

