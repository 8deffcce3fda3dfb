"""``DiscreteAdjoint``: reverse-mode gradients through simulate() at a few forward solves.

Differentiating diffrax's while loop directly (``RecursiveCheckpointAdjoint``)
replays the whole solver machinery -- step-size controller, saving, event
checks, loop bookkeeping -- under checkpointing, which on a small system costs
many forward solves (benchmarks/batch_throughput.py measures how many). What a
gradient of a
Runge-Kutta solution needs is much less: the accepted steps t_0 < t_1 < ... <
t_M with their states y_k, and the vector-Jacobian product of each step map

    y_{k+1} = Phi(t_k, t_{k+1}, y_k; p)                                  (1)

taken backwards from k = M-1 to 0 (the discrete adjoint of the method:
Hairer, Lubich & Wanner, Geometric Numerical Integration, sec. VI.6; Sandu,
"On the properties of Runge-Kutta discrete adjoints", 2006):

    lambda_k = (dPhi/dy_k)^T lambda_{k+1} + (saved outputs in step k),
    dL/dp   += (dPhi/dp)^T lambda_{k+1}.

diffrax stops gradients through the step-size controller, so the mesh is a
constant of its derivative as well: this adjoint is the exact derivative of the
same discrete solution (agreement with ``RecursiveCheckpointAdjoint`` to
round-off is a test). A state saved between steps is the solver's dense output
on step k, a function of (y_k, p): its VJP adds to lambda_k (all saved states
at once, vectorised).

How the backward pass is formed (``DiscreteAdjoint.jacobians``), for D
differentiated input numbers:

* "tangents" (chosen for D <= 4): nothing is recorded; the forward solve carries
  the D tangents dy/d(inputs) along with the state (forward sensitivities: the
  JVP of the same steps, vectorised over the D directions), and the backward
  pass is (output cotangent) . (output Jacobian). This multiplies the same step
  Jacobians in the other order, so it is the same derivative; a guard's event
  time is differentiated too (as by RecursiveCheckpointAdjoint).
* "vjp" (chosen for D > 4): record the accepted steps, then one VJP of the step
  per step from the last to the first; cost independent of D.
* "forward" / "reverse": record, then build the step Jacobians dPhi/dy_k and
  dPhi/dp for a chunk of steps in one vectorised call, and run the recursion as
  n x n matrix-vector products.

Which is cheaper depends on D and on the system: the tangents cost about D
forward solves' worth of JVPs and need no recording, the VJP sweep costs a
recording forward pass and one VJP per step whatever D is, so "auto" takes the
tangents for few differentiated numbers (``benchmarks/batch_throughput.py``
reports the ratios to a forward solve for every mode).

Cost and memory: except in "tangents" mode the forward pass records every
accepted step (``max_steps`` x state size floats per solve, only when
differentiated: a forward-only call records nothing), which makes that pass
several times dearer than a plain forward solve on small systems.

Limits (checked or documented):

* reverse mode only (``jax.grad``/``jax.vjp``); use ``diffrax.ForwardMode()`` for
  ``jax.jvp``/``jax.jacfwd``;
* the times t0, t1 and the save times are not differentiated;
* a solve stopped by a chart guard (``on_guard="stop"``) ends at the event time
  t*: except in "tangents" mode this adjoint holds t* fixed (no dt*/dp term,
  which RecursiveCheckpointAdjoint includes by differentiating the root find),
  and differentiates the last piece as a step from t_{M-1} to t* where the
  forward took the dense output, so the gradient belongs to a solution within
  one step's local error of the returned one (controls gives such trial
  controls an infinite cost, where this does not matter);
* the solver's state must be a function of (t, y) alone (explicit Runge-Kutta,
  FSAL or not: RKMK45, RKMK87, RKMK4, diffrax's explicit tableaus, ``ProjectedSolver``
  around them).
"""

from __future__ import annotations

from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jax.flatten_util import ravel_pytree

from .clip_floor import collapsed_prevbefore

__all__ = ["DiscreteAdjoint"]


