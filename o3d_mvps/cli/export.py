"""``o3d-mvps export``: a refined result folder -> textured mesh, or a print-ready solid."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import ExportError
from ..export import DEFAULT_MAX_DEPTH_JUMP, DEFAULT_SIZE_MM, MESH_SUFFIXES
from .argtypes import deprecated_alias, positive_float, positive_int
from .outputs import add_overwrite_argument, check_files

DESCRIPTION = """\
Turn a refinement (a folder written by Refinement.save / `o3d-mvps refine`) into a mesh, or
convert the whole-object mesh of an `o3d-mvps reconstruct` folder (its mesh.ply, with vertex
colours; --max-triangles simplifies it; .stl or --print MM rescale its print.stl, from reconstruct
--print MM, to MM millimetres).

  .obj  textured mesh: OUT.obj + OUT.mtl + OUT_albedo.png (albedo texture, sRGB)
  .glb  textured mesh, texture embedded
  .ply  mesh with vertex colours and normals
  .stl  print-ready watertight solid in millimetres (implies --print, 120 mm unless --print MM)

With --print MM the relief is closed into a solid (walls down to a flat back plate) scaled so its
largest extent is MM millimetres, as with `o3d-mvps reconstruct --print MM`; it can be written as
.stl, .obj, .glb or .ply. (--size-mm MM is the old spelling of --print MM: it still works, with a
warning.)

examples:
  o3d-mvps export out/refined scan.obj --preview scan.png
  o3d-mvps export out/refined scan.stl --print 100 --base-mm 3 --pieces all
  o3d-mvps export out/object object_small.glb --max-triangles 50000   # a reconstruct folder
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
    parser.add_argument("refined", type=Path, metavar="FOLDER",
                        help="folder written by o3d-mvps refine (Refinement.save) or o3d-mvps reconstruct")
    parser.add_argument("out", type=_mesh_path, help=f"output mesh: {', '.join(MESH_SUFFIXES)}")
    solid = parser.add_argument_group("print-ready solid")
    solid.add_argument("--print", dest="print_mm", type=positive_float, nargs="?", const=DEFAULT_SIZE_MM,
                       default=None, metavar="MM",
                       help="close the relief into a watertight solid MM millimetres across (its largest "
                            f"bounding-box extent), as reconstruct --print MM; implied by .stl, where MM "
                            f"defaults to {DEFAULT_SIZE_MM:g}")
    solid.add_argument("--size-mm", dest="size_mm_alias", type=positive_float, default=None, metavar="MM",
                       action=deprecated_alias("--print MM"), help="deprecated spelling of --print MM")
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
    args.size_mm = _print_size(args)
    make_solid = args.size_mm is not None or out.suffix.lower() == ".stl"
    args.size_mm = DEFAULT_SIZE_MM if args.size_mm is None else args.size_mm
    targets = [out]  # checked before the (slow) meshing; the writers check again
    if out.suffix.lower() == ".obj" and not make_solid:
        targets += [out.with_suffix(".mtl"), out.with_name(out.stem + "_albedo.png")]
    if args.preview is not None:
        targets.append(args.preview)
    check_files(targets, args.overwrite)
    if not args.refined.is_dir():
        raise ExportError(f"{args.refined} is not a folder; pass the folder written by o3d-mvps refine "
                          "(Refinement.save) or o3d-mvps reconstruct")

    from ..reconstruct.api import is_reconstruction_folder

    if is_reconstruction_folder(args.refined):
        mesh = _reconstruction_mesh(args, make_solid)
    elif make_solid:
        refinement = read_refinement(args.refined)
        mesh = printable_solid(refinement, size_mm=args.size_mm, base_mm=args.base_mm, pieces=args.pieces,
                               max_depth_jump=args.max_depth_jump, max_triangles=args.max_triangles)
    else:
        mesh = refinement_to_mesh(read_refinement(args.refined), max_depth_jump=args.max_depth_jump,
                                  max_triangles=args.max_triangles)
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


def _print_size(args) -> float | None:
    """The solid's size in mm from --print MM (or its old spelling --size-mm MM); None without either."""
    size, alias = args.print_mm, args.size_mm_alias
    if alias is not None and size not in (None, DEFAULT_SIZE_MM, alias):
        raise ExportError(f"--print {size:g} and --size-mm {alias:g} disagree; --size-mm is the old spelling of "
                          "--print MM: pass only --print MM")
    return alias if alias is not None else size


def _reconstruction_mesh(args, make_solid: bool):
    """The mesh of a reconstruct folder, simplified to --max-triangles; for a print solid, the folder's
    print.stl (from reconstruct --print MM) rescaled to --print MM, else the mesh itself when it is closed."""
    import open3d as o3d

    from ..export import mesh_arrays, simplify_mesh
    from ..reconstruct.api import read_reconstruction
    from ..reconstruct.solid import mesh_solid

    mesh, report = read_reconstruction(args.refined)
    up = report.get("up", [0.0, -1.0, 0.0])
    if make_solid and (args.refined / "print.stl").is_file():
        solid = o3d.io.read_triangle_mesh(str(args.refined / "print.stl"))  # mm, +z up; STL repeats vertices
        mesh, up = o3d.t.geometry.TriangleMesh.from_legacy(solid.remove_duplicated_vertices()), [0.0, 0.0, 1.0]
    if args.max_triangles is not None:
        mesh = simplify_mesh(mesh, args.max_triangles)
    if not make_solid:
        return mesh
    positions, triangles = mesh_arrays(mesh)[:2]
    try:
        return mesh_solid(positions, triangles, up, args.size_mm)
    except ExportError as err:
        span = report.get("azimuth_span_deg")
        seen = f"; the frames cover {span:g} degrees" if isinstance(span, (int, float)) else ""
        raise ExportError(f"the mesh in {args.refined} is not closed (the object's underside is never seen{seen}), "
                          f"so it is no solid ({err}). Make the print solid with the reconstruction, which closes it "
                          f"from the views' depths: 'o3d-mvps reconstruct CAPTURE {args.refined} --overwrite --print "
                          f"{args.size_mm:g}'; then 'o3d-mvps export {args.refined} OUT.stl --print MM' rescales "
                          "its print.stl") from None
