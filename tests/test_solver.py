"""End-to-end tests of refine() on small rendered captures: accuracy against the baselines,
energy descent, joint pose refinement, result files and the refine CLI."""

import inspect
import json
import os
import subprocess
import sys
import types

import numpy as np
import pytest

from o3d_mvps import RefineOptions, read_refinement, refine, write_capture
from o3d_mvps.capture import image_from_array
from o3d_mvps.cli import main
from o3d_mvps.errors import CaptureError, DeviceError
from o3d_mvps.metrics import evaluate
from o3d_mvps.solver.problem import Estimate, LevelProblem
from o3d_mvps.solver.pyramid import build_level
from o3d_mvps.synthetic import render_capture

from helpers import kicked_poses, perturb_and_refine_poses, with_led_offset_error

FAST = dict(progress=False, levels=4, max_iterations=4)


@pytest.fixture(scope="module")
def capture():
    """6 LED-lit frames; refine starts from an LED offset 1.5 cm off the rendered one."""
    return with_led_offset_error(render_capture("bunny", frames=6, scale_factor=4, size=(320, 240), light="led", seed=0))


@pytest.fixture(scope="module")
def result(capture):
    return refine(capture, RefineOptions(**FAST), initial_poses=capture.groundtruth.poses)


def test_refinement_accuracy_from_a_wrong_led_offset(capture, result):
    """Measured: normal MAE 5.06 deg, depth RMSE 1.91 mm (bicubic 27.6 deg, 3.42 mm); bounds
    +20 %: 6.0 deg and 2.3 mm."""
    ours = evaluate(result, capture.groundtruth)
    assert ours["mae_deg"] < 6.0, ours
    assert ours["rmse_mm"] < 2.3, ours


def test_refined_depth_stays_inside_the_sensor_envelope(capture, result):
    """Every refined depth lies within the least and greatest sensor depth around its pixel,
    widened by the default 2 % (o3d_mvps.solver.pyramid.depth_envelope)."""
    from o3d_mvps.solver.pyramid import depth_envelope

    lower, upper = depth_envelope(capture.depth_array(0).astype(np.float64), capture.color_size,
                                  RefineOptions().depth_envelope)
    depth, mask = result.depth_array(), result.mask_array()
    assert np.all(depth[mask] >= lower[mask] - 1e-6) and np.all(depth[mask] <= upper[mask] + 1e-6)
    assert np.ptp(depth[mask]) > 0.05  # the bounds are local: the object keeps its relief


def test_result_shapes_and_types(capture, result):
    H, W = capture.color_size
    assert result.depth_array().shape == (H, W)
    assert result.albedo_array().shape == (H, W, 3)
    n = result.normals_array()[result.mask_array()]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert result.poses.numpy().shape == (6, 4, 4) and result.lighting.numpy().shape == (6, 2)  # LED: ambient, intensity
    np.testing.assert_allclose(result.poses.numpy()[0], np.eye(4))
    # levels below joint_min_pixels (all of this small capture's) take the paper's two steps
    assert {"poses", "depth", "albedo_lighting", "total"} <= set(result.timings)
    assert "poses_depth" not in result.timings


@pytest.fixture(scope="module")
def joint_result(capture):
    """The same refinement with the joint pose-depth step on every level that refines poses."""
    return refine(capture, RefineOptions(**FAST, joint_min_pixels=0), initial_poses=capture.groundtruth.poses)


@pytest.mark.parametrize("name", ["result", "joint_result"])
def test_energy_never_increases_within_a_level(name, request):
    """Each level's energy after its sweeps falls below its start, and, from the sweep on which its
    smoothness weights are last re-weighed (driver.EVIDENCE_SWEEPS) on, never rises: before it
    the rows are of different energies (a re-weighing raised the finest level's energy of
    ``joint_result`` by 2 % at the start of its second sweep, 16.050 -> 16.366, which the sweep
    lowered to 16.053)."""
    from o3d_mvps.solver.driver import EVIDENCE_SWEEPS

    result = request.getfixturevalue(name)
    if name == "joint_result":
        assert result.timings["poses_depth"] > 0
    levels = {}
    for row in result.energy:
        levels.setdefault(row["level"], []).append(row["energy"])
    assert len(levels) == 4
    for energies in levels.values():
        e = np.array(energies)
        held = e[EVIDENCE_SWEEPS:]
        assert len(held) >= 2 and np.all(np.diff(held) <= 1e-5 * held[:-1]), energies
        assert e[-1] < e[0]


