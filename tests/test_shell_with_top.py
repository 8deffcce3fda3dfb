"""Shell with a top on a spherical hinge (seed 003, sec. 1): the reduced equations
against the engine (two rigid bodies in space, with and without an internal
torque) and against Theorem 1's smooth-plane ball; conservation of E, gamma^2,
the area integral, Chaplygin's K and Omega_z at tight tolerance; the Euler and
Lagrange integrals; parameter checks; and a long run (slow)."""

import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.lie import so3
from nhjax.mechanics import Lagrangian
from nhjax.scenes.shell_with_top import ShellWithTopLagrangian, ShellWithTopReduced

TIGHT = dict(solver=diffrax.Tsit5(), rtol=1e-12, atol=1e-12, saveat=101, max_steps=200_000)


def random_rotation(rng):
    return np.asarray(so3.exp(jnp.asarray(rng.normal(size=3))))


def random_inertia(rng, scale=1e-3):
    """A physical inertia tensor (principal moments in [1, 2] * scale satisfy the
    triangle inequality) in random axes."""
    Q = random_rotation(rng)
    return Q @ np.diag(rng.uniform(1.0, 2.0, 3) * scale) @ Q.T


def random_system(rng, **kw):
    ms = rng.uniform(0.5, 2.0)
    Rs = rng.uniform(0.1, 0.3)
    params = dict(
        ms=ms,
        Rs=Rs,
        Is=rng.uniform(0.4, 0.67) * ms * Rs**2,
        mt=rng.uniform(0.2, 1.5),
        It=random_inertia(rng),
        c=rng.normal(size=3) * 0.03,
    )
    params.update(kw)
    return ShellWithTopReduced(**params)


def random_initial_state(sys, rng, scale=3.0):
    return sys.initial_state(
        rng.normal(size=3) * scale,
        attitude=random_rotation(rng),
        shell_velocity=rng.normal(size=2) * 0.3,
        shell_spin=rng.normal(),
        position=rng.normal(size=2),
    )


# ----------------------------------------------------------------- parameters
def test_mu_J_and_energy_decomposition(rng):
    sys = random_system(rng)
    ms, Is, Rs, mt = (float(v) for v in (sys.ms, sys.Is, sys.Rs, sys.mt))
    c, It = np.asarray(sys.c), np.asarray(sys.It)
    mu = mt * Rs**2 / (Is + (ms + mt) * Rs**2)
    np.testing.assert_allclose(sys.mu, mu, rtol=1e-15)
    J = It + (1 - mu) * mt * (c @ c * np.eye(3) - np.outer(c, c))
    np.testing.assert_allclose(sys.J, J, rtol=1e-14)
    # E_total = E_reduced + Is Omega_z^2 / 2 + (mt/mu) |K|^2 / 2 at arbitrary states

    @jax.jit
    def parts(x):
        K = sys.chaplygin_vector_space(x)
        return K, sys.energy(x), sys.reduced_energy(x), sys.shell_spin(x)

    for _ in range(5):
        K, E, Ered, spin = parts(random_initial_state(sys, rng))
        np.testing.assert_allclose(K[2], 0.0, atol=1e-15)  # K is horizontal
        np.testing.assert_allclose(E, Ered + 0.5 * Is * spin**2 + 0.5 * mt / mu * K @ K, rtol=1e-13)


def test_initial_state_is_consistent(rng):
    sys = random_system(rng)
    R = random_rotation(rng)
    x = sys.initial_state([1.0, 2.0, 3.0], attitude=R, shell_velocity=(0.4, -0.2), shell_spin=0.7)
    np.testing.assert_allclose(sys.attitude(x), R, atol=1e-15)
    V_space = R @ sys.contact_velocity(x)
    np.testing.assert_allclose(V_space, [0.4, -0.2, 0.0], atol=1e-14)
    np.testing.assert_allclose(sys.shell_spin(x), 0.7, rtol=1e-14)
    # (1.5): Omega = gamma x V / Rs + Omega_z gamma
    ga = x[6:9]
    np.testing.assert_allclose(
        x[3:6], jnp.cross(ga, sys.contact_velocity(x)) / sys.Rs + 0.7 * ga, atol=1e-14
    )
    np.testing.assert_allclose(sys.constraints(0.0, x)["frame"], 0.0, atol=1e-15)


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="ms"):
        ShellWithTopReduced(ms=-1.0)
    with pytest.raises(ValueError, match="Rs"):
        ShellWithTopReduced(Rs=0.0)
    with pytest.raises(ValueError, match="It.*positive definite"):
        ShellWithTopReduced(It=(1e-3, -1e-3, 2e-3))
    with pytest.raises(ValueError, match="It.*symmetric"):
        ShellWithTopReduced(It=[[1e-3, 1e-4, 0], [0, 1e-3, 0], [0, 0, 1e-3]])
    with pytest.raises(ValueError, match="c must be a 3-vector"):
        ShellWithTopReduced(c=(0.0, 0.1))
    sys = ShellWithTopReduced()
    with pytest.raises(ValueError, match="attitude"):
        sys.initial_state([0.0, 0.0, 1.0], attitude=np.diag([1.0, 1.0, 2.0]))


