"""``o3d-mvps reconstruct CAPTURE OUT``: the whole object from frames all round it."""

from __future__ import annotations

import argparse
import warnings
from dataclasses import replace

from ..capture import read_capture, read_capture_poses
from ..capture.reading import MASK_SOURCES
from ..export import write_mesh, write_stl
from ..fileio import atomic_folder, json_text
from ..run_report import reconstruction_report, recorded_warnings
from ..reconstruct import ReconstructOptions, reconstruct
from ..reconstruct.parallel import check_scheduler_address
from ..report_page import write_report_page
from ..solver.device import DEVICE_HELP, resolve_device
from .argtypes import frame_count_fits, integer_at_least, nonnegative_int, positive_float, positive_int
from .outputs import add_overwrite_argument, check_folder, frame_files, print_summary
from .refine import add_solver_arguments, options_from_args

DESCRIPTION = """\
Reconstruct a whole object from a capture that goes around it: K reference views spread round
the ring are each refined with the frames that see them (in parallel, as Dask tasks), their
refined depths fused into one mesh, cleaned and textured from the refined albedos (one UV
atlas). Writes OUT/mesh.obj (+ mesh.mtl, mesh_albedo.png), mesh.glb (texture embedded),
mesh.ply (vertex colours), report.json and report.html (plots and a 3D view, for a
browser); --print MM adds print.stl, a
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
    p.add_argument("--mask", choices=MASK_SOURCES, default=None, help="object masks (as for refine)")
    p.add_argument("--references", type=positive_int, default=d.references,
                   help=f"reference views refined and fused (default {d.references})")
    p.add_argument("--frames-per-reference", type=integer_at_least(2), default=d.frames_per_reference,
                   help=f"most frames refined with each reference (default {d.frames_per_reference})")
    p.add_argument("--depth", choices=("refined", "raw"), default="refined",
                   help="fuse refined depth, or the sensor's depth bicubic-upsampled (for comparison)")
    p.add_argument("--voxel-mm", type=positive_float, default=d.voxel_mm,
                   help=f"fusion voxel (default {d.voxel_mm} mm)")
    p.add_argument("--texture-px", type=nonnegative_int, default=d.texture_px,
                   help=f"edge of the square albedo texture, 0 for vertex colours only (default {d.texture_px})")
    p.add_argument("--print", dest="print_mm", type=positive_float, default=None, metavar="MM",
                   help="also write print.stl, a closed solid MM millimetres across")
    p.add_argument("--workers", type=positive_int, default=None, help="local worker processes (default: CPU count)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="run the refinements on this Dask scheduler instead of a local cluster")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    p.add_argument("--scheduler-timeout", type=positive_float, default=d.scheduler_timeout, metavar="S",
                   help="seconds to wait for the scheduler to answer, or for a worker while it has none; then "
                        f"stop, naming the address (default {d.scheduler_timeout:g})")
    add_solver_arguments(p)
    p.set_defaults(handler=run)


def run(args) -> int:
    out = check_folder(args.out, args.overwrite, "output folder", inputs=[args.capture])
    if args.scheduler is not None:
        check_scheduler_address(args.scheduler)
    device, device_line = resolve_device(args.device)
    if not args.quiet:
        print(device_line)
    capture = read_capture(args.capture, mask=args.mask)
    frame_count_fits("--frames", args.frames, capture.n_frames, f"the capture {args.capture}")
    given = read_capture_poses(args.capture, args.poses)
    if args.frames is not None:  # the first N frames, as for refine
        capture = capture.select(list(range(args.frames)))
        given = None if given is None else (given[0][: args.frames], given[1])
    options = ReconstructOptions(references=args.references, frames_per_reference=args.frames_per_reference,
                                 depth=args.depth, voxel_mm=args.voxel_mm, texture_px=args.texture_px,
                                 workers=args.workers, device=device, scheduler_timeout=args.scheduler_timeout,
                                 refine=replace(options_from_args(args), progress=False), progress=not args.quiet)
    said = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with recorded_warnings(said):
            result = reconstruct(capture, options, poses=None if given is None else given[0],
                                 scheduler=args.scheduler)
    if not args.quiet:
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
        report = reconstruction_report(result.info, said, frame_files(args.capture))
        report["summary"]["outputs"] = str(out)
        (tmp / "report.json").write_text(json_text(report, "the reconstruction report"))
    write_report_page(out, mesh=result.mesh, warnings=[w.message for w in caught])
    if not args.quiet:
        for view in result.info["views"]:
            print(f"reference {view['reference']}: frames {view['frames'][1:]}, {view['seconds']:.1f} s")
    print_summary(report["summary"], args.quiet)
    print(f"wrote {out}")
    return 0
