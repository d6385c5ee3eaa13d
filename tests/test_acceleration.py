"""Anderson acceleration across sweeps (o3d_mvps/solver/acceleration.py) and the driver's
energy safeguard around it (driver._accelerated), on a small two-block alternating minimisation
whose plain sweeps creep (a contraction rate of 0.90-0.98 a sweep)."""

from types import SimpleNamespace

import numpy as np
import pytest

from o3d_mvps.model import se3
from o3d_mvps.solver import driver
from o3d_mvps.solver.acceleration import Anderson, partway
from o3d_mvps.solver.problem import Estimate

# E(z, l) = 1/2 |z - l|^2 + 1/2 sum delta (z - a)^2 + 1/2 sum delta (l - b)^2, z (N,), l the lights (n, k)
# flattened (N = n k). Alternating exact minimisation contracts coordinate j by 1 / (1 + delta_j)^2.
N_FRAMES, K = 6, 4
N = N_FRAMES * K
RNG = np.random.default_rng(3)
DELTA = np.linspace(0.01, 0.05, N)
A, B = 3.0 + RNG.normal(size=N), 3.0 + RNG.normal(size=N)  # depths stay positive (the driver checks)


def energy(est: Estimate) -> float:
    z, l = est.z, est.lights.ravel()
    return float(0.5 * np.sum((z - l) ** 2) + 0.5 * np.sum(DELTA * (z - A) ** 2) + 0.5 * np.sum(DELTA * (l - B) ** 2))


def minimum() -> float:
    # stationary point: (1 + d) z - l = d a, -z + (1 + d) l = d b, per coordinate
    det = (1 + DELTA) ** 2 - 1
    z = ((1 + DELTA) * DELTA * A + DELTA * B) / det
    l = (DELTA * A + (1 + DELTA) * DELTA * B) / det
    return energy(Estimate(z, np.zeros((N, 3)), l.reshape(N_FRAMES, K), np.tile(np.eye(4), (N_FRAMES, 1, 1))))


def sweep(est: Estimate) -> None:
    """One alternating sweep, in place: z given the lights, then the lights given z."""
    est.z = (est.lights.ravel() + DELTA * A) / (1 + DELTA)
    est.lights = ((est.z + DELTA * B) / (1 + DELTA)).reshape(N_FRAMES, K)


def start() -> Estimate:
    return Estimate(np.ones(N), np.zeros((N, 3)), np.ones((N_FRAMES, K)), np.tile(np.eye(4), (N_FRAMES, 1, 1)))


def copy(est: Estimate) -> Estimate:
    return Estimate(est.z.copy(), est.albedo.copy(), est.lights.copy(), est.poses.copy(), est.led_offset)


PROBLEM = SimpleNamespace(level=SimpleNamespace(prior=SimpleNamespace(clip=lambda z: z)),
                          energy=lambda est: (energy(est), None))


def solve(accelerate: bool, tolerance: float = 1e-8, cap: int = 2000) -> tuple[int, list]:
    """Sweeps until the energy is within ``tolerance`` (relative) of the minimum; with
    ``accelerate`` the driver's safeguarded Anderson step after each. Returns the sweep count and
    (plain sweep's energy, kept energy) per sweep."""
    est, accelerator, target, trace = start(), Anderson(3), minimum(), []
    for k in range(1, cap + 1):
        before = copy(est)
        sweep(est)
        plain = energy(est)
        kept = plain
        if accelerate:
            best, kept = driver._accelerated(PROBLEM, est, before, accelerator, plain, False, lambda e, t, u: e)
            if best is not None:
                est.z, est.albedo, est.lights, est.poses = best.z, best.albedo, best.lights, best.poses
                assert energy(est) == pytest.approx(kept, rel=1e-12)
        trace.append((plain, kept))
        if energy(est) - target <= tolerance * abs(target):
            return k, trace
    return cap, trace


def test_anderson_reaches_the_minimum_in_far_fewer_sweeps():
    plain, _ = solve(False)
    accelerated, trace = solve(True)
    # measured: 431 plain sweeps, 25 accelerated (to 1e-8 of the minimum)
    assert plain > 350
    assert accelerated <= 30, accelerated
    assert accelerated * 10 < plain


def test_the_safeguard_never_raises_the_energy():
    _, trace = solve(True)
    assert all(kept <= plain for plain, kept in trace)
    assert sum(kept < plain for plain, kept in trace) >= 15  # and it does act (measured: 24 of 25 sweeps)


def test_a_point_that_raises_the_energy_is_refused():
    est, accelerator = start(), Anderson(3)
    for _ in range(3):
        before = copy(est)
        sweep(est)
        plain = energy(est)
        raising = SimpleNamespace(level=PROBLEM.level, energy=lambda trial: (plain + 1e-9, None))
        best, kept = driver._accelerated(raising, est, before, accelerator, energy(est), False, lambda e, t, u: e)
        assert best is None and kept == plain
    assert accelerator.proposed == 2 and accelerator.kept == 0  # none from the first sweep (no history)


def test_partway_moves_poses_along_their_twist():
    T0 = np.tile(np.eye(4), (2, 1, 1))
    xi = np.array([0.01, -0.02, 0.03, 0.02, 0.01, -0.03])
    T1 = np.stack([se3.exp(xi), se3.exp(-xi)])
    est = Estimate(np.ones(3), np.zeros((3, 3)), np.zeros((2, 4)), T0, np.zeros(3))
    point = Estimate(3 * np.ones(3), np.ones((3, 3)), np.ones((2, 4)), T1, np.ones(3))
    half = partway(est, point, 0.5)
    np.testing.assert_allclose(half.z, 2.0)
    np.testing.assert_allclose(half.led_offset, 0.5)
    np.testing.assert_allclose(se3.log(half.poses[0]), 0.5 * xi, atol=1e-12)
    np.testing.assert_allclose(se3.log(half.poses[1]), -0.5 * xi, atol=1e-12)


def test_levels_accelerated_by_light_model_size_and_memory(monkeypatch):
    from o3d_mvps.solver import acceleration

    small, large = 22_284, 89_619  # the D415 render's level 1 and finest level
    assert acceleration.level_accelerator("led", small).memory == acceleration.ANDERSON_MEMORY == 3
    assert acceleration.level_accelerator("sh", small) is not None
    assert acceleration.level_accelerator("point", small) is None  # static captures: as before (NOT_ACCELERATED)
    assert acceleration.level_accelerator("led", acceleration.ANDERSON_MAX_PIXELS) is not None
    assert acceleration.level_accelerator("led", acceleration.ANDERSON_MAX_PIXELS + 1) is None
    assert acceleration.level_accelerator("led", large) is None  # its one kept point left the result worse
    assert acceleration.level_accelerator("led", 239_552) is None  # the 2 MP render's level 1: its points never kept
    monkeypatch.setattr(acceleration, "ANDERSON_MEMORY", 0)
    assert acceleration.level_accelerator("led", small) is None
