"""Shell with an inner body on a nonholonomic hinge (seed 003, sec. 2): (2.4)
against the engine (two rigid bodies in space with the hinge and no-slip
constraints), the integrals F0-F4 (2.6) and the energy (2.7) at tight tolerance,
the invariant measure (2.8) by autodiff, and the zero-momentum system (2.9)."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.lie import so3
from nhjax.mechanics import Lagrangian
from nhjax.scenes.shell_suslov_hinge import ShellWithSuslovHinge, ShellWithSuslovHingeZeroMomentum

TIGHT = dict(solver=diffrax.Tsit5(), rtol=1e-12, atol=1e-12, saveat=101, max_steps=200_000)
E_Z = jnp.array([0.0, 0.0, 1.0])


# The engine's nested autodiff compiles slowly; XLA's cheapest optimization level
# halves that and runs these few pointwise evaluations just as well.
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


def fast_jit(fn, *example_args):
    return jax.jit(fn).lower(*example_args).compile(compiler_options=FAST_COMPILE)


def random_rotation(rng):
    return np.asarray(so3.exp(jnp.asarray(rng.normal(size=3))))


def random_params(rng):
    ms = rng.uniform(0.5, 2.0)
    Rs = rng.uniform(0.1, 0.3)
    return dict(
        ms=ms, Rs=Rs, Is=rng.uniform(0.4, 0.67) * ms * Rs**2, mt=rng.uniform(0.2, 1.5),
        inertia=rng.uniform(1.0, 2.0, 3) * 1e-2 * ms * Rs**2,
    )


def random_state(sys, rng, scale=3.0):
    return sys.initial_state(
        rng.normal(size=3) * scale, rng.normal(size=2) * scale, attitude=random_rotation(rng),
        position=rng.normal(size=2),
    )


# ----------------------------------------------------------------- correctness
def engine_model(sys):
    """Shell and body in space: q = (xc, yc, theta_shell, theta_body) (rotation vectors);
    constraints: no slip (space) and the hinge (omega_s - omega_b, R_b e3) = 0."""

    def kin(q, qd):
        (Rs_, Rb), (dRs, dRb) = jax.jvp(lambda q: (so3.exp(q[2:5]), so3.exp(q[5:8])), (q,), (qd,))
        drC = jnp.stack([qd[0], qd[1], jnp.zeros((), q.dtype)])
        return Rb, so3.vee(dRs @ Rs_.T), so3.vee(dRb @ Rb.T), drC

    def T(q, qd):
        Rb, ws, wb, drC = kin(q, qd)
        wb_body = Rb.T @ wb
        return 0.5 * (sys.m * drC @ drC + sys.Is * ws @ ws + wb_body @ (sys.inertia * wb_body))

    def constraints(t, q, qd):
        Rb, ws, wb, drC = kin(q, qd)
        slip = (drC - sys.Rs * jnp.cross(ws, E_Z))[:2]
        return jnp.concatenate([slip, jnp.atleast_1d((ws - wb) @ (Rb @ E_Z))])

    def reduced_state(q, qd):
        Rb, ws, wb, _ = kin(q, qd)
        return jnp.concatenate([Rb.T @ wb, Rb.T @ ws, Rb[2], Rb[0], Rb[1], q[0:2]])

    return Lagrangian(8, T, velocity_constraints=constraints), constraints, reduced_state


def test_equations_2_4_match_two_body_engine(rng):
    sys = ShellWithSuslovHinge(**random_params(rng))
    lag, cons, reduced_state = engine_model(sys)

    def compare(q, rates):
        qd = jnp.concatenate([jnp.zeros(2), rates])
        A = jax.jacfwd(lambda v: cons(0.0, q, v))(qd)
        qd = qd - jnp.linalg.pinv(A) @ cons(0.0, q, qd)  # admissible velocities
        qdd, _ = lag.accelerations(0.0, q, qd)
        x, dx = jax.jvp(reduced_state, (q, qd), (qd, qdd))
        return x, dx, sys.vector_field(0.0, x, None), cons(0.0, q, qd)

    compare = fast_jit(compare, jnp.zeros(8), jnp.zeros(6))
    for _ in range(6):
        q = jnp.asarray(rng.normal(size=8) * 0.9)
        x, dx_engine, dx_hand, res = compare(q, jnp.asarray(rng.normal(size=6) * 2.0))
        np.testing.assert_allclose(res, 0.0, atol=1e-13)
        np.testing.assert_allclose(x[5], x[2], atol=1e-13)  # Omega3 = omega3
        np.testing.assert_allclose(dx_hand, dx_engine, rtol=0, atol=1e-12 * np.abs(dx_engine).max())


def test_energy_2_7_is_the_kinetic_energy_of_both_bodies(rng):
    sys = ShellWithSuslovHinge(**random_params(rng))
    both = jax.jit(lambda x: (sys.energy(x), sys.kinetic_energy_bodies(x)))
    for _ in range(5):
        E, T = both(random_state(sys, rng))
        np.testing.assert_allclose(E, T, rtol=1e-14)


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="mt"):
        ShellWithSuslovHinge(mt=0.0)
    with pytest.raises(ValueError, match="inertia"):
        ShellWithSuslovHinge(inertia=(1.0, -1.0, 1.0))
    with pytest.raises(ValueError, match="inertia must be diagonal"):
        ShellWithSuslovHinge(inertia=[[1.0, 0.1, 0], [0.1, 1.0, 0], [0, 0, 1.0]])
    sys = ShellWithSuslovHinge()
    x = sys.initial_state([1.0, 2.0, 3.0], (0.5, -0.5))
    with pytest.raises(nhjax.ConstraintViolationError, match="suslov"):
        nhjax.simulate(sys, x.at[5].add(1e-3), 0.1, saveat=3)
    p = sys.project(0.0, x.at[5].add(1e-3))
    np.testing.assert_allclose(p[5] - p[2], 0.0, atol=1e-15)


# ----------------------------------------------------------------- integrals
def test_integrals_2_6_and_energy_2_7(rng):
    """F0-F4, E and M's space components stay constant to 1e-10 relative (Tsit5,
    rtol = atol = 1e-12), for random parameters."""
    for _ in range(3):
        sys = ShellWithSuslovHinge(**random_params(rng))
        x0 = random_state(sys, rng)
        traj = nhjax.simulate(sys, x0, 8.0, **TIGHT)
        xs = traj.xs
        Mmax = float(np.max(np.linalg.norm(jax.vmap(sys.angular_momentum)(xs), axis=1)))
        I1, I2, I3 = np.asarray(sys.inertia)
        w = float(np.max(np.abs(xs[:, 0:3])))
        scales = {
            "F0_gamma_sq": 1.0, "F1_suslov": w, "F2_M_sq": Mmax**2, "F3_M_gamma": Mmax,
            "F4": max(I1 * abs(I1 - I3), I2 * abs(I2 - I3)) * w**2, "M_x": Mmax, "M_y": Mmax,
            "energy": float(traj.invariants["energy"][0]),
        }
        drift = {k: float(v) / scales[k] for k, v in traj.invariant_drift.items()}
        assert set(drift) == set(scales)
        for k, v in drift.items():
            assert v < 1e-10, (k, v, traj.summary())
        # the motion is not trivial: the hinge torque works, omega3 and the body tumble
        assert np.ptp(np.asarray(xs[:, 2])) > 1e-2 * w
        assert np.ptp(np.asarray(xs[:, 8])) > 0.1


def _divergence(f, x, n):
    return jnp.trace(jax.jacfwd(f)(x)[:n, :n])


def test_invariant_measure_2_8(rng):
    """div(rho f) = 0 for rho = sqrt(Delta(gamma3)) in (omega, Omega, gamma), also off
    the hinge constraint; the flat measure (rho = 1) is not invariant."""
    sys = ShellWithSuslovHinge(**random_params(rng))
    f = lambda x: sys.vector_field(0.0, x, None)  # noqa: E731

    @jax.jit
    def div_rho_f(x):
        div = _divergence(f, x, 9)
        dlog_rho = jax.grad(lambda y: jnp.log(sys.invariant_measure_density(y)))(x) @ f(x)
        return div + dlog_rho, div

    for k in range(5):
        x = random_state(sys, rng)
        if k % 2:
            x = x.at[3:6].add(rng.normal(size=3))  # off Omega3 = omega3
        with_rho, flat = div_rho_f(x)
        assert abs(float(with_rho)) < 1e-12 * abs(float(flat)) + 1e-14
        assert abs(float(flat)) > 1e-6


# ----------------------------------------------------------------- zero momentum
def test_zero_momentum_system_2_9(rng):
    """From M = 0 the full system keeps M = 0 and its motion is that of (2.9); (2.9)
    conserves F0, F4, E and the measure Delta^(-1/2) d omega1 d omega2 d^3 gamma."""
    params = random_params(rng)
    full = ShellWithSuslovHinge(**params)
    zm = ShellWithSuslovHingeZeroMomentum(**params)
    R = random_rotation(rng)
    o12 = rng.normal(size=2) * 4.0
    x0 = full.initial_state_zero_momentum(o12, attitude=R)
    np.testing.assert_allclose(full.angular_momentum(x0), 0.0, atol=1e-15)
    np.testing.assert_allclose(x0[5], x0[2], atol=1e-15)
    z0 = zm.initial_state(o12, attitude=R)
    np.testing.assert_allclose(zm.full_state(z0), x0, atol=1e-15)

    tf = nhjax.simulate(full, x0, 8.0, **TIGHT)
    tz = nhjax.simulate(zm, z0, 8.0, **TIGHT)
    assert float(tf.invariant_drift["F2_M_sq"]) < 1e-20
    lifted = jax.vmap(zm.full_state)(tz.xs)
    np.testing.assert_allclose(lifted, tf.xs, atol=1e-8)
    assert np.hypot(*(tz.xs[-1, 11:13])) > 1e-3  # the robot moved from rest of M
    E0 = float(tz.invariants["energy"][0])
    assert float(tz.invariant_drift["energy"]) < 1e-10 * E0
    assert float(tz.invariant_drift["F0_gamma_sq"]) < 1e-10
    I1, I2, I3 = np.asarray(zm.inertia)
    assert float(tz.invariant_drift["F4"]) < 1e-10 * max(I1 * abs(I1 - I3), I2 * abs(I2 - I3)) * 16

    f = lambda z: zm.vector_field(0.0, z, None)  # noqa: E731

    @jax.jit
    def div_rho_f(z):
        dlog_rho = jax.grad(lambda y: jnp.log(zm.invariant_measure_density(y)))(z) @ f(z)
        div = _divergence(f, z, 5)
        return div + dlog_rho, div

    for z in tz.xs[::25]:
        with_rho, flat = div_rho_f(z)
        assert abs(float(with_rho)) < 1e-12 * abs(float(flat)) + 1e-14
