"""Iwai's falling cat (seed 000, secs. 6-7): engine vs hand equations, exact
holonomy, zero angular momentum in 3-D, work-energy balance, RKMK attitudes,
gradients, and the singular chart."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.lie import so3
from nhjax.scenes import FallingCat, FallingCatKinematic, FallingCatLagrangian, ShapeLoopTorque

TORQUE = nhjax.Sinusoids([-0.015, 0.0], [0.04, 0.02], [1.7, 0.9], [0.0, np.pi / 2])
CATS = [FallingCat(), FallingCat(I1=0.3, lam=1.7, B=0.8), FallingCat(I1=2.0, lam=0.05, B=4.0)]


def random_states(rng, n):
    th = rng.uniform(0.1, np.pi - 0.1, n)
    rest = rng.normal(size=(n, 4))
    return jnp.asarray(np.column_stack([th, rest]))


@pytest.mark.parametrize("cat", CATS)
def test_engine_agrees_with_hand_equations(cat, rng):
    xs = random_states(rng, 40)
    us = jnp.asarray(rng.normal(size=(40, 2)))
    engine = FallingCat(cat.I1, cat.lam, cat.B, equations="engine")
    hand_vf = jax.vmap(lambda x, u: cat.vector_field(0.0, x, u))(xs, us)
    eng_vf = jax.vmap(lambda x, u: engine.vector_field(0.0, x, u))(xs, us)
    np.testing.assert_allclose(eng_vf, hand_vf, rtol=1e-10, atol=1e-10)

    lag = cat.lagrangian_model()

    def engine_full(x, u):
        qdd, lam = lag.accelerations(0.0, x[:3], cat.velocities(x), u)
        return qdd, lam

    qdd, lam = jax.vmap(engine_full)(xs, us)
    # psi'' from differentiating the connection psi' = -f(theta) chi'
    th, thd, chd = xs[:, 0], xs[:, 3], xs[:, 4]
    psidd = -jax.vmap(cat.curvature)(th) * thd * chd - jax.vmap(cat.f)(th) * hand_vf[:, 4]
    np.testing.assert_allclose(qdd[:, 2], psidd, rtol=1e-10, atol=1e-10)
    # zero angular momentum is conserved by internal torques: no constraint force is needed
    np.testing.assert_allclose(lam, 0.0, atol=1e-10)


def test_engine_mass_matrix_is_iwai_metric(rng):
    """Hessian of the two-body kinetic energy = the metric (7.2) in (theta, chi, psi)."""
    cat = CATS[1]
    lag = cat.lagrangian_model()
    for th in rng.uniform(0.05, 3.0, 5):
        q = jnp.array([th, rng.normal(), rng.normal()])
        s, D, f, I1 = np.sin(th), float(cat.D(th)), float(cat.f(th)), float(cat.I1)
        lam, B = float(cat.lam), float(cat.B)
        expect = 2 * I1 * np.array(
            [[1 + B * s * s, 0, 0], [0, lam * s * s / D + D * f * f, D * f], [0, D * f, D]]
        )
        np.testing.assert_allclose(lag.mass_matrix(q), expect, rtol=1e-12, atol=1e-14)


def test_from_dimensions():
    m, L, r = 2.0, 0.8, 0.1
    cat = FallingCat.from_dimensions(mass=m, length=L, radius=r)
    np.testing.assert_allclose(cat.B, 3 * L**2 / (3 * r**2 + L**2), rtol=1e-14)
    np.testing.assert_allclose(cat.lam, 6 * r**2 / (3 * r**2 + L**2), rtol=1e-14)
    np.testing.assert_allclose([cat.l, cat.radius, cat.length], [L / 2, r, L], rtol=1e-12)
    with pytest.raises(ValueError, match="lam"):
        FallingCat(lam=-1.0)
    # every cat model is built from the same cylinders, with the same parameters
    from nhjax.scenes import FallingCatAttitudes, FallingCatKinematic, FallingCatLagrangian, FallingCatSmooth

    for cls in (FallingCatKinematic, FallingCatSmooth, FallingCatLagrangian, FallingCatAttitudes):
        other = cls.from_dimensions(mass=m, length=L, radius=r)
        assert type(other) is cls
        np.testing.assert_allclose([other.I1, other.lam, other.B, other.mass], [cat.I1, cat.lam, cat.B, m], rtol=0)
    with pytest.raises(ValueError, match="radius"):
        FallingCatSmooth.from_dimensions(radius=-0.1)


class TwistAtFixedTheta(eqx.Module):
    """Velocity control: chi advances by 2 pi windings in time T at constant rate."""

    rate: jax.Array

    def __call__(self, t, x):
        return jnp.stack([jnp.zeros_like(self.rate), self.rate])


class CircleLoop(eqx.Module):
    """Velocity control: counter-clockwise circle of radius rho in the (theta, chi) plane."""

    rho: jax.Array
    omega: jax.Array

    def __call__(self, t, x):
        a = self.omega * t
        return self.rho * self.omega * jnp.stack([-jnp.sin(a), jnp.cos(a)])


@pytest.mark.parametrize("lam", [0.05, 0.3, 1.0, 2.0])  # 2: a thin disk, the largest an axisymmetric body has
def test_fixed_theta_holonomy_closed_form(lam):
    kin = FallingCatKinematic(lam=lam)
    for theta in (0.2, 0.9, 1.4):
        tr = nhjax.simulate(kin, jnp.array([theta, 0.0, 0.0]), 2.0, control=TwistAtFixedTheta(jnp.asarray(np.pi)),
                            rtol=1e-12, atol=1e-12, saveat=2)
        np.testing.assert_allclose(tr.xs[-1, 2], -2 * np.pi * float(kin.f(theta)), rtol=1e-9)


@pytest.mark.parametrize("cat", CATS)
def test_torque_driven_loop_turns_by_closed_form(cat):
    """Bend, twist once at theta1, unbend, all under torques: psi turns by -2 pi f(theta1)."""
    for theta1 in (0.35, 0.8, 1.3):
        loop = ShapeLoopTorque(cat, theta0=0.15, theta1=theta1, windings=1.0)
        tr = nhjax.simulate(cat, cat.initial_state(0.15), float(loop.duration), control=loop,
                            rtol=1e-12, atol=1e-12, saveat=2)
        np.testing.assert_allclose(tr["psi"][-1], -2 * np.pi * float(cat.f(theta1)), rtol=1e-9)
        np.testing.assert_allclose(tr.xs[-1, [0, 1, 3, 4]], [0.15, 2 * np.pi, 0, 0], atol=1e-9)


def test_small_loops_match_curvature_integral():
    """Stokes: a ccw loop in (theta, chi) turns psi by -(integral of F12 over the disk);
    for small loops that is -F12(centre) * area to O(rho^2)."""
    kin = FallingCatKinematic(lam=0.4)
    thc = 0.7
    nodes, weights = np.polynomial.legendre.leggauss(40)
    for rho in (0.2, 0.05, 0.01):
        x0 = jnp.array([thc + rho, 0.0, 0.0])
        tr = nhjax.simulate(kin, x0, 1.0, control=CircleLoop(jnp.asarray(rho), jnp.asarray(2 * np.pi)),
                            rtol=1e-12, atol=1e-13, saveat=2)
        dpsi = float(tr.xs[-1, 2])
        # area integral of F12 over the disk by Gauss-Legendre in (r, angle)
        r = 0.5 * rho * (nodes + 1)
        a = np.pi * (nodes + 1)
        R, A = np.meshgrid(r, a, indexing="ij")
        F = np.asarray(jax.vmap(kin.curvature)(jnp.asarray(thc + R * np.cos(A)).ravel())).reshape(R.shape)
        integral = np.einsum("i,j,ij->", weights * 0.5 * rho, weights * np.pi, F * R)
        np.testing.assert_allclose(dpsi, -integral, rtol=1e-9, atol=1e-15)
        lead = -float(kin.curvature(thc)) * np.pi * rho**2
        assert abs(dpsi - lead) < 0.2 * rho**2 * abs(lead)


@pytest.fixture(scope="module")
def torque_run():
    cat = FallingCat()
    x0 = cat.initial_state(0.8, chi_dot=0.5)
    return cat, nhjax.simulate(cat, x0, 10.0, control=TORQUE, rtol=1e-12, atol=1e-12, saveat=101)


def test_zero_angular_momentum_in_3d_and_work_energy(torque_run):
    cat, tr = torque_run
    for k in ("x", "y", "z"):
        assert np.abs(np.asarray(tr.invariants[f"angular_momentum_{k}"])).max() < 1e-9
    # the cat moved a lot: this is not a trivial zero
    assert abs(float(tr["psi"][-1])) > 1.0
    assert float(tr.invariant_drift["energy - work"]) < 1e-9
    assert float(jnp.max(tr.work) - jnp.min(tr.work)) > 1e-3


@pytest.mark.slow
def test_engine_equations_give_the_same_motion(torque_run):
    cat, tr = torque_run
    eng = FallingCat(equations="engine")
    tr2 = nhjax.simulate(eng, tr.xs[0], 10.0, control=TORQUE, rtol=1e-12, atol=1e-12, saveat=101)
    np.testing.assert_allclose(tr2.xs, tr.xs, atol=1e-9)


def test_rkmk_attitudes_reconstruct_the_chart(torque_run):
    cat, tr = torque_run
    att = cat.attitude_model()
    y0 = att.initial_state(0.8, chi_dot=0.5)
    ta = nhjax.simulate(att, y0, 10.0, control=TORQUE, rtol=1e-12, atol=1e-12, saveat=101)
    g1, g2, s = ta.xs
    Rs = jax.vmap(lambda x: cat.poses(x[:3])[0])(tr.xs)
    np.testing.assert_allclose(g1, Rs[:, 0], atol=1e-9)
    np.testing.assert_allclose(g2, Rs[:, 1], atol=1e-9)
    for g in (g1, g2):
        assert np.abs(np.einsum("nji,njk->nik", g, g) - np.eye(3)).max() < 1e-13
    # angular momentum from the reconstructed attitudes alone
    for k in ("x", "y", "z"):
        assert np.abs(np.asarray(ta.invariants[f"angular_momentum_{k}"])).max() < 1e-9


@pytest.mark.slow(reason="forward mode through simulate against differences runs in the default run in "
                         "test_one_function (diffrax.ForwardMode) and test_first_answers (defaults); the "
                         "curvature F12 in test_small_loops_match_curvature_integral")
def test_gradient_of_turn_matches_fd_and_closed_form():
    """Forward-mode derivative of the achieved turn in the loop parameters (theta0, theta1,
    t_twist) against central differences and against -2 pi F12(theta1)."""
    cat = FallingCat()

    def turn(p):
        loop = ShapeLoopTorque(cat, theta0=p[0], theta1=p[1], windings=1.0, t_twist=p[2])
        tr = nhjax.simulate(cat, cat.initial_state(p[0]), loop.duration, control=loop, rtol=1e-11,
                            atol=1e-11, saveat=2, adjoint=diffrax.ForwardMode(), diagnostics=False)
        return tr.xs[-1, 2]

    p = jnp.array([0.2, 0.7, 2.5])
    g = jax.jacfwd(turn)(p)
    h = 1e-5
    fd = np.array([(turn(p + h * e) - turn(p - h * e)) / (2 * h) for e in np.eye(3)])
    np.testing.assert_allclose(g, fd, atol=1e-6)
    np.testing.assert_allclose(g[1], -2 * np.pi * float(cat.curvature(0.7)), rtol=1e-7)


@pytest.mark.slow
def test_gradient_in_torque_amplitudes_matches_fd():
    """A motion whose turn depends on everything: sinusoidal torques, gradient in amplitudes."""
    cat, h = FallingCat(), 1e-5

    def psi_end(amp):
        ctrl = nhjax.Sinusoids(TORQUE.offset, amp, TORQUE.omega, TORQUE.phase)
        tr = nhjax.simulate(cat, cat.initial_state(0.8, chi_dot=0.5), 10.0, control=ctrl,
                            rtol=1e-11, atol=1e-11, saveat=2)
        return tr.xs[-1, 2]

    amp = TORQUE.amplitude
    g = jax.grad(psi_end)(amp)
    fd = np.array([(psi_end(amp + h * e) - psi_end(amp - h * e)) / (2 * h) for e in np.eye(2)])
    np.testing.assert_allclose(g, fd, rtol=1e-5)
    assert np.all(np.abs(fd) > 1.0)


def test_singular_chart_is_reported():
    cat = FallingCat(chart_eps=1e-3)
    x0 = cat.initial_state(0.3, theta_dot=-1.0)
    with pytest.raises(nhjax.ChartSingularityError, match=r"sin\(theta\)") as err:
        nhjax.simulate(cat, x0, 2.0)
    e = err.value
    assert e.guard == "sin_theta" and 0.25 < e.t < 0.32
    np.testing.assert_allclose(np.sin(e.trajectory["theta"][-1]), 1e-3, atol=1e-10)
    tr = nhjax.simulate(cat, x0, 2.0, on_guard="stop")
    assert tr.guard == "sin_theta" and float(tr.ts[-1]) == pytest.approx(e.t)
    with pytest.raises(nhjax.ChartSingularityError, match="already outside"):
        nhjax.simulate(cat, cat.initial_state(0.0), 1.0)


def test_inconsistent_initial_conditions():
    lag = FallingCatLagrangian(0.1, 0.3, 2.0)
    q, qd = jnp.array([0.7, 0.0, 0.0]), jnp.array([0.1, 1.0, 0.0])  # psi' should be -f chi'
    with pytest.raises(nhjax.ConstraintViolationError, match="velocity"):
        nhjax.simulate(lag, jnp.concatenate([q, qd]), 1.0)
    x0 = lag.project(0.0, jnp.concatenate([q, qd]))
    np.testing.assert_allclose(x0[5], -float(lag.f(0.7)) * x0[4], rtol=1e-12)
    np.testing.assert_allclose(lag.angular_momentum_3d(x0[:3], x0[3:]), 0.0, atol=1e-15)


@pytest.mark.slow
def test_projected_start_stays_consistent():
    lag = FallingCatLagrangian(0.1, 0.3, 2.0)
    x = jnp.array([0.7, 0.0, 0.0, 0.1, 1.0, 0.0])
    tr = nhjax.simulate(lag, x, 1.0, project=True, rtol=1e-10, atol=1e-10)
    assert float(tr.constraint_drift["velocity"]) < 1e-9
    for k in ("angular_momentum_x", "angular_momentum_z"):
        assert float(tr.invariant_drift[k]) < 1e-12


def test_theta_for_turn():
    cat = FallingCat()
    th = cat.theta_for_turn(np.pi)
    np.testing.assert_allclose(cat.f(th), 0.5, rtol=1e-13)
    np.testing.assert_allclose(cat.holonomy_fixed_theta(cat.theta_for_turn(1.0, 2), 2), -1.0, rtol=1e-13)
    with pytest.raises(ValueError, match="2 pi"):
        cat.theta_for_turn(7.0)
