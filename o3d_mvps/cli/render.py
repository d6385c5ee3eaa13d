"""``o3d-mvps render``: render a synthetic capture (with ground truth) of a mesh, alone or in a room."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from .argtypes import image_size, nonnegative_int, positive_int
from .outputs import add_overwrite_argument, check_folder

EXAMPLES = """\
examples:
  o3d-mvps render bunny captures/bunny
  o3d-mvps render armadillo captures/arma --frames 30 --scale-factor 8 --size 1280x720
  o3d-mvps render my_scan.ply captures/scan --trajectory orbit-translate --light directional --seed 3
  o3d-mvps render bunny captures/room --scene --light room --frames 20   # table, wall, 360-degree ring

The folder holds color/, depth/, mask/, intrinsic.json, depth_intrinsic.json, capture.json and
groundtruth/ (reference depth, normals, albedo, poses, light, mesh_to_reference); read it with
o3d_mvps.read_capture or refine it with `o3d-mvps refine`. A --scene capture has no mask/: refine
finds the object with its automatic masks, as in a user's capture.
"""


def register(subparsers) -> None:
    """Add the ``render`` subcommand."""
    from ..synthetic import LIGHTS, TRAJECTORIES

    p = subparsers.add_parser(
        "render",
        help="render a synthetic capture of a mesh (benchmark data with ground truth)",
        description="Ray-cast MESH (scaled to 0.2 m, 0.6 m in front of the reference camera, procedural "
        "coloured albedo) from a camera orbiting it with an LED attached, simulate the depth sensor "
        "(SF x SF area averaging, noise sigma = 1e-5 z^2 mm, 1 mm steps) and 8-bit sRGB colour, and write "
        "the capture folder OUT with ground truth.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("mesh", metavar="MESH", help="'bunny', 'armadillo' or a mesh file (.ply, .obj, .stl, ...)")
    p.add_argument("out", metavar="OUT", type=Path, help="capture folder to write")
    p.add_argument("--frames", type=positive_int, default=20,
                   help="number of frames, the first is the reference (default 20)")
    p.add_argument("--scale-factor", type=positive_int, default=4, metavar="SF",
                   help="depth grid = colour size / SF; must divide the size (default 4)")
    p.add_argument("--size", type=image_size, default=(640, 480), metavar="WxH", help="colour size (default 640x480)")
    p.add_argument("--trajectory", choices=TRAJECTORIES, default="orbit",
                   help="orbit: yaw/pitch up to 15 deg around the object; orbit-translate: plus a few cm of "
                   "translation and distance change (default orbit)")
    p.add_argument("--light", choices=LIGHTS, default="led",
                   help="led: point light near the camera, 1/r^2, shadows; directional: first-order SH, exact; "
                   "room: ambient plus three distant lights fixed in the room, shadows (default led)")
    p.add_argument("--scene", action="store_true",
                   help="scene mode: the object on a table in front of a wall, frames on a 360-degree ring "
                   "(360/FRAMES degrees apart, 20 degrees above the table), no mask/ folder; --trajectory is "
                   "ignored")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="seed of the albedo texture and noise (default 0)")
    p.add_argument("--no-noise", dest="noise", action="store_false",
                   help="no colour or depth noise (quantisation stays)")
    add_overwrite_argument(p, "capture folder")
    p.set_defaults(handler=run)


def run(args) -> int:
    """Render and write the capture; returns the exit code."""
    from ..capture import write_capture
    from ..synthetic import render_capture, render_ring

    out = check_folder(args.out, args.overwrite, "capture folder")
    start = time.perf_counter()
    common = dict(frames=args.frames, scale_factor=args.scale_factor, size=args.size, light=args.light, seed=args.seed,
                  noise=args.noise, progress=not args.quiet)
    if args.scene:
        capture, _ = render_ring(args.mesh, surroundings=True, **common)
    else:
        capture = render_capture(args.mesh, trajectory=args.trajectory, **common)
    write_capture(capture, out, overwrite=args.overwrite)
    (H, W), (h, w) = capture.color_size, capture.depth_size
    print(f"wrote {capture.n_frames} frames ({W}x{H} colour, {w}x{h} depth) to {out} "
          f"in {time.perf_counter() - start:.1f} s")
    return 0
