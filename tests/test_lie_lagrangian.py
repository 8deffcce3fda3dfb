"""Hamel equations on Lie groups by autodiff, against the classical equations
(Euler, Euler-Poisson, Chaplygin's sleigh), plus regularity errors and
projection after every step."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.lie import Euclidean, SE2Body, SO3Body, se2, so3
from nhjax.mechanics import Lagrangian, LieLagrangian


class HeavyTop(LieLagrangian):
    """Rigid body with a fixed point; centre of mass at chi (body frame) [m]."""

    inertia: jax.Array
    m_g_chi: jax.Array

    @property
    def config_spaces(self):
        return (SO3Body(),)

    def lagrangian(self, g, v):
        (R,) = g
        return 0.5 * v @ self.inertia @ v - (R @ self.m_g_chi)[2]


def test_hamel_gives_euler_poisson(rng):
    I = jnp.asarray(np.diag([1.0, 2.0, 3.5]) + 0.1 * np.ones((3, 3)))
    top = HeavyTop(I, jnp.array([0.1, -0.2, 0.7]))
    for _ in range(5):
        R = so3.exp(jnp.asarray(rng.normal(size=3)))
        W = jnp.asarray(rng.normal(size=3))
        (Rdot,), Wdot = top.vector_field(0.0, ((R,), W), None)
        gamma = R.T @ jnp.array([0.0, 0.0, 1.0])
        # gravity torque about the fixed point, in the body: (R chi) x (-m g e3) -> gamma x (m g chi)
        expect = jnp.linalg.solve(I, jnp.cross(I @ W, W) + jnp.cross(gamma, top.m_g_chi))
        np.testing.assert_allclose(Wdot, expect, atol=1e-13)
        np.testing.assert_allclose(Rdot, W, atol=0)  # body velocity of the SO3Body part


def test_heavy_top_on_the_group_conserves_energy_and_vertical_momentum():
    top = HeavyTop(jnp.diag(jnp.array([1.0, 1.0, 0.4])), jnp.array([0.0, 0.0, 0.5]))
    y0 = ((so3.rot_x(0.4),), jnp.array([0.3, -0.1, 8.0]))
    tr = nhjax.simulate(top, y0, 20.0, rtol=1e-11, atol=1e-11, saveat=41)
    R = tr.xs[0][0]
    assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 1e-13
    assert float(tr.invariant_drift["energy"]) < 1e-9
    Lz = jnp.einsum("nij,jk,nk->ni", R, top.inertia, tr.xs[1])[:, 2]
    np.testing.assert_allclose(Lz, Lz[0], atol=1e-9)


class Sleigh(LieLagrangian):
    """Chaplygin's sleigh: body frame at the knife edge, centre of mass at (a, 0)."""

    mass: jax.Array
    inertia: jax.Array
    a: jax.Array

    @property
    def config_spaces(self):
        return (SE2Body(),)

    def lagrangian(self, g, v):
        vx, vy, w = v
        return 0.5 * self.mass * (vx**2 + (vy + w * self.a) ** 2) + 0.5 * self.inertia * w**2

    def velocity_constraints(self, t, g, v):
        return v[1:2]  # no sideways slip of the knife edge


def test_chaplygin_sleigh_matches_classical_equations():
    m, I, a = 2.0, 0.3, 0.4
    sleigh = Sleigh(jnp.asarray(m), jnp.asarray(I), jnp.asarray(a))
    g0 = se2.from_xytheta(0.0, 0.0, 0.3)
    v0 = jnp.array([0.5, 0.0, 1.2])
    (_,), vd = sleigh.vector_field(0.0, ((g0,), v0), None)
    vx, w = v0[0], v0[2]
    np.testing.assert_allclose(vd, [a * w**2, 0.0, -m * a * vx * w / (I + m * a**2)], atol=1e-14)
    tr = nhjax.simulate(sleigh, ((g0,), v0), 30.0, rtol=1e-11, atol=1e-11, saveat=31)
    assert float(tr.invariant_drift["energy"]) < 1e-9
    assert float(tr.constraint_drift["velocity"]) < 1e-12
    # the sleigh ends up moving straight ahead: w -> 0, energy all in vx
    assert abs(float(tr.xs[1][-1, 2])) < 1e-3 and float(tr.xs[1][-1, 0]) > 0


class Redundant(LieLagrangian):
    @property
    def config_spaces(self):
        return (Euclidean(),)

    def lagrangian(self, g, v):
        return 0.5 * v @ v

    def velocity_constraints(self, t, g, v):
        return jnp.stack([v[0] - v[1], 2 * (v[0] - v[1])])


def test_dependent_constraints_raise_regularity_error():
    with pytest.raises(nhjax.RegularityError, match="constraint_rank"):
        nhjax.simulate(Redundant(), ((jnp.zeros(2),), jnp.array([1.0, 1.0])), 1.0)
    degenerate = Lagrangian(2, T=lambda q, qd: 0.5 * qd[0] ** 2)
    with pytest.raises(nhjax.RegularityError, match="kinetic_metric"):
        nhjax.simulate(degenerate, jnp.zeros(4), 1.0)


def test_projection_after_every_step_removes_drift():
    L = 1.3
    pend = Lagrangian(
        2, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: 9.81 * q[1],
        position_constraints=lambda t, q: jnp.array([q @ q - L**2]),
    )
    x0 = jnp.array([L, 0.0, 0.0, 0.0])
    plain = nhjax.simulate(pend, x0, 100.0, rtol=1e-6, atol=1e-6, project_steps=False)
    proj = nhjax.simulate(pend, x0, 100.0, rtol=1e-6, atol=1e-6, project_steps=True)
    assert float(plain.constraint_drift["position"]) > 1e-6
    assert float(proj.constraint_drift["position"]) < 1e-12
    assert float(proj.constraint_drift["position_rate"]) < 1e-12
    np.testing.assert_allclose(proj.xs[:, 0] ** 2 + proj.xs[:, 1] ** 2, L**2, rtol=1e-13)
