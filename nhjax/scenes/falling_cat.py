r"""Iwai's falling cat: two identical axisymmetric cylinders, twist-free joint.

Seed 000 (T. Iwai, *Geometric mechanics of many-body systems*, J. Comput. Appl.
Math. 140 (2002) 403–422), sections 6–7.

Model
-----
Each cylinder has mass ``m``, transverse moment ``I1`` and axial moment
``I2 = lam I1`` about its centre of mass; the joint sits on the symmetry axis
at distance ``l`` from each centre of mass. Only three numbers enter the
dynamics:

    I1 [kg m^2],   lam = I2 / I1 [-],   B = m l^2 / I1 [-].

For solid cylinders of length L and radius r jointed end to end (l = L/2):
I1 = m (3 r^2 + L^2)/12, lam = 6 r^2 / (3 r^2 + L^2), B = 3 L^2 / (3 r^2 + L^2)
(``FallingCat.from_dimensions``).

Coordinates (6.6): the attitudes of the cylinders are

    g1 = exp(psi e2^) exp(-theta e1^) exp(chi e2^),
    g2 = exp(psi e2^) exp(+theta e1^) exp(chi e2^),

theta is half the bend angle (0: straight along e2, pi/2: folded back), chi the
common twist of both cylinders about their own axes, psi the overall rotation
about e2 (the long axis of the straight cat). With the centre of mass at the
origin, the centres are r1 = -l (a1 + a2)/2 = -r2 (a_i = g_i e2) and the joint
is at r1 + l a1. On these configurations the total angular momentum points
along e2 and equals 2 I1 D (psi' + f chi'), so zero angular momentum is the
connection (6.7):

    psi' + f(theta) chi' = 0,   D = sin^2 theta + lam cos^2 theta,  f = lam cos theta / D.

Lagrangian (7.9) and torque-driven equations (7.14)-(7.15) (s = sin theta,
c = cos theta; inputs u1 on theta, u2 on chi, generalized forces u1 dtheta + u2 dchi):

    2 I1 (1 + B s^2) theta'' = -2 I1 B s c theta'^2 + 2 I1 lam^2 s c / D^2 chi'^2 + u1
    2 I1 lam s^2 / D chi''   = -4 I1 lam^2 s c / D^2 theta' chi' + u2
    psi' = -f(theta) chi'

The signs above were re-derived from (7.9) (the extraction of the seed garbled
them); ``FallingCat(equations="engine")`` derives the same equations by
autodiff from the two-rigid-body kinetic energy and the angular-momentum
constraint, and the tests check that both agree.

Curvature (7.13): F12 = df/dtheta = -lam s (1 + (1 - lam) c^2) / D^2.
Holonomy: a closed shape loop C turns psi by -oint_C f dchi; a loop at fixed
theta with chi advancing 2 pi gives exactly -2 pi f(theta).

State of ``FallingCat``: x = (theta, chi, psi, theta', chi') [rad, rad/s];
psi' is not a state (it is -f chi'). Inputs u = (u1, u2) [N m].
State of ``FallingCatKinematic`` (velocity control (7.1)): x = (theta, chi, psi),
u = (theta', chi') [rad/s].

Chart: (theta, chi, psi) is singular where sin(theta) = 0 (the straight cat:
chi and psi both turn about the same axis; the twist inertia 2 I1 lam s^2/D
vanishes). Simulations stop there with ``ChartSingularityError``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _programs
from .. import _validate as V
from ..lie import SO3Body, Euclidean, so3
from ..mechanics import AbstractSystem, ConstrainedLagrangian, MultibodyKinetics, RigidBody

__all__ = [
    "FallingCat",
    "FallingCatAttitudes",
    "FallingCatKinematic",
    "FallingCatLagrangian",
    "FallingCatSmooth",
    "ShapeLoopTorque",
]

E2 = np.array([0.0, 1.0, 0.0])  # numpy: no program to compile at import

_CHART_HINT = (
    "Iwai's (theta, chi, psi) chart is singular at sin(theta) = 0, where the cat is "
    "straight and chi, psi turn about the same axis; the motion itself is smooth "
    "there. Keep the shape path away from theta = 0 (e.g. start slightly bent), or "
    "lower chart_eps to go closer."
)


_WHAT = {
    "I1": "transverse moment of each cylinder about its centre of mass [kg m^2]",
    "lam": "I2 / I1, axial over transverse moment [-]",
    "B": "m l^2 / I1 [-]",
    "mass": "mass of each cylinder [kg]",
}


def _cat_parameters(owner, I1, lam, B, mass):
    """(I1, lam, B, mass) as float arrays, each finite and positive (named as passed), with
    lam = I2 / I1 <= 2 (an axisymmetric body's axial moment is at most twice its
    transverse one)."""
    out = tuple(V.positive(name, v, owner=owner, what=_WHAT[name])
                for name, v in (("I1", I1), ("lam", lam), ("B", B), ("mass", mass)))
    V.axisymmetric_moments(out[1], 1.0, names=("lam", "1 (lam = I2/I1, the axial over the transverse moment)"),
                           owner=owner)
    return out


def _chart_eps(owner, chart_eps):
    return float(V.in_range("chart_eps", chart_eps, 0.0, 1.0, hi_closed=False, owner=owner, as_float=True, shape=(),
                            what="margin of the chart guard sin(theta) > chart_eps"))


class _CatGeometry(eqx.Module):
    """Parameters and closed-form geometry shared by the cat models."""

    I1: jax.Array
    lam: jax.Array
    B: jax.Array
    mass: jax.Array
    chart_eps: float = eqx.field(static=True, default=1e-3)

    guard_hints: ClassVar[dict] = {"sin_theta": _CHART_HINT}
    guard_arguments: ClassVar[dict] = {"sin_theta": "theta"}

    def _theta_in_chart(self, theta, owner):
        """theta inside the chart of the models with the guard sin(theta) > chart_eps."""
        if "sin_theta" in type(self).guard_arguments and not V.is_traced(theta):
            V.chart_argument(self, "sin_theta", np.sin(np.asarray(theta, float)) - self.chart_eps,
                             owner=owner, name="theta")

    @classmethod
    def from_dimensions(cls, mass=1.0, length=1.0, radius=0.25, joint_offset=None, **kw):
        """Solid cylinders of ``mass`` [kg], ``length`` and ``radius`` [m], joint at
        distance ``joint_offset`` from each centre of mass (default length/2: end to end);
        ``kw`` are the model's other settings. Every cat model has it."""
        owner = f"{cls.__name__}.from_dimensions"
        mass = V.positive("mass", mass, owner=owner, what="mass of each cylinder [kg]")
        length = V.positive("length", length, owner=owner, what="length of each cylinder [m]")
        radius = V.positive("radius", radius, owner=owner, what="radius of each cylinder [m]")
        l = None if joint_offset is None else V.positive(  # noqa: E741
            "joint_offset", joint_offset, owner=owner, what="joint to centre-of-mass distance [m]")

        def moments(xp, m, L, r, l):  # noqa: E741
            l = L / 2 if l is None else l  # noqa: E741
            I1 = m * (3 * r**2 + L**2) / 12
            return I1, m * r**2 / 2 / I1, m * l**2 / I1

        I1, lam, B = V.on_host(moments, mass, length, radius, l)
        return cls(I1=I1, lam=lam, B=B, mass=mass, **kw)

    # --- geometry (6.6), connection (6.7), metric (7.3), curvature (7.13)
    def D(self, theta):
        s, c = jnp.sin(theta), jnp.cos(theta)
        return s * s + self.lam * c * c

    def f(self, theta):
        """Connection coefficient: psi' = -f(theta) chi'."""
        return self.lam * jnp.cos(theta) / self.D(theta)

    def curvature(self, theta):
        """F12(theta) = df/dtheta (7.13)."""
        s, c = jnp.sin(theta), jnp.cos(theta)
        return -self.lam * s * (1 + (1 - self.lam) * c * c) / self.D(theta) ** 2

    def holonomy_fixed_theta(self, theta, windings=1.0):
        """Turn of psi for chi advancing 2 pi * windings at fixed theta: -2 pi f(theta) * windings."""
        return -2 * jnp.pi * windings * self.f(theta)

    def theta_for_turn(self, turn, windings=1):
        """theta in (0, pi/2) whose fixed-theta loop turns psi by ``turn`` (|turn| < 2 pi windings).

        Solves f(theta) = k, k = |turn| / (2 pi windings):  k (lam - 1) c^2 - lam c + k = 0.
        The sign of the turn is set by the direction of the twist.
        """
        k = abs(float(turn)) / (2 * np.pi * windings)
        if not 0 < k < 1:
            raise ValueError(
                f"a fixed-theta loop with {windings} winding(s) turns psi by less than "
                f"2 pi * {windings} in magnitude; asked for {float(turn):.4g}"
            )
        lam = float(self.lam)
        if abs(lam - 1) < 1e-12:
            c = k
        else:
            a, b = k * (lam - 1), -lam
            disc = np.sqrt(b * b - 4 * a * k)
            roots = [(-b + disc) / (2 * a), (-b - disc) / (2 * a)]
            c = [r for r in roots if 0 < r <= 1][0]
        return float(np.arccos(c))

    @property
    def l(self):  # noqa: E743
        """Joint to centre-of-mass distance [m] (from B = m l^2 / I1)."""
        return jnp.sqrt(self.B * self.I1 / self.mass)

    @property
    def radius(self):
        """Cylinder radius [m] of a solid cylinder with I2 = m r^2 / 2 (for drawing)."""
        return jnp.sqrt(2 * self.lam * self.I1 / self.mass)

    @property
    def length(self):
        """Cylinder length [m] of a solid cylinder with I1 = m (3 r^2 + L^2)/12 (for drawing)."""
        return jnp.sqrt(jnp.maximum(12 * self.I1 / self.mass - 3 * self.radius**2, 0.0))

    def body(self):
        I2 = self.lam * self.I1
        return RigidBody(self.mass, jnp.diag(jnp.stack([self.I1, I2, self.I1])))

    def poses(self, q):
        """Attitudes (2,3,3) and centres of mass (2,3) of the cylinders at q = (theta, chi, psi)."""
        theta, chi, psi = q[0], q[1], q[2]
        outer, inner = so3.rot_y(psi), so3.rot_y(chi)
        g1 = outer @ so3.rot_x(-theta) @ inner
        g2 = outer @ so3.rot_x(theta) @ inner
        a1, a2 = g1 @ E2, g2 @ E2
        r1 = -0.5 * self.l * (a1 + a2)
        return jnp.stack([g1, g2]), jnp.stack([r1, -r1])

    def joint(self, q):
        Rs, rs = self.poses(q)
        return rs[0] + self.l * Rs[0] @ E2

    def kinetics(self):
        b = self.body()
        return MultibodyKinetics((b, b), self.poses)

    def angular_momentum_3d(self, q, qd):
        """Total angular momentum [kg m^2/s] of both cylinders, from their 3-D motion."""
        return self.kinetics().angular_momentum(q, qd)

    def guards(self, x):
        return {"sin_theta": jnp.sin(x[0]) - self.chart_eps}


