"""LevelProblem.energy, the frame-at-a-time energy that sweep extrapolation judges its factors
by: the evaluation's energy and usable mask (to float64 round-off of the sum's order), under
the shared SH basis and the per-frame LED basis, with temporaries of one frame (tracemalloc)."""

import tracemalloc

import numpy as np
import pytest

from o3d_mvps.solver import problem as problem_module
from o3d_mvps.solver.lighting import LEDLight
from o3d_mvps.solver.problem import LevelProblem

from helpers import make_problem


def frames_problem(n_frames: int, light: str):
    """make_problem's level with ``n_frames`` frames, poses spread about frame 1's (the last one
    shifted so that part of the reference falls out of its view), and the SH
    or LED light model with lights for every frame."""
    problem, est = make_problem(n_frames)
    est.poses = est.poses.copy()
    for i in range(2, n_frames):  # each frame a little further along
        est.poses[i][:3, 3] *= 1.0 + 0.2 * i
    est.poses[-1][0, 3] += 0.08  # the last frame sees part of the reference out of its view
    if light == "led":
        problem = LevelProblem(problem.level, problem.tau, problem.lam, LEDLight(np.array([0.02, -0.01, 0.0])))
        est.lights = np.tile([0.1, 0.3], (n_frames, 1)) * (1.0 + 0.05 * np.arange(n_frames))[:, None]
    else:
        est.lights = np.tile(est.lights[:1], (n_frames, 1)) * (1.0 + 0.05 * np.arange(n_frames))[:, None]
    est.led_offset = None
    return problem, est


@pytest.mark.parametrize("frames_per_batch", [1, 3, 10])
@pytest.mark.parametrize("light", ["sh", "led"])
def test_frame_at_a_time_energy_is_the_evaluation_energy(light, frames_per_batch, monkeypatch):
    """In batches of 1 frame, of 3 (the last one short) and all 4 at once."""
    problem, est = frames_problem(4, light)
    monkeypatch.setattr(problem_module, "ENERGY_BATCH_PIXELS", frames_per_batch * problem.level.grid.size)
    ev = problem.evaluate(est)
    energy, usable = problem.energy(est)
    assert ev.data > 1e-3 and 0 < usable.sum() < usable.size  # a real residual, some pixels out of view
    assert energy == pytest.approx(ev.energy, rel=1e-12)
    assert np.array_equal(usable, ev.usable)
    est.albedo = est.albedo * 1.1  # a different estimate, a different energy, the same agreement
    assert problem.energy(est)[0] == pytest.approx(problem.evaluate(est).energy, rel=1e-12)
    assert abs(problem.energy(est)[0] - energy) > 1e-3 * energy



@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_led_s_one_pass_energy_is_the_batched_energy(dtype, monkeypatch):
    """On the host the LED's energy is a compiled pass over the pixels a frame (kernels.led_energy_frame,
    no frames x pixels arrays): the batched sums' energy (that of the stored residuals, float32 as
    in the solver or float64) and usable mask, to 1e-12 of the energy, for poses that put part of
    the reference out of a frame's view; and it moves with the estimate as they do."""
    problem, est = frames_problem(4, "led")
    problem = LevelProblem(problem.level, problem.tau, problem.lam, problem.light, residual_dtype=dtype)
    calls = []
    kernel = problem_module.log_products_sum
    monkeypatch.setattr(problem_module, "log_products_sum", lambda *args: calls.append(1) or kernel(*args))

    class Batched(LEDLight):  # not the LED itself: the frame-at-a-time sums
        pass

    batched = Batched(problem.light.offset)
    for scale in (1.0, 1.1):
        est.albedo = est.albedo * scale
        one_pass, usable = problem.energy(est)
        with monkeypatch.context() as patch:
            patch.setattr(problem, "light_model", lambda e: batched)
            energy, batched_usable = problem.energy(est)
        assert 0 < usable.sum() < usable.size and np.array_equal(usable, batched_usable)
        assert one_pass == pytest.approx(energy, rel=1e-12) and one_pass - problem.prior_energy(est.z) > 1e-3
        assert one_pass == pytest.approx(problem.evaluate(est).energy, rel=1e-12)
    assert len(calls) == 2


