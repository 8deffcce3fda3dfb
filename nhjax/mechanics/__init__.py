"""Mechanics: the system interface, constrained Lagrangians by autodiff, rigid bodies,
reduction by symmetry (``reduction``)."""

from .impacts import WithContacts, affine_projector, contact_dynamics, impact_velocities
from .lagrangian import ConstrainedLagrangian, Lagrangian
from .lie_lagrangian import LieLagrangian
from . import reduction
from .reduction import Bodies, ReducedKinematic, ReducedSystem, curvature_integral
from .rigid import MultibodyKinetics, RigidBody, body_angular_velocity, cylinder_inertia
from .system import AbstractSystem

__all__ = [
    "AbstractSystem",
    "Bodies",
    "ConstrainedLagrangian",
    "Lagrangian",
    "LieLagrangian",
    "MultibodyKinetics",
    "ReducedKinematic",
    "ReducedSystem",
    "RigidBody",
    "WithContacts",
    "affine_projector",
    "body_angular_velocity",
    "contact_dynamics",
    "curvature_integral",
    "cylinder_inertia",
    "impact_velocities",
    "reduction",
]