class FallingCat(_CatGeometry, AbstractSystem):
    """Torque-driven falling cat at zero angular momentum (7.14)-(7.15).

    ``equations="hand"`` (default) uses the closed forms above;
    ``equations="engine"`` uses ``FallingCatLagrangian`` (autodiff from the
    rigid-body model). See the module docstring for parameters and units.
    """

    equations: str = eqx.field(static=True, default="hand")

    state_names: ClassVar[tuple] = ("theta", "chi", "psi", "theta_dot", "chi_dot")
    control_dim: ClassVar[int] = 2

    def __init__(
        self,
        I1=0.09895833333333333,
        lam=0.31578947368421056,
        B=2.5263157894736845,
        mass=1.0,
        equations="hand",
        chart_eps=1e-3,
    ):
        V.choice("equations", equations, ("hand", "engine"), owner="FallingCat")
        self.I1, self.lam, self.B, self.mass = _cat_parameters("FallingCat", I1, lam, B, mass)
        self.equations = equations
        self.chart_eps = _chart_eps("FallingCat", chart_eps)

    def initial_state(self, theta, chi=0.0, psi=0.0, theta_dot=0.0, chi_dot=0.0):
        """State from half bend angle, twist, overall angle [rad] and rates [rad/s]."""
        vals = _state_args(type(self).__name__, theta=theta, chi=chi, psi=psi, theta_dot=theta_dot,
                           chi_dot=chi_dot)
        self._theta_in_chart(vals[0], f"{type(self).__name__}.initial_state")
        return V.stacked(vals)

    def velocities(self, x):
        """Generalized velocities (theta', chi', psi') with psi' = -f chi'."""
        return jnp.stack([x[3], x[4], -self.f(x[0]) * x[4]])

    def shape_inertia(self, theta):
        """Diagonal of the vibrational metric (7.3) in (theta, chi): 2 I1 (1 + B s^2), 2 I1 lam s^2/D."""
        s = jnp.sin(theta)
        return jnp.stack([2 * self.I1 * (1 + self.B * s * s), 2 * self.I1 * self.lam * s * s / self.D(theta)])

    def shape_accelerations(self, x, u):
        """(theta'', chi'') from (7.14)."""
        th, thd, chd = x[0], x[3], x[4]
        s, c = jnp.sin(th), jnp.cos(th)
        D = self.D(th)
        I1, lam, B = self.I1, self.lam, self.B
        m1, m2 = self.shape_inertia(th)
        thdd = (-2 * I1 * B * s * c * thd**2 + 2 * I1 * lam**2 * s * c / D**2 * chd**2 + u[0]) / m1
        chdd = (-4 * I1 * lam**2 * s * c / D**2 * thd * chd + u[1]) / m2
        return jnp.stack([thdd, chdd])

    def required_torques(self, x, shape_acc):
        """Inverse of (7.14): the torques (u1, u2) that produce ``shape_acc`` at x."""
        zero = self.shape_accelerations(x, jnp.zeros(2))
        return self.shape_inertia(x[0]) * (shape_acc - zero)

    def lagrangian_model(self):
        return FallingCatLagrangian(self.I1, self.lam, self.B, self.mass)

    def vector_field(self, t, x, u):
        if u is None:
            u = jnp.zeros(2, x.dtype)
        if self.equations == "engine":
            q = x[:3]
            qdd, _ = self.lagrangian_model().accelerations(t, q, self.velocities(x), u)
            acc = qdd[:2]
        else:
            acc = self.shape_accelerations(x, u)
        return jnp.concatenate([self.velocities(x), acc])

    def energy(self, x):
        """Kinetic energy (7.9) with psi' + f chi' = 0 [J]."""
        m = self.shape_inertia(x[0])
        return 0.5 * (m[0] * x[3] ** 2 + m[1] * x[4] ** 2)

    def power(self, t, x, u):
        return u[0] * x[3] + u[1] * x[4]

    def invariants(self, x):
        L = self.angular_momentum_3d(x[:3], self.velocities(x))
        return {"angular_momentum_x": L[0], "angular_momentum_y": L[1], "angular_momentum_z": L[2]}

    def attitude_model(self):
        return FallingCatAttitudes(self.I1, self.lam, self.B, self.mass, chart_eps=self.chart_eps)


