"""The data term's device branches (issue #33, fewer launches per sweep) on the CuPy stand-in
of tests/cupy_emulation.py against the host's functions: equal to round-off, in the launches and
copies each is meant to take. The one-pass kernels themselves: tests/test_cuda_kernels.py; whole
solves on both paths: tests/test_cuda_path.py."""

import cupy_emulation as cp
import numpy as np
import pytest
import scipy.sparse as sp

from benchmarks.gpu import _cpu_kernels_as_cuda_kernels
from o3d_mvps.model.robust import cauchy_weights
from o3d_mvps.solver import lighting
from o3d_mvps.solver.device import to_host
from o3d_mvps.solver.lighting import LEDLight, lit_point_gradients
from o3d_mvps.solver.pyramid import DepthPrior

RNG = np.random.default_rng(3)
N, M = 200, 50


def counted(call):
    """call()'s result and the launches and copies it took on the stand-in (the CUDA kernels'
    launches counted as ``python -m benchmarks.gpu count`` counts them: by their CPU twins)."""
    before = cp.operations.copy()
    with _cpu_kernels_as_cuda_kernels(cp):
        result = call()
    done = cp.operations - before
    copies = done["to_host"] + done["to_device"]
    return result, sum(done.values()) - copies, copies


@pytest.fixture
def prior():
    D = sp.random(M, N, density=0.05, random_state=4, format="csr") + sp.eye(M, N, format="csr")
    S = sp.random(N - 2, N, density=0.03, random_state=5, format="csr")
    z = 0.6 + RNG.random(N) * 0.01
    host = DepthPrior(D.tocsr(), RNG.random(M) * 0.01 + 0.6, z - 0.001, z + 0.001, S.tocsr())
    return host, RNG.random(N) * 0.004 + 0.598


@pytest.mark.parametrize("mu", [0.0, 0.7])
def test_prior_gradient_and_clip_on_the_device_match_the_host(prior, mu):
    """-grad of the prior in one launch (``prior_gradient``, with or without a smoothness term), no copy;
    the clip in one."""
    host, z = prior
    with cp.installed():
        device = host.on_device(cp.array_device())
        z_device = cp.asarray(z)
        expected = host.negative_gradient(z, 2.5, mu)
        device.negative_gradient(z_device, 2.5, mu)  # the first call forms D^T and the zeros (once per level)
        gradient, launches, copies = counted(lambda: device.negative_gradient(z_device, 2.5, mu))
        np.testing.assert_allclose(to_host(gradient), expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
        assert (launches, copies) == (1, 0)
        clipped, launches, copies = counted(lambda: device.clip(z_device))
        np.testing.assert_array_equal(to_host(clipped), host.clip(z))
        assert 0 < (host.clip(z) != z).sum() < N  # some clipped, some not
        assert (launches, copies) == (1, 0)


def test_cauchy_weights_on_the_device_are_one_launch():
    r = (RNG.normal(size=(3, N, 3)) * 0.05).astype(np.float32)
    with cp.installed():
        device = cp.asarray(r)
        weights, launches, copies = counted(lambda: cauchy_weights(device, 0.04))
        np.testing.assert_allclose(to_host(weights), cauchy_weights(r, 0.04), rtol=1e-6)
        assert (launches, copies) == (1, 0)


def test_led_fields_and_point_gradients_on_the_device_match_the_host():
    """The LED's fields (m, N, 3) and point gradients in one launch each and one copy each (the
    fields' light state: lighting.device_light_state, reused by a repeat; the gradients'
    intensities and positions: lighting._light_arrays)."""
    points = RNG.normal(size=(N, 3)) * 0.05 + [0.0, 0.0, 0.6]
    normals = RNG.normal(size=(N, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    poses = np.stack([np.eye(4)] * 3)
    poses[1:, :3, 3] = RNG.normal(size=(2, 3)) * 0.05
    lights = np.array([[0.2, 0.4], [0.1, 0.3], [0.3, 0.5]])
    light = LEDLight(np.array([0.03, -0.01, 0.0]))
    c, L = light.fields(lights, normals, points, poses)
    J = lit_point_gradients(lights, normals, points, light.positions(poses))
    assert (L == 0).any() and (L != 0).any()
    with cp.installed():
        normals_d, points_d = cp.asarray(normals), cp.asarray(points)
        lighting._LIGHT_COPIES.clear()  # no light state copied by an earlier test
        lighting._STATE_COPIES.clear()
        (c_d, L_d), launches, copies = counted(lambda: light.fields(lights, normals_d, points_d, poses))
        np.testing.assert_array_equal(c_d, c)
        np.testing.assert_allclose(to_host(L_d), L, rtol=1e-14)
        assert (launches, copies) == (1, 1)
        _, launches, copies = counted(lambda: light.fields(lights.copy(), normals_d, points_d, poses.copy()))
        assert (launches, copies) == (1, 0)  # the same light state: its copy reused
        J_d, launches, copies = counted(lambda: lit_point_gradients(lights, normals_d, points_d,
                                                                    light.positions(poses)))
        np.testing.assert_allclose(to_host(J_d), J, rtol=1e-14)
        assert (launches, copies) == (1, 1)


def test_led_shading_jacobians_on_the_device_match_the_host():
    """d(shading)/d(xi) (m, N, 6) of the LED in one launch and one copy (were a point-gradient
    kernel, a product, a concatenation and a cross product, three copies)."""
    points = RNG.normal(size=(N, 3)) * 0.05 + [0.0, 0.0, 0.6]
    normals = RNG.normal(size=(N, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    poses = np.stack([np.eye(4)] * 3)
    poses[1, :3, :3] = [[0.999, -0.03, 0.02], [0.03, 0.999, -0.01], [-0.02, 0.01, 0.999]]
    poses[1:, :3, 3] = RNG.normal(size=(2, 3)) * 0.05
    lights = np.array([[0.2, 0.4], [0.1, 0.3], [0.3, 0.5]])
    light = LEDLight(np.array([0.03, -0.01, 0.02]))
    J = light.shading_jacobians(lights, normals, points, poses)
    assert (J == 0).any() and (J != 0).any()
    with cp.installed():
        normals_d, points_d = cp.asarray(normals), cp.asarray(points)
        J_d, launches, copies = counted(lambda: light.shading_jacobians(lights, normals_d, points_d, poses))
        np.testing.assert_allclose(to_host(J_d), J, rtol=1e-12, atol=1e-12 * np.abs(J).max())
        assert (launches, copies) == (1, 1)
