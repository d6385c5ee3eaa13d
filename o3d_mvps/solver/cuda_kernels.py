"""CUDA twins of :mod:`.kernels`: the same launchers, with the same arguments and results, run
by numba's CUDA target.

A caller picks a kernels module (this one or :mod:`.kernels`) and calls the same functions.
Arrays are whatever numba's CUDA target takes: device arrays with ``__cuda_array_interface__``
(CuPy's; outputs are written in place), or NumPy arrays (copied to the device and back on each
launch: the tests, and numba's CUDA simulator). Each kernel calls the per-pixel function of its
CPU twin, compiled for the device from the same Python source (:func:`_device`): one copy of the
maths. Nothing is compiled at import (numba compiles a kernel at its first launch), so this
module imports without CUDA. Compiled kernels are cached on disk (``cache=True``: numba's cache
beside this file, or in the user's cache directory where that is read-only), so only a
machine's first run compiles. numba checks this file's time stamp only: after editing the
per-pixel functions in :mod:`.kernels` or :mod:`o3d_mvps.model`, clear the cache
(``__pycache__/*.nbi``, ``*.nbc``) or touch this file.

Threads take adjacent pixels (the fastest-varying index of the per-pixel arrays), so that
neighbouring threads read neighbouring memory. Reductions over pixels go to per-block partial sums
(:func:`joint_block`, :func:`log1p_square_sum`) added up
afterwards, never to one shared accumulator; float64 throughout, as on the CPU.
"""

from __future__ import annotations

import math
import types

import numba
import numpy as np
from numba import cuda

from ..model.robust import log1p_square_term
from ..model.shading import led_field, led_irradiance, led_point_gradient
from . import kernels

#: the launchers, the same in :mod:`.kernels`
__all__ = ["shading_residuals", "log1p_square_sum", "led_irradiances_into", "led_point_gradients_into", "warp_sample",
           "warp_sample_frames", "warp_gradients", "chebyshev_update", "chebyshev_start", "restrict_residual",
           "prolong_restart", "csr_multiply_add", "cg_start", "cg_scalars", "cg_update", "multigrid_cg",
           "ridge_solves", "led_trial_sums", "albedo_update", "lighting_sums", "levenberg_damp"]

#: Threads per block of every kernel.
THREADS_PER_BLOCK = 128

#: Pixels per thread of :func:`joint_block` (:func:`joint_blocks`: its thread blocks, one row of
#: partial twist sums each): a few pixels a thread keep those partial sums a small part of the traffic.
PIXELS_PER_THREAD = 4

#: Terms per thread of :func:`log1p_square_sum` (one partial sum per block comes back to the host).
TERMS_PER_THREAD = 16


def _device(body):
    """A ``numba.njit`` per-pixel function of :mod:`.kernels` for the CUDA kernels: the function
    itself, which numba's CUDA target compiles for the device from its Python source where a
    kernel calls it (with the njit functions it calls), reading colour frames through their
    float forms (:func:`_float_frames`); under numba's CUDA simulator, which runs kernels as
    Python, its Python source calling the Python source of those (a CPU function cannot take the
    simulator's arrays)."""
    return _python(body) if cuda.config.ENABLE_CUDASIM else _float_frames(body)


#: :func:`_float_frames`' functions made so far, by the function they stand for
_FLOAT_FRAME_FUNCTIONS = {}


def _float_frames(function):
    """A ``numba.njit`` function whose calls (its own and those of the njit functions it calls)
    to :data:`.kernels.FLOAT_FRAME_FORMS`' frame readers go to their float forms: a GPU's frames
    are float32 (decoded on upload), and numba-cuda types the coded frame's branch of their type
    test too (it does not prune it), which cannot index a float array. The function itself where
    it reads no frame."""
    forms = kernels.FLOAT_FRAME_FORMS
    if function in forms:
        return forms[function]
    made = _FLOAT_FRAME_FUNCTIONS
    if function not in made:
        py = function.py_func
        calls = {name: _float_frames(callee) for name in py.__code__.co_names
                 if isinstance(callee := py.__globals__.get(name), numba.core.registry.CPUDispatcher)}
        calls = {name: new for name, new in calls.items() if new is not py.__globals__[name]}
        made[function] = function if not calls else numba.njit(inline=function.targetoptions.get("inline", "never"))(
            types.FunctionType(py.__code__, {**py.__globals__, **calls}, py.__name__, py.__defaults__, py.__closure__))
    return made[function]


def _python(function):
    """The Python function behind a ``numba.njit`` function, its calls to other njit functions
    going to their Python functions too."""
    py = function.py_func
    calls = {name: _python(callee) for name in py.__code__.co_names
             if isinstance(callee := py.__globals__.get(name), numba.core.registry.CPUDispatcher)}
    if not calls:
        return py
    return types.FunctionType(py.__code__, {**py.__globals__, **calls}, py.__name__, py.__defaults__, py.__closure__)


_accumulate_pixel = _device(kernels.accumulate_pixel)
_shading_residual_pixel = _device(kernels.shading_residual_pixel)
_weighted_albedo_pixel = _device(kernels.weighted_albedo_pixel)
_log1p_square_term = _device(log1p_square_term)
_led_irradiance = _device(led_irradiance)
_led_point_gradient = _device(led_point_gradient)
_warp_sample_pixel = _device(kernels.warp_sample_pixel)
_warp_gradients_pixel = _device(kernels.warp_gradients_pixel)
_chebyshev_row = _device(kernels.chebyshev_row)
_csr_row_dot = _device(kernels.csr_row_dot)
_chebyshev_start_row = _device(kernels.chebyshev_start_row)
_restrict_residual_row = _device(kernels.restrict_residual_row)
_prolong_restart_row = _device(kernels.prolong_restart_row)
_cg_row = _device(kernels.cg_row)
_cg_finish = _device(kernels.cg_finish)


def _grid_barrier():  # pragma: no cover - device
    """:func:`.kernels.grid_barrier` in a CUDA kernel: the grid's sync (a cooperative launch)."""
    cuda.cg.this_grid().sync()


def _block_tree_sum(share, t, value):  # pragma: no cover - device
    """Thread t's value added over its block into ``share[0]`` ((THREADS_PER_BLOCK,) shared): a
    tree in a fixed order, every thread past the last barrier when it returns."""
    share[t] = value
    cuda.syncthreads()
    step = THREADS_PER_BLOCK // 2
    while step > 0:
        if t < step:
            share[t] += share[t + step]
        cuda.syncthreads()
        step //= 2


def _block_tree_sum2(share, t, first, second):  # pragma: no cover - device
    """Thread t's (first, second) added over its block into ``share[0]`` ((THREADS_PER_BLOCK, 2)
    shared): a tree in a fixed order, every thread past the last barrier when it returns."""
    share[t, 0] = first
    share[t, 1] = second
    cuda.syncthreads()
    step = THREADS_PER_BLOCK // 2
    while step > 0:
        if t < step:
            share[t, 0] += share[t + step, 0]
            share[t, 1] += share[t + step, 1]
        cuda.syncthreads()
        step //= 2


def _store_block_pair(share, t, first, second, partial):  # pragma: no cover - device
    """The block's sums of its threads' (first, second) (:func:`_block_tree_sum2`) written into
    ``partial[block, 0:2]`` by thread 0: a kernel's per-block partial sums for the host."""
    _block_tree_sum2(share, t, first, second)
    if t == 0:
        partial[cuda.blockIdx.x, 0] = share[0, 0]
        partial[cuda.blockIdx.x, 1] = share[0, 1]


def _grid_sum2(first, second, partial, slot):  # pragma: no cover - device
    """:func:`.kernels.grid_sum2` in a CUDA kernel: each block adds its threads' terms in shared
    memory (a tree, in a fixed order) into ``partial[block, slot:slot + 2]``; after the grid's
    sync every block adds all blocks' sums in the same fixed order, so that every thread gets the
    same totals (the same every run)."""
    share = cuda.shared.array((THREADS_PER_BLOCK, 2), numba.float64)
    t = cuda.threadIdx.x
    for phase in range(2):  # 0: this block's threads; 1: the blocks' sums
        _block_tree_sum2(share, t, first, second)
        first, second = share[0, 0], share[0, 1]
        cuda.syncthreads()  # every thread has read the tree's root before the next writes
        if phase == 0:
            if t == 0:
                partial[cuda.blockIdx.x, slot] = first
                partial[cuda.blockIdx.x, slot + 1] = second
            cuda.cg.this_grid().sync()
            first = second = 0.0
            for k in range(t, cuda.gridDim.x, THREADS_PER_BLOCK):
                first += partial[k, slot]
                second += partial[k, slot + 1]
    return first, second


if not cuda.config.ENABLE_CUDASIM:  # compiled for the device where a kernel calls them
    _block_tree_sum = numba.njit(inline="always")(_block_tree_sum)
    _block_tree_sum2 = numba.njit(inline="always")(_block_tree_sum2)
    _store_block_pair = numba.njit(inline="always")(_store_block_pair)

#: the grid-wide functions of kernels' shared code, for the CUDA target
_GRID = {"grid_barrier": _grid_barrier, "grid_sum2": _grid_sum2}
if not cuda.config.ENABLE_CUDASIM:
    _GRID = {name: numba.njit(inline="always")(function) for name, function in _GRID.items()}