class FallingCatLagrangian(_CatGeometry, ConstrainedLagrangian):
    """The cat from first principles, for the engine: q = (theta, chi, psi).

    T(q, q') is the kinetic energy of the two rigid cylinders placed by
    ``poses`` (autodiff through rotation matrices, not (7.9)); the constraint is
    the e2 component of their total angular momentum (the other components
    vanish identically on these configurations, see the module docstring), and
    the inputs act as generalized forces (u1, u2, 0).
    """

    n: int = eqx.field(static=True, default=3)
    state_names: ClassVar[tuple] = ("theta", "chi", "psi", "theta_dot", "chi_dot", "psi_dot")
    control_dim: ClassVar[int] = 2

    def __init__(self, I1=0.09895833333333333, lam=0.31578947368421056, B=2.5263157894736845, mass=1.0,
                 chart_eps=1e-3):
        self.I1, self.lam, self.B, self.mass = _cat_parameters("FallingCatLagrangian", I1, lam, B, mass)
        self.chart_eps = _chart_eps("FallingCatLagrangian", chart_eps)
        self.n = 3

    def kinetic_energy(self, q, qd):
        return self.kinetics().kinetic_energy(q, qd)

    def velocity_constraints(self, t, q, qd):
        return self.angular_momentum_3d(q, qd)[1:2]

    def generalized_force(self, t, q, qd, u):
        return jnp.stack([u[0], u[1], jnp.zeros((), q.dtype)])

    def guards(self, x):
        return {"sin_theta": jnp.sin(x[0]) - self.chart_eps}

    def invariants(self, x):
        L = self.angular_momentum_3d(x[:3], x[3:])
        return {"angular_momentum_x": L[0], "angular_momentum_z": L[2]}


