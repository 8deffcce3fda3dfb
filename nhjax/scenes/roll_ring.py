r"""The roll-ring transmission with a shock absorber and a double pendulum: Rabier & Rheinboldt (seed 002), sec. 9.1, (9.8)-(9.13), Figs. 9.2-9.3.

A planar multibody mechanism with mixed constraints (one nonholonomic, four
holonomic) and a spring-damper. Everything moves in the vertical (e1, e2)-plane,
e1 along the driveshaft, gravity -g e2.

Bodies and coordinates (the seed's configuration vector, in this order)
---------------------------------------------------------------------
q = (u_r, beta, u_s, v1, v2, alpha1, w1, w2, alpha2):

* the ring body (mass m_r [kg]) slides along the shaft, position u_r [m]; its
  rings are tilted by beta [rad] (moment of inertia J_r [kg m^2] about the tilt
  axis). Rolling on the shaft, which turns at a constant rate, drives it along
  the shaft at the speed (9.8)

      u_r' = c tan(beta)                                  (nonholonomic),

  c = rho_shaft Omega [m/s] the shaft's surface speed (``drive_speed``): a ring
  tilted by beta rolls along a helix of lead angle beta. An external moment N(t)
  [N m] tilts the rings (``moment``, below).
* the shock absorber (mass m_s [kg]) moves along e1 at u_s [m], tied to the ring
  body by a spring (constant gamma [N/m], relaxed at u_s = u_r) and a damper
  (constant delta [N s/m]) acting on u_s - u_r;
* from the shock absorber's centre hangs a planar double pendulum of two
  uniform bars (lengths l1, l2 [m], masses m1, m2 [kg], moments of inertia
  J_i = m_i l_i^2 / 12 about their centres), centres v, w in R^2, angles
  alpha1, alpha2 [rad] from the downward vertical -e2. The pivots are the
  holonomic constraints

      v - (u_s, 0) - l1/2 (sin alpha1, -cos alpha1) = 0,
      w - (u_s, 0) - l1 (sin alpha1, -cos alpha1) - l2/2 (sin alpha2, -cos alpha2) = 0,

  differentiated once into kinematic constraints (sec. 6.2).

Equations of motion: A q'' = f + G^T lam with A = diag(m_r, J_r, m_s, m1, m1, J1,
m2, m2, J2) (as in the seed), f the damper force -delta (u_s' - u_r') on u_s (and
its reaction on u_r), the moment N(t) on beta and gravity on the bars, G the
Jacobian of the five velocity-level constraints; the engine
(``ConstrainedLagrangian``) derives them by autodiff. The constraint force of
(9.8) acts on u_r only (virtual displacements keep u_r fixed), so the tilt obeys
J_r beta'' = N(t) exactly.

The moment N(t) = a v(t) (a = ``moment_scale`` [N m], the seed's 1.0e-3): v is
piecewise constant, 0, +1, 0, -1, 0, -1, 0, +1, 0 between the eight switching
times t0 = 0.5, 1.0, 1.5, 2.0, 5.5, 6.0, 6.5, 7.0 s, each jump replaced by the
cubic 3 s^2 - 2 s^3 (s = (t - t0 + 0.1) / 0.2) on |t - t0| < 0.1 s: the rings are
tilted up, held (the ring body travels at c tan(beta)), and tilted back.

Energy balance (the test of the damper and the drive)
-----------------------------------------------------
E = T + m1 g v2 + m2 g w2 + gamma/2 (u_s - u_r)^2 is not conserved: the damper
dissipates delta (u_s' - u_r')^2, the moment supplies N beta', and the shaft
supplies the power of the constraint force of (9.8) (an affine constraint: its
force does work lam c tan(beta)). The state carries both ledgers,

    x = (q, q', D, W),  D' = delta (u_s' - u_r')^2,  W' = N(t) beta' + (G^T lam) . q',

so that E + D - W is an invariant (``energy_balance``, reported by simulate()).
With the shaft at rest (c = 0) and no moment, W stays 0 and this is
E(t) + D(t) = E(0) (tests/test_roll_ring.py checks D against a quadrature of the
saved velocities, independently of the ledger).

Our copy of the seed lost the formulas (9.8)-(9.13), the data and the values of
the piecewise constant function; only the prose, the structure of A and the
switching times survived. The form of (9.8) (u_r' = c tan(beta)), the signs of
v(t), the spring's rest length (zero extension at u_s = u_r) and all the
parameter values below are ours, chosen to give the behaviour the seed
describes (the ring body moves while the rings are tilted, the absorber and the
pendulum follow through the spring-damper).

Units SI. Defaults: m_r = 2 kg, J_r = 5e-3 kg m^2, m_s = 1 kg, m1 = m2 = 0.5 kg,
l1 = l2 = 0.4 m, gamma = 100 N/m, delta = 5 N s/m, g = 9.81 m/s^2, c = 1 m/s,
a = 1e-3 N m (a tilt of 0.1 rad while held). N(t) is only C^1 at the edges of
the smoothing windows: pass ``jump_ts=RollRing.kink_times()`` to simulate(). Guard ``tilt``: cos(beta) > chart_eps
(tan(beta) in (9.8)).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..mechanics import ConstrainedLagrangian
from ..mechanics._kkt import kkt_accelerations
from ._validate import chart_argument, in_range, on_host, positive, real
from .ball_on_platter import baumgarte_gains

__all__ = ["RollRing"]

SWITCH_TIMES = (0.5, 1.0, 1.5, 2.0, 5.5, 6.0, 6.5, 7.0)
SWITCH_LEVELS = (0.0, 1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0, 0.0)  # v(t) before, between and after them
SMOOTH_HALF_WIDTH = 0.1

_TILT_HINT = (
    "the rings' tilt beta reached +-pi/2, where the drive (9.8) u_r' = c tan(beta) is singular: "
    "reduce the moment (moment_scale) or shorten the run, or use on_guard='stop'."
)


def drive_profile(t):
    """v(t): the seed's piecewise constant drive with each of its eight jumps replaced by a
    cubic on |t - t0| < 0.1 s (dimensionless; N(t) = moment_scale v(t))."""
    t = jnp.asarray(t)
    v = jnp.full_like(t, SWITCH_LEVELS[0], dtype=float)
    for t0, lo, hi in zip(SWITCH_TIMES, SWITCH_LEVELS[:-1], SWITCH_LEVELS[1:]):
        s = jnp.clip((t - t0 + SMOOTH_HALF_WIDTH) / (2 * SMOOTH_HALF_WIDTH), 0.0, 1.0)
        v = v + (hi - lo) * s * s * (3 - 2 * s)
    return v


STATE_NAMES = ("u_r", "beta", "u_s", "v1", "v2", "alpha1", "w1", "w2", "alpha2",
               "u_r_dot", "beta_dot", "u_s_dot", "v1_dot", "v2_dot", "alpha1_dot", "w1_dot", "w2_dot", "alpha2_dot",
               "dissipated", "supplied")



def _ring_state(xp, l1, l2, drive_speed, vals):
    """``RollRing.initial_state``'s arithmetic (numpy on concrete numbers: ``on_host``)."""
    b = vals["beta"]
    a1, a2, s = vals["alpha1"], vals["alpha2"], vals["u_s"]
    a1d, a2d, sd = vals["alpha1_dot"], vals["alpha2_dot"], vals["u_s_dot"]
    e1, e2 = xp.stack([xp.sin(a1), -xp.cos(a1)]), xp.stack([xp.sin(a2), -xp.cos(a2)])
    f1, f2 = xp.stack([xp.cos(a1), xp.sin(a1)]), xp.stack([xp.cos(a2), xp.sin(a2)])
    p0 = xp.stack([s, 0.0 * s])
    p0d = xp.stack([sd, 0.0 * sd])
    v = p0 + 0.5 * l1 * e1
    w = p0 + l1 * e1 + 0.5 * l2 * e2
    vd = p0d + 0.5 * l1 * a1d * f1
    wd = p0d + l1 * a1d * f1 + 0.5 * l2 * a2d * f2
    q = xp.concatenate([xp.stack([vals["u_r"], b, s]), v, a1[None], w, a2[None]])
    qd = xp.concatenate([xp.stack([drive_speed * xp.tan(b), vals["beta_dot"], sd]), vd, a1d[None], wd,
                          a2d[None]])
    return xp.concatenate([q, qd, xp.zeros(2)])


