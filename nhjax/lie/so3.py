"""The rotation group SO(3) and its unit-quaternion double cover S^3.

Conventions (used everywhere in nhjax):

* Vectors w in R^3 stand for elements of so(3) through ``hat``:
  hat(w) x = w x x (cross product), eq. (3.5) of Iwai's paper (seed 000).
* ``exp(w)`` is Rodrigues' formula; ``log`` is its inverse with angle in [0, pi].
* ``dexp(w)`` is the right-trivialised differential of exp (the *left
  Jacobian* of robotics):  d/dt exp(w(t)) = hat(dexp(w) w') exp(w).
  The left-trivialised one is dexp(-w):  exp(-w) d/dt exp(w) = hat(dexp(-w) w').
  ``dexpinv(w)`` is its inverse, I - hat(w)/2 + c(|w|) hat(w)^2, singular only
  at |w| = 2 pi.
* ``Ad(R) = R`` on so(3) ~ R^3:  R hat(w) R^T = hat(R w).
* Quaternions are stored scalar first, q = (q0, q1, q2, q3) = (w, x, y, z), as in
  Rabier & Rheinboldt (seed 002) and jaxlie. q and -q are the same rotation.

All functions accept leading batch dimensions, are jit/vmap/grad friendly, and
have finite derivatives at the special angles 0 and pi (see ``_series``).
"""

from __future__ import annotations

import jax.numpy as jnp
import jaxlie

from . import _series as S

__all__ = [
    "Ad",
    "dexp",
    "dexpinv",
    "exp",
    "hat",
    "log",
    "quat_conj",
    "quat_exp",
    "quat_from_matrix",
    "quat_log",
    "quat_mul",
    "quat_rotate",
    "quat_to_matrix",
    "rot_x",
    "rot_y",
    "rot_z",
    "vee",
]


def hat(w):
    """so(3) matrix of w: hat(w) @ x == cross(w, x). Shape (..., 3) -> (..., 3, 3)."""
    w = jnp.asarray(w)
    z = jnp.zeros_like(w[..., 0])
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    rows = [
        jnp.stack([z, -wz, wy], axis=-1),
        jnp.stack([wz, z, -wx], axis=-1),
        jnp.stack([-wy, wx, z], axis=-1),
    ]
    return jnp.stack(rows, axis=-2)


def vee(W):
    """Inverse of ``hat`` (of the skew part of W, so it is exact for skew input)."""
    W = jnp.asarray(W)
    return 0.5 * jnp.stack(
        [
            W[..., 2, 1] - W[..., 1, 2],
            W[..., 0, 2] - W[..., 2, 0],
            W[..., 1, 0] - W[..., 0, 1],
        ],
        axis=-1,
    )


def _sq(w):
    return jnp.sum(jnp.square(w), axis=-1)[..., None, None]


def exp(w):
    """Rotation matrix exp(hat(w)) by Rodrigues' formula."""
    w = jnp.asarray(w)
    W = hat(w)
    t2 = _sq(w)
    return jnp.eye(3) + S.sinc(t2) * W + S.cosc(t2) * (W @ W)


def dexp(w):
    """Right-trivialised differential of exp (left Jacobian), see module doc."""
    w = jnp.asarray(w)
    W = hat(w)
    t2 = _sq(w)
    return jnp.eye(3) + S.cosc(t2) * W + S.sinc3(t2) * (W @ W)


def dexpinv(w):
    """Inverse of ``dexp(w)``: I - W/2 + (1 - (t/2)cot(t/2))/t^2 W^2, t = |w| < 2 pi."""
    w = jnp.asarray(w)
    W = hat(w)
    t2 = _sq(w)
    return jnp.eye(3) - 0.5 * W + S.dexpinv_coeff(t2) * (W @ W)


def Ad(R):
    """Adjoint of SO(3) on so(3) ~ R^3: the rotation matrix itself."""
    return jnp.asarray(R)


def rot_x(a):
    """Rotation by angle a about e1."""
    return _axis_rotation(a, 0)


