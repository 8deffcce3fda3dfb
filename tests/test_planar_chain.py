"""PlanarChain (seed 001): the two-body closed forms of sec. 4.1, reduced against
unreduced (the engine on R^3N with hinge constraints), momentum conservation,
batches, gradients through the reduced dynamics, and the holonomy of shape loops
against the curvature integral (Stokes)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.mechanics import curvature_integral
from nhjax.scenes import PlanarChain
from nhjax.scenes.planar_chain import two_body_closed_forms

M1, M2, I1, I2, D1, D2 = 1.3, 0.7, 0.11, 0.05, 0.4, 0.25


@jax.jit
def _two_body(ch, phi, phid, mu, u):
    r = phi[None]
    x = ch.join(None, jnp.zeros(3), r, phid[None], mu)
    tau_xi, tau_r = ch.generalized_forces(r, u)
    return dict(M=ch.reduced_metric(r)[0, 0], A=ch.connection(r), I=ch.locked_inertia(r), G=ch.metric(r),
                rdd=ch.shape_accelerations(x, u)[0], tau_xi=tau_xi, tau_r=tau_r[0])


def _hand_forces(phi, u, axes):
    """(tau_v (2), tau_theta, tau_phi) of joint torque T and thrusts F_i along axes (body
    frames), in the mean-angle frame: written out from the geometry, not from the power."""
    e = lambda a: np.array([np.cos(a), np.sin(a)])  # noqa: E731
    ep = lambda a: np.array([-np.sin(a), np.cos(a)])  # noqa: E731
    m = M1 + M2
    t1, t2 = -phi / 2, phi / 2  # body angles in the reference frame
    hinge = D1 * e(t1) + D2 * e(t2)
    s = [-(M2 / m) * hinge, (M1 / m) * hinge]
    dhinge = -(D1 / 2) * ep(t1) + (D2 / 2) * ep(t2)
    ds = [-(M2 / m) * dhinge, (M1 / m) * dhinge]
    T, F = u[0], u[1:]
    f = [F[i] * np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]) @ axes[i] for i, t in enumerate((t1, t2))]
    tau_v = f[0] + f[1]
    tau_th = sum(s[i][0] * f[i][1] - s[i][1] * f[i][0] for i in range(2))
    tau_phi = T + sum(f[i] @ ds[i] for i in range(2))
    return tau_v, tau_th, tau_phi


def test_two_body_equals_seed_closed_forms(rng):
    """M(phi), C(phi), N(phi), A_loc, the locked inertia, G and the forcing X tau of
    sec. 4.1 (re-derived signs, see the module): M phi'' + C phi'^2 + N = X tau to 1e-12."""
    axes = rng.normal(size=(2, 2))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    ch = PlanarChain(masses=(M1, M2), inertias=(I1, I2), hinge_out=[[D1, 0.0]], hinge_in=[[-D2, 0.0]],
                     reference="mean", momentum="body", thruster_axes=axes)
    m = M1 + M2
    for phi in (0.3, 1.2, -2.0, 2.9):
        cf = two_body_closed_forms(M1, M2, I1, I2, D1, D2, phi)
        phid, mu, u = rng.normal(), rng.normal(size=3), rng.normal(size=3)
        q = _two_body(ch, jnp.asarray(phi), jnp.asarray(phid), jnp.asarray(mu), jnp.asarray(u))
        np.testing.assert_allclose(q["M"], cf["M"], rtol=1e-12)
        np.testing.assert_allclose(q["A"][:, 0], [0.0, 0.0, cf["A_theta"]], atol=1e-13)
        np.testing.assert_allclose(q["I"], np.diag([m, m, cf["S"]]), atol=1e-13)
        # G of the seed (sec. 4.1): m I2, 1^T J 1, J-dagger (our sign: (I~2 - I~1)/2), J-ddagger
        J = cf["J"]
        np.testing.assert_allclose(q["G"][2, 3], (J[1, 1] - J[0, 0]) / 2, atol=1e-13)
        np.testing.assert_allclose(q["G"][3, 3], (J[0, 0] + J[1, 1] - 2 * J[0, 1]) / 4, atol=1e-13)
        tau_v, tau_th, tau_phi = _hand_forces(phi, u, axes)
        np.testing.assert_allclose(q["tau_xi"], [*tau_v, tau_th], atol=1e-13)
        np.testing.assert_allclose(q["tau_r"], tau_phi, atol=1e-13)
        X_tau = tau_phi - tau_th * cf["A_theta"]
        lhs = cf["M"] * float(q["rdd"]) + cf["C"] * phid**2 + cf["N_over_mu3sq"] * mu[2] ** 2
        np.testing.assert_allclose(lhs, X_tau, atol=1e-12 * max(1.0, abs(X_tau)))


