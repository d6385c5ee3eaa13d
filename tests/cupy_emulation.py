"""A stand-in for CuPy on NumPy, as strict as CuPy 14 where host and device arrays meet.

The solver's CUDA path takes its array module from the data (o3d_mvps.model.arrays): arrays of
:class:`ndarray` here (a wrapper of a NumPy array, from a module whose name starts with "cupy")
make it import this module as ``cupy`` and :mod:`sparse` as ``cupyx.scipy.sparse`` (see
:func:`installed`). Like CuPy's, these arrays are no NumPy arrays, and raise TypeError where
CuPy does:

- a NumPy array (of any size, 0-d too: CuPy takes Python and NumPy scalars only) in an operation
  with a device array, in a NumPy function given a device array, or in a function of this
  module other than :func:`asarray`, :func:`array` and :func:`asnumpy` (the copies to and from
  the device);
- a device array where NumPy needs a host array: ``np.asarray``/``np.array``/
  ``np.ascontiguousarray`` of it, writing it into a NumPy array, a SciPy function or a CPU
  (numba) kernel given it (``__array__`` raises, as CuPy's does since CuPy 13);
- sparse matrices take and give only device arrays;
- inside :func:`fuse`, the function gets CuPy's fusion proxies (:class:`_FusionProxy`): operators,
  ufuncs and ``where`` only (builtin ``abs``, ``shape``, NumPy functions and ``float()`` raise);
- a 0-d array given to a CUDA kernel for a scalar (numba-cuda cannot compile arithmetic with it).

Allowed, as in CuPy: ``.get()``, ``asnumpy``; ``float()``/``int()``/``bool()``/``.item()`` of a
one-element array (a copy to the host: counted); NumPy arrays and lists as indices, and as the
value written into a device array (copies to the device: counted). Reductions give 0-d arrays.
Everything else is NumPy's and SciPy's, and numba's CUDA simulator runs the CUDA kernels on the
arrays' NumPy data (:func:`installed`). So a solve on them runs the CUDA path's Python as on a
GPU, and fails where it would mix host and device arrays there. (Not caught: CuPy functions that
NumPy has and CuPy lacks.)

:data:`operations` counts what would each be a kernel launch or a transfer on a GPU, by kind
(``benchmarks/gpu.py count`` reads it): elementwise operations and reductions, fused kernels
(:func:`fuse`: one each), other NumPy functions and array methods, sparse products, gathers by
index arrays, writes into arrays, copies to the device and to the host; :func:`recording_sites`
also counts them by the call site in o3d_mvps (the profile of a sweep).
"""

from __future__ import annotations

import sys
import types
from collections import Counter
from contextlib import contextmanager

import numpy as np
import scipy.sparse as _sp
from numpy.lib.mixins import NDArrayOperatorsMixin

#: operations on the stand-in's arrays so far, by kind (see the module's docstring)
operations = Counter()

#: where the operations were asked for, when :func:`recording_sites` is on: (kind, "file:line
#: function" of the innermost caller in o3d_mvps, followed by " [kernel]" for a fused or
#: counted CUDA kernel) -> count
sites = Counter()
_recording = False


#: the name of the kernel :func:`fuse` is running, None outside one
_fusing = None
#: the functions of this module a fused kernel may call (CuPy's fusion takes ufuncs, operators,
#: where; its reductions, which this stand-in does not fuse, only at the end)
_FUSABLE = frozenset({"where"})


def count(kind: str, n: int = 1, name: str | None = None) -> None:
    """Count ``n`` operations of ``kind`` (and their call site, see :data:`sites`, with the
    kernel's ``name`` where given); within a fused kernel (:func:`fuse`) nothing is counted, and
    anything but an elementwise operation raises TypeError."""
    if _fusing is not None:
        if kind != "elementwise" and n:
            raise TypeError(f"cupy.fuse: kernel {_fusing!r} asks for a {kind} operation; a fused kernel takes "
                            "elementwise operations (ufuncs, operators, where) of its arguments only")
        return
    operations[kind] += n
    if _recording and n:
        site = _call_site()
        sites[kind, site if name is None else f"{site} [{name}]"] += n


