"""The array module of the data: NumPy on the host, CuPy on a GPU.

The solver's maths is written once against ``xp = array_module(x)`` (NumPy's functions also
dispatch CuPy arrays to CuPy through ``__array_function__``/``__array_ufunc__``; only array
creation and mixing with host arrays need ``xp``). CuPy is imported only when such an array is
met, so the package runs where it is not installed.
"""

from __future__ import annotations

from types import ModuleType

import numpy as np


def array_module(x) -> ModuleType:
    """``cupy`` for a CuPy array, else ``numpy``."""
    if type(x).__module__.startswith("cupy"):
        import cupy

        return cupy
    return np


def like(a, reference, dtype=None):
    """``a`` (a host array or scalar) as a C-contiguous array of ``reference``'s module (no copy
    of a contiguous host array on the host).

    Host data reaches a GPU through ``cupy.asarray`` only: CuPy's other functions
    (``ascontiguousarray`` among them) refuse NumPy arrays with a TypeError.
    """
    return array_module(reference).asarray(a, dtype=dtype, order="C")


def contiguous(a, dtype=None):
    """``a`` as a C-contiguous array (of ``dtype``, default its own) of its module: itself where
    it is one already. CuPy's ``ascontiguousarray`` also returns such an array as it is, but
    this does not ask it (nor count a launch on the CuPy stand-in of the tests)."""
    if a.flags.c_contiguous and (dtype is None or a.dtype == dtype):
        return a
    return array_module(a).ascontiguousarray(a, dtype=dtype)


def sparse_module(x) -> ModuleType:
    """``cupyx.scipy.sparse`` for a CuPy array (or sparse matrix), else ``scipy.sparse``."""
    if type(x).__module__.startswith("cupy"):
        import cupyx.scipy.sparse

        return cupyx.scipy.sparse
    import scipy.sparse

    return scipy.sparse


def linear_operator(shape: tuple[int, int], matvec, reference):
    """A linear operator applying ``matvec`` (N,) -> (N,): SciPy's LinearOperator for a NumPy
    ``reference`` array (for SciPy's solvers), else a :class:`MatvecOperator` (``A @ x``, all that
    :func:`o3d_mvps.solver.krylov.pcg` asks of it)."""
    if array_module(reference) is np:
        from scipy.sparse.linalg import LinearOperator

        return LinearOperator(shape, matvec=matvec, dtype=np.float64)
    return MatvecOperator(shape, matvec)


class MatvecOperator:
    """``A @ x`` as ``matvec(x)`` for an (N, N) operator: the device's counterpart of a SciPy
    LinearOperator, without relying on cupyx's."""

    def __init__(self, shape: tuple[int, int], matvec):
        self.shape = shape
        self.dtype = np.dtype(np.float64)
        self.matvec = matvec

    def __matmul__(self, x):
        return self.matvec(x)


def fused(function):
    """``function`` (elementwise arithmetic of arrays and scalars: operators, ufuncs,
    ``array_module(x).where``; one result or a tuple) as one kernel on CuPy's arrays, by
    ``cupy.fuse``, compiled once per process; on NumPy's the function itself. On a GPU every
    array operation is a kernel launch (5-20 us from Python whatever the array's size): a fused
    chain of them is one. The function must not write into its arguments."""
    kernels = {}

    def call(*args):
        xp = next((module for a in args if (module := array_module(a)) is not np), np)
        if xp is np:
            return function(*args)
        kernel = kernels.get(xp)
        if kernel is None:
            kernel = kernels[xp] = xp.fuse(kernel_name=function.__name__)(function)
        return kernel(*args)

    call.__name__, call.__doc__, call.__wrapped__ = function.__name__, function.__doc__, function
    return call