CTRL = nhjax.Sinusoids(np.zeros(5), [0.3, -0.2, 0.1, 0.2, -0.1], [1.3, 0.8, 2.0, 1.1, 0.5], [0.0, 0.5, 1.0, 2.0, 3.0])
NO_THRUST = nhjax.Sinusoids(np.zeros(5), [0.3, -0.2, 0.0, 0.0, 0.0], [1.3, 0.8, 2.0, 1.1, 0.5], [0.0, 0.5, 1.0, 2.0, 3.0])


@pytest.fixture(scope="module")
def thruster_chain():
    ch = PlanarChain(masses=(1.0, 0.8, 1.2), lengths=(1.0, 0.7, 0.9), thrusters=True)
    x0 = ch.initial_state([0.4, -0.6], [0.5, 0.2], pose=[0.1, -0.2, 0.3], momentum=[0.2, -0.1, 0.5])
    return ch, x0


def test_reduced_equals_unreduced_engine(thruster_chain):
    """Joint torques and thrusters, nonzero momentum: body poses and velocities of the
    reduced solution (SE(2), connection, reconstruction) = the engine's on R^9 with
    hinge constraints, to 1e-9."""
    ch, x0 = thruster_chain
    tr = nhjax.simulate(ch, x0, 5.0, control=CTRL, rtol=1e-12, atol=1e-12, saveat=11, diagnostics=False)
    un = ch.unreduced()
    tu = nhjax.simulate(un, ch.unreduced_state(x0), 5.0, control=CTRL, rtol=1e-12, atol=1e-12, saveat=11,
                        diagnostics=False)
    yr = jax.jit(jax.vmap(ch.unreduced_state))(tr.xs)
    np.testing.assert_allclose(yr, tu.xs, atol=1e-9)
    assert float(jnp.abs(tr.xs[-1, :3] - x0[:3]).max()) > 0.5  # it moved


def test_momentum_conserved_without_thrusters(thruster_chain):
    """Joint torques only (thrust amplitudes 0, same compiled solve): the momentum map of
    the reconstructed bodies stays at its initial value to 1e-12, while the chain moves."""
    ch, x0 = thruster_chain
    tr = nhjax.simulate(ch, x0, 5.0, control=NO_THRUST, rtol=1e-12, atol=1e-12, saveat=11, diagnostics=False)
    J = jax.jit(jax.vmap(ch.momentum_map))(tr.xs)
    np.testing.assert_allclose(J, np.broadcast_to([0.2, -0.1, 0.5], J.shape), atol=1e-12)
    assert float(jnp.abs(tr.xs[-1, 3:5] - x0[3:5]).max()) > 0.1


class Torques(eqx.Module):
    amp: jax.Array

    def __call__(self, t, x):
        return self.amp * jnp.stack([jnp.sin(2.0 * t), jnp.cos(3.0 * t)])


@pytest.fixture(scope="module")
def zero_momentum_chain():
    return PlanarChain(masses=(1.0, 1.5, 0.8), lengths=(1.0, 1.2, 0.8), group="SO2")


