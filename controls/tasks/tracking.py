r"""Tracking tasks for closed loops (``controls.MPC``): the spherical robot following a
moving target around a figure-eight on the plane.

Model: ``ReducedSteering`` (the reduced vector state of ``nhjax.scenes.ShellWithTop``,
17 numbers x = (omega, Omega, gamma, alpha, beta, x, y), seed 003 sec. 1 with the
internal torque tau [N m] (top axes) as input; see ``controls.tasks.steering``).

Reference (``FigureEight``): the lemniscate of Gerono traced once per ``period`` T_r [s],

    r(t) = c + A (sin(w t), sin(2 w t) / 2),   w = 2 pi / T_r,

through the centre c [m] at t = 0 with velocity A w (1, 1) [m/s]; ``amplitude`` A [m].

Running cost (``TrackingCost``), per second:

    L(t, x, u) = w_p |(x, y) - r(t)|^2 + w_s |omega|^2 + w_u |tau|^2,

w_p [1/(m^2 s)] the tracking weight, w_s [s] a damping of the top's swing (omega the
top's angular velocity [rad/s]), w_u [1/(N^2 m^2 s)] the effort. All three and the
reference's numbers are array leaves: other weights or another figure run the same
compiled programs.

``shell_push`` gives the state increment of a horizontal push of the shell's centre
by dv [m/s] while the top hangs (gamma = e3 in the top's axes): by the rolling
constraint (1.5), dOmega = gamma x dv / Rs.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from nhjax.scenes import ShellWithTop

from nhjax import _validate as V

from ..problem import OCP, ProblemError, as_problem_error, host_array
from .steering import sphere_steering_reduced

__all__ = ["FigureEight", "TrackingCost", "shell_push", "sphere_tracking"]


class FigureEight(eqx.Module):
    """r(t) = centre + amplitude (sin(w t), sin(2 w t) / 2), w = 2 pi / period [m]."""

    amplitude: jax.Array
    period: jax.Array
    centre: jax.Array

    def __call__(self, t):
        w = 2 * jnp.pi / self.period
        return self.centre + self.amplitude * jnp.stack([jnp.sin(w * t), 0.5 * jnp.sin(2 * w * t)])


class TrackingCost(eqx.Module):
    """w_p |(x, y) - r(t)|^2 + w_s |omega|^2 + w_u |tau|^2 on ``ReducedSteering``'s state."""

    reference: FigureEight
    position_weight: jax.Array
    swing_weight: jax.Array
    effort_weight: jax.Array

    def __call__(self, t, x, u):
        e = x[15:17] - self.reference(t)
        om = x[0:3]
        return self.position_weight * (e @ e) + self.swing_weight * (om @ om) + self.effort_weight * (u @ u)

    def error(self, t, x):
        """|(x, y) - r(t)| [m] (vectorized over leading axes of t and x)."""
        r = jnp.vectorize(self.reference, signature="()->(2)")(t)
        return jnp.linalg.norm(x[..., 15:17] - r, axis=-1)


def sphere_tracking(robot: ShellWithTop, *, horizon=1.0, amplitude=0.5, period=20.0, centre=(0.0, 0.0),
                    position_weight=100.0, swing_weight=0.1, effort_weight=1.0, bound=1.0) -> OCP:
    """The horizon problem of the figure-eight tracking task: ``ReducedSteering`` of
    ``robot`` from rest at the origin (top hanging), running cost ``TrackingCost``,
    torques bounded by |tau_i| <= ``bound`` [N m], horizon ``horizon`` [s]."""
    if not isinstance(robot, ShellWithTop):
        raise ProblemError(f"robot must be an nhjax.scenes.ShellWithTop, got {type(robot).__name__}")
    owner = "sphere_tracking"
    with as_problem_error():
        horizon = V.duration("horizon", horizon, owner=owner)
        for name, v, what in (("amplitude", amplitude, "amplitude A of the figure eight [m]"),
                              ("period", period, "time of one lap of the figure eight [s]"),
                              ("bound", bound, "torque bound [N m]")):
            V.positive(name, v, owner=owner, shape=(), what=what)
        for name, v in (("position_weight", position_weight), ("swing_weight", swing_weight),
                        ("effort_weight", effort_weight)):
            V.positive(name, v, allow_zero=True, owner=owner, shape=(), what="weight of the running cost")
        centre = np.asarray(V.vector("centre", centre, 2, owner=owner, what="centre of the figure eight (x, y) [m]"))
    base = sphere_steering_reduced(robot, (0.0, 0.0), horizon)
    ref = FigureEight(host_array(amplitude), host_array(period), host_array(np.asarray(centre, float)))
    cost = TrackingCost(ref, host_array(position_weight), host_array(swing_weight), host_array(effort_weight))
    return OCP(base.system, base.x0, horizon, cost, u_lower=-bound, u_upper=bound)


def shell_push(robot: ShellWithTop, dv) -> np.ndarray:
    """The state increment (17,) of ``ReducedSteering`` for a push that changes the
    shell centre's velocity by dv = (dv_x, dv_y) [m/s] (top axes, the top hanging)."""
    if not isinstance(robot, ShellWithTop):
        raise ProblemError(f"shell_push: robot must be an nhjax.scenes.ShellWithTop, got {type(robot).__name__}")
    with as_problem_error():
        dv = np.asarray(V.vector("dv", dv, 2, owner="shell_push", what="change of the shell centre's velocity "
                                                                        "(dv_x, dv_y) [m/s]"))
    dv3 = np.array([*dv, 0.0])
    inc = np.zeros(17)
    inc[3:6] = np.cross([0.0, 0.0, 1.0], dv3) / float(robot.Rs)
    return inc
