r"""A homogeneous ball rolling without slipping inside a cone: Rabier & Rheinboldt (seed 002), sec. 9.2, (9.20)-(9.29).

Geometry
--------
The cone has its vertex at the origin and its axis along e3 (gravity -g e3);
``gamma`` [rad], 0 < gamma < pi/2, is the half opening angle between the axis
and a generator. In the seed's polar coordinates (rho, alpha) a point of the
cone is rho g(alpha) with

    g   = (sin(gamma) cos(alpha), sin(gamma) sin(alpha), cos(gamma))   (generator, unit),
    e_a = (-sin(alpha), cos(alpha), 0)                                   (horizontal tangent),
    n   = (-cos(gamma) cos(alpha), -cos(gamma) sin(alpha), sin(gamma))   (unit normal into the cone),

(g, e_a, n) right-handed. The ball (mass m [kg], radius r [m], moment of
inertia J [kg m^2] about any axis through its centre; J = 2/5 m r^2 for a solid
ball) touches the cone at x = rho g; its centre is u = rho g + r n, at height
u3 = D cot(gamma) + r / sin(gamma) and horizontal distance

    D = rho sin(gamma) - r cos(gamma) > 0

from the axis. (D = 0 is the ball resting at the bottom, touching the cone all
round a circle: there the single-contact model ends, see the guard below.)

Model (the seed's (u, p) formulation, (9.26)-(9.29))
----------------------------------------------------
State x = (u, p, u', p'), u the centre [m], p the attitude (unit quaternion,
scalar first, body -> space). With n, g, e_a taken at the azimuth of u,

    T = m/2 |u'|^2 + J/2 |W|^2,   W = 2 vec(conj(p) p'),     V = m g u3,
    position constraints   |p|^2 - 1 = 0,   n . u - r = 0   (contact, (9.26)),
    velocity constraints   g . v = 0,   e_a . v = 0          (no slip, (9.29)),
    v = u' + w x (x - u) = u' - r w x n                      (velocity of the material contact point),

w = 2 vec(p' conj(p)) the spatial angular velocity. The normal component n . v
is the derivative of the contact condition (n' is along e_a, u has no e_a
component), so it is not imposed twice. The engine derives the DAE by
autodiff. Our copy of the seed has lost the formulas (9.20)-(9.29) (only the
prose survived: b1 normal, b2 horizontal, b3 along the generator, contact
u . b1 = r, no slip in span{b2, b3}); the above is re-derived from that prose.
The seed's first formulation, the Neimark-Fufaev Lagrangian in (rho, alpha,
Euler angles) (9.21)-(9.25), is not implemented: it is singular where the
Euler angles are, and the reduced equations below replace it as the
independent check.

Integrals (re-derived here; checked by tests/test_ball_in_cone.py)
------------------------------------------------------------------
Newton-Euler with the contact force R: m u'' = R - m g e3, J w' = -r n x R.
Hence w' . n = 0 and, writing w = w_g g + w_a e_a + w_n n, Omega = alpha', the
no-slip conditions are rho' = r w_a and Omega D = -r w_g. The g-component of
the moment equation gives (J/r + m r) [(Omega D)' + Omega D'] = 0, i.e.

    L = D^2 alpha' = (u x u') . e3       [m^2/s]   (the centre's areal velocity about the axis),

and w_n' = w . n' = -Omega cos(gamma) w_a turns into

    N = w_n - L cot(gamma) / (r D)        [rad/s]   (spin about the normal, shifted).

With the energy E = m/2 (1 + k) (rho'^2 + L^2/D^2) + J/2 w_n^2 + m g u3
(k = J/(m r^2)) the motion of D is one-dimensional: D oscillates between the
two positive roots of the cubic

    m g cot(gamma) D^3 + (m g r/sin(gamma) + J N^2/2 - E) D^2 + (J N L cot(gamma)/r) D
        + L^2 (m (1 + k) + J cot(gamma)^2 / r^2) / 2 = 0,

so the ball returns to the same greatest and least heights every radial period
(``turning_points``, ``radial_period``, ``precession_per_period``). That is the
motion of the seed's Fig. 9.5: the ball rolls up, turns, rolls down in an arc
and climbs again, like the skate's cycloid (experiments/ball_in_cone.py). Unlike the skate's
path it has no cusps: alpha' = L / D^2 keeps its sign (or vanishes throughout),
so in (alpha, rho) the path is a chain of arcs between the two heights.

Chart and guard: n, g, e_a need the azimuth of u, undefined on the axis (D = 0,
where a ball with L = 0 would pass through the bottom). The guard ``axis``
(D - chart_eps r > 0) stops ``nhjax.simulate`` there (``ChartSingularityError``,
or the motion up to that time with ``on_guard="stop"``); with L != 0 the
centrifugal term L^2/D^2 keeps D away from 0.

Units: lengths [m], angles [rad], time [s]; defaults m = r = g = 1 (the seed's
dimensionless units), J = 0.4 (solid ball), gamma = 1 (the seed's value).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _programs
from ..errors import OutsideChartError
from ..lie import so3
from ..mechanics import ConstrainedLagrangian
from ._validate import ball_moment, in_range, positive, real, unit_quaternion
from .ball_on_platter import UP_STATE_NAMES, baumgarte_gains

__all__ = ["BallInCone"]

_AXIS_HINT = (
    "the ball's centre reached the cone's axis (D = 0): the ball sits at the bottom "
    "touching the cone all round, where the single-contact model (9.26)-(9.29) ends and "
    "the contact frame (its azimuth) is undefined. Give the ball an angular momentum "
    "about the axis (alpha_dot != 0) to keep it off the axis, or use on_guard='stop'."
)


def _cone_state(system, rho, alpha, rho_dot, alpha_dot, spin, p):
    """``BallInCone.initial_state``'s state from its checked numbers (p the attitude)."""
    sg, cg = jnp.sin(system.gamma), jnp.cos(system.gamma)
    D = rho * sg - system.r * cg
    ca, sa = jnp.cos(alpha), jnp.sin(alpha)
    gv = jnp.stack([sg * ca, sg * sa, cg])
    ea = jnp.stack([-sa, ca, jnp.zeros_like(ca)])
    nv = jnp.stack([-cg * ca, -cg * sa, sg])
    u = rho * gv + system.r * nv
    ud = rho_dot * gv + alpha_dot * D * ea
    w = (-alpha_dot * D / system.r) * gv + (rho_dot / system.r) * ea + spin * nv
    pd = 0.5 * so3.quat_mul(_vec(w), p)
    return jnp.concatenate([u, p, ud, pd])