def test_off_manifold_state_is_rejected_or_projected(rng):
    sys = random_system(rng)
    x0 = random_initial_state(sys, rng)
    bad = x0.at[6:9].multiply(1.001)
    with pytest.raises(nhjax.ConstraintViolationError, match="frame"):
        nhjax.simulate(sys, bad, 0.1, saveat=3)
    p = sys.project(0.0, bad)
    np.testing.assert_allclose(sys.constraints(0.0, p)["frame"], 0.0, atol=1e-14)
    np.testing.assert_allclose(p[6:9], x0[6:9], atol=1e-12)


# ----------------------------------------------------------------- correctness
# The engine's nested autodiff compiles slowly; XLA's cheapest optimization level
# halves that and runs these few pointwise evaluations just as well.
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


def fast_jit(fn, *example_args):
    return jax.jit(fn).lower(*example_args).compile(compiler_options=FAST_COMPILE)


def _engine_compare_fn(red, lag):
    """(q, shape rates, tau) -> (reduced state, its rate from the engine,
    the reduced model's rate, constraint residual)."""

    def compare(q, rates, tau):
        qd = jnp.concatenate([jnp.zeros(2), rates])
        qd = qd.at[0:2].add(-lag.velocity_constraints(0.0, q, qd))  # roll without slipping
        qdd, _ = lag.accelerations(0.0, q, qd, tau)
        x, dx = jax.jvp(lag.reduced_state, (q, qd), (qd, qdd))
        return x, dx, red.forced_vector_field(0.0, x, tau), lag.velocity_constraints(0.0, q, qd)

    return fast_jit(compare, jnp.zeros(8), jnp.zeros(6), jnp.zeros(3))


def test_reduced_equations_match_two_body_engine(rng):
    """(1.5), (1.8), (1.11), (1.12) and the torque terms against the Lagrange–d'Alembert
    equations the engine derives from the two rigid bodies with no-slip written in space."""
    red = random_system(rng)
    lag = ShellWithTopLagrangian.from_reduced(red)
    compare = _engine_compare_fn(red, lag)
    kappa = float(red.Rs / red.I_contact)
    for k in range(6):
        q = jnp.asarray(np.concatenate([rng.normal(size=2), rng.normal(size=6) * 0.9]))
        rates = jnp.asarray(rng.normal(size=6) * 2.0)
        tau = jnp.asarray(rng.normal(size=3) * 0.05 * (k % 2))
        x, dx_engine, dx_hand, slip = compare(q, rates, tau)
        np.testing.assert_allclose(slip, 0.0, atol=1e-14)
        scale = np.abs(dx_engine).max()
        np.testing.assert_allclose(dx_hand, dx_engine, rtol=0, atol=1e-12 * scale)
        # what a torque does to the integrals (for the full steering model):
        R = red.attitude(x)
        dK = jax.jvp(red.chaplygin_vector_space, (x,), (dx_engine,))[1]
        tau_space = R @ tau
        np.testing.assert_allclose(dK, -kappa * jnp.cross(tau_space, jnp.array([0.0, 0, 1])), atol=1e-12 * scale)
        dspin = jax.jvp(red.shell_spin, (x,), (dx_engine,))[1]
        np.testing.assert_allclose(dspin, -tau_space[2] / red.Is, atol=1e-12 * scale)
        dE = jax.jvp(red.energy, (x,), (dx_engine,))[1]
        np.testing.assert_allclose(dE, red.torque_power(x, tau), atol=1e-12 * scale)
        ga = x[6:9]
        LPz = lambda y: red.contact_angular_momentum(y) @ y[6:9]  # noqa: E731
        np.testing.assert_allclose(
            LPz(x), red.Is * red.shell_spin(x) + red.area_integral(x)
            + red.mt * jnp.cross(red.c, red.chaplygin_vector(x)) @ ga, rtol=1e-12
        )
        dLPz = jax.jvp(LPz, (x,), (dx_engine,))[1]
        V, vc = red.contact_velocity(x), jnp.cross(x[0:3], red.c)
        np.testing.assert_allclose(dLPz, -red.mt * jnp.cross(V, vc) @ ga, atol=1e-12 * scale)


