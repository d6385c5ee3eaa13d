"""Compiled per-pixel loops of the solver (numba, parallel over pixels or pixel chunks).

Each kernel reads its per-pixel arrays once and writes or accumulates everything a step needs
from them, where the vectorised NumPy form made a dozen temporaries of frames x pixels x
channels (x 6) per step. The maths is documented where it is used (:mod:`.normal_equations`,
:mod:`.problem`, :mod:`.reflectance`); these are its loops. Reductions over pixels (the 6x6
twist Gram) go to per-chunk partial sums added up afterwards, so threads never share an
accumulator.

Each kernel's work on one pixel (or one pixel of one frame) is a function of its own
(``*_pixel``), which the CPU loops here and the CUDA kernels of :mod:`.cuda_kernels` both call:
one copy of the maths for both devices. They allocate nothing (scratch arrays come from the
caller) and live in this file because numba's on-disk cache of a kernel is invalidated only by
changes to the kernel's own source file, and the CPU kernels inline them.
:mod:`.cuda_kernels` has the same launchers with the same arguments; a caller picks a module.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..model.robust import log1p_square_sum, log1p_square_term, square_factor  # noqa: F401 - log1p_square_sum re-exported: the same names as .cuda_kernels
from ..model.normals import unit_normal_at
from ..model.shading import (FRAME_CHUNK, frame_chunk, led_fields_into, led_irradiance_at, led_irradiance_of,  # noqa: F401
                             led_field_of, led_irradiance, led_irradiances_into, led_point_gradient,
                             led_point_gradient_of, led_point_gradients_into, led_position, twist_row_into)

# OpenMP first: the TBB that Open3D's wheels may put on the path can be too old for numba,
# which then warns on every first parallel call.
numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

#: Pixels per chunk of the parallel loops: large enough to amortise a chunk's set-up, small
#: enough to balance the threads.
CHUNK = 16384


def chunk_count(n_pixels: int) -> int:
    """Number of pixel chunks of :data:`CHUNK` pixels covering ``n_pixels``: the rows of
    :func:`accumulate_frame`'s partial sums."""
    return max(1, -(-n_pixels // CHUNK))


@numba.njit(inline="always")
def twist_jacobian_row(gu, gv, fx, fy, iz, X, Y, Z, J, c):  # pragma: no cover - compiled
    """Row c of J (3, 6): channel c's photometric Jacobian in the twist (translation, rotation) at
    a pixel whose frame point is (X, Y, Z) metres (iz = 1 / Z), its colour gradient (gu, gv) per
    pixel at the projection, focal lengths fx, fy (pixels): the gradient chained with the
    projection, dI/d(X', Y', Z') = (a, b, c), then the point's motion (rotation: P' x (a, b, c))."""
    ja = gu * fx * iz  # dI/dX'
    jb = gv * fy * iz  # dI/dY'
    jc = -iz * (ja * X + jb * Y)  # dI/dZ'
    J[c, 0] = ja
    J[c, 1] = jb
    J[c, 2] = jc
    J[c, 3] = Y * jc - Z * jb
    J[c, 4] = Z * ja - X * jc
    J[c, 5] = X * jb - Y * ja


@numba.njit(cache=True)
def pose_sums(points, grad_u, grad_v, K, color, albedo, shading, dshading, shaded, inv_lam, H,
              g):  # pragma: no cover - compiled
    """A frame's pose Gauss-Newton system H (6, 6) and g (6,) on the host, written, in one pass
    over its N usable pixels (:func:`o3d_mvps.solver.pose.pose_system`): each pixel's Jacobian rows
    (:func:`twist_jacobian_row`, minus albedo x ``dshading`` (N, 6) where ``shaded``), its
    residuals ``color - albedo shading`` (color (N, 3) float32, albedo (N, 3), shading (N,)) and
    their Cauchy IRLS weights, summed pixel by pixel: ``H = sum w J^T J``, ``g = sum w J^T r``.
    points, grad_u, grad_v (N, 3): the frame points and colour gradients at their projections
    (:func:`warp_gradients`); K (3, 3). Replaces some 30 NumPy calls a system: the coarse levels'
    pose steps, 492 systems of 340-22 000 pixels a D415 refine."""
    H[:] = 0.0
    g[:] = 0.0
    J = np.empty((3, 6))
    fx, fy = K[0, 0], K[1, 1]
    for p in range(points.shape[0]):
        X, Y, Z = points[p, 0], points[p, 1], points[p, 2]
        iz = 1.0 / Z
        for c in range(3):
            twist_jacobian_row(grad_u[p, c], grad_v[p, c], fx, fy, iz, X, Y, Z, J, c)
            if shaded:
                for k in range(6):
                    J[c, k] -= albedo[p, c] * dshading[p, k]
            r = np.float64(color[p, c]) - albedo[p, c] * shading[p]
            y = r * inv_lam
            w = 1.0 / (y * y + 1.0)
            for k in range(6):
                wj = J[c, k] * w
                g[k] += wj * r
                for m in range(6):
                    H[k, m] += wj * J[c, m]


@numba.njit(inline="always")
def accumulate_pixel(p, r, shading, use, inv_lam, q, alpha, beta, gamma, extra_c, points_ref, pose, K, image,
                     dshading, albedo, with_jacobian, parallax, sums, e, rows, F, slot, J, G, b, wq, wc):  # pragma: no cover
    """:func:`accumulate_frame`'s work on pixel p: its sums, e, rows and F entries, and its
    twist Gram and right-hand side added to G (6, 6) and b (6,). Scratch: J (3, 6), wq (6,),
    wc (6,).

    The channels' Jacobian rows J[c] are formed first; the twist sums then take all three
    channels at once per entry (one update of G, b, rows and F per pixel, not per channel)."""
    project = e.shape[0] > 0
    with_extra = extra_c.shape[0] > 0
    with_dshading = dshading.shape[0] > 0
    with_F = F.shape[0] > 0
    emit = with_jacobian and slot >= 0
    fx, fy = K[0, 0], K[1, 1]
    al, be = alpha[p], beta[p]
    W = 0.0
    Wqc = 0.0
    Wqr = 0.0
    Sgg = 0.0
    Bg = 0.0
    jac = with_jacobian and use[p]
    X = Y = Z = iz = u = v = ray_x = ray_y = ray_z = 0.0
    if jac:
        x, y, z = points_ref[p, 0], points_ref[p, 1], points_ref[p, 2]
        X, Y, Z, u, v = project_point(pose, K, x, y, z)
        iz = 1.0 / Z
        rx, ry = x / z, y / z  # d(point)/d(z) = (rx, ry, 1) in the reference frame, the pose's rotation times that in frame i's
        ray_x = pose[0, 0] * rx + pose[0, 1] * ry + pose[0, 2]
        ray_y = pose[1, 0] * rx + pose[1, 1] * ry + pose[1, 2]
        ray_z = pose[2, 0] * rx + pose[2, 1] * ry + pose[2, 2]
    g0 = g1 = g2 = g3 = g4 = g5 = 0.0
    if jac:
        g0, g1, g2, g3, g4, g5 = image_gradients_at(image, u, v)
    for c in range(3):
        wc_ = 0.0
        if use[p]:
            x_ = r[p, c] * inv_lam
            wc_ = 1.0 / (1.0 + x_ * x_)  # the Cauchy IRLS weight
        qc = q[p, c]
        cc = -qc * gamma[p]
        if with_extra:
            cc += extra_c[p, c]
        if jac:
            gu, gv = (g0, g1) if c == 0 else ((g2, g3) if c == 1 else (g4, g5))
            twist_jacobian_row(gu, gv, fx, fy, iz, X, Y, Z, J, c)
            if with_dshading:
                for j in range(6):
                    J[c, j] -= albedo[p, c] * dshading[p, j]
            if parallax:
                cc += J[c, 0] * ray_x + J[c, 1] * ray_y + J[c, 2] * ray_z
        wq_ = wc_ * qc
        W += wq_ * qc
        Wqc += wq_ * cc
        Wqr += wq_ * r[p, c]
        Sgg += wc_ * cc * cc
        Bg += wc_ * cc * r[p, c]
        ws = wc_ * shading[p]
        if project:
            wsq = ws * qc
            e[0, p, c] -= wsq * al
            e[1, p, c] -= wsq * be
            e[2, p, c] += ws * cc
        # per channel: w, w q, w c, w r for the twist sums below
        wq[c] = wc_
        wq[3 + c] = wq_
        wc[c] = wc_ * cc
        wc[3 + c] = wc_ * r[p, c]
    sums[0, p] += W * al * al
    sums[1, p] += W * be * be
    sums[2, p] += Sgg
    sums[3, p] += W * al * be
    sums[4, p] -= al * Wqc
    sums[5, p] -= be * Wqc
    sums[6, p] -= al * Wqr
    sums[7, p] -= be * Wqr
    sums[8, p] += Bg
    if not emit:
        return
    if not jac:
        for j in range(6):
            rows[0, slot, j, p] = 0.0
            rows[1, slot, j, p] = 0.0
            rows[2, slot, j, p] = 0.0
            if with_F:
                for c in range(3):
                    F[slot, j, p, c] = 0.0
        return
    w0, w1, w2 = wq[0], wq[1], wq[2]
    sh = shading[p]
    for j in range(6):
        J0, J1, J2 = J[0, j], J[1, j], J[2, j]
        wJ0, wJ1, wJ2 = w0 * J0, w1 * J1, w2 * J2
        for k in range(j, 6):
            G[j, k] += wJ0 * J[0, k] + wJ1 * J[1, k] + wJ2 * J[2, k]
        b[j] -= wc[3] * J0 + wc[4] * J1 + wc[5] * J2
        wqJ = wq[3] * J0 + wq[4] * J1 + wq[5] * J2  # sum_c w q J
        rows[0, slot, j, p] = -al * wqJ
        rows[1, slot, j, p] = -be * wqJ
        rows[2, slot, j, p] = wc[0] * J0 + wc[1] * J1 + wc[2] * J2  # sum_c w c J
        if with_F:
            F[slot, j, p, 0] = sh * wJ0
            F[slot, j, p, 1] = sh * wJ1
            F[slot, j, p, 2] = sh * wJ2


@numba.njit(inline="always")
def pixel_scratch():  # pragma: no cover - compiled
    """A thread's scratch for :func:`accumulate_pixel`: J (3, 6), G (6, 6), b, wqJ, wcJ (6,), zeros."""
    return np.zeros((3, 6)), np.zeros((6, 6)), np.zeros(6), np.zeros(6), np.zeros(6)


@numba.njit(inline="always")
def store_partial_sums(G, b, gram, rhs, k):  # pragma: no cover - compiled
    """Row k of the partial sums: gram[k] (6, 6) = G, rhs[k] (6,) = b."""
    for j in range(6):
        rhs[k, j] = b[j]
        for i in range(6):
            gram[k, j, i] = G[j, i]


@numba.njit(parallel=True, cache=True)
def accumulate_frame(r, shading, use, inv_lam, q, alpha, beta, gamma, extra_c, points_ref, pose, K, image, dshading,
                     albedo, with_jacobian, parallax, sums, e, rows, F, slot, gram, rhs):  # pragma: no cover - compiled
    """Add frame i's depth rows to the per-pixel sums and, with its pose Jacobian, write its
    twist rows: the whole per-pixel sweep of the Gauss-Newton assembly in one pass.

    Per pixel p and channel c, with residual r (N, 3), the Cauchy IRLS weight
    ``w = use / (1 + (r inv_lam)^2)`` (use (N,) bool), q = albedo / dA (N, 3) and the frozen
    light field's row coefficients alpha, beta, gamma (N,): the residual's row in dz is
    ``a Du + b Dv + c I`` with ``a = -q alpha``, ``b = -q beta``, ``c = -q gamma + extra_c + g``
    (g: the parallax d(residual)/dz through the warp, when ``parallax``; extra_c (N, 3) or
    (0, 3) for none).

    sums (9, N) += Saa, Sbb, Sgg, Sab, Sag, Sbg, Ba, Bb, Bg (w-weighted products of a, b, c and
    r summed over channels); e (3, N, 3) (0-sized: no albedo projection) += ws a, ws b, ws c
    with ws = w shading (N,), the frame's shading.

    with_jacobian: the pose Jacobian J (3, 6) per usable pixel (zero elsewhere): the frame's
    colour gradients at the reference points points_ref (N, 3) metres warped by the frame's pose
    (4, 4) and projected by K (3, 3) into its (H, W, 3) image
    (:func:`warp_gradients_pixel`'s), chained with the projection, minus albedo (N, 3) x
    dshading (N, 6) (or (0, 6)). Then, in slot ``slot`` of rows (3, m, 6, N): ``sum_c w q J``
    times -alpha and -beta, and ``sum_c w c J``; of F (m, 6, N, 3) (0-sized: none): ws J;
    and per pixel chunk: gram (chunks, 6, 6), the upper triangle of the frame's Gram sum w J^T J
    (lower triangle 0), and rhs (chunks, 6) = -sum w r J, chunks = :func:`chunk_count` (N).
    Twist-component-major arrays, so that each pixel's writes stream. slot -1: J only for the
    parallax, no twist rows.
    """
    n = r.shape[0]
    for chunk in numba.prange(rhs.shape[0]):
        J, G, b, wqJ, wcJ = pixel_scratch()
        for p in range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK)):
            accumulate_pixel(p, r, shading, use, inv_lam, q, alpha, beta, gamma, extra_c, points_ref, pose, K, image,
                             dshading, albedo, with_jacobian, parallax, sums, e, rows, F, slot, J, G, b, wqJ, wcJ)
        store_partial_sums(G, b, gram, rhs, chunk)


@numba.njit(parallel=True, cache=True)
def accumulate_block(residual, shading, usable, inv_lam, q, alpha, beta, gamma, extra_c, points_ref, poses, K, images,
                     dshading, albedo, frame_slots, parallax, sums, e, rows, F, gram, rhs, chunk_pixels,
                     tables=None):  # pragma: no cover
    """:func:`accumulate_frame` of every frame in one launch (the host's assembly block), in
    parallel over chunks of ``chunk_pixels`` pixels, each taking the frames in turn: each
    pixel's sums take the frames in the same order as one launch per frame, so sums, e, rows and
    F are the same bit for bit; the twist sums are per (frame, chunk), so with
    ``chunk_pixels`` = :data:`CHUNK` they are too (smaller chunks add the pixels' terms in another
    order: the same to rounding).

    images: a tuple of the frames' (H, W, 3) images; tables: None, or for coded frames a tuple of
    their (3, K) tables, ``images`` then holding their codes (:func:`frame_at`: a tuple of
    ``(codes, table)`` pairs is a nested tuple, which numba's parallel loops cannot take);
    dshading (n, N, 6) or (n, 0, 6) for none
    (frames without a Jacobian do not read theirs); gram (m + 1, chunks, 6, 6) and rhs
    (m + 1, chunks, 6) with chunks = ceil(N / chunk_pixels); frames without a slot write no
    twist sums. The other arguments as :func:`accumulate_frames`'s."""
    n, N = residual.shape[0], residual.shape[1]
    for chunk in numba.prange(rhs.shape[1]):
        J, G, b, wqJ, wcJ = pixel_scratch()
        first, last = chunk * chunk_pixels, min(N, (chunk + 1) * chunk_pixels)
        for i in range(n):
            slot = frame_slots[i, 1]
            jac = frame_slots[i, 0] != 0
            ex = extra_c
            if i > 0:
                ex = extra_c[:0]
            G[:] = 0.0
            b[:] = 0.0
            r_i, sh_i, use_i = residual[i], shading[i], usable[i]
            al_i, be_i, ga_i = alpha[i], beta[i], gamma[i]
            pose, image, ds = poses[i], frame_at(images, tables, i), dshading[i]
            for p in range(first, last):
                accumulate_pixel(p, r_i, sh_i, use_i, inv_lam, q, al_i, be_i, ga_i, ex, points_ref, pose, K, image,
                                 ds, albedo, jac, parallax, sums, e, rows, F, slot, J, G, b, wqJ, wcJ)
            if slot >= 0:
                store_partial_sums(G, b, gram[slot], rhs[slot], chunk)


def accumulate_frames(residual, shading, usable, inv_lam, q, alpha, beta, gamma, extra_c, points_ref, poses, K,
                      images, dshading, albedo, frame_slots, parallax, sums, e, rows, F, gram, rhs) -> None:
    """:func:`accumulate_frame` of every frame in turn (the GPU's one launch per assembly block;
    the host's solver calls :func:`accumulate_frame` a frame at a time, with the same result).

    Per frame i: residual[i] (N, 3), shading[i], usable[i], alpha[i], beta[i], gamma[i] (N,),
    poses[i] (4, 4), images[i] (H, W, 3), dshading[i] (N, 6) or (0, 6) for none;
    frame_slots (n, 2) int64: with_jacobian (0 or 1) and the twist slot (-1: none); extra_c
    (N, 3) or (0, 3) is frame 0's only. gram (m + 1, chunks, 6, 6), rhs (m + 1, chunks, 6): the
    partial sums of slot k in row k, of the frames without a slot in the last row. The other
    arguments as :func:`accumulate_frame`'s."""
    for i in range(len(residual)):
        slot = int(frame_slots[i, 1])
        accumulate_frame(residual[i], shading[i], usable[i], inv_lam, q, alpha[i], beta[i], gamma[i],
                         extra_c if i == 0 else extra_c[:0], points_ref, poses[i], K, images[i], dshading[i], albedo,
                         bool(frame_slots[i, 0]), parallax, sums, e, rows, F, slot, gram[slot], rhs[slot])


@numba.njit(inline="always")
def projected_twist_pixel(rows, F, scaled, sqrt_inv_d, f, j, p):  # pragma: no cover - compiled
    """Pixel p's entries (a, b, c) of twist row (f, j) once projected (``rows[k, f, j, p] -
    sum_c scaled[k, p, c] F[f, j, p, c]``), returned; its F entries scaled by sqrt_inv_d in place."""
    F0, F1, F2 = F[f, j, p, 0], F[f, j, p, 1], F[f, j, p, 2]
    a = rows[0, f, j, p] - (scaled[0, p, 0] * F0 + scaled[0, p, 1] * F1 + scaled[0, p, 2] * F2)
    b = rows[1, f, j, p] - (scaled[1, p, 0] * F0 + scaled[1, p, 1] * F1 + scaled[1, p, 2] * F2)
    c = rows[2, f, j, p] - (scaled[2, p, 0] * F0 + scaled[2, p, 1] * F1 + scaled[2, p, 2] * F2)
    F[f, j, p, 0] = F0 * sqrt_inv_d[p, 0]
    F[f, j, p, 1] = F1 * sqrt_inv_d[p, 1]
    F[f, j, p, 2] = F2 * sqrt_inv_d[p, 2]
    return a, b, c


@numba.njit(inline="always")
def project_twist_pixel(rows, F, scaled, sqrt_inv_d, f, j, p):  # pragma: no cover - compiled
    """:func:`project_twist_rows` on pixel p of twist component j of frame slot f."""
    rows[0, f, j, p], rows[1, f, j, p], rows[2, f, j, p] = projected_twist_pixel(rows, F, scaled, sqrt_inv_d, f, j, p)


@numba.njit(parallel=True, cache=True)
def project_twist_rows(rows, F, scaled, sqrt_inv_d):  # pragma: no cover - compiled
    """The albedo projection of the twist rows, in place: rows (3, m, 6, N) lose
    ``sum_c scaled[k, p, c] F[., ., p, c]`` and F (m, 6, N, 3) is scaled by sqrt_inv_d (N, 3)."""
    m, N = F.shape[0], F.shape[2]
    for f in numba.prange(m):
        for j in range(6):
            for p in range(N):
                project_twist_pixel(rows, F, scaled, sqrt_inv_d, f, j, p)


@numba.njit(parallel=True, cache=True)
def scatter_sparse_transpose_rows(indptr, indices, data, X, out):  # pragma: no cover - compiled
    """out (k, C) += (A^T X^T)^T, i.e. each row x (R,) of X (k, R) adds A^T x, for a CSR matrix
    A (R, C) given by its arrays (a block of rows of a larger operator scatters into all its
    columns); in parallel over X's rows, so threads never share an output row."""
    for j in numba.prange(X.shape[0]):
        for row in range(X.shape[1]):
            x = X[j, row]
            for nz in range(indptr[row], indptr[row + 1]):
                out[j, indices[nz]] += data[nz] * x


@numba.njit(inline="always")
def scatter_row(indptr, indices, data, p, x, out):  # pragma: no cover - compiled
    """out (N,) += x A[p]^T: row p's entries of the CSR matrix A (its arrays) scaled by x, in
    stored order. A row of exactly two entries (the central and one-sided differences once
    their stored zeros are gone: every row on the solver's grids) is unrolled: the same additions
    in the same order, without the entry loop's bounds."""
    start, stop = indptr[p], indptr[p + 1]
    if stop - start == 2:
        out[indices[start]] += data[start] * x
        out[indices[start + 1]] += data[start + 1] * x
    else:
        for nz in range(start, stop):
            out[indices[nz]] += data[nz] * x


@numba.njit(inline="always")
def scatter_stencil_row(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, p, a, b, out):  # pragma: no cover
    """out (N,) += a Du[p]^T + b Dv[p]^T (:func:`scatter_row` of each difference operator, Du's
    first; project_stencil_rows 5.6 -> 4.9 ms a 2 MP block on one thread with the unrolled rows)."""
    scatter_row(u_indptr, u_indices, u_data, p, a, out)
    scatter_row(v_indptr, v_indices, v_data, p, b, out)


@numba.njit(parallel=True, cache=True)
def add_stencil_transpose_rows(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, rows, first, out):  # pragma: no cover
    """out (k, N) += the rows' stencil transpose ``Du_b^T a + Dv_b^T b + c`` per row of
    ``rows`` (3, k, B) = (a, b, c), for the rows Du_b, Dv_b (B, N) (CSR arrays) of the difference
    operators at the block of pixels first..first+B, whose c lands on columns first..first+B:
    :func:`scatter_sparse_transpose_rows` of both operators and the identity part in one pass
    (:func:`scatter_stencil_row`); in parallel over the k rows, so threads never share an output row."""
    for j in numba.prange(rows.shape[1]):
        out_j = out[j]
        for p in range(rows.shape[2]):
            out_j[first + p] += rows[2, j, p]
            scatter_stencil_row(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, p, rows[0, j, p],
                                rows[1, j, p], out_j)


