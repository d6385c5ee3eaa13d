"""A stand-in for CuPy on NumPy, as strict as CuPy where host and device arrays meet.

The solver's CUDA path takes its array module from the data (o3d_mvps.model.arrays): arrays of
:class:`ndarray` here (a NumPy subclass from a module whose name starts with "cupy") make it
import this module as ``cupy`` and :mod:`sparse` as ``cupyx.scipy.sparse`` (see
:func:`installed`). Like CuPy's, these arrays refuse to meet a host array (a NumPy array of one
element or more) in an operation or a NumPy function, sparse matrices take and give only device
arrays, and ``.get()`` copies to the host; reductions give 0-d arrays. Everything else is
NumPy's and SciPy's, and numba's CUDA simulator runs the CUDA kernels on these arrays. So a
solve on them runs the CUDA path's Python as on a GPU, and fails where it would mix host and
device arrays there. (Not caught: ``np.asarray`` of a device array, which CuPy refuses and NumPy
cannot be made to; CuPy functions NumPy has and CuPy lacks.)

:data:`operations` counts what would each be a kernel launch or a transfer on a GPU, by kind
(``benchmarks/gpu.py count`` reads it): elementwise operations and reductions, other NumPy
functions, sparse products, gathers by index arrays, writes into arrays, copies to the device
and to the host.
"""

from __future__ import annotations

import sys
import types
from collections import Counter
from contextlib import contextmanager

import numpy as np
import scipy.sparse as _sp


#: operations on the stand-in's arrays so far, by kind (see the module's docstring)
operations = Counter()


class DeviceMixError(TypeError):
    """A host array met a device array (CuPy raises a TypeError there too)."""


def _check(values) -> None:
    for value in values:
        if isinstance(value, (list, tuple)):
            _check(value)
        elif isinstance(value, np.ndarray) and not isinstance(value, ndarray) and value.ndim > 0:
            raise DeviceMixError(f"a host NumPy array {value.shape} {value.dtype} met a device array")
        elif isinstance(value, _sp.spmatrix | _sp.sparray):
            raise DeviceMixError(f"a host SciPy sparse matrix {value.shape} met a device array")


def _host(value):
    """The plain NumPy view of device arrays, also inside lists and tuples."""
    if isinstance(value, ndarray):
        return value.view(np.ndarray)
    if isinstance(value, (list, tuple)):
        return type(value)(_host(v) for v in value)
    if isinstance(value, dict):
        return {k: _host(v) for k, v in value.items()}
    return value


def _device(value):
    """NumPy results as device arrays (scalars as 0-d arrays, as CuPy's reductions give)."""
    if isinstance(value, np.ndarray):
        return value if isinstance(value, ndarray) else value.view(ndarray)
    if isinstance(value, np.generic):
        return np.asarray(value).view(ndarray)
    if isinstance(value, tuple):
        return tuple(_device(v) for v in value)
    if isinstance(value, list):
        return [_device(v) for v in value]
    return value


class ndarray(np.ndarray):  # noqa: N801 - CuPy's name
    """A "device" array: a NumPy array that refuses host arrays in operations."""

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        operations["elementwise" if method == "__call__" else "reduction"] += 1
        _check(inputs)
        out = kwargs.get("out")
        if out is not None:
            _check(out)
            kwargs["out"] = _host(out)
        result = getattr(ufunc, method)(*_host(inputs), **kwargs)
        if out is not None:
            return out[0] if len(out) == 1 else out
        return _device(result)

    def __array_function__(self, func, types, args, kwargs):
        operations["function"] += 1
        _check(args)
        _check(list(kwargs.values()))
        return _device(func(*_host(args), **_host(kwargs)))

    def get(self) -> np.ndarray:
        """A host copy."""
        operations["to_host"] += 1
        return np.array(self.view(np.ndarray))

    def __getitem__(self, index):
        if not _basic_index(index):
            operations["gather"] += 1
        return super().__getitem__(index)

    def __setitem__(self, index, value):
        operations["write"] += 1
        super().__setitem__(index, value)


def _basic_index(index) -> bool:
    """Whether an index is made of integers and slices only (a view, no kernel)."""
    parts = index if isinstance(index, tuple) else (index,)
    return all(isinstance(part, (int, np.integer, slice, type(None), type(Ellipsis))) for part in parts)


def _function(f):
    def wrapped(*args, **kwargs):
        operations["function"] += 1
        _check(args)
        _check(list(kwargs.values()))
        return _device(f(*_host(args), **_host(kwargs)))

    wrapped.__name__ = getattr(f, "__name__", "function")
    return wrapped


def asarray(a, dtype=None):
    """Host or device data as a device array (CuPy copies host arrays to the device)."""
    _count_copy(a)
    return np.asarray(_host(a), dtype=dtype).view(ndarray)


def ascontiguousarray(a, dtype=None):
    _count_copy(a)
    return np.ascontiguousarray(_host(a), dtype=dtype).view(ndarray)


def _count_copy(a) -> None:
    """Count a copy of host data to the device."""
    if not isinstance(a, ndarray):
        operations["to_device"] += 1


