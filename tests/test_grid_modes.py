"""The grid modes (issue #31): depth that alternates from pixel to pixel, which the central
differences of the normals do not see. The smoothness's grid-mode rows
(:func:`o3d_mvps.solver.smoothness.grid_mode_rows`, on where
:func:`~o3d_mvps.solver.smoothness.grid_mode_weight` says) and the measurement
(:mod:`benchmarks.grid_modes`)."""

import numpy as np
import scipy.sparse as sp

from benchmarks.grid_modes import grid_mode_amplitude
from o3d_mvps.model.normals import masked_grid
from o3d_mvps.solver import smoothness
from o3d_mvps.solver.pyramid import DepthPrior, build_level


def _disc(h=40, w=50, r=17):
    yy, xx = np.mgrid[:h, :w]
    return (xx - w / 2) ** 2 + (yy - h / 2) ** 2 < r**2


def test_grid_mode_rows_see_the_modes_and_not_a_cubic():
    """A mode of amplitude 1 um along rows, columns or both gives 4 um x sqrt(weight) in the rows
    that cross it (a second difference's 4 um); a cubic surface gives 0 (1e-15 m)."""
    grid = masked_grid(_disc())
    M = smoothness.grid_mode_rows(grid, 4.0)
    u, v = grid.u.astype(float), grid.v.astype(float)
    for mode in ((-1.0) ** grid.u, (-1.0) ** grid.v, (-1.0) ** (grid.u + grid.v)):
        assert np.isclose(np.abs(M @ (1e-6 * mode)).max(), 8e-6)
    cubic = 0.5 + 1e-4 * u - 2e-5 * v**2 + 3e-7 * u**3 - 1e-7 * u * v**2
    assert np.abs(M @ cubic).max() < 1e-15
    central = grid.gradient(1e-6 * (-1.0) ** grid.u)[0]  # unseen by the normals where both neighbours are in
    assert np.abs(central[(grid.wf_u == 0.5) & (grid.wb_u == 0.5)]).max() == 0.0


def test_row_centres_are_the_second_differences_centres_and_the_mode_rows():
    grid = masked_grid(_disc())
    S = smoothness.second_differences(grid)
    assert np.array_equal(smoothness.row_centres(S), S.indices[S.data < 0])
    M = smoothness.grid_mode_rows(grid, 1.0)
    dense = M.toarray()
    assert np.array_equal(smoothness.row_centres(M), np.argmax(np.abs(dense), axis=1))
    assert np.allclose(dense[np.arange(M.shape[0]), smoothness.row_centres(M)], 1.5)
    # slope-weighted and stacked (columns not in order after the products): the same centres
    z0 = 0.5 + 1e-3 * np.random.default_rng(0).normal(size=(20, 25))
    K = np.array([[60.0, 0, 25], [0, 60.0, 20], [0, 0, 1]])
    weighted = smoothness.smoothness_rows(grid, z0, K, 2.0)
    both = smoothness.with_grid_modes(grid, weighted, z0, K, 2.0, weight=1000.0)
    assert np.array_equal(smoothness.row_centres(both), np.concatenate([S.indices[S.data < 0],
                                                                        smoothness.row_centres(M)]))


def test_evidence_weights_leave_the_grid_mode_rows_alone():
    """weigh_smoothness scales the second differences by their centre's weight and keeps the
    grid-mode rows as built."""
    grid = masked_grid(_disc())
    z0 = np.full((20, 25), 0.5)
    S2 = smoothness.second_differences(grid)
    S = smoothness.with_grid_modes(grid, S2, z0, np.diag([100.0, 100.0, 1.0]), 2.0, weight=9.0)
    assert S.shape[0] > S2.shape[0]
    prior = DepthPrior(None, None, S=S)
    weights = np.random.default_rng(0).uniform(1, 50, grid.size)
    prior.weigh_smoothness(weights)
    k = S2.shape[0]
    centre = S2.indices[S2.data < 0]
    assert np.allclose(prior.S[:k].toarray(), (np.sqrt(weights[centre])[:, None] * S2.toarray()))
    assert np.allclose(prior.S[k:].toarray(), S[k:].toarray())
    assert smoothness.with_grid_modes(grid, S2, z0, np.eye(3), 1.0, weight=0.0) is S2


