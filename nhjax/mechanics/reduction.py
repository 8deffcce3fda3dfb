r"""Reduced dynamics by symmetry, derived from a body model by autodiff.

A user describes a shape-changing system by its **bodies** (point masses, or
rigid bodies with mass and inertia), a **shape map** r -> the poses of the
bodies in a reference frame (a local section of the bundle Q -> Q/G), and a
**symmetry group** G acting on the left on the whole system: ``SO3()``,
``SE3()``, ``SO2()`` (in the plane, or in space about a fixed ``axis``),
``SE2()``. A configuration is (g, r): body i sits at the pose g . s_i(r).
Everything else is computed by JAX from the kinetic energy of the bodies:

Reduced Lagrangian. With xi = g^-1 g' (body velocity of the group, algebra
coordinates below) and the shape velocity r', the kinetic energy is
G-invariant, so it is a function l(r, r', xi): the kinetic energy of the bodies
placed by s(r) and moved by the generator of xi plus ds/dr r'. Its Hessian in
v = (xi, r') is the metric (seed 001, eq. (1) and sec. 3)

    G(r) = [[I(r), B(r)], [B(r)^T, G_rr(r)]],

with I(r) the **locked inertia** (seed 000 (3.9); seed 001 (2), (6)).

Mechanical connection (seed 000 (3.11)-(3.15), seed 001 (3), (8)). The body
momentum mu = dl/dxi = I (xi + A r') defines the local connection

    A(r) = I^-1 B,         xi = -A(r) r' + I(r)^-1 mu            (seed 001 (8), (9a)),

so at zero momentum g' = -g A(r) r' (seed 000 (3.13): A r' = A^-1(q) m_i u^i there).
The spatial momentum (the momentum map) is J = Ad*_{g^-1} mu; without
external forces it is conserved.

Curvature (seed 000 (5.16), here for the left-trivialized local form):

    F_ij = d_i A_j - d_j A_i - [A_i, A_j]        (A_i = A(r) e_i, [a, b] = ad_a b),

and a closed shape loop of small area eps^2 in the (i, j) plane turns the group by
exp(-F_ij eps^2 + O(eps^3)); for an abelian group, or a connection whose
components commute, the holonomy is exactly -(integral of F over the enclosed
region) (Stokes), see ``curvature_integral``.

Reduced (vibrational) metric (seed 000 (4.5)-(4.7), seed 001 (10)):

    M(r) = G_rr - B^T I^-1 B = G_rr - A^T I A.

Equations of motion (Lagrange-Poincare; seed 001 (9a)-(9c), seed 000 (5.23)).
With generalized forces tau = (tau_xi, tau_r) dual to (xi, r') (from the power
of the inputs: joint torques, and body-fixed forces such as thrusters):

    g'   = g xi,                     xi = -A r' + I^-1 mu               (9a)
    mu'  = ad*_xi mu + tau_xi                                           (9b)
    M r'' = tau_r - A^T tau_xi + dl/dr - D_r p_r[r'] + A^T D_r mu[r'] - A^T ad*_xi mu,

where p = (mu, p_r) = G v and D_r p[r'] is its derivative along r' at fixed v.
The last line is (9c) M r'' + r'^T C r' + N = X tau with the Coriolis term C of
(11), the momentum terms N (quadratic and gyroscopic (curvature) terms in mu)
and the forcing X tau = tau_r - A^T tau_xi of the seed, written without
expanding them by hand: every derivative comes from jax. The derivation
eliminates xi' between d/dt dl/dr' - dl/dr = tau_r and mu = I xi + B r'.

State (``ReducedSystem``): x = [group coordinates, r, r', momentum], flat, for
SO(2) (angle) and SE(2) (x, y, angle: a global chart, the angle is not wrapped);
for SO(3) and SE(3) a pair (R, flat) where R in SO(3) is integrated on the group
(``nhjax.lie.SO3Body``, RKMK) and the flat part holds (for SE(3)) the position
b. The momentum part is chosen by ``momentum``:

* ``"zero"``: none; mu = 0 exactly (the seeds' vanishing-momentum systems);
* ``"spatial"`` (default otherwise): J, with J' = Ad*_{g^-1} tau_xi: without
  body forces J stays constant to round-off, whatever the tolerance;
* ``"body"``: mu itself with (9b), the textbook reduced form (decoupled from g).

Point masses and rigid bodies are placed by one shape map; for groups without
translations (SO(3), SO(2)) the reference positions are taken relative to the
centre of mass (the centre-of-mass system of seed 000 (2.1)), so the shape map
may place the bodies anywhere.

Where the bundle degenerates. G acts freely only where the locked inertia is
invertible: for SO(3) not on collinear configurations (seed 000 (2.3)), for
SO(2) about an axis not where every mass lies on that axis. The guard
``locked_inertia`` (spatial groups) is the normalized determinant
det I_c / (tr I_c / 3)^3 (about the axis: n.I_c n / (tr I_c / 2)) of the
rotational inertia about the centre of mass, minus ``guard_eps``: it is 1 for a
spherical inertia and 0 on the degenerate set, and simulate() stops there
(``ChartSingularityError``) instead of integrating a connection that blows up.
The determinant is even in the distance from the degenerate set: it touches zero
there, so a path that crosses straight through it can be stepped over (the guard
is checked at step ends); it stops paths that approach or end near it. Where a
shape chart lets paths cross the degenerate set, a ``chart_guard`` that changes
sign there catches the crossing (``ThreeBodyCat``'s ``collinear``). Shape charts
with their own singularities add guards the same way.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _primitive, _programs
from .._primitive import stored as _stored
from .. import _args as V
from ..errors import ParameterError, StateError
from ..lie import se2, so3
from ..lie.spaces import Euclidean, SO3Body
from .system import AbstractSystem

__all__ = [
    "Bodies",
    "ReducedKinematic",
    "ReducedSystem",
    "SE2",
    "SE3",
    "SO2",
    "SO3",
    "Symmetry",
    "EllipseLoop",
    "curvature_integral",
]

_J2 = np.array([[0.0, -1.0], [1.0, 0.0]])  # numpy: no program to compile at import


def _rot2(th):
    c, s = jnp.cos(th), jnp.sin(th)
    return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)


def _cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


# ---------------------------------------------------------------------------- groups
class Symmetry(eqx.Module):
    """A symmetry group acting on the left on body poses; see the module docstring.

    Algebra coordinates: SO(2): omega; SO(3): omega (3); SE(2): (vx, vy, omega);
    SE(3): (v (3), omega (3)). ``generator(xi)`` returns the spatial velocity field
    (omega, v) at the identity: a point x moves with v + omega x x.
    """

    dim: ClassVar[int]
    spatial: ClassVar[bool]  # bodies in R^3 (else in the plane)
    recentre: ClassVar[bool]  # no translations in G: positions relative to the centre of mass
    matrix: ClassVar[bool]  # an SO(3) attitude matrix is part of the state
    coord_names: ClassVar[tuple] = ()  # flat coordinates of g in the state
    momentum_names: ClassVar[tuple] = ()

    def generator(self, xi):
        raise NotImplementedError

    def ad(self, xi):
        """Matrix of ad_xi: [xi, eta] = ad(xi) @ eta."""
        raise NotImplementedError

    def rates(self, R, c, xi):
        """(body angular velocity of R or None, rates of the flat coordinates c)."""
        raise NotImplementedError

    def to_spatial(self, R, c, mu):
        """J = Ad*_{g^-1} mu (spatial momentum from body momentum)."""
        raise NotImplementedError

    def to_body(self, R, c, J):
        """mu = Ad*_g J."""
        raise NotImplementedError

    def place(self, R, c, rot, pos):
        """Spatial poses g . (rot, pos) of all bodies, and the rotation that maps the
        reference frame's vectors to space (for velocities)."""
        raise NotImplementedError

    def identity(self):
        """(R, c) of the identity."""
        # (host arrays sent to the device: an eager jnp.eye/zeros is an XLA program of its own)
        return (V.to_device(np.eye(3)) if self.matrix else None), V.to_device(np.zeros(len(self.coord_names)))