@numba.njit(cache=True)
def two_entry_stencil(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data):  # pragma: no cover - compiled
    """The block's stencil rows (B of each difference operator, CSR arrays as
    :func:`add_stencil_transpose_rows` takes them) as (columns (B, 4) int64, weights (B, 4)): row p's
    two entries of Du in stored order, then its two of Dv, where every row of both holds exactly
    two (the solver's grids once the stored zeros are gone); else 0-row arrays."""
    B = u_indptr.shape[0] - 1
    for p in range(B):
        if u_indptr[p + 1] - u_indptr[p] != 2 or v_indptr[p + 1] - v_indptr[p] != 2:
            return np.empty((0, 4), np.int64), np.empty((0, 4))
    columns, weights = np.empty((B, 4), np.int64), np.empty((B, 4))
    for p in range(B):
        u, v = u_indptr[p], v_indptr[p]
        columns[p, 0], columns[p, 1], columns[p, 2], columns[p, 3] = u_indices[u], u_indices[u + 1], v_indices[v], \
            v_indices[v + 1]
        weights[p, 0], weights[p, 1], weights[p, 2], weights[p, 3] = u_data[u], u_data[u + 1], v_data[v], v_data[v + 1]
    return columns, weights


@numba.njit(parallel=True, cache=True)
def project_stencil_rows(rows, F, scaled, sqrt_inv_d, u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, first,
                         out):  # pragma: no cover - compiled
    """:func:`project_twist_rows` and then :func:`add_stencil_transpose_rows` of the projected
    rows in one pass (the host's): rows (3, m, 6, B) are read once and not written back (each
    projected entry goes straight into out (6m, N)); F (m, 6, B, 3) is scaled in place. The
    same operations in the same order as the two kernels, so the same values.

    Where every stencil row holds two entries, they are read from :func:`two_entry_stencil`'s
    arrays, four fixed additions a pixel instead of the CSR rows' offsets and counts re-read for
    each of the 6m twist rows (a 2 MP block of 4096 pixels and 19 refined frames, one thread:
    5.0 -> 3.05 ms, the same U bit for bit)."""
    m, B = F.shape[0], F.shape[2]
    columns, weights = two_entry_stencil(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data)
    two = columns.shape[0] == B
    for row in numba.prange(6 * m):
        f, j = row // 6, row % 6
        out_row = out[row]
        if two:
            for p in range(B):
                a, b, c = projected_twist_pixel(rows, F, scaled, sqrt_inv_d, f, j, p)
                out_row[first + p] += c
                out_row[columns[p, 0]] += weights[p, 0] * a
                out_row[columns[p, 1]] += weights[p, 1] * a
                out_row[columns[p, 2]] += weights[p, 2] * b
                out_row[columns[p, 3]] += weights[p, 3] * b
        else:
            for p in range(B):
                a, b, c = projected_twist_pixel(rows, F, scaled, sqrt_inv_d, f, j, p)
                out_row[first + p] += c
                scatter_stencil_row(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, p, a, b, out_row)


@numba.njit(parallel=True, cache=True, fastmath={"reassoc"})
def rows_times(A, x, out):  # pragma: no cover - compiled
    """out (k,) = A x for A (k, N) C-ordered (float32 or float64) and x (N,) float64, each
    row's sum in float64; in parallel over A's rows."""
    for j in numba.prange(A.shape[0]):
        total = 0.0
        for p in range(A.shape[1]):
            total += A[j, p] * x[p]
        out[j] = total


