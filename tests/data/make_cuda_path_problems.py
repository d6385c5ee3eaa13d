"""Write the saved problems of tests/test_cuda_path.py (run from the repository root, with Open3D):
``python tests/data/make_cuda_path_problems.py``.

The bunny at 64x48 colour (226 object pixels), SF 2, three frames, true poses. Under the LED two
levels of one sweep, the poses and depth in the joint step; under room light one level of two
sweeps, the paper's alternation (pose steps, then the depth step with the parallax) and the room
model's light fit. The linear solves run to 1e-10: the paths' preconditioners differ (pyamg's
AMG, the multigrid of o3d_mvps.solver.krylov), and at the default tolerances their CG iterates
differ by up to the tolerance (1 % energies on a 32x24 relief). An isolated object: where the
surface fills the frame, a pixel that lands on another frame's border within round-off is in
view on one path and not on the other (one such pixel moved a 768-pixel relief's energy by 0.9 %).
"""

from pathlib import Path

from o3d_mvps import RefineOptions
from o3d_mvps.solver.problem_input import write_problem
from o3d_mvps.solving import problem_from_capture
from o3d_mvps.synthetic import render_capture

OPTIONS = dict(progress=False, joint_min_pixels=0, pose_min_pixels=0, cg_tolerance=1e-10, joint_cg_tolerance=1e-10)
CASES = {"led": dict(levels=2, max_iterations=1), "room": dict(levels=1, max_iterations=2, joint_pose_depth=False)}

if __name__ == "__main__":
    for light, options in CASES.items():
        capture = render_capture("bunny", frames=3, scale_factor=2, size=(64, 48), light=light, seed=1, progress=False)
        problem, _ = problem_from_capture(capture, RefineOptions(**OPTIONS, **options), capture.groundtruth.poses)
        print(write_problem(problem, Path(__file__).parent / f"cuda_path_{light}.npz", overwrite=True))