def test_theorem1_smooth_plane_ball(rng):
    """Theorem 1: the unbalanced ball on a smooth plane, written from its own
    Lagrangian (1.13) with rotation-vector coordinates (zero horizontal momentum),
    turns like the top for I = J, m = mu mt, a = c, g_b = g / mu."""
    red = random_system(rng)
    p = red.smooth_plane_ball_parameters()
    I, m, a, gb = p["I"], p["m"], p["a"], p["g"]

    def kin(q, qd):
        R, dR = jax.jvp(so3.exp, (q,), (qd,))
        return R, so3.vee(R.T @ dR), (dR @ a)[2]

    def T(q, qd):
        _, w, zdot = kin(q, qd)
        return 0.5 * w @ I @ w + 0.5 * m * zdot**2

    ball = Lagrangian(3, T, V=lambda q: m * gb * (so3.exp(q) @ a)[2])

    def both(q, qd):
        qdd, _ = ball.accelerations(0.0, q, qd)
        (R, w, _), (_, dw, _) = jax.jvp(kin, (q, qd), (qd, qdd))
        dom, dga = red.reduced_vector_field(w, R[2])
        return dw, dom

    both = fast_jit(both, jnp.zeros(3), jnp.zeros(3))

    for _ in range(5):
        q = jnp.asarray(rng.normal(size=3) * 0.9)
        qd = jnp.asarray(rng.normal(size=3) * 2.0)
        dw_ball, dw_top = both(q, qd)
        np.testing.assert_allclose(dw_top, dw_ball, rtol=1e-10, atol=1e-10 * np.abs(dw_ball).max())


def test_contact_path_formula_1_12(rng):
    """With Ox along K (the seed's choice): x' = |K| - mu (v_c, alpha), y' = -mu (v_c, beta)."""
    sys = random_system(rng)
    x = random_initial_state(sys, rng)
    K = sys.chaplygin_vector_space(x)
    # rotate the space axes about the vertical so that Ox is along K
    phi = np.arctan2(float(K[1]), float(K[0]))
    R = np.asarray(so3.rot_z(-phi)) @ np.asarray(sys.attitude(x))
    x = x.at[9:12].set(R[0]).at[12:15].set(R[1])
    Kn = float(jnp.linalg.norm(K))
    np.testing.assert_allclose(sys.chaplygin_vector_space(x), [Kn, 0.0, 0.0], atol=1e-14)
    f = sys.vector_field(0.0, x, None)
    vc = jnp.cross(x[0:3], sys.c)
    np.testing.assert_allclose(f[15], Kn - sys.mu * vc @ x[9:12], rtol=1e-13)
    np.testing.assert_allclose(f[16], -sys.mu * vc @ x[12:15], rtol=1e-13, atol=1e-15)


# ----------------------------------------------------------------- conservation
def relative_drifts(sys, traj):
    """Largest |I(t) - I(0)| divided by a natural scale of each invariant."""
    xs = traj.xs
    om, Om = xs[:, 0:3], xs[:, 3:6]
    J = np.asarray(sys.J)
    kin = float(np.max(jax.vmap(sys.energy)(xs) - sys.mt * sys.g * xs[:, 6:9] @ sys.c))
    e_scale = kin + float(sys.mt * sys.g * np.linalg.norm(sys.c))
    v_scale = float(np.max(np.linalg.norm(jax.vmap(sys.contact_velocity)(xs), axis=1)))
    v_scale += float(sys.mu * np.linalg.norm(sys.c) * np.max(np.linalg.norm(om, axis=1)))
    scales = {
        "energy": e_scale,
        "reduced_energy": e_scale,
        "gamma_sq": 1.0,
        "area": float(np.max(np.linalg.norm(om @ J.T, axis=1))),
        "shell_spin": float(np.max(np.linalg.norm(Om, axis=1))),
        "K_x": v_scale,
        "K_y": v_scale,
        "euler_M2": float(np.max(np.sum((om @ J.T) ** 2, axis=1))),
        "lagrange_M3": float(np.max(np.linalg.norm(om @ J.T, axis=1))),
    }
    return {k: float(v) / scales[k] for k, v in traj.invariant_drift.items()}


