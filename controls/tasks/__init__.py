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
from .steering import (
    ReducedSteering,
    ReducedSteeringTarget,
    SteeringTarget,
    hanging_attitude,
    linear_guess,
    rolling_residual,
    simulate_with_impulse,
    solve_direct_newton,
    sphere_steering,
    sphere_steering_reduced,
    top_heading,
)

__all__ = [
    "FreeWindingResult",
    "ReducedSteering",
    "ReducedSteeringTarget",
    "SteeringTarget",
    "fixed_theta_costates",
    "hanging_attitude",
    "linear_guess",
    "loop_guess",
    "rolling_residual",
    "simulate_with_impulse",
    "smooth_to_chart",
    "solve_direct_newton",
    "somersault_free_winding",
    "sphere_steering",
    "sphere_steering_reduced",
    "top_heading",
    "torque_loop_guess",
    "torque_somersault",
    "velocity_somersault_chart",
    "velocity_somersault_smooth",
]