def test_pose_gauss_newton_recovers_perturbed_poses_under_an_exact_model():
    """With the SH-exact directional light and ground-truth depth, albedo and lighting, the pose
    step pulls perturbed poses back to where they warp the reference within a fraction of a
    pixel of the truth. (Rotation about the object's centre with the matching translation is
    nearly invisible at 320x240, so degrees and millimetres are the wrong yardstick here.)"""
    cap = render_capture("bunny", frames=6, scale_factor=4, size=(320, 240), light="directional", seed=0,
                         noise=False)
    gt = cap.groundtruth
    colors = [cap.color_array(i) for i in range(6)]
    masks = [cap.mask_array(i) for i in range(6)]
    level = build_level(0, colors, masks, gt.depth > 0, cap.color_K(), cap.depth_array(0).astype(float), 4)
    problem = LevelProblem(level, 1.0, 0.04)
    g = level.grid
    lights = np.array(gt.light["sh"])
    est = Estimate(g.gather(gt.depth).astype(float), g.gather(gt.albedo).astype(float), lights, gt.poses.copy())
    problem.update_visibility(est, occlusion_test=True, rel_tol=0.02)
    points = problem.points(est.z)
    normals, _ = problem.normals(est.z)
    before, after = perturb_and_refine_poses(problem, est, gt.poses, points, normals)
    assert np.median(before) > 1.0
    assert np.all(after < 0.5) and np.all(after < 0.4 * before)


def test_sweep_extrapolation_reaches_a_lower_energy(capture):
    """Same sweeps from perturbed poses: continuing each sweep's move ends the finest level lower
    (measured 17.19 against 17.98 with the LED's grid-mode rows, 0.956; without them 16.67
    against 17.64, 0.945; bound 0.97)."""
    start = kicked_poses(capture.groundtruth.poses)
    final = {}
    for extrapolate in (False, True):
        result = refine(capture, RefineOptions(**FAST, extrapolate=extrapolate), initial_poses=start,
                        pose_trust=False)
        final[extrapolate] = [row["energy"] for row in result.energy if row["level"] == 0][-1]
    assert final[True] < 0.97 * final[False], final


def test_the_sh_light_model_refines_from_perturbed_poses(capture):
    """The paper's SH light end to end, from kicked poses (where sweep extrapolation gets taken:
    it once crashed looking for an LED offset the SH model lacks)."""
    result = refine(capture, RefineOptions(**FAST, light_model="sh"), initial_poses=kicked_poses(capture.groundtruth.poses),
                    pose_trust=False)
    assert result.lighting.numpy().shape == (capture.n_frames, 4)
    assert result.info["light_model"]["model"] == "sh"
    ours = evaluate(result, capture.groundtruth)
    assert ours["mae_deg"] < 16.0, ours  # measured 13.1 deg (bicubic 27.6 deg); bound +20 %


def test_two_stage_mode_keeps_the_initial_poses(capture):
    start = capture.groundtruth.poses.copy()
    start[1:, :3, 3] += 0.003
    fixed = refine(capture, RefineOptions(**FAST, refine_poses=False), initial_poses=start).poses.numpy()
    np.testing.assert_allclose(fixed, start)


def test_single_frame_shading_refinement_runs(capture):
    single = refine(capture, RefineOptions(**FAST, frames=1))
    assert single.poses.numpy().shape == (1, 4, 4)
    assert np.isfinite(single.depth_array()).all()


def test_save_and_read_round_trip(tmp_path, result):
    result.save(tmp_path / "r")
    back = read_refinement(tmp_path / "r")
    np.testing.assert_array_equal(back.depth_array(), result.depth_array())
    np.testing.assert_array_equal(back.albedo_array(), result.albedo_array())
    np.testing.assert_array_equal(back.normals_array(), result.normals_array())
    np.testing.assert_array_equal(back.mask_array(), result.mask_array())
    np.testing.assert_allclose(back.poses.numpy(), result.poses.numpy())
    np.testing.assert_allclose(back.lighting.numpy(), result.lighting.numpy())
    np.testing.assert_allclose(back.intrinsic_matrix(), result.intrinsic_matrix())
    assert back.energy == result.energy
    with pytest.raises(FileExistsError, match="overwrite=True"):
        result.save(tmp_path / "r")


def test_bad_input_errors(capture):
    with pytest.raises(DeviceError, match="'CUDA:0'"):  # what is missing: tests/test_saved_problem.py
        refine(capture, RefineOptions(**FAST), device="CUDA:0")
    with pytest.raises(ValueError, match=r"initial_poses must be \(6, 4, 4\)"):
        refine(capture, RefineOptions(**FAST), initial_poses=np.eye(4))
    with pytest.raises(ValueError, match="frames=9"):
        refine(capture, RefineOptions(**FAST, frames=9))
    with pytest.raises(ValueError, match=r"tau must be a number in \(0, inf\), got 0"):
        RefineOptions(tau=0)
    empty = capture.select(range(6))
    empty.masks = [image_from_array(np.zeros(capture.color_size + (1,), np.uint8))] + empty.masks[1:]
    with pytest.raises(CaptureError, match="reference mask is empty"):
        refine(empty, RefineOptions(**FAST))


