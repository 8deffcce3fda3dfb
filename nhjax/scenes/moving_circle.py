r"""A free particle inside a moving circular wall: Ibort et al. (seed 004), example 10.1.

Model
-----
A particle of mass 1 [kg] moves freely in the plane, q = (x, y) [m], inside the
wall x^2 + y^2 <= f(t) whose points move along rays through the origin. The
seed writes the constraint as psi = x^2 + y^2 - f(t) <= 0; here every
one-sided constraint is psi >= 0 on the admissible side, so

    L = (x'^2 + y'^2) / 2,        psi(t, q) = f(t) - x^2 - y^2 >= 0,

with f(t) = R(t)^2 and R(t) = R0 + c t + B sin(Omega t) [m] (R0 > 0; c [m/s]
the wall's radial speed; B [m], Omega [rad/s] an oscillation). R must stay
positive over the simulated interval: ``boundary_margins`` declares it, and
``simulate_impacts`` (and the batches) refuse a time span in which R(t) reaches 0
with ``BoundaryError`` before integrating (the circle degenerates to a point there,
and no motion inside it is defined).

Jumps (the seed's closed forms, re-derived: they are what the affine
projector (18) gives with J = -2 q, psi_t = f'):

    plastic, the constraint remains (alpha = 0):
        v1 = v0 - (q q^T / f) v0 + (f' / (2 f)) q,
    elastic (alpha = 1; the wall's velocity V = f'/(2 f) q, v1n + v0n = 2 V):
        v1 = v0 - 2 (q q^T / f) v0 + (f' / f) q,

and for 0 < alpha < 1 the correction (v1 - v0) of the plastic case times
(1 + alpha) (``seed_jump``). After a plastic impact the particle slides along
the moving wall (a persistent contact; the wall pushes inwards, mu > 0, as long
as the particle turns with it): with angular momentum h = x y' - y x' conserved,
R = R(t), the polar angle obeys theta' = h / R^2, so for B = 0

    theta(t) = theta* + (h / c) (1 / R(t*) - 1 / R(t))     (c != 0),
    theta(t) = theta* + h (t - t*) / R0^2                    (c = 0)

(``sliding_angle``). For B = 0 the first impact from q0, v0 is the smallest
positive root of |q0 + v0 t| = R0 + c t, a quadratic (``first_impact_time``).

Parameters: R0 [m] > 0 (default 1), c [m/s] (default 0), B [m] (default 0),
Omega [rad/s] (default 0), restitution alpha in [0, 1] (default 1).
State x = (x, y, x', y').
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..mechanics import ConstrainedLagrangian
from ..mechanics.impacts import oscillation_resolution
from ._validate import in_range, positive, real, to_device

__all__ = ["ParticleInMovingCircle"]


class ParticleInMovingCircle(ConstrainedLagrangian):
    """Free particle inside the wall x^2 + y^2 <= R(t)^2 (seed 004, ex. 10.1); see the module docstring."""

    R0: jax.Array
    c: jax.Array
    B: jax.Array
    Omega: jax.Array
    restitution: jax.Array
    n: int = eqx.field(static=True, default=2)

    state_names: ClassVar[tuple] = ("x", "y", "x_dot", "y_dot")
    control_dim: ClassVar[int] = 0

    def __init__(self, R0=1.0, c=0.0, B=0.0, Omega=0.0, restitution=1.0):
        positive("R0", R0)
        in_range("restitution", restitution, 0.0, 1.0, owner="ParticleInMovingCircle", what="coefficient of restitution")
        real("c", c, owner="ParticleInMovingCircle")
        real("B", B, owner="ParticleInMovingCircle")
        real("Omega", Omega, owner="ParticleInMovingCircle")
        self.R0, self.c, self.B, self.Omega, self.restitution = (
            to_device(v) for v in (R0, c, B, Omega, restitution))
        self.n = 2

    def kinetic_energy(self, q, qd):
        return 0.5 * jnp.dot(qd, qd)

    def radius(self, t):
        return self.R0 + self.c * t + self.B * jnp.sin(self.Omega * t)

    def f(self, t):
        """f(t) = R(t)^2 [m^2]."""
        return self.radius(t) ** 2

    def f_dot(self, t):
        return 2 * self.radius(t) * (self.c + self.B * self.Omega * jnp.cos(self.Omega * t))

    def unilateral_constraints(self, t, q):
        return jnp.stack([self.f(t) - jnp.dot(q, q)])

    def boundary_margins(self, t):
        """What must stay positive for the wall to be a circle: its radius R(t) [m]."""
        return {"radius": self.radius(t)}

    @property
    def event_resolution(self):
        """Largest step [s]: an eighth of the wall's oscillation period (None if it does not oscillate)."""
        return oscillation_resolution(self.B, self.Omega)

    def initial_state(self, x=0.0, y=0.0, vx=1.0, vy=0.0):
        """Position (x, y) [m] inside the wall and velocity (vx, vy) [m/s]."""
        owner = "ParticleInMovingCircle.initial_state"
        vals = [real(n, v, owner=owner) for n, v in (("x", x), ("y", y), ("vx", vx), ("vy", vy))]
        return jnp.asarray(vals, float)

    def invariants(self, x):
        return {"angular_momentum": x[0] * x[3] - x[1] * x[2]}

    # ---------------------------------------------------------------- closed forms
    def seed_jump(self, t, q, v0, alpha=None):
        """The seed's post-impact velocity at the wall (ex. 10.1): plastic (alpha = 0),
        elastic (alpha = 1), and (1 + alpha) times the plastic correction between."""
        alpha = self.restitution if alpha is None else alpha
        f, fd = self.f(t), self.f_dot(t)
        plastic = v0 - jnp.outer(q, q) @ v0 / f + fd / (2 * f) * q
        return v0 + (1 + alpha) * (plastic - v0)

    def first_impact_time(self, x0):
        """Smallest positive t with |q0 + v0 t| = R0 + c t (B = 0, free flight)."""
        q, v = x0[:2], x0[2:]
        a = jnp.dot(v, v) - self.c**2
        b = 2 * (jnp.dot(q, v) - self.R0 * self.c)
        cc = jnp.dot(q, q) - self.R0**2
        disc = jnp.sqrt(b * b - 4 * a * cc)
        # cc < 0 (inside): with a > 0 the positive root is (-b + disc) / (2a); written
        # without cancellation
        return jnp.where(b > 0, -2 * cc / (b + disc), (-b + disc) / (2 * a))

    def sliding_angle(self, t, t_star, theta_star, h):
        """Polar angle while sliding on the wall (B = 0) from theta* at t*, angular momentum h."""
        c = self.c
        safe = jnp.where(c == 0, 1.0, c)
        moving = theta_star + h / safe * (1 / self.radius(t_star) - 1 / self.radius(t))
        fixed = theta_star + h * (t - t_star) / self.R0**2
        return jnp.where(c == 0, fixed, moving)
