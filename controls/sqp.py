r"""Direct single shooting by sequential quadratic programming (``solve_direct_sqp``).

The problem over the control parameters z (P of them) of a parametrization:

    minimize J(z)  subject to  psi(z) = 0 (m terminal constraints),  lo <= z <= hi,

with J and psi from one simulation (``controls.rollout``) and their Jacobian from
one forward solve carrying the P parameter tangents (``nhjax.DiscreteAdjoint``'s forward
sensitivities; see ``controls.newton._values_and_jacobian``).
Each iteration solves the quadratic program

    minimize_d  g.d + d.B.d / 2   subject to  psi + A d = 0,  lo - z <= d <= hi - z

(g = dJ/dz, A = dpsi/dz) for the step d and the multipliers, by a primal-dual
interior-point iteration on the host (the QP is small and dense: P is tens), then
an Armijo backtracking search on the l1 merit J + mu |psi|_1 with one second-order
correction against the Maratos effect (Nocedal & Wright, Numerical Optimization,
2nd ed., Algorithms 18.3 and 16.1 / 16.7 and eq. (18.36)). B approximates the
Hessian of the Lagrangian L = J - y.psi by damped BFGS (Powell's damping, N&W
Procedure 18.2), started from the exact Hessian of the running cost's control part
(Gauss-Legendre quadrature at x0: exact for int |u|^2 dt), or the identity.

Box bounds on the parameters (control bounds of a PiecewiseConstant or
PiecewiseLinear parametrization, ``OCP(u_lower=..., u_upper=...)``) are constraints
of the QP, so every iterate stays inside them.

Converged when max |psi| < ctol and either the relative stationarity of the
Lagrangian over the parameters not held at a bound, max |g + A^T lam| / max |g|, is
< gtol (lam the least-squares multipliers there, as in ``solve_direct_newton``) or
the QP's predicted cost change is below ftol relative to the cost.
"""

from __future__ import annotations

import time

import numpy as np

from ._result import DirectResult, check_differentiable
from .newton import _control_cost_hessian, _Shooting, _stationarity, _values_and_jacobian
from .problem import (
    OCP,
    ProblemError,
    Progress,
    check_guess,
    check_ocp,
    check_parametrization,
    check_tolerances,
    host_array,
)

__all__ = ["prepare_direct_sqp", "solve_direct_sqp"]


def _kkt_solve(H, A, r1, r2):
    """[[H, -A^T], [A, 0]] (dx, dy) = (r1, r2) (a least-squares solve if singular)."""
    n, m = H.shape[0], A.shape[0]
    K = np.zeros((n + m, n + m))  # (filled in place: np.block costs more than the solve here)
    K[:n, :n], K[:n, n:], K[n:, :n] = H, -A.T, A
    rhs = np.concatenate([r1, r2])
    try:
        sol = np.linalg.solve(K, rhs)
    except np.linalg.LinAlgError:
        try:
            sol = np.linalg.lstsq(K, rhs, rcond=None)[0]
        except np.linalg.LinAlgError:  # NaN/inf in K (an interior point that diverged: no solution)
            sol = np.full(n + m, np.nan)
    return sol[:n], sol[n:]


def qp_box(B, g, A, b, lo, hi, tol=1e-13, max_iter=80):
    """Solve  min g.d + d.B.d/2  s.t.  A d = b,  lo <= d <= hi  (B symmetric positive
    definite; lo/hi may hold -inf/inf, and lo < hi) by a primal-dual interior-point
    iteration with Mehrotra's predictor-corrector (N&W Algorithm 16.4 on the bounds).

    Returns (d, y, zl, zu): the step, the multipliers of A d = b and of the lower and
    upper bounds (B d + g - A^T y - zl + zu = 0, zl, zu >= 0, complementary)."""
    n = g.shape[0]
    L, U = np.isfinite(lo), np.isfinite(hi)
    if not (L.any() or U.any()):
        d, y = _kkt_solve(B, A, -g, b)
        return d, y, np.zeros(n), np.zeros(n)
    # an interior start: d = 0 pulled inside the box (the current iterate may sit on a bound)
    width = np.where(L & U, hi - lo, np.inf)
    margin = np.minimum(1e-2 * np.maximum(1.0, np.abs(np.where(L, lo, 0)) + np.abs(np.where(U, hi, 0))),
                        0.25 * width)
    d = np.clip(np.zeros(n), np.where(L, lo + margin, -np.inf), np.where(U, hi - margin, np.inf))
    y = np.zeros(b.shape[0])
    zl, zu = np.where(L, 1.0, 0.0), np.where(U, 1.0, 0.0)
    scale = max(1.0, np.abs(g).max(initial=0.0), np.abs(b).max(initial=0.0))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        return _interior_point(B, g, A, b, lo, hi, L, U, d, y, zl, zu, scale, tol, max_iter)


