r"""A sharp-edged disk rolling on a plane: Rabier & Rheinboldt (seed 002), sec. 9.2, (9.37)-(9.44).

Geometry
--------
The plane is span{e1, e2}, gravity -g e3. The disk (mass m [kg], radius r [m])
has principal moments J1 about its symmetry axis a1 and J2 about a diameter
[kg m^2] (defaults J1 = 0.35, J2 = 0.5 in units m r^2: the seed's data). The
seed lists a1 first, hence J1 for the axis; with the other assignment the
circular motion of Table 9.1 is unstable: for q - q0 >= 1e-3 the tilt grows to
0.8 rad and the path leaves the circle (eps ~ 1) instead of spiralling slowly
away as the seed reports.

Minimal coordinates (``RollingDisk``), y = (x1, x2, phi, theta, psi):
x = (x1, x2, 0) is the contact point [m]; b = (cos phi, sin phi, 0) is the
horizontal line of the disk's plane (the rolling direction); theta is the tilt
of the disk's plane from the vertical (|theta| < pi/2, theta > 0 leans to the
left of b); psi is the angle of a body radius from the radius to the contact
point, increasing as the disk rolls forward. With n = e3 x b,

    d  = cos(theta) e3 + sin(theta) n     (unit vector contact -> centre),
    u  = x + r d                           (centre of mass),
    a1 = b x d                             (symmetry axis),
    angular velocity  w = -theta' b + phi' cos(theta) d + (phi' sin(theta) - psi') a1.

Rolling without slipping (9.37) (velocity of the material contact point zero):

    x1' = r psi' cos(phi),   x2' = r psi' sin(phi).

Lagrangian (9.38) (re-derived; the seed's formula is garbled in our copy, it
cites Neimark & Fufaev p. 102):

    T = m/2 [x1'^2 + x2'^2 + r^2 theta'^2 + r^2 sin^2(theta) phi'^2
             + 2 r cos(theta) theta' (x2' cos phi - x1' sin phi)
             - 2 r sin(theta) phi' (x1' cos phi + x2' sin phi)]
        + J2/2 (theta'^2 + cos^2(theta) phi'^2) + J1/2 (psi' - sin(theta) phi')^2,
    V = m g r cos(theta).

The engine derives the equations of motion (9.38)-(9.40) from these; the tests
check T against the kinetic energy of the rigid body placed by ``pose`` (autodiff
through the rotation) and the constraints against the material contact velocity.

Chart: the coordinates are singular where the disk lies flat (cos theta = 0:
phi and psi turn about the same axis, the mass matrix degenerates). The seed
monitors |theta| < pi/2 and stops there; here the guard ``tilt``
(cos theta - chart_eps > 0) makes ``nhjax.simulate`` stop with
``ChartSingularityError`` (or return the motion up to that time with
``on_guard="stop"``).

Rigid-body formulation (``RollingDiskQuaternion``), (9.39)-(9.40) of the seed:
q = (u, p) in R^3 x S^3 (centre, unit quaternion body -> space, scalar first,
body axis 1 = the disk's axis), T = m/2 |u'|^2 + 1/2 W . diag(J1, J2, J2) W with
W = 2 vec(conj(p) p'), V = m g u3; position constraints |p|^2 - 1 = 0 and
contact u3 - r |P a1| = 0 (P the projection onto span{e1, e2}: the lowest point
of the rim touches the plane); velocity constraint P(u' + w x (x - u)) = 0 with
x = u - r d, d = (e3 - (a1 . e3) a1)/|P a1| (its vertical component is the
derivative of the contact condition). The engine enforces the geometric
constraints at acceleration level, and ``nhjax.simulate`` projects the state
back onto them after every step (its default for systems with position
constraints), so Baumgarte terms (``baumgarte=(alpha, beta)`` [1/s]) are off by
default: from a projected state the Runge-Kutta stages leave the manifold by
O(h^2) (|p + h k|^2 - 1 = h^2 |k|^2), the gains turn that into extra stage
accelerations that are the same on every step of a steady motion, and the
rolling rates drift. Measured on the circle below (10 orbits, rtol = atol =
1e-8, default solver): (1, 1) with projection errs 9.0e-4 in 616 steps, (0, 0)
with projection 5.6e-5 in 419 steps. Pass gains (e.g. (1, 1), error 6.0e-5)
only together with ``project_steps=False``; without either, the constraints
drift (4.5e-3). The minimal model errs only 2.3e-8 on that circle because its
angles grow linearly in time there (the Runge-Kutta steps are exact for them);
on a wobbling motion over the same time the two formulations are equally
accurate (7.3e-6 here, 1.7e-5 minimal). Both formulations describe the same
motions (tests/test_rolling_disk.py maps states between them).

Circular motions (9.42)-(9.43) (re-derived)
-------------------------------------------
theta = theta0, psi' = s, phi' = q r s: the contact point runs on a circle of
radius 1/q about the origin when it starts at (0, -1/q) with phi = 0. The
theta-equation holds iff (sin, cos of theta0)

    (m r^2 + J1 - J2) sin cos (q r s)^2 - (m r^2 + J1) cos (q r s) s + m g r sin = 0,

so every tilt and curvature with D = (m r^2 + J1) cos q r - (m r^2 + J1 - J2)
sin cos (q r)^2 > 0 has exactly one rolling rate, s^2 = m g r sin / D
(``circular_rate``; for large circles this is tan theta0 = (1 + J1/(m r^2)) v^2/(g R),
the classical coin). The family of circular motions has two parameters, so the
seed's quadratic (9.43) fixes a normalisation of the rates that our copy does
not show: its printed root q0 = 2.17080452 (J1 = 0.35, J2 = 0.5, theta0 = 0.25)
satisfies (1 + J2 - J1) sin cos q^2 - J2 cos q - sin = 0 to 3e-9, which is not
the balance above for any fixed rolling rate. We therefore take the circle of
radius 1/q0 with the rolling rate the balance requires (s0 = 0.362831 in units
sqrt(g/r); period 2 pi/(q0 s0) = 7.977) and reproduce Table 9.1 by starting
from the seed's circle formula with q = q0 + Delta at the rate s0
(``circular_state(theta0, q, spin=s0)``): the deviation from circularity grows
linearly, 3.3 Delta (the seed: 7.2 Delta), and the path turns erratic at
Delta = 0.08 as in the seed's Fig. 9.10 (experiments/rolling_disk_circles.py).

Straight rolling (9.41) (re-derived)
------------------------------------
Upright rolling at psi' = s is unstable iff s^2 < m g r J2 / (J1 (m r^2 + J1))
(s < 1.029 for the seed's data); to first order the tilt obeys
(m r^2 + J2) theta'' = [m g r - (m r^2 + J1) J1 s^2 / J2] theta + const, so a
tilt of 1e-5 at s = 0.3 grows like cosh(0.781 t) and the path curves away
(seed, Fig. 9.9). The seed reports the tilt passing pi/2; in the model above,
and in the (u, p) formulation (their centres agree to 1e-7), the rolling disk leans over
to 1.421 rad and rights itself. The rolling disk is integrable, and in every
run we made with a nonzero rolling rate its integrals kept the tilt below pi/2
(1.527 rad at s = 0.1). A disk that does not roll tips over its edge and
reaches the chart's edge at the exact fall time; experiments/rolling_disk_falls.py
shows both.

Units: lengths [m], angles [rad], time [s]; defaults m = r = g = 1 (the seed's
dimensionless units: lengths in r, times in sqrt(r/g), inertias in m r^2).
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
from ._validate import chart_argument, axisymmetric_moments, in_range, on_host, positive, real
from .ball_on_platter import baumgarte_gains

__all__ = ["RollingDisk", "RollingDiskQuaternion"]

E3 = np.array([0.0, 0.0, 1.0])  # numpy: no program to compile at import

_FLAT_HINT = (
    "the disk fell flat: its tilt reached pi/2 (the plane of the disk became "
    "horizontal), where the sharp-edge contact model (9.37)-(9.44) ends and the "
    "coordinates (phi, theta, psi) are singular. Rabier & Rheinboldt stop their "
    "computation there too. Use on_guard='stop' to get the motion up to this "
    "time, or start faster / more upright to keep the disk rolling."
)


class _DiskParams(eqx.Module):
    m: jax.Array
    r: jax.Array
    g: jax.Array
    J1: jax.Array
    J2: jax.Array
    chart_eps: float = eqx.field(static=True, default=1e-3)

    guard_hints: ClassVar[dict] = {"tilt": _FLAT_HINT}
    guard_arguments: ClassVar[dict] = {"tilt": "theta"}

    def _set(self, m, r, g, J1, J2, chart_eps):
        owner = type(self).__name__
        self.m = positive("m", m, owner=owner, what="mass [kg]")
        self.r = positive("r", r, owner=owner, what="radius [m]")
        self.g = positive("g", g, allow_zero=True, owner=owner, what="gravity [m/s^2]")
        self.J1 = positive("J1", J1, owner=owner, what="moment about the symmetry axis [kg m^2]")
        self.J2 = positive("J2", J2, owner=owner, what="moment about a diameter [kg m^2]")
        axisymmetric_moments(self.J1, self.J2, names=("J1", "J2"), owner=owner, mass=self.m, radius=self.r)
        self.chart_eps = float(in_range("chart_eps", chart_eps, 0.0, 1.0, hi_closed=False, owner=owner, as_float=True,
                                        shape=(), what="margin of the tilt guard cos(theta) > chart_eps"))

    @property
    def inertia(self):
        """Body inertia tensor diag(J1, J2, J2): body axis 1 is the disk's axis."""
        return jnp.diag(jnp.stack([self.J1, self.J2, self.J2]))


