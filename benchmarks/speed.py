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
import contextlib
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
from .registration_worker import peak_rss_mb  # noqa: F401  (the workers' peak memory, re-exported)

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
    parser.add_argument("--registration", action="store_true",
                        help="time the frame registration only (registration.json), on each case's object orbit "
                             "and on a room scene (a 360-degree ring under room light, automatic masks)")
    parser.add_argument("--baseline", default=None, metavar="REV",
                        help="with --registration: also run this git revision (e.g. aacda76) on the same captures, "
                             "in the same run")
    parser.add_argument("--memory-curve", nargs="+", type=int, default=None, metavar="FRAMES",
                        help="peak memory of odometry + refine against frames (these counts) x colour pixels (the "
                             "--cases sizes), one solver sweep per level: memory_curve.json and memory_curve.png")
    parser.add_argument("--captures", default=None, metavar="DIR",
                        help="with --registration: keep the rendered captures here and reuse them on the next run")


def measure(capture_folder: str, options: dict) -> dict:
    """Run the pipeline on a capture folder in this process: seconds, peak MB, timings."""
    from o3d_mvps import RefineOptions, refine
    from o3d_mvps.capture import read_capture

    t = time.perf_counter()
    # handed over as the command line does: refine lets go of it once the solver's input is made
    result = refine(read_capture(capture_folder), RefineOptions(progress=False, **options))
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
    if args.registration:
        return run_registration(args)
    if args.memory_curve:
        return run_memory_curve(args)
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


def registration_captures(cases, frames: int, mesh: str, folder: Path,
                          kinds=("orbit", "scene")) -> list[tuple[str, Path]]:
    """(name, capture folder) of each case's LED orbit (the object ``distance`` m away) and room
    scene (:func:`o3d_mvps.synthetic.render_ring` with surroundings; its ring needs about 20
    frames to be registrable), rendered into ``folder`` unless already there."""
    from o3d_mvps.capture import write_capture
    from o3d_mvps.synthetic import render_capture, render_ring

    out = []
    for (w, h), sf, distance in cases:
        for kind in kinds:
            name = f"{kind}_{w}x{h}_sf{sf}" + (f"_{distance:g}m" if kind == "orbit" else "") + f"_{frames}"
            target = folder / name
            if not (target / "groundtruth" / "poses.npy").exists():
                common = dict(frames=frames, scale_factor=sf, size=(w, h), seed=0, progress=False)
                capture = render_capture(mesh, distance=distance, **common) if kind == "orbit" else \
                    render_ring(mesh, surroundings=True, light="room", **common)[0]
                write_capture(capture, target, overwrite=True)
                del capture
            out.append((name, target))
    return out


