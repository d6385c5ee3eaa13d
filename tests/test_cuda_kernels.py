"""The CUDA kernels (o3d_mvps.solver.cuda_kernels) against their CPU twins (o3d_mvps.solver.kernels)
on small random data: equal to float64 round-off (relative 1e-12), the log1p sum to the CPU's
float32 logarithms (1e-6).

On a GPU they run there; without one in numba's CUDA simulator (tests/conftest.py), which runs
the kernels as Python, one thread at a time: sizes stay small. The simulator compiles nothing, so
:func:`test_kernels_compile_to_ptx` compiles every kernel for the device (no GPU needed).
"""

import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import compile_cuda_kernels
from lighting_reference import weighted_lighting_sums
from o3d_mvps.solver import cuda_kernels, kernels

RNG = np.random.default_rng(11)
N_FRAMES, N_PIXELS, LAM = 3, 300, 0.1
#: a frame's pose (4, 4): a small rotation and translation
POSE = np.array([[0.999, -0.03, 0.02, 0.02], [0.03, 0.999, -0.01, -0.01], [-0.02, 0.01, 0.999, 0.03],
                 [0.0, 0.0, 0.0, 1.0]])


def assert_close(actual, expected, rtol=1e-12):
    """Equal to ``rtol`` relative, entries that cancel to ~0 to ``rtol`` of the array's largest."""
    expected = np.asarray(expected)
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=rtol * np.abs(expected).max(initial=0.0))


def copies(args) -> list:
    """Copies of the array arguments; scalars as they are (np.copy would make them 0-d arrays,
    which numba-cuda types as arrays: arithmetic with them does not compile on a GPU)."""
    return [np.copy(a) if isinstance(a, np.ndarray) else a for a in args]


def run_both(kernel_name, *args):
    """Call the CPU and the CUDA launcher ``kernel_name`` on copies of args: (CPU args, CUDA args)."""
    cpu, gpu = copies(args), copies(args)
    getattr(kernels, kernel_name)(*cpu)
    getattr(cuda_kernels, kernel_name)(*gpu)
    return cpu, gpu


def run_cpu(kernel_name, *args):
    """Call the CPU kernel ``kernel_name`` on copies of args (one with no CUDA twin any more: the
    reference of a fused kernel's test, or the host's path): the copies."""
    cpu = copies(args)
    getattr(kernels, kernel_name)(*cpu)
    return cpu


@pytest.fixture
def frames():
    residual = RNG.normal(size=(N_FRAMES, N_PIXELS, 3)) * 0.1
    usable = RNG.random((N_FRAMES, N_PIXELS)) > 0.2
    color = RNG.random((N_FRAMES, N_PIXELS, 3)).astype(np.float32)  # as the solver's warped colours
    shading = RNG.random((N_FRAMES, N_PIXELS))
    albedo = RNG.random((N_PIXELS, 3))
    return residual, usable, color, shading, albedo


@pytest.mark.parametrize("shared", [True, False])
def test_shading_residuals_match_cpu(frames, shared):
    _, usable, color, _, albedo = frames
    basis = RNG.random((1 if shared else N_FRAMES, N_PIXELS, 4))
    cpu, gpu = run_both("shading_residuals", color, albedo, basis, RNG.random((N_FRAMES, 4)), usable,
                        np.full((N_FRAMES, N_PIXELS), np.nan), np.full((N_FRAMES, N_PIXELS, 3), np.nan))
    assert_close(gpu[-2], cpu[-2])
    assert_close(gpu[-1], cpu[-1])


