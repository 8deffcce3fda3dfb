"""Two-wheeled cart on an inclined plane (seed 002, 9.45-9.52): the closed-form
motion (a skate with the wheels' inertia), its cusps, energy and turning rate."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.scenes.two_wheeled_cart import TwoWheeledCart

N_SAVE = 1001


@eqx.filter_jit
def _error(cart, ts, xs, x0):
    return jnp.max(jnp.abs(xs - cart.exact_solution(ts, x0)), axis=0)


@pytest.mark.parametrize(
    "params, start",
    [
        # the seed's data a = 0.5, Jc = 1, Jw = 0.5, g = 0.3; up the slope, turning left
        (dict(), dict(speed=0.3, theta_dot=0.25)),
        # physical units, a gentle slope, starting sideways and turning right
        (dict(m=12.0, r=0.15, a=0.25, Jc=0.9, Jw=0.02, g=9.81, beta=0.05), dict(x1=1.0, theta=0.5, speed=-0.1, theta_dot=-0.6)),
    ],
)
def test_motion_matches_closed_form_with_cusps(params, start):
    cart = TwoWheeledCart(**params)
    x0 = cart.initial_state(**start)
    t1 = 3 * 2 * np.pi / abs(start["theta_dot"])  # three turns of the heading
    tr = nhjax.simulate(cart, x0, t1, saveat=N_SAVE, rtol=1e-10, atol=1e-12)
    assert float(np.max(_error(cart, tr.ts, tr.xs, x0))) < 1e-7
    assert tr.invariant_drift["turn_rate"] < 1e-12
    scale = 1.0 + float(cart.kinetic_energy(x0[:5], x0[5:])) + float(np.abs(tr.invariants["energy"]).max())
    assert tr.invariant_drift["energy"] < 1e-9 * scale
    assert tr.constraint_drift["velocity"] < 1e-9
    # cusps: the cart stops (v = 0) and reverses, always on the same line of x1
    cusps = cart.cusp_times(x0, t1)
    assert len(cusps) >= 4
    xc = cart.exact_solution(jnp.asarray(cusps), x0)
    np.testing.assert_allclose(cart.speed(xc.T), 0.0, atol=1e-12)
    M = float(cart.m + 2 * cart.Jw / cart.r**2)
    x1_cusp = float(x0[0]) + M * float(cart.speed(x0)) ** 2 / (2 * float(cart.m * cart.g * jnp.sin(cart.beta)))
    np.testing.assert_allclose(xc[:, 0], x1_cusp, rtol=1e-12)
    ts = np.asarray(tr.ts)
    v = np.asarray(cart.speed(tr.xs.T))
    x1 = np.asarray(tr["x1"])
    assert x1.max() <= x1_cusp + 1e-7  # nothing above the cusp line
    # the simulated speed changes sign exactly at the cusp times
    flips = ts[:-1][np.sign(v[1:]) != np.sign(v[:-1])]
    np.testing.assert_allclose(flips, cusps[: len(flips)], atol=ts[1] - ts[0])
    # forward and backward swings between cusps reach different depths down the slope
    depth = [x1[(ts > a) & (ts < b)].min() for a, b in zip(cusps[:-1], cusps[1:])]
    assert abs(depth[0] - depth[1]) > 1e-3 * abs(depth[0] - x1_cusp)
    np.testing.assert_allclose(depth[0], depth[2], atol=1e-4 * np.ptp(x1))  # same kind repeats
    # the wheels roll: r (phi_r' - phi_l') = 2 a theta'
    np.testing.assert_allclose(cart.r * (tr["phi_r_dot"] - tr["phi_l_dot"]), 2 * cart.a * x0[7], rtol=1e-9)


def test_bad_input():
    with pytest.raises(ValueError, match="Jw must be"):
        TwoWheeledCart(Jw=0.0)
    with pytest.raises(ValueError, match="a must be"):
        TwoWheeledCart(a=-0.5)
    cart = TwoWheeledCart()
    skidding = cart.initial_state(speed=0.3, theta_dot=0.25).at[6].set(0.1)
    with pytest.raises(nhjax.ConstraintViolationError, match="velocity"):
        nhjax.simulate(cart, skidding, 1.0, saveat=N_SAVE)
