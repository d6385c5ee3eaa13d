"""Headless previews with pyvista (VTK off-screen rendering; no display needed).

VTK's Linux wheels render off-screen through EGL or OSMesa; they need the system OpenGL
libraries (Debian/Ubuntu: ``libgl1``, ``libegl1`` and a Mesa driver ``libgl1-mesa-dri`` /
``libegl-mesa0``), see the Makefile's system-libs target.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .errors import ExportError
from .export import mesh_arrays
from .fileio import atomic_files, write_png

__all__ = ["render_preview", "VIEWS"]

VIEWS = ("camera", "iso")


def render_preview(mesh, path, *, size: tuple[int, int] = (800, 600), view: str = "camera",
                   overwrite: bool = False) -> Path:
    """Render a mesh off-screen to a PNG, with its albedo texture (or vertex colours) applied.

    Parameters
    ----------
    mesh : o3d.t.geometry.TriangleMesh or o3d.geometry.TriangleMesh
        E.g. from :func:`o3d_mvps.export.refinement_to_mesh` (reference camera frame, metres)
        or :func:`o3d_mvps.export.printable_solid` (print frame, millimetres).
    path : str or Path
        Output PNG.
    size : (int, int)
        Image width and height in pixels.
    view : {"camera", "iso"}
        "camera": from the reference camera (at the origin, looking along +z, image up = -y),
        framing the whole mesh; for meshes in the reference camera frame. "iso": an oblique
        view from above (+z) the mesh; for print solids.
    overwrite : bool
        Replace an existing file.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ExportError
        Empty mesh, bad option, or rendering failed.
    OutputExistsError
        ``path`` exists and ``overwrite`` is False.
    """
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        # Headless: start with EGL instead of trying (and warning about) an X server first.
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv  # imported here: VTK is heavy and only previews need it

    if view not in VIEWS:
        raise ExportError(f"view must be one of {VIEWS}, got {view!r}")
    width, height = (int(s) for s in size)
    if width < 16 or height < 16:
        raise ExportError(f"preview size must be at least 16 x 16 pixels, got {size}")
    path = Path(path)
    positions, tri, normals, colours, uvs, texture = mesh_arrays(mesh)
    if len(tri) == 0:
        raise ExportError("the mesh has no triangles; nothing to render")

    textured = uvs is not None and texture is not None
    if textured:
        # VTK wants texture coordinates per point: give every triangle corner its own point.
        points = positions[tri].reshape(-1, 3)
        faces = np.arange(points.shape[0]).reshape(-1, 3)
        poly = pv.PolyData(points.astype(np.float64), _vtk_faces(faces))
        poly.active_texture_coordinates = np.asarray(uvs, dtype=np.float32).reshape(-1, 2)
        mesh_kwargs = {"texture": pv.Texture(np.ascontiguousarray(texture[..., :3]))}
    else:
        poly = pv.PolyData(positions.astype(np.float64), _vtk_faces(tri))
        if colours is not None:
            poly.point_data["rgb"] = np.round(np.clip(colours, 0, 1) * 255).astype(np.uint8)
            mesh_kwargs = {"scalars": "rgb", "rgb": True}
        else:
            mesh_kwargs = {"color": "lightgray"}
    if normals is not None:  # the mesh's own (photometric) normals, per VTK point
        poly.point_data["Normals"] = np.asarray(normals, dtype=np.float32)[tri].reshape(-1, 3) if textured \
            else np.asarray(normals, dtype=np.float32)
        poly.point_data.active_normals_name = "Normals"
    else:  # per-triangle normals would show every facet: average them per vertex
        poly = poly.compute_normals(auto_orient_normals=False, consistent_normals=False, split_vertices=False)

    plotter = pv.Plotter(off_screen=True, window_size=(width, height))
    try:
        plotter.set_background("white")
        plotter.add_mesh(poly, smooth_shading=True, **mesh_kwargs)
        _place_camera(plotter, positions, view)
        image = plotter.screenshot(None, return_img=True)
    except Exception as err:  # VTK raises bare RuntimeErrors when it has no OpenGL context
        raise ExportError(f"off-screen rendering failed ({err}); VTK needs the system OpenGL libraries "
                          "(Debian/Ubuntu: apt-get install libgl1 libegl1 libgl1-mesa-dri)") from err
    finally:
        plotter.close()
    with atomic_files([path], overwrite) as tmp:
        write_png(tmp[0], np.asarray(image, dtype=np.uint8))
    return path


def _vtk_faces(tri: np.ndarray) -> np.ndarray:
    """VTK's flat face array [3, a, b, c, 3, ...] of triangles (T, 3)."""
    return np.hstack([np.full((len(tri), 1), 3, dtype=np.int64), tri.astype(np.int64)]).ravel()


def _place_camera(plotter, positions: np.ndarray, view: str) -> None:
    """Point the plotter's camera at the mesh (see render_preview's ``view``)."""
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    centre = (lo + hi) / 2.0
    radius = float(np.linalg.norm(hi - lo)) / 2.0 or 1.0
    camera = plotter.camera
    if view == "camera":
        # Look at the bounding-box centre from the origin; open the view angle just enough
        # for every vertex (tangents in the view frame, horizontal ones divided by the aspect).
        forward = centre / (np.linalg.norm(centre) or 1.0)
        right = np.cross(forward, [0.0, -1.0, 0.0])
        right /= np.linalg.norm(right) or 1.0
        up = np.cross(right, forward)
        sample = positions[:: max(1, len(positions) // 200_000)].astype(np.float64)
        depth = np.maximum(sample @ forward, 1e-9)
        width, height = plotter.window_size
        tangent = max(np.max(np.abs(sample @ up) / depth), np.max(np.abs(sample @ right) / depth) * height / width)
        camera.position = (0.0, 0.0, 0.0)
        camera.focal_point = tuple(centre)
        camera.up = tuple(up)
        camera.view_angle = float(np.degrees(2.0 * np.arctan(1.05 * tangent)))
    else:
        direction = np.array([0.6, -1.0, 1.4])
        camera.focal_point = tuple(centre)
        camera.position = tuple(centre + direction / np.linalg.norm(direction) * 3.0 * radius)
        camera.up = (0.0, 0.0, 1.0)
        plotter.reset_camera()
    plotter.reset_camera_clipping_range()
