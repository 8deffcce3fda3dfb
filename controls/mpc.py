r"""Closed-loop model-predictive control (MPC) of nhjax systems.

A controller ``MPC`` re-plans at every control period from the measured state:

    minimize    sum_k J_k(s_k, u_k) + Phi(s_N)
    subject to  s_0 = y (the measurement),  s_{k+1} = F_k(s_k, u_k)  (k = 0 .. N-1),
                psi(s_N) = 0 (terminal constraints, when kept hard),
                u_lower <= u_k <= u_upper,

over the horizon ``ocp.T`` split into N intervals of length h = T / N, with the
input piecewise constant (u_k on interval k) and F_k the classical fourth-order
Runge–Kutta map of the controller's model over interval k (``substeps`` steps of
h / substeps; the running cost L(t, x, u) is integrated alongside as an extra
state, so J_k is RK4's quadrature of int L dt over the interval). The first
``period / h`` inputs of the plan are applied; the next period starts from the
plan shifted by that many intervals (the tail extended by the last input).

Linearized as direct multiple shooting (Bock & Plitt 1984), with the states s_k
steps beside the inputs'. One SQP iteration linearizes the N interval maps at once
(``jax.jacfwd`` of the RK4 map, ``vmap`` over intervals: no Python loop over
intervals),

    ds_0 = y - s_0,   ds_{k+1} = A_k ds_k + B_k du_k + c_k,   c_k = F_k - s_{k+1},

and solves the quadratic program in the Nm input steps (the state steps eliminated,
ds_k = G_k du + e_k: condensing)

    minimize  g.du + du.H.du / 2   s.t.  C_psi ds_N = -psi,  lo <= du <= hi

by a primal-dual interior-point method with Mehrotra's predictor-corrector
(Nocedal & Wright, Numerical Optimization, 2nd ed., Algorithm 16.4), its Newton
systems either dense (``qp="dense"``: H formed by one ``lax.scan``, ``box_qp``) or
stage-wise by the Riccati recursion on the multiple-shooting form, without forming H
(``qp="riccati"``, ``controls._qp.stage_qp``; Rao, Wright & Rawlings 1998).
The Hessian model H is, per interval, the second derivative of the running cost
at the interval's start (Gauss–Newton: h d^2 L / d(x, u)^2; ``hessian=
"gauss-newton"``) or of the interval's Lagrangian J_k + lambda_{k+1} . F_k
(``hessian="exact"``, lambda from the QP by the adjoint recursion
lambda_k = dJ_k/ds + A_k^T lambda_{k+1}), each block's eigenvalues floored at
``regularization`` (the QP then has a unique solution). The fixed point of the
iteration is the KKT point of the discrete problem whatever the Hessian model:
the model changes the rate, not the answer.

Every iterate is feasible for the shooting equations: the plan's inputs are rolled
out from the measurement before the first step, and after each step the states are
the rollout of the new inputs (the step's state part is replaced by the
simulation), so c_k = 0 and ds_0 = 0 at each linearization. The Jacobians and the
QP are those of multiple shooting, the globalization that of single shooting: an
l1 merit over multiple-shooting defects stalled the spherical robot's tracking
problem, whose full steps were good ones in single-shooting terms. A QP step is
finished by one equality-constrained KKT solve on the interior point's active set
(``box_qp``), so that converged iterates sit exactly on their active bounds.

Modes:

* ``mode="converged"``: SQP iterations with a backtracking line search on the
  l1 merit J + mu |psi|_1 of the rolled-out inputs (N&W Algorithm 18.3, mu 1.5 times
  the largest terminal multiplier) until the input step is below ``tol``
  (relative) and the terminal constraints below ``tol``, at most ``max_iter``
  iterations;
* ``mode="rti"``: the real-time iteration (Diehl, Bock & Schlöder 2005): one full
  SQP step per period from the shifted plan. Bounded work: one linearization,
  one QP of at most ``qp_iter`` interior-point iterations.

Terminal conditions (``terminal``): ``"constraint"`` keeps the OCP's
``terminal_constraints`` as equalities of every horizon problem; ``"penalty"``
replaces them by the cost ``terminal_weight |psi(s_N)|^2`` (always feasible);
``terminal_cost`` is used as given in either case.

Horizons (``horizon``): ``"receding"`` (a window of length T moving with the
time); ``"shrinking"``: the horizon ends at the fixed time t0 + T and shrinks
each period (the intervals already past are given zero length), the choice for a
task that ends at a given time (a landing); then, without disturbances and with
the plant equal to the model, the closed loop reproduces the open-loop optimum
(Bellman's principle of optimality for the discrete problem).

Statuses (``MPCStatus``) per period: converged, iterations, the largest
terminal-constraint residual after the step (``violation``), the QP's own
success, the horizon cost, and ``fallback``. A horizon solve *fails* when its
numbers are not finite, its QP does not reach ``qp_tol`` (e.g. a terminal
constraint that the input bounds make unreachable), the line search finds no
decrease, or (``mode="converged"``) it does not converge within ``max_iter``.
A failed solve is never applied: the controller keeps the previous plan,
shifted, and applies its next segment; ``fallback`` says so.

Model errors (``disturbance_gain``): offset-free MPC (Pannocchia & Rawlings 2003)
adds a constant disturbance d to the model's vector field over the horizon and
updates it every period from the measurement's departure from the model's
prediction over the last period (``MPC.step``); without it a model error is
corrected only after it has shown in the measured state.

``closed_loop`` runs the controller against a plant (any nhjax system whose
state has the model's layout, possibly other parameters) as one compiled
``lax.scan`` over periods; ``closed_loop_batch`` vmaps that program over groups of
members (starts, disturbances, plant parameters), the groups one after the other.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from nhjax import _validate as V
from nhjax.integrate.simulate import Trajectory
from nhjax.lie import Euclidean
from nhjax.mechanics import AbstractSystem

from nhjax.errors import NhjaxError

from ._qp import box_qp, stage_qp
from .problem import OCP, ProblemError, batch_workers, compiled, host_array, run_in_shares

__all__ = [
    "MPC",
    "ClosedLoop",
    "MPCError",
    "MPCStatus",
    "Plan",
    "box_qp",
    "closed_loop",
    "closed_loop_batch",
]


class MPCError(ProblemError):
    """An MPC controller or closed loop that cannot be set up as given: a period that
    is not positive or not a whole number of intervals, a horizon shorter than the
    period, a plant whose state or inputs do not match the controller's model, NaN or
    inf in a start, a disturbance or a noise level. Raised before any numerics; it is a
    ``ProblemError`` (and so a ``ValueError``)."""


class _as_mpc_error:
    """Re-raise the validation layer's errors (ParameterError, ...) as MPCError with the
    same words: the entry points here raise one error class."""

    def __enter__(self):
        return self

    def __exit__(self, kind, e, tb):
        if e is not None and isinstance(e, NhjaxError) and not isinstance(e, MPCError) \
                and isinstance(e, (ValueError, TypeError)):
            raise MPCError(str(e)) from e
        return False


as_problem_error = _as_mpc_error


# ------------------------------------------------------------------ records
class MPCStatus(eqx.Module):
    """What a horizon solve did (arrays with a leading period axis in a closed loop).

    converged : the iteration met ``tol`` (in ``"rti"`` mode: the single step did).
    iterations : SQP iterations taken.
    violation : max |psi| (hard terminal constraints) of the plan after the step,
        before the fallback (0 without hard constraints; the shooting equations hold
        by construction).
    qp_ok : every QP reached ``qp_tol``.
    cost : the horizon cost of the plan kept (the model's prediction).
    fallback : the solve failed and the previous plan's next segment was applied.
    solve_ms : wall time of the horizon solve [ms] measured on the host when the loop
        is stepped from Python (``closed_loop(..., timing=True)``); NaN inside one
        compiled program, where no clock can be read."""

    converged: jax.Array
    iterations: jax.Array
    violation: jax.Array
    qp_ok: jax.Array
    cost: jax.Array
    fallback: jax.Array
    solve_ms: jax.Array


class Plan(eqx.Module):
    """The controller's memory between periods: the horizon's states s (N+1, n),
    inputs u (N, m), multipliers lam (N+1, n) of the shooting equations and nu of
    the terminal constraints (for the exact Hessian), and ``valid`` (False until a
    solve succeeded: a fallback from an invalid plan applies its inputs, the guess);
    the disturbance observer's memory (``MPC(disturbance_gain=...)``): the estimate
    ``dist`` (n,) [state units / s], the last measurement ``y_prev`` (n,), the inputs
    applied since ``u_prev`` (p, m), and ``has_prev`` (False before the first period)."""

    s: jax.Array
    u: jax.Array
    lam: jax.Array
    nu: jax.Array
    valid: jax.Array
    dist: jax.Array
    y_prev: jax.Array
    u_prev: jax.Array
    has_prev: jax.Array


class ClosedLoop(eqx.Module):
    """A closed loop's result (one more leading member axis from ``closed_loop_batch``).

    trajectory : ``nhjax.Trajectory`` of the plant at the period boundaries (P + 1
        times): ``ts``, ``xs`` and ``us`` (the input applied from each time on; the
        last row repeats the last input); its ``constraint_drift`` holds the plant's
        constraint residuals over the saved states.
    inputs : (P * p, m) commanded inputs, one per model interval (piecewise constant).
    measurements : (P, n) the states the controller saw (with measurement noise).
    status : ``MPCStatus`` with a leading period axis.
    cost : int L(t, x, u) dt along the plant over the loop (RK4 quadrature on the
        plant's steps), the OCP's running cost with the commanded input.
    """

    trajectory: Trajectory
    inputs: jax.Array
    measurements: jax.Array
    status: MPCStatus
    cost: jax.Array


# ------------------------------------------------------------------ the controller
@jax.custom_batching.sequential_vmap
def _hessian_floor(Q, eps):
    """The symmetric matrix Q with its eigenvalues floored at eps (positive definite).

    Under ``vmap`` the matrices are floored one after the other (``sequential_vmap``: a
    ``lax.map``; nested vmaps nest the maps), never by one batched LAPACK call, which
    can hang two programs running at once (see the note above ``controls._qp._lu_factor``)."""
    w, Vv = jnp.linalg.eigh(0.5 * (Q + Q.T))
    return (Vv * jnp.maximum(w, eps)) @ Vv.T


class MPC(eqx.Module):
    """A receding-horizon (or shrinking-horizon) controller over ``ocp``'s structure;
    see the module docstring for the discretization, the iteration and the statuses.

    ocp : the horizon problem: its system is the controller's model (a vector state:
        ``spaces`` Euclidean, x a flat array), ``ocp.T`` [s] the horizon, its costs,
        terminal constraints and input bounds those of every horizon problem.
        ``running_cost(t, x, u)`` sees absolute time (a moving target is a module
        holding the reference; its arrays are parameters, not recompiled).
    period : control period [s], a whole number p >= 1 of intervals h = T / N.
    intervals : N, intervals of the horizon (piecewise-constant input on each).
    mode : "rti" (one SQP step per period, bounded work) or "converged".
    horizon : "receding" or "shrinking" (the horizon ends at t0 + T).
    substeps : RK4 steps per interval in the model (and the default plant steps per
        interval in ``closed_loop``).
    terminal : "constraint" or "penalty" (default: "constraint" when the OCP has
        terminal constraints).
    terminal_weight : the penalty's weight w in w |psi|^2.
    hessian : "gauss-newton" or "exact".
    max_iter, tol : the converged mode's iteration budget and tolerance (relative step
        and absolute violation).
    qp_iter, qp_tol : the interior-point QP's budget and tolerance.
    qp : how the QP's Newton systems are solved: "dense" (condensed, ``box_qp``: one LU
        of the Nm-dimensional KKT matrix per iteration), "riccati" (stage-wise,
        ``stage_qp``: the Riccati recursion over the N intervals, no condensing), or
        "auto" (default): for one loop (``closed_loop``, ``solve``, ``step``) the one
        with fewer flops per Newton system (``_qp_kind``: the Riccati's O(N (n + m)^3)
        against the LU's O((N m)^3): "riccati" for long horizons of small systems),
        and "riccati" in ``closed_loop_batch``, whose small operations stay inside
        loops that XLA compiles as one function and vectorizes over a group of members,
        where dense LU factorizations are one LAPACK call per member. Both give the
        same step up to rounding.
    regularization : floor of each Hessian block's eigenvalues.
    disturbance_gain : a number or n numbers in [0, 1] (default 0: off). Offset-free
        MPC (Pannocchia & Rawlings, AIChE J. 49, 2003): the model's vector field gets a
        constant additive disturbance d [state units / s], x' = f(t, x, u) + d, over
        the whole horizon; each period the measurement y is compared with the model's
        prediction y_hat from the previous measurement under the inputs applied (with
        the current d) and d_i <- d_i + gain_i (y_i - y_hat_i) / period. Gain 1 on a
        component: the d that explains the last period's prediction error to first
        order. A model error (other masses or inertias than the plant's) is then
        corrected in the prediction instead of only after it has shown in the state.
    """

    ocp: OCP
    period: jax.Array
    intervals: int = eqx.field(static=True)
    steps_per_period: int = eqx.field(static=True)
    mode: str = eqx.field(static=True)
    horizon: str = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    terminal: str = eqx.field(static=True)
    terminal_weight: jax.Array
    hessian: str = eqx.field(static=True)
    max_iter: int = eqx.field(static=True)
    tol: jax.Array
    qp_iter: int = eqx.field(static=True)
    qp_tol: jax.Array
    regularization: jax.Array
    qp: str = eqx.field(static=True)
    disturbance_gain: jax.Array
    observer: bool = eqx.field(static=True)
    dist: jax.Array  # the disturbance used by the model's maps (set per period from Plan.dist)

    def __init__(self, ocp, period, intervals, *, mode="rti", horizon="receding", substeps=1, terminal=None,
                 terminal_weight=1e4, hessian="gauss-newton", max_iter=50, tol=1e-9, qp_iter=60, qp_tol=1e-12,
                 regularization=1e-9, qp="auto", disturbance_gain=0.0):
        owner = "MPC"
        if not isinstance(ocp, OCP):
            raise MPCError(f"{owner}: ocp must be a controls.OCP (the horizon problem), got {type(ocp).__name__}")
        with as_problem_error():
            V.choice("mode", mode, ("rti", "converged"), owner=owner)
            V.choice("horizon", horizon, ("receding", "shrinking"), owner=owner)
            V.choice("hessian", hessian, ("gauss-newton", "exact"), owner=owner)
            V.choice("qp", qp, ("auto", "dense", "riccati"), owner=owner)
            N = V.integer("intervals", intervals, minimum=1, owner=owner)
            substeps = V.integer("substeps", substeps, minimum=1, owner=owner)
            max_iter = V.integer("max_iter", max_iter, minimum=1, owner=owner)
            qp_iter = V.integer("qp_iter", qp_iter, minimum=1, owner=owner)
            for name, v in (("tol", tol), ("qp_tol", qp_tol), ("terminal_weight", terminal_weight),
                            ("regularization", regularization)):
                V.positive(name, v, owner=owner, shape=(), as_float=True)
        _model_checks(ocp.system, ocp.x0, owner)
        try:
            if isinstance(period, (str, bytes, bool)):
                raise TypeError
            period_f = float(period)
        except (TypeError, ValueError):
            raise MPCError(f"{owner}: period must be a number of seconds, got {period!r}") from None
        if not np.isfinite(period_f) or period_f <= 0:
            raise MPCError(f"{owner}: the control period must be positive and finite, got period = {period_f:g} s")
        T = float(ocp.T)
        if T < period_f * (1 - 1e-12):
            raise MPCError(f"{owner}: the horizon ocp.T = {T:g} s is shorter than the period {period_f:g} s: "
                           "a plan must cover at least the segment it applies; lengthen the horizon or shorten "
                           "the period")
        h = T / N
        p = period_f / h
        if abs(p - round(p)) > 1e-9 * max(1.0, p):
            raise MPCError(f"{owner}: the period {period_f:g} s is not a whole number of intervals of "
                           f"h = T / N = {T:g} / {N} = {h:g} s; pick N so that period / h is an integer "
                           f"(e.g. N = {max(1, round(T / period_f))})")
        if terminal is None:
            terminal = "constraint" if ocp.terminal_constraints is not None else "penalty"
        with as_problem_error():
            V.choice("terminal", terminal, ("constraint", "penalty"), owner=owner)
        self.ocp = ocp
        self.period = host_array(period_f)
        self.intervals = N
        self.steps_per_period = int(round(p))
        self.mode, self.horizon, self.substeps, self.terminal = mode, horizon, substeps, terminal
        self.terminal_weight = host_array(terminal_weight)
        self.hessian, self.max_iter, self.qp_iter = hessian, max_iter, qp_iter
        self.tol, self.qp_tol = host_array(tol), host_array(qp_tol)
        self.regularization = host_array(regularization)
        self.qp = qp
        n = int(np.shape(ocp.x0)[0])
        try:
            gain = np.broadcast_to(np.asarray(disturbance_gain, dtype=float), (n,)).copy()
        except (TypeError, ValueError):
            raise MPCError(f"{owner}: disturbance_gain must be a number or {n} numbers in [0, 1] (one per state "
                           f"component), got {disturbance_gain!r}") from None
        if not (np.all(np.isfinite(gain)) and np.all(gain >= 0) and np.all(gain <= 1)):
            raise MPCError(f"{owner}: disturbance_gain must lie in [0, 1] (0: no observer on that component), "
                           f"got {gain.tolist()}")
        self.disturbance_gain = host_array(gain)
        self.observer = bool(np.any(gain > 0))
        self.dist = host_array(np.zeros(n))

    # -------------------------------------------------------------- structure
    @property
    def h(self):
        """Interval length T / N [s]."""
        return self.ocp.T / self.intervals

    @property
    def n_constraints(self) -> int:
        return self.ocp.n_constraints if self.terminal == "constraint" else 0

    def _bounds(self):
        m = self.ocp.system.control_dim
        if self.ocp.u_lower is None:
            return jnp.full(m, -jnp.inf), jnp.full(m, jnp.inf)
        return self.ocp.u_lower, self.ocp.u_upper

    def _qp_kind(self):
        """The QP solver of one loop: ``qp``, or for "auto" the one with fewer flops per
        Newton system: the dense LU of the condensed KKT matrix, ~(2/3) (N m)^3, or the
        Riccati sweep, ~4 N (n + m)^3 (products and inverses of its stage blocks)."""
        if self.qp != "auto":
            return self.qp
        N, n, m = self.intervals, self.ocp.x0.shape[0], self.ocp.system.control_dim
        return "riccati" if 4 * N * (n + m) ** 3 < (2 / 3) * (N * m + self.n_constraints) ** 3 else "dense"

    # -------------------------------------------------------------- model pieces
    def _interval(self, t, h, x, u):
        """RK4 over one interval: (x at its end, int L dt over it)."""
        sysm, L = self.ocp.system, self.ocp.running_cost
        dt = h / self.substeps

        def f(tt, x):
            return sysm.vector_field(tt, x, u) + self.dist, L(tt, x, u)

        J = jnp.zeros(())
        for i in range(self.substeps):
            tt = t + i * dt
            k1x, k1j = f(tt, x)
            k2x, k2j = f(tt + dt / 2, x + dt / 2 * k1x)
            k3x, k3j = f(tt + dt / 2, x + dt / 2 * k2x)
            k4x, k4j = f(tt + dt, x + dt * k3x)
            x = x + dt / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
            J = J + dt / 6 * (k1j + 2 * k2j + 2 * k3j + k4j)
        return x, J

    def _terminal_parts(self, xN):
        """(terminal cost incl. penalty, hard terminal constraints) at s_N."""
        phi, psi = self.ocp.terminal(xN)
        if self.terminal == "penalty":
            return phi + self.terminal_weight * jnp.sum(psi**2), jnp.zeros((0,))
        return phi, psi

    def _grid(self, t_first, active):
        """Start times and lengths of the N intervals."""
        k = jnp.arange(self.intervals)
        return t_first + k * self.h, self.h * active

    def _rollout(self, y, u, ts, hs):
        """The model's RK4 states (N+1, n) from y under u, and the total cost and psi."""
        def body(x, k):
            x1, J = self._interval(ts[k], hs[k], x, u[k])
            return x1, (x1, J)

        _, (xs, Js) = jax.lax.scan(body, y, jnp.arange(self.intervals))
        s = jnp.concatenate([y[None], xs])
        phi, psi = self._terminal_parts(s[-1])
        return s, jnp.sum(Js) + phi, psi

    def _merit(self, y, u, ts, hs, mu):
        """(l1 merit, states, cost, max |psi|) of the inputs u from y."""
        s, cost, psi = self._rollout(y, u, ts, hs)
        return cost + mu * jnp.sum(jnp.abs(psi)), s, cost, jnp.max(jnp.abs(psi), initial=0.0)

    # -------------------------------------------------------------- one SQP step
    def _sqp_step(self, plan, cost_now, ts, hs, lo_box, hi_box, free, y, line_search):
        """One SQP iteration from ``plan`` (its states the rollout of its inputs from y,
        ``cost_now`` their cost): (new plan, qp_ok, accepted, relative input step,
        max |psi|, cost)."""
        s, u, lam, nu = plan.s, plan.u, plan.lam, plan.nu
        N, n = u.shape[0], s.shape[1]
        m = u.shape[1]
        eps = self.regularization

        def flat(t, h, z):
            x1, J = self._interval(t, h, z[:n], z[n:])
            return jnp.concatenate([x1, J[None]]), (x1, J)

        def jac(t, h, x, uu):
            z = jnp.concatenate([x, uu])
            Jm, (x1, J) = jax.jacfwd(flat, argnums=2, has_aux=True)(t, h, z)
            return x1, J, Jm[:n], Jm[n]

        x1, _, AB, q = jax.vmap(jac)(ts, hs, s[:-1], u)
        A, B = AB[:, :, :n], AB[:, :, n:]
        c = x1 - s[1:]
        e0 = y - s[0]

        # Hessian blocks of the interval costs (or Lagrangians)
        if self.hessian == "exact":
            def lag(t, h, z, lam1):
                x1_, J_ = self._interval(t, h, z[:n], z[n:])
                return J_ + lam1 @ x1_

            Q = jax.vmap(jax.hessian(lag, argnums=2))(ts, hs, jnp.concatenate([s[:-1], u], 1), lam[1:])
        else:
            def run(t, h, z):
                return h * self.ocp.running_cost(t, z[:n], z[n:])

            Q = jax.vmap(jax.hessian(run, argnums=2))(ts, hs, jnp.concatenate([s[:-1], u], 1))
        Q = jax.vmap(_hessian_floor, (0, None))(Q, eps)
        Qss, Qsu, Quu = Q[:, :n, :n], Q[:, :n, n:], Q[:, n:, n:]

        phi_fn = lambda x: self._terminal_parts(x)[0]  # noqa: E731
        gphi = jax.grad(phi_fn)(s[-1])
        if self.hessian == "exact" and self.n_constraints:
            P = jax.hessian(lambda x: phi_fn(x) + nu @ self._terminal_parts(x)[1])(s[-1])
        elif self.terminal == "penalty" and self.ocp.terminal_constraints is not None:
            # Gauss-Newton for the penalty w |psi|^2: 2 w C^T C, with the terminal cost's own Hessian
            Cp = jax.jacfwd(lambda x: self.ocp.terminal(x)[1])(s[-1])
            P0 = (jax.hessian(lambda x: self.ocp.terminal(x)[0])(s[-1]) if self.ocp.terminal_cost is not None
                  else jnp.zeros((n, n)))
            P = P0 + 2 * self.terminal_weight * Cp.T @ Cp
        else:
            P = jax.hessian(phi_fn)(s[-1])
        P = _hessian_floor(P, 0.0 * eps)
        psi = self._terminal_parts(s[-1])[1]
        C = jax.jacfwd(lambda x: self._terminal_parts(x)[1])(s[-1]).reshape(psi.shape[0], n)

        lo = jnp.where(free, -jnp.inf, lo_box[None] - u)
        hi = jnp.where(free, jnp.inf, hi_box[None] - u)
        if self._qp_kind() == "riccati":
            # the stage-wise QP, each Newton system by the Riccati recursion (no condensing)
            du_k, ds, yq, qp_ok, _ = stage_qp(Q, q, A, B, c, e0, P, gphi, C, -psi, lo, hi, max_iter=self.qp_iter,
                                              tol=self.qp_tol)
            du = du_k.reshape(-1)
        else:
            # condensing: ds_k = G_k du + e_k, then the dense QP in the Nm input steps
            def cond_step(carry, k):
                G, e = carry
                Gn = (A[k] @ G).reshape(n, N, m).at[:, k, :].add(B[k]).reshape(n, N * m)
                en = A[k] @ e + c[k]
                return (Gn, en), (Gn, en)

            G0 = jnp.zeros((n, N * m))
            _, (Gs, es) = jax.lax.scan(cond_step, (G0, e0), jnp.arange(N))
            G = jnp.concatenate([G0[None], Gs])            # (N+1, n, Nm)
            e = jnp.concatenate([e0[None], es])            # (N+1, n)
            Gk = G[:-1]
            Hss = jnp.einsum("kia,kij,kjb->ab", Gk, Qss, Gk)
            X = jnp.einsum("kia,kij->akj", Gk, Qsu).reshape(N * m, N * m)  # G_k^T Qsu_k into block column k
            Huu = jnp.einsum("kl,kij->kilj", jnp.eye(N), Quu).reshape(N * m, N * m)
            GN = G[-1]
            H = Hss + X + X.T + Huu + GN.T @ P @ GN
            H = 0.5 * (H + H.T)
            gs = q[:, :n] + jnp.einsum("kij,kj->ki", Qss, e[:-1])           # (N, n)
            gu = q[:, n:] + jnp.einsum("kij,ki->kj", Qsu, e[:-1])           # (N, m)
            g = jnp.einsum("kia,ki->a", Gk, gs) + gu.reshape(-1) + GN.T @ (gphi + P @ e[-1])
            Aeq = C @ GN
            beq = -(psi + C @ e[-1])
            du, yq, qp_ok, _ = box_qp(H, g, Aeq, beq, lo.reshape(-1), hi.reshape(-1), max_iter=self.qp_iter,
                                      tol=self.qp_tol)
            du_k = du.reshape(N, m)
            ds = jnp.einsum("kia,a->ki", G, du) + e                          # (N+1, n)

        # multipliers by the adjoint recursion of the QP's stationarity
        nu_new = -yq
        lamN = gphi + P @ ds[-1] + C.T @ nu_new

        def back(lam_next, k):
            lk = q[k, :n] + Qss[k] @ ds[k] + Qsu[k] @ du_k[k] + A[k].T @ lam_next
            return lk, lk

        _, lams = jax.lax.scan(back, lamN, jnp.arange(N), reverse=True)
        lam_new = jnp.concatenate([lams, lamN[None]])

        # step length: backtracking on the l1 merit J + mu |psi|_1 of the rolled-out inputs
        # (converged mode), the full step otherwise; the new states are the rollout
        mu = 1.5 * jnp.max(jnp.abs(nu_new), initial=0.0) + 1e-8
        phi0 = cost_now + mu * jnp.sum(jnp.abs(psi))
        slope = (jnp.sum(q[:, :n] * ds[:-1]) + jnp.sum(q[:, n:] * du_k) + gphi @ ds[-1]
                 - mu * jnp.sum(jnp.abs(psi)))

        def trial(a):
            return self._merit(y, u + a * du_k, ts, hs, mu)

        # a small step whose predicted decrease is at the level of rounding in the merit is
        # taken whole (no decrease can be seen; refusing it would stall a converged iteration)
        tiny = (-slope <= 1e-13 * (1 + jnp.abs(phi0))) & (jnp.max(jnp.abs(du)) <= 1e-6 * (1 + jnp.max(jnp.abs(u))))
        if line_search:
            def ls_cond(carry):
                a, (ph, *_), k = carry
                return ~(ph <= phi0 + 1e-4 * a * jnp.minimum(slope, 0.0)) & (k < 30) & ~tiny

            def ls_body(carry):
                a, _, k = carry
                return a / 2, trial(a / 2), k + 1

            one = jnp.asarray(1.0)
            a, (ph, s1, cost1, viol1), _ = jax.lax.while_loop(ls_cond, ls_body, (one, trial(one), 0))
            accepted = (ph <= phi0 + 1e-4 * a * jnp.minimum(slope, 0.0)) | (tiny & jnp.isfinite(ph))
        else:
            a = 1.0
            ph, s1, cost1, viol1 = trial(1.0)
            accepted = jnp.isfinite(ph)
        new = dataclasses.replace(plan, s=s1, u=u + a * du_k, lam=lam + a * (lam_new - lam),
                                  nu=nu + a * (nu_new - nu) if nu.shape[0] else nu, valid=jnp.asarray(True))
        step = jnp.max(jnp.abs(du)) / (1 + jnp.max(jnp.abs(u)))
        return new, qp_ok, accepted, step, viol1, cost1

    # -------------------------------------------------------------- the horizon solve
    def solve(self, plan: Plan, y, t, period_index=0):
        """Solve the horizon problem from the measured state ``y`` at time ``t`` [s],
        starting from ``plan`` (traceable; ``period_index`` counts periods since the
        start, for the shrinking horizon). Returns (plan, MPCStatus): the solved plan,
        or ``plan`` itself when the solve failed (``status.fallback``)."""
        N = self.intervals
        if self.horizon == "shrinking":
            first = period_index * self.steps_per_period
            active = (jnp.arange(N) >= first).astype(float)
            t_first = t - first * self.h
        else:
            active, t_first = jnp.ones(N), t
        ts, hs = self._grid(t_first, active)
        free = (active == 0)[:, None]
        lo_box, hi_box = self._bounds()
        tol = self.tol

        # the plan's inputs rolled out from the measurement: every iterate is feasible for
        # the shooting equations (they are linearized, condensed, and restored by the rollout)
        s0, cost0, _ = self._rollout(y, plan.u, ts, hs)
        start = dataclasses.replace(plan, s=s0)
        if self.mode == "rti":
            new, qp_ok, accepted, step, viol, cost = self._sqp_step(start, cost0, ts, hs, lo_box, hi_box, free, y,
                                                                    False)
            iters = jnp.asarray(1)
            converged = (step <= tol) & (viol <= tol) & qp_ok
            ok = qp_ok & accepted
        else:
            def body(carry):
                p, k, _, qp_all, acc, _, cost, _ = carry
                new, qp_ok, accepted, step, viol, cost = self._sqp_step(p, cost, ts, hs, lo_box, hi_box, free, y,
                                                                        True)
                conv = (step <= tol) & (viol <= tol) & qp_ok & accepted
                return new, k + 1, step, qp_all & qp_ok, acc & accepted, viol, cost, conv

            def cond(carry):
                _, k, _, qp_all, acc, _, _, conv = carry
                return (k < self.max_iter) & ~conv & qp_all & acc

            init = (start, jnp.asarray(0), jnp.asarray(jnp.inf), jnp.asarray(True), jnp.asarray(True),
                    jnp.asarray(jnp.inf), cost0, jnp.asarray(False))
            new, iters, step, qp_ok, accepted, viol, cost, converged = jax.lax.while_loop(cond, body, init)
            ok = converged
        finite = _all_finite(new) & jnp.isfinite(cost) & jnp.isfinite(viol)
        ok = ok & finite
        kept = jtu.tree_map(lambda a, b: jnp.where(ok, a, b), new, plan)
        status = MPCStatus(converged=converged & finite, iterations=iters, violation=viol, qp_ok=qp_ok,
                           cost=jnp.where(ok, cost, jnp.nan), fallback=~ok, solve_ms=jnp.asarray(jnp.nan))
        return kept, status

    def shift(self, plan: Plan, t):
        """The plan moved on by one period (receding horizon; ``t`` the time of the
        period just started): inputs and states shifted by p intervals, the tail
        extended with the last input and the model's RK4 map. The shrinking horizon
        keeps its plan on the fixed grid (no shift)."""
        if self.horizon == "shrinking":
            return plan
        p, N = self.steps_per_period, self.intervals
        u_tail = jnp.repeat(plan.u[-1:], p, axis=0)
        t_end = t + N * self.h

        def ext(x, k):
            x1, _ = self._interval(t_end + k * self.h, self.h, x, plan.u[-1])
            return x1, x1

        _, s_tail = jax.lax.scan(ext, plan.s[-1], jnp.arange(p))
        return dataclasses.replace(plan, s=jnp.concatenate([plan.s[p:], s_tail]),
                                   u=jnp.concatenate([plan.u[p:], u_tail]),
                                   lam=jnp.concatenate([plan.lam[p:], jnp.repeat(plan.lam[-1:], p, axis=0)]))

    def step(self, plan: Plan, y, t, period_index=0):
        """One control period (traceable): solve from the measurement ``y`` at ``t``,
        keep the plan (or fall back to the previous one), return (u_segment (p, m), the
        plan for the next period (shifted), MPCStatus). ``u_segment`` holds the inputs
        of the p intervals of this period. With the disturbance observer on, the estimate
        is updated from ``y`` first (``disturbance_gain``) and the horizon solved with it."""
        mpc = self
        if self.observer:
            plan = dataclasses.replace(plan, dist=self._observe(plan, y, t))
            mpc = eqx.tree_at(lambda m: m.dist, self, plan.dist)
        kept, status = mpc.solve(plan, y, t, period_index)
        if self.horizon == "shrinking":
            u_seg = jax.lax.dynamic_slice_in_dim(kept.u, period_index * self.steps_per_period,
                                                 self.steps_per_period)
        else:
            u_seg = kept.u[: self.steps_per_period]
        kept = dataclasses.replace(kept, dist=plan.dist, y_prev=y, u_prev=u_seg, has_prev=jnp.asarray(True))
        return u_seg, mpc.shift(kept, t), status

    def _observe(self, plan, y, t):
        """The disturbance estimate after the measurement ``y`` at ``t``: the model (with
        the current estimate) from ``plan.y_prev`` under ``plan.u_prev`` over the last
        period gives y_hat; d + gain (y - y_hat) / period (d itself before the first
        period, when there is no previous measurement)."""
        mpc = eqx.tree_at(lambda m: m.dist, self, plan.dist)
        t_prev = t - self.period

        def roll(x, k):
            x1, _ = mpc._interval(t_prev + k * self.h, self.h, x, plan.u_prev[k])
            return x1, None

        y_hat, _ = jax.lax.scan(roll, plan.y_prev, jnp.arange(self.steps_per_period))
        d = plan.dist + self.disturbance_gain * (y - y_hat) / self.period
        return jnp.where(plan.has_prev, d, plan.dist)

    def init(self, x0=None, u_guess=None, t0=0.0) -> Plan:
        """A first plan: the model's RK4 rollout of ``u_guess`` (N, m) (default zeros, or
        the middle of the input box clipped to it) from ``x0`` (default ``ocp.x0``) at
        ``t0``."""
        N, m = self.intervals, self.ocp.system.control_dim
        x0 = self.ocp.x0 if x0 is None else x0
        x0 = _checked_vector("x0", x0, self.ocp.x0.shape[0], "MPC.init")
        t0 = _start_time(t0, "MPC.init")
        if u_guess is None:
            lo, hi = (np.asarray(b) for b in self._bounds())
            u_guess = np.broadcast_to(np.clip(0.0, lo, hi), (N, m))
        u_guess = _checked_matrix("u_guess", u_guess, (N, m), "MPC.init")
        return Plan(*_init_program(self, host_array(x0), host_array(u_guess), host_array(t0)))


def _with_qp(mpc, qp):
    """``mpc`` with its QP solver set to ``qp`` (a copy; ``qp`` is a static field)."""
    new = copy.copy(mpc)
    object.__setattr__(new, "qp", qp)
    return new


def _init_plan(mpc, x0, u, t0):
    ts, hs = mpc._grid(t0, jnp.ones(mpc.intervals))

    def roll(x, k):
        x1, _ = mpc._interval(ts[k], hs[k], x, u[k])
        return x1, x1

    _, xs = jax.lax.scan(roll, x0, jnp.arange(mpc.intervals))
    s = jnp.concatenate([x0[None], xs])
    n, m = x0.shape[0], u.shape[1]
    return Plan(s, u, jnp.zeros_like(s), jnp.zeros((mpc.n_constraints,)), jnp.asarray(False), jnp.zeros(n),
                jnp.zeros(n), jnp.zeros((mpc.steps_per_period, m)), jnp.asarray(False))


@compiled(quick=True)
def _init_program(mpc, x0, u, t0):
    return _fields(_init_plan(mpc, x0, u, t0))


def _fields(module):
    """An equinox module's fields as a tuple (programs of the cache return builtin containers)."""
    return tuple(getattr(module, f.name) for f in dataclasses.fields(module))


def _max_abs(*arrays):
    return jnp.max(jnp.stack([jnp.max(jnp.abs(a), initial=0.0) for a in arrays]))


def _all_finite(tree):
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in jtu.tree_leaves(tree)
                              if jnp.issubdtype(a.dtype, jnp.floating)]))