#: o3d_mvps's helpers that only pass arrays on: a call site is their caller
_HELPERS = ("model/arrays.py", "solver/device.py")
#: Python 3.11's own frames of comprehensions: a call site is the function they run in
_COMPREHENSIONS = frozenset({"<listcomp>", "<dictcomp>", "<setcomp>", "<genexpr>"})


def _call_site() -> str:
    """The innermost frame of the o3d_mvps package on the stack, but for :data:`_HELPERS`, as
    "path:line function"."""
    frame = sys._getframe(2)
    while frame is not None:
        name = frame.f_code.co_filename
        if "/o3d_mvps/" in name and not name.endswith(_HELPERS) and frame.f_code.co_name not in _COMPREHENSIONS:
            return f"{name.rsplit('/o3d_mvps/', 1)[1]}:{frame.f_lineno} {frame.f_code.co_name}"
        frame = frame.f_back
    return "?"


@contextmanager
def recording_sites():
    """Within: every count also goes to :data:`sites` by call site (slow: walks the stack)."""
    global _recording
    _recording, saved = True, _recording
    try:
        yield sites
    finally:
        _recording = saved

#: CuPy's message when NumPy asks a device array for its data
IMPLICIT_CONVERSION = ("Implicit conversion to a NumPy array is not allowed. Please use `.get()` to construct a "
                       "NumPy array explicitly.")


class DeviceMixError(TypeError):
    """A host array met a device array, or NumPy asked for a device array's data (CuPy raises
    a TypeError there too)."""


def _check(values) -> None:
    """DeviceMixError for a host (NumPy or SciPy sparse) array among ``values`` (nested lists
    and tuples too)."""
    for value in values:
        if isinstance(value, (list, tuple)):
            _check(value)
        elif isinstance(value, np.ndarray):
            raise DeviceMixError(f"Unsupported type {type(value)}: a host NumPy array {value.shape} {value.dtype} "
                                 "met a device array (copy it over with cupy.asarray)")
        elif isinstance(value, _sp.spmatrix | _sp.sparray):
            raise DeviceMixError(f"a host SciPy sparse matrix {value.shape} met a device array")


def _host(value):
    """The NumPy data of device arrays (and of :class:`_FusionProxy`'s values), also inside lists,
    tuples and dicts."""
    if isinstance(value, (ndarray, _FusionProxy)):
        return value._a
    if isinstance(value, (list, tuple)):
        return type(value)(_host(v) for v in value)
    if isinstance(value, dict):
        return {k: _host(v) for k, v in value.items()}
    return value


def _device(value):
    """NumPy results as device arrays (scalars as 0-d arrays, as CuPy's reductions give)."""
    if isinstance(value, np.ndarray):
        return ndarray(value)
    if isinstance(value, np.generic):
        return ndarray(np.asarray(value))
    if isinstance(value, tuple):
        return tuple(_device(v) for v in value)
    if isinstance(value, list):
        return [_device(v) for v in value]
    return value


#: array methods that make a view (no kernel on a GPU: not counted)
_VIEWS = frozenset({"reshape", "view", "transpose", "squeeze", "swapaxes", "ravel"})
#: the kinds of the other counted array methods (default: "function")
_METHOD_KINDS = {"item": "to_host", "tolist": "to_host", **{name: "reduction" for name in (
    "sum", "mean", "max", "min", "prod", "any", "all", "argmax", "argmin", "std", "var", "cumsum")}}