def test_refine_cli_writes_results_and_accuracy(tmp_path, capture):
    write_capture(capture.select(range(3)), tmp_path / "cap")
    code = main(["--quiet", "refine", str(tmp_path / "cap"), str(tmp_path / "out"), "--levels", "3",
                 "--iterations", "2"])
    assert code == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    methods = {row["method"]: row for row in report["accuracy"]}
    assert set(methods) == {"ours", "bicubic", "guided"}
    assert all(np.isfinite(row["mae_deg"]) for row in methods.values())
    assert (tmp_path / "out" / "depth_mm.png").is_file() and (tmp_path / "out" / "albedo.png").is_file()
    # an existing output is never overwritten without --overwrite
    before = (tmp_path / "out" / "report.json").read_bytes()
    assert main(["--quiet", "refine", str(tmp_path / "cap"), str(tmp_path / "out"), "--levels", "2"]) == 1
    assert (tmp_path / "out" / "report.json").read_bytes() == before


def test_refined_scan_exports_a_textured_mesh_and_a_watertight_solid(tmp_path, result):
    import trimesh

    from o3d_mvps.export import printable_solid, write_mesh, write_stl

    mesh = result.to_mesh()
    assert mesh.triangle.indices.shape[0] > 1000
    assert "albedo" in mesh.material.texture_maps
    write_mesh(mesh, tmp_path / "scan.glb")
    solid = printable_solid(result, size_mm=80.0, base_mm=3.0, pieces="all")
    write_stl(solid, tmp_path / "scan.stl")
    back = trimesh.load(tmp_path / "scan.stl")
    assert back.is_watertight and back.is_volume
    assert max(back.extents) == pytest.approx(80.0, rel=1e-5)


def test_coarse_to_fine_runs_coarsest_first_and_passes_skipped_levels_on():
    """Levels 3 .. 0 in turn; a level returning None (too small) hands on what it got; nothing
    solved at all is an error."""
    from o3d_mvps.errors import CaptureError
    from o3d_mvps.solver.driver import coarse_to_fine

    calls = []

    def solve_level(index, carried):
        calls.append((index, carried))
        return None if index == 2 else f"level {index}"

    assert coarse_to_fine(4, solve_level) == "level 0"
    assert calls == [(3, None), (2, "level 3"), (1, "level 3"), (0, "level 1")]
    with pytest.raises(CaptureError, match="no pyramid level"):
        coarse_to_fine(2, lambda index, carried: None)


def _sweeps_run(energies, level_index=0, tolerance=1e-3, settled=False, data=None):
    """How many sweeps a level runs whose energy after each sweep is ``energies`` (the first: the
    level's start) and its data term ``data`` (the same length; None: not told), as
    driver._sweeps decides after each sweep (driver._stalled)."""
    from o3d_mvps.solver.driver import _stalled

    drop = None
    for iteration in range(1, len(energies)):
        drop, last_drop = (energies[iteration - 1] - energies[iteration]) / energies[iteration - 1], drop
        data_drop = None if data is None else (data[iteration - 1] - data[iteration]) / data[iteration - 1]
        if _stalled(level_index, iteration, settled, last_drop, drop, tolerance, data_drop):
            return iteration
    return len(energies) - 1


def _energies(drops, start=100.0):
    """A level's energies: ``start``, then each sweep's lowered by its relative drop in ``drops``."""
    energies = [start]
    for drop in drops:
        energies.append(energies[-1] * (1 - drop))
    return energies


# the finest level's energies, sweep by sweep, of the saved 2 MP and D415 problems (20 frames);
# on 2 MP the smoothness weights are re-weighed before sweeps 2 and 3 (EVIDENCE_SWEEPS), hence the rise
MP2_FINEST = [46246.0, 6278.653, 49297.92, 15004.61, 12755.66, 12603.38, 12602.13]
D415_FINEST = [484.5679, 412.6804, 404.3845, 402.0523, 400.9809, 400.5392, 400.2650]


# the finest level of the 2 MP and D415 (seed 1) benchmark captures of 2026-11-27 (LED, 20 frames):
# the energy at the level's start and after each sweep, and its data term (benchmarks/sweeps.py);
# the energies' starts are the first sweeps' drops (0.80, 0.15) taken back, the data terms' are
# placeholders (no rule reads the first sweep's data drop)
MP2_FINEST_2 = [344720.0, 68943.873, 56901.738, 57715.001, 53442.731, 52442.549, 52376.883]
MP2_FINEST_2_DATA = [3700.0, 3583.407, 3554.607, 3545.81, 3542.503, 3540.985, 3538.235]
D415_FINEST_2 = [474.5, 403.318, 394.52, 391.934, 390.583, 389.968, 389.61]
D415_FINEST_2_DATA = [160.0, 143.165, 134.272, 131.43, 130.143, 129.429, 129.014]