# ------------------------------------------------------------------ checks
def _model_checks(system, x0, owner):
    """The controller's model: a vector state (Euclidean spaces, a flat x0)."""
    if not isinstance(system.spaces, Euclidean) or not eqx.is_array(x0) or np.ndim(x0) != 1:
        raise MPCError(f"{owner}: the controller's model must have a vector state (a flat array on Euclidean "
                       f"space); {type(system).__name__} has spaces {system.spaces!r}. Use a reduced form of "
                       "the scene (e.g. controls.tasks.ReducedSteering for the spherical robot)")


def _start_time(t0, owner):
    """The loop's start time t0 [s]: a finite real scalar (``V.real``), as a float."""
    with as_problem_error():
        return V.real("t0", t0, owner=owner, shape=(), as_float=True, what="start time [s]")


def _checked_vector(name, value, n, owner):
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise MPCError(f"{owner}: {name} must be an array of {n} numbers, got {value!r}") from None
    if a.shape != (n,):
        raise MPCError(f"{owner}: {name} has shape {a.shape}, the controller's model has a state of {n} numbers")
    if not np.all(np.isfinite(a)):
        bad = np.flatnonzero(~np.isfinite(a)).tolist()
        raise MPCError(f"{owner}: {name} contains NaN or inf at components {bad}; pass finite numbers")
    return a


