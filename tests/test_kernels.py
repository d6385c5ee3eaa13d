"""The compiled loops (o3d_mvps.solver.kernels, model.robust.cauchy_energy) against their
NumPy definitions on random data: equal to float64 round-off (relative 1e-12), the energy to
its float32 logarithms (1e-6)."""

import numba
import numpy as np
import pytest
import scipy.sparse as sp

from o3d_mvps.model.robust import cauchy, cauchy_energy, cauchy_weights
from o3d_mvps.model.shading import led_irradiance, led_irradiances, led_irradiances_into, led_vectors
from o3d_mvps.solver.kernels import (FRAME_CHUNK, add_csr_into_pattern, add_row_gram_into_pattern,
                                     add_stencil_transpose_rows, albedo_refit_residuals, albedo_update,
                                     columns_times, project_stencil_rows, project_twist_rows, rows_times,
                                     strong_connections, two_entry_stencil,
                                     scatter_sparse_transpose_rows, shading_residual_pixel, shading_residuals,
                                     weighted_albedo_pixel, weighted_albedo_sums)

RNG = np.random.default_rng(7)
N_FRAMES, N_PIXELS, LAM = 4, 3000, 0.1


@pytest.fixture
def data():
    residual = RNG.normal(size=(N_FRAMES, N_PIXELS, 3)) * 0.1
    usable = RNG.random((N_FRAMES, N_PIXELS)) > 0.2
    color = RNG.random((N_FRAMES, N_PIXELS, 3))
    shading = RNG.random((N_FRAMES, N_PIXELS))
    albedo = RNG.random((N_PIXELS, 3))
    return residual, usable, color, shading, albedo


def test_cauchy_energy_is_the_sum_of_phi(data):
    residual = data[0]
    assert cauchy_energy(residual, LAM) == pytest.approx(cauchy(residual, LAM).sum(), rel=1e-6)
    assert cauchy_energy(residual[:, ::7, 1:], LAM) == pytest.approx(cauchy(residual[:, ::7, 1:], LAM).sum(), rel=1e-6)


def test_weighted_sums_match_numpy(data):
    residual, usable, color, shading, albedo = data
    w = cauchy_weights(residual, LAM) * usable[..., None]
    num, den = np.empty((N_PIXELS, 3)), np.empty((N_PIXELS, 3))
    weighted_albedo_sums(residual, usable, color, shading, 1.0 / LAM, num, den)
    np.testing.assert_allclose(num, np.sum(w * color * shading[..., None], axis=0), rtol=1e-12)
    np.testing.assert_allclose(den, np.sum(w * shading[..., None] ** 2, axis=0), rtol=1e-12)


@pytest.mark.parametrize("shared", [True, False])
def test_shading_residuals_match_numpy(data, shared):
    _, usable, color, _, albedo = data
    basis = RNG.random((1 if shared else N_FRAMES, N_PIXELS, 2))
    lights = RNG.random((N_FRAMES, 2))
    shading, residual = np.empty((N_FRAMES, N_PIXELS)), np.empty((N_FRAMES, N_PIXELS, 3))
    shading_residuals(color, albedo, basis, lights, usable, shading, residual)
    expected = np.einsum("ink,ik->in", np.broadcast_to(basis, (N_FRAMES, N_PIXELS, 2)), lights)
    np.testing.assert_allclose(shading, expected, rtol=1e-12)
    np.testing.assert_allclose(residual, (color - albedo * expected[..., None]) * usable[..., None], rtol=1e-12,
                               atol=1e-15)


def test_sparse_transpose_product_scatters_and_accumulates():
    """A block of rows of an operator scatters into every column: out += (A^T X^T)^T."""
    A = sp.random(500, 400, density=0.01, random_state=1, format="csr")
    X = RNG.normal(size=(7, 500))
    out = RNG.normal(size=(7, 400))
    expected = out + (A.T @ X.T).T
    scatter_sparse_transpose_rows(A.indptr, A.indices, A.data, X, out)
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-14)