class RollRing(ConstrainedLagrangian):
    """The roll-ring model (seed 002, 9.8-9.13): ring body, shock absorber, double pendulum,
    one nonholonomic and four holonomic constraints, spring-damper; see the module docstring."""

    m_r: jax.Array
    J_r: jax.Array
    m_s: jax.Array
    m1: jax.Array
    m2: jax.Array
    l1: jax.Array
    l2: jax.Array
    gamma: jax.Array
    delta: jax.Array
    g: jax.Array
    drive_speed: jax.Array
    moment_scale: jax.Array
    chart_eps: float = eqx.field(static=True, default=1e-3)
    n: int = eqx.field(static=True, default=9)

    state_names: ClassVar[tuple] = STATE_NAMES
    control_dim: ClassVar[int] = 0
    guard_hints: ClassVar[dict] = {"tilt": _TILT_HINT}
    guard_arguments: ClassVar[dict] = {"tilt": "beta"}

    def __init__(self, m_r=2.0, J_r=5e-3, m_s=1.0, m1=0.5, m2=0.5, l1=0.4, l2=0.4, gamma=100.0, delta=5.0, g=9.81,
                 drive_speed=1.0, moment_scale=1e-3, chart_eps=1e-3, baumgarte=(0.0, 0.0)):
        owner = "RollRing"
        self.m_r = positive("m_r", m_r, owner=owner, what="mass of the ring body [kg]")
        self.J_r = positive("J_r", J_r, owner=owner, what="moment of inertia of the rings about the tilt axis [kg m^2]")
        self.m_s = positive("m_s", m_s, owner=owner, what="mass of the shock absorber [kg]")
        self.m1 = positive("m1", m1, owner=owner, what="mass of the first bar [kg]")
        self.m2 = positive("m2", m2, owner=owner, what="mass of the second bar [kg]")
        self.l1 = positive("l1", l1, owner=owner, what="length of the first bar [m]")
        self.l2 = positive("l2", l2, owner=owner, what="length of the second bar [m]")
        self.gamma = positive("gamma", gamma, allow_zero=True, owner=owner, what="spring constant [N/m]")
        self.delta = positive("delta", delta, allow_zero=True, owner=owner, what="damping constant [N s/m]")
        self.g = positive("g", g, allow_zero=True, owner=owner, what="gravity [m/s^2]")
        self.drive_speed = real("drive_speed", drive_speed, owner=owner,
                                what="surface speed c of the driveshaft in (9.8) [m/s]")
        self.moment_scale = real("moment_scale", moment_scale, owner=owner,
                                 what="scale a of the tilting moment N(t) = a v(t) [N m]")
        self.chart_eps = float(in_range("chart_eps", chart_eps, 0.0, 1.0, hi_closed=False, owner=owner, as_float=True,
                                        shape=(), what="margin of the tilt guard cos(beta) > chart_eps"))
        self.n = 9
        self.baumgarte = baumgarte_gains(owner, baumgarte)

    # ------------------------------------------------------------ the model
    def bar_inertias(self):
        """(J1, J2) = (m1 l1^2 / 12, m2 l2^2 / 12) [kg m^2]: uniform bars about their centres."""
        return self.m1 * self.l1**2 / 12, self.m2 * self.l2**2 / 12

    def mass_diagonal(self):
        """The seed's A = diag(m_r, J_r, m_s, m1, m1, J1, m2, m2, J2)."""
        J1, J2 = self.bar_inertias()
        return jnp.stack([self.m_r, self.J_r, self.m_s, self.m1, self.m1, J1, self.m2, self.m2, J2])

    def kinetic_energy(self, q, qd):
        return 0.5 * jnp.sum(self.mass_diagonal() * qd * qd)

    def potential_energy(self, q):
        return self.g * (self.m1 * q[4] + self.m2 * q[7]) + 0.5 * self.gamma * (q[2] - q[0]) ** 2

    @staticmethod
    def kink_times():
        """The 16 times [s] t0 -+ 0.1 where N(t) is only C^1 (its second derivative jumps):
        pass them as ``simulate(..., jump_ts=RollRing.kink_times())`` so that steps land there
        (at rtol 1e-8 this cuts the error at t = 10 s from 1e-4 to 1e-7, at the same step count)."""
        return jnp.array(sorted(t0 + d for t0 in SWITCH_TIMES for d in (-SMOOTH_HALF_WIDTH, SMOOTH_HALF_WIDTH)))

    def moment(self, t):
        """N(t) = a v(t) [N m]: the tilting moment on the rings."""
        return self.moment_scale * drive_profile(t)

    def pivots(self, q):
        """Positions [m] (2,) of the pendulum's pivots: (u_s, 0) and the joint between the bars."""
        p0 = jnp.stack([q[2], jnp.zeros_like(q[2])])
        return p0, p0 + self.l1 * jnp.stack([jnp.sin(q[5]), -jnp.cos(q[5])])

    def position_constraints(self, t, q):
        p0, p1 = self.pivots(q)
        v = p0 + 0.5 * self.l1 * jnp.stack([jnp.sin(q[5]), -jnp.cos(q[5])])
        w = p1 + 0.5 * self.l2 * jnp.stack([jnp.sin(q[8]), -jnp.cos(q[8])])
        return jnp.concatenate([q[3:5] - v, q[6:8] - w])

    def velocity_constraints(self, t, q, qd):
        return jnp.atleast_1d(qd[0] - self.drive_speed * jnp.tan(q[1]))

    def generalized_force(self, t, q, qd, u):
        f = self.delta * (qd[2] - qd[0])
        return jnp.zeros_like(q).at[0].set(f).at[2].set(-f).at[1].set(self.moment(t))

    # ------------------------------------------------------------ ledgers
    def split(self, x):
        return x[:9], x[9:18]

    def vector_field(self, t, x, u):
        q, qd = self.split(x)
        M, rhs, A, b = self.dynamics_terms(t, q, qd, u)
        qdd, lam = kkt_accelerations(M, rhs, A, b)
        dissipation = self.delta * (qd[2] - qd[0]) ** 2
        supplied = self.moment(t) * qd[1] + jnp.dot(A.T @ lam, qd)
        return jnp.concatenate([qd, qdd, jnp.stack([dissipation, supplied])])

    def project(self, t, x):
        return jnp.concatenate([super().project(t, x), x[18:]])

    def mechanical_energy(self, x):
        """E = T + V [J]: kinetic energy, the bars' weight and the spring."""
        q, qd = self.split(x)
        return self.kinetic_energy(q, qd) + self.potential_energy(q)

    def energy(self, x):
        """None: the damper, the moment and the shaft change E (see ``energy_balance``)."""
        return None

    def energy_balance(self, x):
        """E + D - W [J]: constant (the module docstring's ledgers)."""
        return self.mechanical_energy(x) + x[18] - x[19]

    def invariants(self, x):
        return {"energy_balance": self.energy_balance(x)}

    def guards(self, x):
        return {"tilt": jnp.cos(x[1]) - self.chart_eps}

    def shaft_power(self, t, x):
        """Power [W] of the constraint force of (9.8) (the shaft driving the ring body)."""
        q, qd = self.split(x)
        _, lam = self.accelerations(t, q, qd)
        return lam[0] * self.drive_speed * jnp.tan(q[1])

    # ------------------------------------------------------------ states
    def initial_state(self, u_r=0.0, beta=0.0, u_s=0.0, alpha1=0.0, alpha2=0.0,
                      beta_dot=0.0, u_s_dot=0.0, alpha1_dot=0.0, alpha2_dot=0.0):
        """Consistent state from the free coordinates (u_r, u_s [m], beta, alpha1, alpha2 [rad])
        and rates (beta', u_s', alpha1', alpha2'): the bars' centres follow from the pivots,
        u_r' = c tan(beta) from (9.8); both ledgers start at zero."""
        owner = "RollRing.initial_state"
        vals = {k: real(k, v, owner=owner, as_float=True) for k, v in (
            ("u_r", u_r), ("beta", beta), ("u_s", u_s), ("alpha1", alpha1), ("alpha2", alpha2),
            ("beta_dot", beta_dot), ("u_s_dot", u_s_dot), ("alpha1_dot", alpha1_dot), ("alpha2_dot", alpha2_dot))}
        b = vals["beta"]
        chart_argument(self, "tilt", np.cos(float(b)) - self.chart_eps, owner=owner, name="beta")
        return on_host(_ring_state, self.l1, self.l2, self.drive_speed, vals)
