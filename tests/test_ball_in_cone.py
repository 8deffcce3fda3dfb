"""Ball rolling inside a cone (seed 002, 9.20-9.29): the contact kinematics against the
rigid body, the three integrals (energy, L = D^2 alpha', N = w_n - L cot(gamma)/(r D)),
the return to the same greatest and least heights with the period and azimuth advance
of the reduced radial motion (quadrature), and the guard at the axis."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax import errors as E
from nhjax.scenes.ball_in_cone import BallInCone

SOLVE = dict(saveat=8001, rtol=1e-10, atol=1e-10, on_guard="stop")  # one compiled program for both solves
START = dict(rho=3.0, alpha=0.4, rho_dot=0.5, alpha_dot=0.3, spin=1.0)


def _peaks(ts, y, sign=1):
    """Local maxima of sign*y refined by a parabola through three samples: (times, values)."""
    y = sign * np.asarray(y)
    i = np.nonzero((y[1:-1] > y[:-2]) & (y[1:-1] >= y[2:]))[0] + 1
    a, b, c = y[i - 1], y[i], y[i + 1]
    d = 0.5 * (a - c) / (a - 2 * b + c)
    return ts[i] + d * (ts[1] - ts[0]), sign * (b - 0.25 * (a - c) * d)


@eqx.filter_jit
def _kinematics(ball, xs):
    def one(x):
        q, qd = ball.split(x)
        u = q[:3]
        gv, ea, nv = ball.frame(u)
        x_c = ball.contact_point(q)
        # the contact point lies on the cone (angle gamma with the axis) at distance r from u
        cone = jnp.arctan2(jnp.hypot(x_c[0], x_c[1]), x_c[2]) - ball.gamma
        return dict(frame=jnp.stack([gv, ea, nv]) @ jnp.stack([gv, ea, nv]).T - jnp.eye(3),
                    cone=cone, dist=jnp.linalg.norm(u - x_c) - ball.r,
                    slip=ball.contact_slip(q, qd), height=u[2] - ball.height(jnp.hypot(u[0], u[1])))
    return jax.vmap(one)(xs)


def test_initial_states_roll_and_touch_the_cone(rng):
    ball = BallInCone(gamma=0.7, r=0.5, J=0.1, m=2.0)
    xs = jnp.stack([ball.initial_state(rho=rng.uniform(1.5, 4.0), alpha=rng.uniform(-3, 3), rho_dot=rng.normal(),
                                       alpha_dot=rng.normal(), spin=rng.normal(), attitude=rng.normal(size=4))
                    for _ in range(8)])
    k = _kinematics(ball, xs)
    for name, v in k.items():
        assert np.abs(np.asarray(v)).max() < 1e-13, name  # material contact point at rest: the full slip, 3 components
    for x in xs:
        assert all(np.abs(np.asarray(v)).max() < 1e-14 for v in ball.constraints(0.0, x).values())
        rho, alpha = ball.polar(x)
        back = ball.initial_state(rho=rho, alpha=alpha, rho_dot=0.0, alpha_dot=0.0)
        np.testing.assert_allclose(back[:3], x[:3], atol=1e-13)


def test_integrals_and_return_to_the_same_height():
    """Exact relations of the reduced radial motion (module docstring): over ten radial
    periods the centre's distance from the axis (hence its height) returns to the two
    roots of the cubic, the time between greatest heights is the quadrature period, the
    azimuth advances by the quadrature angle, and E, L, N stay constant."""
    ball = BallInCone()  # gamma = 1 as in the seed's Fig. 9.5
    x0 = ball.initial_state(**START)
    T, dalpha = ball.radial_period(x0), ball.precession_per_period(x0)
    dmin, dmax = ball.turning_points(x0)
    assert dmin < float(jnp.hypot(x0[0], x0[1])) < dmax
    tr = nhjax.simulate(ball, x0, jnp.asarray(10 * T), **SOLVE)
    assert not tr.guard
    ts = np.asarray(tr.ts)
    D = np.hypot(tr["u1"], tr["u2"])
    t_hi, d_hi = _peaks(ts, D)
    t_lo, d_lo = _peaks(ts, D, sign=-1)
    assert len(t_hi) == 10 and len(t_lo) == 10
    # measured: 3e-10 (max), 3e-9 (min), period 5e-9, advance 2e-9, integrals 5e-9
    np.testing.assert_allclose(d_hi, dmax, atol=1e-8)
    np.testing.assert_allclose(d_lo, dmin, atol=3e-8)  # the sharper turn: the parabola fit errs more
    np.testing.assert_allclose(np.diff(t_hi), T, atol=1e-7)
    alpha = np.unwrap(np.arctan2(tr["u2"], tr["u1"]))
    np.testing.assert_allclose(np.diff(np.interp(t_hi, ts, alpha)), dalpha, atol=1e-7)
    assert set(tr.invariant_drift) == {"energy", "areal_velocity", "shifted_spin"}
    for k, v in tr.invariant_drift.items():
        assert v < 1e-7, (k, v)
    assert max(float(v) for v in tr.constraint_drift.values()) < 1e-12
    # the integrals are not trivially constant along arbitrary (non-motion) states
    x1 = ball.initial_state(**{**START, "rho": 2.5})
    assert abs(float(ball.shifted_spin(x1) - ball.shifted_spin(x0))) > 1e-3


def test_no_axis_crossing_and_bad_input():
    ball = BallInCone()
    with pytest.raises(E.OutsideChartError, match="rho"):  # outside the chart, as simulate would say
        ball.initial_state(rho=0.5)  # centre across the axis: rho must exceed r cot(gamma) = 0.642
    for bad in (0.0, np.pi / 2, -0.1, np.nan):
        with pytest.raises(E.ParameterError, match="gamma"):
            BallInCone(gamma=bad)
    # straight down a meridian (L = 0): the ball reaches the axis, the guard stops it
    x0 = ball.initial_state(rho=2.0, alpha_dot=0.0)
    tr = nhjax.simulate(ball, x0, jnp.asarray(10.0), **SOLVE)
    assert tr.guard == "axis"
    assert float(jnp.hypot(tr.x_end[0], tr.x_end[1])) == pytest.approx(ball.chart_eps * float(ball.r), abs=1e-6)
    assert float(tr.ts[-1]) < 10.0
