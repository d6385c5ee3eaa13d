"""Perspective normals of a depth map (DESIGN section 2) and the finite differences behind them.

For depth z (metres) on a grid with intrinsics K, the unnormalised normal is
``ñ = [fx z_u, fy z_v, -z - (u - cx) z_u - (v - cy) z_v]``, ``dA = |ñ|``, ``n = ñ / dA``
(unit, pointing to the camera). z_u, z_v are forward differences, backward ones where the
forward neighbour leaves the mask, and 0 where both leave it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class MaskedGrid:
    """Pixels of a boolean mask and the finite-difference stencil on them.

    ``index`` (H, W) int64 maps a pixel to its position in the masked vector (-1 outside);
    ``u``, ``v`` (N,) pixel coordinates; ``nb_u``, ``nb_v`` (N,) the neighbour used for the
    u and v differences and ``sign_u``, ``sign_v`` (N,) in {+1 forward, -1 backward, 0 none},
    so that ``z_u = sign_u * (z[nb_u] - z)``.
    """

    mask: np.ndarray
    index: np.ndarray
    u: np.ndarray
    v: np.ndarray
    nb_u: np.ndarray
    nb_v: np.ndarray
    sign_u: np.ndarray
    sign_v: np.ndarray

    @property
    def size(self) -> int:
        return int(self.u.size)

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape

    def gather(self, image: np.ndarray) -> np.ndarray:
        """Values (N, ...) of an (H, W, ...) image at the masked pixels."""
        return image[self.v, self.u]

    def scatter(self, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """An (H, W, ...) image holding ``values`` (N, ...) on the mask and ``fill`` elsewhere."""
        out = np.full(self.mask.shape + values.shape[1:], fill, dtype=values.dtype)
        out[self.v, self.u] = values
        return out

    def gradient(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(z_u, z_v), each (N,), of a masked depth vector z (N,)."""
        return self.sign_u * (z[self.nb_u] - z), self.sign_v * (z[self.nb_v] - z)

    def difference_operators(self) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """Sparse (N, N) matrices Du, Dv with Du @ z == gradient(z)[0] (and likewise Dv)."""
        n = self.size
        rows = np.arange(n)
        ops = []
        for nb, sign in ((self.nb_u, self.sign_u), (self.nb_v, self.sign_v)):
            data = np.concatenate([sign, -sign]).astype(np.float64)
            ops.append(sp.csr_matrix((data, (np.concatenate([rows, rows]), np.concatenate([nb, rows]))), shape=(n, n)))
        return ops[0], ops[1]


def masked_grid(mask: np.ndarray) -> MaskedGrid:
    """Build the :class:`MaskedGrid` of a boolean (H, W) mask."""
    mask = np.asarray(mask, dtype=bool)
    H, W = mask.shape
    v, u = np.nonzero(mask)
    index = np.full((H, W), -1, dtype=np.int64)
    index[v, u] = np.arange(v.size)

    def neighbour(du: int, dv: int) -> tuple[np.ndarray, np.ndarray]:
        fu, fv = u + du, v + dv
        fwd_ok = (fu < W) & (fv < H)
        fwd_ok[fwd_ok] = mask[fv[fwd_ok], fu[fwd_ok]]
        bu, bv = u - du, v - dv
        bwd_ok = (bu >= 0) & (bv >= 0)
        bwd_ok[bwd_ok] = mask[bv[bwd_ok], bu[bwd_ok]]
        bwd_ok &= ~fwd_ok
        nb = np.arange(v.size)
        nb[fwd_ok] = index[fv[fwd_ok], fu[fwd_ok]]
        nb[bwd_ok] = index[bv[bwd_ok], bu[bwd_ok]]
        sign = fwd_ok.astype(np.float64) - bwd_ok.astype(np.float64)
        return nb, sign

    nb_u, sign_u = neighbour(1, 0)
    nb_v, sign_v = neighbour(0, 1)
    return MaskedGrid(mask, index, u, v, nb_u, nb_v, sign_u, sign_v)


def unnormalised_normals(grid: MaskedGrid, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """ñ (N, 3) of the masked depth vector z (N,) in metres; units metres (pixel-scaled)."""
    z_u, z_v = grid.gradient(z)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.stack([fx * z_u, fy * z_v, -z - (grid.u - cx) * z_u - (grid.v - cy) * z_v], axis=-1)


def perspective_normals(depth: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (H, W, 3) pointing to the camera and dA (H, W) of a depth map in metres.

    ``mask`` (H, W) bool defaults to ``depth > 0``; normals and dA are 0 outside it.
    """
    depth = np.asarray(depth, dtype=np.float64)
    mask = depth > 0 if mask is None else np.asarray(mask, dtype=bool) & (depth > 0)
    grid = masked_grid(mask)
    n_tilde = unnormalised_normals(grid, grid.gather(depth), K)
    dA = np.linalg.norm(n_tilde, axis=1)
    normals = n_tilde / np.maximum(dA, 1e-12)[:, None]
    return grid.scatter(normals), grid.scatter(dA)
