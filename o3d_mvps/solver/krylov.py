"""Preconditioned CG and preconditioners that run on NumPy or CuPy arrays alike.

The CPU path (:mod:`.linear`) preconditions CG with pyamg's smoothed-aggregation cycle, which
cannot run on a GPU. Everything here is written against the array module of its data (NumPy
with scipy.sparse, or CuPy with cupyx.scipy.sparse; CuPy stays optional) and uses only what
both provide: sparse matrix-vector and matrix-matrix products, transposes, diagonals,
elementwise arithmetic, and a dense inverse of a small coarsest matrix.

Preconditioners of an SPD matrix A (N, N) with diagonal D, each a callable r (N,) -> z (N,):

- :func:`jacobi_preconditioner`: z = D^-1 r.
- :func:`chebyshev_preconditioner`: a Chebyshev polynomial in D^-1 A, its interval's top a
  Gershgorin bound (:func:`spectral_bound`).
- :func:`multigrid_preconditioner`: a geometric multigrid V-cycle on the pixel grid
  (:func:`pixel_prolongations`: 2x2-pixel aggregates, built once per grid), Galerkin coarse
  operators, damped-Jacobi or Chebyshev smoothing, a dense solve on the coarsest level.

All three are symmetric positive definite operators (when A is SPD), as CG requires.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..model.arrays import array_module, fused, sparse_module
from .device import kernels_for

#: Multigrid: the hierarchy ends at a level of at most this many unknowns, solved there by a
#: dense inverse (one matrix-vector product). pyamg's ``max_coarse`` on the CPU
#: (:func:`.linear.amg_preconditioner`) is 300; on a GPU, where each level of a V-cycle costs 16
#: kernel launches and a 2000 x 2000 product no more than one, the hierarchy stops a level or
#: two earlier (a 22400-pixel level: 2 levels above the dense one instead of 4).
MAX_COARSE = 2000


#: PCG's convergence test on a device (:func:`pcg`): after the first test, the host reads the
#: status again after as many iterations as the residual's mean reduction per iteration so far
#: needs to reach the tolerance, or, where that cannot be told, after this many.
CHECK_EVERY = 2


def pcg(A, b, x0, rtol: float, maxiter: int, preconditioner: Callable | None = None, first_check: int = 1,
        check_every: int = CHECK_EVERY):
    """Preconditioned CG on ``A x = b`` from x0 (None: zero) until the residual is at most
    ``rtol * |b|`` (as :func:`.linear.pcg`); returns (x, iterations, converged).

    A: (N, N) SPD, a sparse matrix or anything with ``A @ x`` (the Schur operator);
    b, x0: (N,) arrays of one module (NumPy or CuPy); preconditioner: SPD callable r -> z, None
    for plain CG. Stops early, unconverged, where the residual is no longer finite.

    Every scalar stays on the device: an iteration is the preconditioner, one product with A,
    three dot products and three fused kernels (:func:`o3d_mvps.model.arrays.fused`), and the
    residual test is made there too: once it passes, the iterations that follow change nothing
    (the same x and iteration count as stopping there). The host reads the status with the
    squared residuals (one stack and one copy: a synchronisation) after ``first_check``
    iterations, then after as many more as the mean reduction per iteration so far needs to
    reach the tolerance (:func:`_iterations_left`; ``check_every`` where that cannot be told): a
    solve expected to take about ``first_check`` iterations synchronises once or twice.
    """
    xp = array_module(b)
    bb = xp.dot(b, b)
    threshold = (rtol * rtol) * bb
    if x0 is None:
        x, r = xp.zeros_like(b), b
    else:
        x = _zero_if(bb, x0.astype(b.dtype))  # b = 0: x = 0, as on the host
        r = b - A @ x
    rr_start = rr = xp.dot(r, r)
    active, iterations, status = _progress(True, -1, rr, threshold)  # x0: iteration 0
    p = rz_previous = None
    next_check = max(1, min(first_check, maxiter))
    with np.errstate(divide="ignore", invalid="ignore"):  # idle iterations may divide by zero
        for iteration in range(1, maxiter + 1):
            z = r if preconditioner is None else preconditioner(r)
            rz = xp.dot(r, z)
            p = z if p is None else _cg_direction(active, z, p, rz, rz_previous)
            q = A @ p
            x, r = _cg_step(active, x, r, p, q, rz, xp.dot(p, q))
            rz_previous, rr_previous = rz, rr
            rr = xp.dot(r, r)
            active, iterations, status = _progress(active, iterations, rr, threshold)
            if iteration == next_check or iteration == maxiter:
                code, *squares = (float(v) for v in _to_host(xp, status, rr, rr_previous, rr_start, threshold))
                code = int(code)
                if not code & 2:
                    break
                next_check = iteration + _iterations_left(*squares, code >> 2, check_every)
        else:
            code = int(status)  # maxiter 0
    return x, code >> 2, bool(code & 1)


def _to_host(xp, *scalars):
    """The float64 0-d arrays ``scalars`` on the host, (k,): in one copy from a device (one stack)."""
    if xp is np:
        return [float(v) for v in scalars]
    return xp.stack(scalars).get()


def _iterations_left(rr: float, rr_previous: float, rr_start: float, threshold: float, iterations: int,
                     default: int) -> int:
    """CG's iterations still to go (at least 1) for the squared residual ``rr`` (``rr_previous``
    one iteration before) after ``iterations`` active ones from ``rr_start`` to reach
    ``threshold``, at the slower of the last iteration's reduction and the mean one so far (on
    the solver's systems the first iterations reduce the residual most: the mean alone
    foresaw too few), but no more than twice what the mean foresees (a slow last iteration is
    often followed by fast ones: alone it foresaw 15 where 4 were left); ``default`` where that
    cannot be told (no reduction, values not finite)."""
    if not (iterations > 0 and 0.0 < rr < rr_previous <= rr_start and threshold > 0.0 and np.isfinite(rr_start)):
        return default
    left = np.log(threshold / rr)  # < 0 while not converged
    mean = left / (np.log(rr / rr_start) / iterations)
    return max(1, int(np.ceil(min(left / np.log(rr / rr_previous), 2.0 * mean))))


@fused
def _zero_if(bb, x):
    """x (N,), or zeros where ``bb`` (0-d) is zero."""
    return array_module(x).where(bb == 0, 0.0, x)


@fused
def _cg_direction(active, z, p, rz, rz_previous):
    """CG's next direction ``z + (rz / rz_previous) p`` (N,), p itself once ``active`` is False."""
    return array_module(z).where(active, z + (rz / rz_previous) * p, p)


