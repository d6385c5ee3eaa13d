"""The one line search of every update step: backtracking on the true energy.

Each step (depth, joint pose-depth, a frame's pose, the LED offset) proposes a direction from
a Gauss-Newton model and accepts the longest of the lengths 1, 1/2, 1/4, ... whose energy is
not above the current one, so no accepted step raises the energy.
"""

from __future__ import annotations

from typing import Callable, TypeVar

Candidate = TypeVar("Candidate")


def backtrack(trial: Callable[[float], tuple[Candidate, float] | None], energy: float,
              max_halvings: int) -> tuple[float, Candidate, float] | None:
    """Try ``trial(t)`` for t = 1, 1/2, ..., 2^-max_halvings.

    ``trial(t)`` returns (candidate, its energy), or None where the step of length t leaves the
    valid domain (a depth behind the camera, say). Returns (t, candidate, energy) of the first
    candidate whose energy is not above ``energy``, else None.
    """
    t = 1.0
    for _ in range(max_halvings + 1):
        found = trial(t)
        if found is not None and found[1] <= energy:
            return (t, *found)
        # a rejected candidate is dropped before the next is made: one trial's evaluation at a
        # time (0.9 GB at 2 megapixels and 20 frames), not two
        del found
        t *= 0.5
    return None
