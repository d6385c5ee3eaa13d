"""Linear solves: preconditioned CG with an AMG cycle for the depth and joint steps, and the
small ridge-regularised systems of the pose, LED-offset and lighting steps.

The depth block M (7-point stencil plus 2 tau D^T D, sparse SPD) is preconditioned by one
smoothed-aggregation V-cycle (pyamg); the joint step solves the Schur complement
``M - U H^-1 U^T`` with the cycle of M.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from contextlib import contextmanager
from functools import partial

import numpy as np
import pyamg
import scipy.sparse as sp
from pyamg.relaxation.smoothing import change_smoothers
import scipy.sparse.linalg as spla

from ..model.arrays import array_module, contiguous, sparse_module
from . import kernels as host_kernels
from . import krylov
from .device import kernels_for, on_gpu
from .kernels import COOPERATIVE_BLOCKS


#: Levenberg-Marquardt damping of the depth block M, relative to its diagonal. Pixels that only
#: the reference frame sees carry no data once the albedo is projected out; where the prior's SF x SF
#: block averages leave them free and the smoothness is off, M was singular: the AMG hierarchy's
#: coarse solve returned 1e58 and CG NaN (an LED scene on a 360-degree ring), or CG ran to its cap
#: and the free pixels wandered. Damping changes the steps, not the minimiser.
DAMPING = 1e-4


def levenberg_damped(matrix: sp.spmatrix, overwrite: bool = False) -> sp.csr_matrix:
    """``M + DAMPING diag(max(M_pp, mean(M_pp) / 100))`` (N, N) sparse: positive definite for
    any PSD M, also where a row of M is zero. overwrite: damp a host CSR matrix that stores its
    whole diagonal in place (no sparse sum), and return it; on a GPU a CSR matrix in place in one
    launch and no read (:func:`.kernels.levenberg_damp`), which must store its whole diagonal (the
    depth block's pattern does, :func:`.normal_equations.depth_block_pattern`: not checked there,
    a row without one would stay undamped)."""
    if overwrite and on_gpu(matrix.data):
        xp = array_module(matrix.data)
        kernels_for(matrix.data).levenberg_damp(matrix.indptr, matrix.indices, matrix.data, DAMPING,
                                                np.finfo(float).tiny, xp.empty(COOPERATIVE_BLOCKS), xp.empty(1))
        return matrix
    d = matrix.diagonal()
    floor = 0.01 * float(d.mean()) if d.size else 0.0
    damping = DAMPING * np.maximum(d, max(floor, np.finfo(float).tiny))
    if overwrite and isinstance(matrix, sp.csr_matrix) and matrix.has_sorted_indices:
        at = host_kernels.diagonal_positions(matrix.indptr, matrix.indices)
        if at.size == 0 or at.min() >= 0:
            matrix.data[at] += damping
            return matrix
    sparse = sparse_module(matrix)
    return sparse.csr_matrix(matrix + sparse.diags(damping))


#: pyamg's strength-of-connection threshold: an off-diagonal entry couples pixels i and j in the
#: aggregation graph where ``|a_ij| >= STRENGTH_THETA sqrt(a_ii a_jj)``. pyamg's default, 0, keeps
#: every stored entry, also the rounding residues of sums that cancel (on the solver's systems
#: ~1e-22..1e-18 of the diagonal, where the real couplings are >= 1e-6): whether such a residue is
#: stored or exactly zero flips with a 1e-16 change of the input poses, and with it the aggregates,
#: the preconditioner (by ~1 %), CG's iteration count and the solve's outcome (1.4e-5 of the energy).
#: 1e-12 sits in that gap, so the hierarchy is a continuous function of the matrix.
STRENGTH_THETA = 1e-12


#: pyamg's options for :func:`amg_preconditioner` (all but ``strength``): its smoothed
#: aggregation with the Jacobi prolongation smoother weighted row by row (``weighting="local"``,
#: Gershgorin) instead of by an estimate of the spectral radius of D^-1 A, which pyamg computes
#: on every level by restarted Arnoldi: at 2 megapixels (958k unknowns, a saved joint system) 3.8
#: of the set-up's 5.3 s. Local weights: 1.5 s, the same CG iterations (rtol 1e-2: 10, 1e-4: 75),
#: and on the D415 capture the same refine (40 sweeps, energy and accuracy to 1e-5). Plain
#: aggregation (``smooth=None``) set up in 0.4 s for 10-11 and 87 iterations in the same CG time,
#: but its joint steps ended the D415 refine 1 % less accurate (1.353 deg, 0.521 mm against 1.337,
#: 0.516). Nothing in this set-up is random.
AMG_OPTIONS = dict(symmetry="symmetric", max_coarse=300, coarse_solver="splu",
                   smooth=("jacobi", {"omega": 4.0 / 3.0, "weighting": "local"}))


#: pyamg's options for :func:`plain_aggregation` (all but ``strength``): the depth steps of a
#: static camera (poses held at the identity), which have no twists through which the hierarchy's
#: rounding could reach the poses (the reason :data:`AMG_OPTIONS` smooths its prolongations).
#: Plain aggregation, one symmetric Gauss-Seidel sweep before and after the coarse correction,
#: pyamg's candidate improvement left out (4 block Gauss-Seidel sweeps of the candidates on the
#: finest level: without it the tentative prolongation depends on the pattern alone). On the
#: static quilt's finest level (1280x960, 1.13 M unknowns, CG to 1e-2) the set-up took 0.3
#: against 1.6-2.0 CPU s, CG as many iterations (12 and 22 against 11 and 21) in the same time.
PLAIN_AMG_OPTIONS = dict(symmetry="symmetric", max_coarse=300, coarse_solver="splu", smooth=None,
                         presmoother=("gauss_seidel", {"sweep": "symmetric"}),
                         postsmoother=("gauss_seidel", {"sweep": "symmetric"}), improve_candidates=None)


def amg_preconditioner(matrix: sp.csr_matrix, plain: bool = False, hierarchy=None) -> spla.LinearOperator:
    """One smoothed-aggregation AMG V-cycle (pyamg hierarchy, :data:`AMG_OPTIONS`, built by
    :func:`smoothed_aggregation`; ``plain``: :func:`plain_aggregation`'s; ``hierarchy``: that
    pyamg ``MultilevelSolver`` of ``matrix``, made by the caller) as an SPD preconditioner.

    The cycle is run here rather than through ``MultilevelSolver.aspreconditioner``, whose
    ``solve`` also computes two residuals and three norms per application (two extra
    fine-level products per CG iteration, about a quarter of the depth step's time).
    Aggregation ignores couplings weaker than :data:`STRENGTH_THETA` (rounding residues).
    """
    ml = hierarchy if hierarchy is not None else plain_aggregation(matrix) if plain else smoothed_aggregation(matrix)
    # a module-level cycle, not a closure that calls itself: that closure is a reference cycle,
    # which kept every hierarchy (and its matrix: 95 MB at D415 size, 20 frames) alive after its
    # solve until the garbage collector's next full pass
    return spla.LinearOperator(matrix.shape, lambda b: _v_cycle(ml, 0, np.ravel(b)), dtype=matrix.dtype)


def smoothed_aggregation(matrix: sp.csr_matrix):
    """pyamg's smoothed-aggregation hierarchy of ``matrix`` (N, N) (:data:`AMG_OPTIONS`, strength
    :func:`strength_options`), built one level at a time: pyamg's own set-up with ``max_levels=2``
    per level, each coarse matrix ``R A P`` (pyamg's BSR with 1 x 1 blocks) passed on to the next
    as a CSR matrix on the same arrays (:func:`_csr_view`), its entries in the same order. The
    same hierarchy and V-cycle bit for bit (``tests/test_krylov.py``), without scipy's Python
    loop: the Gershgorin weights take ``abs`` of each level's matrix, which made a BSR matrix
    canonical entry by entry in Python (``_bsr.sum_duplicates``; 37 % of the set-up at 2
    megapixels), a CSR matrix in one compiled call (sorting the shared arrays in place, as the
    loop did). The levels keep pyamg's BSR matrices, whose Gauss-Seidel smoothing differs from
    CSR's in rounding. Returns a ``pyamg.multilevel.MultilevelSolver``."""
    levels, A, B, kept = [], matrix, None, matrix
    strength, improve = strength_options(matrix), {}  # pyamg's default candidate improvement on the finest level
    while True:
        with _local_jacobi_smoother():
            ml = pyamg.smoothed_aggregation_solver(A, B=B, strength=strength, max_levels=2, **improve, **AMG_OPTIONS)
        level = ml.levels[0]
        level.A = kept  # pyamg's matrix (its arrays sorted in place through the view)
        levels.append(level)
        if len(ml.levels) == 1:  # the coarsest (at most max_coarse unknowns)
            return pyamg.multilevel.MultilevelSolver(levels, coarse_solver=AMG_OPTIONS["coarse_solver"])
        kept, B = ml.levels[1].A, ml.levels[1].B
        A = _csr_view(kept)
        strength, improve = ("symmetric", {"theta": STRENGTH_THETA}), {"improve_candidates": None}


@contextmanager
def _local_jacobi_smoother():
    """pyamg's prolongation smoother replaced by :func:`_jacobi_prolongation` while a
    hierarchy is set up (and restored after, also on an error); pyamg's own where its module
    does not name it so (another pyamg version)."""
    module = importlib.import_module("pyamg.aggregation.aggregation")
    original = getattr(module, "jacobi_prolongation_smoother", None)
    if original is None:
        yield
        return
    module.jacobi_prolongation_smoother = partial(_jacobi_prolongation, original)
    try:
        yield
    finally:
        module.jacobi_prolongation_smoother = original


def _jacobi_prolongation(original, S, T, C, B, omega=4.0 / 3.0, degree=1, filter_entries=False,
                         weighting="diagonal"):
    """pyamg's ``jacobi_prolongation_smoother`` (``original``, called for any other case) for a
    float64 CSR matrix S (N, N) with ``weighting="local"``, one pass, no filter: the smoothed
    prolongation ``T - omega D^-1 S T`` (D: the rows' Gershgorin sums) with ``omega D^-1 S``
    formed in one compiled pass (:func:`.kernels.jacobi_scaled_rows`) on S's own pattern. pyamg
    formed it from three full copies of S (``abs(S)``, the scaled rows, the product with
    omega): 5 of the set-up's 13.6 CPU s at 2 megapixels x 20 frames, and some 600 MB beside the
    finest matrix. S is made canonical first, as pyamg's ``abs`` did, so the same P bit for bit
    (``tests/test_krylov.py``)."""
    if not (weighting == "local" and degree == 1 and not filter_entries and sp.issparse(S) and S.format == "csr"
            and S.dtype == np.float64):
        return original(S, T, C, B, omega=omega, degree=degree, filter_entries=filter_entries, weighting=weighting)
    S.sum_duplicates()  # canonical, as pyamg's abs(S) left it: its row sums in sorted order
    data = np.empty_like(S.data)
    host_kernels.jacobi_scaled_rows(S.indptr, S.data, float(omega), data)
    scaled = type(S)((data, S.indices, S.indptr), shape=S.shape, copy=False)
    return T - (scaled @ T)


#: the smoothers of pyamg's smoothed aggregation (its default, which :data:`AMG_OPTIONS` keeps):
#: symmetric Gauss-Seidel before and after the coarse correction
SA_SMOOTHER = ("block_gauss_seidel", {"sweep": "symmetric"})


def galerkin_hierarchy(ml, matrix: sp.csr_matrix):
    """The hierarchy ``ml`` (of :func:`smoothed_aggregation`, for another matrix of the same
    size and pattern) made over for ``matrix`` (N, N): its prolongations P and restrictions R
    kept, each coarser matrix formed anew as ``R A P`` (CSR, sorted), the smoothers and the
    coarse solve set up anew (P and R made CSR; each R A P by :func:`_galerkin_product`). A
    V-cycle for ``matrix`` without the prolongations' Jacobi smoothing, the candidates'
    improvement and the aggregation (at the D415's 89 619 unknowns 18 ms against a fresh set-up's
    86-103, once the products' patterns are held); a preconditioner as good as the fresh one where the
    matrices differ little (the joint steps of a level: :mod:`.joint`). ``ml``'s levels are
    taken over (not copied). Returns a ``pyamg.multilevel.MultilevelSolver``."""
    levels = ml.levels
    levels[0].A = matrix
    for fine, coarse in zip(levels[:-1], levels[1:]):
        coarse.A = _galerkin_product(fine, sp.csr_matrix(fine.A))
    made = pyamg.multilevel.MultilevelSolver(levels, coarse_solver=AMG_OPTIONS["coarse_solver"])
    change_smoothers(made, AMG_OPTIONS.get("presmoother", SA_SMOOTHER), AMG_OPTIONS.get("postsmoother", SA_SMOOTHER))
    return made


def _galerkin_product(level, A: sp.csr_matrix) -> sp.csr_matrix:
    """``R A P`` (n, n) CSR, sorted, of a pyamg level's P and R (made CSR once, held on the
    level) and A (N, N) CSR: the first time by scipy's products, the level then holding A's pattern
    and the structural patterns of A P and R A P (:func:`_product_pattern`: scipy drops the entries
    whose sum is exactly 0, which a later A's values may not cancel), and for an A of that same
    pattern again by :func:`.kernels.sparse_product_into` on both kernel threads, into those
    patterns (the same sums as scipy's in the same order; an entry scipy drops is stored as 0)."""
    if not isinstance(level.P, sp.csr_matrix):
        level.P, level.R = sp.csr_matrix(level.P), sp.csr_matrix(level.R)
    P, R = level.P, level.R
    held = getattr(level, "galerkin_patterns", None)
    if held is None or not (np.array_equal(held[0], A.indptr) and np.array_equal(held[1], A.indices)):
        AP = A @ P
        AP.sort_indices()
        RAP = R @ AP
        RAP.sort_indices()
        ap_pattern = _product_pattern(A, P)
        level.galerkin_patterns = (A.indptr, A.indices, *ap_pattern, *_product_pattern(R, ap_pattern, P.shape[1]))
        return RAP
    _, _, ap_indptr, ap_indices, rap_indptr, rap_indices = held
    n = P.shape[1]
    ap = np.empty(ap_indices.size)
    host_kernels.sparse_product_into(A.indptr, A.indices, A.data, P.indptr, P.indices, P.data, ap_indptr, ap_indices,
                                     ap, n)
    rap = np.empty(rap_indices.size)
    host_kernels.sparse_product_into(R.indptr, R.indices, R.data, ap_indptr, ap_indices, ap, rap_indptr, rap_indices,
                                     rap, n)
    return sp.csr_matrix((rap, rap_indices, rap_indptr), shape=(n, n), copy=False)


def _product_pattern(X: sp.csr_matrix, Y, columns: int | None = None) -> tuple:
    """(indptr, indices), columns sorted, of the structural pattern of X Y: every entry some pair
    of stored entries reaches, also where their values would cancel (the product of X's and Y's
    patterns with positive values). Y: a CSR matrix or an (indptr, indices) pattern of
    ``columns`` columns."""
    def ones(indptr, indices, shape):
        return sp.csr_matrix((np.ones(indices.size), indices, indptr), shape=shape)

    Y = ones(*Y, (X.shape[1], columns)) if isinstance(Y, tuple) else ones(Y.indptr, Y.indices, Y.shape)
    product = ones(X.indptr, X.indices, X.shape) @ Y
    product.sort_indices()
    return product.indptr, product.indices


def plain_aggregation(matrix: sp.csr_matrix):
    """pyamg's plain-aggregation hierarchy of ``matrix`` (N, N) (:data:`PLAIN_AMG_OPTIONS`,
    strength :func:`strength_options`): the tentative prolongations, unsmoothed, so no level's
    set-up takes the absolute value that :func:`smoothed_aggregation` builds its levels one by
    one for. Returns a ``pyamg.multilevel.MultilevelSolver``."""
    return pyamg.smoothed_aggregation_solver(matrix, strength=strength_options(matrix), **PLAIN_AMG_OPTIONS)


def _csr_view(A):
    """A BSR matrix with 1 x 1 blocks as a CSR matrix on the same arrays (entries in their order,
    not sorted); any other matrix as it is."""
    if A.format != "bsr" or A.blocksize != (1, 1):
        return A
    return sp.csr_matrix((A.data.reshape(-1), A.indices, A.indptr), shape=A.shape, copy=False)


def strength_options(matrix: sp.csr_matrix) -> list | tuple:
    """pyamg's ``strength`` argument for :func:`amg_preconditioner`: symmetric strength at
    :data:`STRENGTH_THETA` on every level; on the finest, for a float64 CSR matrix, the same
    connections passed as ``"predefined"`` (:func:`.kernels.strong_connections`), a pattern
    without values (standard aggregation reads only the pattern). pyamg's own strength matrix
    is a float64 copy of the matrix with its own indices, held through the finest level's whole
    set-up (240 MB at 2 megapixels); the pattern shares the matrix's arrays where every stored
    entry is strong. The hierarchy is the same bit for bit (``tests/test_krylov.py``)."""
    symmetric = ("symmetric", {"theta": STRENGTH_THETA})
    if not (isinstance(matrix, sp.csr_matrix) and matrix.dtype == np.float64 and matrix.shape[0] > 300):
        return symmetric
    indptr, indices = host_kernels.strong_connections(matrix.indptr, matrix.indices, matrix.data, STRENGTH_THETA)
    ones = np.broadcast_to(np.ones(1, dtype=np.int8), indices.shape)  # values pyamg does not read, stored once
    pattern = sp.csr_matrix((ones, indices, indptr), shape=matrix.shape, copy=False)
    return [("predefined", {"C": pattern}), symmetric]


def _v_cycle(ml, k: int, b: np.ndarray) -> np.ndarray:
    """The V-cycle of :func:`amg_preconditioner` from level k of the pyamg hierarchy ``ml`` on b."""
    level = ml.levels[k]
    if k == len(ml.levels) - 1:
        return np.asarray(ml.coarse_solver(level.A, b)).reshape(b.shape)
    x = np.zeros_like(b)
    level.presmoother(level.A, x, b)
    x += level.P @ _v_cycle(ml, k + 1, level.R @ (b - level.A @ x))
    level.postsmoother(level.A, x, b)
    return x


def pcg(matrix, rhs: np.ndarray, x0: np.ndarray, rtol: float, maxiter: int,
        preconditioner: spla.LinearOperator | None = None) -> tuple[np.ndarray, int, bool]:
    """PCG on ``matrix x = rhs`` ((N, N) sparse SPD or operator) from x0, to a residual of
    ``rtol * |rhs|``; returns (x, iterations, converged).

    ``preconditioner`` defaults to a fresh AMG hierarchy of ``matrix`` (which must then be sparse).
    """
    precond = preconditioner if preconditioner is not None else amg_preconditioner(matrix)
    count = [0]

    def callback(_):
        count[0] += 1

    x, info = spla.cg(matrix, rhs, x0=x0, rtol=rtol, maxiter=maxiter, M=precond, callback=callback)
    return x, count[0], info == 0


#: The CUDA path's last CG iteration count per kind of system (the joint step's Schur operator,
#: the depth step's matrix): where :func:`.krylov.pcg` first reads its status back, one iteration
#: before it but not before the second, whose reduction foretells the iterations left better
#: than the first's (the sweeps, and with the multigrid the levels, take similar counts). A guess
#: of when to test, which changes the number of host synchronisations and idle iterations, never
#: the result. FIRST_CHECK: the guess for a kind not solved yet in this process.
_CG_ITERATIONS: dict[str, int] = {}
FIRST_CHECK = 6


def solve_spd(matrix, rhs: np.ndarray, rtol: float, maxiter: int, sparse_part=None,
              pixel_prolongations: Callable[[], list] | None = None, plain: bool = False,
              hierarchy=None) -> tuple[np.ndarray, int]:
    """PCG from zero on ``matrix`` ((N, N) sparse SPD, or an operator whose sparse part
    ``sparse_part`` the AMG hierarchy is built from), preconditioned by a hierarchy built for
    this system; returns (x, iterations). plain: on the host, a plain-aggregation hierarchy
    (:func:`plain_aggregation`: a static camera's depth steps). hierarchy: on the host, the
    pyamg hierarchy of ``sparse_part`` to use instead (the caller's: :func:`galerkin_hierarchy`).

    On the CUDA path (:func:`.device.on_gpu`), where pyamg cannot run, the hierarchy is the
    geometric multigrid of :mod:`.krylov` (3 Chebyshev steps before and after, the measured
    best there) on the aggregation of the system's pixels that ``pixel_prolongations()`` returns
    (:meth:`.problem.LevelProblem.pixel_prolongations`, then required), and CG that module's.

    A hierarchy is not reused across sweeps: the IRLS weights, albedo and lighting move the
    system between sweeps, and with 3 frames a one-sweep-old hierarchy let CG run to its
    300-iteration cap where a fresh one needed 20-40 (8 frames: 4-23 against 4-6 on the finest
    level). Its setup costs about as much as five CG iterations (0.3 s at 90k unknowns).
    Keeping only the prolongations P, R and forming each new system's Galerkin matrices R A P
    (docs/performance.md, "2 MP joint step: AMG set-up per sweep") matched a fresh hierarchy's
    iterations on saved 2 MP systems at an eighth of the set-up, but on 2 MP x 20 frames its
    1-3-iteration solves on the two finest levels took other, worse steps (why is not known):
    45 sweeps against 37, 4.93 deg against 4.42. The joint step does so on smaller levels
    (:data:`.joint.REUSE_HIERARCHY_MAX_PIXELS`), passing the hierarchy in.
    """
    sparse = matrix if sparse_part is None else sparse_part
    if on_gpu(rhs):
        if pixel_prolongations is None:
            raise ValueError("solve_spd on the CUDA path needs the pixels' aggregation (pixel_prolongations=)")
        kind = type(matrix).__name__  # the joint step's Schur operator, or the depth step's matrix
        x, iterations, _ = krylov.pcg(matrix, rhs, None, rtol, maxiter,
                                      krylov.multigrid_preconditioner(sparse, pixel_prolongations()),
                                      first_check=max(2, _CG_ITERATIONS.get(kind, FIRST_CHECK + 1) - 1))
        _CG_ITERATIONS[kind] = max(iterations, 1)
        return x, iterations
    x, iterations, _ = pcg(matrix, rhs, np.zeros_like(rhs), rtol, maxiter, amg_preconditioner(sparse, plain, hierarchy))
    return x, iterations


def ridge_solve(A: np.ndarray, b: np.ndarray, ridge: float = 1e-9) -> np.ndarray | None:
    """Solution of the small SPD system ``(A + ridge trace(A) I) x = b`` (k,), or None where
    it is not positive definite or not finite: the Gauss-Newton steps of the pose, LED offset and
    lighting on the host. One system of :func:`ridge_solves` (the formula of the GPU's batched
    solves)."""
    x, solved = ridge_solves(np.asarray(A, dtype=np.float64)[None], np.asarray(b, dtype=np.float64).reshape(1, -1, 1),
                             ridge)
    return x[0, :, 0] if solved[0] else None


def ridge_solves(A: np.ndarray, B: np.ndarray, ridge: float = 1e-9, fallback: float = 0.0) -> tuple:
    """A batch of small SPD systems ``(A_i + ridge trace(A_i) I) X_i = B_i`` by Cholesky, where
    the arrays live (on a GPU one launch, one thread per system: the frames' 6x6 pose systems,
    the LED offset's 3x3): A (n, k, k), B (n, k, r); returns X (n, k, r) (NaN for a system
    that is not positive definite or not finite) and solved (n,) float64, 1.0 or 0.0, both
    where A lives. fallback > 0: a system that fails takes ``fallback max|diag A_i|`` on its
    diagonal instead (:func:`.kernels.ridge_solve_system`)."""
    xp = array_module(A)
    A, B = contiguous(A, np.float64), contiguous(B, np.float64)
    X, L, solved = xp.empty(B.shape), xp.empty(A.shape), xp.empty(A.shape[0])
    kernels_for(A).ridge_solves(A, B, float(ridge), float(fallback), L, X, solved)
    return X, solved
