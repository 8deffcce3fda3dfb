r"""Constrained Lagrangian systems on products of Lie groups (Hamel equations by autodiff).

Configuration g: a tuple of parts, each on a space of ``nhjax.lie`` (``Euclidean``
coordinates, ``SO3Body`` rotation matrices, ``UnitQuaternionBody``,
``SE2Body``...). Velocity v: one flat vector of the parts' velocities in their
algebra coordinates (ordinary rates for Euclidean parts, body angular velocities
for ``SO3Body``...), so that g' = g . v part by part.

Given L(g, v), velocity constraints c(t, g, v) = A(t, g) v + a(t, g) = 0 (affine
in v), position constraints phi(t, g) = 0 and generalized forces F(t, g, v, u)
dual to v, the Hamel (Euler–Poincaré–d'Alembert) equations are

    M v' = ad*_v p + X(L) - D_g p[v] + F + A_all^T lam,     A_all v' + b = 0,

with p = dL/dv, M = d^2 L/dv^2, ad*_v p the coadjoint term of each part
(``AbstractSpace.coadjoint``: p x Omega for a body angular velocity, 0 for
Euclidean parts), X(L) the derivative of L along the group (d/de L(g exp(e), v)
at e = 0), D_g p[v] = d/ds p(g exp(s v), v) at s = 0, and A_all, b the
velocity- and acceleration-level forms of all constraints. Everything comes from
jax (grad, jvp) on L and the constraints; the multipliers from the KKT system.
For all-Euclidean configurations this is Lagrange–d'Alembert (see
``ConstrainedLagrangian``).

The state is the pytree y = (g, v) and ``spaces`` tells the RKMK solvers how g
moves, so rotations stay rotations.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.tree_util as jtu

from ..lie.spaces import Euclidean
from ._kkt import (
    REGULARITY_HINTS,
    kkt_accelerations,
    metric_projection,
    newton_project,
    regularity_margins,
)
from .system import AbstractSystem

__all__ = ["LieLagrangian"]


class LieLagrangian(AbstractSystem):
    """Abstract Lagrangian system on a product of Lie groups; see the module docstring.

    Subclasses set ``config_spaces`` (a tuple of spaces, one per part of g) and
    override ``lagrangian(g, v)`` and any of ``velocity_constraints(t, g, v)``,
    ``position_constraints(t, g)``, ``generalized_force(t, g, v, u)``.

    Conserved quantities: override ``invariants(y)`` (conserved for every input) or
    ``free_invariants(y)`` (without inputs), y = (g, v), returning name -> scalar;
    simulate() reports their values and drift as for the shipped scenes. Name them
    ``"name [unit]"`` (as ``Lagrangian(invariants=...)`` does) and ``summary()``
    shows the unit. The state is a pytree, so ``traj["name"]`` (flat states only)
    does not apply: read ``traj.xs`` = (g, v) by part.
    """

    regularity_hints = REGULARITY_HINTS
    large_vector_field = True

    @property
    def config_spaces(self) -> tuple:
        raise NotImplementedError

    # ----------------------------------------------------------- to override
    def lagrangian(self, g, v):
        raise NotImplementedError

    def velocity_constraints(self, t, g, v):
        return jnp.zeros((0,), v.dtype)

    def position_constraints(self, t, g):
        return jnp.zeros((0,), jtu.tree_leaves(g)[0].dtype)

    def generalized_force(self, t, g, v, u):
        return jnp.zeros_like(v)

    # ------------------------------------------------------------- geometry
    @property
    def spaces(self):
        return (tuple(self.config_spaces), Euclidean())

    def _sizes(self, g):
        return [
            sp.algebra_zeros(part).size
            for sp, part in zip(self.config_spaces, g)
        ]

    def split_velocity(self, g, v):
        """The flat velocity as a tuple of per-part algebra vectors."""
        out, i = [], 0
        for sp, part in zip(self.config_spaces, g):
            z = sp.algebra_zeros(part)
            out.append(v[i : i + z.size].reshape(z.shape))
            i += z.size
        return tuple(out)

    def retract(self, g, eps):
        """g . exp(eps), part by part (eps flat)."""
        return tuple(
            sp.retract(part, e) for sp, part, e in zip(self.config_spaces, g, self.split_velocity(g, eps))
        )

    def _move(self, g, eps):
        """g . (1 + eps): the retraction to first order. Every derivative the equations
        need is a first derivative at eps = 0 (or a mixed one of two such moves, where
        the product of two first-order moves has the same mixed term as exp), so this
        gives the same equations as ``retract`` with a much smaller graph to compile."""
        return tuple(
            part + sp.ambient(part, e)
            for sp, part, e in zip(self.config_spaces, g, self.split_velocity(g, eps))
        )

    def _coadjoint(self, g, v, p):
        terms = [
            sp.coadjoint(vi, pi).ravel()
            for sp, vi, pi in zip(self.config_spaces, self.split_velocity(g, v), self.split_velocity(g, p))
        ]
        return jnp.concatenate(terms)

    # ------------------------------------------------------------- dynamics
    def momentum(self, g, v):
        return jax.grad(self.lagrangian, argnums=1)(g, v)

    def mass_matrix(self, g, v=None):
        v = jnp.zeros(sum(self._sizes(g))) if v is None else v
        return jax.jacfwd(self.momentum, argnums=1)(g, v)

    def _all_velocity_constraints(self, t, g, v):
        c = jnp.atleast_1d(self.velocity_constraints(t, g, v))
        phi_dot = jax.jvp(
            lambda s: jnp.atleast_1d(self.position_constraints(t + s, self._move(g, s * v))),
            (jnp.zeros((), v.dtype),),
            (jnp.ones((), v.dtype),),
        )[1]
        return jnp.concatenate([c, phi_dot])

    def constraint_jacobian(self, t, g):
        n = sum(self._sizes(g))
        return jax.jacfwd(lambda w: self._all_velocity_constraints(t, g, w))(jnp.zeros(n))

    def _along_motion(self, fn, t, g, v):
        """d/ds fn(t + s, g . exp(s v), v) at s = 0."""
        return jax.jvp(
            lambda s: fn(t + s, self._move(g, s * v), v),
            (jnp.zeros((), v.dtype),),
            (jnp.ones((), v.dtype),),
        )[1]

    def dynamics_terms(self, t, g, v, u):
        M = self.mass_matrix(g, v)
        p = self.momentum(g, v)
        n = v.shape[0]
        XL = jax.grad(lambda e: self.lagrangian(self._move(g, e), v))(jnp.zeros(n))
        Dp = self._along_motion(lambda s, gg, vv: self.momentum(gg, vv), t, g, v)
        if u is None:
            u = jnp.zeros((self.control_dim,), v.dtype)
        rhs = self._coadjoint(g, v, p) + XL - Dp + self.generalized_force(t, g, v, u)
        A = self.constraint_jacobian(t, g)
        b = self._along_motion(self._all_velocity_constraints, t, g, v)
        return M, rhs, A, b

    def accelerations(self, t, g, v, u=None):
        """(v', lam): velocity rates and constraint multipliers (force A^T lam)."""
        return kkt_accelerations(*self.dynamics_terms(t, g, v, u))

    # --------------------------------------------------- AbstractSystem API
    def vector_field(self, t, y, u):
        g, v = y
        vd, _ = self.accelerations(t, g, v, u)
        return self.split_velocity(g, v), vd

    def constraints(self, t, y):
        g, v = y
        out = {}
        c = jnp.atleast_1d(self.velocity_constraints(t, g, v))
        if c.shape[0]:
            out["velocity"] = c
        phi = jnp.atleast_1d(self.position_constraints(t, g))
        if phi.shape[0]:
            out["position"] = phi
            out["position_rate"] = self._all_velocity_constraints(t, g, v)[c.shape[0] :]
        return out

    def regularity(self, t, y):
        g, _ = y
        return regularity_margins(self.mass_matrix(g), self.constraint_jacobian(t, g))

    def energy(self, y):
        """T + V = p.v - L (for L quadratic in v plus potential)."""
        g, v = y
        return self.momentum(g, v) @ v - self.lagrangian(g, v)

    def power(self, t, y, u):
        g, v = y
        return self.generalized_force(t, g, v, u) @ v

    def project(self, t, y):
        """Minimum-norm Newton on phi(g exp(e)) = 0 in the algebra, then the metric
        projection of v."""
        g, v = y
        n = v.shape[0]
        if jnp.atleast_1d(self.position_constraints(t, g)).shape[0]:
            phi = lambda e: jnp.atleast_1d(self.position_constraints(t, self.retract(g, e)))  # noqa: E731
            g = self.retract(g, newton_project(phi, jnp.zeros(n)))
        A = self.constraint_jacobian(t, g)
        if A.shape[0]:
            r = self._all_velocity_constraints(t, g, v)
            v = v + metric_projection(self.mass_matrix(g), A, r)
        return g, v

