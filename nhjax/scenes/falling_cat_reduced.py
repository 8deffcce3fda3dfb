r"""Iwai's falling cat rebuilt through the general reduction (seed 000, secs. 6-7).

The two jointed cylinders of ``nhjax.scenes.FallingCat``, but nothing about
their reduced dynamics is written by hand: the bodies (mass m, inertia
diag(I1, lam I1, I1) about each centre of mass, symmetry axis e2), the local
section (6.4)/(6.6) at psi = 0,

    g1 = exp(-theta e1^) exp(chi e2^),   g2 = exp(theta e1^) exp(chi e2^),
    r1 = -l (g1 e2 + g2 e2) / 2 = -r2    (centre of mass at 0, joint at r1 + l g1 e2),

and the symmetry left after the twist-free condition, rotations about e2 (the
psi of (6.6); ``SO2(axis=e2)``), go to ``nhjax.mechanics.reduction.ReducedSystem``,
which computes the locked inertia 2 I1 D, the connection A = (0, f(theta)) (6.7),
the vibrational metric (7.3) and the torque-driven equations (7.14)-(7.15) by
autodiff. The tests hold it to ``FallingCat`` to round-off.

Parameters as ``FallingCat``: I1 [kg m^2], lam = I2/I1, B = m l^2 / I1, mass [kg].
State (psi, theta, chi, theta', chi') [rad, rad/s] (the group angle first: the
layout of every ``ReducedSystem``); inputs (u1, u2) [N m] on (theta, chi).
Chart: sin(theta) > ``chart_eps`` (guard ``sin_theta``, as ``FallingCat``).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _validate as V
from ..lie import so3
from ..mechanics.reduction import _LOCKED_HINT, SO2, Bodies, ReducedSystem
from .falling_cat import _CHART_HINT, _cat_parameters, _chart_eps, _state_args

__all__ = ["FallingCatReduced"]

_E2 = np.array([0.0, 1.0, 0.0])  # numpy: no program to compile at import


class CatSection(eqx.Module):
    """(theta, chi) -> attitudes and centres of both cylinders at psi = 0."""

    l: jax.Array

    def __call__(self, r):
        theta, chi = r[0], r[1]
        inner = so3.rot_y(chi)
        g1, g2 = so3.rot_x(-theta) @ inner, so3.rot_x(theta) @ inner
        r1 = -0.5 * self.l * (g1 @ _E2 + g2 @ _E2)
        return jnp.stack([g1, g2]), jnp.stack([r1, -r1])


class CatChart(eqx.Module):
    eps: float = eqx.field(static=True)

    def __call__(self, r):
        return {"sin_theta": jnp.sin(r[0]) - self.eps}


class FallingCatReduced(ReducedSystem):
    """The cat as a ``ReducedSystem``: two rigid cylinders, SO(2) about e2, zero momentum."""

    guard_hints: ClassVar[dict] = {"sin_theta": _CHART_HINT, "locked_inertia": _LOCKED_HINT}
    guard_arguments: ClassVar[dict] = {"sin_theta": "theta", "locked_inertia": "theta"}

    def __init__(self, I1=0.09895833333333333, lam=0.31578947368421056, B=2.5263157894736845, mass=1.0,
                 chart_eps=1e-3, momentum="zero"):
        # checked as FallingCat checks them (finite, > 0, named as passed); one parameter set
        # (the bodies' arrays have no member axis: batches stack built systems, nhjax.stack)
        I1, lam, B, mass = _cat_parameters("FallingCatReduced", I1, lam, B, mass)
        for name, v in (("I1", I1), ("lam", lam), ("B", B), ("mass", mass)):
            V.real(name, v, owner="FallingCatReduced", shape=(), what="one parameter set: build a batch with "
                   "nhjax.stack([FallingCatReduced(...), ...])")
        chart_eps = _chart_eps("FallingCatReduced", chart_eps)
        J = jnp.diag(jnp.stack([I1, lam * I1, I1]))
        bodies = Bodies(jnp.stack([mass, mass]), jnp.stack([J, J]))
        l = jnp.sqrt(B * I1 / mass)  # noqa: E741
        self._setup(bodies, CatSection(l), SO2(axis=(0.0, 1.0, 0.0)), 2, momentum=momentum,
                    shape_names=("theta", "chi"), chart_guard=CatChart(float(chart_eps)))

    def initial_state(self, theta, chi=0.0, psi=0.0, theta_dot=0.0, chi_dot=0.0):
        """State from half bend angle, twist, overall angle [rad] and rates [rad/s]."""
        theta, chi, psi, theta_dot, chi_dot = _state_args(
            "FallingCatReduced", theta=theta, chi=chi, psi=psi, theta_dot=theta_dot, chi_dot=chi_dot)
        if not V.is_traced(theta):
            V.chart_argument(self, "sin_theta", np.sin(np.asarray(theta, float)) - self.chart_guard.eps,
                             owner="FallingCatReduced.initial_state", name="theta")
        return ReducedSystem.initial_state(self, jnp.stack([theta, chi]), jnp.stack([theta_dot, chi_dot]),
                                           psi.reshape(1))
