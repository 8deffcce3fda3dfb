"""The system interface that ``nhjax.simulate`` integrates.

A system is an ``equinox.Module`` (so jit, vmap and grad see its parameters)
with a first-order vector field x' = F(t, x, u) and optional declarations that
make every simulation self-checking:

* ``constraints(t, x)``: residuals that must stay zero (name -> array);
* ``invariants(x)``: quantities conserved for *every* admissible control
  (name -> scalar); ``free_invariants(x)``: those conserved without inputs;
* ``energy(x)`` and ``power(t, x, u)``: with a control, simulate() integrates
  the work of the inputs and reports the drift of energy - work;
* ``guards(x)``: chart guards, positive inside the region where the
  coordinates are valid; simulate() stops (and by default raises
  ``ChartSingularityError``) where one crosses zero;
* ``spaces``: for states with group-valued parts, the ``nhjax.lie`` spaces that
  tell the Lie-group solvers how each part moves;
* ``project(t, x)``: map a nearby state onto the constraint manifold
  (``project_converged`` repeats it until the residual is within tolerance and
  reports the residual reached);
* ``requires_control``: True for systems whose vector field needs the inputs
  (velocity-controlled ones): simulate() refuses to run them without a control;
* ``regularity(t, x)``: margins of the conditions that make the equations well
  posed (e.g. full-rank constraints), checked at x0.

A subclass's ``initial_state`` (the helper that builds a state from physical
quantities) refuses by name a system that holds a batch of parameter sets (one
state is one member's; ``_checked_initial_state``). A start outside the chart is
``OutsideChartError`` wherever it is found: by a scene's own check of its
arguments, by ``simulate`` (naming the argument that sets the guard, from
``guard_arguments``), by an optimal-control problem.
"""

from __future__ import annotations

import functools
import threading
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu

from .._args import single_member
from ..lie.spaces import Euclidean

__all__ = ["AbstractSystem"]


class AbstractSystem(eqx.Module):
    """Base class of every nhjax system; see the module docstring."""

    # Names of the components of a flat state (used by Trajectory["name"]).
    state_names: ClassVar[tuple[str, ...]] = ()
    # Number of control inputs (0: the system takes none).
    control_dim: ClassVar[int] = 0
    # Whether vector_field needs u (velocity-controlled systems; others read u=None as zero).
    requires_control: ClassVar[bool] = False
    # Advice shown when a guard of this name trips.
    guard_hints: ClassVar[dict[str, str]] = {}
    # Explanation shown when a regularity margin of this name is not positive.
    regularity_hints: ClassVar[dict[str, str]] = {}
    # The initial_state argument that sets each guard (OutsideChartError names it).
    guard_arguments: ClassVar[dict[str, str]] = {}
    # Large vector fields (e.g. autodiff-derived multibody dynamics) compile much faster
    # when a Runge-Kutta solver traces them once (stages in a lax.scan).
    large_vector_field: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if "initial_state" in cls.__dict__:
            cls.initial_state = _checked_initial_state(cls.__dict__["initial_state"])

    def vector_field(self, t, x, u):
        raise NotImplementedError

    @property
    def spaces(self) -> Any:
        return Euclidean()

    def constraints(self, t, x) -> dict:
        return {}

    def invariants(self, x) -> dict:
        return {}

    def free_invariants(self, x) -> dict:
        """Quantities conserved when no input acts (reported when simulate() gets no control)."""
        return {}

    def guards(self, x) -> dict:
        return {}

    def energy(self, x):
        return None

    def power(self, t, x, u):
        return None

    def project(self, t, x):
        return x

    @property
    def splits_projection(self) -> bool:
        """Whether a projected solve may project positions after each step
        (``project_positions``) and velocities with the next step's first stage
        (``projected_field``); see ``ConstrainedLagrangian.splits_projection``."""
        return False

    def constraint_residual(self, t, x):
        """Largest |residual| over all ``constraints(t, x)`` (0 without constraints)."""
        vals = [jnp.max(jnp.abs(jnp.asarray(v))) for v in self.constraints(t, x).values() if jnp.size(v)]
        return jnp.max(jnp.stack(vals)) if vals else jnp.zeros(())

    def project_converged(self, t, x, tol=1e-14, max_iter=10):
        """``project`` repeated until the largest constraint residual is <= tol (1 + max|x|),
        at most ``max_iter`` times: returns (x, residual reached, rounds used).

        One round of a Newton projection from far away (a quaternion of norm 2) need not
        reach the manifold; rounds stop changing x once it is within tolerance. A
        fixed-length loop (lax.fori_loop), so jit, vmap and reverse-mode grad pass.
        """
        scale = lambda y: 1.0 + jnp.max(jnp.stack([jnp.max(jnp.abs(a)) for a in jtu.tree_leaves(y)]))  # noqa: E731

        def body(_, carry):
            y, r, n = carry
            go = r > tol * scale(y)
            y_new = self.project(t, y)
            y = jtu.tree_map(lambda a, b: jnp.where(go, b, a), y, y_new)
            return y, jnp.where(go, self.constraint_residual(t, y), r), n + go.astype(jnp.int32)

        r0 = self.constraint_residual(t, x)
        return jax.lax.fori_loop(0, max_iter, body, (x, r0, jnp.zeros((), jnp.int32)))

    def regularity(self, t, x) -> dict:
        """Margins (name -> scalar, positive = fine) of conditions without which the
        equations of motion are ill posed; simulate() checks them at x0."""
        return {}


_DEPTH = threading.local()  # initial_state helpers calling another's (checked once, outermost)


def _checked_initial_state(fn):
    """``fn`` (a subclass's ``initial_state``) after the check of the module docstring:
    the system holds one parameter set (``nhjax._args.single_member``; host-side, no
    program)."""

    @functools.wraps(fn)
    def initial_state(self, *args, **kwargs):
        depth = getattr(_DEPTH, "n", 0)
        if depth:
            return fn(self, *args, **kwargs)
        single_member(self, owner=f"{type(self).__name__}.initial_state")
        _DEPTH.n = depth + 1
        try:
            return fn(self, *args, **kwargs)
        finally:
            _DEPTH.n = depth

    return initial_state