def _vec(a):
    return jnp.concatenate([jnp.zeros_like(a[..., :1]), a], axis=-1)


def cone_parameters(owner, m, r, J, gamma, g):
    """The checked parameters (m, r, J, gamma, g) of a ball in a cone (both models)."""
    m = positive("m", m, owner=owner, what="mass [kg]")
    r = positive("r", r, owner=owner, what="radius [m]")
    return (
        m, r, ball_moment("J", J, m, r, owner=owner),
        in_range("gamma", gamma, 0.0, np.pi / 2, lo_closed=False, hi_closed=False, owner=owner,
                 what="half opening angle of the cone, between axis and generator [rad]"),
        positive("g", g, allow_zero=True, owner=owner, what="gravity [m/s^2]"),
    )


def cone_frame(gamma, c, s):
    """(g, e_a, n) at the azimuth with cosine c and sine s: generator, horizontal
    tangent, inward normal (3,) each, for the half opening angle gamma."""
    sg, cg = jnp.sin(gamma), jnp.cos(gamma)
    return (jnp.stack([sg * c, sg * s, cg]), jnp.stack([-s, c, jnp.zeros_like(c)]),
            jnp.stack([-cg * c, -cg * s, sg]))


class BallInCone(ConstrainedLagrangian):
    """Homogeneous ball rolling inside a cone, in (u, p) in R^3 x S^3 (seed 002, 9.20-9.29).

    See the module docstring for the geometry, the model, the integrals and the guard.
    """

    m: jax.Array
    r: jax.Array
    J: jax.Array
    gamma: jax.Array
    g: jax.Array
    chart_eps: float = eqx.field(static=True, default=1e-3)
    n: int = eqx.field(static=True, default=7)
    # Runge-Kutta stages in a scan: a program about a third smaller than with unrolled
    # stages (a first simulate() compiles and a warm one loads that much less), for a
    # little more time per step (benchmarks/compile_times.py)
    large_vector_field: ClassVar[bool] = True

    state_names: ClassVar[tuple] = UP_STATE_NAMES
    control_dim: ClassVar[int] = 0
    guard_hints: ClassVar[dict] = {"axis": _AXIS_HINT}
    guard_arguments: ClassVar[dict] = {"axis": "rho"}

    def __init__(self, m=1.0, r=1.0, J=0.4, gamma=1.0, g=1.0, chart_eps=1e-3, baumgarte=(0.0, 0.0)):
        owner = "BallInCone"
        self.m, self.r, self.J, self.gamma, self.g = cone_parameters(owner, m, r, J, gamma, g)
        self.chart_eps = float(in_range("chart_eps", chart_eps, 0.0, 1.0, hi_closed=False, owner=owner, as_float=True,
                                        shape=(), what="margin of the axis guard D > chart_eps r"))
        self.n = 7
        self.baumgarte = baumgarte_gains(owner, baumgarte)

    # ------------------------------------------------------------ geometry
    def frame(self, u):
        """(g, e_a, n) at the azimuth of the point u (3,): generator, horizontal tangent, inward normal."""
        D = jnp.sqrt(u[0] ** 2 + u[1] ** 2)
        return cone_frame(self.gamma, u[0] / D, u[1] / D)

    @staticmethod
    def spatial_angular_velocity(p, pd):
        """w = 2 vec(p' conj(p)) [rad/s]."""
        return 2 * so3.quat_mul(pd, so3.quat_conj(p))[..., 1:]

    def contact_point(self, q):
        """x = u - r n [m] (3,): the point where the ball touches the cone."""
        return q[:3] - self.r * self.frame(q[:3])[2]

    def contact_slip(self, q, qd):
        """Velocity v = u' - r w x n of the ball's material contact point [m/s] (3,)."""
        w = self.spatial_angular_velocity(q[3:7], qd[3:7])
        return qd[:3] - self.r * jnp.cross(w, self.frame(q[:3])[2])

    def polar(self, x):
        """(rho, alpha): the contact point in the seed's polar coordinates on the cone [m, rad]
        (alpha in (-pi, pi]; unwrap a trajectory with numpy.unwrap)."""
        u = x[:3]
        D = jnp.sqrt(u[0] ** 2 + u[1] ** 2)
        return (D + self.r * jnp.cos(self.gamma)) / jnp.sin(self.gamma), jnp.arctan2(u[1], u[0])

    # ------------------------------------------------------------ the model
    def kinetic_energy(self, q, qd):
        W = 2 * so3.quat_mul(so3.quat_conj(q[3:7]), qd[3:7])[1:]
        return 0.5 * self.m * jnp.dot(qd[:3], qd[:3]) + 0.5 * self.J * jnp.dot(W, W)

    def potential_energy(self, q):
        return self.m * self.g * q[2]

    def position_constraints(self, t, q):
        return jnp.stack([jnp.dot(q[3:7], q[3:7]) - 1.0, jnp.dot(self.frame(q[:3])[2], q[:3]) - self.r])

    def velocity_constraints(self, t, q, qd):
        gv, ea, _ = self.frame(q[:3])
        v = self.contact_slip(q, qd)
        return jnp.stack([jnp.dot(gv, v), jnp.dot(ea, v)])

    def guards(self, x):
        return {"axis": jnp.sqrt(x[0] ** 2 + x[1] ** 2) - self.chart_eps * self.r}

    # ------------------------------------------------------------ integrals
    def areal_velocity(self, x):
        """L = (u x u') . e3 = D^2 alpha' [m^2/s], conserved."""
        return x[0] * x[8] - x[1] * x[7]

    def normal_spin(self, x):
        """w_n = w . n [rad/s]: the spin about the normal at the contact."""
        return jnp.dot(self.spatial_angular_velocity(x[3:7], x[10:14]), self.frame(x[:3])[2])

    def shifted_spin(self, x):
        """N = w_n - L cot(gamma) / (r D) [rad/s], conserved."""
        D = jnp.sqrt(x[0] ** 2 + x[1] ** 2)
        return self.normal_spin(x) - self.areal_velocity(x) / (jnp.tan(self.gamma) * self.r * D)

    def invariants(self, x):
        return {"areal_velocity": self.areal_velocity(x), "shifted_spin": self.shifted_spin(x)}

    # ------------------------------------------------------------ states
    def initial_state(self, rho=3.0, alpha=0.0, rho_dot=0.0, alpha_dot=0.3, spin=0.0, attitude=None):
        """Consistent state from the contact point's polar coordinates on the cone: rho [m]
        (distance from the vertex along the generator, rho > r cot(gamma)), alpha [rad],
        their rates [m/s, rad/s], the spin w . n about the normal [rad/s] and the attitude
        (unit quaternion, default identity). The other two components of the angular
        velocity follow from rolling: w_a = rho'/r, w_g = -alpha' D / r."""
        owner = "BallInCone.initial_state"
        rho, alpha, rho_dot, alpha_dot, spin = (real(k, v, owner=owner) for k, v in (
            ("rho", rho), ("alpha", alpha), ("rho_dot", rho_dot), ("alpha_dot", alpha_dot), ("spin", spin)))
        if not any(isinstance(v, jax.core.Tracer) for v in (rho, self.gamma, self.r)):
            # the chart check in numpy on the host (no program of its own)
            sg, cg, r = np.sin(float(self.gamma)), np.cos(float(self.gamma)), float(self.r)
            D = float(rho) * sg - r * cg
            if not D > self.chart_eps * r:
                raise OutsideChartError(
                    "axis", 0.0, f"{owner}: rho = {float(rho)!r} puts the ball's centre on or across the cone's axis "
                    f"(D = rho sin(gamma) - r cos(gamma) = {D:.3g}); rho must exceed r cot(gamma) = "
                    f"{r * cg / sg:.6g} (the ball resting at the bottom) by the guard's margin", name="rho")
        p = np.array([1.0, 0.0, 0.0, 0.0]) if attitude is None else unit_quaternion(
            "attitude", attitude, owner=owner, normalize=True)
        # concrete numbers: one compiled program instead of some 40 eager operations (small
        # programs compiled in every new process)
        return _programs.small_call("BallInCone.initial_state", _cone_state, self, rho, alpha, rho_dot, alpha_dot,
                                    spin, p)

    # ------------------------------------------------------------ exact relations
    def _reduced(self, x):
        m, r, J, g, gam = (float(v) for v in (self.m, self.r, self.J, self.g, self.gamma))
        x = np.asarray(x, float)
        D = float(np.hypot(x[0], x[1]))
        L, N = float(self.areal_velocity(x)), float(self.shifted_spin(x))
        E = float(self.energy(jnp.asarray(x)))
        cot = 1.0 / np.tan(gam)
        # E - f(D) = m (1 + k)/2 rho'^2, times D^2: a cubic P(D) = -(coefficients below) . (D^3, D^2, D, 1)
        coef = np.array([m * g * cot, m * g * r / np.sin(gam) + 0.5 * J * N * N - E, J * N * L * cot / r,
                         0.5 * L * L * (m * (1 + J / (m * r * r)) + J * cot * cot / (r * r))])
        return D, L, N, E, coef

    def turning_points(self, x):
        """(D_min, D_max) [m]: the least and greatest distances of the centre from the axis on
        the motion through state x (positive roots of the cubic in the module docstring)."""
        D, *_, coef = self._reduced(x)
        roots = np.roots(coef)
        pos = np.sort(roots[(np.abs(roots.imag) < 1e-9 * (1 + np.abs(roots.real))) & (roots.real > 0)].real)
        if pos.size < 2:
            raise ValueError("no bounded radial motion through this state (fewer than two positive turning points)")
        i = np.searchsorted(pos, D * (1 - 1e-12))
        lo, hi = pos[max(i - 1, 0)], pos[min(i, pos.size - 1)]
        if not lo <= D * (1 + 1e-9) and lo < hi:
            raise ValueError("the state lies outside its own radial well")
        return float(lo), float(hi)

    def height(self, D):
        """Height u3 [m] of the centre at distance D [m] from the axis: D cot(gamma) + r / sin(gamma)."""
        return jnp.asarray(D) / jnp.tan(self.gamma) + self.r / jnp.sin(self.gamma)

    def _quadrature(self, x, n=2001):
        m, J, r, gam = (float(v) for v in (self.m, self.J, self.r, self.gamma))
        _, L, _, _, coef = self._reduced(x)
        a, b = self.turning_points(x)
        # P(D) = D^2 (E - f(D)) = m (1 + k)/2 (D rho')^2 = (D - a)(b - D) c(D), c = coef / (D^2 - (a+b) D + ab)
        c_poly, _ = np.polydiv(coef, np.array([1.0, -(a + b), a * b]))
        # D = a + (b - a)(1 - cos th)/2, dD / sqrt((D - a)(b - D)) = dth: a smooth integrand in cos th
        th = np.linspace(0.0, np.pi, n)
        D = a + 0.5 * (b - a) * (1 - np.cos(th))
        dt = D / (np.sin(gam) * np.sqrt(2 * np.polyval(c_poly, D) / (m * (1 + J / (m * r * r)))))
        w = np.full(n, np.pi / (n - 1))
        w[[0, -1]] *= 0.5  # trapezoid: spectrally accurate for a smooth even function of th
        return 2 * float(np.sum(w * dt)), 2 * float(np.sum(w * dt * L / D**2))

    def radial_period(self, x):
        """Time [s] from one greatest height to the next (quadrature of the radial motion)."""
        return self._quadrature(x)[0]

    def precession_per_period(self, x):
        """Advance of the azimuth alpha [rad] over one radial period (quadrature of L / D^2)."""
        return self._quadrature(x)[1]
