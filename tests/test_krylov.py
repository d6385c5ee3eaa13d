"""Tests of o3d_mvps.solver.krylov (PCG and preconditioners for NumPy or CuPy arrays), here on
NumPy: on a depth system assembled by the solver's own code on a masked grid (7-point data
stencil of random rows, SF-block prior, second differences, Levenberg damping), and on the
systems the solver itself solves on a small rendered LED scene.
"""

from contextlib import contextmanager, nullcontext

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from threadpoolctl import threadpool_limits

from o3d_mvps.model.normals import masked_grid
from o3d_mvps.solver import depth, driver, joint, krylov
from o3d_mvps.solver.linear import levenberg_damped, solve_spd
from o3d_mvps.solver.normal_equations import stencil_normal_matrix
from o3d_mvps.solver.options import RefineOptions
from o3d_mvps.solver.pyramid import depth_prior
from o3d_mvps.solver.smoothness import second_differences
from o3d_mvps.solving import problem_from_capture
from o3d_mvps.synthetic import render_capture


@pytest.fixture(autouse=True)
def one_blas_thread():
    """Dense checks on one BLAS thread: on a loaded 2-core machine OpenBLAS's threads made a
    550 x 550 eigendecomposition take 5 s instead of 0.05 s."""
    with threadpool_limits(1, user_api="blas"):
        yield


