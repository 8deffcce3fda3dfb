"""Lie groups: axioms, exp/log round trips, derivatives (autodiff and finite
differences), behaviour at the special angles 0 and pi, agreement with jaxlie."""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from nhjax.lie import _series, se2, so3

ANGLES = [0.0, 1e-12, 1e-8, 1e-4, 0.0999, 0.1, 0.1001, 0.7, 2.0, np.pi - 1e-7, np.pi]


def unit(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def test_so3_group_axioms(rng):
    A, B, C = (so3.exp(rng.normal(size=3) * 2) for _ in range(3))
    for R in (A, B, C, A @ B):
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_allclose((A @ B) @ C, A @ (B @ C), atol=1e-14)
    w = rng.normal(size=3)
    np.testing.assert_allclose(so3.exp(w) @ so3.exp(-w), np.eye(3), atol=1e-14)
    np.testing.assert_allclose(so3.exp(jnp.zeros(3)), np.eye(3), atol=0)


def test_hat_vee_cross(rng):
    w, x = rng.normal(size=3), rng.normal(size=3)
    np.testing.assert_allclose(so3.hat(w) @ x, np.cross(w, x), atol=1e-15)
    np.testing.assert_allclose(so3.vee(so3.hat(w)), w, atol=0)
    R = so3.exp(rng.normal(size=3))
    np.testing.assert_allclose(R @ so3.hat(w) @ R.T, so3.hat(so3.Ad(R) @ w), atol=1e-14)


@pytest.mark.parametrize("angle", ANGLES)
def test_so3_exp_log_round_trip(angle, rng):
    w = angle * unit(rng)
    R = so3.exp(w)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-15)
    w2 = so3.log(R)
    np.testing.assert_allclose(so3.exp(w2), R, atol=1e-14)
    if angle < np.pi - 1e-6:  # at pi, w and -w are the same rotation
        np.testing.assert_allclose(w2, w, atol=1e-15 + 1e-15 * angle)
    else:
        np.testing.assert_allclose(abs(np.dot(w2, w)), angle**2, rtol=1e-12)
    # independent implementation
    np.testing.assert_allclose(R, jaxlie.SO3.exp(w).as_matrix(), atol=1e-15)


@pytest.mark.parametrize("angle", ANGLES)
def test_so3_dexp_matches_autodiff_and_fd(angle, rng):
    w = jnp.asarray(angle * unit(rng))
    R = so3.exp(w)
    # d/de exp(w + e d) exp(w)^T = hat(dexp(w) d)
    J = jax.jacfwd(lambda d: so3.exp(w + d))(jnp.zeros(3))
    Jl = jnp.stack([so3.vee(J[:, :, k] @ R.T) for k in range(3)], -1)
    np.testing.assert_allclose(Jl, so3.dexp(w), atol=1e-14)
    h = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        fd = (so3.exp(w + d) - so3.exp(w - d)) / (2 * h) @ R.T
        np.testing.assert_allclose(so3.vee(fd), so3.dexp(w)[:, k], atol=1e-9)
    np.testing.assert_allclose(so3.dexpinv(w) @ so3.dexp(w), np.eye(3), atol=1e-13)


@pytest.mark.parametrize("angle", [pytest.param(0.0, marks=pytest.mark.slow), np.pi])
def test_so3_gradients_finite_at_special_angles(angle, rng):
    w = jnp.asarray(angle * unit(rng))
    R = so3.exp(w)
    for fn, arg in [(so3.exp, w), (so3.log, R), (so3.dexp, w), (so3.dexpinv, w), (so3.quat_exp, w)]:
        # compiled (op by op these derivatives dispatch hundreds of small programs)
        assert np.all(np.isfinite(jax.jit(jax.jacfwd(fn))(arg)))
        assert np.all(np.isfinite(jax.jit(jax.jacrev(lambda a: jnp.sum(fn(a) ** 2)))(arg)))
    if angle == 0.0:
        # d log at the identity is the vee map: log(exp(e d)) = e d
        d = jnp.array([0.3, -0.2, 0.9])
        jv = jax.jvp(so3.log, (R,), (so3.hat(d),))[1]
        np.testing.assert_allclose(jv, d, atol=1e-15)


