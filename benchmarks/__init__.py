"""Benchmarks of o3d_mvps (run from the repository root: ``python -m benchmarks --help``)."""