def register_capture(folder: Path, tree: Path) -> dict:
    """Run :mod:`benchmarks.registration_worker` with the package of ``tree`` in a fresh process."""
    worker = Path(__file__).resolve().parent / "registration_worker.py"
    done = subprocess.run([sys.executable, str(worker), str(tree), str(folder)], capture_output=True, text=True,
                          check=False, cwd=tree)
    if done.returncode != 0:
        raise RuntimeError(f"registration worker failed in {tree} ({done.returncode}):\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def run_registration(args) -> list[dict]:
    """Registration A/B: every capture of :func:`registration_captures` registered by this tree and
    (``--baseline``) by that revision, one after the other in the same run; ``registration.json``
    rows {"capture", "version", "seconds", "cpu_seconds", "peak_mb", "frames", "dropped", "deg",
    "mm", and for this tree "ratio_seconds" / "ratio_cpu" = baseline / this}."""
    from .scaling import checkout

    cases, frames, kinds = [parse_case(c) for c in args.cases], args.frames, ("orbit", "scene")
    if args.quick:  # tests/test_odometry.py's capture
        cases, frames, kinds = [((320, 240), 4, 0.6)], 8, ("orbit",)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    with contextlib.ExitStack() as stack:
        folder = Path(args.captures) if args.captures else Path(stack.enter_context(tempfile.TemporaryDirectory()))
        captures = registration_captures(cases, frames, args.mesh, folder, kinds)
        trees = {"current": Path(__file__).resolve().parent.parent}
        if args.baseline:
            trees[args.baseline] = stack.enter_context(checkout(args.baseline))
        for name, capture in captures:
            measured = {version: register_capture(capture, tree) for version, tree in trees.items()}
            for version, row in measured.items():
                if version == "current" and args.baseline:
                    base = measured[args.baseline]
                    row["ratio_seconds"] = base["seconds"] / row["seconds"]
                    row["ratio_cpu"] = base["cpu_seconds"] / row["cpu_seconds"]
                rows.append({"capture": name, "version": version, **row})
                print(f"registration {name} [{version}]: {row['seconds']:.2f} s ({row['cpu_seconds']:.2f} s CPU), "
                      f"peak {row['peak_mb']:.0f} MB, max {max(row['deg'], default=0):.2f} deg", flush=True)
            (out / "registration.json").write_text(json_text(rows, "registration rows"))
    registration_plot(rows, out / "registration.png")
    return rows


def registration_plot(rows: list[dict], path: Path) -> None:
    """Bars of each capture's registration CPU seconds per version (matplotlib, PNG), labelled
    with the baseline / current ratio where the rows have one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    captures = list(dict.fromkeys(r["capture"] for r in rows))
    versions = list(dict.fromkeys(r["version"] for r in rows))
    seconds = {(r["capture"], r["version"]): r["cpu_seconds"] for r in rows}
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / len(versions)
    for k, version in enumerate(versions):
        x = np.arange(len(captures)) + k * width
        ax.bar(x, [seconds.get((c, version), np.nan) for c in captures], width, label=version)
    for j, c in enumerate(captures):
        ratio = next((r.get("ratio_cpu") for r in rows if r["capture"] == c and "ratio_cpu" in r), None)
        if ratio:
            top = max(seconds.get((c, v), 0) for v in versions)
            ax.text(j + 0.4 - width / 2, top, f"x{ratio:.1f}", ha="center", va="bottom")
    ax.set_xticks(np.arange(len(captures)) + 0.4 - width / 2, [c.replace("_", " ") for c in captures], fontsize=7)
    ax.set_ylabel("registration, CPU seconds (20 frames)")
    ax.set_title("Frame registration: this tree against the baseline, same run")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run_memory_curve(args) -> list[dict]:
    """Peak memory (and time) of odometry + refine for every ``--cases`` size x ``--memory-curve``
    frame count, capped at one sweep per level (``max_iterations=1``, to keep the curve cheap: a
    lower bound, as the resident size of a full run keeps growing over the finest level's sweeps,
    docs/performance.md); rows as :func:`run_case`'s plus "revision" (this tree's commit) in
    ``memory_curve.json``, plotted by :func:`memory_curve_plot`."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    warm_up([Path(__file__).resolve().parent.parent])
    rows = []
    revision = subprocess.run(["git", "-C", str(Path(__file__).resolve().parent), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=False).stdout.strip() or None
    for size, sf, distance in (parse_case(c) for c in args.cases):
        for frames in args.memory_curve:
            row = {**run_case(args.mesh, size, sf, frames, {"max_iterations": 1}, distance), "revision": revision}
            rows.append(row)
            print(f"memory: {row['color']}, {frames} frames: peak {row['peak_mb']:.0f} MB, {row['seconds']:.1f} s",
                  flush=True)
            (out / "memory_curve.json").write_text(json_text(rows, "memory curve rows"))
            memory_curve_plot(rows, out / "memory_curve.png")
    return rows


def memory_curve_plot(rows: list[dict], path: Path) -> None:
    """Peak MB against frames, one line per colour size and revision (rows' ``"revision"``, where
    given: the tree's commit; the rows' first solid, older ones dashed, dotted, dash-dotted in
    turn), the legend beside the axes (matplotlib, PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.5))
    revisions = list(dict.fromkeys(r.get("revision") for r in rows))
    styles = ("-", "--", ":", "-.")
    for j, color in enumerate(dict.fromkeys(r["color"] for r in rows)):
        for k, revision in enumerate(revisions):
            mine = sorted((r["frames"], r["peak_mb"]) for r in rows if r["color"] == color
                          and r.get("revision") == revision)
            if mine:  # one colour per size, a line style per revision
                ax.plot(*zip(*mine), marker="o", color=f"C{j}", linestyle=styles[k % len(styles)],
                        alpha=1.0 if k == 0 else 0.6,
                        label=f"{color} colour" + ("" if revision is None else f" ({revision})"))
    ax.set_xlabel("frames")
    ax.set_ylabel("peak resident memory (MiB)")
    ax.set_title("odometry + refine, one sweep per level")
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _worker(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.speed")
    parser.add_argument("--worker", required=True, help="capture folder to time (internal)")
    parser.add_argument("--options", default="{}", help="RefineOptions as JSON")
    args = parser.parse_args(argv)
    print(json.dumps(measure(args.worker, json.loads(args.options))))
    return 0


if __name__ == "__main__":
    raise SystemExit(_worker())
