"""The o3d-mvps command line as a user meets it: outputs checked before any work and named in
command-line wording, --overwrite replacing only what a command writes, --quiet on either side
of the subcommand, Ctrl-C, help texts, and the package's lazy attribute access."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import o3d_mvps.realsense
import o3d_mvps.refinement
import o3d_mvps.synthetic
from o3d_mvps import read_refinement
from o3d_mvps.cli import SUBCOMMANDS, build_parser, main
from o3d_mvps.cli import demo as demo_cli
from o3d_mvps.cli import refine as refine_cli
from o3d_mvps.cli import reconstruct as reconstruct_cli

REPO = Path(__file__).resolve().parents[1]
TINY_SOLVER = ["--levels", "2", "--iterations", "2"]


def users_folder(path: Path) -> Path:
    """A non-empty folder holding a file of the user's."""
    path.mkdir(parents=True, exist_ok=True)
    (path / "notes.txt").write_text("mine")
    return path


def no_work(*args, **kwargs):
    raise AssertionError("the command started its work before checking its output")


# command line, function that would start the work (patched to fail), folder or file to pre-fill
COMMANDS = {
    "refine": (lambda cap, out: ["refine", cap, out], (refine_cli, "refine"), "folder"),
    "reconstruct": (lambda cap, out: ["reconstruct", cap, out], (reconstruct_cli, "reconstruct"), "folder"),
    "demo": (lambda cap, out: ["demo", "--out", out, "--size", "80x60"], (demo_cli, "render_capture"), "folder"),
    "render": (lambda cap, out: ["render", "bunny", out], (o3d_mvps.synthetic, "render_capture"), "folder"),
    "record": (lambda cap, out: ["record", out], (o3d_mvps.realsense, "record_capture"), "folder"),
    "convert": (lambda cap, out: ["convert", "scan.db3", out], (o3d_mvps.realsense, "read_recording"), "folder"),
    "export": (lambda cap, out: ["export", cap, out / "mesh.ply"], (o3d_mvps.refinement, "read_refinement"), "file"),
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_existing_output_is_refused_before_any_work(command, capture_dir, tmp_path, monkeypatch, capsys):
    argv, (module, work), kind = COMMANDS[command]
    monkeypatch.setattr(module, work, no_work)
    out = users_folder(tmp_path / "out")
    if kind == "file":
        (out / "mesh.ply").write_text("an earlier mesh")
    assert main([str(a) for a in argv(capture_dir, out)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"o3d-mvps {command}: error:") and "pass --overwrite" in err
    assert "overwrite=True" not in err  # command-line wording, not the Python keyword
    assert (out / "notes.txt").read_text() == "mine"


def test_every_subcommand_is_checked():
    assert set(COMMANDS) == set(build_parser()._subparsers._group_actions[0].choices)


def test_refine_overwrite_keeps_the_users_files(capture_dir, tmp_path, capsys):
    out = tmp_path / "refined"
    assert main(["--quiet", "refine", str(capture_dir), str(out), *TINY_SOLVER]) == 0
    (out / "notes.txt").write_text("mine")
    (out / "depth.npy").write_bytes(b"stale")
    assert main(["--quiet", "refine", str(capture_dir), str(out), "--overwrite", "--tau", "20", *TINY_SOLVER]) == 0
    assert (out / "notes.txt").read_text() == "mine"
    assert read_refinement(out).depth_array().shape == (60, 80)  # the stale depth.npy was replaced
    assert json.loads((out / "report.json").read_text())["info"]["options"]["model"]["tau"] == 20.0
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folders left


def test_quiet_after_the_subcommand_prints_only_the_result(capture_dir, tmp_path, capsys):
    for i, argv in enumerate([["--quiet", "refine"], ["refine", "--quiet"]]):
        out = tmp_path / f"out{i}"
        assert main([*argv, str(capture_dir), str(out), *TINY_SOLVER]) == 0
        printed = capsys.readouterr()
        assert printed.out == f"wrote {out}\n" and printed.err == ""
    assert main(["refine", str(capture_dir), str(tmp_path / "loud"), *TINY_SOLVER]) == 0
    assert "| ours |" in capsys.readouterr().out  # without --quiet: the accuracy table too


def test_ctrl_c_is_one_line_and_exit_130(monkeypatch, capture_dir, tmp_path, capsys):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(refine_cli, "refine", interrupted)
    assert main(["refine", str(capture_dir), str(tmp_path / "out")]) == 130
    assert capsys.readouterr().err == "o3d-mvps refine: interrupted\n"
    assert "130 (interrupted" in (REPO / "docs" / "cli_intro.md").read_text()  # the CLI reference page


def test_ctrl_c_on_a_running_command(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.Popen([sys.executable, "-u", "-m", "o3d_mvps", "demo", "--out", str(out), "--frames", "40",
                             "--size", "320x240"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    assert proc.stdout.readline().startswith("rendering")  # the work has started
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    assert "Traceback" not in err and err.rstrip().splitlines()[-1].endswith("o3d-mvps demo: interrupted")
    assert list(tmp_path.iterdir()) == []  # nothing written, no temporary folder left


def help_text(command: str, capsys) -> str:
    with pytest.raises(SystemExit) as stop:
        main([command, "--help"])
    assert stop.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("command", SUBCOMMANDS + ["convert"])
def test_help_reads_as_terminal_text_with_examples(command, capsys):
    text = help_text(command, capsys)
    description = text.split("\n\n")[1]
    assert "``" not in text and ":func:" not in text and description[0].isupper(), description
    assert "\nexamples:\n  o3d-mvps " + command in text
    assert "--quiet" in text


def test_demo_seed_has_help(capsys):
    assert "seed of the rendered albedo texture and sensor noise" in " ".join(help_text("demo", capsys).split())


def test_bench_is_python_m_benchmarks(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["bench"])
    assert stop.value.code == 2 and "invalid choice: 'bench'" in capsys.readouterr().err
    readme = (REPO / "README.md").read_text()
    assert "o3d-mvps bench" not in readme and "python -m benchmarks" in readme


def python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)


def test_submodules_after_a_plain_import():
    run = python("import o3d_mvps\n"
                 "capture = o3d_mvps.synthetic.render_capture('bunny', frames=2, size=(32, 24), scale_factor=2, "
                 "progress=False)\n"
                 "print(capture.n_frames, callable(o3d_mvps.realsense.read_recording))")
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["2", "True"]


def test_led_offset_error_names_the_flag_the_user_typed(capture_dir, tmp_path, capsys):
    # millimetres given to --led-offset: the error quotes the flag and its values (not capture.json)
    with pytest.raises(SystemExit) as stop:  # refused by the argument parser, before any work
        main(["refine", str(capture_dir), str(tmp_path / "out"), "--led-offset", "30", "-20", "0", *TINY_SOLVER])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "--led-offset" in err and "30 mm is 0.03 m" in err and "capture.json" not in err
    assert not (tmp_path / "out").exists()


def test_render_makes_ring_captures_for_reconstruct(tmp_path, capsys):
    from o3d_mvps import read_capture
    from o3d_mvps.reconstruct import azimuth_span_deg

    assert main(["render", "bunny", str(tmp_path / "arc"), "--trajectory", "ring", "--arc-deg", "90",
                 "--frames", "4", "--size", "64x48", "--scale-factor", "2"]) == 0
    capture = read_capture(tmp_path / "arc")
    assert capture.n_frames == 4 and (tmp_path / "arc" / "mask").is_dir()
    assert azimuth_span_deg(capture.groundtruth.poses) == pytest.approx(90, abs=0.5)
    assert main(["render", "bunny", str(tmp_path / "x"), "--trajectory", "ring", "--arc-deg", "400"]) == 1
    assert "--arc-deg 400" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["render", "--help"])
    assert "o3d-mvps render bunny captures/ring --trajectory ring" in capsys.readouterr().out


def bump_refinement_folder(path: Path) -> Path:
    """A saved refinement of a 40x30 Gaussian bump (cheap: no solver run)."""
    from o3d_mvps import Refinement

    K = np.array([[50.0, 0, 20], [0, 50.0, 15], [0, 0, 1]])
    v, u = np.mgrid[0:30, 0:40].astype(float)
    depth = 0.6 - 0.05 * np.exp(-((u - 20) ** 2 + (v - 15) ** 2) / 60.0)
    Refinement.from_arrays(depth, np.ones((30, 40), bool), K, albedo=np.full((30, 40, 3), 0.5)).save(path)
    return path


def test_export_print_takes_the_size_as_reconstruct_does_and_size_mm_still_works_with_a_warning(tmp_path, capsys):
    import trimesh

    folder = bump_refinement_folder(tmp_path / "refined")
    extent = lambda name: trimesh.load(tmp_path / name).extents.max()  # noqa: E731

    assert main(["export", str(folder), str(tmp_path / "a.stl"), "--print", "50"]) == 0
    assert extent("a.stl") == pytest.approx(50.0, rel=1e-6)
    assert main(["export", str(folder), str(tmp_path / "b.stl")]) == 0  # .stl alone: the default size
    assert extent("b.stl") == pytest.approx(120.0, rel=1e-6)
    assert main(["export", str(folder), str(tmp_path / "c.ply"), "--print", "40"]) == 0  # a solid as .ply too
    assert trimesh.load(tmp_path / "c.ply").is_volume and extent("c.ply") == pytest.approx(40.0, rel=1e-6)
    assert main(["export", str(folder), str(tmp_path / "d.ply")]) == 0  # no --print: the open relief
    assert not trimesh.load(tmp_path / "d.ply").is_volume
    capsys.readouterr()

    assert main(["export", str(folder), str(tmp_path / "e.stl"), "--size-mm", "70"]) == 0  # the old spelling
    assert "--size-mm is deprecated; use --print MM (e.g. --print 70.0)" in capsys.readouterr().err
    assert extent("e.stl") == pytest.approx(70.0, rel=1e-6)
    assert main(["export", str(folder), str(tmp_path / "f.stl"), "--print", "50", "--size-mm", "70"]) == 1
    err = capsys.readouterr().err
    assert "--print 50 and --size-mm 70 disagree" in err and not (tmp_path / "f.stl").exists()


@pytest.mark.parametrize("command, meaning", [("render", "number of frames to render"),
                                              ("demo", "number of frames to render"),
                                              ("record", "number of frames to record"),
                                              ("convert", "number of frames to keep"),
                                              ("refine", "number of frames to use: the first N"),
                                              ("reconstruct", "number of frames to use: the first N")])
def test_frames_is_a_number_of_frames_everywhere_and_the_help_says_which(command, meaning, capsys):
    text = " ".join(help_text(command, capsys).split())
    assert f"--frames N {meaning}" in text, text


def test_pipelines_use_the_same_vocabulary(capsys):
    sys.path.insert(0, str(REPO / "pipelines"))
    try:
        import print_scan
        import record_and_refine
    finally:
        sys.path.remove(str(REPO / "pipelines"))
    parser = print_scan.build_parser()
    assert parser.parse_args(["cap", "s.stl", "--print", "80"]).size_mm == 80.0
    assert parser.parse_args(["cap", "s.stl"]).size_mm == 120.0
    assert parser.parse_args(["cap", "s.stl", "--size-mm", "60"]).size_mm == 60.0
    assert "print_scan.py: warning: --size-mm is deprecated; use --print MM" in capsys.readouterr().err
    args = record_and_refine.build_parser().parse_args(["out", "--record-frames", "30", "--frames", "10"])
    assert (args.record_frames, args.frames) == (30, 10)  # recorded, then the first 10 refined


def test_refine_frees_the_frames_it_no_longer_reads(capture_dir, tmp_path, monkeypatch):
    """`o3d-mvps refine` hands the capture over to refine(): when the solve starts, the capture's
    depth images and masks are freed (the solver's input holds its own), its colour frames only
    by the solver's views of them; once refine returns, the colour frames of every frame but the
    reference are freed (the accuracy table and report page read frame 0 and the ground truth)."""
    import gc
    import weakref

    import o3d_mvps.solving
    from o3d_mvps.capture import read_capture

    held = {}

    def reading(*args, **kwargs):
        capture = read_capture(*args, **kwargs)
        held.update(color=[weakref.ref(c) for c in capture.color], depth=[weakref.ref(d) for d in capture.depth],
                    masks=[weakref.ref(m) for m in capture.masks], n=capture.n_frames,
                    truth=[weakref.ref(capture.groundtruth.normals)])
        assert capture.groundtruth is not None
        return capture

    def alive(name):
        gc.collect()
        return [i for i, ref in enumerate(held[name]) if ref() is not None]

    solve, at_solve = o3d_mvps.solving.solve, {}

    def solving(problem_input, *args, **kwargs):
        at_solve.update(depth=alive("depth"), masks=alive("masks"), color=alive("color"), truth=alive("truth"))
        held["views"] = [weakref.ref(c) for c in problem_input.colors]  # the solver's views of the colour frames
        return solve(problem_input, *args, **kwargs)

    after = {}
    log_energy = refine_cli.log_energy

    def logged(refinement, quiet):
        after.update(color=alive("color"), depth=alive("depth"), views=alive("views"))
        return log_energy(refinement, quiet)

    monkeypatch.setattr(refine_cli, "read_capture", reading)
    monkeypatch.setattr(o3d_mvps.solving, "solve", solving)
    monkeypatch.setattr(refine_cli, "log_energy", logged)
    assert main(["--quiet", "refine", str(capture_dir), str(tmp_path / "out"), *TINY_SOLVER]) == 0
    assert held["n"] > 1
    # at the solve, only the reference frame's images (kept for after it) are still referenced
    assert at_solve == {"depth": [0], "masks": [0], "color": [0], "truth": []}  # the ground truth is read again after
    assert after == {"color": [0], "depth": [0], "views": []}
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["info"]["capture_frames"] == held["n"]
    # the ground truth read again after the solve: the accuracy table of every method
    assert [row["method"] for row in report["accuracy"]] == ["bicubic", "guided", "ours"]
