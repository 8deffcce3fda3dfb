r"""A planar chain of N rigid bodies joined by hinges, reduced by SE(2) (or SO(2)).

Seed 001 (E. C. de Souza, N. Maruyama, *Lagrangian modeling for a class of
mobile multibody systems*, IFAC 2007): N rigid bodies in the plane, body i+1
hinged to body i, joint torques and body-fixed thrusters; SE(2) symmetry,
momentum map, mechanical connection (3)-(8), reduced equations (9a)-(9c) with
M (10), C (11), N (12) and the forcing X tau, and the two-body closed forms of
sec. 4.1. Here they are not written by hand: ``PlanarChain`` is a
``nhjax.mechanics.reduction.ReducedSystem`` whose locked inertia, connection,
reduced metric and equations come from the bodies by autodiff; the two-body
closed forms (``two_body_closed_forms``) and an unreduced model
(``PlanarChainUnreduced``, the engine ``Lagrangian`` on R^(3N) with hinge
constraints) are the checks.

Model and parameters (SI units)
-------------------------------
Body i: mass m_i [kg], moment of inertia I_i about its centre of mass [kg m^2].
Hinge j (j = 1..N-1) joins body j and body j+1; it sits at ``hinge_out[j]`` in
body j's frame and at ``hinge_in[j]`` in body j+1's frame [m] (body frames at
the centres of mass). Default: links of length ``lengths`` along their body x
axes, hinged end to end (hinge_out = (l_j/2, 0), hinge_in = (-l_{j+1}/2, 0)),
uniform rods (I = m l^2/12).
Shape: joint angles phi_j = theta_{j+1} - theta_j [rad] (seed 001 (12)-(13)).
Group: g = (x, y, angle): the centre of mass of the chain and the orientation of
the reference frame, which is body 1's frame (``reference="first"``, seed (12):
theta = 1 theta_1 + M phi) or the mean of the body angles (``reference="mean"``,
the frame of the seed's two-body example).
Inputs u [N m, N]: the N-1 joint torques (torque T_j acts on body j+1 and -T_j on
body j), then, with ``thrusters``, one thrust F_i per body along the body-fixed
unit axis ``thruster_axes[i]`` at its centre of mass.
State: (x, y, angle, phi_1..phi_{N-1}, phi_dot..., [momentum]) (``group="SE2"``),
or (angle, phi, phi_dot) for ``group="SO2"`` (rotations about the fixed centre
of mass: enough at zero momentum, where the centre of mass stays put).
Momentum: "zero" (no thrusters; the seeds' vanishing momentum), "spatial" (J =
(p_x, p_y, L) carried and constant without thrusters) or "body" (mu, (9b)).

Two bodies (sec. 4.1), hinge at distance d_i from each centre of mass
(hinge_out = (d1, 0), hinge_in = (-d2, 0)), eps = m1 m2 / (m1 + m2),
I~_i = I_i + eps d_i^2, lam(phi) = d1 d2 cos phi, S = I~1 + 2 eps lam + I~2:

    M(phi) = (I~1 I~2 - (eps lam)^2) / S,
    C(phi) = eps d1 d2 sin(phi) (eps lam + I~1)(eps lam + I~2) / S^2,
    N(phi) = eps d1 d2 sin(phi) mu_3^2 / S^2,
    M phi'' + C phi'^2 + N = X tau = tau_phi - tau_theta A_theta(phi),

with A_theta = (I~2 - I~1) / (2 S) in the mean-angle frame. Re-derived (the
extraction of the seed garbled it): the seed prints J-dagger = (I~1 - I~2)/2 and
theta_cm = (pi - phi)/2 - theta_1, which fit phi = theta_1 - theta_2; with the
seed's phi = theta_2 - theta_1 (used here) the sign of A_theta, of J-dagger and
of the forcing's last term flips. M, C and N do not depend on that choice (C is
(1/2) dM/dphi, eq. (11) for one shape coordinate; N is d/dphi of the amended
potential mu_3^2 / (2 S)). The tests hold the autodiff equations to these
closed forms.

At zero momentum a closed loop of the joint angles turns the chain (N >= 3; for
N = 2 the shape space is 1-D and encloses no area) by minus the integral of the
curvature over the enclosed region (SO(2) part of the connection; its
translation part vanishes with the centre of mass as reference point).
"""

from __future__ import annotations


import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ParameterError
from ..mechanics import ConstrainedLagrangian
from ..mechanics.reduction import SE2, SO2, Bodies, ReducedSystem, _rot2
from ._validate import choice, positive, real, to_device

__all__ = ["PlanarChain", "PlanarChainUnreduced", "two_body_closed_forms"]


