"""The benchmark entry point's --quick mode writes every result file with the documented keys."""

import json
from dataclasses import replace
from pathlib import Path

import pytest

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
    room = json.loads((tmp_path / "room.json").read_text())  # the scene under each light, same rows
    assert [scene["light"] for scene in room["scenes"]] == ["room", "led"]
    assert all([r["method"] for r in scene["rows"]] == ["bicubic", "smooth fit", "ours, smoothness 0", "ours"]
               for scene in room["scenes"])
    assert "## Room light" in (tmp_path / "room.md").read_text() and "## LED" in (tmp_path / "room.md").read_text()
    summary = (tmp_path / "summary.md").read_text()
    assert "Speed" in summary and "tau~" in summary
    for png in ("frames_mae.png", "frames_rmse.png", "tau_mae.png", "tau_rmse.png", "room_banding.png",
                "room_banding_led.png"):
        assert (tmp_path / png).stat().st_size > 1000


def test_banding_measure_flags_terraces_and_not_a_smooth_slope():
    """A depth that keeps the sensor's 1 mm terraces (the sawtooth a sloped plane gets from
    rounding, softened as an upsampler would) has its normal errors on the iso-depth lines; the
    true plane with an error that does not depend on the phase gives a ratio of 1."""
    import numpy as np
    from scipy import ndimage

    from benchmarks.room import banding, quantisation_phase
    from o3d_mvps.model.normals import perspective_normals
    from o3d_mvps.synthetic import DEPTH_SCALE

    H, W = 64, 400
    K = np.array([[500.0, 0, W / 2], [0, 500.0, H / 2], [0, 0, 1]])
    u = np.arange(W)[None, :].repeat(H, axis=0)
    true = 0.5 + 0.1e-3 * u  # 0.1 mm per pixel: a terrace every 10 pixels
    terraced = ndimage.gaussian_filter1d(np.rint(true * DEPTH_SCALE) / DEPTH_SCALE, 1.5, axis=1)
    normals_true = perspective_normals(true, K)[0]
    error = np.degrees(np.arccos(np.clip(np.sum(perspective_normals(terraced, K)[0] * normals_true, axis=2), -1, 1)))
    error[:, :8], error[:, -8:] = np.nan, np.nan  # the filter's borders
    on, off, ratio = banding(error, true)
    assert ratio > 1.5 and on > off + 2.0  # measured 1.69 (6.1 deg against 3.6): the risers sit on the lines
    phase = quantisation_phase(true)
    assert abs(phase[0, 0] - 0.5) < 1e-6  # 0.5 m: a sensor level, mid-terrace
    assert min(phase[0, 5], 1 - phase[0, 5]) < 1e-6  # 0.5005 m: where the reading jumps, a line
    flat = np.where(np.isfinite(error), 2.0, np.nan)
    assert banding(flat, true)[2] == 1.0