def test_stencil_transpose_rows_are_both_scatters_and_the_identity_part():
    """One pass adds Du_b^T a + Dv_b^T b + c (c at the block's own columns) to a float32 or
    float64 output, as two scatters and a slice addition do (float32: to its rounding)."""
    Du, Dv = (sp.random(300, 700, density=0.01, random_state=seed, format="csr") for seed in (2, 3))
    rows = RNG.normal(size=(3, 5, 300))
    for dtype, tolerance in ((np.float64, 1e-12), (np.float32, 1e-6)):
        start = RNG.normal(size=(5, 700))
        expected = start + (Du.T @ rows[0].T).T + (Dv.T @ rows[1].T).T
        expected[:, 200:500] += rows[2]
        out = start.astype(dtype)
        add_stencil_transpose_rows(Du.indptr, Du.indices, Du.data, Dv.indptr, Dv.indices, Dv.data, rows, 200, out)
        np.testing.assert_allclose(out, expected, rtol=tolerance, atol=tolerance * np.abs(expected).max())


def test_stencil_rows_of_two_entries_add_in_stored_order():
    """Rows of exactly two entries (the solver's stencils, unrolled) and rows of 0, 1 or 3 (the
    loop) add each entry in stored order into a float32 output, bit for bit as a loop over the
    entries does."""
    B, N, k = 200, 260, 3
    counts = np.full(B, 2)
    counts[::7], counts[3::11], counts[5::13] = 1, 3, 0
    operators = []
    for seed in (8, 9):
        rng = np.random.default_rng(seed)
        indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        indices = np.concatenate([rng.choice(N, c, replace=False) for c in counts]).astype(np.int32)
        operators.append((indptr, indices, rng.normal(size=indices.size)))
    rows = RNG.normal(size=(3, k, B))
    start = RNG.normal(size=(k, N)).astype(np.float32)
    expected = start.copy()
    for j in range(k):
        for p in range(B):
            expected[j, 30 + p] = np.float32(np.float64(expected[j, 30 + p]) + rows[2, j, p])
            for (indptr, indices, data), x in zip(operators, rows[:2, j, p]):
                for nz in range(indptr[p], indptr[p + 1]):
                    expected[j, indices[nz]] = np.float32(np.float64(expected[j, indices[nz]]) + data[nz] * x)
    out = start.copy()
    add_stencil_transpose_rows(*operators[0], *operators[1], rows, 30, out)
    np.testing.assert_array_equal(out, expected)
    assert not np.array_equal(out, start)

def _two_entry_rows(B: int, N: int, seed: int) -> sp.csr_matrix:
    """A (B, N) CSR operator with exactly two entries a row (in either column order), as the
    solver's difference operators without their stored zeros."""
    rng = np.random.default_rng(seed)
    indices = np.concatenate([rng.choice(N, 2, replace=False) for _ in range(B)]).astype(np.int32)
    return sp.csr_matrix((rng.normal(size=2 * B), indices, np.arange(0, 2 * B + 1, 2, dtype=np.int32)), shape=(B, N))


@pytest.mark.parametrize("two_entries", [False, True])
def test_fused_projection_and_stencil_equal_the_two_kernels(two_entries):
    """project_stencil_rows gives the very values (float32 U, scaled F) of project_twist_rows
    followed by add_stencil_transpose_rows, and leaves the rows unwritten: on stencil rows of
    any length (the CSR rows read) and of two entries each (two_entry_stencil's arrays read)."""
    m, B, N = 2, 300, 700
    if two_entries:
        Du, Dv = (_two_entry_rows(B, N, seed) for seed in (4, 5))
        assert two_entry_stencil(Du.indptr, Du.indices, Du.data, Dv.indptr, Dv.indices, Dv.data)[0].shape == (B, 4)
    else:
        Du, Dv = (sp.random(B, N, density=0.01, random_state=seed, format="csr") for seed in (4, 5))
        assert two_entry_stencil(Du.indptr, Du.indices, Du.data, Dv.indptr, Dv.indices, Dv.data)[0].shape == (0, 4)
    rows, F = RNG.normal(size=(3, m, 6, B)), RNG.normal(size=(m, 6, B, 3))
    scaled, sqrt_inv_d = RNG.normal(size=(3, B, 3)), RNG.random((B, 3))
    start = RNG.normal(size=(6 * m, N)).astype(np.float32)
    rows_two, F_two, out_two = rows.copy(), F.copy(), start.copy()
    project_twist_rows(rows_two, F_two, scaled, sqrt_inv_d)
    add_stencil_transpose_rows(Du.indptr, Du.indices, Du.data, Dv.indptr, Dv.indices, Dv.data,
                               rows_two.reshape(3, 6 * m, B), 200, out_two)
    rows_one, F_one, out_one = rows.copy(), F.copy(), start.copy()
    project_stencil_rows(rows_one, F_one, scaled, sqrt_inv_d, Du.indptr, Du.indices, Du.data, Dv.indptr, Dv.indices,
                         Dv.data, 200, out_one)
    np.testing.assert_array_equal(out_one, out_two)
    np.testing.assert_array_equal(F_one, F_two)
    np.testing.assert_array_equal(rows_one, rows)
    assert not np.array_equal(out_one, start)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_products_with_a_stored_matrix_sum_in_float64(dtype):
    """rows_times (A x) and columns_times (A^T y) of a float32 or float64 A (k, N) equal the
    float64 products of the stored values to float64 round-off, over several column chunks."""
    A = RNG.normal(size=(13, 40000)).astype(dtype)
    x, y = RNG.normal(size=40000), RNG.normal(size=13)
    exact = A.astype(np.float64)
    out_k, out_n = np.empty(13), np.empty(40000)
    rows_times(A, x, out_k)
    columns_times(A, y, out_n)
    np.testing.assert_allclose(out_k, exact @ x, rtol=1e-12, atol=1e-12 * np.abs(exact).sum(1).max())
    np.testing.assert_allclose(out_n, exact.T @ y, rtol=1e-12, atol=1e-14)