def test_a_level_stops_once_its_data_term_stalls_with_the_weights_held():
    """At 2 MP the priors' energy still fell 7.4 % and 1.9 % in the finest level's sweeps 5 and 6,
    its data term by 9.3e-4 in sweep 4: the level stops there (the normals 1.3824 deg, 1.3835
    after six); D415's data term still falls 2e-3 to 1e-2 a sweep (its normals 1.4 % a sweep) and
    it runs its six; a stalled data term counts only on the finest level after the
    EVIDENCE_SWEEPS (3), weights held from the start or not, and a rising one never."""
    assert _sweeps_run(MP2_FINEST_2) == 6
    assert _sweeps_run(MP2_FINEST_2, data=MP2_FINEST_2_DATA) == 4
    assert _sweeps_run(D415_FINEST_2, data=D415_FINEST_2_DATA) == _sweeps_run(D415_FINEST_2) == 6
    falling = _energies([0.1, 0.05, 0.04, 0.03, 0.02])
    stalled = [100.0, 99.99, 99.98, 99.97, 99.96, 99.95]
    assert _sweeps_run(falling, data=stalled) == 4  # the weights held after EVIDENCE_SWEEPS (3)
    assert _sweeps_run(falling, settled=True, data=[100.0, 99.0, 98.99, 98.98, 98.97, 98.96]) == 4  # not before
    assert _sweeps_run(falling, level_index=1, data=stalled) == 5  # a coarser level: the energy alone
    assert _sweeps_run(falling, data=[100.0, 90.0, 85.0, 82.0, 80.0, 79.0]) == 5
    assert _sweeps_run(falling, data=[100.0, 99.0, 99.5, 100.0, 100.5, 101.0]) == 5  # rising


def test_the_sweeps_hand_the_data_term_s_drop_to_the_stopping_rule(capture, monkeypatch):
    """driver._sweeps gives _stalled each sweep's relative drop of the data term, the end of the
    sweep before against this one's (a re-weighing does not change the data term), as the
    sweep ends it (after the extrapolation)."""
    from o3d_mvps.solver import driver

    ends, drops = [], []
    extrapolate, stalled = driver._extrapolate, driver._stalled

    def recorded_extrapolate(problem, *args, **kwargs):
        ev = extrapolate(problem, *args, **kwargs)
        ends.append((problem.level.index, ev.data))
        return ev

    def recorded_stalled(level_index, iteration, *args):
        drops.append((level_index, iteration, args[-1]))
        return stalled(level_index, iteration, *args)

    monkeypatch.setattr(driver, "_extrapolate", recorded_extrapolate)
    monkeypatch.setattr(driver, "_stalled", recorded_stalled)
    refine(capture, RefineOptions(**FAST), initial_poses=capture.groundtruth.poses)
    assert len(ends) == len(drops) >= 8
    checked = 0
    for k, (level, iteration, data_drop) in enumerate(drops):
        assert ends[k][0] == level and np.isfinite(data_drop)
        if iteration > 1:
            before = ends[k - 1][1]
            assert data_drop == pytest.approx((before - ends[k][1]) / before, rel=1e-9, abs=1e-15)
            checked += 1
    assert checked >= 4


def test_albedo_and_lighting_rounds_settle_the_light_in_fewer_sweeps(monkeypatch):
    """A sweep refits the albedo and the lights in turn until the data term settles
    (driver.LIGHT_ROUNDS): the LED ambient's slow trade with the albedo is no longer left to the
    sweeps. The 320x240 LED bunny (10 frames, true poses): one round a sweep took 28 sweeps to
    3.785 deg, the rounds 19 to 3.734 (D415: 33 -> 26 sweeps, 1.177 -> 1.082 deg). Asserted: a
    quarter fewer sweeps at least, and normals no worse."""
    from o3d_mvps.solver import driver

    capture = render_capture("bunny", frames=10, scale_factor=2, size=(320, 240), seed=0, progress=False)
    poses = np.asarray(capture.groundtruth.poses)

    def run():
        result = refine(capture, RefineOptions(progress=False), initial_poses=poses)
        sweeps = sum(1 for row in result.energy if row["iteration"] > 0)
        return evaluate(result, capture)["mae_deg"], sweeps, result.info["light_rounds"]

    mae, sweeps, rounds = run()
    monkeypatch.setattr(driver, "LIGHT_ROUNDS", 1)
    one_mae, one_sweeps, one_rounds = run()
    assert max(rounds) > 1 and max(one_rounds) == 1
    assert sweeps <= 0.75 * one_sweeps, (sweeps, one_sweeps)
    assert mae <= one_mae, (mae, one_mae)


