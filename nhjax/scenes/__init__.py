"""Shipped scenes. Each module models only what its scene needs and documents
its parameters, units and the seed equations it implements."""

from .falling_cat import (
    FallingCat,
    FallingCatAttitudes,
    FallingCatKinematic,
    FallingCatLagrangian,
    ShapeLoopTorque,
)

# name -> (class, one-line description); used by `nhjax list`.
REGISTRY = {
    "FallingCat": (FallingCat, "Iwai's jointed cylinders, torque driven, zero angular momentum (seed 000, 7.14-7.15)"),
    "FallingCatKinematic": (FallingCatKinematic, "the same cat under velocity control (seed 000, 7.1)"),
    "FallingCatAttitudes": (FallingCatAttitudes, "the torque-driven cat with both attitudes on SO(3) (RKMK)"),
    "FallingCatLagrangian": (FallingCatLagrangian, "the cat derived by the engine from two rigid bodies"),
}

__all__ = [
    "FallingCat",
    "FallingCatAttitudes",
    "FallingCatKinematic",
    "FallingCatLagrangian",
    "REGISTRY",
    "ShapeLoopTorque",
]
