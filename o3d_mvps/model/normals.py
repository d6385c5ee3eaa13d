"""Perspective normals of a depth map (paper Sec. 3.2) and the finite differences behind them.

For depth z (metres) on a grid with intrinsics K, the unnormalised normal is
``ñ = [fx z_u, fy z_v, -z - (u - cx) z_u - (v - cy) z_v]``, ``dA = |ñ|``, ``n = ñ / dA``
(unit, pointing to the camera).

z_u, z_v are central differences where both neighbours lie in the mask, one-sided ones at
the mask's edge and 0 where neither neighbour is in it. Forward differences estimate the normal half a pixel away from the pixel whose intensity it
must explain, which measurably biased the shading (5.2 deg median normal error on a
ground-truth bunny depth at 320x240, against 1.4 deg central) and pulled the pose updates
off the true poses. ``scheme="forward"`` keeps them for comparison.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np
import scipy.sparse as sp

from .arrays import array_module, fused

SCHEMES = ("central", "forward")


@dataclass(frozen=True)
class MaskedGrid:
    """Pixels of a boolean mask and the finite-difference stencil on them.

    ``index`` (H, W) int64 maps a pixel to its position in the masked vector (-1 outside);
    ``u``, ``v`` (N,) pixel coordinates. For each direction d in (u, v) the difference is
    ``z_d = wf_d * (z[fwd_d] - z) + wb_d * (z - z[bwd_d])`` with neighbour indices
    ``fwd_d``, ``bwd_d`` (N,) and weights ``wf_d``, ``wb_d`` (N,) in {0, 0.5, 1}.
    """

    mask: np.ndarray
    index: np.ndarray
    u: np.ndarray
    v: np.ndarray
    fwd_u: np.ndarray
    bwd_u: np.ndarray
    wf_u: np.ndarray
    wb_u: np.ndarray
    fwd_v: np.ndarray
    bwd_v: np.ndarray
    wf_v: np.ndarray
    wb_v: np.ndarray

    @property
    def size(self) -> int:
        return int(self.u.size)

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape

    def interior(self) -> tuple[np.ndarray, np.ndarray]:
        """(along u, along v) (N,) bool: the pixels whose two neighbours in that direction are both
        masked (the centres of second differences), whatever the scheme's weights (a forward
        scheme's pixel with both neighbours weighs only the forward one)."""
        own = np.arange(self.size)
        return (self.fwd_u != own) & (self.bwd_u != own), (self.fwd_v != own) & (self.bwd_v != own)

    def gather(self, image: np.ndarray) -> np.ndarray:
        """Values (N, ...) of an (H, W, ...) image at the masked pixels."""
        return image[self.v, self.u]

    def scatter(self, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """An (H, W, ...) image holding ``values`` (N, ...) on the mask and ``fill`` elsewhere."""
        out = np.full(self.mask.shape + values.shape[1:], fill, dtype=values.dtype)
        out[self.v, self.u] = values
        return out

    def on_device(self, device) -> "MaskedGrid":
        """This grid with its per-pixel arrays and difference operators on ``device`` (a
        :class:`~o3d_mvps.solver.device.ArrayDevice`); ``mask`` and ``index`` stay on the host, so
        :meth:`gather` and :meth:`scatter` take host arrays."""
        # C-contiguous (np.nonzero's u, v are strided views) for the kernels that take them
        moved = dataclasses.replace(self, **{f.name: device.asarray(np.ascontiguousarray(getattr(self, f.name)))
                                             for f in dataclasses.fields(self) if f.name not in ("mask", "index")})
        # cached_property writes the instance dict, also of a frozen dataclass
        moved.__dict__["_difference_operators"] = tuple(map(device.sparse_matrix, self.difference_operators()))
        moved.__dict__["_transposed_difference_operators"] = tuple(
            map(device.sparse_matrix, self.transposed_difference_operators()))
        return moved

    def _stencils(self):
        return ((self.fwd_u, self.bwd_u, self.wf_u, self.wb_u), (self.fwd_v, self.bwd_v, self.wf_v, self.wb_v))

    def gradient(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(z_u, z_v), each (N,), of a masked depth vector z (N,)."""
        return tuple(_one_sided_sum(z[f], z, z[b], wf, wb) for f, b, wf, wb in self._stencils())

    def difference_operators(self) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """Sparse (N, N) matrices Du, Dv with Du @ z == gradient(z)[0] (and likewise Dv); built
        once per grid."""
        return self._difference_operators

    def transposed_difference_operators(self) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """Du^T, Dv^T as CSR matrices (row access for products), built once per grid."""
        return self._transposed_difference_operators

    @cached_property
    def _transposed_difference_operators(self) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        return tuple(sp.csr_matrix(D.T) for D in self.difference_operators())

    @cached_property
    def _difference_operators(self) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        n = self.size
        rows = np.arange(n)
        ops = []
        for f, b, wf, wb in self._stencils():
            data = np.concatenate([wf, -wb, wb - wf])
            ops.append(sp.csr_matrix((data, (np.tile(rows, 3), np.concatenate([f, b, rows]))), shape=(n, n)))
        return ops[0], ops[1]


def masked_grid(mask: np.ndarray, scheme: str = "central") -> MaskedGrid:
    """Build the :class:`MaskedGrid` of a boolean (H, W) mask; scheme "central" or "forward"."""
    if scheme not in SCHEMES:
        raise ValueError(f"unknown difference scheme {scheme!r}; use one of {SCHEMES}")
    mask = np.asarray(mask, dtype=bool)
    H, W = mask.shape
    v, u = np.nonzero(mask)
    index = np.full((H, W), -1, dtype=np.int64)
    index[v, u] = np.arange(v.size)

    def neighbour(du: int, dv: int):
        own = np.arange(v.size)
        found = []
        for s in (1, -1):
            nu, nv = u + s * du, v + s * dv
            ok = (nu >= 0) & (nv >= 0) & (nu < W) & (nv < H)
            ok[ok] = mask[nv[ok], nu[ok]]
            nb = own.copy()
            nb[ok] = index[nv[ok], nu[ok]]
            found.append((nb, ok))
        (fwd, f_ok), (bwd, b_ok) = found
        if scheme == "forward":
            b_ok = b_ok & ~f_ok
        both = f_ok & b_ok
        wf = np.where(both, 0.5, f_ok.astype(np.float64))
        wb = np.where(both, 0.5, b_ok.astype(np.float64))
        return fwd, bwd, wf, wb

    return MaskedGrid(mask, index, u, v, *neighbour(1, 0), *neighbour(0, 1))


def unnormalised_normals(grid: MaskedGrid, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """ñ (N, 3) of the masked depth vector z (N,) in metres; units metres (pixel-scaled)."""
    z_u, z_v = grid.gradient(z)
    return np.stack(_normal_components(z, z_u, z_v, grid.u, grid.v, K[0, 0], K[1, 1], K[0, 2], K[1, 2]), axis=-1)


def unit_normals(grid: MaskedGrid, z: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals n = ñ / dA (N, 3) and dA = max(|ñ|, 1e-12) (N,) of the masked depth z (N,)
    metres. On the host from :func:`unnormalised_normals`; on a GPU the differences are the
    grid's difference operators' products (``Du z``, ``Dv z``: the same stencil, two launches
    where the gathers took six) and the rest one fused kernel."""
    xp = array_module(z)
    if xp is np:
        n_tilde = unnormalised_normals(grid, z, K)
        dA = np.maximum(np.linalg.norm(n_tilde, axis=1), 1e-12)
        return n_tilde / dA[:, None], dA
    Du, Dv = grid.difference_operators()
    *n, dA = _unit_normal_components(z, Du @ z, Dv @ z, grid.u, grid.v, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    return xp.stack(n, axis=-1), dA


@numba.njit(inline="always")
def unit_normal_at(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, p):  # pragma: no cover - compiled
    """:func:`unit_normals` of pixel p, (n_x, n_y, n_z, dA): the grid's differences (its arrays, as
    :meth:`MaskedGrid.gradient` forms them) and :func:`_normal_components` on one pixel, for the
    compiled loops over frames and pixels (a CUDA kernel computes each pixel's normal from z
    where the array form takes six launches)."""
    zp = z[p]
    z_u = wf_u[p] * (z[fwd_u[p]] - zp) + wb_u[p] * (zp - z[bwd_u[p]])
    z_v = wf_v[p] * (z[fwd_v[p]] - zp) + wb_v[p] * (zp - z[bwd_v[p]])
    nx = K[0, 0] * z_u
    ny = K[1, 1] * z_v
    nz = -zp - (u[p] - K[0, 2]) * z_u - (v[p] - K[1, 2]) * z_v
    dA = math.sqrt(nx * nx + ny * ny + nz * nz)
    if dA < 1e-12:
        dA = 1e-12
    return nx / dA, ny / dA, nz / dA, dA


@fused
def _unit_normal_components(z, z_u, z_v, u, v, fx, fy, cx, cy):
    """n_x, n_y, n_z and dA, each (N,), of depth z (N,) and its differences at pixels (u, v)."""
    nx, ny, nz = _normal_components.__wrapped__(z, z_u, z_v, u, v, fx, fy, cx, cy)
    dA = array_module(z).maximum(array_module(z).sqrt(nx * nx + ny * ny + nz * nz), 1e-12)
    return nx / dA, ny / dA, nz / dA, dA


@fused
def _one_sided_sum(z_forward, z, z_backward, wf, wb):
    """A difference of z (N,) from its neighbours' values: ``wf (z_f - z) + wb (z - z_b)``."""
    return wf * (z_forward - z) + wb * (z - z_backward)


@fused
def _normal_components(z, z_u, z_v, u, v, fx, fy, cx, cy):
    """The components of ñ, each (N,), of depth z (N,) and its differences at pixels (u, v)."""
    return fx * z_u, fy * z_v, -z - (u - cx) * z_u - (v - cy) * z_v


def perspective_normals(depth: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None,
                        scheme: str = "central") -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (H, W, 3) pointing to the camera and dA (H, W) of a depth map in metres.

    ``mask`` (H, W) bool defaults to ``depth > 0``; normals and dA are 0 outside it.
    """
    depth = np.asarray(depth, dtype=np.float64)
    mask = depth > 0 if mask is None else np.asarray(mask, dtype=bool) & (depth > 0)
    grid = masked_grid(mask, scheme)
    n_tilde = unnormalised_normals(grid, grid.gather(depth), K)
    dA = np.linalg.norm(n_tilde, axis=1)
    normals = n_tilde / np.maximum(dA, 1e-12)[:, None]
    return grid.scatter(normals), grid.scatter(dA)
