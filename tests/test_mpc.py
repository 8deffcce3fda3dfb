"""Closed-loop model-predictive control (controls.MPC, closed_loop, closed_loop_batch).

On the torque-driven falling cat (5 states, 2 torques; small horizons): the
shrinking-horizon loop with the plant equal to the model reproduces the open-loop
optimum, which is checked against the optimality conditions of the discrete problem
computed here independently (single shooting, jax.grad); a push is rejected by the
real-time iteration with a model error; an unreachable terminal constraint is
reported period by period and the fallback applies the previous plan; bad input is
refused with MPCError before any numerics; a batch member is the same loop run alone.
The interior-point QP is checked against its own optimality conditions, its
stage-wise (Riccati) form against the dense one on the condensed problem; the
disturbance observer's update against its formula, and its offset-free property on
a plant with a constant torque bias.
"""

import functools
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import controls
from controls import MPC, MPCError, ProblemError, box_qp, closed_loop, closed_loop_batch
from controls._qp import _spd_inverse, stage_qp
from nhjax.mechanics import AbstractSystem, Lagrangian
from controls.tasks.somersault import Effort
from nhjax.scenes import FallingCat, FallingCatKinematic, ShellWithTop

PERIOD, N, T = 0.1, 10, 1.0
PERIODS = 25  # the regulator's loops (push and batch tests share one compiled loop)


class Quadratic(eqx.Module):
    """w . (x - target)^2 (terminal cost) or, called with (t, x, u), the running cost
    w . (x - target)^2 + r |u|^2."""

    target: jax.Array
    w: jax.Array
    r: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(1.0))

    def __call__(self, *args):
        if len(args) == 1:
            return jnp.sum(self.w * (args[0] - self.target) ** 2)
        _, x, u = args
        return jnp.sum(self.w * (x - self.target) ** 2) + self.r * (u @ u)


class ShapeAt(eqx.Module):
    """Terminal constraints: the shape (theta, chi) at a target and the cat at rest."""

    target: jax.Array

    def __call__(self, x):
        return jnp.concatenate([x[:2] - self.target, x[3:]])


CAT = FallingCat()
X0 = CAT.initial_state(0.8)
TARGET = jnp.array([0.9, 0.3, 0.0, 0.0, 0.0])


def _terminal_cost_ocp():
    return controls.OCP(CAT, X0, T, Effort(), terminal_cost=Quadratic(TARGET, jnp.array([100.0, 100, 0, 10, 10])))


def _constrained_ocp(bound):
    return controls.OCP(CAT, X0, T, Effort(), terminal_constraints=ShapeAt(TARGET[:2]), u_lower=-bound,
                        u_upper=bound)


def _single_shooting(mpc):
    """(J(u), psi(u)) of the discrete horizon problem from X0 at t = 0, written here
    from the model's vector field (classical RK4, ``mpc.substeps`` steps per interval)."""
    ocp, h, k = mpc.ocp, float(mpc.h), mpc.substeps
    dt = h / k

    def f(t, y, u):
        return jnp.concatenate([ocp.system.vector_field(t, y[:-1], u), ocp.running_cost(t, y[:-1], u)[None]])

    def rk4(y, tu):
        t, u = tu
        k1 = f(t, y, u)
        k2 = f(t + dt / 2, y + dt / 2 * k1, u)
        k3 = f(t + dt / 2, y + dt / 2 * k2, u)
        k4 = f(t + dt, y + dt * k3, u)
        return y + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4), None

    def run(u):
        ts = jnp.arange(mpc.intervals * k) * dt  # the steps' start times
        y, _ = jax.lax.scan(rk4, jnp.concatenate([X0, jnp.zeros(1)]), (ts, jnp.repeat(u, k, axis=0)))
        phi, psi = ocp.terminal(y[:-1])
        return phi + y[-1], psi

    return run


_solve = eqx.filter_jit(lambda mpc, plan, y: mpc.solve(plan, y, 0.0))


@pytest.mark.parametrize("kind", [
    pytest.param("terminal cost", marks=pytest.mark.slow(reason="two more compiled programs; the default-run "
                                                              "sibling 'terminal constraint, bounds active' checks "
                                                              "the same loop against a stricter KKT test")),
    "terminal constraint, bounds active",
    pytest.param("terminal penalty, exact Hessian", marks=pytest.mark.slow(
        reason="two more compiled programs; the default-run sibling 'terminal constraint, bounds active' checks "
               "the same loop (the penalty's optimum is checked as the terminal cost's)"))])
