"""The impact engine (nhjax.mechanics.impacts, nhjax.simulate_impacts) on cases with exact answers:
the affine projector's algebra, a user's Lagrangian with a one-sided constraint, and the
hard cases of issue 17 (thousands of elastic impacts, chattering, restitution 0 and 1,
grazing, simultaneous impacts, several walls crossed within one step, bad input)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.errors import ConstraintViolationError, IntegrationError
from nhjax.mechanics import Lagrangian, WithContacts, affine_projector, impact_velocities
from nhjax.mechanics.impacts import contact_kinematics

G = 9.81


def _floor(t, q):
    return q[0]


# one user Lagrangian (unit mass under gravity) with the floor x >= 0, shared by the tests
# so that they share one compiled solve (restitution is an array: changing it does not
# recompile; nor do the tolerances)
BALL_L = Lagrangian(1, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: G * q[0])
BALL = WithContacts(BALL_L, _floor, restitution=1.0)
BALL_OPTS = dict(max_impacts=2100, saveat=0)


def falling_ball(restitution):
    return eqx.tree_at(lambda s: s.restitution, BALL, jnp.asarray(restitution, float))


def skate_in_corridor(restitution):
    """A knife-edge skate (nonholonomic) between two moving walls: permanent constraint
    plus two one-sided ones, for the projector's algebra."""
    skate = Lagrangian(
        3,
        T=lambda q, qd: 0.5 * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * 0.3 * qd[2] ** 2,
        velocity_constraints=lambda t, q, qd: jnp.stack([jnp.sin(q[2]) * qd[0] - jnp.cos(q[2]) * qd[1]]),
    )
    return WithContacts(skate, lambda t, q: jnp.stack([q[1] + 1.0 + 0.2 * t, 1.0 - q[1] + q[0] ** 2 + 0.3 * jnp.sin(q[2] + t)]),
                        restitution=restitution)


@eqx.filter_jit
def _projector_checks(s, t, q, v):
    P, c = affine_projector(s, t, q)
    M = s.mass_matrix(q)
    v1 = jnp.linalg.solve(M, P @ (M @ v) + c)
    _, J, Psi1 = contact_kinematics(s, t, q, v1)
    # independent: KKT of the impulsive jump  M dv = A^T l + J^T mu, A v1 = 0, Psi(v1) = 0
    A = s.constraint_jacobian(t, q)
    j = contact_kinematics(s, t, q, jnp.zeros(3))[2]
    K = jnp.block([[M, -A.T, -J.T], [A, jnp.zeros((1, 3))], [J, jnp.zeros((2, 3))]])
    v_kkt = jnp.linalg.solve(K, jnp.concatenate([M @ v, jnp.zeros(1), -j]))[:3]
    _, _, Psi0 = contact_kinematics(s, t, q, v)
    out = []
    for alpha in (0.0, 0.35, 1.0):
        va, mu, used = impact_velocities(s, t, q, v, jnp.array([True, True]), jnp.full(2, alpha))
        out.append((contact_kinematics(s, t, q, va)[2], s.velocity_constraints(t, q, va), used))
    return P, v1, Psi1, s.velocity_constraints(t, q, v1), v_kkt, Psi0, out


def test_affine_projector_is_the_seed_formula_17():
    """(17): p1 = p0 - C'^{ab} beta_a (beta_b M^-1 p0 + betabar_b) with a permanent
    (nonholonomic) constraint and two moving walls: the linear part is a projector; the
    plastic jump meets the impulsive and the permanent constraints and equals the KKT
    solution of the impulsive equations; restitution alpha gives Psi(v1) = -alpha Psi(v0)
    with the permanent constraint kept."""
    s = skate_in_corridor(0.0)
    q = jnp.array([0.3, -0.2, 0.8])
    v = jnp.array([np.cos(0.8), np.sin(0.8), 0.5]) * 1.3  # on the skate's constraint
    P, v1, Psi1, perm1, v_kkt, Psi0, out = _projector_checks(s, 0.37, q, v)
    np.testing.assert_allclose(P @ P, P, atol=1e-14)
    np.testing.assert_allclose(Psi1, 0.0, atol=1e-14)
    np.testing.assert_allclose(perm1, 0.0, atol=1e-14)
    np.testing.assert_allclose(v1, v_kkt, atol=1e-13)
    for alpha, (Psia, perma, used) in zip((0.0, 0.35, 1.0), out):
        used = np.asarray(used)
        assert used.any()
        # contacts in the impact obey Newton's law; one that would have pulled was dropped
        # and separates (complementarity)
        np.testing.assert_allclose(np.asarray(Psia)[used], -alpha * np.asarray(Psi0)[used], atol=1e-13)
        assert np.all(np.asarray(Psia)[~used] >= 0)
        np.testing.assert_allclose(perma, 0.0, atol=1e-14)


