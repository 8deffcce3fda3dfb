r"""Direct single shooting with a feasible-path Newton solver (``solve_direct_newton``).

An alternative to ``controls.solve_direct`` (augmented Lagrangian with L-BFGS
inner solves) for problems with few parameters (tens) whose terminal
constraints are strongly curved in the control parameters, where first-order
inner solves crawl along the curved constraint manifold. It is Miele's
sequential gradient-restoration algorithm (SGRA) with second-order tangent
steps:

* restoration: projection of the parameters z onto psi(z) = 0 with least
  change in the metric Q of the cost (the Hessian of int L(t, x0, u) dt in z by
  Gauss-Legendre quadrature: the exact Hessian of the cost when L depends on u
  only, e.g. int |u|^2 dt; the identity when that Hessian is singular). After a
  tangent step it first uses secant (Broyden) updates of the constraints'
  Jacobian at the point the step left from, one forward solve per iteration;
  Gauss-Newton with fresh Jacobians only when that does not converge;
* multipliers lam = argmin |dJ + A^T lam|, A = dpsi/dz (the Jacobian of (J, psi)
  from one forward solve carrying the P parameter tangents);
* the reduced Hessian Z^T H Z of the Lagrangian J + lam . psi (Z a basis of the
  null space of A) by one-sided differences of its reverse-mode gradient along
  the columns of Z (P - m reverse passes, vmapped). That program is the solver's
  largest to trace and compile, so a first solve (nothing stored yet) with few
  parameters (``SEQUENTIAL_TANGENTS``) takes the same gradients from the Jacobian's
  program instead (P - m forward solves with P tangents: slower to run, nothing to
  trace or compile; the two agree to the differences' accuracy) and, when it
  returns, leaves the program to a thread of its own, which traces it and stores it
  for the next solves (a script's process ends once it is stored);
* a Newton step in the null space of A, with the reduced Hessian's negative
  eigenvalues replaced by their magnitudes (saddle-free Newton), then
  restoration; the step is halved until the restored cost decreases (Armijo), or
  the stationarity where the predicted decrease is below the costs' resolution.

Far from the optimum the iterates need not be exact, so the simulations first
run at ``loose_tol`` (1e-6, unless the requested tolerances are looser), and the line
search's restorations there stop at max(ctol, loose_tol) (below it they would meet the
loose simulations' noise: fresh Jacobians and failed trials for nothing), until the
relative stationarity falls below ``LOOSE_UNTIL`` (or a line search fails
there); then the iterate is restored at the requested tolerances and the
iteration goes on there. The tolerances are arguments of the compiled programs,
so the switch compiles nothing. Converged (at the requested tolerances only)
when max |psi| < ctol and max |dJ + A^T lam| / max |dJ| < gtol. Each iteration
costs a forward solve with P tangents, P - m reverse passes and a few forward solves:
worth it for P up to ~100.
"""

from __future__ import annotations

import time

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import nhjax
from nhjax import _programs

from ._result import DirectResult
from .problem import (
    OCP,
    ProblemError,
    Progress,
    check_guess,
    check_ocp,
    check_parametrization,
    check_tolerances,
    compiled,
    host_array,
    rollout,
)

__all__ = ["solve_direct_newton"]

#: Relative stationarity below which the iteration leaves the loose simulations
#: (``loose_tol``) for the requested tolerances.
LOOSE_UNTIL = 1e-3

#: A line search's trial point is restored by Gauss-Newton only while each step
#: shrinks the violation by at least this factor; otherwise the step is halved.
CONTRACTION = 0.5

#: A first solve (the Hessian's program not stored yet) takes its reduced Hessians from
#: the Jacobian's program when that costs at most this many tangent solves per Hessian
#: ((P - m) forward solves with P tangents each). Below it (the spherical robot's
#: steering, 144; the 3-link chain's reorientation, 504) the first answer came sooner
#: than by waiting for the reverse passes' program; above it (the thruster chain, 3575)
#: later, so there the program is prepared at the start and waited for. (The timings
#: are in the commit that set it.)
SEQUENTIAL_TANGENTS = 1024