def test_shrinking_loop_reproduces_the_open_loop_optimum(kind):
    """Model = plant, no disturbance, shrinking horizon, converged solves: the closed
    loop's inputs and states are the open-loop optimum's to 1e-6 (Bellman's principle
    for the discrete problem), and that optimum satisfies the KKT conditions computed
    here by single shooting: the gradient of J plus the constraints' Jacobian times
    least-squares multipliers vanishes on the inputs off their bounds, points outward
    on those at a bound, and psi = 0."""
    bound = 0.2  # the unconstrained optimum reaches |u| = 0.26
    extra = {}
    if kind == "terminal cost":
        ocp = _terminal_cost_ocp()
    elif kind.startswith("terminal penalty"):
        ocp = controls.OCP(CAT, X0, T, Effort(), terminal_constraints=ShapeAt(TARGET[:2]))
        extra = dict(terminal="penalty", terminal_weight=100.0, hessian="exact")
    else:
        ocp = _constrained_ocp(bound)
    mpc = MPC(ocp, PERIOD, N, mode="converged", horizon="shrinking", substeps=2, tol=1e-10, **extra)
    plan, status = _solve(mpc, mpc.init(), X0)
    assert bool(status.converged) and not bool(status.fallback)
    u = np.asarray(plan.u)

    run = _single_shooting(mpc)
    if kind.startswith("terminal penalty"):  # J + w |psi|^2, no constraints left
        plain = run
        run = lambda v: (plain(v)[0] + 100.0 * jnp.sum(plain(v)[1] ** 2), jnp.zeros(0))  # noqa: E731
    def values(v):
        J, psi = run(v)
        y = jnp.concatenate([J[None], psi])
        return y, y

    # one forward-mode program gives J, psi, dJ/du and dpsi/du (three programs cost the
    # default run ~8 s more of compiling)
    D, y = jax.jit(jax.jacfwd(values, has_aux=True))(jnp.asarray(u))
    J, psi, D = y[0], y[1:], np.asarray(D).reshape(y.shape[0], -1)
    g = D[0]
    assert abs(float(J) - float(status.cost)) < 1e-12 * max(1.0, abs(float(J)))
    if kind != "terminal constraint, bounds active":
        assert np.abs(g).max() < 1e-8 * max(1.0, float(J))
    else:
        assert np.abs(np.asarray(psi)).max() < 1e-9
        A = D[1:]
        at_lo, at_hi = u.ravel() <= -bound + 1e-7, u.ravel() >= bound - 1e-7
        assert (at_lo | at_hi).sum() >= 2, "the test wants the bounds active somewhere"
        free = ~(at_lo | at_hi)
        nu = np.linalg.lstsq(A[:, free].T, -g[free], rcond=None)[0]
        r = g + A.T @ nu  # dJ/du + nu . dpsi/du
        assert np.abs(r[free]).max() < 1e-7 * np.abs(g).max()
        assert np.all(r[at_lo] > -1e-9) and np.all(r[at_hi] < 1e-9)  # pushing against the bound

    loop = closed_loop(mpc, CAT, X0, N)
    assert not np.asarray(loop.status.fallback).any() and np.asarray(loop.status.converged).all()
    np.testing.assert_allclose(np.asarray(loop.inputs), u, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(loop.trajectory.xs), np.asarray(plan.s), rtol=0, atol=1e-6)
    # the plant's running cost plus the terminal part at the plant's final state
    phi, psi_end = ocp.terminal(loop.trajectory.xs[-1])
    final = float(phi) + (100.0 * float(jnp.sum(psi_end**2)) if kind.startswith("terminal penalty") else 0.0)
    assert abs(float(loop.cost) + final - float(J)) < 1e-6


@pytest.mark.slow(reason="compiles the per-period step and plant programs; the default-run sibling "
                         "test_push_is_rejected_by_the_real_time_iteration runs the same loop as one scan")
def test_timed_loop_is_the_scanned_loop():
    """closed_loop(timing=True) steps the same per-period functions from Python: the
    same inputs and states as the scanned loop, and a positive solve time per period."""
    mpc, plant = _regulator(1.1)
    kick = [(0.5, np.array([0.0, 0.0, 0.0, 1.5, 1.0]))]
    scanned = closed_loop(mpc, plant, X0, PERIODS, pushes=kick)
    timed = closed_loop(mpc, plant, X0, PERIODS, pushes=kick, timing=True)
    np.testing.assert_allclose(np.asarray(timed.inputs), np.asarray(scanned.inputs), rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(timed.trajectory.xs), np.asarray(scanned.trajectory.xs), rtol=0,
                               atol=1e-10)
    assert np.all(np.asarray(timed.status.solve_ms) > 0) and np.isnan(np.asarray(scanned.status.solve_ms)).all()


def _regulator(I1_scale=1.0):
    """Receding-horizon regulation of the shape to (0.8, 0) at rest (psi is free: it is
    not stabilizable by a smooth feedback at rest)."""
    target = jnp.array([0.8, 0.0, 0.0, 0.0, 0.0])
    w = jnp.array([50.0, 50.0, 0.0, 1.0, 1.0])
    ocp = controls.OCP(CAT, X0, T, Quadratic(target, w, jnp.asarray(1.0)), terminal_cost=Quadratic(target, 10 * w),
                       u_lower=-3.0, u_upper=3.0)
    return MPC(ocp, PERIOD, N, mode="rti", substeps=1), FallingCat(I1=CAT.I1 * I1_scale)


def test_push_is_rejected_by_the_real_time_iteration():
    """A kick of 1.5 rad/s on the bend rate and 1 rad/s on the twist rate at t = 0.5 s,
    a plant whose inertia I1 is 10% above the model's: the shape error jumps, then
    decays below a tenth of its peak within 1.5 s and stays there (the torques saturate
    at their bound of 3 N m right after the kick); every period's QP succeeded, no
    fallback."""
    mpc, plant = _regulator(1.1)
    kick = np.array([0.0, 0.0, 0.0, 1.5, 1.0])
    loop = closed_loop(mpc, plant, X0, PERIODS, pushes=[(0.5, kick)])
    xs, ts = np.asarray(loop.trajectory.xs), np.asarray(loop.trajectory.ts)
    err = np.abs(xs[:, [0, 1]] - [0.8, 0.0]).max(1) + np.abs(xs[:, [3, 4]]).max(1) * PERIOD
    peak = err[ts <= 1.0].max()
    assert peak > 0.05  # the push moved the cat
    assert err[ts >= 2.0].max() < 0.1 * peak
    assert np.asarray(loop.status.qp_ok).all() and not np.asarray(loop.status.fallback).any()


@pytest.mark.parametrize("mode", [
    "rti", pytest.param("converged", marks=pytest.mark.slow(reason="one more compiled loop; the default-run sibling "
                                                                   "'rti' checks the same statuses and fallback"))])
def test_unreachable_terminal_constraint_is_reported_every_period(mode):
    """|u| <= 1e-3 N m cannot bring the shape to the target in 1 s: every period's
    horizon QP fails, the status says so (qp_ok False, fallback True, not converged,
    cost NaN), and the inputs applied are the previous plan's next segment: here the
    guess, shifted period after period (its tail repeats its last input)."""
    ocp = controls.OCP(CAT, X0, T, Effort(), terminal_constraints=ShapeAt(jnp.array([1.4, 1.0])), u_lower=-1e-3,
                       u_upper=1e-3)
    mpc = MPC(ocp, PERIOD, N, mode=mode, qp_iter=40, max_iter=5)
    guess = np.tile([[5e-4, -2e-4]], (N, 1))
    loop = closed_loop(mpc, CAT, X0, 4, u_guess=guess)
    st = loop.status
    assert np.asarray(st.fallback).all() and not np.asarray(st.converged).any()
    assert not np.asarray(st.qp_ok).all() and np.isnan(np.asarray(st.cost)).all()
    np.testing.assert_array_equal(np.asarray(loop.inputs), np.tile(guess[:1], (4, 1)))


