"""Ready-made optimal-control tasks: the falling cat's somersault, the spherical robot's steering
and figure-eight tracking (for ``controls.MPC``), and the planar chain's reorientation and
thruster steering."""

from .planar_chain import (
    chain_reorientation,
    chain_steering,
    loop_guess as chain_loop_guess,
    loop_path as chain_loop_path,
    loop_turn as chain_loop_turn,
    radius_for_turn as chain_radius_for_turn,
)
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
from .tracking import FigureEight, TrackingCost, shell_push, sphere_tracking

__all__ = [
    "FigureEight",
    "TrackingCost",
    "shell_push",
    "sphere_tracking",
    "FreeWindingResult",
    "chain_loop_guess",
    "chain_loop_path",
    "chain_loop_turn",
    "chain_radius_for_turn",
    "chain_reorientation",
    "chain_steering",
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