def get_array_module(*arrays):
    return sys.modules[__name__] if any(isinstance(a, ndarray) for a in arrays) else np


linalg = types.SimpleNamespace(inv=_function(np.linalg.inv), norm=_function(np.linalg.norm),
                               solve=_function(np.linalg.solve), cholesky=_function(np.linalg.cholesky))


def __getattr__(name: str):
    """NumPy's functions, taking and giving device arrays; its types and constants as they are."""
    value = getattr(np, name)
    if isinstance(value, (types.FunctionType, types.BuiltinFunctionType, np.ufunc)) or callable(value) and \
            not isinstance(value, type):
        return _function(value)
    return value


def _device_only(value):
    if isinstance(value, np.ndarray) and not isinstance(value, ndarray):
        raise DeviceMixError(f"a host NumPy array {value.shape} given to a device sparse matrix")
    return _host(value)


class csr_matrix:  # noqa: N801 - cupyx's name
    """cupyx.scipy.sparse.csr_matrix on a SciPy CSR matrix: built from a SciPy matrix (a copy to
    the device), another device matrix, or device arrays; products with device arrays only."""

    def __init__(self, arg, shape=None, dtype=None):
        if isinstance(arg, csr_matrix):
            self._m = arg._m.tocsr()
        elif isinstance(arg, _sp.spmatrix | _sp.sparray):
            self._m = _sp.csr_matrix(arg)
        elif isinstance(arg, tuple):
            if len(arg) == 2:  # (data, (row, col))
                data, (row, col) = arg
                arg = (_device_only(data), (_device_only(row), _device_only(col)))
            else:  # (data, indices, indptr)
                arg = tuple(_device_only(a) for a in arg)
            self._m = _sp.csr_matrix(arg, shape=shape)
        else:
            raise DeviceMixError(f"csr_matrix of {type(arg).__name__}: give a sparse matrix or device arrays")
        if dtype is not None:
            self._m = self._m.astype(dtype)

    shape = property(lambda self: self._m.shape)
    dtype = property(lambda self: self._m.dtype)
    nnz = property(lambda self: self._m.nnz)
    data = property(lambda self: _device(self._m.data))
    indices = property(lambda self: _device(self._m.indices))
    indptr = property(lambda self: _device(self._m.indptr))
    T = property(lambda self: csr_matrix(self._m.T))

    def tocsr(self):
        return self

    def __getitem__(self, rows: slice):
        if not isinstance(rows, slice):
            raise DeviceMixError(f"csr_matrix[{rows!r}]: only row slices are emulated")
        return csr_matrix(self._m[rows])

    def diagonal(self):
        return _device(self._m.diagonal())

    def toarray(self):
        return _device(self._m.toarray())

    def __matmul__(self, other):
        if isinstance(other, csr_matrix):
            operations["sparse_product"] += 1
            return csr_matrix(self._m @ other._m)
        operations["sparse_matvec"] += 1
        return _device(self._m @ _device_only(other))

    def __add__(self, other):
        return csr_matrix(self._m + _as_host_sparse(other))

    def __sub__(self, other):
        return csr_matrix(self._m - _as_host_sparse(other))

    def __mul__(self, scalar):
        if not np.isscalar(scalar):
            raise DeviceMixError("csr_matrix * non-scalar: use @")
        return csr_matrix(self._m * scalar)

    __rmul__ = __mul__

    def __neg__(self):
        return csr_matrix(-self._m)

    def __abs__(self):
        return csr_matrix(abs(self._m))


def _as_host_sparse(other):
    if not isinstance(other, csr_matrix):
        raise DeviceMixError(f"a device sparse matrix met {type(other).__name__}")
    return other._m


def diags(diagonal, offsets=0, shape=None, format=None):
    return csr_matrix(_sp.diags(_device_only(diagonal), offsets, shape=shape, format="csr"))


sparse = types.ModuleType("cupy_emulation.sparse")
sparse.csr_matrix, sparse.diags = csr_matrix, diags


def array_device(min_level_pixels: int = 0):
    """The solver's array device on this stand-in: that of ``cuda:N``
    (:func:`o3d_mvps.solver.device.array_device`) with this module for CuPy, but solving levels
    of every size there unless ``min_level_pixels`` says otherwise."""
    from o3d_mvps.solver.device import CUDA_RESIDUAL_DTYPE, ArrayDevice

    return ArrayDevice("cuda-emulated", sys.modules[__name__], sparse, CUDA_RESIDUAL_DTYPE, min_level_pixels)


@contextmanager
def installed():
    """Within: ``import cupy`` / ``cupyx.scipy.sparse`` give this module and :data:`sparse`."""
    modules = {"cupy": sys.modules[__name__], "cupyx": types.ModuleType("cupyx"),
               "cupyx.scipy": types.ModuleType("cupyx.scipy"), "cupyx.scipy.sparse": sparse}
    modules["cupyx"].scipy = modules["cupyx.scipy"]
    modules["cupyx.scipy"].sparse = sparse
    saved = {name: sys.modules.get(name) for name in modules}
    sys.modules.update(modules)
    try:
        yield
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module