def test_bad_input_gets_a_named_error_before_numerics():
    ocp = _terminal_cost_ocp()
    for kw, words in [(dict(period=0.0), "positive"), (dict(period=-0.1), "positive"),
                      (dict(period=2.0), "shorter than the period"), (dict(period=0.15), "whole number")]:
        with pytest.raises(MPCError, match=words):
            MPC(ocp, kw["period"], N)
    with pytest.raises(MPCError, match="vector state"):
        from controls.tasks import sphere_steering

        MPC(sphere_steering(ShellWithTop(), (0.1, 0.0), 1.0), 0.1, 10)
    mpc = MPC(ocp, PERIOD, N)
    with pytest.raises(MPCError, match="does not match the model"):
        closed_loop(mpc, FallingCatKinematic(), X0, 3)
    with pytest.raises(MPCError, match="does not match the model"):
        closed_loop(mpc, ShellWithTop(), X0, 3)
    # a plant whose vector field cannot take the model's state (no state names to compare)
    oscillators = Lagrangian(2, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: q @ q, force=lambda t, q, qd, u: u,
                             control_dim=2)
    with pytest.raises(MPCError, match="vector field does not take the model's state of 5 numbers"):
        closed_loop(mpc, oscillators, X0, 3)
    with pytest.raises(MPCError, match="NaN"):
        closed_loop(mpc, CAT, np.array([0.8, np.nan, 0, 0, 0]), 3)
    with pytest.raises(MPCError, match="finite"):
        closed_loop(mpc, CAT, X0, 3, measurement_noise=np.nan, key=jax.random.key(0))
    with pytest.raises(MPCError, match="PRNG key"):
        closed_loop(mpc, CAT, X0, 3, force_noise=0.01)
    with pytest.raises(MPCError, match="NaN"):
        closed_loop(mpc, CAT, X0, 3, pushes=[(0.2, [0, 0, 0, np.nan, 0])])
    with pytest.raises(MPCError, match="members"):
        closed_loop_batch(mpc, CAT, np.array([X0, X0 * np.nan]), 3)
    for bad in (0, 1.5, "two"):
        with pytest.raises(MPCError, match="workers"):
            closed_loop_batch(mpc, CAT, np.array([X0, X0]), 3, workers=bad)
    with pytest.raises(MPCError, match="covers"):
        closed_loop(MPC(ocp, PERIOD, N, horizon="shrinking"), CAT, X0, N + 1)
    assert issubclass(MPCError, ProblemError) and issubclass(MPCError, ValueError)


def _batch_members(rows):
    """The batch tests' members (three kinds: other starts, plant inertias, a push on
    member 1, noise keys), in the order ``rows`` picks them."""
    rows = np.asarray(rows)
    scales = np.array([1.0, 1.1, 0.9])[rows]
    plants = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[FallingCat(I1=CAT.I1 * s) for s in scales])
    X = np.asarray(X0) + np.array([[0.0, 0, 0, 0, 0], [0.05, -0.1, 0, 0, 0.2], [-0.1, 0.05, 0, 0.3, 0]])[rows]
    kicks = np.zeros((3, 1, 5))
    kicks[1, 0, 3] = 1.0
    times = np.full((3, 1), 0.3)
    keys = jax.random.key_data(jax.random.split(jax.random.key(7), 3))
    noise = dict(force_noise=0.01, measurement_noise=1e-3)
    return scales, plants, X, times[rows], kicks[rows], keys[rows], noise


def test_batch_member_is_the_loop_run_alone():
    """Three members with other starts, plant inertias (in_axes plant), pushes and
    noise keys: each member's inputs, states, statuses and cost are those of
    closed_loop on the member alone (the same numbers up to rounding). The loop alone
    solves its QPs densely (``qp="auto"`` picks "dense" for N m = 20 inputs), the batch
    by the Riccati recursion in groups of 2 members (the third member alone in a padded
    group), by default in two threads (a share of one group each): the two solvers' steps
    agree through 25 closed-loop periods. (The Dask test compares this batch with one
    program of all three members, to 1e-12.)"""
    assert _regulator()[0]._qp_kind() == "dense"
    mpc, _ = _regulator()
    scales, plants, X, times, kicks, keys, noise = _batch_members([0, 1, 2])
    keys = jax.random.wrap_key_data(keys)  # (typed keys here, their raw data in the Dask test)
    batch = closed_loop_batch(mpc, plants, X, PERIODS, in_axes={"plant": 0}, pushes=(times, kicks), keys=keys,
                              group=2, **noise)
    for i in (1, 2):
        alone = closed_loop(mpc, FallingCat(I1=CAT.I1 * scales[i]), X[i], PERIODS, pushes=[(0.3, kicks[i, 0])],
                            key=keys[i], **noise)
        np.testing.assert_allclose(np.asarray(batch.inputs[i]), np.asarray(alone.inputs), rtol=0, atol=1e-10)
        np.testing.assert_allclose(np.asarray(batch.trajectory.xs[i]), np.asarray(alone.trajectory.xs), rtol=0,
                                   atol=1e-10)
        np.testing.assert_array_equal(np.asarray(batch.status.fallback[i]), np.asarray(alone.status.fallback))
        assert abs(float(batch.cost[i]) - float(alone.cost)) < 1e-10


def _chart_of_attitudes(y):
    """The model's (theta, chi, psi, theta', chi') from FallingCatAttitudes' state
    (g1, g2, s): psi is the rotation about e2 that takes the first cylinder's attitude
    at psi = 0 (same shape) to g1 (read modulo 2 pi)."""
    g1, _, s = y
    R = g1 @ CAT.poses(jnp.stack([s[0], s[1], 0.0]))[0][0].T
    return jnp.stack([s[0], s[1], jnp.arctan2(R[0, 2], R[0, 0]), s[2], s[3]])


