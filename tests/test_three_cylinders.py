"""Three rolling cylinders (seed 002, 9.30-9.36): the consistent initial states of both
formulations, the (u, p) model (three rigid bodies, 19 constraints) against the
independent minimal-coordinate model (9.30)-(9.31) -- accelerations at random states and
whole trajectories to 1e-9 -- and the energy and constraints over a long run."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax import errors as E
from nhjax.scenes.three_cylinders import ThreeCylinders, ThreeCylindersMinimal

PARAMS = dict(r1=0.4, r2=0.6, a=1.1, m=1.5, J_a=0.3, J_t=0.8, m_l=0.7, J_l=0.05, J_lt=0.3)


def _random_starts(rng, k):
    return [dict(x1=rng.normal(), x2=rng.normal(), theta=rng.uniform(1.5, 2.8), phi=rng.uniform(-3, 3),
                 psi1=rng.normal(), psi2=rng.normal(), theta_dot=rng.normal(), phi_dot=rng.normal())
            for _ in range(k)]


@eqx.filter_jit
def _check_states(up, mn, xs):
    def one(x):
        q, qd = up.split(x)
        y, yd = up.to_minimal(x)
        s1, s2, g1, g2 = up.contact_slips(q, qd)
        zu, zm = up.contact_points(q), mn.contact_points(y)
        return dict(slip=jnp.concatenate([s1, s2, g1, g2]),  # all three components, the vertical ones included
                    contact=jnp.concatenate([zu[0] - zm[0], zu[1] - zm[1]]),
                    energy=up.energy(x) - mn.energy(jnp.concatenate([y, yd])),
                    residual=up.constraint_residual(0.0, x))
    return jax.vmap(one)(xs)


def test_initial_states_are_consistent_and_the_same_body(rng):
    up, mn = ThreeCylinders(**PARAMS), ThreeCylindersMinimal(**PARAMS)
    starts = _random_starts(rng, 6)
    xs = jnp.stack([up.initial_state(**s) for s in starts])
    ys = jnp.stack([mn.initial_state(**s) for s in starts])
    for name, v in _check_states(up, mn, xs).items():
        assert np.abs(np.asarray(v)).max() < 1e-13, name
    for x, y in zip(xs, ys):
        assert mn.constraint_residual(0.0, y) < 1e-14
        back = jnp.concatenate(up.to_minimal(x))
        d = np.array(back - y)
        d[3] = (d[3] + np.pi) % (2 * np.pi) - np.pi  # phi is read back modulo 2 pi
        np.testing.assert_allclose(d, 0.0, atol=1e-13)
    # the two free rates are the ones given; the lower cylinders' rates follow
    s = starts[0]
    assert float(ys[0][8]) == pytest.approx(s["theta_dot"]) and float(ys[0][9]) == pytest.approx(s["phi_dot"])
    # concrete numbers run as one cached program; traced ones (vmap over the starts) as
    # plain operations: the same states
    keys = list(starts[0])
    cols = {k: jnp.asarray([st[k] for st in starts]) for k in keys}
    for model, eager in ((up, xs), (mn, ys)):
        traced = jax.vmap(lambda *v, m=model: m.initial_state(**dict(zip(keys, v))))(*(cols[k] for k in keys))
        np.testing.assert_allclose(np.asarray(traced), np.asarray(eager), rtol=0, atol=1e-14)


@eqx.filter_jit
def _accelerations(up, mn, xs):
    def one(x):
        # d/dt of the minimal rates along the (u, p) vector field, against the minimal model's accelerations
        _, ydd_up = jax.jvp(lambda z: up.to_minimal(z)[1], (x,), (up.vector_field(0.0, x, None),))
        y, yd = up.to_minimal(x)
        ydd_mn = mn.vector_field(0.0, jnp.concatenate([y, yd]), None)[6:]
        return ydd_up, ydd_mn
    return jax.vmap(one)(xs)


def test_the_two_formulations_have_the_same_accelerations(rng):
    """(9.33)-(9.36) in R^21 with 19 constraints and (9.30)-(9.31) in R^6 with four are derived
    independently; at random consistent states they must give the same motion."""
    up, mn = ThreeCylinders(**PARAMS), ThreeCylindersMinimal(**PARAMS)
    xs = jnp.stack([up.initial_state(**s) for s in _random_starts(rng, 6)])
    a_up, a_mn = _accelerations(up, mn, xs)
    assert np.abs(np.asarray(a_mn)).max() > 1e-2  # the motion is not trivially unaccelerated
    np.testing.assert_allclose(np.asarray(a_up), np.asarray(a_mn), rtol=0, atol=1e-11)
    # a different inertia changes the accelerations: the comparison can fail
    _, a_other = _accelerations(up, ThreeCylindersMinimal(**{**PARAMS, "J_t": 1.6}), xs)
    assert np.abs(np.asarray(a_other) - np.asarray(a_mn)).max() > 1e-3


def test_minimal_model_long_run_energy_and_constraints():
    mn = ThreeCylindersMinimal()
    x0 = mn.initial_state()
    tr = nhjax.simulate(mn, x0, 30.0, saveat=301, rtol=1e-10, atol=1e-10, on_guard="stop")
    assert not tr.guard and float(tr.ts[-1]) == 30.0
    assert float(tr.invariant_drift["energy"]) < 1e-8 * float(mn.energy(x0))
    assert float(tr.constraint_drift["velocity"]) < 1e-9
    # the upper cylinder does move: it rolls along e1 and turns
    assert float(tr.xs[-1, 0] - x0[0]) > 10.0 and abs(float(tr.xs[-1, 2] - x0[2])) > 0.1


def test_guard_and_bad_input():
    mn = ThreeCylindersMinimal()
    # turning towards the second lower axis (a = pi/3): the contact point runs off, the guard stops
    x0 = mn.initial_state(theta=1.3, psi1=1.455, psi2=1.925, theta_dot=-0.735, phi_dot=0.5)
    tr = nhjax.simulate(mn, x0, 7.0, saveat=301, rtol=1e-10, atol=1e-10, on_guard="stop")
    assert tr.guard == "parallel" and float(tr.ts[-1]) < 7.0
    th = float(tr.x_end[2])
    assert min(abs(np.sin(th)), abs(np.sin(th - np.pi / 3))) == pytest.approx(mn.chart_eps, abs=1e-6)
    for bad in (0.0, np.pi / 3, np.pi):
        with pytest.raises(E.OutsideChartError, match="theta"):
            ThreeCylinders().initial_state(theta=bad)
        # a concrete theta is checked also when another number is traced
        with pytest.raises(E.OutsideChartError, match="theta"):
            jax.jit(lambda pd, th=bad: mn.initial_state(theta=th, phi_dot=pd))(1.0)
    for bad in (0.0, np.pi, -1.0, np.nan):
        with pytest.raises(E.ParameterError, match="'a'|a "):
            ThreeCylindersMinimal(a=bad)
    with pytest.raises(E.ParameterError, match="r2"):
        ThreeCylinders(r2=-1.0)


@pytest.mark.slow
def test_the_two_formulations_agree_along_a_run():
    """Whole trajectories: the (u, p) model (21 coordinates, 19 constraints) mapped to the
    seed's coordinates agrees with the minimal model to 1e-9 over 6 s at rtol 1e-12, and
    keeps its energy and its 19 constraints."""
    up, mn = ThreeCylinders(), ThreeCylindersMinimal()
    kw = dict(saveat=601, rtol=1e-12, atol=1e-12, on_guard="stop")
    tru = nhjax.simulate(up, up.initial_state(), 6.0, **kw)
    trm = nhjax.simulate(mn, mn.initial_state(), 6.0, **kw)
    assert not tru.guard and not trm.guard
    y, yd = jax.vmap(up.to_minimal)(tru.xs)
    yu = np.concatenate([np.asarray(y), np.asarray(yd)], axis=1)
    yu[:, 3] = np.unwrap(yu[:, 3])
    np.testing.assert_allclose(yu, np.asarray(trm.xs), rtol=0, atol=1e-9)
    assert float(tru.invariant_drift["energy"]) < 1e-9
    assert max(float(v) for v in tru.constraint_drift.values()) < 1e-12