class RollingDisk(_DiskParams, ConstrainedLagrangian):
    """Sharp-edged disk in minimal coordinates (x1, x2, phi, theta, psi) (seed 002, 9.37-9.44).

    See the module docstring for geometry, parameters, the chart guard and the
    circular motions.
    """

    n: int = eqx.field(static=True, default=5)

    state_names: ClassVar[tuple] = (
        "x1", "x2", "phi", "theta", "psi",
        "x1_dot", "x2_dot", "phi_dot", "theta_dot", "psi_dot",
    )  # fmt: skip
    control_dim: ClassVar[int] = 0

    def __init__(self, m=1.0, r=1.0, g=1.0, J1=0.35, J2=0.5, chart_eps=1e-3):
        self._set(m, r, g, J1, J2, chart_eps)
        self.n = 5

    # ------------------------------------------------------------ geometry
    def pose(self, q):
        """(R, u): rotation body -> space (columns a1 = axis, a2, a3) and centre of mass."""
        x1, x2, phi, th, psi = q[0], q[1], q[2], q[3], q[4]
        b = jnp.stack([jnp.cos(phi), jnp.sin(phi), jnp.zeros_like(phi)])
        nrm = jnp.stack([-jnp.sin(phi), jnp.cos(phi), jnp.zeros_like(phi)])
        d = jnp.cos(th) * E3 + jnp.sin(th) * nrm
        a1 = jnp.cross(b, d)
        a2 = -jnp.cos(psi) * d - jnp.sin(psi) * b
        a3 = jnp.cross(a1, a2)
        u = jnp.stack([x1, x2, jnp.zeros_like(x1)]) + self.r * d
        return jnp.stack([a1, a2, a3], axis=1), u

    def centre(self, x):
        """Centre of mass [m] (3,) at state x."""
        return self.pose(x[:5])[1]

    # ------------------------------------------------------------ the model
    def kinetic_energy(self, q, qd):
        m, r = self.m, self.r
        phi, th = q[2], q[3]
        x1d, x2d, phid, thd, psid = qd[0], qd[1], qd[2], qd[3], qd[4]
        s, c = jnp.sin(th), jnp.cos(th)
        sp, cp = jnp.sin(phi), jnp.cos(phi)
        along = x1d * cp + x2d * sp
        across = x2d * cp - x1d * sp
        trans = (
            x1d**2 + x2d**2 + r * r * thd**2 + r * r * s * s * phid**2
            + 2 * r * c * thd * across - 2 * r * s * phid * along
        )  # fmt: skip
        rot = self.J2 * (thd**2 + c * c * phid**2) + self.J1 * (psid - s * phid) ** 2
        return 0.5 * m * trans + 0.5 * rot

    def potential_energy(self, q):
        return self.m * self.g * self.r * jnp.cos(q[3])

    def velocity_constraints(self, t, q, qd):
        rs = self.r * qd[4]
        return jnp.stack([qd[0] - rs * jnp.cos(q[2]), qd[1] - rs * jnp.sin(q[2])])

    def guards(self, x):
        return {"tilt": jnp.cos(x[3]) - self.chart_eps}

    # ------------------------------------------------------------ states
    def initial_state(self, x1=0.0, x2=0.0, phi=0.0, theta=0.0, psi=0.0, phi_dot=0.0, theta_dot=0.0, psi_dot=0.0):
        """Consistent state from the angles [rad] and rates [rad/s]; x' = r psi' b."""
        owner = "RollingDisk.initial_state"
        vals = [real(n, v, owner=owner) for n, v in (("x1", x1), ("x2", x2), ("phi", phi), ("theta", theta),
                                                     ("psi", psi), ("phi_dot", phi_dot),
                                                     ("theta_dot", theta_dot), ("psi_dot", psi_dot))]
        x1, x2, phi, th, psi, phid, thd, psid = vals
        if not isinstance(th, jax.core.Tracer):
            chart_argument(self, "tilt", np.cos(np.asarray(th, float)) - self.chart_eps, owner=owner, name="theta")
        return on_host(lambda xp, r, x1, x2, phi, th, psi, phid, thd, psid: xp.stack([
            x1, x2, phi, th, psi,
            r * psid * xp.cos(phi), r * psid * xp.sin(phi), phid, thd, psid,
        ]), self.r, *vals)  # fmt: skip

    def circular_rate(self, theta0, q):
        """Rolling rate s = psi' [rad/s] of the circular motion with tilt theta0 and
        contact-path curvature q [1/m] (radius 1/q); ValueError if there is none."""
        s, c = np.sin(float(theta0)), np.cos(float(theta0))
        m, r, g, J1, J2 = (float(v) for v in (self.m, self.r, self.g, self.J1, self.J2))
        den = (m * r * r + J1) * c * q * r - (m * r * r + J1 - J2) * s * c * (q * r) ** 2
        num = m * g * r * s
        if not (num / den > 0 if den != 0 else num == 0):
            raise ValueError(
                f"no circular rolling with tilt theta0 = {theta0} and curvature q = {q}: "
                "the tilt must lean towards the centre of the circle (theta0 and q of the "
                "same sign) and the circle must not be too tight"
            )
        return float(np.sqrt(num / den)) if num else 0.0

    def circular_curvature(self, theta0, spin):
        """Curvatures q [1/m] of the circular motions with tilt theta0 and rolling rate
        ``spin`` = psi' (roots of the balance in the module docstring, ascending)."""
        s, c = np.sin(float(theta0)), np.cos(float(theta0))
        m, r, g, J1, J2 = (float(v) for v in (self.m, self.r, self.g, self.J1, self.J2))
        w = float(spin)
        roots = np.roots([(m * r * r + J1 - J2) * s * c * r * r * w * w, -(m * r * r + J1) * c * r * w * w, m * g * r * s])
        return np.sort(roots[np.isreal(roots)].real)

    def circular_state(self, theta0, q, spin=None):
        """State on the circle of radius 1/q about the origin: contact at (0, -1/q),
        heading e1, tilt theta0, psi' = spin, phi' = q r spin (turning left for q > 0).
        With spin=None the rolling rate of the circular motion (``circular_rate``);
        any other spin gives the seed's perturbed data (9.44) (Table 9.1)."""
        owner = "RollingDisk.circular_state"
        theta0 = float(in_range("theta0", theta0, -np.pi / 2, np.pi / 2, lo_closed=False, hi_closed=False,
                                owner=owner, as_float=True, shape=(), what="tilt [rad]"))
        q = float(real("q", q, owner=owner, as_float=True, shape=(), what="curvature of the contact path [1/m]"))
        if q == 0.0:
            raise ParameterError(f"{owner}: q must be nonzero (the circle has radius 1/q), got 0; "
                                 "for straight rolling use initial_state", "q", q)
        s = self.circular_rate(theta0, q) if spin is None else float(real("spin", spin, owner=owner, as_float=True, shape=()))
        return self.initial_state(x2=-1.0 / q, theta=theta0, psi_dot=s, phi_dot=q * float(self.r) * s)

    def circular_period(self, theta0, q):
        """Time for one orbit of the circular motion [s]: 2 pi / phi'."""
        return 2 * np.pi / (q * float(self.r) * self.circular_rate(theta0, q))

    def to_quaternion_state(self, x):
        """The same state in ``RollingDiskQuaternion`` coordinates (u, p, u', p'). A
        concrete x: one compiled program (``nhjax._programs.small_call``) instead of
        eager operations, each a small program compiled in every new process."""
        return _programs.small_call("RollingDisk.to_quaternion_state", _quaternion_state, self, x)

    def quaternion_model(self):
        return RollingDiskQuaternion(self.m, self.r, self.g, self.J1, self.J2, self.chart_eps)