@pytest.mark.slow(reason="compiles the measured loop and its batch; the default run runs a measured plant in docs/guides/optimal-control.md; make test-all")
def test_plants_on_so3_are_measured_into_the_models_coordinates():
    """The regulator against the cat integrated on SO(3) x SO(3) (FallingCatAttitudes:
    psi is no coordinate there; the turn is carried by the attitudes, stepped by RKMK4)
    and measured into the model's coordinates by ``measure``, two members in one
    ``closed_loop_batch`` (group 1): each member's loop equals the one against the chart
    plant from its start (RK4 on psi, one loop at a time) to the two integrators'
    difference (the shape to the QPs' last digits, psi to 1e-7 at 4 plant steps per
    interval), the cost and inputs with it, through a kick given as a map of each
    plant's state; the attitudes stay rotations. Without ``measure`` such plants are
    refused, and so are a push that is not a map of the plant's state, a measure of the
    wrong size and starts whose parts disagree on the number of members. On a Dask
    client (closed_loop_batch_on_client) the same batch gives the same loops."""
    mpc, _ = _regulator()
    att = CAT.attitude_model()
    starts = [dict(theta=0.6, chi=0.4, theta_dot=0.3, chi_dot=-0.5),  # off the target: the loop works
              dict(theta=1.0, chi=-0.3, theta_dot=-0.2, chi_dot=0.4)]
    ys0 = [att.initial_state(**st) for st in starts]
    Y0 = jax.tree_util.tree_map(lambda *a: np.stack(a), *ys0)  # the members on axis 0 of every part
    # a kick of 1 rad/s on the bend rate at t = 0.3 s: an increment of the chart state,
    # a map of the attitude model's state
    kick = [(0.3, np.array([0.0, 0.0, 0.0, 1.0, 0.0]))]
    kick_lie = [(0.3, lambda y: (y[0], y[1], y[2].at[2].add(1.0)))]
    lie = closed_loop_batch(mpc, att, Y0, 10, plant_substeps=4, measure=_chart_of_attitudes, pushes=kick_lie,
                            group=1)
    assert np.asarray(lie.measurements).shape == (2, 10, 5) and np.asarray(lie.trajectory.xs[0]).shape == (2, 11, 3, 3)
    for i, (st, y0) in enumerate(zip(starts, ys0)):
        x0 = CAT.initial_state(**st)
        np.testing.assert_allclose(np.asarray(_chart_of_attitudes(y0)), np.asarray(x0), atol=1e-14)
        chart = closed_loop(mpc, CAT, x0, 10, plant_substeps=4, pushes=kick)
        xs = np.asarray(chart.trajectory.xs)
        ys = np.asarray(lie.measurements[i])
        assert np.ptp(xs[:, 2]) > 0.05  # the cat turns: psi is worth measuring
        assert np.abs(np.diff(xs[:, 3])).max() > 0.5  # the kick shows in the bend rate
        # the same RK4 steps on the same shape equations; the batch's QPs by the Riccati
        # recursion, the loop's densely: equal to the QPs' last digits
        shape = [0, 1, 3, 4]
        np.testing.assert_allclose(ys[:, shape], xs[:-1, shape], rtol=0, atol=1e-10)
        # psi: RK4 on psi' = -f(theta) chi' against RKMK4 on the attitudes, steps of 0.025 s
        np.testing.assert_allclose(ys[:, 2], xs[:-1, 2], rtol=0, atol=1e-7)  # (measured: 2.2e-8)
        # (psi has no weight and does not enter the shape's dynamics: the inputs do not see it)
        np.testing.assert_allclose(np.asarray(lie.inputs[i]), np.asarray(chart.inputs), rtol=0, atol=1e-10)
        np.testing.assert_allclose(float(lie.cost[i]), float(chart.cost), rtol=1e-10)
        end = jax.tree_util.tree_map(lambda a: a[i, -1], lie.trajectory.xs)
        np.testing.assert_allclose(np.asarray(_chart_of_attitudes(end)), xs[-1], rtol=0, atol=1e-7)
    for g in np.asarray(lie.trajectory.xs[0]), np.asarray(lie.trajectory.xs[1]):
        np.testing.assert_allclose(np.einsum("bkji,bkjl->bkil", g, g), np.broadcast_to(np.eye(3), g.shape),
                                   atol=1e-12)
    # the same batch on a Dask client, one member per chunk: member by member the local batch
    # (the pushes, maps of the plant's state, go to every chunk as they are)
    if importlib.util.find_spec("distributed") is not None:
        from dask.distributed import Client, LocalCluster

        from controls.distributed import closed_loop_batch_on_client

        with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster, \
                Client(cluster) as client:
            far = closed_loop_batch_on_client(client, mpc, att, Y0, 10, plant_substeps=4, measure=_chart_of_attitudes,
                                              pushes=kick_lie, group=1, chunk_members=1)
        for a, b in zip(jax.tree_util.tree_leaves(far), jax.tree_util.tree_leaves(lie)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-12)
    y0 = ys0[0]
    with pytest.raises(MPCError, match="measure="):
        closed_loop(mpc, att, y0, 3)
    with pytest.raises(MPCError, match="measure="):
        closed_loop_batch(mpc, att, Y0, 3)
    with pytest.raises(MPCError, match="function of the plant's state"):
        closed_loop(mpc, att, y0, 3, measure=_chart_of_attitudes, pushes=[(0.3, np.ones(5))])
    with pytest.raises(MPCError, match="structure"):
        closed_loop_batch(mpc, att, Y0, 3, measure=_chart_of_attitudes, pushes=[(0.3, lambda y: y[2])])
    with pytest.raises(MPCError, match="5 numbers"):
        closed_loop(mpc, att, y0, 3, measure=lambda y: y[2])
    with pytest.raises(MPCError, match="axis 0 of every part"):
        closed_loop_batch(mpc, att, (Y0[0], Y0[1][:1], Y0[2]), 3, measure=_chart_of_attitudes)
    with pytest.raises(MPCError, match=r"members \[1\]"):
        closed_loop_batch(mpc, att, (Y0[0], Y0[1], Y0[2] * np.array([[1.0], [np.nan]])), 3,
                          measure=_chart_of_attitudes)


