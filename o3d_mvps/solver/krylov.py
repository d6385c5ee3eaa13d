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
from .kernels import (COOPERATIVE_BLOCKS, CG_RR, CG_RR_OLD, CG_RR_START, CG_STATE, CG_STATUS, CG_THRESHOLD,
                      LOW_RANK_CHUNK, MG_A_PTR, MG_B, MG_FIELDS, MG_MAX_LEVELS, MG_N, MG_P_PTR, MG_R_PTR, MG_ROWS,
                      MG_VEC, MG_XU, REDUCTION_BLOCKS)

#: Multigrid: the hierarchy ends at a level of at most this many unknowns, solved there by a
#: dense inverse (one matrix-vector product). pyamg's ``max_coarse`` on the CPU
#: (:func:`.linear.amg_preconditioner`) is 300; on a GPU, where each level of a V-cycle costs 16
#: kernel launches and a 2000 x 2000 product no more than one, the hierarchy stops a level or
#: two earlier (a 22400-pixel level: 2 levels above the dense one instead of 4).
MAX_COARSE = 2000


#: PCG's convergence test on a device (:func:`pcg`): where the residual's reduction after the
#: first test cannot tell the iterations left, the second (and last) test comes after
#: ``max(CHECK_EVERY, 2 iterations so far)`` more.
CHECK_EVERY = 2

#: PCG on a device reads its state at most this often (each read a synchronisation): after the
#: first read, the second is the solve's last (:func:`pcg`).
MAX_READS = 2

#: The second read's margin over the iterations foreseen left (:func:`_iterations_left`): it
#: comes after ``ceil(READ_MARGIN left) + 1`` more iterations (those after convergence change
#: nothing, but cost their launches: on the 640x480 LED problem's finest level a margin of 1.5
#: ran 75 iterations where 63 were needed, 1.0 ran 67; no solve there ended unconverged).
READ_MARGIN = 1.0


def pcg(A, b, x0, rtol: float, maxiter: int, preconditioner: Callable | None = None, first_check: int = 1,
        check_every: int = CHECK_EVERY):
    """Preconditioned CG on ``A x = b`` from x0 (None: zero) until the residual is at most
    ``rtol * |b|`` (as :func:`.linear.pcg`); returns (x, iterations, converged).

    A: (N, N) SPD, a sparse CSR matrix or anything with ``A @ x`` (the Schur operator);
    b, x0: (N,) arrays of one module (NumPy or CuPy); preconditioner: SPD callable r -> z, None
    for plain CG. Stops early, unconverged, where the residual is no longer finite.

    The recurrences are Chronopoulos and Gear's (SIAM J. Comput. Appl. Math. 1989; equal to
    CG's in exact arithmetic): with w = A z, both dot products (r.z, w.z) of an iteration in one
    pass, and s = A p by its recurrence, so that an iteration is the preconditioner and two
    kernels (:func:`.kernels.cg_scalars`: w = A z for a CSR matrix and the dot products;
    :func:`.kernels.cg_update`: p, s, x, r in place and r.r), plus the product with A where A
    is an operator. The scalars stay on the device (a state vector, :data:`.kernels.CG_STATE`),
    and so does the residual test: once it passes, the iterations that follow change nothing
    (the same x and iteration count as stopping there).

    On the host the state is tested after every iteration. On a device the host reads it (one
    copy: a synchronisation) at most :data:`MAX_READS` times: after ``first_check`` iterations,
    then after :data:`READ_MARGIN` times as many more as the residual's reduction so far says
    are left (:func:`_iterations_left`), the solve's last read: where CG has not converged by
    then, it returns unconverged (as at ``maxiter``, which no read passes).

    On a device with a :class:`Multigrid` packed for one kernel (:attr:`Multigrid.packed`) the
    V-cycles and CG's passes run in :func:`.kernels.multigrid_cg` (:func:`_pcg_multigrid`):
    every iteration up to a read in one launch, where A is the hierarchy's own CSR matrix or an
    operator that names its parts (``low_rank_parts``: the Schur complement).
    """
    xp = array_module(b)
    kernels = kernels_for(b)
    on_host = xp is np
    packed = None if on_host else getattr(preconditioner, "packed", None)
    state = xp.empty(CG_STATE)
    p, s = xp.empty_like(b), xp.empty_like(b)
    if packed is not None:  # r and z in the V-cycle's workspace: its level 0's right-hand side and result
        work = xp.empty((MG_ROWS, packed.unknowns))
        r, z = work[MG_B, :b.shape[0]], work[MG_XU, :b.shape[0]]
        x = xp.empty_like(b)
    elif x0 is None:
        x, r = xp.empty_like(b), xp.empty_like(b)
    if x0 is not None:
        x = _zero_if(xp.dot(b, b), x0.astype(b.dtype))  # b = 0: x = 0, as on the host
        residual = b - A @ x
        if packed is None:
            r = residual
        else:
            r[...] = residual
    # a CSR matrix (CuPy's have no format attribute): w = A z in the pass of the dot products
    matrix = getattr(A, "indptr", None) is not None and getattr(A, "format", "csr") == "csr"
    w = xp.empty_like(b) if matrix else None
    next_check, reads = max(1, min(first_check, maxiter)), 0
    code = None
    if packed is not None:  # CG's start in the first launch
        return _pcg_multigrid(A, matrix, b, x0 is None, rtol * rtol, x, p, s, w, work, state, packed, maxiter,
                              next_check, check_every)
    partial = xp.empty((REDUCTION_BLOCKS, 2))
    counter = xp.zeros(1, dtype=np.int32)
    kernels.cg_start(b, x, r, p, s, x0 is None, rtol * rtol, state, partial, counter)
    csr = (A.indptr, A.indices, A.data) if matrix else (counter, counter, state)
    for iteration in range(1, maxiter + 1):
        z = r if preconditioner is None else preconditioner(r)
        if not matrix:
            w = A @ z
        kernels.cg_scalars(*csr, matrix, z, r, w, state, partial, counter)
        kernels.cg_update(z, w, p, s, x, r, state, partial, counter)
        if on_host or iteration == next_check:
            code, rr, rr_previous, rr_start, threshold = _read_state(state)
            reads += 1
            if not code & 2 or (not on_host and reads == MAX_READS):
                break
            next_check = min(maxiter, iteration + _checks_apart(rr, rr_previous, rr_start, threshold, code, iteration,
                                                                check_every))
    if code is None:  # maxiter 0
        code = _read_state(state)[0]
    return x, code >> 2, bool(code & 1)