def test_weighing_in_place_keeps_the_pattern_and_the_taps_come_back_bit_for_bit():
    """weigh_smoothness scales each row's entries in place (S's index arrays shared, its
    columns in order): the values of diags(w^0.5) @ S exactly; and from that weighted S
    unweighted_second_differences gives the built S (second differences and grid-mode rows)
    again bit for bit, sharing its index arrays, for each of three weighings in turn."""
    grid = masked_grid(_disc())
    z0 = 0.5 + 1e-3 * np.random.default_rng(1).normal(size=(20, 25))
    K = np.array([[60.0, 0, 25], [0, 60.0, 20], [0, 0, 1]])
    built = smoothness.with_grid_modes(grid, smoothness.second_differences(grid), z0, K, 2.0, weight=1000.0)
    prior = DepthPrior(None, None, S=built.copy())
    prior.rebuild_smoothness_with(smoothness.unweighted_second_differences)
    rng = np.random.default_rng(0)
    for _ in range(3):
        weights = rng.uniform(1, 50, grid.size)
        prior.weigh_smoothness(weights)
        row_weights = weights[smoothness.row_centres(built)]
        row_weights[smoothness.grid_mode_row_flags(built)] = 1.0
        assert np.array_equal(prior.S.indptr, built.indptr) and np.array_equal(prior.S.indices, built.indices)
        product = sp.csr_matrix(sp.diags(row_weights ** 0.5) @ built)  # its columns come reversed
        weighted = prior.S.copy()
        for matrix in (product, weighted):
            matrix.has_sorted_indices = False
            matrix.sort_indices()
        assert np.array_equal(weighted.data, product.data) and np.array_equal(weighted.indices, product.indices)
        restored = smoothness.unweighted_second_differences(prior.S)
        assert np.shares_memory(restored.indices, prior.S.indices) and np.array_equal(restored.data, built.data)
        assert not np.array_equal(prior.S.data, built.data)


def test_grid_mode_amplitude_measures_a_planted_mode():
    """On a tilted, curved surface (depth 0.5 m) the measure is below 0.01 um; planted modes of
    3 um (checkerboard) and 2 um (along rows) read back to 1 %."""
    h, w = 60, 80
    yy, xx = np.mgrid[:h, :w].astype(float)
    surface = 0.5 + 1e-4 * xx + 2e-6 * (yy - 30) ** 2
    mask = np.ones((h, w), bool)
    clean = grid_mode_amplitude(surface, mask)
    assert max(clean.values()) < 0.01, clean
    got = grid_mode_amplitude(surface + 3e-6 * (-1.0) ** (xx + yy), mask)
    assert abs(got["checkerboard_um"] - 3.0) < 0.03, got
    got = grid_mode_amplitude(surface + 2e-6 * (-1.0) ** xx, mask)
    assert abs(got["rows_um"] - 2.0) < 0.02 and got["cols_um"] < 0.01 and got["checkerboard_um"] < 0.01, got


def test_grid_mode_rows_hold_the_mode_a_mesh_shows(monkeypatch):
    """An LED bunny, 320x240, SF 4, 6 frames, given poses: refined without the grid-mode rows
    and with them at weight 1000 (the LED's default with 6 frames). The mode's median amplitude along rows and the
    forward-difference (mesh) normal error fall (measured: rows 16.1 -> 5.0 um, mesh normals
    6.11 -> 5.17 deg); bounds at 0.5 x and 0.92 x the default's. The central-difference error
    does not get worse (5.08 -> 4.89 deg; bound +2 %)."""
    from benchmarks.grid_modes import score
    from o3d_mvps import RefineOptions, refine, synthetic

    capture = synthetic.render_capture("bunny", frames=6, size=(320, 240), scale_factor=4, seed=0, distance=0.3)
    got = {}
    for weight in (0.0, 1000.0):
        monkeypatch.setattr(smoothness, "GRID_MODE_WEIGHT", weight)
        result = refine(capture, RefineOptions(progress=False), initial_poses=capture.groundtruth.poses)
        got[weight] = score(result.depth_array(), result.mask_array(), capture.color_K(), capture.groundtruth)
    off, on = got[0.0], got[1000.0]
    assert on["rows_um"] < 0.5 * off["rows_um"], got
    assert on["mae_forward_deg"] < 0.92 * off["mae_forward_deg"], got
    assert on["mae_central_deg"] < 1.02 * off["mae_central_deg"], got


def test_the_device_weighing_keeps_the_grid_mode_rows_as_the_host_does():
    """On a GPU (the CuPy stand-in) weigh_smoothness scales S's entries in one fused kernel with
    each row's centre and kept-weight flag, copied once: the same matrix as the host's."""
    import cupy_emulation as cp

    from o3d_mvps.solver.device import to_host

    grid = masked_grid(_disc())
    S2 = smoothness.second_differences(grid)
    S = smoothness.with_grid_modes(grid, S2, np.full((20, 25), 0.5), np.diag([100.0, 100.0, 1.0]), 2.0, weight=9.0)
    weights = np.random.default_rng(1).uniform(1, 50, grid.size)
    host = DepthPrior(None, None, S=S)
    host.weigh_smoothness(weights)
    with cp.installed():
        device = DepthPrior(None, None, S=cp.array_device().sparse_matrix(S))
        device.weigh_smoothness(cp.asarray(weights))
        data, indptr, indices = (to_host(a) for a in (device.S.data, device.S.indptr, device.S.indices))
    got = sp.csr_matrix((data, indices, indptr), shape=S.shape)  # the device keeps S's entry order
    np.testing.assert_allclose(got.toarray(), host.S.toarray(), rtol=1e-14, atol=0)
    assert not np.allclose(got[S2.shape[0]:].toarray(), 0) and np.allclose(got[S2.shape[0]:].toarray(), S[S2.shape[0]:].toarray())


