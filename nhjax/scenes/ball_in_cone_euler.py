r"""The ball inside a cone in the seed's first formulation: polar coordinates of the contact point and Euler angles, Rabier & Rheinboldt (seed 002), (9.20)-(9.25).

Same body and cone as ``BallInCone`` (see nhjax/scenes/ball_in_cone.py for the
geometry: half opening angle gamma, generator g(alpha), horizontal tangent
e_a(alpha), inward normal n(alpha)). The configuration is the seed's
y = (rho, alpha, phi, theta, psi): the contact point rho g(alpha) on the cone
[m, rad] and the ball's attitude in z-x-z Euler angles [rad],

    R = Rz(phi) Rx(theta) Rz(psi),   w = phi' e3 + theta' Rz(phi) e1 + psi' Rz(phi) Rx(theta) e3

(w the spatial angular velocity). The centre is u = rho g(alpha) + r n(alpha), so
contact is built into the coordinates (the seed's remark: in (9.25) "the contact
was implicit in the choice of the variables"), and the Lagrangian is

    L = m/2 |u'|^2 + J/2 |w|^2 - m g u3,   |u'|^2 = rho'^2 + D^2 alpha'^2,  D = rho sin(gamma) - r cos(gamma),

(the homogeneous ball's rotational energy is J/2 |w|^2 in any frame). The no-slip
conditions are the two tangential components of the contact point's velocity,

    g . (u' - r w x n) = 0,   e_a . (u' - r w x n) = 0,

two nonholonomic constraints on five coordinates (three degrees of freedom). The
engine derives the Lagrange-d'Alembert equations by autodiff.

Our copy of the seed lost (9.20)-(9.25) (the Neimark-Fufaev Lagrangian in
these variables); the above is re-derived, and tests/test_ball_in_cone_euler.py
checks it against the independent (u, p) model ``BallInCone`` to 1e-9. The Euler
angles are singular at sin(theta) = 0 (guard ``gimbal``), the polar chart on the
cone's axis (guard ``axis``, D > chart_eps r), as for BallInCone.

Not in ``nhjax.scenes.REGISTRY`` (exported as a cross-check of BallInCone): over long
runs the attitude passes close to theta = 0 or pi, where the Euler rates grow without
bound; the long-run benchmark's 1e4 radial periods of the Fig. 9.5 motion ran out of
steps (782094 accepted by t = 35740 s at rtol 1e-8) where BallInCone needs no such care.

Units and defaults as BallInCone: m = r = g = 1, J = 0.4, gamma = 1.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import OutsideChartError
from ..lie import so3
from ..mechanics import ConstrainedLagrangian
from ._validate import in_range, real
from .ball_in_cone import cone_frame, cone_parameters
from .ball_on_platter import baumgarte_gains

__all__ = ["BallInConeEuler"]

_GIMBAL_HINT = (
    "the ball's Euler angle theta reached 0 or pi (gimbal lock of the z-x-z angles): the "
    "seed's formulation (9.21)-(9.25) is singular there; use BallInCone (u, p in R^3 x S^3), "
    "which has no such singularity, or use on_guard='stop'."
)
_AXIS_HINT = (
    "the ball's centre reached the cone's axis (D = 0), where the polar coordinates (rho, alpha) "
    "of the contact point end; give the ball an angular momentum about the axis, or use on_guard='stop'."
)


def _vec(a):
    return jnp.concatenate([jnp.zeros_like(a[..., :1]), a], axis=-1)


class BallInConeEuler(ConstrainedLagrangian):
    """Ball inside a cone in (rho, alpha, phi, theta, psi) (seed 002, 9.20-9.25); see the module docstring."""

    m: jax.Array
    r: jax.Array
    J: jax.Array
    gamma: jax.Array
    g: jax.Array
    chart_eps: float = eqx.field(static=True, default=1e-3)
    n: int = eqx.field(static=True, default=5)

    state_names: ClassVar[tuple] = ("rho", "alpha", "phi", "theta", "psi",
                                    "rho_dot", "alpha_dot", "phi_dot", "theta_dot", "psi_dot")
    control_dim: ClassVar[int] = 0
    guard_hints: ClassVar[dict] = {"gimbal": _GIMBAL_HINT, "axis": _AXIS_HINT}
    guard_arguments: ClassVar[dict] = {"gimbal": "theta", "axis": "rho"}

    def __init__(self, m=1.0, r=1.0, J=0.4, gamma=1.0, g=1.0, chart_eps=1e-3, baumgarte=(0.0, 0.0)):
        owner = "BallInConeEuler"
        self.m, self.r, self.J, self.gamma, self.g = cone_parameters(owner, m, r, J, gamma, g)
        self.chart_eps = float(in_range("chart_eps", chart_eps, 0.0, 1.0, hi_closed=False, owner=owner, as_float=True,
                                        shape=(), what="margin of the guards sin(theta) > chart_eps, D > chart_eps r"))
        self.n = 5
        self.baumgarte = baumgarte_gains(owner, baumgarte)

    # ------------------------------------------------------------ geometry
    def frame(self, alpha):
        """(g, e_a, n) at azimuth alpha: generator, horizontal tangent, inward normal (3,) each."""
        return cone_frame(self.gamma, jnp.cos(alpha), jnp.sin(alpha))

    def centre(self, q):
        """u = rho g(alpha) + r n(alpha) [m] (3,)."""
        gv, _, nv = self.frame(q[1])
        return q[0] * gv + self.r * nv

    @staticmethod
    def euler_matrix(phi, theta):
        """E(phi, theta) (3, 3): w = E (phi', theta', psi') for R = Rz(phi) Rx(theta) Rz(psi)."""
        e3 = jnp.array([0.0, 0.0, 1.0])
        c1 = so3.rot_z(phi) @ jnp.array([1.0, 0.0, 0.0])
        c2 = so3.rot_z(phi) @ so3.rot_x(theta) @ e3
        return jnp.stack([e3, c1, c2], axis=1)

    def angular_velocity(self, q, qd):
        """w [rad/s] (3,): the ball's spatial angular velocity."""
        return self.euler_matrix(q[2], q[3]) @ qd[2:5]

    def attitude(self, q):
        """Unit quaternion (scalar first) of R = Rz(phi) Rx(theta) Rz(psi)."""
        h = 0.5 * q[2:5]
        z = jnp.zeros_like(h[0])
        qz1 = jnp.stack([jnp.cos(h[0]), z, z, jnp.sin(h[0])])
        qx = jnp.stack([jnp.cos(h[1]), jnp.sin(h[1]), z, z])
        qz2 = jnp.stack([jnp.cos(h[2]), z, z, jnp.sin(h[2])])
        return so3.quat_mul(so3.quat_mul(qz1, qx), qz2)

    # ------------------------------------------------------------ the model
    def kinetic_energy(self, q, qd):
        ud = jax.jvp(self.centre, (q,), (qd,))[1]
        w = self.angular_velocity(q, qd)
        return 0.5 * self.m * ud @ ud + 0.5 * self.J * w @ w

    def potential_energy(self, q):
        return self.m * self.g * self.centre(q)[2]

    def velocity_constraints(self, t, q, qd):
        gv, ea, nv = self.frame(q[1])
        ud = jax.jvp(self.centre, (q,), (qd,))[1]
        v = ud - self.r * jnp.cross(self.angular_velocity(q, qd), nv)
        return jnp.stack([gv @ v, ea @ v])

    def guards(self, x):
        D = x[0] * jnp.sin(self.gamma) - self.r * jnp.cos(self.gamma)
        return {"gimbal": jnp.abs(jnp.sin(x[3])) - self.chart_eps, "axis": D - self.chart_eps * self.r}

    def invariants(self, x):
        """L = D^2 alpha' [m^2/s] (conserved, as for BallInCone)."""
        D = x[0] * jnp.sin(self.gamma) - self.r * jnp.cos(self.gamma)
        return {"areal_velocity": D**2 * x[6]}

    # ------------------------------------------------------------ states
    def initial_state(self, rho=3.0, alpha=0.0, rho_dot=0.0, alpha_dot=0.3, spin=0.0, phi=0.0, theta=np.pi / 2,
                      psi=0.0):
        """Consistent state: the contact point (rho, alpha) and rates as in
        ``BallInCone.initial_state``, the spin w . n [rad/s], and the Euler angles of the
        attitude [rad] (sin(theta) != 0); the Euler rates follow from w = E (phi', theta', psi')."""
        owner = "BallInConeEuler.initial_state"
        vals = [jnp.asarray(real(k, v, owner=owner, as_float=True), float) for k, v in (
            ("rho", rho), ("alpha", alpha), ("rho_dot", rho_dot), ("alpha_dot", alpha_dot), ("spin", spin),
            ("phi", phi), ("theta", theta), ("psi", psi))]
        rho, alpha, rho_dot, alpha_dot, spin, phi, theta, psi = vals
        D = rho * jnp.sin(self.gamma) - self.r * jnp.cos(self.gamma)
        if not isinstance(D, jax.core.Tracer):
            if not bool(D > self.chart_eps * self.r):
                raise OutsideChartError(
                    "axis", 0.0, f"{owner}: rho = {float(rho)!r} puts the ball's centre on or across the cone's axis "
                    f"(D = {float(D):.3g}); rho must exceed r cot(gamma) = {float(self.r / jnp.tan(self.gamma)):.6g}",
                    name="rho")
            if not bool(jnp.abs(jnp.sin(theta)) > self.chart_eps):
                raise OutsideChartError(
                    "gimbal", 0.0, f"{owner}: theta = {float(theta)!r} is a gimbal lock of the z-x-z Euler angles "
                    "(sin(theta) = 0); pick theta in (0, pi), e.g. pi/2", name="theta")
        gv, ea, nv = self.frame(alpha)
        w = (-alpha_dot * D / self.r) * gv + (rho_dot / self.r) * ea + spin * nv
        rates = jnp.linalg.solve(self.euler_matrix(phi, theta), w)
        return jnp.concatenate([jnp.stack([rho, alpha, phi, theta, psi, rho_dot, alpha_dot]), rates])

    def to_up(self, x):
        """The same physical state as a ``BallInCone`` state (u, p, u', p')."""
        q, qd = x[:5], x[5:]
        u = self.centre(q)
        ud = jax.jvp(self.centre, (q,), (qd,))[1]
        p = self.attitude(q)
        pd = 0.5 * so3.quat_mul(_vec(self.angular_velocity(q, qd)), p)
        return jnp.concatenate([u, p, ud, pd])
