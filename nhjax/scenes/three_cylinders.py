r"""Three rigid cylinders in mutual rolling contact: Rabier & Rheinboldt (seed 002), sec. 9.3, (9.30)-(9.36), Figs. 9.6-9.7.

Geometry
--------
Two lower cylinders of equal radius ``r1`` [m] roll without slipping on the
horizontal plane span{e1, e2}; a third ("upper") cylinder of radius ``r2`` [m]
lies across them and rolls without slipping on both. No force or moment acts
(gravity only presses the bodies together: all heights are fixed, so it does no
work). Rolling without slipping keeps each lower axis at a fixed direction:
lower cylinder 1 has its axis along d1 = e1, lower cylinder 2 along
d2 = (cos a, sin a, 0), ``a`` [rad] the fixed angle between them (0 < a < pi).
With n_i = e3 x d_i (the horizontal normal to axis i), lower cylinder i moves
along n_i only; its axis is the line {r1 psi_i n_i + xi d_i + r1 e3}, psi_i its
rolling angle [rad] (the material line on its top moves at 2 r1 psi_i' n_i).
The upper cylinder's axis is horizontal at height 2 r1 + r2 through its centre
x = (x1, x2, 2 r1 + r2) with direction e(theta) = (cos theta, sin theta, 0); phi
[rad] is its rotation about its own axis, so its angular velocity is
w = (phi' cos theta, phi' sin theta, theta') (as in the seed) and its attitude
is R = Rz(theta) Rx(phi) (body axis e1).

The upper cylinder touches lower cylinder i where the projections of the two
axes cross, at height 2 r1:

    z_i = x_h + s_i e - r2 e3,   s_i = (r1 psi_i - n_i . x_h) / sin(theta - a_i)    (a_1 = 0, a_2 = a).

The models need sin(theta - a_i) != 0 (the upper axis not parallel to a lower
one): the guard ``parallel`` stops ``nhjax.simulate`` before the contact point
runs off to infinity. The cylinders are taken long enough that the contact
points stay on them (the seed's assumption; not checked).

Two independent formulations
----------------------------
``ThreeCylindersMinimal``: the seed's first formulation (Neimark-Fufaev), six
coordinates y = (x1, x2, theta, phi, psi1, psi2) with the Lagrangian (9.30)

    L = m/2 (x1'^2 + x2'^2) + J_a/2 phi'^2 + J_t/2 theta'^2 + J_g/2 (psi1'^2 + psi2'^2),

J_a, J_t the upper cylinder's axial and transverse central moments, J_g = J_l +
m_l r1^2 a lower cylinder's moment about its generator line (the line of
contact with the plane). The no-slip conditions at z_1, z_2 (9.31) equate the
velocity of the upper cylinder's material point at z_i, x' + w x (z_i - x) =
x_h' + (r2 phi' + s_i theta') n(theta) (n(theta) = e3 x e), with that of the lower
one, 2 r1 psi_i' n_i: four scalar constraints (their vertical components vanish
identically, the seed's "two trivial zero-relations"), so two degrees of freedom.

``ThreeCylinders``: the seed's second formulation, (u_k, p_k) in R^3 x S^3 for
each body k = 1, 2 (lower), 3 (upper), 21 coordinates, p_k unit quaternions
(scalar first, body -> space; body frame = space frame at the identity, lower
body i's axis along d_i, the upper's along e1). Constraints ((9.33)-(9.36)):

* per lower cylinder i (five, (9.33)-(9.34) turned by Q = Rz(a_i)): the axis
  keeps its direction, vec(p_i) . n_i = 0 and vec(p_i) . e3 = 0, contact with
  the plane u_i3 = r1, and the material point at the plane at rest along d_i
  and n_i: (u_i' + w_i x (-r1 e3)) . {d_i, n_i} = 0;
* for the upper cylinder (six): two points of its axis at height 2 r1 + r2,
  u_33 = 2 r1 + r2 and (R(p_3) e1) . e3 = 0, and no slip at z_1, z_2: the
  horizontal components of u_3' + w_3 x (z_i - u_3) - (u_i' + w_i x (z_i - u_i))
  vanish, with z_i computed from the bodies' own states (axis of body 3 crossed
  with the top line of body i);
* |p_k|^2 = 1 (three): 19 constraints on 21 coordinates.

Kinetic energy sum_k m_k/2 |u_k'|^2 + 1/2 W_k . I_k W_k, W_k = 2 vec(conj(p_k) p_k'),
I_k the body inertia tensor (lower: J_l along d_i, J_lt across; upper: J_a
along e1, J_t across). The engine derives the Lagrange-d'Alembert DAE by
autodiff, the geometric constraints differentiated (index reduction), the
quaternion norm among them. The lower cylinders' transverse moment J_lt never
enters the motion (they only turn about their axes).

Our copy of the seed lost every formula of sec. 9.3 ((9.30)-(9.36)), the
constants and the initial conditions (only the prose, the angular velocity w
and the contact velocities v1 = (0, 2 r1 psi1', 0), v2 = 2 r1 psi2' (-sin a,
cos a, 0) survived); everything above is re-derived from that prose, and the two
formulations are derived independently of each other (tests/test_three_cylinders.py
checks that they agree to 1e-9).

Invariants: the energy (kinetic only; no force does work), the constraints.
Units: lengths [m], masses [kg], moments of inertia [kg m^2], angles [rad],
time [s]. Defaults (ours; the seed's constants are lost): r1 = 0.5, r2 = 0.5,
a = pi/3, m = 2, J_a = m r2^2/2 = 0.25, J_t = 1 (a solid cylinder about 2.4 m
long), m_l = 1, J_l = m_l r1^2/2 = 0.125, J_lt = 0.5.
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
from ._validate import axisymmetric_moments, in_range, positive, real
from .ball_on_platter import UP_STATE_NAMES, baumgarte_gains

__all__ = ["ThreeCylinders", "ThreeCylindersMinimal"]

_PARALLEL_HINT = (
    "the upper cylinder's axis became parallel to a lower cylinder's axis (sin(theta - a_i) = 0): "
    "the contact point z_i of (9.31) runs off to infinity, the cylinders would have to be "
    "infinitely long; shorten the run or start with the upper axis further from both lower axes, "
    "or use on_guard='stop'."
)

MINIMAL_STATE_NAMES = ("x1", "x2", "theta", "phi", "psi1", "psi2",
                       "x1_dot", "x2_dot", "theta_dot", "phi_dot", "psi1_dot", "psi2_dot")
UP3_STATE_NAMES = tuple(f"{c}_{k}" for k in (1, 2, 3) for c in UP_STATE_NAMES[:7]) + tuple(
    f"{c}_{k}_dot" for k in (1, 2, 3) for c in UP_STATE_NAMES[:7])
# "u1_1", ..., "p3_1" (body 1), ..., "p3_3" (body 3, the upper cylinder), then "u1_1_dot", ...
E3 = np.array([0.0, 0.0, 1.0])  # numpy: no program to compile at import


def _params(owner, r1, r2, a, m, J_a, J_t, m_l, J_l, J_lt, chart_eps):
    p = _positive_params(owner, r1, r2, a, m, J_a, J_t, m_l, J_l, J_lt, chart_eps)
    axisymmetric_moments(p["J_a"], p["J_t"], names=("J_a", "J_t"), owner=owner, mass=p["m"], radius=p["r2"],
                         mass_names=("m", "r2"))
    axisymmetric_moments(p["J_l"], p["J_lt"], names=("J_l", "J_lt"), owner=owner, mass=p["m_l"], radius=p["r1"],
                         mass_names=("m_l", "r1"))
    return p


def _positive_params(owner, r1, r2, a, m, J_a, J_t, m_l, J_l, J_lt, chart_eps):
    return dict(
        r1=positive("r1", r1, owner=owner, what="radius of the lower cylinders [m]"),
        r2=positive("r2", r2, owner=owner, what="radius of the upper cylinder [m]"),
        a=in_range("a", a, 0.0, np.pi, lo_closed=False, hi_closed=False, owner=owner,
                   what="angle between the axes of the lower cylinders [rad]"),
        m=positive("m", m, owner=owner, what="mass of the upper cylinder [kg]"),
        J_a=positive("J_a", J_a, owner=owner, what="axial central moment of the upper cylinder [kg m^2]"),
        J_t=positive("J_t", J_t, owner=owner, what="transverse central moment of the upper cylinder [kg m^2]"),
        m_l=positive("m_l", m_l, owner=owner, what="mass of a lower cylinder [kg]"),
        J_l=positive("J_l", J_l, owner=owner, what="axial central moment of a lower cylinder [kg m^2]"),
        J_lt=positive("J_lt", J_lt, owner=owner, what="transverse central moment of a lower cylinder [kg m^2]"),
        chart_eps=float(in_range("chart_eps", chart_eps, 0.0, 1.0, hi_closed=False, owner=owner, as_float=True,
                                 shape=(), what="margin of the guard |sin(theta - a_i)| > chart_eps")),
    )


class _Common(ConstrainedLagrangian):
    r1: jax.Array
    r2: jax.Array
    a: jax.Array
    m: jax.Array
    J_a: jax.Array
    J_t: jax.Array
    m_l: jax.Array
    J_l: jax.Array
    J_lt: jax.Array
    chart_eps: float = eqx.field(static=True, default=1e-3)
    control_dim: ClassVar[int] = 0
    guard_hints: ClassVar[dict] = {"parallel": _PARALLEL_HINT}
    guard_arguments: ClassVar[dict] = {"parallel": "theta"}

    def __init__(self, *args, **kwargs):  # the concrete scenes define their own
        raise TypeError("use ThreeCylinders or ThreeCylindersMinimal")

    def _set(self, owner, r1, r2, a, m, J_a, J_t, m_l, J_l, J_lt, chart_eps, baumgarte):
        for k, v in _params(owner, r1, r2, a, m, J_a, J_t, m_l, J_l, J_lt, chart_eps).items():
            setattr(self, k, v)
        self.baumgarte = baumgarte_gains(owner, baumgarte)

    def lower_axes(self):
        """(d_1, d_2), (n_1, n_2): the lower cylinders' axis directions and horizontal normals n_i = e3 x d_i (3,)."""
        z, o = jnp.zeros(()), jnp.ones(())
        ca, sa = jnp.cos(self.a), jnp.sin(self.a)
        d = (jnp.stack([o, z, z]), jnp.stack([ca, sa, z]))
        n = (jnp.stack([z, o, z]), jnp.stack([-sa, ca, z]))
        return d, n

    def generator_moment(self):
        """J_g = J_l + m_l r1^2 [kg m^2]: a lower cylinder's moment about its line of contact with the plane."""
        return self.J_l + self.m_l * self.r1**2

    # ------------------------------------------------ consistent rates (shared by both initial states)
    def _rates(self, y, theta_dot, phi_dot):
        """(x1', x2', psi1', psi2') that satisfy the four no-slip conditions (9.31) at the
        configuration y given theta' and phi' (the two free rates)."""
        x_h, th, psi = y[:2], y[2], y[4:6]
        e_n = jnp.stack([-jnp.sin(th), jnp.cos(th)])
        (_, _), (n1, n2) = self.lower_axes()
        rows, rhs = [], []
        for i, ni in enumerate((n1[:2], n2[:2])):
            ai = 0.0 if i == 0 else self.a
            s = (self.r1 * psi[i] - ni @ x_h) / jnp.sin(th - ai)
            # x_h' - 2 r1 psi_i' n_i = -(r2 phi' + s theta') e_n
            col = jnp.zeros((2, 2)).at[:, i].set(-2 * self.r1 * ni)
            rows.append(jnp.concatenate([jnp.eye(2), col], axis=1))
            rhs.append(-(self.r2 * phi_dot + s * theta_dot) * e_n)
        return jnp.linalg.solve(jnp.concatenate(rows), jnp.concatenate(rhs))

    def _initial_state(self, owner, x1, x2, theta, phi, psi1, psi2, theta_dot, phi_dot):
        """The consistent state (``_state_of``) of the configuration y and the free rates
        theta', phi' (see ``ThreeCylindersMinimal.initial_state``), after the numbers'
        checks. Concrete numbers: one compiled program (``nhjax._programs.small_call``;
        as separate eager operations the state compiled some 60 small programs in every
        new process, more than the first simulate() itself on a warm cache)."""
        vals = [real(k, v, owner=owner, as_float=True) for k, v in (
            ("x1", x1), ("x2", x2), ("theta", theta), ("phi", phi), ("psi1", psi1), ("psi2", psi2),
            ("theta_dot", theta_dot), ("phi_dot", phi_dot))]
        if not isinstance(vals[2], jax.core.Tracer) and not isinstance(self.a, jax.core.Tracer):
            # the chart check on the host (numpy), whenever theta and a are concrete
            th, a = float(vals[2]), float(self.a)
            margin = min(abs(np.sin(th)), abs(np.sin(th - a)))
            if not margin > self.chart_eps:
                raise OutsideChartError(
                    "parallel", 0.0, f"{owner}: theta = {th!r} puts the upper axis parallel to a lower axis "
                    f"(|sin(theta)| or |sin(theta - a)| = {margin:.3g} <= chart_eps = {self.chart_eps:g}); "
                    f"pick theta away from 0 and from a = {a:.6g} (mod pi)", name="theta")
        traced = any(isinstance(v, jax.core.Tracer) for v in vals)
        numbers = jnp.stack([jnp.asarray(v, float) for v in vals]) if traced else np.asarray(vals, float)
        return _programs.small_call(f"{type(self).__name__}.initial_state", _initial_from_numbers, self, numbers)