class _Shooting(eqx.Module):
    """Single shooting: parameters -> (cost, terminal constraints), as one pytree."""

    ocp: OCP
    param: object
    rtol: jax.Array
    atol: jax.Array
    max_steps: int = eqx.field(static=True, default=20_000)

    def values(self, z, tangents=False, solved=False):
        """(J, psi) at z (with ``solved``: and whether the simulation reached T, for
        programs traced without runtime checks, such as a batch's). Differentiated by the discrete adjoint: its VJP sweep (one
        reverse pass per cotangent), or with ``tangents`` its forward sensitivities (the
        solve carries dx/dz along: one pass gives the whole Jacobian).

        The steps resolve the inputs (``_step_controller``): the step control sees the
        states, not their derivatives in z, so where the states hardly move (a system at
        rest under zero inputs, the usual first guess) it would take a few long steps, and
        the derivatives of the inputs' effect, which the solver needs, would be those of a
        coarse quadrature of the inputs (on the thruster chain at rest the final momenta's
        response came out 0 instead of 0.54 per unit step)."""
        adjoint = nhjax.DiscreteAdjoint(jacobians="auto", max_tangents=z.shape[0] if tangents else 0)
        traj, J, psi = rollout(self.ocp, self.param.signal(z), rtol=self.rtol, atol=self.atol,
                               max_steps=self.max_steps, adjoint=adjoint, solver=_shooting_solver(self.ocp),
                               stepsize_controller=_step_controller(self.param, self.rtol, self.atol))
        y = jnp.concatenate([J[None], psi])
        return (y, traj.result == diffrax.RESULTS.successful) if solved else y


def _shooting_solver(ocp):
    """The solver of a shooting simulation: for a system whose stages run as a scan
    (``large_vector_field``: one copy of the vector field in the program whatever the
    tableau's length) ``nhjax.RKMK87`` without its bootstrapped dense output (a
    shooting solve saves only its end): as quick to compile as RKMK45, and at the
    tolerances the solvers end at (1e-10) far fewer steps (on the spherical robot's
    steering 65 against 488). Otherwise None: simulate's default, RKMK45, whose
    unrolled 7 stages compile in less time than 13 would."""
    if not ocp.system.large_vector_field:
        return None
    # (jumps: the first stage is evaluated afresh after a knot or a projected step)
    return nhjax.RKMK87(scan_stages=True, first_stage_in_scan=True, bootstrap=False, jumps=True)