class ndarray(NDArrayOperatorsMixin):  # noqa: N801 - CuPy's name
    """A "device" array: a wrapper of a NumPy array (its data, :attr:`_a`) that refuses host
    arrays in operations and refuses NumPy its data (``__array__`` raises, as CuPy's)."""

    __slots__ = ("_a",)
    __hash__ = None

    def __init__(self, a: np.ndarray):
        self._a = a

    def __array__(self, dtype=None, copy=None):
        raise DeviceMixError(IMPLICIT_CONVERSION)

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        count("elementwise" if method == "__call__" else "reduction")
        _check(inputs)
        _check(list(kwargs.values()))
        out = kwargs.get("out")
        kwargs = _host(kwargs)
        result = getattr(ufunc, method)(*_host(inputs), **kwargs)
        if out is not None:
            return out[0] if len(out) == 1 else out
        return _device(result)

    def __array_function__(self, func, types, args, kwargs):
        count("function")
        _check(args)
        _check(list(kwargs.values()))
        return _device(func(*_host(args), **_host(kwargs)))

    def __getattr__(self, name: str):
        """NumPy's attributes and methods, on device arrays only."""
        if name.startswith("__") or name == "_a":  # __array_interface__ & co: NumPy gets no host data
            raise AttributeError(name)
        value = getattr(self._a, name)
        if not callable(value):
            return _device(value)

        def method(*args, **kwargs):
            if name not in _VIEWS:
                count(_METHOD_KINDS.get(name, "function"))
            _check(args)
            _check(list(kwargs.values()))
            return _device(value(*_host(args), **_host(kwargs)))

        return method

    def get(self, stream=None, order="C", out=None) -> np.ndarray:
        """A host copy."""
        count("to_host")
        return np.array(self._a, order=order)

    def __getitem__(self, index):
        if not _basic_index(index):
            count("gather")
            _count_host_indices(index)
        return _device(self._a[_host(index)])

    def __setitem__(self, index, value):
        count("write")
        _count_host_indices(index)
        if isinstance(value, np.ndarray) or isinstance(value, (list, tuple)) and not isinstance(value, ndarray):
            count("to_device")  # CuPy copies host data over
        self._a[_host(index)] = _host(value)

    def __len__(self) -> int:
        return len(self._a)

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def _scalar(self, convert):
        count("to_host")  # a synchronisation and a copy on a GPU
        return convert(self._a)

    def __float__(self):
        return self._scalar(float)

    def __int__(self):
        return self._scalar(int)

    def __bool__(self):
        return self._scalar(bool)

    def __complex__(self):
        return self._scalar(complex)

    def __repr__(self) -> str:
        return f"cupy_emulation.{np.array_repr(self._a)}"


def _basic_index(index) -> bool:
    """Whether an index is made of integers and slices only (a view, no kernel)."""
    parts = index if isinstance(index, tuple) else (index,)
    return all(isinstance(part, (int, np.integer, slice, type(None), type(Ellipsis))) for part in parts)


def _count_host_indices(index) -> None:
    """Count the copies to the device of host index arrays (CuPy takes them)."""
    parts = index if isinstance(index, tuple) else (index,)
    count("to_device", sum(isinstance(part, (np.ndarray, list)) for part in parts))


def host_data(a):
    """The NumPy data of a device array, itself for anything else (for the tests' and the
    benchmarks' stand-ins of kernels: no copy, not counted)."""
    return a._a if isinstance(a, ndarray) else a


#: functions that only allocate (from CuPy's memory pool: no kernel, not counted)
_ALLOCATIONS = frozenset({"empty", "empty_like"})


def _function(f):
    def wrapped(*args, **kwargs):
        elementwise = isinstance(f, np.ufunc) or _fusing is not None and wrapped.__name__ in _FUSABLE
        if wrapped.__name__ not in _ALLOCATIONS:
            count("elementwise" if elementwise else "function")
        _check(args)
        _check(list(kwargs.values()))
        result = f(*_host(args), **_host(kwargs))
        return _device(result) if _fusing is None else _proxied(result)

    wrapped.__name__ = getattr(f, "__name__", "function")
    return wrapped


class _Fused:
    """A function fused into one kernel (:func:`fuse`)."""

    def __init__(self, function, kernel_name: str | None):
        self.function, self.name = function, kernel_name or function.__name__

    def __call__(self, *args):
        global _fusing
        if not any(isinstance(a, ndarray) for a in args):  # CuPy calls the function on NumPy's arrays
            return self.function(*args)
        _check(args)
        for a in args:
            if not isinstance(a, (ndarray, int, float, bool, complex, np.generic)):
                raise TypeError(f"cupy.fuse: kernel {self.name!r} got a {type(a).__name__}: give device arrays "
                                "and scalars")
        if _fusing is not None:
            raise TypeError(f"cupy.fuse: kernel {self.name!r} called inside kernel {_fusing!r}")
        _fusing = self.name
        try:
            result = self.function(*(_FusionProxy(_host(a)) for a in args))
        finally:
            _fusing = None
        count("fused", name=self.name)
        return _unproxied(result)


