"""The general reduction by symmetry (nhjax.mechanics.reduction): the metric against
the Hessian of the reduced Lagrangian, the momentum map against Ad*, the reduced
equations against the engines' unreduced ones (Lagrange on SE(2) coordinates, Hamel
on SO(3)), the momentum states, the falling cat rebuilt through the construction
against FallingCat (7.14)-(7.15), and clear errors."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nhjax.lie import Euclidean, SO3Body, so3
from nhjax.mechanics import Lagrangian, LieLagrangian
from nhjax.mechanics.reduction import SE2, SE3, SO2, SO3, Bodies, ReducedSystem
from nhjax.scenes import FallingCat, FallingCatReduced


# ----------------------------------------------------------------- test models
class Rigid3(eqx.Module):
    """Three rigid bodies in space placed by a 2-parameter shape (a bent, twisting chain)."""

    def __call__(self, r):
        a, b = r[0], r[1]
        R = jnp.stack([so3.rot_z(a), so3.rot_x(b) @ so3.rot_y(0.3 * a), so3.rot_y(a - b)])
        pos = jnp.stack([jnp.array([0.0, 0.0, 0.0]),
                         jnp.stack([jnp.cos(a), jnp.sin(a), 0.2 * b]),
                         jnp.stack([0.5 + 0.3 * jnp.sin(b), -0.4, 0.7 * jnp.cos(a + b)])])
        return R, pos


class Planar3(eqx.Module):
    def __call__(self, r):
        a, b = r[0], r[1]
        th = jnp.stack([0.1, a, a + b])
        pos = jnp.stack([jnp.array([0.0, 0.0]), jnp.stack([jnp.cos(0.1), jnp.sin(0.1)]) + 0.5 * jnp.stack([jnp.cos(a), jnp.sin(a)]),
                         jnp.stack([1.2 + 0.3 * jnp.cos(a + b), 0.4 * jnp.sin(b)])])
        return th, pos


def spatial_bodies(rng, n=3):
    J = []
    for _ in range(n):
        Q = so3.exp(jnp.asarray(rng.normal(size=3)))
        J.append(Q @ jnp.diag(jnp.asarray(rng.uniform(0.1, 0.5, 3))) @ Q.T)
    return Bodies(jnp.asarray(rng.uniform(0.5, 2.0, n)), jnp.stack(J))


def planar_bodies(rng, n=3):
    return Bodies(jnp.asarray(rng.uniform(0.5, 2.0, n)), jnp.asarray(rng.uniform(0.05, 0.3, n)))


def systems(rng, momentum="spatial"):
    sb, pb = spatial_bodies(rng), planar_bodies(rng)
    return {
        "SO3": ReducedSystem(sb, Rigid3(), SO3(), 2, momentum=momentum),
        "SE3": ReducedSystem(sb, Rigid3(), SE3(), 2, momentum=momentum),
        "SO2 axis": ReducedSystem(sb, Rigid3(), SO2(axis=(0.0, 0.6, 0.8)), 2, momentum=momentum),
        "SO2": ReducedSystem(pb, Planar3(), SO2(), 2, momentum=momentum),
        "SE2": ReducedSystem(pb, Planar3(), SE2(), 2, momentum=momentum),
    }


def random_state(sys, rng):
    R = so3.exp(jnp.asarray(rng.normal(size=3))) if sys.symmetry.matrix else None
    c = jnp.asarray(rng.normal(size=sys.n_group))
    m = None if sys.momentum == "zero" else jnp.asarray(rng.normal(size=sys.symmetry.dim))
    return sys.join(R, c, jnp.asarray(rng.uniform(-1, 1, 2)), jnp.asarray(rng.normal(size=2)), m)


# ------------------------------------------------------------------- geometry
def test_metric_is_hessian_of_reduced_lagrangian_and_momentum_map_is_ad_star(rng):
    """G from the body-velocity columns = d2 l/dv2 by autodiff; the momentum summed over
    the bodies in space = Ad*_{g^-1} mu, for every group (checks the Ad conventions)."""

    @jax.jit
    def quantities(sys, x):
        R, c, r, rd, J = sys.split(x)
        n = sys.symmetry.dim + sys.k
        H = jax.hessian(lambda v: sys.reduced_lagrangian(r, v))(jnp.zeros(n))
        mu = sys.body_momentum(x)
        xi = sys.group_velocity(x)
        return dict(G=sys.metric(r), H=H, J=J, Jmap=sys.momentum_map(x), Jad=sys.symmetry.to_spatial(R, c, mu),
                    mu=mu, mu_conn=sys.locked_inertia(r) @ (xi + sys.connection(r) @ rd))

    for name, sys in systems(rng).items():
        if name in ("SO2", "SO2 axis"):  # covered by the chain's and the cat's tests
            continue
        for _ in range(2):
            q = quantities(sys, random_state(sys, rng))
            np.testing.assert_allclose(q["G"], q["H"], atol=1e-13, err_msg=name)
            np.testing.assert_allclose(q["Jmap"], q["J"], atol=1e-12, err_msg=name)
            np.testing.assert_allclose(q["Jad"], q["J"], atol=1e-12, err_msg=name)
            # xi from the connection: mu = I (xi + A r')
            np.testing.assert_allclose(q["mu_conn"], q["mu"], atol=1e-12, err_msg=name)


def test_curvature_of_abelian_connection_is_its_exterior_derivative(rng):
    sys = systems(rng)["SO2"]
    r = jnp.array([0.3, -0.7])
    dA, F = jax.jit(lambda r: (jax.jacfwd(sys.connection)(r)[0], sys.curvature(r)))(r)  # dA[j, i] = d_i A_j
    np.testing.assert_allclose(F[0, 0, 1], dA[1, 0] - dA[0, 1], atol=1e-14)
    np.testing.assert_allclose(F[0], -F[0].T, atol=1e-15)


def test_reduced_equations_equal_lagrange_equations_on_se2_coordinates(rng):
    """Unreduced: q = (x, y, angle, r) with L = l(r, (R^T (x', y'), angle', r')) by the
    engine's Lagrange equations; its r'' must equal the reduced (9c) r'' at any momentum."""
    sys = systems(rng, momentum="body")["SE2"]

    def T(q, qd):
        c = jnp.cos(q[2]), jnp.sin(q[2])
        vb = jnp.stack([c[0] * qd[0] + c[1] * qd[1], -c[1] * qd[0] + c[0] * qd[1], qd[2]])
        return sys.reduced_lagrangian(q[3:], jnp.concatenate([vb, qd[3:]]))

    tau = jnp.asarray(rng.normal(size=2))
    eng = Lagrangian(5, T=T, force=lambda t, q, qd, u: jnp.concatenate([jnp.zeros(3), u]), control_dim=2)

    @jax.jit
    @jax.vmap
    def both(x):
        _, c, r, rd, _ = sys.split(x)
        xi = sys.group_velocity(x)
        R = jnp.array([[jnp.cos(c[2]), -jnp.sin(c[2])], [jnp.sin(c[2]), jnp.cos(c[2])]])
        qd = jnp.concatenate([R @ xi[:2], xi[2:], rd])
        qdd, _ = eng.accelerations(0.0, jnp.concatenate([c, r]), qd, tau)
        return sys.vector_field(0.0, x, tau), qd, qdd

    xs = jnp.stack([random_state(sys, rng) for _ in range(4)])
    f, qd, qdd = both(xs)
    np.testing.assert_allclose(f[:, 5:7], qdd[:, 3:], rtol=1e-11, atol=1e-12)
    # and the group rates: g' = g xi
    np.testing.assert_allclose(f[:, :3], qd[:, :3], atol=1e-13)


