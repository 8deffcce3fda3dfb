"""Optimal control on nhjax systems: direct (optax through differentiable
simulations, single or multiple shooting, augmented Lagrangian) and indirect
(Pontryagin, costate shooting by Newton or Levenberg–Marquardt), SQP for single shooting (the
default of solve_direct: damped-BFGS Hessians, exact constraint Jacobians,
control bounds in its QP), a feasible-path Newton direct solver for small
strongly-curved problems, with a residual check of the
optimality conditions that applies to any solution, and grids of problems of one
structure solved in one program (``solve_pontryagin_batch``, ``solve_direct_batch``), and closed-loop
model-predictive control (``MPC``, ``closed_loop``, ``closed_loop_batch``)."""

from .batch import (
    BatchResult,
    DirectBatchResult,
    GridError,
    solve_direct_batch,
    solve_pontryagin_batch,
    stack_members,
)
from .direct import DirectResult, solve_direct
from .mpc import MPC, ClosedLoop, MPCError, MPCStatus, Plan, box_qp, closed_loop, closed_loop_batch
from .newton import solve_direct_newton
from .parametrize import Chebyshev, CubicSpline, Fourier, PiecewiseConstant, PiecewiseLinear
from .sqp import prepare_direct_sqp, solve_direct_sqp
from .pontryagin import (
    HamiltonianSystem,
    IndirectResult,
    continuation,
    pmp_residual,
    prepare_pmp_residual,
    prepare_pontryagin,
    solve_pontryagin,
)
from .problem import OCP, ProblemError, rollout

__all__ = [
    "BatchResult",
    "Chebyshev",
    "ClosedLoop",
    "CubicSpline",
    "DirectBatchResult",
    "DirectResult",
    "Fourier",
    "GridError",
    "HamiltonianSystem",
    "IndirectResult",
    "MPC",
    "MPCError",
    "MPCStatus",
    "OCP",
    "PiecewiseConstant",
    "PiecewiseLinear",
    "Plan",
    "ProblemError",
    "box_qp",
    "closed_loop",
    "closed_loop_batch",
    "continuation",
    "pmp_residual",
    "prepare_direct_sqp",
    "prepare_pmp_residual",
    "prepare_pontryagin",
    "rollout",
    "solve_direct",
    "solve_direct_batch",
    "solve_direct_newton",
    "solve_direct_sqp",
    "solve_pontryagin",
    "solve_pontryagin_batch",
    "stack_members",
]
