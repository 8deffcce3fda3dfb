"""The ball inside a cone in the seed's first formulation (polar coordinates and z-x-z
Euler angles, 9.20-9.25) against the independent (u, p) model BallInCone: the same
states, the same accelerations, and (slow) the same trajectory to 1e-9."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax import errors as E
from nhjax.scenes.ball_in_cone import BallInCone
from nhjax.scenes.ball_in_cone_euler import BallInConeEuler

PARAMS = dict(m=2.0, r=0.5, J=0.15, gamma=0.8, g=1.3)


def _starts(rng, k):
    return [dict(rho=rng.uniform(1.5, 4.0), alpha=rng.uniform(-3, 3), rho_dot=rng.normal(), alpha_dot=rng.normal(),
                 spin=rng.normal(), phi=rng.uniform(-3, 3), theta=rng.uniform(0.3, 2.8), psi=rng.uniform(-3, 3))
            for _ in range(k)]


@eqx.filter_jit
def _accelerations(be, bc, xs):
    def one(x):
        # the (u, p) state's derivative along the Euler model's motion, against BallInCone's vector field
        xu, dxu = jax.jvp(be.to_up, (x,), (be.vector_field(0.0, x, None),))
        return dxu, bc.vector_field(0.0, xu, None)
    return jax.vmap(one)(xs)


def test_same_states_as_the_up_model(rng):
    be, bc = BallInConeEuler(**PARAMS), BallInCone(**PARAMS)
    starts = _starts(rng, 6)
    for s in starts:
        x = be.initial_state(**s)
        assert float(be.constraint_residual(0.0, x)) < 1e-14
        p = be.attitude(x[:5])
        xb = bc.initial_state(**{k: v for k, v in s.items() if k not in ("phi", "theta", "psi")}, attitude=p)
        np.testing.assert_allclose(np.asarray(be.to_up(x)), np.asarray(xb), atol=1e-13)
        assert float(be.energy(x)) == pytest.approx(float(bc.energy(xb)), rel=1e-14)


@pytest.mark.slow  # 24 s of compiling two autodiff-derived vector fields under jvp
def test_same_accelerations_as_the_up_model(rng):
    be, bc = BallInConeEuler(**PARAMS), BallInCone(**PARAMS)
    xs = jnp.stack([be.initial_state(**s) for s in _starts(rng, 6)])
    d_euler, d_up = _accelerations(be, bc, xs)
    assert np.abs(np.asarray(d_up[:, 7:])).max() > 1e-2
    np.testing.assert_allclose(np.asarray(d_euler), np.asarray(d_up), rtol=0, atol=1e-11)
    # a different moment of inertia changes them: the comparison can fail
    _, d_other = _accelerations(be, BallInCone(**{**PARAMS, "J": 0.3}), xs)
    assert np.abs(np.asarray(d_other) - np.asarray(d_up)).max() > 1e-3


def test_bad_input():
    be = BallInConeEuler()
    with pytest.raises(E.OutsideChartError, match="theta") as err:  # outside the chart: as simulate says
        be.initial_state(theta=0.0)
    assert err.value.guard == "gimbal" and err.value.name == "theta"
    with pytest.raises(E.OutsideChartError, match="rho"):
        be.initial_state(rho=0.5)
    with pytest.raises(E.ParameterError, match="gamma"):
        BallInConeEuler(gamma=2.0)


@pytest.mark.slow
def test_same_trajectory_as_the_up_model():
    """10 s of the Fig. 9.5 motion at rtol 1e-12: BallInConeEuler mapped to (u, p) agrees
    with BallInCone to 1e-9 (measured 1e-11) and keeps energy and L."""
    be, bc = BallInConeEuler(), BallInCone()
    start = dict(rho=3.0, alpha=0.4, rho_dot=0.5, alpha_dot=0.3, spin=1.0)
    xe = be.initial_state(**start, phi=0.3, theta=1.2, psi=-0.5)
    xb = bc.initial_state(**start, attitude=be.attitude(xe[:5]))
    kw = dict(saveat=201, rtol=1e-12, atol=1e-12, on_guard="stop")
    tre, trb = nhjax.simulate(be, xe, 10.0, **kw), nhjax.simulate(bc, xb, 10.0, **kw)
    assert not tre.guard and not trb.guard
    np.testing.assert_allclose(np.asarray(jax.vmap(be.to_up)(tre.xs)), np.asarray(trb.xs), rtol=0, atol=1e-9)
    for k, v in tre.invariant_drift.items():
        assert float(v) < 1e-10, k
