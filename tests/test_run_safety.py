"""Runs that end well: outputs checked before the work and written on the output's own file
system, option values refused naming the option, waits on a Dask scheduler that end, Ctrl-C and
SIGTERM at any moment (exit 130, one line, within a second), and the report of every run."""

import collections
import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import o3d_mvps.fileio as fileio
from helpers import snapshot

from o3d_mvps import write_capture
from o3d_mvps.cli import main
from o3d_mvps.cli import refine as refine_cli
from o3d_mvps.errors import CaptureError, OutputPathError
from o3d_mvps.fileio import atomic_folder
from o3d_mvps.run_report import REPORT_KEYS
from o3d_mvps.solver.__main__ import main as solver_main
from o3d_mvps.synthetic import render_capture

REPO = Path(__file__).resolve().parents[1]
TINY = ["--levels", "2", "--iterations", "2"]


def no_work(*args, **kwargs):
    raise AssertionError("the command started its work before checking its output")


def refused(argv, capsys, monkeypatch) -> str:
    """Run ``o3d-mvps argv`` with the work patched to fail; assert exit 1; return stderr."""
    monkeypatch.setattr(refine_cli, "refine", no_work)
    assert main([str(a) for a in argv]) == 1
    return capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# outputs
# ---------------------------------------------------------------------------------------------
def test_an_output_whose_parent_is_a_file(capture_dir, tmp_path, capsys, monkeypatch):
    (tmp_path / "notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    err = refused(["refine", capture_dir, tmp_path / "notes.txt" / "out"], capsys, monkeypatch)
    assert f"{tmp_path / 'notes.txt'} is a file, not a folder" in err and "choose an output path" in err
    assert snapshot(tmp_path) == before


def test_a_read_only_output_folder(capture_dir, tmp_path, capsys, monkeypatch):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    real_mkdir = os.mkdir

    def mkdir(path, *args, **kwargs):  # root ignores the mode bits: answer as the kernel would for a user
        if Path(path).parent == locked:
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_mkdir(path, *args, **kwargs)

    if os.geteuid() == 0:
        monkeypatch.setattr(os, "mkdir", mkdir)
    try:
        err = refused(["refine", capture_dir, locked / "out"], capsys, monkeypatch)
    finally:
        locked.chmod(0o755)
    assert f"cannot write {locked / 'out'}: {locked} is not writable (Permission denied)" in err
    assert "change its permissions" in err and list(locked.iterdir()) == []


@pytest.mark.parametrize("inside", [False, True])
def test_an_output_in_the_capture_is_refused(capture_dir, capsys, monkeypatch, inside):
    """`--overwrite` with OUT = the capture wrote poses.npy into it, which its next run read."""
    before = snapshot(capture_dir)
    out = capture_dir / "refined" if inside else capture_dir
    err = refused(["refine", capture_dir, out, "--overwrite"], capsys, monkeypatch)
    assert f"{out} {'is inside' if inside else 'is'} the input {capture_dir}" in err
    assert "choose an output path outside it" in err
    assert snapshot(capture_dir) == before


def test_a_solution_path_that_is_a_folder(tmp_path, capsys):
    folder = tmp_path / "solutions"
    folder.mkdir()
    assert solver_main(["problem.npz", str(folder)]) == 1  # refused before the problem is read
    err = capsys.readouterr().err
    assert f"{folder} is a folder; name the file to write, e.g. {folder / 'output.npz'}" in err
    assert list(folder.iterdir()) == []


def test_a_solution_over_its_own_problem_is_refused(tmp_path, capsys):
    problem = tmp_path / "problem.npz"
    problem.write_bytes(b"the user's problem")
    assert solver_main([str(problem), str(problem), "--overwrite"]) == 1
    assert f"{problem} is the input {problem}" in capsys.readouterr().err
    assert problem.read_bytes() == b"the user's problem"


def test_a_full_disk_is_named_before_the_work(capture_dir, tmp_path, capsys, monkeypatch):
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(fileio.shutil, "disk_usage", lambda path: usage(2**30, 2**30 - 2**20, 2**20))
    err = refused(["refine", capture_dir, tmp_path / "out"], capsys, monkeypatch)
    assert f"the disk holding {tmp_path / 'out'} is full (1.0 MB free, ENOSPC" in err
    assert list(tmp_path.iterdir()) == []


def test_a_disk_that_fills_while_writing_is_named_and_leaves_nothing(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputPathError, match=r"the disk holding .*out is full .*ENOSPC: no space left on device"):
        with atomic_folder(out, overwrite=True) as tmp:
            (tmp / "depth.npy").write_text("partial")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert [p.name for p in out.iterdir()] == ["notes.txt"]  # no staging folder, the user's file kept


# ---------------------------------------------------------------------------------------------
# an output on another file system: renames across it fail with EXDEV, as the kernel's do
# ---------------------------------------------------------------------------------------------
@pytest.fixture
def mount(tmp_path, monkeypatch):
    """tmp_path/mnt stands for a mount point: a rename whose source and target lie on different
    sides of it raises EXDEV. Records every folder made."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    made, renames = [], []

    def device(path) -> str:
        return "mnt" if Path(os.path.abspath(path)).is_relative_to(mnt) else "root"

    def guard(real):
        def rename(src, dst, *args, **kwargs):
            renames.append((Path(src), Path(dst)))
            if device(src) != device(dst):
                raise OSError(errno.EXDEV, "Invalid cross-device link", str(src), None, str(dst))
            return real(src, dst, *args, **kwargs)
        return rename

    real_mkdir = os.mkdir
    monkeypatch.setattr(os, "rename", guard(os.rename))
    monkeypatch.setattr(os, "replace", guard(os.replace))
    monkeypatch.setattr(os, "mkdir", lambda path, *a, **k: (made.append(Path(path)), real_mkdir(path, *a, **k))[1])
    return mnt, made, renames


@pytest.mark.parametrize("target", ["the mount point", "a new folder on it"])
def test_an_output_on_another_file_system_is_staged_on_it(mount, target):
    mnt, made, renames = mount
    out = mnt if target == "the mount point" else mnt / "refined"
    (mnt / "notes.txt").write_text("mine")
    with atomic_folder(out, overwrite=True) as tmp:
        (tmp / "depth.npy").write_text("new")
    assert (out / "depth.npy").read_text() == "new" and (mnt / "notes.txt").read_text() == "mine"
    staged = [p for p in made if p.name.startswith(".")]
    assert staged and all(p.is_relative_to(mnt) for p in staged)  # beside the target, on its file system
    assert renames and all(src.is_relative_to(mnt) and dst.is_relative_to(mnt) for src, dst in renames)
    assert sorted(p.name for p in mnt.iterdir() if p.name.startswith(".")) == []  # nothing left behind


def test_an_output_file_on_another_file_system(mount):
    mnt, made, renames = mount
    from o3d_mvps.fileio import atomic_files

    with atomic_files([mnt / "solution.npz"], overwrite=False) as (tmp,):
        tmp.write_bytes(b"data")
    assert (mnt / "solution.npz").read_bytes() == b"data" and renames[-1][0].parent == mnt


# ---------------------------------------------------------------------------------------------
# option values
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("argv, flag, value", [
    (["reconstruct", "cap", "out", "--workers", "0"], "--workers", "0"),
    (["refine", "cap", "out", "--frames", "8.7"], "--frames", "8.7"),
    (["refine", "cap", "out", "--frames", "0"], "--frames", "0"),
    (["refine", "cap", "out", "--iterations", "-1"], "--iterations", "-1"),
    (["refine", "cap", "out", "--levels", "-2"], "--levels", "-2"),
    (["refine", "cap", "out", "--tau", "-10"], "--tau", "-10"),
    (["refine", "cap", "out", "--tau", "nan"], "--tau", "nan"),
    (["refine", "cap", "out", "--tolerance", "1.5"], "--tolerance", "1.5"),
    (["refine", "cap", "out", "--led-offset", "30", "0", "0"], "--led-offset", "30"),
    (["reconstruct", "cap", "out", "--frames-per-reference", "1"], "--frames-per-reference", "1"),
    (["reconstruct", "cap", "out", "--texture-px", "-1"], "--texture-px", "-1"),
    (["reconstruct", "cap", "out", "--scheduler-timeout", "0"], "--scheduler-timeout", "0"),
    (["render", "bunny", "out", "--frames", "2.5"], "--frames", "2.5"),
])
def test_option_values_are_refused_naming_the_option(argv, flag, value, capsys):
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"argument {flag}:" in err and repr(value) in err


def test_more_frames_than_the_capture_has(capture_dir, tmp_path, capsys, monkeypatch):
    err = refused(["refine", capture_dir, tmp_path / "out", "--frames", "5"], capsys, monkeypatch)
    assert "--frames 5: the capture" in err and "has 3 frames; pass --frames 1..3" in err


def test_a_fractional_frame_count_in_capture_json(capture_dir, tmp_path):
    import shutil

    from o3d_mvps import read_capture

    copy = tmp_path / "capture"
    shutil.copytree(capture_dir, copy)
    settings = json.loads((copy / "capture.json").read_text())
    (copy / "capture.json").write_text(json.dumps({**settings, "frames": 2.7}))
    with pytest.raises(CaptureError, match=r'capture.json: "frames": 2.7 must be a whole number of frames'):
        read_capture(copy)


# ---------------------------------------------------------------------------------------------
# waits that end
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("address", ["htp:/nope", "tcp://127.0.0.1", "tcp://127.0.0.1:1"])
def test_a_bad_or_unreachable_scheduler_fails_in_seconds_naming_it(address, capture_dir, tmp_path, capsys):
    start = time.perf_counter()
    assert main(["reconstruct", str(capture_dir), str(tmp_path / "out"), "--scheduler", address,
                 "--scheduler-timeout", "1"]) == 1
    assert time.perf_counter() - start < 8
    err = capsys.readouterr().err
    assert address in err and ("--scheduler" in err) and not (tmp_path / "out").exists()


def test_a_scheduler_without_workers_times_out(capture_dir):
    from dask.distributed import LocalCluster

    from o3d_mvps import read_capture
    from o3d_mvps.reconstruct import ReconstructOptions, reconstruct
    from o3d_mvps.reconstruct.parallel import SchedulerError

    capture = read_capture(capture_dir)
    options = ReconstructOptions(references=2, frames_per_reference=2, scheduler_timeout=1.0, progress=False)
    with LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster:
        start = time.perf_counter()
        with pytest.raises(SchedulerError, match=rf"scheduler at {cluster.scheduler_address} has no workers after 1 s"):
            reconstruct(capture, options, poses=np.stack([np.eye(4)] * 3), scheduler=cluster.scheduler_address)
        assert time.perf_counter() - start < 6


# ---------------------------------------------------------------------------------------------
# Ctrl-C and SIGTERM
# ---------------------------------------------------------------------------------------------
def interrupt(argv, sig, *, after_line: bool, delay: float = 0.3, env=None) -> tuple[int, str, float]:
    """Start ``argv``, send ``sig`` (after its first line of output, or after ``delay`` s),
    return (exit code, stderr, seconds from the signal to the exit)."""
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
    if after_line:
        assert proc.stdout.readline()  # the work has started
    time.sleep(delay)
    sent = time.perf_counter()
    proc.send_signal(sig)
    while proc.poll() is None and time.perf_counter() - sent < 30:
        time.sleep(0.01)
    took = time.perf_counter() - sent
    _, err = proc.communicate(timeout=30)
    return proc.returncode, err, took


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_a_refinement(capture_dir, tmp_path, sig):
    out = tmp_path / "out"
    code, err, took = interrupt([sys.executable, "-m", "o3d_mvps", "refine", str(capture_dir), str(out),
                                 "--iterations", "50", "--tolerance", "0"], sig, after_line=True)
    assert code == 130 and took < 2
    # the progress bars before it, then one line
    assert err.endswith("\no3d-mvps refine: interrupted\n") and err.count("interrupted") == 1 and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # nothing written, no staging folder left


def test_ctrl_c_while_the_command_starts(capture_dir, tmp_path):
    """In the first second (Open3D loading) Ctrl-C printed a traceback."""
    code, err, took = interrupt([sys.executable, "-m", "o3d_mvps", "refine", str(capture_dir),
                                 str(tmp_path / "out")], signal.SIGINT, after_line=False, delay=0.6)
    assert code == 130 and err.endswith(": interrupted\n") and len(err.splitlines()) == 1 and took < 2


def test_a_command_stuck_in_a_library_call_is_ended(tmp_path):
    """A library call that holds the GIL (Open3D's UV atlas: 10 s) keeps Python's signal handlers
    from running; the supervising process ends the command anyway. Stand-in: a child whose
    signals are blocked while it sleeps."""
    (tmp_path / "stuck_child.py").write_text(textwrap.dedent("""
        import signal, time
        from o3d_mvps.cli import stop_on_signals
        stop_on_signals("o3d-mvps stuck")
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
        print("started", flush=True)
        time.sleep(60)
    """))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(REPO)])}
    code, err, took = interrupt([sys.executable, "-c", "import sys; from o3d_mvps.cli import supervise; "
                                 "sys.exit(supervise('stuck_child', [], 'o3d-mvps stuck'))"], signal.SIGINT,
                                after_line=True, delay=0.1, env=env)
    assert code == 130 and err == "o3d-mvps stuck: interrupted\n" and took < 1.5


# ---------------------------------------------------------------------------------------------
# the report of a run
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def refined(tmp_path_factory):
    """A small refine with pose refinement (160 x 120, 4 frames, the first 3 used)."""
    root = tmp_path_factory.mktemp("report")
    write_capture(render_capture("bunny", frames=4, scale_factor=2, size=(160, 120), seed=2, progress=False),
                  root / "capture")
    out = root / "refined"
    code = main(["refine", str(root / "capture"), str(out), "--frames", "3", "--levels", "2", "--iterations", "3"])
    assert code == 0
    return out, json.loads((out / "report.json").read_text())


def test_report_keys_and_frames(refined):
    out, report = refined
    assert list(report)[: len(REPORT_KEYS)] == list(REPORT_KEYS) and report["accuracy"]
    assert report["frames"] == [
        {"index": 0, "file": "color/000000.png", "used": True, "reason": None},
        {"index": 1, "file": "color/000001.png", "used": True, "reason": None},
        {"index": 2, "file": "color/000002.png", "used": True, "reason": None},
        {"index": 3, "file": "color/000003.png", "used": False,
         "reason": "not picked (the frames option: --frames or RefineOptions.frames)"}]
    assert report["device"] == "cpu" and report["peak_memory_mb"] > 100
    assert set(report["info"]["stage_peak_memory_mb"]) == {"odometry", "solve"}
    summary = report["summary"]
    assert (summary["frames_used"], summary["frames_dropped"], summary["outputs"]) == (3, 1, str(out))
    assert summary["warnings"] == len(report["warnings"])


def test_report_pose_movement_is_that_of_the_saved_poses(refined):
    out, report = refined
    initial, final = np.array(report["info"]["initial_poses"]), np.load(out / "poses.npy")
    assert [row["frame"] for row in report["poses"]] == [1, 2]  # the reference does not move
    for row, T0, T1 in zip(report["poses"], initial[1:], final[1:]):
        centre = lambda T: -T[:3, :3].T @ T[:3, 3]  # noqa: E731
        moved_deg = np.degrees(np.arccos(np.clip((np.trace(T1[:3, :3] @ T0[:3, :3].T) - 1) / 2, -1, 1)))
        assert row["moved_mm"] == pytest.approx(1000 * np.linalg.norm(centre(T1) - centre(T0)), abs=1e-3)
        assert row["moved_deg"] == pytest.approx(moved_deg, abs=1e-4)
    assert np.allclose(final[0], np.eye(4)) and max(r["moved_mm"] for r in report["poses"]) > 0.01


def test_report_energy_falls_and_residuals_per_frame(refined):
    _, report = refined
    for level in report["energy_per_level"]:
        assert level["last"] < level["first"]
    assert [row["level"] for row in report["energy_per_level"]] == [1, 0]
    finest = report["energy_per_level"][-1]
    assert (report["summary"]["energy_first"], report["summary"]["energy_last"]) == (finest["first"], finest["last"])
    assert [r["frame"] for r in report["residuals"]] == [0, 1, 2]
    assert all(0.001 < r["rms"] < 0.2 for r in report["residuals"])  # linear intensity, noise ~0.01


def test_the_python_api_returns_the_report(capture_dir):
    import o3d_mvps

    capture = o3d_mvps.read_capture(capture_dir)
    with pytest.warns(UserWarning, match="no LED offset"):
        capture.metadata.pop("led_offset", None)
        refinement = o3d_mvps.refine(capture, o3d_mvps.RefineOptions(levels=1, max_iterations=1, progress=False))
    report = refinement.report()
    assert list(report) == list(REPORT_KEYS)
    assert any("no LED offset" in w for w in report["warnings"]) and report["summary"]["warnings"] >= 1
    json.dumps(report, allow_nan=False)  # JSON-ready


def test_a_lost_worker_s_view_is_run_again_and_reported():
    from dask.distributed import Client, LocalCluster

    import o3d_mvps
    from o3d_mvps.reconstruct import ReconstructOptions, reconstruct
    from o3d_mvps.synthetic import render_ring

    capture, _ = render_ring("bunny", frames=6, size=(96, 72))
    options = ReconstructOptions(references=2, frames_per_reference=3, voxel_mm=4, texture_px=0, progress=False,
                                 refine=o3d_mvps.RefineOptions(levels=1, max_iterations=2, progress=False))
    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address="127.0.0.1:0") as cluster, \
            Client(cluster) as client:
        pids = client.run(os.getpid)
        killed = []

        def kill_a_busy_worker():
            deadline = time.monotonic() + 60
            while not killed and time.monotonic() < deadline:
                busy = [address for address, keys in client.processing().items() if keys]
                if busy:
                    os.kill(pids[busy[0]], signal.SIGKILL)
                    killed.append(busy[0])
                time.sleep(0.05)

        import threading

        threading.Thread(target=kill_a_busy_worker, daemon=True).start()
        with pytest.warns(UserWarning, match="left the scheduler while views ran"):
            result = reconstruct(capture, options, poses=capture.groundtruth.poses, client=client)
    assert killed and len(result.views) == 2 and not result.failed
    assert killed[0] in result.info["retried"]["lost workers"]


def test_frames_reach_the_workers_by_scatter_not_in_the_graph():
    """Dask warns "Sending large graph" when a task carries its data (8 warnings on a ring under
    --quiet); a view's frames are scattered instead. Control: the same data in the graph warns."""
    import warnings

    from dask.distributed import Client, LocalCluster

    from o3d_mvps.reconstruct.parallel import run_views
    from o3d_mvps.reconstruct.views import ViewJob
    from o3d_mvps.covisibility import ViewSelection

    big = {"color": [np.zeros((1200, 1600, 3), np.float32)] * 2}  # 46 MB, as two 1600 x 1200 frames
    jobs = [ViewJob(k, [k], big, np.eye(4)[None], np.eye(4), ViewSelection([k], {}, {})) for k in range(2)]
    with LocalCluster(n_workers=1, processes=False, dashboard_address="127.0.0.1:0") as cluster, \
            Client(cluster) as client:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            results, failed, _ = run_views(jobs, None, "refined", client, progress=False, timeout=5)
        assert set(failed) == {0, 1} and not results  # the stand-in frames are no capture: each view fails
        assert not [w for w in caught if "large graph" in str(w.message)]
        with warnings.catch_warnings(record=True) as control:
            warnings.simplefilter("always")
            client.submit(len, big, pure=False).result()
        assert [w for w in control if "large graph" in str(w.message)]


def test_the_summary_shows_the_input_checks_and_the_drops():
    from o3d_mvps.run_report import summarise, summary_lines

    report = {"inputs": {"checks": [{"name": "poses", "status": "ok", "detail": ""},
                                    {"name": "intrinsics", "status": "ok", "detail": ""},
                                    {"name": "depth scale", "status": "warning", "detail": "far"}]},
              "frames": [{"index": 0, "used": True}, {"index": 1, "used": False}],
              "energy": [{"level": 0, "iteration": 0, "energy": 2.0}, {"level": 0, "iteration": 3, "energy": 1.5}],
              "timings": {"total": 12.34}, "peak_memory_mb": 820.4, "warnings": ["a", "b"]}
    assert summary_lines(summarise(report, "out")) == [
        "summary: 1 frame used, 1 dropped; energy 2 -> 1.5 (-25.0 %) at the finest level",
        "         input checks: 2 ok, 1 warning (depth scale)",
        "         12.3 s, peak memory 820 MB; 2 warnings (listed in report.json)",
        "         report: out/report.json"]
    assert summary_lines(summarise(report), one_line=True) == [
        "summary: 1 frame used, 1 dropped; energy 2 -> 1.5 (-25.0 %); 12.3 s, peak memory 820 MB; 2 warnings"]