class HamelSO3(LieLagrangian):
    """The same bodies unreduced on SO(3) x R^2 for the engine's Hamel equations."""

    sys: ReducedSystem

    @property
    def config_spaces(self):
        return (SO3Body(), Euclidean())

    def lagrangian(self, g, v):
        return self.sys.reduced_lagrangian(g[1], v)

    def generalized_force(self, t, g, v, u):
        return jnp.concatenate([jnp.zeros(3), u])

    control_dim = 2


def test_reduced_equations_equal_hamel_equations_on_so3(rng):
    sys = systems(rng, momentum="body")["SO3"]
    eng = HamelSO3(sys)
    tau = jnp.asarray(rng.normal(size=2))

    @jax.jit
    def both(x):
        R, _, r, rd, mu = sys.split(x)
        xi = sys.group_velocity(x)
        vd, _ = eng.accelerations(0.0, (R, r), jnp.concatenate([xi, rd]), tau)
        return sys.vector_field(0.0, x, tau), vd, jnp.cross(mu, xi)

    for _ in range(3):
        f, vd, euler = both(random_state(sys, rng))
        np.testing.assert_allclose(f[1][2:4], vd[3:], rtol=1e-11, atol=1e-12)
        # mu' = ad*_xi mu = mu x xi (Euler) in the body-momentum state
        np.testing.assert_allclose(f[1][-3:], euler, atol=1e-13)


def test_momentum_states_agree(rng):
    """'spatial' (J carried) and 'body' (mu carried) give the same group and shape rates,
    and d/dt Ad*_{g^-1} mu = 0 along the body-momentum flow without body forces."""
    body = systems(np.random.default_rng(5), momentum="body")["SE3"]
    spat = systems(np.random.default_rng(5), momentum="spatial")["SE3"]
    x = random_state(spat, rng)
    u = jnp.asarray(rng.normal(size=2))

    @jax.jit
    def rates(x):
        R, c, r, rd, J = spat.split(x)
        xb = body.join(R, c, r, rd, spat.symmetry.to_body(R, c, J))
        fs, fb = spat.vector_field(0.0, x, u), body.vector_field(0.0, xb, u)
        free = body.vector_field(0.0, xb, jnp.zeros(2))
        J_of = lambda y: body.symmetry.to_spatial(*body.split(y)[:2], body.split(y)[4])  # noqa: E731
        dJ = jax.jvp(J_of, (xb,), ((xb[0] @ so3.hat(free[0]), free[1]),))[1]
        return fs, fb, dJ

    fs, fb, dJ = rates(x)
    np.testing.assert_allclose(fs[0], fb[0], atol=1e-13)
    n = spat.n_group + 2 * spat.k
    np.testing.assert_allclose(fs[1][:n], fb[1][:n], atol=1e-12)
    np.testing.assert_allclose(fs[1][n:], 0.0, atol=0)
    np.testing.assert_allclose(dJ, 0.0, atol=1e-12)


