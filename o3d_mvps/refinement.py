"""The Refinement result type shared by the solver and the baselines."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from .capture import image_from_array, load_json, read_intrinsic_json
from .colour import linear_to_srgb
from .errors import MVPSError
from .fileio import atomic_folder, json_text, write_intrinsic_json, write_png
from .model.camera import as_intrinsic_matrix
from .model.normals import perspective_normals

#: Files of a saved refinement folder (see Refinement.save).
DEPTH_NPY, DEPTH_PNG, MASK_PNG = "depth.npy", "depth_mm.png", "mask.png"
ALBEDO_NPY, ALBEDO_PNG, NORMALS_NPY, NORMALS_PNG = "albedo.npy", "albedo.png", "normals.npy", "normals.png"
POSES_NPY, LIGHTING_JSON, INTRINSIC_JSON, REPORT_JSON = "poses.npy", "lighting.json", "intrinsic.json", "report.json"
REFINEMENT_FILES = (DEPTH_NPY, DEPTH_PNG, MASK_PNG, ALBEDO_NPY, ALBEDO_PNG, NORMALS_NPY, NORMALS_PNG, POSES_NPY,
                    LIGHTING_JSON, INTRINSIC_JSON, REPORT_JSON)


@dataclass
class Refinement:
    """What a depth refinement method returns, at colour resolution (H, W).

    depth: (H, W, 1) float32 metres, 0 outside the mask. normals: (H, W, 3) float32 unit
    normals in the reference camera frame pointing to the camera, 0 outside the mask.
    albedo: (H, W, 3) float32 linear RGB, or None for methods that do not estimate it.
    mask: (H, W, 1) uint8, 255 where the method returns depth. intrinsic: (3, 3) float64
    colour intrinsics. poses: (n, 4, 4) float64 reference -> frame i, or None. lighting:
    (n, k) float64 per frame, or None: k = 2 (LED ambient, intensity) or 4 (first-order SH);
    ``info["light_model"]`` names the model (and the LED offset). energy: rows {"level", "iteration",
    "energy", "cg_iterations"} (the sweep's depth or joint step's CG iterations). timings: seconds per stage. method: the method's name.
    """

    depth: o3d.t.geometry.Image
    normals: o3d.t.geometry.Image
    mask: o3d.t.geometry.Image
    intrinsic: o3d.core.Tensor
    albedo: o3d.t.geometry.Image | None = None
    poses: o3d.core.Tensor | None = None
    lighting: o3d.core.Tensor | None = None
    energy: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    method: str = "ours"
    info: dict = field(default_factory=dict)

    # numpy views -------------------------------------------------------------------------
    def depth_array(self) -> np.ndarray:
        """(H, W) float32 metres, 0 outside the mask."""
        a = self.depth.as_tensor().numpy()
        return np.asarray(a, dtype=np.float32).reshape(a.shape[0], a.shape[1])

    def normals_array(self) -> np.ndarray:
        """(H, W, 3) float32 unit normals, 0 outside the mask."""
        return np.asarray(self.normals.as_tensor().numpy(), dtype=np.float32)

    def mask_array(self) -> np.ndarray:
        """(H, W) bool."""
        a = self.mask.as_tensor().numpy()
        return a.reshape(a.shape[0], a.shape[1]) > 0

    def albedo_array(self) -> np.ndarray | None:
        """(H, W, 3) float32 linear RGB, or None."""
        return None if self.albedo is None else np.asarray(self.albedo.as_tensor().numpy(), dtype=np.float32)

    def intrinsic_matrix(self) -> np.ndarray:
        """(3, 3) float64 colour intrinsics."""
        return as_intrinsic_matrix(self.intrinsic)

    def to_mesh(self, **kwargs) -> o3d.t.geometry.TriangleMesh:
        """Textured triangle mesh of the depth inside the mask (see :func:`o3d_mvps.export.refinement_to_mesh`)."""
        from .export import refinement_to_mesh

        return refinement_to_mesh(self, **kwargs)

    def report(self) -> dict:
        """The JSON-ready report of the run (written as report.json by :meth:`save`): method,
        energy (every sweep) and energy_per_level, timings, info, inputs (checks and conventions
        found), frames (every capture frame: used, or dropped and why), poses (how far each moved
        from its start, mm and degrees), light, residuals (per frame), device, peak_memory_mb,
        warnings and a summary (:mod:`o3d_mvps.run_report`)."""
        from .run_report import refinement_report

        return refinement_report(self)

    def save(self, folder, *, overwrite: bool = False, extra_report: dict | None = None) -> dict:
        """Write the result folder all or nothing (never over an earlier output unless ``overwrite``;
        then only the files below are replaced, any other file in the folder stays).

        Files: depth.npy (H, W) float32 metres and depth_mm.png uint16 millimetres, mask.png,
        normals.npy (H, W, 3) and normals.png ((n + 1) / 2 as 8-bit RGB), albedo.npy (linear)
        and albedo.png (8-bit sRGB) when estimated, poses.npy (n, 4, 4), lighting.json,
        intrinsic.json (Open3D PinholeCameraIntrinsic), report.json (:meth:`report`, plus
        ``extra_report``'s keys; its summary names the folder). Returns that report.
        """
        depth, mask, normals, albedo = self.depth_array(), self.mask_array(), self.normals_array(), self.albedo_array()
        report = {**self.report(), **(extra_report or {})}
        report["summary"]["outputs"] = os.path.abspath(os.path.expanduser(folder))
        text = json_text(report, "the refinement report")
        with atomic_folder(folder, overwrite=overwrite, what="refinement folder", layout=REFINEMENT_FILES) as tmp:
            np.save(tmp / DEPTH_NPY, depth)
            write_png(tmp / DEPTH_PNG, np.clip(np.rint(depth * 1000.0), 0, 65535).astype(np.uint16))
            write_png(tmp / MASK_PNG, mask.astype(np.uint8) * np.uint8(255))
            np.save(tmp / NORMALS_NPY, normals)
            write_png(tmp / NORMALS_PNG, np.rint((normals + 1.0) * 127.5 * mask[..., None]).astype(np.uint8))
            if albedo is not None:
                np.save(tmp / ALBEDO_NPY, albedo)
                write_png(tmp / ALBEDO_PNG, np.rint(linear_to_srgb(albedo) * 255.0).astype(np.uint8))
            if self.poses is not None:
                np.save(tmp / POSES_NPY, self.poses.numpy())
            if self.lighting is not None:
                model = self.info.get("light_model", {"model": "sh",
                                                      "formula": "shading = l . [1, n_x, n_y, n_z]"})
                lighting = {**model, "lighting": self.lighting.numpy().tolist()}
                (tmp / LIGHTING_JSON).write_text(json_text(lighting, "lighting"))
            write_intrinsic_json(tmp / INTRINSIC_JSON, self.intrinsic_matrix(), depth.shape)
            (tmp / REPORT_JSON).write_text(text)
        return report

    @classmethod
    def from_arrays(cls, depth: np.ndarray, mask: np.ndarray, K: np.ndarray, *, albedo=None, poses=None,
                    lighting=None, method: str = "ours", **kwargs) -> "Refinement":
        """Build a Refinement from numpy arrays; normals are computed from depth (perspective
        normals, the paper's section 3.2).

        depth (H, W) metres, mask (H, W) bool, K (3, 3), albedo (H, W, 3) or None,
        poses (n, 4, 4) or None, lighting (n, k) or None (k = 4 SH, 2 LED).
        """
        mask = np.asarray(mask, dtype=bool) & (np.asarray(depth) > 0)
        depth = np.where(mask, depth, 0.0).astype(np.float32)
        normals, _ = perspective_normals(depth, K, mask)
        tensor = lambda a: None if a is None else o3d.core.Tensor(np.asarray(a, dtype=np.float64))  # noqa: E731
        return cls(
            depth=image_from_array(depth[..., None]),
            normals=image_from_array(normals.astype(np.float32)),
            mask=image_from_array((mask.astype(np.uint8) * 255)[..., None]),
            intrinsic=o3d.core.Tensor(np.asarray(K, dtype=np.float64)),
            albedo=None if albedo is None else image_from_array(np.asarray(albedo, dtype=np.float32)),
            poses=tensor(poses),
            lighting=tensor(lighting),
            method=method,
            **kwargs,
        )


def read_refinement(folder) -> Refinement:
    """Read a folder written by :meth:`Refinement.save`."""
    root = Path(folder)
    if not (root / DEPTH_NPY).is_file():
        raise MVPSError(f"{root} is not a refinement folder ({DEPTH_NPY} missing); give the folder that "
                        "'o3d-mvps refine' or Refinement.save wrote")
    try:
        depth = np.load(root / DEPTH_NPY, allow_pickle=False)
        albedo = np.load(root / ALBEDO_NPY, allow_pickle=False) if (root / ALBEDO_NPY).is_file() else None
        poses = np.load(root / POSES_NPY, allow_pickle=False) if (root / POSES_NPY).is_file() else None
    except (OSError, ValueError) as e:
        raise MVPSError(f"cannot read the arrays in {root} ({e}); the folder is corrupt: refine again") from None
    mask_image = cv2.imread(str(root / MASK_PNG), cv2.IMREAD_UNCHANGED)
    mask = depth > 0 if mask_image is None else mask_image > 0
    K, _ = read_intrinsic_json(root / INTRINSIC_JSON)
    lighting = load_json(root / LIGHTING_JSON)["lighting"] if (root / LIGHTING_JSON).is_file() else None
    report = load_json(root / REPORT_JSON) if (root / REPORT_JSON).is_file() else {}
    refinement = Refinement.from_arrays(depth, mask, K, albedo=albedo, poses=poses, lighting=lighting,
                                        method=report.get("method", "ours"), energy=report.get("energy", []),
                                        timings=report.get("timings", {}), info=report.get("info", {}))
    if (root / NORMALS_NPY).is_file():
        refinement.normals = image_from_array(np.load(root / NORMALS_NPY, allow_pickle=False).astype(np.float32))
    return refinement