def test_the_finest_level_holds_the_poses_a_coarser_level_settled(capture, joint_result, monkeypatch):
    """Where a coarser level of at least driver.FINEST_HOLD_MIN_PIXELS object pixels refined the
    poses by joint steps, the finest level keeps them bit for bit and takes depth steps with the
    joint step's parallax rows and CG tolerance (D415 and 2 MP: a quarter and a seventh less
    time there, normals within 0.6 %). This capture's level 1 (about 1 200 pixels) is far under
    the threshold, so joint_result's finest level still refines them; lowered under it, it
    holds them, but not under room light. Measured here: normals 4.51 deg held against 4.43 refined
    (this level 1 settles the poses less than a D415's 22 000 pixels do); bound +5 %. The held
    level's depth steps take the plain-aggregation hierarchy, and its extrapolations are guarded
    and leave the data term no higher (this capture's did so without the guard too: the guard
    itself is tested below)."""
    from o3d_mvps.solver import driver

    assert [kind for _, _, kind in joint_result.info["pose_steps"]][-2:] == ["joint", "joint"]
    level_poses, depth_steps, extrapolations = {}, [], []
    sweeps, update_depth, extrapolate = driver._sweeps, driver.update_depth, driver._extrapolate

    def recorded_sweeps(problem, est, *args, **kwargs):
        rows = sweeps(problem, est, *args, **kwargs)
        level_poses[problem.level.index] = est.poses.copy()
        return rows

    def recorded_depth(problem, est, ev, **kwargs):
        depth_steps.append((problem.level.index, kwargs["parallax"], kwargs["rtol"], kwargs["plain"]))
        return update_depth(problem, est, ev, **kwargs)

    def recorded_extrapolation(problem, est, ev, *args, **kwargs):
        data = ev.data
        kept = extrapolate(problem, est, ev, *args, **kwargs)
        extrapolations.append((problem.level.index, kwargs.get("keep_data", False), data, kept.data))
        return kept

    monkeypatch.setattr(driver, "_sweeps", recorded_sweeps)
    monkeypatch.setattr(driver, "update_depth", recorded_depth)
    monkeypatch.setattr(driver, "_extrapolate", recorded_extrapolation)
    monkeypatch.setattr(driver, "FINEST_HOLD_MIN_PIXELS", 500)
    options = RefineOptions(**FAST, joint_min_pixels=0)
    held = refine(capture, options, initial_poses=capture.groundtruth.poses)
    steps = held.info["pose_steps"]
    assert [(level, kind) for level, _, kind in steps[-2:]] == [(1, "joint"), (0, "held")]
    assert steps[-2][1] >= 500  # level 1's object pixels: at the lowered threshold
    np.testing.assert_array_equal(level_poses[0], level_poses[1])
    np.testing.assert_array_equal(held.poses.numpy(), level_poses[1])
    finest = [step for step in depth_steps if step[0] == 0]
    assert finest and all(parallax and rtol == options.joint_cg_tolerance and plain
                          for _, parallax, rtol, plain in finest)
    held_extrapolations = [step for step in extrapolations if step[0] == 0]
    assert held_extrapolations and all(keep and after <= before for _, keep, before, after in held_extrapolations)
    assert not any(keep for level, keep, _, _ in extrapolations if level > 0)
    assert evaluate(held, capture)["mae_deg"] < 1.05 * evaluate(joint_result, capture)["mae_deg"]
    # under a light fixed in the world the poses rest on the parallax: the finest level refines them
    room = refine(capture, RefineOptions(**FAST, joint_min_pixels=0, light_model="room"),
                  initial_poses=capture.groundtruth.poses)
    assert room.info["pose_steps"][-1][2] == "joint" and room.info["pose_steps"][-2][2] == "joint"


