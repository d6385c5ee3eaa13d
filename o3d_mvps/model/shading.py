"""First-order spherical-harmonics shading (DESIGN section 2).

``m(n) = [1, n_x, n_y, n_z]``; frame i's shading of a unit normal n is ``<l_i, m(n)>``.
"""

from __future__ import annotations

import numpy as np

#: Initial lighting of every frame: a little ambient plus frontal light (normals point to -z).
INITIAL_LIGHT = np.array([0.2, 0.0, 0.0, -1.0])


def sh_basis(normals: np.ndarray) -> np.ndarray:
    """m(n): (..., 4) first-order SH basis of unit normals (..., 3)."""
    return np.concatenate([np.ones(normals.shape[:-1] + (1,), dtype=normals.dtype), normals], axis=-1)


def shading(normals: np.ndarray, light: np.ndarray) -> np.ndarray:
    """<l, m(n)>: (...) shading of unit normals (..., 3) under SH light (4,)."""
    return light[0] + normals @ np.asarray(light[1:], dtype=normals.dtype)