def _checked_matrix(name, value, shape, owner):
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise MPCError(f"{owner}: {name} must be an array of shape {shape}, got {value!r}") from None
    if a.shape != tuple(shape):
        raise MPCError(f"{owner}: {name} has shape {a.shape}, expected {tuple(shape)}")
    if not np.all(np.isfinite(a)):
        raise MPCError(f"{owner}: {name} contains NaN or inf; pass finite numbers")
    return a


def _plant_checks(mpc, plant, owner, batched=False, measured=False):
    """The plant against the model (``batched``: its arrays carry a leading member axis;
    member 0 is checked; ``measured``: the plant has a state of its own, which
    ``_measured_plant`` checks with its start)."""
    model = mpc.ocp.system
    if batched and isinstance(plant, AbstractSystem):
        sizes = {np.shape(a)[0] if np.ndim(a) else None for a in jtu.tree_leaves(plant) if eqx.is_array(a)}
        if len(sizes) != 1 or None in sizes or 0 in sizes:
            raise MPCError(f"{owner}: in_axes={{'plant': 0}} needs a plant whose array leaves all carry one leading "
                           f"member axis (e.g. built with eqx.filter_vmap), got {type(plant).__name__} with leaves "
                           f"of shapes {[np.shape(a) for a in jtu.tree_leaves(plant) if eqx.is_array(a)][:6]}")
        plant = jtu.tree_map(lambda a: a[0] if eqx.is_array(a) else a, plant)
    if not isinstance(plant, AbstractSystem):
        raise MPCError(f"{owner}: plant must be an nhjax system (a scene, a Lagrangian, ...), got "
                       f"{type(plant).__name__}")
    n = mpc.ocp.x0.shape[0]
    if not measured and not isinstance(plant.spaces, Euclidean):
        hint = (f"pass measure= (the model's state from the plant's) to {owner}"
                if owner in ("closed_loop", "closed_loop_batch") else
                "run such plants with closed_loop_batch(..., measure=...)")
        raise MPCError(f"{owner}: the plant's state does not match the model's: {type(plant).__name__} has "
                       f"spaces {plant.spaces!r}, the controller's model {type(model).__name__} a vector of {n} "
                       f"numbers; {hint}")
    if plant.control_dim != model.control_dim:
        raise MPCError(f"{owner}: the plant takes {plant.control_dim} inputs, the controller's model "
                       f"{type(model).__name__} {model.control_dim}")
    if measured:
        return
    names_p, names_m = tuple(plant.state_names), tuple(model.state_names)
    if names_p and names_m and names_p != names_m:
        raise MPCError(f"{owner}: the plant's state does not match the model's: {type(plant).__name__} has "
                       f"state {names_p}, the model {type(model).__name__} {names_m}")
    try:
        dx = V.abstract_call(plant.vector_field, 0.0, mpc.ocp.x0, jax.ShapeDtypeStruct((model.control_dim,), float))
    except Exception as e:  # noqa: BLE001 - re-raised with the cause attached
        raise MPCError(f"{owner}: the plant's state does not match the model's: {type(plant).__name__}'s vector "
                       f"field does not take the model's state of {n} numbers ({e})") from e
    if getattr(dx, "shape", None) != (n,):
        raise MPCError(f"{owner}: the plant's state does not match the model's: {type(plant).__name__}'s vector "
                       f"field returns shape {getattr(dx, 'shape', None)} for a state of {n} numbers")