SKATE_WALL = WithContacts(
    Lagrangian(
        3,
        T=lambda q, qd: 0.5 * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * 0.3 * qd[2] ** 2 + 0.1 * qd[0] * qd[2],
        velocity_constraints=lambda t, q, qd: jnp.stack([jnp.sin(q[2]) * qd[0] - jnp.cos(q[2]) * qd[1]]),
    ),
    lambda t, q: jnp.stack([1.0 - q[0] - 0.3 * q[1] ** 2]),
    restitution=1.0,
)


@eqx.filter_jit
def _reflections(s, q, v):
    def one(q, v):
        v1, _, _ = impact_velocities(s, 0.0, q, v, jnp.array([True]), jnp.array([1.0]))
        v0p, _, _ = impact_velocities(s, 0.0, q, v, jnp.array([True]), jnp.array([0.0]))
        return s.kinetic_energy(q, v), s.kinetic_energy(q, v1), s.kinetic_energy(q, v0p)

    return jax.vmap(one)(q, v)


def test_elastic_jump_on_fixed_walls_keeps_kinetic_energy(rng):
    """A fixed wall (psi_t = 0) and scleronomic rolling: the elastic jump is the
    M-orthogonal reflection, so T is unchanged to round-off; plastic loses energy."""
    q = jnp.asarray(rng.normal(size=(8, 3)))
    sp, w = rng.normal(size=8), rng.normal(size=8)
    v = jnp.stack([sp * np.cos(q[:, 2]), sp * np.sin(q[:, 2]), w], axis=1)
    T0, T1, Tp = _reflections(SKATE_WALL, q, v)
    np.testing.assert_allclose(T1, T0, rtol=1e-13)
    assert np.all(np.asarray(Tp) <= np.asarray(T0) + 1e-14)


def test_thousands_of_elastic_impacts_exact_times_and_energy():
    """2000 elastic bounces on a fixed floor from height 1: impact n at T (2n - 1) with
    T = sqrt(2/g) (the flight is a parabola, integrated exactly), the energy bookkeeping
    error and the energy jumps at round-off level."""
    s = falling_ball(1.0)
    T = np.sqrt(2 / G)
    tr = nhjax.simulate_impacts(s, jnp.array([1.0, 0.0]), 2000 * 2 * T, **BALL_OPTS)
    n = int(tr.num_impacts)
    assert n == 2000 or n == 2001  # the last one lands on t1 to round-off
    times = np.asarray(tr.impact_times[:2000])
    exact = T * (2 * np.arange(1, 2001) - 1)
    # each root is exact to a few ulp of the absolute time (ulp(1800 s) = 2.3e-13 s): the
    # error grows by round-off only, ~1e-12 s per flight
    assert np.max(np.abs(times - exact)) < 5e-9
    assert np.max(np.abs(times[:10] - exact[:10])) < 1e-13
    assert abs(float(tr.energy_error)) < 1e-10 * G
    assert abs(float(tr.energy_jumps)) < 1e-10 * G
    np.testing.assert_allclose(tr.normal_velocity_post[:2000, 0], -tr.normal_velocity_pre[:2000, 0], rtol=1e-12)
    assert int(tr.status) == 0


def test_chattering_ends_in_resting_contact_near_the_zeno_time():
    """alpha = 1/2 on a fixed floor: infinitely many impacts before t_inf = T (1 + 2 alpha
    / (1 - alpha)); the rest rule stops the sequence after finitely many, at a time within
    2 rest_velocity / (g (1 - alpha)) of t_inf, and the ball then rests (x = 0, x' = 0)."""
    alpha, v_rest = 0.5, 1e-6
    s = falling_ball(alpha)
    T = np.sqrt(2 / G)
    t_inf = T * (1 + 2 * alpha / (1 - alpha))
    tr = nhjax.simulate_impacts(s, jnp.array([1.0, 0.0]), 3.0, rest_velocity=v_rest, **BALL_OPTS)
    assert int(tr.status) == 0 and bool(tr.persistent[0])
    t_rest = float(tr.rest_times[0])
    assert t_inf - 2 * v_rest / (G * (1 - alpha)) - 1e-12 <= t_rest <= t_inf + 1e-12
    n = int(tr.num_impacts)
    # the impact velocities halve each time: v_n = alpha^(n-1) sqrt(2 g)
    np.testing.assert_allclose(-tr.normal_velocity_pre[: n - 1, 0], np.sqrt(2 * G) * alpha ** np.arange(n - 1), rtol=1e-9)
    np.testing.assert_allclose(tr.x_final, 0.0, atol=1e-12)
    # resting: the floor carries the weight, energy bookkeeping intact
    assert abs(float(tr.energy_error)) < 1e-9
    assert float(tr.contact_residual) < 1e-12