def _step_controller(param, rtol, atol):
    """The step-size control of a shooting solve over ``param``: the steps stop where its
    signal is not smooth (``param.jump_times()``, the knots of a piecewise one: diffrax's
    ``jump_ts``); a smooth signal (Chebyshev, Fourier) gets steps of at most its horizon
    over its number of parameters per input (one step per degree of freedom)."""
    jumps = param.jump_times()
    if jumps is not None:
        return diffrax.PIDController(rtol=rtol, atol=atol, jump_ts=jumps)
    return diffrax.PIDController(rtol=rtol, atol=atol, dtmax=param.T / max(param.size // max(param.dim, 1), 1))


@compiled
def _values_jit(sh, z):
    return sh.values(z)


def _values(sh, z):
    """(J, psi) at z, or inf where the simulation fails (a wild trial step)."""
    try:
        y = np.asarray(_values_jit(sh, z))
    except eqx.EquinoxRuntimeError:
        return np.full(sh.ocp.n_constraints + 1, np.inf)
    # the compiled programs trace equinox's runtime errors as NaN (no host callbacks)
    return y if np.all(np.isfinite(y)) else np.full(y.shape, np.inf)


@compiled
def _values_and_jacobian(sh, z):
    """(J, psi) and their whole Jacobian, by the solve's forward sensitivities in the P
    parameters (one forward solve carrying P tangents; the VJP sweep of 1 + m reverse
    passes where a step has no forward-mode rule): on the somersault and steering
    problems both cheaper to run and smaller to compile than the reverse passes."""
    y, vjp = jax.vjp(lambda z: sh.values(z, tangents=True), z)
    return y, jax.vmap(vjp)(jnp.eye(y.shape[0], dtype=y.dtype))[0]


@compiled
def _lagrangian_gradients(sh, Z, w):
    """Gradients of w . (J, psi) at each row of Z (one reverse pass per row, vmapped)."""
    return jax.vmap(lambda z: jax.vjp(sh.values, z)[1](w)[0])(Z)


@compiled(quick=True)
def _control_cost_hessian(ocp, param, z):
    """Hessian of int L(t, x0, u(t; z)) dt by composite Gauss-Legendre quadrature: the
    exact Hessian of the cost when L depends on u only (int |u|^2 here). The nodes
    scale with the horizon (t = t0 + T s), so a new T does not recompile."""
    xg, wg = np.polynomial.legendre.leggauss(5)
    m = 4 * max(param.n, 8)
    s = np.linspace(0.0, 1.0, m + 1)
    hs = np.diff(s)[:, None]
    ts = param.t0 + param.T * jnp.asarray((s[:-1, None] + 0.5 * hs * (xg + 1.0)).reshape(-1))
    ws = param.T * jnp.asarray((0.5 * hs * wg).reshape(-1))

    def quad(p):
        sig = param.signal(p)
        return ws @ jax.vmap(lambda t: ocp.running_cost(t, ocp.x0, sig(t, ocp.x0)))(ts)

    return jax.hessian(quad)(z)


def _reduced_hessian(sh, z, g, Z, w, h, wait=True):
    """Z^T H Z, H the Hessian of w . (J, psi) at z, by one-sided differences of its
    reverse-mode gradient along the columns of Z (P - m reverse passes, vmapped; ``g``
    the gradient at z, which the iteration already has), or, with ``wait`` False and
    the reverse passes' program not ready, of the same gradient from the forward
    sensitivities' Jacobian (module docstring). Only the reduced Hessian enters the
    null-space step, so the directions of A's rows are not differenced."""
    k = Z.shape[1]
    if k == 0:
        return np.zeros((0, 0))
    zs, w = z[None, :] + h * Z.T, np.asarray(w)
    if wait or _lagrangian_gradients.ready(sh, zs, w):
        G = np.asarray(_lagrangian_gradients(sh, zs, w))
    else:
        # its program is not stored yet (a first solve in a new process): the same
        # gradients from the forward sensitivities' Jacobian at each point, whose program
        # the solver has (k forward solves with P tangents instead of k vmapped reverse
        # passes: slower to run, nothing to trace or compile). The k solves are
        # independent: two at a time (one program does not keep two cores busy)
        def gradient(zj):
            return np.asarray(_values_and_jacobian(sh, zj)[1]).T @ w

        G = np.stack(list(_programs._pool("run", 2).map(gradient, zs)))
    R = (G - g[None, :]) @ Z / h
    return 0.5 * (R + R.T)


def _stationarity(g, A, free=None):
    """(relative stationarity max |g + A^T lam| / max |g| over the ``free`` parameters,
    lam): lam the least-squares multipliers there (all parameters if ``free`` is None)."""
    free = np.ones(g.shape[0], bool) if free is None else free
    m = A.shape[0]
    lam = -np.linalg.lstsq(A[:, free].T, g[free], rcond=None)[0] if free.any() and m else np.zeros(m)
    r = (g + A.T @ lam)[free]
    return float(np.abs(r).max(initial=0.0) / max(np.abs(g).max(), 1e-300)), lam


def _cost_resolution(J, lam, rtol, tol):
    """How finely the line search can compare two restored costs near J: the simulations'
    relative accuracy (``rtol``) of the cost, and the cost's response lam . psi to the
    violation (up to ``tol``) that each restoration leaves. A Newton step that predicts
    a smaller decrease (near the optimum: the stationarity squared) has its trial costs
    ordered by that noise, not by the step (on the spherical robot's steering to
    (0.2, 0.3), relative stationarity 3e-7 at rtol 1e-10, a decrease of 4e-13 against
    restored costs scattered by 2e-12, relative): the Armijo test then refused the full
    step, and the iteration crept on with steps of 1e-3 until ``max_iter``."""
    return rtol * abs(float(J)) + float(np.abs(lam).sum()) * tol


def _restore_broyden(sh, z, y, A, Q, Qi, tol, max_iter=20):
    """Restoration onto psi = 0 by least-change (Q-metric) steps with a secant
    (Broyden) Jacobian: each iteration one forward solve, no reverse pass. A starts as
    the constraints' Jacobian at the point the step left from (the step lies in its
    null space) and after each trial step s, accepted or not, takes the rank-one
    correction A += (dpsi - A s) (Q s)^T / (s^T Q s) that makes it exact along s, so the
    curvature of the constraints across the step is learned instead of recomputed.
    Only steps that lower the violation are taken. Where a step lowers it by less than
    a factor 10 (the secant steps converging linearly, the curvature across the step
    not yet learned), A is replaced by the exact Jacobian at the new point, so that
    the next steps are Newton's: on the spherical robot's steering the secant tails
    took up to 16 forward solves from a violation of 5e-2, against about a Jacobian
    and 5 solves this way. It goes on below ``tol`` while the violation falls (so that
    the restored cost, compared by the line search, carries no first-order trace of a
    leftover violation). Returns (z, y, ok); ok is False when the violation stays
    above ``tol``."""
    v = np.abs(y[1:]).max()
    fails = 0
    for _ in range(max_iter):
        c = y[1:]
        s = -Qi @ A.T @ np.linalg.solve(A @ Qi @ A.T, c)
        y_t = _values(sh, z + s)
        if not np.all(np.isfinite(y_t)):
            break
        v_t = np.abs(y_t[1:]).max()
        Qs = Q @ s
        A = A + np.outer(y_t[1:] - c - A @ s, Qs) / (s @ Qs)
        if v_t < v:
            slow = v_t > 0.1 * v
            z, y, v, fails = z + s, y_t, v_t, 0
            if v <= 1e-3 * tol:
                break
            if slow and v > tol:
                A = np.asarray(_values_and_jacobian(sh, z)[1])[1:]
        else:
            fails += 1
            if fails >= 2 or v <= tol:
                break
    return z, y, bool(v <= tol)


def _restore(sh, z, y, A, Q, Qi, tol, gn_iter, contraction=None):
    """Restoration from z (values y) with A the constraints' Jacobian at a nearby point:
    secant steps first (forward solves only), then, if they stall above ``tol``,
    Gauss-Newton with fresh Jacobians from z itself (started where the secant steps
    stalled instead, it took a longer path on the Chebyshev-12 steering); see
    ``_project`` for ``contraction``. Returns (z, y, D, ok), D the Jacobian of
    (J, psi) at the returned z."""
    z_s, y_s, ok = _restore_broyden(sh, z, y, A, Q, Qi, tol)
    if ok:
        z, y = z_s, y_s
    y, D = (np.asarray(a) for a in _values_and_jacobian(sh, z))
    if np.abs(y[1:]).max() <= tol:
        return z, y, D, True
    return _project(sh, z, y, D, Qi, tol, max_iter=gn_iter, contraction=contraction)


def _project(sh, z, y, D, Qi, tol, max_iter=10, contraction=None):
    """Gauss–Newton projection onto psi = 0 with least Q-norm steps,
    d = -Q^-1 A^T (A Q^-1 A^T + mu I)^-1 psi (mu -> 0: quadratic convergence;
    Levenberg–Marquardt damping when a step does not reduce |psi|_1).
    With ``contraction`` (a factor < 1) there is no damping: the projection gives up as
    soon as a step fails to shrink max |psi| by that factor. A trial point of a line
    search from which Gauss-Newton does not contract is too far from psi = 0 to be
    worth restoring: the shorter step is cheaper than a damped struggle (on the
    steering problems such struggles ran up to 6 iterations and then failed).
    Returns (z, y, D, ok)."""
    m = y.shape[0] - 1
    mu = 0.0
    for _ in range(max_iter):
        c, A = y[1:], D[1:]
        if np.abs(c).max() <= tol:
            return z, y, D, True
        G = A @ Qi @ A.T
        if contraction is not None:
            d = -Qi @ A.T @ np.linalg.solve(G, c)
            y_try = _values(sh, z + d)
            if not (np.all(np.isfinite(y_try)) and np.abs(y_try[1:]).max() <= contraction * np.abs(c).max()):
                return z, y, D, False
        else:
            for _ in range(12):
                d = -Qi @ A.T @ np.linalg.solve(G + mu * np.eye(m), c)
                y_try = _values(sh, z + d)
                if np.all(np.isfinite(y_try)) and np.abs(y_try[1:]).sum() < np.abs(c).sum():
                    break
                mu = max(10.0 * mu, 1e-8 * np.abs(G).max())
            else:
                return z, y, D, False
        z = z + d
        y, D = (np.asarray(a) for a in _values_and_jacobian(sh, z))
        mu *= 0.01
    return z, y, D, bool(np.abs(y[1:]).max() <= tol)


def solve_direct_newton(ocp: OCP, param, guess, *, rtol=1e-10, atol=1e-10, ctol=1e-10, gtol=1e-7,
                        max_iter=60, fd_step=1e-5, loose_tol=1e-6, verbose=False,
                        progress=True) -> DirectResult:
    """The direct single-shooting method, with a feasible-path Newton solver
    (gradient-restoration, Miele's SGRA with second-order tangent steps): an
    alternative to ``controls.solve_direct`` for problems whose constraints are
    strongly curved in the control parameters.

    Why (measured on spherical-robot steering, ``controls.tasks.sphere_steering``):
    there the top's yaw responds to tau_3 with gain ~1/J_33 and turns the
    direction of every later torque, and the vertical angular momentum about the
    contact point, which must return to zero, is changed only by the second-order
    effect -mt (V x v_c) . gamma. The Hessian of the Lagrangian has eigenvalues
    from about -4e2 to 3e4 against 0.5-7 for the cost, so ``solve_direct``'s
    augmented Lagrangian with L-BFGS inner solves needs hundreds of inner steps
    per outer iteration and leaves the constraints far from met after several, and
    an augmented Lagrangian with exact-Hessian Newton inner solves creeps along the
    curved constraint manifold.

    ocp : a ``controls.OCP`` with terminal constraints (m of them); control
        bounds are not supported (use ``solve_direct``).
    param : a parametrization with P > m parameters; guess : (P,) start.
    rtol, atol : tolerances of the simulations; ctol, gtol : stopping tolerances
        (violation, relative stationarity); fd_step : difference step of the
        Hessian; loose_tol : rtol and atol of the simulations in the first iterations
        (None: ``rtol``, ``atol`` throughout); verbose : print one line per iteration; progress : a progress line
        (tqdm.auto) with the iteration, cost, violation, stationarity and step (False: none).

    Each iteration, from a feasible z (psi(z) = 0 to ``ctol``):
    * multipliers lam = argmin |dJ + A^T lam| (A = dpsi/dz, one solve carrying P tangents);
    * the reduced Hessian of the Lagrangian J + lam.psi on the null space of A, by
      one-sided differences of its reverse-mode gradient (P - m reverse passes, vmapped);
    * the Newton step in the null space of A, with the reduced Hessian's negative
      eigenvalues replaced by their magnitudes (saddle-free Newton);
    * restoration back onto psi = 0 (least change in the cost's metric Q, the exact
      Hessian of int |u|^2 dt): secant updates of A (forward solves only; a fresh
      Jacobian where they converge slowly), then Gauss-Newton if needed; the step is
      halved until the restored cost decreases (Armijo), or, where the decrease the step
      predicts is below the restored costs' resolution (near the optimum), until the
      stationarity does.
    The first iterations simulate at rtol = atol = ``loose_tol`` (and restore to
    max(ctol, loose_tol)) until the
    stationarity falls below ``LOOSE_UNTIL`` (1e-3) or a line search fails there;
    from there on, and for the answer and its convergence test, at ``rtol``,
    ``atol`` (``history["rtol"]`` says which, per iteration).
    Converged when max |psi| < ctol and max |dJ + A^T lam| / max |dJ| < gtol.
    Returns a ``controls.DirectResult`` (multipliers lam: dJ + lam . dpsi = 0).
    """
    t_start = time.perf_counter()
    owner = "solve_direct_newton"
    check_ocp(ocp, owner)
    check_parametrization(param, ocp, owner)
    check_tolerances(owner, rtol=rtol, atol=atol, ctol=ctol, gtol=gtol, fd_step=fd_step, loose_tol=loose_tol,
                     max_iter=(max_iter, "int"))
    # z and the iteration's algebra live on the host (numpy): an eager jax operation is a
    # dispatch, and in a new process a program of its own
    if guess is None:
        raise ProblemError(f"solve_direct_newton: guess must be the ({param.size},) starting parameters of the "
                           "parametrization (e.g. np.zeros(param.size), param.fit(u_fn) or a task's loop guess), "
                           "got None")
    z = np.asarray(check_guess("guess", guess, (param.size,), "parametrization"), float)
    m, P = ocp.n_constraints, param.size
    if m == 0:
        raise ProblemError("solve_direct_newton needs terminal constraints; use controls.solve_direct")
    if ocp.u_lower is not None:
        raise ProblemError("solve_direct_newton does not handle control bounds; use controls.solve_direct")
    if m >= P:
        raise ProblemError(f"{P} control parameters cannot meet {m} terminal constraints and still "
                           "optimize: use a finer parametrization")
    sh_final = _Shooting(ocp, param, host_array(rtol), host_array(atol))
    # far from the optimum the iterates need not be exact: the first iterations run the
    # simulations at loose_tol (the same compiled programs: tolerances are arguments)
    loose = loose_tol is not None and (rtol < loose_tol or atol < loose_tol)
    sh = _Shooting(ocp, param, host_array(max(rtol, loose_tol)),
                   host_array(max(atol, loose_tol))) if loose else sh_final
    # the solver's programs are traced here, one after the other, and compiled by
    # XLA in the background, side by side (in a new process most of a first solve)
    _values_and_jacobian.prepare(sh, z)
    _values_jit.prepare(sh, z)
    _control_cost_hessian.prepare(ocp, param, z)
    # the Hessian's program (the largest to trace and compile): when the Jacobian's
    # program can stand in for it (SEQUENTIAL_TANGENTS), only if it is stored; a first
    # solve then takes its Hessians from the Jacobian's program (_reduced_hessian) and
    # leaves this one to a thread of its own when it returns
    hessian_args = (sh, np.zeros((P - m, P)), np.zeros(m + 1))
    wait = (P - m) * P > SEQUENTIAL_TANGENTS
    _lagrangian_gradients.prepare(*hessian_args, trace=wait)
    y, D = (np.asarray(a) for a in _values_and_jacobian(sh, z))
    if not np.all(np.isfinite(y)) or not np.all(np.isfinite(D)):
        raise ProblemError("the cost, the constraints or their derivatives are not finite at the guess")
    Q = np.asarray(_control_cost_hessian(ocp, param, z))
    q_eig = np.linalg.eigvalsh(0.5 * (Q + Q.T))
    if not (np.all(np.isfinite(q_eig)) and q_eig.min() > 1e-10 * max(q_eig.max(), 0.0)):
        Q = np.eye(P)  # the cost is not strictly convex in the controls: restore in the plain metric
        q_eig = np.ones(P)
    Qi = np.linalg.inv(Q)
    floor = 1e-6 * q_eig.max()
    history = {"cost": [], "violation": [], "stationarity": [], "step": [], "rtol": [], "seconds": []}

    def record(stat, alpha):
        for k, v in (("cost", float(y[0])), ("violation", float(np.abs(y[1:]).max())), ("stationarity", stat),
                     ("step", alpha), ("rtol", float(sh.rtol)), ("seconds", time.perf_counter() - t_start)):
            history[k].append(v)
        bar.update(iteration=len(history["cost"]), cost=float(y[0]), violation=f"{history['violation'][-1]:.1e}",
                   stationarity=f"{stat:.1e}", step=f"{alpha:.3g}", rtol=f"{float(sh.rtol):.0e}")
        if verbose:
            print(f"  {len(history['cost']):3d}: cost {y[0]:.13g}  violation {history['violation'][-1]:.2e}  "
                  f"stationarity {stat:.2e}  step {alpha:.3g}  ({history['seconds'][-1]:.1f} s)", flush=True)

    bar = Progress(progress, max_iter, "direct (feasible-path Newton)")
    converged = False
    try:
        z, y, D, ok = _project(sh, z, y, D, Qi, ctol, max_iter=30)
        if not ok and loose:  # the loose simulations may be too rough to restore: go on at the requested ones
            loose, sh = False, sh_final
            y, D = (np.asarray(a) for a in _values_and_jacobian(sh, z))
            z, y, D, ok = _project(sh, z, y, D, Qi, ctol, max_iter=30)
        if not ok:
            raise ProblemError(
                "the terminal constraints could not be met from this guess (Gauss-Newton restoration "
                f"stalled at violation {np.abs(y[1:]).max():.2e}): the target may be unreachable in time T "
                "with this parametrization, or the guess too far")
        converged, msg, it, alpha, stalled = False, "max_iter reached", 0, 0.0, False
        first_step = 1.0  # where the next line search starts
        for it in range(1, max_iter + 1):
            g, A = D[0], D[1:]
            stat, lam = _stationarity(g, A)
            if loose and (stat < LOOSE_UNTIL or stalled):
                loose, sh = False, sh_final
                # the constraints move by about the loose tolerance: restore starting
                # from the loose Jacobian
                z, y, D, ok = _restore(sh, z, _values(sh, z), D[1:], Q, Qi, ctol, gn_iter=10)
                if not ok:
                    msg = "restoration at the requested tolerances failed"
                    break
                g, A = D[0], D[1:]
                stat, lam = _stationarity(g, A)
            record(stat, alpha)
            if not loose and stat < gtol and np.abs(y[1:]).max() < ctol:
                converged, msg = True, "converged: constraints and stationarity within tolerance"
                break
            w = np.concatenate([[1.0], lam])
            _, S, Vt = np.linalg.svd(A)
            Z = Vt[np.sum(S > 1e-12 * S[0]):].T
            ev, V = np.linalg.eigh(_reduced_hessian(sh, z, D.T @ w, Z, w, fd_step, wait))
            gr = Z.T @ (g + A.T @ lam)
            d = -Z @ (V @ ((V.T @ gr) / np.maximum(np.abs(ev), floor)))
            slope = (g + A.T @ lam) @ d
            tol_now = max(ctol, loose_tol) if loose else ctol
            blind = -slope <= _cost_resolution(y[0], lam, float(sh.rtol), tol_now)
            alpha, accepted = first_step, False
            for _ in range(20):
                z_t = z + alpha * d
                y_t = _values(sh, z_t)
                if np.all(np.isfinite(y_t)):
                    # second-order correction with A(z) (the step lies in its null space)
                    # (the loose simulations' constraints are met to about their own
                    # accuracy: restoring further only meets their noise)
                    z_t, y_t, D_t, ok = _restore(sh, z_t, y_t, A, Q, Qi, tol_now, gn_iter=6,
                                                 contraction=CONTRACTION)
                    if ok and y_t[0] <= y[0] + 1e-4 * alpha * slope + 1e-14 * abs(y[0]):
                        accepted = True
                        break
                    # a decrease below the costs' resolution cannot be seen: the step is
                    # judged by the stationarity it leaves instead (_cost_resolution)
                    if ok and blind and _stationarity(D_t[0], D_t[1:])[0] < stat:
                        accepted = True
                        break
                alpha *= 0.5
            if not accepted and loose:
                stalled, first_step = True, 1.0  # go on at the requested tolerances, from a full step
                continue
            if not accepted:
                msg = "line search failed (cost not decreasing along the restored step)"
                if stat < 1e2 * gtol:
                    msg += f"; stationarity {stat:.1e} is near the tolerance, at the noise of the integration"
                break
            z, y, D = z_t, y_t, D_t
            # the next search starts at twice this step (a full step after a full one):
            # after a short step the full one failed again in the next iteration
            first_step = min(1.0, 2.0 * alpha)
    finally:
        bar.finish(converged)
    if not wait:
        _lagrangian_gradients.prepare_later(*hessian_args)  # for the next solve (nothing if it is there)
    z = host_array(z)
    return DirectResult(
        params=z, control=param.signal(z), cost=float(y[0]), violation=float(np.abs(y[1:]).max()),
        multipliers=lam, iterations=it, converged=converged, message=msg, history=history,
        seconds=time.perf_counter() - t_start,
    )