@pytest.mark.slow(reason="compiles the per-period step and plant programs (as test_timed_loop_is_the_scanned_loop); "
                         "test_plants_on_so3_are_measured_into_the_models_coordinates runs the same measured "
                         "loop (in a batch) as one scan")
def test_a_measured_plant_steps_the_same_from_python():
    """closed_loop(timing=True) on a plant measured into the model's coordinates (the
    attitude cat of the test above): one compiled call per period gives the scanned
    loop's measurements and attitudes."""
    mpc, _ = _regulator()
    att = CAT.attitude_model()
    y0 = att.initial_state(theta=0.6, chi=0.4, theta_dot=0.3, chi_dot=-0.5)
    kick_lie = [(0.3, lambda y: (y[0], y[1], y[2].at[2].add(1.0)))]
    kw = dict(plant_substeps=4, measure=_chart_of_attitudes, pushes=kick_lie)
    scanned = closed_loop(mpc, att, y0, 5, **kw)
    timed = closed_loop(mpc, att, y0, 5, timing=True, **kw)
    assert np.abs(np.diff(np.asarray(scanned.measurements)[:, 3])).max() > 0.5  # the kick (t = 0.3 s) is inside the 5 periods
    np.testing.assert_allclose(np.asarray(timed.measurements), np.asarray(scanned.measurements), rtol=0, atol=1e-12)
    for a, b in zip(timed.trajectory.xs, scanned.trajectory.xs):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-12)
    assert np.all(np.asarray(timed.status.solve_ms) > 0)


def _mark(folder, index):
    """A chunk hook (runs on the worker): leaves a file named by the chunk's index."""
    (Path(folder) / f"chunk-{index}").touch()


@pytest.mark.slow(reason="starts a Dask cluster and compiles the batch program twice (~13 s); the default run's "
                         "test_batch_member_is_the_loop_run_alone checks the local batch; make test-all")
def test_batch_on_a_dask_client_is_the_local_batch_member_by_member(tmp_path):
    """closed_loop_batch_on_client on a threads-only LocalCluster: five members (the
    three of the batch test, two of them twice) in chunks of three, the last chunk
    padded, come back joined in member order, each equal to the local batch's member
    (the chunks' program is the local batch's own: the same three members' shapes).
    Bad input is refused before any task is sent."""
    pytest.importorskip("dask.distributed")
    from dask.distributed import Client, LocalCluster

    from controls.distributed import closed_loop_batch_on_client

    mpc, _ = _regulator()
    _, plants, X, times, kicks, keys, noise = _batch_members([0, 1, 2])
    local = closed_loop_batch(mpc, plants, X, PERIODS, in_axes={"plant": 0}, pushes=(times, kicks), keys=keys,
                              group=2, **noise)
    rows = [0, 1, 2, 2, 0]
    _, plants5, X5, times5, kicks5, keys5, _ = _batch_members(rows)
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        with pytest.raises(MPCError, match="keys"):
            closed_loop_batch_on_client(client, mpc, plants5, X5, PERIODS, in_axes={"plant": 0}, **noise)
        with pytest.raises(MPCError, match="chunk_members"):
            closed_loop_batch_on_client(client, mpc, plants5, X5, PERIODS, in_axes={"plant": 0}, keys=keys5,
                                        chunk_members=0, **noise)
        far = closed_loop_batch_on_client(client, mpc, plants5, X5, PERIODS, in_axes={"plant": 0},
                                          pushes=(times5, kicks5), keys=keys5, group=2, chunk_members=3,
                                          on_chunk=functools.partial(_mark, str(tmp_path)), **noise)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["chunk-0", "chunk-1"]
    from equinox import _errors

    assert _errors.EQX_ON_ERROR == "raise"  # the workers' solver threads left equinox's setting as it was
    assert np.asarray(far.inputs).shape[0] == 5 and np.asarray(far.trajectory.xs).shape[0] == 5
    for i, r in enumerate(rows):
        for a, b in zip(jax.tree_util.tree_leaves(far), jax.tree_util.tree_leaves(local)):
            np.testing.assert_allclose(np.asarray(a)[i], np.asarray(b)[r], rtol=0, atol=1e-12)
    assert not np.allclose(np.asarray(far.inputs[1]), np.asarray(far.inputs[0]))  # the members differ


_CONCURRENT_CHILD = """
import sys, threading
sys.path.insert(0, {root!r})
import numpy as np
import nhjax
from controls import closed_loop_batch
from experiments import mpc_cat

cat, ocp, mpc = mpc_cat.setup(1.0, "rti", 0.0)
x0s = np.tile(np.asarray(ocp.x0), (8, 1))
x0s[:, 0] += np.linspace(-0.05, 0.05, 8)
alone = np.asarray(closed_loop_batch(mpc, cat, x0s, 3, group=4).trajectory.xs)
out = {{}}


def run(i):
    out[i] = np.asarray(closed_loop_batch(mpc, cat, x0s, 3, group=4).trajectory.xs)


for _ in range(3):
    threads = [threading.Thread(target=run, args=(i,), daemon=True) for i in range(2)]
    [t.start() for t in threads]
    [t.join() for t in threads]
    assert all(np.array_equal(out[i], alone) for i in range(2)), "a concurrent run differs from the run alone"
print("done")
"""


@pytest.mark.slow(reason="compiles the cat's exact-Hessian batch program in a child process (~20 s); make test-all")
def test_two_batches_at_once_in_one_process_finish(tmp_path):
    """Two threads of one process run the falling cat's exact-Hessian MPC batch at once
    (8 members in groups of 4: 160 Hessian floors of 7x7 per period), three times: both
    finish, each equal to the batch run alone. With the floors as one batched LAPACK
    eigh, jaxlib 0.10's kernel split the batch over XLA's CPU thread pool and waited from
    a thread of that pool, and the two programs hung on the first try (seen on 2 cores).
    The child is killed after 300 s, so a hang fails the test instead of stalling it."""
    root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, NHJAX_CACHE_DIR=str(tmp_path), JAX_PLATFORMS="cpu")
    try:
        r = subprocess.run([sys.executable, "-c", _CONCURRENT_CHILD.format(root=root)], capture_output=True,
                           text=True, env=env, timeout=300)
    except subprocess.TimeoutExpired:
        pytest.fail("two closed_loop_batch calls at once did not finish in 300 s (hung)")
    assert r.returncode == 0 and r.stdout.strip().endswith("done"), r.stderr[-3000:]


