"""Indirect methods: Pontryagin's maximum principle and shooting on the costates.

For  minimize Phi(x(T)) + int L dt,  x' = f(t, x, u),  psi(x(T)) = 0  (minimum
convention, normal case), with the Hamiltonian

    H(t, x, p, u) = L(t, x, u) + p . f(t, x, u)          (built by autodiff),

an optimal control minimizes H pointwise, and (x, p) solve

    x' = dH/dp = f,    p' = -dH/dx,    p(T) = dPhi/dx + (dpsi/dx)^T nu.

u*(t, x, p): one Newton step on dH/du = 0 from u = 0 is exact when H is
quadratic in u (control-affine dynamics with a quadratic running cost: every
task here); ``u_star="newton"`` iterates for general H. Box bounds clip u*
(exact when d2H/du2 is diagonal).

Shooting: unknowns z = (p(0), nu); residuals (psi(x(T)), p(T) - dPhi/dx -
(dpsi/dx)^T nu); solved by Newton or Levenberg–Marquardt on the residual and its
Jacobian from one solve (``_shooting_root``): single shooting integrates the
variational equations beside the extremal, multiple shooting takes one
forward-mode pass. Multiple shooting adds the (x, p) at interior nodes and their
continuity.
``continuation`` walks a parameter (e.g. the target turn from 0 to pi) with
warm starts. ``pmp_residual`` checks the optimality conditions of any
solution, also a direct one, by integrating the costate backwards along it.

States must be vectors (Euclidean); group-valued states are handled by the
direct methods.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import optimistix as optx

import nhjax
from nhjax._linalg import solve as small_solve
from nhjax.mechanics import AbstractSystem

from .problem import (
    OCP,
    ProblemError,
    Progress,
    as_problem_error,
    check_guess,
    check_ocp,
    check_tolerances,
    compiled,
    host_array,
    prepare_saved_path,
    saved_path,
)

__all__ = ["HamiltonianSystem", "IndirectResult", "continuation", "pmp_residual", "prepare_pmp_residual",
           "prepare_pontryagin", "solve_pontryagin"]


class HamiltonianSystem(AbstractSystem):
    """(x, p) under the optimal control u*(t, x, p): the state is concat(x, p)."""

    ocp: OCP
    u_star_method: str = "quadratic"
    # the right-hand side nests derivatives of H: scanned Runge-Kutta stages compile it
    # once instead of once per stage (a shorter compile, the same steps)
    large_vector_field: ClassVar[bool] = True

    @property
    def n(self):
        return self.ocp.x0.shape[0]

    def hamiltonian(self, t, x, p, u):
        return self.ocp.running_cost(t, x, u) + p @ self.ocp.system.vector_field(t, x, u)

    def u_star(self, t, x, p):
        k = self.ocp.system.control_dim
        Hu = jax.grad(self.hamiltonian, argnums=3)
        Huu = jax.jacfwd(Hu, argnums=3)
        u = jnp.zeros(k, x.dtype)
        steps = 1 if self.u_star_method == "quadratic" else 20
        for _ in range(steps):
            # without LAPACK, so that the extremal's loops compile as one function (nhjax._linalg)
            u = u - small_solve(Huu(t, x, p, u), Hu(t, x, p, u))
        if self.ocp.u_lower is not None:
            u = jnp.clip(u, self.ocp.u_lower, self.ocp.u_upper)
        return u

    def flow(self, t, x, p):
        """(u*, x', p'): the optimal control and the state and costate rates at (t, x, p)."""
        u = self.u_star(t, x, p)
        dx = self.ocp.system.vector_field(t, x, u)
        dp = -jax.grad(self.hamiltonian, argnums=1)(t, x, p, u)
        return u, dx, dp

    def vector_field(self, t, y, _u=None):
        n = self.n
        _, dx, dp = self.flow(t, y[:n], y[n:])
        return jnp.concatenate([dx, dp])

    def guards(self, y):
        return self.ocp.system.guards(y[: self.n])


@dataclasses.dataclass
class IndirectResult:
    """Outcome of ``solve_pontryagin``.

    p0 : (n,) the initial costate p(0) [cost units per state unit].
    nu : (m,) the multipliers of the terminal constraints, p(T) = dPhi/dx + (dpsi/dx)^T nu.
    cost : Phi(x(T)) + int_0^T L(t, x, u*) dt along the extremal from (x0, p0),
        integrated with the running cost as an extra state at the solve's rtol/atol.
    violation : max |psi(x(T))| along that extremal [the constraints' units].
    residual : max |shooting residual| at the solution (terminal constraints,
        transversality and, for multiple shooting, the continuity of (x, p) at the
        nodes).
    converged : True when the residual is finite and below 1e3 * tol (the iteration
        stops when its steps fall below tol relative to z, or at the residual's
        floor within tol; see ``_shooting_root``).
    message : "converged", or why not.
    trajectory : an ``nhjax.Trajectory`` of (x, p) (``xs`` is (401, 2n), the state then
        the costate) at 401 equally spaced times on [0, T].
    controls : (401, k) the optimal control u*(t, x, p) at those times.
    seconds : wall time of the call (compilation included on a first call) [s].
    iterations : Newton / Levenberg-Marquardt steps.
    """

    p0: np.ndarray
    nu: np.ndarray
    cost: float
    violation: float
    residual: float
    converged: bool
    message: str
    trajectory: object
    controls: np.ndarray
    seconds: float
    iterations: int


def _shooting_converged(residual, tol):
    """The solvers' test of convergence (elementwise on arrays): a finite shooting
    residual below 1e3 tol (the iteration stops at tol relative to the unknowns, or
    at the residual's floor; see ``_shooting_root``)."""
    residual = np.asarray(residual, float)
    return np.isfinite(residual) & (residual < 1e3 * tol)


def _shoot(ham: HamiltonianSystem, rtol, atol, saveat=2, t0=0.0, t1=None, x0=None, p0=None):
    y0 = jnp.concatenate([x0, p0])
    # forward-mode adjoint: the shooting Jacobian is a jvp per unknown (Newton, LM)
    return nhjax.simulate(ham, y0, ham.ocp.T if t1 is None else t1, t0=t0, rtol=rtol, atol=atol,
                          saveat=saveat, track_work=False, adjoint=diffrax.ForwardMode(),
                          diagnostics=False)


def _terminal_residual(ocp, xT, pT, nu):
    phi, psi = ocp.terminal(xT)
    dphi = jax.grad(lambda x: ocp.terminal(x)[0])(xT)
    dpsi = jax.jacfwd(lambda x: ocp.terminal(x)[1])(xT) if psi.shape[0] else jnp.zeros((0, xT.shape[0]))
    return jnp.concatenate([psi, pT - dphi - dpsi.T @ nu])


class _Shooting(eqx.Module):
    """Shooting residuals as a pytree (so the root find compiles once per problem structure)."""

    ham: HamiltonianSystem
    rtol: jax.Array
    atol: jax.Array
    segments: int = eqx.field(static=True)
    #: Budget of ODE steps of each solve of single shooting (None: simulate's default):
    #: a trial point whose extremal needs more is a failed (non-finite) trial.
    max_ode_steps: int | None = eqx.field(static=True, default=None)

    @property
    def residual_size(self):
        """Entries of ``residual``: the m terminal constraints and the n transversality
        conditions, and for multiple shooting the 2n jumps of (x, p) at each of the
        S - 1 inner nodes (as many as the unknowns)."""
        n, m = self.ham.ocp.x0.shape[0], self.ham.ocp.n_constraints
        return m + n + (self.segments - 1) * 2 * n

    def residual(self, z):
        ocp = self.ham.ocp
        n, m, S = ocp.x0.shape[0], ocp.n_constraints, self.segments
        if S == 1:
            yT = _shoot(self.ham, self.rtol, self.atol, x0=ocp.x0, p0=z[:n]).xs[-1]
            return _terminal_residual(ocp, yT[:n], yT[n:], z[n:])
        edges = jnp.linspace(0.0, ocp.T, S + 1)
        nodes = jnp.concatenate([jnp.concatenate([ocp.x0, z[:n]])[None], z[n + m:].reshape(S - 1, 2 * n)])
        ends = jax.vmap(
            lambda y, a, b: _shoot(self.ham, self.rtol, self.atol, t0=a, t1=b, x0=y[:n], p0=y[n:]).xs[-1]
        )(nodes, edges[:-1], edges[1:])
        yT = ends[-1]
        return jnp.concatenate([_terminal_residual(ocp, yT[:n], yT[n:], z[n:n + m]),
                                (ends[:-1] - nodes[1:]).reshape(-1)])


#: Saved times of the extremal that solve_pontryagin returns.
_EXTREMAL_POINTS = 401


def _extremal(ham, p0, rtol, atol, adjoint=None, max_steps=None):
    """The extremal from (x0, p0) with its running cost integrated alongside: one solve
    of (x, p, J) (``_CostOfExtremal``), saved at ``_EXTREMAL_POINTS`` times."""
    ocp = ham.ocp
    y0 = jnp.concatenate([ocp.x0, p0, jnp.zeros(1)])
    return nhjax.simulate(_CostOfExtremal(ham), y0, ocp.T, rtol=rtol, atol=atol, saveat=_EXTREMAL_POINTS,
                          track_work=False, diagnostics=False, max_steps=max_steps,
                          **({} if adjoint is None else {"adjoint": adjoint}))


class _ExtremalSensitivity(AbstractSystem):
    """(x, p, J) along the extremal from (x0, p0) (as ``_CostOfExtremal``) and the
    sensitivity Phi = d(x, p)/dp0 (2n x n, row-major after J), by the variational
    equations Phi' = D_(x,p)F(t, x, p) Phi with F = (dH/dp, -dH/dx) under u*."""

    ham: HamiltonianSystem
    large_vector_field: ClassVar[bool] = True

    def vector_field(self, t, y, u=None):
        n = self.ham.n
        phi = y[2 * n + 1:].reshape(2 * n, n)
        extremal = _CostOfExtremal(self.ham)  # (x, p, J)' (J does not enter it)

        def rates(xp):
            return extremal.vector_field(t, jnp.concatenate([xp, jnp.zeros(1)]))

        # (the tangent of J' is not used: XLA drops it)
        f, df = jax.vmap(lambda col: jax.jvp(rates, (y[:2 * n],), (col,)), in_axes=1, out_axes=(None, 1))(phi)
        return jnp.concatenate([f, df[:2 * n].reshape(-1)])


class _LeadingNorm(eqx.Module):
    """The RMS norm of a state's first ``size`` components: the error norm of a solve
    that carries sensitivities, which then takes the steps of the solve without them."""

    size: int = eqx.field(static=True)

    def __call__(self, y):
        return optx.rms_norm(y[: self.size])


@eqx.filter_jit
def _residual_and_extremal(sh, z, saveat=_EXTREMAL_POINTS):
    """Single shooting's residual r at z, its Jacobian dr/dz, and the extremal it comes
    from (``_extremal``'s solve and steps, saved at ``saveat`` points: 2 when only r and
    its Jacobian are wanted): one solve for all three. The
    Jacobian comes from the variational equations integrated alongside
    (``_ExtremalSensitivity``; the error norm on (x, p, J) alone, so the steps are the
    extremal's): the derivative of the discrete flow at those steps (internal
    numerical differentiation, Bock 1981), which is also what forward mode through
    the solve gives (diffrax's controller stops gradients through the step sizes).
    The program then holds the ODE solve once, not its forward-mode derivative (the
    jvp and batching of the solver's whole loop): a shorter trace and compile. A
    nested jit: the root find's ``jax.eval_shape`` of its outputs and its loop share
    one trace."""
    ocp = sh.ham.ocp
    n = ocp.x0.shape[0]
    phi0 = jnp.concatenate([jnp.zeros((n, n)), jnp.eye(n)])  # d(x0, p0)/dp0
    y0 = jnp.concatenate([ocp.x0, z[:n], jnp.zeros(1), phi0.reshape(-1)])
    controller = diffrax.PIDController(rtol=sh.rtol, atol=sh.atol, norm=_LeadingNorm(2 * n + 1))
    tr = nhjax.simulate(_ExtremalSensitivity(sh.ham), y0, ocp.T, saveat=saveat, track_work=False,
                        diagnostics=False, stepsize_controller=controller, max_steps=sh.max_ode_steps)
    yT = tr.xs[-1]
    r, (dr_dxp, dr_dnu) = (_terminal_residual(ocp, yT[:n], yT[n:2 * n], z[n:]),
                           jax.jacfwd(lambda xp, nu: _terminal_residual(ocp, xp[:n], xp[n:], nu),
                                      argnums=(0, 1))(yT[:2 * n], z[n:]))
    jac = jnp.concatenate([dr_dxp @ yT[2 * n + 1:].reshape(2 * n, n), dr_dnu], axis=1)
    tr = eqx.tree_at(lambda t: (t.xs, t.x_end), tr, (tr.xs[:, : 2 * n + 1], tr.x_end[: 2 * n + 1]))
    return r, jac, tr


def _value_and_jacobian(z, evaluate):
    """The residual r(z), its Jacobian and ``evaluate``'s other outputs at z
    (``evaluate(z) = (r, aux)``) from one forward-mode pass: ``jacfwd`` runs the ODE
    solve once for the primal beside its batched tangents."""

    def f(y):
        r, aux = evaluate(y)
        return r, (r, aux)

    jac, (value, aux) = jax.jacfwd(f, has_aux=True)(z)
    return value, jac, aux


#: Levenberg–Marquardt's first damping, relative to diag(J^T J): nearly Gauss-Newton.
#: Starts are usually close (a direct optimum's costates, a continuation step), where
#: damping only slows the quadratic convergence (benchmarks/steering_peer.py's
#: Pontryagin row); a poor step is rejected and the damping then grows quickly
#: (Nielsen's rule doubles its factor at each rejection).
_LM_MU0 = 1e-12


def _shooting_root(shooting, z0, tol, max_steps, damped: bool, extremal: bool = False):
    """Newton's method (``damped=False``) or Levenberg–Marquardt on the shooting
    residual r(z) (``shooting.residual``, with ``shooting.residual_size`` entries): z,
    r(z), the number of steps taken, and with ``extremal`` (single shooting) the
    extremal of z (else ``()``): then the loop's solve is ``_residual_and_extremal``'s,
    which also integrates the running cost, the variational equations for the Jacobian,
    and saves the extremal, and the loop keeps the one of its last accepted point, so
    that the answer needs no solve of its own.

    Each iteration evaluates r and its Jacobian once, at the point it tries: in single
    shooting from the variational equations integrated beside the extremal
    (``_residual_and_extremal``; with ``extremal`` that solve also saves the path, else
    only its ends), in multiple shooting in one forward-mode pass
    (``_value_and_jacobian``: the solves once, beside their batched tangents). Both give
    the derivative of the discrete flow at the solve's steps; the compiled loop holds
    one copy of the extremal's ODE solve. (optimistix's Newton and Levenberg–Marquardt evaluate
    r and build its Jacobian operator separately, three copies of the solve in one
    program: about twice the time to trace and compile, and the time to a first
    answer is mostly that.) The first iteration evaluates at z0 itself.

    Newton takes every step z <- z - J^-1 r. Levenberg–Marquardt solves
    (J^T J + mu D) dz = -J^T r (D = diag(J^T J), Marquardt's scaling), accepts the
    trial point when it lowers |r|^2, and updates mu by the ratio of that decrease
    to the linearization's prediction (Nielsen's rule).

    Stops after a step with max|dz| <= tol (1 + max|z|) (as optimistix's Cauchy
    termination: near a regular root that step also takes r from ~tol to rounding),
    after an accepted step that ends within max|r| <= tol without dividing max|r|
    by 10 (the residual's floor, where redundant unknowns can keep the steps from
    shrinking), at a non-finite trial point (Newton; it keeps the last finite
    point), at a non-finite start, or after ``max_steps`` steps. The caller judges
    convergence by |r|.
    """
    z0 = jnp.asarray(z0, float)
    n = z0.shape[0]
    if extremal:
        values_and_jacobian = functools.partial(_residual_and_extremal, shooting)
        # (the outputs' shapes: a trace that the loop's call of the nested jit reuses)
        aux0 = jtu.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(values_and_jacobian, z0)[2])
    elif isinstance(shooting, _Shooting) and shooting.segments == 1:
        def values_and_jacobian(y):
            r, jac, _ = _residual_and_extremal(shooting, y, saveat=2)
            return r, jac, ()

        aux0 = ()
    else:
        def values_and_jacobian(y):
            return _value_and_jacobian(y, lambda y: (shooting.residual(y), ()))

        aux0 = ()

    def proposal(r, jac, mu):
        """The step and the decrease of 0.5 |r|^2 that the linearization predicts for it."""
        if not damped:
            return -small_solve(jac, r), jnp.ones(())
        jtj, g = jac.T @ jac, jac.T @ r
        scale = jnp.maximum(jnp.diag(jtj), jnp.finfo(r.dtype).eps)
        dz = -small_solve(jtj + mu * jnp.diag(scale), g)
        return dz, 0.5 * dz @ (mu * scale * dz - g)

    def body(c):
        k, z, r, jac, aux, mu, nu, _, _ = c
        first = k == 0
        dz, predicted = proposal(r, jac, mu)
        dz = jnp.where(first, 0.0, dz)
        z_try = jnp.where(first, z0, z + dz)
        r_try, jac_try, aux_try = values_and_jacobian(z_try)
        ok = jnp.all(jnp.isfinite(r_try)) & jnp.all(jnp.isfinite(jac_try))
        gain = 0.5 * (r @ r - r_try @ r_try) / predicted  # actual over predicted decrease
        accept = first | (ok & ((gain > 0) | (not damped)))
        r_prev = r
        z, r, jac = (jnp.where(accept, a, b) for a, b in ((z_try, z), (r_try, r), (jac_try, jac)))
        aux = jtu.tree_map(lambda a, b: jnp.where(accept, a, b), aux_try, aux)
        # Nielsen's damping update (Madsen, Nielsen & Tingleff, Methods for non-linear
        # least squares problems, 2004, eq. (2.21))
        mu = jnp.where(first, mu, jnp.where(accept, mu * jnp.maximum(1 / 3, 1 - (2 * gain - 1) ** 3), mu * nu))
        nu = jnp.where(accept, 2.0, 2 * nu)
        # (a step this small ends the iteration accepted or not: the residual is at the
        # floor its rounding allows, or exactly zero)
        small = ~first & (jnp.max(jnp.abs(dz)) <= tol * (1.0 + jnp.max(jnp.abs(z))))
        # ... or once within tol when a step no longer divides |r| by 10 (the floor, even
        # if redundant unknowns keep the steps from shrinking)
        r_max, r_was = jnp.max(jnp.abs(r)), jnp.max(jnp.abs(jnp.where(accept, r_prev, jnp.inf)))
        small = small | (accept & ~first & (r_max <= tol) & (r_max > 0.1 * r_was))
        # Newton stops at a non-finite trial (keeping the last finite point); the damped
        # iteration rejects it and shortens the step; both stop at a non-finite start
        going = (ok | damped) & jnp.all(jnp.isfinite(r))
        return k + 1, z, r, jac, aux, mu, nu, small, going

    def cond(c):
        k, *_, small, going = c
        return (k == 0) | ((k <= max_steps) & going & ~small)

    m = shooting.residual_size  # (not by eval_shape: that would trace the shooting's solves once more)
    if not damped and not extremal:
        return _newton_root(values_and_jacobian, z0, m, tol, max_steps)
    # (r, J) before the first evaluation: any finite values (its step is masked out)
    start = (jnp.zeros((), int), z0, jnp.zeros(m), jnp.eye(m, n), aux0, jnp.asarray(_LM_MU0), jnp.asarray(2.0),
             jnp.zeros((), bool), jnp.ones((), bool))
    k, z, r, _, aux, *_ = jax.lax.while_loop(cond, body, start)
    return z, r, k - 1, aux


def _newton_root(values_and_jacobian, z0, m, tol, max_steps):
    """``_shooting_root``'s Newton iteration for a caller that evaluates the residual at
    the answer itself (``extremal=False``): the same iterates, stops and step count, but
    the last step, one whose size already meets the tolerance, is taken without
    evaluating r and its Jacobian at its end (that evaluation, a solve of the
    variational equations, only confirmed the stop: Newton accepts every finite trial).
    Each iteration evaluates at its point, then proposes the next step. Returns (z, r at
    the last point evaluated, steps, ())."""
    n = z0.shape[0]

    def body(c):
        k, z, r, jac, dz, _, _ = c
        first = k == 0
        z_try = jnp.where(first, z0, z + dz)
        r_try, jac_try, _ = values_and_jacobian(z_try)
        ok = jnp.all(jnp.isfinite(r_try)) & jnp.all(jnp.isfinite(jac_try))
        accept = first | ok
        r_prev = r
        z, r, jac = (jnp.where(accept, a, b) for a, b in ((z_try, z), (r_try, r), (jac_try, jac)))
        # the residual's floor (as in _shooting_root), judged at this point
        r_max, r_was = jnp.max(jnp.abs(r)), jnp.max(jnp.abs(jnp.where(accept, r_prev, jnp.inf)))
        floor = accept & ~first & (r_max <= tol) & (r_max > 0.1 * r_was)
        going = ok & jnp.all(jnp.isfinite(r))
        # the next step; one within tolerance (and within the budget) is the last
        dz = -small_solve(jac, r)
        last = going & ~floor & (k + 1 <= max_steps) \
            & (jnp.max(jnp.abs(dz)) <= tol * (1.0 + jnp.max(jnp.abs(z + dz))))
        return k + 1, z, r, jac, dz, floor | last | ~going, last

    def cond(c):
        k, *_, stop, _ = c
        return (k == 0) | ((k <= max_steps) & ~stop)

    start = (jnp.zeros((), int), z0, jnp.zeros(m), jnp.eye(m, n), jnp.zeros(n), jnp.zeros((), bool),
             jnp.zeros((), bool))
    k, z, r, _, dz, _, last = jax.lax.while_loop(cond, body, start)
    return jnp.where(last, z + dz, z), r, k - 1 + last.astype(k.dtype), ()


@compiled
def _residual_max(shooting, z):
    return jnp.max(jnp.abs(shooting.residual(z)))


def _extremal_outputs(ham, tr):
    """From an ``_extremal`` solve: the trajectory of (x, p), the controls at its saved
    times, and the total cost."""
    ocp = ham.ocp
    n = ocp.x0.shape[0]
    traj = eqx.tree_at(lambda t: (t.xs, t.x_end), tr, (tr.xs[:, : 2 * n], tr.x_end[: 2 * n]))
    xs, ps = traj.xs[:, :n], traj.xs[:, n:]
    us = jax.vmap(ham.u_star)(traj.ts, xs, ps)
    yT = tr.xs[-1]
    cost = ocp.terminal(yT[:n])[0] + yT[-1]
    return traj, us, cost


def _indirect_body(sh, z0, tol, max_steps, damped: bool, one_solve: bool):
    """The whole indirect solve as one program: Newton or Levenberg–Marquardt
    (``damped``) on the shooting residual (``_shooting_root``), the extremal of the
    solution with its cost, the final residual and the terminal constraints' violation
    max |psi(x(T))| at the extremal's end. ``tol`` and ``max_steps`` are arrays: other
    values do not compile again.

    ``one_solve`` (single shooting): the extremal is the root find's own last accepted
    solve, which then integrates the running cost and saves the extremal at every
    iteration (one ODE solve in the program: a shorter trace and compile, a longer run
    per iteration). Otherwise a solve of its own after the root find (the residual of
    single shooting from its end)."""
    ocp = sh.ham.ocp
    n, m = ocp.x0.shape[0], ocp.n_constraints
    single = sh.segments == 1
    one = one_solve and single
    z, r, steps, tr = _shooting_root(sh, z0, tol, max_steps, damped, extremal=one)
    if not one:
        tr = _extremal(sh.ham, z[:n], sh.rtol, sh.atol, max_steps=sh.max_ode_steps if single else None)
        if single:
            yT = tr.xs[-1]
            r = _terminal_residual(ocp, yT[:n], yT[n:2 * n], z[n:n + m])
        else:
            r = sh.residual(z)
    traj, us, cost = _extremal_outputs(sh.ham, tr)
    viol = jnp.max(jnp.abs(ocp.terminal(traj.xs[-1, :n])[1])) if m else jnp.zeros(())
    return z, jnp.max(jnp.abs(r)), steps, traj, us, cost, viol


@compiled
def _indirect(sh, z0, tol, max_steps, damped: bool):
    """``_indirect_body`` with XLA's solve settings and a solve of its own for the extremal:
    the program for solves that run many times (a fast run)."""
    return _indirect_body(sh, z0, tol, max_steps, damped, one_solve=False)


@compiled(quick=True)
def _indirect_quick(sh, z0, tol, max_steps, damped: bool):
    """``_indirect_body`` with XLA's quick settings and the extremal from the root find's
    last solve (``solve_pontryagin(quick=True)``): the program for a solve that runs once
    from a close start and whose compile the answer waits for (a short compile)."""
    return _indirect_body(sh, z0, tol, max_steps, damped, one_solve=True)


def _check_pontryagin(ocp, owner, solver, u_star):
    """The checks solve_pontryagin and prepare_pontryagin share: a problem with a
    vector state, and the solver and u* options."""
    check_ocp(ocp, owner)
    if not hasattr(ocp.x0, "shape") or ocp.x0.ndim != 1:
        raise ProblemError(f"{owner}: the Pontryagin solver needs a vector state; use the direct methods")
    with as_problem_error():
        nhjax._validate.choice("solver", solver, ("newton", "lm"), owner=owner)
        nhjax._validate.choice("u_star", u_star, ("quadratic", "newton"), owner=owner)


def _root_options(tol, max_steps, solver):
    """_indirect's arguments after the start: tolerance and budget as arrays (other
    values compile nothing), damping as a static flag."""
    return np.asarray(tol, float), np.asarray(max_steps), solver == "lm"


def prepare_pontryagin(ocp: OCP, *, solver: str = "newton", u_star: str = "quadratic", rtol: float = 1e-11,
                       atol: float = 1e-11, tol: float = 1e-10, max_steps: int = 100, quick: bool = False) -> bool:
    """Trace ``solve_pontryagin``'s program (single shooting, these options) for this
    problem's structure now and compile it in the background, for a caller that will
    call it later (e.g. after a direct solve that gives the costates to start from):
    the compile then overlaps the caller's other work. A program kept in nhjax's
    program cache is loaded in the background instead. Returns whether background work
    started (not if the program is in memory already)."""
    owner = "prepare_pontryagin"
    _check_pontryagin(ocp, owner, solver, u_star)
    check_tolerances(owner, rtol=rtol, atol=atol, tol=tol, max_steps=(max_steps, "int"))
    ham = HamiltonianSystem(ocp, u_star)
    sh = _Shooting(ham, host_array(rtol), host_array(atol), 1)
    n, m = ocp.x0.shape[0], ocp.n_constraints
    program = _indirect_quick if quick else _indirect
    return program.prepare(sh, np.zeros(n + m), *_root_options(tol, max_steps, solver))


def solve_pontryagin(
    ocp: OCP,
    p0_guess=None,
    nu_guess=None,
    *,
    shooting: str = "single",
    segments: int = 4,
    solver: str = "newton",
    u_star: str = "quadratic",
    rtol: float = 1e-11,
    atol: float = 1e-11,
    tol: float = 1e-10,
    max_steps: int = 100,
    progress: bool = True,
    quick: bool = False,
) -> IndirectResult:
    """Indirect shooting for ``ocp`` from a costate guess (default zeros).

    solver : "newton" (Newton's method on the residuals) or "lm"
        (Levenberg–Marquardt, more robust far from the solution); see ``_shooting_root``.
    progress : a progress line (tqdm.auto) with the iterations, cost, violation and
        residual when the solve ends (the iteration runs inside one compiled program,
        which has no host callbacks so that JAX's persistent cache keeps it); False: none.
    quick : a program made for a short compile rather than a fast run, for a solve that
        runs once from a close start and whose compile the answer waits for (the polish
        of a direct optimum): XLA's quick settings (``nhjax._programs.QUICK_OPTIONS``,
        LLVM at its lowest optimization) instead of the solve settings, and for single
        shooting one ODE solve in the program, the root find's, which then also
        integrates the cost and saves the extremal at each iteration (instead of a solve
        of the extremal after it). The same solution; last bits may differ from the
        default program's. ``prepare_pontryagin`` takes the same flag.

    The root find, the extremal and its cost are one compiled program per problem
    structure; the problem's numbers (x0, T, targets) and the guesses are its
    arguments. Returns an ``IndirectResult``.
    """
    owner = "solve_pontryagin"
    _check_pontryagin(ocp, owner, solver, u_star)
    if shooting not in ("single", "multiple"):
        raise ProblemError("shooting must be 'single' or 'multiple'")
    check_tolerances(owner, rtol=rtol, atol=atol, tol=tol, max_steps=(max_steps, "int"),
                     segments=(segments, "int", 2 if shooting == "multiple" else 1))
    t_start = time.perf_counter()
    n, m = ocp.x0.shape[0], ocp.n_constraints
    ham = HamiltonianSystem(ocp, u_star)
    if p0_guess is not None and np.shape(p0_guess) != (n,) or nu_guess is not None and np.shape(nu_guess) != (m,):
        raise ProblemError(f"costate guess must have shape ({n},) and multiplier guess ({m},)")
    # host (numpy) bookkeeping: an eager jax operation is a program of its own in a new process
    p0 = np.zeros(n) if p0_guess is None else np.asarray(
        check_guess("p0_guess", p0_guess, (n,), "costate guess"), float)
    nu = np.zeros(m) if nu_guess is None else np.asarray(
        check_guess("nu_guess", nu_guess, (m,), "multiplier guess"), float)
    rt, at = host_array(rtol), host_array(atol)
    S = segments if shooting == "multiple" else 1
    sh = _Shooting(ham, rt, at, S)
    z0 = np.concatenate([p0, nu])
    if S > 1:
        guess = np.asarray(_shoot(ham, rt, at, saveat=S + 1, x0=ocp.x0, p0=p0).xs)
        z0 = np.concatenate([z0, guess[1:-1].reshape(-1)])
    bar = Progress(progress, 1, f"Pontryagin ({'Newton' if solver == 'newton' else 'Levenberg-Marquardt'})")
    converged = False
    try:
        program = _indirect_quick if quick else _indirect
        z, res, steps, traj, us, cost, viol = program(sh, z0, *_root_options(tol, max_steps, solver))
        z, res, viol = np.asarray(z), float(res), float(viol)
        if not (np.all(np.isfinite(z)) and np.isfinite(res)):
            # say what is wrong with the start, if anything; else the iteration diverged
            _check_start(ham, sh, p0, nu, rt, at)
            raise ProblemError(
                f"{owner}: the shooting iteration left the region where the extremal can be integrated, or "
                "diverged to NaN/inf, from a finite start (a Newton step was too long); try solver='lm' "
                "(damped steps), a closer p0_guess, or continuation from an easier problem")
        p0, nu = z[:n], z[n:n + m]
        converged = bool(_shooting_converged(res, tol))
        bar.update(iterations=int(steps), cost=float(cost), violation=f"{viol:.1e}", residual=f"{res:.1e}")
    finally:
        bar.finish(converged)
    msg = "converged" if converged else (
        f"not converged: shooting residual {res:.2e} after {int(steps)} steps; from a poor start try "
        + ("solver='lm' (damped steps), " if solver == "newton" else "") + "a closer p0_guess, or continuation "
        "from an easier problem")
    return IndirectResult(
        p0=np.asarray(p0), nu=np.asarray(nu), cost=float(cost), violation=viol, residual=res,
        converged=converged, message=msg, trajectory=traj, controls=np.asarray(us),
        seconds=time.perf_counter() - t_start, iterations=int(steps),
    )


@compiled(quick=True)
def _terminal_pieces(ocp, xT, nu):
    """Phi, psi and their derivatives at x(T) (for the start's diagnosis)."""
    phi, psi = ocp.terminal(xT)
    res = _terminal_residual(ocp, xT, jnp.zeros_like(xT), nu)
    return phi, psi, res


def _check_start(ham, sh, p0, nu, rt, at):
    """The shooting residual at the initial guess must be finite; if it is not, say which
    piece is to blame (the extremal, the terminal constraints or cost, or their
    derivatives) before Newton's method turns the NaN into a failed solve elsewhere."""
    owner = "solve_pontryagin"
    ocp = ham.ocp
    z0 = jnp.concatenate([p0, nu])
    try:
        if np.isfinite(float(_residual_max(sh, z0))):
            return
    except eqx.EquinoxRuntimeError:
        pass
    try:
        traj = _shoot(ham, rt, at, x0=ocp.x0, p0=p0)
    except nhjax.IntegrationError as e:
        raise ProblemError(
            f"{owner}: the extremal from the initial costate guess cannot be integrated to T: {e}. The "
            "state and costate equations are not finite along it; give a p0_guess closer to the solution "
            "(or check the model's domain)") from e
    xT = np.asarray(traj.xs[-1, : ocp.x0.shape[0]])
    phi, psi, res = (np.asarray(a) for a in _terminal_pieces(ocp, jnp.asarray(xT), nu))
    where = np.array2string(xT, precision=6, separator=", ")
    if not np.all(np.isfinite(psi)):
        bad = np.nonzero(~np.isfinite(psi))[0].tolist()
        raise ProblemError(
            f"{owner}: terminal_constraints(x(T)) is NaN/inf at the start (components {bad}) at the terminal "
            f"state x(T) = {where} of the initial costate guess: the constraint function is not defined "
            "there (e.g. sqrt or log of a negative number). Write it so that it is finite wherever the motion "
            "can end, or give a p0_guess whose extremal ends where it is defined")
    if not np.isfinite(phi):
        raise ProblemError(
            f"{owner}: terminal_cost(x(T)) is NaN/inf at the start, at the terminal state x(T) = {where} of "
            "the initial costate guess: write it so that it is finite wherever the motion can end")
    if not np.all(np.isfinite(res)):
        raise ProblemError(
            f"{owner}: the derivative of terminal_cost or terminal_constraints is NaN/inf at the terminal "
            f"state x(T) = {where} of the initial costate guess (e.g. sqrt(x) at x = 0): the transversality "
            "condition p(T) = dPhi/dx + (dpsi/dx)^T nu needs them differentiable there")
    raise ProblemError(
        f"{owner}: the shooting residual is NaN/inf at the initial guess although the extremal and the "
        "terminal functions are finite: a segment of the multiple-shooting guess may fail; try shooting='single'")


class _CostOfExtremal(AbstractSystem):
    """(x, p, J) along the extremal from (x0, p0)."""

    ham: HamiltonianSystem
    large_vector_field: ClassVar[bool] = True

    def vector_field(self, t, y, u=None):
        n = self.ham.n
        x, p = y[:n], y[n:2 * n]
        ustar, dx, dp = self.ham.flow(t, x, p)
        return jnp.concatenate([dx, dp, self.ham.ocp.running_cost(t, x, ustar)[None]])


def continuation(solve: Callable, values, z0=None):
    """Solve a family of problems along ``values`` with warm starts.

    ``solve(value, z)`` must return a result with fields p0 and nu (z = None at the
    first value means the solver's default guess). Returns the list of results.
    """
    if not callable(solve):
        raise ProblemError(f"continuation: solve must be callable as solve(value, z), got {type(solve).__name__}")
    values = list(values)
    if not values:
        raise ProblemError("continuation: values is empty; pass the parameter values to walk through")
    results, z = [], z0
    for v in values:
        r = solve(v, z)
        if not r.converged:
            raise ProblemError(f"continuation stopped at value {v}: {r.message}")
        results.append(r)
        z = (r.p0, r.nu)
    return results


@compiled(quick=True)
def _costate_sweep(ham, control, xT, nu, rtol, atol, n_points, adjoint):
    """State and costate integrated backward from T along the control, with dH/du etc."""
    ocp = ham.ocp
    n, m = ocp.x0.shape[0], nu.shape[0]
    pT = -_terminal_residual(ocp, xT, jnp.zeros(n), nu)[m:]
    tr = nhjax.simulate(_Backward(ham, control), jnp.concatenate([xT, pT]), ocp.T, rtol=rtol,
                        atol=atol, saveat=n_points, track_work=False, diagnostics=False,
                        adjoint=adjoint)
    ts = ocp.T - tr.ts
    xs, ps = tr.xs[:, :n], tr.xs[:, n:]
    us = jax.vmap(control)(ts, xs)
    Hu = jax.vmap(jax.grad(ham.hamiltonian, argnums=3))(ts, xs, ps, us)
    Lu = jax.vmap(jax.grad(ocp.running_cost, argnums=2))(ts, xs, us)
    H = jax.vmap(ham.hamiltonian)(ts, xs, ps, us)
    L = jax.vmap(ocp.running_cost)(ts, xs, us)
    return ts, xs, ps, us, Hu, Lu, H, L


def _check_sweep(ocp, control, owner, rtol, atol, n_points):
    """The checks pmp_residual and prepare_pmp_residual share."""
    check_ocp(ocp, owner)
    if not callable(control):
        raise ProblemError(f"{owner}: control must be callable as u(t, x), got {type(control).__name__}")
    if not hasattr(ocp.x0, "shape") or ocp.x0.ndim != 1:
        raise ProblemError(f"{owner}: the costate check needs a vector state")
    check_tolerances(owner, rtol=rtol, atol=atol, n_points=(n_points, "int", 2))


def _sweep_pieces(ocp, rtol, atol):
    """_costate_sweep's Hamiltonian system, tolerances (arrays) and adjoint."""
    return (HamiltonianSystem(ocp), host_array(rtol), host_array(atol),
            diffrax.RecursiveCheckpointAdjoint())


def prepare_pmp_residual(ocp: OCP, control, *, rtol=1e-11, atol=1e-11, n_points=201) -> bool:
    """Trace ``pmp_residual``'s costate sweep for this problem and a control of
    ``control``'s structure (e.g. the parametrization's signal of any parameters) now
    and compile it in the background; see ``prepare_pontryagin``."""
    _check_sweep(ocp, control, "prepare_pmp_residual", rtol, atol, n_points)
    return _prepare_residual(ocp, control, rtol, atol, n_points, _sweep_pieces(ocp, rtol, atol))


def _prepare_residual(ocp, control, rtol, atol, n_points, pieces) -> bool:
    """Both of ``pmp_residual``'s programs traced now, one after the other, and compiled
    (or loaded) in the background side by side (the sweep needs only x(T)'s shape)."""
    ham, rt, at, adj = pieces
    started = prepare_saved_path(ocp, control, rtol=rtol, atol=atol, n_points=n_points)
    x_T, nu = np.zeros(ocp.x0.shape[0]), np.zeros(ocp.n_constraints)
    return _costate_sweep.prepare(ham, control, x_T, nu, rt, at, n_points, adj) or started


def pmp_residual(ocp: OCP, control, multipliers=None, *, rtol=1e-11, atol=1e-11, n_points=201):
    """How far (x, u) from ``control`` is from satisfying Pontryagin's conditions.

    Integrates the state forward, then state and costate backward from the
    transversality condition p(T) = dPhi/dx + (dpsi/dx)^T nu. With ``multipliers``
    None, nu is fitted: the costate is affine in nu, so the nu that minimizes the
    stationarity residual in least squares is exact to compute (this is what makes the
    check applicable to any solution, e.g. a direct one). Returns a dict with
    ``stationarity``: max_t |dH/du| / max_t |dL/du|, ``hamiltonian_variation``:
    (max H - min H) / max |L| (H is constant along optimal motions of autonomous
    problems), ``multipliers`` (nu), and the arrays ts, xs, ps, us.
    """
    _check_sweep(ocp, control, "pmp_residual", rtol, atol, n_points)
    m = ocp.n_constraints
    if multipliers is not None:
        check_guess("multipliers", multipliers, (m,), "problem's terminal constraints")
    ham, rt, at, adj = pieces = _sweep_pieces(ocp, rtol, atol)
    _prepare_residual(ocp, control, rtol, atol, n_points, pieces)
    # (saved at n_points only so that a caller's path with as many points, e.g.
    # somersault_free_winding's check, shares its compiled program)
    xT = saved_path(ocp, control, rtol=rtol, atol=atol, n_points=n_points, owner="pmp_residual")[1][-1]
    if multipliers is None and m == 0:
        nu = np.zeros(0)
    elif multipliers is None:
        # dH/du along the fixed (x, u) is affine in nu (the costate equation is linear in
        # p and p(T) is affine in nu): its matrix from m + 1 sweeps of the one compiled
        # function, exact up to the integration tolerance
        # (the small least-squares algebra in numpy on the host: no eager jax programs)
        def stationarity(nu):
            return np.asarray(_costate_sweep(ham, control, xT, nu, rt, at, n_points, adj)[4]).reshape(-1)

        r0 = stationarity(np.zeros(m))
        J = np.stack([stationarity(e) - r0 for e in np.eye(m)], axis=1)
        nu = np.linalg.lstsq(J, -r0, rcond=None)[0]
    else:
        nu = np.asarray(multipliers, float)
    ts, xs, ps, us, Hu, Lu, H, L = (np.asarray(a) for a in _costate_sweep(ham, control, xT, nu, rt, at,
                                                                           n_points, adj))
    return {
        "stationarity": float(np.max(np.abs(Hu)) / np.max(np.abs(Lu))),
        "hamiltonian_variation": float((np.max(H) - np.min(H)) / np.max(np.abs(L))),
        "multipliers": nu,
        "ts": ts, "us": us, "ps": ps, "xs": xs,
    }


class _Backward(AbstractSystem):
    """(x, p) integrated backward in time s = T - t under a given control."""

    ham: HamiltonianSystem
    control: Callable
    large_vector_field: ClassVar[bool] = True

    def vector_field(self, s, y, u=None):
        n = self.ham.n
        t = self.ham.ocp.T - s
        x, p = y[:n], y[n:]
        uu = self.control(t, x)
        dx = self.ham.ocp.system.vector_field(t, x, uu)
        dp = -jax.grad(self.ham.hamiltonian, argnums=1)(t, x, p, uu)
        return -jnp.concatenate([dx, dp])