class _FusionProxy:
    """What a function fused by :func:`fuse` gets for each argument, as CuPy's fusion gives it
    (``_VariableProxy`` of cupy/_core/_fusion_interface.py, CuPy 14): the operators below, this
    module's ufuncs and ``where``, ``dtype``, ``ndim``, ``astype`` and ``copy``. Nothing else:
    no builtin ``abs`` or unary ``+``, no reflected ``**``, no ``shape`` (NotImplementedError),
    no NumPy functions, no conversion to a Python scalar or bool (TypeError), as on a GPU.
    Holds the argument's NumPy data (or the Python scalar)."""

    __slots__ = ("_a",)
    __array_ufunc__ = None  # NumPy's ufuncs refuse it (CuPy's proxies are no NumPy arrays either)

    def __init__(self, a):
        self._a = a

    @property
    def dtype(self):
        return np.result_type(self._a)

    @property
    def ndim(self):
        return np.ndim(self._a)

    @property
    def shape(self):
        raise NotImplementedError("`shape` is not supported, currently.")

    def astype(self, dtype, copy=True):
        return _FusionProxy(np.asarray(self._a).astype(dtype))

    def copy(self):
        return _FusionProxy(np.copy(self._a))

    def _no_scalar(self):
        raise TypeError("Cannot convert to Python scalar in cupy.fuse")

    def _reduction(self, *args, **kwargs):
        count("reduction")  # CuPy fuses a reduction at the end only; this stand-in refuses them all

    sum = prod = max = min = all = any = _reduction

    __bool__ = __int__ = __float__ = __complex__ = _no_scalar
    __hash__ = None


def _fusion_operator(ufunc_name: str, reflected: bool = False, unary: bool = False):
    def operator(self, other=None):
        ufunc = getattr(sys.modules[__name__], ufunc_name)
        if unary:
            return ufunc(self)
        return ufunc(other, self) if reflected else ufunc(self, other)

    return operator


#: CuPy's fusion operators: Python's name -> (ufunc, also reflected)
_FUSION_OPERATORS = {"add": ("add", True), "sub": ("subtract", True), "mul": ("multiply", True),
                     "truediv": ("true_divide", True), "floordiv": ("floor_divide", True),
                     "mod": ("remainder", True), "pow": ("power", False), "lshift": ("left_shift", True),
                     "rshift": ("right_shift", True), "and": ("bitwise_and", True), "or": ("bitwise_or", True),
                     "xor": ("bitwise_xor", True), "lt": ("less", False), "le": ("less_equal", False),
                     "eq": ("equal", False), "ne": ("not_equal", False), "ge": ("greater_equal", False),
                     "gt": ("greater", False)}
for _name, (_ufunc, _reflected) in _FUSION_OPERATORS.items():
    setattr(_FusionProxy, f"__{_name}__", _fusion_operator(_ufunc))
    if _reflected:
        setattr(_FusionProxy, f"__r{_name}__", _fusion_operator(_ufunc, reflected=True))
_FusionProxy.__neg__ = _fusion_operator("negative", unary=True)
_FusionProxy.__invert__ = _fusion_operator("invert", unary=True)


def _proxied(value):
    """A fused function's intermediate results as :class:`_FusionProxy` (tuples too)."""
    if isinstance(value, tuple):
        return tuple(_proxied(v) for v in value)
    return _FusionProxy(value)


def _unproxied(value):
    """A fused function's results as device arrays (tuples too)."""
    if isinstance(value, tuple):
        return tuple(_unproxied(v) for v in value)
    return _device(np.asarray(value._a)) if isinstance(value, _FusionProxy) else _device(value)


def fuse(*args, kernel_name: str | None = None):
    """CuPy's ``fuse``: ``@fuse()`` / ``@fuse`` makes a function of arrays and scalars one kernel
    (one launch, counted as "fused"), run here with NumPy's semantics on the arrays' data; inside
    it only elementwise operations (TypeError for anything else: reductions, copies, other
    functions, float() of an array). Given no device array, it calls the function as it is."""
    if len(args) == 1 and callable(args[0]):
        return _Fused(args[0], kernel_name)
    if args:
        raise TypeError(f"fuse() takes a function or kernel_name=, not {args!r}")
    return lambda function: _Fused(function, kernel_name)


