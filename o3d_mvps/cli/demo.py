"""``o3d-mvps demo``: render a synthetic LED capture of a shipped mesh, refine it, report accuracy."""

from __future__ import annotations

import argparse
import time

from ..capture import write_capture
from ..datasets import DATA_DIR, MESHES
from ..export import printable_solid, write_mesh, write_stl
from ..fileio import atomic_folder, json_text
from ..refinement import REPORT_JSON
from ..report import accuracy_rows, markdown_table
from ..report_page import write_report_page
from ..solver.device import DEVICE_HELP, resolve_device
from ..solver.options import RefineOptions
from ..solving import refine
from ..synthetic import render_capture
from ..viz import render_preview
from .argtypes import image_size, nonnegative_int, positive_int
from .outputs import add_overwrite_argument, check_folder, log_energy, print_summary

DESCRIPTION = """\
Render a synthetic LED-lit capture of a shipped mesh, refine it and report the accuracy
against the baselines. Writes into OUT: capture/ (the rendered capture), refined/ (the
refinement, with report.html: plots and a 3D view for a browser), report.md (accuracy table),
mesh.obj (+ .mtl + albedo texture), mesh.glb, print.stl (print-ready solid) and preview.png.
"""

EXAMPLES = """\
examples:
  o3d-mvps demo --out out/demo
  o3d-mvps demo --out out/arma --mesh armadillo --frames 20 --overwrite
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="render, refine and report on a shipped mesh", description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EXAMPLES)
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    add_overwrite_argument(p, "demo folder")
    p.add_argument("--mesh", default="bunny", choices=sorted(MESHES), help="shipped mesh (default bunny)")
    p.add_argument("--frames", type=positive_int, default=20, metavar="N",
                   help="number of frames to render, all used (default 20)")
    p.add_argument("--scale-factor", type=positive_int, default=4, help="depth super-resolution factor (default 4)")
    p.add_argument("--size", type=image_size, default=(640, 480), metavar="WxH", help="colour resolution (default 640x480)")
    p.add_argument("--seed", type=nonnegative_int, default=0,
                   help="seed of the rendered albedo texture and sensor noise; the same seed gives the same "
                        "capture, bit for bit, and the same printed accuracy (default 0)")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    p.set_defaults(handler=run)


def run(args) -> int:
    out = check_folder(args.out, args.overwrite, "demo folder")
    device, device_line = resolve_device(args.device)
    say = (lambda *a: None) if args.quiet else print
    t0 = time.perf_counter()
    say(f"rendering {args.frames} LED-lit frames of the {args.mesh} (see {DATA_DIR / 'PROVENANCE.md'}) ...")
    capture = render_capture(args.mesh, frames=args.frames, scale_factor=args.scale_factor,
                             size=args.size, seed=args.seed, progress=not args.quiet)
    say(f"refining ... ({device_line})")
    refinement = refine(capture, RefineOptions(frames=args.frames, progress=not args.quiet), device)  # as many as asked for
    log_energy(refinement, args.quiet)
    rows = accuracy_rows(capture, refinement)
    table = markdown_table(rows)
    with atomic_folder(out, overwrite=args.overwrite, what="demo folder") as tmp:
        write_capture(capture, tmp / "capture")
        saved = refinement.save(tmp / "refined", extra_report={"accuracy": rows})
        saved["summary"]["outputs"] = str(out / "refined")  # where it will be, not the staging folder
        (tmp / "refined" / REPORT_JSON).write_text(json_text(saved, "the refinement report"))
        report = [f"# o3d_mvps demo: {args.mesh}, {args.size[0]}x{args.size[1]}, SF {args.scale_factor}, {args.frames} frames", "",
                  table, "", f"total time {time.perf_counter() - t0:.1f} s "
                  f"(refinement {refinement.timings.get('total', 0):.1f} s)", ""]
        (tmp / "report.md").write_text("\n".join(report))
        say("exporting the textured mesh, the print-ready solid and a preview ...")
        mesh = refinement.to_mesh()
        write_mesh(mesh, tmp / "mesh.obj")
        write_mesh(mesh, tmp / "mesh.glb")
        write_stl(printable_solid(refinement), tmp / "print.stl")
        render_preview(mesh, tmp / "preview.png")
    write_report_page(out / "refined", refinement=refinement, capture=capture)
    say(table)
    print_summary(saved["summary"], args.quiet)
    print(f"wrote {out}")
    return 0