@fused
def _cg_step(active, x, r, p, q, rz, pq):
    """CG's step ``x + alpha p``, ``r - alpha q`` (alpha = rz / pq), x and r themselves once
    ``active`` is False."""
    xp = array_module(x)
    alpha = rz / pq
    return xp.where(active, x + alpha * p, x), xp.where(active, r - alpha * q, r)


@fused
def _progress(was_active, iterations, rr, threshold):
    """CG's state after an iteration of residual ``rr`` that ``was_active``: (active, iterations,
    status), active while neither converged (rr <= threshold) nor broken down (rr not finite),
    iterations counting the active ones, status ``4 iterations + 2 active + converged`` (float64:
    what the host reads, with the residuals, in one copy)."""
    converged = rr <= threshold
    iterations = iterations + was_active
    active = was_active & ~converged & array_module(rr).isfinite(rr)
    return active, iterations, 4.0 * iterations + 2.0 * active + 1.0 * converged


def inverse_diagonal(A):
    """1 / diag(A) (N,) of a sparse SPD matrix (a positive diagonal)."""
    return 1.0 / A.diagonal()


def spectral_bound(A, inv_diag) -> float:
    """An upper bound of the eigenvalues of D^-1 A (A (N, N) sparse SPD, inv_diag (N,) = 1 / diag(A)):
    Gershgorin's bound ``max_i sum_j |a_ij| / sqrt(a_ii a_jj)`` of the similar D^-1/2 A D^-1/2.

    One product and no iteration. On four of the solver's systems it lay 1-41 % above the largest
    eigenvalue, where the Rayleigh quotient of ten power iterations fell up to 29 % short (an
    isolated largest eigenvalue); a Chebyshev polynomial whose interval ends below the spectrum
    grows there, and can make the preconditioner indefinite.
    """
    xp = array_module(inv_diag)
    scale = xp.sqrt(inv_diag)
    return float(xp.max(scale * (abs(A) @ scale)))