def test_series_switch_is_seamless():
    """Just below the switch the series equals the closed form (evaluated in numpy at
    the same point); value and derivative barely move across the switch."""
    s = _series.SMALL2
    closed = {
        _series.sinc: lambda t: np.sin(t) / t,
        _series.cosc: lambda t: 2 * np.sin(t / 2) ** 2 / t**2,
        _series.sinc3: lambda t: (t - np.sin(t)) / t**3,
        _series.dexpinv_coeff: lambda t: (1 - (t / 2) / np.tan(t / 2)) / t**2,
        _series.cos_half: lambda t: np.cos(t / 2),
    }
    below, above = s * (1 - 1e-9), s * (1 + 1e-9)
    for fn, ref in closed.items():
        np.testing.assert_allclose(fn(below), ref(np.sqrt(below)), rtol=2e-12)
        np.testing.assert_allclose(fn(below), fn(above), rtol=1e-10)
        np.testing.assert_allclose(jax.grad(fn)(below), jax.grad(fn)(above), rtol=1e-9)


def test_quaternions(rng):
    w1, w2 = rng.normal(size=3), rng.normal(size=3)
    p, q = so3.quat_exp(w1), so3.quat_exp(w2)
    np.testing.assert_allclose(so3.quat_to_matrix(p), so3.exp(w1), atol=1e-15)
    np.testing.assert_allclose(
        so3.quat_to_matrix(so3.quat_mul(p, q)), so3.exp(w1) @ so3.exp(w2), atol=1e-14
    )
    x = rng.normal(size=3)
    np.testing.assert_allclose(so3.quat_rotate(p, x), so3.exp(w1) @ x, atol=1e-14)
    p2 = so3.quat_from_matrix(so3.exp(w1))
    assert min(np.abs(p2 - p).max(), np.abs(p2 + p).max()) < 1e-14
    np.testing.assert_allclose(so3.quat_to_matrix(so3.quat_exp(so3.quat_log(-p))), so3.exp(w1), atol=1e-14)
    batch = so3.quat_from_matrix(jnp.stack([so3.exp(w1), so3.exp(w2)]))
    assert batch.shape == (2, 4)


def test_se2_group_and_round_trips(rng):
    for w in [0.0, 1e-9, 1e-3, 0.5, 2.5, np.pi - 1e-8]:
        xi = jnp.array([rng.normal(), rng.normal(), w])
        g = se2.exp(xi)
        np.testing.assert_allclose(se2.log(g), xi, atol=1e-14)
        np.testing.assert_allclose(g @ se2.inverse(g), np.eye(3), atol=1e-14)
        np.testing.assert_allclose(g, jaxlie.SE2.exp(xi).as_matrix(), atol=1e-14)
        J = jax.jacfwd(lambda d: se2.exp(xi + d))(jnp.zeros(3))
        Jl = jnp.stack([se2.vee(J[:, :, k] @ se2.inverse(g)) for k in range(3)], -1)
        np.testing.assert_allclose(Jl, se2.dexp(xi), atol=1e-14)
        np.testing.assert_allclose(se2.dexpinv(xi) @ se2.dexp(xi), np.eye(3), atol=1e-13)
        assert np.all(np.isfinite(jax.jacrev(lambda a: jnp.sum(se2.dexpinv(a)))(xi)))
    h, eta = se2.from_xytheta(0.3, -1.0, 2.0), jnp.array([0.4, 0.1, -0.7])
    np.testing.assert_allclose(
        h @ se2.hat(eta) @ se2.inverse(h), se2.hat(se2.Ad(h) @ eta), atol=1e-14
    )
    np.testing.assert_allclose(se2.from_xytheta(0.3, -1.0, 2.0), jaxlie.SE2.from_xy_theta(0.3, -1.0, 2.0).as_matrix(), atol=1e-15)