def test_vmapped_qps_and_floors_call_lapack_one_matrix_at_a_time():
    """Under vmap, the controller's linear algebra (box_qp's LU, stage_qp's terminal
    solves, the Riccati blocks' inverses for more than 8 inputs, the Hessian floor's
    eigh) makes no batched LAPACK call, whose jaxlib 0.10 kernel can hang two programs
    running at once; each member's result is the unbatched call's, bit for bit, and the
    floor is numpy's eigendecomposition with the eigenvalues floored, to 1e-12."""
    from controls._qp import _spd_inverse
    from controls.mpc import _hessian_floor
    from nhjax import _programs

    rng = np.random.default_rng(5)
    N, n, m, me, K = 6, 3, 2, 2, 3
    R = rng.standard_normal((K, N, n + m, n + m))
    Q = 0.3 * np.einsum("bkij,bklj->bkil", R, R) + np.diag(np.r_[np.zeros(n), 0.1 * np.ones(m)])
    args = [Q, rng.standard_normal((K, N, n + m)), np.eye(n) + 0.2 * rng.standard_normal((K, N, n, n)),
            rng.standard_normal((K, N, n, m)), 0.1 * rng.standard_normal((K, N, n)), rng.standard_normal((K, n))]
    R2 = rng.standard_normal((K, n, n))
    args += [R2 @ np.swapaxes(R2, 1, 2), rng.standard_normal((K, n)), rng.standard_normal((K, me, n)),
             0.1 * rng.standard_normal((K, me)), np.full((K, N, m), -0.3), np.full((K, N, m), 0.4)]
    args = [jnp.asarray(a) for a in args]
    H, g, Ac, bc = [], [], [], []
    for k in range(K):
        Hk, gk, Ak, bk, _, _ = _condensed(*(np.asarray(a[k]) for a in args[:10]))
        H.append(Hk), g.append(gk), Ac.append(Ak), bc.append(bk)
    box = [jnp.asarray(np.stack(a)) for a in (H, g, Ac, bc)] + [args[10].reshape(K, -1), args[11].reshape(K, -1)]
    M = rng.standard_normal((K, 4, 10, 10))
    spd = jnp.asarray(np.einsum("bkij,bklj->bkil", M, M) + np.eye(10))
    Hf = jnp.asarray(rng.standard_normal((K, 7, 7)))
    cases = [(box_qp, box), (stage_qp, args), (_spd_inverse, [spd]), (lambda q: _hessian_floor(q, 1e-3), [Hf])]
    for fn, a in cases:
        batched = jax.jit(jax.vmap(fn)).lower(*a).compile()
        assert not _programs.batched_lapack(batched)
        out = batched(*a)
        for k in range(K):
            alone = jax.jit(fn)(*(x[k] for x in a))
            for u, v in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(alone)):
                np.testing.assert_array_equal(np.asarray(u)[k], np.asarray(v))
    w, V = np.linalg.eigh(0.5 * (np.asarray(Hf) + np.swapaxes(np.asarray(Hf), 1, 2)))
    floored = np.einsum("bij,bj,bkj->bik", V, np.maximum(w, 1e-3), V)
    np.testing.assert_allclose(np.asarray(jax.vmap(lambda q: _hessian_floor(q, 1e-3))(Hf)), floored, rtol=0,
                               atol=1e-12)
    assert (w < 1e-3).any() and (w > 1e-3).any()  # the floor binds on some eigenvalues, not all


def test_box_qp_meets_its_optimality_conditions():
    """A random strictly convex QP with two equalities and a box that binds: the
    returned step and multipliers satisfy stationarity, feasibility and
    complementarity to 1e-9; an infeasible box reports ok = False."""
    rng = np.random.default_rng(3)
    n = 12
    M = rng.standard_normal((n, n))
    H = M @ M.T + 0.1 * np.eye(n)
    g = 5 * rng.standard_normal(n)
    A = rng.standard_normal((2, n))
    b = rng.standard_normal(2) * 0.1
    lo, hi = -0.3 * np.ones(n), 0.3 * np.ones(n)
    lo[0], hi[1] = -np.inf, np.inf
    d, y, ok, _ = jax.jit(box_qp)(*(jnp.asarray(a) for a in (H, g, A, b, lo, hi)))
    d, y = np.asarray(d), np.asarray(y)
    assert bool(ok)
    assert np.abs(A @ d - b).max() < 1e-9 and np.all(d >= lo - 1e-12) and np.all(d <= hi + 1e-12)
    z = H @ d + g - A.T @ y  # = z_lo - z_hi
    active_lo, active_hi = d <= lo + 1e-7, d >= hi - 1e-7
    assert (active_lo | active_hi).sum() >= 2
    assert np.abs(z[~(active_lo | active_hi)]).max() < 1e-8
    assert np.all(z[active_lo] > -1e-9) and np.all(z[active_hi] < 1e-9)
    # infeasible: sum(d) = 10 with |d_i| <= 0.3
    _, _, ok, _ = jax.jit(box_qp)(jnp.asarray(H), jnp.asarray(g), jnp.ones((1, n)), jnp.array([10.0]),
                                  jnp.full(n, -0.3), jnp.full(n, 0.3))
    assert not bool(ok)