class ChainShape(eqx.Module):
    """Section of the chain: joint angles -> body angles and centres, centre of mass at 0."""

    masses: jax.Array
    hinge_out: jax.Array
    hinge_in: jax.Array
    reference: str = eqx.field(static=True, default="first")

    def __call__(self, phi):
        th = jnp.concatenate([jnp.zeros(1, phi.dtype), jnp.cumsum(phi)])
        if self.reference == "mean":
            th = th - jnp.mean(th)
        R = _rot2(th)
        steps = jnp.einsum("nij,nj->ni", R[:-1], self.hinge_out) - jnp.einsum("nij,nj->ni", R[1:], self.hinge_in)
        pos = jnp.concatenate([jnp.zeros((1, 2), phi.dtype), jnp.cumsum(steps, 0)])
        return th, pos - (self.masses @ pos) / jnp.sum(self.masses)


class ChainInputs(eqx.Module):
    """u = (joint torques (N-1), thrusts (N) along body-fixed axes if any)."""

    thruster_axes: jax.Array | None
    n_joints: int = eqx.field(static=True)

    def __call__(self, r, u):
        tau = u[: self.n_joints]
        if self.thruster_axes is None:
            return tau, None
        F = u[self.n_joints:]
        f = F[:, None] * self.thruster_axes
        return tau, jnp.concatenate([f, jnp.zeros((F.shape[0], 1), u.dtype)], axis=1)


def _masses(owner, masses):
    """Masses (N,) [kg], N >= 2, each finite and > 0."""
    m = positive("masses", masses, owner=owner, what="masses of the bodies [kg]")
    if m.ndim != 1 or m.shape[0] < 2:
        raise ParameterError(f"{owner}: a chain needs at least 2 bodies, got masses={masses!r}", "masses", masses)
    return m


def _hinges(owner, name, value, N):
    """Hinge points (N-1, 2) [m] in body frames, finite."""
    h = real(name, value, owner=owner, what="hinge points in the body frames [m]")
    if h.shape != (N - 1, 2):
        raise ParameterError(f"{owner}: {name} must have shape ({N - 1}, 2) (one point per hinge) [m], "
                             f"got {tuple(h.shape)}", name, value)
    return h


def _thruster_axes(owner, value, N):
    """Body-fixed thrust directions (N, 2), finite and nonzero, normalized."""
    ax = real("thruster_axes", value, owner=owner, what="body-fixed thrust directions")
    if ax.shape != (N, 2):
        raise ParameterError(f"{owner}: thruster_axes must have shape ({N}, 2), got {tuple(ax.shape)}",
                             "thruster_axes", value)
    if isinstance(ax, jax.core.Tracer):
        return ax / jnp.linalg.norm(ax, axis=1, keepdims=True)
    ax = np.asarray(ax)
    norm = np.linalg.norm(ax, axis=1, keepdims=True)
    if not np.all(norm > 0):
        raise ParameterError(f"{owner}: thruster_axes must be nonzero directions, got {ax.tolist()}",
                             "thruster_axes", value)
    return to_device(ax / norm)