def asarray(a, dtype=None, order=None):
    """Host or device data as a device array (CuPy copies host data to the device)."""
    _count_copy(a)
    return ndarray(np.asarray(_host(a), dtype=dtype, order=order))


def array(a, dtype=None, copy=True, order="K", ndmin=0):
    """A device array of host or device data, a copy (CuPy's ``array``)."""
    _count_copy(a)
    return ndarray(np.array(_host(a), dtype=dtype, copy=copy, order=order, ndmin=ndmin))


def asnumpy(a, stream=None, order="C", out=None):
    """A host copy of a device array; host data as it is (CuPy's ``asnumpy``)."""
    if isinstance(a, ndarray):
        return a.get(order=order)
    return np.asarray(a, order=order)


def _count_copy(a) -> None:
    """Count a copy of host data to the device."""
    if not isinstance(a, ndarray):
        count("to_device")


def get_array_module(*arrays):
    return sys.modules[__name__] if any(isinstance(a, ndarray) for a in arrays) else np


linalg = types.SimpleNamespace(inv=_function(np.linalg.inv), norm=_function(np.linalg.norm),
                               solve=_function(np.linalg.solve), cholesky=_function(np.linalg.cholesky))


def __getattr__(name: str):
    """NumPy's functions, taking device arrays only and giving device arrays; its types and
    constants as they are."""
    value = getattr(np, name)
    if isinstance(value, (types.FunctionType, types.BuiltinFunctionType, np.ufunc)) or callable(value) and \
            not isinstance(value, type):
        return _function(value)
    return value


def _device_only(value):
    if isinstance(value, np.ndarray):
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

    def sort_indices(self):
        """In place, as cupyx's (a launch)."""
        count("function")
        self._m.sort_indices()

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
            count("sparse_product")
            return csr_matrix(self._m @ other._m)
        count("sparse_matvec")
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


class _SimulatorArguments:
    """An extension of numba's CUDA simulator's kernels: it runs them on NumPy arrays, so a device
    array goes in as its NumPy data (the real CUDA target takes CuPy's arrays through their
    ``__cuda_array_interface__``)."""

    def prepare_args(self, ty, val, stream=0, retr=None):
        if isinstance(val, (ndarray, np.ndarray)) and val.ndim == 0:
            raise TypeError("a 0-d array as a CUDA kernel's argument: numba-cuda types it as an array, and "
                            "arithmetic with it does not compile on a GPU (KeyError: <ufunc 'multiply'>); "
                            "pass a Python or NumPy scalar (float(x))")
        return ty, host_data(val)


def _simulated_kernels() -> list:
    """The CUDA kernels of o3d_mvps.solver.cuda_kernels where numba's CUDA simulator runs them."""
    from numba import cuda

    if not cuda.config.ENABLE_CUDASIM:
        return []
    from o3d_mvps.solver import cuda_kernels

    return [k for k in vars(cuda_kernels).values() if type(k).__name__ == "FakeCUDAKernel"]


@contextmanager
def installed():
    """Within: ``import cupy`` / ``cupyx.scipy.sparse`` give this module and :data:`sparse`, and
    numba's CUDA simulator (where it is on) runs the CUDA kernels on this module's arrays."""
    modules = {"cupy": sys.modules[__name__], "cupyx": types.ModuleType("cupyx"),
               "cupyx.scipy": types.ModuleType("cupyx.scipy"), "cupyx.scipy.sparse": sparse}
    modules["cupyx"].scipy = modules["cupyx.scipy"]
    modules["cupyx.scipy"].sparse = sparse
    saved = {name: sys.modules.get(name) for name in modules}
    kernels, extension = _simulated_kernels(), _SimulatorArguments()
    sys.modules.update(modules)
    for kernel in kernels:
        kernel.extensions.append(extension)
    try:
        yield
    finally:
        for kernel in kernels:
            kernel.extensions.remove(extension)
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module