def test_a_held_levels_extrapolation_keeps_no_factor_that_raises_the_data_term():
    """driver._extrapolate on a two-term energy (data (z - 1)^2, prior 10 (z - 2)^2 per pixel)
    whose sweep moved z from 1.10 to 1.15, towards the prior: the factors 1, 2 and 4 lower the
    energy while raising the data term, so the extrapolation keeps factor 4 (z 1.35), but with
    keep_data (a held finest level) none; a sweep that lowered both (2.50 -> 2.45) keeps factor 4."""
    from o3d_mvps.solver import driver

    class Ev:
        def __init__(self, problem, z):
            self.data, self.prior = problem.data_energy(z), problem.prior_energy(z)
            self.energy, self.usable = self.data + self.prior, np.ones((1, z.size), bool)

        def release(self):
            pass

    class TwoTerms:  # the parts of a LevelProblem that _extrapolate reads on the host
        level = types.SimpleNamespace(prior=types.SimpleNamespace(clip=lambda z: z))

        def data_energy(self, z):
            return float(np.sum((z - 1.0) ** 2))

        def prior_energy(self, z):
            return float(10.0 * np.sum((z - 2.0) ** 2))

        def energy(self, est, prior=None):
            prior = self.prior_energy(est.z) if prior is None else prior
            return self.data_energy(est.z) + prior, np.ones((1, est.z.size), bool)

        def evaluate(self, est):
            return Ev(self, est.z)

    def estimate(z):  # 4 pixels, 2 frames
        return Estimate(np.full(4, z), np.ones((4, 3)), np.zeros((2, 4)), np.stack([np.eye(4)] * 2), None)

    def extrapolated(z_before, z_after, keep_data):
        problem = TwoTerms()
        est = estimate(z_after)
        ev = driver._extrapolate(problem, est, Ev(problem, est.z), estimate(z_before), keep_data=keep_data)
        return est.z[0], ev.data

    assert extrapolated(1.10, 1.15, keep_data=False) == pytest.approx((1.35, 4 * 0.35**2))
    assert extrapolated(1.10, 1.15, keep_data=True) == pytest.approx((1.15, 4 * 0.15**2))
    assert extrapolated(2.50, 2.45, keep_data=True)[0] == pytest.approx(2.25)  # both terms fall: factor 4 kept


def test_finest_level_stops_once_its_energy_stalls_not_while_it_still_falls():
    """2 MP's finest drops 0.150 then 0.0119 (ratio 0.079): its sixth sweep, predicted 9.5e-4
    (actual 9.9e-5), is not run; D415's still falls slowly (ratios 0.46, 0.41) and runs until a
    drop is within the tolerance (6.9e-4 at the sixth); a coarser level, or one whose last two
    drops straddle the re-weighing, only stops at the tolerance; drops halving each sweep run on."""
    assert _sweeps_run(MP2_FINEST) == 5
    assert _sweeps_run(D415_FINEST) == 6
    assert _sweeps_run(MP2_FINEST, level_index=1) == 6
    assert _sweeps_run(_energies([0.3, 0.2, 0.1, 0.05, 0.025, 0.0125, 0.006, 0.003, 0.0015, 0.0008])) == 10
    straddling = _energies([0.1, 0.05, 0.004, 0.003, 0.002, 0.0009])  # ratio 0.08 at the third
    assert _sweeps_run(straddling) == 6  # the second's drop was of the energy before the re-weighing
    assert _sweeps_run(straddling, settled=True) == 3  # weights held from the start: predicted 3e-4


def _resident_mb() -> float:
    """This process's resident size, MB, counted exactly from its page tables (smaps_rollup).
    /proc/self/status's VmRSS is not: the kernel sums per-CPU counters lazily (proc(5)), and in
    CI it once showed 68 of 96 MB just unmapped."""
    with open("/proc/self/smaps_rollup") as rollup:
        return next(int(line.split()[1]) / 1024 for line in rollup if line.startswith("Rss:"))


@pytest.mark.parametrize("static, pixels, megabytes", [(True, "None", 4), (False, "MMAP_MIN_PIXELS - 1", 9)])
def test_return_freed_arrays_gives_freed_megabyte_arrays_back_to_the_system(static, pixels, megabytes):
    """After return_freed_arrays (glibc), arrays over its threshold (1 MB for a static camera's
    frames of no size given, 8 MB for a moving camera's under 1.5 MP) freed between live ones leave the resident size
    (with glibc's default, once a 16 MB block has been freed, they stay in the heap, resident);
    24 of them freed must lower it by at least 75 % of their size (a margin for the
    interpreter's own allocations; alone it measures 100 %).

    Run in a fresh interpreter, as the command line does: glibc carves a block from free heap
    space whatever the threshold, and late in the suite the test process's heap held enough
    that only 64 of 96 MB came back (CI, 2026-11-27; 0 of 96 with 384 MB freed beforehand)."""
    script = inspect.getsource(_resident_mb) + f"""
import numpy as np
from o3d_mvps.solver.allocator import MMAP_MIN_PIXELS, return_freed_arrays

assert return_freed_arrays(MMAP_MIN_PIXELS - 1) and return_freed_arrays({pixels}, static={static})
big = np.ones(2 << 20)  # 16 MB freed: glibc's default would raise its threshold to it
del big
arrays = [np.ones({megabytes} << 17) for _ in range(48)]  # 48 arrays, touched
before = _resident_mb()
del arrays[::2]
print(before - _resident_mb())
"""
    env = {key: value for key, value in os.environ.items()
           if not key.startswith("MALLOC_") and key != "GLIBC_TUNABLES"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=60)
    assert done.returncode == 0, done.stderr
    assert float(done.stdout) >= 0.75 * 24 * megabytes