class SO3(Symmetry):
    """Rotations of R^3 about the centre of mass (seed 000's centre-of-mass system)."""

    dim = 3
    spatial = True
    recentre = True
    matrix = True
    coord_names = ()
    momentum_names = ("angular_momentum_x", "angular_momentum_y", "angular_momentum_z")

    def generator(self, xi):
        return xi, jnp.zeros(3, xi.dtype)

    def ad(self, xi):
        return so3.hat(xi)

    def rates(self, R, c, xi):
        return xi, jnp.zeros((0,), xi.dtype)

    def to_spatial(self, R, c, mu):
        return R @ mu

    def to_body(self, R, c, J):
        return R.T @ J

    def place(self, R, c, rot, pos):
        return R[None] @ rot, pos @ R.T, R


class SE3(Symmetry):
    """Rigid motions of R^3, g = (R, b); algebra (v, omega), v the body-frame velocity."""

    dim = 6
    spatial = True
    recentre = False
    matrix = True
    coord_names = ("bx", "by", "bz")
    momentum_names = ("linear_momentum_x", "linear_momentum_y", "linear_momentum_z",
                      "angular_momentum_x", "angular_momentum_y", "angular_momentum_z")

    def generator(self, xi):
        return xi[3:], xi[:3]

    def ad(self, xi):
        v, w = so3.hat(xi[:3]), so3.hat(xi[3:])
        z = jnp.zeros((3, 3), xi.dtype)
        return jnp.block([[w, v], [z, w]])

    def rates(self, R, c, xi):
        return xi[3:], R @ xi[:3]

    def to_spatial(self, R, c, mu):
        p = R @ mu[:3]
        return jnp.concatenate([p, jnp.cross(c, p) + R @ mu[3:]])

    def to_body(self, R, c, J):
        return jnp.concatenate([R.T @ J[:3], R.T @ (J[3:] - jnp.cross(c, J[:3]))])

    def place(self, R, c, rot, pos):
        return R[None] @ rot, pos @ R.T + c, R


class SO2(Symmetry):
    """Rotations about the centre of mass: in the plane (``axis=None``), or in space
    about a fixed unit ``axis`` (e.g. Iwai's cat turning about e2)."""

    axis: Any = None
    dim = 1
    recentre = True
    matrix = False
    coord_names = ("angle",)
    momentum_names = ("angular_momentum",)

    def __init__(self, axis=None):
        if axis is not None:
            a = V.real("axis", axis, owner="SO2", what="unit 3-vector of the rotation axis")
            if not isinstance(a, jax.core.Tracer) and (a.shape != (3,) or abs(float(jnp.linalg.norm(a)) - 1) > 1e-12):
                raise ParameterError(f"SO2(axis=...) must be a unit 3-vector, got {axis!r}", "axis", axis)
            axis = a
        self.axis = axis

    @property
    def spatial(self):  # type: ignore[override]
        return self.axis is not None

    def generator(self, xi):
        if self.axis is None:
            return xi[0], jnp.zeros(2, xi.dtype)
        return xi[0] * self.axis, jnp.zeros(3, xi.dtype)

    def ad(self, xi):
        return jnp.zeros((1, 1), xi.dtype)

    def rates(self, R, c, xi):
        return None, xi

    def to_spatial(self, R, c, mu):
        return mu

    def to_body(self, R, c, J):
        return J

    def place(self, R, c, rot, pos):
        if self.axis is None:
            Rg = _rot2(c[0])
            return rot + c[0], pos @ Rg.T, Rg
        Rg = so3.exp(c[0] * self.axis)
        return Rg[None] @ rot, pos @ Rg.T, Rg


class SE2(Symmetry):
    """Rigid motions of the plane, g = (x, y, angle); algebra (vx, vy, omega) as in
    ``nhjax.lie.se2`` (v the body-frame velocity of the reference point)."""

    dim = 3
    spatial = False
    recentre = False
    matrix = False
    coord_names = ("x", "y", "angle")
    momentum_names = ("linear_momentum_x", "linear_momentum_y", "angular_momentum")

    def generator(self, xi):
        return xi[2], xi[:2]

    def ad(self, xi):
        return se2.ad(xi)

    def rates(self, R, c, xi):
        return None, jnp.concatenate([_rot2(c[2]) @ xi[:2], xi[2:]])

    def to_spatial(self, R, c, mu):
        g = se2.from_xytheta(c[0], c[1], c[2])
        return se2.Ad(se2.inverse(g)).T @ mu

    def to_body(self, R, c, J):
        return se2.Ad(se2.from_xytheta(c[0], c[1], c[2])).T @ J

    def place(self, R, c, rot, pos):
        Rg = _rot2(c[2])
        return rot + c[2], pos @ Rg.T + c[:2], Rg


_GROUPS = {"SO3": SO3, "SE3": SE3, "SO2": SO2, "SE2": SE2}


def _symmetry(group):
    if isinstance(group, Symmetry):
        return group
    if isinstance(group, str) and group in _GROUPS:
        return _GROUPS[group]()
    raise ParameterError(
        f"group={group!r}: give a Symmetry (SO3(), SE3(), SO2(), SO2(axis=...), SE2()) "
        f"or one of {sorted(_GROUPS)}", "group", group
    )


# ---------------------------------------------------------------------------- bodies
def _check_inertias(J, given):
    """Planar moments >= 0; spatial tensors symmetric positive semidefinite (zero: a
    point mass; the kinetic energy is then >= 0, as for ``RigidBody``) with principal
    moments that obey the triangle inequality (``nhjax._args.inertias``)."""
    if J.ndim == 1:
        if not np.all(J >= 0):
            raise ParameterError(f"Bodies: inertias must be non-negative [kg m^2], got {J.tolist()}",
                                 "inertias", given)
        return
    V.inertias("inertias", J, owner="Bodies", allow_zero=True)


class Bodies(eqx.Module):
    """Masses [kg] and inertias about the centres of mass [kg m^2] of n bodies.

    Planar bodies: ``inertias`` shape (n,) (moment about the normal); spatial
    bodies: (n, 3, 3) in body frames. Zero inertia makes a point mass. The shape
    map of a ``ReducedSystem`` returns (orientations, positions) of all bodies:
    planar (n,) angles [rad] and (n, 2) positions [m]; spatial (n, 3, 3) rotation
    matrices and (n, 3) positions; or positions alone for point masses.
    """

    masses: jax.Array
    inertias: jax.Array

    def __init__(self, masses, inertias=None, spatial=None):
        m = V.positive("masses", masses, allow_zero=True, owner="Bodies", what="masses of the bodies [kg]")
        if m.ndim != 1 or m.shape[0] == 0:
            raise ParameterError(f"Bodies: masses must be a non-empty 1-D array [kg], got shape {m.shape}",
                                 "masses", masses)
        if not isinstance(m, jax.core.Tracer) and not float(np.sum(np.asarray(m))) > 0:
            raise ParameterError(f"Bodies: masses must be >= 0 with a positive total, got {np.asarray(m)}",
                                 "masses", masses)
        n = m.shape[0]
        if inertias is None:
            if spatial is None:
                raise ParameterError("Bodies: give inertias, or spatial=True/False for point masses",
                                     "inertias", inertias)
            inertias = jnp.zeros((n, 3, 3)) if spatial else jnp.zeros(n)
        J = V.real("inertias", inertias, owner="Bodies", what="inertias about the centres of mass [kg m^2]")
        if J.shape not in ((n,), (n, 3, 3)):
            raise ParameterError(
                f"Bodies: inertias must have shape ({n},) (planar) or ({n}, 3, 3) (spatial), got {J.shape}",
                "inertias", inertias)
        if not isinstance(J, jax.core.Tracer):
            _check_inertias(np.asarray(J), inertias)
        self.masses, self.inertias = m, J

    @property
    def spatial(self) -> bool:
        return self.inertias.ndim == 3

    @property
    def n(self) -> int:
        return self.masses.shape[0]

    @classmethod
    def point_masses(cls, masses, spatial=True):
        return cls(masses, None, spatial=spatial)