def test_gradient_through_reduced_dynamics(zero_momentum_chain):
    """d angle(T) / d torque amplitudes with DiscreteAdjoint = central differences."""
    ch = zero_momentum_chain
    x0 = ch.initial_state([0.5, -0.4])

    def final_angle(amp):
        tr = nhjax.simulate(ch, x0, 3.0, control=Torques(amp), rtol=1e-12, atol=1e-12, saveat=2,
                            adjoint=nhjax.DiscreteAdjoint(), diagnostics=False)
        return tr.xs[-1, 0]

    amp = jnp.array([0.4, -0.3])
    f = jax.jit(final_angle)
    g = jax.jit(jax.grad(final_angle))(amp)
    h = 1e-5
    fd = [(f(amp.at[i].add(h)) - f(amp.at[i].add(-h))) / (2 * h) for i in range(2)]
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9)
    assert float(jnp.abs(g).min()) > 1e-3


@pytest.mark.slow  # (batch = single: test_batch on the cat; make test-all)
def test_batch_equals_single(zero_momentum_chain):
    """simulate_batch on the reduced system: each member as simulate() alone (velocity
    control along shape loops of different sizes: different step counts)."""
    kin = zero_momentum_chain.kinematic()
    X0 = jnp.stack([kin.initial_state([1.0 + a, 0.8]) for a in (1.4, 0.6, 0.1)])
    ctrls = nhjax.stack([LoopRate(jnp.asarray(a), jnp.asarray(b)) for a, b in ((1.4, 1.0), (0.6, 0.9), (0.1, 0.05))])
    tb = nhjax.simulate_batch(kin, X0, 1.0, control=ctrls, in_axes={"x0": 0, "control": 0}, rtol=1e-10,
                              atol=1e-10, saveat=3, diagnostics=False)
    for i in range(3):
        ctrl = jax.tree_util.tree_map(lambda a: a[i], ctrls)
        ts = nhjax.simulate(kin, X0[i], 1.0, control=ctrl, rtol=1e-10, atol=1e-10, saveat=3, diagnostics=False)
        np.testing.assert_allclose(tb.xs[i], ts.xs, rtol=1e-12, atol=1e-12)


class LoopRate(eqx.Module):
    """Velocity control along the ellipse phi(t) = c + (a cos 2 pi t, b sin 2 pi t)."""

    a: jax.Array
    b: jax.Array

    def __call__(self, t, x):
        w = 2 * jnp.pi
        return jnp.stack([-self.a * w * jnp.sin(w * t), self.b * w * jnp.cos(w * t)])


def test_holonomy_of_large_loops_is_curvature_integral(zero_momentum_chain):
    """Stokes: at zero momentum the chain's SO(2) connection is abelian, so a closed loop
    of the joint angles turns the chain by exactly -(integral of F over the enclosed
    region). Large ellipses (semi-axes up to 1.4 rad), one simulation each."""
    kin = zero_momentum_chain.kinematic()
    c = jnp.array([1.0, 0.8])
    turns, predicted = [], []
    for a, b in ((1.4, 1.0), (0.6, 0.9), (0.1, 0.05)):
        x0 = kin.initial_state(c + jnp.array([a, 0.0]))
        tr = nhjax.simulate(kin, x0, 1.0, control=LoopRate(jnp.asarray(a), jnp.asarray(b)), rtol=1e-12, atol=1e-12,
                            saveat=2, diagnostics=False)
        np.testing.assert_allclose(tr.xs[-1, 1:], x0[1:], atol=1e-9)  # the shape returned
        loop = lambda al, a=a, b=b: c + jnp.stack([a * jnp.cos(al), b * jnp.sin(al)])  # noqa: E731
        integral = curvature_integral(kin, loop, c, n=40)
        turns.append(float(tr.xs[-1, 0] - x0[0]))
        predicted.append(-float(integral[0]))
    np.testing.assert_allclose(turns, predicted, rtol=1e-8, atol=1e-12)
    assert abs(turns[0]) > 0.05  # a large loop turns the chain visibly


