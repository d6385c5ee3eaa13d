"""The placed mesh: placement in front of the reference camera, procedural albedo, ray-casting scene."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from ..export.topology import vertex_normals
from .camera import camera_rays, synthetic_intrinsics
from .surroundings import Surroundings, add_surroundings

# Rotations turning a shipped mesh's front toward its +z axis (the side the camera sees).
FRONT_ROTATIONS = {"armadillo": np.diag([-1.0, 1.0, -1.0])}

#: the renders' facets: the mesh is Loop-subdivided until its mean edge spans at most this many
#: pixels of the reference camera (at most :data:`MAX_SUBDIVISIONS` times), so that the rendered
#: depth's own normals are the normals its colour is shaded with (see :func:`build_scene`)
MAX_FACET_PX = 1.5
MAX_SUBDIVISIONS = 3
#: ... and never to more triangles than this (each subdivision makes four of one; the bunny's
#: three are 4.4 M, the ray caster's memory grows with them)
MAX_TRIANGLES = 8_000_000

# Linear-RGB palette of the albedo cells (distinct hues, all within [0.2, 0.9]).
PALETTE = np.array(
    [
        [0.80, 0.30, 0.25],
        [0.30, 0.70, 0.30],
        [0.30, 0.40, 0.80],
        [0.85, 0.75, 0.30],
        [0.70, 0.30, 0.70],
        [0.30, 0.75, 0.75],
        [0.80, 0.80, 0.75],
    ]
)


def apply_matrix(A: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Rows ``A @ p`` (N, k) of points (N, m) for a small (k, m) matrix A.

    einsum, not matmul: BLAS threads gain nothing on (N, 3) x (3, 3) and crawl on a busy machine.
    """
    return np.einsum("km,nm->nk", A, points)


def _as_legacy_mesh(mesh) -> o3d.geometry.TriangleMesh:
    """A legacy TriangleMesh from a tensor mesh, legacy mesh, shipped name or file path."""
    if isinstance(mesh, (str, Path)):
        from ..datasets import load_mesh

        mesh = load_mesh(mesh)
    if isinstance(mesh, o3d.t.geometry.TriangleMesh):
        mesh = mesh.to_legacy()
    if not isinstance(mesh, o3d.geometry.TriangleMesh):
        raise TypeError(
            f"mesh must be an open3d TriangleMesh (tensor or legacy), 'bunny', 'armadillo' or a mesh file path; "
            f"got {type(mesh).__name__}"
        )
    if len(mesh.triangles) == 0 or len(mesh.vertices) == 0:
        raise ValueError("the mesh is empty (no triangles); give a triangle mesh, e.g. 'bunny'")
    return mesh


def placement_transform(
    vertices: np.ndarray, object_size: float, distance: float, front: np.ndarray | None = None
) -> np.ndarray:
    """(4, 4) similarity mesh -> reference camera: upright, centred at (0, 0, distance).

    ``vertices`` (N, 3) in mesh units. Applies the rotation ``front`` (3, 3, default identity;
    it should turn the mesh's front to +z), turns y-up to y-down by 180 degrees about x (so the
    mesh's +z side faces the camera), moves the bounding-box centre to (0, 0, distance) and
    scales the largest extent to ``object_size`` metres.
    """
    R = np.diag([1.0, -1.0, -1.0]) @ (np.eye(3) if front is None else np.asarray(front, dtype=np.float64))
    vertices = vertices @ R.T
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    extent = float(np.max(hi - lo))
    if not np.isfinite(extent) or extent <= 0:
        raise ValueError("the mesh has a degenerate bounding box (all vertices coincide); give a real mesh")
    s = object_size / extent
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = np.array([0.0, 0.0, distance]) - s * (lo + hi) / 2
    return T


