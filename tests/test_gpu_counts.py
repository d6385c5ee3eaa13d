"""The CUDA path's kernel launches and host-device copies per sweep, counted on the CuPy stand-in
(tests/cupy_emulation.py: every array operation a launch, a fused kernel one) by the counting of
``python -m benchmarks.gpu count``, on the saved problems of tests/test_cuda_path.py with every
level on the device. The counts are deterministic (the same operations every run): the bounds
are the counts measured at this commit, so that a change that adds launches to a sweep fails
here. Before issue 33's item 4 (commit 0ece6d0) the same counts were: LED problem 719 launches
and 108 copies per sweep on its finer level, room problem 722 and 84. The LED's evidence weights (on by default since issue 32's "no grain")
added 65-69 launches per LED sweep; their closed-form eigenvalue fused into one kernel took 28
of them back. At 8c3d82f: LED 513 / 495 launches per sweep on its two levels, room 562 (3 host
reads per linear solve at most); issue 33's item 4 continued (batched joint assembly, fused
multigrid passes and downdates, re-evaluations keeping their prior energy): 346 / 346 and 436,
2 reads at most. The albedo-step weights on the LED's finest level (issue 32 item 3) are fused
into these counts (at 8c3d82f they added 15 launches and 1 copy there): 346 / 343 and 440.
Issue 31's memory work scores the LED offset's line-search trials by the frame-batched energy
(no second evaluation held) and evaluates the offset kept once more (at 8c3d82f: +11 launches
and +3 copies on the LED problem's coarser level, where the offset moves). All merged: 353 / 340
and 442, 2 reads at most (7a62d00: 353 / 340 and 441.5). Issue 33's per-frame items (the joint
assembly's twist sums read once per step, the LED offset's system on the device with one read, its
point gradients one kernel, a pose system one read): 353 / 345 and 446 launches (the room's pose
systems: a concatenation for a copy), 52 / 47 and 60.5 copies (were 58 / 52 and 65). Issue 33's
linear solves (CG in two numba-cuda passes per iteration, Chronopoulos-Gear recurrences; 2 host
reads per solve at most in every case), merged with those: 315 / 311 and 423 launches, 52 / 47
and 60.5 copies. Issue 33's V-cycle and CG in one cooperative launch (kernels.multigrid_cg; these
problems' systems are below the multigrid's 2000 unknowns: their cycle is the dense coarsest
product, and an iteration of the joint step was its launch, 2 CG passes and the Schur operator's
3; with the Schur complement's product in the same kernel, 1 per host read): 251 / 253 and 412
launches (were 315 / 311 and 423 at 33f5a07), copies as before. Issue 33's batched small
systems (the joint step's twist system and -H^-1 on the device, twists read once; the LED
offset's step and every line-search trial in one kernel and one read; the lighting's systems in
one copy): alone against 33f5a07 313 / 314 and 423 launches, 45 / 43 and 58.5 copies. Both
merged: 249 / 256 and 412 launches, 45 / 43 and 58.5 copies. The data term's evaluation in one
launch, the set-up's, lighting's and albedo's kernels and the trial states' kernels (issue 33,
2026-11-26; docs/gpu.md): 106 / 119 and 303 launches, 30 / 29 and 54 copies (the room's light
path keeps more array operations). The joint step's assembly, twist system, Schur operator and
twists in a few numba-cuda kernels (issue 33, gpujoint: one per assembly block, no read of the
frames' pixel counts, the poses the evaluation's copy), alone: 80 / 93 and 291 launches, 28 / 27
and 52 copies. Issue 33's evaluation, energy, weights and light updates (gpueval2: one copy per
light state, energies read where used, the LED offset system, the albedo step with its
re-evaluation, a trial with its albedo refit, the extrapolation's energies and the evidence sums
one kernel each), alone: 82 / 93 and 297 launches, 20 / 17 and 49 copies. The multigrid's set-up
in one launch, CG's start in its first launch and the prior's gradient in one (gpukrylov; these
problems' multigrid is the dense coarsest alone), alone: 100 / 113 and 297.5 launches, copies as
before. All three merged (51602b1; gpuclean's removal of dead device code changes no count): 51 /
62 and 290 launches, 18 / 15 and 51 copies (e9b0c3a: 51 / 62 and 280, 18 / 15 and 47). Two
changes of 2026-11-26 add launches on purpose: Anderson's acceleration across sweeps
(solver/acceleration.py) copies each sweep's depth and albedo into its history (+2 a sweep) and,
from a level's second sweep, forms and scores its point (the room problem: +12.5 launches and
+2.5 copies a sweep); the depth block's pattern as one product of the stacked rows (once per
level: +4 on each LED level here, whose one sweep carries it; +2.5 a room sweep). Merged: 57 / 68
and 295 launches, 18 / 15 and 49.5 copies. The albedo and lights refitted in turn until the data
term settles (2026-11-27, driver.LIGHT_ROUNDS: each round a lighting kernel, its sums read, the
lights' state copied, a re-evaluation, an albedo refit and the data energy read; these problems
take 5-8 rounds a sweep): 74 / 89 and 273 launches, 36 / 36 and 60.5 copies (the room problem's
fewer launches: its Anderson point is proposed less). The bounds are these counts with a margin
of about 1 % (1-3 launches, 1 copy).
"""

import shutil

import pytest

from benchmarks import gpu

#: (problem, level) -> (launches per sweep, copies per sweep, host reads per linear solve): at most
BOUNDS = {("led", 1): (75, 37, 2), ("led", 0): (90, 37, 2), ("room", 0): (276, 62, 1)}


@pytest.fixture(scope="module")
def counts(tmp_path_factory):
    folder = tmp_path_factory.mktemp("problems")
    for case in ("led", "room"):
        shutil.copy(f"tests/data/cuda_path_{case}.npz", folder)
    rows = gpu.count(folder, out=tmp_path_factory.mktemp("out"), min_level_pixels=0)
    return {row["problem"].split("_")[-1].split(".")[0]: row for row in rows}


def test_launches_and_copies_per_sweep_stay_within_the_measured_counts(counts):
    for (case, index), (launches, copies, reads) in BOUNDS.items():
        row = counts[case]
        level = next(level for level in row["levels"] if level["level"] == index)
        assert level["device"] == "cuda-emulated" and level["sweeps"] >= 1
        assert level["launches_per_sweep"] <= launches, (case, index, level)
        assert level["transfers_per_sweep"] <= copies, (case, index, level)
        assert row["linear_solves"] >= 1 and row["host_reads_per_linear_solve"]["max"] <= reads, row
        # the fused kernels count: one launch each
        assert row["by_kind"]["fused"] > 0


def test_the_counts_are_deterministic(counts, tmp_path):
    folder = tmp_path / "problems"
    folder.mkdir()
    shutil.copy("tests/data/cuda_path_led.npz", folder)
    again = gpu.count(folder, out=tmp_path, min_level_pixels=0)[0]
    assert again["by_kind"] == counts["led"]["by_kind"]