# ---------------------------------------------------------- the cat, rebuilt
@pytest.mark.parametrize("pars", [dict(), dict(I1=0.3, lam=1.7, B=0.8), dict(I1=2.0, lam=0.05, B=4.0)])
def test_cat_rebuilt_equals_falling_cat(pars, rng):
    """Connection (6.7): A = (0, f); vibrational metric (7.3); curvature (7.13); locked
    inertia 2 I1 D; and the torque-driven equations (7.14)-(7.15), all to 1e-12."""
    cat, red = FallingCat(**pars), FallingCatReduced(**pars)
    th = jnp.asarray(rng.uniform(0.1, 3.0, 8))
    chi, psi, thd, chd = (jnp.asarray(rng.normal(size=8)) for _ in range(4))
    us = jnp.asarray(rng.normal(size=(8, 2)))
    q = _cat_quantities(cat, red, th, chi, psi, thd, chd, us)
    np.testing.assert_allclose(q["A"][:, 0, 1], q["f"], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(q["A"][:, 0, 0], 0.0, atol=1e-14)
    np.testing.assert_allclose(q["M"], q["M_cat"], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(q["F"][:, 0, 0, 1], q["F_cat"], rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(q["I"][:, 0, 0], 2 * cat.I1 * q["D"], rtol=1e-12)
    f = q["vf_cat"]
    np.testing.assert_allclose(q["vf"][:, [1, 2, 0, 3, 4]], f, rtol=1e-12, atol=1e-12 * float(jnp.abs(f).max()))
    # work-energy: the reduced energy is the cat's (7.9) on the connection
    np.testing.assert_allclose(q["E"], q["E_cat"], rtol=1e-12)


@jax.jit
def _cat_quantities(cat, red, th, chi, psi, thd, chd, us):
    r = jnp.stack([th, chi], 1)
    x = jax.vmap(cat.initial_state)(th, chi, psi, thd, chd)
    xr = jax.vmap(red.initial_state)(th, chi, psi, thd, chd)
    return dict(
        A=jax.vmap(red.connection)(r), f=jax.vmap(cat.f)(th),
        M=jax.vmap(red.reduced_metric)(r), M_cat=jax.vmap(lambda t: jnp.diag(cat.shape_inertia(t)))(th),
        F=jax.vmap(red.curvature)(r), F_cat=jax.vmap(cat.curvature)(th),
        I=jax.vmap(red.locked_inertia)(r), D=jax.vmap(cat.D)(th),
        vf=jax.vmap(lambda a, u: red.vector_field(0.0, a, u))(xr, us),
        vf_cat=jax.vmap(lambda a, u: cat.vector_field(0.0, a, u))(x, us),
        E=jax.vmap(red.energy)(xr), E_cat=jax.vmap(cat.energy)(x),
    )


# ------------------------------------------------------------------- errors
def test_clear_errors(rng):
    pb, sb = planar_bodies(rng), spatial_bodies(rng)
    with pytest.raises(ValueError, match="group"):
        ReducedSystem(pb, Planar3(), "SO4", 2)
    with pytest.raises(ValueError, match="planar"):
        ReducedSystem(sb, Rigid3(), SE2(), 2)
    with pytest.raises(ValueError, match="positions of shape"):
        ReducedSystem(pb, lambda r: (jnp.zeros(3), jnp.zeros((2, 2))), SE2(), 2)
    with pytest.raises(ValueError, match="momentum"):
        ReducedSystem(pb, Planar3(), SE2(), 2, momentum="angular")
    thr = lambda r, u: (jnp.zeros(2), jnp.zeros((3, 3)).at[:, 0].set(u))  # noqa: E731
    with pytest.raises(ValueError, match="momentum='zero' cannot hold"):
        ReducedSystem(pb, Planar3(), SE2(), 2, momentum="zero", inputs=thr, control_dim=3)
    with pytest.raises(ValueError, match="control_dim"):
        ReducedSystem(pb, Planar3(), SE2(), 2, inputs=thr)
    with pytest.raises(ValueError, match="masses"):
        Bodies([1.0, -1.0], [0.1, 0.1])
    with pytest.raises(ValueError, match="unit 3-vector"):
        SO2(axis=(1.0, 1.0, 0.0))
    sys = ReducedSystem(pb, Planar3(), SE2(), 2, inputs=thr, control_dim=3)
    assert sys.momentum == "spatial" and sys.external
    with pytest.raises(ValueError, match="shape must have 2"):
        sys.initial_state([0.1, 0.2, 0.3])
