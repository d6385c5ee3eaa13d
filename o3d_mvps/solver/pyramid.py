"""Coarse-to-fine pyramid: per-level images, masks, intrinsics and the depth prior D.

Level 0 is the colour resolution; level l has the colour size divided by 2^l. The depth
prior compares D z with the low-resolution reference depth z0: where a level's grid is finer
than the depth grid by an integer factor k >= 2, D averages k x k blocks (only blocks fully
inside the mask with a valid z0); otherwise D is the identity on z0 resampled to the level.
Its smoothness part S takes the depth's second differences along rows and columns, under room
light each row weighted down where the sensor's surface is steep (:mod:`.smoothness`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property

import cv2
import numpy as np
import scipy.sparse as sp

from ..colour import CodedColours, float_frame
from ..model.arrays import array_module, fused, like, sparse_module
from ..model.camera import scale_intrinsics
from ..model.normals import MaskedGrid, masked_grid
from ..model.resampling import fill_nearest_valid, resample_valid, resize
from .device import kernels_for
from .krylov import multiply_add
from .smoothness import (grid_mode_row_flags, row_centres, second_differences, smoothness_rows,
                         unweighted_second_differences, with_grid_modes)


def _entry_centres(S: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Each stored entry's row centre pixel (nnz,) int32 of the host's smoothness S
    (:func:`.smoothness.row_centres`) and whether its row keeps weight 1: the grid-mode
    rows (:meth:`DepthPrior.weigh_smoothness`), 1.0 or 0.0 (nnz,) float64."""
    counts = np.diff(S.indptr)
    return (np.repeat(row_centres(S), counts).astype(np.int32),
            np.repeat(grid_mode_row_flags(S), counts).astype(np.float64))


def to_host_sparse(S):
    """A device CSR matrix's SciPy copy (its arrays read; the host's itself)."""
    if array_module(S.data) is np:
        return S
    return sp.csr_matrix((S.data.get(), S.indices.get(), S.indptr.get()), shape=S.shape)


@fused
def _row_scaled(data, weights, keep):
    """``data * weights ** 0.5`` elementwise, ``data`` where ``keep``: a CSR matrix's entries
    scaled by the square root of their row's weight (one kernel on a GPU)."""
    return data * ((1.0 - keep) * weights + keep) ** 0.5


def level_size(size: tuple[int, int], level: int) -> tuple[int, int]:
    """(H, W) of pyramid level ``level`` for a colour size (H, W)."""
    f = 2**level
    return max(1, int(round(size[0] / f))), max(1, int(round(size[1] / f)))



def gram(A) -> sp.csr_matrix:
    """A^T A (N, N) as CSR with sorted indices for a sparse A (M, N). On the host the transpose is
    made CSR first and multiplied as such (one ``csr_matmat``): the same matrix bit for bit as
    ``(A.T @ A).tocsr()``, whose CSC product and conversion back took five times as long (S^T S of
    a 1280x960 level: 0.63 -> 0.13 CPU s). A device matrix: ``(A.T @ A).tocsr()``."""
    if not sp.issparse(A):
        return (A.T @ A).tocsr()
    product = A.T.tocsr() @ A
    product.sort_indices()
    return product


#: Grid pixels up to which a prior that can make its unweighted S again
#: (:meth:`DepthPrior.rebuild_smoothness_with`) holds it instead: made anew at each weighing, the
#: slope-weighted rows took 44 ms of serial work at the D415's 89 619 pixels, twice a level
#: (:data:`.driver.EVIDENCE_SWEEPS`), for some 18 MB held there (1.4 M entries); a 2 MP level
#: (77 MB) still makes it anew. The same matrix bit for bit either way.
REBUILD_SMOOTHNESS_PIXELS = 262_144


