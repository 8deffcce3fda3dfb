"""Ball on a rotating platter (seed 002, 9.14-9.19) in (u, p) in R^3 x S^3: the
centre's velocity turns at Omega J / (J + m r^2), the path is a circle, the
invariants hold and the energy (correctly) does not."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.scenes.ball_on_platter import BallOnPlatter

N_SAVE = 401


@eqx.filter_jit
def _checks(ball, ts, xs, x0):
    u, v = ball.exact_solution(ts, x0)
    heading = jnp.unwrap(jnp.arctan2(xs[:, 8], xs[:, 7]))
    T = jax.vmap(lambda x: ball.kinetic_energy(x[:7], x[7:]))(xs)
    centres = jax.vmap(ball.circle_centre)(xs)
    return (
        jnp.max(jnp.abs(xs[:, :2] - u)),
        jnp.max(jnp.abs(xs[:, 7:9] - v)),
        heading,
        jnp.max(jnp.abs(T - T[0])),
        jnp.max(jnp.abs(centres - centres[0])),
    )


@pytest.mark.parametrize(
    "params, start",
    [
        # the seed's data: Omega = 2, J = 0.6 (units m, r); a spinning ball
        (dict(), dict(u1=1.0, u2=0.0, u1_dot=0.0, u2_dot=1.5, spin=1.0)),
        # a solid ball (J = 2/5 m r^2), platter turning the other way
        (dict(m=2.0, r=0.5, J=0.2, Omega=-1.5, g=9.81), dict(u1=-0.3, u2=2.0, u1_dot=0.7, u2_dot=-0.2, spin=-3.0)),
    ],
)
def test_centre_velocity_turns_at_kappa(params, start):
    ball = BallOnPlatter(**params)
    x0 = ball.initial_state(**start)
    kappa = float(ball.Omega * ball.J / (ball.J + ball.m * ball.r**2))
    np.testing.assert_allclose(float(ball.turn_rate), kappa, rtol=1e-15)
    if not params:
        assert kappa == pytest.approx(0.75)
    t1 = 4 * 2 * np.pi / abs(kappa)  # four orbits, as in the seed's Fig. 9.4
    tr = nhjax.simulate(ball, x0, t1, saveat=N_SAVE, rtol=1e-10, atol=1e-10)
    du, dv, heading, dT, dc = (np.asarray(a) for a in _checks(ball, tr.ts, tr.xs, x0))
    assert du < 2e-7 and dv < 1e-7  # centre on the exact circle (measured 5e-8)
    assert dc < 2e-7  # the circle's centre stays put
    # the heading of u' advances linearly at kappa (least-squares slope over 4 orbits)
    slope = np.polyfit(np.asarray(tr.ts), heading, 1)[0]
    assert slope == pytest.approx(kappa, rel=1e-9, abs=1e-12)
    # invariants of every motion; the energy is not one (the platter does work)
    assert "energy" not in tr.invariant_drift
    for name in ("speed", "spin_z", "jacobi_integral"):
        assert tr.invariant_drift[name] < 1e-6, name
    assert dT > 1e-2
    for name, v in tr.constraint_drift.items():
        assert v < 1e-8, name


def test_initial_state_and_bad_input():
    ball = BallOnPlatter()
    x0 = ball.initial_state(u1=0.5, u2=-0.2, u1_dot=0.3, u2_dot=0.1, spin=2.0)
    for v in ball.constraints(0.0, x0).values():
        np.testing.assert_allclose(v, 0.0, atol=1e-15)
    np.testing.assert_allclose(ball.angular_velocity(x0)[2], 2.0, rtol=1e-14)
    # centre velocity = platter velocity under the ball + rolling: u' = Omega e3 x u + r w x e3
    w = ball.angular_velocity(x0)
    np.testing.assert_allclose(
        x0[7:9], [-2.0 * x0[1] + w[1], 2.0 * x0[0] - w[0]], atol=1e-14
    )
    with pytest.raises(ValueError, match="J must be"):
        BallOnPlatter(J=0.0)
    with pytest.raises(ValueError, match="r must be"):
        BallOnPlatter(r=-1.0)
    slipping = x0.at[7].add(1e-3)
    with pytest.raises(nhjax.ConstraintViolationError, match="velocity"):
        nhjax.simulate(ball, slipping, 1.0, saveat=N_SAVE)
