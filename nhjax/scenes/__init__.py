"""Shipped scenes. Each module models only what its scene needs and documents
its parameters, units and the seed equations it implements."""

from .falling_cat import (
    FallingCat,
    FallingCatAttitudes,
    FallingCatKinematic,
    FallingCatLagrangian,
    ShapeLoopTorque,
)
from .shell_suslov_hinge import ShellWithSuslovHinge, ShellWithSuslovHingeZeroMomentum
from .shell_with_top import ShellWithTopLagrangian, ShellWithTopReduced
from .spherical_robot import ShellWithTop
from .suslov_bundle import SuslovBundle

# name -> (class, one-line description); used by `nhjax list`.
REGISTRY = {
    "FallingCat": (FallingCat, "Iwai's jointed cylinders, torque driven, zero angular momentum (seed 000, 7.14-7.15)"),
    "FallingCatKinematic": (FallingCatKinematic, "the same cat under velocity control (seed 000, 7.1)"),
    "FallingCatAttitudes": (FallingCatAttitudes, "the torque-driven cat with both attitudes on SO(3) (RKMK)"),
    "FallingCatLagrangian": (FallingCatLagrangian, "the cat derived by the engine from two rigid bodies"),
    "ShellWithTop": (ShellWithTop, "the spherical robot: shell rolling on a plane, top inside, internal torque; on SO(3) x SO(3) (seed 003, sec. 1)"),
    "ShellWithTopReduced": (ShellWithTopReduced, "the same without torque: reduced system (1.11) + reconstruction (seed 003, sec. 1)"),
    "ShellWithTopLagrangian": (ShellWithTopLagrangian, "the same derived by the engine in rotation-vector coordinates, with internal torque"),
    "ShellWithSuslovHinge": (ShellWithSuslovHinge, "shell with an inner body on a nonholonomic hinge, (2.4) (seed 003, sec. 2)"),
    "ShellWithSuslovHingeZeroMomentum": (ShellWithSuslovHingeZeroMomentum, "its zero-momentum system (2.9)"),
    "SuslovBundle": (SuslovBundle, "free two-body bundle on a nonholonomic hinge, generalized Suslov problem (3.3)/(3.5) (seed 003, sec. 3)"),
}

__all__ = [
    "FallingCat",
    "FallingCatAttitudes",
    "FallingCatKinematic",
    "FallingCatLagrangian",
    "REGISTRY",
    "ShapeLoopTorque",
    "ShellWithSuslovHinge",
    "ShellWithSuslovHingeZeroMomentum",
    "ShellWithTop",
    "ShellWithTopLagrangian",
    "ShellWithTopReduced",
    "SuslovBundle",
]
