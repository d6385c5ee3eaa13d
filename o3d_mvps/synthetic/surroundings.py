"""Scene mode's room around the object: a table top it stands on and a wall behind it.

Both are planes in the scene's reference frame (the level camera the object was placed for:
x right, y down, z forward; the object centre at ``(0, 0, distance)``), added to the ray caster
as two rectangles of two triangles each. Their albedo is textured (wood grain on the table,
a faint mottle on the wall) so that colour-based registration sees what it would in a room.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

TABLE_HALF_WIDTH = 0.5  # metres around the object centre, in x and z
WALL_BEHIND = 0.8  # metres behind the object centre (cameras on a 0.6 m ring stay in front)
WALL_HALF_WIDTH, WALL_HEIGHT = 2.0, 1.5  # metres
TABLE_ALBEDO = (0.55, 0.40, 0.26)  # linear RGB
WALL_ALBEDO = (0.70, 0.70, 0.64)


@dataclass(frozen=True)
class Surroundings:
    """The table top (plane y = ``table_y``) and the wall (plane z = ``wall_z``), metres, scene frame.

    ``table_id``, ``wall_id``: their geometry ids in the scene's ray caster; ``centre_z`` the
    object centre's z (the table is a square of half-width :data:`TABLE_HALF_WIDTH` around it).
    """

    table_y: float
    wall_z: float
    centre_z: float
    table_id: int
    wall_id: int

    def normals(self, geometry_ids: np.ndarray) -> np.ndarray:
        """Unit normals (N, 3), scene frame, of hits on ``geometry_ids`` (N,): up (-y) or toward -z."""
        table = (geometry_ids == self.table_id)[:, None]
        return np.where(table, [0.0, -1.0, 0.0], [0.0, 0.0, -1.0])

    def albedo(self, geometry_ids: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Linear RGB albedo (N, 3) of hits ``points`` (N, 3) (scene frame, metres) on ``geometry_ids``."""
        x, y, z = points.T
        grain = 1.0 + 0.18 * np.sin(55.0 * x + 4.0 * np.sin(7.0 * (z - self.centre_z)))
        mottle = 1.0 + 0.06 * np.sin(9.0 * x) * np.sin(11.0 * y)
        table = (geometry_ids == self.table_id)[:, None]
        return np.where(table, np.multiply.outer(grain, TABLE_ALBEDO), np.multiply.outer(mottle, WALL_ALBEDO))


def add_surroundings(raycaster: o3d.t.geometry.RaycastingScene, object_bottom_y: float,
                     centre_z: float) -> Surroundings:
    """Add a table top at ``object_bottom_y`` (the object's lowest point, y down) and a wall
    :data:`WALL_BEHIND` metres behind ``centre_z`` to ``raycaster``; returns their description."""
    h, c = TABLE_HALF_WIDTH, centre_z
    table = np.array([[-h, object_bottom_y, c - h], [h, object_bottom_y, c - h],
                      [h, object_bottom_y, c + h], [-h, object_bottom_y, c + h]])
    wall_z, w = c + WALL_BEHIND, WALL_HALF_WIDTH
    wall = np.array([[-w, object_bottom_y - WALL_HEIGHT, wall_z], [w, object_bottom_y - WALL_HEIGHT, wall_z],
                     [w, object_bottom_y + 0.8, wall_z], [-w, object_bottom_y + 0.8, wall_z]])
    quad = o3d.core.Tensor(np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32))
    table_id = raycaster.add_triangles(o3d.core.Tensor(table.astype(np.float32)), quad)
    wall_id = raycaster.add_triangles(o3d.core.Tensor(wall.astype(np.float32)), quad)
    return Surroundings(float(object_bottom_y), float(wall_z), float(c), int(table_id), int(wall_id))
