"""Synthetic captures: a mesh rendered by ray casting under an LED that moves with the camera.

The benchmark protocol of DESIGN section 5. Conventions (all lengths in metres):

- Reference camera (frame 0) at the origin, looking along +z, x right, y down (OpenCV /
  Open3D). The mesh (assumed y-up, Stanford style) is turned upright (180 degrees about x, so
  its +z side faces the camera), centred, scaled so its largest bounding-box extent is
  ``object_size`` and put at ``(0, 0, distance)``: ``mesh_to_reference`` (4x4 similarity).
- Colour intrinsics: a pinhole with 60 degree horizontal field of view, square pixels,
  principal point at the image centre ``((W - 1)/2, (H - 1)/2)`` (pixel centres at integer
  coordinates). Depth intrinsics: :func:`o3d_mvps.capture.default_depth_intrinsic`.
- Poses: ``poses[i]`` (4x4) maps reference-camera coordinates to frame-i camera coordinates;
  ``poses[0]`` is the identity. The cameras look at the object centre.
- Colour: linear RGB ``albedo * shading`` (+ Gaussian noise), quantised to 8-bit sRGB; the
  stored floats are exactly ``srgb_to_linear(k / 255)``. Background 0.
- Depth: z rendered at colour resolution, area-averaged over SF x SF blocks (a block is valid
  only if all its pixels hit the object), + Gaussian noise ``sigma = 1e-5 z_mm^2`` mm, 1 mm
  quantisation.

Lights (``groundtruth.light``):

- ``"led"``: a point light at ``offset`` in the camera frame (it moves with the camera);
  ``I = albedo * (ambient + intensity * V * max(0, n.l) / r^2)``, l the unit vector to the light,
  r its distance, V = 0 where a shadow ray toward the light is blocked.
- ``"directional"``: SH-exact, ``I = albedo * <l_i, [1, n_x, n_y, n_z]>`` with n the unit normal
  (pointing to the camera) in reference-camera coordinates and ``l_i = light["sh"][i]``;
  no clamping, no shadows (the shading is positive for every normal).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from .capture import Capture, GroundTruth, default_depth_intrinsic, image_from_array
from .colour import linear_to_srgb, srgb_to_linear

TRAJECTORIES = ("orbit", "orbit-translate")
LIGHTS = ("led", "directional")
MAX_SCALE_FACTOR = 16

HORIZONTAL_FOV_DEG = 60.0
MAX_ORBIT_DEG = 15.0
ORBIT_TURNS = 1.5
COLOR_NOISE_SIGMA = 0.005
DEPTH_SCALE = 1000.0  # depth units per metre: 1 mm quantisation

LED_OFFSET = (0.03, -0.02, 0.0)  # metres, camera frame
LED_FRONTAL_IRRADIANCE = 0.85  # irradiance of a frontal surface at the object centre
LED_AMBIENT = 0.03
SHADOW_OFFSET = 1e-4  # metres along the normal

SH_AMBIENT = 0.5
SH_STRENGTH = 0.45  # < SH_AMBIENT: shading stays >= 0.05 for any normal
SH_DIRECTION = (0.35, -0.3, -1.0)  # toward the light, camera frame (normalised)

# Rotations turning a shipped mesh's front toward its +z axis (the side the camera sees).
FRONT_ROTATIONS = {"armadillo": np.diag([-1.0, 1.0, -1.0])}

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


def _apply(A: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Rows ``A @ p`` (N, k) of points (N, m) for a small (k, m) matrix A.

    einsum, not matmul: BLAS threads gain nothing on (N, 3) x (3, 3) and crawl on a busy machine.
    """
    return np.einsum("km,nm->nk", A, points)


