"""``o3d-mvps reconstruct CAPTURE OUT``: the whole object from frames all round it."""

from __future__ import annotations

import argparse
import json
import warnings
from dataclasses import replace

from ..capture import read_capture
from ..capture.checks import check_given_poses
from ..capture.reading import MASK_SOURCES
from ..export import write_mesh, write_stl
from ..fileio import atomic_folder
from ..reconstruct import ReconstructOptions, reconstruct
from .outputs import add_overwrite_argument, check_folder
from .refine import add_pose_file_arguments, add_solver_arguments, options_from_args, read_given_poses

DESCRIPTION = """\
Reconstruct a whole object from a capture that goes around it: K reference views spread round
the ring are each refined with the frames that see them (in parallel, as Dask tasks), their
refined depths fused into one mesh, cleaned and textured from the refined albedos (one UV
atlas). Writes OUT/mesh.obj (+ mesh.mtl, mesh_albedo.png), mesh.glb (texture embedded),
mesh.ply (vertex colours) and report.json; --print MM adds print.stl, a
closed solid MM millimetres across. A capture that does not go all round gives a mesh of what
was seen (with a warning), and --print closes its back flat.
"""

EXAMPLES = """examples:
  o3d-mvps reconstruct ring/ object/
  o3d-mvps reconstruct ring/ object/ --references 12 --print 80
  o3d-mvps reconstruct ring/ object/ --poses trajectory.log --scheduler tcp://10.0.0.5:8786
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("reconstruct", help="whole object from frames all round it",
                              description=DESCRIPTION, epilog=EXAMPLES,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("capture", help="capture folder whose frames go around the object")
    p.add_argument("out", help="output folder")
    add_overwrite_argument(p, "output folder")
    d = ReconstructOptions()
    p.add_argument("--poses", default=None, metavar="FILE",
                   help="initial poses (Open3D .json/.log, TUM .txt, .npy; default: the capture's poses.* if any, "
                        "else registration)")
    add_pose_file_arguments(p)
    p.add_argument("--mask", choices=MASK_SOURCES, default=None, help="object masks (as for refine)")
    p.add_argument("--references", type=int, default=d.references,
                   help=f"reference views refined and fused (default {d.references})")
    p.add_argument("--frames-per-reference", type=int, default=d.frames_per_reference,
                   help=f"most frames refined with each reference (default {d.frames_per_reference})")
    p.add_argument("--depth", choices=("refined", "raw"), default="refined",
                   help="fuse refined depth, or the sensor's depth bicubic-upsampled (for comparison)")
    p.add_argument("--voxel-mm", type=float, default=d.voxel_mm, help=f"fusion voxel (default {d.voxel_mm} mm)")
    p.add_argument("--texture-px", type=int, default=d.texture_px,
                   help=f"edge of the square albedo texture, 0 for vertex colours only (default {d.texture_px})")
    p.add_argument("--print", dest="print_mm", type=float, default=None, metavar="MM",
                   help="also write print.stl, a closed solid MM millimetres across")
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: CPU count)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="run the refinements on this Dask scheduler instead of a local cluster")
    add_solver_arguments(p)
    p.set_defaults(handler=run)


def run(args) -> int:
    out = check_folder(args.out, args.overwrite, "output folder")
    capture = read_capture(args.capture, mask=args.mask)
    given = read_given_poses(args)
    if given is not None:
        check_given_poses(capture, given)  # a convention mix-up is named before the long work
    options = ReconstructOptions(references=args.references, frames_per_reference=args.frames_per_reference,
                                 depth=args.depth, voxel_mm=args.voxel_mm, texture_px=args.texture_px,
                                 workers=args.workers,
                                 refine=replace(options_from_args(args), progress=False), progress=not args.quiet)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = reconstruct(capture, options, poses=None if given is None else given.poses, scheduler=args.scheduler)
    for w in caught:
        print(f"warning: {w.message}")
    solid = None
    if args.print_mm is not None:
        if not result.goes_around and not args.quiet:
            print(f"print: the frames cover {result.azimuth_span_deg:.0f} degrees; the unseen back is closed flat")
        solid = result.printable_solid(args.print_mm)
    with atomic_folder(out, overwrite=args.overwrite, what="output folder") as tmp:
        for name in ("mesh.ply", "mesh.glb", "mesh.obj"):
            write_mesh(result.mesh, tmp / name)
        if solid is not None:
            write_stl(solid, tmp / "print.stl")
        (tmp / "report.json").write_text(json.dumps(result.info, indent=2))
    if not args.quiet:
        for view in result.info["views"]:
            print(f"reference {view['reference']}: frames {view['frames'][1:]}, {view['seconds']:.1f} s")
    print(f"wrote {out}")
    return 0
