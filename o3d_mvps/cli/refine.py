"""``o3d-mvps refine CAPTURE OUT``: super-resolved depth, albedo, lighting and poses."""

from __future__ import annotations

import argparse

from dataclasses import replace

from ..capture import read_capture
from ..capture.poses import POSE_CONVENTIONS, POSE_UNITS, QUATERNION_ORDERS, given_poses
from ..capture.reading import MASK_SOURCES, mask_source, read_groundtruth
from ..report import accuracy_rows, markdown_table
from ..report_page import write_report_page
from ..solver.device import DEVICE_HELP, resolve_device
from ..solver.lighting import LIGHT_MODELS
from ..solver.options import AUTO, FramesDepth, RefineOptions
from ..solving import refine
from ..covisibility import ViewSelection
from .argtypes import frame_count_fits, metres_offset, positive_float, positive_int, unit_interval
from .outputs import add_overwrite_argument, check_files, check_folder, frame_files, log_energy, print_summary

DESCRIPTION = """\
Refine a capture folder: depth at colour resolution, RGB albedo, per-frame lighting and
refined camera poses of the reference view (the first frame), written to the folder OUT
(depth.npy, depth_mm.png, normals, albedo, poses.npy, lighting.json, report.json, and
report.html: a page with the plots and a 3D view, to open in a browser). For a
synthetic capture (with groundtruth/) the accuracy against the baselines is printed too.
"""

EXAMPLES = """examples:
  o3d-mvps refine capture/ refined/
  o3d-mvps refine capture/ refined/ --frames 10 --tau 100 --iterations 5
  o3d-mvps refine capture/ two_stage/ --no-pose-refinement   # the paper's two-stage baseline
  o3d-mvps refine capture/ refined/ --led-offset 0.03 -0.02 0  # LED 3 cm right of, 2 cm above the lens
  o3d-mvps refine capture/ paper/ --light-model sh            # the paper's SH lighting
  o3d-mvps refine capture/ refined/ --poses trajectory.log     # poses from Open3D's reconstruction system
  o3d-mvps refine capture/ refined/ --poses cams.npy --poses-convention camera-to-world
  o3d-mvps refine capture/ refined/ --mask auto --depth-range 0.3 1.2  # object mask from depth
  o3d-mvps refine capture/ refined/ --save-problem problem.npz  # also keep the solver's input
  python -m o3d_mvps.solver problem.npz solution.npz           # solve it again (no Open3D needed)
"""


