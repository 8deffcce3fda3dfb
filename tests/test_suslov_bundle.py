"""Generalized Suslov problem, a free two-body bundle on a nonholonomic hinge
(seed 003, sec. 3): (3.3) against the engine, (3.5) against (3.3), the
Hamiltonian form (3.7)-(3.8) with its Jacobi identity and Casimirs, and the
integrals (3.4), (3.6), (3.7) at tight tolerance."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.lie import so3
from nhjax.mechanics import Lagrangian
from nhjax.scenes.suslov_bundle import SuslovBundle

TIGHT = dict(solver=diffrax.Tsit5(), rtol=1e-12, atol=1e-12, saveat=101, max_steps=200_000)
E_Z = jnp.array([0.0, 0.0, 1.0])


# The engine's nested autodiff compiles slowly; XLA's cheapest optimization level
# halves that and runs these few pointwise evaluations just as well.
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


def fast_jit(fn, *example_args):
    return jax.jit(fn).lower(*example_args).compile(compiler_options=FAST_COMPILE)


def random_rotation(rng):
    return np.asarray(so3.exp(jnp.asarray(rng.normal(size=3))))


def random_bundle(rng, principal=True):
    d = rng.uniform(1.0, 2.0, 3) * 1e-2
    if principal:
        I = np.diag(d)
    else:  # e3 not principal: a generic symmetric positive definite tensor
        Q = random_rotation(rng)
        I = Q @ np.diag(d) @ Q.T
    return SuslovBundle(Is=rng.uniform(0.5, 2.0) * 1e-2, inertia=I)


def random_state(sys, rng, scale=3.0):
    return sys.initial_state(rng.normal(size=3) * scale, rng.normal(size=2) * scale, attitude=random_rotation(rng))


def test_equations_3_3_match_engine(rng):
    """(3.3) against the Lagrange–d'Alembert equations of the two bodies in space
    (rotation vectors) with the hinge (omega_out - omega_in, R_in e3) = 0."""
    sys = random_bundle(rng, principal=False)
    I = sys.inertia

    def kin(q, qd):
        (Ro, Ri), (dRo, dRi) = jax.jvp(lambda q: (so3.exp(q[0:3]), so3.exp(q[3:6])), (q,), (qd,))
        return Ri, so3.vee(dRo @ Ro.T), so3.vee(dRi @ Ri.T)

    def T(q, qd):
        Ri, wo, wi = kin(q, qd)
        wb = Ri.T @ wi
        return 0.5 * sys.Is * wo @ wo + 0.5 * wb @ I @ wb

    def cons(t, q, qd):
        Ri, wo, wi = kin(q, qd)
        return jnp.atleast_1d((wo - wi) @ (Ri @ E_Z))

    def reduced(q, qd):
        Ri, wo, wi = kin(q, qd)
        return jnp.concatenate([Ri.T @ wi, Ri.T @ wo, Ri[2], Ri[0], Ri[1]])

    lag = Lagrangian(6, T, velocity_constraints=cons)

    def compare(q, qd):
        A = jax.jacfwd(lambda v: cons(0.0, q, v))(qd)
        qd = qd - jnp.linalg.pinv(A) @ cons(0.0, q, qd)
        qdd, _ = lag.accelerations(0.0, q, qd)
        x, dx = jax.jvp(reduced, (q, qd), (qd, qdd))
        return x, dx, sys.vector_field(0.0, x, None)

    compare = fast_jit(compare, jnp.zeros(6), jnp.zeros(6))
    for _ in range(5):
        x, dx_engine, dx_hand = compare(jnp.asarray(rng.normal(size=6)), jnp.asarray(rng.normal(size=6) * 2))
        np.testing.assert_allclose(x[5], x[2], atol=1e-13)
        np.testing.assert_allclose(dx_hand, dx_engine, rtol=0, atol=1e-12 * np.abs(dx_engine).max())


def test_principal_case_3_5_and_hamiltonian_form_3_7_3_8(rng):
    """(3.5) equals (3.3) for diagonal I; x5' = J(x5) grad H with H (3.7) in the
    seed's a, b, c form and the bracket (3.8); Jacobi identity; Casimirs C1 = F2, C2."""
    sys = random_bundle(rng)
    a, b, c = (float(v) for v in sys.abc)
    I1, I2, I3 = np.diag(np.asarray(sys.inertia))

    def H_seed(x5):  # (3.7) literally
        O1, O2, w1, w2, w3 = x5
        return (0.5 * (O1**2 + O2**2) / (1 + c)
                + 0.5 * c * ((1 - a) * w1**2 + (1 - b) * w2**2) / ((1 - a * b) * (1 + c)) + 0.5 * w3**2)

    def omega3_dot_seed(x5):  # (3.5) literally
        O1, O2, w1, w2, _ = x5
        return ((1 - a * b) * (O1 * w2 - O2 * w1) - c * (a - b) * w1 * w2) / ((1 - a * b) * (1 + c))

    @jax.jit
    def check(x):
        x5 = sys.principal_coordinates(x)
        f5 = sys.principal_coordinates(sys.vector_field(0.0, x, None))
        J = sys.poisson_tensor(x5)
        dJ = jax.jacfwd(sys.poisson_tensor)(x5)  # dJ[i, j, l] = d J_ij / d x_l
        as_x = lambda y: jnp.concatenate([y[2:5], y[0:2], y[4:5], x[6:]])  # noqa: E731
        casimirs = [J @ jax.grad(lambda y: C(as_x(y)))(x5) for C in (sys.F2, sys.casimir_C2)]
        return dict(
            x5=x5, f5=f5, f5_principal=sys.principal_vector_field(x5), w3dot_seed=omega3_dot_seed(x5),
            H_seed=H_seed(x5), H=sys.hamiltonian5(x5), T=sys.energy(x), J=J, dJ=dJ,
            J_gradH=J @ jax.grad(H_seed)(x5), casimirs=jnp.stack(casimirs),
        )

    for _ in range(5):
        r = check(random_state(sys, rng))
        f5 = r["f5"]
        np.testing.assert_allclose(r["f5_principal"], f5, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(r["w3dot_seed"], f5[4], rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(r["H_seed"], r["H"], rtol=1e-13)
        np.testing.assert_allclose(r["T"] / (sys.Is + I3), r["H"], rtol=1e-13)
        np.testing.assert_allclose(r["J_gradH"], f5, rtol=1e-12, atol=1e-14)
        # Jacobi identity: J_il d_l J_jk + J_jl d_l J_ki + J_kl d_l J_ij = 0
        J, dJ = np.asarray(r["J"]), np.asarray(r["dJ"])
        jac = (np.einsum("il,jkl->ijk", J, dJ) + np.einsum("jl,kil->ijk", J, dJ)
               + np.einsum("kl,ijl->ijk", J, dJ))
        np.testing.assert_allclose(jac, 0.0, atol=1e-12)
        assert np.linalg.matrix_rank(J) == 2
        # Casimirs: F2 (3.6) and C2 annihilate the bracket
        np.testing.assert_allclose(r["casimirs"], 0.0, atol=1e-12)
    # the flat-body limit I3 = I1 + I2 (1 - ab = 0) stays regular
    flat = SuslovBundle(Is=0.02, inertia=(0.01, 0.015, 0.025))
    xf = random_state(flat, rng)
    assert np.all(np.isfinite(flat.principal_vector_field(flat.principal_coordinates(xf))))
    assert np.isfinite(float(flat.hamiltonian(xf)))


def test_integrals_principal_case(rng):
    """(3.6) F2, (3.7) H, the Casimir C2, M^2 and M in space, T: constant to 1e-10 relative."""
    for _ in range(2):
        sys = random_bundle(rng)
        assert sys.principal
        x0 = random_state(sys, rng)
        traj = nhjax.simulate(sys, x0, 10.0, **TIGHT)
        xs = traj.xs
        Mmax = float(np.max(np.linalg.norm(jax.vmap(sys.angular_momentum)(xs), axis=1)))
        w2 = float(np.max(np.sum(xs[:, 0:6] ** 2, axis=1)))
        a, b, _ = (abs(float(v)) for v in sys.abc)
        scales = {
            "F0_suslov": np.sqrt(w2), "F1_M_sq": Mmax**2, "M_x": Mmax, "M_y": Mmax, "M_z": Mmax,
            "F2": max(a, b) * w2, "H": float(traj.invariants["H"][0]), "C2": 4 * w2,
            "energy": float(traj.invariants["energy"][0]),
        }
        drift = {k: float(v) / scales[k] for k, v in traj.invariant_drift.items()}
        assert set(drift) == set(scales)
        for k, v in drift.items():
            assert v < 1e-10, (k, v, traj.summary())
        assert float(traj.constraint_drift["suslov"]) < 1e-10 * np.sqrt(w2)
        assert np.ptp(np.asarray(xs[:, 2])) > 1e-2 * np.sqrt(w2)  # the hinge works


def test_general_inertia(rng):
    """I13, I23 != 0: M (in space) and T are still conserved (their rates along (3.3)
    vanish), but (3.6) is not (it needs e principal)."""
    sys = random_bundle(rng, principal=False)
    assert not sys.principal
    assert set(sys.invariants(random_state(sys, rng))) == {"F0_suslov", "F1_M_sq", "M_x", "M_y", "M_z"}

    @jax.jit
    def rates(x):
        f = sys.vector_field(0.0, x, None)
        d = lambda fn: jax.jvp(fn, (x,), (f,))[1]  # noqa: E731
        return d(sys.angular_momentum_space), d(sys.energy), d(sys.F2), sys.angular_momentum(x), sys.energy(x)

    for _ in range(5):
        x = random_state(sys, rng)
        dM, dT, dF2, M, T = rates(x)
        w = float(jnp.linalg.norm(x[0:6]))
        np.testing.assert_allclose(dM, 0.0, atol=1e-13 * float(jnp.linalg.norm(M)) * w)
        np.testing.assert_allclose(dT, 0.0, atol=1e-13 * float(T) * w)
        assert abs(float(dF2)) > 1e-6 * w**3  # vs ~1e-13 for the true integrals


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="Is"):
        SuslovBundle(Is=-1.0)
    with pytest.raises(ValueError, match="inertia.*positive definite"):
        SuslovBundle(inertia=(0.01, 0.0, 0.02))
