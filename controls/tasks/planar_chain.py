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

from nhjax import _programs
from nhjax import _validate as V
from nhjax.errors import ParameterError
from nhjax.mechanics.reduction import EllipseLoop, curvature_integral
from nhjax.scenes.planar_chain import PlanarChain

from ..parametrize import fit_samples
from ..problem import OCP, ProblemError
from .somersault import Effort, TerminalTarget, _guess_inputs

__all__ = ["chain_reorientation", "chain_steering", "loop_guess", "loop_path", "loop_turn", "radius_for_turn"]


def _check_chain(chain, group, name):
    if not isinstance(chain, PlanarChain):
        raise ProblemError(f"{name}: chain must be a nhjax.scenes.PlanarChain, got {type(chain).__name__}")
    if type(chain.symmetry).__name__ != group:
        raise ProblemError(f"{name} needs a PlanarChain with group='{group}', got {type(chain.symmetry).__name__}")


def _loop_inputs(owner, chain, phi0, direction, radius=None, orientation=None):
    """Entry checks of the joint-loop helpers: a PlanarChain, phi0 (k,) finite, a nonzero
    finite 2-vector ``direction``, a radius > 0 [rad] and an orientation +1 or -1 (when
    given). Returns (phi0, the unit direction as numpy)."""
    if not isinstance(chain, PlanarChain):
        raise ProblemError(f"{owner}: chain must be a nhjax.scenes.PlanarChain, got {type(chain).__name__}")
    phi0 = _phi0(chain, phi0, owner)
    d = np.asarray(V.vector("direction", direction, 2, owner=owner,
                            what="direction of the loop's centre from phi0 in the plane of the first two joints"))
    if not np.linalg.norm(d) > 0:
        raise ParameterError(f"{owner}: direction must be a nonzero 2-vector (it points from phi0 to the loop's "
                               f"centre), got {d.tolist()}", "direction", direction)
    if radius is not None:
        V.positive("radius", radius, owner=owner, shape=(), what="radius of the joint loop [rad]")
    if orientation is not None:
        V.choice("orientation", orientation, (1, -1), owner=owner)
    return phi0, d / np.linalg.norm(d)


def _phi0(chain, phi0, owner):
    """Joint angles at the start [rad] (k,), default 0, finite."""
    if phi0 is None:
        return V.to_device(np.zeros(chain.k))
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
    # (on the host: an eager .at[].set is a program of its own in every new process)
    target = V.to_device(np.concatenate([np.asarray(turn, float).reshape(1), np.asarray(x0)[1:]]))
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


def _turn_of(chain, phi0, radius, d, orientation, n=32):
    """``loop_turn`` as a traceable function of its numbers (d a unit vector)."""
    c = phi0[:2] + radius * d
    return -orientation * curvature_integral(chain.kinematic(), EllipseLoop(c, radius), c, base=phi0, n=n)[0]


def loop_turn(chain: PlanarChain, phi0, radius, direction=(1.0, 1.0), orientation=1, n=32):
    """The turn [rad] of the loop of ``loop_path``: -(orientation) x the curvature
    integral over the enclosed disk (exact: the SO(2) connection is abelian)."""
    phi0, d = _loop_inputs("chain_loop_turn", chain, phi0, direction, radius, orientation)
    return float(_turn_of(chain, phi0, radius, jnp.asarray(d), orientation, n=n))


#: Secant steps of ``radius_for_turn``: from r_max sqrt(|turn| / |turn(r_max)|) (exact
#: for a turn proportional to the enclosed area) they reach the radius to rounding in
#: seven to nine on the 3-link chain (turns 0.02 to 0.6 rad).
SECANT_STEPS = 10


