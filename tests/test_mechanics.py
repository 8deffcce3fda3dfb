"""The autodiff engine: holonomic and nonholonomic constraints, multipliers,
projection and inverse dynamics, each against an exact or independent answer."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.mechanics import Lagrangian, MultibodyKinetics, RigidBody
from nhjax.lie import so3

G, L = 9.81, 1.3


def cartesian_pendulum(baumgarte=(0.0, 0.0)):
    return Lagrangian(
        2,
        T=lambda q, qd: 0.5 * 2.0 * qd @ qd,
        V=lambda q: 2.0 * G * q[1],
        position_constraints=lambda t, q: jnp.array([q @ q - L**2]),
        baumgarte=baumgarte,
    )


def angle_pendulum():
    return Lagrangian(1, T=lambda q, qd: 0.5 * 2.0 * L**2 * qd[0] ** 2, V=lambda q: -2.0 * G * L * jnp.cos(q[0]))


def test_holonomic_pendulum_matches_angle_form():
    th0, w0 = 1.2, -0.4
    xc0 = jnp.array([L * np.sin(th0), -L * np.cos(th0), L * np.cos(th0) * w0, L * np.sin(th0) * w0])
    tc = nhjax.simulate(cartesian_pendulum(), xc0, 5.0, rtol=1e-11, atol=1e-11, saveat=26)
    ta = nhjax.simulate(angle_pendulum(), jnp.array([th0, w0]), 5.0, rtol=1e-11, atol=1e-11, saveat=26)
    np.testing.assert_allclose(tc.xs[:, 0], L * np.sin(ta.xs[:, 0]), atol=1e-8)
    np.testing.assert_allclose(tc.xs[:, 1], -L * np.cos(ta.xs[:, 0]), atol=1e-8)
    assert float(tc.invariant_drift["energy"]) < 1e-8
    assert float(tc.constraint_drift["position"]) < 1e-8


def test_baumgarte_bounds_position_drift():
    xc0 = jnp.array([L, 0.0, 0.0, 0.0])
    plain = nhjax.simulate(cartesian_pendulum(), xc0, 60.0, rtol=1e-5, atol=1e-5, project_steps=False)
    stab = nhjax.simulate(cartesian_pendulum((5.0, 5.0)), xc0, 60.0, rtol=1e-5, atol=1e-5,
                          project_steps=False)
    assert float(stab.constraint_drift["position"]) < 0.2 * float(plain.constraint_drift["position"])


def skate():
    return Lagrangian(
        3,
        T=lambda q, qd: 0.5 * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * 0.7 * qd[2] ** 2,
        velocity_constraints=lambda t, q, qd: jnp.array([jnp.sin(q[2]) * qd[0] - jnp.cos(q[2]) * qd[1]]),
    )


def test_nonholonomic_skate_circle_and_multiplier():
    """Rabier-Rheinboldt (9.1)-(9.3), beta = 0: a circle of radius 2 centred at (0, -2)."""
    sys = skate()
    x0 = jnp.array([0.0, 0.0, 0.0, -4.0, 0.0, 2.0])
    tr = nhjax.simulate(sys, x0, 2 * np.pi, rtol=1e-11, atol=1e-11, saveat=50)
    t = tr.ts
    np.testing.assert_allclose(tr.xs[:, 0], -2 * np.sin(2 * t), atol=1e-8)
    np.testing.assert_allclose(tr.xs[:, 1], 2 * np.cos(2 * t) - 2, atol=1e-8)
    assert float(tr.constraint_drift["velocity"]) < 1e-9
    # the constraint force is the centripetal force m v^2 / R = 16 / 2
    _, lam = sys.accelerations(0.0, x0[:3], x0[3:])
    np.testing.assert_allclose(jnp.abs(lam), 8.0, rtol=1e-12)


def test_projection_and_inconsistent_initial_state():
    sys = skate()
    bad = jnp.array([0.0, 0.0, 0.3, -4.0, 0.5, 2.0])
    with pytest.raises(nhjax.ConstraintViolationError, match="velocity"):
        nhjax.simulate(sys, bad, 1.0)
    x = sys.project(0.0, bad)
    assert abs(float(sys.constraints(0.0, x)["velocity"][0])) < 1e-14
    # the correction is orthogonal to the constraint manifold in the kinetic metric
    M = sys.mass_matrix(x[:3])
    A = sys.constraint_jacobian(0.0, x[:3])
    d = bad[3:] - x[3:]
    admissible = jnp.array([jnp.cos(0.3), jnp.sin(0.3), 0.0])
    assert abs(float(admissible @ M @ d)) < 1e-14 and np.linalg.matrix_rank(np.asarray(A)) == 1
    tr = nhjax.simulate(sys, bad, 1.0, project=True, rtol=1e-10, atol=1e-10)
    assert float(tr.constraint_drift["velocity"]) < 1e-9
    # position projection (Gauss-Newton on optimistix) for the pendulum
    pend = cartesian_pendulum()
    xp = pend.project(0.0, jnp.array([1.0, -1.0, 0.2, 0.3]))
    np.testing.assert_allclose(xp[:2] @ xp[:2], L**2, rtol=1e-14)
    np.testing.assert_allclose(xp[:2] @ xp[2:], 0.0, atol=1e-14)


def test_inverse_dynamics_round_trip(rng):
    sys = Lagrangian(
        3,
        T=skate().T,
        velocity_constraints=skate().vel_c,
        force=lambda t, q, qd, u: jnp.array([0.0, 0.0, u[0]]) + jnp.array([jnp.cos(q[2]), jnp.sin(q[2]), 0.0]) * u[1],
        control_dim=2,
    )
    q = jnp.asarray(rng.normal(size=3))
    qd = jnp.array([jnp.cos(q[2]), jnp.sin(q[2]), 0.0]) * 1.5 + jnp.array([0, 0, 0.7])
    u = jnp.array([0.3, -1.1])
    qdd, lam = sys.accelerations(0.0, q, qd, u)
    B = jax.jacfwd(lambda uu: sys.generalized_force(0.0, q, qd, uu))(u)
    u2, lam2 = sys.inverse_dynamics(0.0, q, qd, qdd, B)
    np.testing.assert_allclose(u2, u, atol=1e-12)
    np.testing.assert_allclose(lam2, lam, atol=1e-12)


@pytest.mark.slow
def test_rigid_body_kinetics(rng):
    """Multibody kinetic energy = (1/2) q'^T M q' with M from autodiff; free spin momentum."""
    body = RigidBody.solid_cylinder(2.0, 1.0, 0.2)
    kin = MultibodyKinetics((body,), lambda q: (so3.exp(q[:3])[None], q[3:][None]))
    sys = Lagrangian(6, T=kin.kinetic_energy)
    q = jnp.asarray(rng.normal(size=6))
    qd = jnp.asarray(rng.normal(size=6))
    np.testing.assert_allclose(0.5 * qd @ sys.mass_matrix(q) @ qd, kin.kinetic_energy(q, qd), rtol=1e-13)
    # torque-free motion in exponential coordinates conserves spatial angular momentum
    x0 = jnp.concatenate([jnp.array([0.1, 0.2, 0.3, 0, 0, 0]), jnp.array([1.0, -0.5, 2.0, 0.1, 0, 0])])
    tr = nhjax.simulate(sys, x0, 1.0, rtol=1e-11, atol=1e-11, saveat=11)
    Ls = jax.vmap(lambda x: kin.angular_momentum(x[:6], x[6:]))(tr.xs)
    np.testing.assert_allclose(Ls, np.broadcast_to(Ls[0], Ls.shape), atol=1e-8)