def _quaternion_state(disk, x):
    """``RollingDisk.to_quaternion_state``'s computation."""
    q, qd = x[:5], x[5:]
    (R, u), (Rd, ud) = jax.jvp(disk.pose, (q,), (qd,))
    p = so3.quat_from_matrix(R)
    p = p * jnp.sign(p[0] + (p[0] == 0))  # representative with p0 >= 0
    W = so3.vee(R.T @ Rd)
    pd = 0.5 * so3.quat_mul(p, jnp.concatenate([jnp.zeros(1), W]))
    return jnp.concatenate([u, p, ud, pd])


class RollingDiskQuaternion(_DiskParams, ConstrainedLagrangian):
    """The sharp-edged disk as a rigid body in (u, p) in R^3 x S^3 (seed 002, 9.39-9.40).

    State (u, p, u', p'), 14 components; see the module docstring.
    """

    n: int = eqx.field(static=True, default=7)

    state_names: ClassVar[tuple] = (
        "u1", "u2", "u3", "p0", "p1", "p2", "p3",
        "u1_dot", "u2_dot", "u3_dot", "p0_dot", "p1_dot", "p2_dot", "p3_dot",
    )  # fmt: skip
    control_dim: ClassVar[int] = 0

    def __init__(self, m=1.0, r=1.0, g=1.0, J1=0.35, J2=0.5, chart_eps=1e-3, baumgarte=(0.0, 0.0)):
        self._set(m, r, g, J1, J2, chart_eps)
        self.n = 7
        self.baumgarte = baumgarte_gains("RollingDiskQuaternion", baumgarte)

    def axis(self, q):
        """Disk axis a1 = R_p e1 in space (first column of the rotation of p/|p|)."""
        p0, p1, p2, p3 = q[3], q[4], q[5], q[6]
        n2 = p0 * p0 + p1 * p1 + p2 * p2 + p3 * p3
        return jnp.stack([p0 * p0 + p1 * p1 - p2 * p2 - p3 * p3, 2 * (p1 * p2 + p0 * p3), 2 * (p1 * p3 - p0 * p2)]) / n2

    def _horizontal_extent(self, a1):
        # |P a1|: sin of the angle between the axis and the vertical
        return jnp.sqrt(a1[0] ** 2 + a1[1] ** 2)

    def _down(self, q):
        """r d: from the contact point to the centre, d = (e3 - (a1.e3) a1)/|P a1|."""
        a1 = self.axis(q)
        return self.r * (E3 - a1[2] * a1) / self._horizontal_extent(a1)

    def contact_point(self, q):
        """Lowest point of the rim x = u - r d [m] (3,)."""
        return q[:3] - self._down(q)

    def kinetic_energy(self, q, qd):
        W = 2 * so3.quat_mul(so3.quat_conj(q[3:7]), qd[3:7])[1:]
        return 0.5 * self.m * jnp.dot(qd[:3], qd[:3]) + 0.5 * W @ self.inertia @ W

    def potential_energy(self, q):
        return self.m * self.g * q[2]

    def position_constraints(self, t, q):
        a1 = self.axis(q)
        return jnp.stack([jnp.dot(q[3:7], q[3:7]) - 1.0, q[2] - self.r * self._horizontal_extent(a1)])

    def velocity_constraints(self, t, q, qd):
        p, pd = q[3:7], qd[3:7]
        w = 2 * so3.quat_mul(pd, so3.quat_conj(p))[1:]
        v = qd[:3] - jnp.cross(w, self._down(q))
        return v[:2]

    def guards(self, x):
        a1 = self.axis(x[:7])
        return {"tilt": self._horizontal_extent(a1) - self.chart_eps}

    def tilt(self, x):
        """Tilt of the disk's plane from the vertical, |theta| = arcsin(|a1 . e3|) [rad]."""
        return jnp.arcsin(jnp.clip(jnp.abs(self.axis(x[:7])[2]), 0.0, 1.0))

    def minimal_model(self):
        return RollingDisk(self.m, self.r, self.g, self.J1, self.J2, self.chart_eps)