def _measured_plant(mpc, plant, x0, measure, owner):
    """A plant with a state of its own (e.g. attitudes on SO(3)) and the map ``measure``
    from it to the model's state: its start checked (finite numbers, the plant's
    structure) and ``measure`` and the plant's vector field traced on it (abstractly)."""
    n, m = mpc.ocp.x0.shape[0], mpc.ocp.system.control_dim
    if not callable(measure):
        raise MPCError(f"{owner}: measure must be a function from the plant's state to the model's state of {n} "
                       f"numbers, got {type(measure).__name__}")
    with as_problem_error():
        x0 = V.as_state(plant, x0, owner=owner, xp=np)
    leaves = jtu.tree_leaves(x0)
    if not leaves or not all(np.all(np.isfinite(a)) for a in leaves):
        raise MPCError(f"{owner}: x0 (the plant's state) must hold finite numbers")
    try:
        y = jax.eval_shape(measure, x0)
    except Exception as e:  # noqa: BLE001 - re-raised with the cause attached
        raise MPCError(f"{owner}: measure does not take the plant's state ({type(plant).__name__}): {e}") from e
    if getattr(y, "shape", None) != (n,):
        raise MPCError(f"{owner}: measure must return the model's state of {n} numbers, got "
                       f"{getattr(y, 'shape', type(y).__name__)}")
    try:
        V.abstract_call(plant.vector_field, 0.0, x0, jax.ShapeDtypeStruct((m,), float))
    except Exception as e:  # noqa: BLE001 - re-raised with the cause attached
        raise MPCError(f"{owner}: {type(plant).__name__}'s vector field does not take x0: {e}") from e
    return jtu.tree_map(host_array, x0)


