"""Scaling study: time, peak memory, sweeps and CG iterations against object pixels x frames.

Each case renders the bunny at 0.25 m, where it fills about half of the frame (as an object a
user scans does), at the colour size that gives about the asked number of object pixels (SF 4,
LED light; the 2-megapixel frame 1708 x 1136 gives about 1M), writes the capture, and times odometry + refine in
a fresh Python process (the speed benchmark's worker). With ``--baseline REV`` the same capture
is also run by that commit of the package (a temporary git worktree), in the same run, so the
speed-up is a ratio measured on one machine at one time. A case that runs past ``--timeout``
seconds is recorded as unfinished.

Writes ``scaling.json`` (rows {"version", "target_pixels", "object_pixels", "color", "frames",
"seconds", "peak_mb", "sweeps", "finest_cg_iterations", "breakdown"} or {"timeout": s}),
``scaling.md`` with the fitted exponent of seconds against object pixels x frames per version,
and ``scaling.png`` (log-log).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from o3d_mvps.fileio import json_text

from .plots import scaling_plot
from .speed import warm_up

REPOSITORY = Path(__file__).resolve().parent.parent
#: the bunny (0.2 m) at this distance (m) fills about half of the frame
DISTANCE = 0.25
#: its object pixels at a 2-megapixel colour size, measured
REFERENCE_PIXELS, REFERENCE_SIZE = 958_221, (1708, 1136)


def add_arguments(parser) -> None:
    """Options of the scaling study."""
    parser.add_argument("--pixels", type=int, nargs="+", default=[100_000, 300_000, 1_000_000, 2_000_000],
                        help="object pixel counts to aim at")
    parser.add_argument("--frames", type=int, nargs="+", default=[5, 10, 20, 30])
    parser.add_argument("--baseline", default=None, metavar="REV",
                        help="also run this git revision of the package (e.g. the commit before a change)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds a case may run")


def colour_size(target_pixels: int, scale_factor: int = 4) -> tuple[int, int]:
    """(W, H), a multiple of 8 x SF, at which the bunny at :data:`DISTANCE` covers about
    ``target_pixels``."""
    scale = math.sqrt(target_pixels / REFERENCE_PIXELS)
    step = 8 * scale_factor
    return tuple(max(step, int(round(side * scale / step)) * step) for side in REFERENCE_SIZE)


@contextlib.contextmanager
def checkout(revision: str | None):
    """The repository folder of ``revision`` (a temporary detached worktree), or of this one."""
    if revision is None:
        yield REPOSITORY
        return
    with tempfile.TemporaryDirectory(prefix="o3d_mvps_baseline_") as tmp:
        folder = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(REPOSITORY), "worktree", "add", "--detach", "-q", str(folder), revision],
                       check=True)
        try:
            yield folder
        finally:
            subprocess.run(["git", "-C", str(REPOSITORY), "worktree", "remove", "--force", str(folder)], check=False)


def time_capture(folder: Path, tree: Path, timeout: float) -> dict:
    """Run the speed worker of the package in ``tree`` on a capture folder in a fresh process."""
    command = [sys.executable, "-m", "benchmarks.speed", "--worker", str(folder), "--options", "{}"]
    env = {**os.environ, "PYTHONPATH": str(tree)}
    try:
        done = subprocess.run(command, capture_output=True, text=True, check=False, cwd=tree, env=env, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"timeout": timeout}
    if done.returncode != 0:
        raise RuntimeError(f"scaling worker failed in {tree} ({done.returncode}):\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def power_law(rows: list[dict]) -> tuple[float, float] | None:
    """(exponent, prefactor) of seconds = prefactor * (object pixels x frames) ** exponent,
    a least-squares line through log(seconds) against log(work) over the finished rows; None
    with fewer than two distinct amounts of work."""
    done = [r for r in rows if "seconds" in r]
    if len({r["object_pixels"] * r["frames"] for r in done}) < 2:
        return None
    work = np.log([r["object_pixels"] * r["frames"] for r in done])
    slope, intercept = np.polyfit(work, np.log([r["seconds"] for r in done]), 1)
    return float(slope), float(np.exp(intercept))


def fitted_exponent(rows: list[dict]) -> float | None:
    """Slope of log(seconds) against log(object pixels x frames) over the finished rows."""
    fit = power_law(rows)
    return None if fit is None else fit[0]


def run(args) -> list[dict]:
    """Run every (pixels, frames) case for this tree and the baseline; rewrites the results after each."""
    from o3d_mvps.capture import write_capture
    from o3d_mvps.synthetic import render_capture

    pixels, frames = args.pixels, args.frames
    if args.quick:
        pixels, frames = [20_000], [3, 5]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    versions = {"current": None} if args.baseline is None else {"current": None, args.baseline: args.baseline}
    with contextlib.ExitStack() as stack:
        trees = {name: stack.enter_context(checkout(rev)) for name, rev in versions.items()}
        warm_up(trees.values())
        for target in pixels:
            size = colour_size(target)
            for n in frames:
                capture = render_capture("bunny", frames=n, scale_factor=4, size=size, seed=0, distance=DISTANCE)
                object_pixels = int(np.count_nonzero(capture.mask_array(0)))
                with tempfile.TemporaryDirectory(prefix="o3d_mvps_scaling_") as tmp:
                    folder = Path(tmp) / "capture"
                    write_capture(capture, folder)
                    del capture
                    for name, tree in trees.items():
                        measured = time_capture(folder, tree, args.timeout)
                        row = {"version": name, "target_pixels": target, "object_pixels": object_pixels,
                               "color": f"{size[0]}x{size[1]}", "frames": n, **measured}
                        rows.append(row)
                        said = f"{row['seconds']:.1f} s, {row['peak_mb']:.0f} MB" if "seconds" in row else "timed out"
                        print(f"scaling [{name}]: {row['color']}, {n} frames: {said}", flush=True)
                        write_results(out, rows)
    return rows


def write_results(out: Path, rows: list[dict]) -> None:
    """scaling.json, scaling.md and scaling.png from the rows so far."""
    (out / "scaling.json").write_text(json_text(rows, "scaling rows"))
    lines = ["| version | colour | object pixels | frames | seconds | peak MB | sweeps | finest-level CG per step |",
             "|---|---|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        if "seconds" not in r:
            lines.append(f"| {r['version']} | {r['color']} | ~{r['target_pixels']} | {r['frames']} | "
                         f"> {r['timeout']:.0f} (unfinished) | | | |")
            continue
        cg = r.get("finest_cg_iterations")
        lines.append(f"| {r['version']} | {r['color']} | {r['object_pixels']} | {r['frames']} | {r['seconds']:.1f} | "
                     f"{r['peak_mb']:.0f} | {r.get('sweeps', '')} | {'' if cg is None else max(cg, default=0)} |")
    for version in dict.fromkeys(r["version"] for r in rows):
        exponent = fitted_exponent([r for r in rows if r["version"] == version])
        lines.append("")
        lines.append(f"{version}: fitted exponent of seconds against object pixels x frames: "
                     f"{'n/a' if exponent is None else f'{exponent:.2f}'}")
    (out / "scaling.md").write_text("\n".join(lines) + "\n")
    draw_plot(out, rows)


def draw_plot(out: Path, rows: list[dict]) -> None:
    """scaling.png: seconds against object pixels x frames, log-log, each version's points and
    fitted power law."""
    series, fits = {}, {}
    for version in dict.fromkeys(r["version"] for r in rows):
        mine = sorted((r for r in rows if r["version"] == version and "seconds" in r),
                      key=lambda r: r["object_pixels"] * r["frames"])
        if mine:
            series[version] = ([r["object_pixels"] * r["frames"] for r in mine], [r["seconds"] for r in mine])
        fit = power_law(mine)
        if fit is not None:
            fits[version] = fit
    if series:
        scaling_plot(out / "scaling.png", series, fits, title="Refinement time against work (odometry + refine)",
                     xlabel="work: object pixels x frames", ylabel="wall time (s)")
