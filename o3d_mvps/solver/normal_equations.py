"""Gauss-Newton normal equations of the depth and joint pose-depth steps.

Residual r_ic(p) = I~_ic(w_i(p)) - rho_c(p) s_i(p) of frame i, pixel p, channel c. Its row in
the depth increment dz is ``a Du + b Dv + c I`` (7-point stencil): the frozen-dA shading of the
paper, ``s_i = c_i + (alpha_i Du z + beta_i Dv z + gamma_i z) / dA`` with the light field frozen
at the current surface (SH: the frame's light vector; LED: a per-pixel vector), so
``a = -rho alpha / dA``, ``b = -rho beta / dA``, ``c = -rho gamma / dA``, plus, for the joint step,
the warp's parallax (the change of the warped colour I_i(pi(T_i X(z))) and of the LED shading
as z_p moves a point along its ray: ``g = dr/dX' . R_i ray_p``, added to c). The twists xi_i (6,)
of frames 1..n-1 enter through the pose Jacobian of :mod:`.pose` (image and shading).

The albedo is eliminated by variable projection (:class:`_AlbedoProjection`). With IRLS
weights of the Cauchy loss the normal equations are
``[[M, U], [U^T, H]] [dz; xi] = [b_z; b_xi]``: M (N, N) sparse 7-point plus 2 tau D^T D, U (N, 6m)
dense, H (6m, 6m) dense. :meth:`JointSystem.schur_operator` eliminates the twists.

U is the step's largest array (6m x N: 0.87 GB in float64 at 2 megapixels and 20 frames, where
every frame sees nearly every reference pixel, so a per-frame sparse form would save nothing).
On the host it is stored in float32 (:data:`COUPLING_DTYPE`) and multiplied by compiled loops
that sum in float64 (:func:`.kernels.rows_times`, :func:`.kernels.columns_times`): half the
memory and half the bytes read per product; its entries' rounding (6e-8 relative) is far below
the joint step's CG tolerance (1e-2).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from ..colour import frames_and_tables
from ..model.arrays import array_module, fused, like, linear_operator, sparse_module
from ..model.parallel import current_kernel_threads
from . import kernels as host_kernels
from .device import kernels_for, on_gpu, to_host
from .krylov import multiply_add
from .lighting import LEDLight
from .pose import pose_jacobian
from .problem import Estimate, Evaluation, LevelProblem


#: Storage type of the coupling U on the host (:mod:`numpy` arrays); on the GPU it stays float64.
COUPLING_DTYPE = np.float32


@dataclass
class JointSystem:
    """Normal equations of the joint step for the increments dz (N,) and twists xi (6m,).

    matrix (N, N) sparse: the depth block M; rhs_z (N,); coupling (N, 6m): U, the transpose
    (a view) of a C-ordered (6m, N) array, float32 on the host (:data:`COUPLING_DTYPE`); hessian
    (6m, 6m): H (block-diagonal per frame unless the albedo is projected out); rhs_xi (6m,);
    frames (m,): the refined frames' indices. On a GPU H and rhs_xi stay there, with every
    candidate frame's rows: kept (m,) 1.0 or 0.0 on the device, a frame not kept an identity
    block with a zero right-hand side, and selection (6m, 6m) ``-diag(kept)`` per twist row, so
    that ``-H^-1 selection`` drops such a frame's columns (its coupling and twist 0, so
    ``exp(t xi)`` leaves its pose as it is, bit for bit).
    """

    matrix: sp.csr_matrix
    rhs_z: np.ndarray
    coupling: np.ndarray
    hessian: np.ndarray
    rhs_xi: np.ndarray
    frames: list
    kept: np.ndarray | None = None
    selection: np.ndarray | None = None
    _inverse: tuple | None = None  # on a GPU (P, X) of schur_operator: (-U H^-1 diag(kept))^T and X's last column
    _work: tuple | None = None  # on a GPU: [U^T; rhs_z] (K + 1, N) and the inverse's arrays (L, X, solved, twists)

    def schur_operator(self):
        """(S, rhs): ``S = M - U H^-1 U^T`` as an operator (:func:`~o3d_mvps.model.arrays.linear_operator`) and
        its right-hand side ``b_z - U H^-1 b_xi``. S is applied as M x - U (H^-1 (U^T x)): two
        passes over U per product, where forming U H^-1 (N, 6m) once cost as much as twenty
        products. The small solve with H (6m, 6m) runs on the host.

        On the GPU, where the cost is per launch, ``X = [[-H^-1 diag(kept), x], [0, 1]]`` with
        ``x = -H^-1 diag(kept) rhs_xi`` (K + 1, K + 1) is formed there in one launch
        (:func:`.kernels.joint_inverse`: the Cholesky formula of the host's small systems, with
        :func:`_cholesky`'s fallback; the substitutions one thread per column) and
        ``P = X^T [U^T; rhs_z^T]`` (K + 1, N) in one product (as much memory again as U): its
        rows are ``(-U H^-1)^T`` and, last, the Schur right-hand side ``rhs_z + U x``. A product is
        then ``U^T x``, ``-U H^-1`` times it, and ``M x`` added in one kernel
        (:func:`.krylov.multiply_add`), no copy either way; the operator's ``low_rank_parts``
        (M, -U H^-1, U^T) let :func:`.krylov.pcg` form the product inside its multigrid kernel
        instead (none of these launches)."""
        M, U = self.matrix, self.coupling
        if not self.frames:
            return linear_operator(M.shape, lambda x: M @ x.ravel(), self.rhs_z), self.rhs_z
        if on_gpu(U):
            xp, K = array_module(U), len(self.hessian)
            stacked, L, X, solved, _ = self._work
            kernels_for(U).joint_inverse(self.hessian[None], self.selection[None], self.rhs_xi, CHOLESKY_FALLBACK, L, X,
                                         solved)
            P = xp.matmul(X[0].T, stacked)  # (-U H^-1)^T (K, N), then the right-hand side
            coupled = P[:K].T  # -U H^-1
            self._inverse = (P, X)

            def schur_product(x):
                return multiply_add(M, 1.0, x.ravel(), coupled @ (U.T @ x.ravel()))

            operator = linear_operator(M.shape, schur_product, self.rhs_z)
            operator.low_rank_parts = (M, coupled, U.T)  # krylov.pcg forms the product in its kernel
            return operator, P[K]
        factor = _cholesky(self.hessian)

        def solve_h(y):
            return like(scipy.linalg.cho_solve(factor, to_host(y)), self.rhs_z)

        def matvec(x):
            x = x.ravel()
            return M @ x - self.couple(solve_h(self.couple_t(x)))

        return linear_operator(M.shape, matvec, self.rhs_z), self.rhs_z - self.couple(solve_h(self.rhs_xi))

    def add_priors(self, priors: list) -> None:
        """Add each refined frame's pose prior: ``priors`` [(slot k, H_k (6, 6), g_k (6,))] on the
        host, H_k added to H's block k and g_k taken from rhs_xi's (on a GPU in one copy, a
        frame not kept left out)."""
        if not priors:
            return
        if self.kept is None:
            for k, H_k, g_k in priors:
                self.hessian[6 * k:6 * k + 6, 6 * k:6 * k + 6] += H_k
                self.rhs_xi[6 * k:6 * k + 6] -= g_k
            return
        n = len(self.rhs_xi)
        packed = np.zeros((n + 1, n))  # the blocks, then the right-hand side's row
        for k, H_k, g_k in priors:
            packed[6 * k:6 * k + 6, 6 * k:6 * k + 6] = H_k
            packed[n, 6 * k:6 * k + 6] = g_k
        # the prior's columns of a frame not kept zeroed: its blocks lie in its own columns only
        packed = like(packed, self.hessian) * array_module(self.hessian).repeat(self.kept, 6)
        self.hessian += packed[:n]
        self.rhs_xi -= packed[n]

    def couple(self, y: np.ndarray) -> np.ndarray:
        """U y (N,) float64 for y (6m,)."""
        U_t = self.coupling.T
        if array_module(U_t) is not np:
            return U_t.T @ y
        out = np.empty(U_t.shape[1])
        host_kernels.columns_times(U_t, np.ascontiguousarray(y, dtype=np.float64), out)
        return out

    def couple_t(self, x: np.ndarray) -> np.ndarray:
        """U^T x (6m,) float64 for x (N,)."""
        U_t = self.coupling.T
        if array_module(U_t) is not np:
            return U_t @ x
        out = np.empty(U_t.shape[0])
        host_kernels.rows_times(U_t, np.ascontiguousarray(x, dtype=np.float64), out)
        return out

    def twists(self, dz: np.ndarray) -> np.ndarray:
        """The twists (m, 6) that go with the depth increment dz (N,), on the host (on a GPU
        H^-1 (rhs_xi - U^T dz) there, as ``(-U H^-1 diag(kept))^T dz + H^-1 diag(kept) rhs_xi``
        from :meth:`schur_operator`'s product and inverse, one launch
        (:func:`.kernels.twist_readout`) and one read: a frame not kept gets a zero twist,
        exactly)."""
        if not self.frames:
            return np.zeros((0, 6))
        if self._inverse is not None:  # a frame not kept gets exactly 0: its pose stays
            P, X = self._inverse  # H^-1 symmetric: (U X)^T dz = X U^T dz up to rounding
            out = self._work[4]
            kernels_for(out).twist_readout(P, dz.ravel(), X, out)
            return to_host(out).reshape(-1, 6)
        return scipy.linalg.cho_solve(_cholesky(self.hessian), self.rhs_xi - to_host(self.couple_t(dz))).reshape(-1, 6)


#: The relative diagonal shift of a twist matrix H that rounding left semidefinite (:func:`_cholesky`).
CHOLESKY_FALLBACK = 1e-12


def _cholesky(H: np.ndarray):
    """Cholesky factor of the SPD twist Gram H (6m, 6m), with a 1e-12 relative ridge if rounding
    left it semidefinite."""
    try:
        return scipy.linalg.cho_factor(H)
    except np.linalg.LinAlgError:
        return scipy.linalg.cho_factor(H + CHOLESKY_FALLBACK * np.abs(np.diag(H)).max() * np.eye(len(H)))


def residual_jacobians(problem: LevelProblem, est: Estimate, ev: Evaluation, i: int, points_ref: np.ndarray):
    """Frame i's derivatives on every reference pixel, zero where frame i does not see it.

    Returns (use, J, g): ``use`` (N,) bool the usable pixels, J (N, 3, 6) d(residual)/d(xi_i)
    (None for the reference frame, whose pose stays fixed) and g (N, 3) d(residual)/d(z_p)
    through the warp and the light position (zero for the reference frame's warp, which moves
    along the ray). The assembly computes the same per pixel in :func:`.kernels.accumulate_frame`;
    this vectorised form is its reference (tests compare the two).
    """
    use = ev.usable[i]
    pose = est.poses[i]
    ray = points_ref / points_ref[:, 2:3]  # d(point)/d(z), reference coordinates
    dshading = problem.light_model(est).shading_jacobian(est.lights[i], ev.normals, points_ref, pose)  # (N, 6)|None
    if i == 0:
        if dshading is None:
            return use, None, np.zeros(points_ref.shape)
        return use, None, _reference_parallax(est.albedo, dshading, points_ref, use)
    J = pose_jacobian(problem.warped_gradients(i, pose, points_ref), problem.level.K)
    if dshading is not None:
        J -= est.albedo[:, :, None] * dshading[:, None, :]
    J[~use] = 0.0  # also clears what pixels behind the camera gave
    ray_i = ray @ like(pose[:3, :3].T, ray)  # d(frame-i point)/d(z)
    g = np.matmul(J[..., :3], ray_i[:, :, None])[..., 0]  # d/dX' (camera frame) . R ray, (N, 3)
    return use, J, g


def _reference_parallax(albedo: np.ndarray, dshading: np.ndarray, points: np.ndarray, use: np.ndarray) -> np.ndarray:
    """d(residual)/dz (N, 3) of the reference frame, albedo (N, 3): only its LED shading moves with
    z, along the ray d(point)/dz = point / z of the reference points (N, 3); dshading (N, 6)."""
    return _parallax_rows(albedo, dshading[:, 0:1], dshading[:, 1:2], dshading[:, 2:3], points[:, 0:1],
                          points[:, 1:2], points[:, 2:3], use[:, None])


@fused
def _parallax_rows(albedo, d0, d1, d2, x, y, z, use):
    """-albedo (ds . ray) use, ray = (x, y, z) / z (columns (N, 1) each; one kernel on a GPU)."""
    return -albedo * ((d0 * (x / z) + d1 * (y / z) + d2 * (z / z)) * use)


#: Reference pixels per block of the joint assembly. Every per-pixel array of the refined
#: frames' twists ((3, m, 6, B) coupling rows, (m, 6, B, 3) projection rows) exists for one block
#: at a time: at 2 megapixels and 20 frames the whole-image arrays took 5 GB. With 19 refined
#: frames a block's temporaries (these two, the light rows, the LED Jacobians) take about 8 kB
#: per pixel: 260 MB at 32768 pixels, 65 MB at 8192 (the joint step's peak at D415 size fell
#: from 277 to 105 MB over its entry), 32 MB at 4096 (the D415 process's peak, set in this step,
#: 963-975 -> 938 MB), for the same assembly time.
BLOCK_PIXELS = 4096

#: Pixels per parallel chunk of the host's one launch per block (:func:`.kernels.accumulate_block`,
#: used on more than one kernel thread): a block of :data:`BLOCK_PIXELS` in 4 chunks, so 2 threads
#: share it (one chunk of 16384 pixels, :data:`.kernels.CHUNK`, left the second idle: a D415
#: block 18.5 -> 9.5 ms wall); the twist Grams are summed per chunk, so they equal those of one
#: chunk (one thread) to rounding.
HOST_CHUNK_PIXELS = 1024

#: Grid pixels up to which the host's joint and depth steps keep the prior's S^T S for the next
#: step (:meth:`.pyramid.DepthPrior.release_products` above): formed again at every step, the
#: product (33 ms at the D415's 89 619 pixels) was serial and repeated while the evidence
#: weights, which change S, are held (after a level's first sweeps). At this size it takes some
#: 30 MB (9 entries a pixel); a 2 MP level (107 MB) still drops it before its AMG set-up.
HOLD_PRODUCTS_PIXELS = 262_144

#: :data:`BLOCK_PIXELS` on a GPU (:func:`_device_joint_system`), where each block costs three
#: launches (``python -m benchmarks.gpu sites``): the D415's finest level (about 90 000 object
#: pixels) in one block, its temporaries some 0.8 GB of GPU memory at 19 refined frames.
DEVICE_BLOCK_PIXELS = 98304


def joint_system(problem: LevelProblem, est: Estimate, ev: Evaluation, *, parallax: bool = True,
                 twists: bool = True, project_albedo: bool = True, min_pixels: int = 12,
                 block_pixels: int | None = None, release: bool = False) -> JointSystem:
    """Assemble the Gauss-Newton normal equations for the increments (dz, twists).

    parallax: include the warp's (and the LED position's) dependence on z in the depth rows
    (False: the paper's frozen-warp depth rows). twists: include frames 1..n-1's twists.
    project_albedo: eliminate the albedo (variable projection, see :class:`_AlbedoProjection`).

    The reference pixels are taken in blocks of ``block_pixels`` (None: :data:`BLOCK_PIXELS` on
    the host, :data:`DEVICE_BLOCK_PIXELS` on a GPU; the result does not depend on it but for the
    order of sums: every sum over frames is per pixel, every sum over pixels is added up across
    blocks).
    Per block, one compiled launch over every frame (:func:`.kernels.accumulate_block` on the
    host, in parallel over pixel chunks): each frame adds its depth rows to per-pixel sums and
    writes its twist rows and w s J, as :func:`.kernels.accumulate_frame` does a frame at a
    time; the block's albedo projection and its share of the coupling follow. On a GPU:
    :func:`_device_joint_system`.
    release: release ``ev`` (:meth:`.Evaluation.release`): its warped colours and light bases
    (which the pass does not read: 0.3-0.5 GB at 2 megapixels and 20 frames) before the coupling
    is allocated, the rest once the pass has read it, before the matrices are formed.
    """
    if ev.residual is None:
        raise ValueError("joint_system: the evaluation was released by an earlier step (Evaluation.release); "
                         "evaluate the estimate again (LevelProblem.evaluate)")
    if release:  # the warped colours and light bases are not read here: dropped before U is allocated
        ev.release(keep=("residual", "usable", "shading", "normals", "dA"))
    if on_gpu(ev.residual):
        return _device_joint_system(problem, est, ev, parallax, twists, project_albedo, min_pixels, block_pixels,
                                    release)
    grid = problem.level.grid
    N = grid.size
    counts = ev.usable.sum(axis=1)
    candidates = [i for i in range(1, problem.n_frames) if twists and counts[i] >= min_pixels]
    m = len(candidates)
    sums = np.empty((9, N))  # per pixel: Saa, Sbb, Sgg, Sab, Sag, Sbg, Ba, Bb, Bg
    coupling_t = np.zeros((6 * m, N), dtype=COUPLING_DTYPE)  # U^T, frame j's twist in rows 6j..6j+5
    grams, rhs_xi = np.zeros((m, 6, 6)), np.zeros(6 * m)  # per frame: upper triangle of w J^T J; -J^T w r
    downdate = np.zeros((6 * m, 6 * m))  # the albedo projection's sum f f^T over pixels and channels
    points_ref = problem.points(est.z)
    Du, Dv = grid.difference_operators()
    if m:  # without the stored zeros (the central differences' own pixel): a third fewer scatters into U
        Du, Dv = _without_zeros(Du), _without_zeros(Dv)
    if block_pixels is None:
        block_pixels = BLOCK_PIXELS
    slot = {i: k for k, i in enumerate(candidates)}
    with_jacobian = [i > 0 and (parallax or i in slot) for i in range(problem.n_frames)]
    frame_slots = np.array([[jac, slot.get(i, -1)] for i, jac in enumerate(with_jacobian)], dtype=np.int64)
    poses = like(est.poses, points_ref)
    # on more than one kernel thread, a helper thread takes half of each block's projection Gram
    # (BLAS, which releases the GIL) beside the main thread's half: that Gram was serial
    threads = current_kernel_threads()
    # the blocks' temporaries in one buffer for the whole pass (:func:`_block_shapes`): fresh
    # per block, each of more than glibc's mmap threshold (allocator.return_freed_arrays) was mapped,
    # faulted in page by page and unmapped again, 7000 page faults a 2 MP block
    led = isinstance(problem.light_model(est), LEDLight)
    scratch = np.empty(_size(_block_shapes(problem.n_frames, m, min(N, block_pixels), project_albedo, led)))
    with ThreadPoolExecutor(1, thread_name_prefix="o3d_mvps-gram") if threads > 1 else nullcontext() as helper:
        for start in range(0, N, block_pixels):
            block = slice(start, min(N, start + block_pixels))
            # the block's rows of Du and Dv as (indptr, indices, data): its slice of indptr into the whole
            # arrays (no copy: scipy's row slicing took 0.15 s a D415 refinement)
            _assemble_block(problem, est, ev, block, points_ref[block], candidates, parallax, project_albedo,
                            sums[:, block], grams, rhs_xi, downdate, coupling_t, _row_arrays(Du, block),
                            _row_arrays(Dv, block), poses, with_jacobian, frame_slots, helper, scratch=scratch)
    del scratch
    # frames whose own Gram is not safely invertible keep their depth rows but take no twist
    # (kernels.twist_system: the frames' condition numbers and H = blockdiag(Grams) - downdate)
    hessian, twist_rhs, frame_kept = np.empty((6 * m, 6 * m)), np.empty(6 * m), np.empty(m)
    selection = np.empty((6 * m, 6 * m))  # -diag(kept) per twist row
    if m:
        host_kernels.twist_system(grams, rhs_xi, np.zeros_like(rhs_xi), downdate, host_kernels.MAX_TWIST_CONDITION,
                                  np.empty((m, 6, 6)), frame_kept, hessian, twist_rhs, selection)
    del Du, Dv, points_ref  # the zero-free copies (45 MB at 2 megapixels): not held while M is formed
    if release:
        ev.release()
    kept_slots = np.flatnonzero(frame_kept)  # the kept frames' rows and columns
    frames = [candidates[k] for k in kept_slots]
    kept = [6 * k + a for k in kept_slots for a in range(6)]
    hessian, rhs_xi = hessian[np.ix_(kept, kept)], twist_rhs[kept]
    prior = problem.level.prior
    rhs_z = -stencil_transpose(grid, *sums[6:]) + prior.negative_gradient(est.z, problem.tau, problem.mu)
    matrix = depth_block(problem, sums[:6])  # filled into the level's pattern: no sparse products or sums
    del sums
    if N > HOLD_PRODUCTS_PIXELS:  # S^T S not held through the solve (formed again by the next step)
        prior.release_products()
    for row, k in enumerate(kept):  # the kept rows moved up in place (kept is ascending): no second U
        if row != k:
            coupling_t[row] = coupling_t[k]
    coupling = coupling_t[:len(kept)].T  # (N, 6m')
    return JointSystem(sp.csr_matrix(matrix), rhs_z, coupling, hessian, rhs_xi, frames)


def _device_joint_system(problem: LevelProblem, est: Estimate, ev: Evaluation, parallax: bool, twists: bool,
                         project_albedo: bool, min_pixels: int, block_pixels: int | None,
                         release: bool) -> JointSystem:
    """:func:`joint_system` on a GPU: every frame 1..n-1 a candidate (m = n - 1 with twists), those
    with fewer than ``min_pixels`` usable pixels or an ill-conditioned Gram not kept (an identity
    block, a zero twist: :class:`JointSystem`), so that nothing is read back. Per block of pixels
    (:data:`DEVICE_BLOCK_PIXELS`) two launches, :func:`.kernels.joint_block` (the light rows, the
    reference's parallax, every frame's sums and rows, the albedo projection) and
    :func:`.kernels.add_stencil_transpose_rows` (the rows into U^T), and with the projection the
    product of its F with itself (the downdate and its right-hand side); then
    :func:`.kernels.joint_twist_system` and :func:`.kernels.joint_depth_system` (M and rhs_z),
    one launch each, and one allocation that is zeroed (U^T, M's values and the small arrays):
    six launches in all where there was one block (were some 35 and 3 copies). The poses are
    the evaluation's device copy (:meth:`.LevelProblem._device_poses_lights`: no copy)."""
    if release:  # the warped colours and light bases are not read here: dropped before U is allocated
        ev.release(keep=("residual", "usable", "shading", "normals", "dA"))
    grid, prior = problem.level.grid, problem.level.prior
    N, n = grid.size, problem.n_frames
    xp, kernels = array_module(ev.residual), kernels_for(ev.residual)
    m = n - 1 if twists else 0
    K = 6 * m
    if problem.depth_pattern is None:
        problem.depth_pattern = depth_block_pattern(grid, prior)
    indptr, indices = problem.depth_pattern
    # kept with the system: [U^T; rhs_z] (zeroed: the rows' stencil transposes add into U^T), M's
    # values and the count of entries its pattern lacks, the twist system, the inverse's arrays
    kept_shapes = ((K + 1, N), (indices.size,), (1,), (K, K), (K,), (m,), (K, K), (1, K, K), (1, K + 1, K + 1), (1,),
                   (K,))
    stacked, data, missing, hessian, twist_rhs, frame_kept, selection, L, X, solved, readout = _views(
        xp.zeros(_size(kept_shapes)), kept_shapes)
    if block_pixels is None:
        block_pixels = DEVICE_BLOCK_PIXELS
    starts = range(0, N, block_pixels)
    block_rows = [kernels.joint_blocks(min(N, start + block_pixels) - start) for start in starts]
    projected = project_albedo and K > 0
    # the pass's scratch, dropped with this function: the per-pixel sums, the blocks' partial
    # twist sums and F Grams, the twist system's sums, then one block's arrays
    B = min(N, block_pixels)
    pass_shapes = ((9, N), (sum(block_rows), m, host_kernels.JOINT_SUMS),
                   (len(starts) if projected else 0, K + 1, K + 1), (m, 6, 6), (K,), (K + 1, K + 1), (m, 6, 6))
    block_size = (3 + 3 * n + 3 + 9 + 3 * K + (K + 1) * 3 + 3) * B + 9 * VIEW_GAP  # 9 arrays, a gap after each
    scratch = xp.empty(_size(pass_shapes) + block_size)
    sums, partial, products, grams, rhs_frames, D, W = _views(scratch, pass_shapes)
    points_ref = problem.points(est.z)
    poses = problem._device_poses_lights(est)[0]
    model = problem.light_model(est)
    Du, Dv = grid.difference_operators()
    row = 0
    for b, start in enumerate(starts):
        stop = min(N, start + block_pixels)
        block, Bb = slice(start, stop), stop - start
        normals, points = ev.normals[block], points_ref[block]
        field = like(model.fields(est.lights, normals, points, est.poses)[1], normals).reshape(n, -1, 3)
        dshading = model.shading_jacobians(est.lights, normals, points, est.poses) if parallax or m else None
        with_extra = parallax and dshading is not None
        shapes = ((Bb, 3), (n, Bb), (n, Bb), (n, Bb), (Bb if with_extra else 0, 3),
                  (3 if project_albedo else 0, Bb if project_albedo else 1, 3), (3, m, 6, Bb),
                  (K + 1 if projected else 0, 3 * Bb), (Bb, 3))
        q, alpha, beta, gamma, extra, e, rows, stacked_F, root = _views(scratch[scratch.size - block_size:], shapes)
        top = stacked_F[K] if projected else xp.empty(0)  # the projection's s^T W r / sqrt(d) per pixel and channel
        F = stacked_F[:K].reshape(m, 6, Bb, 3) if projected else xp.empty((0, 6, 1, 3))
        kernels.joint_block(ev.residual[:, block], ev.shading[:, block], ev.usable[:, block], 1.0 / problem.lam,
                            est.albedo[block], ev.dA[block], field, grid.u[block], grid.v[block], points, poses,
                            problem.device_K, problem.level.image_stack,
                            xp.empty((n, 0, 6)) if dshading is None else dshading, parallax, twists, q, alpha, beta,
                            gamma, extra, sums[:, block], e, rows, F, top, root,
                            partial[row:row + block_rows[b]])
        row += block_rows[b]
        if K:  # U^T += the rows' stencil transpose: Du^T rows_a + Dv^T rows_b + rows_c
            kernels.add_stencil_transpose_rows(Du.indptr[start:stop + 1], Du.indices, Du.data,
                                               Dv.indptr[start:stop + 1], Dv.indices, Dv.data,
                                               rows.reshape(3, K, Bb), start, stacked[:K])
        if projected:  # the projection's downdate F F^T and, in its last row, right-hand side
            xp.matmul(stacked_F, stacked_F.T, out=products[b])
    del points_ref, Du, Dv
    if release:
        ev.release()
    if K:  # the frames' sums, which are kept, H, its right-hand side and -diag(kept)
        kernels.joint_twist_system(partial, products, min_pixels, host_kernels.MAX_TWIST_CONDITION, grams,
                                   rhs_frames, D, W, frame_kept, hessian, twist_rhs, selection)
    terms = prior.hessian_terms(problem.tau, problem.mu)
    (s1, T1), (s2, T2) = terms[0], terms[1] if len(terms) > 1 else (0.0, terms[0])
    t2_indptr = T2.indptr if len(terms) > 1 else T2.indptr[:1]  # no rows: no second term
    geometry = (grid.fwd_u, grid.bwd_u, grid.wf_u, grid.wb_u, grid.fwd_v, grid.bwd_v, grid.wf_v, grid.wb_v)
    DuT, DvT = grid.transposed_difference_operators()
    kernels.joint_depth_system(indptr, indices, *geometry, *sums[:6], s1, T1.indptr, T1.indices, T1.data, s2, t2_indptr,
                               T2.indices, T2.data, data, missing, DuT.indptr, DuT.indices, DuT.data, DvT.indptr,
                               DvT.indices, DvT.data, *sums[6:], prior.negative_gradient(est.z, problem.tau,
                                                                                         problem.mu), stacked[K])
    del scratch, sums, partial, products
    matrix = sparse_module(T1).csr_matrix((data, indices, indptr), shape=(N, N))
    return JointSystem(matrix, stacked[K], stacked[:K].T, hessian, twist_rhs, list(range(1, n)) if K else [],
                       frame_kept, selection, _work=(stacked, L, X, solved, readout))


#: float64 entries (one 64-byte cache line) left between :func:`_views`' arrays: arrays whose sizes
#: are multiples of 4 KiB (alpha, beta, gamma: 20 frames x 4096 pixels) laid end to end alias in
#: the L1 cache when a kernel walks them in step (:func:`.kernels.joint_rows`: 1.8 against 1.0 ms
#: a static 1280x960 block)
VIEW_GAP = 8


def _size(shapes) -> int:
    """Entries of arrays of these shapes together, with :data:`VIEW_GAP` after each."""
    return sum(int(np.prod(shape)) + VIEW_GAP for shape in shapes)


def _views(buffer, shapes) -> list:
    """C-ordered views of the flat ``buffer`` with these shapes (no copy), one after the other,
    :data:`VIEW_GAP` entries apart."""
    views, at = [], 0
    for shape in shapes:
        size = int(np.prod(shape))
        views.append(buffer[at:at + size].reshape(shape))
        at += size + VIEW_GAP
    return views


def _gapped_rows(buffer, rows: int, shape: tuple):
    """A (rows, *shape) view of the flat ``buffer`` (at least :func:`_gapped_size` entries) whose
    rows lie :data:`VIEW_GAP` entries apart: rows of a multiple of 4 KiB laid end to end (a
    block's per-pixel sums (9, 4096) and the projection's e (3, 4096, 3)) alias in the L1 cache
    when a kernel updates them pixel by pixel (:func:`.kernels.accumulate_block`: 11.4 against
    10.6 ms a 2 MP block on one thread, the same values)."""
    inner = int(np.prod(shape))
    return buffer[:rows * (inner + VIEW_GAP)].reshape(rows, inner + VIEW_GAP)[:, :inner].reshape(rows, *shape)


def _gapped_size(rows: int, shape: tuple) -> int:
    """Entries of :func:`_gapped_rows`' buffer."""
    return rows * (int(np.prod(shape)) + VIEW_GAP)


def _same_types(images: list) -> bool:
    """Whether the host images (H, W, 3) share shape class, dtype and memory layout, so that
    :func:`.kernels.accumulate_block` takes them as one tuple (coded frames: their codes and,
    as a second tuple, their tables: :func:`~o3d_mvps.colour.frames_and_tables`)."""
    frames, tables = frames_and_tables(images)
    return _alike(frames, 3) and (tables is None or _alike(tables, 2))


def _alike(arrays: tuple, ndim: int) -> bool:
    """Whether the arrays share dtype, C order and writeability, each of ``ndim`` dimensions
    (numba types them alike)."""
    first = arrays[0]
    return all(a.dtype == first.dtype and a.ndim == ndim and a.flags.c_contiguous
               and a.flags.writeable == first.flags.writeable for a in arrays)


def _accumulate_frames(kernels, problem, residual, shading, usable, q, alpha, beta, gamma, extra_c, points_ref, poses,
                       dshading, albedo, with_jacobian, parallax, block_sums, e, rows, F, slot, gram, rhs) -> None:
    """:func:`.kernels.accumulate_frame` a frame at a time (images of mixed types on the host):
    the same values as :func:`.kernels.accumulate_block`."""
    xp = array_module(points_ref)
    none3, none6 = xp.empty((0, 3)), xp.empty((0, 6))
    for i in range(problem.n_frames):
        k = slot.get(i, -1)
        kernels.accumulate_frame(residual[i], shading[i], usable[i], 1.0 / problem.lam, q, alpha[i], beta[i],
                                 gamma[i], extra_c if i == 0 else none3, points_ref, poses[i], problem.device_K,
                                 problem.level.images[i],
                                 dshading[i] if dshading is not None and with_jacobian[i] else none6, albedo,
                                 with_jacobian[i], parallax, block_sums, e, rows, F, k, gram[k], rhs[k])


def _without_zeros(D: sp.csr_matrix) -> sp.csr_matrix:
    """A copy of the CSR matrix D without its explicitly stored zeros."""
    D = D.copy()
    D.eliminate_zeros()
    return D


def _row_arrays(D: sp.csr_matrix, rows: slice) -> tuple:
    """(indptr, indices, data) of the CSR matrix D's ``rows`` (a slice, step 1): indptr (B + 1,)
    D's own slice, whose offsets index D's whole indices and data (no copy)."""
    return D.indptr[rows.start:rows.stop + 1], D.indices, D.data


def _block_shapes(n: int, m: int, B: int, project_albedo: bool, led: bool) -> tuple:
    """Shapes of :func:`_assemble_block`'s temporaries for a block of B pixels, n frames and m
    refined ones: the block's sums (9, B) (flat, for :func:`_gapped_rows`), the light rows q (B, 3), alpha, beta, gamma (n, B)
    each, the reference's parallax (B, 3), the frames' light fields (n, B, 3) and shading
    Jacobians (n, B, 6) of a light model with per-pixel fields (``led``: an LEDLight; else
    none), the rows (3, m, 6, B) and the projection's F (m, 6, B, 3)."""
    k = n if led else 0
    return ((_gapped_size(9, (B,)),), (B, 3), (n, B), (n, B), (n, B), (B, 3), (k, B, 3), (k, B, 6), (3, m, 6, B),
            (m if project_albedo else 0, 6, B, 3))


def _assemble_block(problem, est, ev, block, points_ref, candidates, parallax, project_albedo, sums, grams,
                    rhs_xi, downdate, coupling_t, Du_rows, Dv_rows, poses, with_jacobian, frame_slots,
                    helper=None, scratch=None) -> None:
    """One block of :func:`joint_system`'s pass on the host: the block's pixels' per-pixel sums
    (9, B) written into ``sums``; its share of the frames' Grams (m, 6, 6), their right-hand sides
    rhs_xi (6m,) (the albedo projection's too) and the projection's downdate (6m, 6m) added in
    place; the transposed coupling (6m, N) added in place. Du_rows, Dv_rows: the block's rows
    (B, N) of the difference operators as CSR arrays (:func:`_row_arrays`); poses (n, 4, 4);
    with_jacobian (n,) bools: the frames whose twist or parallax rows are formed; frame_slots
    (n, 2) int64: with_jacobian and the refined frame's slot (or -1); helper: a one-thread
    executor for half the projection's Gram (:meth:`_AlbedoProjection.downdate_scaled`), or
    None; scratch: a flat float64 buffer of at least :func:`_block_shapes`' entries for this
    block's temporaries, reused from block to block (None: fresh arrays). (A GPU's pass:
    :func:`_device_joint_system`.)"""
    kernels = host_kernels
    B = points_ref.shape[0]
    m = len(candidates)
    n = problem.n_frames
    none3, none_e = np.empty((0, 3)), np.empty((0, 1, 3))  # the kernel's optional arrays (empty)
    residual, usable, albedo, shading = ev.residual[:, block], ev.usable[:, block], est.albedo[block], ev.shading[:, block]
    normals = ev.normals[block]
    model = problem.light_model(est)
    led = isinstance(model, LEDLight)
    shapes = _block_shapes(n, m, B, project_albedo, led)
    if scratch is None:
        scratch = np.empty(_size(shapes))
    # block_sums zeroed by kernels.joint_rows; rows twist-component-major, so the transposed
    # coupling rows (6m, B) and the projection's rows (6m, 3B) are views
    block_sums, q, alpha, beta, gamma, extra, field_out, jacobian_out, rows, F = _views(scratch, shapes)
    block_sums = _gapped_rows(block_sums, 9, (B,))
    projection = _AlbedoProjection(residual, usable, shading, problem.lam) if project_albedo else None
    slot = {i: k for k, i in enumerate(candidates)}
    if projection is None:
        F = np.empty((0, 6, 1, 3))
    # on one thread a launch per frame is faster (measured: 17.2 against 20.6 ms a D415 block)
    host_block = (problem.level.image_stack is None and current_kernel_threads() > 1
                  and _same_types(problem.level.images))
    chunks = -(-B // HOST_CHUNK_PIXELS) if host_block else kernels.chunk_count(B)
    # per refined frame its partial sums of the twist Gram and right-hand side, and one more for
    # the other frames (whose kernel writes them too)
    gram, rhs = np.empty((m + 1, chunks, 6, 6)), np.empty((m + 1, chunks, 6))
    # every frame's frozen light field and LED shading Jacobian at once, then in one launch, in
    # parallel over pixels: q = albedo / dA, the light rows (alpha, beta, gamma (n, B) each: the
    # formulas of _light_rows) and the reference frame's parallax (extra_c: _parallax_rows')
    if not led:
        field_out = jacobian_out = None
    field = like(model.fields(est.lights, normals, points_ref, est.poses, out=field_out)[1], normals).reshape(n, -1, 3)
    dshading = (model.shading_jacobians(est.lights, normals, points_ref, est.poses, out=jacobian_out)
                if parallax or m else None)
    e = none_e if projection is None else projection.e
    extra_c = extra if parallax and dshading is not None else none3
    grid = problem.level.grid
    kernels.joint_rows(albedo, ev.dA[block], field, grid.u[block], grid.v[block], problem.device_K, points_ref,
                       np.empty((n, 0, 6)) if dshading is None else dshading, usable[0], q, alpha, beta, gamma,
                       extra_c, block_sums, e)
    if host_block:  # every frame in one launch, in parallel over pixel chunks
        images, tables = frames_and_tables(problem.level.images)  # coded frames: codes and tables apart
        kernels.accumulate_block(residual, shading, usable, 1.0 / problem.lam, q, alpha, beta, gamma, extra_c,
                                 points_ref, poses, problem.device_K, images,
                                 np.empty((problem.n_frames, 0, 6)) if dshading is None else dshading, albedo,
                                 frame_slots, parallax, block_sums, e, rows, F, gram, rhs, HOST_CHUNK_PIXELS, tables)
    else:
        _accumulate_frames(kernels, problem, residual, shading, usable, q, alpha, beta, gamma, extra_c, points_ref,
                           poses, dshading, albedo, with_jacobian, parallax, block_sums, e, rows, F, slot, gram, rhs)
    if m:
        grams += gram[:m].sum(axis=1)
        rhs_xi += rhs[:m].sum(axis=1).reshape(-1)
    if projection is not None:
        block_sums -= projection.local()
    sums[:] = block_sums
    if m and projection is not None:
        # the projection of the rows and their stencil transpose into U^T in one pass
        scaled, sqrt_inv_d = projection.twist_scalings()
        kernels.project_stencil_rows(rows, F, scaled, sqrt_inv_d, *Du_rows, *Dv_rows, block.start, coupling_t)
        projection.downdate_scaled(F, downdate, rhs_xi, sqrt_inv_d, helper)
    elif m:  # U^T += the stencil transpose of the rows: Du^T rows_a + Dv^T rows_b + rows_c, in one pass
        kernels.add_stencil_transpose_rows(*Du_rows, *Dv_rows, rows.reshape(3, 6 * m, B), block.start, coupling_t)


class _AlbedoProjection:
    """Variable projection of the albedo out of the Gauss-Newton system (Golub-Pereyra, in
    Kaufman's form).

    The residual r_ic(p) = I~ - rho_c(p) s_i(p) is linear in the albedo with column -s over the
    frames, so eliminating rho_c(p) replaces each (pixel, channel)'s Jacobian J by its part
    W-orthogonal to s: the Gram J^T W J loses ``e e^T / d`` and the gradient J^T W r loses
    ``e (s^T W r) / d``, with ``e = J^T W s`` and ``d = s^T W s``. The depth step then also moves
    the albedo along (instead of leaving it to the next albedo update, a slow alternation),
    and the frozen-dA error of the depth rows, ``s_i`` times a per-pixel factor, drops out
    (frozen dA is exact up to the albedo direction).

    For one block of B pixels: residual (n, B, 3), usable (n, B), shading (n, B) and the Cauchy
    loss's lam, whose IRLS weights are W. ``e``
    (3, B, 3) holds e per (pixel, channel) for the depth rows (a, b, c), accumulated by
    :func:`.kernels.accumulate_frame`; the twist rows' e are ``F`` (m, 6, B, 3), w s J of the
    m refined frames, written by the same kernel. Arrays (B, 3) unless stated. On the host; a
    GPU's pass projects per pixel inside its one launch (:func:`.kernels.joint_pixel_projection`,
    the same formulas).
    """

    def __init__(self, residual: np.ndarray, usable: np.ndarray, shading: np.ndarray, lam: float):
        B = residual.shape[1]
        d, self.sWr = np.empty((B, 3)), np.empty((B, 3))  # s^T W s, s^T W r
        host_kernels.weighted_albedo_sums(residual, usable, residual, shading, 1.0 / lam, self.sWr, d)
        self.inv_d = _safe_inverse(d)
        self.e = _gapped_rows(np.zeros(_gapped_size(3, (B, 3))), 3, (B, 3))  # e for the a, b, c rows

    def local(self) -> np.ndarray:
        """Downdates (9, B) of Saa, Sbb, Sgg, Sab, Sag, Sbg, Ba, Bb, Bg."""
        return np.stack(_projection_downdates(*self._columns()))

    def _columns(self) -> list:
        """:func:`_projection_downdates`' arguments: the e columns, inverse d and s^T W r (B,) each."""
        return ([e[:, c] for e in self.e for c in range(3)] + [self.inv_d[:, c] for c in range(3)]
                + [self.sWr[:, c] for c in range(3)])

    def twist_scalings(self) -> tuple[np.ndarray, np.ndarray]:
        """(e / d (3, B, 3), 1 / sqrt(d) (B, 3)): what the twist rows lose per unit of F
        (:func:`.kernels.project_stencil_rows`), and F's scaling."""
        return self.e * self.inv_d, np.sqrt(self.inv_d)

    def downdate_scaled(self, F: np.ndarray, downdate: np.ndarray, rhs_xi: np.ndarray, sqrt_inv_d: np.ndarray,
                        helper=None) -> None:
        """The projection's sums over the block's F (m, 6, B, 3) (w s J of the m refined frames)
        once scaled by ``sqrt_inv_d`` (B, 3): ``downdate`` (6m, 6m) gains ``sum f f^T / d`` (the
        Gram's loss) and the right-hand side rhs_xi (6m,) ``sum f (s^T W r) / d`` over the block's
        pixels and channels. helper: a one-thread executor that takes half of ``sum f f^T`` beside
        the caller's work, or None."""
        f = F.reshape(6 * len(F), -1)  # (6m, 3B): frame j in rows 6j..
        # f f^T as the Grams of its column halves added, each by BLAS's symmetric rank-k update
        # (NumPy's product of a matrix with its own transpose: half a product); with a helper
        # thread the first half runs there beside the rest (BLAS releases the GIL). The same
        # halves and sum on any thread count, so the same values bit for bit.
        low, high = f[:, :f.shape[1] // 2], f[:, f.shape[1] // 2:]  # views: BLAS takes the row stride
        job = None if helper is None else helper.submit(np.matmul, low, low.T)
        rhs_xi += f @ (self.sWr * sqrt_inv_d).reshape(-1)
        gram_high = high @ high.T
        gram = low @ low.T if job is None else job.result()
        downdate += np.add(gram, gram_high, out=gram)


@fused
def _safe_inverse(d):
    """1 / d where d > 1e-12, else 0 (any shape)."""
    where = array_module(d).where
    return where(d > 1e-12, 1.0 / where(d > 1e-12, d, 1.0), 0.0)


@fused
def _projection_downdates(ea0, ea1, ea2, eb0, eb1, eb2, ec0, ec1, ec2, i0, i1, i2, s0, s1, s2):
    """The albedo projection's downdates of the per-pixel sums, (B,) each: ``sum_c x_c y_c i_c``
    of the e columns of rows a, b, c (``ea0`` = e_a channel 0, ...), the inverse d (i) and s^T W r
    (s): Saa, Sbb, Sgg, Sab, Sag, Sbg, Ba, Bb, Bg."""
    a0, a1, a2 = ea0 * i0, ea1 * i1, ea2 * i2
    b0, b1, b2 = eb0 * i0, eb1 * i1, eb2 * i2
    c0, c1, c2 = ec0 * i0, ec1 * i1, ec2 * i2
    return (a0 * ea0 + a1 * ea1 + a2 * ea2, b0 * eb0 + b1 * eb1 + b2 * eb2, c0 * ec0 + c1 * ec1 + c2 * ec2,
            a0 * eb0 + a1 * eb1 + a2 * eb2, a0 * ec0 + a1 * ec1 + a2 * ec2, b0 * ec0 + b1 * ec1 + b2 * ec2,
            a0 * s0 + a1 * s1 + a2 * s2, b0 * s0 + b1 * s1 + b2 * s2, c0 * s0 + c1 * s1 + c2 * s2)


@fused
def _light_rows(L0, L1, L2, u, v, fx, cx, fy, cy):
    """(alpha, beta, gamma) (n, N) each, the light rows of every frame from the frozen light
    field's components (n, N) each and the pixels' u, v (N,): frame i's shading is
    ``c_i + (alpha_i Du z + beta_i Dv z + gamma_i z) / dA`` with the light field frozen at the
    current surface. The array form of :func:`.kernels.joint_pixel_rows`' (which the host's and a
    GPU's assembly run; tests compare the two)."""
    return fx * L0 - (u - cx) * L2, fy * L1 - (v - cy) * L2, -L2


def prepare_depth_block(problem: LevelProblem) -> None:
    """Build the level's depth-block pattern (:func:`depth_block_pattern`, kept on the problem)
    on the host now, as the level starts: it lasts the level anyway, but built inside its first
    joint step, next to the coupling U, its sparse products' temporaries (some 0.5 GB at 2
    megapixels, with the prior's D^T D it formed then) set that step's peak. Nothing is done
    on a GPU, where :func:`_device_depth_block` makes it at the level's first joint step."""
    if array_module(problem.level.grid.u) is not np:
        return
    if problem.depth_pattern is None:
        problem.depth_pattern = depth_block_pattern(problem.level.grid, problem.level.prior)


def depth_block(problem: LevelProblem, stencil_sums: np.ndarray) -> sp.csr_matrix:
    """The depth block M (N, N) on the host: :func:`stencil_normal_matrix` of the per-pixel sums
    ``stencil_sums`` (6, N) (Saa, Sbb, Sgg, Sab, Sag, Sbg) plus the prior's Hessian
    (:meth:`.pyramid.DepthPrior.hessian_terms`), filled by compiled loops
    (:func:`.kernels.add_stencil_gram`, :func:`.kernels.add_csr_into_pattern`) into a pattern
    built once per level (:func:`depth_block_pattern`, kept on the problem; entries the
    terms leave at zero stay stored). The same entries as the sparse products and sums up to rounding
    (their order of summation differs; measured 2e-16 of the largest), in half their time
    (1.08 M pixels, damping included: 0.85 against 1.7-2.0 CPU s; the pattern, once per level,
    about 1 s)."""
    grid, prior = problem.level.grid, problem.level.prior
    # a block-average D (each pixel in at most one block): 2 tau D^T D added from D's rows, the
    # same sums bit for bit, without D^T D (184 MB at 2 megapixels and SF 4) kept for the level
    rows = prior.D.nnz == 0 or np.bincount(prior.D.indices, minlength=grid.size).max() <= 1
    terms = prior.hessian_terms(problem.tau, problem.mu, rows=rows)
    for attempt in range(2):
        if problem.depth_pattern is None or attempt:  # a second try: the prior's pattern changed
            problem.depth_pattern = depth_block_pattern(grid, prior)
        indptr, indices = problem.depth_pattern
        data = np.zeros(indices.size)
        filled = host_kernels.add_stencil_gram(indptr, indices, grid.fwd_u, grid.bwd_u, grid.wf_u, grid.wb_u,
                                               grid.fwd_v, grid.bwd_v, grid.wf_v, grid.wb_v, *stencil_sums, data)
        for k, (scale, term) in enumerate(terms):
            add = host_kernels.add_row_gram_into_pattern if rows and k == 0 else host_kernels.add_csr_into_pattern
            filled = filled and add(indptr, indices, data, scale, term.indptr, term.indices, term.data)
        if filled:
            break
    else:
        raise RuntimeError("depth_block: the depth block's pattern misses entries of its terms")
    # the pattern's index arrays shared, not copied (89 MB at 2 megapixels): M's structure must
    # not be changed in place (its values may: levenberg_damped(..., overwrite=True))
    matrix = sp.csr_matrix((data, indices, indptr), shape=(grid.size, grid.size), copy=False)
    matrix.has_sorted_indices = True
    return matrix


def depth_block_pattern(grid, prior) -> tuple[np.ndarray, np.ndarray]:
    """(indptr, indices) of a CSR pattern (columns ascending per row) holding every entry of the
    stencil's Gram (pixels coupled through one pixel's central-difference stencil), of the
    prior's D^T D and S^T S (for any smoothness weights) and the diagonal, (N, N); arrays of the
    grid's device (on a GPU by a few sparse products there, once per level).

    The pattern of one product ``X^T X`` of the rows of ``|Du| + |Dv| + I``, D and S stacked: the
    union of the three Grams' patterns, without their sum's two passes or the absolute values'
    copies (1.13 M pixels, the static quilt's finest level: 0.55 against 2.3-3.1 CPU s, the same
    pattern). On the host a symbolic product of the patterns alone (:func:`_gram_pattern`)."""
    Du, Dv = grid.difference_operators()
    S = prior.smoothness_pattern
    xp = array_module(grid.u)
    if xp is np:
        return _gram_pattern(_stacked_rows(Du, Dv, [prior.D] + ([] if S is None else [S])), grid.size)
    sparse = sparse_module(Du)
    # the sum stores no zeros (the stencils' stored zeros lie on the diagonal, where the identity is)
    touched = abs(Du) + abs(Dv) + sparse.diags(xp.ones(grid.size), format="csr")
    parts = [sparse.csr_matrix(m) for m in [touched, prior.D] + ([] if S is None else [S])]
    ends = np.cumsum([0] + [int(m.nnz) for m in parts])
    indptr = xp.concatenate([parts[0].indptr[:1]] + [m.indptr[1:] + int(end) for m, end in zip(parts, ends)])
    indices = xp.concatenate([m.indices for m in parts])  # the rows stacked, as CSR (M', N)
    ones = sparse.csr_matrix((xp.ones(indices.size, dtype=np.float32), indices, indptr),
                             shape=(sum(m.shape[0] for m in parts), grid.size))
    pattern = sparse.csr_matrix(ones.T.tocsr() @ ones)  # positive sums: no entry cancels
    pattern.sort_indices()
    return pattern.indptr, pattern.indices


def _stacked_rows(Du: sp.csr_matrix, Dv: sp.csr_matrix, others: list) -> tuple[np.ndarray, np.ndarray]:
    """(indptr, indices) of the rows of ``|Du| + |Dv| + I`` (N, N) (:func:`.kernels.stencil_rows`:
    the entries that sum keeps, not sorted) followed by those of the host sparse matrices
    ``others`` (each (M_k, N)), stacked as one CSR pattern (N + sum M_k, N), without values."""
    Du, Dv = (sp.csr_matrix(D) for D in (Du, Dv))
    N = Du.shape[0]
    width = int(np.diff(Du.indptr).max(initial=0)) + int(np.diff(Dv.indptr).max(initial=0)) + 1
    columns, counts = np.empty((N, width), dtype=Du.indices.dtype), np.empty(N, dtype=np.int64)
    host_kernels.stencil_rows(Du.indptr, Du.indices, Du.data, Dv.indptr, Dv.indices, Dv.data, columns, counts)
    parts = [sp.csr_matrix(m) for m in others]
    rows_nnz = int(counts.sum())
    ends = np.cumsum([rows_nnz] + [int(m.nnz) for m in parts])
    indptr = np.concatenate([[0], np.cumsum(counts)] + [m.indptr[1:] + int(end) for m, end in zip(parts, ends)])
    indices = np.concatenate([columns[np.arange(width) < counts[:, None]]] + [m.indices for m in parts])
    dtype = np.int32 if indices.size <= np.iinfo(np.int32).max else np.int64
    return indptr.astype(dtype), indices.astype(dtype, copy=False)


def _gram_pattern(X: tuple[np.ndarray, np.ndarray], columns: int) -> tuple[np.ndarray, np.ndarray]:
    """(indptr, indices) of the pattern of X^T X (N, N), columns ascending per row, for the
    pattern (indptr, indices) of a CSR matrix X (M, N = ``columns``) on the host, duplicate
    columns in a row allowed: X^T's pattern (:func:`.kernels.pattern_transpose`), then
    :func:`.kernels.gram_pattern_rows`, two passes (the rows' counts, then their columns), in
    parallel over rows. The same pattern and index dtype (int32 where it fits) as SciPy's
    ``X.T.tocsr() @ X`` sorted, without its values, its serial product or the sort (the 1280x960
    static quilt's five levels: 1.6 against 1.9 CPU s a refine, on a loaded machine; the
    parallel passes shorten the wall time more). X's transpose is made without values too (that
    quilt's five levels, with :func:`_stacked_rows`: 1.15-1.29 against 1.86-2.06 s wall)."""
    x_indptr, x_indices = X
    t_indptr, t_indices = np.empty(columns + 1, dtype=x_indptr.dtype), np.empty_like(x_indices)
    host_kernels.pattern_transpose(x_indptr, x_indices, t_indptr, t_indices)
    counts = np.zeros(columns + 1, dtype=np.int64)
    host_kernels.gram_pattern_rows(t_indptr, t_indices, x_indptr, x_indices, counts, np.empty(0, np.int32), False)
    np.cumsum(counts, out=counts)
    dtype = np.int32 if counts[-1] <= np.iinfo(np.int32).max else np.int64
    indptr = counts.astype(dtype)
    indices = np.empty(int(counts[-1]), dtype=dtype)
    host_kernels.gram_pattern_rows(t_indptr, t_indices, x_indptr, x_indices, indptr, indices, True)
    return indptr, indices


def stencil_normal_matrix(grid, Saa, Sbb, Sgg, Sab, Sag, Sbg) -> sp.csr_matrix:
    """sum over rows of R^T W R for rows ``R = a Du + b Dv + c I``, from the per-pixel weighted
    products (N,) each (``Saa = sum w a a``, ...): an (N, N) sparse 7-point-stencil matrix."""
    Du, Dv = grid.difference_operators()
    sparse = sparse_module(Du)
    diag = sparse.diags
    cross = Du.T @ diag(Sab) @ Dv + Du.T @ diag(Sag) + Dv.T @ diag(Sbg)
    return sparse.csr_matrix(Du.T @ diag(Saa) @ Du + Dv.T @ diag(Sbb) @ Dv + diag(Sgg) + cross + cross.T)


def stencil_transpose(grid, Ba, Bb, Bg):
    """``Du^T Ba + Dv^T Bb + Bg``: R^T applied to per-pixel values (N,) each."""
    DuT, DvT = grid.transposed_difference_operators()
    return DuT @ Ba + DvT @ Bb + Bg
