r"""Steering the spherical robot (``nhjax.scenes.ShellWithTop``) from rest to rest.

Model (seed 003, sec. 1, with an actuator; SI units): a spherical shell (mass
``ms`` [kg], radius ``Rs`` [m], inertia ``Is`` [kg m^2]) rolls without slipping
on the plane z = 0; inside, a rigid "top" (mass ``mt``, inertia ``It``, centre of
mass at ``c`` [m] from the shell's centre C, top axes) hangs on a spherical hinge
at C. The input is the internal torque tau [N m] (3, top axes): +tau on the top,
-tau on the shell. State ((xy, R_shell, R_top), v), v = (xy' [m/s], Omega
[rad/s], shell body axes, omega [rad/s], top body axes); the attitudes are
rotation matrices body -> space, integrated on SO(3) by RKMK.

Task (the design card's "spherical-robot steering"): from rest at the origin with
the top hanging (its centre of mass straight below C) to rest at ``target_xy`` in
time ``T`` [s], minimizing the control effort

    J = int_0^T |tau|^2 dt        [N^2 m^2 s].

Which final states are equilibria? At rest (v = 0) the only force that can move
the robot is gravity on the top: the state stays at rest (with tau = 0) iff
gamma x c = 0, gamma = R_top^T e3 the vertical in the top's axes, i.e. the top
hangs (or stands inverted). A rest state with the top tilted is *not* an
equilibrium: no internal torque can hold it, since holding the top against
gravity pushes the shell, which then rolls. The shell's attitude and the top's
yaw about the vertical are free at any equilibrium. Hence the terminal
constraints (all smooth, independent at the optimum):

* ``xy(T) - target_xy`` (2): the centre (equivalently the contact point) at the
  target [m];
* ``Omega(T)`` (3) and ``omega(T)`` (3): both bodies at rest [rad/s]. The centre's
  velocity xy' is *not* constrained separately: rolling ties it to the shell's,
  xy' = Rs (R_shell Omega)_{2,-1}, so imposing it too would add two dependent
  equations (a rank-deficient constraint Jacobian); it vanishes with Omega to
  the accuracy of the rolling constraint (residual below 1e-14 m/s along the
  optimum at rtol 1e-12).
* ``E^T gamma(T)`` (2): the top hangs as at the start; E (3x2) spans the plane
  orthogonal to gamma(0) (gamma lies on the unit sphere, so 2 numbers fix it
  near gamma(0)). Left out when c = 0: then every rest state is an equilibrium.
* optional ``heading`` psi [rad]: the top's yaw, the direction in the plane of
  the top axis f that points along space x at the start, f = R_top(0)^T e1. One
  equation, (-sin psi, cos psi) . (R_top(T) f)_{xy} = 0 (with gamma(T) fixed,
  R_top(T) f is horizontal; the equation also holds at psi + pi, so the solver
  converges to the branch nearest its guess: check ``top_heading``). The
  shell's yaw is not offered: a featureless sphere has a 3-D attitude, not a
  heading, and any attitude is an equilibrium.

The initial state is ``robot.initial_state`` at the origin with the shell at the
identity and the top hanging (R_top(0) rotates c to straight down; the identity
for the default c = (0, 0, -0.08) m).

The terminal constraints are equinox modules holding the target (and heading)
as arrays, so solving again for another target reuses the compiled code.

Solving. ``linear_guess`` gives the minimum-effort control of the problem
linearized at the start (a zero control does not move the robot); for the
default robot, target (0.5, 0.3) m and T = 3 s its cost is 0.0816 and it misses
the rest state by ~0.3 rad/s. The constraints are strongly curved in the
control parameters: the top's yaw answers tau_3 with gain ~1/J_33 and turns
every later torque, and the vertical angular momentum about the contact point
(it must return to zero, and it does not stay zero by itself when the top's
inertia is not symmetric about the direction of travel) is changed only by the
second-order term -mt (V x v_c) . gamma. ``controls.solve_direct`` (augmented
Lagrangian, L-BFGS inner solves) crawls on this (hundreds of inner steps per outer
iteration, the constraints still violated after several); ``controls.solve_direct_newton``
(feasible-path Newton with second derivatives by differences of reverse-mode gradients)
gets the optimum in a few iterations: cost 0.0813126 (Chebyshev degree 6) and
0.0812912 (degree 12) N^2 m^2 s. Along the optimum the free top turns by ~1 rad
about the vertical (tau_3 stays near 0: the turn comes from the swing).

``sphere_steering_reduced`` is the same problem on the vector state of
``ShellWithTopReduced`` (hand-derived reduced equations; the shell's attitude is
cyclic and dropped), for ``controls.solve_pontryagin`` (Levenberg–Marquardt: the
attitude rows carry 6 redundant costate directions), which gives the continuous
optimum 0.0812881 N^2 m^2 s. ``rolling_residual`` evaluates the no-slip
constraint along a trajectory.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from nhjax.lie import so3
from nhjax.mechanics import AbstractSystem
from nhjax.scenes import ShellWithTop, ShellWithTopReduced

import nhjax

from ..newton import solve_direct_newton
from ..parametrize import fit_samples
from nhjax import _validate as V

from ..problem import (OCP, CostAugmented, ProblemError, _OnState, as_problem_error, check_ocp, check_parametrization,
                       compiled, host_array)
from .somersault import Effort

__all__ = [
    "ReducedSteering",
    "ReducedSteeringTarget",
    "SteeringTarget",
    "hanging_attitude",
    "linear_guess",
    "rolling_residual",
    "simulate_with_impulse",
    "solve_direct_newton",
    "sphere_steering",
    "sphere_steering_reduced",
    "top_heading",
]

_E3 = np.array([0.0, 0.0, 1.0])


def hanging_attitude(c):
    """Rotation R (top axes -> space) with R c pointing straight down: the top's
    equilibrium at rest (the identity when c is along -e3; any rotation when c = 0)."""
    c = np.asarray(c, float)
    n = np.linalg.norm(c)
    if n == 0.0:
        return np.eye(3)
    chat = c / n
    axis = np.cross(chat, -_E3)
    s, co = np.linalg.norm(axis), float(chat @ -_E3)
    if s < 1e-15:  # already down, or straight up: turn by pi about the top's x axis
        return np.eye(3) if co > 0 else np.diag([1.0, -1.0, -1.0])
    return np.asarray(so3.exp(jnp.asarray(axis / s * np.arctan2(s, co))))


def _orthonormal_complement(u):
    """(3, 2) orthonormal basis of the plane orthogonal to the unit vector u."""
    q, _ = np.linalg.qr(np.column_stack([u, np.eye(3)]))
    return q[:, 1:3]


class SteeringTarget(eqx.Module):
    """Terminal constraints of ``sphere_steering`` (see the module docstring):
    (xy - target, Omega, omega, E^T gamma[, heading]) at x(T).

    target : (2,) [m]; plane : (3, k) basis E orthogonal to gamma(0) (k = 2, or 0
    when the top's centre of mass is at the hinge); forward : (3,) top-frame axis f;
    normal : None, or (2,) = (-sin psi, cos psi) for a heading psi.
    All arrays: a new target or heading does not recompile.
    """

    target: jax.Array
    plane: jax.Array
    forward: jax.Array
    normal: jax.Array | None = None

    def __call__(self, x):
        (xy, _, Rt), v = x
        parts = [xy - self.target, v[2:8], self.plane.T @ Rt[2]]
        if self.normal is not None:
            parts.append((self.normal @ (Rt @ self.forward)[:2])[None])
        return jnp.concatenate(parts)


def _as_target(target_xy):
    try:
        t = np.asarray(target_xy, dtype=float)
    except (TypeError, ValueError) as e:
        raise ProblemError(f"target_xy must be a 2-vector (x, y) in metres, got {target_xy!r}") from e
    if t.shape != (2,):
        raise ProblemError(f"target_xy must be a 2-vector (x, y) in metres, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ProblemError(f"target_xy must be finite, got {t.tolist()}")
    return t


def sphere_steering(robot: ShellWithTop, target_xy, T, heading=None) -> OCP:
    """Rest at the origin (top hanging) -> rest at ``target_xy`` [m] in ``T`` [s],
    minimizing int |tau|^2 dt; optionally the top's final yaw ``heading`` [rad]
    (measured from space x, counter-clockwise). See the module docstring for the
    model and why exactly these terminal constraints are imposed.

    Returns a ``controls.OCP`` with ``terminal_constraints`` a ``SteeringTarget``.
    """
    if not isinstance(robot, ShellWithTop):
        raise ProblemError(f"robot must be an nhjax.scenes.ShellWithTop, got {type(robot).__name__}")
    target = _as_target(target_xy)
    try:
        if isinstance(T, (str, bytes, bool)):
            raise TypeError
        T = float(T)
    except (TypeError, ValueError) as e:
        raise ProblemError(f"the horizon T must be a positive number of seconds, got {T!r}") from e
    if not (np.isfinite(T) and T > 0):
        raise ProblemError(f"the horizon T must be a positive number of seconds, got {T}")
    c = np.asarray(robot.c, float)
    Rt0 = hanging_attitude(c)
    x0 = robot.initial_state(top_attitude=Rt0)
    gamma0 = Rt0.T @ _E3
    plane = _orthonormal_complement(gamma0) if np.linalg.norm(c) > 0 else np.zeros((3, 0))
    normal = None
    if heading is not None:
        try:
            psi = np.asarray(heading, dtype=float)
        except (TypeError, ValueError):
            raise ProblemError(f"heading must be a finite angle in radians (a scalar), got {heading!r}") from None
        if psi.shape != () or not np.isfinite(psi):
            raise ProblemError(f"heading must be a finite angle in radians (a scalar), got {heading!r}")
        normal = host_array([-np.sin(psi), np.cos(psi)])
    constraint = SteeringTarget(host_array(target), host_array(plane), host_array(Rt0.T[:, 0]), normal)
    return OCP(robot, x0, T, running_cost=Effort(), terminal_constraints=constraint)


# ------------------------------------------------------- vector-state (reduced) form
class ReducedSteering(AbstractSystem):
    """The robot in the reduced vector state of ``ShellWithTopReduced`` (17 numbers:
    omega, Omega in the top's axes, the rows gamma, alpha, beta of R_top, and xy),
    with the internal torque as its control (``forced_vector_field``). The shell's
    attitude is cyclic (neither the cost nor the constraints see it), so it is left
    out: this is the form for ``controls.solve_pontryagin``, which needs vector states.
    (alpha, beta, gamma) carry 9 numbers for 3 degrees of freedom: the costates have
    6 redundant directions, hence Levenberg–Marquardt for the shooting."""

    reduced: ShellWithTopReduced
    control_dim: ClassVar[int] = 3
    state_names: ClassVar[tuple] = ShellWithTopReduced.state_names

    def vector_field(self, t, x, u):
        return self.reduced.forced_vector_field(t, x, u)


class ReducedSteeringTarget(eqx.Module):
    """``SteeringTarget`` on the reduced state: (xy - target, Omega, omega, E^T gamma
    [, heading]); Omega here in the top's axes (it vanishes with the shell's body one)."""

    target: jax.Array
    plane: jax.Array
    forward: jax.Array
    normal: jax.Array | None = None

    def __call__(self, x):
        om, Om, ga, al, be, xy = ShellWithTopReduced.split(x)
        parts = [xy - self.target, Om, om, self.plane.T @ ga]
        if self.normal is not None:
            parts.append((self.normal @ jnp.stack([al @ self.forward, be @ self.forward]))[None])
        return jnp.concatenate(parts)


def sphere_steering_reduced(robot: ShellWithTop, target_xy, T, heading=None) -> OCP:
    """``sphere_steering`` for the same robot on the reduced vector state
    (``ReducedSteering``): same cost, same constraints, same optimum."""
    ocp = sphere_steering(robot, target_xy, T, heading)
    red = ShellWithTopReduced(ms=robot.ms, Rs=robot.Rs, Is=robot.Is, mt=robot.mt, It=robot.It, c=robot.c,
                              g=robot.g, case="general")
    Rt0 = np.asarray(ocp.x0[0][2])
    x0 = red.initial_state(np.zeros(3), attitude=Rt0)
    tc = ocp.terminal_constraints
    return OCP(ReducedSteering(red), x0, T, running_cost=Effort(),
               terminal_constraints=ReducedSteeringTarget(tc.target, tc.plane, tc.forward, tc.normal))


def top_heading(ocp: OCP, x):
    """The top's yaw [rad] at state x (stacked states give an array): the angle of
    R_top f in the plane, f the top axis along space x at the start."""
    f = ocp.terminal_constraints.forward
    (_, _, Rt), _ = x
    d = Rt @ f
    return jnp.arctan2(d[..., 1], d[..., 0])


def rolling_residual(robot: ShellWithTop, xs, ts=None):
    """The no-slip residual (velocity of the shell's material point at the contact,
    x and y components [m/s]) at every saved state.

    xs : robot states stacked along axis 0, ((xy, R_shell, R_top), v) with leading
        axis N: ``traj.xs`` of ``nhjax.simulate``, ``traj.xs[0]`` of ``controls.rollout``.
    Returns an (N, 2) array (it is zero for an exactly rolling motion)."""
    (xy, Rsh, Rt), v = xs
    if v.ndim != 2:
        raise ValueError("xs must be robot states stacked along a leading time axis")
    ts = jnp.zeros(v.shape[0]) if ts is None else jnp.asarray(ts, float)
    return jax.vmap(lambda t, a, b, c, w: robot.velocity_constraints(t, (a, b, c), w))(ts, xy, Rsh, Rt, v)


def _chart(x0, z):
    """State at chart coordinates z = (dxy, a, b, dv) around x0: attitudes R0 exp(hat a)."""
    (xy, Rsh, Rt), v = x0
    return (xy + z[:2], Rsh @ so3.exp(z[2:5]), Rt @ so3.exp(z[5:8])), v + z[8:]


def linear_guess(ocp: OCP, param, rcond=1e-10, multipliers=False):
    """Parameters of ``param`` fitted to the minimum-effort control of a
    ``sphere_steering`` problem linearized at the start (and, with
    ``multipliers=True``, the linearized problem's multipliers nu = -2 lam of the
    terminal constraints, in the convention dJ + nu . dpsi = 0).

    With z the chart coordinates around x0 (body-frame rotation vectors for the
    attitudes), z' = A z + B u and psi(x(T)) ~ psi(x0) + C z(T), the control
    u(t) = B^T exp(A^T (T - t)) C^T lam, (C W C^T) lam = -psi(x0), W the
    controllability Gramian over [0, T], minimizes int |u|^2 subject to the
    linearized constraints (lam by least squares: the linearization has dependent
    rows, e.g. the vertical angular momentum is conserved to first order).
    """
    check_ocp(ocp, "linear_guess")
    if not isinstance(ocp.system, ShellWithTop):
        raise ProblemError("linear_guess linearizes sphere_steering problems (ShellWithTop states)")
    check_parametrization(param, ocp, "linear_guess")
    with as_problem_error():
        rcond = V.positive("rcond", rcond, owner="linear_guess", shape=(), as_float=True,
                           what="relative cutoff of small singular values")
    ts = host_array(param.sample_times())
    us, lam = _linear_control(ocp, ts, host_array(rcond))
    p = fit_samples(param, ts, us)
    return (p, -2.0 * lam) if multipliers else p


@compiled(quick=True)
def _linear_control(ocp, ts, rcond):
    rob, x0, T = ocp.system, ocp.x0, ocp.T
    n = 2 + 3 + 3 + x0[1].shape[0]

    def f(z, u):
        (dxy, W, w), vd = rob.vector_field(0.0, _chart(x0, z), u)
        return jnp.concatenate([dxy, W, w, vd])

    z0, u0 = jnp.zeros(n), jnp.zeros(rob.control_dim)
    A = jax.jacfwd(f, 0)(z0, u0)
    B = jax.jacfwd(f, 1)(z0, u0)
    psi0 = ocp.terminal(x0)[1]
    C = jax.jacfwd(lambda z: ocp.terminal(_chart(x0, z))[1])(z0)
    # Van Loan: expm([[-A, B B^T], [0, A^T]] T) holds e^{A^T T} and e^{-AT} W
    M = jnp.zeros((2 * n, 2 * n)).at[:n, :n].set(-A).at[:n, n:].set(B @ B.T).at[n:, n:].set(A.T)
    E = jax.scipy.linalg.expm(M * T)
    W = E[n:, n:].T @ E[:n, n:]
    lam = jnp.linalg.lstsq(C @ W @ C.T, -psi0, rcond=rcond)[0]
    return jax.vmap(lambda t: B.T @ jax.scipy.linalg.expm(A.T * (T - t)) @ (C.T @ lam))(ts), lam



class _TorqueImpulseRate(eqx.Module):
    """R_top tau: the torque on the top in space axes [N m]."""

    def __call__(self, t, x, u):
        (_, _, Rt), _ = x
        return Rt @ u


def simulate_with_impulse(ocp: OCP, control, saveat, rtol=1e-12, atol=1e-12):
    """``nhjax.simulate`` of a ``sphere_steering`` problem's robot under ``control`` (u(t, x)),
    with the torque impulse in space int_0^t R_top tau dt [N m s] integrated alongside:
    ``traj.xs`` is (robot states, impulse). Chaplygin's vector obeys K(t) - K(0) = -impulse(t)."""
    aug = CostAugmented(ocp.system, _TorqueImpulseRate())
    return nhjax.simulate(aug, (ocp.x0, jnp.zeros(3)), ocp.T, control=_OnState(control), rtol=rtol, atol=atol,
                          saveat=saveat)