def _initial_from_numbers(system, vals):
    """``_Common._initial_state``'s computation on the 8 numbers (y, theta', phi'): the
    rates x1', x2', psi1', psi2' from the no-slip conditions, then the system's state."""
    y = vals[:6]
    v = system._rates(y, vals[6], vals[7])
    yd = jnp.stack([v[0], v[1], vals[6], vals[7], v[2], v[3]])
    return system._state_of(y, yd)


class ThreeCylindersMinimal(_Common):
    """The three cylinders in the seed's coordinates y = (x1, x2, theta, phi, psi1, psi2)
    ((9.30)-(9.31)); see the module docstring."""

    n: int = eqx.field(static=True, default=6)
    state_names: ClassVar[tuple] = MINIMAL_STATE_NAMES

    def __init__(self, r1=0.5, r2=0.5, a=np.pi / 3, m=2.0, J_a=0.25, J_t=1.0, m_l=1.0, J_l=0.125, J_lt=0.5,
                 chart_eps=1e-3, baumgarte=(0.0, 0.0)):
        self._set("ThreeCylindersMinimal", r1, r2, a, m, J_a, J_t, m_l, J_l, J_lt, chart_eps, baumgarte)
        self.n = 6

    def kinetic_energy(self, q, qd):
        Jg = self.generator_moment()
        return (0.5 * self.m * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * self.J_a * qd[3] ** 2 + 0.5 * self.J_t * qd[2] ** 2
                + 0.5 * Jg * (qd[4] ** 2 + qd[5] ** 2))

    def contact_points(self, q):
        """(z_1, z_2): the upper cylinder's contact points with the lower ones [m] (3,) each."""
        x_h, th, psi = q[:2], q[2], q[4:6]
        e = jnp.stack([jnp.cos(th), jnp.sin(th)])
        (_, _), (n1, n2) = self.lower_axes()
        out = []
        for i, (ni, ai) in enumerate(((n1[:2], 0.0), (n2[:2], self.a))):
            s = (self.r1 * psi[i] - ni @ x_h) / jnp.sin(th - ai)
            out.append(jnp.concatenate([x_h + s * e, jnp.atleast_1d(2 * self.r1)]))
        return tuple(out)

    def velocity_constraints(self, t, q, qd):
        x_h, th, psi = q[:2], q[2], q[4:6]
        e_n = jnp.stack([-jnp.sin(th), jnp.cos(th)])
        (_, _), (n1, n2) = self.lower_axes()
        c = []
        for i, (ni, ai) in enumerate(((n1[:2], 0.0), (n2[:2], self.a))):
            s = (self.r1 * psi[i] - ni @ x_h) / jnp.sin(th - ai)
            c.append(qd[:2] + (self.r2 * qd[3] + s * qd[2]) * e_n - 2 * self.r1 * qd[4 + i] * ni)
        return jnp.concatenate(c)

    def guards(self, x):
        th = x[2]
        return {"parallel": jnp.minimum(jnp.abs(jnp.sin(th)), jnp.abs(jnp.sin(th - self.a))) - self.chart_eps}

    def initial_state(self, x1=0.0, x2=0.0, theta=2.0, phi=0.0, psi1=-1.0, psi2=1.0, theta_dot=-0.3, phi_dot=2.0):
        """Consistent state from the configuration y (upper centre (x1, x2) [m], axis angle theta
        and spin angle phi [rad], lower rolling angles psi1, psi2 [rad]; lower axis i at signed
        distance r1 psi_i from the origin along n_i) and the two free rates theta', phi' [rad/s];
        x1', x2', psi1', psi2' follow from the four no-slip conditions (9.31)."""
        return self._initial_state("ThreeCylindersMinimal.initial_state", x1, x2, theta, phi, psi1, psi2,
                                   theta_dot, phi_dot)

    def _state_of(self, y, yd):
        return jnp.concatenate([y, yd])


