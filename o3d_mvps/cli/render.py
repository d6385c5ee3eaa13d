"""``o3d-mvps render``: render a synthetic capture (with ground truth) of a mesh, alone or in a room."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..errors import MVPSError
from .argtypes import image_size, nonnegative_int, positive_int
from .outputs import add_overwrite_argument, check_folder

EXAMPLES = """\
examples:
  o3d-mvps render bunny captures/bunny
  o3d-mvps render armadillo captures/arma --frames 30 --scale-factor 8 --size 1280x720
  o3d-mvps render my_scan.ply captures/scan --trajectory orbit-translate --light directional --seed 3
  o3d-mvps render bunny captures/room --scene --light room --frames 20   # table, wall, 360-degree ring
  o3d-mvps render bunny captures/real --sensor d415            # terraces, flying pixels, holes, gain drift
  o3d-mvps render bunny captures/static --static-camera --size 1280x960 --scale-factor 2 --sensor d415

ring captures, for `o3d-mvps reconstruct` (the whole object):
  o3d-mvps render bunny captures/ring --trajectory ring --frames 24 --size 320x240 --scale-factor 2
  o3d-mvps reconstruct captures/ring object/ --print 80       # object/mesh.obj, report.html, print.stl
  o3d-mvps render bunny captures/arc --trajectory ring --arc-deg 90 --frames 7   # part of a ring
  o3d-mvps render bunny captures/scene --scene --frames 24   # a ring round the object on a table

The folder holds color/, depth/, mask/, intrinsic.json, depth_intrinsic.json, capture.json and
groundtruth/ (reference depth, normals, albedo, poses, light, mesh_to_reference); read it with
o3d_mvps.read_capture or refine it with `o3d-mvps refine`. A --scene capture has no mask/: refine
finds the object with its automatic masks, as in a user's capture.
"""


def register(subparsers) -> None:
    """Add the ``render`` subcommand."""
    from ..synthetic import LIGHTS, SENSORS, TRAJECTORIES

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
                   metavar="N", help="number of frames to render; the first is the reference (default 20)")
    p.add_argument("--scale-factor", type=positive_int, default=4, metavar="SF",
                   help="depth grid = colour size / SF; must divide the size (default 4)")
    p.add_argument("--size", type=image_size, default=(640, 480), metavar="WxH", help="colour size (default 640x480)")
    p.add_argument("--trajectory", choices=(*TRAJECTORIES, "ring"), default="orbit",
                   help="orbit: yaw/pitch up to 15 deg around the object; orbit-translate: plus a few cm of "
                   "translation and distance change; ring: frames evenly all round the object (360/FRAMES "
                   "degrees apart, 20 degrees above it; --arc-deg for part of a ring), the capture `o3d-mvps "
                   "reconstruct` makes a whole object of (default orbit)")
    p.add_argument("--arc-deg", type=float, default=360.0, metavar="DEG",
                   help="with --trajectory ring or --scene: degrees of the ring the frames cover, both ends "
                   "included below 360 (default 360: all round)")
    p.add_argument("--light", choices=LIGHTS, default="led",
                   help="led: point light near the camera, 1/r^2, shadows; directional: first-order SH, exact; "
                   "room: ambient plus three distant lights fixed in the room, shadows (default led)")
    p.add_argument("--scene", action="store_true",
                   help="scene mode: the object on a table in front of a wall, frames on a ring (as --trajectory "
                   "ring, 20 degrees above the table), no mask/ folder; --trajectory is ignored")
    p.add_argument("--static-camera", action="store_true",
                   help="static camera, moving light (Peng et al. 2017): the camera stays at the reference pose "
                   "and a point light is moved by hand around it, 0.3-0.5 m from the optical axis, one position "
                   "per frame; capture.json says \"camera\": \"static\"; --trajectory and --light are ignored")
    p.add_argument("--sensor", choices=SENSORS, default="gaussian",
                   help="sensor profile: gaussian (the paper's: depth noise 1e-5 z^2 mm, 1 mm steps, colour noise "
                   "0.005), d415 (RealSense-D415-like: disparity terraces of 1.1 mm at 1 m, noise growing with "
                   "z^2 plus a smooth error of a few mm, flying pixels at edges, 3%% speckle holes; colour with "
                   "exposure and white-balance drift, shot and read noise) or none (quantisation only) "
                   "(default gaussian)")
    p.add_argument("--albedo", choices=("patches", "speckled"), default="patches",
                   help="surface texture: patches (coloured cells) or speckled (a pale stone with dark speckles 3-4 "
                   "px wide at 320x240, for 'colour must not become relief'; not with --static-camera) "
                   "(default patches)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="seed of the albedo texture and noise (default 0)")
    p.add_argument("--no-noise", dest="noise", action="store_false",
                   help="no colour or depth noise (quantisation stays): --sensor none")
    add_overwrite_argument(p, "capture folder")
    p.set_defaults(handler=run)


def run(args) -> int:
    """Render and write the capture; returns the exit code."""
    from ..capture import write_capture
    from ..synthetic import render_capture, render_ring, render_static_capture

    if not 0.0 < args.arc_deg <= 360.0:
        raise MVPSError(f"--arc-deg {args.arc_deg:g}: give the degrees of the ring the frames cover, in (0, 360]")
    if args.scene and args.static_camera:
        raise ValueError("--scene and --static-camera exclude each other (a scene is rendered from a ring of "
                         "camera positions); pick one")
    if args.static_camera and args.albedo != "patches":
        raise ValueError(f"--albedo {args.albedo} is not available with --static-camera; drop one of them")
    if not args.noise and args.sensor not in ("gaussian", "none"):
        raise ValueError(f"--no-noise contradicts --sensor {args.sensor}; drop one of them")
    sensor = args.sensor if args.noise else "none"
    out = check_folder(args.out, args.overwrite, "capture folder")
    start = time.perf_counter()
    common = dict(frames=args.frames, scale_factor=args.scale_factor, size=args.size, seed=args.seed, sensor=sensor,
                  progress=not args.quiet)
    if args.static_camera:
        capture = render_static_capture(args.mesh, **common)
    elif args.scene or args.trajectory == "ring":
        capture, _ = render_ring(args.mesh, surroundings=args.scene, arc_deg=args.arc_deg, light=args.light,
                                 albedo=args.albedo, **common)
    else:
        capture = render_capture(args.mesh, trajectory=args.trajectory, light=args.light, albedo=args.albedo, **common)
    write_capture(capture, out, overwrite=args.overwrite)
    (H, W), (h, w) = capture.color_size, capture.depth_size
    print(f"wrote {capture.n_frames} frames ({W}x{H} colour, {w}x{h} depth) to {out} "
          f"in {time.perf_counter() - start:.1f} s")
    return 0
