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
"""

from __future__ import annotations

from collections.abc import Callable

import diffrax


class ProjectedSolver(diffrax.AbstractAdaptiveSolver, diffrax.AbstractWrappedSolver):
    """``solver`` followed by ``project(t, y, args)`` after every step."""

    solver: diffrax.AbstractSolver
    project: Callable

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
        y1, y_error, dense_info, solver_state, result = self.solver.step(
            terms, t0, t1, y0, args, solver_state, True
        )
        return self.project(t1, y1, args), y_error, dense_info, solver_state, result

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)
