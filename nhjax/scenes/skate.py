r"""A skate (knife edge) on an inclined plane: Rabier & Rheinboldt (seed 002), sec. 9.1.

Model
-----
A rigid body touches the plane span{e1, e2} at one point, which is also its
centre of mass, through a sharp edge that points along (cos phi, sin phi): the
contact point may move along the edge but not across it. The plane is tilted
about e2 by ``beta``; gravity points along -sin(beta) e1 - cos(beta) e3, so e1
is "uphill". Coordinates q = (u1, u2, phi): contact point [m] and heading [rad].

Lagrangian (9.1)-(9.2) and constraint (9.1):

    L = m/2 (u1'^2 + u2'^2) + J/2 phi'^2 - m g sin(beta) u1,
    sin(phi) u1' - cos(phi) u2' = 0.

The engine (``nhjax.mechanics.ConstrainedLagrangian``) derives the DAE (9.3)
from these by autodiff:

    m u1'' = -m g sin(beta) + lam sin(phi),   m u2'' = -lam cos(phi),   J phi'' = 0,

with lam the lateral force of the edge [N] (the multiplier returned by
``accelerations``). Parameters: m [kg] > 0, J [kg m^2] > 0 (moment of inertia
about e3), g [m/s^2] >= 0, beta [rad]. Defaults m = J = g = 1, beta = 0 (the
seed's dimensionless units: lengths in a reference length, times such that g = 1).
State x = (u1, u2, phi, u1', u2', phi').

Exact solutions (re-derived; the seed's formulas are garbled in our copy)
-------------------------------------------------------------------------
phi'' = 0, so phi = phi0 + a t (the seed's ``a`` is the spin phi0'). The speed
v along the edge, u' = v (cos phi, sin phi), obeys v' = -g sin(beta) cos(phi);
with G = g sin(beta) and a != 0,

    v(t)  = v0 - (G/a) (sin phi - sin phi0),
    u1(t) = u10 + v0 (sin phi - sin phi0)/a
            - (G/a) [(sin^2 phi - sin^2 phi0)/(2a) - sin phi0 (sin phi - sin phi0)/a],
    u2(t) = u20 + v0 (cos phi0 - cos phi)/a
            - (G/a) [t/2 - (sin 2phi - sin 2phi0)/(4a) - sin phi0 (cos phi0 - cos phi)/a],
    lam(t) = m G sin(phi) - m v phi'.

Special cases in the seed: beta = 0 with u0 = 0, phi0 = 0, u0' = (-4, 0),
phi0' = 2 (``initial_state(speed=-4, phi_dot=2)``) is the circle of radius 2
centred at (0, -2), u = (-2 sin 2t, 2 cos 2t - 2); from rest with spin w
(``initial_state(phi_dot=w)``) the contact point traces the cycloid
u1 = -(G/2w^2) sin^2(w t), u2 = -(G/2w)(t - sin(2wt)/(2w)), whose cusps (the
skate stops and reverses) lie at t = k pi/w, u = (0, -k pi G/(2 w^2)). The seed
(G = 1, w = 1, beta = arcsin 1) prints the cusps at (0, k pi/2): with gravity
along -e1 as stated there, u2 decreases, so the sign was lost in extraction.

Invariants of every motion: energy (reported by simulate) and the spin phi'.

``SkateSE2`` is the same skate on the group SE(2), for the engine's Hamel
equations (``nhjax.mechanics.LieLagrangian``): the pose g = (u, phi) moves by
g' = g hat(v) with body velocity v = (v_along, v_across, phi'), the Lagrangian
is the same, and the edge constraint reads v_across = 0. Integrated with
``nhjax.RKMK45`` the pose stays on SE(2) and, on the horizontal plane, where
the body velocity is constant, the circle is reproduced to round-off (Lie-group
methods integrate g' = g hat(const) exactly). ``Skate`` (the index-reduced DAE
in R^6) is the general model; the two cross-check each other.

Seed anchor: DAENH (which stays on the constraint manifold by local
parametrisations) has max error 0.4e-7 over 10 revolutions of the circle and
0.2e-7 over 10 loops of the cycloid at rtol 1e-8. Measured here at rtol 1e-8,
atol 1e-12 (tests/test_skate.py, experiments/skate_cycloid.py): circle 1e-10
with ``SkateSE2`` (RKMK45), 4.2e-8 with ``Skate`` and
``simulate(project_steps=True)`` (Tsit5), 1.9e-6 with ``Skate`` unprojected;
cycloid 6.9e-9 (``Skate``, projected), 1.5e-8 (unprojected), 2.6e-7 (``SkateSE2``).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..lie import SE2Body
from ..mechanics import ConstrainedLagrangian, LieLagrangian
from ._validate import on_host, positive, real

__all__ = ["Skate", "SkateSE2"]


def _parameters(owner, m, J, g, beta):
    return (positive("m", m, owner=owner, what="mass [kg]"),
            positive("J", J, owner=owner, what="moment of inertia about e3 [kg m^2]"),
            positive("g", g, allow_zero=True, owner=owner, what="gravity [m/s^2]"),
            real("beta", beta, owner=owner, what="tilt of the plane [rad]"))


def _state_args(owner, **kw):
    return [real(name, v, owner=f"{owner}.initial_state") for name, v in kw.items()]


class Skate(ConstrainedLagrangian):
    """Knife-edge skate on a plane tilted by ``beta`` (seed 002, 9.1-9.3); see the module docstring."""

    m: jax.Array
    J: jax.Array
    g: jax.Array
    beta: jax.Array
    n: int = eqx.field(static=True, default=3)

    state_names: ClassVar[tuple] = ("u1", "u2", "phi", "u1_dot", "u2_dot", "phi_dot")
    control_dim: ClassVar[int] = 0

    def __init__(self, m=1.0, J=1.0, g=1.0, beta=0.0):
        self.m, self.J, self.g, self.beta = _parameters("Skate", m, J, g, beta)
        self.n = 3

    # ------------------------------------------------------------ the model
    def kinetic_energy(self, q, qd):
        return 0.5 * self.m * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * self.J * qd[2] ** 2

    def potential_energy(self, q):
        return self.m * self.g * jnp.sin(self.beta) * q[0]

    def velocity_constraints(self, t, q, qd):
        return jnp.stack([jnp.sin(q[2]) * qd[0] - jnp.cos(q[2]) * qd[1]])

    # ------------------------------------------------------------ states
    def initial_state(self, u1=0.0, u2=0.0, phi=0.0, speed=0.0, phi_dot=0.0):
        """State with contact point (u1, u2) [m], heading phi [rad], velocity
        ``speed`` [m/s] along the edge (negative: backwards) and spin phi_dot [rad/s]."""
        u1, u2, phi, v, w = _state_args(type(self).__name__, u1=u1, u2=u2, phi=phi, speed=speed, phi_dot=phi_dot)
        return on_host(lambda xp, u1, u2, phi, v, w: xp.stack([u1, u2, phi, v * xp.cos(phi), v * xp.sin(phi), w]),
                       u1, u2, phi, v, w)

    def speed(self, x):
        """Signed speed along the edge, v = u' . (cos phi, sin phi) [m/s]."""
        return x[3] * jnp.cos(x[2]) + x[4] * jnp.sin(x[2])

    def invariants(self, x):
        return {"spin": x[5]}

    # ------------------------------------------------------------ exact solution
    def exact_solution(self, t, x0):
        """Exact state at times t (any shape) from a consistent initial state x0 at t = 0."""
        t = jnp.asarray(t, float)
        G = self.g * jnp.sin(self.beta)
        u10, u20, phi0, w = x0[0], x0[1], x0[2], x0[5]
        v0 = self.speed(x0)
        phi = phi0 + w * t
        s0, c0, s, c = jnp.sin(phi0), jnp.cos(phi0), jnp.sin(phi), jnp.cos(phi)
        turning = jnp.abs(w) > 1e-12
        a = jnp.where(turning, w, 1.0)
        v_turn = v0 - G / a * (s - s0)
        u1_turn = u10 + v0 * (s - s0) / a - G / a * ((s * s - s0 * s0) / (2 * a) - s0 * (s - s0) / a)
        u2_turn = u20 + v0 * (c0 - c) / a - G / a * (
            t / 2 - (jnp.sin(2 * phi) - jnp.sin(2 * phi0)) / (4 * a) - s0 * (c0 - c) / a
        )
        # phi' = 0: uniformly accelerated motion along the fixed edge direction
        v_str = v0 - G * c0 * t
        d_str = v0 * t - G * c0 * t * t / 2
        v = jnp.where(turning, v_turn, v_str)
        u1 = jnp.where(turning, u1_turn, u10 + d_str * c0)
        u2 = jnp.where(turning, u2_turn, u20 + d_str * s0)
        return jnp.stack([u1, u2, phi, v * c, v * s, jnp.broadcast_to(w, t.shape)], axis=-1)

    def exact_multiplier(self, t, x0):
        """Exact lateral force lam(t) [N] (the engine's multiplier) of the motion from x0."""
        x = self.exact_solution(t, x0)
        G = self.g * jnp.sin(self.beta)
        v = x[..., 3] * jnp.cos(x[..., 2]) + x[..., 4] * jnp.sin(x[..., 2])
        return self.m * G * jnp.sin(x[..., 2]) - self.m * v * x[..., 5]

    def multiplier(self, t, x):
        """Lateral force lam [N] of the edge at state x, from the engine's KKT solve."""
        return self.accelerations(t, x[:3], x[3:])[1][0]

    def lie_model(self):
        """The same skate on SE(2) (``SkateSE2``), for the Lie-group solvers."""
        return SkateSE2(self.m, self.J, self.g, self.beta)