def test_strong_connections_are_the_symmetric_strength_test():
    """strong_connections (three passes in parallel over rows) keeps the diagonal and every
    (i, j) with a_ij^2 >= theta^2 |a_ii| |a_jj| of a CSR matrix, columns in stored order, and
    hands back the matrix's own arrays where every entry is kept."""
    n = 5000
    A = sp.diags([RNG.normal(size=n - k) * RNG.random(n - k) ** 3 for k in (1, 70)], [1, 70], shape=(n, n))
    A = sp.csr_matrix(A + A.T + sp.diags(RNG.random(n) + 0.5))
    A.sort_indices()
    indptr, indices = strong_connections(A.indptr, A.indices, A.data, 0.25)
    coo = A.tocoo()
    d = np.abs(A.diagonal())
    keep = (coo.row == coo.col) | (coo.data**2 >= 0.25**2 * d[coo.row] * d[coo.col])
    assert 0 < keep.sum() < A.nnz  # the test drops some entries and keeps others
    expected = sp.csr_matrix((np.ones(keep.sum()), (coo.row[keep], coo.col[keep])), shape=A.shape)
    expected.sort_indices()
    np.testing.assert_array_equal(indptr, expected.indptr)
    np.testing.assert_array_equal(indices, expected.indices)
    same = strong_connections(A.indptr, A.indices, A.data, 0.0)
    assert same[0] is A.indptr and same[1] is A.indices