def _uses_grid(function) -> bool:
    """Whether a ``numba.njit`` function of :mod:`.kernels` calls one of :data:`_GRID`'s, itself or
    through the njit functions it calls."""
    py = function.py_func
    return any(name in _GRID or (isinstance(callee, numba.core.registry.CPUDispatcher) and _uses_grid(callee))
               for name in py.__code__.co_names if (callee := py.__globals__.get(name)) is not None)


def _on_grid(function):
    """:func:`_device` of a ``numba.njit`` function of :mod:`.kernels` that waits for or sums over
    the whole launch: its calls to :func:`.kernels.grid_barrier` and :func:`.kernels.grid_sum2`
    (also those of the njit functions it calls) go to :data:`_GRID`'s (the same Python source
    otherwise, compiled for the device, or run as Python under the simulator)."""
    py = function.py_func
    calls = {}
    for name in py.__code__.co_names:
        callee = py.__globals__.get(name)
        if name in _GRID:
            calls[name] = _GRID[name]
        elif isinstance(callee, numba.core.registry.CPUDispatcher):
            calls[name] = _on_grid(callee) if _uses_grid(callee) else _device(callee)
    rebound = types.FunctionType(py.__code__, {**py.__globals__, **calls}, py.__name__, py.__defaults__,
                                 py.__closure__)
    return rebound if cuda.config.ENABLE_CUDASIM else numba.njit(rebound)


_multigrid_cg_steps = _on_grid(kernels.multigrid_cg_steps)
_CG_STATE = kernels.CG_STATE  # a global: a constant where a kernel sizes a local array


