"""Whole-object reconstruction on rendered 360-degree rings: raw against refined fusion.

For each shipped mesh and light (the LED, room light): a ring of frames
(:func:`o3d_mvps.synthetic.render_ring`, the light model taken from the capture), reconstructed with
the known poses from the sensor depth (bicubic, ``depth="raw"``) and from refined depth, each
scored against the true mesh: accuracy (mean distance of mesh vertices to the true surface),
completeness (mean distance of true surface points to the mesh), Chamfer = their mean (mm),
normal consistency (mean |cos| between mesh normals and the true normal at the nearest true
point), time; the refined run is repeated with 1, 2 and 4 Dask workers, those the machine has
cores for (wall-time ratios to 1 worker), and its print solid checked (trimesh ``is_volume``).
Writes ``object.json`` and ``object.md``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import open3d as o3d

from o3d_mvps import RefineOptions
from o3d_mvps.fileio import json_text
from o3d_mvps.reconstruct import ReconstructOptions, reconstruct

from o3d_mvps.synthetic import render_ring

MESHES = ("bunny", "armadillo")
LIGHTS = ("led", "room")
WORKERS = (1, 2, 4)
FULL = {"frames": 16, "size": (320, 240), "references": 8, "voxel_mm": 2.0, "levels": 3, "iterations": 5}
QUICK = {"frames": 12, "size": (160, 120), "references": 4, "voxel_mm": 3.0, "levels": 2, "iterations": 2}


def add_arguments(parser) -> None:
    parser.add_argument("--meshes", nargs="+", default=list(MESHES), choices=MESHES)
    parser.add_argument("--lights", nargs="+", default=list(LIGHTS), choices=LIGHTS)


def scores(mesh: o3d.t.geometry.TriangleMesh, capture, scene, samples: int = 50000) -> dict:
    """Accuracy, completeness, Chamfer (mm) and normal consistency of ``mesh`` (frame-0 metres)."""
    to_scene = np.linalg.inv(np.asarray(capture.metadata["world_to_camera"][0]))
    legacy = mesh.to_legacy().transform(to_scene)
    vertices = np.asarray(legacy.vertices, dtype=np.float32)
    accuracy = scene.raycaster.compute_distance(o3d.core.Tensor(vertices)).numpy()
    true_points = _true_samples(scene, samples)
    target = o3d.t.geometry.RaycastingScene()
    target.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(legacy))
    completeness = target.compute_distance(o3d.core.Tensor(true_points)).numpy()
    closest = scene.raycaster.compute_closest_points(o3d.core.Tensor(vertices))
    true_normals = closest["primitive_normals"].numpy()
    legacy.compute_vertex_normals()
    consistency = np.abs(np.sum(np.asarray(legacy.vertex_normals) * true_normals, axis=1))
    acc, comp = 1000 * float(accuracy.mean()), 1000 * float(completeness.mean())
    return {"accuracy_mm": acc, "completeness_mm": comp, "chamfer_mm": (acc + comp) / 2,
            "normal_consistency": float(consistency.mean()), "vertices": len(vertices)}


def _true_samples(scene, n: int) -> np.ndarray:
    """n points (float32, scene frame) sampled uniformly on the true (ray-cast) surface's area."""
    positions, tri = scene.vertices, scene.triangles
    a, b, c = (positions[tri[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(0)
    pick = rng.choice(len(tri), n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n))[:, None], rng.random(n)[:, None]
    return ((1 - r1) * a[pick] + r1 * (1 - r2) * b[pick] + r1 * r2 * c[pick]).astype(np.float32)


def run(args) -> None:
    settings = QUICK if args.quick else FULL
    workers_run = [w for w in WORKERS if w <= (os.cpu_count() or 1)]
    rows = []
    for name, light in [(name, light) for name in args.meshes for light in args.lights]:
        capture, scene = render_ring(name, frames=settings["frames"], size=settings["size"], light=light)
        poses = capture.groundtruth.poses
        refine = RefineOptions(levels=settings["levels"], max_iterations=settings["iterations"], progress=False)
        row = {"mesh": name, "light": light, **{k: (list(v) if isinstance(v, tuple) else v) for k, v in settings.items()}}
        row["seconds_by_workers"] = {}
        for depth, workers in [("raw", 1)] + [("refined", w) for w in workers_run]:
            options = ReconstructOptions(references=settings["references"], voxel_mm=settings["voxel_mm"],
                                         depth=depth, refine=refine, workers=workers, progress=False)
            t = time.perf_counter()
            result = reconstruct(capture, options, poses=poses)
            seconds = time.perf_counter() - t
            if depth == "refined":
                row["seconds_by_workers"][workers] = seconds
            if workers > 1:
                continue
            row[depth] = {**scores(result.mesh, capture, scene), "seconds": seconds}
            if depth == "refined":
                import trimesh

                solid = result.printable_solid(80.0)
                row["print_is_volume"] = bool(trimesh.Trimesh(solid.vertex.positions.numpy(),
                                                              solid.triangle.indices.numpy()).is_volume)
        row["chamfer_gain"] = 1 - row["refined"]["chamfer_mm"] / row["raw"]["chamfer_mm"]
        row["wall_time_ratio_to_1_worker"] = {w: s / row["refined"]["seconds"] for w, s in row["seconds_by_workers"].items()}
        rows.append(row)
        print(f"{name}, {light}: Chamfer raw {row['raw']['chamfer_mm']:.3f} mm, refined {row['refined']['chamfer_mm']:.3f} mm "
              f"({100 * row['chamfer_gain']:.0f} % better), wall time to 1 worker {row['wall_time_ratio_to_1_worker']}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "object.json").write_text(json_text(rows, "object benchmark"))
    lines = ["| mesh | light | depth | accuracy (mm) | completeness (mm) | Chamfer (mm) | normal consistency | time (s) |",
             "|---|---|---|---:|---:|---:|---:|---:|"]
    for row in rows:
        for depth in ("raw", "refined"):
            r = row[depth]
            lines.append(f"| {row['mesh']} | {row['light']} | {depth} | {r['accuracy_mm']:.3f} | {r['completeness_mm']:.3f} | "
                         f"{r['chamfer_mm']:.3f} | {r['normal_consistency']:.4f} | {r['seconds']:.1f} |")
    ratios = " | ".join(f"{w}-worker / 1-worker wall time" for w in workers_run[1:])
    lines += ["", f"| mesh | light | refined Chamfer gain | {ratios} | print solid is a volume |",
              "|---|---|---:|" + "---:|" * len(workers_run[1:]) + "---|"]
    lines += [f"| {r['mesh']} | {r['light']} | {100 * r['chamfer_gain']:.0f} % | "
              + "".join(f"{r['wall_time_ratio_to_1_worker'][w]:.2f} | " for w in workers_run[1:])
              + f"{r['print_is_volume']} |" for r in rows]
    left_out = [w for w in WORKERS if w not in workers_run]
    if left_out:
        lines += ["", f"Not run: {', '.join(map(str, left_out))} workers (this machine has {os.cpu_count()} cores)."]
    (out / "object.md").write_text("\n".join(lines) + "\n")
