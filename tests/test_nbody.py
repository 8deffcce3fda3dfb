"""Many-body systems at zero angular momentum (seed 000, secs. 2-5): the general
reduction against the seed's inertia operator (3.9), vectors m_i (3.10), connection
(3.13) and vibrational metric (4.7); the planar three-body metric against the Hopf
map's |dw|^2/(4|w|); the reconstructed 3-D motion has zero angular momentum; shape
loops turn the system by the curvature integral; collinear shapes stop cleanly."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.lie import so3
from nhjax.mechanics import curvature_integral
from nhjax.scenes import NBodyCat, ThreeBodyCat

MASSES = (1.0, 2.0, 0.5)


class Tetra(eqx.Module):
    """Four particles: a flapping tetrahedron with two shape angles."""

    def __call__(self, q):
        a, b = q[0], q[1]
        return jnp.stack([jnp.array([1.0, 0.0, 0.0]), jnp.array([-0.5, 0.8, 0.0]),
                          jnp.stack([-0.5, -0.8 * jnp.cos(a), 0.8 * jnp.sin(a)]),
                          jnp.stack([0.2 * jnp.cos(b), 0.3, 0.9 + 0.4 * jnp.sin(b)])])


@jax.jit
def _seed_vs_general(cat, w):
    return dict(A=cat.connection(w), A_seed=jnp.linalg.solve(cat.inertia_operator(w), cat.m_vectors(w)),
                I=cat.locked_inertia(w), I_seed=cat.inertia_operator(w),
                M=cat.reduced_metric(w), M_seed=cat.seed_vibrational_metric(w))


def test_connection_and_metric_are_the_seeds(rng):
    """(3.9), (3.10), (3.13) A^-1 m_i and (4.7) written out = the general construction."""
    cats = [ThreeBodyCat(MASSES), NBodyCat(jnp.array([1.0, 0.7, 1.3, 0.9]), Tetra(), 2)]
    for cat in cats:
        for _ in range(3):
            w = jnp.asarray(rng.normal(size=cat.k))
            if cat.k == 3:
                w = w.at[2].set(abs(w[2]) + 0.2)
            q = _seed_vs_general(cat, w)
            for k in ("A", "I", "M"):
                np.testing.assert_allclose(q[k], q[k + "_seed"], rtol=1e-12, atol=1e-13)


def test_three_body_section_and_planar_hopf_metric(rng):
    """The Jacobi section reproduces its shape coordinates (2.7) with the centre of mass
    at 0; in the plane the reduced metric is |dw|^2 / (4|w|) (Hopf map) exactly."""
    cat, planar = ThreeBodyCat(MASSES), ThreeBodyCat(MASSES, planar=True)

    @jax.jit
    def q(w):
        x = cat.reference_poses(w)[1]
        return x, ThreeBodyCat.shape_of(x, MASSES), planar.reduced_metric(w)

    for _ in range(4):
        w = jnp.asarray(rng.normal(size=3))
        w = w.at[2].set(abs(w[2]) + 0.1)
        x, w_back, M = q(w)
        np.testing.assert_allclose(w_back, w, atol=1e-14)
        np.testing.assert_allclose(jnp.asarray(MASSES) @ x, 0.0, atol=1e-15)
        np.testing.assert_allclose(M, np.eye(3) / (4 * np.linalg.norm(w)), rtol=1e-12, atol=1e-15)


class ShapeTorque(eqx.Module):
    """Torques on the two shape coordinates."""

    amp: jax.Array
    bias: jax.Array

    def __call__(self, t, x):
        return self.amp * jnp.stack([jnp.sin(1.3 * t), jnp.cos(0.7 * t)]) + self.bias


class TrackShape(eqx.Module):
    """PD torques towards w_ref(t) = (0.3 + a sin 1.3t, 0.2 + a cos 0.7t, 1)."""

    amp: jax.Array

    def __call__(self, t, x):
        f = x[1]
        ref = jnp.stack([0.3 + self.amp * jnp.sin(1.3 * t), 0.2 + self.amp * jnp.cos(0.7 * t), jnp.ones_like(t)])
        return -4.0 * (f[:3] - ref) - 2.0 * f[3:]


@pytest.mark.parametrize("which", ["three bodies", pytest.param("four bodies", marks=pytest.mark.slow)])
def test_reconstructed_motion_has_zero_angular_momentum(which):
    """Shape torques at zero angular momentum, in 3-D: the particles reconstructed in
    space, x_i = R(t) rho_i(q(t)), with velocities from the integrator's own group
    velocity, have sum m x x x' = 0 to 1e-12 (relative to the sum of the |m x x x'|)
    while the system turns. Three bodies: the triangle (Jacobi section (2.6)-(2.7))
    starts tilted in space, its shape tracks an oscillating reference (PD torques, away
    from collinear), and it turns about its normal; four bodies flap in 3-D and turn by
    more than a radian about a moving axis."""
    if which == "three bodies":
        cat = ThreeBodyCat(MASSES)
        x0 = cat.initial_state([0.3, 0.2, 1.0], [1.5, -2.0, 0.5], group=so3.exp(jnp.array([0.4, -0.3, 0.2])))
        control, min_turn = TrackShape(jnp.asarray(0.8)), 0.05
    else:
        cat = NBodyCat(jnp.array([1.0, 0.7, 1.3, 0.9]), Tetra(), 2)
        x0 = cat.initial_state([0.3, 0.2], [1.5, -2.0])
        control, min_turn = ShapeTorque(jnp.asarray(0.3), jnp.zeros(2)), 1.0
    k = cat.k
    tr = nhjax.simulate(cat, x0, 8.0, control=control, rtol=1e-11,
                        atol=1e-11, saveat=41)
    Rs, fs = tr.xs
    m = cat.bodies.masses

    @jax.jit
    @jax.vmap
    def angular_momentum(R, f):
        xi = cat.vector_field(0.0, (R, f), jnp.zeros(k))[0]  # g^-1 g' (no dependence on u)
        q, qd = f[:k], f[k:2 * k]
        rho, drho = jax.jvp(lambda qq: cat.reference_poses(qq)[1], (q,), (qd,))
        x = rho @ R.T
        xd = (jnp.cross(xi, rho) + drho) @ R.T
        # scale of the terms m x x x' whose sum must vanish (round-off is relative to it)
        return jnp.sum(m[:, None] * jnp.cross(x, xd), 0), jnp.sum(m * jnp.linalg.norm(x, axis=1) * jnp.linalg.norm(xd, axis=1)), xi

    L, scale, xi = angular_momentum(Rs, fs)
    scale = max(1.0, float(scale.max()))
    assert float(jnp.abs(L).max()) < 1e-12 * scale
    np.testing.assert_allclose(jnp.einsum("nji,njk->nik", Rs, Rs), np.broadcast_to(np.eye(3), Rs.shape), atol=1e-13)
    assert float(jnp.linalg.norm(so3.log(Rs[-1] @ Rs[0].T))) > min_turn  # it turned
    if which == "four bodies":
        axes = xi / jnp.linalg.norm(xi, axis=1, keepdims=True)
        assert float(jnp.linalg.norm(axes - axes[0], axis=1).max()) > 0.3  # not about a fixed axis
    for c in ("x", "y", "z"):
        assert float(tr.invariant_drift[f"angular_momentum_{c}"]) < 1e-12 * scale


class Circle(eqx.Module):
    """Velocity control: ccw circle of radius rho in the plane of the first two shape
    coordinates (period 1); the others held."""

    rho: jax.Array
    k: int = eqx.field(static=True)

    def __call__(self, t, x):
        w = 2 * jnp.pi
        return jnp.concatenate([self.rho * w * jnp.stack([-jnp.sin(w * t), jnp.cos(w * t)]), jnp.zeros(self.k - 2)])


def _loop_turn(kin, centre, rho):
    x0 = kin.initial_state(centre.at[0].add(rho))
    tr = nhjax.simulate(kin, x0, 1.0, control=Circle(jnp.asarray(rho), kin.k), rtol=1e-12, atol=1e-12, saveat=2,
                        diagnostics=False)
    loop = lambda a: centre[:2] + rho * jnp.stack([jnp.cos(a), jnp.sin(a)])  # noqa: E731
    integral = curvature_integral(kin, loop, centre[:2], base=centre, n=32)
    return tr, integral


@pytest.mark.slow
def test_three_body_loops_turn_by_the_curvature_integral():
    """Three bodies in space: their connection takes values along the triangle's normal
    (abelian), so a loop in (w1, w2) turns them by exactly -(integral of F)."""
    tr, integral = _loop_turn(ThreeBodyCat(MASSES).kinematic(), jnp.array([0.4, 0.3, 1.0]), 0.5)
    np.testing.assert_allclose(so3.log(tr.xs[0][-1]), -integral, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(tr.xs[1][-1], tr.xs[1][0], atol=1e-10)  # the shape returned
    assert float(jnp.linalg.norm(integral)) > 0.05


@pytest.mark.slow
def test_planar_and_nonabelian_loops():
    """In the plane (SO(2)) the three-body turn is exactly -(integral of F); four bodies
    in 3-D (non-abelian) turn by exp(-integral of F) to leading order, the relative
    error of the log shrinking like the loop's radius."""
    kin = ThreeBodyCat(MASSES, planar=True).kinematic()
    tr, integral = _loop_turn(kin, jnp.array([0.4, 0.3, 1.0]), 0.5)
    np.testing.assert_allclose(tr.xs[-1, 0] - tr.xs[0, 0], -integral[0], rtol=1e-9)
    kin4 = NBodyCat(jnp.array([1.0, 0.7, 1.3, 0.9]), Tetra(), 2).kinematic()
    errs = []
    for rho in (0.4, 0.2):
        tr, integral = _loop_turn(kin4, jnp.array([0.3, 0.2]), rho)
        np.testing.assert_allclose(tr.xs[1][-1], tr.xs[1][0], atol=1e-10)  # the shape returned
        errs.append(float(jnp.linalg.norm(so3.log(tr.xs[0][-1]) + integral)) / float(jnp.linalg.norm(integral)))
    assert errs[0] < 0.2 and 1e-3 < errs[1] < 0.6 * errs[0]  # O(rho): non-abelian, not exact