class FallingCatKinematic(_CatGeometry, AbstractSystem):
    """Velocity-controlled cat (7.1): theta' = u1, chi' = u2, psi' = -f(theta) u2.

    State (theta, chi, psi) [rad]; inputs (theta', chi') [rad/s]. Cost of a
    motion: the vibrational energy (4.8) with the metric (7.3),
    ``vibrational_power(x, u)``.
    """

    state_names: ClassVar[tuple] = ("theta", "chi", "psi")
    control_dim: ClassVar[int] = 2
    requires_control: ClassVar[bool] = True

    def __init__(self, I1=0.09895833333333333, lam=0.31578947368421056, B=2.5263157894736845, mass=1.0, chart_eps=1e-3):
        self.I1, self.lam, self.B, self.mass = _cat_parameters("FallingCatKinematic", I1, lam, B, mass)
        self.chart_eps = _chart_eps("FallingCatKinematic", chart_eps)

    def initial_state(self, theta, chi=0.0, psi=0.0):
        """State (theta, chi, psi) [rad]."""
        vals = _state_args(type(self).__name__, theta=theta, chi=chi, psi=psi)
        self._theta_in_chart(vals[0], f"{type(self).__name__}.initial_state")
        return V.stacked(vals)

    def vector_field(self, t, x, u):
        return jnp.stack([u[0], u[1], -self.f(x[0]) * u[1]])

    def vibrational_power(self, x, u):
        """Integrand of (4.8): (1/2) a_ij u^i u^j = I1 [(1 + B s^2) u1^2 + lam s^2/D u2^2]."""
        s = jnp.sin(x[0])
        return self.I1 * ((1 + self.B * s * s) * u[0] ** 2 + self.lam * s * s / self.D(x[0]) * u[1] ** 2)


