"""Direct methods: optimize control parameters through differentiable simulations.

Single shooting: the parameters p of a control parametrization define u(t);
one simulate() gives the cost J(p) and the terminal residual psi(p), and jax
gives their gradients (nhjax.DiscreteAdjoint, the discrete adjoint of the
Runge-Kutta steps).

Multiple shooting: the horizon is cut into S segments; the unknowns are the
control parameters and the states at the segment starts; segments are solved
in parallel (vmap), and continuity defects join the terminal constraints.

Constraints are handled by an augmented Lagrangian (Hestenes–Powell):

    minimize_p  J(p) + lam . c(p) + rho/2 |c(p)|^2,   then  lam <- lam + rho c,

with rho increased when the violation does not fall fast enough. The inner
problems run L-BFGS (optax's direction, a projected Armijo backtracking search on
the compiled merit and gradient) by default, or Adam, or any optax
transformation, with box bounds by projection. Convergence needs both
the constraint violation below ``ctol`` and the relative cost change below
``ftol``; ``history`` records every inner step.

Everything compiled here is a module-level function of the problem's pytree,
so solving the same problem again with other numbers (a new target, a new
guess, a new horizon T, new weights held in cost modules, the next continuation
step) reuses the compiled code: one program for the merit, its gradient and the
(cost, constraints) beside it, and one for the L-BFGS direction.
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

import nhjax

from .problem import (
    CostAugmented,
    OCP,
    ProblemError,
    Progress,
    _OnState,
    check_guess,
    check_ocp,
    check_parametrization,
    check_tolerances,
    compiled,
    host_array,
    rollout,
)
from ._result import DirectResult, check_differentiable
from .sqp import solve_direct_sqp

__all__ = ["DirectResult", "solve_direct"]


class _Transcription(eqx.Module):
    """The problem, its parametrization and the solve settings, as one pytree."""

    ocp: OCP
    param: object
    rtol: jax.Array
    atol: jax.Array
    segments: int = eqx.field(static=True)

    @property
    def n_ctrl(self):
        return self.param.size

    def pieces(self, z):
        """(cost, constraints) at the decision vector z."""
        if self.segments == 1:
            # A trial control that drives the state out of its chart (a guard) gets an
            # infinite cost: line searches back off instead of the solve failing.
            traj, J, psi = rollout(self.ocp, self.param.signal(z), rtol=self.rtol, atol=self.atol,
                                   on_guard="stop")
            return jnp.where(traj.t_final < self.ocp.T, jnp.inf, J), psi
        ocp, S = self.ocp, self.segments
        n = ocp.x0.shape[0]
        control = self.param.signal(z[: self.n_ctrl])
        nodes = jnp.concatenate([ocp.x0[None], z[self.n_ctrl:].reshape(S - 1, n)])
        edges = jnp.linspace(0.0, ocp.T, S + 1)
        aug = CostAugmented(ocp.system, ocp.running_cost)

        def seg(xs, ta, tb):
            tr = nhjax.simulate(aug, (xs, jnp.zeros(())), tb, t0=ta, control=_OnState(control),
                                rtol=self.rtol, atol=self.atol, saveat=2, track_work=False,
                                on_guard="stop", diagnostics=False, adjoint=nhjax.DiscreteAdjoint())
            return tr.xs[0][-1], jnp.where(tr.t_final < tb, jnp.inf, tr.xs[1][-1])

        ends, costs = jax.vmap(seg)(nodes, edges[:-1], edges[1:])
        phi, psi = ocp.terminal(ends[-1])
        return phi + jnp.sum(costs), jnp.concatenate([psi, (ends[:-1] - nodes[1:]).reshape(-1)])

    def merit(self, z, lam, rho):
        J, c = self.pieces(z)
        return J + lam @ c + 0.5 * rho * c @ c, (J, c)


@compiled
def _merit_and_grad(tr, z, lam, rho):
    """The augmented-Lagrangian merit, its gradient and the (cost, constraints) it is
    made of: the one compiled reverse pass of a solve (lam and rho are arrays, so new
    multipliers do not recompile; the pieces come with it, so no second program is
    compiled for them)."""
    (value, pieces), grad = jax.value_and_grad(tr.merit, has_aux=True)(z, lam, rho)
    return value, grad, pieces


def _pieces(tr, z):
    """(cost, constraints) at z, from the one compiled program."""
    m = tr.ocp.n_constraints + (tr.segments - 1) * (tr.ocp.x0.shape[0] if tr.segments > 1 else 0)
    return _merit_and_grad(tr, z, np.zeros(m), np.asarray(0.0))[2]


@compiled
def _direction(opt, grad, state, z):
    return opt.update(grad, state, z)


@compiled
def _init(opt, z):
    """An optax transformation's initial state (one program instead of an eager
    operation per array of the state)."""
    return opt.init(z)


_LBFGS = optax.scale_by_lbfgs()
_ADAM = optax.adam(1e-2)


def _lbfgs_inner(tr, z, lam, rho, lo, hi, value, grad, max_inner, ftol, gtol, history, outer, bar=None):
    """L-BFGS (optax's two-loop direction) with a projected backtracking Armijo search.

    The line search runs in Python on the compiled merit-and-gradient, so only one
    reverse pass is ever compiled (optax.lbfgs's zoom search traces the solve again
    inside its own loop, which costs several times the compile time). A step whose
    curvature s.y is not positive resets the memory, keeping the direction a descent
    direction; a trial that stops on a guard (infinite merit) is backtracked.

    The vectors the search works on are numpy arrays on the host: each jax operation
    outside a compiled program is a dispatch (and, in a new process, a program to
    compile or load) of its own, for a few multiply-adds."""
    z, grad, lo, hi = (np.asarray(a) for a in (z, grad, lo, hi))
    state = _init(_LBFGS, z)
    for _ in range(max_inner):
        d, new_state = _direction(_LBFGS, grad, state, z)
        d = np.asarray(d)
        slope = float(grad @ d)
        if not slope > 0:  # not a descent direction: restart from the gradient
            state = _init(_LBFGS, z)
            d, new_state = _direction(_LBFGS, grad, state, z)
            d = np.asarray(d)
            slope = float(grad @ d)
        eta, accepted = 1.0, False
        for _ in range(40):
            z_new = np.clip(z - eta * d, lo, hi)
            v_new, g_new, _ = _merit_and_grad(tr, z_new, lam, rho)
            v_new = float(v_new)
            if np.isfinite(v_new) and v_new <= value - 1e-4 * float(grad @ (z - z_new)):
                accepted = True
                break
            eta *= 0.3 if not np.isfinite(v_new) else 0.5
        if not accepted:
            break
        g_new = np.asarray(g_new)
        s_k, y_k = z_new - z, g_new - grad
        state = new_state if float(s_k @ y_k) > 0 else _init(_LBFGS, z_new)
        prev, z, value, grad = value, z_new, v_new, g_new
        gnorm = float(np.linalg.norm(grad))
        history["merit"].append(value)
        history["grad_norm"].append(gnorm)
        history["outer"].append(outer)
        if bar is not None:
            bar.inner(value, gnorm, eta)
        if gnorm < gtol or abs(prev - value) <= 1e-2 * ftol * max(1.0, abs(value)):
            break
    return z


@compiled
def _first_order_step(tr, opt, z, state, lam, rho, lo, hi):
    (value, _), grad = jax.value_and_grad(tr.merit, has_aux=True)(z, lam, rho)
    updates, state = opt.update(grad, state, z)
    return jnp.clip(optax.apply_updates(z, updates), lo, hi), state, value, jnp.linalg.norm(grad)


def _first_order_inner(tr, opt, z, lam, rho, lo, hi, max_inner, ftol, gtol, history, outer, bar=None):
    state, prev = _init(opt, z), np.inf
    for _ in range(max_inner):
        z, state, val, gnorm = _first_order_step(tr, opt, z, state, lam, rho, lo, hi)
        val, gnorm = float(val), float(gnorm)
        history["merit"].append(val)
        history["grad_norm"].append(gnorm)
        history["outer"].append(outer)
        if bar is not None:
            bar.inner(val, gnorm, None)
        if gnorm < gtol or abs(prev - val) <= 1e-2 * ftol * max(1.0, abs(val)):
            break
        prev = val
    return np.asarray(z)


def solve_direct(
    ocp: OCP,
    param,
    guess=None,
    *,
    shooting: str = "single",
    segments: int = 8,
    optimizer: str | optax.GradientTransformation = "auto",
    rtol: float = 1e-10,
    atol: float = 1e-10,
    ctol: float = 1e-8,
    ftol: float = 1e-10,
    gtol: float = 1e-9,
    max_outer: int = 30,
    max_inner: int = 300,
    rho: float = 10.0,
    progress: bool = True,
) -> DirectResult:
    """Solve ``ocp`` over the parameters of ``param`` (a controls.parametrize object).

    guess : initial control parameters (default zeros); for multiple shooting the
        node states start on the simulated guess.
    optimizer : "auto" (default: "sqp" for single shooting, "lbfgs" for multiple),
        "sqp" (``controls.solve_direct_sqp``: SQP with damped-BFGS Hessians and the
        exact constraint Jacobian, control bounds in its QP; single shooting; at most
        ``max_inner`` iterations; ``max_outer`` and ``rho`` do not apply), "lbfgs"
        (augmented Lagrangian with L-BFGS inner solves), "adam", or an optax
        transformation (reuse one object across calls: a new object compiles anew).
    rtol, atol : tolerances of the simulations; ctol : constraint violation and ftol :
        relative cost change over an outer iteration, both needed to converge; gtol :
        gradient norm that ends an inner solve; rho : initial penalty.
    progress : a progress line (tqdm.auto) over the outer iterations with the inner
        step, merit, gradient norm, cost and violation; False: none; a string: the
        line's label.

    The problem's numbers (x0, T, targets and weights held in modules, the guess,
    the tolerances) are arguments of the compiled programs: a second solve of the
    same structure with other values compiles nothing. Returns a ``DirectResult``.
    """
    owner = "solve_direct"
    check_ocp(ocp, owner)
    check_parametrization(param, ocp, owner)
    if shooting not in ("single", "multiple"):
        raise ProblemError("shooting must be 'single' or 'multiple'")
    if shooting == "multiple" and (not hasattr(ocp.x0, "shape") or ocp.x0.ndim != 1):
        raise ProblemError("multiple shooting needs a vector state")
    check_tolerances(owner, rtol=rtol, atol=atol, ctol=ctol, ftol=ftol, gtol=gtol, rho=rho,
                     max_outer=(max_outer, "int"), max_inner=(max_inner, "int"),
                     segments=(segments, "int", 2 if shooting == "multiple" else 1))
    if isinstance(optimizer, str) and optimizer == "auto":
        optimizer = "sqp" if shooting == "single" else "lbfgs"
    if isinstance(optimizer, str) and optimizer == "sqp":
        if shooting != "single":
            raise ProblemError("optimizer='sqp' is single shooting; use 'lbfgs' with shooting='multiple'")
        return solve_direct_sqp(ocp, param, guess, rtol=rtol, atol=atol, ctol=ctol, gtol=gtol, ftol=ftol,
                                max_iter=max_inner, progress=progress)
    t_start = time.perf_counter()
    # the decision vector and the optimizer's bookkeeping live on the host (numpy): an
    # eager jax operation costs a dispatch, and in a new process a program of its own
    p0 = np.zeros(param.size) if guess is None else np.asarray(
        check_guess("guess", guess, (param.size,), "parametrization"), float)
    S = segments if shooting == "multiple" else 1
    tr = _Transcription(ocp, param, host_array(rtol), host_array(atol), S)
    z = p0
    if S > 1:
        traj, _, _ = rollout(ocp, param.signal(p0), rtol=rtol, atol=atol, saveat=S + 1)
        z = np.concatenate([p0, np.asarray(traj.xs[0])[1:-1].reshape(-1)])
    lo, hi = np.full(z.shape, -np.inf), np.full(z.shape, np.inf)
    if ocp.u_lower is not None:
        plo, phi = param.param_bounds(ocp.u_lower, ocp.u_upper)
        lo[: param.size], hi[: param.size] = plo, phi
        z = np.clip(z, lo, hi)

    J0, c0 = (np.asarray(a) for a in _pieces(tr, z))
    for name, val in (("cost", J0), ("terminal constraints", c0)):
        if not np.all(np.isfinite(val)):
            raise ProblemError(
                f"the {name} is not finite at the initial guess (the guess may drive the "
                "state out of its chart, e.g. through a singular configuration)"
            )
    m = c0.shape[0]
    # gradient of J + w.c + |c|^2/2 for random weights w: finite and not zero unless the
    # cost and constraints are non-differentiable or do not depend on the parameters
    w = np.random.default_rng(0).uniform(0.5, 1.5, m)
    check_differentiable(np.asarray(_merit_and_grad(tr, z, w, np.asarray(1.0))[1]))
    lam = np.zeros(m)
    if isinstance(optimizer, str):
        if optimizer not in ("lbfgs", "adam"):
            raise ProblemError("optimizer must be 'auto', 'sqp', 'lbfgs', 'adam' or an optax transformation")
        opt = _ADAM if optimizer == "adam" else None
    else:
        opt = optimizer

    history = {"outer": [], "cost": [], "violation": [], "merit": [], "grad_norm": []}
    bar = Progress(progress, max_outer, "direct (augmented Lagrangian)")
    J_prev, viol_prev, converged, msg = np.inf, np.inf, False, "max_outer reached"
    J, viol = float(J0), float(np.max(np.abs(c0))) if m else 0.0
    try:
        for outer in range(1, max_outer + 1):
            rho_a = np.asarray(rho, float)  # arrays: new values do not recompile
            if opt is None:
                value, grad, _ = _merit_and_grad(tr, z, lam, rho_a)
                z = _lbfgs_inner(tr, z, lam, rho_a, lo, hi, float(value), grad, max_inner, ftol, gtol,
                                 history, outer, bar)
            else:
                z = _first_order_inner(tr, opt, z, lam, rho_a, lo, hi, max_inner, ftol, gtol, history, outer,
                                       bar)
            Jc, c = (np.asarray(a) for a in _pieces(tr, z))
            J, viol = float(Jc), float(np.max(np.abs(c))) if m else 0.0
            history["cost"].append(J)
            history["violation"].append(viol)
            bar.update(outer=outer, steps=len(history["merit"]), cost=J, violation=f"{viol:.1e}",
                       rho=f"{rho:.0e}")
            if not np.isfinite(J):
                raise ProblemError("the cost became non-finite during the optimization")
            if viol < ctol and abs(J - J_prev) <= ftol * max(1.0, abs(J)):
                converged, msg = True, "converged: constraints and cost change within tolerance"
                break
            if m:
                lam = lam + rho * c
                if viol > 0.25 * viol_prev:
                    rho *= 10.0
            J_prev, viol_prev = J, viol
    finally:
        bar.finish(converged)
    if not converged and m and min(history["violation"]) > 1e3 * ctol:
        msg = (
            "the terminal constraints could not be met (violation stays at "
            f"{min(history['violation']):.2e}): the target may be unreachable within the "
            "control bounds or the horizon"
        )
    p = jnp.asarray(z[: param.size])
    nodes = jnp.asarray(z[param.size:].reshape(S - 1, -1)) if S > 1 else None
    return DirectResult(
        params=p, control=param.signal(p), cost=J, violation=viol, multipliers=np.asarray(lam),
        iterations=len(history["merit"]), converged=converged, message=msg, history=history,
        seconds=time.perf_counter() - t_start, node_states=nodes,
    )
