"""Spherical-robot steering (ShellWithTop, rest to rest, min int |tau|^2) by the direct
method: the optimum reaches the target at rest; the shell rolls without slipping along
it; Chaplygin's vector and the energy balance hold along it (dK/dt = -R_top tau, and
the actuator does no net work between two equilibria); the mirror image of the optimum
is the optimum of the mirrored target; shooting gradients agree with finite
differences; bad input is named."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import controls
import nhjax
from controls.tasks import (
    linear_guess,
    rolling_residual,
    simulate_with_impulse,
    solve_direct_newton,
    sphere_steering,
    sphere_steering_reduced,
    top_heading,
)
from controls import newton as nt
from nhjax.scenes import ShellWithTop

T = 3.0
TARGET = (0.5, 0.3)
DENSE = 601


# A start near the optimum for degree-6 Chebyshev controls: its coefficients rounded to
# 1e-3 N m (misses the target's rest state by ~1e-2; a solve from the linear guess, as in
# experiments/steer_sphere.py and the slow tests, takes 60-75 s more under load: more than this file may take).
WARM = [[0.084, 0.0, 0.0], [0.001, 0.247, -0.005], [0.075, -0.001, 0.0], [0.001, -0.008, 0.0],
        [-0.011, 0.0, 0.0], [0.0, 0.004, 0.001], [-0.003, 0.0, 0.0]]


@pytest.fixture(scope="module")
def optimum():
    robot = ShellWithTop()
    ocp = sphere_steering(robot, TARGET, T)
    param = controls.Chebyshev(6, T, 3)
    res = solve_direct_newton(ocp, param, jnp.asarray(WARM).reshape(-1), ctol=1e-10, gtol=1e-7)
    # the optimum re-simulated at tight tolerance, saved densely, with the space torque
    # impulse int_0^t R_top tau dt integrated as extra states
    traj = simulate_with_impulse(ocp, res.control, saveat=DENSE)
    return robot, ocp, param, res, traj


def test_optimum_reaches_the_target_at_rest(optimum):
    robot, ocp, param, res, traj = optimum
    assert res.converged, res.message
    sh = nt._Shooting(ocp, param, jnp.asarray(1e-10, float), jnp.asarray(1e-10, float))
    assert np.abs(nt._values(sh, jnp.asarray(WARM).reshape(-1))[1:]).max() > 1e-3  # a real start
    assert res.violation < 1e-9
    assert res.history["stationarity"][-1] < 1e-7
    # Newton did the work: from the restored start, stationarity fell by orders of magnitude
    assert res.history["stationarity"][0] > 1e3 * res.history["stationarity"][-1]
    assert res.cost <= res.history["cost"][0]
    # (that it is the same optimum as a cold solve from the linear guess, and within 1e-4 of
    # the Pontryagin extremal, is checked by the slow tests below)
    ((xy, _, Rt), v), _ = traj.xs
    np.testing.assert_allclose(xy[-1], TARGET, rtol=0, atol=1e-6)
    assert float(jnp.max(jnp.abs(v[-1]))) < 1e-6  # all 8 velocities, xy' included
    np.testing.assert_allclose(Rt[-1][2], [0.0, 0.0, 1.0], atol=1e-6)  # the top hangs again
    # ... and it did move: the contact point travelled and the top swung
    assert float(jnp.max(jnp.linalg.norm(v[:, :2], axis=1))) > 0.1
    assert float(jnp.max(jnp.arccos(jnp.clip(Rt[:, 2, 2], -1, 1)))) > 0.1
    # the reported cost is the integral of |tau|^2 along the motion (trapezoid on 601 points)
    us = np.asarray(jax.vmap(lambda t: res.control(t, None))(traj.ts))
    np.testing.assert_allclose(np.trapezoid((us**2).sum(1), np.asarray(traj.ts)), res.cost, rtol=1e-4)


def test_rolling_without_slipping_along_the_optimum(optimum):
    robot, _, _, _, traj = optimum
    x, _ = traj.xs
    r = np.asarray(rolling_residual(robot, x, traj.ts))
    assert r.shape == (DENSE, 2)
    assert np.abs(r).max() < 1e-10, np.abs(r).max()
    (_, Rsh, Rt), _ = x
    for R in (Rsh, Rt):
        assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 1e-12


def test_chaplygin_vector_and_energy_balance(optimum):
    """K(t) - K(0) = -int_0^t R_top tau dt (K is Chaplygin's vector, written independently
    of the equations of motion), and energy - work stays constant. At the end, the robot
    is at rest with the top hanging again: K(T) = 0 and E(T) = E(0), so the optimal
    torque has zero net impulse in space and does zero net work."""
    robot, _, _, _, traj = optimum
    x, impulse = traj.xs
    K = jax.vmap(lambda a, b, c, v: robot.chaplygin_vector(((a, b, c), v)))(*x[0], x[1])
    assert float(jnp.max(jnp.abs(impulse))) > 0.05  # the torque impulse is not small on the way
    np.testing.assert_allclose(np.asarray(K - K[0]), -np.asarray(impulse), rtol=0, atol=1e-10)
    assert float(jnp.max(jnp.abs(impulse[-1]))) < 1e-7
    assert float(traj.invariant_drift["energy - work"]) < 1e-9
    assert abs(float(traj.work[-1])) < 1e-7
    assert float(jnp.max(jnp.abs(traj.work))) > 1e-2  # ... though the actuator works on the way


def test_mirror_image_of_the_optimum_is_optimal(optimum):
    """The default robot (It diagonal, c on the top's z axis) is symmetric under the
    reflection y -> -y; torques are pseudo-vectors, tau -> (-tau1, tau2, -tau3). The
    mirrored control must reach the mirrored target at rest, with the same cost, and be
    stationary there: no recompilation (the target is an array of the constraint)."""
    _, ocp, param, res, _ = optimum
    mirror = sphere_steering(ocp.system, (TARGET[0], -TARGET[1]), T)
    z = res.params.reshape(param.n + 1, 3) * jnp.array([-1.0, 1.0, -1.0])
    sh = nt._Shooting(mirror, param, jnp.asarray(1e-10, float), jnp.asarray(1e-10, float))
    y, D = (np.asarray(a) for a in nt._values_and_jacobian(sh, z.reshape(-1)))
    np.testing.assert_allclose(y[0], res.cost, rtol=1e-9)
    assert np.abs(y[1:]).max() < 1e-8
    lam = -np.linalg.lstsq(D[1:].T, D[0], rcond=None)[0]
    assert np.abs(D[0] + D[1:].T @ lam).max() < 1e-6 * np.abs(D[0]).max()
    # the new target is data, not structure: the two problems share their compiled code
    static = lambda o: eqx.filter(o, eqx.is_array, inverse=True)  # noqa: E731
    assert eqx.tree_equal(static(ocp), static(mirror))


def test_optimum_replays_on_the_hand_derived_reduced_equations(optimum):
    """The same torque on ShellWithTopReduced (seed 003's reduced system (1.11) with the
    torque terms derived by hand, a vector state without the shell's attitude) gives the
    same cost and meets the same terminal constraints."""
    robot, _, _, res, _ = optimum
    red = sphere_steering_reduced(robot, TARGET, T)
    traj, cost, psi = controls.rollout(red, res.control, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(float(cost), res.cost, rtol=1e-9)
    assert float(jnp.max(jnp.abs(psi))) < 1e-7
    np.testing.assert_allclose(traj.xs[0][-1, 15:17], TARGET, atol=1e-7)


def test_shooting_gradient_matches_central_differences(optimum):
    """Reverse-mode derivatives of (cost, terminal constraints) through the RKMK solve on
    SO(3) x SO(3) against central differences, in random directions at the optimum."""
    _, ocp, param, res, _ = optimum
    sh = nt._Shooting(ocp, param, jnp.asarray(1e-12, float), jnp.asarray(1e-12, float))
    _, D = (np.asarray(a) for a in nt._values_and_jacobian(sh, res.params))
    rng = np.random.default_rng(5)
    h = 1e-5
    for _ in range(3):
        e = rng.normal(size=param.size)
        e /= np.linalg.norm(e)
        fd = (np.asarray(nt._values(sh, res.params + h * e)) - np.asarray(nt._values(sh, res.params - h * e))) / (2 * h)
        np.testing.assert_allclose(D @ e, fd, rtol=1e-5, atol=1e-6 * np.abs(D).max())


def test_bad_input_is_named():
    robot = ShellWithTop()
    with pytest.raises(controls.ProblemError, match="target_xy must be a 2-vector"):
        sphere_steering(robot, (0.5, 0.3, 0.0), T)
    with pytest.raises(controls.ProblemError, match="target_xy must be a 2-vector"):
        sphere_steering(robot, "far", T)
    with pytest.raises(controls.ProblemError, match="finite"):
        sphere_steering(robot, (np.nan, 0.0), T)
    for bad_T in (0.0, -1.0, np.inf):
        with pytest.raises(controls.ProblemError, match="horizon T must be a positive"):
            sphere_steering(robot, TARGET, bad_T)
    with pytest.raises(controls.ProblemError, match="heading"):
        sphere_steering(robot, TARGET, T, heading=(0.1, 0.2))
    with pytest.raises(controls.ProblemError, match="ShellWithTop"):
        sphere_steering(nhjax.scenes.RollingDisk(), TARGET, T)
    ocp = sphere_steering(robot, TARGET, T)
    with pytest.raises(controls.ProblemError, match="guess has shape"):
        solve_direct_newton(ocp, controls.Chebyshev(6, T, 3), jnp.zeros(5))
    with pytest.raises(controls.ProblemError, match="cannot meet"):
        solve_direct_newton(ocp, controls.Chebyshev(2, T, 3), jnp.zeros(9))


def test_constraints_are_the_equilibria():
    """The terminal constraints vanish exactly at rest states with the top hanging (any
    shell attitude, any top yaw), and not at a rest state with the top tilted."""
    robot = ShellWithTop()
    ocp = sphere_steering(robot, TARGET, T)
    psi = ocp.terminal_constraints
    from nhjax.lie import so3

    shell = so3.exp(jnp.array([0.3, -1.2, 2.0]))
    rest = robot.initial_state(xy=TARGET, shell_attitude=shell, top_attitude=so3.rot_z(0.7))
    assert psi(rest).shape == (10,)
    assert float(jnp.max(jnp.abs(psi(rest)))) < 1e-15
    tilted = robot.initial_state(xy=TARGET, top_attitude=so3.rot_x(0.2))
    assert float(jnp.max(jnp.abs(psi(tilted)))) > 0.1
    # with a heading the top's yaw is fixed as well (one more equation)
    ocp_h = sphere_steering(robot, TARGET, T, heading=0.7)
    assert ocp_h.n_constraints == 11
    assert float(jnp.max(jnp.abs(ocp_h.terminal_constraints(rest)))) < 1e-15
    np.testing.assert_allclose(float(top_heading(ocp_h, rest)), 0.7, atol=1e-15)
    assert abs(float(ocp_h.terminal_constraints(robot.initial_state(xy=TARGET))[-1])) > 0.5


@pytest.mark.slow
def test_pontryagin_agrees_with_the_direct_optimum(optimum):
    """Indirect shooting on the reduced vector state (Levenberg–Marquardt: the frame's 9
    numbers make 6 costate directions redundant), started from the costates of a direct
    optimum (``pmp_residual``): the extremal meets the constraints, its cost is at most
    the direct ones (Chebyshev controls are a restriction) and the direct costs approach
    it as the degree grows. The degree-6 optimum's costates are too rough a start (LM
    stalls at a residual of 2e-4), so the direct optimum is first refined to degree 12."""
    robot, ocp, param, res6, _ = optimum
    p12 = controls.Chebyshev(12, T, 3)
    pad = jnp.zeros((13, 3)).at[:7].set(res6.params.reshape(7, 3)).reshape(-1)
    res = solve_direct_newton(ocp, p12, pad, ctol=1e-10, gtol=1e-7)
    assert res.converged and res.cost < res6.cost
    red = sphere_steering_reduced(robot, TARGET, T)
    pmp = controls.pmp_residual(red, res.control, rtol=1e-10, atol=1e-10)
    ind = controls.solve_pontryagin(red, pmp["ps"][-1], pmp["multipliers"], solver="lm", rtol=1e-11,
                                    atol=1e-11, tol=1e-10, max_steps=60)
    assert ind.converged, ind.message
    assert ind.violation < 1e-9
    assert ind.cost <= res.cost < res6.cost
    assert (res.cost - ind.cost) < 0.3 * (res6.cost - ind.cost)  # degree 12 much closer than 6
    np.testing.assert_allclose(ind.cost, res.cost, rtol=1e-4)
    # the extremal's control and the direct one coincide to the parametrization's accuracy
    us = jax.vmap(lambda t: res.control(t, None))(jnp.asarray(ind.trajectory.ts))
    assert float(jnp.max(jnp.abs(us - ind.controls))) < 0.05 * float(jnp.max(jnp.abs(ind.controls)))


@pytest.mark.slow
def test_solve_from_the_linear_guess(optimum):
    """From the minimum-effort control of the linearized problem (violation ~0.3) to the
    same optimum as from the warm start."""
    _, ocp, param, res, _ = optimum
    cold = solve_direct_newton(ocp, param, linear_guess(ocp, param), ctol=1e-10, gtol=1e-7)
    assert cold.converged, cold.message
    np.testing.assert_allclose(cold.cost, res.cost, rtol=1e-9)
    np.testing.assert_allclose(cold.params, res.params, atol=1e-6)


@pytest.mark.slow
def test_steering_with_a_heading():
    """The top's final yaw as an extra constraint: the robot arrives turned by 0.6 rad."""
    robot = ShellWithTop()
    ocp = sphere_steering(robot, TARGET, T, heading=0.6)
    param = controls.Chebyshev(6, T, 3)
    res = solve_direct_newton(ocp, param, linear_guess(ocp, param), ctol=1e-10, gtol=1e-7)
    assert res.converged, res.message
    traj, cost, psi = controls.rollout(ocp, res.control, rtol=1e-12, atol=1e-12)
    x_end = jax.tree_util.tree_map(lambda a: a[-1], traj.xs[0])
    np.testing.assert_allclose(float(top_heading(ocp, x_end)), 0.6, atol=1e-8)
    assert float(jnp.max(jnp.abs(psi))) < 1e-8
    # turning costs effort: more than the same move without the heading
    free = solve_direct_newton(sphere_steering(robot, TARGET, T), param, res.params, ctol=1e-10, gtol=1e-7)
    assert free.converged and free.cost < cost


def test_tracking_task_and_guess_arguments_are_named():
    """sphere_tracking's numbers, shell_push's dv and robot, linear_guess's problem,
    parametrization and rcond, sphere_steering's T as a string and a heading that is not
    a number: named ProblemErrors before any numerics (they were numpy TypeErrors, a JAX
    shape error inside the running cost, AttributeErrors, or silently accepted)."""
    from controls.tasks import shell_push, sphere_tracking

    robot = ShellWithTop()
    for kw, words in ((dict(amplitude="a"), "amplitude must be a real number"),
                      (dict(amplitude=[0.5, 0.5]), "amplitude must be a scalar"),
                      (dict(horizon=None), "horizon must be a time in seconds"),
                      (dict(centre=(0.0, 0.0, 0.0)), "centre must be a 2-vector"),
                      (dict(centre=(np.nan, 0.0)), "centre must be finite"),
                      (dict(position_weight=-1.0), "position_weight must be non-negative"),
                      (dict(swing_weight=np.nan), "swing_weight must be finite"),
                      (dict(effort_weight="a"), "effort_weight must be a real number")):
        with pytest.raises(controls.ProblemError, match=f"sphere_tracking: {words}"):
            sphere_tracking(robot, **kw)
    with pytest.raises(controls.ProblemError, match="shell_push: dv must be a 2-vector"):
        shell_push(robot, (0.1, 0.0, 0.0))
    with pytest.raises(controls.ProblemError, match="shell_push: robot must be an nhjax.scenes.ShellWithTop"):
        shell_push(nhjax.scenes.FallingCat(), (0.1, 0.0))
    with pytest.raises(controls.ProblemError, match="horizon T must be a positive number of seconds, got '1'"):
        sphere_steering(robot, TARGET, "1")
    with pytest.raises(controls.ProblemError, match="heading must be a finite angle"):
        sphere_steering(robot, TARGET, T, heading="north")
    ocp = sphere_steering(robot, TARGET, T)
    with pytest.raises(controls.ProblemError, match="linear_guess: the problem must be a controls.OCP"):
        linear_guess("ocp", controls.Chebyshev(6, T, 3))
    with pytest.raises(controls.ProblemError, match="linear_guess: param must be a control parametrization"):
        linear_guess(ocp, "p")
    with pytest.raises(controls.ProblemError, match="linear_guess: the parametrization has 2 inputs"):
        linear_guess(ocp, controls.Chebyshev(6, T, 2))
    with pytest.raises(controls.ProblemError, match="linear_guess: rcond must be positive"):
        linear_guess(ocp, controls.Chebyshev(6, T, 3), rcond=-1.0)