# ---------------------------------------------------------------------------- system
_LOCKED_HINT = (
    "the locked inertia is (nearly) singular: the bodies are (nearly) collinear (or all "
    "on the symmetry axis), where the group does not act freely and the bundle Q -> Q/G "
    "degenerates (seed 000, condition (2.3)); the connection A = I^-1 B blows up there. "
    "Keep the shape away from such configurations, or lower guard_eps to go closer."
)
_REG_HINTS = {
    "locked_inertia": _LOCKED_HINT,
    "shape_metric": "the reduced metric M(r) = G_rr - A^T I A is singular: the shape "
    "coordinates are degenerate here (a singular chart of the shape map) or do not move "
    "any mass.",
}


def _vec_arg(name, value, n, owner, what):
    """A finite vector of n entries (a scalar for n = 1)."""
    a = V.real(name, value, owner=owner, what=what)
    if not isinstance(a, jax.core.Tracer) and a.size != n:
        raise ParameterError(f"{owner}: {name} must have {n} entries ({what}), got shape {tuple(a.shape)}",
                             name, value)
    return a.reshape(-1)


def _geometry(name, *params):
    """``@_stored(name)`` (one stored program on known values) with the method's
    arguments checked first by ``_check_geometry``: a wrong number of shape coordinates,
    a state of another system, NaN, are named before anything runs. ``params``: the
    (name, kind) of each argument. The checks of shapes are static, so they hold while
    traced too (inside a solve they add nothing to the program)."""

    def decorate(fn):
        stored = _stored(name)(fn)

        @functools.wraps(fn)
        def method(self, *args):
            _check_geometry(self, fn.__name__, params, args)
            return stored(self, *args)

        method.plain = fn
        return method

    return decorate


def _check_geometry(system, method, params, args):
    """Check the arguments of a reduction helper; kinds: "r" (shape coordinates, (k,)),
    "rdd" (shape accelerations, (k,)), "u" (inputs, (n_inputs,); None allowed), "x" (a
    state of ``system``: its structure, the group part's shape, the flat part's length).
    Known values must be finite. ParameterError / StateError naming the argument."""
    owner = f"{type(system).__name__}.{method}"
    for (pname, kind), a in zip(params, args):
        if kind == "u" and a is None:
            continue
        if kind == "x":
            system._state_arg(a, pname, owner)
            continue
        size, what = ((system.n_inputs, "inputs") if kind == "u" else
                      (system.k, "shape accelerations" if kind == "rdd" else "shape coordinates"))
        shape = np.shape(a) if hasattr(a, "shape") else None
        if shape is None:
            try:
                shape = np.shape(np.asarray(a, float))
            except (TypeError, ValueError):
                raise ParameterError(f"{owner}: {pname} must be an array of {size} real numbers ({what}), "
                                     f"got {a!r}", pname, a) from None
        if tuple(shape) != (size,):
            names = f" {system.shape_names}" if kind != "u" else ""
            raise ParameterError(f"{owner}: {pname} must have shape ({size},): {size} {what}{names} of "
                                 f"{type(system).__name__}, got shape {tuple(shape)}", pname, a)
        if not isinstance(a, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(a, float))):
            raise ParameterError(f"{owner}: {pname} contains NaN or inf ({what}); pass finite numbers", pname, a)


class _ShapeForces(eqx.Module):
    """Default inputs: one generalized force per shape coordinate (joint torques)."""

    def __call__(self, r, u):
        return u, None