@dataclass
class JacobiSmoother:
    """``steps`` damped Jacobi sweeps ``x += omega D^-1 (b - A x)`` on A (N, N) sparse SPD;
    with ``x`` None they start from zero (the first sweep then needs no product). One sweep with
    omega 1 from zero is the Jacobi preconditioner D^-1 b."""

    A: object
    inv_diag: object
    omega: float
    steps: int

    def __post_init__(self):
        self._scaled = self.omega * self.inv_diag  # omega D^-1, once: one operation less per sweep

    def __call__(self, b, x=None):
        """x (N,) after the sweeps on right-hand side b (N,), from x (N,) or zero (a new array:
        neither is written)."""
        for _ in range(self.steps):
            x = self._scaled * b if x is None else _jacobi_sweep(x, self._scaled, b, self.A @ x)
        return x


@fused
def _jacobi_sweep(x, scaled, b, Ax):
    """One damped Jacobi sweep ``x + omega D^-1 (b - A x)`` (N,) (scaled: omega D^-1)."""
    return x + scaled * (b - Ax)


@dataclass
class ChebyshevSmoother:
    """``steps`` steps of the Chebyshev iteration on A (N, N) sparse SPD, preconditioned by its
    diagonal D, for the eigenvalues of D^-1 A in [lower, upper] (Saad, Iterative Methods for
    Sparse Linear Systems, 2nd ed., algorithm 12.1). From zero, ``x = q(D^-1 A) D^-1 b`` with q
    of degree steps - 1 (steps - 1 products with A): symmetric, and positive definite where
    ``upper`` bounds the spectrum. Its residual polynomial is smallest on [lower, upper]."""

    A: object
    inv_diag: object
    lower: float
    upper: float
    steps: int

    def __post_init__(self):
        # the iteration's scalars do not depend on b: its diagonal scalings are formed once, so
        # that a step is a product and four vector operations (a GPU's cost is per operation)
        theta, delta = (self.upper + self.lower) / 2, (self.upper - self.lower) / 2
        sigma = theta / delta
        rho = 1.0 / sigma
        self._first = self.inv_diag / theta
        self._scales, self._diagonals = [], []
        for _ in range(self.steps - 1):
            rho_next = 1.0 / (2.0 * sigma - rho)
            self._scales.append(rho_next * rho)
            self._diagonals.append((2.0 * rho_next / delta) * self.inv_diag)
            rho = rho_next

    def __call__(self, b, x=None, correction=None):
        """x (N,) after the steps on right-hand side b (N,), from x (N,) or zero (a new array:
        neither is written); with ``correction`` (P (N, n) sparse CSR, c (n,)) from ``x + P c``.
        A step is one kernel (:func:`.kernels.chebyshev_update`: the product with A and the vector
        updates in one pass); on a GPU the first two from zero are one
        (:func:`.kernels.chebyshev_start`), and so are the correction and the restart
        (:func:`.kernels.prolong_restart`)."""
        scales, diagonals = self._scales, self._diagonals
        if x is not None and correction is not None:
            P, c = correction
            r, d, x = _prolong_restart(self.A, P, b, x, c, self._first)
        elif x is not None:  # the restart: r = b - A x, d = first r, x + d
            r, d, x = _chebyshev_update(self.A, b, x, x, 0.0, self._first, x)
        elif scales and array_module(b) is not np:  # d = x = first b and the next step in one kernel
            r, d, x = _chebyshev_start(self.A, b, self._first, scales[0], diagonals[0])
            scales, diagonals = scales[1:], diagonals[1:]
        else:
            r = b
            d = x = self._first * r
        for scale, diagonal in zip(scales, diagonals):
            r, d, x = _chebyshev_update(self.A, r, d, d, scale, diagonal, x)
        return x