def rot_y(a):
    """Rotation by angle a about e2."""
    return _axis_rotation(a, 1)


def rot_z(a):
    """Rotation by angle a about e3."""
    return _axis_rotation(a, 2)


def _axis_rotation(a, k):
    a = jnp.asarray(a, dtype=jnp.result_type(a, float))
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    i, j = (k + 1) % 3, (k + 2) % 3
    # rows of the identity with the (i, j) plane rotated by a
    M = [[None] * 3 for _ in range(3)]
    for r in range(3):
        for col in range(3):
            M[r][col] = o if (r == col == k) else z
    M[i][i], M[i][j], M[j][i], M[j][j] = c, -s, s, c
    return jnp.stack([jnp.stack(row, -1) for row in M], -2)


# ---------------------------------------------------------------- quaternions


def quat_mul(p, q):
    """Hamilton product p * q (scalar first)."""
    p0, pv = p[..., :1], p[..., 1:]
    q0, qv = q[..., :1], q[..., 1:]
    s = p0 * q0 - jnp.sum(pv * qv, axis=-1, keepdims=True)
    v = p0 * qv + q0 * pv + jnp.cross(pv, qv)
    return jnp.concatenate([s, v], axis=-1)


def quat_conj(q):
    """Conjugate (the inverse for unit quaternions)."""
    return q * jnp.array([1.0, -1.0, -1.0, -1.0])


def quat_exp(w):
    """Unit quaternion of the rotation exp(hat(w)): (cos(t/2), sin(t/2) w/t), t = |w|."""
    w = jnp.asarray(w)
    t2 = jnp.sum(jnp.square(w), axis=-1, keepdims=True)
    return jnp.concatenate([S.cos_half(t2), S.half_sinc(t2) * w], axis=-1)


def quat_log(q):
    """w with quat_exp(w) = +-q and |w| <= pi (q need not be exactly unit)."""
    q = jnp.asarray(q)
    q = jnp.where(q[..., :1] < 0, -q, q)  # q ~ -q: pick the representative with w >= 0
    w0, v = q[..., 0], q[..., 1:]
    n2 = jnp.sum(jnp.square(v), axis=-1)
    small = n2 < S.SMALL2 * 1e-2  # rotation angle below ~0.02 rad
    n_safe = jnp.sqrt(jnp.where(small, 1.0, n2))
    w_safe = jnp.where(small, w0, 1.0)
    x2 = n2 / w_safe**2  # atan(x)/x series, x = n/w <= 0.01
    series = (2.0 / w_safe) * (1 - x2 / 3 + x2**2 / 5 - x2**3 / 7 + x2**4 / 9)
    factor = jnp.where(small, series, 2.0 * jnp.arctan2(n_safe, w0) / n_safe)
    return factor[..., None] * v


def quat_to_matrix(q):
    """Rotation matrix of a unit quaternion (scalar first)."""
    q = jnp.asarray(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ]
    return jnp.stack(rows, axis=-2)


def quat_from_matrix(R):
    """Unit quaternion (scalar first, sign unspecified) of a rotation matrix.

    Uses jaxlie's branch-per-largest-diagonal construction, which stays accurate
    for every rotation angle, pi included.
    """
    R = jnp.asarray(R)
    if R.ndim == 2:
        return jaxlie.SO3.from_matrix(R).wxyz
    flat = R.reshape((-1, 3, 3))
    import jax

    q = jax.vmap(lambda m: jaxlie.SO3.from_matrix(m).wxyz)(flat)
    return q.reshape(R.shape[:-2] + (4,))


def quat_rotate(q, x):
    """Rotate vector x by unit quaternion q."""
    qx = jnp.concatenate([jnp.zeros_like(x[..., :1]), x], axis=-1)
    return quat_mul(quat_mul(q, qx), quat_conj(q))[..., 1:]


def log(R):
    """w in R^3 with exp(w) = R and |w| <= pi; finite derivatives at angles 0 and pi."""
    return quat_log(quat_from_matrix(R))