class FallingCatSmooth(_CatGeometry, AbstractSystem):
    """Velocity-controlled cat in coordinates that are smooth at the straight cat.

    Shape: w = theta (cos chi, sin chi) in R^2 (the shape space RP^2 near theta = 0;
    |w| = theta); fiber: phi = psi + chi (the attitude of the straight cat about e2).
    With u = w' [rad/s] (inputs) the connection psi' = -f chi' becomes

        phi' = k(theta^2) (w1 u2 - w2 u1),   k = (1 - f(theta)) / theta^2,

    and the vibrational metric (7.3) becomes 2 I1 (a |u|^2 + b (w . u)^2) with
    a = lam s^2 / (D theta^2), b = ((1 + B s^2) - a) / theta^2 (s = sin theta). All
    three are even, smooth functions of theta^2, evaluated through series-guarded
    sinc-type functions (exact at theta = 0):

        k = (lam cosc + (1 - lam) sinc^2) / D,     a = lam sinc^2 / D,
        b = B sinc^2 + (lam sinc3 (1 + sinc) + (1 - lam) sinc^2) / D,
        D = lam + (1 - lam) theta^2 sinc^2,

    with sinc = sin(theta)/theta, cosc = (1 - cos theta)/theta^2, sinc3 =
    (theta - sin theta)/theta^3. A motion whose shape returns (w(T) = w(0)) turns
    the cat about e2 by phi(T) - phi(0) (mod 2 pi); the winding of w about the
    origin is the number of twists chi made. No chart guard: paths may cross theta = 0.

    State (w1, w2, phi) [rad]; inputs (w1', w2') [rad/s].
    """

    state_names: ClassVar[tuple] = ("w1", "w2", "phi")
    control_dim: ClassVar[int] = 2
    requires_control: ClassVar[bool] = True

    guard_arguments: ClassVar[dict] = {}  # smooth at theta = 0: no chart guard

    def __init__(self, I1=0.09895833333333333, lam=0.31578947368421056, B=2.5263157894736845, mass=1.0):
        self.I1, self.lam, self.B, self.mass = _cat_parameters("FallingCatSmooth", I1, lam, B, mass)
        self.chart_eps = 0.0

    def initial_state(self, theta, chi=0.0, psi=0.0):
        """State (w1, w2, phi) of the cat at Iwai's (theta, chi, psi) [rad]."""
        return self.from_chart(*_state_args(type(self).__name__, theta=theta, chi=chi, psi=psi))

    def coefficients(self, w):
        """(k, a, b) at shape w (see the class docstring)."""
        from ..lie import _series as S

        t2 = w @ w
        sc, cc, s3 = S.sinc(t2), S.cosc(t2), S.sinc3(t2)
        lam = self.lam
        D = lam + (1 - lam) * t2 * sc * sc
        k = (lam * cc + (1 - lam) * sc * sc) / D
        a = lam * sc * sc / D
        b = self.B * sc * sc + (lam * s3 * (1 + sc) + (1 - lam) * sc * sc) / D
        return k, a, b

    def vector_field(self, t, x, u):
        k, _, _ = self.coefficients(x[:2])
        return jnp.stack([u[0], u[1], k * (x[0] * u[1] - x[1] * u[0])])

    def vibrational_power(self, x, u):
        """Integrand of (4.8) in these coordinates: I1 (a |u|^2 + b (w . u)^2)."""
        _, a, b = self.coefficients(x[:2])
        return self.I1 * (a * u @ u + b * (x[:2] @ u) ** 2)

    def guards(self, x):
        return {}

    @staticmethod
    def from_chart(theta, chi, psi):
        """(w1, w2, phi) from Iwai's (theta, chi, psi)."""
        return jnp.stack([theta * jnp.cos(chi), theta * jnp.sin(chi), psi + chi])

    @staticmethod
    def winding(ws):
        """Number of turns of a path ws (N, 2) about the origin (chi's total advance / 2 pi);
        a numpy path is measured in numpy (no jax program)."""
        xp = np if isinstance(ws, np.ndarray) else jnp
        ang = xp.unwrap(xp.arctan2(ws[:, 1], ws[:, 0]))
        return (ang[-1] - ang[0]) / (2 * np.pi)


