"""nhjax.DiscreteAdjoint: the discrete adjoint of the Runge-Kutta steps.

diffrax holds the step-size controller out of the derivative, so the discrete
adjoint and differentiating diffrax's loop (RecursiveCheckpointAdjoint) compute
the derivative of the same discrete map: they must agree to round-off, on flat
states, on Lie-group states (RKMK), with a projection after each step, through
dense output at saved times, through the integrated work, and under vmap. Both
must also agree with central differences to the solve's accuracy.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.mechanics import Lagrangian
from nhjax.scenes import FallingCat, ShellWithTop

RC = diffrax.RecursiveCheckpointAdjoint()
TORQUE = nhjax.Sinusoids([-0.015, 0.0], [0.04, 0.02], [1.7, 0.9], [0.0, np.pi / 2])


def _cat_loss(adjoint, saveat):
    """Loss on the cat in the torque amplitudes, the inertia ratio lam and the initial
    state: terminal turn, plus (with saved times) a sum over the saved states and the
    final work of the torques."""

    def loss(p):
        amp, lam, x0 = p
        cat = FallingCat(lam=lam)
        ctrl = nhjax.Sinusoids(TORQUE.offset, amp, TORQUE.omega, TORQUE.phase)
        tr = nhjax.simulate(cat, x0, 6.0, control=ctrl, rtol=1e-10, atol=1e-10, saveat=saveat,
                            adjoint=adjoint, diagnostics=False, track_work=True)
        out = tr.xs[-1, 2] ** 2 + 3.0 * tr.x_end[4]
        if not isinstance(saveat, int) or saveat > 2:
            out = out + jnp.sum(jnp.sin(tr.xs[:, 0]) * tr.xs[:, 3]) + 10.0 * tr.work[-1]
        return out

    return loss


def _cat_params():
    return (TORQUE.amplitude, jnp.asarray(0.3157894736842105), FallingCat().initial_state(0.8, chi_dot=0.5))


# (all slow: the default run compares DiscreteAdjoint's gradient with the differentiated
# loop's, RecursiveCheckpointAdjoint under jax.jit, to 1e-12 and with differences in
# test_first_answers; these add saved states' cotangents and a system parameter)
@pytest.mark.parametrize("saveat", [pytest.param(2, marks=pytest.mark.slow), pytest.param(41, marks=pytest.mark.slow),
                                    pytest.param("uneven", marks=pytest.mark.slow)])
def test_cat_gradient_equals_differentiated_loop_and_fd(saveat):
    if saveat == "uneven":  # save times bunched and spread, one at t0, one at t1
        saveat = np.concatenate([[0.0], np.linspace(0.001, 0.05, 7), [1.3, 2.9, 3.0, 5.5, 6.0]])
    p = _cat_params()
    g_disc = jax.jit(jax.grad(_cat_loss(nhjax.DiscreteAdjoint(), saveat)))(p)
    g_rc = jax.jit(jax.grad(_cat_loss(RC, saveat)))(p)
    for a, b in zip(jax.tree_util.tree_leaves(g_disc), jax.tree_util.tree_leaves(g_rc)):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-11 * float(np.max(np.abs(b))))
    # and against central differences in the amplitudes and lam (truncation ~h^2, error ~tol/h)
    f = jax.jit(_cat_loss(None, saveat))
    amp, lam, x0 = p
    h = 1e-5
    fd = [(f((amp + h * e, lam, x0)) - f((amp - h * e, lam, x0))) / (2 * h) for e in np.eye(2)]
    fd.append((f((amp, lam + h, x0)) - f((amp, lam - h, x0))) / (2 * h))
    got = np.concatenate([np.asarray(g_disc[0]), [float(g_disc[1])]])
    np.testing.assert_allclose(got, np.asarray(fd), rtol=2e-5)


@pytest.mark.slow  # (17 s; tangents on defaults are checked by test_first_answers)
def test_tangents_mode_agrees_with_the_differentiated_loop():
    """Forward sensitivities carried through the solve ("tangents"), here with all D = 9
    inputs of the cat loss (amplitudes, lam, initial state; saved states and work)."""
    p = _cat_params()
    g_t = jax.jit(jax.grad(_cat_loss(nhjax.DiscreteAdjoint(jacobians="tangents"), 41)))(p)
    g_rc = jax.jit(jax.grad(_cat_loss(RC, 41)))(p)
    for a, b in zip(jax.tree_util.tree_leaves(g_t), jax.tree_util.tree_leaves(g_rc)):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-11 * float(np.max(np.abs(b))))


@pytest.mark.slow  # (25 s; make test-all)
def test_auto_mode_follows_the_number_of_differentiated_inputs(monkeypatch):
    """auto: tangents for D <= max_tangents differentiated numbers, per-step VJPs above."""
    from nhjax.integrate import adjoint as A

    used = []
    monkeypatch.setattr(A, "_tangent_forward", lambda *a, f=A._tangent_forward: used.append("tangents") or f(*a))
    monkeypatch.setattr(A, "_sequential_vjps", lambda *a, f=A._sequential_vjps: used.append("vjp") or f(*a))
    cat = FallingCat()
    x0 = cat.initial_state(0.8, chi_dot=0.5)

    def loss(amp, x0, adjoint):
        ctrl = nhjax.Sinusoids(TORQUE.offset, amp, TORQUE.omega, TORQUE.phase)
        tr = nhjax.simulate(cat, x0, 3.0, control=ctrl, rtol=1e-9, atol=1e-9, saveat=2,
                            adjoint=adjoint, diagnostics=False, track_work=False)
        return tr.x_end[2] ** 2

    g_few = jax.grad(loss)(TORQUE.amplitude, x0, nhjax.DiscreteAdjoint())  # D = 2
    g_many = jax.grad(loss, argnums=(0, 1))(TORQUE.amplitude, x0, nhjax.DiscreteAdjoint())  # D = 7
    g_rc = jax.grad(loss, argnums=(0, 1))(TORQUE.amplitude, x0, RC)
    assert used == ["tangents", "vjp"]
    np.testing.assert_allclose(g_few, g_rc[0], rtol=1e-11)
    np.testing.assert_allclose(g_many[0], g_rc[0], rtol=1e-11)
    np.testing.assert_allclose(g_many[1], g_rc[1], rtol=1e-11, atol=1e-11 * float(jnp.max(jnp.abs(g_rc[1]))))


@pytest.mark.slow  # (event-time derivatives of impacts: test_bouncing_ball; the chart guard's stop: test_falling_cat; make test-all)
def test_tangents_differentiate_a_guards_event_time():
    """A solve stopped at the chart's edge (sin theta = eps): theta_dot(t*) + t* in the initial
    tilt rate. "tangents" differentiates the event time t* (like the differentiated loop
    and central differences); the recorded modes hold t* fixed (documented)."""
    cat = FallingCat(chart_eps=1e-3)

    def loss(w, adjoint):
        x0 = cat.initial_state(0.3, theta_dot=w)
        tr = nhjax.simulate(cat, x0, 2.0, on_guard="stop", rtol=1e-11, atol=1e-11, saveat=2,
                            adjoint=adjoint, diagnostics=False)
        return tr.x_end[3] + tr.t_final

    w = jnp.asarray(-1.0)
    g_t = jax.jit(jax.grad(lambda w: loss(w, nhjax.DiscreteAdjoint(jacobians="tangents"))))(w)
    g_rc = jax.jit(jax.grad(lambda w: loss(w, RC)))(w)
    f = jax.jit(lambda w: loss(w, None))
    assert 0.2 < float(nhjax.simulate(cat, cat.initial_state(0.3, theta_dot=-1.0), 2.0,
                                      on_guard="stop").t_final) < 0.4
    h = 1e-5
    fd = (f(w + h) - f(w - h)) / (2 * h)
    np.testing.assert_allclose(g_t, g_rc, rtol=1e-8)
    np.testing.assert_allclose(g_t, fd, rtol=1e-5)
    assert abs(float(g_t)) > 0.01


@pytest.mark.slow  # default runs cover "tangents", "vjp" (the cat; the robot in test_steering) and auto's choice
def test_three_ways_of_forming_the_step_products_agree():
    """Chunked forward-mode Jacobians, chunked reverse-mode Jacobians (chunks that do not
    divide the step count) and one VJP per step."""
    p = _cat_params()
    grads = [jax.jit(jax.grad(_cat_loss(nhjax.DiscreteAdjoint(jacobians=m, chunk=c), 41)))(p)
             for m, c in (("forward", 16), ("reverse", 7), ("vjp", 64))]
    for g in grads[1:]:
        for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(grads[0])):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * float(np.max(np.abs(b))))


# slow (~50 s on 2 cores); the default run keeps Lie-group gradients through test_steering's
# shooting-gradient test (ShellWithTop, DiscreteAdjoint against central differences)
@pytest.mark.slow
def test_lie_group_state_gradient():
    """The spherical robot on R^2 x SO(3) x SO(3) (RKMK45): final position, top attitude
    and spin in the torque amplitudes and the initial top spin."""
    robot = ShellWithTop()

    def loss(p, adjoint):
        amp, spin = p
        x0 = robot.initial_state(top_omega=jnp.array([0.0, 0.0, spin]))
        ctrl = nhjax.Sinusoids(jnp.zeros(3), amp, jnp.array([1.1, 0.7, 2.0]), jnp.array([0.0, 0.4, 1.0]))
        tr = nhjax.simulate(robot, x0, 2.0, control=ctrl, rtol=1e-9, atol=1e-9, saveat=5,
                            adjoint=adjoint, diagnostics=False)
        (xy, _, Rt), v = tr.x_end
        return xy[0] ** 2 + xy[1] + Rt[0, 2] + v[6] + jnp.sum(tr.xs[1][:, 0])

    p = (jnp.array([0.02, -0.01, 0.015]), jnp.asarray(3.0))
    g_disc = jax.jit(jax.grad(lambda p: loss(p, nhjax.DiscreteAdjoint())))(p)
    g_rc = jax.jit(jax.grad(lambda p: loss(p, RC)))(p)
    for a, b in zip(jax.tree_util.tree_leaves(g_disc), jax.tree_util.tree_leaves(g_rc)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * float(np.max(np.abs(b))))
    assert float(jnp.max(jnp.abs(g_disc[0]))) > 1e-3  # the loss does depend on the torques


@jax.custom_vjp
def _sine(x):
    """sin with a reverse-mode rule only: JAX refuses its forward-mode derivative."""
    return jnp.sin(x)


_sine.defvjp(lambda x: (jnp.sin(x), x), lambda x, g: (jnp.cos(x) * g,))


class _SineFeedback(eqx.Module):
    k: jax.Array

    def __call__(self, t, x):
        return -self.k * _sine(x[:1])


def test_auto_takes_the_vjps_where_a_step_has_no_forward_mode_rule(monkeypatch, tmp_path):
    """A control built on a custom_vjp function (no forward-mode rule): "auto" with
    D = 1 <= max_tangents tries the tangents, meets JAX's refusal while tracing them
    and forms the backward pass by VJPs instead, with the differentiated loop's
    derivative; "tangents" asked for by name passes the refusal on. (An empty program
    cache: a backward pass stored by an earlier run would be loaded, not traced.)"""
    from nhjax import _primitive, _programs
    from nhjax.integrate import adjoint as A

    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    monkeypatch.setattr(_primitive, "_SPECS", {})

    used = []
    monkeypatch.setattr(A, "_sequential_vjps", lambda *a, f=A._sequential_vjps: used.append("vjp") or f(*a))
    osc = Lagrangian(1, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: 2.0 * q @ q,
                     force=lambda t, q, qd, u: u, control_dim=1)

    def loss(k, adjoint):
        return nhjax.simulate(osc, jnp.array([1.0, 0.0]), 2.0, control=_SineFeedback(k), rtol=1e-9, atol=1e-9,
                              saveat=2, adjoint=adjoint, diagnostics=False).x_end[0]

    k = jnp.asarray(0.7)
    g_auto = jax.grad(lambda k: loss(k, nhjax.DiscreteAdjoint()))(k)
    assert used == ["vjp"]
    g_rc = jax.grad(lambda k: loss(k, RC))(k)
    assert abs(float(g_rc)) > 1e-2
    np.testing.assert_allclose(g_auto, g_rc, rtol=1e-10)
    with pytest.raises(TypeError, match="custom_vjp"):
        jax.grad(lambda k: loss(k, nhjax.DiscreteAdjoint(jacobians="tangents")))(k)


@pytest.mark.slow  # (25 s; make test-all)
def test_projected_steps_gradient():
    """A pendulum in Cartesian coordinates (|q| = 1): projection onto the position and
    velocity constraints after every step (Newton and a KKT solve inside the step map)."""
    pend = Lagrangian(2, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: 9.81 * q[1],
                      position_constraints=lambda t, q: jnp.atleast_1d(q @ q - 1.0))

    def loss(w, adjoint):
        s, c = jnp.sin(w[0]), jnp.cos(w[0])
        x0 = jnp.array([s, -c, w[1] * c, w[1] * s])
        tr = nhjax.simulate(pend, x0, 3.0, rtol=1e-9, atol=1e-9, saveat=7, adjoint=adjoint,
                            diagnostics=False)
        return jnp.sum(tr.xs[:, 0] ** 2) + tr.x_end[3]

    w = jnp.array([0.4, 1.5])
    g_disc = jax.jit(jax.grad(lambda w: loss(w, nhjax.DiscreteAdjoint())))(w)
    g_rc = jax.jit(jax.grad(lambda w: loss(w, RC)))(w)
    np.testing.assert_allclose(g_disc, g_rc, rtol=1e-10)
    h = 1e-5
    f = jax.jit(lambda w: loss(w, None))
    fd = np.array([(f(w + h * e) - f(w - h * e)) / (2 * h) for e in np.eye(2)])
    np.testing.assert_allclose(g_disc, fd, rtol=1e-5)


@pytest.mark.slow  # (batched solves = one by one: test_batch; the discrete adjoint's gradient: test_first_answers; make test-all)
def test_vmapped_gradients_equal_one_by_one():
    """A batch of gradients whose members take different numbers of steps."""
    cat = FallingCat()

    def loss(x0):
        tr = nhjax.simulate(cat, x0, 5.0, control=TORQUE, rtol=1e-9, atol=1e-9, saveat=2,
                            adjoint=nhjax.DiscreteAdjoint(chunk=8), diagnostics=False)
        return tr.xs[-1, 2] + tr.xs[-1, 4] ** 2

    X0 = jnp.stack([cat.initial_state(0.8, chi_dot=c, theta_dot=c / 3) for c in (0.0, 2.0, 6.0)])
    batched = jax.jit(jax.vmap(jax.grad(loss)))(X0)
    single = jax.jit(jax.grad(loss))
    for i in range(3):
        np.testing.assert_allclose(batched[i], single(X0[i]), rtol=1e-12, atol=1e-14)
    steps = [int(nhjax.simulate(cat, x, 5.0, control=TORQUE, rtol=1e-9, atol=1e-9).num_accepted_steps)
             for x in X0]
    assert max(steps) > 5 * min(steps), steps  # measured 39, 80, 271 accepted steps


@pytest.mark.slow  # (vmapped discrete-adjoint gradients = one by one: test_vmapped_gradients_equal_one_by_one; the tangents mode on defaults: test_first_answers; make test-all)
def test_vmapped_tangent_gradients_equal_one_by_one():
    """The tangents mode (D = 2 amplitudes) under vmap, members spinning at different
    rates (different step counts)."""
    cat = FallingCat()

    def loss(amp, chi_dot):
        ctrl = nhjax.Sinusoids(TORQUE.offset, amp, TORQUE.omega, TORQUE.phase)
        x0 = jax.lax.stop_gradient(cat.initial_state(0.8, chi_dot=chi_dot))
        tr = nhjax.simulate(cat, x0, 5.0, control=ctrl, rtol=1e-9, atol=1e-9, saveat=2,
                            adjoint=nhjax.DiscreteAdjoint(), diagnostics=False, track_work=False)
        return tr.x_end[2] ** 2

    amps = jnp.stack([TORQUE.amplitude, 2 * TORQUE.amplitude, 0.5 * TORQUE.amplitude])
    rates = jnp.array([0.0, 2.0, 6.0])
    batched = jax.jit(jax.vmap(jax.grad(loss)))(amps, rates)
    single = jax.jit(jax.grad(loss))
    for i in range(3):
        np.testing.assert_allclose(batched[i], single(amps[i], rates[i]), rtol=1e-12, atol=1e-14)
    assert float(jnp.min(jnp.abs(batched))) > 0.1


def test_bad_use_is_named():
    cat = FallingCat()
    x0 = cat.initial_state(0.8)
    with pytest.raises(ValueError, match="jacobians"):
        nhjax.DiscreteAdjoint(jacobians="sideways")
    with pytest.raises(nhjax.SystemKindError, match="explicit"):
        nhjax.simulate(cat, x0, 1.0, solver=diffrax.Kvaerno5(), adjoint=nhjax.DiscreteAdjoint())
    # the step budget it records is max_steps: exhausting it says so
    with pytest.raises(nhjax.IntegrationError, match="max_steps=20 exhausted"):
        nhjax.simulate(cat, x0, 10.0, control=TORQUE, adjoint=nhjax.DiscreteAdjoint(max_steps=20))