def test_row_gram_into_pattern_is_the_sparse_gram_bit_for_bit():
    """add_row_gram_into_pattern of a block average A (each column in one row; rows in parallel)
    adds scale A^T A into a pattern bit for bit as add_csr_into_pattern of the product, and
    reports a pattern that lacks one of its entries."""
    n, width = 6000, 4
    A = sp.csr_matrix((RNG.random(n), (np.arange(n) // width, RNG.permutation(n))), shape=(n // width, n))
    gram = sp.csr_matrix(A.T @ A + sp.identity(n))
    gram.sort_indices()
    expected, actual = np.zeros(gram.nnz), np.zeros(gram.nnz)
    product = sp.csr_matrix(A.T @ A)
    assert add_csr_into_pattern(gram.indptr, gram.indices, expected, 0.7, product.indptr, product.indices,
                                product.data)
    assert add_row_gram_into_pattern(gram.indptr, gram.indices, actual, 0.7, A.indptr, A.indices, A.data)
    np.testing.assert_array_equal(actual, expected)
    diagonal = sp.identity(n, format="csr")
    assert not add_row_gram_into_pattern(diagonal.indptr, diagonal.indices, np.zeros(n), 0.7, A.indptr, A.indices,
                                         A.data)


def test_led_irradiances_match_led_vectors():
    points = RNG.normal(size=(N_PIXELS, 3)) * 0.05 + [0.0, 0.0, 0.6]
    normals = RNG.normal(size=(N_PIXELS, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    positions = RNG.normal(size=(5, 3)) * 0.05
    expected = np.stack([np.einsum("ij,ij->i", normals, led_vectors(points, s)) for s in positions])
    np.testing.assert_allclose(led_irradiances(normals, points, positions), expected, rtol=1e-12, atol=1e-12)


def test_warp_sample_is_warp_in_view_and_bilinear_sampling():
    """The fused kernel against its NumPy definition: the warped points' in-view test and
    bilinear samples of a float32 image (NumPy's gathers, float64 weights), points in view,
    behind the camera and outside the image among them: usable identical, colours to float32
    round-off (1e-6 of values up to 1)."""
    from o3d_mvps.model.se3 import exp
    from o3d_mvps.model.warping import in_view, sample_bilinear, warp
    from o3d_mvps.solver.kernels import warp_sample

    H, W = 30, 40
    K = np.array([[50.0, 0.0, 19.5], [0.0, 50.0, 14.5], [0.0, 0.0, 1.0]])
    image = RNG.random((H, W, 3)).astype(np.float32)
    points = RNG.normal(size=(N_PIXELS, 3)) * [0.3, 0.2, 0.3] + [0.0, 0.0, 0.6]
    points[:20, 2] = -0.1  # behind the camera
    pose = exp(np.array([0.02, -0.01, 0.03, 0.05, -0.04, 0.02]))
    visible = RNG.random(N_PIXELS) > 0.1
    color, usable = np.full((N_PIXELS, 3), np.nan, np.float32), np.zeros(N_PIXELS, bool)
    warp_sample(points, pose, K, image, visible, color, usable)
    _, u, v, Z = warp(points, pose, K)
    expected_usable = visible & in_view(u, v, Z, (H, W))
    np.testing.assert_array_equal(usable, expected_usable)
    assert 0.3 * N_PIXELS < usable.sum() < 0.95 * N_PIXELS  # both kinds of pixel are there
    expected = sample_bilinear(image.astype(np.float64), np.nan_to_num(u), np.nan_to_num(v))
    np.testing.assert_allclose(color[Z > 1e-6], expected[Z > 1e-6], rtol=0, atol=1e-6)


def test_warp_gradients_are_warp_and_central_differences_of_the_bilinear_image():
    """The assembly's per-pixel warp and colour gradients against their NumPy definition (warp,
    then half the difference of the bilinear samples (NumPy's float64 gathers) one pixel either
    side of the clamped position), points inside the image, near its border and outside it
    (clamped) among them: points to round-off, gradients to 1e-12."""
    from o3d_mvps.model.se3 import exp
    from o3d_mvps.model.warping import in_view, sample_bilinear, warp
    from o3d_mvps.solver.kernels import warp_gradients

    H, W = 30, 40
    K = np.array([[50.0, 0.0, 19.5], [0.0, 50.0, 14.5], [0.0, 0.0, 1.0]])
    image = RNG.random((H, W, 3)).astype(np.float32)
    points = RNG.normal(size=(N_PIXELS, 3)) * [0.3, 0.2, 0.3] + [0.0, 0.0, 0.6]
    points = points[points[:, 2] > 0.05]
    pose = exp(np.array([0.02, -0.01, 0.03, 0.05, -0.04, 0.02]))
    frame_points, grad_u, grad_v = (np.full(points.shape, np.nan) for _ in range(3))
    warp_gradients(points, pose, K, image, frame_points, grad_u, grad_v)
    expected_points, u, v, Z = warp(points, pose, K)
    assert 0.3 < in_view(u, v, Z, (H, W)).mean() < 0.95  # inside and outside
    np.testing.assert_allclose(frame_points, expected_points, rtol=1e-14, atol=1e-15)
    u, v = np.clip(u, 0, W - 1), np.clip(v, 0, H - 1)
    image64 = image.astype(np.float64)
    expected_u = 0.5 * (sample_bilinear(image64, u + 1, v) - sample_bilinear(image64, u - 1, v))
    expected_v = 0.5 * (sample_bilinear(image64, u, v + 1) - sample_bilinear(image64, u, v - 1))
    np.testing.assert_allclose(grad_u, expected_u, rtol=0, atol=1e-12)
    np.testing.assert_allclose(grad_v, expected_v, rtol=0, atol=1e-12)
    assert np.abs(grad_u).max() > 0.3 and np.abs(grad_v).max() > 0.3


@numba.njit
def _pixel_by_pixel(color, albedo, basis, lights, usable, residual_in, values, shading_in, inv_lam, positions,
                    normals, points, shading, residual, num, den, irradiance):  # pragma: no cover
    """The kernels' per-pixel functions in their first loop order (every frame inside each pixel):
    what the chunked launchers must reproduce bit for bit."""
    n, N = usable.shape
    for p in range(N):
        for i in range(n):
            shading_residual_pixel(color, albedo, basis, lights, usable, shading, residual, i, p)
        weighted_albedo_pixel(residual_in, usable, values, shading_in, inv_lam, num, den, p)
        for i in range(positions.shape[0]):
            irradiance[i, p] = led_irradiance(normals, points, positions, i, p)


@pytest.mark.parametrize("n_pixels", [5, FRAME_CHUNK, 2 * FRAME_CHUNK + 123])
def test_chunked_frame_loops_equal_the_per_pixel_loop(n_pixels):
    """The launchers that run frame after frame over chunks of pixels (FRAME_CHUNK) give exactly
    the per-pixel loop's numbers, on sizes below, at and across chunk boundaries."""
    n = 5
    residual = RNG.normal(size=(n, n_pixels, 3)) * 0.1
    usable = RNG.random((n, n_pixels)) > 0.2
    color = RNG.random((n, n_pixels, 3)).astype(np.float32)
    values = RNG.random((n, n_pixels, 3))
    shading_in = RNG.random((n, n_pixels))
    albedo = RNG.random((n_pixels, 3))
    basis = RNG.random((n, n_pixels, 2))
    lights = RNG.random((n, 2))
    points = RNG.normal(size=(n_pixels, 3)) * 0.05 + [0.0, 0.0, 0.6]
    normals = RNG.normal(size=(n_pixels, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    positions = RNG.normal(size=(n, 3)) * 0.05
    expected = [np.full((n, n_pixels), np.nan), np.full((n, n_pixels, 3), np.nan),
                *(np.full((n_pixels, 3), np.nan) for _ in range(2)), np.full((n, n_pixels), np.nan)]
    _pixel_by_pixel(color, albedo, basis, lights, usable, residual, values, shading_in, 1.0 / LAM, positions, normals,
                    points, *expected)
    got = [np.full_like(a, np.nan) for a in expected]
    shading_residuals(color, albedo, basis, lights, usable, got[0], got[1])
    weighted_albedo_sums(residual, usable, values, shading_in, 1.0 / LAM, got[2], got[3])
    led_irradiances_into(normals, points, positions, got[4])
    for name, a, b in zip(("shading", "residual", "num", "den", "irradiance"), got, expected):
        assert np.array_equal(a, b), name


@pytest.mark.parametrize("scored", [True, False])
@pytest.mark.parametrize("shared", [True, False])
@pytest.mark.parametrize("n_pixels", [5, FRAME_CHUNK + 123])
def test_albedo_refit_in_one_pass_equals_the_update_and_reevaluation(shared, n_pixels, scored):
    """kernels.albedo_refit_residuals (the host's albedo refit and re-evaluation in one pass)
    against albedo_update, shading_residuals and cauchy_energy in turn, on float32 residuals,
    colours and basis as the solver stores them: the albedo, shading and residuals the same bit
    for bit, the energy to 1e-13 (its factors grouped per pixel, not per 8 stored terms; measured
    ~1e-15); a pixel that no frame sees keeps its albedo. Not ``scored``: the same albedo, shading
    and residuals, and the energy's arrays left as they were."""
    n, f32 = 6, np.float32
    usable = RNG.random((n, n_pixels)) > 0.2
    usable[:, 0] = False
    color = RNG.random((n, n_pixels, 3)).astype(f32)
    basis = RNG.random((1 if shared else n, n_pixels, 2)).astype(f32)
    lights, albedo = RNG.random((n, 2)), RNG.random((n_pixels, 3))
    shading, residual = np.empty((n, n_pixels), f32), np.empty((n, n_pixels, 3), f32)
    shading_residuals(color, albedo, basis, lights, usable, shading, residual)
    residual *= 3.0  # residuals away from the fit, so that the IRLS weights vary
    expected = [a.copy() for a in (shading, residual)]
    num, den, refit = (np.empty((n_pixels, 3)) for _ in range(3))
    albedo_update(expected[1], usable, color, expected[0], 1.0 / LAM, albedo, num, den, refit)
    shading_residuals(color, refit, basis, lights, usable, *expected)
    energy = cauchy_energy(expected[1], LAM)
    got, products, parts = np.full((n_pixels, 3), np.nan), np.ones(n_pixels), np.zeros(-(-n_pixels // FRAME_CHUNK))
    albedo_refit_residuals(residual, usable, color, shading, 1.0 / LAM, albedo, basis, lights, num, den, got,
                           products, parts, scored)
    assert np.array_equal(got, refit) and np.array_equal(got[0], albedo[0])
    assert np.array_equal(shading, expected[0]) and np.array_equal(residual, expected[1])
    if scored:
        assert 0.5 * LAM * LAM * parts.sum() == pytest.approx(energy, rel=1e-13, abs=0)
    else:
        assert np.array_equal(products, np.ones(n_pixels)) and not parts.any()
    assert not np.array_equal(refit, albedo)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("size", [1, 7, 8, 9, 100003])
def test_log1p_square_sum_blocks_equal_the_per_term_float32_logarithms(dtype, size):
    """model.robust.log1p_square_sum (a logarithm per block of LOG_BLOCK factors) against the sum
    of log1p_square_term (the GPU's: a float32 logarithm per term): equal to 1e-9 of the sum (the
    float32 logarithms' rounding, ~1e-7 a term, averages out; measured ~1e-10 on 5.4M D415-like
    residuals), sizes that are no multiple of the block included, and against float64 log1p
    to 1e-6; large residuals (1 + y^2 near the float32 maximum) neither overflow nor lose the sum."""
    from o3d_mvps.model.robust import LOG_BLOCK, log1p_square_sum, log1p_square_term

    x = (RNG.normal(0.0, 0.03, size) * (RNG.random(size) > 0.3)).astype(dtype)
    x[: min(size, 3)] = [5.0, -0.2, 0.0][: min(size, 3)]
    per_term = numba.njit(lambda x, s: sum([log1p_square_term(v, s) for v in x]))
    expected = float(per_term(x, 1.0 / LAM))
    got = log1p_square_sum(x, 1.0 / LAM)
    assert got == pytest.approx(expected, rel=1e-8 if size > 1000 else 1e-7)  # few terms: one float32 logarithm's 6e-8
    assert got == pytest.approx(np.log1p((x.astype(np.float64) / LAM) ** 2).sum(), rel=1e-6)
    big = np.full(2 * LOG_BLOCK, 1e18 * LAM, dtype)  # y = 1e18: each factor 1e36, a block's product 1e288
    assert log1p_square_sum(big, 1.0 / LAM) == pytest.approx(2 * LOG_BLOCK * np.log(1e36), rel=1e-6)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_coded_frames_sample_as_their_decoded_frames(dtype):
    """The sampling kernels read a coded frame ``(codes, table)`` as the float32 frame it decodes
    to: the warped colours, their gradients and the LED's data energy are the same bit for bit
    (per-frame tables with a white balance folded in, points inside, at the border and outside)."""
    from o3d_mvps.colour import CodedColours
    from o3d_mvps.model.se3 import exp
    from o3d_mvps.solver.kernels import led_energy_frame, log_products_sum, warp_gradients, warp_sample

    H, W = 30, 40
    K = np.array([[50.0, 0.0, 19.5], [0.0, 50.0, 14.5], [0.0, 0.0, 1.0]])
    top = np.iinfo(dtype).max
    codes = [RNG.integers(0, top + 1, size=(H, W, 3)).astype(dtype) for _ in range(2)]
    coded = CodedColours.from_codes(codes).divided(RNG.uniform(0.9, 1.1, size=(2, 3)))
    points = RNG.normal(size=(N_PIXELS, 3)) * [0.3, 0.2, 0.3] + [0.0, 0.0, 0.6]
    points[:20, 2] = -0.1  # behind the camera
    poses = np.stack([np.eye(4), exp(np.array([0.02, -0.01, 0.03, 0.05, -0.04, 0.02]))])
    visible = RNG.random((2, N_PIXELS)) > 0.1
    normals = RNG.normal(size=(N_PIXELS, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo, lights, positions = RNG.random((N_PIXELS, 3)), RNG.random((2, 2)), RNG.normal(size=(2, 3)) * 0.05
    results = []
    for image in (coded.frame(1), coded[1]):
        color, usable = np.full((N_PIXELS, 3), np.nan, np.float32), np.zeros(N_PIXELS, bool)
        warp_sample(points, poses[1], K, image, visible[1], color, usable)
        front = points[:, 2] > 0.05
        frame_points, grad_u, grad_v = (np.full((int(front.sum()), 3), np.nan) for _ in range(3))
        warp_gradients(np.ascontiguousarray(points[front]), poses[1], K, image, frame_points, grad_u, grad_v)
        products, parts, seen = np.ones(N_PIXELS), np.zeros(N_PIXELS), np.zeros((2, N_PIXELS), bool)
        led_energy_frame(points, normals, poses, K, image, visible, albedo, lights, positions, 3.0, True, 1, seen,
                         products, parts)
        results.append((color, usable, grad_u, grad_v, seen, log_products_sum(products, parts)))
    assert 0.3 * N_PIXELS < results[0][1].sum() < 0.95 * N_PIXELS and np.abs(results[0][2]).max() > 0.1
    for got, expected in zip(*results):
        np.testing.assert_array_equal(got, expected)


def test_coded_frames_assemble_as_their_decoded_frames():
    """The joint step's per-pixel assembly reads coded frames as their decoded float32 frames:
    every frame in one launch (:func:`accumulate_block`, codes and tables as two tuples) and a
    frame at a time (:func:`accumulate_frame`) write the same sums, rows and twist sums bit for bit."""
    from o3d_mvps.colour import CodedColours, frames_and_tables
    from o3d_mvps.model.se3 import exp
    from o3d_mvps.solver import kernels

    rng = np.random.default_rng(5)
    H, W, N, n, m = 30, 40, 3000, 3, 2
    K = np.array([[50.0, 0.0, 19.5], [0.0, 50.0, 14.5], [0.0, 0.0, 1.0]])
    coded = CodedColours.from_codes([rng.integers(0, 256, (H, W, 3)).astype(np.uint8) for _ in range(n)])
    f = lambda *shape: rng.random(shape)  # noqa: E731
    poses = np.stack([np.eye(4)] + [exp(0.02 * (f(6) - 0.5)) for _ in range(n - 1)])
    points = np.column_stack([(f(N, 2) - 0.5) * 0.5, 0.6 + 0.05 * f(N)])
    r, shading, usable, q = f(n, N, 3) - 0.5, f(n, N), rng.random((n, N)) > 0.2, f(N, 3)
    alpha, beta, gamma, extra_c, albedo = f(n, N) - 0.5, f(n, N) - 0.5, f(n, N), f(N, 3) - 0.5, f(N, 3)
    dshading, frame_slots = f(n, N, 6) - 0.5, np.array([[0, -1], [1, 1], [1, 0]], dtype=np.int64)
    chunks = kernels.chunk_count(N)
    outputs = []
    for frames in ([coded.frame(i) for i in range(n)], list(coded)):
        block = [np.zeros((9, N)), np.zeros((3, N, 3)), np.zeros((3, m, 6, N)), np.zeros((m, 6, N, 3)),
                 np.zeros((m + 1, chunks, 6, 6)), np.zeros((m + 1, chunks, 6))]
        images, tables = frames_and_tables(frames)
        kernels.accumulate_block(r, shading, usable, 25.0, q, alpha, beta, gamma, extra_c, points, poses, K, images,
                                 dshading, albedo, frame_slots, True, *block, kernels.CHUNK, tables)
        single = [np.zeros_like(a) for a in block]
        for i, (with_jacobian, slot) in enumerate(frame_slots):
            kernels.accumulate_frame(r[i], shading[i], usable[i], 25.0, q, alpha[i], beta[i], gamma[i],
                                     extra_c if i == 0 else np.zeros((0, 3)), points, poses[i], K, frames[i],
                                     dshading[i], albedo, bool(with_jacobian), True, *single[:4], int(slot),
                                     single[4][slot], single[5][slot])
        outputs.append(block + single)
    assert np.abs(outputs[0][2]).max() > 0 and np.abs(outputs[0][4][:m]).max() > 0  # rows and Grams written
    for got, expected in zip(*outputs):
        np.testing.assert_array_equal(got, expected)
