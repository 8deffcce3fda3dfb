"""Exceptions raised by nhjax. Each names what went wrong, where, and the fix.

Every class derives from ``NhjaxError`` and from the built-in exception a caller
would expect (``ValueError`` for bad values, ``TypeError`` for bad kinds,
``RuntimeError`` for failed solves, ``MemoryError`` for oversized requests), so
that existing ``except ValueError`` clauses keep working.

Bad input (checked by ``nhjax._validate`` before any tracing where the values
are concrete; inside jit/vmap/grad the same checks are ``equinox`` runtime
errors with the same words, without the values):

* ``ParameterError``: a physical or numerical parameter out of its range
  (``mass must be positive, got 0``), named by the argument the user passed;
* ``StateError``: an initial state of the wrong structure, shape or length, or
  with NaN/inf; ``GroupMembershipError``: a group-valued part (rotation,
  unit quaternion, SE(2) pose) off its group beyond the tolerance;
* ``ConstraintViolationError``: an initial state off its constraint manifold;
  ``ProjectionError``: ``project=True`` could not bring it onto the manifold;
* ``OutsideChartError``: a start outside the coordinate chart a scene is written in,
  wherever it is found (a scene's ``initial_state``, ``simulate``, a batch, an
  optimal-control problem); it is a ``ChartSingularityError`` too, the error a solve
  raises when the motion reaches the chart's edge later;
* ``BoundaryError``: a moving boundary (a wall, a circle) that degenerates within the
  time span (a circle's radius reaching 0);
* ``ControlError``: a control missing, not callable, of the wrong shape or NaN;
* ``SystemKindError``: a system or solver of a kind the path does not take (impacts on
  a system without one-sided constraints, a solver that would leave the group);
* ``TimeSpanError``: t0, t1 or the saved times empty, reversed or not finite;
* ``ResourceError``: a request whose memory would exceed what is available;
* ``ProblemError``: an optimal-control problem that cannot be posed or solved as
  given (``controls``).
"""

from __future__ import annotations

__all__ = [
    "BoundaryError",
    "ChartSingularityError",
    "ConstraintViolationError",
    "ControlError",
    "GroupMembershipError",
    "IntegrationError",
    "NhjaxError",
    "OutsideChartError",
    "ParameterError",
    "ProblemError",
    "ProjectionError",
    "RegularityError",
    "ResourceError",
    "StateError",
    "SystemKindError",
    "TimeSpanError",
]


class NhjaxError(Exception):
    """Base class of every error nhjax raises on purpose."""


class ParameterError(NhjaxError, ValueError):
    """A parameter is out of its range (sign, finiteness, shape, allowed values).

    Attributes: ``name`` (the argument as the user passed it), ``value``, ``names``
    (every argument the failed condition relates, for a relation between several, e.g.
    a ball's moment of inertia and its mass and radius: ("J", "m", "r"); else (name,)).
    """

    def __init__(self, message: str, name: str = "", value=None, names=None):
        self.name, self.value = name, value
        self.names = tuple(names) if names else (name,)
        super().__init__(message)


class StateError(NhjaxError, ValueError):
    """An initial state does not fit the system: wrong structure, shape, length, or NaN/inf.

    Attributes: ``name`` (the argument, e.g. ``"x0"`` or ``"x0[0][1]"``).
    """

    def __init__(self, message: str, name: str = "x0"):
        self.name = name
        super().__init__(message)


class GroupMembershipError(StateError):
    """A group-valued part of a state (rotation matrix, unit quaternion, SE(2) pose)
    is off its group by more than the tolerance.

    Attributes: ``name`` (the part, e.g. ``"x0[0][1]"``), ``residual``, ``tol``.
    """

    def __init__(self, message: str, name: str, residual: float, tol: float):
        self.residual, self.tol = float(residual), float(tol)
        super().__init__(message, name)


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


class ProjectionError(NhjaxError, ValueError):
    """``project=True`` did not bring the state onto its constraint manifold (or group)
    within the iteration bound.

    Attributes: ``name`` (the constraint or state part), ``residual`` (reached),
    ``tol``, ``iterations``.
    """

    def __init__(self, name: str, residual: float, tol: float, iterations: int, hint: str = ""):
        self.name, self.residual, self.tol = name, float(residual), float(tol)
        self.iterations = int(iterations)
        msg = (
            f"projecting the initial state onto the constraint manifold did not converge: "
            f"after {iterations} projections constraint '{name}' still has |residual| = "
            f"{residual:.3e} > tol = {tol:.1e}. The state is too far from the manifold for the "
            "Newton projection (or the constraints are singular there): start from a state "
            "closer to it, e.g. one built by the scene's initial_state()"
        )
        super().__init__(msg + (f" ({hint})." if hint else "."))


class ControlError(NhjaxError, ValueError, TypeError):
    """A control is missing where the system needs one, given where it takes none, not
    callable, of the wrong shape, or not finite."""


class SystemKindError(NhjaxError, TypeError):
    """A system or solver of a kind the called path does not take: ``simulate_impacts``
    (and its batch) on a system that declares no one-sided constraints or is not a
    ``ConstrainedLagrangian``; a solver that is not a Lie-group one on group-valued
    states; ``DiscreteAdjoint`` with an implicit solver. A ``TypeError`` too."""


class TimeSpanError(NhjaxError, ValueError):
    """t0, t1 or the saved times are not finite, reversed, empty or out of order."""


class ResourceError(NhjaxError, MemoryError):
    """A request (saved times, step budget, batch) would need more memory than is
    available. Attributes: ``need`` and ``available`` in bytes."""

    def __init__(self, message: str, need: float = 0.0, available: float = 0.0):
        self.need, self.available = float(need), float(available)
        super().__init__(message)


class ProblemError(NhjaxError, ValueError):
    """An optimal-control problem that cannot be posed or solved as given."""


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


class OutsideChartError(ChartSingularityError, ValueError):
    """A start (an initial state, or the arguments a scene's ``initial_state`` builds one
    from) lies outside the coordinate chart of the scene: on or beyond the edge where a
    chart guard vanishes. Bad input, so a ``ValueError``; also a
    ``ChartSingularityError`` (the same guard, reached at the start instead of during the
    motion), so one ``except`` clause catches both.

    Attributes as ChartSingularityError (``guard``, ``t``) plus ``name``: the argument
    that put the start there ("x0", "theta", "rho", ...).
    """

    def __init__(self, guard: str, t: float, detail: str = "", name: str = "x0"):
        self.name = name
        super().__init__(guard, t, detail)


class BoundaryError(NhjaxError, ValueError):
    """A moving boundary of an impact system degenerates within the time span (a moving
    circle's radius reaching zero): no motion is defined past that time.

    Attributes: ``boundary`` (its name, e.g. "radius"), ``t`` (the first time found at
    which its margin is <= 0), ``value`` (the margin there).
    """

    def __init__(self, message: str, boundary: str, t: float, value: float):
        self.boundary, self.t, self.value = boundary, float(t), float(value)
        super().__init__(message)


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
