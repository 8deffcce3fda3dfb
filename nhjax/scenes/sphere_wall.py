r"""A sphere rolling without slipping that hits a moving smooth wall: Ibort et al. (seed 004), ex. 10.3.

Model
-----
A sphere of radius r [m], mass m [kg] (the seed: m = 1) and radius of gyration
k [m] about its centre (k^2 = 2 r^2 / 5 for a homogeneous ball) rolls on the
plane z = 0. Coordinates q = (x, y, z, theta, phi, psi): centre [m] and the
Euler angles [rad] of the seed, psi the precession about the vertical, theta
the nutation, phi the spin (z-x-z convention). The angular velocity in space
is

    omega = (theta' cos psi + phi' sin theta sin psi,
             theta' sin psi - phi' sin theta cos psi,
             psi' + phi' cos theta),

so the seed's Lagrangian is

    L = m/2 (x'^2 + y'^2 + z'^2 + k^2 (theta'^2 + phi'^2 + psi'^2 + 2 phi' psi' cos theta)),

and rolling without slipping (contact point at rest: x' = r omega_y,
y' = -r omega_x) and z' = 0 are the permanent constraints (the seed's phi'_1,
phi'_2, phi'_3, "after some algebraic manipulations"):

    x' cos psi + y' sin psi + r phi' sin theta = 0,
    x' sin psi - y' cos psi - r theta' = 0,
    z' = 0.

A smooth wall x = f(t) moves along e1; the sphere stays on the side
x - r >= f(t):  psi_wall(t, q) = x - r - f(t) >= 0, with
f(t) = f0 + V t + a t^2 / 2 + B sin(Omega t) [m]. The wall is smooth, so its
impulse mu is along e1 through the centre (no torque), and the rolling
constraints take their own impulses so that the sphere keeps rolling.

The seed's jump (re-derived; our copy of the paper is partly garbled): with
restitution alpha, x1' - f' = -alpha (x0' - f'), i.e. the wall's impulse is
mu = (1 + alpha)(f' - x0')(k^2 + r^2) / r^2 (for m = 1), and

    dx' = r^2 mu / (k^2 + r^2) = (1 + alpha)(f' - x0'),   dy' = dz' = 0,
    dtheta' = r sin psi mu / (k^2 + r^2),
    dphi'   = -r cos psi mu / ((k^2 + r^2) sin theta),
    dpsi'   = r cos theta cos psi mu / ((k^2 + r^2) sin theta)

(``seed_jump``), which in momenta is the seed's matrix formula
p1 = p0 - (1 + alpha) E p0 + (1 + alpha) f' e with E's only non-zero column
the first, (1, 0, 0, k^2 sin psi / r, -k^2 sin theta cos psi / r, 0), and
e = that column (``seed_momentum_matrix``). The engine's affine projector
(``nhjax.mechanics.impacts``) must give the same. Between impacts the sphere
rolls uniformly (x', y', omega constant).

The Euler-angle chart is singular at sin theta = 0; ``initial_state`` starts
at theta = pi/2, where rolling along e1 keeps theta and psi constant.

Parameters: r [m] > 0 (default 0.1), k [m] > 0 (default sqrt(2/5) r), m [kg] > 0
(default 1), f0 [m] (default 0), V [m/s] (default 0), a [m/s^2] (default 0),
B [m] (default 0), Omega [rad/s] (default 0), restitution alpha in [0, 1]
(default 1). State x = (q, q').
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import OutsideChartError
from ..mechanics import ConstrainedLagrangian
from ..mechanics.impacts import oscillation_resolution
from ._validate import ball_moment, in_range, positive, real, to_device

__all__ = ["RollingSphereWall"]


class RollingSphereWall(ConstrainedLagrangian):
    """Rolling sphere and a moving smooth wall x = f(t) (seed 004, ex. 10.3); see the module docstring."""

    r: jax.Array
    k: jax.Array
    m: jax.Array
    f0: jax.Array
    V: jax.Array
    a: jax.Array
    B: jax.Array
    Omega: jax.Array
    restitution: jax.Array
    n: int = eqx.field(static=True, default=6)

    state_names: ClassVar[tuple] = (
        "x", "y", "z", "theta", "phi", "psi",
        "x_dot", "y_dot", "z_dot", "theta_dot", "phi_dot", "psi_dot",
    )
    control_dim: ClassVar[int] = 0

    def __init__(self, r=0.1, k=None, m=1.0, f0=0.0, V=0.0, a=0.0, B=0.0, Omega=0.0, restitution=1.0):
        positive("r", r)
        k = np.sqrt(2 / 5) * r if k is None else k
        positive("k", k)
        positive("m", m)
        ball_moment("k", np.asarray(m, float) * np.asarray(k, float) ** 2, m, r, owner="RollingSphereWall",
                    label="m k^2", what="radius of gyration k [m]: moment m k^2 about a diameter")
        in_range("restitution", restitution, 0.0, 1.0, owner="RollingSphereWall", what="coefficient of restitution")
        real("f0", f0, owner="RollingSphereWall")
        real("V", V, owner="RollingSphereWall")
        real("a", a, owner="RollingSphereWall")
        real("B", B, owner="RollingSphereWall")
        real("Omega", Omega, owner="RollingSphereWall")
        self.r, self.k, self.m, self.f0, self.V, self.a, self.B, self.Omega, self.restitution = (
            to_device(v) for v in (r, k, m, f0, V, a, B, Omega, restitution))
        self.n = 6

    def kinetic_energy(self, q, qd):
        th = q[3]
        rot = qd[3] ** 2 + qd[4] ** 2 + qd[5] ** 2 + 2 * qd[4] * qd[5] * jnp.cos(th)
        return 0.5 * self.m * (qd[0] ** 2 + qd[1] ** 2 + qd[2] ** 2 + self.k**2 * rot)

    def velocity_constraints(self, t, q, qd):
        th, ps = q[3], q[5]
        return jnp.stack([
            qd[0] * jnp.cos(ps) + qd[1] * jnp.sin(ps) + self.r * qd[4] * jnp.sin(th),
            qd[0] * jnp.sin(ps) - qd[1] * jnp.cos(ps) - self.r * qd[3],
            qd[2],
        ])

    def wall(self, t):
        return self.f0 + self.V * t + 0.5 * self.a * t**2 + self.B * jnp.sin(self.Omega * t)

    def wall_velocity(self, t):
        return self.V + self.a * t + self.B * self.Omega * jnp.cos(self.Omega * t)

    def unilateral_constraints(self, t, q):
        return jnp.stack([q[0] - self.r - self.wall(t)])

    @property
    def event_resolution(self):
        return oscillation_resolution(self.B, self.Omega)

    def angular_velocity(self, q, qd):
        th, ps = q[3], q[5]
        return jnp.stack([
            qd[3] * jnp.cos(ps) + qd[4] * jnp.sin(th) * jnp.sin(ps),
            qd[3] * jnp.sin(ps) - qd[4] * jnp.sin(th) * jnp.cos(ps),
            qd[5] + qd[4] * jnp.cos(th),
        ])

    def initial_state(self, x=0.5, y=0.0, vx=-1.0, vy=0.0, spin=0.0, theta=np.pi / 2, phi=0.0, psi=0.0):
        """Rolling state: centre (x, y, r), velocity (vx, vy) [m/s], vertical spin [rad/s];
        the Euler angles' rates follow from omega = (-vy/r, vx/r, spin)."""
        owner = "RollingSphereWall.initial_state"
        x, y, vx, vy, spin, phi, psi = (real(n, v, owner=owner) for n, v in (
            ("x", x), ("y", y), ("vx", vx), ("vy", vy), ("spin", spin), ("phi", phi), ("psi", psi)))
        theta = real("theta", theta, owner=owner, what="Euler angle [rad]")
        if not isinstance(theta, jax.core.Tracer) and not 0.0 < float(theta) < np.pi:
            raise OutsideChartError(
                "sin_theta", 0.0, f"{owner}: theta = {float(theta)!r} is outside the Euler angles' chart (0, pi): "
                "0 and pi are its singular points; pick theta in (0, pi), e.g. pi/2", name="theta")
        r = self.r
        th, ph, ps = (to_device(v) for v in (theta, phi, psi))
        wx, wy, wz = -jnp.asarray(vy, float) / r, jnp.asarray(vx, float) / r, jnp.asarray(spin, float)
        th_d = wx * jnp.cos(ps) + wy * jnp.sin(ps)
        ph_d = (wx * jnp.sin(ps) - wy * jnp.cos(ps)) / jnp.sin(th)
        ps_d = wz - ph_d * jnp.cos(th)
        q = jnp.stack([jnp.asarray(x, float), jnp.asarray(y, float), r, th, ph, ps])
        qd = jnp.stack([jnp.asarray(vx, float), jnp.asarray(vy, float), 0.0 * r, th_d, ph_d, ps_d])
        return jnp.concatenate([q, qd])

    def invariants(self, x):
        return {}

    # ---------------------------------------------------------------- closed forms
    def seed_jump(self, t, x, alpha=None):
        """Post-impact velocities by the seed's formulas (ex. 10.3)."""
        alpha = self.restitution if alpha is None else alpha
        q, qd = x[:6], x[6:]
        r, k2 = self.r, self.k**2
        th, ps = q[3], q[5]
        mu = (1 + alpha) * (self.wall_velocity(t) - qd[0]) * (k2 + r**2) / r**2
        d = mu / (k2 + r**2)
        dq = jnp.stack([
            r**2 * d, 0.0 * d, 0.0 * d, r * jnp.sin(ps) * d,
            -r * jnp.cos(ps) * d / jnp.sin(th), r * jnp.cos(th) * jnp.cos(ps) * d / jnp.sin(th),
        ])
        return qd + dq

    def seed_momentum_matrix(self, q):
        """(E, e): the seed's matrix formula p1 = p0 - (1+alpha) E p0 + (1+alpha) f'(t) e
        (momenta p = dL/dq' of the mass-1 sphere; for mass m multiply e by m)."""
        r, k2 = self.r, self.k**2
        th, ps = q[3], q[5]
        col = jnp.stack([1.0 + 0 * r, 0 * r, 0 * r, k2 * jnp.sin(ps) / r, -k2 * jnp.sin(th) * jnp.cos(ps) / r, 0 * r])
        E = jnp.zeros((6, 6)).at[:, 0].set(col)
        return E, col