def test_the_rows_are_on_by_light_model_frames_and_level():
    """grid_mode_weight: the LED with enough frames and the point lights' finer levels get
    GRID_MODE_WEIGHT, room light, few LED frames and the lamp-placing levels none; build_level
    adds rows of the weight it gives for the level's object pixels."""
    w = smoothness.GRID_MODE_WEIGHT
    assert w > 0
    assert smoothness.grid_mode_weight("led", 20, 100) == w
    assert smoothness.grid_mode_weight("led", smoothness.GRID_MODE_MIN_FRAMES - 1, 10**6) == 0.0
    assert smoothness.grid_mode_weight("point", 12, 20000, lamp_level_pixels=20000) == 0.0
    assert smoothness.grid_mode_weight("point", 12, 20001, lamp_level_pixels=20000) == w
    assert smoothness.grid_mode_weight("room", 20, 10**6) == 0.0 and smoothness.grid_mode_weight("sh", 20, 10**6) == 0.0
    mask = _disc()
    colors = [np.random.default_rng(0).uniform(0.2, 0.8, mask.shape + (3,)).astype(np.float32)]
    K = np.array([[60.0, 0, 25], [0, 60.0, 20], [0, 0, 1]])
    z0 = np.full((20, 25), 0.5)
    asked = []

    def rule(pixels):
        asked.append(pixels)
        return 9.0 if pixels > 500 else 0.0

    fine, coarse = (build_level(i, colors, [None], mask, K, z0, 2, grid_modes=rule) for i in (0, 1))
    assert asked == [fine.grid.size, coarse.grid.size] and coarse.grid.size < 500 < fine.grid.size
    assert smoothness.grid_mode_row_flags(fine.prior.S).any()
    assert not smoothness.grid_mode_row_flags(coarse.prior.S).any()
    assert not smoothness.grid_mode_row_flags(build_level(0, colors, [None], mask, K, z0, 2).prior.S).any()


def test_the_stencil_rows_are_those_of_their_triplets():
    """:func:`.smoothness.second_differences` and :func:`.smoothness.grid_mode_rows`, built as CSR
    directly, equal the matrices of their (row, column, value) triplets (the COO build they
    replaced): index arrays and dtypes, columns ascending, values; on a ragged mask, both schemes
    alike (rows at the pixels whose two neighbours are masked, read off the mask here; the forward
    scheme once had none, so its smoothness did nothing)."""
    mask = _disc() & (np.random.default_rng(1).random((40, 50)) > 0.05)
    for scheme in ("central", "forward"):
        grid = masked_grid(mask, scheme)
        own = np.arange(grid.size)
        for M, taps, reach in ((smoothness.second_differences(grid), [1.0, -2.0, 1.0], 1),
                               (smoothness.grid_mode_rows(grid, 4.0), [0.5, -2.0, 3.0, -2.0, 0.5], 2)):
            rows, cols, vals, count = [], [], [], 0
            padded = np.pad(mask, 1)
            for fwd, bwd, (du, dv) in ((grid.fwd_u, grid.bwd_u, (1, 0)), (grid.fwd_v, grid.bwd_v, (0, 1))):
                u, v = grid.u + 1, grid.v + 1
                inner = padded[v + dv, u + du] & padded[v - dv, u - du]
                both = own[inner & inner[fwd] & inner[bwd]] if reach == 2 else own[inner]
                stencil = ([bwd[bwd[both]], bwd[both], both, fwd[both], fwd[fwd[both]]] if reach == 2
                           else [bwd[both], both, fwd[both]])
                rows += [count + np.arange(both.size)] * len(taps)
                cols += stencil
                vals += [np.full(both.size, t) for t in taps]
                count += both.size
            expected = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                     shape=(count, grid.size))
            assert M.shape == expected.shape and M.nnz > 0 and M.has_sorted_indices
            for a, b in ((M.indptr, expected.indptr), (M.indices, expected.indices), (M.data, expected.data)):
                assert a.dtype == b.dtype and np.array_equal(a, b)
