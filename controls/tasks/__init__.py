"""Ready-made optimal-control tasks: the falling cat's somersault and the spherical robot's steering."""

from .somersault import (
    fixed_theta_costates,
    torque_somersault,
    velocity_somersault_chart,
    velocity_somersault_smooth,
)

__all__ = [
    "fixed_theta_costates",
    "torque_somersault",
    "velocity_somersault_chart",
    "velocity_somersault_smooth",
]