class ReducedSystem(AbstractSystem):
    """Reduced dynamics of a body model with symmetry; see the module docstring.

    Parameters
    ----------
    bodies : ``Bodies`` (masses, inertias), planar or spatial as the group.
    shape_map : r -> (orientations, positions) of the bodies in the reference
        frame (a local section), or r -> positions for point masses. A function
        (its closed-over arrays are constants) or an equinox module (its arrays are
        parameters for jit/vmap/grad).
    group : ``SO3()``, ``SE3()``, ``SO2()``, ``SO2(axis=...)``, ``SE2()`` (or their names).
    shape_dim : number k of shape coordinates r.
    momentum : "zero" | "spatial" | "body" (default: "zero" without body forces,
        else "spatial").
    inputs : None (u = generalized forces on the k shape coordinates, e.g. joint
        torques [N m] on joint angles), or a callable ``inputs(r, u) -> (tau_r,
        wrenches)``: generalized shape forces (k,) and body-frame wrenches on the
        bodies at their centres of mass, (n, 3) = (fx, fy, torque) planar or
        (n, 6) = (force, torque) spatial, or None. Body wrenches are external
        (thrusters): they change the momentum.
    control_dim : number of inputs u (default k when ``inputs`` is None).
    shape_names : names of the shape coordinates (state names r, r_dot).
    chart_guard : optional r -> {name: value} positive where the shape chart is valid.
    guard_eps : threshold of the ``locked_inertia`` guard (spatial groups).
    """

    bodies: Bodies
    shape_map: Callable
    symmetry: Symmetry
    inputs: Callable
    chart_guard: Callable | None
    k: int = eqx.field(static=True)
    momentum: str = eqx.field(static=True)
    n_inputs: int = eqx.field(static=True)
    external: bool = eqx.field(static=True)
    shape_names: tuple = eqx.field(static=True)
    guard_eps: float = eqx.field(static=True)
    positions_only: bool = eqx.field(static=True)

    large_vector_field: ClassVar[bool] = True
    regularity_hints: ClassVar[dict] = _REG_HINTS
    guard_hints: ClassVar[dict] = {"locked_inertia": _LOCKED_HINT, "collinear": _LOCKED_HINT}
    guard_arguments: ClassVar[dict] = {"locked_inertia": "shape", "collinear": "shape"}

    def __init__(self, bodies, shape_map, group, shape_dim, *, momentum=None, inputs=None,
                 control_dim=None, shape_names=None, chart_guard=None, guard_eps=1e-6):
        self._setup(bodies, shape_map, group, shape_dim, momentum=momentum, inputs=inputs,
                    control_dim=control_dim, shape_names=shape_names, chart_guard=chart_guard,
                    guard_eps=guard_eps)

    def _setup(self, bodies, shape_map, group, shape_dim, *, momentum=None, inputs=None,
               control_dim=None, shape_names=None, chart_guard=None, guard_eps=1e-6):
        owner = type(self).__name__
        sym = _symmetry(group)
        if not isinstance(bodies, Bodies):
            raise ParameterError(f"{owner}: bodies must be a nhjax.mechanics.reduction.Bodies, "
                                 f"got {type(bodies).__name__}", "bodies", bodies)
        if bodies.spatial != sym.spatial:
            where = "spatial (inertias (n, 3, 3))" if sym.spatial else "planar (inertias (n,))"
            raise ParameterError(f"{owner}: group {type(sym).__name__} needs {where} bodies", "group", group)
        V.function("shape_map", shape_map, owner=owner, signature="r -> (orientations, positions) or positions")
        V.function("chart_guard", chart_guard, owner=owner, signature="r -> {name: value}", optional=True)
        k = V.integer("shape_dim", shape_dim, minimum=1, owner=owner, what="number of shape coordinates")
        V.choice("momentum", momentum, (None, "zero", "spatial", "body"), owner=owner)
        if inputs is None:
            inputs, control_dim = _ShapeForces(), k if control_dim is None else control_dim
        elif control_dim is None:
            raise ParameterError(f"{owner}: with inputs=..., give control_dim (the number of inputs u)",
                                 "control_dim", control_dim)
        V.function("inputs", inputs, owner=owner, signature="(r, u) -> (tau_r, wrenches)")
        n_inputs = V.integer("control_dim", control_dim, minimum=0, owner=owner, what="number of inputs u")
        if shape_names is not None and (isinstance(shape_names, str) or not isinstance(shape_names, (tuple, list))
                                        or not all(isinstance(n, str) for n in shape_names)):
            raise ParameterError(f"{owner}: shape_names must be a tuple of {k} strings, got {shape_names!r}",
                                 "shape_names", shape_names)
        names = tuple(shape_names) if shape_names is not None else tuple(f"r{i}" for i in range(k))
        if len(names) != k:
            raise ParameterError(f"{owner}: shape_names has {len(names)} names for shape_dim = {k}",
                                 "shape_names", shape_names)
        guard_eps = V.in_range("guard_eps", guard_eps, 0.0, 1.0, hi_closed=False, owner=owner, shape=(),
                               as_float=True, what="margin of the locked_inertia guard")
        self.bodies, self.shape_map, self.symmetry = bodies, shape_map, sym
        self.inputs, self.chart_guard = inputs, chart_guard
        self.n_inputs = n_inputs
        self.k, self.shape_names, self.guard_eps = k, names, guard_eps
        out = jax.eval_shape(shape_map, jax.ShapeDtypeStruct((k,), jnp.float64))
        self.positions_only = not isinstance(out, (tuple, list))
        self._check_shape_map(out)
        f64 = jnp.float64
        tau_r, wrench = jax.eval_shape(inputs, jax.ShapeDtypeStruct((k,), f64),
                                       jax.ShapeDtypeStruct((self.n_inputs,), f64))
        if tau_r is not None and tau_r.shape != (k,):
            raise ParameterError(f"{owner}: inputs(r, u) must return shape forces of shape ({k},), "
                                 f"got {tau_r.shape}", "inputs", inputs)
        w = 6 if sym.spatial else 3
        if wrench is not None and wrench.shape != (bodies.n, w):
            raise ParameterError(f"{owner}: inputs(r, u) must return body wrenches of shape ({bodies.n}, {w}), "
                                 f"got {wrench.shape}", "inputs", inputs)
        # a body wrench (thruster) is external: it changes the momentum
        self.external = wrench is not None
        if momentum is None:
            momentum = "spatial" if self.external else "zero"
        if momentum == "zero" and self.external:
            raise ParameterError(
                f"{owner}: momentum='zero' cannot hold with body forces (thrusters change the momentum): "
                "use momentum='spatial' or 'body'", "momentum", momentum
            )
        self.momentum = momentum

    def _check_shape_map(self, out):
        n, d = self.bodies.n, 3 if self.symmetry.spatial else 2
        pos = out if self.positions_only else out[1]
        want_rot = (n, 3, 3) if self.symmetry.spatial else (n,)
        owner = type(self).__name__
        if pos.shape != (n, d):
            raise ParameterError(
                f"{owner}: shape_map(r) must give positions of shape ({n}, {d}) for {n} bodies, got {pos.shape}",
                "shape_map", self.shape_map)
        if not self.positions_only and out[0].shape != want_rot:
            raise ParameterError(
                f"{owner}: shape_map(r) must give orientations of shape {want_rot}, got {out[0].shape}",
                "shape_map", self.shape_map)
        if self.positions_only and not isinstance(self.bodies.inertias, jax.core.Tracer):
            if np.any(np.asarray(self.bodies.inertias) != 0):
                raise ParameterError(f"{owner}: shape_map returns positions only, but the bodies have inertia: "
                                     "return (orientations, positions)", "shape_map", self.shape_map)

    # ----------------------------------------------------------------- names
    @property
    def control_dim(self):  # type: ignore[override]
        return self.n_inputs

    @property
    def n_group(self):
        return len(self.symmetry.coord_names)

    @property
    def state_names(self):  # type: ignore[override]
        if self.symmetry.matrix:
            return ()
        return self.flat_names

    @property
    def flat_names(self):
        """Names of the flat part of the state."""
        mom = () if self.momentum == "zero" else tuple(
            ("mu_" if self.momentum == "body" else "J_") + n for n in self.symmetry.momentum_names)
        return (tuple(self.symmetry.coord_names) + self.shape_names
                + tuple(n + "_dot" for n in self.shape_names) + mom)

    @property
    def spaces(self):
        if self.symmetry.matrix:
            return (SO3Body(), Euclidean())
        return Euclidean()

    # ---------------------------------------------------------------- state
    def split(self, x):
        """(R or None, group coordinates c, r, r', momentum m or None)."""
        R, f = (x[0], x[1]) if self.symmetry.matrix else (None, x)
        ng, k = self.n_group, self.k
        c, r, rd = f[:ng], f[ng:ng + k], f[ng + k:ng + 2 * k]
        m = None if self.momentum == "zero" else f[ng + 2 * k:]
        return R, c, r, rd, m

    def join(self, R, c, r, rd, m=None):
        parts = [c, r, rd] + ([] if self.momentum == "zero" else [m])
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(parts)):
            f = jnp.concatenate([jnp.asarray(p, float).reshape(-1) for p in parts])
        else:  # concrete parts (a start state): joined on the host, without an eager program
            f = V.to_device(np.concatenate([np.asarray(p, float).reshape(-1) for p in parts]))
        return (R, f) if self.symmetry.matrix else f

    def initial_state(self, shape, shape_rate=None, group=None, momentum=None):
        """State from the shape r, its rate r' (default 0), the group element (default
        identity: (R, c) for SO(3)/SE(3), else the coordinates c) and the spatial
        momentum J (default 0; converted to mu for momentum='body')."""
        owner = f"{type(self).__name__}.initial_state"
        r = self._shape_arg("shape", shape, owner)
        rd = V.to_device(np.zeros(self.k)) if shape_rate is None else self._shape_arg("shape_rate", shape_rate, owner)
        R, c = self._group_arg(group, owner)
        m = None
        if self.momentum != "zero":
            J = V.to_device(np.zeros(self.symmetry.dim)) if momentum is None else _vec_arg(
                "momentum", momentum, self.symmetry.dim, owner, "spatial momentum J")
            m = J if self.momentum == "spatial" else self.symmetry.to_body(R, c, J)
        elif momentum is not None:
            J = V.real("momentum", momentum, owner=owner, what="momentum (zero for this system)")
            if not isinstance(J, jax.core.Tracer) and not np.allclose(np.asarray(J), 0):
                raise ParameterError(f"{owner}: momentum={momentum!r}, but this is a momentum='zero' system: "
                                     "the momentum is zero by construction; build it with momentum='spatial' "
                                     "to carry one", "momentum", momentum)
        return self.join(R, c, r, rd, m)

    def _shape_arg(self, name, value, owner):
        """A shape-space vector (k,) (finite); a scalar is accepted for k = 1."""
        r = V.real(name, value, owner=owner, what=f"shape coordinates {self.shape_names}")
        if not isinstance(r, jax.core.Tracer) and r.size != self.k:
            raise ParameterError(f"{owner}: {name} must have {self.k} entries {self.shape_names}, "
                                 f"got shape {tuple(r.shape)}", name, value)
        return r.reshape(-1)

    def _state_arg(self, x, name, owner):
        """A state of this system: (R, flat) for SO(3)/SE(3), else flat; the flat part with
        one entry per name of ``flat_names``; finite where its values are known. StateError."""
        want = len(self.flat_names)
        layout = (f"(R, flat) with R 3x3 and flat of {want} entries {self.flat_names}" if self.symmetry.matrix
                  else f"a flat array of {want} entries {self.flat_names}")
        parts = x if self.symmetry.matrix and isinstance(x, (tuple, list)) and len(x) == 2 else (
            None if self.symmetry.matrix else (x,))
        shapes = None if parts is None else [np.shape(p) if hasattr(p, "shape") else None for p in parts]
        if parts is not None and any(sh is None for sh in shapes):
            try:
                shapes = [np.shape(np.asarray(p, float)) for p in parts]
            except (TypeError, ValueError):
                shapes = None
        ok = shapes is not None and tuple(shapes[-1]) == (want,) and (
            not self.symmetry.matrix or tuple(shapes[0]) == (3, 3))
        if not ok:
            got = "something else" if shapes is None else ", ".join(f"shape {tuple(sh)}" for sh in shapes)
            raise StateError(f"{owner}: {name} must be a state of {type(self).__name__}: {layout}; got {got}. "
                             f"Build it with {type(self).__name__}.initial_state(...)", name)
        if not any(isinstance(p, jax.core.Tracer) for p in parts) and not all(
                np.all(np.isfinite(np.asarray(p, float))) for p in parts):
            raise StateError(f"{owner}: {name} contains NaN or inf; pass finite numbers", name)

    def _group_arg(self, group, owner):
        """(R, c) of the group element: identity by default; (R, c) or R for SO(3)/SE(3),
        with R checked on SO(3); else the flat coordinates (angle / x, y, angle)."""
        R, c = self.symmetry.identity()
        if group is None:
            return R, c
        if self.symmetry.matrix:
            Rg, cg = group if isinstance(group, tuple) else (group, c)
            R = V.rotation("group", Rg, owner=owner)
            c = _vec_arg("group", cg, c.shape[0], owner, "position b of the group element [m]")
        else:
            c = _vec_arg("group", group, c.shape[0], owner, f"group coordinates {self.symmetry.coord_names}")
        return R, c

    # ---------------------------------------------------------- kinematics
    @_stored("reduction.reference_poses")
    def reference_poses(self, r):
        """(orientations, positions) of the bodies in the reference frame at shape r
        (positions relative to the centre of mass for SO(3)/SO(2))."""
        out = self.shape_map(r)
        if self.positions_only:
            pos = out
            n = self.bodies.n
            rot = jnp.broadcast_to(jnp.eye(3), (n, 3, 3)) if self.symmetry.spatial else jnp.zeros(n)
        else:
            rot, pos = out
        if self.symmetry.recentre:
            m = self.bodies.masses
            pos = pos - (m @ pos) / jnp.sum(m)
        return rot, pos

    def _vel(self, S, Sdot, xi):
        """Body velocities (n, c) in the reference frame for poses S = (rot, pos), pose
        rates Sdot from the shape motion and group velocity xi; linear in (Sdot, xi).
        Planar c = 3: (u_x, u_y, omega); spatial c = 6: (u, Omega), Omega in the body frame."""
        rot, pos = S
        drot, dpos = Sdot
        w, vt = self.symmetry.generator(xi)
        if self.symmetry.spatial:
            lin = dpos + vt + jnp.cross(w, pos)
            ang = so3.vee(jnp.swapaxes(rot, -1, -2) @ drot) + jnp.einsum("nji,j->ni", rot, w)
            return jnp.concatenate([lin, ang], -1)
        lin = dpos + vt + w * pos @ _J2.T
        return jnp.concatenate([lin, (drot + w)[:, None]], -1)

    def _form(self, a, b):
        """The kinetic bilinear form of two body-velocity arrays (n, c): T = form(w, w) / 2."""
        m, J = self.bodies.masses, self.bodies.inertias
        if self.symmetry.spatial:
            return jnp.sum(m * jnp.sum(a[:, :3] * b[:, :3], -1)) + jnp.einsum("ni,nij,nj->", a[:, 3:], J, b[:, 3:])
        return jnp.sum(m * jnp.sum(a[:, :2] * b[:, :2], -1)) + jnp.sum(J * a[:, 2] * b[:, 2])

    def _gram(self, V, W):
        """Matrix of _form between the body-velocity arrays V (a, n, c) and W (b, n, c)."""
        m, J = self.bodies.masses, self.bodies.inertias
        if self.symmetry.spatial:
            Wm = jnp.concatenate([W[..., :3] * m[:, None], jnp.einsum("nij,bnj->bni", J, W[..., 3:])], -1)
        else:
            Wm = W * jnp.stack([m, m, J], -1)
        return jnp.einsum("anc,bnc->ab", V, Wm)

    def _poses_and_jacobian(self, r):
        return self.reference_poses(r), jax.jacfwd(self.reference_poses)(r)

    def _columns(self, S, DS):
        """V (d + k, n, c): the body velocities of the basis vectors of v = (xi, r')."""
        d = self.symmetry.dim
        zero = jax.tree_util.tree_map(jnp.zeros_like, S)
        Vxi = jax.vmap(lambda e: self._vel(S, zero, e))(jnp.eye(d))
        cols = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 0), DS)
        Vr = jax.vmap(lambda sd: self._vel(S, sd, jnp.zeros(d)))(cols)
        return jnp.concatenate([Vxi, Vr], 0)

    def _motion(self, r, v):
        """Poses and velocities of the bodies in the reference frame for v = (xi, r'):
        (rot, pos, angular velocity (planar: rate; spatial: body frame), linear velocity)."""
        d = self.symmetry.dim
        S, Sd = jax.jvp(self.reference_poses, (r,), (v[d:],))
        w = self._vel(S, Sd, v[:d])
        c = 3 if self.symmetry.spatial else 2
        ang = w[:, c:] if self.symmetry.spatial else w[:, 2]
        return S[0], S[1], ang, w[:, :c]

    def reduced_lagrangian(self, r, v):
        """l(r, r', xi) at v = (xi, r'): the kinetic energy [J] (seed 001 sec. 3)."""
        d = self.symmetry.dim
        S, Sd = jax.jvp(self.reference_poses, (r,), (v[d:],))
        w = self._vel(S, Sd, v[:d])
        return 0.5 * self._form(w, w)

    @_geometry("reduction.metric", ("r", "r"))
    def metric(self, r):
        """G(r) = d^2 l / dv^2: the kinetic metric in v = (xi, r') [(d + k) x (d + k)]."""
        V = self._columns(*self._poses_and_jacobian(r))
        return self._gram(V, V)

    @_geometry("reduction.locked_inertia", ("r", "r"))
    def locked_inertia(self, r):
        """I(r), the locked inertia in the reference frame (seed 000 (3.9), seed 001 (6))."""
        d = self.symmetry.dim
        return self.metric(r)[:d, :d]

    @_geometry("reduction.connection", ("r", "r"))
    def connection(self, r):
        """A(r) = I^-1 B (d x k), the local mechanical connection: xi = -A r' + I^-1 mu."""
        d = self.symmetry.dim
        G = self.metric(r)
        return jnp.linalg.solve(G[:d, :d], G[:d, d:])

    @_geometry("reduction.reduced_metric", ("r", "r"))
    def reduced_metric(self, r):
        """M(r) = G_rr - A^T I A (k x k), the vibrational metric (seed 000 (4.7), seed 001 (10))."""
        d = self.symmetry.dim
        G = self.metric(r)
        return G[d:, d:] - G[d:, :d] @ jnp.linalg.solve(G[:d, :d], G[:d, d:])

    @_geometry("reduction.curvature", ("r", "r"))
    def curvature(self, r):
        """F (d, k, k): F[:, i, j] = d_i A_j - d_j A_i - [A_i, A_j] (module docstring)."""
        A = self.connection(r)
        dA = jax.jacfwd(self.connection)(r)  # dA[a, j, i] = d_i A^a_j
        ext = jnp.swapaxes(dA, 1, 2) - dA  # [a, i, j] = d_i A_j - d_j A_i
        br = jax.vmap(lambda ai: jax.vmap(lambda aj: self.symmetry.ad(ai) @ aj)(A.T))(A.T)  # [i, j, a]
        return ext - jnp.moveaxis(br, 2, 0)

    @_geometry("reduction.rotational_inertia", ("r", "r"))
    def rotational_inertia(self, r):
        """Inertia about the centre of mass of the locked system [kg m^2]: 3x3 (spatial)
        or scalar (planar)."""
        rot, pos = self.reference_poses(r)
        m = self.bodies.masses
        y = pos - (m @ pos) / jnp.sum(m)
        if self.symmetry.spatial:
            own = jnp.einsum("nij,njk,nlk->il", rot, self.bodies.inertias, rot)
            return own + jnp.einsum("n,ij->ij", m * jnp.sum(y * y, -1), jnp.eye(3)) - jnp.einsum(
                "n,ni,nj->ij", m, y, y)
        return jnp.sum(self.bodies.inertias) + jnp.sum(m * jnp.sum(y * y, -1))

    @_geometry("reduction.inertia_condition", ("r", "r"))
    def inertia_condition(self, r):
        """Normalized determinant of the rotational locked inertia about the centre of
        mass: 1 for a spherical inertia, 0 where the group stops acting freely
        (spatial groups; planar groups return 1)."""
        if not self.symmetry.spatial:
            return jnp.ones((), r.dtype)
        Ic = self.rotational_inertia(r)
        if isinstance(self.symmetry, SO2):
            n = self.symmetry.axis
            return n @ Ic @ n / (0.5 * jnp.trace(Ic))
        return jnp.linalg.det(Ic) / (jnp.trace(Ic) / 3) ** 3

    def _wrench_forces(self, S, V, wrench):
        """Forces dual to v of body-frame wrenches at the centres of mass (their power
        sum_i f_i . (R_i^T u_i) + t_i . Omega_i is linear in v, with coefficients V)."""
        rot = S[0]
        if self.symmetry.spatial:
            fb = jnp.einsum("nij,nj->ni", rot, wrench[:, :3])  # f . (R^T u) = (R f) . u
            return jnp.einsum("ni,bni->b", fb, V[:, :, :3]) + jnp.einsum("ni,bni->b", wrench[:, 3:], V[:, :, 3:])
        fb = jnp.einsum("nij,nj->ni", _rot2(rot), wrench[:, :2])
        return jnp.einsum("ni,bni->b", fb, V[:, :, :2]) + jnp.einsum("n,bn->b", wrench[:, 2], V[:, :, 2])

    def _inputs(self, r, u, S, V):
        d, k = self.symmetry.dim, self.k
        tau_r, wrench = self.inputs(r, u)
        tau_r = jnp.zeros(k, r.dtype) if tau_r is None else jnp.asarray(tau_r)
        if wrench is None:
            return jnp.zeros(d, r.dtype), tau_r
        tau = self._wrench_forces(S, V, wrench)
        return tau[:d], tau_r + tau[d:]

    def generalized_forces(self, r, u):
        """(tau_xi, tau_r): the forces dual to (xi, r') of the inputs u (from their power)."""
        S, DS = self._poses_and_jacobian(r)
        return self._inputs(r, u, S, self._columns(S, DS))

    # ------------------------------------------------------------ dynamics
    def body_momentum(self, x):
        """mu, the body momentum of the locked system (zero for momentum='zero')."""
        R, c, r, rd, m = self.split(x)
        if self.momentum == "zero":
            return jnp.zeros(self.symmetry.dim, r.dtype)
        return m if self.momentum == "body" else self.symmetry.to_body(R, c, m)

    @_geometry("reduction.group_velocity", ("x", "x"))
    def group_velocity(self, x):
        """xi = g^-1 g' = -A(r) r' + I(r)^-1 mu  (seed 001 (8))."""
        _, _, r, rd, _ = self.split(x)
        d = self.symmetry.dim
        G = self.metric(r)
        return jnp.linalg.solve(G[:d, :d], self.body_momentum(x) - G[:d, d:] @ rd)

    def _dynamics(self, r, rd, mu, u):
        """(xi, r'', mu', tau_xi) from the elimination in the module docstring.

        Only the shape map is differentiated (its Jacobian DS and the derivative of DS
        along r', one forward-over-forward pass); the metric, dl/dr and the derivative
        of the momenta along r' are assembled from the body velocities of the basis
        vectors of v = (xi, r') and their derivatives (small dense algebra)."""
        d = self.symmetry.dim
        (S, DS), (Sd, DSd) = jax.jvp(self._poses_and_jacobian, (r,), (rd,))
        V = self._columns(S, DS)
        G = self._gram(V, V)
        I, B, Grr = G[:d, :d], G[:d, d:], G[d:, d:]
        sol = jnp.linalg.solve(I, jnp.concatenate([B, mu[:, None]], 1))  # one factorization
        A = sol[:, :-1]
        xi = sol[:, -1] - A @ rd
        v = jnp.concatenate([xi, rd])
        w = self._vel(S, Sd, xi)
        cols = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 0), DS)
        dcols = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 0), DSd)
        # dl/dr_j = form(w, d_j w); d_j of (S, DS r') is (DS e_j, D^2S[e_j, r']) = (DS e_j, DSd e_j)
        dw = jax.vmap(lambda a, b: jax.jvp(lambda S_, Sd_: self._vel(S_, Sd_, xi), (S, Sd), (a, b))[1])(cols, dcols)
        dl_dr = self._gram(dw, w[None])[:, 0]
        # the columns' derivative along r', then D_r p[r'] = dG v with dG = form(dV, V) + form(V, dV)
        zero = jax.tree_util.tree_map(jnp.zeros_like, S)
        dVxi = jax.vmap(lambda e: jax.jvp(lambda S_: self._vel(S_, zero, e), (S,), (Sd,))[1])(jnp.eye(d))
        dVr = jax.vmap(lambda a, b: jax.jvp(lambda S_, s_: self._vel(S_, s_, jnp.zeros(d)), (S, a), (Sd, b))[1])(
            cols, dcols)
        dV = jnp.concatenate([dVxi, dVr], 0)
        dVv = jnp.einsum("a,anc->nc", v, dV)
        Dp = self._gram(dV, w[None])[:, 0] + self._gram(V, dVv[None])[:, 0]
        if u is None:
            u = jnp.zeros(self.n_inputs, r.dtype)
        tau_xi, tau_r = self._inputs(r, u, S, V)
        mu_dot = self.symmetry.ad(xi).T @ mu + tau_xi
        M = Grr - B.T @ A
        rhs = tau_r + dl_dr - Dp[d:] - A.T @ (mu_dot - Dp[:d])
        return xi, jnp.linalg.solve(M, rhs), mu_dot, tau_xi

    @_geometry("reduction.shape_accelerations", ("x", "x"), ("u", "u"))
    def shape_accelerations(self, x, u=None):
        """r'' at state x under inputs u."""
        _, _, r, rd, _ = self.split(x)
        return self._dynamics(r, rd, self.body_momentum(x), u)[1]

    def vector_field(self, t, x, u):
        R, c, r, rd, m = self.split(x)
        xi, rdd, mu_dot, tau_xi = self._dynamics(r, rd, self.body_momentum(x), u)
        wR, dc = self.symmetry.rates(R, c, xi)
        if self.momentum == "zero":
            dm = None
        elif self.momentum == "body":
            dm = mu_dot
        else:
            dm = self.symmetry.to_spatial(R, c, tau_xi)
        f = jnp.concatenate([dc, rd, rdd] + ([] if dm is None else [dm]))
        return (wR, f) if self.symmetry.matrix else f

    # ------------------------------------------------------- reconstruction
    def group_element(self, x):
        """(R or None, group coordinates c)."""
        R, c, *_ = self.split(x)
        return R, c

    @_geometry("reduction.body_states", ("x", "x"))
    def body_states(self, x):
        """Spatial poses and velocities of the bodies at state x:
        (orientations, positions, angular velocities, linear velocities); planar:
        angles (n,), (n, 2), rates (n,), (n, 2); spatial: (n, 3, 3), (n, 3), body-frame
        angular velocities (n, 3), (n, 3)."""
        R, c, r, rd, _ = self.split(x)
        v = jnp.concatenate([self.group_velocity(x), rd])
        rot, pos, ang, vel = self._motion(r, v)
        rot_s, pos_s, Rg = self.symmetry.place(R, c, rot, pos)
        return rot_s, pos_s, ang, vel @ Rg.T

    @_geometry("reduction.momentum_map", ("x", "x"))
    def momentum_map(self, x):
        """The spatial momentum J of the bodies, summed over them in space (not from mu):
        for SO(3) the angular momentum about the centre of mass; SE(2) (p_x, p_y, L);
        SE(3) (p, L); SO(2) the angular momentum about its axis."""
        rot, pos, ang, vel = self.body_states(x)
        m, J = self.bodies.masses, self.bodies.inertias
        p = jnp.sum(m[:, None] * vel, 0)
        if self.symmetry.spatial:
            L = jnp.sum(m[:, None] * jnp.cross(pos, vel), 0) + jnp.einsum("nij,njk,nk->i", rot, J, ang)
        else:
            L = jnp.sum(m * _cross2(pos, vel)) + jnp.sum(J * ang)
        sym = self.symmetry
        if isinstance(sym, SO3):
            return L
        if isinstance(sym, SE3):
            return jnp.concatenate([p, L])
        if isinstance(sym, SE2):
            return jnp.concatenate([p, L[None]])
        return (L @ sym.axis if sym.spatial else L)[None]

    def _momentum_dict(self, x):
        J = self.momentum_map(x)
        return {n: J[i] for i, n in enumerate(self.symmetry.momentum_names)}

    def invariants(self, x):
        return {} if self.external else self._momentum_dict(x)

    def free_invariants(self, x):
        return self._momentum_dict(x) if self.external else {}

    def energy(self, x):
        """Kinetic energy [J] (no potential: the symmetry excludes gravity-like fields)."""
        _, _, r, rd, _ = self.split(x)
        return self.reduced_lagrangian(r, jnp.concatenate([self.group_velocity(x), rd]))

    def power(self, t, x, u):
        _, _, r, rd, _ = self.split(x)
        tau_xi, tau_r = self.generalized_forces(r, u)
        return tau_xi @ self.group_velocity(x) + tau_r @ rd

    def guards(self, x):
        r = self.split(x)[2]
        out = {}
        if self.symmetry.spatial:
            out["locked_inertia"] = self.inertia_condition(r) - self.guard_eps
        if self.chart_guard is not None:
            out.update(self.chart_guard(r))
        return out

    def regularity(self, t, x):
        r = self.split(x)[2]
        ev = jnp.linalg.eigvalsh(self.locked_inertia(r))
        em = jnp.linalg.eigvalsh(self.reduced_metric(r))
        return {"locked_inertia": ev[0] / ev[-1] - 1e-13, "shape_metric": em[0] / em[-1] - 1e-13}

    # ------------------------------------------------------------ helpers
    def kinematic(self):
        """The velocity-controlled system (seed 000 (3.13)) of the same bodies."""
        return ReducedKinematic(self.bodies, self.shape_map, self.symmetry, self.k,
                                shape_names=self.shape_names, chart_guard=self.chart_guard,
                                guard_eps=self.guard_eps)

    @_geometry("reduction.inverse_dynamics", ("x", "x"), ("shape_acc", "rdd"))
    def inverse_dynamics(self, x, shape_acc):
        """Shape forces tau_r that produce r'' = ``shape_acc`` at x (no body wrenches):
        the inverse of r'' = M^-1 (tau_r + h), i.e. tau_r = M (r'' - r''(tau = 0))."""
        _, _, r, rd, _ = self.split(x)
        free = self._dynamics(r, rd, self.body_momentum(x), jnp.zeros(self.n_inputs, r.dtype))[1]
        return self.reduced_metric(r) @ (shape_acc - free)