def _push_functions(pushes, x0, owner):
    """A measured plant's pushes, (time, function of the plant's state) pairs, each
    function returning a state of the same structure and shapes (checked abstractly), as
    (times (P,), the P functions)."""
    times, fns = [], []
    for item in pushes or ():
        try:
            t, fn = item
            t = float(t)
        except (TypeError, ValueError):
            raise MPCError(f"{owner}: pushes on a plant with a state of its own (measure=) are (time [s], "
                           f"function of the plant's state) pairs, got {item!r}") from None
        if not np.isfinite(t) or not callable(fn):
            raise MPCError(f"{owner}: pushes on a plant with a state of its own (measure=) are (finite time [s], "
                           f"function of the plant's state) pairs, got ({t!r}, {fn!r})")
        try:
            out = jax.eval_shape(fn, x0)
        except Exception as e:  # noqa: BLE001 - re-raised with the cause attached
            raise MPCError(f"{owner}: the push at t = {t:g} s does not take the plant's state: {e}") from e
        if jtu.tree_structure(out) != jtu.tree_structure(x0) or any(
                o.shape != np.shape(a) for o, a in zip(jtu.tree_leaves(out), jtu.tree_leaves(x0))):
            raise MPCError(f"{owner}: the push at t = {t:g} s must return a state of the plant's structure and "
                           "shapes")
        times.append(t)
        fns.append(fn)
    return np.asarray(times, float), tuple(fns)


def _noise(name, value, k, owner):
    """A noise level: a number or k numbers, finite and >= 0."""
    try:
        a = np.broadcast_to(np.asarray(value, dtype=float), (k,)).copy()
    except (TypeError, ValueError):
        raise MPCError(f"{owner}: {name} must be a number or {k} numbers (standard deviations), got {value!r}") \
            from None
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise MPCError(f"{owner}: {name} must be finite and >= 0, got {a.tolist()}")
    return a


def _pushes(pushes, n, lead, owner):
    """(times (..., P), increments (..., P, n)) from a list of (t, dx) pairs or a pair of
    arrays; P = 0 for none."""
    if pushes is None or (isinstance(pushes, (list, tuple)) and len(pushes) == 0):
        return np.zeros(lead + (0,)), np.zeros(lead + (0, n))
    if isinstance(pushes, tuple) and len(pushes) == 2 and np.ndim(pushes[0]) >= 1 \
            and np.ndim(pushes[1]) == np.ndim(pushes[0]) + 1:
        times, dxs = (np.asarray(a, dtype=float) for a in pushes)
    else:
        try:
            times = np.asarray([float(t) for t, _ in pushes])
            dxs = np.stack([np.asarray(dx, dtype=float) for _, dx in pushes])
        except (TypeError, ValueError):
            raise MPCError(f"{owner}: pushes must be a list of (time [s], state increment ({n},)) pairs, got "
                           f"{pushes!r}") from None
    if times.ndim > 1 and times.shape[:-1] != lead:
        want = (f"a leading axis of {lead[0]} members (times (B, P), increments (B, P, {n}))" if lead else
                f"times of shape (P,) and increments (P, {n}) for one loop")
        raise MPCError(f"{owner}: per-member pushes must have {want}, got times of shape {times.shape}")
    if dxs.shape[-1:] != (n,) or dxs.shape[:-1] != times.shape:
        raise MPCError(f"{owner}: pushes: each state increment must have {n} numbers (the model's state), got "
                       f"times of shape {times.shape} and increments of shape {dxs.shape}")
    if not (np.all(np.isfinite(times)) and np.all(np.isfinite(dxs))):
        raise MPCError(f"{owner}: pushes contain NaN or inf; pass finite times and increments")
    times = np.broadcast_to(times, lead + times.shape[-1:])
    dxs = np.broadcast_to(dxs, lead + dxs.shape[-2:])
    return times, dxs