class PlanarChain(ReducedSystem):
    """N hinged rigid bodies in the plane, reduced by SE(2) or SO(2); see the module docstring.

    ``PlanarChain(masses=(1, 1, 1), lengths=(1, 1, 1))``: three uniform rods, joint
    torques only, zero momentum, SE(2). ``thrusters=True`` adds a thruster per body
    along its x axis (or give ``thruster_axes``, (N, 2)).
    """

    reference: str = eqx.field(static=True, default="first")

    def __init__(self, masses=(1.0, 1.0, 1.0), inertias=None, lengths=None, hinge_out=None,
                 hinge_in=None, thrusters=False, thruster_axes=None, group="SE2", momentum=None,
                 reference="first"):
        owner = "PlanarChain"
        m = _masses(owner, masses)
        N = m.shape[0]
        L = None if lengths is None else positive("lengths", lengths, owner=owner, shape=(N,),
                                                  what="link lengths, one per body [m]")
        if inertias is not None:  # zero: a point mass on the chain (its hinge offsets still give it rotational inertia)
            inertias = positive("inertias", inertias, allow_zero=True, owner=owner, shape=(N,),
                                what="moments of inertia about the centres of mass [kg m^2]")
        ho = None if hinge_out is None else _hinges(owner, "hinge_out", hinge_out, N)
        hi = None if hinge_in is None else _hinges(owner, "hinge_in", hinge_in, N)
        # the defaults' arithmetic on the host when the parameters are concrete: each eager
        # jnp operation is an XLA program of its own, compiled (or looked up) in every new
        # process before the first answer; under a trace (a gradient in the masses) in jnp
        xp = jnp if any(isinstance(a, jax.core.Tracer) for a in (m, L, inertias)) else np
        L = xp.ones(N) if L is None else L
        if inertias is None:
            inertias = to_device(xp.asarray(m) * xp.asarray(L) ** 2 / 12.0)
        Lh = xp.asarray(L)
        if ho is None:
            ho = to_device(xp.stack([Lh[:-1] / 2, xp.zeros(N - 1)], 1))
        if hi is None:
            hi = to_device(xp.stack([-Lh[1:] / 2, xp.zeros(N - 1)], 1))
        choice("reference", reference, ("first", "mean"), owner=owner)
        if not isinstance(thrusters, (bool, np.bool_)):
            raise ParameterError(f"{owner}: thrusters must be True or False, got {thrusters!r}", "thrusters", thrusters)
        if thruster_axes is not None:
            thrusters = True
            ax = _thruster_axes(owner, thruster_axes, N)
        else:
            ax = to_device(np.tile([[1.0, 0.0]], (N, 1))) if thrusters else None
        group = {"SE2": SE2(), "SO2": SO2()}.get(group, group) if isinstance(group, str) else group
        if not isinstance(group, (SE2, SO2)) or group.spatial:
            raise ParameterError(f"{owner}: group must be 'SE2' or 'SO2' (planar), got {group!r}", "group", group)
        if thrusters and isinstance(group, SO2):
            raise ParameterError(f"{owner}: thrusters move the centre of mass: use group='SE2'", "group", group)
        shape = ChainShape(m, ho, hi, reference)
        inputs = ChainInputs(ax, N - 1)
        names = tuple(f"phi{j + 1}" for j in range(N - 1))
        self._setup(Bodies(m, inertias), shape, group, N - 1, momentum=momentum,
                    inputs=inputs, control_dim=(N - 1) + (N if thrusters else 0), shape_names=names)
        self.reference = reference

    # ------------------------------------------------------------- accessors
    @property
    def n_bodies(self):
        return self.bodies.n

    @property
    def masses(self):
        return self.bodies.masses

    @property
    def has_thrusters(self):
        return self.inputs.thruster_axes is not None

    def initial_state(self, phi=0.0, phi_dot=0.0, pose=None, momentum=None):
        """State from joint angles [rad] (default 0: the straight chain), their rates
        [rad/s] (default 0), each (N-1,) or one number for every joint, the pose of the
        reference frame (x, y, angle) [m, m, rad] (SE2; SO2: angle; default 0) and the
        spatial momentum (p_x, p_y, L) [kg m/s, kg m^2/s] (SE2) or L (SO2) (default 0)."""
        owner = "PlanarChain.initial_state"
        args = []
        for name, v in (("phi", phi), ("phi_dot", phi_dot)):
            v = 0.0 if v is None else v  # None: the default, as before
            a = real(name, v, owner=owner, what=f"joint angles {self.shape_names} [rad]" if name == "phi"
                     else "joint rates [rad/s]")
            if a.ndim == 0:
                a = jnp.full(self.k, a) if isinstance(a, jax.core.Tracer) else to_device(np.full(self.k, np.asarray(a)))
            elif a.shape != (self.k,):
                raise ParameterError(f"{owner}: {name} must have {self.k} entries (one per joint) or be one "
                                     f"number, got shape {tuple(a.shape)}", name, v)
            args.append(a)
        if pose is not None:
            ng = self.n_group
            pose = real("pose", pose, owner=owner, what=f"pose {self.symmetry.coord_names} of the reference frame")
            if pose.size != ng:
                raise ParameterError(f"{owner}: pose must have {ng} entries {self.symmetry.coord_names}, "
                                     f"got shape {tuple(pose.shape)}", "pose", pose)
        return ReducedSystem.initial_state(self, args[0], args[1], pose, momentum)

    def body_poses(self, x):
        """(angles (N,), centres (N, 2)) of the bodies in space."""
        rot, pos, _, _ = self.body_states(x)
        return rot, pos

    def joints(self, x):
        """Hinge positions (N-1, 2) in space [m]."""
        th, pos = self.body_poses(x)
        return pos[:-1] + jnp.einsum("nij,nj->ni", _rot2(th[:-1]), self.shape_map.hinge_out)

    def unreduced(self):
        """The same chain for the engine: ``PlanarChainUnreduced`` (R^(3N), hinge constraints)."""
        return PlanarChainUnreduced(self.bodies.masses, self.bodies.inertias, self.shape_map.hinge_out,
                                    self.shape_map.hinge_in, self.inputs.thruster_axes)

    def unreduced_state(self, x):
        """(q, q') of ``PlanarChainUnreduced``: (x_i, y_i, theta_i) per body and rates."""
        th, pos, w, vel = self.body_states(x)
        q = jnp.concatenate([pos, th[:, None]], 1).reshape(-1)
        qd = jnp.concatenate([vel, w[:, None]], 1).reshape(-1)
        return jnp.concatenate([q, qd])