class ReducedKinematic(ReducedSystem):
    """Velocity control at zero momentum (seed 000 (3.13)): r' = u, g' = -g A(r) u.

    State [group coordinates, r] (with R first for SO(3)/SE(3)); inputs u = r'.
    ``vibrational_power(x, u)`` = u^T M(r) u / 2 is the integrand of the
    vibrational energy (4.8) whose Pontryagin Hamiltonian is (4.12),
    ``optimal_hamiltonian(r, P)`` = P^T M(r)^-1 P / 2.
    """

    requires_control: ClassVar[bool] = True  # the inputs are the shape velocities

    def __init__(self, bodies, shape_map, group, shape_dim, *, shape_names=None, chart_guard=None,
                 guard_eps=1e-6):
        self._setup(bodies, shape_map, group, shape_dim, momentum="zero", shape_names=shape_names,
                    chart_guard=chart_guard, guard_eps=guard_eps)

    @property
    def flat_names(self):
        return tuple(self.symmetry.coord_names) + self.shape_names

    def split(self, x):
        R, f = (x[0], x[1]) if self.symmetry.matrix else (None, x)
        ng = self.n_group
        return R, f[:ng], f[ng:ng + self.k], jnp.zeros(self.k, f.dtype), None

    def join(self, R, c, r, rd=None, m=None):
        f = jnp.concatenate([jnp.asarray(c, float).reshape(-1), jnp.asarray(r, float).reshape(-1)])
        return (R, f) if self.symmetry.matrix else f

    def initial_state(self, shape, group=None):
        owner = f"{type(self).__name__}.initial_state"
        r = self._shape_arg("shape", shape, owner)
        R, c = self._group_arg(group, owner)
        return self.join(R, c, r)

    def vector_field(self, t, x, u):
        R, c, r, _, _ = self.split(x)
        xi = -self.connection(r) @ u
        wR, dc = self.symmetry.rates(R, c, xi)
        f = jnp.concatenate([dc, u])
        return (wR, f) if self.symmetry.matrix else f

    def vibrational_power(self, x, u):
        """u^T M(r) u / 2 [W]: the kinetic energy of the motion with shape velocity u (4.8)."""
        r = self.split(x)[2]
        return 0.5 * u @ self.reduced_metric(r) @ u

    def optimal_hamiltonian(self, r, P):
        """(4.12): H = P^T M(r)^-1 P / 2."""
        return 0.5 * P @ jnp.linalg.solve(self.reduced_metric(r), P)

    def invariants(self, x):
        return {}

    def free_invariants(self, x):
        return {}

    # no kinetic energy or power of inputs to track (the inputs are velocities)
    energy = AbstractSystem.energy
    power = AbstractSystem.power

    def regularity(self, t, x):
        r = self.split(x)[2]
        ev = jnp.linalg.eigvalsh(self.locked_inertia(r))
        return {"locked_inertia": ev[0] / ev[-1] - 1e-13}


