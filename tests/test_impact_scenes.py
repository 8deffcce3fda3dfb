"""Seed 004's examples 10.1 and 10.3 against their closed forms: the particle in a moving
circle (impact times, the seed's elastic / plastic / restitution jumps, sliding along the
moving wall after a plastic impact) and the rolling sphere hitting a moving smooth wall (the
seed's velocity and momentum-matrix formulas, rolling kept through the jump, sticking to an
oscillating wall and its release)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.integrate.impacts import solve_impacts
from nhjax.mechanics import impact_velocities
from nhjax.scenes import ParticleInMovingCircle, RollingSphereWall

OPTS = dict(saveat=0, max_impacts=64)
SPHERE_OPTS = dict(OPTS, dtmax=0.125)  # one compiled solve for every sphere test


def test_circle_elastic_impacts_are_the_seeds_formula_at_the_exact_times():
    """Expanding wall R = 1 + 0.2 t, elastic: each impact at the root of the quadratic
    |q_i + v_i s| = R(t_i) + c s from the previous one; v1 = v0 - 2 (q q^T / f) v0 + (f'/f) q."""
    c = ParticleInMovingCircle(R0=1.0, c=0.2, restitution=1.0)
    x0 = c.initial_state(0.1, -0.2, 1.5, 0.9)
    tr = nhjax.simulate_impacts(c, x0, 8.0, **OPTS)
    n = int(tr.num_impacts)
    assert n >= 3 and int(tr.status) == 0
    np.testing.assert_allclose(float(tr.impact_times[0]), float(c.first_impact_time(x0)), rtol=1e-14)
    for i in range(n):
        t = tr.impact_times[i]
        q, v0 = tr.x_pre[i, :2], tr.velocities_pre[i]
        np.testing.assert_allclose(tr.velocities_post[i], c.seed_jump(t, q, v0, 1.0), rtol=1e-13, atol=1e-14)
        if i + 1 < n:
            shifted = ParticleInMovingCircle(R0=float(c.radius(t)), c=0.2)
            t_next = float(t) + float(shifted.first_impact_time(tr.x_post[i]))
            np.testing.assert_allclose(float(tr.impact_times[i + 1]), t_next, rtol=1e-13)
    # free flight conserves energy: all energy changes are the wall's impacts
    assert abs(float(tr.energy_error)) < 1e-12


def test_circle_restitution_scales_the_plastic_correction():
    c = ParticleInMovingCircle(R0=1.0, c=-0.1, restitution=0.4)
    x0 = c.initial_state(0.2, 0.1, -0.7, 0.9)
    tr = nhjax.simulate_impacts(c, x0, 2.0, **OPTS)
    t, q, v0 = tr.impact_times[0], tr.x_pre[0, :2], tr.velocities_pre[0]
    np.testing.assert_allclose(float(t), float(c.first_impact_time(x0)), rtol=1e-14)
    np.testing.assert_allclose(tr.velocities_post[0], c.seed_jump(t, q, v0, 0.4), rtol=1e-13)
    # the normal velocity relative to the wall is reversed and scaled by alpha
    np.testing.assert_allclose(tr.normal_velocity_post[0], -0.4 * tr.normal_velocity_pre[0], rtol=1e-13)


def test_circle_plastic_impact_then_sliding_on_the_moving_wall():
    """Plastic (the seed's case (i): the constraint remains): the particle slides along the
    expanding wall, r = R(t), with its angular momentum h conserved, so the polar angle is
    theta* + (h/c)(1/R(t*) - 1/R(t)); the wall pushes (mu > 0) throughout."""
    c = ParticleInMovingCircle(R0=1.0, c=0.2, restitution=0.0)
    x0 = c.initial_state(0.1, -0.2, 1.5, 0.9)
    tr = nhjax.simulate_impacts(c, x0, 3.0, **OPTS)
    assert int(tr.num_impacts) == 1 and bool(tr.persistent[0])
    t_s, q, v0 = tr.impact_times[0], tr.x_pre[0, :2], tr.velocities_pre[0]
    xp = tr.x_post[0]
    np.testing.assert_allclose(xp[2:], c.seed_jump(t_s, q, v0, 0.0), rtol=1e-13)
    h = xp[0] * xp[3] - xp[1] * xp[2]
    th = c.sliding_angle(3.0, t_s, jnp.arctan2(xp[1], xp[0]), h)
    xf = tr.x_final
    np.testing.assert_allclose(float(jnp.hypot(xf[0], xf[1])), float(c.radius(3.0)), rtol=1e-12)
    np.testing.assert_allclose(float(jnp.arctan2(xf[1], xf[0])), float(jnp.arctan2(jnp.sin(th), jnp.cos(th))), atol=1e-9)
    np.testing.assert_allclose(float(xf[0] * xf[3] - xf[1] * xf[2]), float(h), rtol=1e-9)
    assert float(tr.contact_residual) < 1e-12
    assert abs(float(tr.energy_error)) < 1e-9


SPHERE = RollingSphereWall(r=0.1, V=0.05, restitution=0.7)


@eqx.filter_jit
def _sphere_jumps(s, X, t):
    def one(x):
        q, qd = x[:6], x[6:]
        v1, mu, _ = impact_velocities(s, t, q, qd, jnp.array([True]), jnp.array([s.restitution]))
        E, e = s.seed_momentum_matrix(q)
        M = s.mass_matrix(q)
        p0 = M @ qd
        p1 = p0 - (1 + s.restitution) * E @ p0 + (1 + s.restitution) * s.m * s.wall_velocity(t) * e
        return v1, s.seed_jump(t, x), jnp.linalg.solve(M, p1), s.velocity_constraints(t, q, v1), mu

    return jax.vmap(one)(X)


def test_sphere_jump_is_the_seeds_matrix_formula(rng):
    """At random orientations and rolling velocities (any direction, any spin): the engine's
    projector gives the seed's post-impact velocities and its momentum matrix formula
    p1 = p0 - (1+alpha) E p0 + (1+alpha) f' e, and keeps the rolling constraints."""
    s = eqx.tree_at(lambda m: m.m, SPHERE, jnp.asarray(2.5))  # the seed has m = 1
    X = jnp.stack([
        s.initial_state(x=0.3, y=rng.normal(), vx=rng.normal(), vy=rng.normal(), spin=rng.normal(),
                        theta=rng.uniform(0.3, 2.8), phi=rng.normal(), psi=rng.normal())
        for _ in range(6)
    ])
    v1, seed, matrix, rolling, mu = _sphere_jumps(s, X, 0.7)
    np.testing.assert_allclose(v1, seed, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(v1, matrix, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(rolling, 0.0, atol=1e-13)
    # the wall's impulse (generalized, along e1): m (1 + alpha)(f' - x0') (k^2 + r^2)/r^2
    r, k2, al = float(s.r), float(s.k) ** 2, float(s.restitution)
    np.testing.assert_allclose(mu[:, 0], 2.5 * (1 + al) * (0.05 - X[:, 6]) * (k2 + r * r) / r**2, rtol=1e-12)


def test_sphere_rolls_into_the_wall_at_the_exact_time_and_keeps_rolling():
    """Rolling at -1 m/s towards the wall x = 0.05 t: impact at (x0 - r)/(V + 1), rebound
    x' = (1 + alpha) V - alpha x0', y' unchanged, rolling residual at round-off, and the
    uniform rolling afterwards (x exact at t1)."""
    s = SPHERE
    x0 = s.initial_state(x=0.5, vx=-1.0)
    tr = nhjax.simulate_impacts(s, x0, 2.0, **SPHERE_OPTS)
    t_hit = (0.5 - 0.1) / (0.05 + 1.0)
    assert int(tr.num_impacts) == 1
    np.testing.assert_allclose(float(tr.impact_times[0]), t_hit, rtol=1e-14)
    v1 = 1.7 * 0.05 + 0.7 * 1.0
    np.testing.assert_allclose(tr.velocities_post[0], s.seed_jump(t_hit, tr.x_pre[0]), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(float(tr.velocities_post[0, 0]), v1, rtol=1e-14)
    x_hit = 0.1 + 0.05 * t_hit
    np.testing.assert_allclose(float(tr.x_final[0]), x_hit + v1 * (2.0 - t_hit), rtol=1e-12)
    assert float(tr.constraint_residual) < 1e-13
    assert abs(float(tr.energy_error)) < 1e-12


def test_sphere_sticks_to_an_accelerating_wall_and_is_released_where_it_decelerates():
    """Plastic impact on the wall x = 0.05 sin(2 pi t): while the wall accelerates towards
    the sphere (f'' > 0) the contact persists (the sphere rolls along with the wall); it is
    released where f'' changes sign, t = k/2, moving at the wall's speed."""
    s = RollingSphereWall(r=0.1, B=0.05, Omega=2 * np.pi, restitution=0.0)
    x0 = s.initial_state(x=0.3, vx=-0.25)
    tr = nhjax.simulate_impacts(s, x0, 1.5, **SPHERE_OPTS)
    t_imp = float(tr.impact_times[0])
    assert np.sin(2 * np.pi * t_imp) < 0  # impact while the wall accelerates towards +x
    np.testing.assert_allclose(float(tr.rest_times[0]), t_imp, rtol=1e-14)
    t_rel = np.ceil(2 * t_imp) / 2
    np.testing.assert_allclose(float(tr.release_times[0]), t_rel, rtol=1e-9)
    # after the release the sphere rolls on at the wall's speed at t_rel
    f_dot = 0.05 * 2 * np.pi * np.cos(2 * np.pi * t_rel)
    if int(tr.num_impacts) == 1:
        np.testing.assert_allclose(float(tr.x_final[6]), f_dot, rtol=1e-8)
    assert float(tr.constraint_residual) < 1e-12


def test_wall_faster_than_the_sphere_and_persistent_push():
    """The wall x = V t + a t^2/2 chases a sphere rolling away at u < V: it catches up at
    the root t* of x0 - r + u t = V t + a t^2 / 2; the rebound is (1 + alpha) f'(t*) -
    alpha u; plastic: the wall pushes the rolling sphere along (persistent contact,
    acceleration a), and the energy bookkeeping (the wall's work, the impact's loss)
    closes."""
    V, a, u, x0 = 2.0, 0.4, 0.5, 1.0
    t_hit = (-(V - u) + np.sqrt((V - u) ** 2 + 2 * a * (x0 - 0.1))) / a
    s = RollingSphereWall(r=0.1, V=V, a=a)
    for alpha in (1.0, 0.6, 0.0):
        tr = nhjax.simulate_impacts(s, s.initial_state(x=x0, vx=u), 3.0, restitution=alpha, **SPHERE_OPTS)
        np.testing.assert_allclose(float(tr.impact_times[0]), t_hit, rtol=1e-14)
        w = V + a * t_hit
        np.testing.assert_allclose(float(tr.velocities_post[0, 0]), (1 + alpha) * w - alpha * u, rtol=1e-13)
        assert int(tr.num_impacts) == 1
        assert abs(float(tr.energy_error)) < 1e-10
    assert bool(tr.persistent[0])
    np.testing.assert_allclose(np.asarray(tr.x_final)[[0, 6]], [0.1 + V * 3.0 + 0.5 * a * 9.0, V + 3.0 * a], rtol=1e-12)
    assert float(tr.constraint_residual) < 1e-12


@pytest.mark.slow
def test_sphere_gradient_through_the_impact_matches_the_closed_form():
    """x(T) = x* + x1' (T - t*) with t* = (x0 - r - f0)/(V - x0'), x* = r + f0 + V t*,
    x1' = (1 + alpha) V - alpha x0': forward-mode derivative w.r.t. (V, alpha, x0')."""
    T = 2.0

    def xT(p):
        s = eqx.tree_at(lambda m: (m.V, m.restitution), SPHERE, (p[0], p[1]))
        tr = solve_impacts(s, s.initial_state(x=0.5, vx=p[2]), T, max_impacts=8)
        return tr.x_final[0]

    def exact(p):
        V, al, u = p
        ts = (0.5 - 0.1) / (V - u)
        return 0.1 + V * ts + ((1 + al) * V - al * u) * (T - ts)

    p = jnp.array([0.05, 0.7, -1.0])
    np.testing.assert_allclose(jax.jit(jax.jacfwd(xT))(p), jax.grad(exact)(p), rtol=1e-10)
