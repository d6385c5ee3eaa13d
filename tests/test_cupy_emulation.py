"""The CuPy stand-in of tests/cupy_emulation.py is as strict as CuPy 14 where host and device
arrays meet: it raises TypeError wherever CuPy does (a NumPy array given to a CuPy function other
than asarray/array/asnumpy or met in an operation, NumPy asked for a device array's data), so
that the CUDA path's tests (tests/test_cuda_path.py) fail on what would fail on a GPU; and it
allows what CuPy allows (scalars, float() of one element, .get()).
"""

import numpy as np
import pytest
import scipy.linalg

import cupy_emulation as cp
from o3d_mvps.model.arrays import array_module, like
from o3d_mvps.solver import kernels

HOST = np.arange(6.0).reshape(2, 3)
IMPLICIT = "Implicit conversion to a NumPy array is not allowed"


@pytest.fixture
def device():
    return cp.asarray(HOST)


@pytest.mark.parametrize("call", [
    lambda d: cp.ascontiguousarray(HOST),  # the crash of model.arrays.like on a GPU (issue 33)
    lambda d: cp.zeros_like(HOST),
    lambda d: cp.concatenate([d, HOST]),
    lambda d: cp.einsum("ij,ij->i", d, HOST),
])
def test_cupy_functions_refuse_host_arrays(device, call):
    with pytest.raises(TypeError, match="host NumPy array"):
        call(device)


@pytest.mark.parametrize("call", [
    lambda d: d + HOST,
    lambda d: HOST * d,
    lambda d: np.add(HOST, d),
    lambda d: d @ HOST.T,
    lambda d: d + np.array(2.0),  # a 0-d host array too: CuPy takes Python and NumPy scalars only
    lambda d: np.stack([d, HOST]),
    lambda d: d.dot(HOST.T),
    lambda d: cp.sparse.csr_matrix(scipy_eye()) @ HOST[0, :2],
])
def test_operations_refuse_host_arrays(device, call):
    with pytest.raises(TypeError):
        call(device)


def scipy_eye():
    import scipy.sparse

    return scipy.sparse.eye(2, format="csr")


@pytest.mark.parametrize("call", [
    np.asarray, np.array, np.ascontiguousarray, lambda d: np.asarray(d, dtype=np.float32),
    scipy.linalg.cho_factor,  # SciPy converts with np.asarray
])
def test_numpy_cannot_take_a_device_array(device, call):
    with pytest.raises(TypeError, match=IMPLICIT):
        call(device)


def test_a_device_array_is_not_written_into_a_host_array(device):
    host = np.zeros((2, 3))
    with pytest.raises(TypeError, match=IMPLICIT):
        host[:] = device
    assert not host.any()


def test_cpu_kernels_refuse_device_arrays(device):
    """numba's CPU kernels type their arguments: a device array is no NumPy array to them."""
    from numba.core.errors import TypingError

    with pytest.raises(TypingError, match="non-precise type pyobject"):
        kernels.log1p_square_sum(device[0], 1.0)


def test_what_cupy_allows(device):
    """Copies both ways, scalars in operations, one element to a Python number (a
    synchronisation on a GPU), host index arrays, host values written into a device array."""
    assert not isinstance(device, np.ndarray)
    with cp.installed():
        assert array_module(device) is cp
    np.testing.assert_array_equal(device.get(), HOST)
    assert type(device.get()) is np.ndarray and type(cp.asnumpy(device)) is np.ndarray
    np.testing.assert_array_equal(cp.array(HOST).get(), HOST)
    total = (device * 2.0 + np.float64(1.0)).sum()
    assert isinstance(total, cp.ndarray) and total.shape == () and float(total) == 36.0
    assert int(device[1, 2]) == 5 and bool(device[0, 1]) and device.max().item() == 5.0
    np.testing.assert_array_equal(device[np.array([1, 0])].get(), HOST[[1, 0]])
    copy = cp.zeros_like(device)
    copy[0] = HOST[1]
    np.testing.assert_array_equal(copy.get()[0], HOST[1])
    host = np.zeros(2)
    host[0] = device[1, 1]  # one element: float(), as NumPy does for CuPy's
    assert host[0] == 4.0


def test_like_copies_host_data_with_asarray(device):
    """model.arrays.like: a host array of the device's module through asarray (before issue 33 it
    called ascontiguousarray, which CuPy and this stand-in refuse)."""
    with cp.installed():
        moved = like(HOST.T, device, dtype=np.float32)
        assert isinstance(moved, cp.ndarray) and moved.dtype == np.float32 and moved.flags.c_contiguous
        np.testing.assert_array_equal(moved.get(), HOST.T)
        assert like(HOST, HOST) is HOST  # the host: no copy
        with pytest.raises(TypeError, match="host NumPy array"):
            array_module(device).ascontiguousarray(HOST)


def test_model_functions_take_device_arrays(device):
    """The model's elementwise maths on device arrays (host lights copied over), as on the host."""
    from o3d_mvps.model.robust import cauchy, cauchy_weights
    from o3d_mvps.model.shading import shading

    normals = np.array([[0.0, 0.6, -0.8], [0.0, 0.0, -1.0]])
    light = np.array([0.2, 0.1, -0.3, -1.0])
    with cp.installed():
        for f, args, device_args in ((cauchy, (HOST, 0.5), (device, 0.5)),
                                     (cauchy_weights, (HOST, 0.5), (device, 0.5)),
                                     (shading, (normals, light), (cp.asarray(normals), light))):
            result = f(*device_args)
            assert isinstance(result, cp.ndarray)
            np.testing.assert_allclose(result.get(), f(*args), rtol=1e-15)