# ----------------------------------------------------------------------- holonomy
def curvature_integral(system: ReducedSystem, loop, centre, *, base=None, plane=(0, 1), n=48,
                       closure_tol=1e-8):
    """Integral of the curvature F over the region enclosed by a closed shape loop.

    The loop lies in the 2-D plane of shape coordinates ``plane`` (the others fixed
    at ``base``, default the centre's), is given by ``loop(alpha)`` -> (2,) for alpha
    in [0, 2 pi] (counter-clockwise about ``centre``), and the region must be
    star-shaped with respect to ``centre``: P(s, alpha) = c + s (loop(alpha) - c),
    s in [0, 1]. Gauss-Legendre with n x n nodes on (s, alpha) (exponentially
    accurate for smooth loops). Returns the algebra vector int F_ij dr^i dr^j
    (i, j = plane); the holonomy of the loop is exp(-that) for an abelian
    connection (exactly), and to leading order in the loop's size otherwise.

    Checked before the quadrature: ``loop`` returns 2 finite numbers at every node and
    closes, |loop(2 pi) - loop(0)| <= ``closure_tol`` x (its largest distance from
    ``centre``): an open path encloses no region, and the integral over the sector it
    sweeps is not the turn along it. ParameterError naming ``loop`` otherwise.
    """
    owner = "curvature_integral"
    if not isinstance(system, ReducedSystem):
        raise ParameterError(f"{owner}: system must be a nhjax.mechanics.ReducedSystem, got "
                             f"{type(system).__name__}", "system", system)
    V.function("loop", loop, owner=owner, signature="alpha -> (2,) point of the shape plane")
    try:
        i, j = (V.integer("plane", p, minimum=0, owner=owner) for p in plane)
    except (TypeError, ValueError):
        raise ParameterError(f"{owner}: plane must be two shape indices (i, j), got {plane!r}", "plane", plane) from None
    if i == j or max(i, j) >= system.k:
        raise ParameterError(f"{owner}: plane must be two distinct shape indices below k = {system.k}, "
                             f"got {plane!r}", "plane", plane)
    n = V.integer("n", n, minimum=1, owner=owner, what="Gauss-Legendre nodes per direction")
    c = _vec_arg("centre", centre, 2, owner, "point of the shape plane the region is star-shaped about")
    b = jnp.zeros(system.k) if base is None else _vec_arg("base", base, system.k, owner, "shape of the plane's origin")
    closure_tol = V.positive("closure_tol", closure_tol, owner=owner, as_float=True,
                             what="relative gap allowed between loop(0) and loop(2 pi)")
    xg, wg = np.polynomial.legendre.leggauss(n)
    _check_loop(loop, c, np.concatenate([[0.0], np.pi * (xg + 1), [2 * np.pi]]), closure_tol, owner)
    S, Aa = np.meshgrid(0.5 * (xg + 1), np.pi * (xg + 1), indexing="ij")
    W = np.outer(0.5 * wg, np.pi * wg)
    args = (system, loop, c, b, jnp.asarray(S.ravel(), float), jnp.asarray(Aa.ravel(), float),
            jnp.asarray(W.ravel(), float), (int(i), int(j)))
    # one stored program per system structure and loop (a loop that is an equinox module
    # with array parameters, e.g. ``EllipseLoop``, takes them as inputs: new sizes reuse it)
    return _primitive.call("curvature_integral", _curvature_quadrature, args,
                           fallback=_curvature_quadrature_jit)


