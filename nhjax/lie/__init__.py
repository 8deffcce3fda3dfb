"""Lie groups used by nhjax: SO(3) (with unit quaternions), SE(2), and the state
spaces that tell the Lie-group integrators how each part of a state moves."""

from . import se2, so3
from .spaces import (
    AbstractSpace,
    Euclidean,
    SE2Body,
    SO3Body,
    SO3Spatial,
    UnitQuaternionBody,
)

__all__ = [
    "AbstractSpace",
    "Euclidean",
    "SE2Body",
    "SO3Body",
    "SO3Spatial",
    "UnitQuaternionBody",
    "se2",
    "so3",
]
