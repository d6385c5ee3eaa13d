"""Shared fixtures. Keep renders small: the suite must stay fast on a 2-core machine."""

import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(0)