def _check_loop(loop, centre, alphas, closure_tol, owner):
    """``loop`` at ``alphas`` (0, the quadrature's nodes, 2 pi): shape (2,) each (from
    its trace: a user's function of the wrong size is named, not a broadcasting error of
    the quadrature), finite, and closed to ``closure_tol`` relative to its size."""
    try:
        out = jax.eval_shape(loop, jnp.zeros(()))
    except Exception as e:  # noqa: BLE001 - the user's function: say what it is for
        raise ParameterError(f"{owner}: loop(alpha) could not be evaluated on a scalar angle alpha [rad]: "
                             f"{type(e).__name__}: {e}", "loop", loop) from None
    if not hasattr(out, "shape") or tuple(out.shape) != (2,):
        raise ParameterError(f"{owner}: loop(alpha) must return a point of the shape plane, shape (2,), got "
                             f"{getattr(out, 'shape', type(out).__name__)}", "loop", loop)
    if V.is_traced(loop, centre):  # values unknown (under jit or vmap): the shape check only
        return
    pts = np.asarray(_programs.call("curvature_integral.loop", _loop_points, (loop, jnp.asarray(alphas, float)),
                                    compiler_options=_programs.QUICK_OPTIONS))
    if not np.all(np.isfinite(pts)):
        k = int(np.argmax(~np.all(np.isfinite(pts), axis=1)))
        raise ParameterError(f"{owner}: loop(alpha) is not finite at alpha = {alphas[k]:.6g} (got "
                             f"{pts[k].tolist()}); a loop of finite shape coordinates is needed", "loop", loop)
    size = np.max(np.linalg.norm(pts - np.asarray(centre), axis=1))
    gap = float(np.linalg.norm(pts[-1] - pts[0]))
    if not gap <= closure_tol * max(size, np.finfo(float).tiny):
        raise ParameterError(
            f"{owner}: the loop does not close: |loop(2 pi) - loop(0)| = {gap:.3g}, more than closure_tol = "
            f"{closure_tol:.1e} times its size {size:.3g}. The curvature integral is the holonomy of a closed "
            "shape loop (alpha in [0, 2 pi], back to its start); an open path encloses no region", "loop", loop)