def _condensed(Q, q, A, B, c, e0, P, p, C, b):
    """The stage QP with the states eliminated, written here with numpy loops:
    x_k = G_k d + e_k, H = sum_k S_k^T Q_k S_k + G_N^T P G_N, g its gradient at d = 0."""
    N, n, m = B.shape
    G, e = np.zeros((N + 1, n, N * m)), np.zeros((N + 1, n))
    e[0] = e0
    for k in range(N):
        G[k + 1] = A[k] @ G[k]
        G[k + 1][:, k * m:(k + 1) * m] += B[k]
        e[k + 1] = A[k] @ e[k] + c[k]
    H, g = np.zeros((N * m, N * m)), np.zeros(N * m)
    for k in range(N):
        S = np.zeros((n + m, N * m))
        S[:n], S[n:, k * m:(k + 1) * m] = G[k], np.eye(m)
        H += S.T @ Q[k] @ S
        g += S.T @ (Q[k] @ np.concatenate([e[k], np.zeros(m)]) + q[k])
    H += G[N].T @ P @ G[N]
    g += G[N].T @ (P @ e[N] + p)
    return 0.5 * (H + H.T), g, C @ G[N], b - C @ e[N], G, e


@pytest.mark.parametrize("me", [0, pytest.param(1, marks=pytest.mark.slow), pytest.param(2, marks=pytest.mark.slow)])
def test_stage_qp_is_box_qp_on_the_condensed_problem(me):
    """Random stage-wise QPs (N = 8 intervals, 4 states, 2 inputs, random dynamics with
    an affine term and a start, positive semidefinite stage blocks, me terminal
    equalities, bounds that bind on several inputs, one input unbounded below and one
    above): stage_qp's inputs and multipliers are box_qp's on the condensed problem
    (built here independently) to 1e-10, its states are the dynamics' rollout of its
    inputs, and both report success. Unreachable terminal equalities (me > 0: bounds
    too tight) are reported as failures by both."""
    rng = np.random.default_rng(10 + me)
    N, n, m = 8, 4, 2
    for trial in range(3):
        R = rng.standard_normal((N, n + m, n + m))
        Q = 0.3 * np.einsum("kij,klj->kil", R, R) + np.diag(np.r_[np.zeros(n), 0.1 * np.ones(m)])
        q = rng.standard_normal((N, n + m))
        A = np.eye(n) + 0.2 * rng.standard_normal((N, n, n))
        B = rng.standard_normal((N, n, m))
        c, e0 = 0.1 * rng.standard_normal((N, n)), rng.standard_normal(n)
        R2 = rng.standard_normal((n, n))
        P, p = R2 @ R2.T, rng.standard_normal(n)
        C, b = rng.standard_normal((me, n)), 0.1 * rng.standard_normal(me)
        lo, hi = -0.3 * np.ones((N, m)), 0.4 * np.ones((N, m))
        lo[0, 0], hi[1, 1] = -np.inf, np.inf
        H, g, Ac, bc, G, e = _condensed(Q, q, A, B, c, e0, P, p, C, b)
        d, y, ok, _ = jax.jit(box_qp)(*(jnp.asarray(a) for a in (H, g, Ac, bc, lo.reshape(-1), hi.reshape(-1))))
        u, x, y2, ok2, _ = jax.jit(stage_qp)(*(jnp.asarray(a) for a in (Q, q, A, B, c, e0, P, p, C, b, lo, hi)))
        d, u, x = np.asarray(d), np.asarray(u), np.asarray(x)
        assert bool(ok) and bool(ok2)
        at_bound = np.isclose(d, lo.reshape(-1), atol=1e-12) | np.isclose(d, hi.reshape(-1), atol=1e-12)
        assert at_bound.sum() >= 2  # the bounds bind
        np.testing.assert_allclose(u.reshape(-1), d, rtol=0, atol=1e-10)
        np.testing.assert_allclose(np.asarray(y2), np.asarray(y), rtol=0, atol=1e-10)
        np.testing.assert_allclose(x, np.einsum("kia,a->ki", G, u.reshape(-1)) + e, rtol=0, atol=1e-10)
    if me:
        b_far = 100.0 * np.ones(me)  # C x_N = 100 with |u| <= 0.4: unreachable
        _, _, _, ok2, _ = jax.jit(stage_qp)(*(jnp.asarray(a) for a in (Q, q, A, B, c, e0, P, p, C, b_far, lo, hi)))
        assert not bool(ok2)


def test_spd_inverse_unrolled_is_the_inverse():
    """The unrolled Cholesky inverse of the Riccati's m x m blocks (m = 1 .. 4, a
    batch of random SPD matrices) is numpy's inverse to 1e-12 relative."""
    rng = np.random.default_rng(4)
    for m in range(1, 5):
        R = rng.standard_normal((6, m, m))
        M = np.einsum("bij,bkj->bik", R, R) + 0.5 * np.eye(m)
        np.testing.assert_allclose(np.asarray(jax.jit(_spd_inverse)(jnp.asarray(M))), np.linalg.inv(M), rtol=1e-12,
                                   atol=1e-12)


def test_disturbance_observer_update_is_its_formula():
    """MPC.step with a previous measurement y_prev and inputs u_prev: the new estimate
    is d + gain (y - y_hat) / period, y_hat the model's RK4 map (with d) over the last
    period, computed here from the model's vector field; before the first period
    (has_prev False) the estimate is left as it is."""
    gain = np.array([0.0, 0.5, 1.0, 0.5, 1.0])
    mpc = MPC(_terminal_cost_ocp(), PERIOD, N, mode="rti", disturbance_gain=gain)
    plan = mpc.init()
    d0 = jnp.array([0.0, 0.01, -0.02, 0.03, 0.0])
    u_prev = jnp.array([[0.2, -0.1]])
    y_prev = X0
    h = float(mpc.h)

    def f(x):
        return CAT.vector_field(0.0, x, u_prev[0]) + d0

    k1 = f(y_prev)
    k2 = f(y_prev + h / 2 * k1)
    k3 = f(y_prev + h / 2 * k2)
    k4 = f(y_prev + h * k3)
    y_hat = y_prev + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    delta = jnp.array([1e-3, -2e-3, 3e-3, 0.05, -0.04])
    step = jax.jit(lambda p, y: mpc.step(p, y, PERIOD, 1))
    for has_prev in (True, False):
        prev = eqx.tree_at(lambda p: (p.dist, p.y_prev, p.u_prev, p.has_prev), plan,
                           (d0, y_prev, u_prev, jnp.asarray(has_prev)))
        _, new, _ = step(prev, y_hat + delta)
        want = d0 + gain * delta / PERIOD if has_prev else d0
        np.testing.assert_allclose(np.asarray(new.dist), np.asarray(want), rtol=0, atol=1e-12)
        assert bool(new.has_prev)
        np.testing.assert_allclose(np.asarray(new.y_prev), np.asarray(y_hat + delta), rtol=0, atol=0)