@pytest.mark.slow
def test_two_links_cannot_turn_by_a_loop():
    """N = 2: the shape space is 1-D, a closed joint motion encloses no area and the chain
    returns to its attitude (at zero momentum)."""
    kin = PlanarChain(masses=(1.0, 2.0), lengths=(1.0, 0.5), group="SO2").kinematic()
    ctrl = nhjax.Sinusoids([0.0], [2.0], [2 * np.pi], [0.0])
    tr = nhjax.simulate(kin, kin.initial_state([0.3]), 1.0, control=ctrl, rtol=1e-12, atol=1e-12, saveat=21)
    np.testing.assert_allclose(tr.xs[-1], tr.xs[0], atol=1e-10)
    assert float(jnp.abs(tr.xs[:, 0]).max()) > 0.05  # it turned on the way


def test_errors():
    with pytest.raises(ValueError, match="at least 2 bodies"):
        PlanarChain(masses=(1.0,))
    with pytest.raises(ValueError, match="masses must be positive"):
        PlanarChain(masses=(1.0, -1.0))
    with pytest.raises(ValueError, match="hinge_out must have shape"):
        PlanarChain(masses=(1.0, 1.0), hinge_out=[[0.5, 0.0], [0.1, 0.0]])
    with pytest.raises(ValueError, match="thrusters move the centre of mass"):
        PlanarChain(thrusters=True, group="SO2")
    with pytest.raises(ValueError, match="momentum='zero' cannot hold"):
        PlanarChain(thrusters=True, momentum="zero")


@pytest.mark.slow
def test_reorientation_direct_and_pontryagin_agree():
    """A 3-link chain turns by 0.2 rad at zero momentum, rest to rest, least int |u|^2:
    the direct method (Newton over Chebyshev torques, from a Stokes-sized joint loop) and
    Pontryagin shooting from its costates agree to 1e-6, and pmp_residual confirms the
    Pontryagin extremal (and the direct optimum up to its Chebyshev restriction)."""
    import controls
    from controls.tasks import chain_loop_guess, chain_radius_for_turn, chain_reorientation

    chain = PlanarChain(group="SO2")
    phi0, T, turn = jnp.array([0.5, 0.5]), 3.0, 0.2
    radius, orientation = chain_radius_for_turn(chain, turn, phi0)
    ocp = chain_reorientation(chain, turn, T, phi0)
    param = controls.Chebyshev(30, T, 2)
    d = controls.solve_direct_newton(ocp, param, chain_loop_guess(chain, param, phi0, T, radius, orientation=orientation))
    assert d.converged and d.violation < 1e-9
    res = controls.pmp_residual(ocp, d.control)
    assert res["stationarity"] < 1e-2
    ind = controls.solve_pontryagin(ocp, res["ps"][-1], res["multipliers"], solver="lm")
    assert ind.converged and ind.violation < 1e-9
    assert abs(d.cost - ind.cost) / ind.cost < 1e-6
    assert ind.cost <= d.cost * (1 + 1e-9)  # the Chebyshev restriction can only cost more
    np.testing.assert_allclose(ind.trajectory.xs[-1, 0], turn, atol=1e-9)


