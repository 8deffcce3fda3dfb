"""The spherical robot on SO(3) x SO(3) x R^2 (Hamel equations by autodiff):
exact motions, torque-free integrals, and the work of the internal torque."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.lie import so3
from nhjax.scenes.spherical_robot import ShellWithTop


def random_inertia(rng):
    """A body's inertia in random axes: principal moments in [0.01, 0.02] kg m^2 (each at
    most the sum of the other two, as every rigid body's)."""
    Q = np.asarray(so3.exp(jnp.asarray(rng.normal(size=3))))
    return Q @ np.diag(rng.uniform(0.01, 0.02, 3)) @ Q.T


def test_centred_top_decouples(rng):
    """c = 0: the top spins by Euler's equations, the shell rolls uniformly."""
    It = random_inertia(rng)
    rob = ShellWithTop(It=It, c=(0.0, 0.0, 0.0))
    y0 = rob.initial_state(shell_omega=(0.4, -0.7, 0.2), top_omega=(1.0, 2.0, -0.5))
    tr = nhjax.simulate(rob, y0, 3.0, rtol=1e-11, atol=1e-11, saveat=7)
    (xy, Rsh, Rt), v = tr.xs
    W_space = jnp.einsum("nij,nj->ni", Rsh, v[:, 2:5])
    np.testing.assert_allclose(W_space, np.broadcast_to([0.4, -0.7, 0.2], W_space.shape), atol=1e-9)
    V0 = np.cross([0.4, -0.7, 0.2], [0, 0, 0.2])[:2]
    np.testing.assert_allclose(xy, tr.ts[:, None] * V0, atol=1e-9)
    # the top is a free rigid body (Euler): its spatial angular momentum and energy are fixed
    w, Itj = v[:, 5:8], jnp.asarray(It)
    Lt = jnp.einsum("nij,jk,nk->ni", Rt, Itj, w)
    np.testing.assert_allclose(Lt, np.broadcast_to(Lt[0], Lt.shape), atol=1e-9)
    Et = 0.5 * jnp.einsum("ni,ij,nj->n", w, Itj, w)
    np.testing.assert_allclose(Et, Et[0], rtol=1e-10)
    assert float(jnp.max(jnp.abs(w - w[0]))) > 0.1  # ... while its body angular velocity moves


@pytest.fixture(scope="module")
def free_run():
    rng = np.random.default_rng(7)
    rob = ShellWithTop(It=random_inertia(rng), c=tuple(rng.normal(size=3) * 0.05))
    y0 = rob.initial_state(shell_omega=(0.5, -1.0, 0.3), top_omega=(1.0, 0.2, -0.4),
                           top_attitude=so3.exp(jnp.array([0.3, 0.1, 0.0])))
    return rob, nhjax.simulate(rob, y0, 10.0, rtol=1e-12, atol=1e-12, saveat=51)


def test_torque_free_integrals(free_run):
    rob, tr = free_run
    # energy scale: kinetic plus |potential| (the potential's zero is arbitrary)
    (g0, v0) = jax.tree_util.tree_map(lambda a: a[0], tr.xs)
    scale = abs(float(rob.momentum(g0, v0) @ v0)) / 2 + abs(float(rob.mt * rob.g * jnp.linalg.norm(rob.c)))
    assert float(tr.invariant_drift["energy"]) < 1e-10 * scale
    K = np.stack([np.asarray(tr.invariants[k]) for k in ("K_x", "K_y", "K_z")], -1)
    assert np.abs(K - K[0]).max() < 1e-10 * np.linalg.norm(K[0])
    assert float(tr.invariant_drift["shell_spin_z"]) < 1e-10
    assert float(tr.constraint_drift["velocity"]) < 1e-10
    (_, Rsh, Rt), _ = tr.xs
    for R in (Rsh, Rt):
        assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 1e-13
    # it really moves: the contact point travels and the top tumbles
    assert float(jnp.linalg.norm(tr.xs[0][0][-1] - tr.xs[0][0][0])) > 0.5