@dataclass
class DepthPrior:
    """tau * || D z - z0 ||^2 + mu * || S z ||^2 on one level: D (M, N) sparse, z0 (M,) metres;
    S (K, N) sparse second differences (:func:`second_differences`, None: no smoothness term);
    the depth envelope lower <= z <= upper, (N,) metres each (see :func:`depth_envelope`)."""

    D: sp.csr_matrix
    z0: np.ndarray
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    S: sp.csr_matrix | None = None

    def weigh_smoothness(self, pixel_weights: np.ndarray) -> None:
        """Weight each second-difference row of the unweighted S by ``pixel_weights`` (N,) at its
        centre pixel (:func:`.smoothness.row_centres`; grid-mode rows keep theirs): the energy's
        mu ||S z||^2 becomes mu sum_k w_k (S z)_k^2; replaces the last weights. Where the prior
        can make its unweighted S again (:meth:`rebuild_smoothness_with`) and its grid has more
        than :data:`REBUILD_SMOOTHNESS_PIXELS` pixels it does so for each weighing instead of
        holding it beside the weighted one (77 MB at 2 megapixels, through the level's joint steps)."""
        if self.S is None:
            return
        self.__dict__.pop("StS", None)
        base = self._unweighted_smoothness()  # may be put back from the last weighted S
        self.S = None  # the last weighted S goes before the next is made (77 MB at 2 MP)
        if self.__dict__.get("_S_build") is None or base.shape[1] <= REBUILD_SMOOTHNESS_PIXELS:
            self.__dict__.setdefault("_S_unweighted", base)
        entries = None
        if array_module(pixel_weights) is not np:  # once per level (set by on_device): each entry's row centre
            entries = self.__dict__.get("_entry_centres")
            if entries is None:
                entries = self.__dict__["_entry_centres"] = tuple(
                    like(a, pixel_weights) for a in _entry_centres(to_host_sparse(base)))
        if entries is not None:  # on a GPU: a gather and one fused kernel, S's pattern kept
            centres, keep = entries
            self.S = sparse_module(base).csr_matrix((_row_scaled(base.data, pixel_weights[centres], keep),
                                                     base.indices, base.indptr), shape=base.shape)
        else:
            weights = pixel_weights[row_centres(base)]
            # the grid-mode rows (5 entries) keep their weight: the shading's evidence says nothing of
            # the mode, and the LED's ceiling weight on them flattened the rims (640x480 bunny: RMSE
            # 0.898 -> 1.159 mm at weight 1000, 0.962 without it)
            weights[grid_mode_row_flags(base)] = 1.0
            # each row's entries scaled in place, S's pattern and column order kept (its index arrays
            # shared, as on a GPU): the values of diags(w^0.5) @ S, whose sparse product (columns
            # reversed) took 0.13-0.5 CPU s at 2 MP
            scaled = base.data * np.repeat(weights ** 0.5, np.diff(base.indptr))
            self.S = sp.csr_matrix((scaled, base.indices, base.indptr), shape=base.shape)
        self.__dict__["_weighted"] = True

    def rebuild_smoothness_with(self, build) -> None:
        """Give the prior ``build(S)``, which returns its unweighted S anew from its last weighted
        ``S`` (the same matrix bit for bit: made again from the level, or the taps put back), so
        that weighing it does not keep a copy. Handed S rather than closing over the prior: a
        closure would make a reference cycle that keeps a dropped level's matrices alive until
        the garbage collector runs."""
        self.__dict__["_S_build"] = build

    def _unweighted_smoothness(self) -> sp.csr_matrix:
        """S before any weights: S itself until weighed, then the copy kept or made anew."""
        if not self.__dict__.get("_weighted"):
            return self.S
        if "_S_unweighted" in self.__dict__:
            return self.__dict__["_S_unweighted"]
        return self.__dict__["_S_build"](self.S)

    def energy(self, z: np.ndarray, tau: float, mu: float) -> float:
        """tau ||D z - z0||^2 + mu ||S z||^2 of depth z (N,) metres."""
        if array_module(z) is np:
            d = self.D @ z - self.z0
        else:  # D z - z0 in one kernel
            d = multiply_add(self.D, 1.0, z, self._negative_z0)
        if mu > 0 and self.S is not None:
            s = self.S @ z
            return float(_weighted_sum(tau, d @ d, mu, s @ s))  # one copy to the host (a synchronisation on a GPU)
        return float(tau * (d @ d))

    def retarget(self, z0: np.ndarray) -> None:
        """The target replaced by ``z0`` (M,) metres (host; the same rows, kept where the prior's
        arrays are: on a GPU copied there)."""
        self.z0 = like(np.asarray(z0, dtype=np.float64), self.z0)
        self.__dict__.pop("_negative_z0", None)

    @cached_property
    def _negative_z0(self) -> np.ndarray:
        """-z0 (M,), formed once (:meth:`energy` on a GPU)."""
        return -self.z0

    @cached_property
    def _Dt(self):
        """D^T (N, M) as CSR, formed once (:meth:`negative_gradient` on a GPU)."""
        return sparse_module(self.D).csr_matrix(self.D.T)

    @cached_property
    def DtD(self) -> sp.csr_matrix:
        """D^T D (N, N), built once per level."""
        return gram(self.D)

    @cached_property
    def StS(self) -> sp.csr_matrix:
        """S^T S (N, N), built at its first use after S is set or weighted (S is set when the
        level is built, before any use); :meth:`release_products` drops it."""
        return gram(self.S)

    def release_products(self) -> None:
        """Drop S^T S (:attr:`StS`) until it is asked for again: a step that has formed its
        system from it (:func:`.normal_equations.joint_system` on the host) does not hold it
        through its solve (9 entries a pixel: 107 MB at 2 megapixels, beside the AMG set-up).
        Formed again by the same product, it is the same bit for bit. Nothing is dropped while
        :meth:`hold_products` holds it."""
        if not self.__dict__.get("_hold_products"):
            self.__dict__.pop("StS", None)

    def hold_products(self, hold: bool) -> None:
        """Keep S^T S between steps (``hold``: :meth:`release_products` then drops nothing) for a
        level whose smoothness weights stay as they are through its sweeps (a static camera's
        levels after the lamps are placed: one product a level, not one a step; 0.9 CPU s a
        step at 1.13 M pixels), or let it go (False: dropped now)."""
        self.__dict__["_hold_products"] = bool(hold)
        if not hold:
            self.release_products()

    def normal_equations(self, z: np.ndarray, tau: float, mu: float) -> tuple[sp.csr_matrix, np.ndarray]:
        """The energy's Hessian (N, N) and minus its gradient (N,) at depth z (N,)."""
        (scale, first), *rest = self.hessian_terms(tau, mu)
        hessian = scale * first
        for scale, term in rest:
            hessian = hessian + scale * term
        return hessian, self.negative_gradient(z, tau, mu)

    def hessian_terms(self, tau: float, mu: float, rows: bool = False) -> list:
        """The energy's Hessian as [(scale, (N, N) sparse)] to add up: 2 tau D^T D, and
        2 mu S^T S where there is a smoothness term. rows: the first term as (2 tau, D) (M, N),
        for a caller that adds the Gram of D's rows itself (D^T D not formed nor kept)."""
        terms = [(2.0 * tau, self.D if rows else self.DtD)]
        if mu > 0 and self.S is not None:
            terms.append((2.0 * mu, self.StS))
        return terms

    def negative_gradient(self, z: np.ndarray, tau: float, mu: float) -> np.ndarray:
        """Minus the energy's gradient (N,) at depth z (N,) (on a GPU one launch of
        :func:`.kernels.prior_gradient`: ``D z - z0``, ``-2 tau D^T (.)``, ``-2 mu S^T S z`` added)."""
        if array_module(z) is not np:  # one launch (the sums of three csr_multiply_add passes)
            with_s = mu > 0 and self.S is not None
            S = self.StS if with_s else self.D  # unread without S
            out = array_module(z).empty_like(z)
            kernels_for(z).prior_gradient(self.D.indptr, self.D.indices, self.D.data, self._Dt.indptr, self._Dt.indices,
                                          self._Dt.data, S.indptr, S.indices, S.data, with_s, z, self._negative_z0,
                                          -2.0 * tau, -2.0 * mu, out)
            return out
        rhs = -2.0 * tau * (self.D.T @ (self.D @ z - self.z0))
        if mu > 0 and self.S is not None:
            rhs = rhs - 2.0 * mu * (self.StS @ z)
        return rhs

    @property
    def smoothness_pattern(self) -> sp.csr_matrix | None:
        """S before :meth:`weigh_smoothness` (whose weights keep its pattern), or None."""
        return None if self.S is None else self._unweighted_smoothness()

    def on_device(self, device) -> "DepthPrior":
        """This prior with its arrays and operators on ``device`` (an
        :class:`~.device.ArrayDevice`)."""
        moved = DepthPrior(device.sparse_matrix(self.D), device.asarray(self.z0),
                           *(None if a is None else device.asarray(a) for a in (self.lower, self.upper)),
                           None if self.S is None else device.sparse_matrix(self.S))
        moved.__dict__["envelope_positive"] = self.envelope_positive  # from the host's arrays: no read there
        # formed here, with the level (a copy each), not by launches in its first sweep
        moved.__dict__["_negative_z0"] = device.asarray(-self.z0)
        moved.__dict__["_zeros"] = device.asarray(np.zeros(self.D.shape[1]))
        entries = None if self.S is None or device.xp is np else _entry_centres(self._unweighted_smoothness())
        if entries is not None:
            moved.__dict__["_entry_centres"] = tuple(device.asarray(a) for a in entries)
        moved.__dict__["DtD"] = device.sparse_matrix(self.DtD)
        if self.S is not None:
            moved.__dict__["StS"] = device.sparse_matrix(self.StS)
        return moved

    @cached_property
    def envelope_positive(self) -> bool:
        """Whether every depth clipped into the envelope is > 0 (or NaN): both bounds > 0 at every
        pixel (False without an envelope). A GPU's line searches then need not read whether a
        trial depth left the domain (a NaN trial's energy is NaN, which no search accepts)."""
        if self.lower is None:
            return False
        return bool(np.all(self.lower > 0) and np.all(self.upper > 0))

    def clip(self, z: np.ndarray) -> np.ndarray:
        """z (N,) clipped into the envelope (on a GPU one fused kernel)."""
        if self.lower is None:
            return z
        return np.clip(z, self.lower, self.upper) if array_module(z) is np else _clipped(z, self.lower, self.upper)

    @property
    def rows(self) -> int:
        return int(self.z0.size)