@pytest.mark.parametrize("frames, ends, at_start", [
    ("MMAP_MIN_PIXELS - 1, static=True", "return_freed_arrays(MMAP_MIN_PIXELS - 1)", False),
    ("MMAP_MIN_PIXELS, static=True", "map_large_blocks()", False),
    ("MMAP_MIN_PIXELS", "map_large_blocks()", False),
    ("MMAP_MIN_PIXELS - 1, static=True", "map_large_blocks()", True),
])
def test_heap_only_frames_keep_freed_arrays_in_the_heap_until_the_mode_ends(frames, ends, at_start):
    """For a static camera's frames of any size and a moving camera's from MMAP_MIN_PIXELS on,
    return_freed_arrays takes every block from glibc's heap and keeps its top (allocator.heap_only):
    a freed 64 MB array (over glibc's 32 MB mmap ceiling) stays resident, to be reused without its
    pages faulted and zeroed anew; map_large_blocks (the solve's end), or a call for frames that
    do not take the mode, maps large blocks again: a freed 128 MB one (more than the heap's free
    space, which glibc would carve it from whatever the settings) leaves the resident size (by at
    least 75 % of its size). MALLOC_TRIM_THRESHOLD_ set after the process started (as Dask's nanny
    does in its own process) did not reach glibc and changes nothing; set when it started
    (``at_start``), it is the user's: the heap-only mode is not taken and the freed array leaves at
    once. Run in a fresh interpreter (as the test above)."""
    script = inspect.getsource(_resident_mb) + f"""
import os
import numpy as np
from o3d_mvps.solver.allocator import MMAP_MIN_PIXELS, map_large_blocks, return_freed_arrays

def freed_mb(megabytes):
    big = np.ones(megabytes << 17)  # touched
    before = _resident_mb()
    del big
    return before - _resident_mb()

os.environ["MALLOC_TRIM_THRESHOLD_"] = "65536"
assert return_freed_arrays({frames})
small = freed_mb(64)  # MB it gave back
assert {ends}
print(small, freed_mb(128))
"""
    env = {key: value for key, value in os.environ.items()
           if not key.startswith("MALLOC_") and key != "GLIBC_TUNABLES"}
    if at_start:
        env["MALLOC_TRIM_THRESHOLD_"] = "65536"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=60)
    assert done.returncode == 0, done.stderr
    small, large = map(float, done.stdout.split())  # MB each freed array gave back
    if at_start:
        assert small >= 0.75 * 64, small
    else:  # kept in the heap
        assert small < 16.0, small
    assert large >= 0.75 * 128, large


def test_a_large_moving_captures_heap_only_mode_ends_with_a_failed_refine(capture, monkeypatch):
    """refine sets the malloc policy before the registration: for a moving camera's frames from
    MMAP_MIN_PIXELS on (here lowered to the 320x240 render's size) every block comes from the heap
    (allocator.MOVING_HEAP_ONLY) through the registration, and the mode ends however the refine
    does: here with the input checks' CaptureError."""
    from o3d_mvps import solving
    from o3d_mvps.solver import allocator

    seen = []

    def failing(*args, **kwargs):
        seen.append(allocator._heap_only[0])
        raise CaptureError("checked")

    monkeypatch.setattr(allocator, "MMAP_MIN_PIXELS", 320 * 240)
    monkeypatch.setattr(solving, "problem_from_capture", failing)
    with pytest.raises(CaptureError, match="checked"):
        refine(capture, RefineOptions(**FAST))
    users = allocator._user_malloc_settings()  # the mode is not taken against the user's settings
    taken = allocator._libc_function("mallopt") is not None and not users & {"mmap_threshold", "mmap_max", "trim_threshold"}
    assert seen == [allocator.MOVING_MMAP_THRESHOLD if taken else None], seen
    assert allocator._heap_only[0] is None


def test_kernel_threads_follow_the_level_size_and_are_restored(capture, monkeypatch):
    """Each level sets its kernels' thread count by its object pixels (model.parallel.kernel_threads);
    the caller's count is back after the solve. With 2000 pixels a thread, the 320x240 render's
    finest level (about 5 000 object pixels) gets both threads, its coarser levels one."""
    import numba

    from o3d_mvps.model import parallel
    from o3d_mvps.solver import driver

    n = min(2, numba.config.NUMBA_NUM_THREADS)  # 2 on any machine of 2 cores or more
    monkeypatch.setattr(parallel, "PIXELS_PER_THREAD", 2000)
    counts = []

    def recording(threads):
        counts.append(threads)
        return parallel.set_kernel_threads(threads)

    monkeypatch.setattr(driver, "set_kernel_threads", recording)
    before = numba.get_num_threads()
    numba.set_num_threads(n)
    try:
        refine(capture, RefineOptions(**{**FAST, "max_iterations": 1}), initial_poses=capture.groundtruth.poses)
        assert numba.get_num_threads() == n
    finally:
        numba.set_num_threads(before)
    per_level, restored = counts[0::2], counts[1::2]
    assert per_level[-1] == n and per_level[0] == 1 and restored == [n] * len(restored), counts


