"""Shared fixtures; helpers shared by several test files live in tests/helpers.py (importable as
``helpers``: pytest puts this folder on sys.path). Keep renders small: the suite must stay fast
on a 2-core machine."""

import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(0)
