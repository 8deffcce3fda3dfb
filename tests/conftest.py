import jax
import numpy as np
import pytest

# the compilation cache of the tests is set up by the repository's conftest.py


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)


def pytest_configure(config):
    assert jax.config.jax_enable_x64, "nhjax must run in float64"