class DiscreteAdjoint(eqx.Module):
    """Reverse-mode gradients of ``nhjax.simulate`` by the discrete adjoint of the
    Runge-Kutta steps (see the module docstring for the method and its limits).

    Pass as ``simulate(..., adjoint=nhjax.DiscreteAdjoint())``. The forward pass
    of a differentiated solve stores up to ``max_steps`` accepted states (not in
    "tangents" mode); a solve that is not differentiated stores nothing.

    jacobians : how the backward pass is formed, for D differentiated numbers
        (the parts of the initial state and of the system/control parameters that
        carry a gradient), n state numbers:
        "tangents" -- no recording: the forward solve carries the D tangents
        dy/d(inputs) along (forward sensitivities, diffrax's ForwardMode steps),
        and the backward pass is one product per output; cost grows with D.
        "vjp" -- record the steps, then one vector-Jacobian product per step,
        last to first; cost independent of D.
        "forward" / "reverse" -- record the steps, then build the step Jacobians
        dPhi/dy (n x n) and dPhi/dp (n x D) for a chunk of steps at a time by
        forward / reverse mode, and run the recursion as matrix-vector products.
        "auto": "tangents" while D <= ``max_tangents`` and the step has
        forward-mode rules (a custom_vjp function inside the control or the
        system has none: found while tracing the tangents), else "vjp"
        (``benchmarks/batch_throughput.py`` times every mode against a forward solve).
    max_tangents : the largest D for which "auto" picks "tangents".
    chunk : steps whose Jacobians are evaluated together in one vectorised call
        ("forward"/"reverse"; memory: chunk x n x (n + D) floats).
    max_steps : simulate()'s default step budget under this adjoint (each
        differentiated solve records max_steps x n floats; filling a larger
        buffer costs time on every gradient).
    """

    jacobians: str = eqx.field(default="auto", static=True)
    chunk: int = eqx.field(default=64, static=True)
    max_tangents: int = eqx.field(default=4, static=True)
    max_steps: int = eqx.field(default=4096, static=True)

    def __check_init__(self):
        if self.jacobians not in _MODES:
            raise ValueError(f"jacobians must be one of {', '.join(map(repr, _MODES))}, got {self.jacobians!r}")


_MODES = ("auto", "tangents", "vjp", "forward", "reverse")


def _save_state(t, y, args):
    return y


class _Problem(eqx.Module):
    """Everything a solve needs besides y0 and args (which carry the gradients)."""

    term: Any
    solver: Any
    controller: Any
    event: Any
    sub: Any  # the user's SubSaveAt (ts=..., or t0 and t1)
    progress_meter: Any
    t0: Any
    t1: Any
    dt0: Any
    max_steps: int = eqx.field(static=True)

    def run(self, y0, args, record: bool, adjoint=None):
        subs = [self.sub, diffrax.SubSaveAt(t1=True)]
        if record:
            subs.append(diffrax.SubSaveAt(steps=True, fn=_save_state))
        with collapsed_prevbefore():  # (clip_floor.py: a smaller program to compile)
            sol = diffrax.diffeqsolve(
                self.term, self.solver, self.t0, self.t1, self.dt0, y0, args=args,
                saveat=diffrax.SaveAt(subs=subs), stepsize_controller=self.controller,
                adjoint=adjoint or diffrax.RecursiveCheckpointAdjoint(), event=self.event,
                max_steps=self.max_steps, throw=False, progress_meter=self.progress_meter,
            )
        out = dict(
            ts=sol.ts[0], ys=sol.ys[0], t_final=sol.ts[1][-1],
            y_end=jtu.tree_map(lambda a: a[-1], sol.ys[1]),
            num_steps=sol.stats["num_steps"], num_accepted_steps=sol.stats["num_accepted_steps"],
            num_rejected_steps=sol.stats["num_rejected_steps"], result=sol.result,
            event_mask=sol.event_mask,
        )
        steps = (sol.ts[2], sol.ys[2]) if record else None
        return out, steps


@eqx.filter_custom_vjp
def discrete_solve(diff, problem: _Problem, adjoint: DiscreteAdjoint):
    """diffrax solve of ``problem`` from y0 with args, ``diff = (y0, args)``; its
    reverse-mode derivative is the discrete adjoint (module docstring)."""
    y0, args = diff
    out, _ = problem.run(y0, args, record=False)
    return out