def test_fuse_is_one_launch_with_numpys_results(device):
    """cupy.fuse as CuPy's: a chain of elementwise operations (where too) of device arrays and
    scalars is one kernel, counted as one "fused" launch, with NumPy's results; the same function
    on host arrays only is called as it is (CuPy's fallback)."""
    def step(x, y, a):
        return cp.where(x > 1.0, x + a * y, x), x * y

    fused = cp.fuse(kernel_name="step")(step)
    before = cp.operations.copy()
    z, w = fused(device, device * 2.0, 0.5)
    counted = cp.operations - before
    assert counted == {"fused": 1, "elementwise": 1}  # device * 2.0 outside the kernel
    np.testing.assert_array_equal(z.get(), np.where(HOST > 1.0, HOST + 0.5 * HOST * 2.0, HOST))
    np.testing.assert_array_equal(w.get(), HOST * HOST * 2.0)
    assert isinstance(cp.fuse(lambda x: x + 1.0)(HOST), np.ndarray)


def test_sites_name_the_fused_kernel_and_the_caller():
    """With recording_sites on, a fused kernel's launch is counted at its caller in o3d_mvps with
    the kernel's name (what ``python -m benchmarks.gpu sites`` groups by)."""
    from o3d_mvps.model.camera import backproject

    cp.sites.clear()
    K = np.array([[300.0, 0.0, 80.0], [0.0, 310.0, 60.0], [0.0, 0.0, 1.0]])
    z, u, v = (cp.asarray(np.linspace(0.5, 0.6, 4)) for _ in range(3))
    with cp.installed(), cp.recording_sites():
        backproject(z, K, u, v)
    fused = [site for (kind, site), n in cp.sites.items() if kind == "fused"]
    assert fused and all(site.startswith("model/camera.py:") and site.endswith("backproject [_backproject_xy]")
                         for site in fused), dict(cp.sites)
    cp.sites.clear()


@pytest.mark.parametrize("body, message", [
    (lambda x, y: x.sum() + y, "asks for a reduction operation"),
    (lambda x, y: x + float(y.max()), "asks for a reduction operation"),
    (lambda x, y: cp.concatenate([x, y]), "asks for a function operation"),
    (lambda x, y: x[cp.asarray(np.array([0]))] + y, "asks for a to_device operation"),
])
def test_fuse_refuses_what_is_not_elementwise(device, body, message):
    before = cp.operations.copy()
    with pytest.raises(TypeError, match=message):
        cp.fuse()(body)(device, device)
    assert cp.operations == before  # nothing counted, no kernel launched


@pytest.mark.parametrize("body, error, message", [
    (lambda x, y: abs(x - y), TypeError, "bad operand type for abs"),  # robust.py's crash on an H100
    (lambda x, y: +x, TypeError, "bad operand type for unary"),
    (lambda x, y: 2.0 ** x, TypeError, "unsupported operand"),
    (lambda x, y: x + y.shape[0], NotImplementedError, "`shape` is not supported"),
    (lambda x, y: x if x > y else y, TypeError, "Cannot convert to Python scalar in cupy.fuse"),
    (lambda x, y: x + float(y), TypeError, "Cannot convert to Python scalar in cupy.fuse"),
    (lambda x, y: np.sqrt(x) + y, TypeError, "does not support ufuncs"),
])
def test_fuse_gives_cupys_proxies(device, body, error, message):
    """Inside cupy.fuse the arguments are CuPy 14's proxies (cupy/_core/_fusion_interface.py):
    operators, ufuncs of the array module and where, nothing else; what CuPy refuses there is
    refused here, with CuPy's error type."""
    with pytest.raises(error, match=message):
        cp.fuse()(body)(device, device)
    xp_body = cp.fuse()(lambda x, y: cp.abs(x - y) + cp.where(x > y, x ** 2.0, -y))
    np.testing.assert_array_equal(xp_body(device, device * 0.5).get(),
                                  np.abs(0.5 * HOST) + np.where(HOST > 0.5 * HOST, HOST ** 2.0, -0.5 * HOST))


def test_fuse_refuses_host_arrays(device):
    with pytest.raises(TypeError, match="host NumPy array"):
        cp.fuse()(lambda x, y: x + y)(device, HOST)


def test_fused_helper_runs_numpy_or_one_kernel(device):
    """o3d_mvps.model.arrays.fused: the function itself on NumPy's arrays, one kernel on the
    device's (cupy.fuse of the arrays' module)."""
    from o3d_mvps.model.arrays import fused

    @fused
    def axpy(a, x, y):
        return a * x + y

    np.testing.assert_array_equal(axpy(2.0, HOST, HOST), 3.0 * HOST)
    with cp.installed():
        before = cp.operations.copy()
        result = axpy(2.0, device, device)
        assert cp.operations - before == {"fused": 1}
    np.testing.assert_array_equal(result.get(), 3.0 * HOST)