def _vec(a):
    return jnp.concatenate([jnp.zeros_like(a[..., :1]), a], axis=-1)


# The redundant model's vector algebra is written in elementwise products and sums, not
# ``@``, ``jnp.dot`` or ``jnp.cross``: XLA's CPU compiler emits every dot_general as a
# kernel of its own, and jnp.cross's slices and concatenation cut fusions too. The
# engine differentiates this algebra up to three times (M, A, the KKT right-hand side)
# in the step of every projected solve, where the dots had doubled the program's
# kernels and so the compile time of a first simulate() (benchmarks/compile_times.py).
def _dot(a, b):
    """a . b along the last axis."""
    return jnp.sum(a * b, axis=-1)


def _cross(a, b):
    """a x b along the last axis, component by component."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


class ThreeCylinders(_Common):
    """The three cylinders as three rigid bodies in (u_k, p_k) in R^3 x S^3 ((9.33)-(9.36)):
    state (u_1, p_1, u_2, p_2, u_3, p_3, and their rates), bodies 1, 2 the lower cylinders,
    3 the upper one; see the module docstring."""

    n: int = eqx.field(static=True, default=21)
    state_names: ClassVar[tuple] = UP3_STATE_NAMES

    def __init__(self, r1=0.5, r2=0.5, a=np.pi / 3, m=2.0, J_a=0.25, J_t=1.0, m_l=1.0, J_l=0.125, J_lt=0.5,
                 chart_eps=1e-3, baumgarte=(0.0, 0.0)):
        self._set("ThreeCylinders", r1, r2, a, m, J_a, J_t, m_l, J_l, J_lt, chart_eps, baumgarte)
        self.n = 21

    # ------------------------------------------------------------ bodies
    @staticmethod
    def body(q, k):
        """(u_k, p_k) of body k = 0, 1 (lower), 2 (upper) from a configuration (21,)."""
        return q[7 * k:7 * k + 3], q[7 * k + 3:7 * k + 7]

    @staticmethod
    def bodies(q):
        """(u, p): the three bodies' positions (3, 3) and quaternions (3, 4), rows k = 0, 1
        (lower), 2 (upper), from a configuration (21,) (or its rates: (u', p'))."""
        b = q.reshape(3, 7)
        return b[:, :3], b[:, 3:]

    @staticmethod
    def spatial_angular_velocity(p, pd):
        """w = 2 vec(p' conj(p)) = 2 (p_0 p'_v - p'_0 p_v + p_v x p'_v) [rad/s] (p, p' (..., 4))."""
        return 2 * (p[..., :1] * pd[..., 1:] - pd[..., :1] * p[..., 1:] + _cross(p[..., 1:], pd[..., 1:]))

    @staticmethod
    def body_angular_velocity(p, pd):
        """W = 2 vec(conj(p) p') = 2 (p_0 p'_v - p'_0 p_v - p_v x p'_v) [rad/s] (p, p' (..., 4))."""
        return 2 * (p[..., :1] * pd[..., 1:] - pd[..., :1] * p[..., 1:] - _cross(p[..., 1:], pd[..., 1:]))

    def _inertias(self):
        (d1, d2), _ = self.lower_axes()
        I3 = jnp.eye(3)
        lower = [self.J_lt * (I3 - jnp.outer(d, d)) + self.J_l * jnp.outer(d, d) for d in (d1, d2)]
        e1 = I3[0]
        upper = self.J_t * (I3 - jnp.outer(e1, e1)) + self.J_a * jnp.outer(e1, e1)
        return (self.m_l, lower[0]), (self.m_l, lower[1]), (self.m, upper)

    def kinetic_energy(self, q, qd):
        # the three bodies at once, in products and sums (see _cross)
        _, p = self.bodies(q)
        ud, pd = self.bodies(qd)
        W = self.body_angular_velocity(p, pd)
        inertias = self._inertias()
        m = jnp.stack([mk for mk, _ in inertias])
        I = jnp.stack([Ik for _, Ik in inertias])  # noqa: E741
        return 0.5 * jnp.sum(m * _dot(ud, ud)) + 0.5 * jnp.sum(W[:, :, None] * I * W[:, None, :])

    def upper_axis(self, q):
        """e = R(p_3) e1 = (p0^2 + p1^2 - p2^2 - p3^2, 2 (p1 p2 + p0 p3), 2 (p1 p3 - p0 p2)):
        the upper cylinder's axis direction (3,) (for a unit p_3)."""
        p0, p1, p2, p3 = (q[17 + i] for i in range(4))
        return jnp.stack([p0 * p0 + p1 * p1 - p2 * p2 - p3 * p3, 2 * (p1 * p2 + p0 * p3), 2 * (p1 * p3 - p0 * p2)])

    def _contact_points(self, q):
        """(2, 3): z_1, z_2 (see ``contact_points``)."""
        _, (n1, n2) = self.lower_axes()
        nh = jnp.stack([n1, n2])[:, :2]
        u, _ = self.bodies(q)
        e = self.upper_axis(q)
        s = _dot(nh, u[:2, :2] - u[2, :2]) / _dot(nh, e[:2])
        return u[2] + s[:, None] * e - self.r2 * E3

    def contact_points(self, q):
        """(z_1, z_2) [m]: where the upper axis's projection crosses the lower axes', at height 2 r1
        (the bodies' own states; the upper's lowest line and the lowers' top lines)."""
        z = self._contact_points(q)
        return z[0], z[1]

    def _slips(self, q, qd):
        """(s, g) (2, 3) each: ``contact_slips``' (s_1, s_2) and (g_1, g_2)."""
        u, p = self.bodies(q)
        ud, pd = self.bodies(qd)
        w = self.spatial_angular_velocity(p, pd)
        z = self._contact_points(q)
        upper = ud[2] + _cross(w[2], z - u[2])
        lower = ud[:2] + _cross(w[:2], z - u[:2])
        g = ud[:2] + _cross(w[:2], -self.r1 * E3)
        return upper - lower, g

    def contact_slips(self, q, qd):
        """Relative velocities [m/s] (3,) at z_1, z_2 (upper minus lower material point) and the
        velocities of the lower cylinders' material points at the plane: (s_1, s_2, g_1, g_2)."""
        s, g = self._slips(q, qd)
        return s[0], s[1], g[0], g[1]

    def position_constraints(self, t, q):
        # (|p_i|^2 - 1, vec(p_i) . n_i, p_i3, u_i3 - r1) for i = 1, 2, then
        # (|p_3|^2 - 1, u_33 - (2 r1 + r2), e . e3)
        _, (n1, n2) = self.lower_axes()
        u, p = self.bodies(q)
        norms = _dot(p, p) - 1.0
        lower = jnp.stack([norms[:2], _dot(p[:2, 1:], jnp.stack([n1, n2])), p[:2, 3], u[:2, 2] - self.r1], axis=-1)
        upper = jnp.stack([norms[2], u[2, 2] - (2 * self.r1 + self.r2), self.upper_axis(q)[2]])
        return jnp.concatenate([lower.reshape(8), upper])

    def velocity_constraints(self, t, q, qd):
        # (g_1 . d_1, g_1 . n_1, g_2 . d_2, g_2 . n_2, s_1[:2], s_2[:2])
        (d1, d2), (n1, n2) = self.lower_axes()
        s, g = self._slips(q, qd)
        rolling = jnp.stack([_dot(g, jnp.stack([d1, d2])), _dot(g, jnp.stack([n1, n2]))], axis=-1)
        return jnp.concatenate([rolling.reshape(4), s[:, :2].reshape(4)])

    def guards(self, x):
        _, (n1, n2) = self.lower_axes()
        e = self.upper_axis(x[:21])
        return {"parallel": jnp.minimum(jnp.abs(_dot(n1, e)), jnp.abs(_dot(n2, e))) - self.chart_eps}

    # ------------------------------------------------------------ states
    def from_minimal(self, y, yd):
        """The (u, p) state of the configuration y = (x1, x2, theta, phi, psi1, psi2) and its rates
        yd: lower cylinder i at u_i = r1 psi_i n_i + r1 e3 turned by -psi_i about d_i
        (its top then moves at 2 r1 psi_i' n_i), the upper at (x1, x2, 2 r1 + r2) with
        attitude Rz(theta) Rx(phi)."""
        (d1, d2), (n1, n2) = self.lower_axes()
        q, qd = [], []
        for i, (d, nv) in enumerate(((d1, n1), (d2, n2))):
            ang = -y[4 + i]
            p = jnp.concatenate([jnp.atleast_1d(jnp.cos(ang / 2)), jnp.sin(ang / 2) * d])
            w = -yd[4 + i] * d
            q += [self.r1 * y[4 + i] * nv + self.r1 * E3, p]
            qd += [self.r1 * yd[4 + i] * nv, 0.5 * so3.quat_mul(_vec(w), p)]
        th, ph = y[2], y[3]
        pz = jnp.stack([jnp.cos(th / 2), 0.0 * th, 0.0 * th, jnp.sin(th / 2)])
        px = jnp.stack([jnp.cos(ph / 2), jnp.sin(ph / 2), 0.0 * ph, 0.0 * ph])
        p = so3.quat_mul(pz, px)
        w = jnp.stack([yd[3] * jnp.cos(th), yd[3] * jnp.sin(th), yd[2]])
        q += [jnp.stack([y[0], y[1], 2 * self.r1 + self.r2]), p]
        qd += [jnp.stack([yd[0], yd[1], 0.0 * yd[0]]), 0.5 * so3.quat_mul(_vec(w), p)]
        return jnp.concatenate(q + qd)

    def to_minimal(self, x):
        """(y, yd) of a (u, p) state: x1, x2, theta (from the upper axis, in (-pi, pi]), phi (in
        (-pi, pi]; unwrap a trajectory with numpy.unwrap), psi_i = n_i . u_i / r1, and their rates
        (theta' = w_3 . e3, phi' = w_3 . e, psi_i' = n_i . u_i' / r1)."""
        q, qd = x[:21], x[21:]
        _, (n1, n2) = self.lower_axes()
        u3, p3 = self.body(q, 2)
        ud3, pd3 = self.body(qd, 2)
        e = self.upper_axis(q)
        th = jnp.arctan2(e[1], e[0])
        R = so3.quat_to_matrix(p3)
        Rx = so3.rot_z(-th) @ R
        ph = jnp.arctan2(Rx[2, 1], Rx[1, 1])
        w = self.spatial_angular_velocity(p3, pd3)
        psi = [n @ self.body(q, i)[0] / self.r1 for i, n in enumerate((n1, n2))]
        psid = [n @ self.body(qd, i)[0] / self.r1 for i, n in enumerate((n1, n2))]
        y = jnp.stack([u3[0], u3[1], th, ph, psi[0], psi[1]])
        yd = jnp.stack([ud3[0], ud3[1], w[2], w @ e, psid[0], psid[1]])
        return y, yd

    def initial_state(self, x1=0.0, x2=0.0, theta=2.0, phi=0.0, psi1=-1.0, psi2=1.0, theta_dot=-0.3, phi_dot=2.0):
        """Consistent (u, p) state of the configuration y = (x1, x2, theta, phi, psi1, psi2) with
        the free rates theta', phi' (see ``ThreeCylindersMinimal.initial_state``): the same
        physical state as the minimal model's, built by ``from_minimal``."""
        return self._initial_state("ThreeCylinders.initial_state", x1, x2, theta, phi, psi1, psi2, theta_dot,
                                   phi_dot)

    def _state_of(self, y, yd):
        return self.from_minimal(y, yd)