@pytest.mark.slow  # (the step control it needs: test_controls.py's Jacobian-at-rest tests; make test-all)
def test_thruster_steering_reaches_the_target_pose_at_rest():
    """controls.tasks.chain_steering (thrusts and joint torques, rest to rest at a pose) by
    both direct methods from zero inputs (where the chain stays at rest: the shooting
    solves' step cap keeps their Jacobian that of the inputs, see controls.newton._step_cap):
    the answer's control, re-simulated apart at 1e-12, ends at the target pose with the
    joints back and the momentum zero; the reported cost is int |u|^2 of that control by
    quadrature; SQP and feasible-path Newton reach the same optimum."""
    import controls
    from controls.tasks import chain_steering

    chain, phi0, T, target = PlanarChain(thrusters=True), jnp.array([0.5, 0.5]), 3.0, (0.5, 0.3, 0.3)
    ocp = chain_steering(chain, target, T, phi0)
    param = controls.Chebyshev(12, T, chain.control_dim)
    d = controls.solve_direct_newton(ocp, param, jnp.zeros(param.size), progress=False)
    assert d.converged and d.violation < 1e-9, d.message
    q = controls.solve_direct(ocp, param, jnp.zeros(param.size), progress=False)
    assert q.converged and q.violation < 1e-8, q.message
    np.testing.assert_allclose(q.cost, d.cost, rtol=1e-7)
    tr = nhjax.simulate(chain, ocp.x0, T, control=d.control, rtol=1e-12, atol=1e-12, saveat=2001)
    goal = np.asarray(ocp.x0).copy()
    goal[:3] = target
    np.testing.assert_allclose(np.asarray(tr.xs[-1]), goal, rtol=0, atol=1e-8)
    assert float(jnp.max(jnp.abs(tr.xs[:, 0]))) > 0.1  # it did travel
    us = np.asarray(tr.us)
    np.testing.assert_allclose(np.trapezoid((us**2).sum(1), np.asarray(tr.ts)), d.cost, rtol=1e-6)


def test_reduction_helpers_name_bad_arguments(zero_momentum_chain, open_ellipse):
    """Issue 40: the geometry of a ReducedSystem with the wrong number of shape
    coordinates, a state of another system or NaN, and curvature_integral with an open
    path, a loop of the wrong size or NaN, are refused by name before any numerics."""
    from nhjax.errors import ParameterError, StateError
    from nhjax.mechanics.reduction import EllipseLoop

    ch = zero_momentum_chain  # k = 2 joint angles
    x = ch.initial_state([0.3, -0.2], [0.1, 0.4])
    for method in ("metric", "locked_inertia", "connection", "reduced_metric", "curvature", "rotational_inertia",
                   "inertia_condition"):
        for bad in (jnp.zeros(3), jnp.zeros(1), jnp.zeros((2, 2)), [0.1, "a"]):
            with pytest.raises(ParameterError, match=f"PlanarChain.{method}: r must") as err:
                getattr(ch, method)(bad)
            assert err.value.name == "r"
        with pytest.raises(ParameterError, match="NaN"):
            getattr(ch, method)(jnp.array([0.1, np.nan]))
    for method in ("group_velocity", "body_states", "momentum_map", "shape_accelerations"):
        for bad in (x[:3], jnp.concatenate([x, x]), (jnp.eye(3), x)):
            with pytest.raises(StateError, match=f"PlanarChain.{method}: x must be a state of PlanarChain"):
                getattr(ch, method)(bad)
        with pytest.raises(StateError, match="NaN"):
            getattr(ch, method)(x.at[2].set(np.inf))
    with pytest.raises(ParameterError, match="u must have shape \\(2,\\)"):
        ch.shape_accelerations(x, jnp.zeros(3))
    with pytest.raises(ParameterError, match="shape_acc must have shape"):
        ch.inverse_dynamics(x, jnp.zeros(1))

    kin = ch.kinematic()
    c = jnp.array([1.0, 0.8])
    with pytest.raises(ParameterError, match="does not close: \\|loop\\(2 pi\\) - loop\\(0\\)\\| = 6.28") as err:
        curvature_integral(kin, lambda a: c + jnp.stack([a, 0.3 * jnp.sin(a)]), c)  # an open path
    assert err.value.name == "loop"
    with pytest.raises(ParameterError, match="shape \\(2,\\), got \\(3,\\)"):
        curvature_integral(kin, lambda a: jnp.stack([a, a, a]), c)
    with pytest.raises(ParameterError, match="centre must be finite"):
        EllipseLoop([np.nan, 0.8], 0.1)
    with pytest.raises(ParameterError, match="a must be positive"):
        EllipseLoop(c, -0.1)
    nan_loop = EllipseLoop(c, 0.1)
    nan_loop = eqx.tree_at(lambda e: e.b, nan_loop, jnp.asarray(np.nan))  # past the constructor's check
    with pytest.raises(ParameterError, match="not finite at alpha"):
        curvature_integral(kin, nan_loop, c)
    # a loop open by 1e-6 of its size fails the default closure_tol (1e-8) and passes a looser
    # one, with the integral of the closed ellipse to that order (one program for both)
    with pytest.raises(ParameterError, match="closure_tol = 1.0e-08"):
        curvature_integral(kin, open_ellipse(c, *jnp.array([0.6, 0.9, 0.6e-6])), c, n=40)
    closed = curvature_integral(kin, open_ellipse(c, *jnp.array([0.6, 0.9, 0.0])), c, n=40)
    loose = curvature_integral(kin, open_ellipse(c, *jnp.array([0.6, 0.9, 0.6e-6])), c, n=40, closure_tol=1e-5)
    np.testing.assert_allclose(loose, closed, rtol=1e-5)
    assert abs(float(closed[0])) > 0.01