def _checks_apart(rr: float, rr_previous: float, rr_start: float, threshold: float, code: int, iteration: int,
                  check_every: int) -> int:
    """Iterations from a read of CG's state after ``iteration`` to the next (and last) on a device:
    :data:`READ_MARGIN` times the iterations foreseen left (:func:`_iterations_left`), plus one,
    or ``max(check_every, 2 iteration)`` where they cannot be foreseen."""
    left = _iterations_left(rr, rr_previous, rr_start, threshold, code >> 2)
    return max(check_every, 2 * iteration) if left is None else int(np.ceil(READ_MARGIN * left)) + 1


def _pcg_multigrid(A, matrix: bool, b, from_zero: bool, rtol2: float, x, p, s, w, work, state, packed, maxiter: int,
                   next_check: int, check_every: int):
    """:func:`pcg`'s start and iterations on a device with a packed multigrid (:attr:`Multigrid.packed`),
    the start (:func:`.kernels.cg_start`'s, on b (N,), ``from_zero``, rtol2 = rtol^2) in the first launch:
    where A is the hierarchy's own CSR matrix M, or ``M + C U^T`` (an operator with
    ``low_rank_parts`` (M, C (N, K), U^T (K, N)): the joint step's Schur complement), all
    iterations up to a read of the state in one launch of :func:`.kernels.multigrid_cg` (the
    V-cycles, products, dot products and steps), else per iteration the operator's product and
    one launch (the dot products and step, then the next V-cycle); the same reads as
    :func:`pcg`'s. Returns (x, iterations, converged)."""
    xp = array_module(x)
    kernels = kernels_for(x)
    partial = xp.empty((COOPERATIVE_BLOCKS, 4))
    z = work[MG_XU, :x.shape[0]]
    M = packed.source
    parts = getattr(A, "low_rank_parts", None)
    # CG's product in the kernel where A is the hierarchy's own matrix, or M + C U^T with M that matrix
    low_rank = not matrix and parts is not None and parts[0] is M
    matrix = (matrix and A is M) or low_rank
    csr = (M.indptr, M.indices, M.data)
    if low_rank:
        u_t, coupled = parts[2], parts[1]
        t_partial, t = xp.empty((-(-x.shape[0] // LOW_RANK_CHUNK), u_t.shape[0])), xp.empty(u_t.shape[0])
    else:
        u_t = coupled = t_partial = xp.empty((0, 0))
        t = xp.empty(0)

    begin = [True]  # the first launch starts CG

    def launch(n_steps: int, cycle_first: bool, w):
        kernels.multigrid_cg(n_steps, cycle_first, matrix, *csr, *packed.arrays, work, x, p, s, w, u_t, coupled,
                             t_partial, t, packed.layout, packed.levels, packed.cheb, begin[0], b, from_zero, rtol2,
                             state, partial)
        begin[0] = False

    iteration, reads, code = 0, 0, None
    w = xp.empty_like(x) if w is None else w
    if not matrix or maxiter < 1:
        launch(0, maxiter >= 1, x)  # the start and the first cycle, z from r (w unread)
    while iteration < maxiter:
        if matrix:
            launch(next_check - iteration, iteration == 0, w)
            iteration = next_check
        else:
            iteration += 1
            launch(1, False, A @ z)
            if iteration < next_check:
                continue
        code, rr, rr_previous, rr_start, threshold = _read_state(state)
        reads += 1
        if not code & 2 or reads == MAX_READS:
            break
        next_check = min(maxiter, iteration + _checks_apart(rr, rr_previous, rr_start, threshold, code, iteration,
                                                            check_every))
    if code is None:  # maxiter 0
        code = _read_state(state)[0]
    return x, code >> 2, bool(code & 1)


def _read_state(state) -> tuple:
    """(status code, rr, rr_previous, rr_start, threshold) of CG's state (:data:`.kernels.CG_STATE`)
    on the host: one copy from a device."""
    values = state if array_module(state) is np else state.get()
    return (int(values[CG_STATUS]), *(float(values[k]) for k in (CG_RR, CG_RR_OLD, CG_RR_START, CG_THRESHOLD)))


def _iterations_left(rr: float, rr_previous: float, rr_start: float, threshold: float, iterations: int) -> int | None:
    """CG's iterations still to go (at least 1) for the squared residual ``rr`` (``rr_previous``
    one iteration before) after ``iterations`` active ones from ``rr_start`` to reach
    ``threshold``, at the slower of the last iteration's reduction and the mean one so far (on
    the solver's systems the first iterations reduce the residual most: the mean alone
    foresaw too few), but no more than twice what the mean foresees (a slow last iteration is
    often followed by fast ones: alone it foresaw 15 where 4 were left); twice the mean's alone
    where the last iteration did not reduce the residual (CG's residual need not fall at every
    step); None where neither can be told (no reduction, values not finite)."""
    if not (iterations > 0 and 0.0 < rr < rr_start and threshold > 0.0 and np.isfinite(rr_start)):
        return None
    left = np.log(threshold / rr)  # < 0 while not converged
    mean = left / (np.log(rr / rr_start) / iterations)
    if not rr < rr_previous:
        return max(1, int(np.ceil(2.0 * mean)))
    return max(1, int(np.ceil(min(left / np.log(rr / rr_previous), 2.0 * mean))))


@fused
def _half_sum(a, b):
    """``(a + b) / 2`` (any shape; one kernel on a GPU)."""
    return (a + b) / 2


@fused
def _zero_if(bb, x):
    """x (N,), or zeros where ``bb`` (0-d) is zero."""
    return array_module(x).where(bb == 0, 0.0, x)


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
    return float(spectral_bound_array(A, inv_diag))


def spectral_bound_array(A, inv_diag):
    """:func:`spectral_bound` as a 0-d array of inv_diag's module: on a device it stays there
    (the multigrid's set-up reads nothing back)."""
    xp = array_module(inv_diag)
    scale = xp.sqrt(inv_diag)
    return xp.max(scale * (abs(A) @ scale))


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


def chebyshev_scalars(lower: float, upper: float, steps: int) -> tuple[float, list, list]:
    """The scalars of ``steps`` Chebyshev steps for the spectrum of D^-1 A in [lower, upper]
    (Saad, algorithm 12.1): (theta, scales, factors): the first step ``x = d = D^-1 b / theta``,
    step j (j = 1 .. steps - 1) ``d = scales[j-1] d + factors[j-1] D^-1 r``."""
    theta, delta = (upper + lower) / 2, (upper - lower) / 2
    sigma = theta / delta
    rho = 1.0 / sigma
    scales, factors = [], []
    for _ in range(steps - 1):
        rho_next = 1.0 / (2.0 * sigma - rho)
        scales.append(rho_next * rho)
        factors.append(2.0 * rho_next / delta)
        rho = rho_next
    return theta, scales, factors


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
        # the iteration's scalars do not depend on b: its diagonal scalings are formed once (at
        # the first call: the packed V-cycle of a GPU, :attr:`Multigrid.packed`, needs none), so
        # that a step is a product and four vector operations (a GPU's cost is per operation)
        self.theta, self.scales, self.factors = chebyshev_scalars(self.lower, self.upper, self.steps)
        self._first = None

    def _scalings(self):
        """(first, scales, diagonals): the first step's D^-1 / theta and each later step's
        scale and factor D^-1 (formed at the first call)."""
        if self._first is None:
            self._first = self.inv_diag / self.theta
            self._diagonals = [factor * self.inv_diag for factor in self.factors]
        return self._first, self.scales, self._diagonals

    def __call__(self, b, x=None, correction=None):
        """x (N,) after the steps on right-hand side b (N,), from x (N,) or zero (a new array:
        neither is written); with ``correction`` (P (N, n) sparse CSR, c (n,)) from ``x + P c``.
        A step is one kernel (:func:`.kernels.chebyshev_update`: the product with A and the vector
        updates in one pass); on a GPU the first two from zero are one
        (:func:`.kernels.chebyshev_start`), and so are the correction and the restart
        (:func:`.kernels.prolong_restart`)."""
        first, scales, diagonals = self._scalings()
        if x is not None and correction is not None:
            P, c = correction
            r, d, x = _prolong_restart(self.A, P, b, x, c, first)
        elif x is not None:  # the restart: r = b - A x, d = first r, x + d
            r, d, x = _chebyshev_update(self.A, b, x, x, 0.0, first, x)
        elif scales and array_module(b) is not np:  # d = x = first b and the next step in one kernel
            r, d, x = _chebyshev_start(self.A, b, first, scales[0], diagonals[0])
            scales, diagonals = scales[1:], diagonals[1:]
        else:
            r = b
            d = x = first * r
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


def make_smoother(A, inv_diag, upper, kind: str, steps: int):
    """A multigrid smoother of ``kind`` (:data:`SMOOTHERS`) taking ``steps`` steps on A (N, N)
    sparse SPD, inv_diag (N,) = 1 / diag(A), ``upper`` (a float or a 0-d array of inv_diag's
    module: read by no host; None where inv_diag is D^-1 divided by it already) bounding the
    spectrum of D^-1 A. Both smoothers are made for
    ``(D^-1 / upper) A``, whose spectrum lies in (0, 1]: the same iterations (damped Jacobi
    with omega 4/3, Chebyshev on [:data:`CHEBYSHEV_LOWER_FRACTION`, 1]), their scalars
    independent of ``upper``."""
    scaled = inv_diag if upper is None else inv_diag / upper  # None: inv_diag is D^-1 / upper already
    if kind == "jacobi":
        return JacobiSmoother(A, scaled, 4.0 / 3.0, steps)
    if kind == "chebyshev":
        return ChebyshevSmoother(A, scaled, CHEBYSHEV_LOWER_FRACTION, 1.0, steps)
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
class PackedHierarchy:
    """A :class:`Multigrid` of Chebyshev smoothers as :func:`.kernels.multigrid_cg` takes it (one
    launch for a whole V-cycle): source, level 0's operator (sparse CSR); arrays, the
    coarser levels' operators and every level's prolongation and restriction (CSR arrays each,
    concatenated), every level's D^-1 / bound (concatenated), the coarsest level's inverse and
    its product's scratch (segments, n); layout (:data:`.kernels.MG_FIELDS` ints per level, see
    there), levels (above the coarsest), cheb (theta, then each later step's scale and factor:
    :func:`chebyshev_scalars`), unknowns (of all levels: the workspace's columns)."""

    source: object
    arrays: tuple
    layout: tuple
    levels: int
    cheb: tuple
    unknowns: int


#: Columns of the coarsest inverse per segment of its product in :func:`.kernels.multigrid_cycle`
#: (a GPU's threads take a segment of a column each: 2000 unknowns, 63 segments, 126 000 threads)
COARSE_SEGMENT = 32


def pack_transfers(levels: list, xp) -> tuple:
    """The prolongations and restrictions of a V-cycle's ``levels`` (:class:`MultigridLevel`)
    packed as :func:`.kernels.multigrid_cg` takes them: (P indptr, indices, data, R indptr,
    indices, data), each the levels' arrays end to end (:func:`pack_hierarchy`), arrays of
    module ``xp``."""
    return tuple(_joined(xp, [getattr(getattr(level, kind), name) for level in levels], dtype)
                 for kind in ("P", "R") for name, dtype in (("indptr", np.int32), ("indices", np.int32),
                                                             ("data", np.float64)))


def _hierarchy_layout(sizes: list, nonzeros: list) -> tuple[list, dict]:
    """The packed hierarchy's layout (:data:`.kernels.MG_FIELDS` ints per level, for
    :data:`.kernels.MG_MAX_LEVELS` levels) and the packed arrays' lengths: sizes (L + 1,) the
    levels' unknowns, the coarsest last; nonzeros (L,) per level above the coarsest the
    non-zeros (or room for them) of its matrix A (None: not packed, level 0's), P and R. Returns
    (layout, {"vec", "A_ptr", "A_nz", "P_ptr", "P_nz", "R_ptr", "R_nz"}: the lengths)."""
    layout = [0] * (MG_FIELDS * MG_MAX_LEVELS)
    ends = dict.fromkeys(("vec", "A_ptr", "A_nz", "P_ptr", "P_nz", "R_ptr", "R_nz"), 0)
    for k, n in enumerate(sizes):
        base = MG_FIELDS * k
        layout[base + MG_VEC], layout[base + MG_N] = ends["vec"], n
        ends["vec"] += n
        if k == len(sizes) - 1:
            break
        for name, field, rows, nz in zip("APR", (MG_A_PTR, MG_P_PTR, MG_R_PTR), (n, n, sizes[k + 1]), nonzeros[k]):
            if nz is not None:
                layout[base + field], layout[base + field + 1] = ends[f"{name}_ptr"], ends[f"{name}_nz"]
                ends[f"{name}_ptr"] += rows + 1
                ends[f"{name}_nz"] += int(nz)
    return layout, ends


def pack_hierarchy(levels: list, coarse_inverse, steps: int, transfers: tuple | None = None) -> PackedHierarchy | None:
    """The :class:`PackedHierarchy` of a V-cycle's ``levels`` (:class:`MultigridLevel`, Chebyshev
    smoothers of ``steps`` steps on [CHEBYSHEV_LOWER_FRACTION, 1]) and its coarsest inverse (n, n)
    on a device; None for more than :data:`.kernels.MG_MAX_LEVELS` levels. A list of one array is
    that array itself, so the packing costs a concatenation per kind of array of two levels or more;
    ``transfers``: the levels' :func:`pack_transfers` where kept (they depend on the grid alone)."""
    if len(levels) + 1 > MG_MAX_LEVELS:
        return None
    xp = array_module(coarse_inverse)
    sizes = [level.A.shape[0] for level in levels] + [coarse_inverse.shape[0]]
    layout, offsets = _hierarchy_layout(sizes, [(level.A.data.size if k else None, level.P.data.size,
                                                 level.R.data.size) for k, level in enumerate(levels)])
    theta, scales, factors = chebyshev_scalars(CHEBYSHEV_LOWER_FRACTION, 1.0, steps)
    n_coarse = coarse_inverse.shape[0]
    arrays = [_joined(xp, [getattr(level.A, name) for level in levels[1:]], dtype)
              for name, dtype in (("indptr", np.int32), ("indices", np.int32), ("data", np.float64))]
    arrays += pack_transfers(levels, xp) if transfers is None else transfers
    arrays.append(_joined(xp, [level.smoother.inv_diag for level in levels], np.float64))
    arrays += [coarse_inverse, xp.empty((-(-n_coarse // COARSE_SEGMENT), n_coarse))]
    return PackedHierarchy(levels[0].A if levels else None, tuple(arrays), tuple(layout), len(levels),
                           (theta, *(v for pair in zip(scales, factors) for v in pair)), offsets["vec"])


def _joined(xp, parts: list, dtype):
    """``parts`` (1-D arrays) end to end: an empty array of ``dtype`` for none, the array itself
    for one."""
    if not parts:
        return xp.empty(0, dtype=dtype)
    return parts[0] if len(parts) == 1 else xp.concatenate(parts)


@dataclass
class Multigrid:
    """A symmetric V-cycle: per level, the smoother from zero, the coarse correction of the
    residual, the same smoother again; ``coarse_inverse`` (n, n) dense at the coarsest.
    ``packed``: on a device, with Chebyshev smoothers, the same cycle for
    :func:`.kernels.multigrid_cg` (:func:`pack_hierarchy`; :func:`pcg` then runs the cycle and CG
    in one launch), else None."""

    levels: list
    coarse_inverse: object
    packed: PackedHierarchy | None = None

    def __call__(self, r):
        """The cycle applied to r (N,): z (N,)."""
        if self.levels and self.levels[0].smoother is None:
            raise TypeError("a device multigrid made by one set-up launch runs its cycle in krylov.pcg's kernel only "
                            "(Multigrid.packed); call krylov.pcg with it")
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


def pixel_prolongations(u, v, stride: int = 2, max_coarse: int = MAX_COARSE, like=None) -> list:
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

    ``like``: an array of the module the prolongations are for (a device's), u and v then on
    the host: aggregated there (the grid's mask stays on the host) and copied over in two copies
    (:meth:`Prolongations.moved`), no launch.
    """
    prolongations = Prolongations()
    while u.size > max_coarse:
        aggregate, cu, cv = pixel_aggregates(u, v, stride)
        if cu.size == u.size:
            break
        prolongations.append(tentative_prolongation(aggregate, cu.size))
        u, v = cu, cv
    if like is not None and array_module(like) is not np:
        return prolongations.moved(like)
    return prolongations


class Prolongations(list):
    """:func:`pixel_prolongations`' list, with what depends on the grid alone, made at its first
    use by :func:`multigrid_preconditioner` and kept for the next solves on the grid:
    ``restrictions`` (R = P^T per level) and ``packed`` (:func:`pack_transfers`), else None."""

    restrictions: list | None = None
    packed: tuple | None = None

    def moved(self, like) -> "Prolongations":
        """These host prolongations (and their restrictions, packed: :func:`pack_transfers`) on
        the module of ``like`` (a device's): their int32 CSR indices in one copy, their values (all
        ones; P's and R's alike) in another; the matrices are views of those arrays."""
        xp, sparse = array_module(like), sparse_module(like)
        moved = Prolongations()
        if not self:
            return moved
        restrictions = [P.T.tocsr() for P in self]
        parts = [[m.indptr for m in self], [m.indices for m in self], [m.indptr for m in restrictions],
                 [m.indices for m in restrictions]]
        lengths = [[a.size for a in kind] for kind in parts]
        indices = xp.asarray(np.concatenate([a for kind in parts for a in kind]).astype(np.int32))
        ones = xp.asarray(np.ones(sum(lengths[1])))
        packed, at = [], 0
        for kind in lengths:
            packed.append(indices[at:at + sum(kind)])
            at += sum(kind)
        moved.packed = (packed[0], packed[1], ones, packed[2], packed[3], ones)
        for host, out, ptr, ind in ((self, moved, 0, 1), (restrictions, None, 2, 3)):
            matrices, p_at, i_at = [], 0, 0
            for m, n_ptr, n_ind in zip(host, lengths[ptr], lengths[ind]):
                matrices.append(sparse.csr_matrix((ones[i_at:i_at + n_ind], packed[ind][i_at:i_at + n_ind],
                                                   packed[ptr][p_at:p_at + n_ptr]), shape=m.shape))
                p_at, i_at = p_at + n_ptr, i_at + n_ind
            if out is None:
                moved.restrictions = matrices
            else:
                out.extend(matrices)
        return moved


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

    On a device, with Chebyshev smoothers and the grid's tentative prolongations
    (:class:`Prolongations`), the whole set-up is one launch (:func:`_device_multigrid`).
    """
    xp = array_module(A.data)
    sparse = sparse_module(A)
    kept = not smoothed_prolongation and isinstance(prolongations, Prolongations)  # R and their packing per grid
    if kept and prolongations.restrictions is None:
        prolongations.restrictions = [P.T.tocsr() for P in prolongations]
    if xp is not np and kept and smoother == "chebyshev" and len(prolongations) + 1 <= MG_MAX_LEVELS:
        return _device_multigrid(A, prolongations, smoothing_steps)
    levels = []
    for k, P in enumerate(prolongations):
        inv_diag = inverse_diagonal(A)
        upper = spectral_bound_array(A, inv_diag)  # on a device: not read back
        if smoothed_prolongation:
            P = (P - (4.0 / (3.0 * float(upper))) * (sparse.diags(inv_diag, format="csr") @ (A @ P))).tocsr()
        R = prolongations.restrictions[k] if kept else P.T.tocsr()
        levels.append(MultigridLevel(A, make_smoother(A, inv_diag, upper, smoother, smoothing_steps), P, R))
        A = (R @ (A @ P)).tocsr()
    inverse = xp.linalg.inv(A.toarray())
    inverse = _half_sum(inverse, inverse.T)  # symmetric (on a GPU one launch, was two)
    packed = None
    if xp is not np and smoother == "chebyshev":
        if kept and prolongations.packed is None:
            prolongations.packed = pack_transfers(levels, xp)
        packed = pack_hierarchy(levels, inverse, smoothing_steps, prolongations.packed if kept else None)
        if packed is not None and packed.source is None:  # no level above the coarsest: the matrix itself
            packed.source = A
    return Multigrid(levels, inverse, packed)


def _device_multigrid(A, prolongations: "Prolongations", steps: int) -> Multigrid:
    """:func:`multigrid_preconditioner` on a device (Chebyshev smoothers of ``steps`` steps,
    tentative prolongations kept with the grid): the whole set-up in one launch of
    :func:`.kernels.multigrid_setup` (every level's D^-1 / bound, the Galerkin operators
    ``P^T A P``: CSR above the coarsest, sized for at most the finer level's non-zeros, and the
    coarsest's dense inverse), packed for :func:`.kernels.multigrid_cg` as it is made. Its
    levels hold P and R (and level 0 its A) only: the cycle runs in :func:`pcg`'s kernel."""
    xp = array_module(A.data)
    levels = [MultigridLevel(A if k == 0 else None, None, P, R)
              for k, (P, R) in enumerate(zip(prolongations, prolongations.restrictions))]
    if prolongations.packed is None:
        prolongations.packed = pack_transfers(levels, xp)
    sizes = [A.shape[0]] + [P.shape[1] for P in prolongations]
    capacity = [int(A.data.size)]  # level k + 1's non-zeros are at most level k's (each sums some of them)
    for n in sizes[1:]:
        capacity.append(min(capacity[-1], n * n))
    layout, ends = _hierarchy_layout(sizes, [(capacity[k] if k else None, level.P.data.size, level.R.data.size)
                                             for k, level in enumerate(levels)])
    n_coarse = sizes[-1]
    a_indptr, a_indices = xp.empty(ends["A_ptr"], dtype=np.int32), xp.empty(ends["A_nz"], dtype=np.int32)
    a_data = xp.empty(ends["A_nz"])
    inv_diag = xp.empty(sum(sizes[:-1]))
    inverse = xp.empty((n_coarse, n_coarse))
    transfers = prolongations.packed
    kernels_for(A.data).multigrid_setup(A.indptr, A.indices, A.data, a_indptr, a_indices, a_data, transfers[0],
                                        transfers[1], transfers[3], transfers[4], inv_diag, inverse,
                                        xp.empty((2, 2, n_coarse)), xp.empty(COOPERATIVE_BLOCKS), tuple(layout),
                                        len(levels))
    theta, scales, factors = chebyshev_scalars(CHEBYSHEV_LOWER_FRACTION, 1.0, steps)
    arrays = (a_indptr, a_indices, a_data, *transfers, inv_diag, inverse,
              xp.empty((-(-n_coarse // COARSE_SEGMENT), n_coarse)))
    packed = PackedHierarchy(A, arrays, tuple(layout), len(levels),
                             (theta, *(v for pair in zip(scales, factors) for v in pair)), ends["vec"])
    return Multigrid(levels, inverse, packed)
