"""Wall time and peak memory of the full pipeline (odometry + refine) at given resolutions.

The solver's kernels are compiled once first (:func:`warm_up`). Each case is rendered and
written as a capture folder, then run in a fresh subprocess that
reads it, runs ``refine`` (Open3D odometry included) and reports its own peak resident set
size (:func:`peak_rss_mb`, which covers numpy, SciPy and Open3D allocations that tracemalloc
misses). Rows of ``speed.json``: {"color": "WxH", "depth": "wxh", "frames",
"distance", "object_pixels", "seconds", "cpu_seconds", "peak_mb", "breakdown", "sweeps",
"finest_cg_iterations"} (breakdown: ``Refinement.timings``; cpu_seconds includes the worker's
imports and capture reading).
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

import numpy as np

from o3d_mvps.fileio import json_text

from .accuracy import QUICK_FRAMES, QUICK_OPTIONS, QUICK_SIZE, parse_size

#: (colour size, scale factor, distance of the bunny in m): the 640 x 480 benchmark size, the
#: D415's 1280 x 720 colour with 640 x 360 depth, and a 2-megapixel frame (a phone's or DSLR's,
#: turned to fit the bunny) that the object fills by half: about 1M object pixels.
CASES = (((640, 480), 4, 0.6), ((1280, 720), 2, 0.6), ((1708, 1136), 4, 0.25))


def add_arguments(parser) -> None:
    """Options of the speed benchmark."""
    parser.add_argument("--cases", nargs="+", default=[f"{w}x{h}:{sf}:{d}" for (w, h), sf, d in CASES],
                        help="colour size, scale factor and (optional) the object's distance in m, e.g. 1280x720:2 "
                             "or 1708x1136:4:0.25")
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--mesh", default="bunny")


def peak_rss_mb() -> float:
    """This process's peak resident set size in MiB: ``VmHWM`` of ``/proc/self/status``, the
    high-water mark of this program's own memory. (Linux's ``getrusage`` ``ru_maxrss`` also
    counts the parent's size at the fork that started this process: a worker started by a
    benchmark that had rendered a 2-megapixel capture reported the parent's gigabytes.) Falls
    back to ``ru_maxrss`` where /proc is missing (macOS: bytes there, not KiB)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024.0


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
    return {"seconds": seconds, "cpu_seconds": usage.ru_utime + usage.ru_stime, "peak_mb": peak_rss_mb(),
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


def run_case(mesh: str, size: tuple[int, int], sf: int, frames: int, options: dict, distance: float = 0.6) -> dict:
    """Render one capture (the object ``distance`` m from the reference camera), then time the
    pipeline on it in a fresh Python process."""
    from o3d_mvps.capture import write_capture
    from o3d_mvps.synthetic import render_capture

    capture = render_capture(mesh, frames=frames, scale_factor=sf, size=size, seed=0, distance=distance)
    object_pixels = int(np.count_nonzero(capture.mask_array(0)))
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
    return {"mesh": mesh, "color": f"{w}x{h}", "depth": f"{w // sf}x{h // sf}", "frames": frames,
            "distance": distance, "object_pixels": object_pixels, **measured}


def parse_case(text: str) -> tuple[tuple[int, int], int, float]:
    """'WxH:SF' or 'WxH:SF:DISTANCE' -> ((W, H), SF, distance in m; 0.6 when not given)."""
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise ValueError(f"speed case {text!r}: give WxH:SF or WxH:SF:DISTANCE, e.g. 1280x720:2 or 1708x1136:4:0.25")
    return parse_size(parts[0]), int(parts[1]), float(parts[2]) if len(parts) == 3 else 0.6


def run(args) -> list[dict]:
    """Run every case one after the other; writes ``speed.json`` into ``args.out`` after each."""
    cases = [parse_case(c) for c in args.cases]
    frames, options = args.frames, {}
    if args.quick:
        cases, frames, options = [(QUICK_SIZE, 4, 0.6)], QUICK_FRAMES, QUICK_OPTIONS
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    warm_up([Path(__file__).resolve().parent.parent])
    for size, sf, distance in cases:
        row = run_case(args.mesh, size, sf, frames, options, distance)
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