def _blocks(n_threads: int) -> int:
    """Blocks of :data:`THREADS_PER_BLOCK` threads covering ``n_threads`` (at least one)."""
    return max(1, -(-n_threads // THREADS_PER_BLOCK))


@cuda.jit(cache=True)
def _shading_residuals(color, albedo, basis, lights, usable, shading, residual):  # pragma: no cover - device
    index = cuda.grid(1)
    n, N = usable.shape
    if index < n * N:
        _shading_residual_pixel(color, albedo, basis, lights, usable, shading, residual, index // N, index % N)


def shading_residuals(color, albedo, basis, lights, usable, shading, residual) -> None:
    """:func:`.kernels.shading_residuals` on the GPU (one thread per frame and pixel)."""
    _shading_residuals[_blocks(usable.size), THREADS_PER_BLOCK](color, albedo, basis, lights, usable, shading,
                                                                residual)


@cuda.jit(cache=True)
def _led_irradiances_into(normals, points, positions, out):  # pragma: no cover - device
    index = cuda.grid(1)
    N = points.shape[0]
    if index < positions.shape[0] * N:
        i, p = index // N, index % N
        out[i, p] = _led_irradiance(normals, points, positions, i, p)


def led_irradiances_into(normals, points, positions, out) -> None:
    """:func:`o3d_mvps.model.shading.led_irradiances_into` on the GPU: out (m, N) = <n, v> of
    float64 normals, points (N, 3) under light positions (m, 3); one thread per light and point."""
    _led_irradiances_into[_blocks(out.size), THREADS_PER_BLOCK](normals, points, positions, out)


@cuda.jit(cache=True)
def _led_point_gradients_into(intensities, normals, points, positions, out):  # pragma: no cover - device
    index = cuda.grid(1)
    N = points.shape[0]
    if index < positions.shape[0] * N:
        _led_point_gradient(intensities, normals, points, positions, out, index // N, index % N)


def led_point_gradients_into(intensities, normals, points, positions, out) -> None:
    """:func:`o3d_mvps.model.shading.led_point_gradients_into` on the GPU: out (m, N, 3), the
    lit intensities (m,) times d<n, v>/dX of float64 normals, points (N, 3) under light positions
    (m, 3); one thread per light and point."""
    _led_point_gradients_into[_blocks(positions.shape[0] * points.shape[0]), THREADS_PER_BLOCK](
        intensities, normals, points, positions, out)


@cuda.jit(cache=True)
def _warp_sample(points_ref, pose, K, image, visible, color, usable):  # pragma: no cover - device
    p = cuda.grid(1)
    if p < points_ref.shape[0]:
        _warp_sample_pixel(points_ref, pose, K, image, visible, color, usable, p)


def warp_sample(points_ref, pose, K, image, visible, color, usable) -> None:
    """:func:`.kernels.warp_sample` on the GPU (one thread per pixel)."""
    _warp_sample[_blocks(points_ref.shape[0]), THREADS_PER_BLOCK](points_ref, pose, K, image, visible, color, usable)


@cuda.jit(cache=True)
def _warp_sample_frames(points_ref, poses, K, images, visible, color, usable):  # pragma: no cover - device
    index = cuda.grid(1)
    n, N = visible.shape
    if index < n * N:
        i, p = index // N, index % N
        _warp_sample_pixel(points_ref, poses[i], K, images[i], visible[i], color[i], usable[i], p)


def warp_sample_frames(points_ref, poses, K, images, visible, color, usable) -> None:
    """:func:`.kernels.warp_sample_frames` on the GPU (one thread per frame and pixel)."""
    _warp_sample_frames[_blocks(visible.size), THREADS_PER_BLOCK](points_ref, poses, K, images, visible, color,
                                                                  usable)


@cuda.jit(cache=True)
def _chebyshev_update(indptr, indices, data, r, v, d, scale, diagonal, x, r_out, d_out, x_out):  # pragma: no cover
    row = cuda.grid(1)
    if row < r.shape[0]:
        _chebyshev_row(indptr, indices, data, r, v, d, scale, diagonal, 1.0, x, r_out, d_out, x_out, row)


def chebyshev_update(indptr, indices, data, r, v, d, scale, diagonal, x, r_out, d_out, x_out) -> None:
    """:func:`.kernels.chebyshev_update` on the GPU (one thread per row)."""
    _chebyshev_update[_blocks(r.shape[0]), THREADS_PER_BLOCK](indptr, indices, data, r, v, d, scale, diagonal, x,
                                                             r_out, d_out, x_out)


@cuda.jit(cache=True)
def _chebyshev_start(indptr, indices, data, b, first, scale, diagonal, r_out, d_out, x_out):  # pragma: no cover
    row = cuda.grid(1)
    if row < b.shape[0]:
        _chebyshev_start_row(indptr, indices, data, b, first, 1.0, scale, diagonal, 1.0, r_out, d_out, x_out, row)


def chebyshev_start(indptr, indices, data, b, first, scale, diagonal, r_out, d_out, x_out) -> None:
    """:func:`.kernels.chebyshev_start` on the GPU (one thread per row)."""
    _chebyshev_start[_blocks(b.shape[0]), THREADS_PER_BLOCK](indptr, indices, data, b, first, scale, diagonal, r_out,
                                                            d_out, x_out)


@cuda.jit(cache=True)
def _restrict_residual(R_indptr, R_indices, R_data, indptr, indices, data, b, x, coarse):  # pragma: no cover
    row = cuda.grid(1)
    if row < coarse.shape[0]:
        _restrict_residual_row(R_indptr, R_indices, R_data, indptr, indices, data, b, x, coarse, row)


def restrict_residual(R_indptr, R_indices, R_data, indptr, indices, data, b, x, coarse) -> None:
    """:func:`.kernels.restrict_residual` on the GPU (one thread per coarse row)."""
    _restrict_residual[_blocks(coarse.shape[0]), THREADS_PER_BLOCK](R_indptr, R_indices, R_data, indptr, indices,
                                                                   data, b, x, coarse)


@cuda.jit(cache=True)
def _prolong_restart(indptr, indices, data, P_indptr, P_indices, P_data, b, x, c, first, r_out, d_out,
                     x_out):  # pragma: no cover - device
    row = cuda.grid(1)
    if row < b.shape[0]:
        _prolong_restart_row(indptr, indices, data, P_indptr, P_indices, P_data, b, x, c, first, 1.0, r_out, d_out,
                             x_out, row)


def prolong_restart(indptr, indices, data, P_indptr, P_indices, P_data, b, x, c, first, r_out, d_out, x_out) -> None:
    """:func:`.kernels.prolong_restart` on the GPU (one thread per row)."""
    _prolong_restart[_blocks(b.shape[0]), THREADS_PER_BLOCK](indptr, indices, data, P_indptr, P_indices, P_data, b, x,
                                                            c, first, r_out, d_out, x_out)


@cuda.jit(cache=True)
def _csr_multiply_add(indptr, indices, data, alpha, v, y, out):  # pragma: no cover - device
    row = cuda.grid(1)
    if row < out.shape[0]:
        out[row] = y[row] + alpha * _csr_row_dot(indptr, indices, data, v, row)


def csr_multiply_add(indptr, indices, data, alpha, v, y, out) -> None:
    """:func:`.kernels.csr_multiply_add` on the GPU (one thread per row)."""
    _csr_multiply_add[_blocks(out.shape[0]), THREADS_PER_BLOCK](indptr, indices, data, alpha, v, y, out)


@cuda.jit(cache=True)
def _cg_pass(mode, indptr, indices, data, with_matrix, from_zero, b, z, w, p, s, x, r, rtol2, state, partial,
             counter):  # pragma: no cover - device
    """:func:`.kernels.cg_pass` in one launch: each thread sums its strided rows' terms, each
    block adds its threads' sums in shared memory (a tree in a fixed order) into ``partial``;
    the block that finishes last (an atomic count of the finished blocks, after a memory fence)
    adds the blocks' sums in a fixed order, sets the scalars and resets the count: the same
    sums, so the same results, every run."""
    share = cuda.shared.array((THREADS_PER_BLOCK, 2), numba.float64)
    last = cuda.shared.array(1, numba.int32)
    t = cuda.threadIdx.x
    if mode != kernels.CG_START and state[kernels.CG_ACTIVE] == 0.0:
        return  # every thread of every block: the state changes only after all have read it
    alpha, beta = state[kernels.CG_ALPHA], state[kernels.CG_BETA]
    first = second = 0.0
    for row in range(cuda.grid(1), b.shape[0], cuda.gridsize(1)):
        a, c = _cg_row(mode, indptr, indices, data, with_matrix, from_zero, b, z, w, p, s, x, r, alpha, beta, row)
        first += a
        second += c
    for phase in range(2):  # 0: this block's rows; 1 (the last block only): the blocks' sums
        _block_tree_sum2(share, t, first, second)
        if phase == 1:
            if t == 0:
                counter[0] = 0
                _cg_finish(mode, state, share[0, 0], share[0, 1], rtol2)
            return
        if t == 0:
            partial[cuda.blockIdx.x, 0] = share[0, 0]
            partial[cuda.blockIdx.x, 1] = share[0, 1]
            cuda.threadfence()
            last[0] = 1 if cuda.atomic.add(counter, 0, 1) == cuda.gridDim.x - 1 else 0
        cuda.syncthreads()
        if last[0] == 0:
            return
        first = second = 0.0
        for k in range(t, cuda.gridDim.x, THREADS_PER_BLOCK):
            first += partial[k, 0]
            second += partial[k, 1]


def _cg_launch(mode, indptr, indices, data, with_matrix, from_zero, b, z, w, p, s, x, r, rtol2, state, partial,
               counter) -> None:
    blocks = min(kernels.REDUCTION_BLOCKS, _blocks(b.shape[0]))
    _cg_pass[blocks, THREADS_PER_BLOCK](mode, indptr, indices, data, with_matrix, from_zero, b, z, w, p, s, x, r,
                                        float(rtol2), state, partial, counter)


def cg_start(b, x, r, p, s, from_zero, rtol2, state, partial, counter) -> None:
    """:func:`.kernels.cg_start` on the GPU (one launch of :func:`_cg_pass`)."""
    _cg_launch(kernels.CG_START, counter, counter, state, False, bool(from_zero), b, b, b, p, s, x, r, rtol2, state,
               partial, counter)


def cg_scalars(indptr, indices, data, with_matrix, z, r, w, state, partial, counter) -> None:
    """:func:`.kernels.cg_scalars` on the GPU (one launch of :func:`_cg_pass`)."""
    _cg_launch(kernels.CG_SCALARS, indptr, indices, data, bool(with_matrix), False, z, z, w, z, z, z, r, 0.0, state,
               partial, counter)


def cg_update(z, w, p, s, x, r, state, partial, counter) -> None:
    """:func:`.kernels.cg_update` on the GPU (one launch of :func:`_cg_pass`)."""
    _cg_launch(kernels.CG_UPDATE, counter, counter, state, False, False, z, z, w, p, s, x, r, 0.0, state, partial,
               counter)


@cuda.jit(cache=True)
def _warp_gradients(points_ref, pose, K, image, points, grad_u, grad_v):  # pragma: no cover - device
    p = cuda.grid(1)
    if p < points_ref.shape[0]:
        _warp_gradients_pixel(points_ref, pose, K, image, points, grad_u, grad_v, p)


def warp_gradients(points_ref, pose, K, image, points, grad_u, grad_v) -> None:
    """:func:`.kernels.warp_gradients` on the GPU (one thread per pixel)."""
    _warp_gradients[_blocks(points_ref.shape[0]), THREADS_PER_BLOCK](points_ref, pose, K, image, points, grad_u,
                                                                     grad_v)


@cuda.jit(cache=True)
def _log1p_square_partials(x, scale, partial):  # pragma: no cover - device
    """partial[block] = the block's share of sum log(1 + (scale x)^2): each thread sums a strided
    share, then the block adds its threads' sums in shared memory (a tree, in a fixed order)."""
    share = cuda.shared.array(THREADS_PER_BLOCK, numba.float64)
    t = cuda.threadIdx.x
    total = 0.0
    for i in range(cuda.grid(1), x.size, cuda.gridsize(1)):
        total += _log1p_square_term(x[i], scale)
    _block_tree_sum(share, t, total)
    if t == 0:
        partial[cuda.blockIdx.x] = share[0]


def log1p_square_sum(x, scale: float) -> float:
    """:func:`o3d_mvps.model.robust.log1p_square_sum` on the GPU: sum log(1 + (scale x)^2) over a
    1-D float64 array x (float32 terms, float64 sums); the blocks' partial sums are added on the
    host."""
    blocks = _blocks(-(-x.size // TERMS_PER_THREAD))
    partial = cuda.device_array(blocks, dtype=np.float64)
    _log1p_square_partials[blocks, THREADS_PER_BLOCK](x, scale, partial)
    return float(partial.copy_to_host().sum())


@cuda.jit(cache=True)
def _multigrid_cg(n_steps, cycle_first, with_matrix, m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr,
                  p_indices, p_data, r_indptr, r_indices, r_data, inv_diag, coarse_inverse, coarse_partial, work, x, p,
                  s, w, u_t, coupled, t_partial, t, layout, levels, cheb, begin, b, from_zero, rtol2, state,
                  partial):  # pragma: no cover - device
    local = cuda.local.array(_CG_STATE, numba.float64)
    _multigrid_cg_steps(n_steps, cycle_first, with_matrix, m_indptr, m_indices, m_data, a_indptr, a_indices, a_data,
                        p_indptr, p_indices, p_data, r_indptr, r_indices, r_data, inv_diag, coarse_inverse,
                        coarse_partial, work, x, p, s, w, u_t, coupled, t_partial, t, layout, levels, cheb, begin, b,
                        from_zero, rtol2, state, partial, local, cuda.grid(1), cuda.gridsize(1))


#: (device, argument types) -> the most blocks of :func:`_multigrid_cg` resident at once
_RESIDENT_BLOCKS: dict = {}


def _cooperative_blocks(kernel, args, wanted: int) -> int:
    """Blocks for a cooperative launch of ``kernel`` on ``args``: ``wanted``, but no more than
    :data:`.kernels.COOPERATIVE_BLOCKS` and than the device holds at once (compiling the kernel first
    where needed); 1 under numba's simulator (which runs one block of a cooperative grid)."""
    if cuda.config.ENABLE_CUDASIM:
        return 1
    argtypes = tuple(kernel.typeof_pyval(a) for a in args)
    key = (cuda.get_current_device().id, kernel.py_func.__name__, argtypes)
    if key not in _RESIDENT_BLOCKS:
        _RESIDENT_BLOCKS[key] = kernel.compile(argtypes).max_cooperative_grid_blocks(THREADS_PER_BLOCK)
    return max(1, min(wanted, kernels.COOPERATIVE_BLOCKS, _RESIDENT_BLOCKS[key]))


def multigrid_cg(n_steps, cycle_first, with_matrix, m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr,
                 p_indices, p_data, r_indptr, r_indices, r_data, inv_diag, coarse_inverse, coarse_partial, work, x, p,
                 s, w, u_t, coupled, t_partial, t, layout, levels, cheb, begin, b, from_zero, rtol2, state,
                 partial) -> None:
    """:func:`.kernels.multigrid_cg` on the GPU in one cooperative launch (its passes separated by
    the grid's sync; rows in grid-stride loops over at most :data:`.kernels.COOPERATIVE_BLOCKS` blocks,
    the rows of ``partial`` (blocks, 4))."""
    args = (int(n_steps), bool(cycle_first), bool(with_matrix), m_indptr, m_indices, m_data, a_indptr, a_indices,
            a_data, p_indptr, p_indices, p_data, r_indptr, r_indices, r_data, inv_diag, coarse_inverse,
            coarse_partial, work, x, p, s, w, u_t, coupled, t_partial, t, tuple(int(v) for v in layout), int(levels),
            tuple(float(v) for v in cheb), bool(begin), b, bool(from_zero), float(rtol2), state, partial)
    wanted = _blocks(max(x.shape[0], coarse_partial.size, t_partial.size))
    blocks = min(_cooperative_blocks(_multigrid_cg, args, wanted), partial.shape[0])
    _multigrid_cg[blocks, THREADS_PER_BLOCK](*args)
_ridge_solve_system = _device(kernels.ridge_solve_system)
_ridge_cholesky = _device(kernels.ridge_cholesky)
_cholesky_column = _device(kernels.cholesky_column)
_led_trial_term = _device(kernels.led_trial_term)
_led_offset_step = _device(kernels.led_offset_step)
_store_offset_step = _device(kernels.store_offset_step)


@cuda.jit(cache=True)
def _ridge_solves(A, B, ridge, fallback, L, X, solved):  # pragma: no cover - device
    i = cuda.grid(1)
    if i < A.shape[0]:
        _ridge_solve_system(A, B, ridge, fallback, L, X, solved, i)


def ridge_solves(A, B, ridge, fallback, L, X, solved) -> None:
    """:func:`.kernels.ridge_solves` on the GPU: one thread per system (a 6x6 Cholesky and its
    substitutions are some 150 operations: a warp's worth of frames in one launch)."""
    _ridge_solves[_blocks(A.shape[0]), THREADS_PER_BLOCK](A, B, float(ridge), float(fallback), L, X, solved)


@cuda.jit(cache=True)
def _led_trial_partials(color, usable, albedo, normals, points, poses, start, H, g, lights, scale, single, zero_row,
                        out):  # pragma: no cover - device
    """out[k, block] = the block's share of trial k's sum (grid: blocks x trials): every thread
    solves the offset's 3x3 system (some 50 operations; no launch of its own), sums a strided
    share of the frames' pixels, then the block adds its threads' sums in shared memory (a tree,
    in a fixed order); block (0, 0) also writes the step into the last row."""
    share = cuda.shared.array(THREADS_PER_BLOCK, numba.float64)
    L = cuda.local.array((1, 3, 3), numba.float64)
    X = cuda.local.array((1, 3, 1), numba.float64)
    solved = cuda.local.array(1, numba.float64)
    t = cuda.threadIdx.x
    k = cuda.blockIdx.y
    trial = k if k != zero_row else -1  # -1: the offset ``start`` itself
    n, N = usable.shape
    _led_offset_step(H, g, L, X, solved)
    if k == 0 and cuda.blockIdx.x == 0 and t == 0:
        _store_offset_step(X, solved, g, out)
    total = 0.0
    for index in range(cuda.blockIdx.x * THREADS_PER_BLOCK + t, n * N, cuda.gridDim.x * THREADS_PER_BLOCK):
        total += _led_trial_term(color, usable, albedo, normals, points, poses, start, X[0, 0, 0], X[0, 1, 0],
                                 X[0, 2, 0], lights, scale, single, trial, index // N, index % N)
    _block_tree_sum(share, t, total)
    if t == 0:
        out[k, cuda.blockIdx.x] = share[0]


def trial_blocks(n_frames: int, n_pixels: int) -> int:
    """Columns of :func:`led_trial_sums`' out (its blocks per trial, at least 7 and at most
    :data:`.kernels.REDUCTION_BLOCKS`; not a launch)."""
    return min(kernels.REDUCTION_BLOCKS, max(7, _blocks(-(-n_frames * n_pixels // TERMS_PER_THREAD))))


def led_trial_sums(color, usable, albedo, normals, points, poses, start, H, g, lights, scale, single, out,
                   current: bool = False) -> None:
    """:func:`.kernels.led_trial_sums` on the GPU: the step and every trial in one launch (grid:
    blocks x trials), out (K + 1, :func:`trial_blocks`) one sum per block, the step's row."""
    _led_trial_partials[(out.shape[1], out.shape[0] - 1), THREADS_PER_BLOCK](
        color, usable, albedo, normals, points, poses, start, H, g, lights, float(scale), bool(single),
        out.shape[0] - 2 if current else -1, out)


_twist_entry = _device(kernels.twist_entry)


# --- the data term's evaluation in one launch (gpueval, issue #33) -----------------------------
# :func:`.kernels.energy_partials` and :func:`.kernels.evaluation_partials` on the GPU: every
# frame and pixel and the prior's rows of a level in one launch, one block per row of the
# partial sums (each thread a strided share of the frames' pixels, then of the prior's rows; the
# block adds its threads' sums in shared memory, a tree in a fixed order). The host reads the
# partial sums (one copy) and adds them.

_energy_term = _device(kernels.energy_term)
_evaluation_term = _device(kernels.evaluation_term)
_prior_sum = _device(kernels.prior_sum)
_prior_rows = _device(kernels.prior_rows)
_led_field = _device(led_field)
_evaluate_pixel = _device(kernels.evaluate_pixel)
_led_shading_jacobian = _device(kernels.led_shading_jacobian)
__all__ += ["energy_partials", "evaluation_partials", "led_fields_into", "evaluate_partials",
            "led_shading_jacobians_into"]


@cuda.jit(cache=True)
def _energy_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                     lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr, S_indices,
                     S_data, tau, mu, usable, partial):  # pragma: no cover - device
    share = cuda.shared.array((THREADS_PER_BLOCK, 2), numba.float64)
    t = cuda.threadIdx.x
    n, N = visible.shape
    data = 0.0
    for index in range(cuda.grid(1), n * N, cuda.gridsize(1)):
        data += _energy_term(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible,
                             albedo, lights, led, o0, o1, o2, scale, single, usable, index // N, index % N)
    prior = _prior_sum(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z, cuda.grid(1),
                       _prior_rows(z0, S_indptr, tau, mu), cuda.gridsize(1))
    _store_block_pair(share, t, data, prior, partial)


def energy_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                    lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr, S_indices,
                    S_data, tau, mu, usable, partial) -> None:
    """:func:`.kernels.energy_partials` on the GPU: one launch of partial.shape[0] blocks."""
    _energy_partials[partial.shape[0], THREADS_PER_BLOCK](
        z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo, lights,
        bool(led), float(o0), float(o1), float(o2), float(scale), bool(single), D_indptr, D_indices, D_data, z0,
        S_indptr, S_indices, S_data, float(tau), float(mu), usable, partial)


@cuda.jit(cache=True)
def _evaluation_partials(color, albedo, basis, lights, usable, shading, residual, scale, D_indptr, D_indices, D_data,
                         z0, S_indptr, S_indices, S_data, tau, mu, z, partial):  # pragma: no cover - device
    share = cuda.shared.array((THREADS_PER_BLOCK, 2), numba.float64)
    t = cuda.threadIdx.x
    n, N = usable.shape
    data = 0.0
    for index in range(cuda.grid(1), n * N, cuda.gridsize(1)):
        data += _evaluation_term(color, albedo, basis, lights, usable, shading, residual, scale, index // N,
                                 index % N)
    prior = _prior_sum(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z, cuda.grid(1),
                       _prior_rows(z0, S_indptr, tau, mu), cuda.gridsize(1))
    _store_block_pair(share, t, data, prior, partial)


def evaluation_partials(color, albedo, basis, lights, usable, shading, residual, scale, D_indptr, D_indices, D_data,
                        z0, S_indptr, S_indices, S_data, tau, mu, z, partial) -> None:
    """:func:`.kernels.evaluation_partials` on the GPU: one launch of partial.shape[0] blocks."""
    _evaluation_partials[partial.shape[0], THREADS_PER_BLOCK](
        color, albedo, basis, lights, usable, shading, residual, float(scale), D_indptr, D_indices, D_data, z0,
        S_indptr, S_indices, S_data, float(tau), float(mu), z, partial)


@cuda.jit(cache=True)
def _led_fields_into(intensities, normals, points, positions, out):  # pragma: no cover - device
    index = cuda.grid(1)
    N = points.shape[0]
    if index < positions.shape[0] * N:
        _led_field(intensities, normals, points, positions, out, index // N, index % N)


def led_fields_into(intensities, normals, points, positions, out) -> None:
    """:func:`o3d_mvps.model.shading.led_fields_into` on the GPU: out (m, N, 3), the lit LED
    fields ``I_i v_i`` of float64 normals, points (N, 3) under light positions (m, 3) with
    intensities (m,); one thread per light and point."""
    _led_fields_into[_blocks(positions.shape[0] * points.shape[0]), THREADS_PER_BLOCK](
        intensities, normals, points, positions, out)


@cuda.jit(cache=True)
def _evaluate_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                       lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr, S_indices,
                       S_data, tau, mu, points, normals, dA, color, usable, basis, shading, residual,
                       partial):  # pragma: no cover - device
    share = cuda.shared.array((THREADS_PER_BLOCK, 2), numba.float64)
    t = cuda.threadIdx.x
    n, N = visible.shape
    data = 0.0
    for index in range(cuda.grid(1), n * N, cuda.gridsize(1)):
        data += _evaluate_pixel(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images,
                                visible, albedo, lights, led, o0, o1, o2, scale, single, points, normals, dA, color,
                                usable, basis, shading, residual, index // N, index % N)
    prior = _prior_sum(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z, cuda.grid(1),
                       _prior_rows(z0, S_indptr, tau, mu), cuda.gridsize(1))
    _store_block_pair(share, t, data, prior, partial)


def evaluate_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo,
                      lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr, S_indices,
                      S_data, tau, mu, points, normals, dA, color, usable, basis, shading, residual, partial) -> None:
    """:func:`.kernels.evaluate_partials` on the GPU: one launch of partial.shape[0] blocks."""
    _evaluate_partials[partial.shape[0], THREADS_PER_BLOCK](
        z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo, lights,
        bool(led), float(o0), float(o1), float(o2), float(scale), bool(single), D_indptr, D_indices, D_data, z0,
        S_indptr, S_indices, S_data, float(tau), float(mu), points, normals, dA, color, usable, basis, shading,
        residual, partial)


@cuda.jit(cache=True)
def _led_shading_jacobians_into(intensities, normals, points, positions, rotations, offset,
                                out):  # pragma: no cover - device
    index = cuda.grid(1)
    N = points.shape[0]
    if index < positions.shape[0] * N:
        _led_shading_jacobian(intensities, normals, points, positions, rotations, offset, out, index // N, index % N)


def led_shading_jacobians_into(intensities, normals, points, positions, rotations, offset, out) -> None:
    """:func:`.kernels.led_shading_jacobians_into` on the GPU: one thread per light and point."""
    _led_shading_jacobians_into[_blocks(positions.shape[0] * points.shape[0]), THREADS_PER_BLOCK](
        intensities, normals, points, positions, rotations, offset, out)


# ============================================================================================
# gpusetup (issue 33 item 4): the linear solve's set-up and the albedo / lighting / LED-offset
# updates in fewer launches; their CPU twins in :mod:`.kernels`' section of the same name.
# ============================================================================================

MAX_LIGHT_TERMS = kernels.MAX_LIGHT_TERMS
_LIGHT_SUMS = MAX_LIGHT_TERMS * MAX_LIGHT_TERMS + MAX_LIGHT_TERMS + 1
_weighted_lighting_terms = _device(kernels.weighted_lighting_terms)


@cuda.jit(cache=True)
def _albedo_update(residual, usable, values, shading, inv_lam, fallback, num, den, out):  # pragma: no cover - device
    p = cuda.grid(1)
    if p < usable.shape[1]:
        _weighted_albedo_pixel(residual, usable, values, shading, inv_lam, num, den, p)
        for c in range(3):
            d = den[p, c]
            out[p, c] = num[p, c] / d if d > 1e-8 else fallback[p, c]


def albedo_update(residual, usable, values, shading, inv_lam, fallback, num, den, out) -> None:
    """out (N, 3) = num / den where den > 1e-8, else ``fallback`` (N, 3), num and den (N, 3)
    :func:`.kernels.weighted_albedo_sums` (written too): the albedo's closed form in one launch
    (one thread per pixel; was the sums' launch and a fused ratio)."""
    _albedo_update[_blocks(usable.shape[1]), THREADS_PER_BLOCK](residual, usable, values, shading, float(inv_lam),
                                                                fallback, num, den, out)


@cuda.jit(cache=True)
def _lighting_partials(residual, usable, color, albedo, inv_lam, basis, out):  # pragma: no cover - device
    """Block (b, i): its share of frame i's sums, out[i, b] = (Gram k x k, rhs k, usable count);
    each thread a strided share of the pixels, then the block's tree sum of each value."""
    share = cuda.shared.array(THREADS_PER_BLOCK, numba.float64)
    acc = cuda.local.array(_LIGHT_SUMS, numba.float64)
    t = cuda.threadIdx.x
    i = cuda.blockIdx.y
    N = usable.shape[1]
    k = basis.shape[2]
    m = min(i, basis.shape[0] - 1)  # a basis per frame, or one for all
    size = k * k + k + 1
    for e in range(size):
        acc[e] = 0.0
    for p in range(cuda.blockIdx.x * THREADS_PER_BLOCK + t, N, cuda.gridDim.x * THREADS_PER_BLOCK):
        if usable[i, p]:
            a, b = _weighted_lighting_terms(residual, usable, color, albedo, inv_lam, i, p)
            for r in range(k):
                br = basis[m, p, r]
                for c in range(k):
                    acc[r * k + c] += br * a * basis[m, p, c]
                acc[k * k + r] += b * br
            acc[size - 1] += 1.0
    for e in range(size):
        _block_tree_sum(share, t, acc[e])
        if t == 0:
            out[i, cuda.blockIdx.x, e] = share[0]
        cuda.syncthreads()  # the root read before the next tree writes


lighting_blocks = kernels.lighting_blocks


def lighting_sums(residual, usable, color, albedo, inv_lam, basis, out) -> None:
    """The lighting's per-frame weighted normal equations in one launch: out (n,
    :func:`lighting_blocks`, k k + k + 1) the blocks' shares (their sum over axis 1: frame i's
    Gram sum_p (sum_c w rho^2) B B^T (k, k), right-hand side sum_p (sum_c w rho I~) B (k) and
    usable count), w the Cauchy IRLS weights of residual (n, N, 3) (:func:`.kernels.weighted_lighting_terms`),
    basis (n or 1, N, k), k at most :data:`MAX_LIGHT_TERMS`. Grid: blocks x frames."""
    k = basis.shape[2]
    if k > MAX_LIGHT_TERMS or out.shape[2] != k * k + k + 1:
        raise ValueError(f"lighting_sums: a light basis of {k} terms (at most {MAX_LIGHT_TERMS}) and out "
                         f"{out.shape} (needs {k * k + k + 1} values a block)")
    _lighting_partials[(out.shape[1], out.shape[0]), THREADS_PER_BLOCK](residual, usable, color, albedo,
                                                                        float(inv_lam), basis, out)


_stencil_transpose_row = _device(kernels.stencil_transpose_row)


_stencil_pixel = _device(kernels.stencil_pixel)
_stencil_gram_value = _device(kernels.stencil_gram_value)
_csr_position = _device(kernels.csr_position)


def _depth_block_rows(indptr, indices, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, Saa, Sbb, Sgg, Sab, Sag, Sbg,
                      s1, t1_indptr, t1_indices, t1_data, s2, t2_indptr, t2_indices, t2_data, data, missing, nodes, cu,
                      cv, ce, k):  # pragma: no cover - device
    """Thread k's share of :func:`.kernels.depth_block_fill`: pixel k's 5 x 5 stencil block, then row k of
    each term, added by atomics (scratch nodes, cu, cv, ce (5,))."""
    if k < fwd_u.shape[0]:
        _stencil_pixel(fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, nodes, cu, cv, ce, k)
        for p in range(5):
            if cu[p] == 0.0 and cv[p] == 0.0 and ce[p] == 0.0:
                continue
            for q in range(5):
                if cu[q] == 0.0 and cv[q] == 0.0 and ce[q] == 0.0:
                    continue
                at = _csr_position(indptr, indices, nodes[p], nodes[q])
                if at < 0:
                    cuda.atomic.add(missing, 0, 1.0)
                else:
                    cuda.atomic.add(data, at, _stencil_gram_value(Saa[k], Sbb[k], Sgg[k], Sab[k], Sag[k], Sbg[k], cu,
                                                                  cv, ce, p, q))
    if k < t1_indptr.shape[0] - 1:
        for nz in range(t1_indptr[k], t1_indptr[k + 1]):
            at = _csr_position(indptr, indices, k, t1_indices[nz])
            if at < 0:
                cuda.atomic.add(missing, 0, 1.0)
            else:
                cuda.atomic.add(data, at, s1 * t1_data[nz])
    if k < t2_indptr.shape[0] - 1:
        for nz in range(t2_indptr[k], t2_indptr[k + 1]):
            at = _csr_position(indptr, indices, k, t2_indices[nz])
            if at < 0:
                cuda.atomic.add(missing, 0, 1.0)
            else:
                cuda.atomic.add(data, at, s2 * t2_data[nz])


if not cuda.config.ENABLE_CUDASIM:  # compiled for the device where a kernel calls it (not inline="always":
    _depth_block_rows = numba.njit(_depth_block_rows)  # numba's inlining refuses its 31 arguments)


_diagonal_value = _device(kernels.diagonal_value)
_damp_diagonal = _device(kernels.damp_diagonal)


@cuda.jit(cache=True)
def _levenberg_damp(indptr, indices, data, damping, tiny, partial, missing):  # pragma: no cover - device
    """Cooperative: the diagonal's sum (each block's into partial, after the grid's sync every
    thread's total over the blocks in the same order), then each row's damping."""
    share = cuda.shared.array(THREADS_PER_BLOCK, numba.float64)
    t = cuda.threadIdx.x
    n = indptr.shape[0] - 1
    start, step = cuda.grid(1), cuda.gridsize(1)
    if start == 0:
        missing[0] = 0.0  # counted after the grid's sync
    total = 0.0
    for row in range(start, n, step):
        total += _diagonal_value(indptr, indices, data, row)[1]
    _block_tree_sum(share, t, total)
    if t == 0:
        partial[cuda.blockIdx.x] = share[0]
    cuda.cg.this_grid().sync()
    total = 0.0
    for b in range(cuda.gridDim.x):
        total += partial[b]
    floor = max(0.01 * (total / n), tiny) if n else tiny
    for row in range(start, n, step):
        if _diagonal_value(indptr, indices, data, row)[0] < 0:
            cuda.atomic.add(missing, 0, 1.0)
        else:
            _damp_diagonal(indptr, indices, data, damping, floor, missing, row)


def levenberg_damp(indptr, indices, data, damping, tiny, partial, missing) -> None:
    """:func:`.kernels.levenberg_damp` on the GPU in one cooperative launch and no read (was a
    mean read by the host, three array operations and a sparse sum); rows in grid-stride loops
    over at most ``partial.size`` blocks."""
    args = (indptr, indices, data, float(damping), float(tiny), partial, missing)
    blocks = min(_cooperative_blocks(_levenberg_damp, args, _blocks(indptr.shape[0] - 1)), partial.shape[0])
    _levenberg_damp[blocks, THREADS_PER_BLOCK](*args)


# ============================================================================================
# gpu3 (issue 33 item 4): the driver's extrapolation trials in one launch
# (CPU twins in :mod:`.kernels`' section of the same name)
# ============================================================================================

__all__ += ["extrapolation_trials"]

extrapolation_blocks = kernels.extrapolation_blocks
_clipped_depth = _device(kernels.clipped_depth)


@cuda.jit(cache=True)
def _extrapolation_trials(z, z0, albedo, albedo0, factors, lower, upper, z_out, albedo_out,
                          bad):  # pragma: no cover - device
    """Block (b, f): a strided share of factor f's pixels, then the block's count of depths not
    > 0 into bad[f, b]."""
    share = cuda.shared.array(THREADS_PER_BLOCK, numba.float64)
    t = cuda.threadIdx.x
    f = cuda.blockIdx.y
    s = factors[f]
    count = 0.0
    for p in range(cuda.blockIdx.x * THREADS_PER_BLOCK + t, z.shape[0], cuda.gridDim.x * THREADS_PER_BLOCK):
        x = _clipped_depth(z[p] + s * (z[p] - z0[p]), lower, upper, p)
        z_out[f, p] = x
        if not x > 0.0:
            count += 1.0
        for c in range(3):
            albedo_out[f, p, c] = albedo[p, c] + s * (albedo[p, c] - albedo0[p, c])
    _block_tree_sum(share, t, count)
    if t == 0:
        bad[f, cuda.blockIdx.x] = share[0]


def extrapolation_trials(z, z0, albedo, albedo0, factors, lower, upper, z_out, albedo_out, bad) -> None:
    """:func:`.kernels.extrapolation_trials` on the GPU in one launch (was three array operations,
    a clip, a comparison, a reduction and a read per factor): blocks x factors, each thread a
    strided share of the pixels; factors a tuple of floats (kernel arguments, no copy)."""
    F = z_out.shape[0]
    if not F <= len(factors) <= kernels.MAX_EXTRAPOLATION_FACTORS or bad.shape[0] != F:
        raise ValueError(f"extrapolation_trials: {len(factors)} factors (at most "
                         f"{kernels.MAX_EXTRAPOLATION_FACTORS}) for {F} trials and bad {bad.shape}")
    _extrapolation_trials[(bad.shape[1], F), THREADS_PER_BLOCK](z, z0, albedo, albedo0,
                                                               tuple(float(f) for f in factors), lower, upper,
                                                               z_out, albedo_out, bad)


__all__ += ["depth_step"]


@cuda.jit(cache=True)
def _depth_step(z, dz, t, lower, upper, out, bad):  # pragma: no cover - device
    """Block b: a strided share of the pixels, then its count of depths not > 0 into bad[b]."""
    share = cuda.shared.array(THREADS_PER_BLOCK, numba.float64)
    tid = cuda.threadIdx.x
    count = 0.0
    for p in range(cuda.blockIdx.x * THREADS_PER_BLOCK + tid, z.shape[0], cuda.gridDim.x * THREADS_PER_BLOCK):
        x = _clipped_depth(z[p] + t * dz[p], lower, upper, p)
        out[p] = x
        if not x > 0.0:
            count += 1.0
    _block_tree_sum(share, tid, count)
    if tid == 0:
        bad[cuda.blockIdx.x] = share[0]


def depth_step(z, dz, t, lower, upper, out, bad) -> None:
    """:func:`.kernels.depth_step` on the GPU in one launch (was two or three array operations, a
    clip and a reduction): ``bad.size`` blocks, each thread a strided share of the pixels."""
    _depth_step[bad.shape[0], THREADS_PER_BLOCK](z, dz, float(t), lower, upper, out, bad)


# --- gpujoint (issue #33): the joint step's device assembly, twist system and read-out ---------
# (CPU twins in :mod:`.kernels`' section of the same name)

__all__ += ["joint_block", "add_stencil_transpose_rows", "joint_twist_system", "joint_depth_system", "joint_inverse",
            "twist_readout"]

_JOINT_SUMS = kernels.JOINT_SUMS  # a global: a constant where a kernel sizes a shared array
_joint_pixel_rows = _device(kernels.joint_pixel_rows)
_joint_frame = _device(kernels.joint_frame)
_joint_pack_sums = _device(kernels.joint_pack_sums)
_joint_pixel_projection = _device(kernels.joint_pixel_projection)
_joint_unpack_sums = _device(kernels.joint_unpack_sums)
_joint_frame_kept = _device(kernels.joint_frame_kept)
_joint_inverse_row = _device(kernels.joint_inverse_row)


def joint_blocks(n_pixels: int) -> int:
    """Partial rows of :func:`joint_block`'s twist sums for a block of ``n_pixels``: its thread
    blocks (:data:`PIXELS_PER_THREAD` pixels a thread)."""
    return _blocks(-(-n_pixels // PIXELS_PER_THREAD))


@cuda.jit(cache=True)
def _joint_block(residual, shading, usable, inv_lam, albedo, dA, L, u, v, points_ref, poses, K, images, dshading,
                 parallax, twists, q, alpha, beta, gamma, extra, sums, e, rows, F, top, root,
                 partial):  # pragma: no cover - device
    """Thread t takes pixels t, t + T, ... (T the launch's threads) through the set-up, the frames
    in order and the projection; after each refined frame the block's threads add their twist
    sums in shared memory (a fixed order: thread s's values in turn by value) into the block's
    partial row."""
    share = cuda.shared.array((THREADS_PER_BLOCK, _JOINT_SUMS), numba.float64)
    J = cuda.local.array((3, 6), numba.float64)
    G = cuda.local.array((6, 6), numba.float64)
    b = cuda.local.array(6, numba.float64)
    wqJ = cuda.local.array(6, numba.float64)
    wcJ = cuda.local.array(6, numba.float64)
    num = cuda.local.array(3, numba.float64)
    den = cuda.local.array(3, numba.float64)
    t = cuda.threadIdx.x
    first, stride = cuda.grid(1), cuda.gridsize(1)
    B = residual.shape[1]
    for p in range(first, B, stride):
        _joint_pixel_rows(p, albedo, dA, L, u, v, K, points_ref, dshading, usable[0], q, alpha, beta, gamma, extra,
                          sums, e)
    for i in range(residual.shape[0]):
        jac, slot = _joint_frame(i, parallax, twists)
        for j in range(6):
            b[j] = 0.0
            for k in range(6):
                G[j, k] = 0.0
        count = 0.0
        ex = extra[:extra.shape[0] if i == 0 else 0]
        r_i, sh_i, use_i = residual[i], shading[i], usable[i]
        al_i, be_i, ga_i = alpha[i], beta[i], gamma[i]
        pose, image, ds = poses[i], images[i], dshading[i]
        for p in range(first, B, stride):
            _accumulate_pixel(p, r_i, sh_i, use_i, inv_lam, q, al_i, be_i, ga_i, ex, points_ref, pose, K, image, ds,
                              albedo, jac, parallax, sums, e, rows, F, slot, J, G, b, wqJ, wcJ)
            if use_i[p]:
                count += 1.0
        if slot >= 0:  # the same for every thread: the barriers are reached by all
            _joint_pack_sums(G, b, count, share, t)
            cuda.syncthreads()
            if t < _JOINT_SUMS:
                total = 0.0
                for s in range(THREADS_PER_BLOCK):
                    total += share[s, t]
                partial[cuda.blockIdx.x, slot, t] = total
            cuda.syncthreads()
    if e.shape[0] > 0:
        for p in range(first, B, stride):
            _joint_pixel_projection(p, residual, usable, shading, inv_lam, sums, e, rows, F, top, root, den, num)


def joint_block(residual, shading, usable, inv_lam, albedo, dA, L, u, v, points_ref, poses, K, images, dshading,
                parallax, twists, q, alpha, beta, gamma, extra, sums, e, rows, F, top, root, partial) -> None:
    """:func:`.kernels.joint_block` on the GPU in one launch (was some 20 launches a block): the
    partial rows are its :func:`joint_blocks` (B) thread blocks (partial (R, m,
    :data:`.kernels.JOINT_SUMS`))."""
    _joint_block[partial.shape[0], THREADS_PER_BLOCK](residual, shading, usable, float(inv_lam), albedo, dA, L, u, v,
                                                      points_ref, poses, K, images, dshading, bool(parallax),
                                                      bool(twists), q, alpha, beta, gamma, extra, sums, e, rows, F,
                                                      top, root, partial)


@cuda.jit(cache=True)
def _add_stencil_transpose_rows(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, rows, first,
                                out):  # pragma: no cover - device
    index = cuda.grid(1)
    B = rows.shape[2]
    if index < rows.shape[1] * B:
        j, p = index // B, index % B
        a, b = rows[0, j, p], rows[1, j, p]
        cuda.atomic.add(out, (j, first + p), rows[2, j, p])
        for nz in range(u_indptr[p], u_indptr[p + 1]):
            cuda.atomic.add(out, (j, u_indices[nz]), u_data[nz] * a)
        for nz in range(v_indptr[p], v_indptr[p + 1]):
            cuda.atomic.add(out, (j, v_indices[nz]), v_data[nz] * b)


def add_stencil_transpose_rows(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, rows, first, out) -> None:
    """:func:`.kernels.add_stencil_transpose_rows` on the GPU in one launch (was two scatters and
    a sum): one thread per row and pixel, adding by atomics (neighbouring pixels share columns:
    the order of the additions, so the rounding, varies from run to run)."""
    _add_stencil_transpose_rows[_blocks(rows.shape[1] * rows.shape[2]), THREADS_PER_BLOCK](
        u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, rows, int(first), out)


@cuda.jit(cache=True)
def _joint_twist_system(partial, products, min_pixels, limit, grams, rhs_frames, D, W, kept, hessian, rhs,
                        selection):  # pragma: no cover - device
    """One block: the sums (strided over the items), the frames' kept flags, the entries; a
    barrier between."""
    t = cuda.threadIdx.x
    m = partial.shape[1]
    items = m * _JOINT_SUMS
    for item in range(t, items + D.shape[0] * D.shape[1], THREADS_PER_BLOCK):
        if item < items:
            _joint_unpack_sums(partial, products, grams, rhs_frames, kept, D, item // _JOINT_SUMS,
                               item % _JOINT_SUMS)
        else:
            _joint_unpack_sums(partial, products, grams, rhs_frames, kept, D, 0, item - items + _JOINT_SUMS)
    cuda.syncthreads()
    for f in range(t, m, THREADS_PER_BLOCK):
        _joint_frame_kept(grams, limit, min_pixels, W, kept, f)
    cuda.syncthreads()
    k = hessian.shape[0]
    for index in range(t, k * k, THREADS_PER_BLOCK):
        _twist_entry(grams, rhs_frames, D[k], D, kept, hessian, rhs, selection, index // k, index % k)


def joint_twist_system(partial, products, min_pixels, limit, grams, rhs_frames, D, W, kept, hessian, rhs,
                       selection) -> None:
    """:func:`.kernels.joint_twist_system` on the GPU: one launch of one block (was two
    reductions, a sum and a twist-system launch; :func:`.kernels.twist_system`'s values)."""
    _joint_twist_system[1, THREADS_PER_BLOCK](partial, products, float(min_pixels), float(limit), grams, rhs_frames, D,
                                              W, kept, hessian, rhs, selection)


@cuda.jit(cache=True)
def _joint_depth_system(indptr, indices, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, Saa, Sbb, Sgg, Sab, Sag,
                        Sbg, s1, t1_indptr, t1_indices, t1_data, s2, t2_indptr, t2_indices, t2_data, data, missing,
                        u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, Ba, Bb, Bg, y,
                        out):  # pragma: no cover - device
    """Thread k: :func:`.kernels.depth_block_fill`'s pixel k and rows k, then row k of the right-hand side."""
    nodes = cuda.local.array(5, numba.int64)
    cu = cuda.local.array(5, numba.float64)
    cv = cuda.local.array(5, numba.float64)
    ce = cuda.local.array(5, numba.float64)
    k = cuda.grid(1)
    _depth_block_rows(indptr, indices, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, Saa, Sbb, Sgg, Sab, Sag, Sbg,
                      s1, t1_indptr, t1_indices, t1_data, s2, t2_indptr, t2_indices, t2_data, data, missing, nodes, cu,
                      cv, ce, k)
    if k < out.shape[0]:
        _stencil_transpose_row(u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, Ba, Bb, Bg, y, out, k)


def joint_depth_system(indptr, indices, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, Saa, Sbb, Sgg, Sab, Sag,
                       Sbg, s1, t1_indptr, t1_indices, t1_data, s2, t2_indptr, t2_indices, t2_data, data, missing,
                       u_indptr, u_indices, u_data, v_indptr, v_indices, v_data, Ba, Bb, Bg, y, out) -> None:
    """:func:`.kernels.joint_depth_system` on the GPU in one launch (the work of
    :func:`.kernels.depth_block_fill` and :func:`.kernels.stencil_transpose_subtract`): one thread
    per pixel, term row and right-hand side row."""
    rows = max(fwd_u.shape[0], t1_indptr.shape[0] - 1, t2_indptr.shape[0] - 1, out.shape[0])
    _joint_depth_system[_blocks(rows), THREADS_PER_BLOCK](
        indptr, indices, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, Saa, Sbb, Sgg, Sab, Sag, Sbg, float(s1),
        t1_indptr, t1_indices, t1_data, float(s2), t2_indptr, t2_indices, t2_data, data, missing, u_indptr, u_indices,
        u_data, v_indptr, v_indices, v_data, Ba, Bb, Bg, y, out)


@cuda.jit(cache=True)
def _joint_inverse(hessian, selection, rhs, fallback, L, X, solved):  # pragma: no cover - device
    """One block: thread 0 factors; after the barrier the threads take X's columns, then its
    last column's rows and its last row."""
    t = cuda.threadIdx.x
    ok = cuda.shared.array(1, numba.int32)
    if t == 0:
        done = _ridge_cholesky(hessian, 0.0, fallback, L, 0)
        solved[0] = 1.0 if done else 0.0
        ok[0] = 1 if done else 0
    cuda.syncthreads()
    K = hessian.shape[1]
    for c in range(t, K, THREADS_PER_BLOCK):
        _cholesky_column(L, selection, X, ok[0] != 0, 0, c)
    cuda.syncthreads()
    for j in range(t, K + 1, THREADS_PER_BLOCK):
        _joint_inverse_row(X, rhs, j)


def joint_inverse(hessian, selection, rhs, fallback, L, X, solved) -> None:
    """:func:`.kernels.joint_inverse` on the GPU: one launch of one block."""
    _joint_inverse[1, THREADS_PER_BLOCK](hessian, selection, rhs, float(fallback), L, X, solved)


@cuda.jit(cache=True)
def _twist_readout(P, dz, X, out):  # pragma: no cover - device
    """Block j: its threads' strided shares of P[j] . dz, added in a tree."""
    share = cuda.shared.array(THREADS_PER_BLOCK, numba.float64)
    t = cuda.threadIdx.x
    j = cuda.blockIdx.x
    total = 0.0
    for q in range(t, dz.shape[0], THREADS_PER_BLOCK):
        total += P[j, q] * dz[q]
    _block_tree_sum(share, t, total)
    if t == 0:
        out[j] = share[0] - X[0, j, out.shape[0]]


def twist_readout(P, dz, X, out) -> None:
    """:func:`.kernels.twist_readout` on the GPU: one launch, a block per twist (was a product
    and a difference)."""
    if out.shape[0]:
        _twist_readout[out.shape[0], THREADS_PER_BLOCK](P, dz, X, out)
# ============================================================================================
# gpueval2 (issue 33): the LED offset's system from the light state in one launch (CPU twin in
# :mod:`.kernels`' section of the same name)
# ============================================================================================

__all__ += ["led_offset_system"]

_led_offset_system_add = _device(kernels.led_offset_system_add)


@cuda.jit(cache=True)
def _led_offset_system(intensities, normals, points, positions, rotations, residual, usable, albedo, inv_lam, stride,
                       H, g):  # pragma: no cover - device
    share = cuda.shared.array(THREADS_PER_BLOCK, numba.float64)
    acc = cuda.local.array(12, numba.float64)
    t = cuda.threadIdx.x
    n, N = usable.shape
    M = (N + stride - 1) // stride
    for e in range(12):
        acc[e] = 0.0
    for index in range(t, n * M, THREADS_PER_BLOCK):
        _led_offset_system_add(intensities, normals, points, positions, rotations, residual, usable, albedo, inv_lam,
                               stride, acc, index // M, index % M)
    for e in range(12):
        _block_tree_sum(share, t, acc[e])
        if t == 0:
            if e < 9:
                H[0, e // 3, e % 3] = share[0]
            else:
                g[0, e - 9, 0] = share[0]
        cuda.syncthreads()  # the root read before the next tree writes


def led_offset_system(intensities, normals, points, positions, rotations, residual, usable, albedo, inv_lam, stride, H,
                      g) -> None:
    """:func:`.kernels.led_offset_system` on the GPU: one launch of one block (as
    :func:`.kernels.offset_system`), each thread forming its spread pixels' Jacobians (was a Jacobian
    launch, two array operations, a copy of the rotations and the system's launch)."""
    _led_offset_system[1, THREADS_PER_BLOCK](intensities, normals, points, positions, rotations, residual, usable,
                                             albedo, float(inv_lam), int(stride), H, g)


__all__ += ["led_evidence_sums"]

_led_evidence_pixel = _device(kernels.led_evidence_pixel)


@cuda.jit(cache=True)
def _led_evidence_sums(usable, albedo, shading, intensities, normals, points, positions, G6, v,
                       d):  # pragma: no cover - device
    p = cuda.grid(1)
    if p < usable.shape[1]:
        _led_evidence_pixel(usable, albedo, shading, intensities, normals, points, positions, G6, v, d, p)


def led_evidence_sums(usable, albedo, shading, intensities, normals, points, positions, G6, v, d) -> None:
    """:func:`.kernels.led_evidence_sums` on the GPU: one thread per pixel, its frames in turn (was
    the fields' launch and some eight array operations)."""
    _led_evidence_sums[_blocks(usable.shape[1]), THREADS_PER_BLOCK](usable, albedo, shading, intensities, normals,
                                                                    points, positions, G6, v, d)


__all__ += ["albedo_evaluation_partials"]

_albedo_ratio_pixel = _device(kernels.albedo_ratio_pixel)


@cuda.jit(cache=True)
def _albedo_evaluation_partials(residual, usable, color, shading, inv_lam, fallback, num, den, albedo, basis, lights,
                                D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z,
                                partial):  # pragma: no cover - device
    """Each thread a grid-stride share of the pixels: a pixel's albedo from its frames' old
    residuals, then its frames' new residuals and their energy; the prior's rows likewise."""
    share = cuda.shared.array((THREADS_PER_BLOCK, 2), numba.float64)
    t = cuda.threadIdx.x
    n, N = usable.shape
    data = 0.0
    for p in range(cuda.grid(1), N, cuda.gridsize(1)):
        _weighted_albedo_pixel(residual, usable, color, shading, inv_lam, num, den, p)
        _albedo_ratio_pixel(num, den, fallback, albedo, p)
        for i in range(n):
            data += _evaluation_term(color, albedo, basis, lights, usable, shading, residual, inv_lam, i, p)
    prior = _prior_sum(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z, cuda.grid(1),
                       _prior_rows(z0, S_indptr, tau, mu), cuda.gridsize(1))
    _store_block_pair(share, t, data, prior, partial)


def albedo_evaluation_partials(residual, usable, color, shading, inv_lam, fallback, num, den, albedo, basis, lights,
                               D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z,
                               partial) -> None:
    """:func:`.kernels.albedo_evaluation_partials` on the GPU: one launch of partial.shape[0]
    blocks (was the albedo's launch and the evaluation's)."""
    _albedo_evaluation_partials[partial.shape[0], THREADS_PER_BLOCK](
        residual, usable, color, shading, float(inv_lam), fallback, num, den, albedo, basis, lights, D_indptr,
        D_indices, D_data, z0, S_indptr, S_indices, S_data, float(tau), float(mu), z, partial)


__all__ += ["evaluate_albedo_partials"]


@cuda.jit(cache=True)
def _evaluate_albedo_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible,
                              albedo, lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr,
                              S_indices, S_data, tau, mu, points, normals, dA, color, usable, basis, shading, residual,
                              partial, num, den, refit):  # pragma: no cover - device
    """Each thread a grid-stride share of the pixels: a pixel's frames evaluated (frame 0 first:
    its point, normal, dA), its albedo refitted, its frames' residuals at that albedo and their
    energy; the prior's rows likewise."""
    share = cuda.shared.array((THREADS_PER_BLOCK, 2), numba.float64)
    t = cuda.threadIdx.x
    n, N = visible.shape
    data = 0.0
    for p in range(cuda.grid(1), N, cuda.gridsize(1)):
        for i in range(n):
            _evaluate_pixel(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible,
                            albedo, lights, led, o0, o1, o2, scale, single, points, normals, dA, color, usable, basis,
                            shading, residual, i, p)
        _weighted_albedo_pixel(residual, usable, color, shading, scale, num, den, p)
        _albedo_ratio_pixel(num, den, albedo, refit, p)
        for i in range(n):
            data += _evaluation_term(color, refit, basis, lights, usable, shading, residual, scale, i, p)
    prior = _prior_sum(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, z, cuda.grid(1),
                       _prior_rows(z0, S_indptr, tau, mu), cuda.gridsize(1))
    _store_block_pair(share, t, data, prior, partial)


def evaluate_albedo_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible,
                             albedo, lights, led, o0, o1, o2, scale, single, D_indptr, D_indices, D_data, z0, S_indptr,
                             S_indices, S_data, tau, mu, points, normals, dA, color, usable, basis, shading, residual,
                             partial, num, den, refit) -> None:
    """:func:`.kernels.evaluate_albedo_partials` on the GPU: one launch of partial.shape[0] blocks
    (was the evaluation's launch and the albedo step's)."""
    _evaluate_albedo_partials[partial.shape[0], THREADS_PER_BLOCK](
        z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo, lights,
        bool(led), float(o0), float(o1), float(o2), float(scale), bool(single), D_indptr, D_indices, D_data, z0,
        S_indptr, S_indices, S_data, float(tau), float(mu), points, normals, dA, color, usable, basis, shading,
        residual, partial, num, den, refit)


__all__ += ["trial_energy_partials"]


@cuda.jit(cache=True)
def _trial_energy_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible,
                           albedo, lights, led, offsets, scale, single, D_indptr, D_indices, D_data, z0, S_indptr,
                           S_indices, S_data, tau, mu, usable, partial):  # pragma: no cover - device
    """Block (b, f): a strided share of trial f's frames' pixels and prior rows, as
    :func:`_energy_partials` (one launch for every trial)."""
    share = cuda.shared.array((THREADS_PER_BLOCK, 2), numba.float64)
    t = cuda.threadIdx.x
    f = cuda.blockIdx.y
    n, N = visible.shape
    zf = z[f]
    start, step = cuda.blockIdx.x * THREADS_PER_BLOCK + t, cuda.gridDim.x * THREADS_PER_BLOCK
    data = 0.0
    for index in range(start, n * N, step):
        data += _energy_term(zf, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses[f], images,
                             visible, albedo[f], lights[f], led, offsets[f, 0], offsets[f, 1], offsets[f, 2], scale,
                             single, usable[f], index // N, index % N)
    prior = _prior_sum(D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data, tau, mu, zf, start,
                       _prior_rows(z0, S_indptr, tau, mu), step)
    _store_block_pair(share, t, data, prior, partial[f])


def trial_energy_partials(z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible,
                          albedo, lights, led, offsets, scale, single, D_indptr, D_indices, D_data, z0, S_indptr,
                          S_indices, S_data, tau, mu, usable, partial) -> None:
    """:func:`.kernels.trial_energy_partials` on the GPU: one launch, partial.shape[1] blocks per
    trial (was a launch and a read per trial)."""
    _trial_energy_partials[(partial.shape[1], partial.shape[0]), THREADS_PER_BLOCK](
        z, u, v, fwd_u, bwd_u, wf_u, wb_u, fwd_v, bwd_v, wf_v, wb_v, K, poses, images, visible, albedo, lights,
        bool(led), offsets, float(scale), bool(single), D_indptr, D_indices, D_data, z0, S_indptr, S_indices, S_data,
        float(tau), float(mu), usable, partial)
# --- gpukrylov ------------------------------------------------------------------------------------
# The device multigrid's set-up in one cooperative launch (issue 33): kernels.multigrid_setup.

__all__ += ["multigrid_setup"]


def _grid_max(value, partial):  # pragma: no cover - device
    """:func:`.kernels.grid_max` in a CUDA kernel: each block's largest (a tree in shared memory)
    into ``partial[block]``, the grid's sync, then every thread's largest over the blocks."""
    share = cuda.shared.array(THREADS_PER_BLOCK, numba.float64)
    t = cuda.threadIdx.x
    share[t] = value
    cuda.syncthreads()
    half = THREADS_PER_BLOCK // 2
    while half > 0:
        if t < half:
            share[t] = max(share[t], share[t + half])
        cuda.syncthreads()
        half //= 2
    if t == 0:
        partial[cuda.blockIdx.x] = share[0]
    cuda.cg.this_grid().sync()
    largest = -math.inf
    for b in range(cuda.gridDim.x):
        largest = max(largest, partial[b])
    return largest


def _grid_prefix(value, partial):  # pragma: no cover - device
    """:func:`.kernels.grid_prefix` in a CUDA kernel: the block's threads' values before this
    thread's (thread 0 of the block adds them in order in shared memory), the block's total into
    ``partial[block]``, the grid's sync, then the earlier blocks' totals added in order."""
    share = cuda.shared.array(THREADS_PER_BLOCK, numba.float64)
    t = cuda.threadIdx.x
    share[t] = value
    cuda.syncthreads()
    if t == 0:
        running = 0.0
        for k in range(THREADS_PER_BLOCK):
            here = share[k]
            share[k] = running
            running += here
        partial[cuda.blockIdx.x] = running
    cuda.syncthreads()
    before = share[t]
    cuda.cg.this_grid().sync()
    for b in range(cuda.blockIdx.x):
        before += partial[b]
    return before


_GRID["grid_max"], _GRID["grid_prefix"] = (
    (_grid_max, _grid_prefix) if cuda.config.ENABLE_CUDASIM else
    (numba.njit(inline="always")(_grid_max), numba.njit(inline="always")(_grid_prefix)))
_multigrid_setup_steps = _on_grid(kernels.multigrid_setup_steps)


@cuda.jit(cache=True)
def _multigrid_setup(m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr, p_indices, r_indptr,
                     r_indices, inv_diag, coarse, pivots, partial, layout, levels):  # pragma: no cover - device
    _multigrid_setup_steps(m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr, p_indices, r_indptr,
                           r_indices, inv_diag, coarse, pivots, partial, layout, levels, cuda.grid(1),
                           cuda.gridsize(1))


def multigrid_setup(m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr, p_indices, r_indptr, r_indices,
                    inv_diag, coarse, pivots, partial, layout, levels) -> None:
    """:func:`.kernels.multigrid_setup` on the GPU in one cooperative launch (its passes separated
    by the grid's sync; rows and entries in grid-stride loops over at most ``partial.size``
    blocks)."""
    args = (m_indptr, m_indices, m_data, a_indptr, a_indices, a_data, p_indptr, p_indices, r_indptr, r_indices,
            inv_diag, coarse, pivots, partial, tuple(int(v) for v in layout), int(levels))
    wanted = _blocks(max(m_indptr.shape[0], coarse.size))
    blocks = min(_cooperative_blocks(_multigrid_setup, args, wanted), partial.shape[0])
    _multigrid_setup[blocks, THREADS_PER_BLOCK](*args)


__all__ += ["prior_gradient"]
_prior_gradient_row = _device(kernels.prior_gradient_row)


@cuda.jit(cache=True)
def _prior_gradient(D_indptr, D_indices, D_data, t_indptr, t_indices, t_data, S_indptr, S_indices, S_data, with_s, z,
                    negative_z0, tau2, mu2, out):  # pragma: no cover - device
    i = cuda.grid(1)
    if i < out.shape[0]:
        out[i] = _prior_gradient_row(D_indptr, D_indices, D_data, t_indptr, t_indices, t_data, S_indptr, S_indices,
                                     S_data, with_s, z, negative_z0, tau2, mu2, i)


def prior_gradient(D_indptr, D_indices, D_data, t_indptr, t_indices, t_data, S_indptr, S_indices, S_data, with_s, z,
                   negative_z0, tau2, mu2, out) -> None:
    """:func:`.kernels.prior_gradient` on the GPU (one thread per row)."""
    _prior_gradient[_blocks(out.shape[0]), THREADS_PER_BLOCK](D_indptr, D_indices, D_data, t_indptr, t_indices, t_data,
                                                              S_indptr, S_indices, S_data, bool(with_s), z,
                                                              negative_z0, float(tau2), float(mu2), out)