def test_zeno_without_rest_rule_is_a_clear_error_or_a_stop():
    """rest_velocity = 0: the Zeno sequence cannot end by resting. It never hangs: the
    impacts accumulate below round-off and the solve reports a stall (a clear error naming
    the Zeno point), or, with slow decay (alpha = 0.99), max_impacts stops it first: an
    error, or the motion up to there with on_max_impacts="stop"."""
    T = np.sqrt(2 / G)
    with pytest.raises(IntegrationError, match="Zeno") as err:
        nhjax.simulate_impacts(falling_ball(0.5), jnp.array([1.0, 0.0]), 3.0, rest_velocity=0.0, **BALL_OPTS)
    np.testing.assert_allclose(err.value.t, 3 * T, rtol=1e-9)  # stuck at the Zeno time
    N = BALL_OPTS["max_impacts"]
    s = falling_ball(0.99)
    with pytest.raises(IntegrationError, match="max_impacts"):
        nhjax.simulate_impacts(s, jnp.array([1.0, 0.0]), 100.0, rest_velocity=0.0, **BALL_OPTS)
    tr = nhjax.simulate_impacts(s, jnp.array([1.0, 0.0]), 100.0, rest_velocity=0.0,
                                on_max_impacts="stop", **BALL_OPTS)
    assert int(tr.status) == 1 and int(tr.num_impacts) == N
    assert float(tr.t_final) == float(tr.impact_times[N - 1])
    # impact n at T (1 + 2 (alpha + ... + alpha^(n-1)))
    n = np.arange(N)
    exact = T * (1 + 2 * 0.99 * (1 - 0.99**n) / 0.01)
    np.testing.assert_allclose(np.asarray(tr.impact_times), exact, rtol=1e-10)


def test_plastic_impact_rests_at_once_elastic_rebounds():
    T = np.sqrt(2 / G)
    tr0 = nhjax.simulate_impacts(falling_ball(0.0), jnp.array([1.0, 0.0]), 2.0, **BALL_OPTS)
    assert int(tr0.num_impacts) == 1 and bool(tr0.persistent[0])
    np.testing.assert_allclose(float(tr0.impact_times[0]), T, rtol=1e-13)
    np.testing.assert_allclose(float(tr0.energy_jumps), -G, rtol=1e-12)
    np.testing.assert_allclose(tr0.x_final, 0.0, atol=1e-13)
    tr1 = nhjax.simulate_impacts(falling_ball(1.0), jnp.array([1.0, 0.0]), 2.0, **BALL_OPTS)
    np.testing.assert_allclose(float(tr1.normal_velocity_post[0, 0]), np.sqrt(2 * G), rtol=1e-13)
    s = 2.0 - 3 * T  # rising since the impact at 3T
    x_exact = np.sqrt(2 * G) * s - 0.5 * G * s**2
    np.testing.assert_allclose(float(tr1.x_final[0]), x_exact, rtol=1e-12)


class Ceiling(eqx.Module):
    """psi = h - y: an equinox Module, so h is an array (no recompile when it changes)."""

    h: jax.Array

    def __call__(self, t, q):
        return jnp.stack([self.h - q[1]])


PROJECTILE = Lagrangian(2, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: G * q[1])


def projectile(ceiling):
    """A unit mass thrown up under gravity below a fixed ceiling y <= ceiling."""
    return WithContacts(PROJECTILE, Ceiling(jnp.asarray(ceiling, float)), restitution=1.0)


def test_grazing_apex_exactly_at_the_ceiling_gives_no_impulse():
    """Apex exactly on the ceiling (zero normal velocity there): no impact is recorded
    (or one of zero impulse), the motion is the free parabola; 1e-7 higher it is an impact
    with the tiny normal velocity sqrt(2 g 1e-7)."""
    v = 3.0
    h = v * v / (2 * G)
    x0 = jnp.array([0.0, 0.0, 1.0, v])
    tr = nhjax.simulate_impacts(projectile(h), x0, 1.0, saveat=0)
    exact = np.array([1.0, v * 1.0 - 0.5 * G, 1.0, v - G])
    np.testing.assert_allclose(tr.x_final, exact, atol=1e-12)
    if int(tr.num_impacts):
        assert float(jnp.nanmax(jnp.abs(tr.impulses))) < 1e-6
    tr = nhjax.simulate_impacts(projectile(h - 1e-7), x0, 1.0, saveat=0)
    assert int(tr.num_impacts) == 1
    np.testing.assert_allclose(-float(tr.normal_velocity_pre[0, 0]), np.sqrt(2 * G * 1e-7), rtol=1e-6)
    t_hit = (v - np.sqrt(2 * G * 1e-7)) / G
    np.testing.assert_allclose(float(tr.impact_times[0]), t_hit, rtol=1e-10)