class PathRate(eqx.Module):
    """The joint rates phi' of controls.tasks.chain_loop_path's circle (its quintic time
    law), as the kinematic chain's input."""

    phi0: jax.Array
    radius: jax.Array
    orientation: int = eqx.field(static=True)
    T: float = eqx.field(static=True)

    def __call__(self, t, x):
        from controls.tasks import chain_loop_path

        return chain_loop_path(self.phi0, self.radius, (1.0, 1.0), self.orientation, self.T)(t)[1]


def test_radius_for_turn_sizes_a_loop_that_turns_the_chain_by_the_request():
    """controls.tasks.chain_radius_for_turn (one stored program: the secant method on the
    curvature integral) for both signs of the turn: the kinematic chain driven once around
    the circle of that radius turns by the request to the integration tolerance and its
    joints come back (Stokes: exact for the abelian SO(2) connection); the circle's
    curvature integral, evaluated apart, is the request to 1e-10; a turn that even the
    largest circle cannot give is refused."""
    from controls import ProblemError
    from controls.tasks import chain_loop_turn, chain_radius_for_turn

    chain, phi0, T = PlanarChain(group="SO2"), jnp.array([0.5, 0.5]), 3.0
    kin = chain.kinematic()
    x0 = kin.initial_state(phi0)
    for turn in (0.2, -0.35):
        radius, orientation = chain_radius_for_turn(chain, turn, phi0)
        assert 0.1 < radius < 2.0
        assert abs(chain_loop_turn(chain, phi0, radius, orientation=orientation) - turn) < 1e-10
        tr = nhjax.simulate(kin, x0, T, control=PathRate(phi0, jnp.asarray(radius), orientation, T), rtol=1e-12,
                            atol=1e-12, saveat=2, diagnostics=False)
        np.testing.assert_allclose(tr.xs[-1, 1:], x0[1:], rtol=0, atol=1e-9)  # the joints are back
        assert abs(float(tr.xs[-1, 0] - x0[0]) - turn) < 1e-8
    with pytest.raises(ProblemError, match="turns the chain by only"):
        chain_radius_for_turn(chain, 10.0, phi0)