def test_internal_torque_work_and_momentum_balance(free_run):
    rob, _ = free_run
    y0 = rob.initial_state()
    tau = nhjax.Sinusoids([0.0, 0.0, 0.0], [0.3, 0.1, 0.05], [2.0, 3.0, 1.0])
    tr = nhjax.simulate(rob, y0, 4.0, control=tau, rtol=1e-11, atol=1e-11, saveat=801)
    assert float(tr.invariant_drift["energy - work"]) < 1e-9
    # starting from rest, the torque sets the robot rolling
    assert float(jnp.linalg.norm(tr.xs[0][0][-1])) > 1e-3
    # Chaplygin's vector changes exactly by the torque on the shell: dK/dt = -Rt tau
    K = jax.vmap(lambda g0, g1, g2, v: rob.chaplygin_vector(((g0, g1, g2), v)))(*tr.xs[0], tr.xs[1])
    torque = np.asarray(jnp.einsum("nij,nj->ni", tr.xs[0][2], tr.us))
    dt = float(tr.ts[1] - tr.ts[0])  # equally spaced: Simpson's rule at every other saved time
    impulse = np.concatenate([np.zeros((1, 3)), np.cumsum(dt / 3 * (torque[:-2:2] + 4 * torque[1:-1:2]
                                                                     + torque[2::2]), 0)])
    assert np.abs(impulse).max() > 0.05
    np.testing.assert_allclose(np.asarray(K)[::2] - np.asarray(K[0]), -impulse, atol=1e-7)


def test_bad_parameters():
    with pytest.raises(ValueError, match="It must be symmetric positive definite"):
        ShellWithTop(It=np.diag([1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="ms must be positive"):
        ShellWithTop(ms=0.0)


def test_agrees_with_reduced_hand_equations(rng):
    """Hamel equations on SO(3) x SO(3) x R^2 (autodiff) against the hand-derived reduced
    system (1.11) with its torque terms (ShellWithTopReduced), on random states."""
    from nhjax.scenes.shell_with_top import ShellWithTopReduced

    It, c = random_inertia(rng), rng.normal(size=3) * 0.05
    rob = ShellWithTop(ms=1.3, Rs=0.25, mt=0.7, It=It, c=c)
    red = ShellWithTopReduced(ms=1.3, Rs=0.25, mt=0.7, It=It, c=c)
    E3 = jnp.array([0.0, 0.0, 1.0])
    # one compiled program each (op by op, these large fields dispatch for seconds)
    red_field = jax.jit(lambda x, tau: red.forced_vector_field(0.0, x, tau))
    rob_field = jax.jit(lambda y, tau: rob.vector_field(0.0, y, tau))
    for _ in range(4):
        y = rob.initial_state(
            xy=rng.normal(size=2), shell_attitude=so3.exp(jnp.asarray(rng.normal(size=3))),
            top_attitude=so3.exp(jnp.asarray(rng.normal(size=3))),
            shell_omega=rng.normal(size=3), top_omega=rng.normal(size=3),
        )
        tau = jnp.asarray(rng.normal(size=3) * 0.1)
        (xy, Rsh, Rt), v = y
        Om_top = Rt.T @ Rsh @ v[2:5]
        x = jnp.concatenate([v[5:8], Om_top, Rt.T @ E3, Rt.T @ jnp.array([1.0, 0, 0]), Rt.T @ jnp.array([0, 1.0, 0]), xy])
        dx = red_field(x, tau)
        _, vd = rob_field(y, tau)
        np.testing.assert_allclose(vd[5:8], dx[0:3], rtol=1e-10, atol=1e-10)
        dOm = -jnp.cross(v[5:8], Om_top) + Rt.T @ Rsh @ vd[2:5]
        np.testing.assert_allclose(dOm, dx[3:6], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(v[:2], dx[15:17], atol=1e-12)  # contact point velocity