def _interior_point(B, g, A, b, lo, hi, L, U, d, y, zl, zu, scale, tol, max_iter):
    for _ in range(max_iter):
        sl, su = np.where(L, d - lo, 1.0), np.where(U, hi - d, 1.0)
        rd = B @ d + g - A.T @ y - zl + zu
        rp = A @ d - b
        k = L.sum() + U.sum()
        mu = (zl @ np.where(L, sl, 0.0) + zu @ np.where(U, su, 0.0)) / k
        if max(np.abs(rd).max(), np.abs(rp).max(initial=0.0)) <= tol * scale and mu <= tol * scale:
            break
        H = B + np.diag(np.where(L, zl / sl, 0.0) + np.where(U, zu / su, 0.0))

        def direction(sigma_mu, corr_l=0.0, corr_u=0.0):
            # bound rows: zl sl = sigma mu - corr, zu su = sigma mu - corr (Mehrotra's second-order term)
            cl = np.where(L, (sigma_mu - corr_l) / sl - zl, 0.0)
            cu = np.where(U, (sigma_mu - corr_u) / su - zu, 0.0)
            dd, dy = _kkt_solve(H, A, -rd + cl - cu, -rp)
            dzl = np.where(L, (sigma_mu - corr_l - zl * sl - zl * dd) / sl, 0.0)
            dzu = np.where(U, (sigma_mu - corr_u - zu * su + zu * dd) / su, 0.0)
            return dd, dy, dzl, dzu

        def longest(frac, dd, dzl, dzu):
            a_p = a_d = 1.0
            for s, ds in ((sl, dd), (su, -dd)):
                mask = (L if s is sl else U) & (ds < 0)
                if mask.any():
                    a_p = min(a_p, frac * np.min(-s[mask] / ds[mask]))
            for z, dz, M in ((zl, dzl, L), (zu, dzu, U)):
                mask = M & (dz < 0)
                if mask.any():
                    a_d = min(a_d, frac * np.min(-z[mask] / dz[mask]))
            return a_p, a_d

        dd, dy, dzl, dzu = direction(0.0)  # affine scaling (predictor)
        a_p, a_d = longest(1.0, dd, dzl, dzu)
        mu_aff = ((zl + a_d * dzl) @ np.where(L, sl + a_p * dd, 0.0)
                  + (zu + a_d * dzu) @ np.where(U, su - a_p * dd, 0.0)) / k
        sigma = (mu_aff / mu) ** 3 if mu > 0 else 0.0
        dd, dy, dzl, dzu = direction(sigma * mu, np.where(L, dzl * dd, 0.0), np.where(U, -dzu * dd, 0.0))
        a_p, a_d = longest(0.995, dd, dzl, dzu)
        d, y, zl, zu = d + a_p * dd, y + a_d * dy, zl + a_d * dzl, zu + a_d * dzu
    return d, y, zl, zu


def _check_sqp(ocp, param, owner, rtol, atol):
    check_ocp(ocp, owner)
    check_parametrization(param, ocp, owner)
    check_tolerances(owner, rtol=rtol, atol=atol)
    if ocp.n_constraints >= param.size:
        raise ProblemError(f"{param.size} control parameters cannot meet {ocp.n_constraints} terminal "
                           "constraints and still optimize: use a finer parametrization")