class SkateSE2(LieLagrangian):
    """The skate on SE(2), for the engine's Hamel equations: state ((g,), v).

    g is the 3x3 homogeneous pose of the skate (contact point u, heading phi),
    v = (v_along, v_across, phi') its body velocity; L = m/2 (v_along^2 +
    v_across^2) + J/2 phi'^2 - m g sin(beta) u1 and the edge constraint is
    v_across = 0. ``nhjax.simulate`` integrates it with ``nhjax.RKMK45``.
    See the module docstring.
    """

    m: jax.Array
    J: jax.Array
    g: jax.Array
    beta: jax.Array

    state_names: ClassVar[tuple] = ()
    control_dim: ClassVar[int] = 0

    def __init__(self, m=1.0, J=1.0, g=1.0, beta=0.0):
        self.m, self.J, self.g, self.beta = _parameters("SkateSE2", m, J, g, beta)

    @property
    def config_spaces(self):
        return (SE2Body(),)

    def lagrangian(self, g, v):
        pose = g[0]
        kinetic = 0.5 * self.m * (v[0] ** 2 + v[1] ** 2) + 0.5 * self.J * v[2] ** 2
        return kinetic - self.m * self.g * jnp.sin(self.beta) * pose[0, 2]

    def velocity_constraints(self, t, g, v):
        return v[1:2]

    def skate(self):
        return Skate(self.m, self.J, self.g, self.beta)

    def initial_state(self, u1=0.0, u2=0.0, phi=0.0, speed=0.0, phi_dot=0.0):
        """Same arguments as ``Skate.initial_state``."""
        return self.from_flat(self.skate().initial_state(u1, u2, phi, speed, phi_dot))

    def from_flat(self, x):
        """((g,), v) from a ``Skate`` state (u1, u2, phi, u1', u2', phi')."""
        def parts(xp, x):
            c, s = xp.cos(x[2]), xp.sin(x[2])
            v = xp.stack([x[3] * c + x[4] * s, -x[3] * s + x[4] * c, x[5]])
            g = xp.stack([xp.stack([c, -s, x[0]]), xp.stack([s, c, x[1]]), xp.stack([0.0 * c, 0.0 * c, 1.0 + 0.0 * c])])
            return (g,), v

        return on_host(parts, x)

    def to_flat(self, y):
        """``Skate`` states from ((g,), v), batched along a leading time axis or not
        (phi is unwrapped along the batch)."""
        (g,), v = y
        phi = jnp.arctan2(g[..., 1, 0], g[..., 0, 0])
        if phi.ndim == 1:
            phi = jnp.unwrap(phi)
        c, s = g[..., 0, 0], g[..., 1, 0]
        ud = jnp.stack([v[..., 0] * c - v[..., 1] * s, v[..., 0] * s + v[..., 1] * c], axis=-1)
        return jnp.concatenate([g[..., :2, 2], phi[..., None], ud, v[..., 2:3]], axis=-1)

    def invariants(self, y):
        return {"spin": y[1][2]}
