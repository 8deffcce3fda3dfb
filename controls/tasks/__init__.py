"""Ready-made optimal-control tasks: the falling cat's somersault and the spherical robot's steering."""

from .somersault import (
    FreeWindingResult,
    fixed_theta_costates,
    loop_guess,
    smooth_to_chart,
    somersault_free_winding,
    torque_loop_guess,
    torque_somersault,
    velocity_somersault_chart,
    velocity_somersault_smooth,
)

__all__ = [
    "FreeWindingResult",
    "fixed_theta_costates",
    "loop_guess",
    "smooth_to_chart",
    "somersault_free_winding",
    "torque_loop_guess",
    "torque_somersault",
    "velocity_somersault_chart",
    "velocity_somersault_smooth",
]
