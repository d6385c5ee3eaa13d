"""Wall time and peak memory of the full pipeline (odometry + refine) at given resolutions.

The solver's kernels are compiled once first (:func:`warm_up`). Each case is rendered and
written as a capture folder, then run in a fresh subprocess that
reads it, runs ``refine`` (Open3D odometry included) and reports its own peak resident set
size (``getrusage(RUSAGE_SELF).ru_maxrss``, which covers numpy, SciPy and Open3D allocations
that tracemalloc misses). Rows of ``speed.json``: {"color": "WxH", "depth": "wxh", "frames",
"seconds", "cpu_seconds", "peak_mb", "breakdown"} (breakdown: ``Refinement.timings``;
cpu_seconds includes the worker's imports and capture reading).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from o3d_mvps.fileio import json_text

from .accuracy import QUICK_FRAMES, QUICK_OPTIONS, QUICK_SIZE, parse_size

#: (colour size, scale factor): the 640 x 480 benchmark size and the D415's 1280 x 720 colour with
#: 640 x 360 depth.
CASES = (((640, 480), 4), ((1280, 720), 2))


def add_arguments(parser) -> None:
    """Options of the speed benchmark."""
    parser.add_argument("--cases", nargs="+", default=[f"{w}x{h}:{sf}" for (w, h), sf in CASES],
                        help="colour size and scale factor, e.g. 1280x720:2")
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--mesh", default="bunny")


def measure(capture_folder: str, options: dict) -> dict:
    """Run the pipeline on a capture folder in this process: seconds, peak MB, timings."""
    from o3d_mvps import RefineOptions, refine
    from o3d_mvps.capture import read_capture

    t = time.perf_counter()
    capture = read_capture(capture_folder)
    result = refine(capture, RefineOptions(progress=False, **options))
    seconds = time.perf_counter() - t
    usage = resource.getrusage(resource.RUSAGE_SELF)
    # cpu_seconds (user + system, this process) is what the wall time would be without other load
    finest = [row for row in result.energy if row["level"] == 0 and row["iteration"] > 0]
    return {"seconds": seconds, "cpu_seconds": usage.ru_utime + usage.ru_stime, "peak_mb": usage.ru_maxrss / 1024.0,
            "breakdown": result.timings,
            "sweeps": len([row for row in result.energy if row["iteration"] > 0]),
            "finest_cg_iterations": [row.get("cg_iterations") for row in finest]}


def warm_up(trees) -> None:
    """Run the worker of the package in each tree (folders) once on a tiny capture, untimed: the
    first run compiles the solver's kernels into numba's on-disk cache, which later runs load
    (a one-off of 10-20 s that would otherwise land on the first timed case)."""
    from o3d_mvps.capture import write_capture
    from o3d_mvps.synthetic import render_capture

    capture = render_capture("bunny", frames=3, scale_factor=2, size=(160, 120), seed=0)
    with tempfile.TemporaryDirectory(prefix="o3d_mvps_warm_up_") as tmp:
        folder = Path(tmp) / "capture"
        write_capture(capture, folder)
        for tree in trees:
            command = [sys.executable, "-m", "benchmarks.speed", "--worker", str(folder), "--options",
                       json.dumps({"max_iterations": 2, "joint_min_pixels": 0, "pose_min_pixels": 0})]
            subprocess.run(command, capture_output=True, text=True, check=False, cwd=tree,
                           env={**os.environ, "PYTHONPATH": str(tree)})


def run_case(mesh: str, size: tuple[int, int], sf: int, frames: int, options: dict) -> dict:
    """Render one capture, then time the pipeline on it in a fresh Python process."""
    from o3d_mvps.capture import write_capture
    from o3d_mvps.synthetic import render_capture

    capture = render_capture(mesh, frames=frames, scale_factor=sf, size=size, seed=0)
    with tempfile.TemporaryDirectory(prefix="o3d_mvps_speed_") as tmp:
        folder = Path(tmp) / "capture"
        write_capture(capture, folder)
        del capture
        command = [sys.executable, "-m", "benchmarks.speed", "--worker", str(folder), "--options", json.dumps(options)]
        done = subprocess.run(command, capture_output=True, text=True, check=False,
                              cwd=Path(__file__).resolve().parent.parent)
    if done.returncode != 0:
        raise RuntimeError(f"speed worker failed ({done.returncode}):\n{done.stderr[-2000:]}")
    measured = json.loads(done.stdout.strip().splitlines()[-1])
    w, h = size
    return {"mesh": mesh, "color": f"{w}x{h}", "depth": f"{w // sf}x{h // sf}", "frames": frames, **measured}


def run(args) -> list[dict]:
    """Run every case one after the other; writes ``speed.json`` into ``args.out`` after each."""
    cases = [(parse_size(c.split(":")[0]), int(c.split(":")[1])) for c in args.cases]
    frames, options = args.frames, {}
    if args.quick:
        cases, frames, options = [(QUICK_SIZE, 4)], QUICK_FRAMES, QUICK_OPTIONS
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    warm_up([Path(__file__).resolve().parent.parent])
    for size, sf in cases:
        row = run_case(args.mesh, size, sf, frames, options)
        rows.append(row)
        print(f"speed: {row['color']} / {row['depth']}, {frames} frames: {row['seconds']:.1f} s, "
              f"peak {row['peak_mb']:.0f} MB", flush=True)
        (out / "speed.json").write_text(json_text(rows, "speed rows"))
    return rows


def _worker(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.speed")
    parser.add_argument("--worker", required=True, help="capture folder to time (internal)")
    parser.add_argument("--options", default="{}", help="RefineOptions as JSON")
    args = parser.parse_args(argv)
    print(json.dumps(measure(args.worker, json.loads(args.options))))
    return 0


if __name__ == "__main__":
    raise SystemExit(_worker())
