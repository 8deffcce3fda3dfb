"""Projection after every step: keep states on their constraint manifold.

``ProjectedSolver`` wraps any diffrax solver: each step is taken by the wrapped
solver, then the new state is mapped back onto the constraint manifold by the
system's ``project`` (Newton/Gauss–Newton on the position constraints with
optimistix, then the kinetic-metric projection of the velocities). This is the
projection alternative to Rabier & Rheinboldt's local parametrizations (seed
002, DAENH): it does not change the order of the method (the projection moves
the state by the size of the local error) and it removes the drift that an
index-reduced formulation accumulates over long runs.

FSAL solvers are restarted every step (their stored last stage belongs to the
unprojected state), which costs one vector-field evaluation per step.

Split projection (``entry`` given, an RKMK solver with its stages in a scan): the
step ends with ``project_positions`` only, and the velocities are projected by the
next step's first stage, ``entry(t, y, args, True) -> (y', f(t, y'))``, which
evaluates the kinetic metric and the constraint Jacobian at the projected positions
anyway: the projection then costs no second evaluation of them, in the program
or per step. The states a step starts from are the same as with ``project`` after
the step; the state it ends with has its velocities projected only when the next
step starts (the solve projects its saved and final states itself).
"""

from __future__ import annotations

from collections.abc import Callable

import diffrax


class ProjectedSolver(diffrax.AbstractAdaptiveSolver, diffrax.AbstractWrappedSolver):
    """``solver`` followed by ``project(t, y, args)`` after every step; or, with
    ``entry`` and ``project_positions`` and a solver that can take them (see the
    module docstring), ``project_positions`` after the step and ``entry`` at the
    next step's first stage."""

    solver: diffrax.AbstractSolver
    project: Callable
    entry: Callable | None = None
    project_positions: Callable | None = None

    def splits(self, terms) -> bool:
        """Whether steps on ``terms`` take the split projection."""
        return (self.entry is not None and hasattr(self.solver, "step_with_entry")
                and self.solver.can_enter(terms))

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        if self.splits(terms):
            y1, y_error, dense_info, solver_state, result = self.solver.step_with_entry(
                terms, t0, t1, y0, args, solver_state, self.entry)
            return self.project_positions(t1, y1, args), y_error, dense_info, solver_state, result
        y1, y_error, dense_info, solver_state, result = self.solver.step(
            terms, t0, t1, y0, args, solver_state, True
        )
        return self.project(t1, y1, args), y_error, dense_info, solver_state, result

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)