def test_invariants_conserved_random_tops(rng):
    """E, gamma^2, (J omega, gamma), Omega_z and K (fixed in space) to 1e-10 relative,
    Tsit5 at rtol = atol = 1e-12, for random inertia tensors and offsets."""
    for _ in range(3):
        sys = random_system(rng)
        assert sys.case == "general"
        x0 = random_initial_state(sys, rng)
        t1 = 6 * 2 * np.pi / float(jnp.linalg.norm(x0[0:3]))  # ~6 turns of the top
        traj = nhjax.simulate(sys, x0, t1, **TIGHT)
        rel = relative_drifts(sys, traj)
        assert set(rel) == {"energy", "reduced_energy", "gamma_sq", "area", "shell_spin", "K_x", "K_y"}
        for k, v in rel.items():
            assert v < 1e-10, (k, v, traj.summary())
        assert float(traj.constraint_drift["frame"]) < 1e-10
        # the motion is not trivial: the top tumbles and the shell travels
        assert np.ptp(np.asarray(traj.xs[:, 8])) > 0.1
        assert np.hypot(*(traj.xs[-1, 15:17] - x0[15:17])) > 1e-3


def _as_general(sys):
    """The same parameters with case="general": simulate() then reuses the compiled
    general-case solve (the case is a static field), and the extra integral is
    evaluated on the saved states below."""
    return ShellWithTopReduced(ms=sys.ms, Rs=sys.Rs, Is=sys.Is, mt=sys.mt, It=sys.It, c=sys.c, g=sys.g, case="general")


def test_euler_case(rng):
    """c = 0: |J omega|^2 is conserved; the top is a free Euler top (J = It) and the
    shell rolls at constant velocity."""
    sys = random_system(rng, c=np.zeros(3))
    assert sys.case == "euler" and "euler_M2" in sys.invariants(random_initial_state(sys, rng))
    np.testing.assert_allclose(sys.J, sys.It, rtol=1e-15)
    x0 = random_initial_state(sys, rng)
    traj = nhjax.simulate(_as_general(sys), x0, 5.0, **TIGHT)
    rel = relative_drifts(sys, traj)
    M2 = jax.vmap(sys.euler_integral)(traj.xs)
    rel["euler_M2"] = float(np.ptp(np.asarray(M2))) / float(np.max(M2))
    for k, v in rel.items():
        assert v < 1e-10, (k, v)
    V_space = jax.vmap(lambda x: sys.attitude(x) @ sys.contact_velocity(x))(traj.xs)
    np.testing.assert_allclose(V_space, np.broadcast_to(V_space[0], V_space.shape), atol=1e-10)


def test_lagrange_case(rng):
    """It axisymmetric about c: (J omega, c/|c|) is conserved; not so for a general top."""
    e = np.asarray(random_rotation(rng))[:, 0]
    A, C = 1.3e-3, 2.1e-3
    It = A * np.eye(3) + (C - A) * np.outer(e, e)
    sys = random_system(rng, It=It, c=0.05 * e)
    x0 = random_initial_state(sys, rng)
    assert sys.case == "lagrange" and "lagrange_M3" in sys.invariants(x0)
    traj = nhjax.simulate(_as_general(sys), x0, 5.0, **TIGHT)
    rel = relative_drifts(sys, traj)
    M3 = np.asarray(jax.vmap(sys.lagrange_integral)(traj.xs))
    rel["lagrange_M3"] = float(np.ptp(M3)) / float(np.max(np.linalg.norm(traj.xs[:, 0:3] @ sys.J, axis=1)))
    for k, v in rel.items():
        assert v < 1e-10, (k, v)
    # the same quantity changes by O(1) for a non-symmetric top (the check can fail)
    general = random_system(rng, c=0.05 * e)
    assert general.case == "general"
    tr = nhjax.simulate(general, x0, 5.0, **TIGHT)
    M3 = jax.vmap(general.lagrange_integral)(tr.xs)
    assert np.ptp(np.asarray(M3)) > 1e-3 * float(np.max(np.abs(M3)))


