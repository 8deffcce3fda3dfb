"""The lock-step batch of impact solves (``simulate_impacts_batch``): every member, whatever
lane it ran in and whenever it entered the lane (refilled from the queue after another
member ended), is its own ``simulate_impacts`` solve: same impacts, same impact times and
states to 1e-12. Members differ in amplitude (a chattering ball that comes to rest, a
period-1 bouncer, a chaotic one) and in initial data, so lanes end at very different
iteration counts and are refilled."""

import equinox as eqx
import jax
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
                                      saveat=5, on_max_impacts="stop", **OPTS)
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
        assert int(one.num_events) == int(tr.num_events[i])
        np.testing.assert_allclose(np.asarray(tr.event_times[i]), np.asarray(one.event_times), rtol=0, atol=tol / 10)
        for field in ("x_pre", "x_post", "impulses", "event_states"):
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

    # the batch interface of simulate_batch: with on_max_impacts="stop" a member that reached
    # max_impacts is stopped, not failed; without it (via) it failed, and says so
    maxed = np.asarray(tr.status) == 1
    assert maxed.any() and (~maxed).any()
    np.testing.assert_array_equal(tr.stopped, maxed)
    np.testing.assert_array_equal(tr.ok, np.asarray(tr.t_final) == T1)
    np.testing.assert_array_equal(via.failed, maxed)
    assert sorted(via.reasons) == np.flatnonzero(maxed).tolist()
    assert all("max_impacts=40" in via.reasons[m] for m in via.reasons)
    assert via.counts() == {"success": int((~maxed).sum()), "max_impacts": int(maxed.sum())}
    assert f"{len(gam)} members: success {int((~maxed).sum())}" in via.summary()
    # on_error="raise" (simulate_batch's default): the failed members, with the result
    with pytest.raises(nhjax.BatchError) as err:
        nhjax.simulate_batch(balls, x0, T1, in_axes={"system": ["A"], "x0": 0}, lanes=2, workers=2, saveat=5,
                             **OPTS)
    assert err.value.members == np.flatnonzero(maxed).tolist()
    np.testing.assert_array_equal(np.asarray(err.value.trajectory.num_impacts), n)

    # A sweep with a member that starts below the table (inserted at index 3): it is not
    # solved, its reason says why, and the other members are exactly the solves above (the
    # same members in the same chunks and lanes)
    A = np.insert(gam * G / W**2, 3, gam[0] * G / W**2)
    bad_x0 = np.insert(x0, 3, [-0.01, 0.0], axis=0)
    sweep = nhjax.simulate_impacts_batch(eqx.tree_at(lambda s: s.A, ball, jnp.asarray(A)), bad_x0, T1,
                                         in_axes={"system": ["A"], "x0": 0}, lanes=2, workers=2, saveat=5,
                                         on_max_impacts="stop", on_error="return", **OPTS)
    assert sweep.status_names()[3] == "bad input" and sweep.failed.tolist() == [i == 3 for i in range(8)]
    assert "forbidden side of unilateral[0] (psi = -0.01" in sweep.reasons[3]
    assert float(sweep.t_final[3]) == 0.0 and int(sweep.num_impacts[3]) == 0
    assert np.isnan(np.asarray(sweep.impact_times[3])).all() and np.isnan(np.asarray(sweep.x_final[3])).all()
    keep = np.arange(8) != 3
    for field in ("impact_times", "x_post", "x_final", "xs", "num_steps", "status"):
        np.testing.assert_array_equal(np.asarray(getattr(sweep, field))[keep], np.asarray(getattr(tr, field)))


def test_bad_members_are_refused_before_any_solve(monkeypatch):
    """Each member gets the checks of simulate_impacts before anything is solved: a
    restitution of 1.5 on one member, a start below the table, NaN; shared bad inputs get
    the single call's own error; budgets and shapes are named."""
    from nhjax.integrate import impacts

    def no_solve(*a, **k):
        raise AssertionError("a batch with bad members was solved")

    monkeypatch.setattr(impacts, "_lockstep_chunk", no_solve)
    ball, balls, gam, x0 = _members()
    alpha = np.full(gam.size, 0.5)
    alpha[2] = 1.5
    x0 = x0.copy()
    x0[4] = [-0.02, 0.0]
    x0[5, 1] = np.nan
    both = eqx.tree_at(lambda s: (s.A, s.restitution), ball, (jnp.asarray(gam * G / W**2), jnp.asarray(alpha)))
    axes = {"system": ["A", "restitution"], "x0": 0}
    with pytest.raises(nhjax.BatchError) as err:
        nhjax.simulate_impacts_batch(both, x0, T1, in_axes=axes, **OPTS)
    assert err.value.members == [2, 4, 5]
    r = dict(zip(err.value.members, err.value.reasons))
    assert "restitution[0] = 1.5 outside [0, 1]" in r[2]
    assert "forbidden side of unilateral[0] (psi = -0.02" in r[4] and "NaN" in r[5]
    # simulate_batch on an impact system: the same checks (and on_error="raise" is its default)
    with pytest.raises(nhjax.BatchError, match="bad inputs in 3 member"):
        nhjax.simulate_batch(both, x0, T1, in_axes=axes, **OPTS)
    # shared inputs: the error simulate_impacts raises for the same numbers
    shared = eqx.tree_at(lambda s: s.restitution, ball, jnp.asarray(1.5))
    for call in (lambda: nhjax.simulate_impacts(shared, jnp.array([0.1, 0.0]), T1),
                 lambda: nhjax.simulate_impacts_batch(shared, x0[:2], T1)):
        with pytest.raises(ParameterError, match="restitution must lie in \\[0, 1\\]") as e:
            call()
        assert e.value.name == "restitution"
    with pytest.raises(nhjax.BatchError) as err:  # a shared x0 below every member's table
        nhjax.simulate_impacts_batch(balls, np.array([-0.02, 0.0]), T1, in_axes={"system": ["A"]})
    assert err.value.members == list(range(gam.size))
    with pytest.raises(ParameterError, match="max_impacts must be at least 1"):
        nhjax.simulate_impacts_batch(ball, x0[:2], T1, max_impacts=0)
    with pytest.raises(ParameterError, match="rest_velocity"):
        nhjax.simulate_impacts_batch(ball, x0[:2], T1, rest_velocity=-1.0)
    with pytest.raises(ParameterError, match="unknown option"):
        nhjax.simulate_impacts_batch(ball, x0[:2], T1, max_imppacts=3)
    for bad in (np.ones((3, 3)), np.ones(3), "x"):
        with pytest.raises(nhjax.StateError, match="x0"):
            nhjax.simulate_impacts_batch(ball, bad, T1)
    # simulate_batch's default tolerances for impact systems are simulate_impacts' (1e-10)
    seen = {}
    monkeypatch.setattr(impacts, "simulate_impacts_batch", lambda *a, **k: seen.update(k))
    nhjax.simulate_batch(ball, x0[:2], T1)
    assert seen["rtol"] == seen["atol"] == 1e-10 and seen["on_error"] == "raise"


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


