r"""A homogeneous ball rolling on a rotating platter: Rabier & Rheinboldt (seed 002), sec. 9.2.

Model (the seed's (u, p) formulation, (9.14)-(9.19))
----------------------------------------------------
The platter is the plane span{e1, e2}, turning at the constant rate ``Omega``
[rad/s] about e3. The ball (mass m [kg], radius r [m], moment of inertia J
[kg m^2] about any axis through its centre; J = 2/5 m r^2 for a solid ball)
has centre u in R^3 and attitude p in S^3 (unit quaternion, scalar first,
body -> space; p and -p are the same ball). Coordinates q = (u1, u2, u3, p0,
p1, p2, p3), state x = (q, q').

    T = m/2 |u'|^2 + J/2 |W|^2,   W = 2 vec(conj(p) p')  (body angular velocity),
    V = m g u3,
    position constraints   u3 - r = 0 (contact),   |p|^2 - 1 = 0,
    velocity constraints   P [u' + w x (x - u) - Omega e3 x x] = 0   (9.15)-(9.17),

with w = 2 vec(p' conj(p)) the spatial angular velocity, x = (u1, u2, 0) the
contact point, x - u = -r e3, and P the projection onto span{e1, e2}: the
material point of the ball at x moves with the platter point under it. (The
vertical component of that condition is d/dt(u3 - r) = 0, already implied.)
The engine derives the DAE (9.18)-(9.19) (M, Coriolis terms, multipliers: the
friction force and the normal force m g) by autodiff; (9.16) R_p w = 2 K(p) p'
is ``spatial_angular_velocity``. The seed's symbols in our copy are garbled; the
above is re-derived from the Lagrangian and the no-slip condition.

Parameters and defaults: m = 1, r = 1, J = 0.6, Omega = 2, g = 1 (the seed's
dimensionless data: lengths in r, J in m r^2, Omega = 2, J = 0.6). The
geometric constraints (|p| = 1, u3 = r) hold at acceleration level; ``simulate``
projects the state back onto them after every step, so Baumgarte terms
(``baumgarte=(alpha, beta)`` [1/s]) are off by default: on top of the
projection they only add stage accelerations the constraints do not call for
(measured, 10 orbits of the centre: error 9.7e-6 with (1, 1) against 6.2e-6
without at rtol 1e-8, 8.2e-8 against 2.9e-8 at 1e-10). Pass gains together
with ``project_steps=False``.

Exact solution (re-derived)
---------------------------
Newton-Euler with the contact force F (horizontal part F_h): m u'' = F_h,
J w' = -r e3 x F. Differentiating the no-slip condition
u' - r w x e3 = Omega e3 x u gives (J + m r^2) u'' = Omega J e3 x u', so the
centre's velocity turns at the constant rate

    kappa = Omega J / (J + m r^2)        (= 2 Omega / 7 for a solid ball)

and the centre runs on a circle of radius |u'| / kappa centred at
c = u + e3 x u' / kappa, whatever the initial spin. (The seed describes its
Fig. 9.4 as an ellipse with a focus at the origin; for a homogeneous ball the
path is this circle, traversed once every 2 pi / kappa.) The vertical spin w3 is
constant (the contact force has no moment about e3 through the centre) and
w_h = (e3 x u' + Omega u_h) / r follows from the constraint.

Invariants of every motion: the speed |u'|, the vertical spin w3, and the Jacobi
integral T + V - Omega L3 (L3: angular momentum about the platter's axis,
m (u x u')_3 + J w3), conserved because in the platter's frame the constraints
are homogeneous. The energy T + V is *not* conserved (the platter does work
through the contact), so ``energy`` returns None and simulate() does not report it.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _programs
from ..errors import ParameterError
from ..lie import so3
from ..mechanics import ConstrainedLagrangian
from ._validate import ball_moment, positive, real, unit_quaternion

__all__ = ["BallOnPlatter"]


def baumgarte_gains(owner, gains):
    """(alpha, beta) [1/s]: two finite, non-negative Baumgarte gains."""
    try:
        a, b = gains
    except (TypeError, ValueError):
        raise ParameterError(f"{owner}: baumgarte must be a pair (alpha, beta) of gains [1/s], got {gains!r}",
                             "baumgarte", gains) from None
    return tuple(float(positive(n, v, allow_zero=True, owner=owner, as_float=True, shape=(), what="Baumgarte gain [1/s]"))
                 for n, v in (("baumgarte[0]", a), ("baumgarte[1]", b)))

E3 = np.array([0.0, 0.0, 1.0])  # numpy: no program to compile at import


def _platter_state(system, u1, u2, u1_dot, u2_dot, spin, p):
    """``BallOnPlatter.initial_state``'s state from its checked numbers (p the attitude):
    the horizontal angular velocity from the no-slip condition."""
    u = jnp.stack([u1, u2, system.r])
    ud = jnp.stack([u1_dot, u2_dot, jnp.zeros(())])
    w_h = (jnp.cross(E3, ud) + system.Omega * u * jnp.array([1.0, 1.0, 0.0])) / system.r
    w = w_h + spin * E3
    pd = 0.5 * so3.quat_mul(_vec(w), p)
    return jnp.concatenate([u, p, ud, pd])


def _vec(a):
    return jnp.concatenate([jnp.zeros_like(a[..., :1]), a], axis=-1)


#: State of a rigid body in R^3 x S^3 with its velocities: centre u, unit quaternion p.
UP_STATE_NAMES = (
    "u1", "u2", "u3", "p0", "p1", "p2", "p3",
    "u1_dot", "u2_dot", "u3_dot", "p0_dot", "p1_dot", "p2_dot", "p3_dot",
)  # fmt: skip


class BallOnPlatter(ConstrainedLagrangian):
    """Homogeneous ball on a platter turning at Omega, in (u, p) in R^3 x S^3 (seed 002, 9.14-9.19).

    See the module docstring for the model, parameters, exact solution and invariants.
    """

    m: jax.Array
    r: jax.Array
    J: jax.Array
    Omega: jax.Array
    g: jax.Array
    n: int = eqx.field(static=True, default=7)
    # Runge-Kutta stages in a scan: a program about a third smaller than with unrolled
    # stages (a first simulate() compiles and a warm one loads that much less), for a
    # little more time per step (benchmarks/compile_times.py)
    large_vector_field: ClassVar[bool] = True

    state_names: ClassVar[tuple] = UP_STATE_NAMES
    control_dim: ClassVar[int] = 0

    def __init__(self, m=1.0, r=1.0, J=0.6, Omega=2.0, g=1.0, baumgarte=(0.0, 0.0)):
        owner = "BallOnPlatter"
        self.m = positive("m", m, owner=owner, what="mass [kg]")
        self.r = positive("r", r, owner=owner, what="radius [m]")
        self.J = ball_moment("J", J, self.m, self.r, owner=owner)
        self.Omega = real("Omega", Omega, owner=owner, what="rate of the platter [rad/s]")
        self.g = positive("g", g, allow_zero=True, owner=owner, what="gravity [m/s^2]")
        self.n = 7
        self.baumgarte = baumgarte_gains(owner, baumgarte)

    # ------------------------------------------------------------ kinematics
    @staticmethod
    def body_angular_velocity(p, pd):
        """W = 2 vec(conj(p) p') [rad/s]."""
        return 2 * so3.quat_mul(so3.quat_conj(p), pd)[..., 1:]

    @staticmethod
    def spatial_angular_velocity(p, pd):
        """w = 2 vec(p' conj(p)) = R_p W [rad/s] (9.16)."""
        return 2 * so3.quat_mul(pd, so3.quat_conj(p))[..., 1:]

    def contact_slip(self, q, qd):
        """Velocity of the ball's material contact point relative to the platter point under it."""
        u, p, ud, pd = q[:3], q[3:], qd[:3], qd[3:]
        w = self.spatial_angular_velocity(p, pd)
        x = u * jnp.array([1.0, 1.0, 0.0])
        return ud + jnp.cross(w, x - u) - self.Omega * jnp.cross(E3, x)

    # ------------------------------------------------------------ the model
    def kinetic_energy(self, q, qd):
        W = self.body_angular_velocity(q[3:], qd[3:])
        return 0.5 * self.m * jnp.dot(qd[:3], qd[:3]) + 0.5 * self.J * jnp.dot(W, W)

    def potential_energy(self, q):
        return self.m * self.g * q[2]

    def position_constraints(self, t, q):
        return jnp.stack([q[2] - self.r, jnp.dot(q[3:], q[3:]) - 1.0])

    def velocity_constraints(self, t, q, qd):
        return self.contact_slip(q, qd)[:2]

    def energy(self, x):
        """None: the moving platter does work, T + V is not conserved (see ``jacobi_integral``)."""
        return None

    # ------------------------------------------------------------ states
    @property
    def turn_rate(self):
        """kappa = Omega J / (J + m r^2) [rad/s]: the rate at which the centre's velocity turns."""
        return self.Omega * self.J / (self.J + self.m * self.r**2)

    def initial_state(self, u1=1.0, u2=0.0, u1_dot=0.0, u2_dot=1.0, spin=0.0, attitude=None):
        """Consistent state: centre (u1, u2, r) [m], centre velocity (u1', u2') [m/s],
        vertical spin w3 [rad/s], attitude (unit quaternion, default identity).
        The horizontal angular velocity follows from the no-slip condition."""
        owner = "BallOnPlatter.initial_state"
        numbers = [real(n, v, owner=owner) for n, v in (
            ("u1", u1), ("u2", u2), ("u1_dot", u1_dot), ("u2_dot", u2_dot), ("spin", spin))]
        p = np.array([1.0, 0.0, 0.0, 0.0]) if attitude is None else unit_quaternion(
            "attitude", attitude, owner=owner, normalize=True)
        # concrete numbers: one compiled program instead of eager operations (small programs
        # compiled in every new process)
        return _programs.small_call("BallOnPlatter.initial_state", _platter_state, self, *numbers, p)

    def angular_velocity(self, x):
        """Spatial angular velocity w [rad/s] at state x."""
        return self.spatial_angular_velocity(x[3:7], x[10:14])

    def angular_momentum_z(self, x):
        """L3 = m (u x u')_3 + J w3 about the platter's axis [kg m^2/s]."""
        u, ud = x[:3], x[7:10]
        return self.m * (u[0] * ud[1] - u[1] * ud[0]) + self.J * self.angular_velocity(x)[2]

    def jacobi_integral(self, x):
        """T + V - Omega L3 [J], conserved (the energy in the platter's frame)."""
        q, qd = self.split(x)
        return (
            self.kinetic_energy(q, qd) + self.potential_energy(q)
            - self.Omega * self.angular_momentum_z(x)
        )

    def circle_centre(self, x):
        """Centre c = u + e3 x u' / kappa of the circle the ball's centre runs on [m] (2,)."""
        u, ud = x[:2], x[7:9]
        return u + jnp.stack([-ud[1], ud[0]]) / self.turn_rate

    def invariants(self, x):
        return {
            "speed": jnp.linalg.norm(x[7:10]),
            "spin_z": self.angular_velocity(x)[2],
            "jacobi_integral": self.jacobi_integral(x),
        }

    # ------------------------------------------------------------ exact solution
    def exact_solution(self, t, x0):
        """Exact centre position (..., 2) and velocity (..., 2) at times t from state x0 at t = 0."""
        t = jnp.asarray(t, float)[..., None]
        k = self.turn_rate
        u0, v0 = x0[:2], x0[7:9]
        c = self.circle_centre(x0)
        ang = k * t
        cs, sn = jnp.cos(ang), jnp.sin(ang)
        rot = lambda a: jnp.concatenate(  # noqa: E731
            [cs * a[0] - sn * a[1], sn * a[0] + cs * a[1]], axis=-1
        )
        v = rot(v0)
        u = c + rot(u0 - c)
        return u, v