def test_loop_guess_torques_drive_the_chain_around_its_loop():
    """controls.tasks.chain_loop_guess (the computed torques of the loop, sampled by one
    stored program, fitted to Chebyshev(30) torques): the dynamic chain under the fitted
    torques, from rest, follows the loop's joint angles to 1e-2 rad and ends turned by the
    loop's turn to 1e-3 rad (the fit's error: wrong inverse dynamics would miss by
    order one)."""
    import controls
    from controls.tasks import chain_loop_guess, chain_loop_path, chain_radius_for_turn

    chain, phi0, T, turn = PlanarChain(group="SO2"), jnp.array([0.5, 0.5]), 3.0, 0.2
    radius, orientation = chain_radius_for_turn(chain, turn, phi0)
    param = controls.Chebyshev(30, T, 2)
    z = chain_loop_guess(chain, param, phi0, T, radius, orientation=orientation)
    tr = nhjax.simulate(chain, chain.initial_state(phi0), T, control=param.signal(z), rtol=1e-10, atol=1e-10,
                        saveat=13)
    path = chain_loop_path(phi0, radius, (1.0, 1.0), orientation, T)
    ref = np.stack([np.asarray(path(t)[0]) for t in np.asarray(tr.ts)])
    assert np.abs(np.asarray(tr.xs[:, 1:3]) - ref).max() < 1e-2
    assert abs(float(tr.xs[-1, 0]) - turn) < 1e-3


def test_loop_helpers_name_bad_arguments():
    """controls.tasks' joint-loop helpers (chain_radius_for_turn, chain_loop_turn,
    chain_loop_guess) check the chain, phi0, the direction, the radius, the orientation, T
    and the parametrization before any numerics (NaN results, numpy and JAX shape errors,
    AttributeErrors otherwise)."""
    import controls
    from controls.tasks import chain_loop_guess, chain_loop_turn, chain_radius_for_turn
    from nhjax.errors import ParameterError

    chain, phi0 = PlanarChain(group="SO2"), jnp.array([0.5, 0.5])
    for bad, words in (([0.5, np.nan], "phi0 must be finite"), ("ab", "phi0 must be a real number"),
                       ([0.5, 0.5, 0.5], "phi0 must be a 2-vector")):
        with pytest.raises(ParameterError, match=f"radius_for_turn: {words}"):
            chain_radius_for_turn(chain, 0.2, bad)
    with pytest.raises(ParameterError, match="direction must be a nonzero 2-vector"):
        chain_radius_for_turn(chain, 0.2, phi0, direction=(0.0, 0.0))
    with pytest.raises(ParameterError, match="direction must be a 2-vector"):
        chain_radius_for_turn(chain, 0.2, phi0, direction=(1.0, 0.0, 0.0))
    with pytest.raises(controls.ProblemError, match="radius_for_turn: chain must be a nhjax.scenes.PlanarChain"):
        chain_radius_for_turn(nhjax.scenes.FallingCat(), 0.2, phi0)
    with pytest.raises(ParameterError, match="chain_loop_turn: orientation must be one of 1, -1"):
        chain_loop_turn(chain, phi0, 0.1, orientation=2)
    with pytest.raises(ParameterError, match="chain_loop_turn: radius must be positive"):
        chain_loop_turn(chain, phi0, -1.0)
    param = controls.Chebyshev(10, 3.0, 2)
    for T, words in ((0.0, "T = 0.0 must be positive"), (np.nan, "T must be a finite time")):
        with pytest.raises(controls.ProblemError, match=f"chain_loop_guess: {words}"):
            chain_loop_guess(chain, param, phi0, T, 0.1)
    with pytest.raises(ParameterError, match="chain_loop_guess: radius must be finite"):
        chain_loop_guess(chain, param, phi0, 3.0, np.nan)
    with pytest.raises(controls.ProblemError, match="the parametrization has 3 inputs, PlanarChain takes 2"):
        chain_loop_guess(chain, controls.Chebyshev(10, 3.0, 3), phi0, 3.0, 0.1)
    with pytest.raises(ParameterError, match="chain_loop_guess: phi0 must be a 2-vector"):
        chain_loop_guess(chain, param, [0.5, 0.5, 0.5], 3.0, 0.1)