def test_lazy_cond_gives_each_lane_what_lax_cond_gives_it_and_skips_an_untaken_branch():
    """lockstep.lazy_cond, which the impact batch's iteration uses for its branches: under
    vmap (lanes first or last, nested, a closure over a batched value, a shared
    predicate) every lane gets lax.cond's value; the true branch runs only in calls
    where some lane takes it, where lax.cond under vmap runs it on every call (its
    batched predicate becomes a select)."""
    from nhjax.integrate.lockstep import lazy_cond

    def f(cond, x, k):
        y = jnp.sin(x) * k  # a batched value the branches close over
        inner = lambda z: cond(z > 1.5, lambda w: w * 10.0, lambda w: w - y, z)  # noqa: E731
        return cond(x > 0.0, inner, lambda z: -z * y, x), cond(k > 0.0, lambda z: z + 1.0, lambda z: z, y)

    xs, ks = jnp.array([-1.0, 0.5, 2.0, 3.0]), jnp.array([1.0, -2.0, 3.0, 0.5])
    want = jax.vmap(lambda x, k: f(jax.lax.cond, x, k))(xs, ks)
    shared = jax.vmap(lambda x: f(jax.lax.cond, x, 2.0))(xs)  # k shared: its predicate too
    for got, ref in ((jax.vmap(lambda x, k: f(lazy_cond, x, k))(xs, ks), want),
                     (jax.jit(jax.vmap(lambda x, k: f(lazy_cond, x, k), in_axes=(-1, -1), out_axes=-1))(xs, ks), want),
                     (jax.vmap(lambda x: f(lazy_cond, x, 2.0))(xs), shared)):
        for g, w in zip(got, ref):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    assert [float(v) for v in f(lazy_cond, 3.0, 0.5)] == [float(v) for v in f(jax.lax.cond, 3.0, 0.5)]

    calls = []

    def count(cond, x):
        def costly(z):
            jax.debug.callback(lambda: calls.append(1))
            return z * 2.0
        return cond(x > 10.0, costly, lambda z: z + 1.0, x)

    for cond, xs_, taken in ((lazy_cond, jnp.arange(4.0), False), (lazy_cond, jnp.array([0.0, 20.0]), True),
                             (jax.lax.cond, jnp.arange(4.0), True)):
        calls.clear()
        out = jax.jit(jax.vmap(lambda x: count(cond, x)))(xs_)
        jax.block_until_ready(out)
        jax.effects_barrier()
        assert bool(calls) == taken, (cond, xs_, len(calls))
        np.testing.assert_array_equal(np.asarray(out), np.where(np.asarray(xs_) > 10.0, 2 * xs_, xs_ + 1.0))


def test_in_axes_that_is_not_a_dict_is_named():
    """in_axes given as a list or a string (a raw TypeError/ValueError of dict() before)."""
    ball = BouncingBall()
    X = np.array([[0.1, 0.0], [0.2, 0.0]])
    with pytest.raises(ParameterError, match="simulate_impacts_batch: in_axes must be a dict") as err:
        nhjax.simulate_impacts_batch(ball, X, 1.0, in_axes="x0")
    assert err.value.name == "in_axes"
    with pytest.raises(ParameterError, match=r"simulate_batch \(a system with one-sided constraints\): in_axes must"):
        nhjax.simulate_batch(ball, X, 1.0, in_axes=[0], progress=False)
    cat = nhjax.scenes.FallingCat()
    x0 = cat.initial_state(0.8)
    with pytest.raises(ParameterError, match="simulate_batch: in_axes must be a dict"):
        nhjax.simulate_batch(cat, jnp.stack([x0, x0]), 0.1, in_axes=[0], progress=False)