@discrete_solve.def_fwd
def _discrete_solve_fwd(perturbed, diff, problem, adjoint):
    # the mode travels to the backward pass with the residuals (a str: equinox keeps
    # non-array residuals static)
    mode = _mode(adjoint, diff, perturbed)
    if mode == "tangents":
        try:
            out, residuals = _tangent_forward(perturbed, diff, problem)
            return out, (mode, residuals)
        except (NotImplementedError, TypeError) as e:
            # "auto" on a step without a forward-mode rule (a custom_vjp function in a
            # user's control or system, a primitive JAX differentiates in reverse
            # only): the trace of the tangents stops there, and the VJPs take over.
            # (Trying is cheaper than asking first, which meant tracing a step's JVP
            # in every tangents-mode solve: for a large vector field, seconds.)
            if adjoint.jacobians != "auto" or (isinstance(e, TypeError) and "custom_vjp" not in str(e)):
                raise
            mode = "vjp"
    y0, args = diff
    out, steps = problem.run(y0, args, record=True)
    # the saved outputs' shapes (static), for the cotangents of those no loss reads
    ys_like = jtu.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), out["ys"])
    return out, (mode, (steps, out["t_final"], ys_like))


def _mode(adjoint: DiscreteAdjoint, diff, perturbed) -> str:
    """The way of forming the backward pass (``DiscreteAdjoint.jacobians``) for this
    solve, chosen in the forward pass ("auto": tangents for at most ``max_tangents``
    differentiated numbers; the forward pass takes the VJPs instead where the steps
    have no forward-mode rule)."""
    if adjoint.jacobians != "auto":
        return adjoint.jacobians
    D = sum(jnp.size(a) for a in jtu.tree_leaves(eqx.filter(diff, perturbed)))
    return "tangents" if D <= adjoint.max_tangents else "vjp"


def _tangent_forward(perturbed, diff, problem: _Problem):
    """"tangents": the solve with the tangents of its outputs in all D differentiated
    input directions carried along (diffrax's ForwardMode steps, vectorised over the
    directions; the primal is computed once). Residuals: the Jacobians of the saved
    states, the final state and the final time (a guard's event time) in those inputs."""
    dyn = eqx.filter(diff, perturbed)
    stat = eqx.filter(diff, perturbed, inverse=True)
    flat, unravel = ravel_pytree(dyn)

    def solve(flat):
        y0, args = eqx.combine(unravel(flat), stat)
        out, _ = problem.run(y0, args, record=False, adjoint=diffrax.ForwardMode())
        return (out["ys"], out["y_end"], out["t_final"]), out

    jac, out = jax.jacfwd(solve, has_aux=True)(flat)
    return out, (jac, out["ts"] <= out["t_final"])


def _tangent_backward(residuals, grad_out, perturbed, diff):
    """The cotangent of the differentiated inputs: (output cotangent) . (its Jacobian),
    summed over the outputs; saved entries past a guard's stop (inf) contribute nothing."""
    (J_ys, J_end, J_tf), valid = residuals
    flat, unravel = ravel_pytree(eqx.filter(diff, perturbed))
    ct = jnp.zeros_like(flat)

    def add(ct, g, J, mask=None):
        if g is None:
            return ct
        if mask is not None:
            m = mask.reshape(mask.shape + (1,) * (g.ndim - 1))
            g, J = jnp.where(m, g, 0.0), jnp.where(m[..., None], J, 0.0)
        return ct + jnp.tensordot(g, J, axes=g.ndim)

    none = lambda x: x is None  # noqa: E731
    for g_tree, J_tree, mask in ((grad_out["ys"], J_ys, valid), (grad_out["y_end"], J_end, None)):
        for g, J in zip(jtu.tree_leaves(g_tree, is_leaf=none), jtu.tree_leaves(J_tree)):
            ct = add(ct, g, J, mask)
    ct = add(ct, grad_out["t_final"], J_tf)
    return unravel(ct)


def _zeros_if_none(ct, like):
    if ct is None:
        return jtu.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), like)
    return jtu.tree_map(lambda c, a: jnp.zeros(a.shape, a.dtype) if c is None else c, ct, like,
                        is_leaf=lambda x: x is None)