# ----------------------------------------------------------------- long run
@pytest.mark.slow
def test_long_run_10k_orbits(rng):
    """10^4 turns of the top (Dopri8, rtol = atol = 1e-12), in 10 segments of 1000:
    relative drift of every invariant per 1000 turns stays below 3e-9 (measured:
    1e-10 to 9e-10; the K components grow slowly with the unprojected frame's drift)."""
    sys = random_system(rng)
    x0 = random_initial_state(sys, rng, scale=2.0)
    period = 2 * np.pi / float(jnp.linalg.norm(x0[0:3]))
    I0 = {k: float(v) for k, v in sys.invariants(x0).items()}
    I0["energy"] = float(sys.energy(x0))
    x, t = x0, 0.0
    per_segment = []
    start = time.perf_counter()
    for seg in range(10):
        traj = nhjax.simulate(
            sys, x, t + 1000 * period, t0=t, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-12,
            saveat=201, max_steps=2_000_000,
        )
        rel = relative_drifts(sys, traj)
        per_segment.append(rel)
        x, t = traj.x_final, t + 1000 * period
        print(f"turns {1000 * (seg + 1):6d}: steps {int(traj.num_accepted_steps)}, "
              + ", ".join(f"{k} {v:.1e}" for k, v in sorted(rel.items())))
    now = {k: float(v) for k, v in sys.invariants(x).items()}
    now["energy"] = float(sys.energy(x))
    print(f"10^4 turns in {time.perf_counter() - start:.0f} s; total absolute change: "
          + ", ".join(f"{k} {abs(now[k] - I0[k]):.1e}" for k in sorted(now)))
    for rel in per_segment:
        for k, v in rel.items():
            assert v < 3e-9, (k, v)


def test_rotation_vector_chart_guard():
    """The engine model's rotation-vector chart is singular at |theta| = 2 pi: its guards
    measure the distance to that sphere (less chart_eps) for shell and top separately."""
    lag = ShellWithTopLagrangian(chart_eps=0.1)
    x = jnp.zeros(16).at[2:5].set(jnp.array([0.0, 3.0, 4.0])).at[5:8].set(jnp.array([6.0, 0.0, 0.0]))
    g = lag.guards(x)
    np.testing.assert_allclose(g["shell rotation vector"], 2 * np.pi - 0.1 - 5.0, rtol=1e-14)
    np.testing.assert_allclose(g["top rotation vector"], 2 * np.pi - 0.1 - 6.0, rtol=1e-14)
    assert np.all(np.isfinite(jax.grad(lambda y: lag.guards(y)["top rotation vector"])(jnp.zeros(16))))
    assert ShellWithTopLagrangian(chart_eps=0.0).guards(x) == {}  # guard off on request
    for bad in (7.0, -0.1):
        with pytest.raises(ValueError, match="chart_eps"):
            ShellWithTopLagrangian(chart_eps=bad)


@pytest.mark.slow
def test_spinning_shell_stops_at_the_rotation_vector_chart_edge():
    """A shell spinning about the vertical at 3 rad/s (top hanging at rest) in rotation-vector
    coordinates: the simulation stops where |theta_s| = 2 pi - chart_eps, after about
    (2 pi - 0.1) / 3 s, and names the guard."""
    lag = ShellWithTopLagrangian(c=(0.0, 0.0, -0.06), chart_eps=0.1)
    x0 = jnp.zeros(16).at[12].set(3.0)
    with pytest.raises(nhjax.ChartSingularityError, match="rotation-vector chart") as err:
        nhjax.simulate(lag, x0, 5.0, rtol=1e-10, atol=1e-10)
    e = err.value
    assert e.guard == "shell rotation vector"
    np.testing.assert_allclose(e.t, (2 * np.pi - 0.1) / 3.0, rtol=1e-6)  # steady spin: theta_s = 3 t e3
    xs = e.trajectory.xs
    np.testing.assert_allclose(np.linalg.norm(xs[-1, 2:5]), 2 * np.pi - 0.1, atol=1e-9)
