"""SolverOutput: what the solver returns for the reference view, and its .npz file."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..fileio import atomic_files, json_text

SOLUTION_FORMAT, SOLUTION_VERSION = "o3d_mvps.solver_output", 1
#: Columns of the energy log array; cg_iterations is NaN on a level's first row (before any sweep).
ENERGY_COLUMNS = ("level", "iteration", "energy", "cg_iterations")


@dataclass
class SolverOutput:
    """The refined reference view at colour resolution (H, W).

    depth: (H, W) float64 metres, 0 outside the mask. mask: (H, W) bool reference mask. albedo:
    (H, W, 3) float64 linear RGB, 0 outside the mask. K: (3, 3) float64 colour intrinsics.
    lighting: (n, k) float64 per frame (k = 2 LED ambient and intensity, 4 first-order SH). poses:
    (n, 4, 4) float64 reference -> frame i. energy: rows {"level", "iteration", "energy",
    "cg_iterations"}. timings: seconds per stage. info: frames used, options, light model, solver
    statistics.
    """

    depth: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray
    K: np.ndarray
    lighting: np.ndarray
    poses: np.ndarray
    energy: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    def energy_array(self) -> np.ndarray:
        """The energy log as an (m, 4) float64 array of :data:`ENERGY_COLUMNS`."""
        return np.array([[row.get(c, np.nan) for c in ENERGY_COLUMNS] for row in self.energy],
                        dtype=np.float64).reshape(-1, len(ENERGY_COLUMNS))


def write_solution(output: SolverOutput, path, *, overwrite: bool = False) -> Path:
    """Write ``output`` to the .npz ``path`` (refuses an existing file unless ``overwrite``).

    Keys: format, format_version, depth, mask, albedo, K, lighting, poses, energy (m, 4) with
    energy_columns, report (JSON: energy rows, timings, info).
    """
    path = Path(path)
    report = json_text({"energy": output.energy, "timings": output.timings, "info": output.info}, "the solver report")
    with atomic_files([path], overwrite) as (tmp,), open(tmp, "wb") as file:
        np.savez_compressed(file, format=np.array(SOLUTION_FORMAT), format_version=np.array(SOLUTION_VERSION),
                            depth=output.depth, mask=output.mask, albedo=output.albedo, K=output.K,
                            lighting=output.lighting, poses=output.poses, energy=output.energy_array(),
                            energy_columns=np.array(ENERGY_COLUMNS), report=np.array(report))
    return path
