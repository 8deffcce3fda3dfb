"""Integration: simulate(), Lie-group solvers, trajectories and their diagnostics."""

from .adjoint import DiscreteAdjoint
from .batch import BatchError, BatchTrajectory, simulate_batch, stack
from .impacts import ImpactBatchTrajectory, ImpactTrajectory, simulate_impacts, simulate_impacts_batch, solve_impacts
from .rkmk import LieODETerm, RKMK4, RKMK45, RKMK87
from .signals import PiecewiseConstant, PiecewiseLinear, Sinusoids
from .simulate import Trajectory, simulate

__all__ = [
    "BatchError",
    "BatchTrajectory",
    "DiscreteAdjoint",
    "ImpactBatchTrajectory",
    "ImpactTrajectory",
    "LieODETerm",
    "PiecewiseConstant",
    "PiecewiseLinear",
    "RKMK4",
    "RKMK45",
    "RKMK87",
    "Sinusoids",
    "Trajectory",
    "simulate",
    "simulate_batch",
    "simulate_impacts",
    "simulate_impacts_batch",
    "solve_impacts",
    "stack",
]
