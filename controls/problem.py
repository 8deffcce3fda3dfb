"""Optimal-control problems on nhjax systems.

    minimize    Phi(x(T)) + int_0^T L(t, x, u) dt
    subject to  x' = f(t, x, u)  (the nhjax system),  x(0) = x0,
                psi(x(T)) = 0    (terminal equality constraints),
                u_lower <= u <= u_upper.

``OCP`` holds the data; ``rollout`` simulates a control and returns the
trajectory with its cost and terminal-constraint residual (the running cost is
integrated as an extra state component, to the solver's tolerance).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu

import nhjax
from nhjax.lie import Euclidean
from nhjax.mechanics import AbstractSystem

__all__ = ["OCP", "ProblemError", "rollout"]


class ProblemError(ValueError):
    """An optimal-control problem that cannot be posed or solved as given."""


class OCP(eqx.Module):
    """An optimal-control problem (see the module docstring).

    running_cost(t, x, u) -> scalar; terminal_cost(x) -> scalar (or None);
    terminal_constraints(x) -> (m,) array (or None). Callables may be plain
    functions or equinox modules (whose arrays are then parameters).
    """

    system: AbstractSystem
    x0: Any
    T: float = eqx.field(static=True)
    running_cost: Callable
    terminal_cost: Callable | None = None
    terminal_constraints: Callable | None = None
    u_lower: Any = None
    u_upper: Any = None

    def __init__(self, system, x0, T, running_cost, terminal_cost=None, terminal_constraints=None,
                 u_lower=None, u_upper=None):
        if system.control_dim == 0:
            raise ProblemError(f"{type(system).__name__} has no control inputs to optimize")
        if not float(T) > 0:
            raise ProblemError(f"the horizon T must be positive, got {T}")
        self.system = system
        self.x0 = jtu.tree_map(lambda a: jnp.asarray(a, float), x0)
        self.T = float(T)
        self.running_cost = running_cost
        self.terminal_cost = terminal_cost
        self.terminal_constraints = terminal_constraints
        k = system.control_dim
        self.u_lower = None if u_lower is None else jnp.broadcast_to(jnp.asarray(u_lower, float), (k,))
        self.u_upper = None if u_upper is None else jnp.broadcast_to(jnp.asarray(u_upper, float), (k,))
        if (self.u_lower is None) != (self.u_upper is None):
            raise ProblemError("give both u_lower and u_upper, or neither")
        if self.u_lower is not None and bool(jnp.any(self.u_lower >= self.u_upper)):
            raise ProblemError("every lower control bound must be below the upper one")
        self._check_shapes()

    def _check_shapes(self):
        u = jnp.zeros(self.system.control_dim)
        names = self.system.state_names
        if names and getattr(self.x0, "shape", None) != (len(names),):
            raise ProblemError(
                f"x0 does not fit {type(self.system).__name__}: it has shape "
                f"{getattr(self.x0, 'shape', None)}, the state is {names}"
            )
        try:
            dx = jax.eval_shape(lambda: self.system.vector_field(0.0, self.x0, u))
        except Exception as e:  # noqa: BLE001 - re-raised with the cause attached
            raise ProblemError(f"x0 does not fit {type(self.system).__name__}: {e}") from e
        if jtu.tree_structure(dx) != jtu.tree_structure(self.x0):
            raise ProblemError(f"x0 does not fit {type(self.system).__name__}: its vector field "
                               "returns a differently structured state")
        L = jax.eval_shape(lambda: self.running_cost(0.0, self.x0, u))
        if L.shape != ():
            raise ProblemError(f"running_cost(t, x, u) must return a scalar, got shape {L.shape}")
        if self.terminal_cost is not None:
            P = jax.eval_shape(lambda: self.terminal_cost(self.x0))
            if P.shape != ():
                raise ProblemError(f"terminal_cost(x) must return a scalar, got shape {P.shape}")
        if self.terminal_constraints is not None:
            c = jax.eval_shape(lambda: self.terminal_constraints(self.x0))
            if len(c.shape) != 1:
                raise ProblemError(f"terminal_constraints(x) must return a 1-D array, got shape {c.shape}")
        del dx

    @property
    def n_constraints(self) -> int:
        if self.terminal_constraints is None:
            return 0
        return jax.eval_shape(lambda: self.terminal_constraints(self.x0)).shape[0]

    def terminal(self, x):
        """(Phi(x), psi(x)) with zeros where absent."""
        phi = jnp.zeros(()) if self.terminal_cost is None else self.terminal_cost(x)
        psi = jnp.zeros((0,)) if self.terminal_constraints is None else self.terminal_constraints(x)
        return phi, psi


class CostAugmented(AbstractSystem):
    """The system with its running cost integrated alongside: state (x, J)."""

    system: AbstractSystem
    running_cost: Callable

    @property
    def control_dim(self):  # type: ignore[override]
        return self.system.control_dim

    @property
    def spaces(self):
        return (self.system.spaces, Euclidean())

    @property
    def large_vector_field(self):  # type: ignore[override]
        return self.system.large_vector_field

    def vector_field(self, t, y, u):
        x, _ = y
        return self.system.vector_field(t, x, u), self.running_cost(t, x, u)

    def constraints(self, t, y):
        return self.system.constraints(t, y[0])

    def guards(self, y):
        return self.system.guards(y[0])

    def energy(self, y):
        return self.system.energy(y[0])

    def power(self, t, y, u):
        return self.system.power(t, y[0], u)


class _OnState(eqx.Module):
    control: Any

    @property
    def breakpoints(self):
        return getattr(self.control, "breakpoints", None)

    def __call__(self, t, y):
        return self.control(t, y[0])


def rollout(ocp: OCP, control, *, rtol=1e-9, atol=1e-9, saveat=2, max_steps=None, adjoint=None,
            diagnostics=False, **kw):
    """Simulate ``control`` (callable u(t, x)) on the problem.

    Returns (traj, cost, psi): the trajectory of (x, J) pairs, the total cost
    Phi(x(T)) + J(T), and the terminal-constraint residual. Reverse-mode
    gradients go through ``nhjax.DiscreteAdjoint`` unless ``adjoint`` says
    otherwise (``max_steps`` None: that adjoint's budget, 4096 steps).
    """
    if adjoint is None:
        adjoint = nhjax.DiscreteAdjoint()
    aug = CostAugmented(ocp.system, ocp.running_cost)
    y0 = (ocp.x0, jnp.zeros(()))
    traj = nhjax.simulate(aug, y0, ocp.T, control=_OnState(control), rtol=rtol, atol=atol,
                          saveat=saveat, max_steps=max_steps, adjoint=adjoint, track_work=False,
                          diagnostics=diagnostics, **kw)
    xT, JT = jtu.tree_map(lambda a: a[-1], traj.xs)
    phi, psi = ocp.terminal(xT)
    return traj, phi + JT, psi
