#!/usr/bin/env python
"""360-degree reconstruction: refine several reference views, fuse them in an Open3D TSDF.

Each reference frame is refined with its neighbouring frames (o3d_mvps.refine_rgbd: Open3D
RGB-D images in, refined RGB-D image out) and its super-resolved depth is integrated into an
o3d.t.geometry.VoxelBlockGrid; a mesh is then extracted. For comparison the raw depth (the
sensor's depth, bicubic-upsampled to colour resolution, same object masks) is fused the
same way.

Input is a synthetic 360-degree ring rendered here (o3d_mvps.synthetic: a shipped mesh, LED
light, sensor noise), so the Chamfer distance of both meshes to the true surface can be
reported: accuracy = mean distance of the mesh vertices to the true mesh, completeness = mean
distance of true surface points seen by the reference views to the mesh, Chamfer = their
average (millimetres). The ring's poses are taken as known, as Open3D's reconstruction system
(pose graph) would give them for a real capture: they initialise each refinement (which
refines the neighbours' poses) and place every fused view, for both fusions, so only the
depth differs.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d
from _common import run_main, say

from o3d_mvps import RefineOptions, refine_rgbd
from o3d_mvps.baselines import bicubic
from o3d_mvps.cli.argtypes import image_size, positive_float, positive_int
from o3d_mvps.cli.outputs import add_overwrite_argument, check_folder
from o3d_mvps.colour import linear_to_srgb
from o3d_mvps.datasets import MESHES
from o3d_mvps.fileio import atomic_folder
from o3d_mvps.integration import capture_from_rgbd
from o3d_mvps.model.camera import transform
from o3d_mvps.synthetic import (
    DEPTH_SCALE,
    random_stream,
    build_scene,
    make_light,
    quantise_srgb8,
    render_frame,
    ring_trajectory,
    simulate_depth_sensor,
)

EXAMPLES = """examples:
  python pipelines/reconstruct_tsdf.py --out out/tsdf
  python pipelines/reconstruct_tsdf.py --size 320x240 --ring-frames 24 --references 6 --neighbours 2