class FallingCatAttitudes(_CatGeometry, AbstractSystem):
    """The torque-driven cat with both attitudes integrated on SO(3).

    State: (g1, g2, s) with g_i in SO(3) (3x3, body-frame velocities) and
    s = (theta, chi, theta', chi'). The attitudes obey g_i' = g_i hat(Omega_i),
    Omega_i the body angular velocity implied by the shape velocities and the
    zero-momentum connection, so psi is not a coordinate here: the rotation is
    reconstructed on the group (use ``nhjax.RKMK45``/``RKMK4``). The invariants
    are computed from the attitudes alone (centres from the joint condition).
    """

    state_names: ClassVar[tuple] = ()
    control_dim: ClassVar[int] = 2
    # stages in a lax.scan: the vector field is traced once per step, not once per stage,
    # for a shorter first compile at no cost in run time (benchmarks/compile_times.py)
    large_vector_field: ClassVar[bool] = True

    def __init__(self, I1=0.09895833333333333, lam=0.31578947368421056, B=2.5263157894736845, mass=1.0,
                 chart_eps=1e-3):
        self.I1, self.lam, self.B, self.mass = _cat_parameters("FallingCatAttitudes", I1, lam, B, mass)
        self.chart_eps = _chart_eps("FallingCatAttitudes", chart_eps)

    @property
    def spaces(self):
        return (SO3Body(), SO3Body(), Euclidean())

    def _cat(self):
        return FallingCat(self.I1, self.lam, self.B, self.mass, chart_eps=self.chart_eps)

    def initial_state(self, theta, chi=0.0, psi=0.0, theta_dot=0.0, chi_dot=0.0):
        """((g1, g2, s)) from half bend angle, twist, overall angle [rad] and rates [rad/s]."""
        numbers = _state_args(type(self).__name__, theta=theta, chi=chi, psi=psi, theta_dot=theta_dot,
                              chi_dot=chi_dot)
        self._theta_in_chart(numbers[0], f"{type(self).__name__}.initial_state")
        # concrete numbers: one compiled program instead of eager operations (small programs
        # compiled in every new process)
        return _programs.small_call("FallingCatAttitudes.initial_state", _attitudes_state, self, *numbers)

    def body_angular_velocities(self, s):
        """Omega_1, Omega_2 [rad/s] for shape state s = (theta, chi, theta', chi')."""
        q = jnp.array([s[0], s[1], 0.0])
        qd = jnp.stack([s[2], s[3], -self.f(s[0]) * s[3]])
        (Rs, _), (Rds, _) = jax.jvp(self.poses, (q,), (qd,))
        return so3.vee(jnp.swapaxes(Rs, -1, -2) @ Rds)

    def vector_field(self, t, y, u):
        g1, g2, s = y
        if u is None:
            u = jnp.zeros(2, s.dtype)
        x5 = jnp.array([s[0], s[1], 0.0, s[2], s[3]])
        acc = self._cat().shape_accelerations(x5, u)
        W = self.body_angular_velocities(s)
        return (W[0], W[1], jnp.concatenate([s[2:], acc]))

    def guards(self, y):
        return {"sin_theta": jnp.sin(y[2][0]) - self.chart_eps}

    def wrap_control(self, control):
        """Use a control written for ``FallingCat`` (state of 5) on this model."""
        return _OnAttitudeModel(control)

    def angular_momentum(self, y):
        """Total angular momentum from the attitudes and their rates alone."""
        g1, g2, s = y
        W = self.body_angular_velocities(s)
        b = self.body()
        gd1, gd2 = g1 @ so3.hat(W[0]), g2 @ so3.hat(W[1])
        a1, a2 = g1 @ E2, g2 @ E2
        ad1, ad2 = gd1 @ E2, gd2 @ E2
        r1, rd1 = -0.5 * self.l * (a1 + a2), -0.5 * self.l * (ad1 + ad2)
        return b.angular_momentum(g1, gd1, r1, rd1) + b.angular_momentum(g2, gd2, -r1, -rd1)

    def invariants(self, y):
        L = self.angular_momentum(y)
        return {"angular_momentum_x": L[0], "angular_momentum_y": L[1], "angular_momentum_z": L[2]}

    def energy(self, y):
        g1, g2, s = y
        return self._cat().energy(jnp.array([s[0], s[1], 0.0, s[2], s[3]]))

    def power(self, t, y, u):
        s = y[2]
        return u[0] * s[2] + u[1] * s[3]