# --------------------------------------------------------------------------------------
# Argument checks
# --------------------------------------------------------------------------------------
def _check_arguments(frames, scale_factor, size, trajectory, light, object_size, distance) -> tuple[int, int]:
    """Validate render_capture's arguments; returns (W, H)."""
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise ValueError(
            f"frames must be an integer >= 1 (the reference is frame 0), got {frames!r}; pass e.g. frames=20"
        )
    if (
        isinstance(scale_factor, bool)
        or not isinstance(scale_factor, (int, np.integer))
        or not 1 <= scale_factor <= MAX_SCALE_FACTOR
    ):
        raise ValueError(
            f"scale_factor must be an integer in 1..{MAX_SCALE_FACTOR}, got {scale_factor!r}; pass e.g. scale_factor=4"
        )
    try:
        W, H = (int(s) for s in size)
        if (W, H) != tuple(size):
            raise ValueError
    except (TypeError, ValueError):
        raise ValueError(f"size must be (width, height) in pixels, got {size!r}; pass e.g. size=(640, 480)") from None
    if W < 8 or H < 8:
        raise ValueError(f"size {W}x{H} is too small; give at least 8x8 pixels, e.g. size=(640, 480)")
    if W % scale_factor or H % scale_factor:
        raise ValueError(
            f"scale_factor {scale_factor} does not divide the size {W}x{H}; choose a size whose width and "
            f"height are multiples of {scale_factor} (e.g. {W - W % scale_factor}x{H - H % scale_factor})"
        )
    if trajectory not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory {trajectory!r}; choose one of {list(TRAJECTORIES)}")
    if light not in LIGHTS:
        raise ValueError(f"unknown light {light!r}; choose one of {list(LIGHTS)}")
    if not (np.isfinite(object_size) and object_size > 0):
        raise ValueError(f"object_size must be a positive length in metres, got {object_size!r}; e.g. 0.2")
    if not (np.isfinite(distance) and distance > object_size):
        raise ValueError(
            f"distance ({distance!r} m) must exceed object_size ({object_size!r} m) so the camera is outside "
            "the object; e.g. distance=0.6 with object_size=0.2"
        )
    return W, H