def _solve_radius(chain, phi0, d, turn, r_max):
    """(turn of the r_max circle, the radius whose circle turns the chain by |turn|, and
    |turn(radius)| - |turn|): the secant method, kept in (0, r_max], one curvature
    integral per step. One program for the whole search, with one copy of the curvature
    integral in it: a loop whose first three trips evaluate the r_max circle and the two
    starting radii, the others the secant steps (four copies compiled four times over)."""
    target = jnp.abs(turn)

    def trip(k, state):
        full, r0, f0, r1, f1 = state
        df = f1 - f0
        step = jnp.clip(jnp.where(df != 0.0, r1 - f1 * (r1 - r0) / jnp.where(df != 0.0, df, 1.0), r1),
                        1e-6 * r_max, r_max)
        start = r_max * jnp.sqrt(jnp.clip(target / jnp.abs(full), 1e-12, 1.0))
        r = jnp.select([k == 0, k == 1, k == 2], [r_max, start, 0.9 * r0], step)
        value = _turn_of(chain, phi0, r, d, 1.0)
        f = jnp.abs(value) - target
        return jax.lax.switch(jnp.minimum(k, 2), [
            lambda: (value, r0, f0, r1, f1),  # the r_max circle
            lambda: (full, r, f, r, f),  # the first start (in both places)
            lambda: (full, r1, f1, r, f),  # the second start, then the secant steps
        ])

    z = jnp.zeros_like(r_max)
    full, _, _, r, f = jax.lax.fori_loop(0, SECANT_STEPS + 3, trip, (z, z, z, z, z))
    return full, r, f


def radius_for_turn(chain: PlanarChain, turn, phi0, direction=(1.0, 1.0), r_max=2.0):
    """(radius, orientation) of a ``loop_path`` circle whose turn is ``turn``: the
    secant method on the radius in (0, r_max] (raises if even r_max turns too little, or
    if the search ends more than 1e-10 relative from the turn). The search runs as
    one stored program (``nhjax._programs.call``): in a notebook's new process it is
    loaded, neither traced nor compiled again."""
    owner = "radius_for_turn"
    phi0, d = _loop_inputs(owner, chain, phi0, direction)
    turn = float(V.real("turn", turn, owner=owner, shape=(), what="turn of the chain [rad]"))
    r_max = float(V.positive("r_max", r_max, owner=owner, shape=(), what="largest loop radius [rad]"))
    args = (chain, phi0, *(V.to_device(v) for v in (d, turn, r_max)))
    full, radius, miss = (float(a) for a in _programs.call("controls.tasks.radius_for_turn", _solve_radius, args,
                                                           compiler_options=_programs.QUICK_OPTIONS))
    if abs(full) < abs(turn):
        raise ProblemError(
            f"radius_for_turn: a circular joint loop of radius {r_max} rad from phi0 turns the chain by only "
            f"{abs(full):.3g} rad < |turn| = {abs(turn):.3g}: ask for less, or start elsewhere"
        )
    # (a turn below what the smallest circle, 1e-6 r_max, gives ends there: no miss to judge)
    if radius > 1e-6 * r_max and not abs(miss) <= 1e-10 * max(abs(turn), 1e-3):
        raise ProblemError(f"radius_for_turn: the secant search for the radius stopped {abs(miss):.2e} rad from "
                           f"the turn {turn:.6g} after {SECANT_STEPS} steps")
    return radius, 1 if np.sign(full) == np.sign(turn) else -1


def _loop_torques(chain, phi0, radius, d, orientation, T, ts):
    """The computed torques (inverse reduced dynamics) along the ``loop_path`` circle at ts."""
    path = loop_path(phi0, radius, d, orientation, T)
    ng = chain.n_group

    def u(t):
        q, v, a = path(t)
        x = chain.join(None, jnp.zeros(ng), q, v, None if chain.momentum == "zero" else jnp.zeros(chain.symmetry.dim))
        return chain.inverse_dynamics(x, a)

    return jax.vmap(u)(ts)


def loop_guess(chain: PlanarChain, param, phi0, T, radius, direction=(1.0, 1.0), orientation=1):
    """Parameters of ``param`` fitted to the joint torques that drive the chain around
    the ``loop_path`` circle (computed torque: the inverse of the reduced equations),
    sampled at ``param.sample_times()`` by one stored program."""
    owner = "chain_loop_guess"
    phi0, d = _loop_inputs(owner, chain, phi0, direction, radius, orientation)
    T = _guess_inputs(owner, param, chain.control_dim, T, system=type(chain).__name__)
    ts = param.sample_times()
    us = _programs.small_call("controls.tasks.loop_guess", _loop_torques, chain, phi0, radius,
                              d, float(orientation), float(T), ts)
    return fit_samples(param, ts, us)

