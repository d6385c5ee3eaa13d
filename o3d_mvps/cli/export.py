"""``o3d-mvps export``: a refined result folder -> textured mesh, or a print-ready solid."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import ExportError
from ..export import DEFAULT_MAX_DEPTH_JUMP, MESH_SUFFIXES
from .argtypes import positive_float, positive_int
from .outputs import add_overwrite_argument, check_files

DESCRIPTION = """\
Turn a refinement (a folder written by Refinement.save / `o3d-mvps refine`) into a mesh.

  .obj  textured mesh: OUT.obj + OUT.mtl + OUT_albedo.png (albedo texture, sRGB)
  .glb  textured mesh, texture embedded
  .ply  mesh with vertex colours and normals
  .stl  print-ready watertight solid in millimetres (implies --print)

With --print the relief is closed into a solid (walls down to a flat back plate) scaled so its
largest extent is --size-mm; it can be written as .stl, .obj, .glb or .ply.

examples:
  o3d-mvps export out/refined scan.obj --preview scan.png
  o3d-mvps export out/refined scan.stl --size-mm 100 --base-mm 3 --pieces all
"""


def _depth_jump(text: str) -> float | None:
    if text.lower() in ("none", "off"):
        return None
    return positive_float(text)


def _mesh_path(text: str) -> Path:
    path = Path(text)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise argparse.ArgumentTypeError(
            f"{text!r}: unknown mesh format {path.suffix or '(no suffix)'!r}; use one of {', '.join(MESH_SUFFIXES)}"
        )
    return path


def _png_path(text: str) -> Path:
    path = Path(text)
    if path.suffix.lower() != ".png":
        raise argparse.ArgumentTypeError(f"{text!r}: the preview is a PNG image; name it *.png")
    return path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "export", help="refined result -> textured mesh (.obj/.glb/.ply) or print-ready solid (.stl)",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("refined", type=Path, help="folder written by Refinement.save (o3d-mvps refine)")
    parser.add_argument("out", type=_mesh_path, help=f"output mesh: {', '.join(MESH_SUFFIXES)}")
    solid = parser.add_argument_group("print-ready solid")
    solid.add_argument("--print", dest="print_solid", action="store_true",
                       help="close the relief into a watertight solid in millimetres (implied by .stl)")
    solid.add_argument("--size-mm", type=positive_float, default=120.0, metavar="MM",
                       help="largest bounding-box extent of the solid (default: %(default)s)")
    solid.add_argument("--base-mm", type=positive_float, default=4.0, metavar="MM",
                       help="back plate thickness behind the deepest point (default: %(default)s)")
    solid.add_argument("--pieces", choices=["largest", "all"], default="largest",
                       help="keep the largest connected piece or all pieces (default: %(default)s)")
    parser.add_argument("--max-triangles", type=positive_int, metavar="N",
                        help="simplify the relief to at most N triangles (quadric decimation)")
    parser.add_argument("--max-depth-jump", type=_depth_jump, default=DEFAULT_MAX_DEPTH_JUMP, metavar="K",
                        help="cut edges whose depth step exceeds K pixel footprints, i.e. surfaces steeper than "
                             "atan(K) to the image plane; 'none' keeps all (default: %(default)s)")
    parser.add_argument("--preview", type=_png_path, metavar="PNG", help="also render an off-screen preview image")
    add_overwrite_argument(parser, "output file")
    parser.set_defaults(handler=run)


def run(args) -> int:
    from ..export import printable_solid, refinement_to_mesh, write_mesh
    from ..refinement import read_refinement

    out: Path = args.out
    make_solid = args.print_solid or out.suffix.lower() == ".stl"
    targets = [out]  # checked before the (slow) meshing; the writers check again
    if out.suffix.lower() == ".obj" and not make_solid:
        targets += [out.with_suffix(".mtl"), out.with_name(out.stem + "_albedo.png")]
    if args.preview is not None:
        targets.append(args.preview)
    check_files(targets, args.overwrite)
    if not args.refined.is_dir():
        raise ExportError(f"{args.refined} is not a folder; pass the folder written by Refinement.save (o3d-mvps refine)")

    refinement = read_refinement(args.refined)
    if make_solid:
        mesh = printable_solid(refinement, size_mm=args.size_mm, base_mm=args.base_mm, pieces=args.pieces,
                               max_depth_jump=args.max_depth_jump, max_triangles=args.max_triangles)
    else:
        mesh = refinement_to_mesh(refinement, max_depth_jump=args.max_depth_jump, max_triangles=args.max_triangles)
    written = write_mesh(mesh, out, overwrite=args.overwrite)
    if args.preview is not None:
        from ..viz import render_preview

        written.append(render_preview(mesh, args.preview, view="iso" if make_solid else "camera", overwrite=args.overwrite))
    if not args.quiet:
        kind = f"solid, {args.size_mm:g} mm" if make_solid else "mesh"
        print(f"{kind}: {len(mesh.vertex.positions)} vertices, {len(mesh.triangle.indices)} triangles")
    for path in written:
        print(f"wrote {path}")
    return 0