# ------------------------------------------------------------------ the closed loop
def _plant_period(mpc, plant, x, t, u_seg, force, push_t, push_dx, plant_substeps, measure=None, push_fns=()):
    """Advance the plant over one period by RK4 (``plant_substeps`` steps per model
    interval) under the inputs u_seg (p, m) plus the force noise (p * plant_substeps, m);
    pushes whose time falls in a step's [t, t + dt) are added to the state at that
    step's start. Returns (x at the period's end, int L dt over it). A plant with a
    state of its own (``measure``): ``_measured_period``."""
    if measure is not None:
        return _measured_period(mpc, plant, x, t, u_seg, force, plant_substeps, measure, push_t, push_fns)
    L = mpc.ocp.running_cost
    dt = mpc.h / plant_substeps
    p = mpc.steps_per_period

    def f(tt, x, u, w):
        return plant.vector_field(tt, x, u + w), L(tt, x, u)

    def body(carry, j):
        x, J = carry
        tt = t + j * dt
        hit = (push_t >= tt) & (push_t < tt + dt)
        x = x + jnp.sum(jnp.where(hit[:, None], push_dx, 0.0), axis=0)
        u, w = u_seg[j // plant_substeps], force[j]
        k1x, k1j = f(tt, x, u, w)
        k2x, k2j = f(tt + dt / 2, x + dt / 2 * k1x, u, w)
        k3x, k3j = f(tt + dt / 2, x + dt / 2 * k2x, u, w)
        k4x, k4j = f(tt + dt, x + dt * k3x, u, w)
        x = x + dt / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
        J = J + dt / 6 * (k1j + 2 * k2j + 2 * k3j + k4j)
        return (x, J), None

    (x, J), _ = jax.lax.scan(body, (x, jnp.zeros(())), jnp.arange(p * plant_substeps))
    return x, J


def _measured_period(mpc, plant, x, t, u_seg, force, plant_substeps, measure, push_t, push_fns):
    """``_plant_period`` for a plant with a state of its own (group-valued parts, e.g.
    attitudes on SO(3)): RKMK4 steps (``nhjax.RKMK4``, the Munthe-Kaas form of RK4, so
    that rotations stay rotations; its stages in a scan for the plant's
    ``large_vector_field``), the cost int L(t, measure(x), u) dt carried as one more
    (Euclidean) part of the state, so that it gets the same RK4 quadrature as a vector
    plant's. The plant's ``project`` (its constraints, where it has any) at the period's
    end. Pushes: ``push_fns[k]`` (a map of the plant's state) applied at the start of the
    step that contains ``push_t[k]``."""
    from nhjax.integrate.rkmk import RKMK4, LieODETerm

    L = mpc.ocp.running_cost
    dt = mpc.h / plant_substeps
    p = mpc.steps_per_period

    def field(tt, y, args):
        xx, _ = y
        u, w = args
        return plant.vector_field(tt, xx, u + w), L(tt, measure(xx), u)

    term = LieODETerm(field, (plant.spaces, Euclidean()))
    solver = RKMK4(scan_stages=bool(getattr(plant, "large_vector_field", False)))

    def body(y, j):
        tt = t + j * dt
        xx, J = y
        for k, push in enumerate(push_fns):
            hit = (push_t[k] >= tt) & (push_t[k] < tt + dt)
            xx = jtu.tree_map(lambda a, b: jnp.where(hit, a, b), push(xx), xx)
        args = (u_seg[j // plant_substeps], force[j])
        y1 = solver.step(term, tt, tt + dt, (xx, J), args, None, False)[0]
        return y1, None

    (x, J), _ = jax.lax.scan(body, (x, jnp.zeros(())), jnp.arange(p * plant_substeps))
    return plant.project(t + mpc.period, x), J


def _draws(mpc, key, periods, plant_substeps, force_sd, meas_sd):
    """Force noise (periods, p * plant_substeps, m) and measurement noise (periods, n)."""
    n, m = mpc.ocp.x0.shape[0], mpc.ocp.system.control_dim
    kf, km = jax.random.split(key)
    force = jax.random.normal(kf, (periods, mpc.steps_per_period * plant_substeps, m)) * force_sd
    meas = jax.random.normal(km, (periods, n)) * meas_sd
    return force, meas


def _loop(mpc, plant, x0, plan0, t0, key, push_t, push_dx, force_sd, meas_sd, periods, plant_substeps,
          measure=None, push_fns=()):
    force, meas = _draws(mpc, key, periods, plant_substeps, force_sd, meas_sd)

    def body(carry, j):
        x, plan, J = carry
        t = t0 + j * mpc.period
        y = (x if measure is None else measure(x)) + meas[j]
        u_seg, plan, status = mpc.step(plan, y, t, j)
        x1, dJ = _plant_period(mpc, plant, x, t, u_seg, force[j], push_t, push_dx, plant_substeps, measure,
                               push_fns)
        return (x1, plan, J + dJ), (x, y, u_seg, status)

    (xT, _, J), (xs, ys, us, status) = jax.lax.scan(body, (x0, plan0, jnp.zeros(())), jnp.arange(periods))
    xs = jtu.tree_map(lambda a, b: jnp.concatenate([a, b[None]]), xs, xT)
    ts = t0 + jnp.arange(periods + 1) * mpc.period
    return xs, ys, us.reshape(-1, us.shape[-1]), _fields(status), J, _constraint_drift(plant, ts, xs)


@compiled
def _loop_program(mpc, plant, x0, plan0, t0, key_data, push_t, push_dx, force_sd, meas_sd, periods,
                  plant_substeps, measure=None, push_fns=()):
    return _loop(mpc, plant, x0, Plan(*plan0), t0, jax.random.wrap_key_data(key_data), push_t, push_dx, force_sd,
                 meas_sd, periods, plant_substeps, measure, push_fns)


@compiled
def _step_program(mpc, plan, y, t, j):
    u_seg, plan, status = mpc.step(Plan(*plan), y, t, j)
    return u_seg, _fields(plan), _fields(status)


@compiled
def _plant_program(mpc, plant, x, t, u_seg, force, push_t, push_dx, plant_substeps, measure=None, push_fns=()):
    return _plant_period(mpc, plant, x, t, u_seg, force, push_t, push_dx, plant_substeps, measure, push_fns)


@compiled(quick=True)
def _measure_program(measure, x, noise):
    return measure(x) + noise


@compiled(quick=True)
def _draws_program(mpc, key_data, periods, plant_substeps, force_sd, meas_sd):
    return _draws(mpc, jax.random.wrap_key_data(key_data), periods, plant_substeps, force_sd, meas_sd)


@compiled(errors="off")
def _batch_program(mpc, plant, plant_axis, X, u0, t0, key_data, push_t, push_dx, fsd, msd, periods, plant_substeps,
                   group, measure=None, push_fns=()):
    def member(pl, x0, kd, pt, pdx):
        plan = _init_plan(mpc, x0 if measure is None else measure(x0), u0, t0)
        return _loop(mpc, pl, x0, plan, t0, jax.random.wrap_key_data(kd), pt, pdx, fsd, msd, periods,
                     plant_substeps, measure, push_fns)

    # groups of ``group`` members vmapped together, the groups one after the other
    # (lax.map): the loops of a small group stay small enough for XLA to compile each as
    # one function (nhjax._xla_flags), where one vmap over all members runs them kernel by
    # kernel with every kernel as wide as the batch
    B = jtu.tree_leaves(X)[0].shape[0]
    n_groups = -(-B // group)
    pad = n_groups * group - B

    def grouped(a):
        a = jnp.concatenate([a, jnp.repeat(a[:1], pad, axis=0)]) if pad else a
        return a.reshape((n_groups, group) + a.shape[1:])

    arrays, static = eqx.partition(plant, eqx.is_array)
    if plant_axis == 0:
        vm = eqx.filter_vmap(lambda ar, *a: member(eqx.combine(ar, static), *a))
        xs = (jtu.tree_map(grouped, arrays),)
    else:
        vm = eqx.filter_vmap(lambda *a: member(plant, *a))
        xs = ()
    out = jax.lax.map(lambda t: vm(*t), xs + (jtu.tree_map(grouped, X), grouped(key_data), grouped(push_t),
                                             grouped(push_dx)))
    return jtu.tree_map(lambda a: a.reshape((n_groups * group,) + a.shape[2:])[:B], out)


def _constraint_drift(plant, ts, xs):
    try:
        res = jax.vmap(lambda t, x: plant.constraints(t, x))(ts, xs)
    except Exception:  # noqa: BLE001 - a plant without traceable constraints reports none
        return {}
    return {k: jnp.max(jnp.abs(v)) for k, v in res.items()}


def _result(mpc, plant, t0, xs, ys, us, status, J, drift, periods):
    """The ClosedLoop of one loop's (or, with leading member axes, a batch's) arrays."""
    # assembled on the host and handed over (no eager programs: a first answer pays
    # for each of those in every new process)
    p = mpc.steps_per_period
    ts = np.asarray(t0) + np.arange(periods + 1) * float(mpc.period)
    lead = ys.shape[:-2]  # (the measurements: the model's vector states; the plant's may be a pytree)
    if lead:
        ts = np.broadcast_to(ts, lead + ts.shape)
    u_host = np.asarray(us)
    u_at = V.to_device(np.concatenate([u_host[..., ::p, :], u_host[..., -1:, :]], axis=-2))
    x_end = jtu.tree_map(lambda a: V.to_device(np.asarray(a)[(slice(None),) * len(lead) + (-1,)]), xs)
    steps = jax.device_put(np.full(lead, periods * p))
    traj = Trajectory(ts=V.to_device(ts), xs=xs, us=u_at, work=None, invariants={}, invariant_drift={},
                      constraint_drift=dict(drift), num_steps=steps, num_accepted_steps=steps,
                      num_rejected_steps=jax.device_put(np.zeros(lead, int)), t_final=V.to_device(ts[..., -1]),
                      x_end=x_end, result=None, event_mask=None,
                      state_names=tuple(plant.state_names))
    return ClosedLoop(trajectory=traj, inputs=us, measurements=ys, status=MPCStatus(*status), cost=J)


def _setup(mpc, plant, periods, plant_substeps, owner, batched=False, measured=False):
    if not isinstance(mpc, MPC):
        raise MPCError(f"{owner}: mpc must be a controls.MPC, got {type(mpc).__name__}")
    _plant_checks(mpc, plant, owner, batched, measured)
    with as_problem_error():
        periods = V.integer("periods", periods, minimum=1, owner=owner)
        plant_substeps = V.integer("plant_substeps", mpc.substeps if plant_substeps is None else plant_substeps,
                                   minimum=1, owner=owner)
    if mpc.horizon == "shrinking" and periods * mpc.steps_per_period > mpc.intervals:
        raise MPCError(f"{owner}: a shrinking horizon of {mpc.intervals} intervals covers "
                       f"{mpc.intervals // mpc.steps_per_period} periods, asked for {periods}")
    return periods, plant_substeps


def closed_loop(mpc: MPC, plant, x0, periods, *, t0=0.0, u_guess=None, pushes=None, force_noise=0.0,
                measurement_noise=0.0, key=None, plant_substeps=None, timing=False, measure=None) -> ClosedLoop:
    """Run ``mpc`` against ``plant`` for ``periods`` control periods from ``x0`` at ``t0``.

    Each period: the controller measures y = x + v (v ~ N(0, diag(measurement_noise^2)),
    one draw per period), solves its horizon problem (``MPC.step``), and the plant is
    advanced over the period by RK4 (``plant_substeps`` steps per model interval,
    default ``mpc.substeps``) under the commanded input plus the force noise
    w ~ N(0, diag(force_noise^2)) [input units], drawn anew on every plant step.
    ``pushes``: a list of (time [s], state increment) pairs (a velocity kick is an
    increment of the velocity components): each is added to the plant's state at the
    start of the plant step that contains its time.

    plant : any nhjax system with the model's inputs. Without ``measure``: one whose
        state has the model's layout (the same vector of n numbers; other parameters
        allowed: a model error), advanced by RK4.
    measure : for a plant with a state of its own, e.g. attitudes on SO(3) where the
        model has coordinates or a reduced state: a function (jax-traceable) from the
        plant's state to the model's n numbers, y = measure(x) + v. ``x0`` is then the
        plant's state; the plant is advanced by RKMK4 (``nhjax.RKMK4``, RK4 in its
        Munthe-Kaas form: group parts stay on their group), its ``project`` applied at
        each period's end, the cost evaluated on measure(x); ``pushes`` are then
        (time [s], function) pairs, each function a map of the plant's state (e.g. a
        change of its velocities), applied at the start of the plant step that contains
        its time.
    key : a ``jax.random`` key for the noises (required when a noise level is not 0).
    u_guess : (N, m) the first plan's inputs (``MPC.init``).
    timing : False (default): the whole loop is one compiled ``lax.scan`` over periods
        (statuses' ``solve_ms`` NaN). True: the same per-period functions run from
        Python, one compiled call per period, and ``status.solve_ms`` holds each horizon
        solve's wall time: the real-time use of the controller.

    Returns a ``ClosedLoop``."""
    owner = "closed_loop"
    if not isinstance(timing, (bool, np.bool_)):
        raise MPCError(f"{owner}: timing must be True (one compiled call per period, each timed) or False (one "
                       f"compiled loop), got {timing!r}")
    periods, plant_substeps = _setup(mpc, plant, periods, plant_substeps, owner, measured=measure is not None)
    t0 = _start_time(t0, owner)
    n, m = mpc.ocp.x0.shape[0], mpc.ocp.system.control_dim
    if measure is None:
        y0 = _checked_vector("x0", x0, n, owner)
        x0 = host_array(y0)
    else:
        x0 = _measured_plant(mpc, plant, x0, measure, owner)
    fsd, msd = _noise("force_noise", force_noise, m, owner), _noise("measurement_noise", measurement_noise, n, owner)
    kd = _key_data(key, fsd, msd, owner)
    if measure is None:
        (push_t, push_dx), push_fns = _pushes(pushes, n, (), owner), ()
    else:
        (push_t, push_fns), push_dx = _push_functions(pushes, x0, owner), np.zeros((0, n))
        y0 = _measure_program(measure, x0, host_array(np.zeros(n)))  # the model's start (noise-free)
    plan0 = mpc.init(y0, u_guess, t0)
    t0a = host_array(t0)
    pt, pdx, fs, ms = (host_array(a) for a in (push_t, push_dx, fsd, msd))
    if not timing:
        xs, ys, us, status, J, drift = _loop_program(mpc, plant, x0, _fields(plan0), t0a, kd, pt, pdx,
                                                     fs, ms, periods, plant_substeps, measure, push_fns)
        return _result(mpc, plant, t0a, xs, ys, us, status, J, drift, periods)
    force, meas = _draws_program(mpc, kd, periods, plant_substeps, fs, ms)
    x, plan, J = x0, _fields(plan0), host_array(0.0)
    # compiled (or loaded) before the clock runs: solve_ms is the solve after compile
    warm = _step_program(mpc, plan, host_array(y0), t0a, jnp.asarray(np.asarray(0, np.int64)))
    jax.block_until_ready(_plant_program(mpc, plant, x, t0a, warm[0], force[0], pt, pdx, plant_substeps, measure,
                                         push_fns))
    xs, ys, segs, stats = [x], [], [], []
    for j in range(periods):
        t = t0a + j * mpc.period
        y = x + meas[j] if measure is None else _measure_program(measure, x, meas[j])
        y.block_until_ready()
        tic = time.perf_counter()
        u_seg, plan, st = _step_program(mpc, plan, y, t, jnp.asarray(np.asarray(j, np.int64)))
        u_seg.block_until_ready()
        st = (*st[:-1], jnp.asarray((time.perf_counter() - tic) * 1e3))
        x, dJ = _plant_program(mpc, plant, x, t, u_seg, force[j], pt, pdx, plant_substeps, measure, push_fns)
        J = J + dJ
        xs.append(x), ys.append(y), segs.append(u_seg), stats.append(st)
    xs = jtu.tree_map(lambda *a: jnp.stack(a), *xs)
    status = tuple(jnp.stack(a) for a in zip(*stats))
    drift = _drift_program(plant, t0a + jnp.arange(periods + 1) * mpc.period, xs)
    return _result(mpc, plant, t0a, xs, jnp.stack(ys), jnp.concatenate(segs), status, J, drift, periods)


@compiled(quick=True)
def _drift_program(plant, ts, xs):
    return _constraint_drift(plant, ts, xs)


def _key_data(key, fsd, msd, owner, members=None):
    """The raw data of ``key`` (``members``: of a (members,) array of keys). Default:
    that of ``jax.random.key(0)`` for every member, handed over from the host: without
    noise the draws are multiplied by zero, so any key serves, and ``jax.random.key``
    and ``jax.random.split`` are eager programs, paid in every new process."""
    if key is None:
        if np.any(fsd > 0) or np.any(msd > 0):
            raise MPCError(f"{owner}: noise needs a PRNG key: pass key=jax.random.key(seed)" if members is None else
                           f"{owner}: noise needs one PRNG key per member: keys=jax.random.split(key, {members})")
        if jax.config.jax_default_prng_impl == "threefry2x32":  # key(0)'s data: (0, 0)
            data = np.zeros(2, np.uint32)
        else:
            data = np.asarray(jax.random.key_data(jax.random.key(0)))
        return jax.device_put(data if members is None else np.broadcast_to(data, (members, *data.shape)).copy())
    name, want = ("key", "one PRNG key, jax.random.key(seed)") if members is None else (
        "keys", f"one PRNG key per member ({members}), jax.random.split(key, {members})")
    typed = isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
    legacy = isinstance(key, (jax.Array, np.ndarray)) and key.dtype == np.uint32 and key.ndim >= 1
    lead = () if members is None else (members,)
    if not (typed or legacy) or (key.shape if typed else key.shape[:-1]) != lead:
        got = (f"{type(key).__name__} of shape {tuple(key.shape)} and dtype {key.dtype}" if hasattr(key, "shape")
               and hasattr(key, "dtype") else repr(key) if isinstance(key, (int, float, str)) else type(key).__name__)
        raise MPCError(f"{owner}: {name} must be {want}, got {got}")
    return jax.random.key_data(key)


def _batch_inputs(mpc, plant, x0s, periods, in_axes, pushes, force_noise, measurement_noise, keys, plant_substeps,
                  group, owner, measure=None):
    """``closed_loop_batch``'s arguments checked (MPCError before any numerics) and put in
    the program's form: (plant_axis, periods, plant_substeps, group, X (B, n) numpy (with
    ``measure``: the plant's states, every leaf with the members on axis 0), force and
    measurement noise levels, the keys' raw data (B, ...), pushes' times (B, P) and
    increments (B, P, n), the pushes' functions (``measure``; else ()))."""
    with as_problem_error():
        in_axes = V.axes_dict(in_axes, ("plant",), owner=owner)
    plant_axis = in_axes.get("plant")
    if plant_axis not in (None, 0):
        raise MPCError(f"{owner}: in_axes['plant'] must be 0 or None, got {plant_axis!r}")
    periods, plant_substeps = _setup(mpc, plant, periods, plant_substeps, owner, batched=plant_axis == 0,
                                     measured=measure is not None)
    with as_problem_error():
        group = V.integer("group", group, minimum=1, owner=owner)
    n, m = mpc.ocp.x0.shape[0], mpc.ocp.system.control_dim
    # (members of a batched plant: one leading size on every array leaf, _plant_checks)
    plant_B = [a for a in jtu.tree_leaves(plant) if eqx.is_array(a)][0].shape[0] if plant_axis == 0 else None
    if measure is not None:
        X, B, push_t, push_fns = _measured_batch(mpc, plant, plant_axis, x0s, measure, pushes, owner)
    else:
        try:
            X = np.asarray(x0s, dtype=float) if not isinstance(x0s, jax.Array) else np.asarray(x0s, dtype=float)
        except (TypeError, ValueError):
            raise MPCError(f"{owner}: x0s must be an array of shape (B, {n}) of real numbers (one start per "
                           f"member), got {type(x0s).__name__} {x0s!r:.80}") from None
        if X.ndim != 2 or X.shape[1] != n or X.shape[0] == 0:
            raise MPCError(f"{owner}: x0s must have shape (B, {n}) with B >= 1 (one start per member), got "
                           f"{X.shape}")
        if not np.all(np.isfinite(X)):
            rows = np.flatnonzero(~np.all(np.isfinite(X), axis=1)).tolist()
            raise MPCError(f"{owner}: x0s contains NaN or inf in members {rows}; pass finite starts")
        B, push_fns = X.shape[0], ()
    if plant_B is not None and plant_B != B:
        raise MPCError(f"{owner}: the plant's arrays carry {plant_B} members (in_axes={{'plant': 0}}), x0s {B}; pass "
                       "one plant per start")
    fsd, msd = _noise("force_noise", force_noise, m, owner), _noise("measurement_noise", measurement_noise, n, owner)
    key_data = _key_data(keys, fsd, msd, owner, members=B)
    if measure is not None:  # (the pushes are the functions; no increments)
        push_dx = np.zeros(push_t.shape + (n,))
    else:
        push_t, push_dx = _pushes(pushes, n, (B,), owner)
        if push_t.shape[0] != B:
            raise MPCError(f"{owner}: per-member pushes must have a leading axis of {B} members")
    return plant_axis, periods, plant_substeps, group, X, fsd, msd, key_data, push_t, push_dx, push_fns


def _measured_batch(mpc, plant, plant_axis, x0s, measure, pushes, owner):
    """A batch of measured plants' starts (``x0s``: the plant's state with the members on
    axis 0 of every leaf): (X on the host, B, pushes' times (B, P), their functions).
    Member 0 is checked as ``closed_loop``'s start (``_measured_plant``); every member
    must have its structure and shapes and finite numbers. Pushes: (time, function)
    pairs shared by all members."""
    leaves = jtu.tree_leaves(x0s)
    sizes = {np.shape(a)[0] if np.ndim(a) else None for a in leaves}
    if not leaves or len(sizes) != 1 or None in sizes or 0 in sizes:
        raise MPCError(f"{owner}: with measure=, x0s is the plant's state with the members on axis 0 of every "
                       f"part (one start per member), got parts of shapes {[np.shape(a) for a in leaves]}")
    (B,) = sizes
    X = jtu.tree_map(lambda a: np.asarray(a, dtype=float), x0s)
    plant0 = jtu.tree_map(lambda a: a[0] if eqx.is_array(a) else a, plant) if plant_axis == 0 else plant
    first = _measured_plant(mpc, plant0, jtu.tree_map(lambda a: a[0], X), measure, owner)
    if jtu.tree_structure(first) != jtu.tree_structure(X) or any(
            np.shape(a) != np.shape(b)[1:] for a, b in zip(jtu.tree_leaves(first), jtu.tree_leaves(X))):
        raise MPCError(f"{owner}: x0s must have the plant's state structure with a leading member axis on every "
                       "part")
    finite = np.ones(B, bool)
    for a in jtu.tree_leaves(X):
        finite &= np.all(np.isfinite(a.reshape(B, -1)), axis=1)
    if not finite.all():
        raise MPCError(f"{owner}: x0s contains NaN or inf in members {np.flatnonzero(~finite).tolist()}; pass "
                       "finite starts")
    if isinstance(pushes, tuple) and len(pushes) == 2 and all(isinstance(p, np.ndarray) for p in pushes):
        raise MPCError(f"{owner}: pushes on measured plants are (time [s], function of the plant's state) pairs "
                       "shared by all members")
    times, fns = _push_functions(pushes, first, owner)
    return X, B, np.broadcast_to(times, (B, times.size)).copy(), fns


def closed_loop_batch(mpc: MPC, plant, x0s, periods, *, in_axes=None, t0=0.0, u_guess=None, pushes=None,
                      force_noise=0.0, measurement_noise=0.0, keys=None, plant_substeps=None,
                      group=4, measure=None, workers=None) -> ClosedLoop:
    """B closed loops (``closed_loop``'s arguments, one member per row of ``x0s`` (B, n))
    in one compiled program: ``closed_loop``'s ``lax.scan`` over periods, vmapped over
    groups of ``group`` members, the groups one after the other (``lax.map``; the last
    group padded with copies of member 0, dropped from the result). With ``workers``
    > 1 the members are cut into that many equal shares (a whole number of groups each,
    the last padded with copies of its first member) that run the same compiled program
    at once in threads of this process (XLA releases the GIL), joined in member order.
    Returns a ``ClosedLoop`` whose arrays have a leading member axis.

    Why groups: XLA's CPU runtime compiles a loop whose body moves less than
    ``nhjax._xla_flags``' threshold of bytes per iteration as one function, and runs
    a larger one kernel by kernel. A vmap over all members makes every loop of the
    controller (the interior point's iterations, the Riccati sweeps, the RK4 steps) as
    wide as the batch and runs it kernel by kernel; a few members at a time keep those
    loops compiled whole. The horizon QPs are solved by the Riccati recursion when
    ``mpc.qp`` is "auto" (no LAPACK call per member).

    in_axes : {"plant": 0} when the plant's array leaves carry a leading member axis
        (plant parameters per member, e.g. built with ``eqx.filter_vmap`` or stacked
        with ``jax.tree_util.tree_map``); default: one plant for all.
    pushes : a list of (time, increment) pairs shared by all members, or a pair of
        arrays (times (B, P), increments (B, P, n)) per member (a zero increment for
        a member without that push).
    keys : (B,) PRNG keys (``jax.random.split(key, B)``), required with noise.
    group : members vmapped together (default 4).
    workers : threads that run shares of the members at once (default: 2 on a machine
        with two or more CPUs, else 1; never more than the batch has groups). The shares'
        results equal those of one program to the last bit (each member's loop does not
        depend on the others). Inside a Dask worker (``closed_loop_batch_on_client``)
        the default is 1: the cluster's workers already share the cores.
    measure : as ``closed_loop``'s, for plants with a state of their own: ``x0s`` is
        then the plant's state with the members on axis 0 of every part (e.g. B
        attitudes (B, 3, 3)), and ``pushes`` are (time [s], function of the plant's
        state) pairs shared by all members.

    How it relates to ``nhjax.simulate_batch``: that function steps adaptive solves of
    unequal length in lanes and refills a lane when its member ends; here every member
    runs the same number of periods with the same fixed-step plant integration, so all
    end together and nothing is refilled. A period's SQP loop (converged mode) and the
    QP's interior-point loop are ``lax.while_loop``s under ``vmap``: each member stops
    iterating (its values frozen) when it converges and its group's loop ends when the
    group's slowest member does. Per-member statuses say which
    members converged or fell back. For more members than one process holds:
    ``controls.distributed.closed_loop_batch_on_client`` (chunks of members on the
    workers of a Dask cluster, joined into one result)."""
    owner = "closed_loop_batch"
    t0 = _start_time(t0, owner)
    plant_axis, periods, plant_substeps, group, X, fsd, msd, key_data, push_t, push_dx, push_fns = _batch_inputs(
        mpc, plant, x0s, periods, in_axes, pushes, force_noise, measurement_noise, keys, plant_substeps, group, owner,
        measure)
    B = jtu.tree_leaves(X)[0].shape[0]
    group = min(group, B)
    with as_problem_error():
        workers = batch_workers(workers, B, group, owner)
    if measure is None:
        y0 = X[0]
    else:  # the model's start of member 0 (noise-free): the first plan's inputs
        n = mpc.ocp.x0.shape[0]
        y0 = _measure_program(measure, jtu.tree_map(lambda a: host_array(a[0]), X), host_array(np.zeros(n)))
    plan0 = mpc.init(y0, u_guess, t0)
    t0a = host_array(t0)
    if mpc.qp == "auto":  # the Riccati QP, whose small operations vectorize over the members
        mpc = _with_qp(mpc, "riccati")
    per_member = (plant if plant_axis == 0 else None, X, key_data, push_t, push_dx)

    def args_of(part):
        """The program's arguments for some of the members (``per_member`` at them)."""
        pl, x, kd, pt, pdx = part
        return (mpc, plant if pl is None else pl, plant_axis, jtu.tree_map(jnp.asarray, x), plan0.u, t0a, kd,
                jnp.asarray(pt), jnp.asarray(pdx), jnp.asarray(fsd), jnp.asarray(msd), periods, plant_substeps,
                group, measure, push_fns)

    # whole groups in equal shares (one program for all), run at once in threads
    out = jtu.tree_map(jnp.asarray, run_in_shares(_batch_program, args_of, per_member, B, workers, group,
                                                  "nhjax-mpc"))
    xs, ys, us, status, J, drift = out
    return _result(mpc, plant, t0a, xs, ys, us, status, J, drift, periods)