def test_trim_heap_gives_freed_heap_arrays_back_to_the_system():
    """Arrays below the mmap threshold (here 256 kB, under return_freed_arrays' 1 MB) freed
    between live ones stay resident in glibc's heap; trim_heap (malloc_trim) returns their pages:
    80 MB freed must lower the resident size by at least 60 MB (a 25 % margin for other threads
    of the test process), and the live arrays keep their values."""
    from o3d_mvps.solver.allocator import return_freed_arrays, trim_heap

    assert return_freed_arrays()
    arrays = [np.full(1 << 15, float(k)) for k in range(640)]  # 640 x 256 kB from the heap, touched
    del arrays[::2]
    before = _resident_mb()
    assert trim_heap()
    assert before - _resident_mb() >= 60.0
    assert all(np.all(a == 2 * k + 1) for k, a in enumerate(arrays))


def test_frames_read_from_files_solve_as_their_decoded_floats(capture, tmp_path):
    """A capture read from PNGs keeps its colour as uint8 codes (a quarter of float32's memory);
    its solver input holds them coded (the kernels decode per sample) and solves to the very
    depth, albedo, poses, lighting and energies of the same frames decoded to float32."""
    from dataclasses import replace

    from o3d_mvps.capture import read_capture
    from o3d_mvps.colour import CodedColours
    from o3d_mvps.solver.driver import solve
    from o3d_mvps.solving import problem_from_capture

    write_capture(capture, tmp_path / "capture")
    read = read_capture(tmp_path / "capture")
    problem, _ = problem_from_capture(read, RefineOptions(**FAST), initial_poses=capture.groundtruth.poses)
    assert isinstance(problem.colors, CodedColours) and problem.colors.codes[0].dtype == np.uint8
    assert problem.colors.nbytes < 0.3 * problem.float_colors().nbytes
    coded = solve(problem)
    decoded = solve(replace(problem, colors=list(problem.float_colors())))
    for name in ("depth", "albedo", "poses", "lighting"):
        np.testing.assert_array_equal(getattr(coded, name), getattr(decoded, name), err_msg=name)
    assert [row["energy"] for row in coded.energy] == [row["energy"] for row in decoded.energy]
    assert len(coded.energy) > 4


@pytest.mark.parametrize("coded", [True, False])
def test_coarse_images_are_the_levels_own(coded):
    """Each frame decoded once for every coarse level (pyramid.coarse_images): every coarse level,
    built from them or from the colours, holds each frame decoded (colour.codes_to_linear) and
    area-averaged to its size, bit for bit; the full size is not made again (the finest level
    reads the colours themselves); a wrong level's images are refused."""
    from o3d_mvps.colour import CodedColours, codes_to_linear
    from o3d_mvps.model.resampling import resize
    from o3d_mvps.solver.pyramid import coarse_images, level_size

    rng = np.random.default_rng(3)
    codes = [rng.integers(0, 256, size=(96, 128, 3), dtype=np.uint8) for _ in range(3)]
    colors = CodedColours.from_codes(codes) if coded else [c.astype(np.float32) / 255 for c in codes]
    ref_mask = np.zeros((96, 128), bool)
    ref_mask[20:80, 30:110] = True
    K = np.array([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]])
    z0 = np.full((24, 32), 0.5)
    sizes = [level_size(ref_mask.shape, index) for index in range(4)]
    found = coarse_images(colors, sizes)
    assert list(found) == sizes[1:]
    decoded = [codes_to_linear(c) for c in codes] if coded else colors
    for index in range(1, 4):
        expected = [resize(frame, sizes[index]).astype(np.float32) for frame in decoded]
        own = build_level(index, colors, [None] * 3, ref_mask, K, z0, 4)
        given = build_level(index, colors, [None] * 3, ref_mask, K, z0, 4, images=found[sizes[index]])
        for level in (own, given):
            assert all(a.dtype == np.float32 and np.array_equal(a, b) for a, b in zip(level.images, expected))
    finest = build_level(0, colors, [None] * 3, ref_mask, K, z0, 4)
    assert all(a is b for a, b in zip(finest.images, colors)) if not coded else \
        all(a[0] is c for a, c in zip(finest.images, codes))
    with pytest.raises(ValueError, match="images must be"):
        build_level(1, colors, [None] * 3, ref_mask, K, z0, 4, images=found[sizes[2]])
