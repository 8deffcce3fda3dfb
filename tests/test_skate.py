"""Skate on an inclined plane (seed 002, 9.1-9.3): exact circle and cycloid, the
seed's DAENH accuracy anchor, the multiplier, invariants and bad input."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.scenes.skate import Skate, SkateSE2

N_SAVE = 1001  # one saveat shape for every Skate run: one compile


@eqx.filter_jit
def _errors(sk, ts, xs, x0):
    exact = sk.exact_solution(ts, x0)
    lam = jax.vmap(sk.multiplier)(ts, xs)
    return jnp.max(jnp.abs(xs - exact), axis=0), jnp.max(jnp.abs(lam - sk.exact_multiplier(ts, x0)))


@eqx.filter_jit
def _lie_error(lie, sk, ts, ys, x0):
    return jnp.max(jnp.abs(lie.to_flat(ys) - sk.exact_solution(ts, x0)))


def max_errors(sk, traj, x0):
    """Max |error| over the saved times of the six state components and the multiplier."""
    err, lam_err = _errors(sk, traj.ts, traj.xs, x0)
    return np.asarray(err), float(lam_err)


# Rabier & Rheinboldt's DAENH stays on the constraint manifold (local
# parametrisations); simulate(project_steps=True) is the same idea here.
SEED_RUN = dict(saveat=N_SAVE, rtol=1e-8, atol=1e-12, project_steps=True)


def test_circle_exact_solution_and_seed_anchor():
    """beta = 0, u0' = (-4, 0), phi0' = 2: circle of radius 2 about (0, -2), ten revolutions."""
    sk = Skate()
    x0 = sk.initial_state(speed=-4.0, phi_dot=2.0)
    t1 = 10 * np.pi  # ten revolutions (period pi)
    ts = jnp.linspace(0.0, t1, 7)
    np.testing.assert_allclose(
        sk.exact_solution(ts, x0)[:, :2],
        np.stack([-2 * np.sin(2 * ts), 2 * np.cos(2 * ts) - 2], 1), atol=1e-13,
    )
    # On SE(2) (Hamel equations, RKMK45) at the seed's rtol = 1e-8: exact to round-off.
    lie = sk.lie_model()
    tr = nhjax.simulate(lie, lie.initial_state(speed=-4.0, phi_dot=2.0), t1, saveat=N_SAVE, rtol=1e-8, atol=1e-12)
    assert float(_lie_error(lie, sk, tr.ts, tr.xs, x0)) < 4e-8  # DAENH: 0.4e-7; measured 1e-10
    assert tr.constraint_drift["velocity"] < 1e-12 and tr.invariant_drift["energy"] < 1e-12
    # The DAE in R^6, Tsit5 with projected steps, rtol = 1e-8: DAENH's error to its one digit.
    tr = nhjax.simulate(sk, x0, t1, **SEED_RUN)
    err, lam_err = max_errors(sk, tr, x0)
    assert err.max() < 5e-8 and lam_err < 1e-7  # measured 4.2e-8 (lam = m v phi' ~ 8: 8.5e-8)
    radius = np.hypot(tr["u1"], tr["u2"] + 2.0)
    assert np.abs(radius - 2.0).max() < 5e-8
    assert tr.constraint_drift["velocity"] < 1e-12
    assert tr.invariant_drift["spin"] == 0.0 and tr.invariant_drift["energy"] < 1e-6


def test_cycloid_exact_solution_and_seed_anchor():
    """beta = arcsin 1, g = 1, from rest with phi' = 1: cusps at (0, -k pi/2), ten loops."""
    sk = Skate(beta=np.pi / 2)
    x0 = sk.initial_state(phi_dot=1.0)
    t1 = 10 * np.pi
    tr = nhjax.simulate(sk, x0, t1, **SEED_RUN)
    err, lam_err = max_errors(sk, tr, x0)
    # DAENH: max error of the seven components (u, u', lam) about 2e-8 over ~10 loops.
    assert max(err.max(), lam_err) < 2e-8, (err, lam_err)  # measured 6.9e-9
    # cusps: the skate stops at t = k pi on the line u1 = 0, spaced pi/2 apart
    k = np.arange(11)
    cusps = sk.exact_solution(k * np.pi, x0)
    np.testing.assert_allclose(cusps[:, 0], 0.0, atol=1e-14)
    np.testing.assert_allclose(cusps[:, 1], -k * np.pi / 2, atol=1e-13)
    np.testing.assert_allclose(cusps[:, 3:5], 0.0, atol=1e-14)
    i = np.searchsorted(np.asarray(tr.ts), k[1:] * np.pi)  # saved times at the cusps
    np.testing.assert_allclose(tr.ts[i], k[1:] * np.pi, rtol=1e-12)
    np.testing.assert_allclose(tr.xs[i][:, :2], cusps[1:, :2], atol=2e-8)
    assert tr.invariant_drift["energy"] < 1e-7 and tr.constraint_drift["velocity"] < 1e-12
    # the SE(2) model of the same motion (less accurate here: 2.6e-7)
    lie = sk.lie_model()
    trl = nhjax.simulate(lie, lie.initial_state(phi_dot=1.0), t1, saveat=N_SAVE, rtol=1e-8, atol=1e-12)
    assert float(_lie_error(lie, sk, trl.ts, trl.xs, x0)) < 1e-6


def test_general_motion_on_a_slope(rng):
    """Random consistent initial states on a 0.3 rad slope: engine vs the closed form."""
    sk = Skate(m=2.0, J=0.7, g=9.81, beta=0.3)
    tol = dict(SEED_RUN, rtol=1e-10)
    for _ in range(3):
        u1, u2, phi, v = rng.normal(size=4)
        x0 = sk.initial_state(u1, u2, phi, speed=v, phi_dot=rng.uniform(0.5, 2.0) * rng.choice([-1, 1]))
        tr = nhjax.simulate(sk, x0, 5.0, **tol)
        err, lam_err = max_errors(sk, tr, x0)
        assert err.max() < 1e-7 and lam_err < 1e-6
    # phi' = 0: uniformly accelerated motion along the fixed edge (closed form's other branch)
    x0 = sk.initial_state(0.0, 0.0, 0.4, speed=1.0, phi_dot=0.0)
    tr = nhjax.simulate(sk, x0, 2.0, **tol)
    assert max_errors(sk, tr, x0)[0].max() < 1e-8


def test_bad_input():
    with pytest.raises(ValueError, match="m must be"):
        Skate(m=0.0)
    with pytest.raises(ValueError, match="J must be"):
        Skate(J=-1.0)
    sk = Skate()
    x_bad = sk.initial_state(speed=1.0).at[4].set(0.5)  # velocity across the edge
    with pytest.raises(nhjax.ConstraintViolationError, match="velocity"):
        nhjax.simulate(sk, x_bad, 1.0, **SEED_RUN)
    assert isinstance(sk.lie_model(), SkateSE2)