def _prepare(sh, z):
    """Both of the SQP's programs: traced now, compiled (or loaded) in the background."""
    started = _values_and_jacobian.prepare(sh, z)
    return _control_cost_hessian.prepare(sh.ocp, sh.param, z) or started


def prepare_direct_sqp(ocp: OCP, param, *, rtol=1e-10, atol=1e-10) -> bool:
    """Trace the programs of ``solve_direct_sqp`` (``solve_direct``'s default for single
    shooting) for this problem and parametrization now, and compile them in the
    background (or load them from nhjax's program cache there), for a caller that
    solves later and has other work first (tracing or preparing other programs: see
    ``prepare_pontryagin``). Returns whether background work started (not if the
    programs are in memory already)."""
    _check_sqp(ocp, param, "prepare_direct_sqp", rtol, atol)
    return _prepare(_Shooting(ocp, param, host_array(rtol), host_array(atol)), np.zeros(param.size))


def solve_direct_sqp(ocp: OCP, param, guess=None, *, rtol=1e-10, atol=1e-10, ctol=1e-8, gtol=1e-9,
                     ftol=1e-12, max_iter=100, progress=True) -> DirectResult:
    """Solve ``ocp`` over the parameters of ``param`` by SQP (see the module docstring):
    the second-order direct method, with control bounds.

    ocp : a ``controls.OCP``; its control bounds (u_lower, u_upper) become bounds on
        the parameters (``param.param_bounds``: PiecewiseConstant, PiecewiseLinear).
    param : a parametrization with P > m parameters; guess : (P,) start (default
        zeros; clipped into the bounds).
    rtol, atol : tolerances of the simulations; ctol : max |psi| [the constraints'
        units], needed to converge, with either the relative stationarity below gtol or
        the QP's predicted cost decrease below ftol relative to the cost (where the
        integration's noise keeps the stationarity from falling further); max_iter :
        SQP iterations.
    progress : a progress line (tqdm.auto) with the iteration, cost, violation,
        stationarity and step (False: none).

    Each iteration: one simulation with the Jacobian of (J, psi) (1 + m reverse
    passes, vmapped), a small dense QP on the host, and the line search's
    simulations. Returns a ``controls.DirectResult`` (multipliers lam:
    dJ + lam . dpsi = 0 over the parameters not held at a bound).
    """
    t_start = time.perf_counter()
    owner = "solve_direct_sqp"
    _check_sqp(ocp, param, owner, rtol, atol)
    check_tolerances(owner, ctol=ctol, gtol=gtol, ftol=ftol, max_iter=(max_iter, "int"))
    P = param.size
    # host (numpy) iterates: an eager jax operation is a program of its own in a new process
    z = np.zeros(P) if guess is None else np.asarray(check_guess("guess", guess, (P,), "parametrization"), float)
    lo, hi = parameter_bounds(ocp, param)
    z = np.clip(z, lo, hi)
    sh = _Shooting(ocp, param, host_array(rtol), host_array(atol))
    _prepare(sh, z)  # the Hessian's program compiles beside the Jacobian's
    hessian = np.asarray(_control_cost_hessian(ocp, param, z))
    bar = Progress(progress, max_iter, "direct (SQP)")

    def report(it, cost, viol, stat, alpha):
        bar.update(iteration=it, cost=cost, violation=f"{viol:.1e}", stationarity=f"{stat:.1e}", step=f"{alpha:.3g}")

    iteration = sqp_iteration(z, lo, hi, hessian, ctol, gtol, ftol, max_iter, t_start, report)
    converged = False
    try:
        z_request = next(iteration)
        while True:
            y, D = (np.asarray(a) for a in _values_and_jacobian(sh, z_request))
            z_request = iteration.send((y, D))
    except StopIteration as stop:
        z, y, lam, it, converged, msg, history = stop.value
    finally:
        bar.finish(converged)
    zj = host_array(z)
    return DirectResult(
        params=zj, control=param.signal(zj), cost=float(y[0]), violation=float(np.abs(y[1:]).max(initial=0.0)),
        multipliers=lam, iterations=it, converged=converged, message=msg, history=history,
        seconds=time.perf_counter() - t_start,
    )


