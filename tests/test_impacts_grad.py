"""Reverse-mode gradients through impacts (``simulate_impacts(adjoint="reverse")``: the event
loop as a checkpointed equinox while loop): jax.grad of a loss built from the state after
three impacts and from the impact times, with respect to the table's amplitude and
frequency, the restitution and the initial data, against central differences of the same
solve (the flights are exact parabolas, so the differences measure the true derivative,
impact-time dependence included) and against forward mode."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.scenes import BouncingBall

BALL = BouncingBall(A=0.01, omega=2 * np.pi * 10, restitution=0.8)
T = 0.9
KW = dict(saveat=0, max_impacts=8, max_steps=2048, dtmax=0.0125)


def _loss(p, adjoint):
    """x(T) + 0.3 x'(T) + t_1 + t_2 + t_3 + 0.1 v1_3 as a function of (A, omega, alpha, x0, v0)."""
    b = eqx.tree_at(lambda s: (s.A, s.omega, s.restitution), BALL, (p[0], p[1], p[2]))
    tr = nhjax.simulate_impacts(b, jnp.stack([p[3], p[4]]), T, adjoint=adjoint, **KW)
    val = (tr.x_final[0] + 0.3 * tr.x_final[1] + jnp.sum(tr.impact_times[:3])
           + 0.1 * tr.velocities_post[2, 0])
    return val, tr.num_impacts


_VAG = jax.jit(jax.value_and_grad(lambda q: _loss(q, "reverse"), has_aux=True))
P = jnp.array([0.010, 2 * np.pi * 10, 0.8, 0.10, 0.0])


def test_grad_through_impacts_matches_central_differences():
    (val, n), g = _VAG(P)
    assert int(n) >= 3
    h = 1e-6 * np.maximum(np.abs(np.asarray(P)), 1e-2)
    fd = []
    for i in range(5):  # differences of the same compiled solve (no second compile)
        e = jnp.asarray(np.eye(5)[i] * h[i])
        ((vp, n_p), _), ((vm, n_m), _) = _VAG(P + e), _VAG(P - e)
        assert int(n_p) == int(n_m) == int(n)  # no impact gained or lost
        fd.append((float(vp) - float(vm)) / (2 * h[i]))
    fd = np.array(fd)
    g = np.asarray(g)
    assert np.all(np.abs(g) > 1e-3)  # every input matters (the test could fail for each)
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6)


@pytest.mark.slow
def test_reverse_and_forward_mode_agree():
    """The checkpointed loop computes the same solve as the lax loop, and its gradient is
    forward mode's derivative."""
    (val, n), g = _VAG(P)
    val_f, n_f = jax.jit(lambda q: _loss(q, "forward"))(P)
    assert int(n) == int(n_f) and float(val) == float(val_f)
    g_fwd = np.asarray(jax.jit(jax.jacfwd(lambda q: _loss(q, "forward")[0]))(P))
    np.testing.assert_allclose(np.asarray(g), g_fwd, rtol=1e-9, atol=1e-9)