class _OnAttitudeModel(eqx.Module):
    control: Any

    @property
    def breakpoints(self):
        return getattr(self.control, "breakpoints", None)

    def __call__(self, t, y):
        s = y[2]
        return self.control(t, jnp.stack([s[0], s[1], jnp.zeros_like(s[0]), s[2], s[3]]))


def _attitudes_state(cat, theta, chi, psi, theta_dot, chi_dot):
    """``FallingCatAttitudes.initial_state``'s state from its checked numbers."""
    Rs, _ = cat.poses(jnp.stack([theta, chi, psi]))
    return (Rs[0], Rs[1], jnp.stack([theta, chi, theta_dot, chi_dot]))


def _state_args(owner, **kw):
    """The named state arguments as finite float scalars (or arrays), in order."""
    return [V.real(name, v, owner=f"{owner}.initial_state") for name, v in kw.items()]


def _smoothstep(tau):
    """Quintic 0 -> 1 with zero first and second derivatives at both ends."""
    tau = jnp.clip(tau, 0.0, 1.0)
    return tau**3 * (10 - 15 * tau + 6 * tau**2)


class ShapeLoopTorque(eqx.Module):
    """Computed-torque control that drives the cat around a closed shape loop.

    The loop (all phases quintic in time, rest to rest):
      1. bend:   theta from theta0 to theta1 at chi = 0             (duration t_bend)
      2. twist:  chi from 0 to 2 pi * windings at theta = theta1    (duration t_twist)
      3. unbend: theta from theta1 back to theta0                   (duration t_unbend)
    Only phase 2 moves psi: the loop turns the cat by exactly
    -2 pi windings f(theta1) (``FallingCat.holonomy_fixed_theta``).

    u = M_s (q_d'' + kp (q_d - q) + kd (q_d' - q')) + h(q, q'): the inverse of
    (7.14) along the plan, with optional PD correction (gains in 1/s^2, 1/s).
    ``breakpoints`` tells simulate() where the phases join.
    """

    cat: FallingCat
    theta0: jax.Array
    theta1: jax.Array
    windings: jax.Array
    t_bend: jax.Array
    t_twist: jax.Array
    t_unbend: jax.Array
    kp: jax.Array
    kd: jax.Array

    def __init__(self, cat, theta0, theta1, windings=1.0, t_bend=1.0, t_twist=3.0, t_unbend=1.0, kp=0.0, kd=0.0):
        owner = "ShapeLoopTorque"
        if not isinstance(cat, FallingCat):
            raise V.ParameterError(f"{owner}: cat must be an nhjax.scenes.FallingCat, got {type(cat).__name__}",
                                   "cat", cat)
        self.cat = cat
        self.theta0, self.theta1 = (
            V.in_range(n, v, 0.0, np.pi, lo_closed=False, hi_closed=False, owner=owner,
                       what="half bend angle inside the chart (0, pi) [rad]")
            for n, v in (("theta0", theta0), ("theta1", theta1)))
        self.windings = V.real("windings", windings, owner=owner, what="turns of the twist chi")
        self.t_bend, self.t_twist, self.t_unbend = (
            V.positive(n, v, owner=owner, what="phase duration [s]")
            for n, v in (("t_bend", t_bend), ("t_twist", t_twist), ("t_unbend", t_unbend)))
        self.kp = V.positive("kp", kp, allow_zero=True, owner=owner, what="proportional gain [1/s^2]")
        self.kd = V.positive("kd", kd, allow_zero=True, owner=owner, what="derivative gain [1/s]")

    @classmethod
    def for_turn(cls, cat, turn=np.pi, theta0=0.15, windings=1, **kw):
        """The loop whose closed-form holonomy turns psi by ``turn`` (sign from the twist direction)."""
        theta1 = cat.theta_for_turn(turn, windings)
        w = -np.sign(turn) * windings
        return cls(cat, theta0, theta1, windings=w, **kw)

    @property
    def duration(self):
        return self.t_bend + self.t_twist + self.t_unbend

    @property
    def breakpoints(self):
        return jnp.stack([self.t_bend, self.t_bend + self.t_twist])

    @property
    def turn(self):
        """Closed-form turn of psi over the whole loop."""
        return self.cat.holonomy_fixed_theta(self.theta1, self.windings)

    def path(self, t):
        """Planned (theta, chi) at time t."""
        t1 = self.t_bend
        t2 = t1 + self.t_twist
        s1 = _smoothstep(t / self.t_bend)
        s2 = _smoothstep((t - t1) / self.t_twist)
        s3 = _smoothstep((t - t2) / self.t_unbend)
        theta = self.theta0 + (self.theta1 - self.theta0) * (s1 - s3)
        chi = 2 * jnp.pi * self.windings * s2
        return jnp.stack([theta, chi])

    def plan(self, t):
        """(q_d, q_d', q_d'') of the shape at time t."""
        dpath = lambda tt: jax.jvp(self.path, (tt,), (jnp.ones_like(tt),))[1]  # noqa: E731
        t = jnp.asarray(t, float)
        qd_, qdd_ = jax.jvp(dpath, (t,), (jnp.ones_like(t),))
        return self.path(t), qd_, qdd_

    def __call__(self, t, x):
        q, v, a = self.plan(t)
        shape = jnp.stack([x[0], x[1]])
        rate = jnp.stack([x[3], x[4]])
        acc = a + self.kp * (q - shape) + self.kd * (v - rate)
        return self.cat.required_torques(x, acc)
