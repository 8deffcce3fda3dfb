import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

# the compilation cache of the tests is set up by the repository's conftest.py


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)


def pytest_configure(config):
    assert jax.config.jax_enable_x64, "nhjax must run in float64"


class OpenEllipse(eqx.Module):
    """alpha -> c + (a cos alpha + gap alpha / 2 pi, b sin alpha): an ellipse that ends
    ``gap`` from its start (a loop for curvature_integral's closure check; its numbers are
    arrays, so that ellipses of other sizes share the programs)."""

    c: jax.Array
    a: jax.Array
    b: jax.Array
    gap: jax.Array

    def __call__(self, alpha):
        return self.c + jnp.stack([self.a * jnp.cos(alpha) + self.gap * alpha / (2 * np.pi), self.b * jnp.sin(alpha)])


@pytest.fixture(scope="session")
def open_ellipse():
    return OpenEllipse