class Spread(eqx.Module):
    """Four particles on the e1 axis, spread out of line by s (collinear at s = 0)."""

    def __call__(self, q):
        s, b = q[0], q[1]
        line = jnp.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.7, 0.0, 0.0], [1.5, 0.0, 0.0]])
        off = jnp.stack([jnp.array([0.0, 1.0, 0.3]), jnp.stack([0.0, jnp.cos(b), jnp.sin(b)]),
                         jnp.array([0.0, -0.5, 0.8]), jnp.stack([0.2, jnp.sin(b), -1.0])])
        return line + s * off


class Collapse(eqx.Module):
    """Velocity feedback s' = -2 s, b' = 1: the shape tends to collinear as exp(-2 t)."""

    def __call__(self, t, x):
        return jnp.stack([-2.0 * x[1][0], jnp.ones_like(t)])


@pytest.mark.slow  # (16 s; make test-all)
def test_near_collinear_shapes_stop_cleanly():
    """Where SO(3) stops acting freely (collinear bodies) the locked inertia is singular:
    a shape that tends to a line is stopped by the locked_inertia guard when its
    normalized determinant reaches guard_eps, with the time and a finite trajectory;
    three bodies driven through a collinear triangle are stopped by their chart guard
    (w3 changes sign there); a collinear start is refused."""
    kin = NBodyCat(jnp.array([1.0, 0.7, 1.3, 0.9]), Spread(), 2).kinematic()
    x0 = kin.initial_state([0.3, 0.0])
    with pytest.raises(nhjax.ChartSingularityError, match="locked_inertia") as err:
        nhjax.simulate(kin, x0, 6.0, control=Collapse(), rtol=1e-10, atol=1e-10, diagnostics=False)
    tr = err.value.trajectory
    s_end = float(tr.x_end[1][0])
    assert abs(float(kin.inertia_condition(tr.x_end[1])) - kin.guard_eps) < 1e-10
    np.testing.assert_allclose(float(tr.t_final), np.log(0.3 / s_end) / 2, rtol=1e-6)
    assert np.all(np.isfinite(np.asarray(tr.xs[0]))) and 0 < s_end < 0.01
    cat = ThreeBodyCat(MASSES).kinematic()
    with pytest.raises(nhjax.ChartSingularityError) as err:
        nhjax.simulate(cat, cat.initial_state([0.3, 0.2, 0.05]), 1.0,
                       control=lambda t, x: jnp.array([0.0, 0.0, -0.1]), rtol=1e-10, atol=1e-10,
                       diagnostics=False)
    # w3 = 0.05 - 0.1 t: stopped just before w3 = 0 (t = 0.5), by whichever guard came first
    assert err.value.guard in ("locked_inertia", "collinear") and 0.49 < err.value.t < 0.5
    assert 0 < float(err.value.trajectory.x_end[1][2]) < 1e-3
    with pytest.raises(nhjax.ChartSingularityError, match="already outside"):
        nhjax.simulate(cat, cat.initial_state([0.3, 0.2, 0.0]), 1.0, control=lambda t, x: jnp.zeros(3))
