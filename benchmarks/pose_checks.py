"""How often the pose check names a frame whose given pose is a little off, and how often it refuses true poses.

``python -m benchmarks.pose_checks [--quick] [--out DIR]`` (not part of 'all'; about 10 minutes on two
cores, --quick a minute). Renders the rings, arcs and orbits of docs/input-checks.md; checks the true
poses of each whole capture and of its 4 reference views (:func:`o3d_mvps.reconstruct.views.plan_view`);
then puts each frame of each view, alone, 5 degrees off about one camera axis (or a random axis) or
10 mm off along one (or a random direction) and counts the frames the check names (dropped, or the
poses refused). Writes pose_checks.json and pose_checks.md to DIR (default benchmarks/results).
"""

from __future__ import annotations

import argparse
import collections
import json
import time
import warnings
from pathlib import Path

import numpy as np

from o3d_mvps.capture.pose_checks import check_poses
from o3d_mvps.capture.poses import GivenPoses
from o3d_mvps.covisibility import MIN_COVISIBILITY
from o3d_mvps.errors import CaptureError
from o3d_mvps.model import se3
from o3d_mvps.reconstruct import choose_references
from o3d_mvps.reconstruct.views import plan_view
from o3d_mvps.synthetic import render_capture, render_ring

BUNNY = dict(frames=12, size=(320, 240), scale_factor=2)
#: name: render_ring's arguments (mesh "bunny" unless named); "orbit..." names render_capture's.
RENDERS = {
    "ring12": BUNNY, "ring12_d415": {**BUNNY, "sensor": "d415", "seed": 1}, "ring24": {**BUNNY, "frames": 24},
    "arc180": {**BUNNY, "arc_deg": 180}, "arc180_d415": {**BUNNY, "arc_deg": 180, "sensor": "d415", "seed": 3},
    "elev45": {**BUNNY, "elevation_deg": 45}, "armadillo": {**BUNNY, "mesh": "armadillo"},
    "armadillo_d415": {**BUNNY, "mesh": "armadillo", "sensor": "d415", "seed": 2},
    "elev45_arm": {**BUNNY, "mesh": "armadillo", "elevation_deg": 45},
    "ring12_160": dict(frames=12, size=(160, 120), scale_factor=4),
    "room_scene": dict(frames=12, size=(160, 120), light="room", surroundings=True),
    "ring12_640": {**BUNNY, "size": (640, 480)},
    "room320": {**BUNNY, "light": "room", "surroundings": True},
    "room320_d415": {**BUNNY, "light": "room", "surroundings": True, "sensor": "d415", "seed": 4},
    "ring18_d415_arm": {**BUNNY, "mesh": "armadillo", "frames": 18, "sensor": "d415", "seed": 5,
                        "elevation_deg": 30},
    "orbit": dict(frames=6, size=(160, 120), scale_factor=2),
    "orbit_d415size": dict(frames=20, size=(1280, 720), scale_factor=2),
}
QUICK = ("ring12_160", "orbit")
#: case: (rotation or translation, camera axis 0-2 or -1 for a random one).
KICKS = {"rx5": ("r", 0), "ry5": ("r", 1), "rz5": ("r", 2), "r5_any": ("r", -1),
         "tx10": ("t", 0), "ty10": ("t", 1), "tz10": ("t", 2), "t10_any": ("t", -1)}


def views(name: str) -> list:
    """[(label, depths, depth K, poses (n, 4, 4) reference -> frame)] of one render."""
    kw = dict(RENDERS[name])
    mesh = kw.pop("mesh", "bunny")
    if name.startswith("orbit"):
        capture = render_capture(mesh, light="led", seed=0, **kw)
        return [("whole", [capture.depth_array(k) for k in range(capture.n_frames)], capture.depth_K(),
                 capture.groundtruth.poses)]
    ring, _ = render_ring(mesh, **kw)
    poses = ring.groundtruth.poses
    out = [("whole", [ring.depth_array(k) for k in range(ring.n_frames)], ring.depth_K(), poses)]
    for r in choose_references(poses, 4):
        job = plan_view(ring, poses, r, min_covisibility=MIN_COVISIBILITY, max_frames=8)
        out.append((f"view {r}", job.arrays["depth"], job.arrays["depth_K"], job.poses))
    return out


def named(depths, K, poses, k=None) -> bool:
    """Whether the check refuses the poses or drops frame k (any frame when k is None)."""
    n = len(depths)
    try:
        found = check_poses(depths, K, GivenPoses.from_array(poses), list(range(n)), [f"frame {i}" for i in range(n)], 3)
    except CaptureError:
        return True
    return bool(found.dropped) if k is None else k in found.dropped


def kicked(poses, k, kind, axis, sign, rng):
    """``poses`` with frame k's 5 degrees off about, or 10 mm off along, a camera axis (-1: random)."""
    direction = np.eye(3)[axis] if axis >= 0 else rng.normal(size=3)
    twist = np.zeros(6)
    twist[3 * (kind == "r"):3 * (kind == "r") + 3] = sign * direction / np.linalg.norm(direction) * (
        np.radians(5) if kind == "r" else 0.01)
    out = poses.copy()
    out[k] = se3.exp(twist) @ poses[k]
    return out


def run(names, out: Path) -> dict:
    warnings.simplefilter("ignore")
    rng = np.random.default_rng(0)
    refused, checks, seconds = [], 0, []
    caught = {key: 0 for key in KICKS}
    missed = {key: collections.Counter() for key in KICKS}
    frames = collections.Counter()
    for name in names:
        for label, depths, K, poses in views(name):
            t0 = time.perf_counter()
            checks += 1
            if named(depths, K, poses):
                refused.append(f"{name} {label}")
            seconds.append(time.perf_counter() - t0)
            if label == "whole" and not name.startswith("orbit"):
                continue  # the perturbations run on the reference views (and the orbits)
            frames[name] += len(depths) - 1
            for k in range(1, len(depths)):
                for j, (key, (kind, axis)) in enumerate(KICKS.items()):
                    if named(depths, K, kicked(poses, k, kind, axis, 1.0 if (k + j) % 2 else -1.0, rng), k):
                        caught[key] += 1
                    else:
                        missed[key][name] += 1
    total = sum(frames.values())
    result = {"renders": list(names), "checks": checks, "true_poses_refused": refused, "frames": total,
              "frames_per_render": dict(frames), "caught": caught, "missed": {k: dict(v) for k, v in missed.items()},
              "check_seconds_median": round(float(np.median(seconds)), 3)}
    out.mkdir(parents=True, exist_ok=True)
    (out / "pose_checks.json").write_text(json.dumps(result, indent=1))
    lines = ["# Pose check: detection rates", "",
             f"{len(names)} renders, {checks} checks of true poses: {len(refused)} refused or dropped a frame.", "",
             "| one frame off by | caught | missed on |", "|---|---|---|"]
    lines += [f"| {key} | {caught[key]} of {total} | {', '.join(f'{n} {c}' for n, c in missed[key].items()) or '-'} |"
              for key in KICKS]
    (out / "pose_checks.md").write_text("\n".join(lines) + "\n")
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.pose_checks", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK)} (about a minute)")
    parser.add_argument("--out", default="benchmarks/results", help="results folder")
    args = parser.parse_args(argv)
    result = run(QUICK if args.quick else tuple(RENDERS), Path(args.out))
    print(json.dumps({k: result[k] for k in ("checks", "true_poses_refused", "frames", "caught")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
