"""Rigid bodies: inertia, kinetic energy and momenta from attitudes and positions.

A body's pose is (R, r): R in SO(3) maps body-frame vectors to space, r is the
position of its centre of mass. From (R, R', r, r'):

    body angular velocity   Omega = vee(R^T R')
    kinetic energy          T = m |r'|^2 / 2 + Omega . I Omega / 2
    angular momentum        L = m r x r' + R I Omega          (about the origin)

``MultibodyKinetics`` turns a pose map q -> [(R_i, r_i)] into T(q, q') and the
total momenta by forward-mode differentiation of the poses, so scenes written
as "bodies placed by coordinates" get their Lagrangian without hand algebra.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _args as Vd
from ..lie import so3

__all__ = [
    "MultibodyKinetics",
    "RigidBody",
    "body_angular_velocity",
    "cylinder_inertia",
]


def cylinder_inertia(mass, length, radius):
    """(I_transverse, I_axial) of a solid circular cylinder about its centre of mass.

    I_transverse = m (3 r^2 + L^2) / 12,  I_axial = m r^2 / 2   [kg m^2].
    """
    mass = Vd.positive("mass", mass, owner="cylinder_inertia", what="[kg]")
    length = Vd.positive("length", length, owner="cylinder_inertia", what="[m]")
    radius = Vd.positive("radius", radius, owner="cylinder_inertia", what="[m]")
    return mass * (3 * radius**2 + length**2) / 12.0, mass * radius**2 / 2.0


class RigidBody(eqx.Module):
    """Mass [kg] and inertia tensor [kg m^2] about the centre of mass, body frame."""

    mass: jax.Array
    inertia: jax.Array

    def __check_init__(self):
        if Vd.is_traced(self.mass, self.inertia):
            return
        Vd.positive("mass", self.mass, owner="RigidBody", what="[kg]")
        if jnp.shape(self.inertia)[-2:] != (3, 3):
            raise Vd.ParameterError(f"RigidBody: inertia must be a 3x3 tensor [kg m^2], got shape "
                                    f"{jnp.shape(self.inertia)}", "inertia", self.inertia)
        Vd.inertias("inertia", self.inertia, owner="RigidBody")

    @classmethod
    def solid_cylinder(cls, mass, length, radius, axis: int = 1):
        """Solid cylinder with its symmetry axis along body axis ``axis``."""
        axis = Vd.choice("axis", axis, (0, 1, 2), owner="RigidBody.solid_cylinder")
        it, ia = cylinder_inertia(mass, length, radius)
        diag = jnp.full((3,), it).at[axis].set(ia)
        return cls(jnp.asarray(mass, float), jnp.diag(diag))

    def kinetic_energy(self, R, Rd, r, rd):
        W = body_angular_velocity(R, Rd)
        return 0.5 * self.mass * jnp.dot(rd, rd) + 0.5 * W @ self.inertia @ W

    def angular_momentum(self, R, Rd, r, rd):
        """About the space origin."""
        W = body_angular_velocity(R, Rd)
        return self.mass * jnp.cross(r, rd) + R @ (self.inertia @ W)

    def linear_momentum(self, rd):
        return self.mass * rd


def body_angular_velocity(R, Rd):
    """Omega with R' = R hat(Omega)."""
    return so3.vee(R.T @ Rd)


class MultibodyKinetics(eqx.Module):
    """Kinetic energy and momenta of bodies placed by a pose map q -> (Rs, rs).

    ``poses(q)`` returns Rs with shape (k, 3, 3) and rs with shape (k, 3).
    """

    bodies: tuple[RigidBody, ...]
    poses: Callable

    def __check_init__(self):
        if not all(isinstance(b, RigidBody) for b in self.bodies):
            raise Vd.ParameterError("MultibodyKinetics: bodies must be a tuple of nhjax.mechanics.RigidBody",
                                    "bodies", self.bodies)
        Vd.function("poses", self.poses, owner="MultibodyKinetics", signature="poses(q) -> (Rs (k,3,3), rs (k,3))")

    def _poses_and_rates(self, q, qd):
        (Rs, rs), (Rds, rds) = jax.jvp(self.poses, (q,), (qd,))
        return Rs, rs, Rds, rds

    def kinetic_energy(self, q, qd):
        Rs, rs, Rds, rds = self._poses_and_rates(q, qd)
        return sum(
            b.kinetic_energy(Rs[i], Rds[i], rs[i], rds[i]) for i, b in enumerate(self.bodies)
        )

    def angular_momentum(self, q, qd):
        Rs, rs, Rds, rds = self._poses_and_rates(q, qd)
        return sum(
            b.angular_momentum(Rs[i], Rds[i], rs[i], rds[i]) for i, b in enumerate(self.bodies)
        )

    def linear_momentum(self, q, qd):
        _, _, _, rds = self._poses_and_rates(q, qd)
        return sum(b.linear_momentum(rds[i]) for i, b in enumerate(self.bodies))
