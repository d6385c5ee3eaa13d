"""benchmarks.sweeps: the per-sweep trace of a solve (issue #31, stopping rules)."""

import numpy as np
import pytest

from benchmarks import sweeps
from o3d_mvps.capture import write_capture
from o3d_mvps.solver import driver
from o3d_mvps.solver.options import RefineOptions
from o3d_mvps.solver.problem_input import write_problem
from o3d_mvps.solving import problem_from_capture
from o3d_mvps.synthetic import render_capture


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sweeps")
    capture = render_capture("bunny", frames=3, scale_factor=2, size=(160, 120), seed=0, progress=False)
    write_capture(capture, folder / "capture")
    problem, _ = problem_from_capture(capture, RefineOptions(frames=3))
    write_problem(problem, folder / "problem.npz")
    return folder / "problem.npz", folder / "capture"


def test_trace_ends_at_the_solve_result_and_caps_apply(saved):
    problem, capture = saved
    traced = sweeps.run(problem, capture)
    # the finest level's "if stopped here" path (sensor tie, upsampling, metrics) is the solver's own:
    # its last sweep scores what the solve returned, to rounding
    finest = [r for r in traced["sweeps"] if r["level"] == 0]
    assert finest[-1]["mae_deg"] == pytest.approx(traced["accuracy"]["mae_deg"], rel=1e-6)
    assert finest[-1]["rmse_mm"] == pytest.approx(traced["accuracy"]["rmse_mm"], rel=1e-6)
    assert len(traced["sweeps"]) == traced["n_sweeps"] == sum(r["sweeps"] for r in traced["levels"])
    assert all(r["cpu"] > 0 and r["dz_mm"] >= 0 for r in traced["sweeps"])
    # coarser levels are scored a second time without their grid modes, the finest level once
    assert all(("mae_smooth_deg" in r) == (r["level"] > 0) for r in traced["sweeps"])
    # the stage times are the solver's own: the hooks' accuracy evaluations are not in them
    assert all(0 < sum(r["steps"].values()) <= r["cpu"] * 1.05 for r in traced["levels"])
    capped = sweeps.run(problem, capture, caps=[2] * 5, trace=False)
    assert [r["sweeps"] for r in capped["levels"]] == [min(2, r["sweeps"]) for r in traced["levels"]]
    assert driver._sweeps.__module__ == driver.__name__  # the hooks were taken out again


def test_grid_modes_are_taken_out_and_a_smooth_surface_kept():
    """without_grid_modes: the depth that alternates pixel to pixel (unseen by central
    differences) goes, to 1 % of it; a bowl and the pixels outside the mask stay."""
    v, u = np.mgrid[0:60, 0:80].astype(float)
    bowl = 0.5 + 1e-5 * ((u - 40) ** 2 + (v - 30) ** 2)  # second differences 2e-5 m, 0.5 m away
    mask = np.ones(bowl.shape, bool)
    mask[:, :3] = False
    mode = 5e-6 * ((-1.0) ** u + (-1.0) ** v)  # 5 micrometres along rows and along columns
    inner = (slice(2, -2), slice(5, -2))
    out = sweeps.without_grid_modes(bowl + mode, mask)
    assert np.abs(out - bowl)[inner].max() < 0.01 * 5e-6
    assert np.abs(sweeps.without_grid_modes(bowl, mask) - bowl)[inner].max() < 1e-12
    assert np.array_equal(out[~mask], (bowl + mode)[~mask])