def _chebyshev_update(A, r, v, d, scale: float, diagonal, x):
    """(r - A v, scale d + diagonal r_new, x + d_new), new (N,) arrays each, in one kernel on a
    GPU (on the host, where only the tests run this module's multigrid, by SciPy's product: the
    per-call start of numba's threads would cost more on their small systems)."""
    xp = array_module(r)
    if xp is np:
        r = r - A @ v
        d = d * scale + diagonal * r
        return r, d, x + d
    outputs = tuple(xp.empty_like(r) for _ in range(3))
    kernels_for(r).chebyshev_update(A.indptr, A.indices, A.data, r, v, d, float(scale), diagonal, x, *outputs)
    return outputs


def _chebyshev_start(A, b, first, scale: float, diagonal):
    """The Chebyshev smoother's first two steps from zero, (r, d, x) (N,) each, in one kernel
    (GPU only: :func:`.kernels.chebyshev_start`)."""
    outputs = tuple(array_module(b).empty_like(b) for _ in range(3))
    kernels_for(b).chebyshev_start(A.indptr, A.indices, A.data, b, first, float(scale), diagonal, *outputs)
    return outputs


def _prolong_restart(A, P, b, x, c, first):
    """(r, d, x) (N,) each of the Chebyshev smoother's restart from ``x + P c`` (r = b - A y,
    d = first r, y + d), in one kernel on a GPU (:func:`.kernels.prolong_restart`); on the host
    ``y`` by SciPy's product, then the restart."""
    xp = array_module(b)
    if xp is np:
        y = multiply_add(P, 1.0, c, x)
        return _chebyshev_update(A, b, y, y, 0.0, first, y)
    outputs = tuple(xp.empty_like(b) for _ in range(3))
    kernels_for(b).prolong_restart(A.indptr, A.indices, A.data, P.indptr, P.indices, P.data, b, x, c, first, *outputs)
    return outputs


def _restrict_residual(R, A, b, x):
    """``R (b - A x)`` (n,), a new array, in one kernel on a GPU (:func:`.kernels.restrict_residual`;
    on the host by SciPy's products)."""
    xp = array_module(b)
    if xp is np:
        return R @ multiply_add(A, -1.0, x, b)
    out = xp.empty(R.shape[0])
    kernels_for(b).restrict_residual(R.indptr, R.indices, R.data, A.indptr, A.indices, A.data, b, x, out)
    return out


def multiply_add(A, alpha: float, v, y):
    """``y + alpha A v`` (N,), a new array, for A (N, M) sparse CSR (float64 CSR data, int32
    indices on a GPU), in one kernel on a GPU (by
    SciPy's product on the host, as :func:`_chebyshev_update`)."""
    xp = array_module(y)
    if xp is np:
        return y + alpha * (A @ v)
    out = xp.empty_like(y)
    kernels_for(y).csr_multiply_add(A.indptr, A.indices, A.data, float(alpha), v, y, out)
    return out


def jacobi_preconditioner(A) -> JacobiSmoother:
    """z = D^-1 r for A (N, N) sparse SPD."""
    return JacobiSmoother(A, inverse_diagonal(A), 1.0, 1)


#: Bottom of a Chebyshev interval as a fraction of its top (:func:`spectral_bound`), for the
#: preconditioner and the multigrid smoother alike. On four of the solver's systems, multigrid
#: with 2-4 smoothing steps took, against 0.03: with 0.01 between 25 % fewer and 13 % more
#: iterations (mostly within 5 %); with 0.1 and 0.3 (the usual smoother choices, leaving the lower
#: spectrum to the coarse levels) 2-63 % and 20-125 % more. The polynomial alone: 0.003-0.03
#: within 7 %, 0.1 up to 22 % more.
CHEBYSHEV_LOWER_FRACTION = 0.03