def _cauchy_lambda(text: str) -> float | str:
    """--lambda: a number, or "auto"."""
    if text == AUTO:
        return AUTO
    try:
        return positive_float(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a positive number or {AUTO!r}, got {text!r}") from None


def add_solver_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by every subcommand that runs the solver."""
    d = RefineOptions()
    g = parser.add_argument_group("solver")
    g.add_argument("--frames", type=positive_int, default=None, metavar="N",
                   help="number of frames to use: the first N of the capture (default: all)")
    g.add_argument("--tau", type=positive_float, default=d.tau,
                   help=f"normalised depth-prior weight (default {d.tau:g})")
    g.add_argument("--lambda", dest="cauchy_lambda", type=_cauchy_lambda, default=None, metavar="LAMBDA|auto",
                   help="Cauchy scale in linear intensity, or auto: the residuals' robust standard deviation "
                        "(default: 0.04 with the LED and SH models, auto with room light)")
    g.add_argument("--levels", type=positive_int, default=d.levels, help=f"pyramid levels (default {d.levels})")
    g.add_argument("--iterations", type=positive_int, default=d.max_iterations,
                   help=f"sweep cap per level (default {d.max_iterations})")
    g.add_argument("--tolerance", type=unit_interval, default=d.tolerance,
                   help=f"relative energy change that ends a level (default {d.tolerance:g})")
    g.add_argument("--no-pose-refinement", action="store_true", help="keep the odometry poses (two-stage baseline)")
    g.add_argument("--no-occlusion-test", action="store_true", help="let hidden pixels enter the data term")
    g.add_argument("--keep-flying-pixels", action="store_true",
                   help="keep the reference depth pixels the other frames contradict (only reported; by default "
                        "they are replaced: docs/fidelity.md, flying pixels of a moving camera)")
    g.add_argument("--average-frames-depth", choices=[m.value for m in FramesDepth],
                   default=str(d.average_frames_depth),
                   help="how the other frames' depth enters the depth prior: off (the default: frame 0's depth "
                        "alone), finest (the finest level's prior from every frame's residual against the surface; "
                        "for 20 frames of a noisy sensor) or initial (the frames' mean before any level, for a noisy "
                        "sensor whose poses fit its depth); docs/fidelity.md, the frames' mean depth")
    g.add_argument("--light-model", choices=LIGHT_MODELS, default=None,
                   help="near-field LED, one SH light fixed in the room (room) or the paper's first-order SH "
                        "per frame (sh), or a point light per frame at its own position, a lamp moved around a static camera "
                        "(point) (default: capture.json's light, led -> led, room -> room; led when it "
                        "does not say)")
    g.add_argument("--led-offset", type=metres_offset, nargs=3, metavar=("X", "Y", "Z"), default=None,
                   help="LED position in metres from the colour lens (x right, y down, z forward); a ruler "
                        "measure within ~1 cm is enough, the solver refines it (default: capture.json's "
                        "metadata.led_offset, else 0 0 0)")


def add_pose_file_arguments(parser: argparse.ArgumentParser) -> None:
    """--poses-convention, --quaternion-order, --poses-unit: how to read a pose file (--poses or poses.*)."""
    parser.add_argument("--poses-convention", choices=POSE_CONVENTIONS, default=None,
                        help="what the pose file's matrices map (default: the format's own: world-to-camera for "
                             ".json and .npy, camera-to-world for .log and TUM)")
    parser.add_argument("--quaternion-order", choices=QUATERNION_ORDERS, default=None,
                        help="TUM quaternion order (default xyzw: 'id tx ty tz qx qy qz qw')")
    parser.add_argument("--poses-unit", choices=tuple(POSE_UNITS), default="m",
                        help="unit of the pose file's translations (default m)")


def read_given_poses(args):
    """The capture's initial poses (:class:`~o3d_mvps.capture.poses.GivenPoses`) from --poses or
    its poses.*, read as the pose-file options say; None without a pose file."""
    return given_poses(args.capture, args.poses, convention=args.poses_convention,
                       quaternion_order=args.quaternion_order, unit=args.poses_unit)


def options_from_args(args) -> RefineOptions:
    return RefineOptions(frames=args.frames, tau=args.tau, cauchy_lambda=args.cauchy_lambda, levels=args.levels,
                         max_iterations=args.iterations, tolerance=args.tolerance,
                         refine_poses=not args.no_pose_refinement, occlusion_test=not args.no_occlusion_test,
                         drop_depth_outliers=not args.keep_flying_pixels,
                         average_frames_depth=args.average_frames_depth,
                         light_model=args.light_model,
                         led_offset=None if args.led_offset is None else tuple(args.led_offset),
                         progress=not args.quiet)


def register(subparsers) -> None:
    p = subparsers.add_parser("refine", help="refine a capture folder", description=DESCRIPTION, epilog=EXAMPLES,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("capture", help="capture folder (color/, depth/, intrinsic.json, ...)")
    p.add_argument("out", help="output folder for the refinement")
    add_overwrite_argument(p, "output folder (or --save-problem file)")
    p.add_argument("--poses", default=None, metavar="FILE",
                   help="initial poses: Open3D trajectory .json or .log, TUM .txt, or (n, 4, 4) .npy (docs/capture-guide.md, "
                        "'Poses'; default: the capture folder's poses.* if any, else registration)")
    add_pose_file_arguments(p)
    p.add_argument("--pose-trust", type=float, nargs=2, metavar=("MM", "DEG"), default=None,
                   help="how far the --poses (or the folder's poses.*) are trusted: the refinement keeps each "
                        "pose unless the images and the frame's own depth agree on a better one, with a prior of "
                        "this width towards it (default 2 mm 0.2 deg; docs/poses-and-light.md)")
    p.add_argument("--no-input-checks", action="store_true",
                   help="skip the cross-checks of intrinsics, depth scale, frame quality and poses against depth "
                        "before the solve (docs/input-checks.md; they take about 1 %% of a refinement)")
    p.add_argument("--strict", action="store_true",
                   help="stop when a frame cannot be registered, instead of dropping it with a warning")
    p.add_argument("--mask", choices=MASK_SOURCES, default=None,
                   help="object masks: the capture's mask/ folder, automatic from depth (the connected region "
                        "nearest the image centre, table and wall planes cut), or none (default: mask/ when "
                        "present, else auto)")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    p.add_argument("--save-problem", default=None, metavar="FILE.npz",
                   help="also write the solver's input (frames, depth, masks, intrinsics, registered poses, "
                        "options) to this file once the capture is read, masked and registered; `python -m "
                        "o3d_mvps.solver FILE.npz OUT.npz` solves it, without Open3D (bug reports, a GPU box)")
    p.add_argument("--depth-range", type=positive_float, nargs=2, metavar=("NEAR", "FAR"), default=None,
                   help="metres; the automatic mask keeps only depths in this range (default: around the "
                        "depth at the image centre)")
    add_solver_arguments(p)
    p.set_defaults(handler=run)


def run(args) -> int:
    out = check_folder(args.out, args.overwrite, "refinement folder", inputs=[args.capture])
    device, device_line = resolve_device(args.device)
    if args.save_problem is not None:
        check_files([args.save_problem], args.overwrite, inputs=[args.capture])
    capture = read_capture(args.capture, mask=args.mask, depth_range=args.depth_range)
    frame_count_fits("--frames", args.frames, capture.n_frames, f"the capture {args.capture}")
    if not args.quiet:
        print(device_line)
        print(f"masks: {mask_source(args.capture, args.mask, args.depth_range)}")
    given = read_given_poses(args)
    options = replace(options_from_args(args), strict_registration=args.strict)
    if given is not None and not args.quiet:
        print(f"poses: from {given.path}")
    # after the solve only the reference frame's images and the ground truth are read (the accuracy
    # table's baselines, the report page); the capture itself is handed over to refine, which lets go
    # of it once the solver's input is made: its masks, depth images and ground truth are freed before
    # the solve (100 MB at 2 MP) and its other colour frames with the solve's arrays (210 MB at D415
    # size, 440 MB at 2 MP). The ground truth is read again after the solve.
    truth_frames = None if capture.groundtruth is None else capture.n_frames
    capture, handed = replace(capture.reference_only(), groundtruth=None), [capture]
    refinement = refine(handed.pop(), options, device, initial_poses=given, pose_trust=args.pose_trust,
                        save_problem=args.save_problem, overwrite=args.overwrite, checks=not args.no_input_checks)
    if truth_frames is not None:
        capture.groundtruth = read_groundtruth(args.capture, truth_frames, capture.color_size)
    log_energy(refinement, args.quiet)
    views = refinement.info.get("views")
    if views and views["left_out"] and not args.quiet:
        print(ViewSelection.from_dict(views).describe())
    extra = {}
    if capture.groundtruth is not None:
        rows = accuracy_rows(capture, refinement)
        extra["accuracy"] = rows
        if not args.quiet:
            print(markdown_table(rows))
    refinement.info["frame_files"] = frame_files(args.capture)
    report = refinement.save(out, overwrite=args.overwrite, extra_report=extra)
    write_report_page(out, refinement=refinement, capture=capture)
    print_summary(report["summary"], args.quiet)
    print(f"wrote {out}")
    return 0
