"""The falling cat's somersault as optimal-control problems (seed 000, secs. 4 and 7).

Velocity control (7.1), minimizing the vibrational energy (4.8)
int I1 [(1 + B s^2) theta'^2 + lam s^2/D chi'^2] dt, whose Pontryagin
Hamiltonian is Iwai's (7.6) (here in the minimum convention, with H_min =
-H_Iwai at the optimum):

* ``velocity_somersault_chart``: in Iwai's chart (theta, chi, psi); the shape
  returns (theta(T) = theta0) after chi winds ``windings`` times, and psi turns
  by ``turn`` (this fixes the representative of psi and the winding).
* ``velocity_somersault_smooth``: in coordinates smooth at the straight cat
  (``FallingCatSmooth``: w = theta (cos chi, sin chi), phi = psi + chi); the
  shape returns (w(T) = w(0)) and the fiber turns by ``turn + 2 pi j``: the
  optimizer chooses how often chi winds, and j picks the class modulo 2 pi.

Torque control (7.14)-(7.15): ``torque_somersault``, rest to rest, minimizing
int |u|^2 dt.

``fixed_theta_costates`` gives the exact extremal of the chart problem when the
turn is the holonomy of the fixed-theta loop (-2 pi f(theta0) per winding): the
start of a continuation in the turn.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from nhjax.scenes import FallingCat, FallingCatKinematic
from nhjax.scenes.falling_cat import FallingCatSmooth

from ..problem import OCP

__all__ = [
    "Effort",
    "TerminalTarget",
    "Vibrational",
    "fixed_theta_costates",
    "torque_somersault",
    "velocity_somersault_chart",
    "velocity_somersault_smooth",
]


class Vibrational(eqx.Module):
    """Running cost: the vibrational energy rate (4.8) of a velocity-controlled cat."""

    system: object

    def __call__(self, t, x, u):
        return self.system.vibrational_power(x, u)


class Effort(eqx.Module):
    """Running cost |u|^2."""

    def __call__(self, t, x, u):
        return u @ u


class TerminalTarget(eqx.Module):
    """Terminal constraints x(T) - target (an array: a new target does not recompile)."""

    target: jax.Array

    def __call__(self, x):
        return x - self.target


def velocity_somersault_chart(cat: FallingCatKinematic, theta0, turn, T, windings=1) -> OCP:
    """Chart problem: x = (theta, chi, psi), x0 = (theta0, 0, 0); at T: theta = theta0,
    chi = 2 pi windings, psi = turn."""
    target = jnp.stack([jnp.asarray(v, float) for v in (theta0, 2 * np.pi * windings, turn)])
    return OCP(cat, jnp.stack([jnp.asarray(theta0, float), 0.0, 0.0]), T,
               running_cost=Vibrational(cat), terminal_constraints=TerminalTarget(target))


def velocity_somersault_smooth(cat: FallingCatSmooth, theta0, turn, T, j=0) -> OCP:
    """Smooth problem: x = (w1, w2, phi), x0 = (theta0, 0, 0); at T: w = (theta0, 0) and
    phi = turn + 2 pi j."""
    target = jnp.stack([jnp.asarray(v, float) for v in (theta0, 0.0, turn + 2 * np.pi * j)])
    return OCP(cat, jnp.stack([jnp.asarray(theta0, float), 0.0, 0.0]), T,
               running_cost=Vibrational(cat), terminal_constraints=TerminalTarget(target))


def torque_somersault(cat: FallingCat, theta0, turn, T, windings=1) -> OCP:
    """Rest to rest under torques: x = (theta, chi, psi, theta', chi'); cost int |u|^2."""
    target = jnp.stack([jnp.asarray(v, float) for v in (theta0, 2 * np.pi * windings, turn, 0.0, 0.0)])
    return OCP(cat, cat.initial_state(theta0), T, running_cost=Effort(),
               terminal_constraints=TerminalTarget(target))


def fixed_theta_costates(cat: FallingCatKinematic, theta0, T, windings=1):
    """Exact (p(0), nu) of the chart problem whose turn is -2 pi windings f(theta0).

    Along theta = theta0, chi' = c = 2 pi windings / T, stationarity of H = L + p.f in
    u2 and dH/dtheta = 0 (so p_theta stays 0) give
        p_psi = I1 c (lam s^2/D)' / f',   p_chi = f p_psi - 2 I1 (lam s^2/D) c,
    and the costates are constant; nu = p(T) (no terminal cost).
    """
    c = 2 * np.pi * windings / T
    g = lambda th: cat.lam * jnp.sin(th) ** 2 / cat.D(th)  # noqa: E731
    dg = jax.grad(g)(jnp.asarray(theta0, float))
    df = cat.curvature(theta0)
    p_psi = cat.I1 * c * dg / df
    p_chi = cat.f(theta0) * p_psi - 2 * cat.I1 * g(theta0) * c
    p = jnp.stack([jnp.zeros(()), p_chi, p_psi])
    return p, p