def test_led_irradiances_match_cpu():
    points = RNG.normal(size=(N_PIXELS, 3)) * 0.05 + [0.0, 0.0, 0.6]
    normals = RNG.normal(size=(N_PIXELS, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cpu, gpu = run_both("led_irradiances_into", normals, points, RNG.normal(size=(4, 3)) * 0.05,
                        np.full((4, N_PIXELS), np.nan))
    assert_close(gpu[-1], cpu[-1])


def test_led_point_gradients_match_cpu():
    points = RNG.normal(size=(N_PIXELS, 3)) * 0.05 + [0.0, 0.0, 0.6]
    normals = RNG.normal(size=(N_PIXELS, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cpu, gpu = run_both("led_point_gradients_into", RNG.random(4) + 0.1, normals, points,
                        RNG.normal(size=(4, 3)) * 0.05, np.full((4, N_PIXELS, 3), np.nan))
    assert np.isfinite(cpu[-1]).all() and (cpu[-1] == 0).any() and (cpu[-1] != 0).any()  # lit and unlit points
    assert_close(gpu[-1], cpu[-1])


@pytest.mark.parametrize("size", [1, 5000])
def test_log1p_square_sum_matches_cpu(size):
    """Float32 logarithms on both (the CPU's vectorised, the GPU's libdevice): 1e-6 relative. Its
    own generator: drawn from the module's, its values depended on which tests ran before (with
    ``-k`` one tiny sum, 1e-3, came out 5e-5 apart, float32 rounding of 1 + y^2)."""
    x = np.random.default_rng(size).normal(size=size) * 0.1
    expected = kernels.log1p_square_sum(x, 1.0 / LAM)
    assert cuda_kernels.log1p_square_sum(x, 1.0 / LAM) == pytest.approx(expected, rel=1e-6)


def test_both_modules_offer_the_same_launchers():
    for name in cuda_kernels.__all__:
        assert callable(getattr(kernels, name)) and callable(getattr(cuda_kernels, name))


def test_kernels_compile_to_ptx():
    """Every CUDA kernel compiles to PTX for sm_90 (numba's compiler and NVVM; no GPU needed): the
    simulator runs Python, so only this finds code the device cannot run. In a process of its own
    without NUMBA_ENABLE_CUDASIM (numba.cuda is the simulator in this one). NVVM comes with
    numba-cuda[cu12], which the ``dev`` extra installs (``make test``): no skip without it."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    script = Path(compile_cuda_kernels.__file__)
    # this checkout's o3d_mvps (the script's own folder, tests/, comes first on its sys.path)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(script.parents[1]), env.get("PYTHONPATH"))))
    done = subprocess.run([sys.executable, str(script), "9.0"], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode != compile_cuda_kernels.NO_NVVM, done.stdout + " (pip install -e '.[dev]')"
    assert done.returncode == 0, done.stdout + done.stderr
    compiled = {line.split()[0] for line in done.stdout.splitlines()}
    assert compiled == set(compile_cuda_kernels.SIGNATURES)


def test_warp_gradients_match_cpu():
    H, W = 30, 40
    K = np.array([[50.0, 0.0, 19.5], [0.0, 50.0, 14.5], [0.0, 0.0, 1.0]])
    points = RNG.normal(size=(N_PIXELS, 3)) * [0.3, 0.2, 0.3] + [0.0, 0.0, 0.6]
    cpu, gpu = run_both("warp_gradients", points, POSE, K,
                        RNG.random((H, W, 3)).astype(np.float32), *(np.full((N_PIXELS, 3), np.nan) for _ in range(3)))
    for result_gpu, result_cpu in zip(gpu[-3:], cpu[-3:]):  # frame points, gradients
        assert_close(result_gpu, result_cpu)
    assert np.abs(cpu[-1]).max() > 0.1


def test_warp_sample_matches_cpu():
    H, W = 30, 40
    K = np.array([[50.0, 0.0, 19.5], [0.0, 50.0, 14.5], [0.0, 0.0, 1.0]])
    points = RNG.normal(size=(N_PIXELS, 3)) * [0.3, 0.2, 0.3] + [0.0, 0.0, 0.6]
    points[:10, 2] = -0.1
    cpu, gpu = run_both("warp_sample", points, POSE, K,
                        RNG.random((H, W, 3)).astype(np.float32), RNG.random(N_PIXELS) > 0.1,
                        np.zeros((N_PIXELS, 3), np.float32), np.zeros(N_PIXELS, bool))
    np.testing.assert_array_equal(gpu[-1], cpu[-1])
    assert 0 < cpu[-1].sum() < N_PIXELS
    np.testing.assert_array_equal(gpu[-2], cpu[-2])  # float64 interpolation, both rounded to float32


def test_warp_sample_frames_matches_cpu_and_the_per_frame_kernel():
    """Every frame in one launch: the CUDA kernel equals its CPU twin, which equals
    warp_sample called a frame at a time (the host's loop)."""
    H, W, n = 30, 40, N_FRAMES
    K = np.array([[50.0, 0.0, 19.5], [0.0, 50.0, 14.5], [0.0, 0.0, 1.0]])
    points = RNG.normal(size=(N_PIXELS, 3)) * [0.3, 0.2, 0.3] + [0.0, 0.0, 0.6]
    poses = np.stack([POSE, np.eye(4), POSE @ POSE])
    images = RNG.random((n, H, W, 3)).astype(np.float32)
    visible = RNG.random((n, N_PIXELS)) > 0.1
    cpu, gpu = run_both("warp_sample_frames", points, poses, K, images, visible,
                        np.zeros((n, N_PIXELS, 3), np.float32), np.zeros((n, N_PIXELS), bool))
    np.testing.assert_array_equal(gpu[-1], cpu[-1])
    np.testing.assert_array_equal(gpu[-2], cpu[-2])
    for i in range(n):
        color, usable = np.zeros((N_PIXELS, 3), np.float32), np.zeros(N_PIXELS, bool)
        kernels.warp_sample(points, poses[i], K, images[i], visible[i], color, usable)
        np.testing.assert_array_equal(cpu[-1][i], usable)
        np.testing.assert_array_equal(cpu[-2][i], color)
    assert 0 < cpu[-1].sum() < n * N_PIXELS


def test_multigrid_kernels_match_cpu_and_the_sparse_formulas():
    """The multigrid's one-pass kernels: chebyshev_update (r - A v, scale d + diagonal r, x + d)
    and csr_multiply_add (y + alpha A v), CUDA against CPU against SciPy's product."""
    n = 60
    A = sp.random(n, n, density=0.1, random_state=3, format="csr") + sp.eye(n, format="csr")
    A.indices, A.indptr = A.indices.astype(np.int32), A.indptr.astype(np.int32)
    r, v, d, diagonal, x = RNG.normal(size=(5, n))
    cpu, gpu = run_both("chebyshev_update", A.indptr, A.indices, A.data, r, v, d, 0.7, diagonal, x,
                        np.zeros(n), np.zeros(n), np.zeros(n))
    r_new = r - A @ v
    d_new = 0.7 * d + diagonal * r_new
    for k, expected in zip((-3, -2, -1), (r_new, d_new, x + d_new)):
        assert_close(cpu[k], expected)
        assert_close(gpu[k], cpu[k])
    P = sp.random(n, 15, density=0.2, random_state=4, format="csr")
    P.indices, P.indptr = P.indices.astype(np.int32), P.indptr.astype(np.int32)
    c = RNG.normal(size=15)
    cpu, gpu = run_both("csr_multiply_add", P.indptr, P.indices, P.data, -1.0, c, x, np.zeros(n))
    assert_close(cpu[-1], x - P @ c)
    assert_close(gpu[-1], cpu[-1])


def test_fused_multigrid_kernels_match_cpu_and_the_sparse_formulas():
    """The V-cycle's fused passes: chebyshev_start (the smoother's first two steps from zero),
    restrict_residual (R (b - A x)) and prolong_restart (x + P c, then the smoother's restart),
    CUDA against CPU against SciPy's products."""
    n, n_coarse = 60, 15
    A = sp.random(n, n, density=0.1, random_state=5, format="csr") + sp.eye(n, format="csr")
    P = sp.random(n, n_coarse, density=0.2, random_state=6, format="csr")
    R = P.T.tocsr()
    for M in (A, P, R):
        M.indices, M.indptr = M.indices.astype(np.int32), M.indptr.astype(np.int32)
    b, first, diagonal, x = RNG.normal(size=(4, n))
    c = RNG.normal(size=n_coarse)
    cpu, gpu = run_both("chebyshev_start", A.indptr, A.indices, A.data, b, first, 0.7, diagonal, np.zeros(n),
                        np.zeros(n), np.zeros(n))
    r_new = b - A @ (first * b)
    d_new = 0.7 * first * b + diagonal * r_new
    for k, expected in zip((-3, -2, -1), (r_new, d_new, first * b + d_new)):
        assert_close(cpu[k], expected)
        assert_close(gpu[k], cpu[k])
    cpu, gpu = run_both("restrict_residual", R.indptr, R.indices, R.data, A.indptr, A.indices, A.data, b, x,
                        np.zeros(n_coarse))
    assert_close(cpu[-1], R @ (b - A @ x))
    assert_close(gpu[-1], cpu[-1])
    cpu, gpu = run_both("prolong_restart", A.indptr, A.indices, A.data, P.indptr, P.indices, P.data, b, x, c, first,
                        np.zeros(n), np.zeros(n), np.zeros(n))
    y = x + P @ c
    r_new = b - A @ y
    for k, expected in zip((-3, -2, -1), (r_new, first * r_new, y + first * r_new)):
        assert_close(cpu[k], expected)
        assert_close(gpu[k], cpu[k])


def test_cg_passes_match_cpu_and_textbook_cg():
    """The CG passes (cg_start, cg_scalars, cg_update: Chronopoulos and Gear's recurrences, the
    dot products of a pass summed by the blocks and the last block to finish) on 300 rows (3
    blocks on the GPU): CUDA against CPU to round-off, state included, after 1-4 iterations, and
    the iterates against textbook CG (s = A p formed, two separate dot products) to 1e-10; the
    block counter back at zero after each pass, w = A z formed in the pass or given."""
    n = N_PIXELS
    B = sp.random(n, n, density=0.02, random_state=7, format="csr")
    A = (B @ B.T + sp.eye(n)).tocsr()
    A.indices, A.indptr = A.indices.astype(np.int32), A.indptr.astype(np.int32)
    b, inv_diag = RNG.normal(size=n), 1.0 / A.diagonal()
    runs = {}
    for name, module in (("cpu", kernels), ("cuda", cuda_kernels)):
        for with_matrix in (True, False):
            state, partial = np.zeros(kernels.CG_STATE), np.zeros((kernels.REDUCTION_BLOCKS, 2))
            counter = np.zeros(1, np.int32)
            x, r, p, s, w = (np.full(n, np.nan) for _ in range(5))
            module.cg_start(b, x, r, p, s, True, 1e-20, state, partial, counter)
            iterates = []
            for _ in range(4):
                z = inv_diag * r
                if not with_matrix:
                    w = A @ z
                module.cg_scalars(A.indptr, A.indices, A.data, with_matrix, z, r, w, state, partial, counter)
                module.cg_update(z, w, p, s, x, r, state, partial, counter)
                assert counter[0] == 0
                iterates.append((x.copy(), r.copy(), state.copy()))
            runs[name, with_matrix] = iterates
    # textbook PCG (Jacobi), the same iterations
    x, r = np.zeros(n), b.copy()
    z = inv_diag * r
    p, rz = z.copy(), r @ z
    for k in range(4):
        q = A @ p
        alpha = rz / (p @ q)
        x, r = x + alpha * p, r - alpha * q
        for (name, with_matrix), iterates in runs.items():
            x_k, r_k, state_k = iterates[k]
            assert_close(x_k, x, rtol=1e-10)
            assert state_k[kernels.CG_ITERATIONS] == k + 1 and state_k[kernels.CG_ACTIVE] == 1.0
            assert state_k[kernels.CG_RR] == pytest.approx(r @ r, rel=1e-9)
            assert state_k[kernels.CG_THRESHOLD] == pytest.approx(1e-20 * (b @ b), rel=1e-12)
            cpu_x, cpu_r, cpu_state = runs["cpu", with_matrix][k]
            assert_close(x_k, cpu_x)
            assert_close(r_k, cpu_r)
            assert_close(state_k, cpu_state)
        z = inv_diag * r
        rz, rz_previous = r @ z, rz
        p = z + (rz / rz_previous) * p


def test_cg_passes_stop_at_convergence_and_idle_after():
    """Once the residual passes the threshold the state says converged and inactive, and the
    passes that follow change nothing (nor count an iteration)."""
    n = 200
    A = sp.diags(RNG.uniform(1.0, 2.0, size=n), format="csr")
    A.indices, A.indptr = A.indices.astype(np.int32), A.indptr.astype(np.int32)
    b = RNG.normal(size=n)
    for module in (kernels, cuda_kernels):
        state, partial, counter = np.zeros(kernels.CG_STATE), np.zeros((kernels.REDUCTION_BLOCKS, 2)), np.zeros(1, np.int32)
        x, r, p, s, w = (np.zeros(n) for _ in range(5))
        module.cg_start(b, x, r, p, s, True, 1e-16, state, partial, counter)
        for step in range(3):  # Jacobi on a diagonal matrix: exact after one iteration
            z = r / A.diagonal()
            module.cg_scalars(A.indptr, A.indices, A.data, True, z, r, w, state, partial, counter)
            module.cg_update(z, w, p, s, x, r, state, partial, counter)
            if step == 0:
                after_one = (x.copy(), state.copy())
        assert state[kernels.CG_ACTIVE] == 0.0 and state[kernels.CG_ITERATIONS] == 1
        assert state[kernels.CG_STATUS] == 4 + 1  # one iteration, converged
        np.testing.assert_array_equal(x, after_one[0])
        np.testing.assert_array_equal(state, after_one[1])
        assert_close(x, b / A.diagonal())


def multigrid_grid(shape=(22, 26)):
    """The disc of pixels of :func:`multigrid_system`."""
    from o3d_mvps.model.normals import masked_grid

    H, W = shape
    v, u = np.mgrid[:H, :W]
    return masked_grid((u - W / 2) ** 2 + (v - H / 2) ** 2 < (0.45 * min(H, W)) ** 2)


def multigrid_system(shape=(22, 26)):
    """(A, hierarchy): an SPD matrix on a disc of pixels (a 5-point Laplacian plus a random
    positive diagonal) and its multigrid (:func:`krylov.multigrid_preconditioner`, host) of three
    levels (305, 87, 36 unknowns) above a dense coarsest of 16."""
    from o3d_mvps.model.normals import masked_grid
    from o3d_mvps.solver import krylov

    H, W = shape
    v, u = np.mgrid[:H, :W]
    grid = masked_grid((u - W / 2) ** 2 + (v - H / 2) ** 2 < (0.45 * min(H, W)) ** 2)
    index = -np.ones(shape, int)
    index[grid.v, grid.u] = np.arange(grid.size)
    rows, cols = [], []
    for du, dv in ((1, 0), (0, 1)):
        inside = (grid.u + du < W) & (grid.v + dv < H)
        j = index[np.minimum(grid.v + dv, H - 1), np.minimum(grid.u + du, W - 1)]
        keep = inside & (j >= 0)
        rows.append(np.arange(grid.size)[keep])
        cols.append(j[keep])
    i, j = np.concatenate(rows), np.concatenate(cols)
    L = sp.coo_matrix((np.ones(i.size), (i, j)), shape=(grid.size, grid.size))
    L = L + L.T
    A = (sp.diags(np.asarray(L.sum(axis=1)).ravel() + RNG.uniform(0.01, 0.1, grid.size)) - L).tocsr()
    A.indices, A.indptr = A.indices.astype(np.int32), A.indptr.astype(np.int32)
    hierarchy = krylov.multigrid_preconditioner(A, krylov.pixel_prolongations(grid.u, grid.v, max_coarse=30))
    for level in hierarchy.levels:
        for m in (level.A, level.P, level.R):
            m.indices, m.indptr = m.indices.astype(np.int32), m.indptr.astype(np.int32)
    return A, hierarchy


def device_multigrid(A, grid, simulated: bool):
    """:func:`krylov.multigrid_preconditioner` of A on the device: its set-up launch run by the
    CUDA kernel (simulated: on a GPU with CuPy's arrays, else in numba's simulator on the CuPy
    stand-in of tests/cupy_emulation.py) or by its CPU twin (on the stand-in); the packed arrays
    as NumPy arrays, the layout and the stand-in's launches (None on a GPU)."""
    import cupy_emulation as cp
    import numba
    from contextlib import nullcontext

    from benchmarks.gpu import _cpu_kernels_as_cuda_kernels
    from o3d_mvps.solver import krylov

    if simulated and not numba.config.ENABLE_CUDASIM:  # a GPU: CuPy's arrays for the CUDA kernel
        import cupy
        import cupyx.scipy.sparse

        prolongations = krylov.pixel_prolongations(cupy.asarray(grid.u), cupy.asarray(grid.v), max_coarse=30)
        multigrid = krylov.multigrid_preconditioner(cupyx.scipy.sparse.csr_matrix(A), prolongations)
        return [cupy.asnumpy(a) for a in multigrid.packed.arrays], multigrid.packed.layout, None
    with cp.installed(), nullcontext() if simulated else _cpu_kernels_as_cuda_kernels(cp):
        prolongations = krylov.pixel_prolongations(cp.asarray(grid.u), cp.asarray(grid.v), max_coarse=30)
        before = cp.operations["kernel"]
        multigrid = krylov.multigrid_preconditioner(cp.sparse.csr_matrix(A), prolongations)
        launches = cp.operations["kernel"] - before
        return [cp.host_data(a) for a in multigrid.packed.arrays], multigrid.packed.layout, launches


def test_multigrid_setup_matches_cpu_and_the_host_hierarchy():
    """The device multigrid's set-up in one launch (kernels.multigrid_setup: every level's
    D^-1 / bound, the Galerkin operators P^T A P, the coarsest's inverse): CUDA (the simulator runs
    one block) against its CPU twin to round-off; both against the host's hierarchy (SciPy's
    products, NumPy's inverse): the scalings and the coarse operators' patterns and values equal
    (measured: bit for bit, the same sums), the coarsest inverse to 1e-13 (measured 1.2e-15)."""
    A, hierarchy = multigrid_system()
    grid = multigrid_grid()
    (cpu, layout, launches), (gpu, _, _) = (device_multigrid(A, grid, simulated) for simulated in (False, True))
    assert launches == 1 and len(hierarchy.levels) == 3
    for k, level in enumerate(hierarchy.levels):
        offset, n = layout[kernels.MG_FIELDS * k + kernels.MG_VEC], layout[kernels.MG_FIELDS * k + kernels.MG_N]
        np.testing.assert_array_equal(cpu[9][offset:offset + n], level.smoother.inv_diag)
        assert_close(gpu[9][offset:offset + n], cpu[9][offset:offset + n])
        if k == 0:
            continue
        start, nz = layout[kernels.MG_FIELDS * k + kernels.MG_A_PTR], layout[kernels.MG_FIELDS * k + kernels.MG_A_NZ]
        for arrays in (cpu, gpu):
            indptr = arrays[0][start:start + n + 1]
            C = sp.csr_matrix((arrays[2][nz:nz + indptr[-1]], arrays[1][nz:nz + indptr[-1]], indptr), shape=(n, n))
            assert C.has_sorted_indices and C.nnz == level.A.nnz
            np.testing.assert_array_equal(C.indices, level.A.indices)
            assert_close(C.data, level.A.data)
    assert_close(cpu[10], hierarchy.coarse_inverse, rtol=1e-13)
    np.testing.assert_array_equal(cpu[10], cpu[10].T)
    assert_close(gpu[10], cpu[10])


def test_multigrid_cg_matches_cpu_the_host_cycle_and_host_pcg():
    """multigrid_cg (the V-cycle and CG in one cooperative launch; the simulator runs one block):
    CUDA against CPU to round-off; its V-cycle alone (no CG step) against the host's
    :class:`krylov.Multigrid` (SciPy's products) and its CG iterations, from one launch or two,
    with w = A z in the kernel (also for A + C U^T, a Schur complement's low-rank term) or given,
    against the host's :func:`krylov.pcg` after as many; CG's start by cg_start or in the first
    launch."""
    from o3d_mvps.solver import krylov

    A, hierarchy = multigrid_system()
    assert len(hierarchy.levels) == 3
    packed = krylov.pack_hierarchy(hierarchy.levels, hierarchy.coarse_inverse, 3)
    n = A.shape[0]
    b = RNG.normal(size=n)
    expected_z = hierarchy(b)
    K = 5  # the low-rank term of a Schur complement A + C U^T (C = -U H^-1: SPD for H = 4 I, U U^T small)
    U = RNG.normal(size=(n, K)) * 0.05
    C = -U / 4.0
    S = A.toarray() + C @ U.T
    for steps, with_matrix, low_rank in (((0,), True, False), ((3,), True, False), ((1, 2), True, False),
                                         ((0, 1, 1, 1), False, False), ((2, 1), True, True)):
        u_t, coupled = (np.ascontiguousarray(U.T), np.ascontiguousarray(C)) if low_rank else (np.zeros((0, 0)),) * 2
        results = {}
        for name, module in (("cpu", kernels), ("cuda", cuda_kernels)):
            arrays = [np.copy(a) for a in packed.arrays]
            work = np.full((kernels.MG_ROWS, packed.unknowns), np.nan)
            r, z = work[kernels.MG_B, :n], work[kernels.MG_XU, :n]
            state, partial = np.zeros(kernels.CG_STATE), np.zeros((kernels.REDUCTION_BLOCKS, 2))
            x, p, s, w = (np.full(n, np.nan) for _ in range(4))
            begin = len(steps) % 2 == 0  # CG's start in the first launch, else cg_start's own
            if not begin:
                module.cg_start(b, x, r, p, s, True, 1e-30, state, partial, np.zeros(1, np.int32))
            for k, n_steps in enumerate(steps):
                if not with_matrix:
                    w = A @ z  # the operator's product between launches
                t_partial, t = np.zeros((-(-n // kernels.LOW_RANK_CHUNK), u_t.shape[0])), np.zeros(u_t.shape[0])
                module.multigrid_cg(n_steps, k == 0, with_matrix, A.indptr, A.indices, A.data, *arrays, work, x, p, s,
                                    w, u_t, coupled, t_partial, t, packed.layout, packed.levels, packed.cheb,
                                    begin and k == 0, b, True, 1e-30, state, np.zeros((kernels.COOPERATIVE_BLOCKS, 4)))
            results[name] = (x.copy(), z.copy(), state.copy())
        (x, z, state), (x_gpu, z_gpu, state_gpu) = results["cpu"], results["cuda"]
        assert_close(z_gpu, z)
        assert_close(state_gpu, state)
        if steps == (0,):
            assert_close(z, expected_z)  # the cycle, not yet a CG step
            assert state[kernels.CG_ITERATIONS] == 0
            continue
        assert_close(x_gpu, x)
        system = spla.aslinearoperator(S) if low_rank else A
        host_x, iterations, _ = krylov.pcg(system, b, None, 1e-15, 3, hierarchy)
        assert iterations == 3 == state[kernels.CG_ITERATIONS]
        assert_close(x, host_x, rtol=1e-11)
def test_ridge_solves_match_numpy_and_cpu():
    """The batched small SPD solves (one thread per system on a GPU): each system equals NumPy's
    solve of ``A + ridge trace(A) I``; a zero, a non-finite and an indefinite system are not
    solved (NaN, solved 0), and with a fallback a semidefinite one takes its diagonal shift."""
    k, ridge = 6, 1e-9
    M = np.random.default_rng(6).normal(size=(5, k, k))
    A = M @ M.transpose(0, 2, 1)
    A[2], A[3] = 0.0, np.nan
    A[4] = np.diag([1.0, -1.0, 1.0, 1.0, 1.0, 1.0])
    B = RNG.normal(size=(5, k, 2))
    cpu, gpu = run_both("ridge_solves", A, B, ridge, 0.0, np.zeros_like(A), np.zeros_like(B), np.zeros(5))
    for i in (0, 1):
        expected = np.linalg.solve(A[i] + ridge * np.trace(A[i]) * np.eye(k), B[i])
        assert_close(cpu[5][i], expected, rtol=1e-10)
        # a GPU contracts a * b + c into one rounding (FMA), the CPU does not: the solves differ
        # by round-off times the condition number (an H100: 2.4e-11 of the largest entry on an
        # earlier, worse conditioned draw; the simulator: none); bounded by 1e-14 cond (here 104, 26)
        assert_close(gpu[5][i], cpu[5][i], rtol=max(1e-12, 1e-14 * np.linalg.cond(A[i])))
    np.testing.assert_array_equal(cpu[6], [1.0, 1.0, 0.0, 0.0, 0.0])
    assert np.isnan(cpu[5][2:]).all()
    np.testing.assert_array_equal(gpu[6], cpu[6])
    assert np.isnan(gpu[5][2:]).all()
    # semidefinite: not positive definite without a ridge, solved with the fallback shift 1e-6 max|diag|
    S = np.diag([4.0, 0.0, 1.0])[None]
    _, (_, _, _, _, _, X, solved) = run_both("ridge_solves", S, np.ones((1, 3, 1)), 0.0, 1e-6, np.zeros_like(S),
                                            np.zeros((1, 3, 1)), np.zeros(1))
    assert solved[0] == 1.0
    assert_close(X[0, :, 0], 1.0 / (np.diag(S[0]) + 4e-6))


def test_led_trial_sums_match_the_formula_and_cpu():
    """The LED offset's step and line-search trials in one pass: the step's negative x solves
    (H + 1e-9 trace(H) I) x = g as the host's ridge_solve does (last row, with g), and row k of
    the sums adds up to ``sum log(1 + (r / lam)^2)`` of the residuals ``I - rho (l_0 + l_1
    max(0, <n, v>))`` over usable pixels, the LED at offset ``start - 2^-k x`` (float32
    logarithms, as the GPU's energy), CPU and CUDA alike; the LED's positions as
    LEDLight.positions gives them."""
    from o3d_mvps.solver.lighting import LEDLight
    from o3d_mvps.solver.linear import ridge_solve

    n, N, K = 3, N_PIXELS, 4
    normals = RNG.normal(size=(N, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = RNG.normal(size=(N, 3)) * 0.1 + [0.0, 0.0, 0.6]
    poses = np.stack([np.eye(4), POSE, POSE @ POSE])
    M = RNG.normal(size=(3, 3))
    H, g = (M @ M.T)[None] * 1e4, RNG.normal(size=(1, 3, 1)) * 1e2
    start, x = np.array([0.02, -0.01, 0.005]), -ridge_solve(H[0], -g[0, :, 0])
    color = RNG.random((n, N, 3)).astype(np.float32)
    usable = RNG.random((n, N)) > 0.2
    albedo, lights = RNG.random((N, 3)), np.abs(RNG.normal(size=(n, 2))) * [0.2, 0.03]
    args = (color, usable, albedo, normals, points, poses, start, H, g, lights, 1.0 / LAM)
    for single in (False, True):
        cpu = np.zeros((K + 1, kernels.trial_blocks(n, N)))
        gpu = np.zeros((K + 1, cuda_kernels.trial_blocks(n, N)))
        kernels.led_trial_sums(*args, single, cpu)
        cuda_kernels.led_trial_sums(*args, single, gpu)
        np.testing.assert_array_equal(cpu[K, :7], np.r_[x, 1.0, g[0, :, 0]])
        # the step's solve: bit for bit in the simulator; a GPU's fused multiply-adds part it by
        # round-off times the condition number (an H200: 4.1e-15 relative at cond(H) 246; the shared
        # RNG draws cond 20 to 250 by which tests ran before)
        if numba.config.ENABLE_CUDASIM:
            np.testing.assert_array_equal(gpu[K, :7], cpu[K, :7])
        else:
            assert_close(gpu[K, :7], cpu[K, :7], rtol=1e-14 * np.linalg.cond(H[0]))
        for k in range(K):
            positions = LEDLight(start - 0.5**k * x).positions(poses)
            np.testing.assert_array_equal(positions, np.einsum("mji,mj->mi", poses[:, :3, :3],
                                                               start - 0.5**k * x - poses[:, :3, 3]))
            d = positions[:, None, :] - points  # (n, N, 3)
            r2 = (d * d).sum(axis=-1)
            basis = np.maximum((normals * d).sum(axis=-1) / (r2 * np.sqrt(r2)), 0.0)
            residual = color - albedo * (lights[:, :1] + basis * lights[:, 1:])[..., None]
            if single:
                residual = residual.astype(np.float32)
            y = (residual[usable] / LAM).astype(np.float32)
            expected = np.log(np.float32(1.0) + y * y).astype(np.float64).sum()
            assert_close(cpu[k].sum(), expected, rtol=1e-6)
        assert len(set(cpu[:K].sum(axis=1))) == K  # the trials differ
        # the simulator takes Python's float64 logarithm of each float32 term: ~1e-9 of the sums
        assert_close(gpu[:K].sum(axis=1), cpu[:K].sum(axis=1), rtol=1e-8)
        # current: the last trial row is the offset ``start`` itself (gpueval2), the others unchanged
        now_cpu, now_gpu = np.zeros_like(cpu), np.zeros_like(gpu)
        kernels.led_trial_sums(*args, single, now_cpu, current=True)
        cuda_kernels.led_trial_sums(*args, single, now_gpu, current=True)
        np.testing.assert_array_equal(now_cpu[:K - 1], cpu[:K - 1])
        np.testing.assert_array_equal(now_cpu[K], cpu[K])
        residual = color - albedo * (lights[:, :1] + np.maximum(LEDLight(start).irradiances(normals, points, poses),
                                                                0.0) * lights[:, 1:])[..., None]
        y = (residual.astype(np.float32 if single else np.float64)[usable] / LAM).astype(np.float32)
        assert_close(now_cpu[K - 1].sum(), np.log(np.float32(1.0) + y * y).astype(np.float64).sum(), rtol=1e-6)
        assert_close(now_gpu[:K].sum(axis=1), now_cpu[:K].sum(axis=1), rtol=1e-8)


def test_twist_system_matches_numpy_and_cpu():
    """The joint step's twist matrix from its sums: a frame is kept where its Gram's condition
    number (Jacobi eigenvalues) is at most 1e12 as NumPy's ``cond`` says (here 1e3 and 1e15
    apart from it, and a singular one), H = blockdiag(Grams) - downdate over the kept frames,
    identity rows and zero right-hand sides for the others (the host's joint step; the GPU's is
    joint_twist_system, below)."""
    m = 3
    grams = np.zeros((m, 6, 6))
    for f, spread in enumerate((-1.5, -7.5)):
        M = RNG.normal(size=(6, 6)) * np.logspace(0, spread, 6)
        grams[f] = np.triu(M @ M.T)
    grams[2] = np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 0.0])
    conditions = [np.linalg.cond(g + np.triu(g, 1).T) for g in grams]
    assert conditions[0] < 1e9 and conditions[1] > 1e14
    D = RNG.normal(size=(6 * m, 6 * m)) * 1e-3
    rhs_frames, rhs_projection = RNG.normal(size=6 * m), RNG.normal(size=6 * m)
    args = (grams, rhs_frames, rhs_projection, D @ D.T, kernels.MAX_TWIST_CONDITION, np.zeros((m, 6, 6)),
            np.zeros(m), np.zeros((6 * m, 6 * m)), np.zeros(6 * m), np.ones((6 * m, 6 * m)))
    cpu = run_cpu("twist_system", *args)
    np.testing.assert_array_equal(cpu[6], [1.0, 0.0, 0.0])
    expected = np.eye(6 * m)
    expected[:6, :6] = grams[0] + np.triu(grams[0], 1).T - (D @ D.T)[:6, :6]
    np.testing.assert_array_equal(cpu[7], expected)
    np.testing.assert_array_equal(cpu[8], np.r_[(rhs_frames + rhs_projection)[:6], np.zeros(12)])
    np.testing.assert_array_equal(cpu[9], -np.diag(np.r_[np.ones(6), np.zeros(12)]))


# --- the data term's evaluation in one launch (gpueval) -----------------------------------------
def _level_data(led: bool):
    """A small level: a masked grid, z (N,), K, 3 frames (poses, float32 images, visibility),
    albedo, lights (n, 2 or 4), the LED's offset, a block-average D with z0 and second
    differences S (int32 CSR, as on a GPU)."""
    from o3d_mvps.model.normals import masked_grid
    from o3d_mvps.solver.pyramid import depth_prior
    from o3d_mvps.solver.smoothness import second_differences

    H, W = 24, 32
    yy, xx = np.mgrid[0:H, 0:W]
    grid = masked_grid(((yy - 11.5) ** 2 / 100 + (xx - 15.5) ** 2 / 196) < 1.0)
    rng = np.random.default_rng(5)
    z = 0.6 + 0.01 * np.sin(grid.u / 3.0) + 0.004 * grid.v / H + rng.normal(size=grid.size) * 1e-4
    K = np.array([[40.0, 0.0, 15.5], [0.0, 40.0, 11.5], [0.0, 0.0, 1.0]])
    poses = np.stack([np.eye(4), POSE, POSE @ POSE])
    images = rng.random((3, H, W, 3)).astype(np.float32)
    visible = rng.random((3, grid.size)) > 0.1
    albedo = rng.random((grid.size, 3))
    lights = np.stack([[0.2, 0.36]] * 3) * [1.0, 1.0 + rng.random()] if led else rng.normal(size=(3, 4)) * 0.5
    prior = depth_prior(grid, rng.random((H // 2, W // 2)) * 0.01 + 0.6, 2.0)
    csr = lambda A: (A.indptr.astype(np.int32), A.indices.astype(np.int32), A.data)  # noqa: E731
    S = second_differences(grid)
    return grid, z, K, poses, images, visible, albedo, lights, (0.03, -0.02, 0.0), prior, csr(prior.D), csr(S), S


def _array_formulas(grid, z, K, poses, images, visible, albedo, lights, offset, led):
    """The CPU path's evaluation of the same level by its array functions: usable (n, N) and the
    float32 residuals (n, N, 3)."""
    from o3d_mvps.model.camera import backproject
    from o3d_mvps.model.normals import unit_normals
    from o3d_mvps.model.shading import sh_basis
    from o3d_mvps.solver.lighting import LEDLight

    points = backproject(z, K, grid.u.astype(np.float64), grid.v.astype(np.float64))
    normals, _ = unit_normals(grid, z, K)
    n, N = visible.shape
    color, usable = np.zeros((n, N, 3), np.float32), np.zeros((n, N), bool)
    kernels.warp_sample_frames(points, poses, K, images, visible, color, usable)
    basis = (LEDLight(np.array(offset)).bases(normals, points, poses, dtype=np.float32) if led
             else sh_basis(normals)[None].astype(np.float32))
    shading, residual = np.zeros((n, N), np.float32), np.zeros((n, N, 3), np.float32)
    kernels.shading_residuals(color, albedo, basis, lights, usable, shading, residual)
    return usable, residual, color, basis


@pytest.mark.parametrize("led", [True, False])
def test_energy_partials_match_cpu_and_the_array_formulas(led):
    """One pass over every frame, pixel and prior row: the CUDA kernel's sums equal its CPU twin's
    (data 1e-6: the float32 logarithms, the simulator's Python ones in float64; prior 1e-12),
    which equal the array path's residuals' robust sum and the prior's energy; usable exactly."""
    grid, z, K, poses, images, visible, albedo, lights, offset, prior, D, S, S_matrix = _level_data(led)
    usable_ref, residual, *_ = _array_formulas(grid, z, K, poses, images, visible, albedo, lights, offset, led)
    assert 0 < usable_ref.sum() < usable_ref.size
    tau, mu, scale = 3.0, 0.5, 1.0 / LAM
    d = prior.D @ z - prior.z0
    prior_ref = tau * (d @ d) + mu * np.sum((S_matrix @ z) ** 2)
    data_ref = kernels.log1p_square_sum(residual.ravel(), scale)
    grid_arrays = [np.ascontiguousarray(a) for a in (grid.u, grid.v, grid.fwd_u, grid.bwd_u, grid.wf_u, grid.wb_u,
                                                        grid.fwd_v, grid.bwd_v, grid.wf_v, grid.wb_v)]
    n, N = visible.shape
    args = [z, *grid_arrays, K, poses, images, visible, albedo, lights, led, *offset, scale, True, *D, prior.z0, *S,
            tau, mu, np.zeros((n, N), bool), np.full((3, 2), np.nan)]  # three blocks on the GPU
    cpu, gpu = run_both("energy_partials", *args)
    np.testing.assert_array_equal(cpu[-2], usable_ref)
    np.testing.assert_array_equal(gpu[-2], usable_ref)
    assert cpu[-1][:, 0].sum() == pytest.approx(data_ref, rel=1e-9)
    assert cpu[-1][:, 1].sum() == pytest.approx(prior_ref, rel=1e-12)
    assert gpu[-1][:, 0].sum() == pytest.approx(data_ref, rel=1e-6)
    assert gpu[-1][:, 1].sum() == pytest.approx(prior_ref, rel=1e-12)
    # without the prior (tau = mu = 0): the data term alone
    args[-4:-2] = 0.0, 0.0
    cpu, gpu = run_both("energy_partials", *args)
    assert not cpu[-1][:, 1].any() and not gpu[-1][:, 1].any()
    assert gpu[-1][:, 0].sum() == pytest.approx(data_ref, rel=1e-6)


def test_evaluation_partials_match_cpu_and_the_array_formulas():
    """Residuals and shading as shading_residuals writes them, their robust sum and the prior's
    energy in one pass, on the CPU and the GPU; on no frames the prior alone."""
    led = True
    grid, z, K, poses, images, visible, albedo, lights, offset, prior, D, S, S_matrix = _level_data(led)
    usable, residual, color, basis = _array_formulas(grid, z, K, poses, images, visible, albedo, lights, offset, led)
    tau, mu, scale = 3.0, 0.5, 1.0 / LAM
    d = prior.D @ z - prior.z0
    prior_ref = tau * (d @ d) + mu * np.sum((S_matrix @ z) ** 2)
    n, N = usable.shape
    cpu, gpu = run_both("evaluation_partials", color, albedo, basis, lights, usable,
                        np.full((n, N), np.nan, np.float32), np.full((n, N, 3), np.nan, np.float32), scale, *D,
                        prior.z0, *S, tau, mu, z, np.full((2, 2), np.nan))
    for out in (cpu, gpu):
        np.testing.assert_array_equal(out[6], residual)
        assert out[-1][:, 1].sum() == pytest.approx(prior_ref, rel=1e-12)
    assert cpu[-1][:, 0].sum() == pytest.approx(kernels.log1p_square_sum(residual.ravel(), scale), rel=1e-9)
    assert gpu[-1][:, 0].sum() == pytest.approx(cpu[-1][:, 0].sum(), rel=1e-6)
    empty = (np.zeros((0, N, 3), np.float32), albedo, np.zeros((0, N, 2), np.float32), np.zeros((0, 2)),
             np.zeros((0, N), bool), np.zeros((0, N), np.float32), np.zeros((0, N, 3), np.float32))
    cpu, gpu = run_both("evaluation_partials", *empty, scale, *D, prior.z0, *S, tau, mu, z, np.full((1, 2), np.nan))
    for out in (cpu, gpu):
        assert out[-1][0, 0] == 0.0 and out[-1][0, 1] == pytest.approx(prior_ref, rel=1e-12)


def test_led_fields_match_cpu():
    points = RNG.normal(size=(N_PIXELS, 3)) * 0.05 + [0.0, 0.0, 0.6]
    normals = RNG.normal(size=(N_PIXELS, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cpu, gpu = run_both("led_fields_into", RNG.random(4) + 0.1, normals, points, RNG.normal(size=(4, 3)) * 0.05,
                        np.full((4, N_PIXELS, 3), np.nan))
    assert np.isfinite(cpu[-1]).all() and (cpu[-1] == 0).any() and (cpu[-1] != 0).any()  # lit and unlit points
    assert_close(gpu[-1], cpu[-1])


@pytest.mark.parametrize("led", [True, False])
def test_evaluate_partials_match_cpu_and_the_array_formulas(led):
    """An evaluation in one pass: points, normals, dA, warped colours, usable, bases, shading and
    float32 residuals as the array functions make them (to round-off; the samples and the masks
    exactly), and the sums of energy_partials; the CUDA kernel equal to its CPU twin."""
    from o3d_mvps.model.camera import backproject
    from o3d_mvps.model.normals import unit_normals

    grid, z, K, poses, images, visible, albedo, lights, offset, prior, D, S, S_matrix = _level_data(led)
    usable_ref, residual_ref, color_ref, basis_ref = _array_formulas(grid, z, K, poses, images, visible, albedo,
                                                                     lights, offset, led)
    normals_ref, dA_ref = unit_normals(grid, z, K)
    tau, mu, scale = 3.0, 0.5, 1.0 / LAM
    d = prior.D @ z - prior.z0
    prior_ref = tau * (d @ d) + mu * np.sum((S_matrix @ z) ** 2)
    grid_arrays = [np.ascontiguousarray(a) for a in (grid.u, grid.v, grid.fwd_u, grid.bwd_u, grid.wf_u, grid.wb_u,
                                                        grid.fwd_v, grid.bwd_v, grid.wf_v, grid.wb_v)]
    n, N = visible.shape
    nan = lambda *shape, dtype=np.float64: np.full(shape, np.nan, dtype)  # noqa: E731
    cpu, gpu = run_both("evaluate_partials", z, *grid_arrays, K, poses, images, visible, albedo, lights, led, *offset,
                        scale, True, *D, prior.z0, *S, tau, mu, nan(N, 3), nan(N, 3), nan(N),
                        nan(n, N, 3, dtype=np.float32), np.zeros((n, N), bool),
                        nan(*basis_ref.shape, dtype=np.float32), nan(n, N, dtype=np.float32),
                        nan(n, N, 3, dtype=np.float32), nan(3, 2))
    for out in (cpu, gpu):
        points, normals, dA, color, usable, basis, shading, residual, partial = out[-9:]
        assert_close(points, backproject(z, K, grid.u.astype(np.float64), grid.v.astype(np.float64)))
        assert_close(normals, normals_ref)
        assert_close(dA, dA_ref)
        np.testing.assert_array_equal(color, color_ref)
        np.testing.assert_array_equal(usable, usable_ref)
        assert_close(basis, basis_ref, rtol=1e-6)  # float32 of float64 values equal to round-off
        assert_close(residual, residual_ref, rtol=1e-6)
        assert partial[:, 1].sum() == pytest.approx(prior_ref, rel=1e-12)
        assert partial[:, 0].sum() == pytest.approx(kernels.log1p_square_sum(residual_ref.ravel(), scale), rel=1e-6)
    for a, b in zip(cpu[-9:-1], gpu[-9:-1]):
        np.testing.assert_array_equal(a, b) if a.dtype == bool else assert_close(b, a)


def test_led_shading_jacobians_match_cpu():
    points = RNG.normal(size=(N_PIXELS, 3)) * 0.05 + [0.0, 0.0, 0.6]
    normals = RNG.normal(size=(N_PIXELS, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    rotations = np.stack([np.eye(3), POSE[:3, :3], POSE[:3, :3].T, POSE[:3, :3] @ POSE[:3, :3]])
    cpu, gpu = run_both("led_shading_jacobians_into", RNG.random(4) + 0.1, normals, points,
                        RNG.normal(size=(4, 3)) * 0.05, rotations, np.array([0.03, -0.02, 0.01]),
                        np.full((4, N_PIXELS, 6), np.nan))
    assert np.isfinite(cpu[-1]).all() and (cpu[-1] == 0).any() and (cpu[-1] != 0).any()  # lit and unlit points
    assert_close(gpu[-1], cpu[-1])
def test_albedo_update_matches_cpu_and_the_ratio(frames):
    """One launch: the sums and the closed form; pixels without weight keep the fallback."""
    residual, usable, color, shading, albedo = frames
    usable = usable.copy()
    usable[:, :7] = False  # no frame: den = 0, the fallback
    usable[0, 7:] = True  # at least one frame elsewhere
    empty = lambda *shape: np.full(shape, np.nan)  # noqa: E731
    cpu, gpu = run_both("albedo_update", residual, usable, color, shading, np.float64(1.0 / LAM), albedo,
                        empty(N_PIXELS, 3), empty(N_PIXELS, 3), empty(N_PIXELS, 3))
    num, den, out = cpu[-3:]
    np.testing.assert_array_equal(out[:7], albedo[:7])
    assert_close(out[7:], num[7:] / den[7:])
    for a, b in zip(gpu[-3:], cpu[-3:]):
        assert_close(a, b)


@pytest.mark.parametrize("shared", [True, False])
def test_lighting_sums_match_cpu_and_the_matrix_formula(frames, shared):
    """Frame i's Gram sum_p a_p B_p B_p^T, rhs sum_p b_p B_p and usable count (a, b the weighted
    channel sums of the NumPy reference lighting_reference.weighted_lighting_sums), blocks' shares added;
    float32 basis as the solver's."""
    residual, usable, color, _, albedo = frames
    k = 4 if shared else 2
    basis = RNG.random((1 if shared else N_FRAMES, N_PIXELS, k)).astype(np.float32)
    blocks = 3
    cpu, gpu = run_both("lighting_sums", residual, usable, color, albedo, np.float64(1.0 / LAM), basis,
                        np.full((N_FRAMES, blocks, k * k + k + 1), np.nan))
    a, b = weighted_lighting_sums(residual, usable, color, albedo, LAM)
    B = np.broadcast_to(basis.astype(np.float64), (N_FRAMES, N_PIXELS, k))
    expected = np.concatenate([np.einsum("ip,ipr,ipc->irc", a, B, B).reshape(N_FRAMES, -1),
                               np.einsum("ip,ipr->ir", b, B), usable.sum(axis=1)[:, None]], axis=1)
    assert_close(cpu[-1].sum(axis=1), expected, rtol=1e-12)
    assert_close(gpu[-1].sum(axis=1), expected, rtol=1e-12)
    with pytest.raises(ValueError, match="5 terms"):
        cuda_kernels.lighting_sums(residual, usable, color, albedo, 1.0 / LAM, np.zeros((1, N_PIXELS, 5)),
                                   np.zeros((N_FRAMES, 1, 31)))


def _offset_normal_equations(ds: np.ndarray, w: np.ndarray, albedo: np.ndarray, residual: np.ndarray):
    """NumPy reference of the LED offset's Gauss-Newton Gram H (3, 3) and gradient g (3,) summed
    over pixels and frames (the host's array formula before kernels.led_offset_system ran there):
    ds (..., M, 3) d(shading)/d(offset), w (..., M, 3) IRLS weights, albedo (M, 3), residual
    (..., M, 3) ``I - rho s``, so dr/do = -rho ds."""
    rho_w = albedo ** 2 * w
    ds_flat = ds.reshape(-1, 3)
    H = (ds * rho_w.sum(axis=-1)[..., None]).reshape(-1, 3).T @ ds_flat
    return H, -(ds_flat.T @ np.sum(w * albedo * residual, axis=-1).reshape(-1))


def test_offset_system_matches_cpu_and_the_array_formula(frames):
    """The LED offset's system from every 3rd pixel: the same as the array formula
    (_offset_normal_equations) on those pixels, unusable ones weighted 0 (the reference of
    led_offset_system's test)."""
    from o3d_mvps.model.robust import cauchy_weights

    residual, usable, _, _, albedo = frames
    stride = 3
    ds = RNG.normal(size=(N_FRAMES, -(-N_PIXELS // stride), 3))
    cpu = run_cpu("offset_system", ds, residual, usable, albedo, np.float64(1.0 / LAM), stride,
                  np.full((1, 3, 3), np.nan), np.full((1, 3, 1), np.nan))
    spread = slice(None, None, stride)
    H, g = _offset_normal_equations(ds, cauchy_weights(residual[:, spread], LAM) * usable[:, spread, None],
                                    albedo[spread], residual[:, spread])
    assert_close(cpu[-2][0], H)
    assert_close(cpu[-1][0, :, 0], g)


def test_stencil_transpose_subtract_matches_cpu_and_the_sparse_formula():
    """y - (Du^T Ba + Dv^T Bb + Bg), as normal_equations.stencil_transpose on a grid (the CPU's
    joint_depth_system's second half)."""
    from o3d_mvps.model.normals import masked_grid

    mask = np.ones((9, 11), dtype=bool)
    mask[:2, :3] = False
    grid = masked_grid(mask)
    N = grid.size
    DuT, DvT = grid.transposed_difference_operators()
    Ba, Bb, Bg, y = RNG.normal(size=(4, N))
    cpu = run_cpu("stencil_transpose_subtract", DuT.indptr, DuT.indices, DuT.data, DvT.indptr, DvT.indices,
                  DvT.data, Ba, Bb, Bg, y, np.full(N, np.nan))
    assert_close(cpu[-1], y - (DuT @ Ba + DvT @ Bb + Bg))


def test_depth_block_fill_matches_cpu_and_the_sparse_products():
    """The depth block (stencil Gram + 2 tau D^T D + 2 mu S^T S) filled into the level's pattern (the
    CPU's joint_depth_system's first half): the sparse products' matrix to rounding (the CPU's
    depth_block's measured 2e-16), no entry missing; a pattern without the prior's entries counts
    the part that lacks some."""
    from o3d_mvps.model.normals import masked_grid
    from o3d_mvps.solver.normal_equations import depth_block_pattern, stencil_normal_matrix

    mask = np.ones((8, 10), dtype=bool)
    mask[:2, :3] = False
    grid = masked_grid(mask)
    N = grid.size
    sums = RNG.random((6, N))
    D = sp.random(N // 4, N, density=0.05, random_state=3, format="csr")
    S = sp.random(N, N, density=0.02, random_state=4, format="csr")
    prior = type("Prior", (), {"D": D, "smoothness_pattern": S})()
    indptr, indices = depth_block_pattern(grid, prior)
    DtD, StS = (D.T @ D).tocsr(), (S.T @ S).tocsr()
    geometry = (grid.fwd_u, grid.bwd_u, grid.wf_u, grid.wb_u, grid.fwd_v, grid.bwd_v, grid.wf_v, grid.wb_v)
    cpu = run_cpu("depth_block_fill", indptr, indices, *geometry, *sums, 1.4, DtD.indptr, DtD.indices, DtD.data,
                  0.6, StS.indptr, StS.indices, StS.data, np.zeros(indices.size), np.zeros(1))
    expected = (stencil_normal_matrix(grid, *sums) + 1.4 * DtD + 0.6 * StS).toarray()
    assert cpu[-1][0] == 0.0
    assert_close(sp.csr_matrix((cpu[-2], indices, indptr), shape=(N, N)).toarray(), expected, rtol=1e-13)
    # without a second term (no rows) and a pattern of the stencil alone: the first term's entries missing
    no_rows = DtD.indptr[:1]
    touched_only = type("Prior", (), {"D": sp.csr_matrix((1, N)), "smoothness_pattern": None})()
    small_ptr, small_idx = depth_block_pattern(grid, touched_only)
    cpu = run_cpu("depth_block_fill", small_ptr, small_idx, *geometry, *sums, 1.4, DtD.indptr, DtD.indices,
                  DtD.data, 0.0, no_rows, DtD.indices, DtD.data, np.zeros(small_idx.size), np.zeros(1))
    outside = (abs(sp.csr_matrix((np.ones(small_idx.size), small_idx, small_ptr), shape=(N, N))).toarray() == 0)
    assert (DtD.toarray()[outside] != 0).sum() > 0 and cpu[-1][0] == 1.0  # on the host 1 for the one part lacking some


def test_levenberg_damp_matches_cpu_and_levenberg_damped():
    """In place and in one launch: linear.levenberg_damped's matrix (1e-14: the diagonal's mean added
    in another order); a row without a stored diagonal is counted, left as it is."""
    from o3d_mvps.solver.linear import levenberg_damped

    n = 120
    B = sp.random(n, n, density=0.05, random_state=8, format="csr")
    A = (B @ B.T + sp.diags(np.linspace(0.0, 2.0, n))).tocsr()
    A.indptr, A.indices = A.indptr.astype(np.int32), A.indices.astype(np.int32)
    A.setdiag(A.diagonal())  # every diagonal entry stored (zeros too)
    expected = levenberg_damped(A.copy()).toarray()
    def damp(module, M):  # (data, missing) after the launch
        data, missing = M.data.copy(), np.full(1, np.nan)
        module.levenberg_damp(M.indptr, M.indices, data, 1e-4, np.finfo(float).tiny, np.full(8, np.nan), missing)
        return data, missing[0]

    for module in (kernels, cuda_kernels):
        data, missing = damp(module, A)
        assert missing == 0.0
        assert_close(sp.csr_matrix((data, A.indices, A.indptr), shape=(n, n)).toarray(), expected, rtol=1e-14)
    C = sp.csr_matrix(A.toarray() - np.diag(np.diag(A.toarray())) + np.diag(np.r_[0.0, np.ones(n - 1)]))  # row 0: none
    C.indptr, C.indices = C.indptr.astype(np.int32), C.indices.astype(np.int32)
    data, missing = damp(cuda_kernels, C)
    assert missing == 1.0
    np.testing.assert_array_equal(data[C.indptr[0]:C.indptr[1]], C.data[C.indptr[0]:C.indptr[1]])


# --- gpu3: the driver's extrapolation trials in one launch ---------------------------------------


@pytest.mark.parametrize("envelope", [True, False])
def test_extrapolation_trials_match_cpu_and_the_driver_formulas(envelope):
    """Every factor's trial at once, equal to the driver's per-factor formulas (clip of
    x + f (x - x0)); the depths not > 0 counted per factor (a NaN too), the albedo unclipped."""
    N, factors = 700, (1.0, 2.0, 4.0)
    z0 = 0.5 + 0.1 * RNG.random(N)
    z = z0 + 0.02 * (RNG.random(N) - 0.5)
    z[5] = z0[5] - 0.3  # factor 2 leaves it at 0.5 - 0.6 < 0 without an envelope
    z[7] = np.nan
    albedo0, albedo = RNG.random((N, 3)), RNG.random((N, 3))
    lower, upper = (z0 - 0.04, z0 + 0.04) if envelope else (np.empty(0), np.empty(0))
    blocks = kernels.extrapolation_blocks(N)
    assert blocks == cuda_kernels.extrapolation_blocks(N) == 1  # one block a factor here
    cpu, gpu = run_both("extrapolation_trials", z, z0, albedo, albedo0, factors, lower, upper,
                        np.full((3, N), np.nan), np.full((3, N, 3), np.nan), np.full((3, blocks), np.nan))
    for j, factor in enumerate(factors):
        x = z + factor * (z - z0)
        expected = np.clip(x, lower, upper) if envelope else x
        np.testing.assert_array_equal(cpu[-3][j], expected)  # NaN where z is NaN, as np.clip
        np.testing.assert_array_equal(np.isnan(gpu[-3][j]), np.arange(N) == 7)
        assert_close(np.delete(gpu[-3][j], 7), np.delete(expected, 7))
        assert_close(gpu[-2][j], albedo + factor * (albedo - albedo0))
        np.testing.assert_array_equal(cpu[-2][j], albedo + factor * (albedo - albedo0))
        not_positive = np.sum(~(expected > 0))
        assert cpu[-1][j].sum() == gpu[-1][j].sum() == not_positive
    assert cpu[-1].sum(axis=1).tolist() == ([1, 1, 1] if envelope else [2, 2, 2])
    with pytest.raises(ValueError, match="5 factors"):
        cuda_kernels.extrapolation_trials(z, z0, albedo, albedo0, (1.0,) * 5, lower, upper, np.empty((5, N)),
                                          np.empty((5, N, 3)), np.empty((5, blocks)))


@pytest.mark.parametrize("envelope", [True, False])
def test_depth_step_matches_cpu_and_the_line_search_formula(envelope):
    """clip(z + t dz) with the depths not > 0 counted (a NaN too), several blocks on the GPU."""
    N, t = 5000, 0.5
    z = 0.5 + 0.1 * RNG.random(N)
    dz = 0.02 * (RNG.random(N) - 0.5)
    dz[11] = -2.0  # 0.5..0.6 - 1.0 < 0 without an envelope
    dz[13] = np.nan
    lower, upper = (z - 0.005, z + 0.005) if envelope else (np.empty(0), np.empty(0))
    blocks = kernels.extrapolation_blocks(N)
    assert blocks == 3
    cpu, gpu = run_both("depth_step", z, dz, t, lower, upper, np.full(N, np.nan), np.full(blocks, np.nan))
    x = z + t * dz
    expected = np.clip(x, lower, upper) if envelope else x
    np.testing.assert_array_equal(cpu[-2], expected)
    np.testing.assert_array_equal(np.isnan(gpu[-2]), np.arange(N) == 13)
    assert_close(np.delete(gpu[-2], 13), np.delete(expected, 13))
    assert cpu[-1].sum() == gpu[-1].sum() == (1 if envelope else 2)


# --- gpujoint (issue #33): the joint step's device assembly, twist system and read-out ----------


@pytest.mark.parametrize("project", [True, False])
def test_joint_block_matches_cpu_and_the_host_pass(project):
    """One launch per assembly block (light rows, reference parallax, every frame's sums and rows,
    the albedo projection): the CPU twin equals the host's pass of separate steps on the same data
    (_light_rows, _parallax_rows, accumulate_frames, _AlbedoProjection's downdates, scalings and
    project_twist_rows) to round-off, the CUDA kernel its twin; the partial twist sums add up to
    accumulate_frames' and count each frame's usable pixels."""
    from o3d_mvps.solver.normal_equations import _AlbedoProjection, _light_rows, _parallax_rows

    n, B = 3, 140  # more pixels than a thread block's threads: some threads take two
    m = n - 1
    f = lambda *shape: RNG.random(shape)  # noqa: E731
    K = np.array([[300.0, 0.0, 80.0], [0.0, 310.0, 60.0], [0.0, 0.0, 1.0]])
    poses = np.stack([np.eye(4), POSE, POSE @ POSE])
    # float64 residuals: the simulator's NumPy scalars would keep float32 products in float32
    residual, shading = f(n, B, 3) - 0.5, f(n, B)
    usable = RNG.random((n, B)) > 0.2
    usable[:, 5] = False  # d = 0 there
    albedo, dA, field = f(B, 3), f(B) + 0.5, f(n, B, 3) - 0.5
    u, v = RNG.integers(0, 160, B), RNG.integers(0, 120, B)
    points = (f(B, 3) - 0.5) * [0.6, 0.4, 0.2] + [0.0, 0.0, 1.0]
    images, dshading = RNG.random((n, 120, 160, 3)).astype(np.float32), f(n, B, 6) - 0.5
    inputs = (residual, shading, usable, 1.0 / LAM, albedo, dA, field, u, v, points, poses, K, images, dshading, True,
              True)

    def outputs(rows_count):
        return [np.full(shape, np.nan) for shape in ((B, 3), (n, B), (n, B), (n, B), (B, 3), (9, B),
                                                     (3 if project else 0, B if project else 1, 3), (3, m, 6, B),
                                                     (m if project else 0, 6, B if project else 1, 3),
                                                     (3 * B if project else 0,), (B, 3), (rows_count, m, 28))]

    cpu = outputs(kernels.joint_blocks(B))
    kernels.joint_block(*inputs, *cpu)
    gpu = outputs(cuda_kernels.joint_blocks(B))
    cuda_kernels.joint_block(*copies(inputs), *gpu)
    # the host's steps
    alpha, beta, gamma = _light_rows(field[..., 0], field[..., 1], field[..., 2], u, v, 300.0, 80.0, 310.0, 60.0)
    extra = _parallax_rows(albedo, *(dshading[0][:, k:k + 1] for k in range(3)), *(points[:, k:k + 1] for k in range(3)),
                           usable[0][:, None])
    frame_slots = np.array([[0, -1], [1, 0], [1, 1]], dtype=np.int64)
    sums, e = np.zeros((9, B)), np.zeros((3, B, 3)) if project else np.zeros((0, 1, 3))
    rows, F = np.zeros((3, m, 6, B)), np.zeros((m, 6, B, 3)) if project else np.zeros((0, 6, 1, 3))
    gram, rhs = np.zeros((m + 1, kernels.chunk_count(B), 6, 6)), np.zeros((m + 1, kernels.chunk_count(B), 6))
    kernels.accumulate_frames(residual, shading, usable, 1.0 / LAM, albedo / dA[:, None], alpha, beta, gamma, extra,
                              points, poses, K, images, dshading, albedo, frame_slots, True, sums, e, rows, F, gram, rhs)
    expected = {7: sums, 8: rows}
    if project:
        projection = _AlbedoProjection(residual, usable, shading, LAM)
        projection.e = e
        sums = sums - projection.local()
        scaled, root = projection.twist_scalings()
        kernels.project_twist_rows(rows, F, scaled, root)
        expected = {5: sums, 6: scaled, 7: rows, 8: F, 9: (projection.sWr * root).reshape(-1), 10: root}
    else:
        expected = {5: sums, 7: rows}
    for k, value in {0: albedo / dA[:, None], 1: alpha, 2: beta, 3: gamma, 4: extra, **expected}.items():
        assert_close(cpu[k], value)
        assert_close(gpu[k], cpu[k])
    for got in (cpu, gpu):
        totals = got[11].sum(axis=0)  # (m, 28)
        upper = np.triu_indices(6)
        assert_close(totals[:, :21], gram[:m].sum(axis=1)[:, upper[0], upper[1]])
        assert_close(totals[:, 21:27], rhs[:m].sum(axis=1))
        np.testing.assert_array_equal(totals[:, 27], usable[1:].sum(axis=1))
    assert np.abs(cpu[7]).max() > 0.0 and (not project or cpu[10][5].tolist() == [0.0, 0.0, 0.0])


def test_add_stencil_transpose_rows_matches_cpu_and_the_sparse_formula():
    """U^T += Du_b^T a + Dv_b^T b + c for one block's rows of the difference operators, given by
    the block's slice of indptr and the whole indices and data: the CUDA kernel's atomic adds
    (neighbouring pixels share columns) equal the CPU's to round-off and the sparse products."""
    from o3d_mvps.model.normals import masked_grid

    mask = np.ones((9, 11), dtype=bool)
    mask[:2, :3] = False
    grid = masked_grid(mask)
    N, k, start, stop = grid.size, 5, 20, 60
    Du, Dv = grid.difference_operators()
    rows, out = RNG.normal(size=(3, k, stop - start)), RNG.normal(size=(k, N))
    cpu, gpu = run_both("add_stencil_transpose_rows", Du.indptr[start:stop + 1], Du.indices, Du.data,
                        Dv.indptr[start:stop + 1], Dv.indices, Dv.data, rows, start, out)
    expected = out + (Du[start:stop].T @ rows[0].T + Dv[start:stop].T @ rows[1].T).T
    expected[:, start:stop] += rows[2]
    assert_close(cpu[-1], expected)
    assert_close(gpu[-1], cpu[-1])


def test_joint_twist_system_matches_cpu_and_twist_system():
    """The twist system from the assembly's partial sums (two blocks' rows and F Grams): the
    twist_system of the summed Grams, right-hand sides and downdate, and a frame with fewer usable
    pixels than asked dropped (an identity block, a zero right-hand side); CPU and CUDA alike."""
    m, R = 3, 4
    K = 6 * m
    partial = RNG.normal(size=(R, m, 28))
    for f in range(m):  # a well-conditioned Gram per frame, split over the rows
        M = RNG.normal(size=(6, 6))
        partial[:, f, :21] = (np.triu(M @ M.T + 6 * np.eye(6))[np.triu_indices(6)] / R)
    partial[:, :, 27] = [[10.0, 2.0, 9.0]] * R  # usable pixels: 40, 8, 36
    products = RNG.normal(size=(2, K + 1, K + 1)) * 1e-3
    products = products @ products.transpose(0, 2, 1)
    args = (partial, products, 12, kernels.MAX_TWIST_CONDITION, np.zeros((m, 6, 6)), np.zeros(K),
            np.zeros((K + 1, K + 1)), np.zeros((m, 6, 6)), np.zeros(m), np.full((K, K), np.nan), np.zeros(K),
            np.ones((K, K)))
    cpu, gpu = run_both("joint_twist_system", *args)
    grams = np.zeros((m, 6, 6))
    for f in range(m):
        grams[f][np.triu_indices(6)] = partial[:, f, :21].sum(axis=0)
    D = products.sum(axis=0)
    reference = (grams, partial[:, :, 21:27].sum(axis=0).reshape(-1), D[K, :K].copy(), D[:K, :K].copy(),
                 kernels.MAX_TWIST_CONDITION, np.zeros((m, 6, 6)), np.zeros(m), np.zeros((K, K)), np.zeros(K),
                 np.zeros((K, K)))
    kernels.twist_system(*reference)
    np.testing.assert_array_equal(cpu[8], [1.0, 0.0, 1.0])
    np.testing.assert_array_equal(reference[6], [1.0, 1.0, 1.0])  # the Grams alone keep all three
    keep = np.r_[np.ones(6), np.zeros(6), np.ones(6)].astype(bool)
    assert_close(cpu[9][np.ix_(keep, keep)], reference[7][np.ix_(keep, keep)])
    np.testing.assert_array_equal(cpu[9][6:12, 6:12], np.eye(6))
    assert_close(cpu[10], np.where(keep, reference[8], 0.0))
    np.testing.assert_array_equal(cpu[11], -np.diag(keep.astype(float)))
    for k in (8, 9, 10, 11):
        assert_close(gpu[k], cpu[k])


def test_joint_depth_system_matches_cpu_and_its_two_kernels():
    """The depth block and its right-hand side in one launch: depth_block_fill's and
    stencil_transpose_subtract's values, CPU and CUDA alike."""
    from o3d_mvps.model.normals import masked_grid
    from o3d_mvps.solver.normal_equations import depth_block_pattern

    mask = np.ones((8, 10), dtype=bool)
    mask[:2, :3] = False
    grid = masked_grid(mask)
    N = grid.size
    sums = RNG.random((9, N))
    D = sp.random(N // 4, N, density=0.05, random_state=3, format="csr")
    prior = type("Prior", (), {"D": D, "smoothness_pattern": None})()
    indptr, indices = depth_block_pattern(grid, prior)
    DtD = (D.T @ D).tocsr()
    DuT, DvT = grid.transposed_difference_operators()
    geometry = (grid.fwd_u, grid.bwd_u, grid.wf_u, grid.wb_u, grid.fwd_v, grid.bwd_v, grid.wf_v, grid.wb_v)
    fill = (indptr, indices, *geometry, *sums[:6], 1.4, DtD.indptr, DtD.indices, DtD.data, 0.0, DtD.indptr[:1],
            DtD.indices, DtD.data, np.zeros(indices.size), np.zeros(1))
    rhs = (DuT.indptr, DuT.indices, DuT.data, DvT.indptr, DvT.indices, DvT.data, *sums[6:], RNG.normal(size=N),
           np.full(N, np.nan))
    cpu, gpu = run_both("joint_depth_system", *fill, *rhs)
    alone = [np.copy(a) for a in fill], [np.copy(a) for a in rhs]
    kernels.depth_block_fill(*alone[0])
    kernels.stencil_transpose_subtract(*alone[1])
    n_fill = len(fill)
    for k in (n_fill - 2, n_fill - 1):
        assert_close(cpu[k], alone[0][k])
        assert_close(gpu[k], cpu[k])
    assert_close(cpu[-1], alone[1][-1])
    assert_close(gpu[-1], cpu[-1])
    assert cpu[n_fill - 1][0] == 0.0 and np.abs(cpu[n_fill - 2]).max() > 0.0


def test_joint_inverse_and_twist_readout_match_numpy_and_cpu():
    """X = [[H^-1 selection, H^-1 selection b], [0, 1]] in one launch, and the twists
    ``P[j] . dz - X[j, K]`` of P = X^T [U^T; rhs_z^T] in another: NumPy's formulas (the Schur
    right-hand side rhs_z + U x in P's last row), CPU and CUDA alike."""
    K, N = 12, 50
    M = RNG.normal(size=(K, K))
    H = (M @ M.T)[None]
    selection = -np.diag(np.r_[np.ones(6), np.zeros(6)])[None]
    b = RNG.normal(size=K)
    cpu, gpu = run_both("joint_inverse", H, selection, b, 1e-12, np.zeros((1, K, K)), np.full((1, K + 1, K + 1), np.nan),
                        np.zeros(1))
    X = np.linalg.solve(H[0], selection[0])
    assert_close(cpu[5][0, :K, :K], X, rtol=1e-9)
    assert_close(cpu[5][0, :K, K], X @ b, rtol=1e-9)
    np.testing.assert_array_equal(cpu[5][0, K], np.r_[np.zeros(K), 1.0])
    assert cpu[6][0] == 1.0
    assert_close(gpu[5], cpu[5])
    stacked = RNG.normal(size=(K + 1, N))  # [U^T; rhs_z^T]
    P = cpu[5][0].T @ stacked
    assert_close(P[K], stacked[K] + stacked[:K].T @ (X @ b))
    dz = RNG.normal(size=N)
    out_cpu, out_gpu = run_both("twist_readout", P, dz, cpu[5], np.full(K, np.nan))
    # (U X)^T dz - X b: with the solver's H and selection (X symmetric) -H^-1 diag(kept) (b - U^T dz)
    assert_close(out_cpu[-1], X.T @ (stacked[:K] @ dz) - X @ b, rtol=1e-9)
    assert_close(out_gpu[-1], out_cpu[-1])
# --- gpueval2 (issue 33) ---------------------------------------------------------------------


def _led_surface():
    """Unit normals and points (N_PIXELS, 3) in front of the camera, and a light state of four
    frames: poses (4, 4, 4), an LED offset (3,), lights (4, 2)."""
    from o3d_mvps.solver.lighting import LEDLight

    points = RNG.normal(size=(N_PIXELS, 3)) * 0.05 + [0.0, 0.0, 0.6]
    normals = RNG.normal(size=(N_PIXELS, 3))
    normals[:, 2] = -np.abs(normals[:, 2])  # most face the camera: lit and unlit pixels
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    poses = np.stack([np.eye(4), POSE, np.linalg.inv(POSE), POSE @ POSE])
    light = LEDLight(np.array([0.03, -0.02, 0.01]))
    return normals, points, poses, light, np.column_stack([RNG.random(4) * 0.2, RNG.random(4) * 0.4 + 0.1])


def test_led_offset_system_matches_the_jacobians_and_offset_system(frames):
    """The LED offset's system with its Jacobians formed per pixel (one launch on a GPU): the
    same as offset_system on the light model's own offset_jacobians (the host's array formulas)
    of every 4th pixel."""
    residual, usable, _, _, albedo = frames
    residual, usable = np.concatenate([residual, residual[:1]]), np.concatenate([usable, usable[:1]])  # 4 frames
    normals, points, poses, light, lights = _led_surface()
    stride = 4
    ds = light.offset_jacobians(lights, normals[::stride], points[::stride], poses)
    H, g = np.full((1, 3, 3), np.nan), np.full((1, 3, 1), np.nan)
    kernels.offset_system(ds, residual, usable, albedo, 1.0 / LAM, stride, H, g)
    rotations = np.ascontiguousarray(poses[:, :3, :3])
    cpu, gpu = run_both("led_offset_system", lights[:, 1].copy(), normals, points, light.positions(poses), rotations,
                        residual, usable, albedo, np.float64(1.0 / LAM), stride, np.full((1, 3, 3), np.nan),
                        np.full((1, 3, 1), np.nan))
    assert np.abs(H).max() > 0 and (ds == 0).any()  # lit and unlit pixels
    assert_close(cpu[-2], H, rtol=1e-10)  # the product's order of sums differs (J R^T against matmul)
    assert_close(cpu[-1], g, rtol=1e-10)
    assert_close(gpu[-2], cpu[-2])
    assert_close(gpu[-1], cpu[-1])


def _evidence_sums_by_frame(usable, rho2, shading, L) -> tuple:
    """normal_evidence's sums in NumPy from the fields L (n, N, 3): G6 (6, N) the entries 00, 01,
    02, 11, 12, 22 of sum u L L^T, v (3, N) sum u s L, d (N,) sum u s^2 (u = usable rho2), each
    pixel's frames added in order, as the compiled kernels add them."""
    N = usable.shape[1]
    G6, v, d = np.zeros((6, N)), np.zeros((3, N)), np.zeros(N)
    for i in range(usable.shape[0]):
        seen, s = usable[i], shading[i].astype(np.float64)
        us = rho2 * s
        for k, (a, b) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
            G6[k] = np.where(seen, G6[k] + rho2 * L[i, :, a] * L[i, :, b], G6[k])
        for a in range(3):
            v[a] = np.where(seen, v[a] + us * L[i, :, a], v[a])
        d = np.where(seen, d + us * s, d)
    return G6, v, d


def test_led_evidence_sums_match_the_sums_over_the_light_models_fields(frames):
    """normal_evidence's sums with the LED's fields formed per pixel (one compiled pass on the
    host, one launch on a GPU): on the CPU equal bit for bit to the sums, frame by frame, of the
    light model's own fields (LEDLight.fields), unusable frames and a float32 shading included."""
    _, usable, _, shading, albedo = frames
    usable, shading = np.concatenate([usable, usable[:1]]), np.concatenate([shading, shading[:1]]).astype(np.float32)
    normals, points, poses, light, lights = _led_surface()
    _, L = light.fields(lights, normals, points, poses)
    expected = _evidence_sums_by_frame(usable, (albedo ** 2).sum(axis=1), shading, L)
    nan = lambda *shape: np.full(shape, np.nan)  # noqa: E731
    cpu, gpu = run_both("led_evidence_sums", usable, albedo, shading, lights[:, 1].copy(), normals, points,
                        light.positions(poses), nan(6, N_PIXELS), nan(3, N_PIXELS), nan(N_PIXELS))
    assert (L == 0).any() and (L != 0).any()
    for got, want in zip(cpu[-3:], expected):
        np.testing.assert_array_equal(got, want)
    for a, b in zip(gpu[-3:], cpu[-3:]):
        assert_close(a, b)


def test_albedo_evaluation_partials_match_the_albedo_update_and_evaluation_partials():
    """The albedo's closed form and the evaluation at it in one pass (one launch on a GPU): the
    albedo, shading and residuals of albedo_update then evaluation_partials, their sums the same
    to the partial sums' order; the residuals read before they are overwritten."""
    led = True
    grid, z, K, poses, images, visible, albedo, lights, offset, prior, D, S, S_matrix = _level_data(led)
    usable, residual, color, basis = _array_formulas(grid, z, K, poses, images, visible, albedo, lights, offset, led)
    tau, mu, inv_lam = 3.0, 0.5, 1.0 / LAM
    n, N = usable.shape
    shading = np.full((n, N), np.nan, np.float32)
    kernels.shading_residuals(color, albedo, basis, lights, usable, shading, residual)
    residual = residual + (RNG.normal(size=residual.shape) * 0.05).astype(np.float32) * usable[..., None]
    usable = usable.copy()
    usable[:, :5] = False  # no frame: the fallback albedo
    nan = lambda *shape: np.full(shape, np.nan)  # noqa: E731
    ref = [residual.copy(), nan(N, 3), nan(N, 3), nan(N, 3), shading.copy(), nan(2, 2)]
    kernels.albedo_update(ref[0], usable, color, shading, inv_lam, albedo, ref[1], ref[2], ref[3])
    kernels.evaluation_partials(color, ref[3], basis, lights, usable, ref[4], ref[0], inv_lam, *D, prior.z0, *S, tau,
                                mu, z, ref[5])
    cpu, gpu = run_both("albedo_evaluation_partials", residual, usable, color, shading, np.float64(inv_lam), albedo,
                        nan(N, 3), nan(N, 3), nan(N, 3), basis, lights, *D, prior.z0, *S, tau, mu, z, nan(2, 2))
    np.testing.assert_array_equal(cpu[8][:5], albedo[:5])
    for out, rtol in ((cpu, 1e-12), (gpu, 1e-6)):  # the simulator's Python: float32 residual x float = float32 (NEP 50)
        assert_close(out[8], ref[3], rtol=rtol)  # the albedo
        assert_close(out[3], ref[4])  # the shading
        assert_close(out[0], ref[0], rtol=1e-6)  # the float32 residuals
        assert out[-1][:, 1].sum() == pytest.approx(ref[5][:, 1].sum(), rel=1e-12)
        assert out[-1][:, 0].sum() == pytest.approx(ref[5][:, 0].sum(), rel=1e-6)
    assert not np.array_equal(cpu[0], residual)  # written


@pytest.mark.parametrize("led", [True, False])
def test_evaluate_albedo_partials_match_the_evaluation_then_the_albedo_step(led):
    """A line-search trial's evaluation and its albedo refit in one pass (one launch on a GPU):
    what evaluate_partials and then albedo_evaluation_partials write, to round-off."""
    grid, z, K, poses, images, visible, albedo, lights, offset, prior, D, S, S_matrix = _level_data(led)
    basis_shape = _array_formulas(grid, z, K, poses, images, visible, albedo, lights, offset, led)[3].shape
    tau, mu, scale = 3.0, 0.5, 1.0 / LAM
    grid_arrays = [np.ascontiguousarray(a) for a in (grid.u, grid.v, grid.fwd_u, grid.bwd_u, grid.wf_u, grid.wb_u,
                                                        grid.fwd_v, grid.bwd_v, grid.wf_v, grid.wb_v)]
    n, N = visible.shape
    nan = lambda *shape, dtype=np.float64: np.full(shape, np.nan, dtype)  # noqa: E731
    outputs = lambda: [nan(N, 3), nan(N, 3), nan(N), nan(n, N, 3, dtype=np.float32),  # noqa: E731
                       np.zeros((n, N), bool), nan(*basis_shape, dtype=np.float32), nan(n, N, dtype=np.float32),
                       nan(n, N, 3, dtype=np.float32), nan(3, 2)]
    inputs = [z, *grid_arrays, K, poses, images, visible, albedo, lights, led, *offset, scale, True, *D, prior.z0, *S,
              tau, mu]
    ref = outputs()
    kernels.evaluate_partials(*inputs, *ref)
    points, normals, dA, color, usable, basis, shading, residual, partial = ref
    refit = nan(N, 3)
    kernels.albedo_evaluation_partials(residual, usable, color, shading, scale, albedo, nan(N, 3), nan(N, 3), refit,
                                       basis, lights, *D, prior.z0, *S, tau, mu, z, partial)
    cpu, gpu = run_both("evaluate_albedo_partials", *inputs, *outputs(), nan(N, 3), nan(N, 3), nan(N, 3))
    assert not np.allclose(refit, albedo)  # refitted
    for out, rtol in ((cpu, 1e-12), (gpu, 1e-6)):  # the simulator's float32 x float = float32 (NEP 50)
        assert_close(out[-1], refit, rtol=rtol)
        for got, want in zip(out[-12:-4], ref[:8]):
            np.testing.assert_array_equal(got, want) if want.dtype == bool else assert_close(got, want, rtol=1e-6)
        assert out[-4][:, 0].sum() == pytest.approx(partial[:, 0].sum(), rel=1e-6)
        assert out[-4][:, 1].sum() == pytest.approx(partial[:, 1].sum(), rel=1e-12)


def test_trial_energy_partials_match_energy_partials_per_trial():
    """Three trial states' energies in one pass (one launch on a GPU): each trial's sums, usable
    mask and prior those of energy_partials on that trial alone (the CPU twin exactly)."""
    led = True
    grid, z, K, poses, images, visible, albedo, lights, offset, prior, D, S, S_matrix = _level_data(led)
    tau, mu, scale = 3.0, 0.5, 1.0 / LAM
    grid_arrays = [np.ascontiguousarray(a) for a in (grid.u, grid.v, grid.fwd_u, grid.bwd_u, grid.wf_u, grid.wb_u,
                                                        grid.fwd_v, grid.bwd_v, grid.wf_v, grid.wb_v)]
    n, N = visible.shape
    F = 3
    zs = np.stack([z * (1.0 + 0.002 * f) for f in range(F)])
    all_poses = np.stack([poses] * F)
    all_poses[1:, :, :3, 3] += 0.001
    albedos = np.stack([albedo * (1.0 + 0.05 * f) for f in range(F)])
    all_lights = np.stack([lights * (1.0 + 0.1 * f) for f in range(F)])
    offsets = np.array([offset, np.add(offset, 0.002), np.add(offset, -0.001)], dtype=np.float64)
    cpu, gpu = run_both("trial_energy_partials", zs, *grid_arrays, K, all_poses, images, visible, albedos, all_lights,
                        led, offsets, scale, True, *D, prior.z0, *S, tau, mu, np.zeros((F, n, N), bool),
                        np.full((F, 2, 2), np.nan))
    for f in range(F):
        one = [np.zeros((n, N), bool), np.full((2, 2), np.nan)]
        kernels.energy_partials(zs[f], *grid_arrays, K, all_poses[f], images, visible, albedos[f], all_lights[f], led,
                                *offsets[f], scale, True, *D, prior.z0, *S, tau, mu, *one)
        np.testing.assert_array_equal(cpu[-2][f], one[0])
        np.testing.assert_array_equal(cpu[-1][f], one[1])
        np.testing.assert_array_equal(gpu[-2][f], one[0])
        assert gpu[-1][f, :, 0].sum() == pytest.approx(one[1][:, 0].sum(), rel=1e-6)
        assert gpu[-1][f, :, 1].sum() == pytest.approx(one[1][:, 1].sum(), rel=1e-12)
    assert len(set(cpu[-1][:, :, 0].sum(axis=1))) == F  # the trials differ
def test_prior_gradient_matches_cpu_and_the_sparse_formula():
    """The depth prior's minus gradient ``-2 tau D^T (D z - z0) - 2 mu S^T S z`` in one launch
    (kernels.prior_gradient; was three csr_multiply_add passes): equal to the sparse formula to
    round-off, CUDA against CPU; without S its first term alone (S's arrays unread)."""
    N, M, tau, mu = 60, 20, 3.0, 0.5
    D = sp.random(M, N, density=0.1, random_state=7, format="csr")
    S = sp.random(N, N, density=0.05, random_state=8, format="csr")
    StS = (S.T @ S).tocsr()
    Dt = D.T.tocsr()
    for m in (D, Dt, StS):
        m.indptr, m.indices = m.indptr.astype(np.int32), m.indices.astype(np.int32)
    z, z0 = RNG.random(N), RNG.random(M)
    expected = -2 * tau * (D.T @ (D @ z - z0)) - 2 * mu * (StS @ z)
    for with_s in (True, False):
        Q = StS if with_s else D
        cpu, gpu = run_both("prior_gradient", D.indptr, D.indices, D.data, Dt.indptr, Dt.indices, Dt.data, Q.indptr,
                            Q.indices, Q.data, with_s, z, -z0, -2 * tau, -2 * mu, np.full(N, np.nan))
        assert_close(cpu[-1], expected if with_s else -2 * tau * (D.T @ (D @ z - z0)))
        assert_close(gpu[-1], cpu[-1])
