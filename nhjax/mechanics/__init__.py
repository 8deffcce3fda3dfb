"""Mechanics: the system interface, constrained Lagrangians by autodiff, rigid bodies."""

from .lagrangian import ConstrainedLagrangian, Lagrangian
from .rigid import MultibodyKinetics, RigidBody, body_angular_velocity, cylinder_inertia
from .system import AbstractSystem

__all__ = [
    "AbstractSystem",
    "ConstrainedLagrangian",
    "Lagrangian",
    "MultibodyKinetics",
    "RigidBody",
    "body_angular_velocity",
    "cylinder_inertia",
]
