"""The solver's shared pieces: the backtracking line search and the small ridge solve."""

import numpy as np

from o3d_mvps.solver.line_search import backtrack
from o3d_mvps.solver.linear import ridge_solve


def test_backtrack_takes_the_longest_step_that_does_not_raise_the_energy():
    tried = []

    def trial(t):  # energy (t - 0.3)^2 from 0.09 at t = 0; t = 1 is invalid
        tried.append(t)
        return None if t == 1.0 else (f"x{t}", (t - 0.3) ** 2)

    assert backtrack(trial, 0.09, max_halvings=5) == (0.5, "x0.5", 0.04000000000000001)
    assert tried == [1.0, 0.5]
    assert backtrack(lambda t: ("x", 1.0 + t), 1.0, max_halvings=3) is None  # every length raises it


def test_ridge_solve_solves_spd_systems_and_refuses_broken_ones():
    A = np.array([[4.0, 1.0], [1.0, 3.0]])
    np.testing.assert_allclose(ridge_solve(A, np.array([1.0, 2.0]), ridge=0.0), np.linalg.solve(A, [1.0, 2.0]))
    np.testing.assert_allclose(A @ ridge_solve(A, np.array([1.0, 2.0])), [1.0, 2.0], rtol=1e-8)
    assert ridge_solve(np.full((2, 2), np.nan), np.ones(2)) is None
    assert ridge_solve(np.zeros((2, 2)), np.ones(2)) is None  # singular, trace 0: no ridge helps
