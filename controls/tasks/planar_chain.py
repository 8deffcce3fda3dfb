"""Optimal control of planar chains on their reduced dynamics (seed 001; MODELS.md
"Planar reorientation").

* ``chain_reorientation``: a ``PlanarChain`` (group SO(2), zero momentum: the
  centre of mass stays put) turns by ``turn`` [rad] in time T, rest to rest, its
  joint angles back where they started, with the least effort int |u|^2 dt
  (u: joint torques [N m]). Only a closed loop of the joint angles can turn it
  (holonomy; N >= 3): ``loop_guess`` gives the torques that drive a circular
  joint loop sized by Stokes (``loop_turn``) to the requested turn, a start for
  the direct method, whose costates then start Pontryagin shooting.
* ``chain_steering``: a chain with thrusters (group SE(2), momentum carried)
  moves from rest at the origin to rest at a target pose (x, y, angle) [m, m,
  rad], joint angles back at their start, least int |u|^2 dt (u: joint torques
  [N m] and thrusts [N]).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from nhjax import _validate as V
from nhjax.mechanics.reduction import EllipseLoop, curvature_integral
from nhjax.scenes.planar_chain import PlanarChain

from ..problem import OCP, ProblemError
from .somersault import Effort, TerminalTarget

__all__ = ["chain_reorientation", "chain_steering", "loop_guess", "loop_path", "loop_turn", "radius_for_turn"]


def _check_chain(chain, group, name):
    if not isinstance(chain, PlanarChain):
        raise ProblemError(f"{name}: chain must be a nhjax.scenes.PlanarChain, got {type(chain).__name__}")
    if type(chain.symmetry).__name__ != group:
        raise ProblemError(f"{name} needs a PlanarChain with group='{group}', got {type(chain.symmetry).__name__}")


def _phi0(chain, phi0, owner):
    """Joint angles at the start [rad] (k,), default 0, finite."""
    if phi0 is None:
        return jnp.zeros(chain.k)
    return V.vector("phi0", phi0, chain.k, owner=owner, what="joint angles at the start and end [rad]")


def chain_reorientation(chain: PlanarChain, turn, T, phi0=None) -> OCP:
    """Rest to rest at zero momentum: x = (angle, phi, phi'), x0 = (0, phi0, 0); at T:
    angle = turn, phi = phi0, phi' = 0; cost int |u|^2 dt."""
    _check_chain(chain, "SO2", "chain_reorientation")
    if chain.momentum != "zero":
        raise ProblemError("chain_reorientation is posed at zero momentum (momentum='zero')")
    phi0 = _phi0(chain, phi0, "chain_reorientation")
    turn = V.real("turn", turn, owner="chain_reorientation", shape=(), what="turn of the chain [rad]")
    x0 = chain.initial_state(phi0)
    target = x0.at[0].set(turn)
    return OCP(chain, x0, T, running_cost=Effort(), terminal_constraints=TerminalTarget(target))


def chain_steering(chain: PlanarChain, target, T, phi0=None) -> OCP:
    """Thrusters and joint torques, rest to rest: from the pose (0, 0, 0) to ``target`` =
    (x, y, angle) of the reference frame (body 1 at the centre of mass), joint angles
    back at ``phi0``, momentum zero at both ends; cost int |u|^2 dt."""
    _check_chain(chain, "SE2", "chain_steering")
    if not chain.has_thrusters:
        raise ProblemError("chain_steering needs a PlanarChain with thrusters (thrusters=True)")
    phi0 = _phi0(chain, phi0, "chain_steering")
    target = V.vector("target", target, 3, owner="chain_steering", what="target pose (x, y, angle) [m, m, rad]")
    x0 = chain.initial_state(phi0)
    goal = x0.at[:3].set(target)
    return OCP(chain, x0, T, running_cost=Effort(), terminal_constraints=TerminalTarget(goal))


# ------------------------------------------------------------------ loop starts
def loop_path(phi0, radius, direction, orientation, T):
    """A circular joint loop through phi0, rest to rest in time T: centre phi0 + radius d
    (d: the unit ``direction`` in the plane of the first two joints), run once
    counter-clockwise (orientation +1) or clockwise (-1) with a quintic time law.
    Returns t -> (phi, phi', phi'')."""
    phi0 = jnp.asarray(phi0, float)
    d = jnp.asarray(direction, float)
    d = d / jnp.linalg.norm(d)
    c = phi0[:2] + radius * d

    def phi(t):
        tau = jnp.clip(t / T, 0.0, 1.0)
        s = tau**3 * (10 - 15 * tau + 6 * tau**2)
        a = jnp.arctan2(-d[1], -d[0]) + orientation * 2 * jnp.pi * s
        return phi0.at[:2].set(c + radius * jnp.stack([jnp.cos(a), jnp.sin(a)]))

    def derivs(t):
        t = jnp.asarray(t, float)
        d1 = lambda tt: jax.jvp(phi, (tt,), (jnp.ones_like(tt),))[1]  # noqa: E731
        v, a = jax.jvp(d1, (t,), (jnp.ones_like(t),))
        return phi(t), v, a

    return derivs


def loop_turn(chain: PlanarChain, phi0, radius, direction=(1.0, 1.0), orientation=1, n=32):
    """The turn [rad] of the loop of ``loop_path``: -(orientation) x the curvature
    integral over the enclosed disk (exact: the SO(2) connection is abelian)."""
    phi0 = jnp.asarray(phi0, float)
    d = jnp.asarray(direction, float) / jnp.linalg.norm(jnp.asarray(direction, float))
    c = phi0[:2] + radius * d
    kin = chain.kinematic()
    return -orientation * float(curvature_integral(kin, EllipseLoop(c, radius), c, base=phi0, n=n)[0])


def radius_for_turn(chain: PlanarChain, turn, phi0, direction=(1.0, 1.0), r_max=2.0):
    """(radius, orientation) of a ``loop_path`` circle whose turn is ``turn``, by
    bisection on the radius in (0, r_max] (raises if even r_max turns too little)."""
    full = loop_turn(chain, phi0, r_max, direction, 1)
    if abs(full) < abs(turn):
        raise ProblemError(
            f"radius_for_turn: a circular joint loop of radius {r_max} rad from phi0 turns the chain by only "
            f"{abs(full):.3g} rad < |turn| = {abs(turn):.3g}: ask for less, or start elsewhere"
        )
    orientation = 1 if np.sign(full) == np.sign(turn) else -1
    lo, hi = 0.0, r_max
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if abs(loop_turn(chain, phi0, mid, direction, 1)) < abs(turn):
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi), orientation


def loop_guess(chain: PlanarChain, param, phi0, T, radius, direction=(1.0, 1.0), orientation=1):
    """Parameters of ``param`` fitted to the joint torques that drive the chain around
    the ``loop_path`` circle (computed torque: the inverse of the reduced equations)."""
    path = loop_path(phi0, radius, direction, orientation, T)
    ng = chain.n_group

    def u(t):
        q, v, a = path(t)
        x = chain.join(None, jnp.zeros(ng), q, v, None if chain.momentum == "zero" else jnp.zeros(chain.symmetry.dim))
        return chain.inverse_dynamics(x, a)

    return param.fit(jax.jit(u))

