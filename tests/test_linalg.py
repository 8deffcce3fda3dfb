"""nhjax._linalg.solve: Gaussian elimination with partial pivoting, unrolled, without
LAPACK (used for u* in Pontryagin's Hamiltonian flow)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nhjax._linalg import SMALL, solve


@pytest.mark.parametrize("n", range(1, SMALL + 1))
def test_backward_stable_on_random_and_pivot_needing_systems(n):
    rng = np.random.default_rng(n)
    run = jax.jit(solve)
    for trial in range(20):
        A = rng.normal(size=(n, n))
        if n > 1 and trial % 2:
            A[0, 0] = 0.0  # no factorization without row exchanges
            A[1, 1] = 1e-14 * A[1, 1]
        b, B = rng.normal(size=n), rng.normal(size=(n, 3))
        for rhs in (b, B):
            x = np.asarray(run(A, rhs))
            # backward error at the level of LAPACK's (a few units of round-off)
            err = np.linalg.norm(A @ x - rhs) / (np.linalg.norm(A, 2) * np.linalg.norm(x) + np.linalg.norm(rhs))
            assert err < 1e-14 * n, (trial, err)
            np.testing.assert_allclose(x, np.linalg.solve(A, rhs), rtol=1e-9 * np.linalg.cond(A), atol=1e-12)


@pytest.mark.slow  # (17 s; make test-all)
def test_derivatives_match_lapack_solve_and_singular_gives_nonfinite():
    A = jnp.array([[0.0, 2.0, 1.0], [1.0, 1.0, 0.5], [3.0, -1.0, 2.0]])  # needs a row exchange
    b = jnp.array([1.0, -2.0, 0.5])
    f = lambda A, b: jnp.sum(jnp.sin(solve(A, b)))  # noqa: E731
    g = lambda A, b: jnp.sum(jnp.sin(jnp.linalg.solve(A, b)))  # noqa: E731
    for ours, ref in zip(jax.grad(f, (0, 1))(A, b), jax.grad(g, (0, 1))(A, b)):
        np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(jax.jacfwd(solve, 0)(A, b), jax.jacfwd(jnp.linalg.solve, 0)(A, b), rtol=1e-12,
                               atol=1e-14)
    # vmapped as the lanes of a batch
    As = jnp.stack([A, 2 * A + jnp.eye(3)])
    np.testing.assert_allclose(jax.vmap(solve, (0, None))(As, b), jnp.linalg.solve(As, b[None, :, None])[..., 0],
                               rtol=1e-13)
    assert not np.all(np.isfinite(np.asarray(solve(jnp.ones((2, 2)), jnp.ones(2)))))


def test_no_lapack_call_in_the_program_below_the_size_limit():
    A, b = jnp.eye(SMALL) + 0.1, jnp.ones(SMALL)
    text = jax.jit(solve).lower(A, b).compile().as_text()
    assert "custom_call_target=\"lapack" not in text
    big = jax.jit(solve).lower(jnp.eye(SMALL + 1), jnp.ones(SMALL + 1)).compile().as_text()
    assert "custom_call_target=\"lapack" in big  # above the limit: jnp.linalg.solve