def chebyshev_preconditioner(A, degree: int, lower_fraction: float = CHEBYSHEV_LOWER_FRACTION) -> ChebyshevSmoother:
    """The Chebyshev iteration of ``degree`` steps from zero (degree - 1 products with A) for A (N, N)
    sparse SPD, on [lower_fraction, 1] times the bound of D^-1 A's spectrum (:func:`spectral_bound`)."""
    inv_diag = inverse_diagonal(A)
    upper = spectral_bound(A, inv_diag)
    return ChebyshevSmoother(A, inv_diag, lower_fraction * upper, upper, degree)


#: Multigrid smoothers: damped Jacobi with omega = 4 / (3 lambda) (lambda: :func:`spectral_bound`
#: of D^-1 A), or Chebyshev on [:data:`CHEBYSHEV_LOWER_FRACTION` lambda, lambda].
SMOOTHERS = ("jacobi", "chebyshev")


def make_smoother(A, inv_diag, upper: float, kind: str, steps: int):
    """A multigrid smoother of ``kind`` (:data:`SMOOTHERS`) taking ``steps`` steps on A (N, N)
    sparse SPD, inv_diag (N,) = 1 / diag(A), ``upper`` bounding the spectrum of D^-1 A."""
    if kind == "jacobi":
        return JacobiSmoother(A, inv_diag, 4.0 / (3.0 * upper), steps)
    if kind == "chebyshev":
        return ChebyshevSmoother(A, inv_diag, CHEBYSHEV_LOWER_FRACTION * upper, upper, steps)
    raise ValueError(f"unknown smoother {kind!r}; use one of {SMOOTHERS}")


