"""The planar rigid motions SE(2).

Elements are 3x3 homogeneous matrices [[R, t], [0, 1]]; the algebra se(2) is
written in coordinates xi = (vx, vy, omega) with
hat(xi) = [[0, -omega, vx], [omega, 0, vy], [0, 0, 0]].
``exp``, ``log``, ``dexp`` (right-trivialised: d/dt exp(xi) = hat(dexp(xi) xi') exp(xi)),
``dexpinv`` and ``Ad`` (g hat(xi) g^-1 = hat(Ad(g) xi)) follow the same
conventions as ``nhjax.lie.so3`` and are finite with finite derivatives at
omega = 0 and omega = pi.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from . import _series as S

__all__ = ["Ad", "ad", "compose", "dexp", "dexpinv", "exp", "from_xytheta", "hat", "inverse", "log", "vee"]

_J = np.array([[0.0, -1.0], [1.0, 0.0]])  # numpy: no program to compile at import


def hat(xi):
    xi = jnp.asarray(xi)
    vx, vy, w = xi[..., 0], xi[..., 1], xi[..., 2]
    z = jnp.zeros_like(w)
    return jnp.stack(
        [jnp.stack([z, -w, vx], -1), jnp.stack([w, z, vy], -1), jnp.stack([z, z, z], -1)], -2
    )


def vee(X):
    X = jnp.asarray(X)
    return jnp.stack([X[..., 0, 2], X[..., 1, 2], 0.5 * (X[..., 1, 0] - X[..., 0, 1])], -1)


def from_xytheta(x, y, theta):
    """Homogeneous matrix of the pose (x, y, theta)."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack(
        [jnp.stack([c, -s, x + z], -1), jnp.stack([s, c, y + z], -1), jnp.stack([z, z, o], -1)], -2
    )


def _block(A, b):
    """[[A, b], [0, 0, 1]] from a (...,2,2) block and a (...,2) column."""
    top = jnp.concatenate([A, b[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), top.shape[:-2] + (1, 3))
    return jnp.concatenate([top, bottom], axis=-2)


def _coeffs(w):
    t2 = (w * w)[..., None, None]
    return t2, S.sinc(t2), S.cosc(t2), S.sinc3(t2)


def exp(xi):
    xi = jnp.asarray(xi)
    v, w = xi[..., :2], xi[..., 2]
    t2, a, c, _ = _coeffs(w)
    W = w[..., None, None] * _J
    R = jnp.eye(2) + a * W + c * (W @ W)
    V = a * jnp.eye(2) + c * W
    return _block(R, jnp.einsum("...ij,...j->...i", V, v))


def log(g):
    g = jnp.asarray(g)
    w = jnp.arctan2(g[..., 1, 0], g[..., 0, 0])
    t = g[..., :2, 2]
    t2 = (w * w)[..., None, None]
    # V^-1 = (w/2) cot(w/2) I - W/2  (W = w J)
    Vinv = S.half_cot(t2) * jnp.eye(2) - 0.5 * w[..., None, None] * _J
    v = jnp.einsum("...ij,...j->...i", Vinv, t)
    return jnp.concatenate([v, w[..., None]], axis=-1)


def inverse(g):
    R = g[..., :2, :2]
    Rt = jnp.swapaxes(R, -1, -2)
    return _block(Rt, -jnp.einsum("...ij,...j->...i", Rt, g[..., :2, 2]))


def compose(g, h):
    return g @ h


def Ad(g):
    """Matrix of Ad_g on (vx, vy, omega): [[R, (ty, -tx)], [0, 1]]."""
    g = jnp.asarray(g)
    t = g[..., :2, 2]
    return _block(g[..., :2, :2], jnp.stack([t[..., 1], -t[..., 0]], -1))


def ad(xi):
    """Matrix of ad_xi on (vx, vy, omega): [hat(xi), hat(eta)] = hat(ad(xi) eta)."""
    xi = jnp.asarray(xi)
    v, w = xi[..., :2], xi[..., 2]
    # _block puts 1 in the corner (group matrices); the algebra's corner is 0.
    return _block(w[..., None, None] * _J, _ad_col(v)) - jnp.diag(jnp.array([0.0, 0.0, 1.0]))


def _ad_col(v):
    # ad_xi eta = (omega J v_eta - omega_eta J v, 0): the omega_eta column is -J v.
    return -jnp.einsum("ij,...j->...i", _J, v)


def dexp(xi):
    """sum_k ad_xi^k/(k+1)!  in closed form."""
    xi = jnp.asarray(xi)
    v, w = xi[..., :2], xi[..., 2]
    t2, a, c, s3 = _coeffs(w)
    W = w[..., None, None] * _J
    A = a * jnp.eye(2) + c * W  # phi1(W)
    P2 = c * jnp.eye(2) + s3 * W  # phi2(W)
    return _block(A, jnp.einsum("...ij,...j->...i", P2, _ad_col(v)))


def dexpinv(xi):
    """Inverse of ``dexp(xi)`` (block-triangular inverse, |omega| < 2 pi)."""
    D = dexp(xi)
    A, b = D[..., :2, :2], D[..., :2, 2]
    a, bb = A[..., 0, 0], A[..., 1, 0]
    det = (a * a + bb * bb)[..., None, None]  # A = a I + bb J is a scaled rotation
    Ainv = (a[..., None, None] * jnp.eye(2) - bb[..., None, None] * _J) / det
    return _block(Ainv, -jnp.einsum("...ij,...j->...i", Ainv, b))
