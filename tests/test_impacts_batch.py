"""The lock-step batch of impact solves (``simulate_impacts_batch``): every member, whatever
lane it ran in and whenever it entered the lane (refilled from the queue after another
member ended), is its own ``simulate_impacts`` solve: same impacts, same impact times and
states to 1e-12. Members differ in amplitude (a chattering ball that comes to rest, a
period-1 bouncer, a chaotic one) and in initial data, so lanes end at very different
iteration counts and are refilled."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.errors import ParameterError
from nhjax.scenes import BouncingBall

G, W = 9.81, 2 * np.pi
T1 = 6.0
OPTS = dict(max_impacts=40, rest_velocity=1e-4)


def _members():
    gam = np.array([0.7, 1.3, 2.0, 3.6, 4.0, 2.7, 1.1])  # below 1: comes to rest on the table
    ball = BouncingBall(g=G, A=1.0, omega=W, restitution=0.5)
    balls = eqx.tree_at(lambda s: s.A, ball, jnp.asarray(gam * G / W**2))
    x0 = np.stack([np.linspace(1e-3, 0.3, gam.size), np.linspace(0.0, 1.0, gam.size)], 1)
    return ball, balls, gam, x0


def test_each_lockstep_member_is_its_own_solve():
    ball, balls, gam, x0 = _members()
    # 2 chunks (members dealt in turn), 2 lanes each: the lanes are refilled from the queue
    tr = nhjax.simulate_impacts_batch(balls, x0, T1, in_axes={"system": ["A"], "x0": 0}, lanes=2, workers=2,
                                      saveat=5, **OPTS)
    n = np.asarray(tr.num_impacts)
    steps = np.asarray(tr.num_steps)
    assert np.ptp(steps) > 100  # members of very different lengths
    assert np.any(np.asarray(tr.persistent)[:, 0])  # one comes to rest
    for i in range(gam.size):
        b = eqx.tree_at(lambda s: s.A, ball, jnp.asarray(gam[i] * G / W**2))
        one = nhjax.simulate_impacts(b, jnp.asarray(x0[i]), T1, saveat=5, on_max_impacts="stop", **OPTS)
        assert int(one.num_impacts) == n[i] and int(one.status) == int(tr.status[i])
        k = n[i]
        assert k >= 1
        # Bouncing members take the same steps and agree to 1e-12. Members that chatter
        # (impacts at normal velocities down to rest_velocity = 1e-4, then rest and release)
        # amplify the last-bit differences of vectorized and scalar code (XLA's loops over
        # the lanes round differently) and may take a few steps more or less while resting;
        # their impacts agree to 1e-11 in time.
        chatter = gam[i] < 1.5
        tol = 1e-10 if chatter else 1e-12
        if not chatter:
            assert int(one.num_steps) == steps[i]
        np.testing.assert_allclose(np.asarray(tr.impact_times[i][:k]), np.asarray(one.impact_times[:k]),
                                   rtol=0, atol=tol / 10, err_msg=f"member {i}")
        for field in ("x_pre", "x_post", "impulses"):
            a, b_ = np.asarray(getattr(tr, field)[i][:k]), np.asarray(getattr(one, field)[:k])
            np.testing.assert_allclose(a, b_, rtol=0, atol=tol, err_msg=f"member {i}: {field}")
        assert np.all(np.isnan(np.asarray(tr.impact_times[i][k:])))  # nothing from a lane's previous member
        np.testing.assert_allclose(np.asarray(tr.x_final[i]), np.asarray(one.x_final), rtol=0, atol=tol)
        np.testing.assert_allclose(np.asarray(tr.xs[i]), np.asarray(one.xs), rtol=0, atol=tol)
        np.testing.assert_allclose(float(tr.t_final[i]), float(one.t_final), rtol=0, atol=tol)
        assert abs(float(tr.energy_error[i]) - float(one.energy_error)) < tol
    # nhjax.simulate_batch sends systems with one-sided constraints to the same batch
    via = nhjax.simulate_batch(balls, x0, T1, in_axes={"system": ["A"], "x0": 0}, lanes=2, workers=2, saveat=5,
                               on_error="return", **OPTS)
    assert isinstance(via, type(tr))
    np.testing.assert_array_equal(np.asarray(via.num_impacts), n)
    # (its chunks may group members otherwise: chattering members to the 1e-10 above)
    np.testing.assert_allclose(np.asarray(via.impact_times), np.asarray(tr.impact_times), rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(via.x_final), np.asarray(tr.x_final), rtol=0, atol=1e-10)
    with pytest.raises(TypeError, match="max_impacts"):  # impact options on a system without impacts
        nhjax.simulate_batch(nhjax.scenes.FallingCat(), x0, T1, max_impacts=3)


def test_batch_sizes_must_agree():
    ball, balls, gam, x0 = _members()
    with pytest.raises(ParameterError, match="one batch size"):
        nhjax.simulate_impacts_batch(balls, x0[:3], T1, in_axes={"system": ["A"], "x0": 0})
    with pytest.raises(ValueError, match="lanes"):
        nhjax.simulate_impacts_batch(balls, x0, T1, in_axes={"system": ["A"], "x0": 0}, lanes=0)


def test_simulate_batch_signature_names_what_impacts_do_not_support():
    from nhjax.integrate.impacts import simulate_batch_impacts

    ball, balls, gam, x0 = _members()
    with pytest.raises(ValueError, match="control"):
        simulate_batch_impacts(ball, x0, T1, control=lambda t, x: 0.0)
    with pytest.raises(ValueError, match="project"):
        simulate_batch_impacts(ball, x0, T1, project=True)
    with pytest.raises(ValueError, match="in_axes keys"):
        simulate_batch_impacts(ball, x0, T1, in_axes={"control": 0})