def parameter_bounds(ocp: OCP, param):
    """(lo, hi): the box on the P parameters from the problem's control bounds
    (``param.param_bounds``), or -inf/inf without bounds."""
    if ocp.u_lower is None:
        return np.full(param.size, -np.inf), np.full(param.size, np.inf)
    return tuple(np.asarray(a, float) for a in param.param_bounds(ocp.u_lower, ocp.u_upper))


def _no_qp_step_message(A, lo, hi, z):
    """Why the QP has no step: its linearized terminal constraints A d = -psi cannot be
    met, within the control bounds if there are any; without bounds only when the rows
    of A are dependent (a rank below m), e.g. at a guess where some constraints do not
    move at first order (zero inputs: where every input's effect on the turn passes
    through the shape's motion)."""
    bounded = bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))
    m = A.shape[0]
    sv = np.linalg.svd(A, compute_uv=False) if m else np.zeros(0)
    rank = int(np.sum(sv > 1e-10 * max(sv.max(initial=0.0), 1e-300)))
    if bounded:
        at = int(np.sum((z <= lo) | (z >= hi)))
        return ("the linearized terminal constraints cannot be met within the control bounds (the QP has no "
                f"solution; {at} of {z.shape[0]} parameters at a bound, constraint Jacobian of rank {rank} of "
                f"{m}): the target may be unreachable within the bounds or the horizon")
    return (f"the linearized terminal constraints are inconsistent at this point: their Jacobian has rank {rank} "
            f"of {m} (the QP has no solution; there are no control bounds), so some constraints do not move at "
            "first order here, as at a guess of zero inputs when the constraints move only through the motion: "
            "start from a guess that moves the system (e.g. param.fit of a plain motion)")


