"""Exceptions raised by nhjax. Each names what went wrong, where, and the fix."""

from __future__ import annotations


class NhjaxError(Exception):
    """Base class of every error nhjax raises on purpose."""


class ConstraintViolationError(NhjaxError, ValueError):
    """An initial condition violates a constraint beyond the tolerance.

    Attributes: ``name`` (the constraint), ``residual`` (its max-abs value),
    ``tol``.
    """

    def __init__(self, name: str, residual: float, tol: float, hint: str = ""):
        self.name, self.residual, self.tol = name, float(residual), float(tol)
        msg = (
            f"initial state violates constraint '{name}': |residual| = {residual:.3e} "
            f"> tol = {tol:.1e}. Pass project=True to simulate() to project it onto "
            "the constraint manifold, or fix the initial state"
        )
        super().__init__(msg + (f" ({hint})." if hint else "."))


class IntegrationError(NhjaxError, RuntimeError):
    """The integrator could not reach t1: max_steps exhausted, NaN/inf, step collapse.

    Attributes: ``t`` (the last time reached), ``reason``, ``trajectory`` (what
    was computed up to ``t``, if available).
    """

    def __init__(self, reason: str, t: float, detail: str = "", trajectory=None):
        self.reason, self.t, self.trajectory = reason, float(t), trajectory
        super().__init__(f"{reason} at t = {t:.10g}" + (f": {detail}" if detail else ""))


class ChartSingularityError(IntegrationError):
    """The state reached the edge of the coordinate chart a scene is written in.

    Attributes as IntegrationError plus ``guard`` (the name of the chart guard
    that crossed zero). ``trajectory`` holds the motion up to that time.
    """

    def __init__(self, guard: str, t: float, detail: str = "", trajectory=None):
        self.guard = guard
        super().__init__(
            f"chart singularity ('{guard}' reached its limit)", t, detail, trajectory
        )


class RegularityError(NhjaxError, ValueError):
    """The equations of motion are ill posed at the initial state (e.g. dependent
    constraints, or a kinetic energy degenerate on the admissible velocities).

    Attributes: ``condition`` (its name), ``margin`` (the failed relative margin).
    """

    def __init__(self, condition: str, margin: float, hint: str = ""):
        self.condition, self.margin = condition, float(margin)
        super().__init__(
            f"the initial state violates the regularity condition '{condition}' "
            f"(relative margin {margin:.2e} <= 0)" + (f": {hint}" if hint else "")
        )
