"""State spaces for Lie-group integrators.

A space says how a leaf of an ODE state moves: the vector field gives, for each
leaf, a *velocity* v, and the leaf evolves by

* ``Euclidean``:          y' = v                              (any array shape)
* ``SO3Body``:            R' = R hat(v)    R a 3x3 rotation, v the body angular velocity
* ``SO3Spatial``:         R' = hat(v) R    v the spatial angular velocity
* ``UnitQuaternionBody``: p' = p * (0, v) / 2   (same motion as SO3Body, on S^3)
* ``SE2Body``:            g' = g hat(v)    g a 3x3 homogeneous SE(2) matrix

Munthe-Kaas integrators write y(t) = y0 . exp(sigma(t)) and integrate the
algebra coordinates sigma, which obey sigma' = dexpinv_sigma(v) (``dexpinv``
below); ``retract`` maps sigma back to the group, so every stage and every step
lies exactly on the group (up to round-off in a product of group elements).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from . import se2, so3


def _mv(A, v):
    return jnp.einsum("...ij,...j->...i", A, v)


class AbstractSpace(eqx.Module):
    """How one leaf of a state moves; see the module docstring."""

    def retract(self, y0, sigma):
        """y0 . exp(sigma)."""
        raise NotImplementedError

    def dexpinv(self, sigma, v):
        """sigma' such that t -> y0 . exp(sigma(t)) has velocity v."""
        raise NotImplementedError

    def ambient(self, y0, sigma):
        """A representation of a small algebra increment sigma at y0, shaped like y0.

        Used for error estimates (step-size control) and for differences between
        dense-output points.
        """
        raise NotImplementedError

    def algebra_zeros(self, y0):
        raise NotImplementedError

    def coadjoint(self, xi, mu):
        """The term ad*_xi mu of the Hamel (Euler-Poincare) equations for this part:
        d/dt dL/dxi = coadjoint(xi, dL/dxi) + (derivative of L along the group) + forces."""
        raise NotImplementedError


class Euclidean(AbstractSpace):
    def retract(self, y0, sigma):
        return y0 + sigma

    def dexpinv(self, sigma, v):
        return v

    def ambient(self, y0, sigma):
        return sigma

    def algebra_zeros(self, y0):
        return jnp.zeros_like(y0)

    def coadjoint(self, xi, mu):
        return jnp.zeros_like(mu)


class SO3Body(AbstractSpace):
    def retract(self, y0, sigma):
        return y0 @ so3.exp(sigma)

    def dexpinv(self, sigma, v):
        # y0 exp(s): exp(-s) d/dt exp(s) = hat(dexp(-s) s')  =>  s' = dexpinv(-s) v
        return _mv(so3.dexpinv(-sigma), v)

    def ambient(self, y0, sigma):
        return y0 @ so3.hat(sigma)

    def algebra_zeros(self, y0):
        return jnp.zeros(y0.shape[:-2] + (3,), y0.dtype)

    def coadjoint(self, xi, mu):
        # <mu, xi x eta> = <mu x xi, eta>: Euler's  d/dt (I W) = (I W) x W
        return jnp.cross(mu, xi)


class SO3Spatial(AbstractSpace):
    def retract(self, y0, sigma):
        return so3.exp(sigma) @ y0

    def dexpinv(self, sigma, v):
        return _mv(so3.dexpinv(sigma), v)

    def ambient(self, y0, sigma):
        return so3.hat(sigma) @ y0

    def algebra_zeros(self, y0):
        return jnp.zeros(y0.shape[:-2] + (3,), y0.dtype)

    def coadjoint(self, xi, mu):
        # right trivialisation: the sign of the bracket flips
        return jnp.cross(xi, mu)


class UnitQuaternionBody(AbstractSpace):
    def retract(self, y0, sigma):
        return so3.quat_mul(y0, so3.quat_exp(sigma))

    def dexpinv(self, sigma, v):
        return _mv(so3.dexpinv(-sigma), v)

    def ambient(self, y0, sigma):
        zero = jnp.zeros_like(sigma[..., :1])
        return 0.5 * so3.quat_mul(y0, jnp.concatenate([zero, sigma], -1))

    def algebra_zeros(self, y0):
        return jnp.zeros(y0.shape[:-1] + (3,), y0.dtype)

    def coadjoint(self, xi, mu):
        return jnp.cross(mu, xi)


class SE2Body(AbstractSpace):
    def retract(self, y0, sigma):
        return y0 @ se2.exp(sigma)

    def dexpinv(self, sigma, v):
        return _mv(se2.dexpinv(-sigma), v)

    def ambient(self, y0, sigma):
        return y0 @ se2.hat(sigma)

    def algebra_zeros(self, y0):
        return jnp.zeros(y0.shape[:-2] + (3,), y0.dtype)

    def coadjoint(self, xi, mu):
        return _mv(jnp.swapaxes(se2.ad(xi), -1, -2), mu)


def is_space(x) -> bool:
    return isinstance(x, AbstractSpace)
