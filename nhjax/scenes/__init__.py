"""Shipped scenes. Each module models only what its scene needs and documents
its parameters, units and the seed equations it implements."""

from .falling_cat import (
    FallingCat,
    FallingCatAttitudes,
    FallingCatKinematic,
    FallingCatLagrangian,
    FallingCatSmooth,
    ShapeLoopTorque,
)
from .ball_in_cone import BallInCone
from .ball_in_cone_euler import BallInConeEuler
from .ball_on_platter import BallOnPlatter
from .bouncing_ball import BouncingBall
from .falling_cat_reduced import FallingCatReduced
from .moving_circle import ParticleInMovingCircle
from .nbody import NBodyCat, ThreeBodyCat
from .planar_chain import PlanarChain, PlanarChainUnreduced
from .roll_ring import RollRing
from .rolling_disk import RollingDisk, RollingDiskQuaternion
from .shell_suslov_hinge import ShellWithSuslovHinge, ShellWithSuslovHingeZeroMomentum
from .shell_with_top import ShellWithTopLagrangian, ShellWithTopReduced
from .spherical_robot import ShellWithTop
from .sphere_wall import RollingSphereWall
from .skate import Skate, SkateSE2
from .suslov_bundle import SuslovBundle
from .three_cylinders import ThreeCylinders, ThreeCylindersMinimal
from .two_wheeled_cart import TwoWheeledCart

# name -> (class, one-line description); used by `nhjax list`.
REGISTRY = {
    "FallingCat": (FallingCat, "Iwai's jointed cylinders, torque driven, zero angular momentum (seed 000, 7.14-7.15)"),
    "FallingCatKinematic": (FallingCatKinematic, "the same cat under velocity control (seed 000, 7.1)"),
    "FallingCatAttitudes": (FallingCatAttitudes, "the torque-driven cat with both attitudes on SO(3) (RKMK)"),
    "FallingCatLagrangian": (FallingCatLagrangian, "the cat derived by the engine from two rigid bodies"),
    "FallingCatSmooth": (FallingCatSmooth, "velocity-controlled cat in coordinates smooth at the straight cat (w, phi)"),
    "FallingCatReduced": (FallingCatReduced, "the cat rebuilt by the general reduction (two rigid bodies, SO(2) about e2, by autodiff)"),
    "NBodyCat": (NBodyCat, "n point masses at zero angular momentum, SO(3) reduction by autodiff from a shape map (default: three bodies, Jacobi section) (seed 000, 3.9-4.7)"),
    "ThreeBodyCat": (ThreeBodyCat, "three point masses, Jacobi vectors and shape coordinates (2.6)-(2.7), zero angular momentum (seed 000)"),
    "PlanarChain": (PlanarChain, "N hinged rigid bodies in the plane, joint torques and thrusters, SE(2) reduction (seed 001, (9a)-(12))"),
    "PlanarChainUnreduced": (PlanarChainUnreduced, "the same chain as N bodies in R^3N with hinge constraints (engine check)"),
    "Skate": (Skate, "knife-edge skate on an inclined plane, DAE in R^6 with closed-form motions (seed 002, 9.1-9.3)"),
    "SkateSE2": (SkateSE2, "the same skate on SE(2) (Hamel equations, RKMK)"),
    "BallOnPlatter": (BallOnPlatter, "homogeneous ball on a rotating platter in R^3 x S^3, exact circular path (seed 002, 9.14-9.19)"),
    "BallInCone": (BallInCone, "homogeneous ball rolling inside a cone in R^3 x S^3, three integrals, returns to the same height (seed 002, 9.20-9.29)"),
    "RollRing": (RollRing, "roll-ring transmission: ring body driven along a shaft (nonholonomic), shock absorber on a spring-damper, double pendulum (seed 002, 9.8-9.13)"),
    "ThreeCylinders": (ThreeCylinders, "three cylinders in mutual rolling contact, three rigid bodies in (u, p) in R^3 x S^3, 19 constraints (seed 002, 9.33-9.36)"),
    "ThreeCylindersMinimal": (ThreeCylindersMinimal, "the same in the seed's coordinates (x1, x2, theta, phi, psi1, psi2), four no-slip conditions (seed 002, 9.30-9.31)"),
    "RollingDisk": (RollingDisk, "sharp-edged rolling disk in minimal coordinates, tilt guard, circular motions (seed 002, 9.37-9.44)"),
    "RollingDiskQuaternion": (RollingDiskQuaternion, "the same disk as a rigid body in (u, p) in R^3 x S^3 (seed 002, 9.39-9.40)"),
    "TwoWheeledCart": (TwoWheeledCart, "two-wheeled cart on an inclined plane, closed-form motion and cusps (seed 002, 9.45-9.52)"),
    "ShellWithTop": (ShellWithTop, "the spherical robot: shell rolling on a plane, top inside, internal torque; on SO(3) x SO(3) (seed 003, sec. 1)"),
    "ShellWithTopReduced": (ShellWithTopReduced, "the same without torque: reduced system (1.11) + reconstruction (seed 003, sec. 1)"),
    "ShellWithTopLagrangian": (ShellWithTopLagrangian, "the same derived by the engine in rotation-vector coordinates, with internal torque"),
    "ShellWithSuslovHinge": (ShellWithSuslovHinge, "shell with an inner body on a nonholonomic hinge, (2.4) (seed 003, sec. 2)"),
    "ShellWithSuslovHingeZeroMomentum": (ShellWithSuslovHingeZeroMomentum, "its zero-momentum system (2.9)"),
    "SuslovBundle": (SuslovBundle, "free two-body bundle on a nonholonomic hinge, generalized Suslov problem (3.3)/(3.5) (seed 003, sec. 3)"),
    "ParticleInMovingCircle": (ParticleInMovingCircle, "free particle inside a moving circular wall, impacts by the affine projector (seed 004, ex. 10.1)"),
    "BouncingBall": (BouncingBall, "ball bouncing on a vibrating table under gravity, exact impacts and the high-bounce map (seed 004, ex. 10.2)"),
    "RollingSphereWall": (RollingSphereWall, "sphere rolling without slipping hits a moving smooth wall, jump keeps rolling (seed 004, ex. 10.3)"),
}

__all__ = [
    "BallInCone",
    "BallInConeEuler",
    "BallOnPlatter",
    "BouncingBall",
    "FallingCat",
    "FallingCatAttitudes",
    "FallingCatKinematic",
    "FallingCatLagrangian",
    "FallingCatReduced",
    "FallingCatSmooth",
    "NBodyCat",
    "ParticleInMovingCircle",
    "PlanarChain",
    "PlanarChainUnreduced",
    "REGISTRY",
    "RollRing",
    "RollingSphereWall",
    "RollingDisk",
    "RollingDiskQuaternion",
    "ShapeLoopTorque",
    "ShellWithSuslovHinge",
    "ShellWithSuslovHingeZeroMomentum",
    "ShellWithTop",
    "ShellWithTopLagrangian",
    "ShellWithTopReduced",
    "Skate",
    "SkateSE2",
    "SuslovBundle",
    "ThreeBodyCat",
    "ThreeCylinders",
    "ThreeCylindersMinimal",
    "TwoWheeledCart",
]