class TorqueBias(AbstractSystem):
    """The cat whose actuators add a constant torque ``bias`` [N m] to the command."""

    cat: FallingCat
    bias: jax.Array
    state_names = FallingCat.state_names
    control_dim = 2

    def vector_field(self, t, x, u):
        return self.cat.vector_field(t, x, u + self.bias)


@pytest.mark.slow  # (the observer's update: test_disturbance_observer_update_is_its_formula; make test-all)
def test_disturbance_observer_removes_the_offset_of_a_torque_bias():
    """The regulator of the shape (receding horizon) against a plant whose actuators add
    a constant torque (0.2, -0.1) N m: without the observer the shape settles off its
    target (the controller keeps commanding what its model says holds the cat still);
    with it (gain 1 on every component) the estimate absorbs the bias and the shape
    error at the end is a tenth of the observer-less one or less."""
    base, _ = _regulator()
    plant = TorqueBias(CAT, jnp.array([0.2, -0.1]))
    errors = {}
    for gain in (0.0, 1.0):
        mpc = MPC(base.ocp, PERIOD, N, mode="rti", disturbance_gain=gain)
        loop = closed_loop(mpc, plant, X0, PERIODS)
        xs = np.asarray(loop.trajectory.xs)
        errors[gain] = np.abs(xs[-1, [0, 1]] - [0.8, 0.0]).max()
    assert errors[0.0] > 1e-2  # the bias moved the shape off target
    assert errors[1.0] < 0.1 * errors[0.0]


def test_new_options_get_named_errors():
    """qp, disturbance_gain and closed_loop_batch's group are checked before any numerics."""
    ocp = _terminal_cost_ocp()
    with pytest.raises(MPCError, match="qp"):
        MPC(ocp, PERIOD, N, qp="cholesky")
    with pytest.raises(MPCError, match="disturbance_gain"):
        MPC(ocp, PERIOD, N, disturbance_gain=1.5)
    with pytest.raises(MPCError, match="disturbance_gain"):
        MPC(ocp, PERIOD, N, disturbance_gain=[0.5, 0.5])
    with pytest.raises(MPCError, match="group"):
        closed_loop_batch(MPC(ocp, PERIOD, N), CAT, np.asarray(X0)[None], 2, group=0)


def test_loop_arguments_of_the_wrong_kind_get_named_errors():
    """Start times, PRNG keys, batched starts, in_axes, per-member plants and pushes of the
    wrong kind or size are refused with MPCError naming the argument, before any numerics
    (they gave NaN times, TypeErrors from jax.random, ZeroDivisionError, IndexError)."""
    ocp = _terminal_cost_ocp()
    with pytest.raises(MPCError, match="period must be a number of seconds, got '0.1'"):
        MPC(ocp, "0.1", N)
    mpc = MPC(ocp, PERIOD, N)
    for t0, words in ((np.nan, "t0 must be finite"), ("0", "t0 must be a real number"),
                      (np.zeros(2), "t0 must be a scalar")):
        with pytest.raises(MPCError, match=f"closed_loop: {words}"):
            closed_loop(mpc, CAT, X0, 2, t0=t0)
    for timing in ("yes", 1, None):
        with pytest.raises(MPCError, match="closed_loop: timing must be True .* or False"):
            closed_loop(mpc, CAT, X0, 2, timing=timing)
    with pytest.raises(MPCError, match="closed_loop_batch: t0 must be finite"):
        closed_loop_batch(mpc, CAT, np.array([X0, X0]), 2, t0=np.inf)
    with pytest.raises(MPCError, match="MPC.init: t0 must be finite"):
        mpc.init(None, None, np.nan)
    for key in (0, "k", jax.random.split(jax.random.key(0), 2), jax.random.split(jax.random.PRNGKey(0), 2)):
        with pytest.raises(MPCError, match="closed_loop: key must be one PRNG key"):
            closed_loop(mpc, CAT, X0, 2, force_noise=0.01, key=key)
    X = np.array([X0, X0])
    for keys in ([1, 2], jax.random.split(jax.random.key(0), 3), jax.random.split(jax.random.PRNGKey(0), 3)):
        with pytest.raises(MPCError, match=r"closed_loop_batch: keys must be one PRNG key per member \(2\)"):
            closed_loop_batch(mpc, CAT, X, 2, force_noise=0.1, keys=keys)
    with pytest.raises(MPCError, match="B >= 1"):
        closed_loop_batch(mpc, CAT, np.zeros((0, 5)), 2)
    for bad in ("x", [[1.0, 2.0], [3.0]]):
        with pytest.raises(MPCError, match=r"x0s must be an array of shape \(B, 5\) of real numbers"):
            closed_loop_batch(mpc, CAT, bad, 2)
    with pytest.raises(MPCError, match="in_axes must be a dict"):
        closed_loop_batch(mpc, CAT, X, 2, in_axes=[0])
    with pytest.raises(MPCError, match="one leading member axis"):
        closed_loop_batch(mpc, CAT, X, 2, in_axes={"plant": 0})
    plants = eqx.filter_vmap(lambda s: FallingCat(I1=CAT.I1 * s))(jnp.array([1.0, 1.1, 1.2]))
    with pytest.raises(MPCError, match="carry 3 members"):
        closed_loop_batch(mpc, plants, X, 2, in_axes={"plant": 0})
    with pytest.raises(MPCError, match="leading axis of 2 members"):
        closed_loop_batch(mpc, CAT, X, 2, pushes=(np.zeros((3, 1)), np.zeros((3, 1, 5))))