# --------------------------------------------------------------------------------------
# Camera, trajectory
# --------------------------------------------------------------------------------------
def synthetic_intrinsics(width: int, height: int, fov_deg: float = HORIZONTAL_FOV_DEG) -> np.ndarray:
    """(3, 3) pinhole K of a ``width`` x ``height`` camera with horizontal FOV ``fov_deg``.

    Square pixels, principal point at the image centre ``((W - 1)/2, (H - 1)/2)``.
    """
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def look_at_pose(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) reference -> camera transform of a camera at ``centre`` looking at ``target``.

    No roll: the camera's x axis is horizontal in the reference frame (y down stays "down").
    """
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)  # camera -> reference rotation (columns: camera axes)
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ centre
    return T


def orbit_trajectory(
    frames: int, distance: float, kind: str = "orbit", max_angle_deg: float = MAX_ORBIT_DEG
) -> np.ndarray:
    """Camera poses (frames, 4, 4), reference -> frame i; ``poses[0]`` is the identity.

    ``"orbit"``: an outward spiral (``ORBIT_TURNS`` turns) of yaw/pitch offsets around the
    object centre ``(0, 0, distance)``, radius growing linearly to ``max_angle_deg``, at
    constant distance, always looking at the centre. ``"orbit-translate"`` adds a distance
    change of up to +-5 cm and a sideways camera shift of up to 3 cm (x) and 2 cm (y).
    """
    if kind not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory {kind!r}; choose one of {list(TRAJECTORIES)}")
    target = np.array([0.0, 0.0, distance])
    poses = np.empty((frames, 4, 4))
    for i in range(frames):
        t = i / (frames - 1) if frames > 1 else 0.0
        radius = np.radians(max_angle_deg) * t
        phase = 2 * np.pi * ORBIT_TURNS * t
        yaw, pitch = radius * np.cos(phase), radius * np.sin(phase)
        d = distance
        if kind == "orbit-translate":
            d = distance - 0.05 * np.sin(2 * np.pi * t)
        direction = np.array([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
        centre = target - d * direction
        T = look_at_pose(centre, target)
        if kind == "orbit-translate":  # a sideways shift in the camera's own frame
            shift = np.array([0.03 * np.sin(3 * np.pi * t), 0.02 * np.sin(2 * np.pi * t), 0.0])
            T[:3, 3] -= shift
        poses[i] = T
    poses[0] = np.eye(4)
    return poses


def ring_trajectory(frames: int, distance: float, elevation_deg: float = 15.0) -> np.ndarray:
    """Camera poses (frames, 4, 4) of a full 360-degree ring around the object, reference -> frame i.

    The cameras sit at ``distance`` from the object centre ``(0, 0, distance)`` (reference
    frame), ``elevation_deg`` above it (toward -y, image up), at azimuths ``360 * i / frames``
    degrees about the vertical axis through the centre, looking at the centre without roll.
    Unlike :func:`orbit_trajectory`, ``poses[0]`` is the identity only for ``elevation_deg=0``:
    the reference frame stays the level camera the object was placed for (:func:`build_scene`).
    """
    target = np.array([0.0, 0.0, distance])
    elevation = np.radians(elevation_deg)
    poses = np.empty((int(frames), 4, 4))
    for i in range(int(frames)):
        azimuth = 2 * np.pi * i / frames
        direction = np.array([np.sin(azimuth) * np.cos(elevation), np.sin(elevation),
                              np.cos(azimuth) * np.cos(elevation)])  # camera -> centre
        poses[i] = look_at_pose(target - distance * direction, target)
    return poses


# --------------------------------------------------------------------------------------
# Mesh placement and albedo
# --------------------------------------------------------------------------------------
def _as_legacy_mesh(mesh) -> o3d.geometry.TriangleMesh:
    """A legacy TriangleMesh from a tensor mesh, legacy mesh, shipped name or file path."""
    if isinstance(mesh, (str, Path)):
        from .datasets import load_mesh

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
        smooth = 1.0 + 0.25 * np.sin(_apply(self.waves, q) + self.phases).mean(axis=1)
        return np.clip(base * smooth[:, None], 0.2, 0.9)


@dataclass
class SyntheticScene:
    """The placed mesh ready for ray casting.

    ``raycaster`` holds the mesh in reference-camera coordinates. ``K`` (3, 3) colour
    intrinsics for ``size`` = (W, H). ``mesh_to_reference`` (4, 4) similarity;
    ``object_size`` metres; ``albedo`` the surface texture (object coordinates
    ``q = R^T (x_ref - t) / object_size`` with R, t the rotation/translation of the placement).
    """

    raycaster: o3d.t.geometry.RaycastingScene
    K: np.ndarray
    size: tuple[int, int]
    mesh_to_reference: np.ndarray
    object_size: float
    distance: float
    albedo: ProceduralAlbedo
    triangles: np.ndarray | None = None
    vertex_normals: np.ndarray | None = None

    def smooth_normals(self, primitive_ids: np.ndarray, primitive_uvs: np.ndarray) -> np.ndarray:
        """Unit normals (N, 3), reference frame, interpolated from vertex normals at hit points.

        Like a camera integrating over its pixel, this avoids the aliasing of scanned meshes'
        per-face normals (bumpy below a pixel), which no depth map at pixel resolution explains.
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
        return _apply(R.T, points_ref - M[:3, 3]) / self.object_size


def build_scene(mesh, *, size=(640, 480), object_size=0.2, distance=0.6, seed=0) -> SyntheticScene:
    """Place ``mesh`` (tensor/legacy TriangleMesh, name or path) in front of the reference camera.

    ``size`` (W, H) pixels; ``object_size``, ``distance`` metres; ``seed`` draws the albedo.
    """
    front = FRONT_ROTATIONS.get(mesh) if isinstance(mesh, str) else None
    legacy = _as_legacy_mesh(mesh)
    vertices = np.asarray(legacy.vertices, dtype=np.float64)
    M = placement_transform(vertices, object_size, distance, front)
    placed = _apply(M[:3, :3], vertices) + M[:3, 3]
    raycaster = o3d.t.geometry.RaycastingScene()
    raycaster.add_triangles(
        o3d.core.Tensor(placed.astype(np.float32)),
        o3d.core.Tensor(np.asarray(legacy.triangles, dtype=np.uint32)),
    )
    albedo = ProceduralAlbedo.random(_rng(seed, "albedo"))
    W, H = (int(s) for s in size)
    legacy.compute_vertex_normals()
    vertex_normals = _apply(M[:3, :3], np.asarray(legacy.vertex_normals, dtype=np.float64))
    vertex_normals /= np.maximum(np.linalg.norm(vertex_normals, axis=1, keepdims=True), 1e-12)
    return SyntheticScene(raycaster, synthetic_intrinsics(W, H), (W, H), M, float(object_size), float(distance),
                          albedo, np.asarray(legacy.triangles, dtype=np.int64), vertex_normals)