"""

DEPTH_MAX_M = 3.0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="reconstruct_tsdf.py", description=__doc__, epilog=EXAMPLES,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    ring = parser.add_argument_group("synthetic 360-degree ring")
    ring.add_argument("--mesh", default="bunny", choices=sorted(MESHES), help="shipped mesh (default bunny)")
    ring.add_argument("--size", type=image_size, default=(640, 480), metavar="WxH", help="colour size (default 640x480)")
    ring.add_argument("--scale-factor", type=positive_int, default=4, help="depth super-resolution factor (default 4)")
    ring.add_argument("--ring-frames", type=positive_int, default=48, help="frames around the ring (default 48)")
    ring.add_argument("--elevation", type=float, default=15.0, help="camera elevation in degrees (default 15)")
    ring.add_argument("--seed", type=int, default=0)
    fusion = parser.add_argument_group("refinement and fusion")
    fusion.add_argument("--references", type=positive_int, default=12,
                        help="reference views refined and fused, evenly spaced (default 12)")
    fusion.add_argument("--neighbours", type=positive_int, default=2,
                        help="frames on each side of a reference refined with it (default 2)")
    fusion.add_argument("--levels", type=positive_int, default=5, help="pyramid levels (default 5)")
    fusion.add_argument("--iterations", type=positive_int, default=10, help="sweep cap per level (default 10)")
    fusion.add_argument("--tau", type=positive_float, default=10.0, help="depth-prior weight (default 10)")
    fusion.add_argument("--voxel-mm", type=positive_float, default=1.5, help="TSDF voxel size (default 1.5 mm)")
    parser.add_argument("--out", type=Path, help="write raw_mesh.ply, refined_mesh.ply and report.json here")
    add_overwrite_argument(parser, "output folder")
    parser.add_argument("--quiet", action="store_true", help="no logs")
    return parser


def render_ring(args):
    """(scene, poses (n, 4, 4) scene -> frame i, RGBD images, masks (H, W) bool, true frames)."""
    scene = build_scene(args.mesh, size=args.size, seed=args.seed)
    poses = ring_trajectory(args.ring_frames, scene.distance, args.elevation)
    light = make_light("led", scene.distance)
    color_rng, depth_rng = random_stream(args.seed, "color"), random_stream(args.seed, "depth")
    images, masks, renders = [], [], []
    for pose in poses:
        frame = render_frame(scene, pose, light)
        srgb = np.rint(linear_to_srgb(quantise_srgb8(frame.color, color_rng)) * 255).astype(np.uint8)
        z = simulate_depth_sensor(frame.depth, args.scale_factor, depth_rng)
        depth = np.rint(z * DEPTH_SCALE).astype(np.uint16)[..., None]
        images.append(o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(o3d.core.Tensor(srgb)),
                                               o3d.t.geometry.Image(o3d.core.Tensor(depth)), False))
        masks.append(frame.mask)
        renders.append(frame)
    return scene, poses, images, masks, renders


def new_grid(voxel_m: float) -> o3d.t.geometry.VoxelBlockGrid:
    return o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight", "color"),
                                         (o3d.core.float32, o3d.core.float32, o3d.core.float32),
                                         ((1), (1), (3)), voxel_m, 16, 50000, o3d.core.Device("CPU:0"))


def integrate(grid, depth: np.ndarray, color, K: np.ndarray, extrinsic: np.ndarray) -> None:
    """Fuse (H, W) float32 metres depth with its colour image; extrinsic: world -> camera (4, 4)."""
    depth_image = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(depth, np.float32)[..., None]))
    K, T = o3d.core.Tensor(K), o3d.core.Tensor(extrinsic)
    coords = grid.compute_unique_block_coordinates(depth_image, K, T, 1.0, DEPTH_MAX_M)
    grid.integrate(coords, depth_image, color.to(o3d.core.float32, scale=1.0 / 255), K, T, 1.0, DEPTH_MAX_M)


def chamfer_mm(mesh: o3d.t.geometry.TriangleMesh, scene, true_points: np.ndarray) -> dict:
    """Accuracy, completeness and Chamfer distance (mm) of ``mesh`` to the true surface."""
    vertices = mesh.vertex.positions.numpy()
    if len(vertices) == 0:
        raise ValueError("the fused mesh is empty; use more references or a larger --voxel-mm")
    accuracy = scene.raycaster.compute_distance(o3d.core.Tensor(vertices.astype(np.float32))).numpy()
    target = o3d.t.geometry.RaycastingScene()
    target.add_triangles(mesh.cpu())
    completeness = target.compute_distance(o3d.core.Tensor(true_points.astype(np.float32))).numpy()
    acc, comp = 1000 * float(accuracy.mean()), 1000 * float(completeness.mean())
    return {"accuracy_mm": acc, "completeness_mm": comp, "chamfer_mm": (acc + comp) / 2,
            "accuracy_median_mm": 1000 * float(np.median(accuracy)), "vertices": len(vertices)}


def run(args) -> int:
    n = args.ring_frames
    if 2 * args.neighbours + 1 > n or args.references > n:
        raise ValueError(f"--ring-frames {n} is too few for --references {args.references} and "
                         f"--neighbours {args.neighbours}; render more frames")
    if args.out is not None:
        check_folder(args.out, args.overwrite, "output folder")
    t0 = time.perf_counter()
    scene, poses, images, masks, renders = render_ring(args)
    K = scene.K
    say(args, f"rendered {n} frames around the {args.mesh} in {time.perf_counter() - t0:.1f} s")
    options = RefineOptions(tau=args.tau, levels=args.levels, max_iterations=args.iterations, progress=False)
    grids = {"raw": new_grid(args.voxel_mm / 1000), "refined": new_grid(args.voxel_mm / 1000)}
    true_points = []
    references = [round(k * n / args.references) % n for k in range(args.references)]
    for k in references:
        t = time.perf_counter()
        order = [k] + [(k + s * j) % n for j in range(1, args.neighbours + 1) for s in (-1, 1)]
        frames, frame_masks = [images[i] for i in order], [masks[i] for i in order]
        relative = np.array([poses[i] @ np.linalg.inv(poses[k]) for i in order])  # reference k -> frame i
        refined, _ = refine_rgbd(frames, K, options=options, masks=frame_masks, initial_poses=relative)
        raw = bicubic(capture_from_rgbd(frames, K, masks=frame_masks)).depth_array()
        integrate(grids["refined"], refined[0].depth.as_tensor().numpy()[..., 0], images[k].color, K, poses[k])
        integrate(grids["raw"], raw, images[k].color, K, poses[k])
        seen = renders[k].points[renders[k].mask]  # true surface seen by this reference, camera k
        true_points.append(transform(np.linalg.inv(poses[k]), seen))
        say(args, f"reference {k:3d} (frames {order}): {time.perf_counter() - t:.1f} s")
    true_points = np.concatenate(true_points)[:: max(1, sum(map(len, true_points)) // 200_000)]

    results, meshes = {}, {}
    for name, grid in grids.items():
        meshes[name] = grid.extract_triangle_mesh(weight_threshold=1.0)
        results[name] = chamfer_mm(meshes[name], scene, true_points)
    lines = ["| depth | accuracy (mm) | completeness (mm) | Chamfer (mm) | vertices |", "|---|---:|---:|---:|---:|"]
    lines += [f"| {k} | {r['accuracy_mm']:.3f} | {r['completeness_mm']:.3f} | {r['chamfer_mm']:.3f} | {r['vertices']} |"
              for k, r in results.items()]
    say(args, "\n".join(lines))
    say(args, f"total {time.perf_counter() - t0:.1f} s")
    if args.out is not None:
        report = {"settings": {k: (list(v) if isinstance(v, tuple) else str(v) if isinstance(v, Path) else v)
                               for k, v in vars(args).items()},
                  "references": references, "results": results}
        with atomic_folder(args.out, overwrite=args.overwrite, what="output folder") as tmp:
            for name, mesh in meshes.items():
                o3d.t.io.write_triangle_mesh(str(tmp / f"{name}_mesh.ply"), mesh)
            (tmp / "report.json").write_text(json.dumps(report, indent=2))
            (tmp / "report.md").write_text("\n".join(lines) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(build_parser(), run))
