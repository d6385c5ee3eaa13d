"""The joint variational solver (paper sections 3-4; docs/method.md).

NumPy in, NumPy out, without Open3D: :func:`.driver.solve` takes a :class:`.problem_input.SolverInput`
(the arrays of a read, masked and registered capture; saved as .npz by ``refine --save-problem``)
and returns a :class:`.solution.SolverOutput`; ``python -m o3d_mvps.solver PROBLEM.npz OUT.npz``
solves a saved problem.
"""
