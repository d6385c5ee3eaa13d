"""Pictures for the README and the docs: normals of every method next to the truth, and a textured preview.

Writes ``normals_<mesh>.png`` (ground truth, bicubic, guided, ours; normals as RGB) and
``preview_<mesh>.png`` (the refined mesh with its albedo texture, pyvista off-screen); with
``--reconstruct PATH`` only the whole-object picture instead: the textured mesh reconstructed
from a rendered ring next to its print solid.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from o3d_mvps import RefineOptions, refine
from o3d_mvps.baselines import bicubic, guided
from o3d_mvps.metrics import evaluate
from o3d_mvps.reconstruct import ReconstructOptions, reconstruct
from o3d_mvps.reconstruct.solid import print_frame
from o3d_mvps.synthetic import render_capture
from o3d_mvps.viz import render_preview

from .plots import image_row


def normals_picture(normals: np.ndarray, mask: np.ndarray, box: tuple) -> np.ndarray:
    """(h, w, 3) uint8 RGB tile of unit normals (H, W, 3) as (n + 1) / 2, white off the mask, cropped to box."""
    r0, r1, c0, c1 = box
    return np.where(mask[..., None], (normals + 1.0) * 127.5, 255.0)[r0:r1, c0:c1].astype(np.uint8)


def add_arguments(parser) -> None:
    parser.add_argument("--mesh", default="bunny")
    parser.add_argument("--reconstruct", type=Path, default=None, metavar="PNG",
                        help="only write the whole-object picture (textured mesh and print solid) here")


def reconstruct_picture(mesh: str, path: Path, quick: bool) -> None:
    """The textured mesh reconstructed from a rendered ring of ``mesh`` beside its print solid
    (both turned up and seen obliquely from above), as one PNG."""
    from o3d_mvps.synthetic import render_ring

    frames, size, references = (12, (160, 120), 4) if quick else (16, (320, 240), 8)
    capture, _ = render_ring(mesh, frames=frames, size=size)
    options = ReconstructOptions(references=references, voxel_mm=2.0, progress=False,
                                 refine=RefineOptions(levels=3, max_iterations=5, progress=False))
    result = reconstruct(capture, options, poses=capture.groundtruth.poses)
    solid = result.printable_solid(80.0)
    textured = result.mesh.clone()  # the mesh in the solid's print frame (mm, up = +z)
    textured.vertex.positions = o3d.core.Tensor(
        print_frame(textured.vertex.positions.numpy().astype(np.float64), result.up, 80.0).astype(np.float32))
    textured.compute_vertex_normals()
    with tempfile.TemporaryDirectory() as tmp:
        tiles = []
        for name, shown in (("mesh", textured), ("solid", solid)):
            render_preview(shown, Path(tmp) / f"{name}.png", size=(480, 480), view="iso")
            tiles.append(cv2.cvtColor(cv2.imread(str(Path(tmp) / f"{name}.png")), cv2.COLOR_BGR2RGB))
    image_row(path, tiles, ["textured mesh (albedo texture)", "print solid (80 mm, closed)"], width=4.0)
    print(f"wrote {path}")


def run(args) -> None:
    if args.reconstruct is not None:
        reconstruct_picture(args.mesh, args.reconstruct, args.quick)
        return
    size, frames = ((320, 240), 6) if args.quick else ((640, 480), 20)
    capture = render_capture(args.mesh, frames=frames, scale_factor=4, size=size, seed=0)
    gt = capture.groundtruth
    mask = gt.depth > 0
    rows, cols = np.nonzero(mask)
    box = (max(rows.min() - 8, 0), rows.max() + 8, max(cols.min() - 8, 0), cols.max() + 8)
    ours = refine(capture, RefineOptions(progress=False))
    tiles, titles = [normals_picture(gt.normals, mask, box)], ["ground truth"]
    for name, result in (("bicubic", bicubic(capture)), ("guided", guided(capture)), ("ours", ours)):
        tiles.append(normals_picture(result.normals_array(), result.mask_array(), box))
        titles.append(f"{name}: MAE {evaluate(result, gt)['mae_deg']:.2f} deg")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    image_row(out / f"normals_{args.mesh}.png", tiles, titles,
              title=f"Normals as RGB, {args.mesh}, SF 4, {frames} frames, {size[0]}x{size[1]}")
    render_preview(ours.to_mesh(), out / f"preview_{args.mesh}.png", size=(640, 480), overwrite=True)
    print(f"wrote {out / f'normals_{args.mesh}.png'} and {out / f'preview_{args.mesh}.png'}")