def _loop_points(loop, alphas):
    return jax.vmap(loop)(alphas)


def _curvature_quadrature(system, loop, c, b, s, a, w, plane):
    i, j = plane

    def integrand(s, a):
        p = loop(a)
        dp = jax.jacfwd(loop)(a)
        P = c + s * (p - c)
        r = b.at[i].set(P[0]).at[j].set(P[1])
        jac = s * _cross2(p - c, dp)
        return system.curvature(r)[:, i, j] * jac

    return jnp.einsum("n,na->a", w, jax.vmap(integrand)(s, a))


_curvature_quadrature_jit = eqx.filter_jit(_curvature_quadrature)


class EllipseLoop(eqx.Module):
    """alpha -> centre + (a cos alpha, b sin alpha): a loop for ``curvature_integral``."""

    centre: jax.Array
    a: jax.Array
    b: jax.Array

    def __init__(self, centre, a, b=None):
        owner = "EllipseLoop"
        self.centre = V.real("centre", centre, owner=owner, shape=(2,), what="point of the shape plane")
        self.a = V.positive("a", a, owner=owner, shape=(), what="semi-axis along the plane's first coordinate")
        self.b = self.a if b is None else V.positive("b", b, owner=owner, shape=(),
                                                      what="semi-axis along the plane's second coordinate")

    def __call__(self, alpha):
        return self.centre + jnp.stack([self.a * jnp.cos(alpha), self.b * jnp.sin(alpha)])