def grid_system(shape=(40, 56), seed=0, tau=50.0, mu=0.3):
    """(M, b, grid): the damped depth matrix (N, N) of random data rows ``a Du + b Dv + c I`` (3
    channels) on a disc mask of ``shape``, plus ``2 tau D^T D`` (2x2 blocks) and ``2 mu S^T S``;
    a random right-hand side b (N,)."""
    rng = np.random.default_rng(seed)
    H, W = shape
    v, u = np.mgrid[:H, :W]
    grid = masked_grid((u - W / 2) ** 2 / (0.45 * W) ** 2 + (v - H / 2) ** 2 / (0.45 * H) ** 2 < 1)
    a, b, c = rng.normal(size=(3, grid.size, 3)) * np.array([1.0, 1.0, 0.1])[:, None, None]
    products = [(x * y).sum(axis=1) for x, y in ((a, a), (b, b), (c, c), (a, b), (a, c), (b, c))]
    prior = depth_prior(grid, np.ones((H // 2, W // 2)), 2.0)
    S = second_differences(grid)
    M = stencil_normal_matrix(grid, *products) + 2 * tau * (prior.D.T @ prior.D) + 2 * mu * (S.T @ S)
    return levenberg_damped(M), rng.normal(size=grid.size), grid


def dense_operator(apply, n):
    """The (n, n) matrix of a linear map given as a callable on (n,) vectors."""
    return np.stack([apply(e) for e in np.eye(n)], axis=1)


@pytest.mark.parametrize("preconditioner", ["none", "jacobi", "multigrid"])
def test_pcg_reaches_the_tolerance_and_agrees_with_a_direct_solve_and_scipy(preconditioner):
    M, b, grid = grid_system()
    P = {"none": None, "jacobi": krylov.jacobi_preconditioner(M),
         "multigrid": krylov.multigrid_preconditioner(M, krylov.pixel_prolongations(grid.u, grid.v, max_coarse=300)),
         }[preconditioner]
    exact = spla.spsolve(M.tocsc(), b)
    for rtol in (1e-4, 1e-10):
        x, iterations, converged = krylov.pcg(M, b, None, rtol, 5000, P)
        assert converged and iterations > 1
        assert np.linalg.norm(b - M @ x) <= 1.01 * rtol * np.linalg.norm(b)
        # scipy's CG with the same preconditioner and stopping rule takes as many iterations
        count = []
        spla.cg(M, b, rtol=rtol, maxiter=5000, callback=count.append,
                M=None if P is None else spla.LinearOperator(M.shape, P, dtype=float))
        assert abs(len(count) - iterations) <= 1
    # cond(M) < 1e5 here: a 1e-10 residual leaves at most 1e-5 relative error (1e-8 seen)
    assert np.linalg.norm(x - exact) <= 1e-5 * np.linalg.norm(exact)
    # from the solution itself: nothing to do; from a zero right-hand side: zero
    assert krylov.pcg(M, b, exact, 1e-6, 10, P)[1:] == (0, True)
    x, iterations, converged = krylov.pcg(M, np.zeros_like(b), b, 1e-6, 10, P)
    assert (iterations, converged) == (0, True) and not x.any()


def test_pcg_reports_a_run_out_of_iterations():
    M, b, _ = grid_system()
    x, iterations, converged = krylov.pcg(M, b, None, 1e-8, 5)
    assert (iterations, converged) == (5, False)
    assert np.linalg.norm(b - M @ x) > 1e-8 * np.linalg.norm(b)


def test_the_amg_hierarchy_is_freed_with_its_solve_without_the_garbage_collector(monkeypatch):
    """The AMG preconditioner holds no reference cycle: its hierarchy (and the matrix it was
    built from) is freed when the solve returns, not at the collector's next pass (a
    self-calling closure kept 95 MB per sweep alive at D415 size)."""
    import gc
    import weakref

    from o3d_mvps.solver import linear

    made = []
    build = linear.smoothed_aggregation

    def recorded(*args, **kwargs):
        ml = build(*args, **kwargs)
        made.append(weakref.ref(ml))
        return ml

    monkeypatch.setattr(linear, "smoothed_aggregation", recorded)
    n = 2000
    matrix = sp.diags([-np.ones(n - 1), 2.01 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr()
    enabled = gc.isenabled()
    gc.disable()
    try:
        x, _ = solve_spd(matrix, np.ones(n), 1e-10, 200)
        assert len(made) == 1 and made[0]() is None
    finally:
        if enabled:
            gc.enable()
    np.testing.assert_allclose(matrix @ x, np.ones(n), atol=1e-7)


def test_the_finest_strength_pattern_gives_pyamgs_hierarchy_bit_for_bit():
    """The finest level's strength, passed to pyamg as a pattern (:func:`.linear.strength_options`),
    is pyamg's own symmetric strength at STRENGTH_THETA (stored zeros and rounding residues
    dropped, the diagonal kept), and the V-cycle built from it equals pyamg's default-strength
    cycle bit for bit; where every entry is strong the pattern shares the matrix's arrays."""
    import pyamg

    from o3d_mvps.solver import linear

    M, b, _ = grid_system()
    M = sp.csr_matrix(M)
    rows = np.repeat(np.arange(M.shape[0]), np.diff(M.indptr))
    off = np.flatnonzero(rows != M.indices)
    M.data[off[::11]] *= 1e-20  # rounding residues (weak) and stored zeros: dropped
    M.data[off[5::13]] = 0.0
    M.data[np.flatnonzero(rows == M.indices)[::17]] = 0.0  # a stored zero diagonal: kept
    options = linear.strength_options(M)
    pattern = options[0][1]["C"]
    reference = pyamg.strength.symmetric_strength_of_connection(M, linear.STRENGTH_THETA)
    assert pattern.nnz < M.nnz
    np.testing.assert_array_equal(pattern.indptr, reference.indptr)
    np.testing.assert_array_equal(pattern.indices, reference.indices)

    def cycle(strength):
        np.random.seed(0)
        ml = pyamg.smoothed_aggregation_solver(M, symmetry="symmetric", max_coarse=300, coarse_solver="splu",
                                               strength=strength)
        return [level.A.shape[0] for level in ml.levels], linear._v_cycle(ml, 0, b)

    sizes, ours = cycle(options)
    ref_sizes, theirs = cycle(("symmetric", {"theta": linear.STRENGTH_THETA}))
    assert sizes == ref_sizes and len(sizes) >= 2
    np.testing.assert_array_equal(ours, theirs)
    strong = sp.csr_matrix(sp.diags([-np.ones(499), 2.01 * np.ones(500), -np.ones(499)], [-1, 0, 1]))
    pattern = linear.strength_options(strong)[0][1]["C"]
    assert np.shares_memory(pattern.indices, strong.indices) and np.shares_memory(pattern.indptr, strong.indptr)
    assert linear.strength_options(strong.astype(np.float32)) == ("symmetric", {"theta": linear.STRENGTH_THETA})


def test_the_level_by_level_set_up_is_pyamgs_hierarchy_bit_for_bit():
    """:func:`.linear.smoothed_aggregation` (pyamg's set-up one level at a time, each coarse matrix
    passed on as CSR) gives pyamg's one-call hierarchy bit for bit: the same levels (matrices,
    prolongations, restrictions; pyamg's BSR coarse matrices kept), the same V-cycle, without
    scipy's Python loop over a BSR matrix's entries (``_bsr.sum_duplicates``, not called), and
    with every level's smoothed prolongation from the compiled Jacobi rows
    (kernels.jacobi_scaled_rows, not pyamg's three copies of the matrix; its smoother restored
    after), also from a matrix whose rows are stored unsorted."""
    from unittest import mock

    import pyamg
    import pyamg.aggregation.aggregation as sa
    import scipy.sparse._bsr as bsr

    from o3d_mvps.solver import kernels, linear

    M = sp.csr_matrix(grid_system(shape=(80, 112))[0])
    b = np.random.default_rng(3).normal(size=M.shape[0])
    original = sa.jacobi_prolongation_smoother
    with mock.patch.object(bsr._bsr_base, "sum_duplicates", autospec=True,
                           side_effect=bsr._bsr_base.sum_duplicates) as loop, \
            mock.patch.object(kernels, "jacobi_scaled_rows", side_effect=kernels.jacobi_scaled_rows) as rows:
        ours = linear.smoothed_aggregation(M)
    assert loop.call_count == 0 and rows.call_count == len(ours.levels) - 1
    assert sa.jacobi_prolongation_smoother is original
    theirs = pyamg.smoothed_aggregation_solver(M, strength=linear.strength_options(M), **linear.AMG_OPTIONS)
    assert len(ours.levels) == len(theirs.levels) >= 3
    for k, (x, y) in enumerate(zip(ours.levels, theirs.levels)):
        assert type(x.A) is type(y.A)
        pairs = [(x.A, y.A)] + ([(x.P, y.P), (x.R, y.R)] if k < len(ours.levels) - 1 else [])
        for a, c in pairs:
            a, c = sp.csr_matrix(a), sp.csr_matrix(c)
            for name in ("indptr", "indices", "data"):
                np.testing.assert_array_equal(getattr(a, name), getattr(c, name))
    np.testing.assert_array_equal(linear._v_cycle(ours, 0, b), linear._v_cycle(theirs, 0, b))
    # rows stored in reverse order: the smoother makes them canonical first, as pyamg's abs did
    shuffled = M.copy()
    for i in range(M.shape[0]):
        row = slice(M.indptr[i], M.indptr[i + 1])
        shuffled.indices[row], shuffled.data[row] = M.indices[row][::-1], M.data[row][::-1]
    shuffled.has_sorted_indices = False
    T = sp.csr_matrix(theirs.levels[0].P)  # any (N, Nc) matrix in the place of the tentative one
    expected = original(M.copy(), T, None, None, omega=4.0 / 3.0, weighting="local")
    got = linear._jacobi_prolongation(original, shuffled, T, None, None, omega=4.0 / 3.0, weighting="local")
    assert shuffled.has_canonical_format and type(got) is type(expected)
    for name in ("indptr", "indices", "data"):
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name))


def test_a_hierarchy_made_over_for_its_own_matrix_gives_the_fresh_v_cycle_and_for_another_a_good_one():
    """:func:`.linear.galerkin_hierarchy` keeps P and R and forms each coarse matrix anew as R A P:
    made over for the matrix it was built from, its V-cycle is the fresh one's to rounding; for
    another matrix of the same pattern (each row rescaled by up to 30 %, as the joint steps'
    weights move), CG with it takes at most one iteration more than with a fresh set-up, and
    solves the system."""
    from o3d_mvps.solver import linear

    M = sp.csr_matrix(grid_system(shape=(80, 112))[0])
    b = np.random.default_rng(3).normal(size=M.shape[0])
    fresh = linear.smoothed_aggregation(M)
    expected = linear._v_cycle(fresh, 0, b)
    made = linear.galerkin_hierarchy(linear.smoothed_aggregation(M), M)
    assert len(made.levels) == len(fresh.levels) >= 3
    np.testing.assert_allclose(linear._v_cycle(made, 0, b), expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    scale = sp.diags(np.random.default_rng(4).uniform(0.85, 1.15, M.shape[0]))
    other = sp.csr_matrix(scale @ M @ scale)
    kept = linear.galerkin_hierarchy(linear.smoothed_aggregation(M), other)
    x_kept, n_kept, ok_kept = linear.pcg(other, b, np.zeros_like(b), 1e-8, 300, linear.amg_preconditioner(other, hierarchy=kept))
    x_fresh, n_fresh, ok_fresh = linear.pcg(other, b, np.zeros_like(b), 1e-8, 300, linear.amg_preconditioner(other))
    assert ok_kept and ok_fresh and n_kept <= n_fresh + 1, (n_kept, n_fresh)
    np.testing.assert_allclose(other @ x_kept, b, atol=1e-7 * np.abs(b).max())


def test_sparse_product_into_a_pattern_is_scipys_product_bit_for_bit():
    """kernels.sparse_product_into writes A B into a given CSR pattern with scipy's sums in
    scipy's order: the same values bit for bit; a pattern entry the product lacks gets 0. The
    made-over hierarchy's second R A P (by the kernel, into the first one's patterns) equals the
    first (by scipy)."""
    from o3d_mvps.solver import kernels, linear

    rng = np.random.default_rng(5)
    A = sp.random(300, 200, density=0.03, random_state=1, format="csr")
    B = sp.random(200, 50, density=0.05, random_state=2, format="csr")
    C = A @ B
    C.sort_indices()
    extra = sp.random(300, 50, density=0.02, random_state=3, format="csr")
    pattern = sp.csr_matrix(((C != 0) + (extra != 0)).astype(np.float64))  # C's pattern and more
    pattern.sort_indices()
    out = rng.normal(size=pattern.nnz)  # overwritten everywhere
    kernels.sparse_product_into(A.indptr, A.indices, A.data, B.indptr, B.indices, B.data, pattern.indptr,
                                pattern.indices, out, 50)
    got = sp.csr_matrix((out, pattern.indices, pattern.indptr), shape=C.shape)
    assert got.nnz > C.nnz
    dense, expected = got.toarray(), C.toarray()
    assert np.array_equal(dense, expected)
    M = sp.csr_matrix(grid_system(shape=(80, 112))[0])
    first = linear.galerkin_hierarchy(linear.smoothed_aggregation(M), M)
    again = linear.galerkin_hierarchy(linear.galerkin_hierarchy(linear.smoothed_aggregation(M), M), M)
    for x, y in zip(first.levels[1:], again.levels[1:]):
        for name in ("indptr", "indices", "data"):
            np.testing.assert_array_equal(getattr(x.A, name), getattr(y.A, name))


@contextmanager
def on_stand_in(simulated: bool):
    """Within: the CuPy stand-in (tests/cupy_emulation.py, yielded), the CUDA kernels run by
    numba's CUDA simulator (``simulated``) or, as ``python -m benchmarks.gpu count`` runs them,
    by their CPU twins (tests/test_cuda_kernels.py holds the two equal): the simulator runs a
    launch's threads as Python threads, too slow for solves of a hundred iterations."""
    import cupy_emulation as cp
    from benchmarks.gpu import _cpu_kernels_as_cuda_kernels

    with cp.installed(), nullcontext() if simulated else _cpu_kernels_as_cuda_kernels(cp):
        yield cp


@pytest.mark.parametrize("preconditioner", ["jacobi", "multigrid"])
def test_pcg_on_device_arrays_matches_numpy(preconditioner):
    """The CUDA path's PCG and preconditioners run on device arrays (the CuPy stand-in of
    tests/cupy_emulation.py, which refuses host arrays as CuPy does): the same iterations and,
    to round-off (1e-12 relative; the same arithmetic), the same solution as on NumPy."""
    M, b, grid = grid_system(shape=(24, 36))
    with on_stand_in(simulated=preconditioner == "multigrid") as cp:
        results = []
        for A, rhs, u, v in ((M, b, grid.u, grid.v), (cp.sparse.csr_matrix(M), cp.asarray(b), cp.asarray(grid.u),
                                                      cp.asarray(grid.v))):
            P = (krylov.jacobi_preconditioner(A) if preconditioner == "jacobi" else
                 krylov.multigrid_preconditioner(A, krylov.pixel_prolongations(u, v, max_coarse=100)))
            # the device's first read one iteration before the host's count, as linear.solve_spd guesses it from
            # the last solve (from the first iteration's reduction alone the second, last read came too early)
            results.append(krylov.pcg(A, rhs, None, 1e-8, 1000, P, first_check=max(2, results[0][1] - 1) if results
                                      else 1))
    (x, iterations, converged), (x_device, iterations_device, converged_device) = results
    assert isinstance(x_device, cp.ndarray) and converged and converged_device
    assert iterations_device == iterations > 1
    np.testing.assert_allclose(x_device.get(), x, rtol=0, atol=1e-12 * np.abs(x).max())


def test_pcg_on_a_device_reads_the_host_twice_however_early_its_first_check():
    """After its first status read, PCG on device arrays reads again where the residual's
    reduction so far says it will have converged: two host reads (synchronisations) for a first
    check 1-8 iterations early on this 9-iteration solve, and the iterations and solution of an
    exact stop."""
    M, b, grid = grid_system(shape=(24, 36))
    with on_stand_in(simulated=False) as cp:
        A, rhs = cp.sparse.csr_matrix(M), cp.asarray(b)
        P = krylov.multigrid_preconditioner(A, krylov.pixel_prolongations(cp.asarray(grid.u), cp.asarray(grid.v),
                                                                          max_coarse=100))
        exact = krylov.pcg(A, rhs, None, 1e-8, 1000, P, first_check=9)
        for first_check in (1, 2, 5, 8):
            before = cp.operations["to_host"]
            x, iterations, converged = krylov.pcg(A, rhs, None, 1e-8, 1000, P, first_check=first_check)
            assert cp.operations["to_host"] - before == 2, first_check
            assert (iterations, converged) == exact[1:] == (9, True)
            np.testing.assert_array_equal(x.get(), exact[0].get())


def test_pcg_on_a_device_reads_the_host_at_most_twice_and_honours_maxiter():
    """Whatever the first check and the cap, PCG on device arrays reads its state back at most
    twice per solve (the second read is the last: unconverged there, it says so), never runs
    past maxiter, and where it says converged the residual meets the tolerance; plain CG (no
    preconditioner: ~50 iterations, a residual that does not fall at every step) too. The
    multigrid's set-up reads nothing back (its spectral bounds stay on the device)."""
    M, b, grid = grid_system(shape=(24, 36))
    with on_stand_in(simulated=False) as cp:
        A, rhs = cp.sparse.csr_matrix(M), cp.asarray(b)
        prolongations = krylov.pixel_prolongations(cp.asarray(grid.u), cp.asarray(grid.v), max_coarse=100)
        before = cp.operations["to_host"]
        P = krylov.multigrid_preconditioner(A, prolongations)  # once per grid: the aggregates read their sizes
        assert cp.operations["to_host"] == before
        for preconditioner in (P, None):
            for first_check, maxiter in ((1, 1000), (2, 1000), (3, 7), (1, 4), (40, 1000), (1, 1)):
                before = cp.operations["to_host"]
                x, iterations, converged = krylov.pcg(A, rhs, None, 1e-8, maxiter, preconditioner,
                                                      first_check=first_check)
                assert 1 <= cp.operations["to_host"] - before <= 2, (first_check, maxiter)
                assert iterations <= maxiter
                residual = np.linalg.norm(b - M @ x.get())
                # the recurrence's residual against the true one: 1 % apart at most
                bound = 1e-8 * np.linalg.norm(b) * (1.01 if converged else 0.99)
                assert (residual <= bound) == converged, (first_check, maxiter, residual / bound)
        # generous first checks: converged (the cap of 1000 is never reached)
        assert krylov.pcg(A, rhs, None, 1e-8, 1000, None, first_check=40)[2]
        assert krylov.pcg(A, rhs, None, 1e-8, 1000, P, first_check=3)[2]


def test_pixel_aggregates_join_2x2_pixels_stride_apart():
    u, v = (c.ravel() for c in np.mgrid[:4, :4][::-1])  # a full 4x4 grid, row-major
    for stride, members in ((1, {(0, 0), (1, 0), (0, 1), (1, 1)}), (2, {(0, 0), (2, 0), (0, 2), (2, 2)})):
        aggregate, cu, cv = krylov.pixel_aggregates(u, v, stride)
        assert cu.size == 4 and np.bincount(aggregate).tolist() == [4, 4, 4, 4]
        assert {(int(a), int(b)) for a, b in zip(u[aggregate == aggregate[0]], v[aggregate == aggregate[0]])} == members
        # the coarse grid is again a 2x2 grid, each coarse pixel the aggregate's own
        assert sorted(zip(cu.tolist(), cv.tolist())) == [(0, 0), (0, 1), (1, 0), (1, 1)]


def test_spectral_bound_bounds_the_largest_eigenvalue_tightly():
    M, _, _ = grid_system()
    inv_diag = krylov.inverse_diagonal(M)
    scaling = sp.diags(np.sqrt(inv_diag))
    largest = spla.eigsh(scaling @ M @ scaling, k=1, which="LA", return_eigenvectors=False)[0]
    bound = krylov.spectral_bound(M, inv_diag)
    assert largest <= bound <= 1.5 * largest


def test_chebyshev_attains_its_error_bound():
    """From zero, k steps on [lambda_min, lambda_max] of D^-1 A reduce the A-norm error by at most
    ``2 q^k / (1 + q^2k)``, q = (sqrt(kappa) - 1) / (sqrt(kappa) + 1), and by no less for some
    right-hand side (the bound is sharp)."""
    M, b, _ = grid_system(shape=(20, 28))
    inv_diag = krylov.inverse_diagonal(M)
    scale = np.sqrt(inv_diag)
    eigenvalues, vectors = np.linalg.eigh(M.multiply(np.outer(scale, scale)).toarray())
    low, high = eigenvalues[0], eigenvalues[-1]
    q = (np.sqrt(high / low) - 1) / (np.sqrt(high / low) + 1)
    for steps in (1, 2, 5):
        chebyshev = krylov.ChebyshevSmoother(M, inv_diag, low, high, steps)
        error = np.eye(M.shape[0]) - dense_operator(chebyshev, M.shape[0]) @ M.toarray()
        # the error map's A-norm: its largest eigenvalue in magnitude (it is A-self-adjoint)
        similar = np.diag(1 / scale) @ error @ np.diag(scale)
        contraction = np.abs(np.linalg.eigvals(similar)).max()
        assert contraction == pytest.approx(2 * q**steps / (1 + q ** (2 * steps)), rel=1e-6)


@pytest.mark.parametrize("smoother, steps, smoothed, stride", [
    ("jacobi", 1, True, 1), ("jacobi", 2, False, 2), ("chebyshev", 2, True, 2), ("chebyshev", 3, False, 1)])
def test_multigrid_cycle_is_symmetric_positive_definite(smoother, steps, smoothed, stride):
    M, _, grid = grid_system(shape=(24, 36))
    prolongations = krylov.pixel_prolongations(grid.u, grid.v, stride, max_coarse=20)
    cycle = krylov.multigrid_preconditioner(M, prolongations, smoother=smoother, smoothing_steps=steps,
                                            smoothed_prolongation=smoothed)
    assert len(cycle.levels) >= 3
    B = dense_operator(cycle, M.shape[0])
    assert np.abs(B - B.T).max() <= 1e-12 * np.abs(B).max()
    assert np.linalg.eigvalsh((B + B.T) / 2)[0] > 0
    rng = np.random.default_rng(1)
    for x, y in rng.normal(size=(10, 2, M.shape[0])):
        assert x @ cycle(y) == pytest.approx(y @ cycle(x), rel=1e-12)
        assert x @ cycle(x) > 0


def test_chebyshev_and_jacobi_preconditioners_are_symmetric_positive_definite():
    M, _, _ = grid_system(shape=(24, 36))
    for P in (krylov.jacobi_preconditioner(M), krylov.chebyshev_preconditioner(M, 3, 0.03)):
        B = dense_operator(P, M.shape[0])
        assert np.abs(B - B.T).max() <= 1e-12 * np.abs(B).max()
        assert np.linalg.eigvalsh((B + B.T) / 2)[0] > 0


# ---------------------------------------------------------------------------------------------
# the systems of a real solve


BUILD_LEVEL = driver.build_level


@pytest.fixture(scope="module")
def solver_systems():
    """The last depth-only and the last joint system of three sweeps on the finest level of a
    320x240 LED bunny (3 frames, SF 4, true poses): dicts of the operator (matrix or Schur
    operator), right-hand side, tolerance, the sparse M, and the grid."""
    capture = render_capture("bunny", frames=3, scale_factor=4, size=(320, 240), light="led", seed=0)
    systems = {}
    with pytest.MonkeyPatch.context() as patch:
        levels = []

        def build_level(*args, **kwargs):
            levels.append(BUILD_LEVEL(*args, **kwargs))
            return levels[-1]

        patch.setattr(driver, "build_level", build_level)
        for module, kind in ((depth, "depth"), (joint, "joint")):
            def keep(matrix, rhs, rtol, maxiter, sparse_part=None, pixel_prolongations=None, solve=module.solve_spd,
                     kind=kind, **plain):
                systems[kind] = dict(A=matrix, b=rhs, rtol=rtol, M=matrix if sparse_part is None else sparse_part,
                                     grid=levels[-1].grid)
                return solve(matrix, rhs, rtol, maxiter, sparse_part, pixel_prolongations, **plain)
            patch.setattr(module, "solve_spd", keep)
        for refine_poses in (False, True):
            options = RefineOptions(levels=1, max_iterations=3, refine_poses=refine_poses, joint_min_pixels=0)
            problem_input, _ = problem_from_capture(capture, options, capture.groundtruth.poses)
            driver.solve(problem_input)
    return systems


def recommended_multigrid(system):
    """The multigrid recommended for the GPU path (:func:`krylov.multigrid_preconditioner`'s defaults)."""
    return krylov.multigrid_preconditioner(system["M"], krylov.pixel_prolongations(system["grid"].u, system["grid"].v))


def test_multigrid_needs_few_iterations_where_jacobi_needs_many(solver_systems):
    """Depth-only system (5608 unknowns, rtol 1e-4), with the LED's evidence weights (a pixel's
    smoothness up to the sensor's where its shading says little; three frames here): measured
    17 iterations with the multigrid (bound 20), 135 with Jacobi and 54 with a degree-3
    Chebyshev polynomial (pyamg's CG 21). Without the weights: 9, 60, 25 (pyamg 12)."""
    s = solver_systems["depth"]
    assert s["rtol"] == RefineOptions().cg_tolerance and s["M"].shape[0] > 5000
    counts = {name: krylov.pcg(s["A"], s["b"], None, s["rtol"], 1000, P)[1:] for name, P in (
        ("multigrid", recommended_multigrid(s)), ("jacobi", krylov.jacobi_preconditioner(s["M"])),
        ("chebyshev", krylov.chebyshev_preconditioner(s["M"], 3, 0.03)))}
    assert all(converged for _, converged in counts.values())
    assert counts["multigrid"][0] <= 20
    assert counts["jacobi"][0] >= 100 and counts["chebyshev"][0] >= 40


def test_schur_operator_with_the_multigrid_of_its_sparse_part(solver_systems):
    """Joint system: S = M - U H^-1 U^T as an operator, the cycle built from M. To the joint
    tolerance 1e-2: measured 6 iterations (bound 9), Jacobi 19; to 1e-8 the residual of S holds
    and the solution agrees with the CPU path's (AMG-preconditioned scipy CG)."""
    s = solver_systems["joint"]
    assert isinstance(s["A"], spla.LinearOperator) and s["rtol"] == RefineOptions().joint_cg_tolerance
    cycle = recommended_multigrid(s)
    _, iterations, converged = krylov.pcg(s["A"], s["b"], None, s["rtol"], 1000, cycle)
    assert converged and iterations <= 9
    assert krylov.pcg(s["A"], s["b"], None, s["rtol"], 1000, krylov.jacobi_preconditioner(s["M"]))[1] >= 15
    x, _, converged = krylov.pcg(s["A"], s["b"], None, 1e-8, 1000, cycle)
    assert converged and np.linalg.norm(s["b"] - s["A"] @ x) <= 1.01e-8 * np.linalg.norm(s["b"])
    reference, _ = solve_spd(s["A"], s["b"], 1e-10, 1000, sparse_part=s["M"])
    assert np.linalg.norm(x - reference) <= 1e-5 * np.linalg.norm(reference)


def test_the_device_multigrid_runs_its_cycles_and_cg_in_one_launch_per_host_read():
    """On device arrays, a multigrid of Chebyshev smoothers is packed for one kernel
    (:func:`krylov.pack_hierarchy`): PCG with the system's own CSR matrix is one launch of
    multigrid_cg per host read, CG's start in the first (2 launches for 9 iterations; were 15 per
    iteration, then 3 with cg_start's own), with an operator one launch per iteration besides the
    operator's product, plus the first cycle's (with the start); with a Schur complement given by
    its parts (M, C, U^T) one launch per read again; the
    same solutions. The packed prolongations and restrictions depend on the grid alone: kept with the
    grid's prolongations, so a second set-up makes none of them again."""
    M, b, grid = grid_system(shape=(24, 36))
    with on_stand_in(simulated=False) as cp:
        A, rhs = cp.sparse.csr_matrix(M), cp.asarray(b)
        prolongations = krylov.pixel_prolongations(cp.asarray(grid.u), cp.asarray(grid.v), max_coarse=100)
        counts = []
        for _ in range(2):
            before = sum(cp.operations.values())
            P = krylov.multigrid_preconditioner(A, prolongations)
            counts.append(sum(cp.operations.values()) - before)
        assert P.packed is not None and P.packed.levels == len(P.levels) == 2
        assert P.packed.arrays[3] is prolongations.packed[0] and P.packed.arrays[6] is prolongations.packed[3]
        assert counts[1] < counts[0]
        before = cp.operations["kernel"]
        x, iterations, converged = krylov.pcg(A, rhs, None, 1e-8, 1000, P, first_check=8)
        assert (iterations, converged) == (9, True)
        assert cp.operations["kernel"] - before == 2
        from o3d_mvps.model.arrays import MatvecOperator

        before = cp.operations["kernel"]
        x_op, iterations_op, _ = krylov.pcg(MatvecOperator(A.shape, lambda v: A @ v), rhs, None, 1e-8, 1000, P,
                                            first_check=8)
        # the start and the first cycle, then one launch per iteration run: 10 (the second read comes one
        # iteration past the 9th, where CG converged: the 10th changes nothing)
        assert iterations_op == 9 and cp.operations["kernel"] - before == 1 + 10
        np.testing.assert_allclose(x_op.get(), x.get(), rtol=0, atol=1e-12 * np.abs(x.get()).max())
        # a Schur complement M + C U^T whose parts are given: its product in the kernel too, one launch per read
        U = np.random.default_rng(3).normal(size=(M.shape[0], 6)) * 0.05
        U_t, C = cp.asarray(np.ascontiguousarray(U.T)), cp.asarray(-U / 4.0)
        results = []
        for with_parts in (False, True):
            schur = MatvecOperator(A.shape, lambda v: krylov.multiply_add(A, 1.0, v, C @ (U_t @ v)))
            if with_parts:
                schur.low_rank_parts = (A, C, U_t)
            before = cp.operations["kernel"]
            results.append(krylov.pcg(schur, rhs, None, 1e-8, 1000, P, first_check=8))
            results[-1] += (cp.operations["kernel"] - before,)
        (x_plain, it_plain, _, kernels_plain), (x_parts, it_parts, converged_parts, kernels_parts) = results
        assert converged_parts and it_parts == it_plain and kernels_parts == 2 < kernels_plain
        np.testing.assert_allclose(x_parts.get(), x_plain.get(), rtol=0, atol=1e-12 * np.abs(x_plain.get()).max())


def test_device_prolongations_from_the_host_pixels_are_two_copies_and_the_same_hierarchy():
    """The grid's prolongations for a device, aggregated from the host's pixels (``like=``): two
    copies to the device and no launch, the same P and R (and their packing) as aggregated on the
    device; the multigrid's set-up is then one launch per solve, and PCG takes the same iterations
    and solution."""
    M, b, grid = grid_system(shape=(24, 36))
    with on_stand_in(simulated=False) as cp:
        A, rhs = cp.sparse.csr_matrix(M), cp.asarray(b)
        on_device = krylov.pixel_prolongations(cp.asarray(grid.u), cp.asarray(grid.v), max_coarse=100)
        before = dict(cp.operations)
        moved = krylov.pixel_prolongations(grid.u, grid.v, max_coarse=100, like=rhs)
        spent = {kind: n - before.get(kind, 0) for kind, n in cp.operations.items() if n != before.get(kind, 0)}
        assert spent == {"to_device": 2}
        results = []
        for prolongations in (on_device, moved):
            before = sum(cp.operations.values())
            P = krylov.multigrid_preconditioner(A, prolongations)
            if prolongations is moved:
                assert sum(cp.operations.values()) - before == 1  # the set-up's launch
            results.append(krylov.pcg(A, rhs, None, 1e-8, 1000, P, first_check=8))
        assert len(moved) == len(on_device) == 2
        for mine, theirs in zip(moved.packed, on_device.packed):
            np.testing.assert_array_equal(mine.get(), theirs.get())
        for P, Q in zip(moved + moved.restrictions, on_device + on_device.restrictions):
            assert P.shape == Q.shape
            np.testing.assert_array_equal(P.indices.get(), Q.indices.get())
        assert results[0][1:] == results[1][1:] == (9, True)
        np.testing.assert_array_equal(results[0][0].get(), results[1][0].get())


def test_the_amg_set_up_estimates_no_spectral_radius_and_preconditions_as_well(monkeypatch):
    """:func:`.linear.amg_preconditioner` weights its Jacobi prolongation smoother row by row
    (:data:`.linear.AMG_OPTIONS`, pyamg's ``weighting="local"``): no spectral-radius estimate
    (pyamg's restarted Arnoldi was 3.8 of the set-up's 5.3 s at 2 megapixels), nothing random
    (the global RNG's state does not matter), and CG takes as many iterations as with the
    estimate."""
    import pyamg

    from o3d_mvps.solver import linear

    M, b, _ = grid_system(shape=(80, 112))
    M = sp.csr_matrix(M)

    def iterations(preconditioner):
        return linear.pcg(M, b, np.zeros_like(b), 1e-8, 500, preconditioner)[1]

    np.random.seed(0)
    estimated = pyamg.smoothed_aggregation_solver(M, strength=linear.strength_options(M),
                                                  **{**linear.AMG_OPTIONS, "smooth": ("jacobi", {"omega": 4.0 / 3.0})})
    with_estimate = iterations(spla.LinearOperator(M.shape, lambda x: linear._v_cycle(estimated, 0, x), dtype=float))

    def refuse(*args, **kwargs):
        raise AssertionError("spectral radius estimated")

    monkeypatch.setattr(pyamg.aggregation.smooth, "approximate_spectral_radius", refuse)
    monkeypatch.setattr(pyamg.relaxation.smoothing, "approximate_spectral_radius", refuse)
    np.random.seed(1)
    first = linear.amg_preconditioner(M)
    np.random.seed(2)
    assert np.array_equal(first @ b, linear.amg_preconditioner(M) @ b)
    assert 5 <= iterations(first) <= with_estimate + 1  # measured: 8 and 8


def test_the_plain_aggregation_hierarchy_solves_a_depth_system_as_the_smoothed_one():
    """A static camera's depth steps (:func:`.linear.solve_spd` with ``plain=True``): pyamg's plain
    aggregation (:data:`.linear.PLAIN_AMG_OPTIONS`, no spectral radius, no candidate improvement)
    reaches the direct solution as the smoothed hierarchy does. Measured on the 120 x 160 disc:
    at CG's 1e-6 the A-norm error 1.6e-7 (smoothed 4.0e-7) in 8 iterations (smoothed 6); at the
    settled levels' 1e-2 a residual of 8.6e-3 in 2 (smoothed 2). Bounds: the residual at its
    tolerance, the A-norm error 10 times it, at most 2 more iterations than the smoothed
    hierarchy plus 1. Its tentative prolongation depends on the matrix's strong pattern alone:
    the same for the matrix scaled by 3."""
    import pyamg

    from o3d_mvps.solver import linear

    M, b, _ = grid_system(shape=(120, 160))
    M = sp.csr_matrix(M)
    direct = spla.spsolve(M.tocsc(), b)
    a_norm = np.sqrt(direct @ (M @ direct))
    for rtol in (1e-2, 1e-6):
        smoothed = solve_spd(M, b, rtol, 500)[1]
        x, iterations = solve_spd(M, b, rtol, 500, plain=True)
        assert np.linalg.norm(M @ x - b) <= rtol * np.linalg.norm(b)
        assert np.sqrt((x - direct) @ (M @ (x - direct))) < 10 * rtol * a_norm
        assert iterations <= smoothed + 3
    monkeypatch = pytest.MonkeyPatch()
    monkeypatch.setattr(pyamg.relaxation.smoothing, "approximate_spectral_radius",
                        lambda *a, **k: pytest.fail("spectral radius estimated"))
    try:
        first, scaled = linear.plain_aggregation(M), linear.plain_aggregation(sp.csr_matrix(3.0 * M))
    finally:
        monkeypatch.undo()
    assert len(first.levels) >= 2
    assert all((p.P != q.P).nnz == 0 for p, q in zip(first.levels[:-1], scaled.levels[:-1]))


def test_a_static_levels_depth_steps_take_the_plain_hierarchy_and_hold_s_transpose_s(monkeypatch):
    """Which hierarchy the driver's depth steps build: the plain one (:func:`.linear.plain_aggregation`)
    exactly where the poses are held at the identity (a static camera), the smoothed one on a
    moving capture (whose figures stay bit for bit); and S^T S is held between steps
    (:meth:`.pyramid.DepthPrior.hold_products`) only on a static camera's settled levels, and
    let go when the level ends."""
    import warnings

    from benchmarks.static import render
    from o3d_mvps import refine
    from o3d_mvps.solver import linear
    from o3d_mvps.solver.pyramid import DepthPrior

    prior = DepthPrior(sp.identity(4, format="csr"), np.ones(4), S=sp.csr_matrix(np.eye(4)[:3]))
    first = prior.StS
    prior.hold_products(True)
    prior.release_products()
    assert prior.StS is first
    prior.hold_products(False)
    assert "StS" not in prior.__dict__ and (prior.StS != first).nnz == 0
    built, holds = [], []
    for name in ("plain_aggregation", "smoothed_aggregation"):
        monkeypatch.setattr(linear, name, lambda M, f=getattr(linear, name), name=name: built.append(name) or f(M))
    hold = DepthPrior.hold_products
    monkeypatch.setattr(DepthPrior, "hold_products", lambda self, h: holds.append(h) or hold(self, h))
    monkeypatch.setattr(driver, "POINT_FIT_MAX_PIXELS", 1000)  # the 80x60 level settled
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        refine(render("quilt", frames=4, size=(80, 60), scale_factor=2, sensor="none", seed=0),
               RefineOptions(progress=False, levels=2))
    assert built and set(built) == {"plain_aggregation"} and True in holds and holds[-1] is False
    built.clear(), holds.clear()
    capture = render_capture("bunny", frames=3, scale_factor=2, size=(80, 60), light="led", seed=0)
    options = RefineOptions(levels=1, max_iterations=2, joint_pose_depth=False)
    driver.solve(problem_from_capture(capture, options, capture.groundtruth.poses)[0], options)
    assert built and set(built) == {"smoothed_aggregation"} and True not in holds


def test_the_depth_block_pattern_is_the_union_of_the_grams_patterns():
    """:func:`.normal_equations.depth_block_pattern`, one product of the stacked rows (stencils,
    D, S) with unit values, holds exactly the entries of the stencil's Gram, D^T D, S^T S and the
    diagonal (the sum of their products with absolute values it replaced), columns ascending."""
    from o3d_mvps.solver.normal_equations import depth_block_pattern

    def holed(H, W, scheme):  # a disc with holes and one-pixel spurs: one-sided and missing neighbours
        v, u = np.mgrid[:H, :W]
        mask = (u - W / 2) ** 2 / (0.45 * W) ** 2 + (v - H / 2) ** 2 / (0.45 * H) ** 2 < 1
        mask &= np.random.default_rng(1).uniform(size=(H, W)) > 0.15
        return masked_grid(mask, scheme)

    cases = [((40, 56), True, None), ((40, 56), False, None), ((128, 160), True, None),  # 128x160: 4 chunks of rows
             ((40, 56), True, "central"), ((40, 56), True, "forward")]
    for (H, W), smoothness, scheme in cases:
        grid = grid_system(shape=(H, W))[2] if scheme is None else holed(H, W, scheme)
        prior = depth_prior(grid, np.ones((H // 2, W // 2)), 2.0)
        smoothness = second_differences(grid) if smoothness else None
        fake = type("Prior", (), {"D": prior.D, "smoothness_pattern": smoothness})()
        indptr, indices = depth_block_pattern(grid, fake)
        Du, Dv = grid.difference_operators()
        touched = abs(Du) + abs(Dv) + sp.identity(grid.size, format="csr")
        union = touched.T @ touched + abs(prior.D).T @ abs(prior.D)
        if smoothness is not None:
            union = union + abs(smoothness).T @ abs(smoothness)
        union = sp.csr_matrix(union)
        union.sort_indices()
        np.testing.assert_array_equal(indptr, union.indptr)
        np.testing.assert_array_equal(indices, union.indices)


def test_the_priors_grams_are_those_of_the_csc_product_bit_for_bit():
    """:func:`.pyramid.gram` (the transpose made CSR, one CSR product) gives S^T S and D^T D of a
    weighted level exactly as ``(A.T @ A).tocsr()`` did: pattern, sorted columns and values."""
    from o3d_mvps.solver.pyramid import gram

    _, _, grid = grid_system()
    H, W = 40, 56
    prior = depth_prior(grid, np.ones((H // 2, W // 2)), 2.0)
    S = second_differences(grid)
    S = sp.csr_matrix(sp.diags(np.random.default_rng(0).uniform(0.1, 3.0, S.shape[0])) @ S)
    for A in (S, prior.D):
        expected, found = (A.T @ A).tocsr(), gram(A)
        assert found.format == "csr" and found.has_sorted_indices
        np.testing.assert_array_equal(found.indptr, expected.indptr)
        np.testing.assert_array_equal(found.indices, expected.indices)
        np.testing.assert_array_equal(found.data, expected.data)


def test_galerkin_product_keeps_entries_the_first_product_cancelled():
    """A first A whose stored zeros make some entries of A P and R A P sum to exactly 0 (scipy
    drops them) must not leave the held patterns short: a second A of the same pattern without
    those zeros gives R A P equal to scipy's (a pattern without them lost those entries and
    carried their sums into the next row)."""
    from types import SimpleNamespace

    from o3d_mvps.solver import linear

    rng = np.random.default_rng(3)
    N, n = 60, 12
    A2 = sp.random(N, N, density=0.15, random_state=4, format="csr") + sp.eye(N, format="csr")
    A2.sort_indices()
    A1 = A2.copy()
    A1.data[rng.random(A1.data.size) < 0.5] = 0.0  # stored zeros: the same pattern, cancelled products
    P = sp.random(N, n, density=0.1, random_state=5, format="csr")
    level = SimpleNamespace(P=P, R=P.T.tocsr())
    assert (A1 @ P).nnz < _structural_nnz(A1, P)  # scipy drops entries of the first A P
    linear._galerkin_product(level, A1)
    again = linear._galerkin_product(level, A2)
    assert np.array_equal(again.toarray(), (level.R @ (A2 @ P)).toarray())


def _structural_nnz(A, P) -> int:
    ones = [sp.csr_matrix((np.ones(M.nnz), M.indices, M.indptr), shape=M.shape) for M in (A, P)]
    return (ones[0] @ ones[1]).nnz