@dataclass(frozen=True)
class ProceduralAlbedo:
    """Coloured albedo on the surface: Voronoi cells of palette colours times smooth variation.

    Defined on object coordinates q (metres / object_size, object within about [-0.5, 0.5]^3),
    so it is the same surface texture in every view. ``seeds`` (K, 3) cell centres,
    ``colors`` (K, 3) their linear RGB, ``waves`` (M, 3) and ``phases`` (M,) the smooth factor
    ``1 + 0.25 * mean_m sin(waves_m . q + phases_m)``. Values clipped to [0.2, 0.9].
    """

    seeds: np.ndarray
    colors: np.ndarray
    waves: np.ndarray
    phases: np.ndarray

    @classmethod
    def random(cls, rng: np.random.Generator, cells_per_axis: int = 6, waves: int = 3) -> "ProceduralAlbedo":
        """A random texture drawn from ``rng`` (deterministic for its seed).

        Cell centres are a jittered ``cells_per_axis``^3 grid over [-0.5, 0.5]^3 (patches about
        1/cells_per_axis of the object). Colours: a randomly permuted palette indexed by
        ``(i + 2j + 4k) mod 7`` on the grid, so face-adjacent cells always differ.
        """
        g = (np.arange(cells_per_axis) + 0.5) / cells_per_axis - 0.5
        grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
        seeds = grid + rng.uniform(-0.35, 0.35, size=grid.shape) / cells_per_axis
        ijk = np.stack(np.meshgrid(*[np.arange(cells_per_axis)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
        colors = PALETTE[rng.permutation(len(PALETTE))][(ijk @ [1, 2, 4]) % len(PALETTE)]
        directions = rng.normal(size=(waves, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        wave = directions * rng.uniform(6.0, 14.0, size=(waves, 1))  # 1-2 periods over the object
        return cls(seeds, colors, wave, rng.uniform(0, 2 * np.pi, size=waves))

    @cached_property
    def _cells(self) -> cKDTree:
        return cKDTree(self.seeds)

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """Linear RGB albedo (N, 3) of object-coordinate points q (N, 3)."""
        q = np.asarray(q, dtype=np.float64)
        base = self.colors[self._cells.query(q)[1]]
        smooth = 1.0 + 0.25 * np.sin(apply_matrix(self.waves, q) + self.phases).mean(axis=1)
        return np.clip(base * smooth[:, None], 0.2, 0.9)


@dataclass(frozen=True)
class SpeckledAlbedo:
    """A dark-speckled stone (granite, speckled plaster): pale grey cells and dark speckles, each
    cell's brightness varied a little; the texture whose colour must not become relief (issue 32
    item 3).

    Defined on object coordinates q like :class:`ProceduralAlbedo`. ``seeds`` (K, 3) centres of
    small Voronoi cells (about 1/``cells_per_axis`` of the object: 8 mm on a 0.2 m object, 3-4
    pixels at 320x240 and 0.6 m), ``dark`` (K,) bool the speckles' cells, ``shade`` (K,) each
    cell's brightness factor; the base is ``BASE * shade`` and a speckle ``DARK * shade``.
    """

    seeds: np.ndarray
    dark: np.ndarray
    shade: np.ndarray

    #: linear RGB of the pale stone and of its speckles (the speckles about 8x darker)
    BASE = np.array([0.62, 0.58, 0.52])
    DARK = np.array([0.075, 0.07, 0.065])

    @classmethod
    def random(cls, rng: np.random.Generator, cells_per_axis: int = 25, dark_fraction: float = 0.3) -> "SpeckledAlbedo":
        """A random speckled texture drawn from ``rng``: ``cells_per_axis``^3 cells uniformly over
        [-0.5, 0.5]^3, ``dark_fraction`` of them speckles, brightness factors in [0.85, 1.15]."""
        k = int(cells_per_axis) ** 3
        return cls(rng.uniform(-0.5, 0.5, size=(k, 3)), rng.random(k) < dark_fraction, rng.uniform(0.85, 1.15, k))

    @cached_property
    def _cells(self) -> cKDTree:
        return cKDTree(self.seeds)

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """Linear RGB albedo (N, 3) of object-coordinate points q (N, 3)."""
        cell = self._cells.query(np.asarray(q, dtype=np.float64))[1]
        return np.where(self.dark[cell, None], self.DARK, self.BASE) * self.shade[cell, None]


#: the surface textures :func:`build_scene` draws (``albedo=``)
ALBEDOS = {"patches": ProceduralAlbedo, "speckled": SpeckledAlbedo}


@dataclass
class SyntheticScene:
    """The placed mesh ready for ray casting.

    ``raycaster`` holds the mesh in reference-camera coordinates. ``K`` (3, 3) colour
    intrinsics for ``size`` = (W, H). ``mesh_to_reference`` (4, 4) similarity;
    ``object_size`` metres; ``albedo`` the surface texture (object coordinates
    ``q = R^T (x_ref - t) / object_size`` with R, t the rotation/translation of the placement).
    ``vertices`` (V, 3) reference-frame metres and ``triangles`` (F, 3) the ray-cast surface: the
    mesh after ``subdivisions`` Loop subdivisions; ``vertex_normals`` (V, 3) its unit normals.
    ``object_id``: the mesh's geometry id in the ray caster; ``surroundings``: scene mode's table
    and wall, or None for the object alone.
    """

    raycaster: o3d.t.geometry.RaycastingScene
    K: np.ndarray
    size: tuple[int, int]
    mesh_to_reference: np.ndarray
    object_size: float
    distance: float
    albedo: ProceduralAlbedo | SpeckledAlbedo
    vertices: np.ndarray
    triangles: np.ndarray
    vertex_normals: np.ndarray
    object_id: int = 0
    surroundings: Surroundings | None = None
    subdivisions: int = 0

    def smooth_normals(self, primitive_ids: np.ndarray, primitive_uvs: np.ndarray) -> np.ndarray:
        """Unit normals (N, 3), reference frame, interpolated from vertex normals at hit points.

        The surface is subdivided below about a pixel (:data:`MAX_FACET_PX`), so these are the
        normals of the rendered depth, without the per-face steps no pixel could resolve.
        """
        tri = self.triangles[primitive_ids]
        a, b = primitive_uvs[:, :1], primitive_uvs[:, 1:2]
        n = (1.0 - a - b) * self.vertex_normals[tri[:, 0]] + a * self.vertex_normals[tri[:, 1]] \
            + b * self.vertex_normals[tri[:, 2]]
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    @cached_property
    def rays(self) -> np.ndarray:
        """Unit ray directions (H*W, 3) through the pixel centres, camera frame, row-major."""
        return camera_rays(self.K, self.size).reshape(-1, 3)

    @cached_property
    def rays32(self) -> np.ndarray:
        """:attr:`rays` as float32 (what the ray caster takes)."""
        return self.rays.astype(np.float32)

    def object_coordinates(self, points_ref: np.ndarray) -> np.ndarray:
        """Object coordinates (N, 3) (units of object_size) of reference-frame points (N, 3)."""
        M = self.mesh_to_reference
        R = M[:3, :3] / np.cbrt(np.linalg.det(M[:3, :3]))
        return apply_matrix(R.T, points_ref - M[:3, 3]) / self.object_size


def build_scene(mesh, *, size=(640, 480), object_size=0.2, distance=0.6, seed=0,
                surroundings: bool = False, albedo: str = "patches",
                subdivisions: int | None = None) -> SyntheticScene:
    """Place ``mesh`` (tensor/legacy TriangleMesh, name or path) in front of the reference camera.

    ``size`` (W, H) pixels; ``object_size``, ``distance`` metres; ``seed`` draws the albedo;
    ``surroundings`` stands the object on a table in front of a wall (:mod:`.surroundings`);
    ``albedo`` the texture: "patches" (:class:`ProceduralAlbedo`) or "speckled" (:class:`SpeckledAlbedo`).

    The colour is shaded with normals interpolated from the vertex normals while the depth is the
    facets', which a scanned mesh's facets of a few pixels part by 2-4 degrees: no depth would
    explain such an image. So the mesh is Loop-subdivided ``subdivisions`` times (None: until its
    mean edge spans at most :data:`MAX_FACET_PX` pixels at ``distance``, at most
    :data:`MAX_SUBDIVISIONS` times), a smooth surface whose depth has the shading's normals.
    The placement is the given mesh's, so the object sits where it would unsubdivided.
    """
    if albedo not in ALBEDOS:
        raise ValueError(f"unknown albedo {albedo!r}; choose one of {list(ALBEDOS)}")
    if subdivisions is not None and (isinstance(subdivisions, bool) or not isinstance(subdivisions, (int, np.integer))
                                     or subdivisions < 0):
        raise ValueError(f"subdivisions must be None (chosen from the pixel size) or an integer >= 0, got "
                         f"{subdivisions!r}; e.g. 0 (the mesh as given) or 2")
    front = FRONT_ROTATIONS.get(mesh) if isinstance(mesh, str) else None
    legacy = _as_legacy_mesh(mesh)
    M = placement_transform(np.asarray(legacy.vertices, dtype=np.float64), object_size, distance, front)
    W, H = (int(s) for s in size)
    K = synthetic_intrinsics(W, H)
    vertices, triangles = _referenced(legacy)
    if subdivisions is None:
        subdivisions = facet_subdivisions(vertices, triangles, float(np.cbrt(np.linalg.det(M[:3, :3])))
                                          * K[0, 0] / float(distance))
    if subdivisions:
        given = len(triangles)
        vertices, triangles = (_shipped_subdivided(mesh, int(subdivisions)) if _is_shipped_name(mesh)
                               else loop_subdivide(vertices, triangles, int(subdivisions)))
        subdivisions = subdivisions if len(triangles) > given else 0  # VTK could not: rendered as given
    placed = apply_matrix(M[:3, :3], vertices) + M[:3, 3]
    raycaster = o3d.t.geometry.RaycastingScene()
    object_id = raycaster.add_triangles(
        o3d.core.Tensor(placed.astype(np.float32)),
        o3d.core.Tensor(triangles.astype(np.uint32)),
    )
    room = add_surroundings(raycaster, float(placed[:, 1].max()), float(distance)) if surroundings else None
    texture = ALBEDOS[albedo].random(random_stream(seed, "albedo"))
    return SyntheticScene(raycaster, K, (W, H), M, float(object_size), float(distance), texture, placed,
                          triangles, vertex_normals(placed, triangles), int(object_id), room,
                          int(subdivisions))


def facet_subdivisions(vertices: np.ndarray, triangles: np.ndarray, pixels_per_unit: float) -> int:
    """Loop subdivisions (0..:data:`MAX_SUBDIVISIONS`) that bring the mean edge of ``triangles``
    (F, 3) over ``vertices`` (V, 3) to at most :data:`MAX_FACET_PX` pixels (each halves it), short
    of more than :data:`MAX_TRIANGLES` triangles (each quadruples them).
    ``pixels_per_unit``: image pixels per mesh unit at the object's distance."""
    edges = vertices[triangles] - vertices[np.roll(triangles, 1, axis=1)]
    edge_px = float(np.linalg.norm(edges, axis=2).mean()) * pixels_per_unit
    k = 0
    while k < MAX_SUBDIVISIONS and edge_px / 2**k > MAX_FACET_PX and len(triangles) * 4 ** (k + 1) <= MAX_TRIANGLES:
        k += 1
    return k


def loop_subdivide(vertices: np.ndarray, triangles: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """``iterations`` Loop subdivisions of a triangle mesh (V, 3) float, (F, 3) int: VTK's filter
    through pyvista (Open3D's gives NaN vertices on the shipped bunny). A mesh VTK cannot subdivide
    (not manifold) is returned as given, with a warning."""
    import pyvista as pv  # imported here: VTK is heavy and only renders of coarse meshes need it

    with pv.vtk_verbosity("off"):  # a failure is said once, below, not as VTK's log on stderr
        surface = pv.PolyData.from_regular_faces(vertices, triangles).subdivide(iterations, "loop")
    points, faces = np.asarray(surface.points, dtype=np.float64), surface.regular_faces.astype(np.int64)
    if len(faces) == 0 or not np.isfinite(points).all():
        warnings.warn(f"the mesh ({len(triangles)} triangles) could not be Loop-subdivided (not manifold?); it is "
                      f"rendered as given, so its depth's normals may differ from the shading's by a few degrees",
                      RuntimeWarning, stacklevel=3)
        return vertices, triangles
    return points, faces


def _referenced(legacy: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and triangles (F, 3) int64 of ``legacy`` without unreferenced vertices."""
    triangles = np.asarray(legacy.triangles, dtype=np.int64)
    used, remapped = np.unique(triangles, return_inverse=True)
    return np.asarray(legacy.vertices, dtype=np.float64)[used], remapped.reshape(triangles.shape)


def _is_shipped_name(mesh) -> bool:
    from ..datasets import MESHES

    return isinstance(mesh, str) and mesh in MESHES


@lru_cache(maxsize=2)
def _shipped_subdivided(name: str, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """A shipped mesh's referenced vertices and triangles after ``iterations`` Loop subdivisions
    (cached: the suite renders the bunny many times; two entries, for the bunny's three
    subdivisions hold 160 MB); read-only arrays."""
    vertices, triangles = loop_subdivide(*_referenced(_as_legacy_mesh(name)), iterations)
    vertices.flags.writeable = triangles.flags.writeable = False
    return vertices, triangles


def random_stream(seed: int, stream: str) -> np.random.Generator:
    """An independent generator per purpose, so e.g. noise=False leaves the albedo unchanged."""
    streams = {"albedo": 0, "color": 1, "depth": 2}
    return np.random.default_rng([int(seed), streams[stream]])