def pixel_aggregates(u, v, stride: int):
    """Aggregates of 2x2 pixels ``stride`` apart, of pixels at integer coordinates u, v (N,)
    each: (aggregate of each pixel (N,), the aggregates' coordinates (n,) each, n <= N).

    stride 1 joins neighbours; stride 2 joins the pixels two apart (u, u + 2) x (v, v + 2)
    within each 4x4 tile and keeps the four parity classes (u mod 2, v mod 2) apart on the
    coarse grid too (coordinate ``2 (u // 4) + u mod 2``).
    """
    xp = array_module(u)
    cu = stride * (u // (2 * stride)) + u % stride
    cv = stride * (v // (2 * stride)) + v % stride
    width = int(cu.max()) + 1
    keys, aggregate = xp.unique(cv * width + cu, return_inverse=True)
    return aggregate.ravel(), keys % width, keys // width


def tentative_prolongation(aggregate, n_coarse: int):
    """Piecewise-constant prolongation (N, n) sparse: 1 where pixel p lies in aggregate j."""
    xp = array_module(aggregate)
    n = aggregate.size
    return sparse_module(aggregate).csr_matrix((xp.ones(n), (xp.arange(n), aggregate)), shape=(n, n_coarse))


@dataclass
class MultigridLevel:
    """One level of :class:`Multigrid` above the coarsest: A (N, N) sparse SPD, its smoother,
    prolongation P (N, n) and restriction R = P^T (n, N)."""

    A: object
    smoother: object
    P: object
    R: object


@dataclass
class Multigrid:
    """A symmetric V-cycle: per level, the smoother from zero, the coarse correction of the
    residual, the same smoother again; ``coarse_inverse`` (n, n) dense at the coarsest."""

    levels: list
    coarse_inverse: object

    def __call__(self, r):
        """The cycle applied to r (N,): z (N,)."""
        return self._cycle(0, r)

    def _cycle(self, k: int, b):
        if k == len(self.levels):
            return self.coarse_inverse @ b
        level = self.levels[k]
        x = level.smoother(b)
        coarse = self._cycle(k + 1, _restrict_residual(level.R, level.A, b, x))
        if isinstance(level.smoother, ChebyshevSmoother):  # the correction in the smoother's restart
            return level.smoother(b, x, (level.P, coarse))
        return level.smoother(b, multiply_add(level.P, 1.0, coarse, x))

    @property
    def operator_complexity(self) -> float:
        """Stored non-zeros of all levels' operators over the finest's (coarsest counted dense)."""
        nnz = [level.A.nnz for level in self.levels] + [self.coarse_inverse.size]
        return sum(nnz) / nnz[0]


def pixel_prolongations(u, v, stride: int = 2, max_coarse: int = MAX_COARSE) -> list:
    """The tentative prolongations of a pixel grid's aggregation hierarchy: (N_l, N_l+1) sparse
    per level, from the pixels at integer coordinates u, v (N,) each
    (:attr:`o3d_mvps.model.normals.MaskedGrid.u`, ``.v``) by 2x2-pixel aggregates ``stride``
    apart (:func:`pixel_aggregates`), until at most ``max_coarse`` unknowns remain (or an
    aggregation joins nothing). They depend on the grid alone: built once per pyramid level,
    they serve every solve on it.

    Stride 2 (default): the central differences of the data rows do not couple a pixel to its
    neighbours, so where the smoothness weight is small (LED light) the slowest modes alternate
    in sign between neighbours and are smooth on each of the four parity classes, which
    neighbour aggregates cannot represent: on 26 LED systems CG took 0.68 times pyamg's
    iterations (geometric mean) with stride 2 and 1.11 times with stride 1 (958k-pixel depth
    system: 11 against 58). Under room light (large smoothness weight) stride 1 did better:
    1.12 against 1.25 times pyamg's (a 73k-pixel joint system: 20 against 33).
    """
    prolongations = []
    while u.size > max_coarse:
        aggregate, cu, cv = pixel_aggregates(u, v, stride)
        if cu.size == u.size:
            break
        prolongations.append(tentative_prolongation(aggregate, cu.size))
        u, v = cu, cv
    return prolongations


def multigrid_preconditioner(A, prolongations: list, *, smoother: str = "chebyshev", smoothing_steps: int = 3,
                             smoothed_prolongation: bool = False) -> Multigrid:
    """A multigrid V-cycle for A (N, N) sparse SPD on the hierarchy of tentative
    ``prolongations`` (:func:`pixel_prolongations`; the first has N rows).

    The coarse operators are ``P^T A P``; with ``smoothed_prolongation`` each P is first
    smoothed by one damped Jacobi step ``P = (I - 4/(3 lambda) D^-1 A) P_tent`` (lambda:
    :func:`spectral_bound`; as in smoothed aggregation). The coarsest level is solved by a dense
    inverse. ``smoother``: one of :data:`SMOOTHERS`, ``smoothing_steps`` before and after the
    coarse correction.

    The defaults are the measured best for the GPU: Chebyshev 3 took the fewest iterations of
    the smoothers tried (1 or 2 damped Jacobi steps: 1.5-3 times as many); smoothed
    prolongations saved 10-14 % of the iterations in all (-20 to +38 % per system) for 1.9-2.3
    times the non-zeros read per iteration and 7-14 times the setup (on the CPU), and they depend
    on A, so they cannot be built once per grid.
    """
    xp = array_module(A.diagonal())
    sparse = sparse_module(A)
    levels = []
    for P in prolongations:
        inv_diag = inverse_diagonal(A)
        upper = spectral_bound(A, inv_diag)
        if smoothed_prolongation:
            P = (P - (4.0 / (3.0 * upper)) * (sparse.diags(inv_diag, format="csr") @ (A @ P))).tocsr()
        R = P.T.tocsr()
        levels.append(MultigridLevel(A, make_smoother(A, inv_diag, upper, smoother, smoothing_steps), P, R))
        A = (R @ (A @ P)).tocsr()
    inverse = xp.linalg.inv(A.toarray())
    return Multigrid(levels, (inverse + inverse.T) / 2)