def sqp_iteration(z, lo, hi, hessian, ctol, gtol, ftol, max_iter, t_start, report=None):
    """The SQP iteration of ``solve_direct_sqp`` from ``z`` (inside [lo, hi]) as a
    generator: it yields each point where it needs (J, psi) and their Jacobian D (rows
    dJ/dz, dpsi/dz) and is sent back ``(y, D)`` (y = (J, psi)); it returns
    ``(z, y, multipliers, iterations, converged, message, history)``. The caller owns
    the simulations: ``solve_direct_sqp`` runs one at a time, ``solve_direct_batch``
    sends many members' points to one vmapped program. ``hessian``: the running cost's
    control Hessian at z (the first B, when positive definite). ``report(it, cost,
    violation, stationarity, step)`` is called once per iteration.

    Raises ProblemError (before any step) when (J, psi) or D is not usable at z."""
    y, D = yield z
    y, D = np.asarray(y), np.asarray(D)
    if not np.all(np.isfinite(y)):
        raise ProblemError("the cost or the terminal constraints are not finite at the initial guess (the guess "
                           "may drive the state out of its chart, e.g. through a singular configuration)")
    check_differentiable(D)
    P, m = z.shape[0], y.shape[0] - 1
    B = 0.5 * (hessian + hessian.T)
    ev = np.linalg.eigvalsh(B)
    if not (np.all(np.isfinite(ev)) and ev.min() > 1e-8 * max(ev.max(), 0.0)):
        B = np.eye(P) * max(1.0, np.abs(D[0]).max())
    history = {"cost": [], "violation": [], "stationarity": [], "step": [], "seconds": []}
    mu, converged, msg, alpha, lam, it = 0.0, False, "max_iter reached", 0.0, np.zeros(m), 0

    def evaluate(z):
        y, D = yield z
        y, D = np.asarray(y), np.asarray(D)
        return (y, D) if np.all(np.isfinite(y)) and np.all(np.isfinite(D)) else (None, None)

    for it in range(max_iter + 1):
        g, A, c = D[0], D[1:], y[1:]
        d, yq, zl, zu = qp_box(B, g, A, -c, lo - z, hi - z)
        if not (np.all(np.isfinite(d)) and np.all(np.isfinite(yq))) or (
                m and np.abs(A @ d + c).max() > 1e-8 * max(1.0, np.abs(c).max())):
            msg = _no_qp_step_message(A, lo, hi, z)
            break
        # parameters the QP holds at a bound (active, with a positive multiplier)
        at_bound = ((z + d - lo <= 1e-9 * np.maximum(1.0, np.abs(lo))) & (zl > 1e-10)) | (
            (hi - z - d <= 1e-9 * np.maximum(1.0, np.abs(hi))) & (zu > 1e-10))
        stat, lam = _stationarity(g, A, ~at_bound)
        viol = float(np.abs(c).max(initial=0.0))
        for k, v in (("cost", float(y[0])), ("violation", viol), ("stationarity", stat), ("step", alpha),
                     ("seconds", time.perf_counter() - t_start)):
            history[k].append(v)
        if report is not None:
            report(it, float(y[0]), viol, stat, alpha)
        dBd = max(d @ B @ d, 0.0)
        predicted = abs(g @ d + 0.5 * dBd)  # the QP's cost change
        if viol < ctol and (stat < gtol or predicted <= ftol * max(1.0, abs(float(y[0])))):
            converged, msg = True, "converged: constraints and stationarity within tolerance"
            break
        if it == max_iter:
            break
        # l1 merit J + mu |psi|_1, mu large enough for d to be a descent direction (N&W
        # (18.36)) and above the multipliers' size. Set afresh each iteration, not kept
        # as the largest so far: a penalty fixed by large multipliers far from the
        # optimum (|y| ~ 20 on a free-winding start, ~0.1 later) held the steps to
        # 1/64 for 40 iterations; two starts failed with it
        c1 = np.abs(c).sum()
        if c1 > 0:
            mu = max((g @ d + 0.5 * dBd) / (0.5 * c1), 1.1 * np.abs(yq).max(initial=0.0))
        merit = y[0] + mu * c1
        slope = g @ d - mu * c1

        def sufficient(y_t, alpha):  # Armijo on the merit
            return y_t is not None and y_t[0] + mu * np.abs(y_t[1:]).sum() <= \
                merit + 1e-4 * alpha * min(slope, 0.0) + 1e-14 * abs(merit)

        alpha, accepted = 1.0, False
        for trial in range(30):
            z_t = np.clip(z + alpha * d, lo, hi)
            y_t, D_t = yield from evaluate(z_t)
            if sufficient(y_t, alpha):
                accepted = True
                break
            if trial == 0 and y_t is not None:
                # second-order correction: the least-norm step back onto psi's linearization
                corr = -A.T @ np.linalg.lstsq(A @ A.T, y_t[1:], rcond=None)[0] if m else 0.0
                z_s = np.clip(z + d + corr, lo, hi)
                y_s, D_s = yield from evaluate(z_s)
                if sufficient(y_s, 1.0):
                    z_t, y_t, D_t, accepted = z_s, y_s, D_s, True
                    break
            alpha *= 0.5
        if not accepted:
            msg = "line search failed (the merit does not decrease along the SQP step)"
            if stat < 1e2 * gtol and viol < ctol:
                msg += f"; stationarity {stat:.1e} is near the tolerance, at the noise of the integration"
            break
        # damped BFGS on the Lagrangian J - yq . psi (N&W Procedure 18.2)
        s = z_t - z
        r = (D_t[0] - D_t[1:].T @ yq) - (g - A.T @ yq)
        Bs = B @ s
        sBs, sr = s @ Bs, s @ r
        if sBs > 0:
            theta = 1.0 if sr >= 0.2 * sBs else 0.8 * sBs / (sBs - sr)
            r = theta * r + (1 - theta) * Bs
            B = B - np.outer(Bs, Bs) / sBs + np.outer(r, r) / (s @ r)
            B = 0.5 * (B + B.T)
        z, y, D = z_t, y_t, D_t
    return z, y, lam, it, converged, msg, history