@discrete_solve.def_bwd
def _discrete_solve_bwd(residuals, grad_out, perturbed, diff, problem, adjoint):
    mode, residuals = residuals
    if mode == "tangents":
        return _tangent_backward(residuals, grad_out, perturbed, diff)
    (ts_rec, ys_rec), t_final, ys_like = residuals
    y0, args = diff
    # Only the perturbed parameters get cotangents: fewer directions for the step Jacobians.
    dyn = eqx.filter(args, perturbed[1])
    stat = eqx.filter(args, perturbed[1], inverse=True)
    term, solver, sub = problem.term, problem.solver, problem.sub
    t0 = jnp.asarray(problem.t0, float)

    # Mesh t_0 .. t_M and states y_0 .. y_M: t_0, y_0 are the inputs, the recorded buffer
    # holds t_1 .. t_M, y_1 .. y_M and then inf up to max_steps; everything below reads
    # only the rows it needs (the buffer can be large: max_steps x n).
    C = adjoint.chunk
    y_flat0, unravel_y = ravel_pytree(y0)
    p_flat, unravel_p = ravel_pytree(dyn)
    n, P = y_flat0.size, p_flat.size
    if P == 0:  # nothing but the initial state is differentiated (ravel gives float32[0])
        p_flat = jnp.zeros((0,), y_flat0.dtype)
    M = jnp.searchsorted(ts_rec, jnp.inf, side="left")  # sorted, inf-padded

    def t_at(k):
        return jnp.where(k == 0, t0, ts_rec[jnp.clip(k - 1, 0, ts_rec.size - 1)])

    def y_at(k):  # k: 1-D array of step indices -> (len(k), n) flat states
        rows = jtu.tree_map(lambda a: a[jnp.clip(k - 1, 0, ts_rec.size - 1)], ys_rec)
        flat = jax.vmap(lambda y: ravel_pytree(y)[0])(rows)
        return jnp.where((k == 0)[:, None], y_flat0, flat)

    y_M = y_at(M[None])[0]

    def step(yf, pf, tk, tk1):
        y, a = unravel_y(yf), eqx.combine(unravel_p(pf), stat)
        state = solver.init(term, tk, tk1, y, a)
        y1, _, dense, _, _ = solver.step(term, tk, tk1, y, a, state, False)
        return ravel_pytree(y1)[0], dense

    def saved_at(yf, pf, tk, tk1, s):
        """The saved output at time s in step k: fn(s, dense output of step k at s)."""
        _, dense = step(yf, pf, tk, tk1)
        interp = solver.interpolation_cls(t0=tk, t1=tk1, **dense)
        return sub.fn(s, interp.evaluate(s), eqx.combine(unravel_p(pf), stat))

    def fn_vjp(t, yf, ct):
        f = lambda yy, pf: sub.fn(t, unravel_y(yy), eqx.combine(unravel_p(pf), stat))  # noqa: E731
        return jax.vjp(f, yf, p_flat)[1](ct)

    # lam: cotangent of y_M; ct_p: of the parameters.
    lam = ravel_pytree(_zeros_if_none(grad_out["y_end"], unravel_y(y_M)))[0]
    ct_p = jnp.zeros_like(p_flat)
    g_ys = grad_out["ys"]  # None when no saved output is differentiated
    if g_ys is not None and any(g is None for g in jtu.tree_leaves(g_ys, is_leaf=lambda x: x is None)):
        g_ys = _zeros_if_none(g_ys, ys_like)  # (shapes from the forward pass: no solve traced again)
    ends_only = sub.ts is None
    A_k = A_v = None  # saved outputs inside steps: step index and cotangent on y_k
    if g_ys is not None and ends_only:  # saved outputs are fn(t0, y_0) and fn(t_final, y_M)
        a, b = fn_vjp(t_final, y_M, jtu.tree_map(lambda g: g[1], g_ys))
        lam, ct_p = lam + a, ct_p + b
    elif g_ys is not None:
        # Every saved output depends on the state at the start of its step and on p:
        # their VJPs are independent of the recursion, so take them all at once.
        S = jnp.asarray(sub.ts, float)
        valid = S <= t_final  # saved entries past a guard's stop are inf in the output
        g_ys = jtu.tree_map(lambda g: jnp.where(valid.reshape((-1,) + (1,) * (g.ndim - 1)), g, 0.0), g_ys)
        # step of each save time: t_k < s <= t_{k+1} (s = t_0 in step 0)
        A_k = jnp.clip(jnp.searchsorted(ts_rec, S, side="left"), 0, M - 1)
        tk, tk1 = t_at(A_k), t_at(A_k + 1)
        s = jnp.clip(S, tk, tk1)

        def one(yf, tk, tk1, s, g):
            return jax.vjp(lambda yy, pf: saved_at(yy, pf, tk, tk1, s), yf, p_flat)[1](g)

        A_v, b = jax.vmap(one)(y_at(A_k), tk, tk1, s, g_ys)
        ct_p = ct_p + jnp.sum(b, axis=0)

    # Step Jacobians J_k = dPhi/dy_k (n x n) and dPhi/dp (n x P), a chunk of C steps at a
    # time: they depend only on the recorded states, so each chunk is one vectorised
    # evaluation (on the CPU a per-step Jacobian or VJP would pay XLA's per-kernel
    # overhead ~100 times per step); then the recursion lam_k = J_k^T lam_{k+1} + A_k.
    def step_jacobians(yf, tk, tk1, jac):
        return jac(lambda yy, pf: step(yy, pf, tk, tk1)[0], argnums=(0, 1))(yf, p_flat)

    def chunked_jacobians(lam, ct_p, jac):
        """lam_k = J_k^T lam_{k+1} + A_k with the step Jacobians of C steps built per vectorised
        call (padding steps past M get J = I, dPhi/dp = 0), chunks from the last to the first."""
        eye = jnp.eye(n)

        def chunk_body(carry):
            c, lam, ct_p = carry
            start = c * C
            ks = start + jnp.arange(C)
            ok = ks < M
            yk = jnp.where(ok[:, None], y_at(ks), y_flat0)
            tk = jnp.where(ok, t_at(ks), t0)
            tk1 = jnp.where(ok, t_at(ks + 1), t0)
            Jy, Jp = jax.vmap(lambda y, a, b: step_jacobians(y, a, b, jac))(yk, tk, tk1)
            Jy = jnp.where(ok[:, None, None], Jy, eye)
            Jp = jnp.where(ok[:, None, None], Jp, 0.0)
            extra = (jnp.zeros((C, n)) if A_k is None else
                     jax.ops.segment_sum(A_v, A_k - start, num_segments=C))

            def back(lam_next, inp):
                J, e = inp
                return J.T @ lam_next + e, lam_next

            lam, lam_next = jax.lax.scan(back, lam, (Jy, extra), reverse=True, unroll=8)
            return c - 1, lam, ct_p + jnp.einsum("knp,kn->p", Jp, lam_next)

        n_chunks = (M + C - 1) // C
        _, lam, ct_p = jax.lax.while_loop(lambda c: c[0] >= 0, chunk_body, (n_chunks - 1, lam, ct_p))
        return lam, ct_p

    if mode == "vjp":
        lam, ct_p = _sequential_vjps(step, y_at, t_at, M, lam, ct_p, p_flat, A_k, A_v)
    else:
        lam, ct_p = chunked_jacobians(lam, ct_p, jax.jacfwd if mode == "forward" else jax.jacrev)
    if g_ys is not None and ends_only:
        a, b = fn_vjp(t0, y_flat0, jtu.tree_map(lambda g: g[0], g_ys))
        lam, ct_p = lam + a, ct_p + b
    return unravel_y(lam), unravel_p(ct_p)


def _sequential_vjps(step, y_at, t_at, M, lam, ct_p, p_flat, A_k, A_v):
    """lam_k = J_k^T lam_{k+1} + A_k by one VJP of the step per accepted step, k = M-1 .. 0
    (cost independent of n and P; the choice for large states)."""

    def body(c):
        k, j, lam, ct_p = c
        tk, tk1 = t_at(k), t_at(k + 1)
        yk = y_at(k[None])[0]
        _, vjp = jax.vjp(lambda yy, pf: step(yy, pf, tk, tk1)[0], yk, p_flat)
        a, b = vjp(lam)
        if A_k is not None:  # saved outputs of step k (A_k is sorted)
            j, a = jax.lax.while_loop(
                lambda ic: (ic[0] >= 0) & (A_k[jnp.maximum(ic[0], 0)] == k),
                lambda ic: (ic[0] - 1, ic[1] + A_v[ic[0]]), (j, a))
        return k - 1, j, a, ct_p + b

    j0 = jnp.asarray(-1 if A_k is None else A_k.shape[0] - 1)
    _, _, lam, ct_p = jax.lax.while_loop(lambda c: c[0] >= 0, body, (M - 1, j0, lam, ct_p))
    return lam, ct_p
