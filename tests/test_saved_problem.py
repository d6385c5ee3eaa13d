"""The solver apart from Open3D: saved problems (refine --save-problem, python -m o3d_mvps.solver),
their file format and its errors, the solver and model importing and solving with Open3D
unimportable, and the device check (cpu runs; cuda says what is missing)."""

import json
import os
import subprocess
import sys
import types
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from o3d_mvps import RefineOptions, read_refinement, refine
from o3d_mvps.capture import write_capture
from o3d_mvps.cli import main
from o3d_mvps.colour import CodedColours, codes_to_linear
from o3d_mvps.cli import refine as refine_cli
from o3d_mvps.errors import DeviceError, MVPSError, OutputExistsError
from o3d_mvps.solver import __main__ as solver_main
from o3d_mvps.solver.device import check_device
from o3d_mvps.solver.driver import solve
from o3d_mvps.solver.problem_input import SolverInput, read_problem, write_problem
from o3d_mvps.synthetic import render_capture

REPO = Path(__file__).resolve().parents[1]
TINY_SOLVER = ["--levels", "2", "--iterations", "2"]


@pytest.fixture
def capture(tiny_capture):
    return tiny_capture  # conftest.py's, shared by the session (capture_dir is it as a folder)


@pytest.fixture
def without_open3d(tmp_path) -> dict:
    """Environment for a subprocess in which ``import open3d`` fails (a stand-in package first on
    the path raises ImportError), as on a machine without Open3D."""
    blocker = tmp_path / "no_open3d" / "open3d"
    blocker.mkdir(parents=True)
    (blocker / "__init__.py").write_text("raise ImportError('open3d is not installed here')\n")
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(blocker.parent), str(REPO)])}


def test_model_and_solver_import_without_open3d(tmp_path, without_open3d):
    """Every module of o3d_mvps.model and o3d_mvps.solver imports where Open3D cannot."""
    code = ("import pkgutil, importlib, o3d_mvps.model, o3d_mvps.solver\n"
            "names = [m.name for p in (o3d_mvps.model, o3d_mvps.solver)\n"
            "         for m in pkgutil.iter_modules(p.__path__, p.__name__ + '.')]\n"
            "[importlib.import_module(n) for n in names]\n"
            "print(len(names))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                         env=without_open3d, timeout=120)
    assert run.returncode == 0, run.stderr
    assert int(run.stdout) >= 20  # model's 8 modules and the solver's, __main__ included
    blocked = subprocess.run([sys.executable, "-c", "import o3d_mvps.capture"], capture_output=True, text=True,
                             cwd=tmp_path, env=without_open3d, timeout=120)
    assert "open3d is not installed here" in blocked.stderr  # the blocker does block


#: The test files a GPU machine runs (docs/gpu.md): they must import where Open3D cannot.
GPU_TEST_FILES = ("test_cuda_kernels.py", "test_cuda_path.py", "test_gpu_evaluation.py", "test_gpu_counts.py",
                  "test_cupy_emulation.py")


def test_gpu_test_files_collect_without_open3d(tmp_path, without_open3d):
    """The GPU's test files collect on a machine without Open3D (GPU images rarely have its 0.9 GB):
    a helper that imports Open3D (tests/helpers.py) once kept test_cuda_kernels.py from loading."""
    files = [str(REPO / "tests" / name) for name in GPU_TEST_FILES]
    run = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                          "-p", "no:dash", *files], capture_output=True, text=True, cwd=REPO, env=without_open3d,
                         timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert " error" not in run.stdout.splitlines()[-1], run.stdout[-3000:]