class PlanarChainUnreduced(ConstrainedLagrangian):
    """The chain as N free planar bodies q = (x_i, y_i, theta_i), i = 1..N, with the
    2(N-1) hinge constraints x_j + R(theta_j) hinge_out_j = x_{j+1} + R(theta_{j+1})
    hinge_in_j (position constraints, index-reduced and projected after each step),
    joint torques and thrusters as generalized forces; equations by the engine
    (``nhjax.mechanics.ConstrainedLagrangian``). The independent check of ``PlanarChain``.

    Parameters as ``PlanarChain`` (masses [kg], inertias [kg m^2] > 0, hinge points
    [m], thrust directions); the defaults are ``PlanarChain()``'s: three uniform rods
    of 1 kg and 1 m (I = 1/12 kg m^2) hinged end to end, no thrusters
    (``PlanarChain().unreduced()`` builds the same model from any chain)."""

    masses: jax.Array
    inertias: jax.Array
    hinge_out: jax.Array
    hinge_in: jax.Array
    thruster_axes: jax.Array | None
    n: int = eqx.field(static=True)
    n_inputs: int = eqx.field(static=True)

    def __init__(self, masses=(1.0, 1.0, 1.0), inertias=(1 / 12, 1 / 12, 1 / 12),
                 hinge_out=((0.5, 0.0), (0.5, 0.0)), hinge_in=((-0.5, 0.0), (-0.5, 0.0)), thruster_axes=None):
        owner = "PlanarChainUnreduced"
        self.masses = _masses(owner, masses)
        N = self.masses.shape[0]
        # > 0: the free bodies' mass matrix must be invertible for the engine's KKT solve
        self.inertias = positive("inertias", inertias, owner=owner, shape=(N,),
                                 what="moments of inertia about the centres of mass [kg m^2]")
        self.hinge_out = _hinges(owner, "hinge_out", hinge_out, N)
        self.hinge_in = _hinges(owner, "hinge_in", hinge_in, N)
        self.thruster_axes = None if thruster_axes is None else _thruster_axes(owner, thruster_axes, N)
        self.n = 3 * N
        self.n_inputs = (N - 1) + (N if thruster_axes is not None else 0)

    @property
    def control_dim(self):  # type: ignore[override]
        return self.n_inputs

    def kinetic_energy(self, q, qd):
        return self._T(q, qd)

    def position_constraints(self, t, q):
        return self._hinges(t, q)

    def generalized_force(self, t, q, qd, u):
        return self._force(t, q, qd, u)

    def _T(self, q, qd):
        v = qd.reshape(-1, 3)
        return 0.5 * jnp.sum(self.masses * (v[:, 0] ** 2 + v[:, 1] ** 2)) + 0.5 * jnp.sum(self.inertias * v[:, 2] ** 2)

    def _hinges(self, t, q):
        b = q.reshape(-1, 3)
        R = _rot2(b[:, 2])
        a = b[:-1, :2] + jnp.einsum("nij,nj->ni", R[:-1], self.hinge_out)
        c = b[1:, :2] + jnp.einsum("nij,nj->ni", R[1:], self.hinge_in)
        return (a - c).reshape(-1)

    def _force(self, t, q, qd, u):
        N = self.masses.shape[0]
        T = u[: N - 1]
        f = jnp.zeros((N, 3), q.dtype)
        f = f.at[1:, 2].add(T).at[:-1, 2].add(-T)
        if self.thruster_axes is not None:
            F = u[N - 1:]
            R = _rot2(q.reshape(-1, 3)[:, 2])
            f = f.at[:, :2].add(F[:, None] * jnp.einsum("nij,nj->ni", R, self.thruster_axes))
        return f.reshape(-1)


def two_body_closed_forms(m1, m2, I1, I2, d1, d2, phi):
    """Seed 001, sec. 4.1 (re-derived, see the module docstring): a dict with
    M(phi), C(phi), N(phi)/mu_3^2 (``N_over_mu3sq``), A_theta(phi) (mean-angle frame,
    phi = theta_2 - theta_1), the locked rotational inertia S = 1^T J 1 and the
    matrix J(phi)."""
    eps = m1 * m2 / (m1 + m2)
    I1t, I2t = I1 + eps * d1**2, I2 + eps * d2**2
    lam = d1 * d2 * np.cos(phi)
    sig = d1 * d2 * np.sin(phi)
    S = I1t + 2 * eps * lam + I2t
    return dict(
        M=(I1t * I2t - (eps * lam) ** 2) / S,
        C=eps * sig * (eps * lam + I1t) * (eps * lam + I2t) / S**2,
        N_over_mu3sq=eps * sig / S**2,
        A_theta=(I2t - I1t) / (2 * S),
        S=S,
        J=np.array([[I1t, eps * lam], [eps * lam, I2t]]),
    )
