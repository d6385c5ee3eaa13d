"""Meshes from a Refinement: a textured surface for viewers and a watertight solid for printing.

Two products (docs/api.md):

- :func:`refinement_to_mesh` -- the refined depth back-projected into the reference camera
  frame (metres) and triangulated on the pixel grid, with vertex normals, per-vertex sRGB
  colours, texture coordinates and the albedo image as the material's albedo texture.
- :func:`printable_solid` -- that relief closed into a watertight, consistently oriented solid
  in millimetres, ready for a slicer.

Writers: :func:`write_mesh` (``.obj`` + ``.mtl`` + texture PNG, ``.glb``, ``.ply``, ``.stl``) and
:func:`write_stl`. Every writer refuses to replace an existing file unless ``overwrite=True``
and writes atomically (temporary files renamed into place), so a failure leaves no
half-written output.

Conventions
-----------
Pixel (u, v) is column u, row v, with pixel centres at integer coordinates
(:mod:`o3d_mvps.model.camera`). Texture coordinates follow OBJ (and Open3D's in-memory
convention, which its glTF writer converts): ``U = (u + 0.5) / W``, ``V = 1 - (v + 0.5) / H``,
origin at the bottom-left of the image. Colours (``vertex.colors`` and the texture) are
sRGB-encoded, ready for display; the albedo itself is linear RGB.
"""

from .relief import DEFAULT_MAX_DEPTH_JUMP, refinement_to_mesh, simplify_mesh
from .solid import DEFAULT_SIZE_MM, PIECES, check_solid, printable_solid, solid_volume
from .topology import mesh_arrays
from .writers import MESH_SUFFIXES, write_mesh, write_stl

__all__ = [
    "DEFAULT_MAX_DEPTH_JUMP",
    "DEFAULT_SIZE_MM",
    "MESH_SUFFIXES",
    "PIECES",
    "refinement_to_mesh",
    "simplify_mesh",
    "printable_solid",
    "check_solid",
    "solid_volume",
    "write_mesh",
    "write_stl",
    "mesh_arrays",
]
