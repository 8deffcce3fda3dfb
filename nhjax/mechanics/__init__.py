"""Mechanics: the system interface, constrained Lagrangians by autodiff, rigid bodies."""

from .impacts import WithContacts, affine_projector, contact_dynamics, impact_velocities
from .lagrangian import ConstrainedLagrangian, Lagrangian
from .lie_lagrangian import LieLagrangian
from .rigid import MultibodyKinetics, RigidBody, body_angular_velocity, cylinder_inertia
from .system import AbstractSystem

__all__ = [
    "AbstractSystem",
    "ConstrainedLagrangian",
    "Lagrangian",
    "LieLagrangian",
    "MultibodyKinetics",
    "RigidBody",
    "WithContacts",
    "affine_projector",
    "body_angular_velocity",
    "contact_dynamics",
    "cylinder_inertia",
    "impact_velocities",
]
