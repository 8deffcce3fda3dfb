"""The bouncing ball on a vibrating table (seed 004, ex. 10.2) against its closed forms: exact
parabolic flights (impact times against an independent NumPy root find), the seed's rebound
law, release from resting contact where the table's acceleration passes -g, resting for
Gamma < 1, the high-bounce map as the limit of small amplitude, and forward-mode gradients
through impacts (with the impact-time dependence) against central differences under vmap."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.integrate.impacts import solve_impacts
from nhjax.scenes import BouncingBall

# one static configuration for all solves of this file (one compiled program)
OPTS = dict(saveat=0, max_impacts=2100)


def test_impacts_are_the_roots_of_the_exact_flight():
    """Gamma = 4, alpha = 0.8 (chaotic bouncing): every impact time is the first root of
    the exact parabola from the previous impact minus the table (NumPy bisection,
    independent of JAX), the approach velocity is that parabola's, and the rebound is
    the seed's v1 = (1 + alpha) A omega cos(omega t) - alpha v0."""
    b = BouncingBall(A=0.01, omega=2 * np.pi * 10, restitution=0.8)
    tr = nhjax.simulate_impacts(b, b.initial_state(0.1, 0.0), 30.0, **OPTS)
    n = int(tr.num_impacts)
    assert n > 80 and int(tr.status) == 0
    t = np.asarray(tr.impact_times[:n])
    xp = np.asarray(tr.x_post[:n])
    vpre = np.asarray(tr.velocities_pre[:n, 0])
    vpost = np.asarray(tr.velocities_post[:n, 0])
    t_ref, v_ref = [], []
    for i in range(0, n - 1, 3):  # every third flight (the NumPy search is the slow part)
        ref = b.reference_impacts(t[i], xp[i, 0], xp[i, 1], 1)
        t_ref.append(ref["times"][0] - t[i + 1])
        v_ref.append(ref["v_pre"][0] - vpre[i + 1])
    assert np.max(np.abs(t_ref)) < 1e-12
    assert np.max(np.abs(v_ref)) < 1e-11
    A, w, al = 0.01, 2 * np.pi * 10, 0.8
    np.testing.assert_allclose(vpost, (1 + al) * A * w * np.cos(w * t) - al * vpre, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(xp[:, 0], A * np.sin(w * t), atol=1e-15)
    # the first ten impacts straight from the start agree with the reference run as a whole
    # (the motion is chaotic: the two computations' round-off grows ~10x per few impacts)
    ref = b.reference_impacts(0.0, 0.1, 0.0, 10)
    np.testing.assert_allclose(t[:5], ref["times"][:5], rtol=0, atol=1e-13)
    np.testing.assert_allclose(t[:10], ref["times"], rtol=0, atol=1e-10)
    assert abs(float(tr.energy_error)) < 1e-11


def test_release_from_rest_where_the_table_accelerates_down_faster_than_g():
    """A ball resting on the table (Gamma = 4) leaves it where the contact force
    m (g - A omega^2 sin(omega t)) vanishes: t = arcsin(1/Gamma)/omega; its flight from
    there is the exact parabola (next impact = NumPy root of the exact flight)."""
    b = BouncingBall(A=0.01, omega=2 * np.pi * 10, restitution=0.5)
    x0 = jnp.array([0.0, float(b.table_velocity(0.0))])
    tr = nhjax.simulate_impacts(b, x0, 0.3, **OPTS)
    assert float(tr.rest_times[0]) == 0.0  # starts in resting contact
    t_rel = np.arcsin(1 / float(b.gamma)) / float(b.omega)
    assert int(tr.num_releases) >= 1
    first_release_flight = b.reference_impacts(t_rel, float(b.table(t_rel)), float(b.table_velocity(t_rel)), 1)
    np.testing.assert_allclose(float(tr.impact_times[0]), first_release_flight["times"][0], rtol=1e-10)
    assert abs(float(tr.energy_error)) < 1e-9  # work of the table while in contact included


def test_gamma_below_one_chatters_to_rest_and_rides_the_table():
    """Gamma = 0.5: the table never pulls away (its acceleration stays above -g), so the
    chattering ball comes to rest by the rest rule and then moves with the table."""
    b = BouncingBall(A=0.002, omega=2 * np.pi * 7.87, restitution=0.6)
    assert float(b.gamma) < 1
    tr = nhjax.simulate_impacts(b, b.initial_state(0.02, 0.0), 2.0, **OPTS)
    assert int(tr.status) == 0 and bool(tr.persistent[0]) and int(tr.num_releases) == 0
    t1 = float(tr.t_final)
    np.testing.assert_allclose(tr.x_final, [b.table(t1), b.table_velocity(t1)], atol=1e-10)
    assert float(tr.contact_residual) < 1e-12


def test_period_one_orbit_impacts_are_roots_whatever_the_largest_step_divides():
    """Issue 40: on the contracting period-1 orbit (alpha = 0.5, Gamma = 1.3 between the
    thresholds pi (1 - alpha)/(1 + alpha) and its flip bound) the flight takes one table
    period tau, a multiple of the default largest step tau / 4: steps end within
    round-off of the impacts. Each of 60 impacts is the exact orbit's t* + k tau to
    1e-13 s, with the ball on the table to round-off (not inside it), for a largest step
    that divides the flight, one that does not, and one whose event samples (4 per
    step) fall on the impacts (tau / 5.5: 22 samples per flight)."""
    g, w, al, gam = 9.81, 2 * np.pi * 10, 0.5, 1.3
    tau, A = 2 * np.pi / w, gam * 9.81 / w**2
    b = BouncingBall(g=g, A=A, omega=w, restitution=al)
    # departure velocity g tau / 2 (a flight of one period), approach -g tau / 2: the rebound
    # law gives cos(w t*) = g tau (1 - alpha) / (2 (1 + alpha) A w); the stable branch
    t_star = np.arccos(g * tau * (1 - al) / (2 * (1 + al) * A * w)) / w
    x0 = jnp.array([A * np.sin(w * t_star), g * tau / 2])
    for dtmax in (float(b.event_resolution), tau / 4.37, tau / 5.5):
        assert dtmax != float(b.event_resolution) or np.isclose(tau / dtmax, 4)
        tr = nhjax.simulate_impacts(b, x0, t_star + 60.5 * tau, t0=t_star, dtmax=dtmax, **OPTS)
        assert int(tr.num_impacts) == 60
        t = np.asarray(tr.impact_times[:60])
        assert np.max(np.abs(t - (t_star + tau * np.arange(1, 61)))) <= 1e-13
        gap = np.asarray(tr.x_pre[:60, 0]) - A * np.sin(w * t)
        assert np.max(np.abs(gap)) < 1e-15
        np.testing.assert_allclose(np.asarray(tr.velocities_post[:60, 0]), g * tau / 2, rtol=1e-12)


def test_every_rest_and_release_is_recorded():
    """Gamma = 1.3: the ball chatters to rest once per table period and is released where
    the table's acceleration passes -g, at sin(w t) = 1/Gamma (rising): every rest and
    release is a row of the event record, in order, alternating, each release at its
    closed-form time with the table's state."""
    w = 2 * np.pi
    b = BouncingBall(g=9.81, A=1.3 * 9.81 / w**2, omega=w, restitution=0.5)
    tr = nhjax.simulate_impacts(b, b.initial_state(0.02, 0.0), 4.5, rest_velocity=1e-4, **OPTS)
    m = int(tr.num_events)
    t = np.asarray(tr.event_times[:m])
    rest, rel = np.asarray(tr.event_rest[:m, 0]), np.asarray(tr.event_release[:m, 0])
    assert np.all(rest ^ rel) and np.all(rest[0::2]) and np.all(rel[1::2])  # rest, release, rest, ...
    assert int(rel.sum()) == int(tr.num_releases) >= 3 and np.all(np.diff(t) > 0)
    assert np.isnan(np.asarray(tr.event_times[m:])).all()
    t_rel = t[rel]
    k = np.round(t_rel - np.arcsin(1 / 1.3) / w)
    np.testing.assert_allclose(t_rel, (np.arcsin(1 / 1.3) + 2 * np.pi * k) / w, rtol=0, atol=1e-9)
    x = np.asarray(tr.event_states[:m])
    np.testing.assert_allclose(x[:, 0], np.asarray(b.table(t)), atol=1e-12)  # on the table at every event
    np.testing.assert_allclose(x[:, 1], np.asarray(b.table_velocity(t)), atol=1e-9)  # moving with it
    # the last of each kind is what rest_times / release_times report
    assert float(tr.rest_times[0]) == t[rest][-1] and float(tr.release_times[0]) == t_rel[-1]


def test_high_bounce_map_is_the_small_amplitude_limit():
    """The seed's map f(t, v) neglects the table's displacement: its orbit differs from
    the exact impacts by O(A). Tenfold smaller A, about tenfold smaller difference."""
    diffs = []
    for A in (1e-4, 1e-5):
        b = BouncingBall(A=A, omega=2 * np.pi * 5, restitution=1.0)
        tr = nhjax.simulate_impacts(b, b.initial_state(0.0, 3.0), 6.0, **OPTS)
        n = int(tr.num_impacts)
        assert n >= 8
        ts, vs = b.high_bounce_orbit(tr.impact_times[0], tr.velocities_post[0, 0], n - 1)
        diffs.append(max(np.max(np.abs(np.asarray(ts) - np.asarray(tr.impact_times[1:n]))),
                         np.max(np.abs(np.asarray(vs) - np.asarray(tr.velocities_post[1:n, 0])))))
    assert diffs[0] < 1e-3
    assert 4 < diffs[0] / diffs[1] < 20


BALL = BouncingBall(A=0.01, omega=2 * np.pi * 10, restitution=0.8)
T_GRAD = 0.9


def _outputs(p):
    """State at T_GRAD and the first three impacts, as functions of (A, omega, alpha, x0, v0)."""
    b = eqx.tree_at(lambda s: (s.A, s.omega, s.restitution), BALL, (p[0], p[1], p[2]))
    tr = solve_impacts(b, jnp.stack([p[3], p[4]]), T_GRAD, max_impacts=16, dtmax=0.0125)
    return jnp.concatenate([tr.x_final, tr.impact_times[:3], tr.velocities_post[:3, 0],
                            jnp.asarray(tr.num_impacts, float)[None]])


def test_amplitude_derivative_through_impacts_matches_central_differences():
    """d/dA of the state at 0.9 s and of the first three impact times by jax.jvp through
    simulate_impacts (forward mode; the impact times' dependence included), against
    central differences of the same solve (exact parabolic flights: the differences
    measure the true derivative), and dt_1/dA against its closed form -dpsi/dA / Psi."""
    x0 = jnp.array([0.1, 0.0])

    def out(A):
        b = eqx.tree_at(lambda s: s.A, BALL, A)
        tr = nhjax.simulate_impacts(b, x0, T_GRAD, **OPTS)
        return jnp.concatenate([tr.x_final, tr.impact_times[:3]]), tr.num_impacts

    A = jnp.asarray(0.01)
    (val, n), (tan, _) = jax.jvp(out, (A,), (jnp.ones(()),))
    h = 1e-8
    (vp, n_p), (vm, n_m) = out(A + h), out(A - h)
    assert int(n) == int(n_p) == int(n_m) >= 3
    fd = (np.asarray(vp) - np.asarray(vm)) / (2 * h)
    np.testing.assert_allclose(np.asarray(tan), fd, rtol=2e-6, atol=1e-6)
    t1 = float(val[2])
    _, v1 = BALL.flight(t1, 0.0, 0.1, 0.0)
    Psi = float(v1 - BALL.table_velocity(t1))
    np.testing.assert_allclose(float(tan[2]), np.sin(float(BALL.omega) * t1) / Psi, rtol=1e-9)


@pytest.mark.slow
def test_gradients_through_impacts_match_central_differences_under_vmap():
    """Jacobian of (x(T), x'(T), t_1..t_3, v1_1..v1_3) w.r.t. amplitude, frequency,
    restitution and initial data, by jax.jacfwd through the impacts (the impact times'
    dependence included), for three members at once (jax.vmap; members with different
    impact histories) against central differences of the same solves. The flights are
    exact parabolas, so differences measure the true derivative."""
    P = jnp.array([
        [0.010, 2 * np.pi * 10, 0.8, 0.10, 0.0],
        [0.012, 2 * np.pi * 9, 0.6, 0.05, 0.5],
        [0.008, 2 * np.pi * 11, 0.9, 0.15, -0.3],
    ])
    J = jax.jit(jax.vmap(jax.jacfwd(_outputs)))(P)  # (3, 10, 5)
    f = jax.jit(jax.vmap(_outputs))
    counts = np.asarray(f(P)[:, -1])
    assert np.all(counts >= 3) and len(set(counts.tolist())) > 1
    h = 1e-6 * np.maximum(np.abs(np.asarray(P)), 1e-2)
    E = np.eye(5)
    plus = np.stack([np.asarray(P) + h[:, i : i + 1] * E[i] for i in range(5)], 1).reshape(-1, 5)
    minus = np.stack([np.asarray(P) - h[:, i : i + 1] * E[i] for i in range(5)], 1).reshape(-1, 5)
    Fp, Fm = f(jnp.asarray(plus)), f(jnp.asarray(minus))
    assert np.all(np.asarray(Fp[:, -1]) == np.repeat(counts, 5))  # no impact gained or lost
    fd = ((np.asarray(Fp) - np.asarray(Fm)).reshape(3, 5, -1) / (2 * h[:, :, None])).transpose(0, 2, 1)
    Jn = np.asarray(J)[:, :-1]
    fd = fd[:, :-1]
    scale = np.maximum(np.abs(fd), 1.0)
    assert np.max(np.abs(Jn - fd) / scale) < 1e-5
    # the first impact time's derivative w.r.t. A has the closed form -dpsi/dA / Psi
    b0 = BALL
    t1 = float(f(P)[0, 2])
    x1, v1 = b0.flight(t1, 0.0, 0.10, 0.0)
    Psi = float(v1 - b0.table_velocity(t1))
    np.testing.assert_allclose(float(J[0, 2, 0]), -(-np.sin(float(b0.omega) * t1)) / Psi, rtol=1e-9)