def _rng(seed: int, stream: str) -> np.random.Generator:
    """An independent generator per purpose, so e.g. noise=False leaves the albedo unchanged."""
    streams = {"albedo": 0, "color": 1, "depth": 2}
    return np.random.default_rng([int(seed), streams[stream]])


# --------------------------------------------------------------------------------------
# Lights
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LEDLight:
    """Point light at ``offset`` (3,) metres in the camera frame, moving with the camera.

    ``I = albedo * (ambient + intensity * V * max(0, n.l) / r^2)``; ``intensity`` in
    irradiance x m^2; V the shadow-ray visibility.
    """

    offset: tuple = LED_OFFSET
    intensity: float = LED_FRONTAL_IRRADIANCE * 0.6**2
    ambient: float = LED_AMBIENT
    shadows: bool = True

    def shading(self, scene: SyntheticScene, pose: np.ndarray, frame: "FrameRender") -> np.ndarray:
        """Shading (N,) of the frame's hit pixels (N = frame.mask.sum())."""
        X = frame.points[frame.mask]  # camera frame
        n = frame.normals[frame.mask]
        to_light = np.asarray(self.offset) - X
        r = np.linalg.norm(to_light, axis=1)
        cos = np.maximum(0.0, np.einsum("ij,ij->i", n, to_light) / r)
        if self.shadows:
            cos *= self._visible(scene, pose, X, n, to_light, cos > 0)
        return self.ambient + self.intensity * cos / r**2

    @staticmethod
    def _visible(scene, pose, X, n, to_light, lit) -> np.ndarray:
        """1.0 where a shadow ray from X + SHADOW_OFFSET n reaches the light, else 0 (N,)."""
        visible = np.zeros(len(X))
        if not lit.any():
            return visible
        R_c2r, C = pose[:3, :3].T, -pose[:3, :3].T @ pose[:3, 3]
        origin = _apply(R_c2r, X[lit] + SHADOW_OFFSET * n[lit]) + C
        direction = _apply(R_c2r, to_light[lit] - SHADOW_OFFSET * n[lit])  # reaches the light at t = 1
        rays = o3d.core.Tensor(np.hstack([origin, direction]).astype(np.float32))
        occluded = scene.raycaster.test_occlusions(rays, tnear=0.0, tfar=1.0).numpy()
        visible[lit] = ~occluded.astype(bool)
        return visible

    def parameters(self, poses: np.ndarray) -> dict:
        """JSON-serialisable parameters; ``positions`` (n, 3) light centres in reference coordinates."""
        inv = np.linalg.inv(poses)
        positions = inv[:, :3, :3] @ np.asarray(self.offset) + inv[:, :3, 3]
        return {
            "model": "led",
            "offset": [float(v) for v in self.offset],
            "intensity": float(self.intensity),
            "ambient": float(self.ambient),
            "falloff": "inverse-square",
            "shadows": bool(self.shadows),
            "positions": positions.tolist(),
            "formula": "albedo * (ambient + intensity * visible * max(0, n.l) / r^2), camera frame",
        }