@numba.njit(parallel=True, cache=True)
def columns_times(A, y, out):  # pragma: no cover - compiled
    """out (N,) = A^T y for A (k, N) C-ordered (float32 or float64) and y (k,) float64, in
    float64; in parallel over chunks of :data:`CHUNK` columns, each reading A's rows in order.
    Each out[p] sums its terms in row order from 0; four rows per pass over the chunk (one load
    and store of out[p] per four terms, not per term: 7.4 -> 3.0 ms a D415 product, the same
    sums bit for bit)."""
    N, k = A.shape[1], A.shape[0]
    for chunk in numba.prange((N + CHUNK - 1) // CHUNK):
        first, last = chunk * CHUNK, min(N, (chunk + 1) * CHUNK)
        for p in range(first, last):
            out[p] = 0.0
        j = 0
        while j + 4 <= k:
            y0, y1, y2, y3 = y[j], y[j + 1], y[j + 2], y[j + 3]
            for p in range(first, last):
                out[p] = (((out[p] + A[j, p] * y0) + A[j + 1, p] * y1) + A[j + 2, p] * y2) + A[j + 3, p] * y3
            j += 4
        for j in range(j, k):
            yj = y[j]
            for p in range(first, last):
                out[p] += A[j, p] * yj


@numba.njit(inline="always")
def csr_row_dot(indptr, indices, data, v, row):  # pragma: no cover - compiled
    """(A v)[row] of a CSR matrix A given by its arrays."""
    total = 0.0
    for nz in range(indptr[row], indptr[row + 1]):
        total += data[nz] * v[indices[nz]]
    return total


@numba.njit(inline="always")
def chebyshev_row(indptr, indices, data, r, v, d, scale, diagonal, factor, x, r_out, d_out, x_out, row):  # pragma: no cover
    """:func:`chebyshev_update` on one row, its diagonal ``factor diagonal`` (:func:`multigrid_cg`:
    a step's scalar times the level's scaled D^-1; 1 elsewhere). r_out, x_out may be r, x."""
    r_new = r[row] - csr_row_dot(indptr, indices, data, v, row)
    d_new = d[row] * scale + (factor * diagonal[row]) * r_new
    r_out[row] = r_new
    d_out[row] = d_new
    x_out[row] = x[row] + d_new


@numba.njit(parallel=True, cache=True)
def chebyshev_update(indptr, indices, data, r, v, d, scale, diagonal, x, r_out, d_out, x_out):  # pragma: no cover
    """One step of the multigrid's Chebyshev smoother (:class:`.krylov.ChebyshevSmoother`) for a
    CSR matrix A (N, N) given by its arrays, vectors (N,): ``r_out = r - A v``, ``d_out = scale d
    + diagonal r_out``, ``x_out = x + d_out`` (the outputs are other arrays than the inputs: A v
    reads v's neighbours). A step is v = d; the restart from x is r = b, v = x, scale 0."""
    for row in numba.prange(r.shape[0]):
        chebyshev_row(indptr, indices, data, r, v, d, scale, diagonal, 1.0, x, r_out, d_out, x_out, row)


@numba.njit(parallel=True, cache=True)
def csr_multiply_add(indptr, indices, data, alpha, v, y, out):  # pragma: no cover - compiled
    """``out = y + alpha A v`` (out (N,), another array than v) for a CSR matrix A (N, M) given
    by its arrays, v (M,), y (N,): the multigrid's residual ``b - A x`` and coarse correction
    ``x + P c`` in one pass each."""
    for row in numba.prange(out.shape[0]):
        out[row] = y[row] + alpha * csr_row_dot(indptr, indices, data, v, row)


@numba.njit(inline="always")
def chebyshev_start_row(indptr, indices, data, b, first, theta, scale, diagonal, factor, r_out, d_out, x_out,
                        row):  # pragma: no cover - compiled
    """:func:`chebyshev_start` on one row, its first step ``first / theta`` and its diagonal
    ``factor diagonal`` (:func:`multigrid_cg`: the level's scaled D^-1 for both; 1 elsewhere)."""
    total = 0.0
    for nz in range(indptr[row], indptr[row + 1]):
        q = indices[nz]
        total += data[nz] * ((first[q] / theta) * b[q])
    r_new = b[row] - total
    d = (first[row] / theta) * b[row]
    d_new = d * scale + (factor * diagonal[row]) * r_new
    r_out[row] = r_new
    d_out[row] = d_new
    x_out[row] = d + d_new


@numba.njit(parallel=True, cache=True)
def chebyshev_start(indptr, indices, data, b, first, scale, diagonal, r_out, d_out, x_out):  # pragma: no cover
    """The Chebyshev smoother's first two steps from zero in one pass: with ``d = x = first b``
    (the first step), :func:`chebyshev_update` of r = b, v = d (``first b`` formed where it is
    read: no array of it), vectors (N,)."""
    for row in numba.prange(b.shape[0]):
        chebyshev_start_row(indptr, indices, data, b, first, 1.0, scale, diagonal, 1.0, r_out, d_out, x_out, row)


@numba.njit(inline="always")
def restrict_residual_row(R_indptr, R_indices, R_data, indptr, indices, data, b, x, coarse, row):  # pragma: no cover
    """:func:`restrict_residual` on coarse row ``row``."""
    total = 0.0
    for nz in range(R_indptr[row], R_indptr[row + 1]):
        p = R_indices[nz]
        total += R_data[nz] * (b[p] - csr_row_dot(indptr, indices, data, x, p))
    coarse[row] = total


@numba.njit(parallel=True, cache=True)
def restrict_residual(R_indptr, R_indices, R_data, indptr, indices, data, b, x, coarse):  # pragma: no cover
    """The multigrid's restricted residual ``coarse = R (b - A x)`` in one pass (the fine
    residual formed where it is read) for CSR matrices R (n, N) and A (N, N) given by their
    arrays, b, x (N,), coarse (n,)."""
    for row in numba.prange(coarse.shape[0]):
        restrict_residual_row(R_indptr, R_indices, R_data, indptr, indices, data, b, x, coarse, row)


@numba.njit(inline="always")
def prolong_restart_row(indptr, indices, data, P_indptr, P_indices, P_data, b, x, c, first, theta, r_out, d_out, x_out,
                        row):  # pragma: no cover - compiled
    """:func:`prolong_restart` on one row, its first step ``first / theta`` (1 but in
    :func:`multigrid_cg`)."""
    total = 0.0
    for nz in range(indptr[row], indptr[row + 1]):
        q = indices[nz]
        total += data[nz] * (x[q] + csr_row_dot(P_indptr, P_indices, P_data, c, q))
    r_new = b[row] - total
    d_new = (first[row] / theta) * r_new
    r_out[row] = r_new
    d_out[row] = d_new
    x_out[row] = (x[row] + csr_row_dot(P_indptr, P_indices, P_data, c, row)) + d_new


@numba.njit(parallel=True, cache=True)
def prolong_restart(indptr, indices, data, P_indptr, P_indices, P_data, b, x, c, first, r_out, d_out, x_out):  # pragma: no cover
    """The multigrid's coarse correction and the Chebyshev smoother's restart in one pass: with
    ``y = x + P c`` (formed where it is read) for CSR matrices A (N, N) and P (N, n) given by
    their arrays, ``r_out = b - A y``, ``d_out = first r_out``, ``x_out = y + d_out`` (N,) each."""
    for row in numba.prange(b.shape[0]):
        prolong_restart_row(indptr, indices, data, P_indptr, P_indices, P_data, b, x, c, first, 1.0, r_out, d_out,
                            x_out, row)


#: Slots of the preconditioned CG's state (float64 (CG_STATE,), on the device with the vectors:
#: :func:`.krylov.pcg`): gamma = r.z and its previous value, delta = w.z (w = A z), the step
#: alpha and direction scale beta, the squared residual rr, its previous and starting values,
#: the threshold rtol^2 b.b, active (1/0), the active iterations and the status
#: ``4 iterations + 2 active + converged`` (what the host reads).
(CG_GAMMA, CG_GAMMA_OLD, CG_DELTA, CG_ALPHA, CG_BETA, CG_RR, CG_RR_OLD, CG_RR_START, CG_THRESHOLD, CG_ACTIVE,
 CG_ITERATIONS, CG_STATUS) = range(12)
CG_STATE = 12
#: :func:`cg_start`, :func:`cg_scalars`, :func:`cg_update`: which pass of CG a call makes
CG_START, CG_SCALARS, CG_UPDATE = range(3)
#: Blocks of the GPU's CG passes at most (grid-stride loops; the rows of their partial sums)
REDUCTION_BLOCKS = 256
#: Blocks of the GPU's cooperative :func:`multigrid_cg` at most (the rows of its partial sums):
#: fewer where the device holds fewer at once (a grid that syncs must be resident as a whole)
COOPERATIVE_BLOCKS = 1024


@numba.njit(inline="always")
def cg_row(mode, indptr, indices, data, with_matrix, from_zero, b, z, w, p, s, x, r, alpha, beta, row):  # pragma: no cover
    """One row of a CG pass (``mode``, see :func:`cg_start`, :func:`cg_scalars`,
    :func:`cg_update`): the row's two terms of the pass's dot products."""
    if mode == CG_START:
        p[row] = 0.0
        s[row] = 0.0
        if from_zero:
            x[row] = 0.0
            r[row] = b[row]
        return b[row] * b[row], r[row] * r[row]
    if mode == CG_SCALARS:
        if with_matrix:
            w[row] = csr_row_dot(indptr, indices, data, z, row)
        return r[row] * z[row], w[row] * z[row]
    p_new = z[row] + beta * p[row]
    s_new = w[row] + beta * s[row]
    p[row] = p_new
    s[row] = s_new
    x[row] = x[row] + alpha * p_new
    r_new = r[row] - alpha * s_new
    r[row] = r_new
    return r_new * r_new, 0.0


@numba.njit(inline="always")
def cg_finish(mode, state, first, second, rtol2):  # pragma: no cover - compiled
    """A CG pass's scalars in ``state`` from its dot products (first, second): the start's
    threshold and squared residual (b.b, r.r); the coefficients of Chronopoulos and Gear's CG
    (gamma, delta: beta = gamma / gamma_old, alpha = gamma / (delta - beta gamma / alpha_old),
    at the first iteration beta = 0, alpha = gamma / delta; NaN where a divisor is zero); the
    update's squared residual rr and the progress: active while neither converged
    (rr <= threshold) nor broken down (rr not finite)."""
    if mode == CG_SCALARS:
        gamma, delta = first, second
        if state[CG_ITERATIONS] == 0.0:
            beta = 0.0
            alpha = gamma / delta if delta != 0.0 else math.nan
        else:
            beta = gamma / state[CG_GAMMA] if state[CG_GAMMA] != 0.0 else math.nan
            divisor = delta - beta * gamma / state[CG_ALPHA] if state[CG_ALPHA] != 0.0 else math.nan
            alpha = gamma / divisor if divisor != 0.0 else math.nan
        state[CG_GAMMA_OLD] = state[CG_GAMMA]
        state[CG_GAMMA] = gamma
        state[CG_DELTA] = delta
        state[CG_ALPHA] = alpha
        state[CG_BETA] = beta
        return
    rr = first
    if mode == CG_START:
        for k in range(CG_STATE):
            state[k] = 0.0
        rr = second
        state[CG_THRESHOLD] = rtol2 * first
        state[CG_RR_START] = rr
        state[CG_ITERATIONS] = -1.0  # the start counts as iteration 0
    state[CG_RR_OLD] = state[CG_RR]
    state[CG_RR] = rr
    state[CG_ITERATIONS] += 1.0
    converged = rr <= state[CG_THRESHOLD]
    state[CG_ACTIVE] = 0.0 if converged or not math.isfinite(rr) else 1.0
    state[CG_STATUS] = 4.0 * state[CG_ITERATIONS] + 2.0 * state[CG_ACTIVE] + (1.0 if converged else 0.0)


@numba.njit(cache=True)
def cg_pass(mode, indptr, indices, data, with_matrix, from_zero, b, z, w, p, s, x, r, rtol2, state, partial,
            counter):  # pragma: no cover - compiled
    """A CG pass over the rows in one loop (:func:`cg_row`), then its scalars (:func:`cg_finish`);
    nothing once CG is inactive (but for the start). partial, counter: the CUDA kernel's
    scratch (unused here)."""
    if mode != CG_START and state[CG_ACTIVE] == 0.0:
        return
    alpha, beta = state[CG_ALPHA], state[CG_BETA]
    first = second = 0.0
    for row in range(b.shape[0]):
        a, c = cg_row(mode, indptr, indices, data, with_matrix, from_zero, b, z, w, p, s, x, r, alpha, beta, row)
        first += a
        second += c
    cg_finish(mode, state, first, second, rtol2)


def cg_start(b, x, r, p, s, from_zero, rtol2, state, partial, counter) -> None:
    """CG's start on ``A x = b`` (vectors (N,)): p = s = 0, with ``from_zero`` x = 0 and r = b
    (else r = b - A x already), the state (:data:`CG_STATE`) from b.b and r.r for the tolerance
    rtol2 = rtol^2. partial (:data:`REDUCTION_BLOCKS`, 2) float64 and counter (1,) int32 zero:
    scratch of the GPU's reduction."""
    cg_pass(CG_START, counter, counter, state, False, from_zero, b, b, b, p, s, x, r, rtol2, state, partial, counter)


def cg_scalars(indptr, indices, data, with_matrix, z, r, w, state, partial, counter) -> None:
    """CG's coefficients (:func:`cg_finish`) from gamma = r.z and delta = w.z, with
    ``with_matrix`` w = A z (CSR arrays of A (N, N)) formed here (else w given; the CSR arrays
    are then not read)."""
    cg_pass(CG_SCALARS, indptr, indices, data, with_matrix, False, z, z, w, z, z, z, r, 0.0, state, partial, counter)


def cg_update(z, w, p, s, x, r, state, partial, counter) -> None:
    """CG's step in place: p = z + beta p, s = w + beta s (= A p), x += alpha p, r -= alpha s,
    then rr = r.r and the progress (:func:`cg_finish`)."""
    cg_pass(CG_UPDATE, counter, counter, state, False, False, z, z, w, p, s, x, r, 0.0, state, partial, counter)


#: The multigrid V-cycle and CG in one launch (:func:`multigrid_cg`). Its hierarchy's layout, a
#: tuple of :data:`MG_FIELDS` ints per level (:data:`MG_MAX_LEVELS` levels, the coarsest
#: included; unused levels zero): the level's offset in the vector workspace and its unknowns,
#: then the offsets of its operator A (not read on level 0: the system's own matrix), of its
#: prolongation P and of its restriction R in the packed CSR arrays: indptr offset, data offset
#: each (every level's indptr counts from 0 in its own data).
MG_VEC, MG_N, MG_A_PTR, MG_A_NZ, MG_P_PTR, MG_P_NZ, MG_R_PTR, MG_R_NZ = range(8)
MG_FIELDS = 8
MG_MAX_LEVELS = 12
#: rows of :func:`multigrid_cg`'s vector workspace (6, unknowns of all levels): per level the
#: right-hand side (level 0: CG's residual r), the smoother's result before the coarse
#: correction, its result after it (level 0: CG's z), the smoother's residual and two direction
#: buffers (a step reads the last direction at the neighbours and writes the other)
MG_B, MG_X, MG_XU, MG_RES, MG_D0, MG_D1 = range(6)
MG_ROWS = 6


@numba.njit(inline="always")
def grid_barrier():  # pragma: no cover - compiled
    """Where :func:`multigrid_cg_steps` waits for every thread of its launch: nothing on the host
    (one thread); the grid's sync in the CUDA kernel (:mod:`.cuda_kernels` puts it here)."""
    return


@numba.njit(inline="always")
def grid_sum2(first, second, partial, slot):  # pragma: no cover - compiled
    """Two sums over every thread of the launch: on the host (one thread) the terms themselves;
    the CUDA kernel's sums the blocks' shares through ``partial[:, slot:slot + 2]`` in a fixed
    order, the same totals in every thread (:mod:`.cuda_kernels`)."""
    return first, second


@numba.njit(inline="always")
def _mg_vector(work, which, layout, k):  # pragma: no cover - compiled
    """Row ``which`` of the workspace on level k's unknowns."""
    offset = layout[MG_FIELDS * k + MG_VEC]
    return work[which, offset:offset + layout[MG_FIELDS * k + MG_N]]


@numba.njit(inline="always")
def _mg_csr(indptr, indices, data, layout, k, field, rows):  # pragma: no cover - compiled
    """Level k's CSR matrix of ``rows`` rows in packed arrays (its offsets at ``field``)."""
    start, nz = layout[MG_FIELDS * k + field], layout[MG_FIELDS * k + field + 1]
    return indptr[start:start + rows + 1], indices[nz:], data[nz:]


@numba.njit
def multigrid_cycle(m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr, p_indices, p_data, r_indptr,
                    r_indices, r_data, inv_diag, coarse_inverse, coarse_partial, work, layout, levels, cheb, start,
                    stride):  # pragma: no cover - compiled
    """The V-cycle of :class:`.krylov.Multigrid` (Chebyshev smoothers) on level 0's right-hand
    side ``work[MG_B]`` into ``work[MG_XU]`` (level 0's slices), the rows of each pass taken
    ``start, start + stride, ...`` by this thread, every pass followed by :func:`grid_barrier`.
    cheb: (theta, scale_1, factor_1, ..., scale_{s-1}, factor_{s-1}) of an s-step smoother on
    (D^-1 / bound) A (:class:`.krylov.ChebyshevSmoother`: its first step ``inv_diag / theta``,
    step j's diagonal ``factor_j inv_diag``); coarse_inverse (n, n) symmetric, coarse_partial
    (segments, n) scratch of its product."""
    steps = (len(cheb) + 1) // 2
    theta = cheb[0]
    for k in range(levels):  # down: smooth from zero, restrict the residual
        n = layout[MG_FIELDS * k + MG_N]
        if k == 0:
            indptr, indices, data = m_indptr, m_indices, m_data
        else:
            indptr, indices, data = _mg_csr(a_indptr, a_indices, a_data, layout, k, MG_A_PTR, n)
        offset = layout[MG_FIELDS * k + MG_VEC]
        diagonal = inv_diag[offset:offset + n]
        b, x = _mg_vector(work, MG_B, layout, k), _mg_vector(work, MG_X, layout, k)
        r = _mg_vector(work, MG_RES, layout, k)
        d0, d1 = _mg_vector(work, MG_D0, layout, k), _mg_vector(work, MG_D1, layout, k)
        if steps == 1:
            for row in range(start, n, stride):
                x[row] = (diagonal[row] / theta) * b[row]
        else:
            for row in range(start, n, stride):
                chebyshev_start_row(indptr, indices, data, b, diagonal, theta, cheb[1], diagonal, cheb[2], r, d1, x,
                                    row)
        grid_barrier()
        for j in range(2, steps):
            d, d_out = (d1, d0) if j % 2 == 0 else (d0, d1)
            for row in range(start, n, stride):
                chebyshev_row(indptr, indices, data, r, d, d, cheb[2 * j - 1], diagonal, cheb[2 * j], x, r, d_out, x,
                              row)
            grid_barrier()
        R_indptr, R_indices, R_data = _mg_csr(r_indptr, r_indices, r_data, layout, k, MG_R_PTR,
                                              layout[MG_FIELDS * (k + 1) + MG_N])
        coarse = _mg_vector(work, MG_B, layout, k + 1)
        for row in range(start, coarse.shape[0], stride):
            restrict_residual_row(R_indptr, R_indices, R_data, indptr, indices, data, b, x, coarse, row)
        grid_barrier()
    # the coarsest level: its dense inverse's product, by column segments (the inverse is
    # symmetric: thread i reads column i, neighbouring threads neighbouring memory), then their sum
    b, out = _mg_vector(work, MG_B, layout, levels), _mg_vector(work, MG_XU, layout, levels)
    chunked_product(coarse_inverse, b, coarse_partial, out, -(-b.shape[0] // coarse_partial.shape[0]), True, start,
                    stride)
    for k in range(levels - 1, -1, -1):  # up: correct from the coarse level, smooth again
        n = layout[MG_FIELDS * k + MG_N]
        if k == 0:
            indptr, indices, data = m_indptr, m_indices, m_data
        else:
            indptr, indices, data = _mg_csr(a_indptr, a_indices, a_data, layout, k, MG_A_PTR, n)
        offset = layout[MG_FIELDS * k + MG_VEC]
        diagonal = inv_diag[offset:offset + n]
        P_indptr, P_indices, P_data = _mg_csr(p_indptr, p_indices, p_data, layout, k, MG_P_PTR, n)
        b, x = _mg_vector(work, MG_B, layout, k), _mg_vector(work, MG_X, layout, k)
        xu, r = _mg_vector(work, MG_XU, layout, k), _mg_vector(work, MG_RES, layout, k)
        d0, d1 = _mg_vector(work, MG_D0, layout, k), _mg_vector(work, MG_D1, layout, k)
        c = _mg_vector(work, MG_XU, layout, k + 1)
        for row in range(start, n, stride):
            prolong_restart_row(indptr, indices, data, P_indptr, P_indices, P_data, b, x, c, diagonal, theta, r, d0, xu,
                                row)
        grid_barrier()
        for j in range(1, steps):
            d, d_out = (d0, d1) if j % 2 == 1 else (d1, d0)
            for row in range(start, n, stride):
                chebyshev_row(indptr, indices, data, r, d, d, cheb[2 * j - 1], diagonal, cheb[2 * j], xu, r, d_out, xu,
                              row)
            grid_barrier()


@numba.njit(inline="always")
def chunked_product(M, b, partial, out, length, by_column, start, stride):  # pragma: no cover - compiled
    """``out = M^T b`` (by_column: ``out[i] = sum_j M[j, i] b[j]``, neighbouring threads reading
    neighbouring memory) or ``out = M b`` (``out[i] = sum_j M[i, j] b[j]``) by the launch's
    threads: item (chunk c, i) sums ``length`` terms j of chunk c into ``partial[c, i]``
    (partial (chunks, len(out)), chunks * length >= len(b)), then each out[i] its chunks in order
    (the same sums every run); each pass followed by :func:`grid_barrier`."""
    n_out, n_in = out.shape[0], b.shape[0]
    chunks = partial.shape[0]
    for item in range(start, chunks * n_out, stride):
        c, i = item // n_out, item % n_out
        total = 0.0
        for j in range(c * length, min(n_in, (c + 1) * length)):
            total += (M[j, i] if by_column else M[i, j]) * b[j]
        partial[c, i] = total
    grid_barrier()
    for i in range(start, n_out, stride):
        total = 0.0
        for c in range(chunks):
            total += partial[c, i]
        out[i] = total
    grid_barrier()


#: Rows per chunk of :func:`low_rank_product`'s partial sums
LOW_RANK_CHUNK = 256


@numba.njit(inline="always")
def low_rank_product(u_t, z, t_partial, t, start, stride):  # pragma: no cover - compiled
    """``t = U^T z`` (K,) for u_t = U^T (K, N) C-ordered, z (N,), by the launch's threads: item
    (chunk c, column j) sums rows c :data:`LOW_RANK_CHUNK` ... of column j into
    ``t_partial[c, j]`` (t_partial (chunks, K)), then each t[j] its chunks in order; each pass
    followed by :func:`grid_barrier`."""
    chunked_product(u_t, z, t_partial, t, LOW_RANK_CHUNK, False, start, stride)


@numba.njit
def multigrid_cg_steps(n_steps, cycle_first, with_matrix, m_indptr, m_indices, m_data, a_indptr, a_indices, a_data,
                       p_indptr, p_indices, p_data, r_indptr, r_indices, r_data, inv_diag, coarse_inverse,
                       coarse_partial, work, x, p, s, w, u_t, coupled, t_partial, t, layout, levels, cheb, begin,
                       b, from_zero, rtol2, state, partial, local, start, stride):  # pragma: no cover - compiled
    """:func:`multigrid_cg` by one thread of ``start, start + stride, ...`` rows, its scalars in
    ``local`` (:data:`CG_STATE`, each thread's copy of the state: every thread sums the same
    partial sums in the same order, so all hold the same; the thread of ``start`` 0 writes them
    back)."""
    for k in range(CG_STATE):
        local[k] = state[k]
    n = x.shape[0]
    r, z = work[MG_B, :n], work[MG_XU, :n]
    if begin:  # CG's start (cg_start's pass), its sums through partial's slots 2, 3
        first = second = 0.0
        for row in range(start, n, stride):
            a, c = cg_row(CG_START, m_indptr, m_indices, m_data, False, from_zero, b, b, b, p, s, x, r, 0.0, 0.0,
                          row)
            first += a
            second += c
        first, second = grid_sum2(first, second, partial, 2)
        cg_finish(CG_START, local, first, second, rtol2)
        if start == 0:
            for k in range(CG_STATE):
                state[k] = local[k]
    if local[CG_ACTIVE] == 0.0:  # every thread read the state before any writes it (after a barrier)
        return
    if cycle_first:
        multigrid_cycle(m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr, p_indices, p_data,
                        r_indptr, r_indices, r_data, inv_diag, coarse_inverse, coarse_partial, work, layout, levels,
                        cheb, start, stride)
    low_rank = with_matrix and u_t.shape[0] > 0
    for _ in range(n_steps):
        if low_rank:  # t = U^T z: the rows' partial sums by chunks, then the chunks' sums
            low_rank_product(u_t, z, t_partial, t, start, stride)
        first = second = 0.0
        for row in range(start, n, stride):
            if low_rank:  # w = C t + M z, added as krylov.multiply_add adds them
                total = 0.0
                for j in range(t.shape[0]):
                    total += coupled[row, j] * t[j]
                w[row] = total + 1.0 * csr_row_dot(m_indptr, m_indices, m_data, z, row)
            a, b = cg_row(CG_SCALARS, m_indptr, m_indices, m_data, with_matrix and not low_rank, False, z, z, w, p, s,
                          x, r, 0.0, 0.0, row)
            first += a
            second += b
        first, second = grid_sum2(first, second, partial, 0)
        cg_finish(CG_SCALARS, local, first, second, 0.0)
        alpha, beta = local[CG_ALPHA], local[CG_BETA]
        first = 0.0
        for row in range(start, n, stride):
            a, b = cg_row(CG_UPDATE, m_indptr, m_indices, m_data, False, False, z, z, w, p, s, x, r, alpha, beta, row)
            first += a
        first, second = grid_sum2(first, 0.0, partial, 2)
        cg_finish(CG_UPDATE, local, first, 0.0, 0.0)
        if start == 0:
            for k in range(CG_STATE):
                state[k] = local[k]
        if local[CG_ACTIVE] == 0.0:
            return
        multigrid_cycle(m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr, p_indices, p_data,
                        r_indptr, r_indices, r_data, inv_diag, coarse_inverse, coarse_partial, work, layout, levels,
                        cheb, start, stride)


@numba.njit(cache=True)
def multigrid_cg(n_steps, cycle_first, with_matrix, m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr,
                 p_indices, p_data, r_indptr, r_indices, r_data, inv_diag, coarse_inverse, coarse_partial, work, x, p,
                 s, w, u_t, coupled, t_partial, t, layout, levels, cheb, begin, b, from_zero, rtol2, state,
                 partial):  # pragma: no cover - compiled
    """Up to ``n_steps`` iterations of multigrid-preconditioned CG (:func:`.krylov.pcg` with a
    :class:`.krylov.Multigrid` of Chebyshev smoothers) in one launch: per iteration the dot
    products (:func:`cg_row`: w = A z where ``with_matrix``, else w given), the
    step (x, r, p, s in place) and, while CG goes on, the V-cycle z = M r (:func:`multigrid_cycle`)
    for the next; first the V-cycle alone where ``cycle_first``; nothing once CG is inactive.

    m_*: CSR arrays of the system's sparse matrix (the hierarchy's level 0, and CG's A where
    ``with_matrix``); a_*, p_*, r_*: the coarser levels' operators and every level's
    prolongation and restriction, packed (``layout``, :data:`MG_FIELDS`), ``levels`` levels above
    the coarsest; inv_diag: every level's D^-1 / bound, packed like the vectors; work
    (:data:`MG_ROWS`, unknowns of all levels): r and z are level 0's rows :data:`MG_B` and
    :data:`MG_XU`; x, p, s, w (N,); u_t (K, N), coupled (N, K): with K > 0, A is the Schur
    complement ``M + coupled U^T`` (:meth:`.normal_equations.JointSystem.schur_operator`,
    coupled = -U H^-1), its product formed here too where ``with_matrix``
    (:func:`low_rank_product`; t_partial (chunks, K), t (K,) its scratch); state
    (:data:`CG_STATE`) after :func:`cg_start`, or with ``begin`` that start made here first (on
    b (N,), ``from_zero``, rtol2: :func:`cg_start`'s; r is work's row); partial
    (blocks, 4): the CUDA kernel's scratch. Another operator's case launches ``n_steps`` 0 (the
    first cycle), then 1 per iteration (with w = A z given)."""
    multigrid_cg_steps(n_steps, cycle_first, with_matrix, m_indptr, m_indices, m_data, a_indptr, a_indices, a_data,
                       p_indptr, p_indices, p_data, r_indptr, r_indices, r_data, inv_diag, coarse_inverse,
                       coarse_partial, work, x, p, s, w, u_t, coupled, t_partial, t, layout, levels, cheb, begin, b,
                       from_zero, rtol2, state, partial, np.empty(CG_STATE), 0, 1)


@numba.njit(inline="always")
def shading_residual_pixel(color, albedo, basis, lights, usable, shading, residual, i, p):  # pragma: no cover
    """:func:`shading_residuals` on pixel p of frame i."""
    b = 0 if basis.shape[0] == 1 else i
    s = 0.0
    for j in range(basis.shape[2]):
        s += basis[b, p, j] * lights[i, j]
    shading[i, p] = s
    if usable[i, p]:
        for c in range(3):
            residual[i, p, c] = color[i, p, c] - albedo[p, c] * s
    else:
        for c in range(3):
            residual[i, p, c] = 0.0


@numba.njit(parallel=True, cache=True)
def shading_residuals(color, albedo, basis, lights, usable, shading, residual):  # pragma: no cover - compiled
    """Per frame i, pixel p, channel c: the shading s = <basis, light_i> (n, N) and the
    residual ``(I - rho_c s) usable`` (n, N, 3), written into ``shading`` and ``residual``.

    color (n, N, 3) warped colours, albedo (N, 3), basis (m, N, k) with m = n, or 1 when the
    frames share it, lights (n, k), usable (n, N) bool.
    """
    n, N = usable.shape
    for k in numba.prange(-(-N // FRAME_CHUNK)):
        for i in range(n):
            for p in range(k * FRAME_CHUNK, min(N, (k + 1) * FRAME_CHUNK)):
                shading_residual_pixel(color, albedo, basis, lights, usable, shading, residual, i, p)


@numba.njit(inline="always")
def weighted_albedo_pixel(residual, usable, values, shading, inv_lam, num, den, p):  # pragma: no cover - compiled
    """:func:`weighted_albedo_sums` on pixel p (all frames and channels)."""
    for c in range(3):
        num[p, c] = 0.0
        den[p, c] = 0.0
    for i in range(usable.shape[0]):
        weighted_albedo_add(residual, usable, values, shading, inv_lam, num, den, i, p)


@numba.njit(inline="always")
def weighted_albedo_add(residual, usable, values, shading, inv_lam, num, den, i, p):  # pragma: no cover - compiled
    """Frame i's terms of :func:`weighted_albedo_sums` at pixel p, added to num and den."""
    if usable[i, p]:
        for c in range(3):
            x = residual[i, p, c] * inv_lam
            ws = shading[i, p] / (1.0 + x * x)
            num[p, c] += ws * values[i, p, c]
            den[p, c] += ws * shading[i, p]


@numba.njit(parallel=True, cache=True)
def weighted_albedo_sums(residual, usable, values, shading, inv_lam, num, den):  # pragma: no cover - compiled
    """num (N, 3) = sum_i w s x and den (N, 3) = sum_i w s^2 over the frames, with the Cauchy
    IRLS weight w = usable / (1 + (r inv_lam)^2) of residual (n, N, 3), shading s (n, N) and
    values x (n, N, 3): the warped colours for the albedo's weighted least squares, the
    residuals for its variable projection; usable (n, N) bool."""
    N = usable.shape[1]
    for k in numba.prange(-(-N // FRAME_CHUNK)):
        weighted_albedo_chunk(residual, usable, values, shading, inv_lam, num, den, k * FRAME_CHUNK,
                              min(N, (k + 1) * FRAME_CHUNK))


@numba.njit(inline="always")
def weighted_albedo_chunk(residual, usable, values, shading, inv_lam, num, den, start,
                          stop):  # pragma: no cover - compiled
    """:func:`weighted_albedo_sums` on the pixels start..stop-1, the frames in turn over them
    (each pixel's sums in frame order, as :func:`weighted_albedo_pixel`'s)."""
    for p in range(start, stop):
        for c in range(3):
            num[p, c] = 0.0
            den[p, c] = 0.0
    for i in range(usable.shape[0]):
        for p in range(start, stop):
            weighted_albedo_add(residual, usable, values, shading, inv_lam, num, den, i, p)


@numba.njit(inline="always")
def weighted_lighting_terms(residual, usable, color, albedo, inv_lam, i, p):  # pragma: no cover - compiled
    """(sum_c w rho^2, sum_c w rho I) at pixel p of frame i (the lighting's per-pixel weights,
    :func:`lighting_sums`), with the Cauchy IRLS weight w = usable / (1 + (r inv_lam)^2) of
    residual (n, N, 3), albedo rho (N, 3) and warped colour I (n, N, 3)."""
    a = 0.0
    b = 0.0
    if usable[i, p]:
        for c in range(3):
            x = residual[i, p, c] * inv_lam
            w = 1.0 / (1.0 + x * x)
            a += w * albedo[p, c] * albedo[p, c]
            b += w * albedo[p, c] * color[i, p, c]
    return a, b


@numba.njit(inline="always")
def project_point(pose, K, x, y, z):  # pragma: no cover - compiled
    """The reference point (x, y, z) in a frame with pose (4, 4) (reference -> frame) and its
    pixel there: (X, Y, Z, u, v); u = v = 0 where the projection is not finite."""
    X = pose[0, 0] * x + pose[0, 1] * y + pose[0, 2] * z + pose[0, 3]
    Y = pose[1, 0] * x + pose[1, 1] * y + pose[1, 2] * z + pose[1, 3]
    Z = pose[2, 0] * x + pose[2, 1] * y + pose[2, 2] * z + pose[2, 3]
    u = 0.0
    v = 0.0
    if Z != 0.0:
        u = K[0, 0] * X / Z + K[0, 2]
        v = K[1, 1] * Y / Z + K[1, 2]
    if not (math.isfinite(u) and math.isfinite(v)):
        u = 0.0
        v = 0.0
    return X, Y, Z, u, v


@numba.njit(inline="always")
def float_frame_size(image):  # pragma: no cover - compiled
    """(H, W) of an (H, W, C) float colour frame (:func:`frame_size`'s float form)."""
    return image.shape[0], image.shape[1]


@numba.njit(inline="always")
def float_frame_value(image, v, u, c):  # pragma: no cover - compiled
    """Channel c of an (H, W, C) float frame's pixel (u, v) as float64 (:func:`frame_value`'s float form)."""
    return np.float64(image[v, u, c])


@numba.njit  # not inlined in numba's IR: compiled per frame type, its type test decided there
def frame_size(image):  # pragma: no cover - compiled
    """(H, W) of a colour frame: an (H, W, C) float array, or a coded frame ``(codes (H, W, C),
    table (C, K))`` (:meth:`o3d_mvps.colour.CodedColours.frame`; the CPU's only: a GPU's
    frames are decoded on upload, and its kernels read :data:`FLOAT_FRAME_FORMS`)."""
    if isinstance(image, tuple):
        return image[0].shape[0], image[0].shape[1]
    return float_frame_size(image)


@numba.njit  # not inlined in numba's IR: compiled per frame type, its type test decided there
def frame_value(image, v, u, c):  # pragma: no cover - compiled
    """Channel c of a colour frame's pixel (u, v) (integers) as float64: the float array's value,
    or a coded frame's ``table[c, codes[v, u, c]]``, the float32 its decoded frame holds
    (:func:`o3d_mvps.colour.decode_frame`), so every sample is the same bit for bit."""
    if isinstance(image, tuple):
        return np.float64(image[1][c, image[0][v, u, c]])
    return float_frame_value(image, v, u, c)


#: the float-frame forms of the frame readers, which the CUDA kernels compile in their place
#: (:func:`.cuda_kernels._float_frames`): numba-cuda types both branches of the type test
FLOAT_FRAME_FORMS = {frame_size: float_frame_size, frame_value: float_frame_value}


@numba.njit  # not inlined in numba's IR: compiled per frame type, its type test decided there
def frame_at(images, tables, i):  # pragma: no cover - compiled
    """Frame i of a tuple of colour frames as :func:`frame_value` reads it: ``images[i]``, or
    where ``tables`` (a tuple of (C, K) tables) is not None the coded frame
    ``(images[i], tables[i])``."""
    if isinstance(tables, tuple):  # a type test, decided when compiled (no branch at run time)
        return images[i], tables[i]
    return images[i]


@numba.njit(inline="always")
def bilinear_cell(image, u, v):  # pragma: no cover - compiled
    """The (H, W, C) image's bilinear cell at pixel (u, v), clamped to the image (the border
    repeats; pixel centres at integers): its top-left pixel (u0, v0) and the weights (a, b) in
    [0, 1] towards the next column and row, for :func:`bilinear_in_cell`. H, W >= 2. ``image``:
    any colour frame of :func:`frame_size`."""
    H, W = frame_size(image)
    # no min, max or int(): numba 0.68's own CUDA target needs a driver to type those,
    # numba-cuda does not
    u = 0.0 if u < 0.0 else (W - 1.0 if u > W - 1.0 else u)
    v = 0.0 if v < 0.0 else (H - 1.0 if v > H - 1.0 else v)
    u0 = np.int64(u)
    v0 = np.int64(v)
    if u0 > W - 2:
        u0 = W - 2
    if v0 > H - 2:
        v0 = H - 2
    return u0, v0, u - u0, v - v0


@numba.njit(inline="always")
def bilinear_in_cell(image, u0, v0, a, b, c):  # pragma: no cover - compiled
    """Channel c of the image's bilinear sample in the cell (u0, v0, a, b) of :func:`bilinear_cell`,
    in float64."""
    i00, i01 = frame_value(image, v0, u0, c), frame_value(image, v0, u0 + 1, c)  # float64 differences
    i10, i11 = frame_value(image, v0 + 1, u0, c), frame_value(image, v0 + 1, u0 + 1, c)
    top = i00 + a * (i01 - i00)
    bottom = i10 + a * (i11 - i10)
    return top + b * (bottom - top)


@numba.njit(inline="always")
def image_gradients_at(image, u, v):  # pragma: no cover - compiled
    """(d/du, d/dv) of channels 0, 1 and 2 of the image at pixel (u, v) clamped to it, as
    (gu0, gv0, gu1, gv1, gu2, gv2): central differences over one pixel of the bilinear
    interpolant (the border repeats: :func:`bilinear_cell`).

    Bilinear interpolation commutes with whole-pixel shifts, so these are the bilinear samples
    of the image's central-difference gradient images, without computing and storing those
    (two float32 copies of every frame): exactly so from one pixel inside the border on. The four
    bilinear cells are found once for the three channels (a cell a channel, as before, cost a
    third of the joint step's assembly: D415 armadillo 1.02 -> 0.66 s a refine, the same values)."""
    H, W = frame_size(image)
    u = 0.0 if u < 0.0 else (W - 1.0 if u > W - 1.0 else u)
    v = 0.0 if v < 0.0 else (H - 1.0 if v > H - 1.0 else v)
    ru0, rv0, ra, rb = bilinear_cell(image, u + 1.0, v)
    lu0, lv0, la, lb = bilinear_cell(image, u - 1.0, v)
    du0, dv0, da, db = bilinear_cell(image, u, v + 1.0)
    tu0, tv0, ta, tb = bilinear_cell(image, u, v - 1.0)
    return (0.5 * (bilinear_in_cell(image, ru0, rv0, ra, rb, 0) - bilinear_in_cell(image, lu0, lv0, la, lb, 0)),
            0.5 * (bilinear_in_cell(image, du0, dv0, da, db, 0) - bilinear_in_cell(image, tu0, tv0, ta, tb, 0)),
            0.5 * (bilinear_in_cell(image, ru0, rv0, ra, rb, 1) - bilinear_in_cell(image, lu0, lv0, la, lb, 1)),
            0.5 * (bilinear_in_cell(image, du0, dv0, da, db, 1) - bilinear_in_cell(image, tu0, tv0, ta, tb, 1)),
            0.5 * (bilinear_in_cell(image, ru0, rv0, ra, rb, 2) - bilinear_in_cell(image, lu0, lv0, la, lb, 2)),
            0.5 * (bilinear_in_cell(image, du0, dv0, da, db, 2) - bilinear_in_cell(image, tu0, tv0, ta, tb, 2)))


@numba.njit(inline="always")
def warp_sample_pixel(points_ref, pose, K, image, visible, color, usable, p):  # pragma: no cover - compiled
    """:func:`warp_sample` on pixel p: the point's projection in the frame, whether the frame
    sees it there, and the image's bilinear sample at it (at the clamped position; 0 where the
    point is behind the camera)."""
    _, _, Z, u, v = project_point(pose, K, points_ref[p, 0], points_ref[p, 1], points_ref[p, 2])
    H, W = frame_size(image)
    usable[p] = visible[p] and Z > 1e-6 and u >= 0.0 and u <= W - 1.0 and v >= 0.0 and v <= H - 1.0
    u0, v0, a, b = bilinear_cell(image, u, v)  # once for the three channels
    for c in range(3):
        color[p, c] = bilinear_in_cell(image, u0, v0, a, b, c)


@numba.njit(parallel=True, cache=True)
def warp_sample(points_ref, pose, K, image, visible, color, usable):  # pragma: no cover - compiled
    """Frame i's view of the reference points: per pixel p of points_ref (N, 3) metres, its
    projection ``K (R P + t)`` (pose (4, 4) = [R t], K (3, 3)), ``usable[p]`` =
    ``visible[p]`` (N,) bool and in front of the camera and inside the (H, W, 3) ``image``, and
    ``color[p]`` (N, 3) its bilinear sample there (pixel centres at integers; the border
    repeats): :func:`o3d_mvps.model.warping.warp`, ``in_view`` and ``sample_bilinear`` in one
    pass. H, W >= 2."""
    for p in numba.prange(points_ref.shape[0]):
        warp_sample_pixel(points_ref, pose, K, image, visible, color, usable, p)


@numba.njit(parallel=True, cache=True)
def warp_sample_frames(points_ref, poses, K, images, visible, color, usable):  # pragma: no cover - compiled
    """:func:`warp_sample` of every frame at once: poses (n, 4, 4), images (n, H, W, 3),
    visible (n, N) bool; writes color (n, N, 3) and usable (n, N) (the GPU's one launch per
    evaluation; the host's loop calls :func:`warp_sample` a frame at a time)."""
    n, N = visible.shape
    for index in numba.prange(n * N):
        i, p = index // N, index % N
        warp_sample_pixel(points_ref, poses[i], K, images[i], visible[i], color[i], usable[i], p)


#: :func:`led_energy_frame` takes the logarithm of a pixel's running product of factors ``1 + y^2``
#: before it passes this (a frame's three factors are each below 1.2e77: y is a float32), so the
#: product never overflows
PRODUCT_LOG_LIMIT = 1e150


@numba.njit(parallel=True, cache=True)
def led_energy_frame(points_ref, normals, poses, K, image, visible, albedo, lights, positions, scale, single, i,
                     usable, products, parts):  # pragma: no cover - compiled
    """Frame i's share of the data energy ``sum_{i,p,c} log(1 + (scale r)^2)`` under the LED in one
    pass over the pixels, without the frame's colour, basis, shading and residual arrays (the
    host's :meth:`.LevelProblem.energy`; :func:`log_products_sum` ends it): per pixel p the warp
    and usable test (:func:`warp_sample_pixel`'s, written into ``usable[i, p]``), the colour's
    bilinear sample (rounded to float32, as stored), the basis ``[1, max(0, <n, v_i>)]``
    (:func:`~o3d_mvps.model.shading.led_bases_into`'s), the shading ``<B, l_i>``
    (:func:`shading_residual_pixel`'s sum) and the residuals ``I - rho_c s``; ``single``: the basis
    and residuals rounded to float32 as the evaluations store them. Their factors ``1 + y^2``
    (:func:`~o3d_mvps.model.robust.square_factor`) multiply the pixel's running product
    ``products[p]`` (N,), whose logarithm is added to ``parts[k]`` (per chunk k of
    :func:`~o3d_mvps.model.shading.frame_chunk` pixels) before it passes :data:`PRODUCT_LOG_LIMIT`.
    points_ref, normals (N, 3) float64; poses (n, 4, 4); K (3, 3); image (H, W, 3) float32;
    visible, usable (n, N) bool; albedo (N, 3); lights (n, 2); positions (n, 3) the LED in
    reference coordinates per frame."""
    N = visible.shape[1]
    chunk = frame_chunk(N)
    H, W = frame_size(image)
    for k in numba.prange(-(-N // chunk)):
        for p in range(k * chunk, min(N, (k + 1) * chunk)):
            _, _, Z, u, v = project_point(poses[i], K, points_ref[p, 0], points_ref[p, 1], points_ref[p, 2])
            use = visible[i, p] and Z > 1e-6 and u >= 0.0 and u <= W - 1.0 and v >= 0.0 and v <= H - 1.0
            usable[i, p] = use
            if use:  # else residuals 0: factors 1
                parts[k] += led_pixel_factors(image, u, v, normals, points_ref, positions, albedo, lights, scale,
                                              single, i, p, products)


@numba.njit(inline="always")
def flushed_product(product):  # pragma: no cover - compiled
    """(product, logarithm taken) of a pixel's running product of Cauchy factors before more are
    multiplied in: once it passes :data:`PRODUCT_LOG_LIMIT`, (1, its logarithm), else (it, 0), so
    that three more factors cannot overflow."""
    if product > PRODUCT_LOG_LIMIT:
        return 1.0, math.log(product)
    return product, 0.0


@numba.njit(inline="always")
def led_pixel_factors(image, u, v, normals, points_ref, positions, albedo, lights, scale, single, i, p,
                      products):  # pragma: no cover - compiled
    """:func:`led_energy_frame` at a usable pixel p of frame i seen at (u, v): its three factors
    multiplied into ``products[p]``; returns the logarithm taken of the product before (0 where
    it stayed below :data:`PRODUCT_LOG_LIMIT`)."""
    s = led_shading_at(led_irradiance(normals, points_ref, positions, i, p), lights, single, i)
    u0, v0, a, w = bilinear_cell(image, u, v)
    product, flushed = flushed_product(products[p])
    for c in range(3):
        r = np.float64(np.float32(bilinear_in_cell(image, u0, v0, a, w, c))) - albedo[p, c] * s
        if single:
            r = np.float64(np.float32(r))
        product *= square_factor(r, scale)
    products[p] = product
    return flushed


@numba.njit(inline="always")
def led_shading_at(g, lights, single, i):  # pragma: no cover - compiled
    """Frame i's LED shading ``<[1, max(0, g)], l_i>`` of a pixel whose ``<n, v_i>`` is g, summed
    as :func:`shading_residual_pixel` sums it, the basis rounded to float32 first where ``single``
    (as the evaluations store it)."""
    b = g if g > 0.0 else 0.0
    if single:
        b = np.float64(np.float32(b))
    s = 0.0
    s += 1.0 * lights[i, 0]
    s += b * lights[i, 1]
    return s


@numba.njit(parallel=True, cache=True)
def log_products_sum(products, parts):  # pragma: no cover - compiled
    """The data energy's sum that :func:`led_energy_frame` left: ``parts`` (chunks,) plus the
    logarithms of the pixels' products (N,), chunk by chunk (its chunks)."""
    N = products.shape[0]
    chunk = frame_chunk(N)
    total = 0.0
    for k in numba.prange(-(-N // chunk)):
        part = parts[k]
        for p in range(k * chunk, min(N, (k + 1) * chunk)):
            part += math.log(products[p])
        total += part
    return total


@numba.njit(inline="always")
def warp_gradients_pixel(points_ref, pose, K, image, points, grad_u, grad_v, p):  # pragma: no cover - compiled
    """:func:`warp_gradients` on pixel p."""
    X, Y, Z, u, v = project_point(pose, K, points_ref[p, 0], points_ref[p, 1], points_ref[p, 2])
    points[p, 0] = X
    points[p, 1] = Y
    points[p, 2] = Z
    g = image_gradients_at(image, u, v)
    grad_u[p, 0], grad_v[p, 0], grad_u[p, 1], grad_v[p, 1], grad_u[p, 2], grad_v[p, 2] = g


@numba.njit(parallel=True, cache=True)
def warp_gradients(points_ref, pose, K, image, points, grad_u, grad_v):  # pragma: no cover - compiled
    """What a pose Jacobian reads of frame i at the reference points points_ref (N, 3) metres:
    the frame-i points ``R P + t`` (N, 3) (pose (4, 4) = [R t]) and the (H, W, 3) image's colour
    gradients grad_u, grad_v (N, 3) at their projections (:func:`image_gradients_at`; where the
    projection is not finite, at pixel (0, 0)). The same per-pixel function as :func:`accumulate_frame`'s."""
    for p in numba.prange(points_ref.shape[0]):
        warp_gradients_pixel(points_ref, pose, K, image, points, grad_u, grad_v, p)


@numba.njit(inline="always")
def csr_position(indptr, indices, row, column):  # pragma: no cover - compiled
    """Index into a CSR matrix's data of entry (row, column), its row's columns ascending; -1
    where the pattern has no such entry (binary search)."""
    lo, hi = indptr[row], indptr[row + 1]
    while lo < hi:
        mid = (lo + hi) // 2
        if indices[mid] < column:
            lo = mid + 1
        else:
            hi = mid
    if lo < indptr[row + 1] and indices[lo] == column:
        return lo
    return -1


@numba.njit(parallel=True, cache=True)
def add_stencil_gram(indptr, indices, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, Saa, Sbb, Sgg, Sab, Sag,
                     Sbg, data):  # pragma: no cover - compiled
    """data (nnz,) += the entries of ``sum_k R_k^T W_k R_k`` on a CSR pattern (indptr, indices,
    columns ascending per row) that holds them: for pixel k the row ``R_k = a Du_k + b Dv_k + c e_k``
    of the central-difference stencil (:class:`o3d_mvps.model.normals.MaskedGrid`: Du_k holds
    wf_u at fwd_u[k], -wb_u at bwd_u[k] and wb_u - wf_u at k), and the per-pixel weighted
    products Saa = sum w a a, ..., Sbg (N,) each. Returns False (the entries found written) where
    the pattern lacks an entry.

    Each pixel adds a 5 x 5 block on its stencil's nodes, so pixels share entries. The pattern's
    rows are taken in parallel: :func:`stencil_incidence` lists, per row, the pixels whose
    stencil holds it (pixels ascending), and each row adds their blocks' entries in its row in
    that order: every entry gets its terms in the order of one pass over the pixels, so the
    same sums bit for bit on any thread count."""
    N = fwd_u.shape[0]
    start, members = stencil_incidence(fwd_u, bwd_u, fwd_v, bwd_v)
    missing = 0
    for chunk in numba.prange(-(-N // CHUNK)):
        nodes = np.empty(5, np.int64)
        cu, cv, ce = np.zeros(5), np.zeros(5), np.zeros(5)
        for row in range(chunk * CHUNK, min(N, (chunk + 1) * CHUNK)):
            for at_member in range(start[row], start[row + 1]):
                k, p = members[at_member] // 5, members[at_member] % 5
                stencil_pixel(fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, nodes, cu, cv, ce, k)
                if cu[p] == 0.0 and cv[p] == 0.0 and ce[p] == 0.0:
                    continue
                for q in range(5):
                    if cu[q] == 0.0 and cv[q] == 0.0 and ce[q] == 0.0:
                        continue
                    at = csr_position(indptr, indices, row, nodes[q])
                    if at < 0:
                        missing += 1
                    else:
                        data[at] += stencil_gram_value(Saa[k], Sbb[k], Sgg[k], Sab[k], Sag[k], Sbg[k], cu, cv, ce, p,
                                                       q)
    return missing == 0


@numba.njit(cache=True)
def stencil_incidence(fwd_u, bwd_u, fwd_v, bwd_v):  # pragma: no cover - compiled
    """Which pixels' stencils (:func:`stencil_pixel`) hold each grid pixel: (start (N + 1,),
    members (5N,)) int64, row r's members ``members[start[r]:start[r + 1]]``, each ``5 k + p``
    for pixel k's node p (pixels ascending, then nodes); a counting sort, one pass each way."""
    N = fwd_u.shape[0]
    start = np.zeros(N + 1, np.int64)
    for k in range(N):
        start[k + 1] += 1
        start[fwd_u[k] + 1] += 1
        start[bwd_u[k] + 1] += 1
        start[fwd_v[k] + 1] += 1
        start[bwd_v[k] + 1] += 1
    for r in range(N):
        start[r + 1] += start[r]
    fill = start[:N].copy()
    members = np.empty(5 * N, np.int64)
    for k in range(N):
        for p in range(5):
            node = k if p == 0 else fwd_u[k] if p == 1 else bwd_u[k] if p == 2 else fwd_v[k] if p == 3 else bwd_v[k]
            members[fill[node]] = 5 * k + p
            fill[node] += 1
    return start, members


@numba.njit(inline="always")
def stencil_pixel(fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, nodes, cu, cv, ce, k):  # pragma: no cover
    """Pixel k's stencil row ``R_k = a Du_k + b Dv_k + c e_k`` of :func:`add_stencil_gram`: its 5
    nodes (k, u-forward, u-backward, v-forward, v-backward) into ``nodes`` (5,) and the
    coefficients of Du_k, Dv_k, e_k on them into cu, cv, ce (5,) each."""
    nodes[0], nodes[1], nodes[2], nodes[3], nodes[4] = k, fwd_u[k], bwd_u[k], fwd_v[k], bwd_v[k]
    for p in range(5):
        cu[p] = 0.0
        cv[p] = 0.0
        ce[p] = 0.0
    ce[0] = 1.0
    cu[0], cu[1], cu[2] = wb_u[k] - wf_u[k], wf_u[k], -wb_u[k]
    cv[0], cv[3], cv[4] = wb_v[k] - wf_v[k], wf_v[k], -wb_v[k]


@numba.njit(inline="always")
def stencil_gram_value(saa, sbb, sgg, sab, sag, sbg, cu, cv, ce, p, q):  # pragma: no cover - compiled
    """Entry (p, q) of one pixel's 5 x 5 block of R^T W R (:func:`stencil_pixel`'s coefficients,
    the pixel's weighted products Saa = sum w a a, ...)."""
    return (saa * cu[p] * cu[q] + sbb * cv[p] * cv[q] + sgg * ce[p] * ce[q]
            + sab * (cu[p] * cv[q] + cv[p] * cu[q]) + sag * (cu[p] * ce[q] + ce[p] * cu[q])
            + sbg * (cv[p] * ce[q] + ce[p] * cv[q]))


@numba.njit(parallel=True, cache=True)
def add_csr_into_pattern(indptr, indices, data, scale, a_indptr, a_indices, a_data):  # pragma: no cover - compiled
    """data (nnz,) of a CSR pattern (indptr, indices, columns ascending per row) += ``scale`` times
    the CSR matrix (a_indptr, a_indices, a_data) of the same shape; returns False (the entries
    found written) where the pattern lacks one of its entries. In parallel over the rows: each
    writes its own row's entries only, in its order, so the sums do not depend on the threads."""
    missing = 0
    for row in numba.prange(a_indptr.shape[0] - 1):
        for nz in range(a_indptr[row], a_indptr[row + 1]):
            at = csr_position(indptr, indices, row, a_indices[nz])
            if at < 0:
                missing += 1
            else:
                data[at] += scale * a_data[nz]
    return missing == 0


@numba.njit(inline="always")
def _add_column(columns, p, count, q):  # pragma: no cover - compiled
    """columns[p, :count] with column q added where absent; returns the new count."""
    for k in range(count):
        if columns[p, k] == q:
            return count
    columns[p, count] = q
    return count + 1


@numba.njit(parallel=True, cache=True)
def stencil_rows(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, columns, counts):  # pragma: no cover
    """The rows of the pattern of ``|Du| + |Dv| + I`` (N, N), whose Gram holds the depth block's
    stencil Gram, from the CSR arrays of Du and Dv (N, N): row p's columns, each once and not
    sorted (p first, then Du's and Dv's columns whose values are not zero: the entries the sum
    of absolute values keeps), into ``columns[p, :counts[p]]`` (columns (N, K), K at least the
    longest row of Du plus that of Dv plus one; counts (N,)). In parallel over rows."""
    for p in numba.prange(counts.shape[0]):
        columns[p, 0] = p
        count = 1
        for nz in range(u_indptr[p], u_indptr[p + 1]):
            if u_data[nz] != 0.0:
                count = _add_column(columns, p, count, u_indices[nz])
        for nz in range(v_indptr[p], v_indptr[p + 1]):
            if v_data[nz] != 0.0:
                count = _add_column(columns, p, count, v_indices[nz])
        counts[p] = count


@numba.njit(cache=True)
def pattern_transpose(indptr, indices, t_indptr, t_indices):  # pragma: no cover - compiled
    """The pattern of X^T (N, M) from that of a CSR matrix X (M, N) (indptr (M + 1,), indices
    (nnz,)), without values: X^T's row q lists the rows of X that hold column q, ascending, into
    t_indices (nnz,), its offsets into t_indptr (N + 1,). Serial: a count, its cumulative sum
    and one pass over X's rows in order."""
    t_indptr[:] = 0
    for nz in range(indices.shape[0]):
        t_indptr[indices[nz] + 1] += 1
    for q in range(t_indptr.shape[0] - 1):
        t_indptr[q + 1] += t_indptr[q]
    fill = t_indptr[:-1].copy()
    for r in range(indptr.shape[0] - 1):
        for nz in range(indptr[r], indptr[r + 1]):
            q = indices[nz]
            t_indices[fill[q]] = r
            fill[q] += 1


#: Row chunks that :func:`gram_pattern_rows` splits the pattern's rows into (each thread takes
#: whole chunks, each chunk a marker of one int32 per column; not from the thread count, which a
#: cached function cannot read).
GRAM_PATTERN_CHUNKS = 16


@numba.njit(inline="always")
def _gram_pattern_row(p, xt_indptr, xt_indices, x_indptr, x_indices, marker, out, start):  # pragma: no cover - compiled
    """Row p of the pattern of X^T X: every column of the rows of X (CSR) that hold column p
    (X^T's row p), each once (``marker[q] == p`` once seen); where ``start`` >= 0 written into
    ``out[start:]`` in ascending order (an insertion sort: a few dozen columns a row). Returns
    their count."""
    c = 0
    for a in range(xt_indptr[p], xt_indptr[p + 1]):
        r = xt_indices[a]
        for b in range(x_indptr[r], x_indptr[r + 1]):
            q = x_indices[b]
            if marker[q] != p:
                marker[q] = p
                if start >= 0:
                    j = start + c
                    while j > start and out[j - 1] > q:
                        out[j] = out[j - 1]
                        j -= 1
                    out[j] = q
                c += 1
    return c


@numba.njit(parallel=True, cache=True)
def gram_pattern_rows(xt_indptr, xt_indices, x_indptr, x_indices, indptr, indices, fill):  # pragma: no cover - compiled
    """The pattern of X^T X (N, N) for X (M, N) given as CSR (x_indptr, x_indices) and its
    transpose X^T as CSR (xt_indptr, xt_indices): with ``fill`` False the row counts written
    into indptr[1:] (N + 1,), with ``fill`` True (indptr then the counts' cumulative sum) the
    columns, ascending per row, into indices (nnz,). A symbolic product: no values, no
    temporaries but a marker per chunk of rows; in parallel over chunks of rows."""
    N = indptr.shape[0] - 1
    chunk = max(4096, -(-N // GRAM_PATTERN_CHUNKS))
    for k in numba.prange(-(-N // chunk)):
        marker = np.full(N, -1, np.int32)
        for p in range(k * chunk, min(N, (k + 1) * chunk)):
            if fill:
                _gram_pattern_row(p, xt_indptr, xt_indices, x_indptr, x_indices, marker, indices, indptr[p])
            else:
                indptr[p + 1] = _gram_pattern_row(p, xt_indptr, xt_indices, x_indptr, x_indices, marker, indices, -1)


@numba.njit(parallel=True, cache=True)
def add_row_gram_into_pattern(indptr, indices, data, scale, a_indptr, a_indices, a_data):  # pragma: no cover - compiled
    """data (nnz,) of a CSR pattern (columns ascending per row) += ``scale`` times A^T A of the
    CSR matrix A (M, N) (a_indptr, a_indices, a_data), without forming A^T A: each row's outer
    product added. Every column of A must hold at most one entry (a block average's rows): then
    each entry of A^T A is one product, written by one row, so the rows run in parallel without
    sharing an entry, and the sums equal :func:`add_csr_into_pattern` of ``A.T @ A`` bit for bit.
    Returns False (data partly written) where the pattern lacks one of its entries."""
    missing = 0
    for r in numba.prange(a_indptr.shape[0] - 1):
        for x in range(a_indptr[r], a_indptr[r + 1]):
            for y in range(a_indptr[r], a_indptr[r + 1]):
                at = csr_position(indptr, indices, a_indices[x], a_indices[y])
                if at < 0:
                    missing += 1
                else:
                    data[at] += scale * (a_data[x] * a_data[y])
    return missing == 0


@numba.njit(parallel=True, cache=True)
def jacobi_scaled_rows(indptr, data, omega, out):  # pragma: no cover - compiled
    """The values ``out`` (nnz,) of pyamg's locally weighted Jacobi operator ``omega D^-1 S``
    (``jacobi_prolongation_smoother``, ``weighting="local"``) of a canonical CSR matrix S (N, N)
    with float64 ``data``: row i's entries times ``1 / |sum_j |s_ij||`` (0 where that sum is 0),
    then times omega, in pyamg's order of operations (its row sums of ``abs(S)`` times a column
    of ones, summed in stored order from 0; its ``scale_rows``; its product with the scalar), so
    the same values bit for bit, without its three copies of S. In parallel over rows."""
    n = indptr.shape[0] - 1
    for i in numba.prange(n):
        d = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            d += abs(data[jj]) * 1.0
        inv = 1.0 / abs(d) if d != 0.0 else 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            out[jj] = (data[jj] * inv) * omega


#: rows of A per parallel chunk of :func:`sparse_product_into` (each chunk zeroes one dense row)
PRODUCT_CHUNK_ROWS = 256


@numba.njit(parallel=True, cache=True)
def sparse_product_into(a_indptr, a_indices, a_data, b_indptr, b_indices, b_data, c_indptr, c_indices, c_data,
                        columns):  # pragma: no cover - compiled
    """C = A B written into C's given pattern (CSR arrays; A (m, k), B (k, columns), C (m,
    columns)): every entry of the product must lie in the pattern (one it lacks is lost), a
    pattern entry the product lacks gets 0. Each row's entries are summed as scipy's
    ``csr_matmat`` sums them (A's row in order, each B row in order, into a dense row), in
    parallel over chunks of :data:`PRODUCT_CHUNK_ROWS` rows of A."""
    m = a_indptr.size - 1
    for chunk in numba.prange((m + PRODUCT_CHUNK_ROWS - 1) // PRODUCT_CHUNK_ROWS):
        acc = np.zeros(columns)
        for i in range(chunk * PRODUCT_CHUNK_ROWS, min(m, (chunk + 1) * PRODUCT_CHUNK_ROWS)):
            for k in range(a_indptr[i], a_indptr[i + 1]):
                a = a_data[k]
                j = a_indices[k]
                for l in range(b_indptr[j], b_indptr[j + 1]):
                    acc[b_indices[l]] += a * b_data[l]
            for k in range(c_indptr[i], c_indptr[i + 1]):
                c_data[k] = acc[c_indices[k]]
                acc[c_indices[k]] = 0.0


@numba.njit(inline="always")
def strong_in_row(indptr, indices, data, diags, theta, i, kept, start):  # pragma: no cover - compiled
    """Row i's strong connections of :func:`strong_connections` (pyamg's test, the diagonal
    always): their count, and where ``start`` >= 0 their columns written from ``kept[start]``."""
    eps = theta * theta * diags[i]
    c = 0
    for jj in range(indptr[i], indptr[i + 1]):
        j = indices[jj]
        if j == i or data[jj] * data[jj] >= eps * diags[j]:
            if start >= 0:
                kept[start + c] = j
            c += 1
    return c


@numba.njit(parallel=True, cache=True)
def strong_connections(indptr, indices, data, theta):  # pragma: no cover - compiled
    """The pattern (indptr (N+1,), indices (nnz',)) of pyamg's symmetric strength of connection
    of a CSR matrix (N, N) with float64 ``data``: the diagonal, and every (i, j) with
    ``a_ij^2 >= theta^2 |a_ii| |a_jj|``, in pyamg's order of operations (``amg_core``'s
    ``symmetric_strength_of_connection``, whose values smoothed aggregation does not read).
    Returns the input arrays themselves where every stored entry is kept. Three passes in
    parallel over rows (the diagonal, the rows' counts, their columns), the counts' running sum
    between them: the same pattern on any thread count."""
    n = indptr.shape[0] - 1
    diags = np.zeros(n)
    for i in numba.prange(n):
        d = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            if indices[jj] == i:
                d += data[jj]
        diags[i] = abs(d)
    counts = np.zeros(n + 1, indptr.dtype)
    for i in numba.prange(n):
        counts[i + 1] = strong_in_row(indptr, indices, data, diags, theta, i, indices, -1)
    for i in range(n):
        counts[i + 1] += counts[i]
    if counts[n] == indptr[n]:
        return indptr, indices
    kept = np.empty(counts[n], indices.dtype)
    for i in numba.prange(n):
        strong_in_row(indptr, indices, data, diags, theta, i, kept, counts[i])
    return counts, kept


@numba.njit(cache=True)
def diagonal_positions(indptr, indices):  # pragma: no cover - compiled
    """(N,) index into a CSR matrix's data of each diagonal entry (columns ascending per row),
    -1 where it is not stored."""
    n = indptr.shape[0] - 1
    out = np.empty(n, np.int64)
    for row in range(n):
        out[row] = csr_position(indptr, indices, row, row)
    return out



@numba.njit(inline="always")
def _cholesky_shifted(A, shift, L, i):  # pragma: no cover - compiled
    """L[i] (k, k) lower, ``L L^T = A[i] + shift I`` (A[i]'s lower triangle read); False at the
    first pivot that is not positive."""
    k = A.shape[1]
    for j in range(k):
        for c in range(j + 1):
            s = A[i, j, c] + (shift if j == c else 0.0)
            for m in range(c):
                s -= L[i, j, m] * L[i, c, m]
            if j == c:
                if not s > 0.0:
                    return False
                L[i, j, j] = math.sqrt(s)
            else:
                L[i, j, c] = s / L[i, c, c]
    return True


@numba.njit(inline="always")
def ridge_cholesky(A, ridge, fallback, L, i):  # pragma: no cover - compiled
    """The Cholesky factor L[i] of ``A[i] + ridge trace(A[i]) I`` (A (n, k, k) symmetric, its lower
    triangle read), or where that is not positive definite and ``fallback`` > 0, of
    ``A[i] + fallback max|diag A[i]| I``; False where A[i] is not finite or neither is positive
    definite."""
    k = A.shape[1]
    trace = 0.0
    largest = 0.0
    for j in range(k):
        trace += A[i, j, j]
        largest = max(largest, abs(A[i, j, j]))
        for c in range(j + 1):
            if not math.isfinite(A[i, j, c]):
                return False
    if _cholesky_shifted(A, ridge * trace, L, i):
        return True
    return fallback > 0.0 and _cholesky_shifted(A, fallback * largest, L, i)


@numba.njit(inline="always")
def cholesky_column(L, B, X, ok, i, c):  # pragma: no cover - compiled
    """Column c of X[i] = (L[i] L[i]^T)^-1 B[i] by forward and back substitution (NaN where not
    ``ok``): B, X (n, k, r)."""
    k = L.shape[1]
    for j in range(k):  # forward: L y = b
        s = B[i, j, c]
        if ok:
            for m in range(j):
                s -= L[i, j, m] * X[i, m, c]
            X[i, j, c] = s / L[i, j, j]
        else:
            X[i, j, c] = math.nan
    if ok:
        for j in range(k - 1, -1, -1):  # back: L^T x = y
            s = X[i, j, c]
            for m in range(j + 1, k):
                s -= L[i, m, j] * X[i, m, c]
            X[i, j, c] = s / L[i, j, j]


@numba.njit(inline="always")
def ridge_solve_system(A, B, ridge, fallback, L, X, solved, i):  # pragma: no cover - compiled
    """System i of a batch of small SPD systems: ``X[i] = (A[i] + ridge trace(A[i]) I)^-1 B[i]``
    by Cholesky (L[i] its factor, scratch); where that is not positive definite and ``fallback``
    > 0, with ``fallback max|diag A[i]|`` on the diagonal instead (:func:`ridge_cholesky`).
    solved[i] = 1.0, or 0.0 (X[i] NaN) where A[i] is not finite or neither shift makes it
    positive definite. A (n, k, k) symmetric, B and X (n, k, r), L (n, k, k), solved (n,)
    float64. The formula of :func:`.linear.ridge_solve` (the host's pose, LED offset and
    lighting steps) and of the GPU's batched solves (:func:`ridge_solves`, and
    :mod:`.cuda_kernels`' twin: one thread per system), the LED offset's step
    (:func:`led_offset_step`) and the joint step's inverse (:func:`joint_inverse`: the same Cholesky)."""
    ok = ridge_cholesky(A, ridge, fallback, L, i)
    solved[i] = 1.0 if ok else 0.0
    for c in range(B.shape[2]):
        cholesky_column(L, B, X, ok, i, c)


@numba.njit(cache=True)
def ridge_solves(A, B, ridge, fallback, L, X, solved):  # pragma: no cover - compiled
    """:func:`ridge_solve_system` of every system of the batch A (n, k, k), B (n, k, r) in
    turn: X (n, k, r), solved (n,) written, L (n, k, k) scratch."""
    for i in range(A.shape[0]):
        ridge_solve_system(A, B, ridge, fallback, L, X, solved, i)


@numba.njit(inline="always")
def led_trial_term(color, usable, albedo, normals, points, poses, start, x0, x1, x2, lights, scale, single, k, i,
                   p):  # pragma: no cover - compiled
    """Pixel p of frame i with the LED at trial k's offset ``start - 2^-k x`` (x = (x0, x1, x2):
    the step's negative; ``start`` itself where k < 0): ``sum_c log(1 + (scale r_c)^2)`` of its residuals
    ``r_c = I~_c - rho_c (l_0 + l_1 max(0, <n, v>))`` (0 where not usable), as
    :meth:`.LevelProblem.energy` forms them (:func:`shading_residual_pixel` on the LED basis of
    :func:`~o3d_mvps.model.shading.led_irradiance`, the LED's position
    :func:`~o3d_mvps.model.shading.led_position`); single: the basis and residual rounded to
    float32 as the GPU's evaluations store them."""
    if not usable[i, p]:
        return 0.0
    length = 1.0 if k >= 0 else 0.0  # k < 0: the offset ``start`` itself
    for _ in range(k):
        length *= 0.5
    o0 = start[0] - length * x0
    o1 = start[1] - length * x1
    o2 = start[2] - length * x2
    g = led_irradiance_at(normals, points, led_position(poses, o0, o1, o2, i, 0), led_position(poses, o0, o1, o2, i, 1),
                          led_position(poses, o0, o1, o2, i, 2), p)
    s = led_shading_at(g, lights, single, i)
    total = 0.0
    for c in range(3):
        r = color[i, p, c] - albedo[p, c] * s
        if single:
            r = np.float64(np.float32(r))
        total += log1p_square_term(r, scale)
    return total


@numba.njit(inline="always")
def led_offset_step(H, g, L, X, solved):  # pragma: no cover - compiled
    """The LED offset's Gauss-Newton step's negative ``x = (H + 1e-9 trace(H) I)^-1 g`` into
    X (1, 3, 1), solved (1,) (:func:`ridge_solve_system`, the host's :func:`.linear.ridge_solve`);
    H (1, 3, 3), g (1, 3, 1), L (1, 3, 3) scratch."""
    ridge_solve_system(H, g, 1e-9, 0.0, L, X, solved, 0)


@numba.njit(inline="always")
def store_offset_step(X, solved, g, out):  # pragma: no cover - compiled
    """The last row of :func:`led_trial_sums`' out: x (3,), solved, g (3,)."""
    K = out.shape[0] - 1
    for j in range(3):
        out[K, j] = X[0, j, 0]
        out[K, 4 + j] = g[0, j, 0]
    out[K, 3] = solved[0]


@numba.njit(parallel=True, cache=True)
def _led_trial_sums(color, usable, albedo, normals, points, poses, start, H, g, lights, scale, single, zero_row,
                    out):  # pragma: no cover - compiled
    K, n = out.shape[0] - 1, usable.shape[0]
    N = usable.shape[1]
    L, X, solved = np.empty((1, 3, 3)), np.empty((1, 3, 1)), np.empty(1)
    led_offset_step(H, g, L, X, solved)
    out[:] = 0.0
    store_offset_step(X, solved, g, out)
    x0, x1, x2 = X[0, 0, 0], X[0, 1, 0], X[0, 2, 0]
    for ki in numba.prange(K * n):
        k, i = ki // n, ki % n
        total = 0.0
        for p in range(N):
            total += led_trial_term(color, usable, albedo, normals, points, poses, start, x0, x1, x2, lights, scale,
                                    single, k if k != zero_row else -1, i, p)
        out[k, i] = total


def trial_blocks(n_frames: int, n_pixels: int) -> int:
    """Columns B of :func:`led_trial_sums`' out: here one per frame, at least 7 (not a launch)."""
    return max(7, n_frames)


def led_trial_sums(color, usable, albedo, normals, points, poses, start, H, g, lights, scale, single, out,
                   current: bool = False) -> None:
    """The LED offset's step and its K line-search trials in one pass. The step's negative x
    from its Gauss-Newton system H (1, 3, 3), g (1, 3, 1) (:func:`led_offset_step`); out (K + 1,
    B): rows k < K partial sums adding up to ``sum_{i,p,c} log(1 + (scale r)^2)`` of trial k,
    the LED at ``start - 2^-k x`` (:func:`led_trial_term`), row K = x (3), solved (1.0 or 0.0),
    g (3) (:func:`store_offset_step`), B = :func:`trial_blocks` (n, N) (here one sum per frame;
    on a GPU one launch, B its blocks). color (n, N, 3), usable (n, N), albedo, normals, points
    (N, 3) float64, poses (n, 4, 4), start (3,), lights (n, 2) float64; single: float32
    residuals. current: the last trial row K - 1 is the LED at ``start`` (the current
    offset's data sum, read with the trials: no read of its own)."""
    _led_trial_sums(color, usable, albedo, normals, points, poses, start, H, g, lights, float(scale), bool(single),
                    out.shape[0] - 2 if current else -1, out)


#: The joint step's refined frames: one whose own twist Gram (6, 6) has a condition number
#: above this takes no twist (its depth rows stay): :func:`twist_system`.
MAX_TWIST_CONDITION = 1e12


@numba.njit(inline="always")
def symmetric_condition(A, W, i):  # pragma: no cover - compiled
    """The 2-norm condition number ``max|lambda| / min|lambda|`` of the symmetric matrix whose
    upper triangle is A[i]'s (k, k) (its lower triangle not read): cyclic Jacobi rotations in
    the scratch W[i] (k, k) until the off-diagonal part is below 1e-16 of the diagonal (the
    eigenvalues then carry an absolute error of ~1e-16 |A|, as LAPACK's do); inf where an entry
    is not finite or an eigenvalue is 0."""
    k = A.shape[1]
    for j in range(k):
        for c in range(j, k):
            if not math.isfinite(A[i, j, c]):
                return math.inf
            W[i, j, c] = A[i, j, c]
            W[i, c, j] = A[i, j, c]
    for _ in range(100):
        off = 0.0
        diagonal = 0.0
        for j in range(k):
            diagonal += W[i, j, j] * W[i, j, j]
            for c in range(j + 1, k):
                off += W[i, j, c] * W[i, j, c]
        if off <= 1e-32 * diagonal:
            break
        for p in range(k - 1):
            for q in range(p + 1, k):
                apq = W[i, p, q]
                if apq == 0.0:
                    continue
                theta = (W[i, q, q] - W[i, p, p]) / (2.0 * apq)
                t = 0.5 / abs(theta) if abs(theta) > 1e150 else 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                cos = 1.0 / math.sqrt(t * t + 1.0)
                sin = t * cos
                W[i, p, p] -= t * apq
                W[i, q, q] += t * apq
                W[i, p, q] = 0.0
                W[i, q, p] = 0.0
                for r in range(k):
                    if r != p and r != q:
                        arp, arq = W[i, r, p], W[i, r, q]
                        W[i, r, p] = cos * arp - sin * arq
                        W[i, p, r] = W[i, r, p]
                        W[i, r, q] = sin * arp + cos * arq
                        W[i, q, r] = W[i, r, q]
    largest, smallest = 0.0, math.inf
    for j in range(k):
        largest = max(largest, abs(W[i, j, j]))
        smallest = min(smallest, abs(W[i, j, j]))
    return largest / smallest if smallest > 0.0 else math.inf


@numba.njit(inline="always")
def twist_frame_kept(grams, limit, W, kept, f):  # pragma: no cover - compiled
    """kept[f] = 1.0 where frame slot f's twist Gram (upper triangle of grams[f] (6, 6)) has a
    condition number (:func:`symmetric_condition`) of at most ``limit``, else 0.0."""
    kept[f] = 1.0 if symmetric_condition(grams, W, f) <= limit else 0.0


@numba.njit(inline="always")
def twist_entry(grams, rhs_frames, rhs_projection, downdate, kept, hessian, rhs, selection, j,
                c):  # pragma: no cover - compiled
    """Entry (j, c) of the joint step's twist matrix: ``H = blockdiag(G_f) - downdate`` (6m, 6m)
    over the kept frames (G_f the symmetric Gram whose upper triangle grams[f] holds), an
    identity row and column for a frame not kept; of ``selection`` (6m, 6m): ``-diag(kept)``
    per twist row (the right-hand sides that make ``-H^-1 diag(kept)``, whose columns of a frame
    not kept are 0); for c = 0 also rhs[j] = rhs_frames[j] + rhs_projection[j] (0 for a frame
    not kept)."""
    fj, fc = j // 6, c // 6
    if kept[fj] == 0.0 or kept[fc] == 0.0:
        hessian[j, c] = 1.0 if j == c else 0.0
    else:
        a, b = j % 6, c % 6
        g = 0.0
        if fj == fc:
            g = grams[fj, a, b] + 0.0 if a <= b else grams[fj, b, a] + 0.0
        hessian[j, c] = g - downdate[j, c]
    selection[j, c] = -1.0 if j == c and kept[fj] != 0.0 else 0.0
    if c == 0:
        rhs[j] = rhs_frames[j] + rhs_projection[j] if kept[fj] != 0.0 else 0.0


@numba.njit(cache=True)
def twist_system(grams, rhs_frames, rhs_projection, downdate, limit, W, kept, hessian, rhs,
                 selection):  # pragma: no cover - compiled
    """The joint step's twist system from its sums over pixels: kept (m,) (:func:`twist_frame_kept`
    of every frame slot), hessian (6m, 6m), rhs (6m,) and selection (6m, 6m)
    (:func:`twist_entry`). grams (m, 6, 6) upper triangles, rhs_frames, rhs_projection (6m,),
    downdate (6m, 6m); W (m, 6, 6) scratch."""
    for f in range(grams.shape[0]):
        twist_frame_kept(grams, limit, W, kept, f)
    for j in range(hessian.shape[0]):
        for c in range(hessian.shape[1]):
            twist_entry(grams, rhs_frames, rhs_projection, downdate, kept, hessian, rhs, selection, j, c)


# --- the data term's evaluation in one pass (gpueval, issue #33) -------------------------------
# The energy of a level (data and prior) and an evaluation's residuals from one launch each on a
# GPU: every frame and pixel (backprojection, normal, warp and sample, light basis, residuals,
# robust terms) and the prior's rows in one kernel, which leaves per-block partial sums; the host
# reads those (one copy). The CPU's solver keeps its own path (:meth:`.LevelProblem.energy`);
# these loops are the CUDA kernels' twins (their tests, the launch counts).

#: most rows of the partial sums of :func:`energy_partials` and :func:`evaluation_partials`
#: (the CUDA kernels' blocks): a few per multiprocessor, one small copy to the host
ENERGY_BLOCKS = 1024

#: items (frame pixels or prior rows) per thread at the least, below :data:`ENERGY_BLOCKS`
ENERGY_ITEMS_PER_THREAD = 16


def energy_blocks(items: int) -> int:
    """Rows of the partial sums (the CUDA kernels' blocks of 128 threads) for ``items`` terms
    (not a launch)."""
    return max(1, min(ENERGY_BLOCKS, -(-items // (128 * ENERGY_ITEMS_PER_THREAD))))


@numba.njit(inline="always")
def prior_rows(z0, S_indptr, tau, mu):  # pragma: no cover - compiled
    """Rows of the prior that :func:`prior_term` sums: D's (z0's) where tau != 0, then S's where
    mu != 0 (tau = mu = 0: none, for an energy whose prior the caller has)."""
    rows = z0.shape[0] if tau != 0.0 else 0
    return rows + (S_indptr.shape[0] - 1 if mu != 0.0 else 0)


@numba.njit(inline="always")
def prior_term(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z, row):  # pragma: no cover
    """Row ``row`` of :func:`prior_rows`' count: ``tau (D z - z0)_row^2``, then past D's rows (or
    from the first where tau = 0) ``mu (S z)_k^2`` (:meth:`.pyramid.DepthPrior.energy`)."""
    M = z0.shape[0] if tau != 0.0 else 0
    if row < M:
        d = csr_row_dot(D_indptr, D_indices, D_data, z, row) - z0[row]
        return tau * (d * d)
    s = csr_row_dot(S_indptr, S_indices, S_data, z, row - M)
    return mu * (s * s)


@numba.njit(inline="always")
def prior_sum(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z, start, stop,
              step):  # pragma: no cover - compiled
    """Sum of :func:`prior_term` over rows ``range(start, stop, step)`` (stop at most
    :func:`prior_rows`): a contiguous share on the CPU, a grid-stride share on a GPU."""
    total = 0.0
    for row in range(start, stop, step):
        total += prior_term(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z, row)
    return total


@numba.njit(inline="always")
def pixel_view(z, u, v, K, poses, images, visible, i, p):  # pragma: no cover - compiled
    """The reference point (x, y, z) of depth z at pixel p (:func:`~o3d_mvps.model.camera.backproject`),
    its pixel (uu, vv) in frame i and whether frame i sees it there (:func:`warp_sample_pixel`'s
    test): (x, y, z, uu, vv, usable)."""
    zp = z[p]
    x = (u[p] - K[0, 2]) / K[0, 0] * zp
    y = (v[p] - K[1, 2]) / K[1, 1] * zp
    _, _, Z, uu, vv = project_point(poses[i], K, x, y, zp)
    H, W = images.shape[1], images.shape[2]
    use = visible[i, p] and Z > 1e-6 and uu >= 0.0 and uu <= W - 1.0 and vv >= 0.0 and vv <= H - 1.0
    return x, y, zp, uu, vv, use


@numba.njit(inline="always")
def basis_values(led, n0, n1, n2, x, y, zp, poses, o0, o1, o2, single, i):  # pragma: no cover - compiled
    """Frame i's light basis past its leading 1 at a point (x, y, zp) with unit normal n: SH
    ``(n0, n1, n2)``; led ``(max(0, <n, v_i>), 0, 0)`` with the LED at offset (o0, o1, o2) in the
    frame's camera (:func:`~o3d_mvps.model.shading.led_position`); rounded to float32 where
    ``single`` (as the GPU's evaluations store their bases)."""
    if led:
        g = led_irradiance_of(n0, n1, n2, x, y, zp, led_position(poses, o0, o1, o2, i, 0),
                              led_position(poses, o0, o1, o2, i, 1), led_position(poses, o0, o1, o2, i, 2))
        b = g if g > 0.0 else 0.0
        if single:
            b = np.float64(np.float32(b))
        return b, 0.0, 0.0
    if single:
        return np.float64(np.float32(n0)), np.float64(np.float32(n1)), np.float64(np.float32(n2))
    return n0, n1, n2


@numba.njit(inline="always")
def basis_shading(led, lights, b1, b2, b3, i):  # pragma: no cover - compiled
    """``<B, l_i>`` of the basis (1, b1, b2, b3) of :func:`basis_values`, summed in the order of
    :func:`shading_residual_pixel`."""
    s = 0.0
    s += 1.0 * lights[i, 0]
    s += b1 * lights[i, 1]
    if not led:
        s += b2 * lights[i, 2]
        s += b3 * lights[i, 3]
    return s


@numba.njit(inline="always")
def energy_term(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                lights, led, o0, o1, o2, scale, single, usable, i, p):  # pragma: no cover - compiled
    """Frame i, pixel p of :meth:`.LevelProblem.energy` in one pass: the reference point of
    depth z, its warp into frame i and the usable test (:func:`pixel_view`; written into
    ``usable[i, p]``), its unit normal (:func:`~o3d_mvps.model.normals.unit_normal_at`), the
    shading ``<B_i(p), l_i>`` (SH: ``B = [1, n]``; led: ``B = [1, max(0, <n, v_i>)]``:
    :func:`basis_values`), and ``sum_c log(1 + (scale r_c)^2)`` of its residuals
    (:func:`shading_residual_pixel`, 0 where not usable). single: the basis and residuals
    rounded to float32 as the GPU's evaluations store them; the colours are float32 samples."""
    x, y, zp, uu, vv, use = pixel_view(z, u, v, K, poses, images, visible, i, p)
    usable[i, p] = use
    if not use:
        return 0.0
    n0, n1, n2, _ = unit_normal_at(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, p)
    b1, b2, b3 = basis_values(led, n0, n1, n2, x, y, zp, poses, o0, o1, o2, single, i)
    s = basis_shading(led, lights, b1, b2, b3, i)
    image = images[i]
    u0, v0, a, b = bilinear_cell(image, uu, vv)
    total = 0.0
    for c in range(3):
        r = np.float64(np.float32(bilinear_in_cell(image, u0, v0, a, b, c))) - albedo[p, c] * s
        if single:
            r = np.float64(np.float32(r))
        total += log1p_square_term(r, scale)
    return total


@numba.njit  # not inline="always": numba's inlining pass refuses its 34 arguments ("a closure with *args")
def evaluate_pixel(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                   lights, led, o0, o1, o2, scale, single, points, normals, dA, color, usable, basis, shading,
                   residual, i, p):  # pragma: no cover - compiled
    """:func:`energy_term` writing what an evaluation holds: frame i's colour sample
    (:func:`warp_sample_pixel`), usable, basis (frame i's row where basis has one per frame, the
    one shared row from frame 0's pixels), shading and residuals (:func:`shading_residual_pixel`)
    at pixel p, and from frame 0 the pixel's point (N, 3), unit normal (N, 3) and dA (N,); single:
    the basis and residuals are float32 (rounded as stored). Returns the pixel's robust sum."""
    x, y, zp, uu, vv, use = pixel_view(z, u, v, K, poses, images, visible, i, p)
    usable[i, p] = use
    n0, n1, n2, area = unit_normal_at(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, p)
    b1, b2, b3 = basis_values(led, n0, n1, n2, x, y, zp, poses, o0, o1, o2, single, i)
    if i == 0:
        points[p, 0] = x
        points[p, 1] = y
        points[p, 2] = zp
        normals[p, 0] = n0
        normals[p, 1] = n1
        normals[p, 2] = n2
        dA[p] = area
    if led or i == 0:
        row = i if led else 0
        basis[row, p, 0] = 1.0
        basis[row, p, 1] = b1
        if not led:
            basis[row, p, 2] = b2
            basis[row, p, 3] = b3
    s = basis_shading(led, lights, b1, b2, b3, i)
    shading[i, p] = s
    image = images[i]
    u0, v0, a, b = bilinear_cell(image, uu, vv)
    for c in range(3):
        color[i, p, c] = bilinear_in_cell(image, u0, v0, a, b, c)
    total = 0.0
    for c in range(3):
        residual[i, p, c] = color[i, p, c] - albedo[p, c] * s if use else 0.0
        total += log1p_square_term(residual[i, p, c], scale)
    return total


@numba.njit(parallel=True, cache=True)
def _energy_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                     lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr, S_indices,
                     S_data, tau, mu, usable, partial):  # pragma: no cover - compiled
    n, N = visible.shape
    B = partial.shape[0]
    items, rows = n * N, prior_rows(z0, S_indptr, tau, mu)
    for k in numba.prange(B):
        data = 0.0
        for index in range(k * items // B, (k + 1) * items // B):
            data += energy_term(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images,
                                visible, albedo, lights, led, o0, o1, o2, scale, single, usable, index // N,
                                index % N)
        partial[k, 0] = data
        partial[k, 1] = prior_sum(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z,
                                  k * rows // B, (k + 1) * rows // B, 1)


def energy_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                    lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr, S_indices,
                    S_data, tau, mu, usable, partial) -> None:
    """A level's energy in one pass: partial (B, 2) rows whose column 0 adds up to ``sum_{i,p,c}
    log(1 + (scale r)^2)`` of every frame's residuals (:func:`energy_term`), column 1 to the
    prior's ``tau ||D z - z0||^2 + mu ||S z||^2`` (:func:`prior_term`); usable (n, N) written.
    z (N,) metres; the grid's u, v, differences' neighbours and weights (N,) each
    (:class:`~o3d_mvps.model.normals.MaskedGrid`); K (3, 3); poses (n, 4, 4); images (n, H, W, 3)
    float32; visible (n, N) bool; albedo (N, 3); lights (n, k) float64 (k = 2 where ``led``, else 4);
    (o0, o1, o2) the LED's offset (metres, camera frame); D and S as CSR arrays, z0 (M,).
    B = :func:`energy_blocks` (here a contiguous share of the items per row; on a GPU one block
    per row)."""
    _energy_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                     lights, bool(led), float(o0), float(o1), float(o2), float(scale), bool(single), D_indptr,
                     D_indices, D_data, z0, S_indptr, S_indices, S_data, float(tau), float(mu), usable, partial)


@numba.njit(inline="always")
def evaluation_term(color, albedo, basis, lights, usable, shading, residual, scale, i, p):  # pragma: no cover
    """:func:`shading_residual_pixel` on pixel p of frame i and ``sum_c log(1 + (scale r_c)^2)``
    of the residuals as stored (in the residual array's type)."""
    shading_residual_pixel(color, albedo, basis, lights, usable, shading, residual, i, p)
    total = 0.0
    for c in range(3):
        total += log1p_square_term(residual[i, p, c], scale)
    return total


@numba.njit(parallel=True, cache=True)
def _evaluation_partials(color, albedo, basis, lights, usable, shading, residual, scale, D_indptr, D_indices, D_data,
                         z0, S_indptr, S_indices, S_data, tau, mu, z, partial):  # pragma: no cover - compiled
    n, N = usable.shape
    B = partial.shape[0]
    items, rows = n * N, prior_rows(z0, S_indptr, tau, mu)
    for k in numba.prange(B):
        data = 0.0
        for index in range(k * items // B, (k + 1) * items // B):
            data += evaluation_term(color, albedo, basis, lights, usable, shading, residual, scale, index // N,
                                    index % N)
        partial[k, 0] = data
        partial[k, 1] = prior_sum(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z,
                                  k * rows // B, (k + 1) * rows // B, 1)


def evaluation_partials(color, albedo, basis, lights, usable, shading, residual, scale, D_indptr, D_indices, D_data,
                        z0, S_indptr, S_indices, S_data, tau, mu, z, partial) -> None:
    """:func:`shading_residuals` (shading (n, N), residual (n, N, 3) written) and the energy of
    its residuals and of the prior at depth z (N,) in one pass: partial (B, 2) as in
    :func:`energy_partials` (n = 0 frames: the prior alone)."""
    _evaluation_partials(color, albedo, basis, lights, usable, shading, residual, float(scale), D_indptr, D_indices,
                         D_data, z0, S_indptr, S_indices, S_data, float(tau), float(mu), z, partial)


@numba.njit(parallel=True, cache=True)
def _evaluate_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                       lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr, S_indices,
                       S_data, tau, mu, points, normals, dA, color, usable, basis, shading, residual,
                       partial):  # pragma: no cover - compiled
    n, N = visible.shape
    B = partial.shape[0]
    items, rows = n * N, prior_rows(z0, S_indptr, tau, mu)
    for k in numba.prange(B):
        data = 0.0
        for index in range(k * items // B, (k + 1) * items // B):
            data += evaluate_pixel(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images,
                                   visible, albedo, lights, led, o0, o1, o2, scale, single, points, normals, dA, color,
                                   usable, basis, shading, residual, index // N, index % N)
        partial[k, 0] = data
        partial[k, 1] = prior_sum(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z,
                                  k * rows // B, (k + 1) * rows // B, 1)


def evaluate_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                      lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr, S_indices,
                      S_data, tau, mu, points, normals, dA, color, usable, basis, shading, residual, partial) -> None:
    """:meth:`.LevelProblem.evaluate` in one pass (:func:`evaluate_pixel`): the arguments of
    :func:`energy_partials` (single: the basis and residuals are float32), and written: the
    points, unit normals (N, 3), dA (N,), colours (n, N, 3) float32, usable (n, N), basis (n, N, 2)
    under the LED or (1, N, 4), shading (n, N) and residuals (n, N, 3), and the partial sums
    (B, 2) as :func:`energy_partials`'."""
    _evaluate_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                       lights, bool(led), float(o0), float(o1), float(o2), float(scale), bool(single), D_indptr,
                       D_indices, D_data, z0, S_indptr, S_indices, S_data, float(tau), float(mu), points, normals, dA,
                       color, usable, basis, shading, residual, partial)


@numba.njit(inline="always")
def led_shading_jacobian(intensities, normals, points, positions, rotations, offset, out, i, p):  # pragma: no cover
    """out[i, p] (6,): d(shading)/d(xi) of frame i at point p under the LED
    (:meth:`.lighting.LEDLight.shading_jacobians`): the point gradient
    (:func:`~o3d_mvps.model.shading.led_point_gradient`, into out[i, p, :3] first) turned into
    the frame's camera, ``G = J R_i^T`` (rotations (m, 3, 3)), and ``[G, o x G]``."""
    led_point_gradient(intensities, normals, points, positions, out, i, p)
    J0, J1, J2 = out[i, p, 0], out[i, p, 1], out[i, p, 2]
    G0 = J0 * rotations[i, 0, 0] + J1 * rotations[i, 0, 1] + J2 * rotations[i, 0, 2]
    G1 = J0 * rotations[i, 1, 0] + J1 * rotations[i, 1, 1] + J2 * rotations[i, 1, 2]
    G2 = J0 * rotations[i, 2, 0] + J1 * rotations[i, 2, 1] + J2 * rotations[i, 2, 2]
    twist_row_into(G0, G1, G2, offset, out, i, p)


@numba.njit(parallel=True, cache=True)
def led_shading_jacobians_into(intensities, normals, points, positions, rotations, offset,
                               out):  # pragma: no cover - compiled
    """The LED's shading Jacobians (m, N, 6) written into out in one pass
    (:func:`led_shading_jacobian`): intensities (m,), float64 unit normals and points (N, 3),
    light positions (m, 3) in reference coordinates, the frames' rotations (m, 3, 3), the LED's
    offset (3,) in the camera frame (metres). The host's and a GPU's solver both run it."""
    N = points.shape[0]
    chunk = frame_chunk(N)
    for k in numba.prange(-(-N // chunk)):
        for i in range(positions.shape[0]):
            for p in range(k * chunk, min(N, (k + 1) * chunk)):
                led_shading_jacobian(intensities, normals, points, positions, rotations, offset, out, i, p)


# ============================================================================================
# gpusetup (issue 33 item 4): launchers that are one launch each on the GPU
# (:mod:`.cuda_kernels`' section of the same name); here their CPU twins.
# ============================================================================================

#: the most light-basis terms :func:`lighting_sums` takes (SH: 4, LED: 2)
MAX_LIGHT_TERMS = 4


@numba.njit(parallel=True, cache=True)
def albedo_update(residual, usable, values, shading, inv_lam, fallback, num, den, out):  # pragma: no cover - compiled
    """out (N, 3) = num / den where den > 1e-8, else ``fallback`` (N, 3): the albedo's closed
    form, num and den (N, 3) :func:`weighted_albedo_sums` (written too)."""
    weighted_albedo_sums(residual, usable, values, shading, inv_lam, num, den)
    for p in numba.prange(out.shape[0]):
        for c in range(3):
            d = den[p, c]
            out[p, c] = num[p, c] / d if d > 1e-8 else fallback[p, c]


@numba.njit(parallel=True, cache=True)
def albedo_refit_residuals(residual, usable, color, shading, inv_lam, fallback, basis, lights, num, den, albedo,
                           products, parts, scored):  # pragma: no cover - compiled
    """The host's albedo refit and re-evaluation in one pass over chunks of ``FRAME_CHUNK`` pixels:
    :func:`albedo_update` (albedo (N, 3) written; num, den (N, 3) its sums) from the IRLS weights of
    ``residual`` (n, N, 3), then :func:`shading_residual_pixel` at that albedo (shading (n, N) and
    residual written: the residual is read first and overwritten), and the data energy's
    ``sum log(1 + (inv_lam r)^2)`` of the residuals as stored: each pixel's factors multiplied
    into ``products[p]`` (N,, ones on entry; its logarithm taken before it passes
    :data:`PRODUCT_LOG_LIMIT`), chunk k's logarithms in ``parts[k]`` (zeros on entry); the energy is
    ``parts.sum()``. Albedo, shading and residuals the same bit for bit as the two steps (each
    pixel's frames in the same order); the energy equal to :func:`log1p_square_sum`'s to ~1e-14
    (another grouping of the factors). basis (n or 1, N, k), lights (n, k). ``scored`` False:
    no energy (products and parts left as they are), for a caller that refits the lights next."""
    n, N = usable.shape
    for k in numba.prange(-(-N // FRAME_CHUNK)):
        start, stop = k * FRAME_CHUNK, min(N, (k + 1) * FRAME_CHUNK)
        weighted_albedo_chunk(residual, usable, color, shading, inv_lam, num, den, start, stop)
        for p in range(start, stop):
            albedo_ratio_pixel(num, den, fallback, albedo, p)
        flushed = 0.0
        for i in range(n):
            for p in range(start, stop):
                shading_residual_pixel(color, albedo, basis, lights, usable, shading, residual, i, p)
                if scored and usable[i, p]:  # else residuals 0: factors 1
                    product, taken = flushed_product(products[p])
                    flushed += taken
                    for c in range(3):
                        product *= square_factor(residual[i, p, c], inv_lam)
                    products[p] = product
        if scored:
            for p in range(start, stop):
                flushed += math.log(products[p])
            parts[k] = flushed


def lighting_blocks(n_pixels: int) -> int:
    """The middle axis of :func:`lighting_sums`' out: its blocks per frame on the GPU (not a launch)."""
    return min(REDUCTION_BLOCKS, max(1, -(-n_pixels // (16 * 128))))


@numba.njit(parallel=True, cache=True)
def lighting_sums(residual, usable, color, albedo, inv_lam, basis, out):  # pragma: no cover - compiled
    """The lighting's per-frame weighted normal equations: out (n, B, k k + k + 1) shares over
    B chunks of the pixels, their sum over axis 1 frame i's Gram sum_p (sum_c w rho^2) B B^T
    (k x k, row-major), right-hand side sum_p (sum_c w rho I~) B (k) and usable count; w the
    Cauchy IRLS weights of residual (n, N, 3) (:func:`weighted_lighting_terms`), basis
    (n or 1, N, k)."""
    n, N = usable.shape
    B = out.shape[1]
    k = basis.shape[2]
    size = k * k + k + 1
    chunk = -(-N // B)
    for job in numba.prange(n * B):
        i, b = job // B, job % B
        m = min(i, basis.shape[0] - 1)
        for e in range(size):
            out[i, b, e] = 0.0
        for p in range(b * chunk, min(N, (b + 1) * chunk)):
            if usable[i, p]:
                a, s = weighted_lighting_terms(residual, usable, color, albedo, inv_lam, i, p)
                for r in range(k):
                    br = basis[m, p, r]
                    for c in range(k):
                        out[i, b, r * k + c] += br * a * basis[m, p, c]
                    out[i, b, k * k + r] += s * br
                out[i, b, size - 1] += 1.0


@numba.njit(inline="always")
def offset_system_add(ds, residual, usable, albedo, inv_lam, stride, acc, i, q):  # pragma: no cover - compiled
    """Frame i's spread pixel q (pixel q stride) added to acc (12,): the LED offset's Gram
    sum rho^2 w ds ds^T (3 x 3, row-major) and gradient -sum w rho r ds (3), w the Cauchy IRLS
    weights of the residual r (zero where not usable)."""
    p = q * stride
    if usable[i, p]:
        rw, rr = offset_pixel_weights(residual, albedo, inv_lam, i, p)
        offset_terms_add(acc, ds[i, q, 0], ds[i, q, 1], ds[i, q, 2], rw, rr)


@numba.njit(inline="always")
def offset_pixel_weights(residual, albedo, inv_lam, i, p):  # pragma: no cover - compiled
    """Pixel p of frame i's weights in the LED offset's system: (sum_c rho_c^2 w_c, sum_c w_c
    rho_c r_c), w the Cauchy IRLS weights of the residuals r (n, N, 3)."""
    rw = 0.0
    rr = 0.0
    for c in range(3):
        x = residual[i, p, c] * inv_lam
        w = 1.0 / (1.0 + x * x)
        rw += albedo[p, c] * albedo[p, c] * w
        rr += w * albedo[p, c] * residual[i, p, c]
    return rw, rr


@numba.njit(inline="always")
def offset_terms_add(acc, d0, d1, d2, rw, rr):  # pragma: no cover - compiled
    """acc (12,) += one pixel's Gram rw ds ds^T (row-major) and gradient -rr ds, ds = (d0, d1, d2)."""
    acc[0] += d0 * rw * d0
    acc[1] += d0 * rw * d1
    acc[2] += d0 * rw * d2
    acc[3] += d1 * rw * d0
    acc[4] += d1 * rw * d1
    acc[5] += d1 * rw * d2
    acc[6] += d2 * rw * d0
    acc[7] += d2 * rw * d1
    acc[8] += d2 * rw * d2
    acc[9] -= d0 * rr
    acc[10] -= d1 * rr
    acc[11] -= d2 * rr


@numba.njit(cache=True)
def offset_system(ds, residual, usable, albedo, inv_lam, stride, H, g):  # pragma: no cover - compiled
    """The LED offset's Gauss-Newton system over all frames from every ``stride``-th pixel: H
    (1, 3, 3), g (1, 3, 1) (:func:`offset_system_add`); ds (n, M, 3) d(shading)/d(offset) of
    the spread pixels, residual (n, N, 3), usable (n, N), albedo (N, 3) of all pixels."""
    acc = np.zeros(12)
    for i in range(ds.shape[0]):
        for q in range(ds.shape[1]):
            offset_system_add(ds, residual, usable, albedo, inv_lam, stride, acc, i, q)
    for e in range(9):
        H[0, e // 3, e % 3] = acc[e]
    for a in range(3):
        g[0, a, 0] = acc[9 + a]


@numba.njit(inline="always")
def inverse_diagonal_row(indptr, indices, data, inv_diag, i):  # pragma: no cover - compiled
    """inv_diag[i] = 1 / a_ii of the CSR matrix (its stored diagonal entries added; 1 / 0 = inf
    where none is stored, as ``1.0 / A.diagonal()``)."""
    d = 0.0
    for nz in range(indptr[i], indptr[i + 1]):
        if indices[nz] == i:
            d += data[nz]
    inv_diag[i] = 1.0 / d if d != 0.0 else math.inf


@numba.njit(inline="always")
def gershgorin_row(indptr, indices, data, inv_diag, i):  # pragma: no cover - compiled
    """Row i's ``sqrt(1/a_ii) sum_j |a_ij| sqrt(1/a_jj)``: the row sum of :func:`.krylov.spectral_bound`'s
    D^-1/2 |A| D^-1/2, in the order of ``scale * (abs(A) @ scale)``."""
    total = 0.0
    for nz in range(indptr[i], indptr[i + 1]):
        total += abs(data[nz]) * math.sqrt(inv_diag[indices[nz]])
    return math.sqrt(inv_diag[i]) * total


@numba.njit(inline="always")
def stencil_transpose_row(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, Ba, Bb, Bg, y, out,
                          i):  # pragma: no cover - compiled
    """out[i] = y[i] - (Du^T Ba + Dv^T Bb + Bg)[i], Du^T and Dv^T (N, N) CSR."""
    out[i] = y[i] - (csr_row_dot(u_indptr, u_indices, u_data, Ba, i) + csr_row_dot(v_indptr, v_indices, v_data, Bb, i)
                     + Bg[i])


@numba.njit(parallel=True, cache=True)
def stencil_transpose_subtract(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, Ba, Bb, Bg, y,
                               out):  # pragma: no cover - compiled
    """out (N,) = y - (Du^T Ba + Dv^T Bb + Bg): the joint step's depth right-hand side from the
    prior's negative gradient y (N,) and the per-pixel sums Ba, Bb, Bg (N,) each
    (:func:`.normal_equations.stencil_transpose`), Du^T, Dv^T (N, N) CSR."""
    for i in numba.prange(out.shape[0]):
        stencil_transpose_row(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, Ba, Bb, Bg, y, out, i)


@numba.njit(cache=True)
def depth_block_fill(indptr, indices, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, Saa, Sbb, Sgg, Sab, Sag, Sbg,
                     s1, t1_indptr, t1_indices, t1_data, s2, t2_indptr, t2_indices, t2_data, data,
                     missing):  # pragma: no cover - compiled
    """data (nnz,) of the depth block's CSR pattern (indptr, indices; zeroed by the caller) +=
    the stencil's Gram (:func:`add_stencil_gram`) + s1 T1 + s2 T2, T1 and T2 (N, N) CSR (the
    prior's Hessian terms; T2 with no rows where there is none); missing (1,) += the entries the
    pattern lacks (left out; on the host 1 for each part that lacks some)."""
    if not add_stencil_gram(indptr, indices, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, Saa, Sbb, Sgg, Sab,
                            Sag, Sbg, data):
        missing[0] += 1.0
    for scale, a_indptr, a_indices, a_data in ((s1, t1_indptr, t1_indices, t1_data),
                                               (s2, t2_indptr, t2_indices, t2_data)):
        if not add_csr_into_pattern(indptr, indices, data, scale, a_indptr, a_indices, a_data):
            missing[0] += 1.0


@numba.njit(inline="always")
def diagonal_value(indptr, indices, data, row):  # pragma: no cover - compiled
    """(position, value) of row's diagonal entry in a CSR matrix (a scan: any column order);
    (-1, 0.0) where it is not stored."""
    for nz in range(indptr[row], indptr[row + 1]):
        if indices[nz] == row:
            return nz, data[nz]
    return -1, 0.0


@numba.njit(inline="always")
def damp_diagonal(indptr, indices, data, damping, floor, missing, row):  # pragma: no cover - compiled
    """Row's diagonal entry d += damping max(d, floor) in place; missing[0] += 1 where not stored."""
    at, d = diagonal_value(indptr, indices, data, row)
    if at < 0:
        missing[0] += 1.0
    else:
        data[at] = d + damping * max(d, floor)


@numba.njit(cache=True)
def levenberg_damp(indptr, indices, data, damping, tiny, partial, missing):  # pragma: no cover - compiled
    """:func:`.linear.levenberg_damped` in place on a CSR matrix (N, N) that stores its whole
    diagonal: M_pp += damping max(M_pp, max(mean(M_pp) / 100, tiny)); missing (1,) += the rows
    without a stored diagonal (left undamped; set here); partial (blocks,) scratch of the GPU's
    launch."""
    n = indptr.shape[0] - 1
    missing[0] = 0.0
    total = 0.0
    for row in range(n):
        total += diagonal_value(indptr, indices, data, row)[1]
    floor = max(0.01 * (total / n), tiny) if n else tiny
    for row in range(n):
        damp_diagonal(indptr, indices, data, damping, floor, missing, row)


# ============================================================================================
# gpu3 (issue 33 item 4): the driver's extrapolation trials in one launch on the GPU
# (:mod:`.cuda_kernels`' section of the same name); here its CPU twin.
# ============================================================================================

#: the most factors :func:`extrapolation_trials` takes (the driver's: 1, 2, 4)
MAX_EXTRAPOLATION_FACTORS = 4


def extrapolation_blocks(n_pixels: int) -> int:
    """The second axis of :func:`extrapolation_trials`' ``bad``: its blocks per factor on the GPU
    (not a launch)."""
    return min(REDUCTION_BLOCKS, max(1, -(-n_pixels // (16 * 128))))


@numba.njit(inline="always")
def clipped_depth(x, lower, upper, p):  # pragma: no cover - compiled
    """x clipped into [lower[p], upper[p]] as ``np.clip`` (a NaN stays NaN); as it is where
    lower is empty (0,) (no envelope)."""
    if lower.shape[0] == 0:
        return x
    if x < lower[p]:
        x = lower[p]
    if x > upper[p]:
        x = upper[p]
    return x


@numba.njit(parallel=True, cache=True)
def extrapolation_trials(z, z0, albedo, albedo0, factors, lower, upper, z_out, albedo_out,
                         bad):  # pragma: no cover - compiled
    """Every factor's trial state of the driver's extrapolation at once: z_out (F, N), row f
    ``z + factors[f] (z - z0)`` of z, z0 (N,) metres clipped into [lower, upper] (N,) each (no
    clip where they are empty (0,)); albedo_out (F, N, 3) the same of albedo, albedo0 (N, 3),
    unclipped; bad (F, B) shares of the count of trial depths not > 0 (NaN counted), their sum
    over axis 1 the count (B :func:`extrapolation_blocks`, the GPU's blocks; here all in column
    0). factors: a tuple of at least F floats."""
    F, N = z_out.shape
    for f in range(F):
        s = factors[f]
        count = 0
        for p in numba.prange(N):
            x = clipped_depth(z[p] + s * (z[p] - z0[p]), lower, upper, p)
            z_out[f, p] = x
            if not x > 0.0:
                count += 1
            for c in range(3):
                albedo_out[f, p, c] = albedo[p, c] + s * (albedo[p, c] - albedo0[p, c])
        for b in range(bad.shape[1]):
            bad[f, b] = 0.0
        bad[f, 0] = count


@numba.njit(parallel=True, cache=True)
def depth_step(z, dz, t, lower, upper, out, bad):  # pragma: no cover - compiled
    """A line search's trial depth: out (N,) = z + t dz of z, dz (N,) metres, clipped into
    [lower, upper] (N,) each (no clip where they are empty (0,)); bad (B,) shares of the count
    of out's entries not > 0 (NaN counted), their sum the count (B :func:`extrapolation_blocks`,
    the GPU's blocks; here all in entry 0)."""
    N = z.shape[0]
    count = 0
    for p in numba.prange(N):
        x = clipped_depth(z[p] + t * dz[p], lower, upper, p)
        out[p] = x
        if not x > 0.0:
            count += 1
    for b in range(bad.shape[0]):
        bad[b] = 0.0
    bad[0] = count


# --- gpujoint (issue #33): the joint step's device assembly, twist system and read-out -------
# The GPU's joint step (:func:`.normal_equations.joint_system` on a device) in a handful of
# launches: a block of pixels in one (:func:`joint_block`: the light rows, the reference frame's
# parallax, every frame's sums and rows, the albedo projection), its rows' stencil transpose in
# one (:func:`add_stencil_transpose_rows`), the twist system from the partial sums in one
# (:func:`joint_twist_system`), the depth block and its right-hand side in one
# (:func:`joint_depth_system`), ``-H^-1`` with the Schur right-hand side's column in one
# (:func:`joint_inverse`) and the twists in one (:func:`twist_readout`). The host's solver keeps
# its own path; these are the CUDA kernels' CPU twins (the tests', and the launch counts').

#: Values per (partial row, frame slot) of :func:`joint_block`'s twist sums: the Gram's upper
#: triangle (21, row by row), the right-hand side (6) and the frame's usable pixels (1).
JOINT_SUMS = 28


def joint_blocks(n_pixels: int) -> int:
    """Partial rows of :func:`joint_block`'s twist sums for a block of ``n_pixels``: one per
    chunk of :data:`CHUNK` pixels (on the GPU: one per thread block)."""
    return chunk_count(n_pixels)


@numba.njit(inline="always")
def joint_pixel_rows(p, albedo, dA, L, u, v, K, points_ref, dshading, use0, q, alpha, beta, gamma, extra, sums,
                     e):  # pragma: no cover - compiled
    """:func:`joint_block`'s set-up of pixel p (block-local): q (B, 3) = albedo / dA; per frame i
    the light rows (:func:`.normal_equations._light_rows` of the frozen field L[i] (B, 3), or
    (1, 3) for one value per frame, and the pixel's u, v): alpha, beta, gamma (n, B); the
    reference frame's parallax into extra (B, 3) where it has rows (the formula of
    :func:`.normal_equations._parallax_rows`, from dshading[0] (B, 6) and use0 (B,)); the
    pixel's sums (9, B) and e (3, B, 3) (where it has rows) zeroed."""
    for c in range(3):
        q[p, c] = albedo[p, c] / dA[p]
    fx, cx, fy, cy = K[0, 0], K[0, 2], K[1, 1], K[1, 2]
    at = p if L.shape[1] > 1 else 0
    for i in range(alpha.shape[0]):
        L0, L1, L2 = L[i, at, 0], L[i, at, 1], L[i, at, 2]
        alpha[i, p] = fx * L0 - (u[p] - cx) * L2
        beta[i, p] = fy * L1 - (v[p] - cy) * L2
        gamma[i, p] = -L2
    if extra.shape[0] > 0:
        x, y, z = points_ref[p, 0], points_ref[p, 1], points_ref[p, 2]
        d0, d1, d2 = dshading[0, p, 0], dshading[0, p, 1], dshading[0, p, 2]
        use = 1.0 if use0[p] else 0.0
        for c in range(3):
            extra[p, c] = -albedo[p, c] * ((d0 * (x / z) + d1 * (y / z) + d2 * (z / z)) * use)
    for k in range(9):
        sums[k, p] = 0.0
    for k in range(e.shape[0]):
        for c in range(3):
            e[k, p, c] = 0.0


@numba.njit(parallel=True, cache=True)
def joint_rows(albedo, dA, L, u, v, K, points_ref, dshading, use0, q, alpha, beta, gamma, extra, sums,
               e):  # pragma: no cover - compiled
    """:func:`joint_pixel_rows` of every pixel of a host assembly block (its arguments), in
    parallel over the pixels: the light rows, q and the reference's parallax the same bit for bit
    as the array formulas (:func:`.normal_equations._light_rows`, ``albedo / dA``,
    :func:`.normal_equations._parallax_rows`), with sums and e zeroed."""
    for k in numba.prange(albedo.shape[0]):
        p = np.int64(k)  # a signed index (prange's may be unsigned: "p if ... else 0" would type as a float)
        joint_pixel_rows(p, albedo, dA, L, u, v, K, points_ref, dshading, use0, q, alpha, beta, gamma, extra, sums, e)


@numba.njit(inline="always")
def joint_frame(i, parallax, twists):  # pragma: no cover - compiled
    """(with_jacobian, slot) of frame i in :func:`joint_block`: every frame but the reference
    has its Jacobian where the parallax or the twists need it; with twists frame i > 0 has slot
    i - 1 (every frame a candidate: :func:`joint_twist_system` drops those without enough
    pixels), else none (-1)."""
    return i > 0 and (parallax or twists), (i - 1) if twists and i > 0 else -1


@numba.njit(inline="always")
def joint_pack_sums(G, b, count, out, r):  # pragma: no cover - compiled
    """out[r] (:data:`JOINT_SUMS`,) = the upper triangle of G (6, 6) row by row, b (6,), count."""
    k = 0
    for j in range(6):
        for c in range(j, 6):
            out[r, k] = G[j, c]
            k += 1
    for j in range(6):
        out[r, 21 + j] = b[j]
    out[r, 27] = count


@numba.njit(inline="always")
def joint_pixel_projection(p, residual, usable, shading, inv_lam, sums, e, rows, F, top, root, den,
                           num):  # pragma: no cover - compiled
    """The albedo projection of pixel p (:class:`.normal_equations._AlbedoProjection`'s formulas,
    per pixel, after every frame's :func:`accumulate_pixel`): d = s^T W s and s^T W r per channel
    (the frames in order, :func:`weighted_albedo_add`) into den, num (3,) scratch; 1 / d where
    d > 1e-12 (else 0) and its square root into root[p] (B, 3); the sums (9, B) less the
    projection's downdates; e (3, B, 3) scaled by 1 / d; the twist rows (3, m, 6, B) projected
    and F (m, 6, B, 3) scaled by root (:func:`project_twist_pixel`); top (3B,): s^T W r root, the
    row that F's Gram with it makes the projection's right-hand side."""
    for c in range(3):
        num[c] = 0.0
        den[c] = 0.0
    for i in range(usable.shape[0]):
        if usable[i, p]:
            for c in range(3):
                x = residual[i, p, c] * inv_lam
                ws = shading[i, p] / (1.0 + x * x)
                num[c] += ws * residual[i, p, c]
                den[c] += ws * shading[i, p]
    i0 = 1.0 / den[0] if den[0] > 1e-12 else 0.0
    i1 = 1.0 / den[1] if den[1] > 1e-12 else 0.0
    i2 = 1.0 / den[2] if den[2] > 1e-12 else 0.0
    ea0, ea1, ea2 = e[0, p, 0], e[0, p, 1], e[0, p, 2]
    eb0, eb1, eb2 = e[1, p, 0], e[1, p, 1], e[1, p, 2]
    ec0, ec1, ec2 = e[2, p, 0], e[2, p, 1], e[2, p, 2]
    a0, a1, a2 = ea0 * i0, ea1 * i1, ea2 * i2
    b0, b1, b2 = eb0 * i0, eb1 * i1, eb2 * i2
    c0, c1, c2 = ec0 * i0, ec1 * i1, ec2 * i2
    s0, s1, s2 = num[0], num[1], num[2]
    sums[0, p] -= a0 * ea0 + a1 * ea1 + a2 * ea2
    sums[1, p] -= b0 * eb0 + b1 * eb1 + b2 * eb2
    sums[2, p] -= c0 * ec0 + c1 * ec1 + c2 * ec2
    sums[3, p] -= a0 * eb0 + a1 * eb1 + a2 * eb2
    sums[4, p] -= a0 * ec0 + a1 * ec1 + a2 * ec2
    sums[5, p] -= b0 * ec0 + b1 * ec1 + b2 * ec2
    sums[6, p] -= a0 * s0 + a1 * s1 + a2 * s2
    sums[7, p] -= b0 * s0 + b1 * s1 + b2 * s2
    sums[8, p] -= c0 * s0 + c1 * s1 + c2 * s2
    e[0, p, 0] = a0
    e[0, p, 1] = a1
    e[0, p, 2] = a2
    e[1, p, 0] = b0
    e[1, p, 1] = b1
    e[1, p, 2] = b2
    e[2, p, 0] = c0
    e[2, p, 1] = c1
    e[2, p, 2] = c2
    root[p, 0] = math.sqrt(i0)
    root[p, 1] = math.sqrt(i1)
    root[p, 2] = math.sqrt(i2)
    for f in range(F.shape[0]):
        for j in range(6):
            project_twist_pixel(rows, F, e, root, f, j, p)
    if top.shape[0] > 0:
        top[3 * p] = s0 * root[p, 0]
        top[3 * p + 1] = s1 * root[p, 1]
        top[3 * p + 2] = s2 * root[p, 2]


@numba.njit(parallel=True, cache=True)
def joint_block(residual, shading, usable, inv_lam, albedo, dA, L, u, v, points_ref, poses, K, images, dshading,
                parallax, twists, q, alpha, beta, gamma, extra, sums, e, rows, F, top, root, partial):  # pragma: no cover
    """One block of B pixels of the joint step's assembly in one pass: per pixel
    :func:`joint_pixel_rows`, then every frame's :func:`accumulate_pixel` in order (each frame's
    Jacobian and slot by :func:`joint_frame`), then with the albedo projection (e (3, B, 3);
    (0, 1, 3): none) :func:`joint_pixel_projection`.

    residual (n, B, 3), shading, usable (n, B), albedo (B, 3), dA (B,), L (n, B or 1, 3) the
    frozen light field, u, v (B,) the pixels, points_ref (B, 3), poses (n, 4, 4), K (3, 3),
    images (n, H, W, 3), dshading (n, B, 6) or (n, 0, 6) for none; scratch q (B, 3), alpha, beta,
    gamma (n, B), extra (B, 3) (the reference's parallax, only with ``parallax`` and dshading;
    else (0, 3)); written: sums (9, B) the per-pixel sums of :func:`accumulate_frame`, rows
    (3, m, 6, B) and F (m, 6, B, 3) the twist rows, projected (m = n - 1 with ``twists``, else
    0), top (3B,) or (0,) (:func:`joint_pixel_projection`), root (B, 3), and partial (R, m,
    :data:`JOINT_SUMS`) the twist sums (:func:`joint_pack_sums`) per chunk of :data:`CHUNK`
    pixels, R = :func:`joint_blocks` (B)."""
    n, B = residual.shape[0], residual.shape[1]
    for chunk in numba.prange(partial.shape[0]):
        J, G, b, wqJ, wcJ = pixel_scratch()
        num, den = np.zeros(3), np.zeros(3)
        first, last = chunk * CHUNK, min(B, (chunk + 1) * CHUNK)
        for p in range(first, last):
            joint_pixel_rows(p, albedo, dA, L, u, v, K, points_ref, dshading, usable[0], q, alpha, beta, gamma, extra,
                             sums, e)
        for i in range(n):
            jac, slot = joint_frame(i, parallax, twists)
            G[:] = 0.0
            b[:] = 0.0
            count = 0.0
            ex = extra if i == 0 else extra[:0]
            r_i, sh_i, use_i = residual[i], shading[i], usable[i]
            for p in range(first, last):
                accumulate_pixel(p, r_i, sh_i, use_i, inv_lam, q, alpha[i], beta[i], gamma[i], ex, points_ref,
                                 poses[i], K, images[i], dshading[i], albedo, jac, parallax, sums, e, rows, F, slot,
                                 J, G, b, wqJ, wcJ)
                if use_i[p]:
                    count += 1.0
            if slot >= 0:
                joint_pack_sums(G, b, count, partial[:, slot], chunk)
        if e.shape[0] > 0:
            for p in range(first, last):
                joint_pixel_projection(p, residual, usable, shading, inv_lam, sums, e, rows, F, top, root, den, num)


@numba.njit(inline="always")
def joint_unpack_sums(partial, products, grams, rhs_frames, counts, D, f, item):  # pragma: no cover - compiled
    """Item ``item`` of :func:`joint_twist_system`'s sums: for item < :data:`JOINT_SUMS` value
    ``item`` of frame slot f summed over partial's rows (in order) into grams (m, 6, 6) (upper
    triangle), rhs_frames (6m,) or counts (m,); beyond, entry item - JOINT_SUMS of D
    ((6m + 1)^2) summed over products' (P, 6m + 1, 6m + 1)."""
    if item < JOINT_SUMS:
        total = 0.0
        for r in range(partial.shape[0]):
            total += partial[r, f, item]
        if item < 21:
            j, k = 0, item
            while k >= 6 - j:
                k -= 6 - j
                j += 1
            grams[f, j, j + k] = total
        elif item < 27:
            rhs_frames[6 * f + item - 21] = total
        else:
            counts[f] = total
        return
    index = item - JOINT_SUMS
    k = D.shape[0]
    total = 0.0
    for s in range(products.shape[0]):
        total += products[s, index // k, index % k]
    D[index // k, index % k] = total


@numba.njit(cache=True)
def joint_twist_system(partial, products, min_pixels, limit, grams, rhs_frames, D, W, kept, hessian, rhs,
                       selection):  # pragma: no cover - compiled
    """The joint step's twist system from :func:`joint_block`'s sums: the frames' Grams (m, 6, 6),
    right-hand sides rhs_frames (6m,) and usable pixels (into kept (m,), first) summed over
    partial (R, m, :data:`JOINT_SUMS`) (:func:`joint_unpack_sums`), D (6m + 1, 6m + 1) over
    products (P, 6m + 1, 6m + 1) (each block's F Gram with its top row: the projection's
    downdate and, in row 6m, its right-hand side); then kept[f] = 1.0 where the frame has at
    least ``min_pixels`` usable pixels and :func:`twist_frame_kept`, and hessian (6m, 6m), rhs
    (6m,) and selection (6m, 6m) by :func:`twist_entry`. W (m, 6, 6) scratch."""
    m = partial.shape[1]
    for f in range(m):
        for item in range(JOINT_SUMS):
            joint_unpack_sums(partial, products, grams, rhs_frames, kept, D, f, item)
    for index in range(D.shape[0] * D.shape[1]):
        joint_unpack_sums(partial, products, grams, rhs_frames, kept, D, 0, JOINT_SUMS + index)
    for f in range(m):
        joint_frame_kept(grams, limit, min_pixels, W, kept, f)
    K = hessian.shape[0]
    for j in range(K):
        for c in range(K):
            twist_entry(grams, rhs_frames, D[K], D, kept, hessian, rhs, selection, j, c)


@numba.njit(inline="always")
def joint_frame_kept(grams, limit, min_pixels, W, kept, f):  # pragma: no cover - compiled
    """kept[f] (its usable pixels on entry) = 1.0 where that is at least ``min_pixels`` and
    :func:`twist_frame_kept`, else 0.0."""
    enough = kept[f] >= min_pixels
    twist_frame_kept(grams, limit, W, kept, f)
    if not enough:
        kept[f] = 0.0


def joint_depth_system(indptr, indices, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, Saa, Sbb, Sgg, Sab, Sag,
                       Sbg, s1, t1_indptr, t1_indices, t1_data, s2, t2_indptr, t2_indices, t2_data, data, missing,
                       u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, Ba, Bb, Bg, y, out) -> None:
    """The joint step's depth block and right-hand side: :func:`depth_block_fill` (data (nnz,)
    zeroed by the caller, missing (1,)) and :func:`stencil_transpose_subtract` (out (N,)), the
    GPU's one launch."""
    depth_block_fill(indptr, indices, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, Saa, Sbb, Sgg, Sab, Sag, Sbg,
                     s1, t1_indptr, t1_indices, t1_data, s2, t2_indptr, t2_indices, t2_data, data, missing)
    stencil_transpose_subtract(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, Ba, Bb, Bg, y, out)


@numba.njit(inline="always")
def joint_inverse_row(X, rhs, j):  # pragma: no cover - compiled
    """Row j of X[0] ((K + 1, K + 1)) past its K x K block: X[0, j, K] = X[0, j, :K] . rhs for
    j < K, the last row (0, ..., 0, 1) for j = K."""
    K = rhs.shape[0]
    if j < K:
        total = 0.0
        for c in range(K):
            total += X[0, j, c] * rhs[c]
        X[0, j, K] = total
    else:
        for c in range(K):
            X[0, K, c] = 0.0
        X[0, K, K] = 1.0


@numba.njit(cache=True)
def joint_inverse(hessian, selection, rhs, fallback, L, X, solved):  # pragma: no cover - compiled
    """The joint step's ``H^-1 selection`` (:func:`ridge_cholesky` without a ridge,
    :func:`.normal_equations._cholesky`'s ``fallback``) in one augmented matrix X
    (1, K + 1, K + 1): ``[[H^-1 selection, H^-1 selection rhs], [0, 1]]``, so that
    ``X^T [U^T; rhs_z^T]`` gives the Schur complement's ``(-U H^-1)^T`` and right-hand side in
    one product. hessian, selection, L (1, K, K), rhs
    (K,), solved (1,)."""
    ok = ridge_cholesky(hessian, 0.0, fallback, L, 0)
    solved[0] = 1.0 if ok else 0.0
    for c in range(hessian.shape[1]):
        cholesky_column(L, selection, X, ok, 0, c)
    for j in range(X.shape[1]):
        joint_inverse_row(X, rhs, j)


@numba.njit(cache=True)
def twist_readout(P, dz, X, out):  # pragma: no cover - compiled
    """The twists out (K,) = P[j] . dz - X[0, j, K] of the Schur product P (K + 1, N) (rows j < K:
    (-U H^-1 diag(kept))^T) and the augmented inverse X (1, K + 1, K + 1) of :func:`joint_inverse`
    (its last column: -H^-1 diag(kept) rhs_xi), dz (N,)."""
    K = out.shape[0]
    for j in range(K):
        total = 0.0
        for q in range(dz.shape[0]):
            total += P[j, q] * dz[q]
        out[j] = total - X[0, j, K]
# ============================================================================================
# gpueval2 (issue 33): the LED offset's system from the light state in one launch on the GPU
# (:mod:`.cuda_kernels`' section of the same name); here its CPU twin.
# ============================================================================================


@numba.njit(inline="always")
def led_offset_system_add(intensities, normals, points, positions, rotations, residual, usable, albedo, inv_lam,
                          stride, acc, i, q):  # pragma: no cover - compiled
    """:func:`offset_system_add` of frame i's spread pixel q (pixel q stride) with its
    d(shading)/d(offset) formed here: ``ds = -J R_i^T``, J the LED's point gradient
    (:func:`~o3d_mvps.model.shading.led_point_gradient_of`; :meth:`.lighting.LEDLight.offset_jacobians`)."""
    p = q * stride
    if usable[i, p]:
        J0, J1, J2 = led_point_gradient_of(intensities, normals, points, positions, i, p)
        d0 = -(J0 * rotations[i, 0, 0] + J1 * rotations[i, 0, 1] + J2 * rotations[i, 0, 2])
        d1 = -(J0 * rotations[i, 1, 0] + J1 * rotations[i, 1, 1] + J2 * rotations[i, 1, 2])
        d2 = -(J0 * rotations[i, 2, 0] + J1 * rotations[i, 2, 1] + J2 * rotations[i, 2, 2])
        rw, rr = offset_pixel_weights(residual, albedo, inv_lam, i, p)
        offset_terms_add(acc, d0, d1, d2, rw, rr)


@numba.njit(cache=True)
def led_offset_system(intensities, normals, points, positions, rotations, residual, usable, albedo, inv_lam, stride, H,
                      g):  # pragma: no cover - compiled
    """:func:`offset_system` with the Jacobians formed per pixel (:func:`led_offset_system_add`),
    not read from an (n, M, 3) array: H (1, 3, 3), g (1, 3, 1) over every frame's pixels 0,
    stride, 2 stride, ...; intensities (n,), light positions (n, 3) in reference coordinates,
    rotations (n, 3, 3) of the poses, normals, points (N, 3) float64, residual (n, N, 3), usable
    (n, N), albedo (N, 3)."""
    acc = np.zeros(12)
    n, N = usable.shape
    for i in range(n):
        for q in range(-(-N // stride)):
            led_offset_system_add(intensities, normals, points, positions, rotations, residual, usable, albedo,
                                  inv_lam, stride, acc, i, q)
    for e in range(9):
        H[0, e // 3, e % 3] = acc[e]
    for a in range(3):
        g[0, a, 0] = acc[9 + a]


@numba.njit(inline="always")
def evidence_frame_terms(sums, r, s, l0, l1, l2):  # pragma: no cover - compiled
    """One frame's terms of :func:`.weighting.normal_evidence`'s sums at a pixel added to
    ``sums`` (g00, g01, g02, g11, g12, g22, v0, v1, v2, d: 10 floats): rho2 ``r``, shading ``s``
    (float64), light vector (l0, l1, l2); the new 10 sums (:func:`led_evidence_pixel`'s)."""
    g00, g01, g02, g11, g12, g22, v0, v1, v2, dd = sums
    us = r * s
    return (g00 + r * l0 * l0, g01 + r * l0 * l1, g02 + r * l0 * l2, g11 + r * l1 * l1, g12 + r * l1 * l2,
            g22 + r * l2 * l2, v0 + us * l0, v1 + us * l1, v2 + us * l2, dd + us * s)


@numba.njit(inline="always")
def led_evidence_pixel(usable, albedo, shading, intensities, normals, points, positions, G6, v, d,
                       p):  # pragma: no cover - compiled
    """Pixel p's sums of :func:`.weighting.normal_evidence`, its frames in order
    (:func:`evidence_frame_terms`), with the LED's fields
    formed here (:func:`~o3d_mvps.model.shading.led_field_of`), not read from an (n, N, 3) array:
    G6[:, p], v[:, p], d[p] over the frames that see p; rho2 = sum_c albedo[p, c]^2."""
    r = albedo[p, 0] * albedo[p, 0] + albedo[p, 1] * albedo[p, 1] + albedo[p, 2] * albedo[p, 2]
    sums = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for i in range(usable.shape[0]):
        if usable[i, p]:
            l0, l1, l2 = led_field_of(intensities, normals, points, positions, i, p)
            sums = evidence_frame_terms(sums, r, np.float64(shading[i, p]), l0, l1, l2)
    G6[0, p], G6[1, p], G6[2, p], G6[3, p], G6[4, p], G6[5, p] = sums[:6]
    v[0, p], v[1, p], v[2, p], d[p] = sums[6:]


@numba.njit(parallel=True, cache=True)
def led_evidence_sums(usable, albedo, shading, intensities, normals, points, positions, G6, v,
                      d):  # pragma: no cover - compiled
    """:func:`.weighting.normal_evidence`'s per-pixel sums under the LED (or point lights) in one
    pass, the fields formed per pixel (:func:`led_evidence_pixel`): G6 (6, N), v (3, N), d (N,)
    written; usable (n, N), albedo (N, 3), shading (n, N), intensities (n,), float64 unit normals
    and points (N, 3), light positions (n, 3) in reference coordinates."""
    for p in numba.prange(usable.shape[1]):
        led_evidence_pixel(usable, albedo, shading, intensities, normals, points, positions, G6, v, d, p)


@numba.njit(inline="always")
def albedo_ratio_pixel(num, den, fallback, out, p):  # pragma: no cover - compiled
    """out[p] (3,) = num / den where den > 1e-8, else ``fallback[p]`` (:func:`albedo_update`'s closed form)."""
    for c in range(3):
        d = den[p, c]
        out[p, c] = num[p, c] / d if d > 1e-8 else fallback[p, c]


def albedo_evaluation_partials(residual, usable, color, shading, inv_lam, fallback, num, den, albedo, basis, lights,
                               D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z,
                               partial) -> None:
    """:func:`albedo_update` (albedo (N, 3) written, from the IRLS weights of ``residual``) and
    then :func:`evaluation_partials` at that albedo (shading and residual written: the residual
    array is read first and overwritten) in one pass on a GPU (each thread a pixel: its albedo,
    then its frames' residuals): the driver's albedo step and re-evaluation, partial (B, 2) the
    data and prior sums, the data's scale ``inv_lam``."""
    albedo_update(residual, usable, color, shading, float(inv_lam), fallback, num, den, albedo)
    evaluation_partials(color, albedo, basis, lights, usable, shading, residual, inv_lam, D_indptr, D_indices, D_data,
                        z0, S_indptr, S_indices, S_data, tau, mu, z, partial)


def evaluate_albedo_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible,
                             albedo, lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr,
                             S_indices, S_data, tau, mu, points, normals, dA, color, usable, basis, shading, residual,
                             partial, num, den, refit) -> None:
    """:func:`evaluate_partials` at ``albedo`` and then :func:`albedo_evaluation_partials` (the
    albedo refit (N, 3) written into ``refit``, num and den (N, 3) scratch, the shading and
    residuals and partial sums those at the refit albedo) in one pass on a GPU (each thread a
    pixel: its frames' evaluation, its albedo, its frames' residuals again): a line search's
    trial with its albedo projected out (:func:`.depth.search_estimates`)."""
    evaluate_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                      lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr, S_indices,
                      S_data, tau, mu, points, normals, dA, color, usable, basis, shading, residual, partial)
    albedo_evaluation_partials(residual, usable, color, shading, scale, albedo, num, den, refit, basis, lights,
                               D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z, partial)


def trial_energy_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible,
                          albedo, lights, led, offsets, scale, single, D_indptr, D_indices, D_data, z0, S_indptr,
                          S_indices, S_data, tau, mu, usable, partial) -> None:
    """:func:`energy_partials` of F trial states at once (the driver's extrapolation factors):
    z (F, N), poses (F, n, 4, 4), albedo (F, N, 3), lights (F, n, k), offsets (F, 3) the LED's,
    usable (F, n, N) and partial (F, B, 2) written, trial f's in row f; the grid, K, images,
    visibility and prior as :func:`energy_partials` takes them. On a GPU one launch (grid:
    blocks x trials)."""
    for f in range(z.shape[0]):
        energy_partials(z[f], u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses[f], images, visible,
                        albedo[f], lights[f], led, offsets[f, 0], offsets[f, 1], offsets[f, 2], scale, single,
                        D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, usable[f], partial[f])
# --- gpukrylov --------------------------------------------------------------------------------
# The device multigrid's per-sweep set-up in one launch (issue 33): every level's smoother
# scaling, the Galerkin coarse operators (CSR on the middle levels, dense on the coarsest) and the
# coarsest level's inverse, from the system's CSR matrix and the grid's aggregation.


@numba.njit(inline="always")
def grid_max(value, partial):  # pragma: no cover - compiled
    """The largest ``value`` over every thread of the launch: on the host (one thread) the value
    itself; the CUDA kernel's through ``partial`` (blocks,) after the grid's sync (:mod:`.cuda_kernels`)."""
    return value


@numba.njit(inline="always")
def grid_prefix(value, partial):  # pragma: no cover - compiled
    """The sum of ``value`` over the launch's threads before this one (thread order: ``start``):
    0 on the host (one thread); the CUDA kernel's through ``partial`` (blocks,) after the grid's
    sync (:mod:`.cuda_kernels`). Integers as float64: exact below 2^53."""
    return 0.0


@numba.njit(inline="always")
def galerkin_row(indptr, indices, data, R_indptr, R_indices, P_indptr, P_indices, I, out_indices, out_data,
                 position, write):  # pragma: no cover - compiled
    """Row I of the Galerkin product ``P^T A P`` of A (N, N) CSR and a piecewise-constant
    prolongation P (N, n) (one entry of 1 a row: pixel i's aggregate ``P_indices[P_indptr[i]]``;
    R = P^T's row I: the aggregate's pixels): its columns J (ascending) and values, the sum of
    ``a_ij`` over i in aggregate I (R's order), j in aggregate J (A's stored order), written from
    ``position`` where ``write``; returns the row's number of columns."""
    count = 0
    last = -1
    big = 2147483647
    while True:
        following = big
        for k in range(R_indptr[I], R_indptr[I + 1]):
            i = R_indices[k]
            for nz in range(indptr[i], indptr[i + 1]):
                J = P_indices[P_indptr[indices[nz]]]
                if last < J < following:
                    following = J
        if following == big:
            return count
        if write:
            total = 0.0
            for k in range(R_indptr[I], R_indptr[I + 1]):
                i = R_indices[k]
                for nz in range(indptr[i], indptr[i + 1]):
                    if P_indices[P_indptr[indices[nz]]] == following:
                        total += data[nz]
            out_indices[position + count] = following
            out_data[position + count] = total
        count += 1
        last = following


@numba.njit(inline="always")
def dense_galerkin_row(indptr, indices, data, R_indptr, R_indices, P_indptr, P_indices, aggregated, I,
                       dense):  # pragma: no cover - compiled
    """Row I of ``P^T A P`` (:func:`galerkin_row`, the same sums in the same order) into the dense
    ``dense`` (n, n); with ``aggregated`` False, row I of A itself (P the identity)."""
    for J in range(dense.shape[1]):
        dense[I, J] = 0.0
    if not aggregated:
        for nz in range(indptr[I], indptr[I + 1]):
            dense[I, indices[nz]] += data[nz]
        return
    for k in range(R_indptr[I], R_indptr[I + 1]):
        i = R_indices[k]
        for nz in range(indptr[i], indptr[i + 1]):
            dense[I, P_indices[P_indptr[indices[nz]]]] += data[nz]


@numba.njit(inline="always")
def sweep_entry(M, pivots, k, b, item):  # pragma: no cover - compiled
    """Entry ``item`` (row-major) of step k of the Gauss-Jordan inversion in place of M (n, n)
    SPD (no pivoting: its pivots stay positive), reading pivot row and column k from
    ``pivots[b]`` (2, n) and writing row and column k + 1 after the step into ``pivots[1 - b]``
    (so that a step needs one barrier)."""
    n = M.shape[0]
    i, j = item // n, item % n
    p = pivots[b, 0, k]
    if i == k and j == k:
        value = 1.0 / p
    elif i == k:
        value = pivots[b, 0, j] / p
    elif j == k:
        value = -pivots[b, 1, i] / p
    else:
        value = M[i, j] - pivots[b, 1, i] * (pivots[b, 0, j] / p)
    M[i, j] = value
    if i == k + 1:
        pivots[1 - b, 0, j] = value
    if j == k + 1:
        pivots[1 - b, 1, i] = value


@numba.njit
def multigrid_setup_steps(m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr, p_indices, r_indptr,
                          r_indices, inv_diag, coarse, pivots, partial, layout, levels, start,
                          stride):  # pragma: no cover - compiled
    """:func:`multigrid_setup` by one thread of ``start, start + stride, ...`` rows (entries),
    every pass followed by :func:`grid_barrier`."""
    indptr, indices, data = m_indptr, m_indices, m_data
    P_indptr, P_indices, R_indptr, R_indices = m_indptr, m_indices, m_indptr, m_indices
    for k in range(levels + 1):
        n = layout[MG_FIELDS * k + MG_N]
        if k == 0:
            indptr, indices, data = m_indptr, m_indices, m_data
        else:
            indptr, indices, data = _mg_csr(a_indptr, a_indices, a_data, layout, k, MG_A_PTR, n)
        if k == levels:
            break
        offset = layout[MG_FIELDS * k + MG_VEC]
        diagonal = inv_diag[offset:offset + n]
        for i in range(start, n, stride):  # the smoother's D^-1 / bound (krylov.inverse_diagonal, spectral_bound)
            inverse_diagonal_row(indptr, indices, data, diagonal, i)
        grid_barrier()
        bound = -math.inf
        for i in range(start, n, stride):
            bound = max(bound, gershgorin_row(indptr, indices, data, diagonal, i))
        bound = grid_max(bound, partial)  # every thread past the Gershgorin sums (a grid sync)
        for i in range(start, n, stride):
            diagonal[i] = diagonal[i] / bound
        n_coarse = layout[MG_FIELDS * (k + 1) + MG_N]
        P_indptr, P_indices, _ = _mg_csr(p_indptr, p_indices, p_indices, layout, k, MG_P_PTR, n)
        R_indptr, R_indices, _ = _mg_csr(r_indptr, r_indices, r_indices, layout, k, MG_R_PTR, n_coarse)
        if k + 1 == levels:
            break
        C_indptr, C_indices, C_data = _mg_csr(a_indptr, a_indices, a_data, layout, k + 1, MG_A_PTR, n_coarse)
        for I in range(start, n_coarse, stride):  # the coarse rows' lengths, then their offsets, then the rows
            C_indptr[I + 1] = galerkin_row(indptr, indices, data, R_indptr, R_indices, P_indptr, P_indices, I,
                                           C_indices, C_data, 0, False)
        grid_barrier()
        chunk = -(-n_coarse // stride)
        low, high = min(n_coarse, start * chunk), min(n_coarse, (start + 1) * chunk)
        total = 0
        for I in range(low, high):
            total += C_indptr[I + 1]
        running = int(grid_prefix(float(total), partial))
        if start == 0:
            C_indptr[0] = 0
        for I in range(low, high):
            running += C_indptr[I + 1]
            C_indptr[I + 1] = running
        grid_barrier()
        for I in range(start, n_coarse, stride):
            galerkin_row(indptr, indices, data, R_indptr, R_indices, P_indptr, P_indices, I, C_indices, C_data,
                         C_indptr[I], True)
        grid_barrier()
    # the coarsest level: its dense matrix, then its inverse (Gauss-Jordan, symmetrised)
    n = coarse.shape[0]
    for I in range(start, n, stride):
        if levels == 0:
            dense_galerkin_row(indptr, indices, data, indptr, indices, indptr, indices, False, I, coarse)
        else:
            dense_galerkin_row(indptr, indices, data, R_indptr, R_indices, P_indptr, P_indices, True, I, coarse)
    grid_barrier()
    for item in range(start, 2 * n, stride):  # pivot row and column 0
        if item < n:
            pivots[0, 0, item] = coarse[0, item]
        else:
            pivots[0, 1, item - n] = coarse[item - n, 0]
    grid_barrier()
    for k in range(n):
        for item in range(start, n * n, stride):
            sweep_entry(coarse, pivots, k, k % 2, item)
        grid_barrier()
    for item in range(start, n * n, stride):
        i, j = item // n, item % n
        if i < j:
            value = (coarse[i, j] + coarse[j, i]) / 2
            coarse[i, j] = value
            coarse[j, i] = value
    grid_barrier()


@numba.njit(cache=True)
def multigrid_setup(m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr, p_indices, r_indptr,
                    r_indices, inv_diag, coarse, pivots, partial, layout, levels):  # pragma: no cover - compiled
    """The per-solve set-up of the device multigrid (:func:`.krylov.multigrid_preconditioner`) in
    one launch, on the hierarchy's ``layout`` (:data:`MG_FIELDS` ints per level, ``levels``
    above the coarsest): per level k < levels from its CSR matrix (level 0: m_*; then the
    packed a_*), D^-1 / bound into its slice of inv_diag (:func:`.krylov.make_smoother`'s values),
    and its Galerkin product ``P^T A P`` (piecewise-constant P: p_* its packed indptr and indices,
    r_* those of R = P^T; :func:`galerkin_row`) as the next level's CSR matrix in a_* (its
    columns ascending; a_* sized for level k + 1 at most level k's non-zeros) or, for the
    coarsest, dense into ``coarse`` (n, n), which is then inverted in place (Gauss-Jordan
    without pivoting, :func:`sweep_entry`; SPD) and symmetrised ((M + M^T) / 2). levels 0: the
    coarsest is m itself. pivots (2, 2, n), partial (blocks,): scratch."""
    multigrid_setup_steps(m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr, p_indices, r_indptr,
                          r_indices, inv_diag, coarse, pivots, partial, layout, levels, 0, 1)


@numba.njit(inline="always")
def prior_gradient_row(D_indptr, D_indices, D_data, t_indptr, t_indices, t_data, S_indptr, S_indices, S_data,
                       with_s, z, negative_z0, tau2, mu2, i):  # pragma: no cover - compiled
    """Row i of ``tau2 D^T (D z - z0) + mu2 S^T S z`` (with_s; else its first term), D^T's
    row from its CSR arrays t_* and each ``(D z - z0)_m`` it takes formed here, added as
    :func:`csr_multiply_add`'s three passes add them (``-z0 + 1 D z``, ``0 + tau2 D^T d``, ``+ mu2
    S^T S z``)."""
    total = 0.0
    for k in range(t_indptr[i], t_indptr[i + 1]):
        m = t_indices[k]
        total += t_data[k] * (negative_z0[m] + 1.0 * csr_row_dot(D_indptr, D_indices, D_data, z, m))
    value = 0.0 + tau2 * total
    if with_s:
        value = value + mu2 * csr_row_dot(S_indptr, S_indices, S_data, z, i)
    return value


@numba.njit(parallel=True, cache=True)
def prior_gradient(D_indptr, D_indices, D_data, t_indptr, t_indices, t_data, S_indptr, S_indices, S_data, with_s, z,
                   negative_z0, tau2, mu2, out):  # pragma: no cover - compiled
    """The depth prior's ``out = tau2 D^T (D z - z0) + mu2 S^T S z`` (N,) in one pass
    (:meth:`.pyramid.DepthPrior.negative_gradient`: tau2 = -2 tau, mu2 = -2 mu) for D (M, N),
    D^T (N, M) and S^T S (N, N) CSR (with_s False: S^T S unread), z (N,), negative_z0 (M,) = -z0."""
    for i in numba.prange(out.shape[0]):
        out[i] = prior_gradient_row(D_indptr, D_indices, D_data, t_indptr, t_indices, t_data, S_indptr, S_indices,
                                    S_data, with_s, z, negative_z0, tau2, mu2, i)