@fused
def _clipped(z, lower, upper):
    """``np.clip(z, lower, upper)`` (N,) as one kernel on a GPU."""
    xp = array_module(z)
    return xp.minimum(xp.maximum(z, lower), upper)


@fused
def _weighted_sum(a, x, b, y):
    """``a x + b y`` (one kernel on a GPU)."""
    return a * x + b * y


def depth_prior(grid: MaskedGrid, z0: np.ndarray, level_factor: float) -> DepthPrior:
    """D and z0 for a level whose pixels are ``level_factor`` = SF / 2^level depth pixels wide."""
    H, W = grid.shape
    valid0 = z0 > 0
    k = int(round(level_factor))
    if level_factor >= 2 and abs(level_factor - k) < 1e-9 and z0.shape == (H // k, W // k):
        blocks = (grid.v // k) * z0.shape[1] + (grid.u // k)
        counts = np.bincount(blocks, minlength=z0.size)
        good = (counts == k * k) & valid0.ravel()
        keep = good[blocks]
        row_of_block = np.cumsum(good) - 1
        rows = row_of_block[blocks[keep]]
        cols = np.nonzero(keep)[0]
        D = sp.csr_matrix((np.full(cols.size, 1.0 / (k * k)), (rows, cols)), shape=(int(good.sum()), grid.size))
        return DepthPrior(D, z0.ravel()[good].astype(np.float64))
    z0_level, ok = resample_valid(z0, valid0, (H, W)) if z0.shape != (H, W) else (z0.astype(np.float64), valid0)
    on = ok[grid.v, grid.u]
    cols = np.nonzero(on)[0]
    D = sp.csr_matrix((np.ones(cols.size), (np.arange(cols.size), cols)), shape=(cols.size, grid.size))
    return DepthPrior(D, z0_level[grid.v[on], grid.u[on]])


def depth_envelope(z0: np.ndarray, size: tuple[int, int], margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Bounds (H, W) metres each for the depth of a level of ``size`` (H, W): the least and
    greatest sensor depth z0 (h, w) around each pixel (its depth pixel and their neighbours),
    widened by the relative ``margin``.

    The depth super-resolved from a block-average prior is free within a block where the
    photometric terms say little (at depth discontinuities); without bounds a pixel there can
    run off far behind or before everything the sensor saw while its block mean stays put.
    """
    valid = z0 > 0
    filled = fill_nearest_valid(z0.astype(np.float64), valid)
    h, w = z0.shape
    radius = max(1, int(np.ceil(max(h / size[0], w / size[1]))))
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    lower = cv2.erode(filled, kernel) * (1.0 - margin)
    upper = cv2.dilate(filled, kernel) * (1.0 + margin)
    return tuple(cv2.resize(b, (size[1], size[0]), interpolation=cv2.INTER_NEAREST) for b in (lower, upper))


@dataclass
class Level:
    """Everything one pyramid level of the solver reads.

    grid: masked reference pixels. K: (3, 3) level intrinsics. size: (H, W).
    images: per frame an (H, W, 3) float32 linear RGB image, or on the finest level of coded
        frames the frame's ``(codes, table)`` (:meth:`~o3d_mvps.colour.CodedColours.frame`,
        decoded where sampled: :func:`.kernels.frame_value`); its gradients are sampled from it
        (:func:`.kernels.image_gradients_at`).
    frame_masks: per frame an (H, W) bool mask or None. prior: the depth prior.
    image_stack: on a GPU, the images as one (n, H, W, 3) array (``images`` are its frames),
        for kernels over every frame at once; None on the host.
    """

    index: int
    grid: MaskedGrid
    K: np.ndarray
    size: tuple[int, int]
    images: list
    frame_masks: list
    prior: DepthPrior
    image_stack: object = None

    def on_device(self, device) -> "Level":
        """This level with its grid, images and prior on ``device`` (an
        :class:`~.device.ArrayDevice`; the host's is this level itself). Frame masks stay on the
        host (the visibility test runs there)."""
        if device.xp is np:
            return self
        # one copy (coded frames decoded: the GPU's kernels read float32); the frames' images are views of it
        stack = device.asarray(np.stack([float_frame(image) for image in self.images]))
        return replace(self, grid=self.grid.on_device(device), images=[stack[i] for i in range(len(stack))],
                       image_stack=stack, prior=self.prior.on_device(device))


def level_mask(ref_mask: np.ndarray, index: int) -> np.ndarray:
    """The reference mask (H, W) bool on level ``index``: area-averaged, more than half inside
    (the object pixels of :func:`build_level`'s grid)."""
    return resize(ref_mask.astype(np.float32), level_size(ref_mask.shape, index)) > 0.5


def coarse_images(colors, sizes: list) -> dict:
    """{size: n (h, w, 3) float32 frames} for each (h, w) of ``sizes`` smaller than the colours
    (n frames, or a :class:`~o3d_mvps.colour.CodedColours`): each frame area-averaged, a coarse
    level's images (:func:`build_level` makes one level's here). Asked for every coarse size at
    once, each frame is decoded once for all of them instead of once a level (D415, 20 frames, 4
    coarse levels and the light selection's: 100 decodes of 2.4 ms -> 20); ``build_level(...,
    images=...)`` takes them."""
    full = tuple(colors.codes[0].shape[:2] if isinstance(colors, CodedColours) else colors[0].shape[:2])
    sizes = [tuple(size) for size in dict.fromkeys(map(tuple, sizes)) if tuple(size) != full]
    found = {size: [] for size in sizes}
    for i in range(len(colors) if sizes else 0):
        frame = colors[i]  # decoded (a new float32 array) or the float frame itself
        for size in sizes:
            found[size].append(resize(frame, size).astype(np.float32))
    return found


def build_level(index: int, colors: list, masks: list, ref_mask: np.ndarray, K: np.ndarray, z0: np.ndarray,
                scale_factor: int, scheme: str = "central", envelope_margin: float | None = None,
                slope_weighted: bool = False, grid_modes: Callable[[int], float] | None = None,
                images: list | None = None) -> Level:
    """Level ``index`` from full-resolution colours (n (H, W, 3) float32 frames, or a
    :class:`~o3d_mvps.colour.CodedColours`), masks, reference mask and z0;
    ``envelope_margin`` None leaves the depth unbounded (see :func:`depth_envelope`);
    ``slope_weighted``: the smoothness rows are :func:`smoothness_rows` (else plain second differences);
    ``grid_modes``: the weight of the grid-mode rows (:func:`.smoothness.with_grid_modes`) given the
    level's object pixels (the driver's :func:`.smoothness.grid_mode_weight`); None: none.
    images: the level's n (h, w, 3) float32 frames where the caller made them (:func:`coarse_images`),
    None: made here from ``colors``."""
    size = level_size(ref_mask.shape, index)
    K_level = scale_intrinsics(K, size[1] / ref_mask.shape[1], size[0] / ref_mask.shape[0])
    # the finest level reads the full-resolution colours themselves (no copy: they are only read;
    # coded frames as their codes and table), coarser levels area-averaged float32 copies
    if images is not None:
        if len(images) != len(colors) or any(image.shape[:2] != tuple(size) for image in images):
            raise ValueError(f"build_level: images must be {len(colors)} frames of {size}")
    elif tuple(size) != tuple(ref_mask.shape):
        images = coarse_images(colors, [size])[tuple(size)]
    elif isinstance(colors, CodedColours):
        images = [colors.frame(i) for i in range(len(colors))]
    else:
        images = [color if color.dtype == np.float32 else color.astype(np.float32) for color in colors]
    frame_masks = [m if m is None or m.shape == tuple(size) else resize(m.astype(np.float32), size) > 0.5
                   for m in masks]  # the finest level reads the masks themselves
    grid = masked_grid(level_mask(ref_mask, index), scheme)
    prior = depth_prior(grid, z0, scale_factor / 2**index)
    grid_mode_weight = 0.0 if grid_modes is None else grid_modes(grid.size)

    def smoothness():
        return with_grid_modes(grid, smoothness_rows(grid, z0, K_level, scale_factor / 2**index) if slope_weighted
                               else second_differences(grid), z0, K_level, scale_factor / 2**index,
                               grid_mode_weight)

    prior.S = smoothness()
    # weighed without a copy of the unweighted S kept: made anew, or where its rows are plain second
    # differences their taps put back into the weighted S (2 MP: a weighing 0.67 -> 0.26 CPU s with the
    # scaling in place)
    prior.rebuild_smoothness_with((lambda S: smoothness()) if slope_weighted else unweighted_second_differences)
    if envelope_margin is not None:
        prior.lower, prior.upper = (grid.gather(b) for b in depth_envelope(z0, size, envelope_margin))
    return Level(index, grid, K_level, size, images, frame_masks, prior)