@dataclass(frozen=True)
class DirectionalLight:
    """SH-exact light fixed in the camera frame: shading ``ambient + strength * d . n_cam``.

    ``direction`` (3,) toward the light (normalised on use), camera frame. With
    ``strength < ambient`` the shading is positive for every normal; no clamping, no shadows.
    """

    direction: tuple = SH_DIRECTION
    ambient: float = SH_AMBIENT
    strength: float = SH_STRENGTH

    def sh_camera(self) -> np.ndarray:
        """(4,) SH vector [ambient, strength * d] in camera coordinates."""
        d = np.asarray(self.direction, dtype=np.float64)
        return np.concatenate([[self.ambient], self.strength * d / np.linalg.norm(d)])

    def sh_reference(self, pose: np.ndarray) -> np.ndarray:
        """(4,) SH vector of the frame with ``pose`` (reference -> frame) in reference coordinates."""
        l = self.sh_camera()
        return np.concatenate([l[:1], pose[:3, :3].T @ l[1:]])

    def shading(self, scene: SyntheticScene, pose: np.ndarray, frame: "FrameRender") -> np.ndarray:
        """Shading (N,) of the frame's hit pixels: ``<l_cam, [1, n_cam]>``."""
        l = self.sh_camera()
        return l[0] + _apply(l[None, 1:], frame.normals[frame.mask])[:, 0]

    def parameters(self, poses: np.ndarray) -> dict:
        """JSON-serialisable parameters; ``sh`` (n, 4) per-frame SH vectors in reference coordinates."""
        return {
            "model": "directional",
            "direction": [float(v) for v in self.sh_camera()[1:] / self.strength],
            "ambient": float(self.ambient),
            "strength": float(self.strength),
            "sh": [self.sh_reference(T).tolist() for T in poses],
            "formula": "albedo * <sh[i], [1, n_x, n_y, n_z]>, n unit normal in reference coordinates",
        }


def make_light(light: str, distance: float = 0.6):
    """The light model named ``light`` ("led" or "directional"), LED scaled for ``distance`` m."""
    if light == "led":
        return LEDLight(intensity=LED_FRONTAL_IRRADIANCE * distance**2)
    if light == "directional":
        return DirectionalLight()
    raise ValueError(f"unknown light {light!r}; choose one of {list(LIGHTS)}")


# --------------------------------------------------------------------------------------
# Rendering one frame
# --------------------------------------------------------------------------------------
@dataclass
class FrameRender:
    """Noise-free buffers of one frame at colour resolution (H, W), camera-frame quantities.

    ``mask`` (H, W) bool hit; ``depth`` (H, W) float64 z metres (0 off the object);
    ``points`` (H, W, 3) camera-frame hit points; ``normals`` (H, W, 3) unit face normals,
    camera frame, pointing to the camera; ``albedo`` (H, W, 3) linear RGB;
    ``color`` (H, W, 3) linear RGB ``albedo * shading`` (not clipped). Zero off the object.
    """

    mask: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    color: np.ndarray