def _walls(t, q):
    return jnp.stack([q[0], 1.0 - q[0], q[1], 1.0 - q[1]])


# a free particle in the unit square: four one-sided constraints
BOX = WithContacts(Lagrangian(2, T=lambda q, qd: 0.5 * qd @ qd), _walls, restitution=1.0)
BOX_OPTS = dict(max_impacts=100, saveat=0)


def test_corner_hit_is_one_simultaneous_impact_with_both_walls():
    x0 = jnp.array([0.5, 0.5, 1.0, 1.0])
    tr = nhjax.simulate_impacts(BOX, x0, 0.75, dtmax=3.0, **BOX_OPTS)
    assert int(tr.num_impacts) == 1
    np.testing.assert_array_equal(np.asarray(tr.impact_contacts[0]), [False, True, False, True])
    np.testing.assert_allclose(float(tr.impact_times[0]), 0.5, rtol=1e-14)
    np.testing.assert_allclose(tr.velocities_post[0], [-1.0, -1.0], rtol=1e-14)
    np.testing.assert_allclose(tr.x_final, [0.75, 0.75, -1.0, -1.0], atol=1e-14)


def test_several_walls_crossed_within_one_step_are_found_in_order():
    """Free flight is linear, so the solver's steps grow without bound; with dtmax = 3
    one step spans several wall hits. The impact times are those of the unfolded straight
    line: x hits at (k - x0)/vx, y hits at (k - y0)/vy, merged in order."""
    x0 = jnp.array([0.3, 0.6, 1.7, 1.1])
    t1 = 12.0
    tr = nhjax.simulate_impacts(BOX, x0, t1, dtmax=3.0, **BOX_OPTS)
    n = int(tr.num_impacts)
    tx = (np.arange(1, 40) - 0.3) / 1.7
    ty = (np.arange(1, 40) - 0.6) / 1.1
    exact = np.sort(np.concatenate([tx, ty]))
    exact = exact[exact < t1]
    assert n == exact.size
    np.testing.assert_allclose(np.asarray(tr.impact_times[:n]), exact, rtol=1e-12, atol=1e-12)
    assert float(jnp.min(tr.min_gap)) > -1e-12


def test_bad_input_is_named():
    s = falling_ball(0.5)
    with pytest.raises(ConstraintViolationError, match="unilateral"):
        nhjax.simulate_impacts(s, jnp.array([-0.1, 0.0]), 1.0)
    with pytest.raises(ValueError, match="restitution"):
        nhjax.simulate_impacts(s, jnp.array([1.0, 0.0]), 1.0, restitution=1.5)
    with pytest.raises(ValueError, match="x0 has shape"):
        nhjax.simulate_impacts(s, jnp.array([1.0, 0.0, 0.0]), 1.0)
    with pytest.raises(ValueError, match="on_max_impacts"):
        nhjax.simulate_impacts(s, jnp.array([1.0, 0.0]), 1.0, on_max_impacts="ignore")
    with pytest.raises(nhjax.SystemKindError, match="unilateral_constraints"):
        nhjax.simulate_impacts(Lagrangian(1, T=lambda q, qd: 0.5 * qd @ qd), jnp.array([1.0, 0.0]), 1.0)
    cat = nhjax.scenes.FallingCat()  # not a ConstrainedLagrangian: no contact multipliers to form
    for run in (lambda: nhjax.simulate_impacts(cat, cat.initial_state(0.8), 1.0),
                lambda: nhjax.simulate_impacts_batch(cat, jnp.stack([cat.initial_state(0.8)] * 2), 1.0)):
        with pytest.raises(nhjax.SystemKindError, match="needs a ConstrainedLagrangian .* got FallingCat"):
            run()
    with pytest.raises(ValueError, match="t1"):
        nhjax.simulate_impacts(s, jnp.array([1.0, 0.0]), 0.0)


def test_unilateral_keyword_adds_a_wall_to_a_plain_lagrangian():
    tr = nhjax.simulate_impacts(BALL_L, jnp.array([1.0, 0.0]), 1.0, unilateral=_floor, restitution=1.0,
                                **BALL_OPTS)
    np.testing.assert_allclose(float(tr.impact_times[0]), np.sqrt(2 / G), rtol=1e-13)