def test_peak_rss_counts_this_process_only():
    """A worker's peak memory is its own high-water mark: in a fresh process it rises by what the
    process touches (200 MiB here, with 25 % margin for the allocator) from well under that."""
    import subprocess
    import sys

    code = ("import numpy as np; from benchmarks.speed import peak_rss_mb; before = peak_rss_mb(); "
            "block = np.ones(200 * 2**20 // 8); print(before, peak_rss_mb() - before)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    before, rise = map(float, done.stdout.split())
    assert 150 < rise < 250 and before < 1000, (before, rise)


def test_gpu_benchmark_compares_the_cuda_path_with_the_cpu_path(tmp_path):
    """benchmarks.gpu on a tiny problem, its CUDA path on the GPU or, where none is listed (numba's
    CUDA simulator on: tests/conftest.py), on the CuPy stand-in of tests/cupy_emulation.py: the
    row's fields, and the two paths agreeing to the GPU issue's tolerances (the paths' CG
    preconditioners differ; both stop at 1e-4). The tiny level runs on the device (the product
    would solve it on the CPU: o3d_mvps.solver.device.CUDA_MIN_LEVEL_PIXELS).

    Then ``count`` on the same problem: its level's device operations, none where the level is
    below the product's threshold."""
    import cupy_emulation
    import numba

    from benchmarks import gpu
    from o3d_mvps.colour import CodedColours
    from o3d_mvps.solver.device import array_device
    from o3d_mvps.solver.problem_input import read_problem

    gpu.make(tmp_path, cases=(((64, 48), 2),), frames=3, options={"levels": 1, "max_iterations": 1})
    if numba.config.ENABLE_CUDASIM:
        with cupy_emulation.installed():
            (row,) = gpu.run(tmp_path, tmp_path / "results", cupy_emulation.array_device())
        assert row["device"] == "cuda-emulated" and row["peak_gpu_mb"] == 0.0
        assert row["level_devices"] == ["cuda-emulated"]
    else:
        (row,) = gpu.run(tmp_path, tmp_path / "results", replace(array_device("cuda:0"), min_level_pixels=0))
        assert row["peak_gpu_mb"] > 0 and row["level_devices"] == ["cuda:0"]
    assert json.loads((tmp_path / "results" / "gpu.json").read_text()) == [row]
    assert (row["color"], row["depth"], row["frames"]) == ("64x48", "32x24", 3)
    assert row["object_pixels"] > 200 and row["sweeps_cpu"] == row["sweeps_cuda"] == 2
    assert row["max_depth_diff_mm"] < 0.1 and row["mae_diff_deg"] < 0.1 and row["energy_rel_diff"] < 1e-3
    # the saved problem holds the frames as 8-bit codes; decoded first, the device solves the same
    # (the stand-in: bit for bit; an H200 parted them by 7.5e-6 mm at 640x480, its atomic sums' order)
    assert isinstance(read_problem(tmp_path / "gpu_64x48.npz").colors, CodedColours)
    same = row["coded_vs_float"]
    if numba.config.ENABLE_CUDASIM:
        assert same["max_depth_diff_mm"] == same["mae_diff_deg"] == same["energy_rel_diff"] == 0.0, same
    else:
        assert same["sweeps_cpu"] == same["sweeps_cuda"], same  # else no energy to compare sweep by sweep
        assert same["max_depth_diff_mm"] < 1e-3 and same["energy_rel_diff"] < 1e-6, same

    (counted,) = gpu.count(tmp_path, tmp_path / "results", min_level_pixels=0)
    (level,) = counted["levels"]
    assert level["device"] == "cuda-emulated" and level["sweeps"] == 1
    # a sweep's kernels, sparse products and copies (measured: 64 with issue 33's joint step,
    # evaluation and multigrid set-up in a few kernels each (gpujoint, gpueval2, gpukrylov merged),
    # 125 after its one-launch evaluation and set-up kernels, 290 before them, 493 before the fused
    # and batched kernels)
    assert 55 < level["operations"] < counted["operations"]
    assert counted["by_kind"]["kernel"] > 0 and counted["by_kind"]["to_host"] > 0  # (CG's products are kernels now)
    kinds = counted["by_kind"]
    assert counted["transfers"] == kinds["to_host"] + kinds["to_device"] > 0
    assert counted["launches"] + counted["transfers"] == counted["operations"]
    assert level["launches"] + level["transfers"] == level["operations"] == level["operations_per_sweep"]
    assert json.loads((tmp_path / "results" / "gpu_counts.json").read_text()) == [counted]
    (on_cpu,) = gpu.count(tmp_path, tmp_path / "results")
    assert on_cpu["levels"][0]["device"] == "cpu" and on_cpu["levels"][0]["operations"] == 0

    # levels: per-level seconds of the CPU, every level on the device, and the product's split
    # (a threshold above the level's pixels: on the CPU); without a GPU the CUDA kernels' CPU
    # twins stand in for them (the simulator ran them above)
    if numba.config.ENABLE_CUDASIM:
        with cupy_emulation.installed(), gpu._cpu_kernels_as_cuda_kernels(cupy_emulation):
            timed = gpu.levels(tmp_path, tmp_path / "results", cupy_emulation.array_device(10**6), repeats=1,
                                warm_up=False)
    else:
        timed = gpu.levels(tmp_path, tmp_path / "results", replace(array_device("cuda:0"), min_level_pixels=10**6),
                           repeats=1, warm_up=False)
    assert json.loads((tmp_path / "results" / "gpu_levels.json").read_text()) == timed
    runs = timed["problems"]["gpu_64x48.npz"]
    assert [run["level_devices"] for name in ("cpu", "device_all", "device_product") for run in runs[name]] == \
        [["cpu"], [row["level_devices"][0]], ["cpu"]]
    for name, (run,) in runs.items():
        (level,) = run["levels"]
        assert level["pixels"] == row["object_pixels"] and level["sweeps"] == 2 and 0 < level["seconds"] < run["seconds"]
        assert [e[:2] for e in run["energies"]] == [[0, 0], [0, 1]]
    assert runs["device_product"][0]["against_cpu"]["max_depth_diff_mm"] == 0.0
    assert runs["device_all"][0]["against_cpu"]["max_depth_diff_mm"] < 0.1


def test_summary_redraws_the_plots_from_saved_results(tmp_path):
    """``python -m benchmarks summary`` runs nothing: from scaling rows and saved room error maps
    it draws scaling.png (log-log, fitted power law) and the error-map pictures."""
    import numpy as np

    from benchmarks.room import save_maps
    from benchmarks.scaling import power_law
    from o3d_mvps.fileio import json_text

    rows = [{"version": "current", "target_pixels": p, "object_pixels": p, "color": "64x48", "frames": n,
             "seconds": 0.002 * (p * n) ** 0.9, "peak_mb": 1.0} for p in (1e4, 1e5) for n in (5, 20)]
    exponent, prefactor = power_law(rows)
    assert abs(exponent - 0.9) < 1e-9 and abs(prefactor - 0.002) < 1e-9  # exact data, exact fit
    (tmp_path / "scaling.json").write_text(json_text(rows, "rows"))
    error = np.full((30, 40), np.nan)
    error[5:25, 5:35] = np.linspace(0, 80, 600).reshape(20, 30)
    save_maps(tmp_path / "room_maps.npz", {"room": {"bicubic": error, "ours": error / 2}})
    assert main(["summary", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "scaling.png").stat().st_size > 10_000
    assert (tmp_path / "room_banding.png").stat().st_size > 10_000
    assert not (tmp_path / "room_banding_led.png").exists()  # only the lights saved are drawn
    assert not (tmp_path / "scaling.md").exists()  # the hand-annotated table is left alone


def test_no_hand_drawn_plots_in_benchmarks():
    """Plots are matplotlib's: no OpenCV text, lines or rectangles drawn in benchmarks/*.py."""
    import re
    from pathlib import Path

    folder = Path(__file__).resolve().parents[1] / "benchmarks"
    drawn = [p.name for p in folder.glob("*.py") if re.search(r"cv2\.(putText|line|rectangle)", p.read_text())]
    assert drawn == []


def test_registration_benchmark_rows(tmp_path):
    """``speed --registration --quick``: a row for the 8-frame 320 x 240 orbit with each frame's pose
    error against the render's truth, the registration's time and peak memory."""
    import json

    from benchmarks.__main__ import main

    main(["speed", "--registration", "--quick", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "registration.json").read_text())
    assert [r["capture"] for r in rows] == ["orbit_320x240_sf4_0.6m_8"]
    orbit = rows[0]
    assert orbit["version"] == "current" and orbit["dropped"] == [] and len(orbit["deg"]) == len(orbit["frames"]) - 1
    assert max(orbit["deg"]) < 2.5 and max(orbit["mm"]) < 25, orbit  # test_odometry's bounds
    assert all(r["seconds"] > 0 and r["peak_mb"] > 100 for r in rows)
    assert (tmp_path / "registration.png").stat().st_size > 1000


def test_stage_benchmark_rows(tmp_path):
    """``benchmarks.stages``: this tree against itself on a tiny capture, alternating; each row's
    stage timings are CPU seconds (their sum within the process's CPU time), each stage's peak
    memory its own (at least the capture's resident size, at most the process's peak), the same
    energy for the same code, and the plot."""
    import json

    from benchmarks import stages
    from o3d_mvps.capture import write_capture
    from o3d_mvps.synthetic import render_capture

    write_capture(render_capture("bunny", frames=3, scale_factor=2, size=(160, 120), seed=0), tmp_path / "tiny")
    tree = str(Path(stages.__file__).resolve().parent.parent)
    stages.main(["--baseline-tree", tree, "--captures", f"tiny={tmp_path / 'tiny'}", "--repeats", "1",
                 "--options", '{"max_iterations": 1}', "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "speed_stages.json").read_text())
    assert [(r["capture"], r["version"]) for r in rows] == [("tiny", "baseline"), ("tiny", "this")]
    for r in rows:
        stage_cpu = sum(v for k, v in r["timings"].items() if k != "total")
        assert 0 < stage_cpu <= r["cpu_seconds"], r
        peaks = r["stage_peak_mb"]
        assert {"read", "odometry", "build_level", "albedo", "extrapolation"} <= set(peaks), peaks
        assert all(peaks["read"] * 0.95 <= v <= r["peak_mb"] for v in peaks.values()), peaks
    # the same code, to 1e-9: Open3D's registration sums in threads, its poses differ between
    # processes by ~1e-16 m, and the solve carries that on continuously (measured <= 2e-13 over 30
    # such moves; before the AMG strength threshold of solver/linear.py: two outcomes 1.4e-5 apart)
    assert rows[0]["energy"] == pytest.approx(rows[1]["energy"], rel=1e-9)
    assert (tmp_path / "speed_stages.png").stat().st_size > 1000


def test_pose_check_benchmark_counts_frames_named_and_true_poses_refused(tmp_path):
    """--quick: the 40x30-depth ring and the 6-frame orbit; no true pose refused (6 checks), and on
    the orbit (80x60 depth) every frame 5 degrees off about an axis or 10 mm off along one is named;
    the ring's frames (about 20 points each) only in part."""
    from benchmarks import pose_checks

    assert pose_checks.main(["--quick", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "pose_checks.json").read_text())
    assert result["checks"] == 6 and result["true_poses_refused"] == [] and result["frames"] == 22
    for key in ("rx5", "ry5", "rz5", "tx10", "ty10", "tz10"):
        assert "orbit" not in result["missed"][key], key
    assert set(result["missed"]["rz5"]) <= {"ring12_160"} and result["caught"]["rz5"] >= 5
    assert f"| rz5 | {result['caught']['rz5']} of 22 |" in (tmp_path / "pose_checks.md").read_text()


def test_memory_curve_plot_marks_older_revisions(tmp_path, monkeypatch):
    """speed.memory_curve_plot draws a line per colour size and revision, the rows' first
    revision solid and older ones dashed, then dotted, each labelled with its commit."""
    import matplotlib.axes

    from benchmarks.speed import memory_curve_plot

    drawn = []
    plot = matplotlib.axes.Axes.plot

    def recorded(self, *args, **kwargs):
        drawn.append((kwargs.get("label"), kwargs.get("linestyle"), list(args[1])))
        return plot(self, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "plot", recorded)
    rows = [{"color": "640x480", "frames": f, "peak_mb": 400.0 + f, "revision": "new1234"} for f in (5, 10)]
    rows += [{"color": "1708x1136", "frames": f, "peak_mb": 2000.0 + f, "revision": "old5678"} for f in (10, 5)]
    rows += [{"color": "1708x1136", "frames": 30, "peak_mb": 2600.0, "revision": "older90"}]
    memory_curve_plot(rows, tmp_path / "curve.png")
    assert drawn == [("640x480 colour (new1234)", "-", [405.0, 410.0]),
                     ("1708x1136 colour (old5678)", "--", [2005.0, 2010.0]),
                     ("1708x1136 colour (older90)", ":", [2600.0])]
    assert (tmp_path / "curve.png").stat().st_size > 1000