def camera_rays(K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Unit ray directions (H, W, 3) through the pixel centres, camera frame."""
    W, H = size
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def render_frame(scene: SyntheticScene, pose: np.ndarray, light) -> FrameRender:
    """Ray-cast one frame with ``pose`` (4, 4) reference -> frame; one ray per pixel centre.

    ``light`` is an :class:`LEDLight` or :class:`DirectionalLight` (see :func:`make_light`).
    """
    W, H = scene.size
    R_c2r = pose[:3, :3].T
    C = -R_c2r @ pose[:3, 3]
    d_cam = scene.rays
    rays = np.empty((H * W, 6), dtype=np.float32)
    rays[:, :3] = C
    rays[:, 3:] = _apply(R_c2r.astype(np.float32), scene.rays32)
    hit = scene.raycaster.cast_rays(o3d.core.Tensor(rays), nthreads=0)
    t = hit["t_hit"].numpy()  # distance along the unit ray
    index = np.flatnonzero(np.isfinite(t))
    d_hit = d_cam[index]
    points = t[index, None].astype(np.float64) * d_hit
    smooth = scene.smooth_normals(hit["primitive_ids"].numpy()[index].astype(np.int64),
                                  hit["primitive_uvs"].numpy()[index].astype(np.float64))
    normals = _apply(R_c2r.T, smooth)
    normals *= np.where(np.einsum("ij,ij->i", normals, d_hit) > 0, -1.0, 1.0)[:, None]  # face the camera
    albedo = scene.albedo(scene.object_coordinates(_apply(R_c2r, points) + C))

    def image(values: np.ndarray) -> np.ndarray:
        out = np.zeros((H * W,) + values.shape[1:])
        out[index] = values
        return out.reshape((H, W) + values.shape[1:])

    mask = np.zeros(H * W, dtype=bool)
    mask[index] = True
    frame = FrameRender(
        mask=mask.reshape(H, W),
        depth=image(points[:, 2]),
        points=image(points),
        normals=image(normals),
        albedo=image(albedo),
        color=np.zeros((H, W, 3)),
    )
    frame.color[frame.mask] = albedo * light.shading(scene, pose, frame)[:, None]
    return frame


# --------------------------------------------------------------------------------------
# Sensor simulation
# --------------------------------------------------------------------------------------
SRGB8_TO_LINEAR = srgb_to_linear(np.arange(256) / 255.0)  # (256,) float32 decode table


def quantise_srgb8(
    linear: np.ndarray, rng: np.random.Generator | None = None, sigma: float = COLOR_NOISE_SIGMA
) -> np.ndarray:
    """8-bit sRGB camera: linear RGB (..., 3) -> float32 linear values exactly ``srgb_to_linear(k/255)``.

    Adds zero-mean Gaussian noise of std ``sigma`` (linear units) first when ``rng`` is given.
    """
    linear = np.asarray(linear, dtype=np.float64)
    if rng is not None:
        linear = linear + rng.normal(0.0, sigma, size=linear.shape)
    codes = np.rint(linear_to_srgb(np.clip(linear, 0.0, 1.0)).astype(np.float64) * 255.0).astype(np.uint8)
    return SRGB8_TO_LINEAR[codes]


def area_average(depth: np.ndarray, scale_factor: int) -> np.ndarray:
    """Low-resolution depth (H/SF, W/SF) float64: mean of each SF x SF block of ``depth`` (H, W).

    A block is valid only if all its pixels are > 0; invalid blocks are 0.
    """
    H, W = depth.shape
    sf = int(scale_factor)
    blocks = np.asarray(depth, dtype=np.float64).reshape(H // sf, sf, W // sf, sf)
    valid = (blocks > 0).all(axis=(1, 3))
    return np.where(valid, blocks.mean(axis=(1, 3)), 0.0)


def depth_noise_sigma(z: np.ndarray) -> np.ndarray:
    """Kinect-like depth noise std in metres of depth z in metres: ``1e-5 * z_mm^2`` mm."""
    z_mm = np.asarray(z, dtype=np.float64) * 1000.0
    return 1e-5 * z_mm**2 / 1000.0


def simulate_depth_sensor(
    depth: np.ndarray,
    scale_factor: int,
    rng: np.random.Generator | None = None,
    depth_scale: float | None = DEPTH_SCALE,
) -> np.ndarray:
    """Depth sensor: area-average (H, W) -> (h, w), Gaussian noise if ``rng``, quantise.

    Noise: ``depth_noise_sigma(z)`` on valid pixels. Quantisation: ``rint(z * depth_scale) /
    depth_scale`` (what a uint16 PNG at ``depth_scale`` units per metre stores); ``None``
    skips it. Returns float64 metres, 0 where invalid.
    """
    z = area_average(depth, scale_factor)
    valid = z > 0
    if rng is not None:
        z = z + valid * rng.normal(size=z.shape) * depth_noise_sigma(z)
    if depth_scale is not None:
        z = np.rint(z * depth_scale) / depth_scale
    return np.where(valid & (z > 0), z, 0.0)


# --------------------------------------------------------------------------------------
# The capture
# --------------------------------------------------------------------------------------
def render_capture(
    mesh,
    *,
    frames: int = 20,
    scale_factor: int = 4,
    size=(640, 480),
    trajectory: str = "orbit",
    light: str = "led",
    seed: int = 0,
    noise: bool = True,
    object_size: float = 0.2,
    distance: float = 0.6,
    progress: bool = False,
) -> Capture:
    """Render a synthetic LED-lit RGB-D capture of ``mesh`` with ground truth.

    Parameters
    ----------
    mesh : o3d.t.geometry.TriangleMesh, o3d.geometry.TriangleMesh, str or Path
        The object; ``"bunny"``, ``"armadillo"`` or a mesh file load via :mod:`o3d_mvps.datasets`.
    frames : int
        Number of frames n >= 1; frame 0 is the reference (pose identity).
    scale_factor : int
        Super-resolution factor SF (1..16) dividing both image sides; depth is (H/SF, W/SF).
    size : (int, int)
        Colour resolution (W, H) in pixels.
    trajectory : {"orbit", "orbit-translate"}
        See :func:`orbit_trajectory`.
    light : {"led", "directional"}
        Point LED with shadows, or the SH-exact directional light (module docstring).
    seed : int
        Seeds the albedo texture and the noise; equal seeds give identical captures.
    noise : bool
        Colour (sigma 0.005 linear) and depth (sigma 1e-5 z_mm^2 mm) noise; quantisation always.
    object_size, distance : float
        Largest bounding-box extent of the object and its distance to the reference camera (m).
    progress : bool
        Show a tqdm progress bar over frames.

    Returns
    -------
    Capture
        Colour (H, W, 3) linear floats of 8-bit sRGB values, depth (h, w, 1) metres in 1 mm
        steps, masks (H, W, 1) uint8 255 on the object, and :class:`GroundTruth`.
    """
    W, H = _check_arguments(frames, scale_factor, size, trajectory, light, object_size, distance)
    scene = build_scene(mesh, size=(W, H), object_size=object_size, distance=distance, seed=seed)
    poses = orbit_trajectory(int(frames), distance, trajectory)
    lighting = make_light(light, distance)
    color_rng = _rng(seed, "color") if noise else None
    depth_rng = _rng(seed, "depth") if noise else None

    color, depth, masks = [], [], []
    reference = None
    for i in _progress(range(int(frames)), progress):
        frame = render_frame(scene, poses[i], lighting)
        reference = frame if i == 0 else reference
        color.append(image_from_array(quantise_srgb8(frame.color, color_rng).astype(np.float32)))
        z = simulate_depth_sensor(frame.depth, scale_factor, depth_rng)
        depth.append(image_from_array(z.astype(np.float32)[:, :, None]))
        masks.append(image_from_array((frame.mask * np.uint8(255))[:, :, None]))

    K = scene.K
    gt = GroundTruth(
        depth=reference.depth.astype(np.float32),
        normals=reference.normals.astype(np.float32),
        albedo=reference.albedo.astype(np.float32),
        poses=poses,
        light=lighting.parameters(poses),
        mesh_to_reference=scene.mesh_to_reference,
    )
    return Capture(
        color=color,
        depth=depth,
        color_intrinsic=o3d.core.Tensor(K),
        depth_intrinsic=o3d.core.Tensor(default_depth_intrinsic(K, scale_factor)),
        masks=masks,
        depth_scale=DEPTH_SCALE,
        depth_trunc=3.0,
        color_encoding="srgb",
        sensor="synthetic",
        groundtruth=gt,
        metadata={
            # what a user measures with a ruler and writes into capture.json (read by refine)
            **({"led_offset": [float(v) for v in lighting.offset]} if isinstance(lighting, LEDLight) else {}),
            "synthetic": {
                "mesh": str(mesh) if isinstance(mesh, (str, Path)) else type(mesh).__name__,
                "frames": int(frames),
                "scale_factor": int(scale_factor),
                "size": [W, H],
                "trajectory": trajectory,
                "light": light,
                "seed": int(seed),
                "noise": bool(noise),
                "object_size": float(object_size),
                "distance": float(distance),
            }
        },
    )


def _progress(iterable, enabled: bool):
    """Wrap ``iterable`` in a tqdm bar when ``enabled``."""
    if not enabled:
        return iterable
    from tqdm.auto import tqdm

    return tqdm(iterable, desc="rendering", unit="frame")
