"""What the direct solvers return, and their shared check of the initial guess.

``solve_direct`` (augmented Lagrangian), ``solve_direct_newton`` and
``solve_direct_sqp`` return the same ``DirectResult`` and refuse a problem whose cost
and constraints have no usable derivative at the guess the same way; both live here,
below the three solvers, so that none of them imports another for them.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from .problem import ProblemError

__all__ = ["DirectResult", "check_differentiable"]


@dataclasses.dataclass
class DirectResult:
    """Outcome of ``solve_direct`` (and ``solve_direct_newton``).

    params : (P,) the optimal control parameters of the parametrization.
    control : ``param.signal(params)``, callable as u(t, x) [the system's input units].
    cost : Phi(x(T)) + int_0^T L dt at ``params``, simulated at the solve's rtol/atol
        [the cost's units].
    violation : max |c| over the terminal constraints psi(x(T)) (and, for multiple
        shooting, the continuity defects of the segments) [the constraints' units].
    multipliers : (m,) the constraint multipliers lam of the augmented Lagrangian
        (dJ + lam . dc = 0 at a solution; for multiple shooting the first m belong to
        psi).
    iterations : inner (L-BFGS/optax) steps taken in all (Newton iterations for
        ``solve_direct_newton``).
    converged : True when the violation is below ``ctol`` and the cost changed by less
        than ``ftol`` (relative) over the last outer iteration (``solve_direct``), or the
        violation is below ``ctol`` and the relative stationarity below ``gtol``
        (``solve_direct_newton``). False: see ``message``.
    message : why the solve stopped.
    history : per-step records (merit, grad_norm, outer; per outer iteration cost and
        violation).
    seconds : wall time of the call (compilation included on a first call) [s].
    node_states : (S - 1, n) the states at the interior segment starts (multiple
        shooting), else None.
    """

    params: jax.Array
    control: object
    cost: float
    violation: float
    multipliers: np.ndarray
    iterations: int
    converged: bool
    message: str
    history: dict
    seconds: float
    node_states: object = None


def check_differentiable(jac):
    """ProblemError unless the Jacobian ``jac`` of (cost, constraints) in the control
    parameters at the initial guess is finite and not identically zero."""
    if not np.all(np.isfinite(jac)):
        raise ProblemError(
            "the cost or the terminal constraints have a non-finite derivative at the initial "
            "guess: use differentiable (smooth) cost and constraint functions"
        )
    if float(np.max(np.abs(jac))) == 0.0:
        raise ProblemError(
            "neither the cost nor the constraints depend on the control parameters (zero "
            "gradient): they are constant, or not differentiable where it matters (e.g. "
            "built from rounding or comparisons)"
        )
