"""Integration: simulate(), Lie-group solvers, trajectories and their diagnostics."""

from .rkmk import LieODETerm, RKMK4, RKMK45
from .signals import PiecewiseConstant, PiecewiseLinear, Sinusoids
from .simulate import Trajectory, simulate

__all__ = [
    "LieODETerm",
    "PiecewiseConstant",
    "PiecewiseLinear",
    "RKMK4",
    "RKMK45",
    "Sinusoids",
    "Trajectory",
    "simulate",
]
