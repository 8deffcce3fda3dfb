r"""A two-wheeled cart on an inclined plane: Rabier & Rheinboldt (seed 002), sec. 9.2, (9.45)-(9.52).

Model
-----
The plane span{e1, e2} is tilted about e2 by ``beta``; e1 points uphill and
gravity pulls along -sin(beta) e1 (and -cos(beta) e3, taken by the plane).
Two sharp-edged wheels of radius r [m] sit on one axle of half-length a [m];
a pole under the cart slides freely so the cart body stays level. Coordinates
q = (x1, x2, theta, phi_l, phi_r): (x1, x2, r) is the point where the cart's
symmetry axis meets the axle (the centre of mass), theta [rad] the angle from
e1 to the symmetry axis s = (cos theta, sin theta), phi_l, phi_r [rad] the
rotation angles of the left and right wheel (at +a n and -a n,
n = (-sin theta, cos theta)).

Rolling without sliding (9.45)-(9.46):

    x1' cos(theta) + x2' sin(theta) - a theta' = r phi_l',
    x1' cos(theta) + x2' sin(theta) + a theta' = r phi_r',
    x1' sin(theta) - x2' cos(theta) = 0            (no lateral sliding),

Lagrangian (9.47):

    L = m/2 (x1'^2 + x2'^2) + Jc/2 theta'^2 + Jw/2 (phi_l'^2 + phi_r'^2) - m g sin(beta) x1,

m [kg] the mass of the whole cart, Jc [kg m^2] its moment of inertia about
the vertical through (x1, x2, r), Jw [kg m^2] the axial moment of each wheel.
The engine derives the equations of motion (9.49)-(9.51) by autodiff.

Re-derivations. The seed's copy gives the direction of gravity as
(sin beta, 0, -cos beta), but also says that the initial velocity (9.52) with
a positive first component "points upward" and that gravity then makes the
cart roll back down; we take gravity along -e1 (as for the skate), which
agrees with that description. The seed's dimensionless data a = 0.5, Jc = 1,
Jw = 0.5, g = 0.3 are lengths in r, inertias in m r^2, and g standing for
g sin(beta) in units r / time^2; defaults: m = r = 1, a = 0.5, Jc = 1,
Jw = 0.5, g = 0.3, beta = pi/2 (so that g sin(beta) = 0.3).

Exact solution. With v = x' . s (speed along the symmetry axis) the constraints
give x' = v s, r phi_l' = v - a theta', r phi_r' = v + a theta', and

    T = (m + 2 Jw/r^2)/2 v^2 + (Jc + 2 Jw a^2/r^2)/2 theta'^2,

so theta'' = 0 (no moment about the vertical) and
(m + 2 Jw/r^2) v' = -m g sin(beta) cos(theta): the cart is a skate
(``nhjax.scenes.Skate``) with heading theta and effective slope acceleration
G = m g sin(beta) / (m + 2 Jw / r^2). For theta' = w != 0,

    v = v0 - (G/w)(sin theta - sin theta0),

and the path has cusps where v changes sign (sin theta = sin theta0 + v0 w / G),
all on the line x1 = x10 + (m + 2 Jw/r^2) v0^2 / (2 m g sin beta) (energy: the
turning energy is constant, so the translational and wheel energy trade with
x1 alone and vanish at the cusps). With v0 != 0 the
forward and backward swings between cusps differ in depth, as the seed notes.
``exact_solution`` gives the whole state.

Invariants of every motion: energy (reported by simulate) and the turning rate theta'.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..mechanics import ConstrainedLagrangian
from ._validate import on_host, positive, real

__all__ = ["TwoWheeledCart"]


class TwoWheeledCart(ConstrainedLagrangian):
    """Two-wheeled cart on an inclined plane (seed 002, 9.45-9.52); see the module docstring."""

    m: jax.Array
    r: jax.Array
    a: jax.Array
    Jc: jax.Array
    Jw: jax.Array
    g: jax.Array
    beta: jax.Array
    n: int = eqx.field(static=True, default=5)

    state_names: ClassVar[tuple] = (
        "x1", "x2", "theta", "phi_l", "phi_r",
        "x1_dot", "x2_dot", "theta_dot", "phi_l_dot", "phi_r_dot",
    )  # fmt: skip
    control_dim: ClassVar[int] = 0

    def __init__(self, m=1.0, r=1.0, a=0.5, Jc=1.0, Jw=0.5, g=0.3, beta=jnp.pi / 2):
        owner = "TwoWheeledCart"
        what = {"m": "mass of the cart [kg]", "r": "wheel radius [m]", "a": "half-length of the axle [m]",
                "Jc": "moment of inertia about the vertical [kg m^2]", "Jw": "axial moment of a wheel [kg m^2]"}
        self.m, self.r, self.a, self.Jc, self.Jw = (
            positive(n, v, owner=owner, what=what[n]) for n, v in (("m", m), ("r", r), ("a", a), ("Jc", Jc), ("Jw", Jw)))
        self.g = positive("g", g, allow_zero=True, owner=owner, what="gravity [m/s^2]")
        self.beta = real("beta", beta, owner=owner, what="tilt of the plane [rad]")
        self.n = 5

    # ------------------------------------------------------------ the model
    def kinetic_energy(self, q, qd):
        return (
            0.5 * self.m * (qd[0] ** 2 + qd[1] ** 2)
            + 0.5 * self.Jc * qd[2] ** 2
            + 0.5 * self.Jw * (qd[3] ** 2 + qd[4] ** 2)
        )

    def potential_energy(self, q):
        return self.m * self.g * jnp.sin(self.beta) * q[0]

    def velocity_constraints(self, t, q, qd):
        c, s = jnp.cos(q[2]), jnp.sin(q[2])
        along = qd[0] * c + qd[1] * s
        return jnp.stack([
            along - self.a * qd[2] - self.r * qd[3],
            along + self.a * qd[2] - self.r * qd[4],
            qd[0] * s - qd[1] * c,
        ])  # fmt: skip

    # ------------------------------------------------------------ states
    def initial_state(self, x1=0.0, x2=0.0, theta=0.0, phi_l=0.0, phi_r=0.0, speed=0.0, theta_dot=0.0):
        """Consistent state from the pose, the speed along the symmetry axis [m/s]
        and the turning rate [rad/s]; the wheel rates follow from rolling."""
        x1, x2, th, pl, pr, v, w = (real(n, z, owner="TwoWheeledCart.initial_state") for n, z in (
            ("x1", x1), ("x2", x2), ("theta", theta), ("phi_l", phi_l), ("phi_r", phi_r), ("speed", speed),
            ("theta_dot", theta_dot)))
        return on_host(lambda xp, a, r, x1, x2, th, pl, pr, v, w: xp.stack([
            x1, x2, th, pl, pr,
            v * xp.cos(th), v * xp.sin(th), w,
            (v - a * w) / r, (v + a * w) / r,
        ]), self.a, self.r, x1, x2, th, pl, pr, v, w)  # fmt: skip

    def speed(self, x):
        """Speed along the symmetry axis v = x' . (cos theta, sin theta) [m/s]."""
        return x[5] * jnp.cos(x[2]) + x[6] * jnp.sin(x[2])

    @property
    def slope_acceleration(self):
        """G = m g sin(beta) / (m + 2 Jw / r^2) [m/s^2]: v' = -G cos(theta)."""
        return self.m * self.g * jnp.sin(self.beta) / (self.m + 2 * self.Jw / self.r**2)

    def invariants(self, x):
        return {"turn_rate": x[7]}

    def exact_solution(self, t, x0):
        """Exact state at times t (any shape) from a consistent state x0 at t = 0 (theta' != 0)."""
        t = jnp.asarray(t, float)
        G = self.slope_acceleration
        th0, w, v0 = x0[2], x0[7], self.speed(x0)
        th = th0 + w * t
        s0, c0, s, c = jnp.sin(th0), jnp.cos(th0), jnp.sin(th), jnp.cos(th)
        v = v0 - G / w * (s - s0)
        x1 = x0[0] + v0 * (s - s0) / w - G / w * ((s * s - s0 * s0) / (2 * w) - s0 * (s - s0) / w)
        x2 = x0[1] + v0 * (c0 - c) / w - G / w * (
            t / 2 - (jnp.sin(2 * th) - jnp.sin(2 * th0)) / (4 * w) - s0 * (c0 - c) / w
        )
        arc = v0 * t - G / w * ((c0 - c) / w - s0 * t)  # integral of v
        pl = x0[3] + (arc - self.a * w * t) / self.r
        pr = x0[4] + (arc + self.a * w * t) / self.r
        wb = jnp.broadcast_to(w, t.shape)
        return jnp.stack(
            [x1, x2, th, pl, pr, v * c, v * s, wb, (v - self.a * w) / self.r, (v + self.a * w) / self.r],
            axis=-1,
        )

    def cusp_times(self, x0, t1):
        """Times in (0, t1] where the cart stops and reverses (v = 0), from the exact solution."""
        import numpy as np

        G, w = float(self.slope_acceleration), float(x0[7])
        th0, v0 = float(x0[2]), float(self.speed(x0))
        k = np.sin(th0) + v0 * w / G  # sin(theta) at the cusps
        if abs(k) > 1:
            return np.zeros(0)
        base = np.array([np.arcsin(k), np.pi - np.arcsin(k)])
        out = []
        turns = int(abs(w) * t1 / (2 * np.pi)) + 3
        for n in range(-turns, turns + 1):
            for b in base:
                tt = (b + 2 * np.pi * n - th0) / w
                if 1e-12 < tt <= t1:
                    out.append(tt)
        return np.unique(np.array(out))