@pytest.mark.parametrize("light", ["sh", "led"])
def test_an_unscored_trial_refits_to_the_scored_evaluation(light):
    """evaluate(scored=False), the line search's trial before its albedo refit, has the scored
    evaluation's residuals, shading and prior bit for bit; reading its data energy raises; the
    refitted evaluation (reflectance.refit_albedo) is the same, energy included, either way."""
    from dataclasses import replace

    from o3d_mvps.solver.reflectance import refit_albedo

    problem, est = frames_problem(4, light)
    scored, unscored = problem.evaluate(est), problem.evaluate(est, scored=False)
    for name in ("residual", "shading", "usable"):
        assert np.array_equal(getattr(scored, name), getattr(unscored, name))
    assert unscored.prior == scored.prior
    with pytest.raises(RuntimeError, match="without its data energy"):
        unscored.energy
    one, other = replace(est), replace(est)
    refitted, refitted_unscored = refit_albedo(problem, one, scored), refit_albedo(problem, other, unscored)
    assert np.array_equal(one.albedo, other.albedo) and not np.array_equal(one.albedo, est.albedo)
    assert refitted_unscored.energy == refitted.energy < scored.energy


@pytest.mark.parametrize("light", ["sh", "led"])
def test_a_refit_without_its_energy_is_the_same_evaluation(light):
    """reflectance.refit_albedo(scored=False), a light round's refit (the lights' energy is read,
    not this one): the scored refit's albedo, residuals, shading and prior bit for bit; reading its
    data energy raises; re-evaluated, its energy is the scored refit's (to the 1e-13 of the
    refit's other grouping of the factors)."""
    from dataclasses import replace

    from o3d_mvps.solver.reflectance import refit_albedo

    problem, est = frames_problem(4, light)
    one, other = replace(est), replace(est)
    scored = refit_albedo(problem, one, problem.evaluate(one))
    unscored = refit_albedo(problem, other, problem.evaluate(other), scored=False)
    assert np.array_equal(one.albedo, other.albedo) and not np.array_equal(one.albedo, est.albedo)
    for name in ("residual", "shading", "usable"):
        assert np.array_equal(getattr(scored, name), getattr(unscored, name))
    assert unscored.prior == scored.prior
    with pytest.raises(RuntimeError, match="without its data energy"):
        unscored.energy
    assert problem.reevaluate(other, unscored).energy == pytest.approx(scored.energy, rel=1e-12)


def test_a_static_camera_s_energy_reuses_the_samples_of_its_evaluation(monkeypatch):
    """Identity poses (a static camera): after one evaluation the energy reads the frames' cached
    samples, warping no frame again, and agrees with the evaluation for another z."""
    problem, est = frames_problem(3, "sh")
    est.poses = np.tile(np.eye(4), (3, 1, 1))
    monkeypatch.setattr(problem_module, "ENERGY_BATCH_PIXELS", problem.level.grid.size)  # a frame a batch
    problem.evaluate(est)  # samples the frames once
    warped = []
    monkeypatch.setattr(problem, "_warp_sample", lambda *args: warped.append(args[0]))
    est.z = est.z * 1.01
    energy, usable = problem.energy(est)
    ev = problem.evaluate(est)
    assert warped == [] and energy == pytest.approx(ev.energy, rel=1e-12) and np.array_equal(usable, ev.usable)

def _peak_bytes(call) -> int:
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start = tracemalloc.get_traced_memory()[0]
        result = call()
        peak = tracemalloc.get_traced_memory()[1] - start
    finally:
        tracemalloc.stop()
    del result
    return peak


def test_frame_at_a_time_energy_holds_one_frame_of_temporaries(monkeypatch):
    """From 2 to 10 frames the evaluation's peak grows by at least 50 bytes a pixel and frame
    (warped colours, residuals, shading, LED basis), the energy's, one frame a batch, by at most 4
    (the usable mask, 1 byte, and slack)."""
    monkeypatch.setattr(problem_module, "ENERGY_BATCH_PIXELS", 1)
    peaks = {}
    for n in (2, 10):
        problem, est = frames_problem(n, "led")
        problem.energy(est), problem.evaluate(est)  # first calls (kernel dispatch) outside the measurement
        peaks[n] = (_peak_bytes(lambda: problem.energy(est)), _peak_bytes(lambda: problem.evaluate(est)))
    pixels = problem.level.grid.size
    energy_growth, evaluation_growth = ((peaks[10][k] - peaks[2][k]) / (8 * pixels) for k in (0, 1))
    assert evaluation_growth > 50, peaks
    assert energy_growth < 4, peaks
    assert peaks[10][0] < 0.3 * peaks[10][1], peaks