def test_saved_problem_solves_to_refines_depth_without_open3d(capture_dir, tmp_path, without_open3d):
    """`refine --save-problem` then `python -m o3d_mvps.solver` (Open3D unimportable) gives the
    refinement's depth, poses and lighting bit for bit (same code, same deterministic AMG set-up)."""
    problem, out = tmp_path / "problem.npz", tmp_path / "refined"
    assert main(["--quiet", "refine", str(capture_dir), str(out), "--save-problem", str(problem),
                 *TINY_SOLVER]) == 0
    run = subprocess.run([sys.executable, "-m", "o3d_mvps.solver", str(problem), str(tmp_path / "solution.npz"),
                          "--quiet"], capture_output=True, text=True, cwd=tmp_path, env=without_open3d,
                         timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == f"wrote {tmp_path / 'solution.npz'}"
    refined = read_refinement(out)
    with np.load(tmp_path / "solution.npz", allow_pickle=False) as solution:
        np.testing.assert_array_equal(solution["depth"].astype(np.float32), refined.depth_array())
        np.testing.assert_array_equal(solution["poses"], refined.poses.numpy())
        np.testing.assert_array_equal(solution["lighting"], refined.lighting.numpy())
        np.testing.assert_array_equal(solution["K"], refined.intrinsic_matrix())
        report = json.loads(str(solution["report"]))
        np.testing.assert_array_equal(solution["energy"][:, 2], [row["energy"] for row in refined.energy])
    assert report["energy"] == refined.energy
    assert report["info"]["frames"] == refined.info["frames"] == [0, 1, 2]


def test_problem_round_trip(capture, tmp_path):
    """write_problem -> read_problem: every array equal, a frame without mask stays without, options
    and the measured depth noise equal."""
    rng = np.random.default_rng(0)
    n, H, W, sf = 3, 12, 16, 2
    poses = np.stack([np.eye(4)] * n)
    poses[1:, :3, 3] = rng.normal(0, 0.01, (n - 1, 3))
    options = RefineOptions(tau=20, levels=3, light_model="sh", led_offset=(0.03, -0.02, 0.0), frames=[0, 2, 4],
                            refine_poses=False, progress=False)
    problem = SolverInput(colors=rng.random((n, H, W, 3)), depths=rng.uniform(0.4, 0.6, (n, H // sf, W // sf)),
                          masks=[rng.random((H, W)) > 0.5, None, np.ones((H, W), bool)], K=capture.color_K(),
                          depth_K=capture.depth_K(), scale_factor=sf, initial_poses=poses,
                          led_offset=[0.03, -0.02, 0.0], frames=[0, 2, 4], options=options, depth_noise=0.0123)
    back = read_problem(write_problem(problem, tmp_path / "p.npz"))
    assert back.depth_noise == 0.0123  # what the frames' mean depth is judged by
    assert read_problem(write_problem(replace(problem, depth_noise=None), tmp_path / "q.npz")).depth_noise is None
    with pytest.raises(ValueError, match="depth_noise must be a finite s"):
        replace(problem, depth_noise=float("nan"))
    for name in ("colors", "depths", "K", "depth_K", "initial_poses", "led_offset"):
        np.testing.assert_array_equal(getattr(back, name), getattr(problem, name), err_msg=name)
        assert getattr(back, name).dtype == getattr(problem, name).dtype
    assert back.masks[1] is None
    np.testing.assert_array_equal(back.masks[0], problem.masks[0])
    np.testing.assert_array_equal(back.masks[2], problem.masks[2])
    assert (back.scale_factor, back.frames, back.options) == (sf, [0, 2, 4], options)
    with pytest.raises(OutputExistsError, match="overwrite=True"):
        write_problem(problem, tmp_path / "p.npz")
    with pytest.raises(ValueError, match=r"depths has shape \(3, 5, 8\), not \(3, 6, 8\)"):
        replace(problem, depths=problem.depths[:, :5])
    # colours as a list of frames (a capture's own): float32 frames kept, not copied; saved the same
    frames = [np.ascontiguousarray(c, dtype=np.float32) for c in problem.colors]
    listed = replace(problem, colors=frames)
    assert all(a is b for a, b in zip(listed.colors, frames)) and listed.color_size == (H, W)
    again = read_problem(write_problem(listed, tmp_path / "listed.npz"))
    np.testing.assert_array_equal(again.colors, problem.colors)
    with pytest.raises(ValueError, match=r"colors\[1\] has shape \(12, 15, 3\), not \(12, 16, 3\)"):
        replace(problem, colors=[frames[0], frames[1][:, :15], frames[2]])
    # coded frames (read from files): kept coded, sized without decoding, saved as codes and tables
    codes = [rng.integers(0, 256, (H, W, 3)).astype(np.uint8) for _ in range(n)]
    coded = replace(problem, colors=CodedColours.from_codes(codes).divided(rng.uniform(0.8, 1.2, (n, 3))))
    assert isinstance(coded.colors, CodedColours) and coded.colors.codes[2] is codes[2] and coded.color_size == (H, W)
    saved = read_problem(write_problem(coded, tmp_path / "coded.npz"))
    assert isinstance(saved.colors, CodedColours)
    np.testing.assert_array_equal(np.stack(saved.colors.codes), np.stack(codes))
    np.testing.assert_array_equal(saved.colors.tables, coded.colors.tables)  # white balance folded in
    np.testing.assert_array_equal(np.stack(list(saved.colors)), np.stack(list(coded.colors)))
    np.testing.assert_array_equal(CodedColours.from_codes(codes)[1], codes_to_linear(codes[1]))
    decoded = read_problem(write_problem(replace(coded, colors=coded.float_colors()), tmp_path / "decoded.npz"))
    np.testing.assert_array_equal(decoded.colors, np.stack(list(coded.colors)))
    with zipfile.ZipFile(tmp_path / "coded.npz") as z:  # the codes stored as uint8: a quarter of float32's bytes
        assert z.getinfo("colors.npy").file_size < 0.3 * zipfile.ZipFile(tmp_path / "decoded.npz").getinfo(
            "colors.npy").file_size
    with pytest.raises(ValueError, match=r"colors\[1\] has shape \(12, 15, 3\), not \(12, 16, 3\)"):
        replace(problem, colors=CodedColours.from_codes([codes[0], codes[1][:, :15], codes[2]]))


def saved_problem(capture, path: Path) -> Path:
    refine(capture, RefineOptions(progress=False, levels=1, max_iterations=1), save_problem=path,
           initial_poses=capture.groundtruth.poses)
    return path


def test_unreadable_problem_files_name_the_file_and_the_fix(capture, tmp_path):
    good = saved_problem(capture, tmp_path / "good.npz")
    with pytest.raises(OutputExistsError, match="overwrite=True"):  # before any work
        refine(capture, save_problem=good)
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    np.savez(tmp_path / "foreign.npz", depth=np.zeros(3))
    with np.load(good) as npz:
        arrays = dict(npz)
    np.savez(tmp_path / "newer.npz", **{**arrays, "format_version": np.array(3)})
    np.savez(tmp_path / "truncated.npz", **{k: v for k, v in arrays.items() if k != "depths"})
    expected = {"missing.npz": "no such file", "junk.npz": "is not a saved o3d_mvps problem",
                "foreign.npz": "is an .npz but not a saved o3d_mvps problem",
                "newer.npz": r"format version 3, newer than this o3d_mvps reads \(2\); upgrade",
                "truncated.npz": "lacks the array 'depths'; the file is damaged: write it again"}
    for name, problem in expected.items():
        with pytest.raises(MVPSError, match=problem) as error:
            read_problem(tmp_path / name)
        assert str(tmp_path / name) in str(error.value)
        assert "--save-problem" in str(error.value) or "pip install -U o3d-mvps" in str(error.value)
    with zipfile.ZipFile(good) as z:
        assert {"format.npy", "format_version.npy", "options.npy", "has_mask.npy"} <= set(z.namelist())


def test_existing_problem_file_is_refused_before_any_work(capture_dir, tmp_path, monkeypatch, capsys):
    (tmp_path / "problem.npz").write_text("the user's file")
    monkeypatch.setattr(refine_cli, "read_capture", lambda *a, **k: pytest.fail("read the capture first"))
    assert main(["refine", str(capture_dir), str(tmp_path / "out"), "--save-problem",
                 str(tmp_path / "problem.npz")]) == 1
    assert "pass --overwrite" in capsys.readouterr().err
    assert (tmp_path / "problem.npz").read_text() == "the user's file"


def test_python_m_solver_errors_are_one_line(capture, tmp_path, capsys):
    good = saved_problem(capture, tmp_path / "good.npz")
    (tmp_path / "out.npz").write_text("an earlier solution")
    assert solver_main.main([str(good), str(tmp_path / "out.npz")]) == 1
    assert "pass --overwrite" in capsys.readouterr().err
    assert (tmp_path / "out.npz").read_text() == "an earlier solution"
    assert solver_main.main([str(tmp_path / "missing.npz"), str(tmp_path / "new.npz")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("python -m o3d_mvps.solver: error:") and "no such file" in err
    assert not (tmp_path / "new.npz").exists()


# --- devices -----------------------------------------------------------------------------------


def fake_cupy(count=None):
    """A stand-in ``cupy`` module whose runtime sees ``count`` GPUs (None: no CUDA driver)."""
    def device_count():
        if count is None:
            raise RuntimeError("cudaErrorNoDevice: no CUDA-capable device is detected")
        return count

    runtime = types.SimpleNamespace(getDeviceCount=device_count)
    return types.SimpleNamespace(cuda=types.SimpleNamespace(runtime=runtime))


def test_cpu_device_names():
    for name in ("cpu", "CPU:0", "cpu:0", o3d.core.Device("CPU:0")):
        assert check_device(name) == "cpu"
    for name in ("gpu", "cpu:1", "cuda:x", ""):
        with pytest.raises(ValueError, match="is not a device name; pass 'auto', 'cpu'"):
            check_device(name)


@pytest.mark.parametrize("cupy, device, message", [
    (None, "cuda", r"needs CuPy, which is not installed: pip install o3d-mvps\[cuda\] \(CuPy and numba-cuda for "
                   r"CUDA 12; for CUDA 13: pip install o3d-mvps\[cuda13\]\)"),
    (fake_cupy(None), "CUDA:0", "CuPy sees no GPU; check the NVIDIA driver"),
    (fake_cupy(1), "cuda:1", r"CuPy sees 1 GPU\(s\), cuda:0 to cuda:0; .* or solve on the CPU instead"),
    (fake_cupy(1), "cuda:0", r"needs numba's CUDA target \(numba-cuda\), which is not installed: pip install "
                             r"o3d-mvps\[cuda\] .*; or solve on the CPU instead \(device='cpu', --device cpu\)"),
])
def test_cuda_device_says_what_is_missing(monkeypatch, cupy, device, message):
    monkeypatch.setitem(sys.modules, "cupy", cupy)
    monkeypatch.setitem(sys.modules, "numba.cuda", None)  # where CuPy sees a GPU: numba-cuda missing
    with pytest.raises(DeviceError, match=message):
        check_device(device)


def test_cuda_device_is_refused_before_any_work(monkeypatch, capture, capture_dir, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "cupy", None)
    monkeypatch.setattr(refine_cli, "read_capture", lambda *a, **k: pytest.fail("read the capture first"))
    assert main(["refine", str(capture_dir), str(tmp_path / "out"), "--device", "cuda:0"]) == 1
    assert "pip install o3d-mvps[cuda]" in capsys.readouterr().err
    monkeypatch.setattr("o3d_mvps.solving.problem_from_capture", lambda *a: pytest.fail("registered first"))
    with pytest.raises(DeviceError, match="'CUDA:0' needs CuPy"):
        refine(capture, device="CUDA:0")
    assert solver_main.main([str(tmp_path / "missing.npz"), str(tmp_path / "s.npz"), "--device", "cuda"]) == 1
    assert "pip install o3d-mvps[cuda]" in capsys.readouterr().err  # the device before the problem file


@pytest.mark.parametrize("mode", ["initial", "finest"])
def test_a_saved_problem_averages_the_frames_depth_as_refine_did(tmp_path, mode):
    """The frames' mean depth is judged by the depth noise that the frames' disagreement gave; the
    saved problem carries it (``depth_noise``), so that its solve averages as ``refine`` did:
    the same depth bit for bit, and the averaged pixels counted alike. Without it ("initial" and
    "finest" both need it) the solve ties the depth to frame 0 alone, and says so."""
    capture = render_capture("bunny", frames=5, scale_factor=2, size=(160, 120), seed=2, progress=False)
    folder, problem, out = tmp_path / "capture", tmp_path / "problem.npz", tmp_path / "refined"
    write_capture(capture, folder)
    assert main(["--quiet", "refine", str(folder), str(out), "--save-problem", str(problem), "--levels", "2",
                 "--iterations", "4", "--average-frames-depth", mode]) == 0
    saved = read_problem(problem)
    assert saved.depth_noise is not None and saved.depth_noise > 0
    refined = read_refinement(out)
    solved = solve(saved)
    np.testing.assert_array_equal(solved.depth.astype(np.float32), refined.depth_array())
    if mode == "initial":
        assert saved.report["reference_depth_outliers"]["averaged"] == \
            refined.info["reference_depth_outliers"]["averaged"] > 0
    else:
        assert solved.info["frames_depth"] == refined.info["frames_depth"]
        assert solved.info["frames_depth"]["averaged"] > 0
    with pytest.warns(UserWarning, match=f"average_frames_depth='{mode}' needs .* noise not measured"):
        without = solve(replace(read_problem(problem), depth_noise=None))  # as a file saved without it
    assert not np.array_equal(without.depth, solved.depth)
