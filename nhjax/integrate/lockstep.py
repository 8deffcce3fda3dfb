"""Lock-step batch integrator: many solves of one problem, stepped together, batch axis last.

``simulate_batch`` used to ``vmap`` ``diffrax.diffeqsolve``. On the CPU that costs
about 0.7 us per member per step on the falling cat (4096 members, one thread),
no better than a scalar compiled loop, for three reasons found by profiling
(perf + XLA's optimized HLO, benchmarks/batch_throughput.py case):

1. the batch axis leads (``[B, n]``), so each vector-field fusion builds its
   ``[B, n]`` output by a concatenate along the short minor axis: XLA's loop
   emitter evaluates it element by element, recomputes shared subexpressions
   for each of the n components and does not vectorize;
2. float64 ``sin``/``cos`` are scalar C-library calls per element (40 % of the
   time), see ``fast_trig``;
3. the vmapped while loop carries and selects ~60 buffers per step (diffrax's
   whole loop state: saving, events, progress meter, dense-output bookkeeping).

Per kernel (jax.profiler trace of the cat chunk, 1024 members, after the changes
below): the six right-hand-side fusions take about half of the loop, the error
norm 6 %, the rest is selects and bookkeeping; a guard's dense output is
recomputed after the loop instead of being stored every step (that store was
13 %), and batch.py compiles the chunks without YNNPACK fusions (the per-member
error norm had become a YNNPACK dot, 10-25 %).

Here the loop is ours and holds only what a step needs; every array keeps the
batch axis last (``[n, B]``: each state component is a contiguous ``[B]``
vector, so the stage arithmetic fuses and vectorizes); the pieces of a step are
diffrax's own, vmapped over the members: ``solver.step``,
``controller.init``/``adapt_step_size``, the solver's dense interpolation, the
event's root find. So each member takes exactly the steps a single
``simulate()`` takes, and saves, stops at guards and fails the same way
(``tests/test_batch.py`` compares them member by member).

Not covered (``simulate_batch`` falls back to vmapped diffrax): differentiation
(the loop has no reverse-mode rule). sin/cos inside a while loop or a conditional
keep libm's functions (inside a scan, such as the RKMK stage scan of
``large_vector_field`` systems, they are replaced too).
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import optimistix as optx

from ..lie.spaces import AbstractSpace, Euclidean, is_space
from .fast_trig import with_fast_trig
from .projection import ProjectedSolver
from .rkmk import LieODETerm, _AbstractRKMK

__all__ = ["lockstep_solve", "vmap_lanes"]


def _lanes_last(tree):
    return jtu.tree_map(lambda a: jnp.moveaxis(a, 0, -1) if jnp.ndim(a) else a, tree)


def _lanes_first(tree):
    return jtu.tree_map(lambda a: jnp.moveaxis(a, -1, 0) if jnp.ndim(a) else a, tree)


def vmap_lanes(f, in_axes):
    """``f`` vmapped with the batch axis last: ``in_axes`` is a tuple (one entry per
    positional argument, -1 or None, or a prefix tree of them); non-array leaves pass
    through; every array output gets the batch axis last, shared ones broadcast."""

    def wrapped(*args):
        dyn, stat = eqx.partition(args, eqx.is_array)
        out_stat = []

        def g(d):
            out = f(*eqx.combine(d, stat))
            od, os_ = eqx.partition(out, eqx.is_array)
            out_stat.append(os_)
            return od

        od = jax.vmap(g, in_axes=(in_axes,), out_axes=-1)(dyn)
        return eqx.combine(od, out_stat[0])

    return wrapped


class _LanesSpace(AbstractSpace):
    """A group-valued state part, every operation vmapped over the trailing batch axis
    (Euclidean parts need no wrapper: their operations are elementwise)."""

    space: AbstractSpace

    def retract(self, y0, sigma):
        return vmap_lanes(self.space.retract, (-1, -1))(y0, sigma)

    def dexpinv(self, sigma, v):
        return vmap_lanes(self.space.dexpinv, (-1, -1))(sigma, v)

    def ambient(self, y0, sigma):
        return vmap_lanes(self.space.ambient, (-1, -1))(y0, sigma)

    def algebra_zeros(self, y0):
        return vmap_lanes(self.space.algebra_zeros, (-1,))(y0)


def _where(pred, new, old):
    """Per member: new where pred else old (pred [B]; leaves [..., B])."""
    return jtu.tree_map(lambda a, b: jnp.where(pred, a, b), new, old)


def _prev_ulps(t, n):
    """t stepped n floats towards -inf (= n times jnp.nextafter(t, -inf), for finite t)."""
    bits = jax.lax.bitcast_convert_type(jnp.asarray(t, jnp.float64), jnp.int64)
    neg_zero_side = jnp.int64(-(2**63)) | n  # -n * (smallest subnormal)
    out = jnp.where(t > 0, bits - n, jnp.where(t < 0, bits + n, neg_zero_side))
    return jax.lax.bitcast_convert_type(out, jnp.float64)


def _clip_to_end(tprev, tnext, t1, t1_clip_floor, keep_step):
    # diffrax's rule (diffrax/_integrate.py): within 100 ulp of t1, step to t1 exactly.
    clip = tnext > t1_clip_floor
    tclip = jnp.where(keep_step, t1, tprev + 0.5 * (t1 - tprev))
    return jnp.where(clip, tclip, tnext)


def lockstep_solve(problem, y0, args, args_axes, fast_trig=True):
    """Solve ``problem`` (an ``adjoint._Problem`` whose array leaves carry a trailing
    batch axis) from ``y0`` (leaves ``[..., B]``) with ``args`` batched along their last
    axis where ``args_axes`` says -1 (None: shared). Returns ``(out, bad)``: ``out`` is
    ``_Problem.run``'s dict with a leading batch axis on every leaf; ``bad`` is True when
    a replaced sin/cos saw an argument beyond ``fast_trig.LIMIT`` (re-run with
    ``fast_trig=False``)."""
    B = jtu.tree_leaves(problem.t1)[0].shape[-1]
    solver, term, event, sub = problem.solver, problem.term, problem.event, problem.sub
    ends_only = sub.ts is None
    successful = diffrax.RESULTS.successful._value
    ok_event = diffrax.RESULTS.event_occurred._value

    def vm(f, *lanes):
        axes = (-1, tuple(args_axes)) + (-1,) * len(lanes)
        return vmap_lanes(f, axes)(problem, args, *lanes)

    # The step itself: nhjax's Runge-Kutta-Munthe-Kaas solvers are written leaf by leaf
    # with elementwise stage arithmetic, so they run on whole [..., B] arrays (per-member
    # step sizes broadcast along the trailing axis): only the vector field, the group
    # operations and a projection are vmapped. That keeps every state component a
    # contiguous [B] vector through the stages. Other diffrax solvers: vmapped per member.
    inner = solver.solver if isinstance(solver, ProjectedSolver) else solver
    batch_level = isinstance(inner, _AbstractRKMK)
    if batch_level:
        spaces_b = jtu.tree_map(lambda sp: sp if isinstance(sp, Euclidean) else _LanesSpace(sp),
                                term.spaces, is_leaf=is_space)
        term_b = LieODETerm(vmap_lanes(term.vector_field, (-1, -1, tuple(args_axes))), spaces_b)
        solver_b = solver
        if isinstance(solver, ProjectedSolver):
            solver_b = ProjectedSolver(inner, vmap_lanes(solver.project, (-1, -1, tuple(args_axes))))

    def interpolation(t0_, t1_, dense_arrays):
        # per member; dense_arrays: the array part of the step's dense_info
        d = eqx.combine(dense_arrays, dense_static[0])
        if batch_level:
            d = dict(d, spaces=term.spaces)
        return solver.interpolation_cls(t0=t0_, t1=t1_, **d)

    dense_static = []  # the dense output's non-array part, recorded by take_step's first trace

    # -- initial state (diffeqsolve's initialisation, per member) --
    def init(pr, a, y):
        ctrl = pr.controller.wrap(1)
        tnext, cstate = ctrl.init(term, pr.t0, pr.t1, y, pr.dt0, a, solver.func, solver.error_order(term))
        tnext = jnp.minimum(tnext, pr.t1)
        sstate = solver.init(term, pr.t0, tnext, y, a)
        floor = _prev_ulps(pr.t1, 100)
        ev = None if event is None else event.cond_fn(pr.t0, y, a)
        first = sub.fn(pr.t0, y, a) if ends_only else None
        as_arrays = lambda tree: jtu.tree_map(jnp.asarray, tree)  # noqa: E731 (Python scalars too)
        return ctrl, tnext, as_arrays(cstate), as_arrays(sstate), floor, ev, first

    ctrl_b, tnext, cstate, sstate, t1_floor, ev0, first = vm(init, y0)
    problem = eqx.tree_at(lambda p: p.controller, problem, ctrl_b)
    zeros_i = jnp.zeros(B, jnp.int32)
    carry = dict(
        y=y0, tprev=problem.t0 + 0.0 * tnext, tnext=tnext, sstate=sstate, cstate=cstate,
        made_jump=jnp.zeros(B, bool), result=jnp.full(B, successful, jnp.int32),
        num_steps=zeros_i, num_accepted=zeros_i, num_rejected=zeros_i,
    )
    if not ends_only:
        n_ts = sub.ts.shape[0]
        ex = vm(lambda pr, a, yy: sub.fn(pr.t0, yy, a), y0)
        carry["ys"] = jtu.tree_map(lambda e: jnp.full((n_ts,) + e.shape, jnp.inf, e.dtype), ex)
        carry["save_index"] = zeros_i
    def take_step(y, tprev, tnext, sstate, made_jump):
        """One step of every member: (y1, y_err, dense arrays, solver state, result)."""
        if batch_level:
            out = solver_b.step(term_b, tprev, tnext, y, args, sstate, made_jump)
        else:
            out = vm(lambda pr, a, yy, tp, tn, ss, mj: solver.step(term, tp, tn, yy, a, ss, mj),
                     y, tprev, tnext, sstate, made_jump)
        y1, y_err, dense, s1, sres = out
        dense_arr, dstat = eqx.partition(dense, eqx.is_array)
        if not dense_static:
            dense_static.append(dstat)
        sres = jnp.broadcast_to(sres._value, tprev.shape)
        return y1, y_err, dense_arr, s1, sres

    if event is not None:
        carry["ev_value"] = ev0
        carry["ev_mask"] = jnp.zeros(B, bool)
        carry["ev_tprev"] = carry["tprev"]
        carry["ev_tnext"] = tnext
        # the step in which a guard fired, to be taken again for its dense output after
        # the loop (storing every step's dense output cost 13 % of the loop)
        carry["ev_y"], carry["ev_sstate"], carry["ev_made_jump"] = y0, sstate, carry["made_jump"]
    lane = jnp.arange(B)

    def active_of(c):
        return (c["tprev"] < problem.t1) & (c["result"] == successful)

    # -- step-size control (per member) --
    def member_adapt(pr, a, y, y1, y_err, tprev, tnext, cstate):
        y_err = jtu.tree_map(lambda e: jnp.where(jnp.isnan(e), jnp.inf, e), y_err)
        keep, tp, tn, mj, c1, cres = pr.controller.adapt_step_size(
            tprev, tnext, y, y1, a, y_err, solver.error_order(term), cstate)
        return keep, tp, tn, jnp.asarray(mj), c1, cres._value

    def body(c):
        active = active_of(c)
        y1, y_err, dense, s1, sres = take_step(c["y"], c["tprev"], c["tnext"], c["sstate"], c["made_jump"])
        keep, tp, tn, mj, c1, cres = vm(member_adapt, c["y"], y1, y_err, c["tprev"], c["tnext"], c["cstate"])
        tp = jnp.minimum(tp, problem.t1)
        tn = _clip_to_end(tp, tn, problem.t1, t1_floor, keep)
        new = dict(c)
        new["y"] = _where(keep, y1, c["y"])
        new["sstate"] = _where(keep, s1, c["sstate"])
        new["cstate"] = c1
        new["made_jump"] = jnp.where(keep, mj, c["made_jump"])
        new["tprev"], new["tnext"] = tp, tn
        sres = jnp.where(keep, sres, successful)
        res = jnp.where(c["result"] == successful, sres, c["result"])
        res = jnp.where(res == successful, cres, res)
        new["num_steps"] = c["num_steps"] + 1
        new["num_accepted"] = c["num_accepted"] + keep
        new["num_rejected"] = c["num_rejected"] + ~keep

        if not ends_only:  # every save time passed by an accepted step, by dense output
            def save_time(idx):  # each member's next save time
                return jnp.take_along_axis(problem.sub.ts, jnp.minimum(idx, n_ts - 1)[None], 0)[0]

            def pending(sc):
                idx = sc[0]
                return active & keep & (idx < n_ts) & (save_time(idx) <= c["tnext"])

            def save_one(sc):
                idx, ys = sc
                pend = pending(sc)
                t_s = save_time(idx)

                def value(pr, a, t0_, t1_, d, t):
                    return sub.fn(t, interpolation(t0_, t1_, d).evaluate(t), a)

                vals = vm(value, c["tprev"], c["tnext"], dense, t_s)
                row = jnp.where(pend, idx, n_ts)  # out of range: dropped
                ys = jtu.tree_map(
                    lambda buf, v: buf.at[row, ..., lane].set(jnp.moveaxis(v, -1, 0), mode="drop", unique_indices=True),
                    ys, vals)
                return idx + pend, ys

            idx, ys = jax.lax.while_loop(lambda sc: jnp.any(pending(sc)), save_one,
                                         (c["save_index"], c["ys"]))
            new["save_index"], new["ys"] = idx, ys

        if event is not None:
            val = vm(lambda pr, a, t, yy: event.cond_fn(t, yy, a), tp, new["y"])
            mask = jnp.sign(c["ev_value"]) != jnp.sign(val)
            res = jnp.where(mask, ok_event, res)
            new["ev_value"], new["ev_mask"] = val, mask
            new["ev_tprev"], new["ev_tnext"] = c["tprev"], c["tnext"]
            new["ev_y"], new["ev_sstate"], new["ev_made_jump"] = c["y"], c["sstate"], c["made_jump"]
        new["result"] = res
        # members that had finished keep their state (the save buffer was only written
        # where a member was active)
        return {k: v if k in ("ys", "save_index") else _where(active, v, c[k]) for k, v in new.items()}

    max_steps = problem.max_steps
    if fast_trig:
        step_fn = with_fast_trig(body, carry)

        def loop_body(lc):
            i, c, bad = lc
            c, b = step_fn(c)
            return i + 1, c, bad | b
    else:
        def loop_body(lc):
            i, c, bad = lc
            return i + 1, body(c), bad

    def loop_cond(lc):
        i, c, bad = lc
        return (i < max_steps) & jnp.any(active_of(c)) & ~bad

    _, c, bad = jax.lax.while_loop(loop_cond, loop_body, (jnp.zeros((), jnp.int32), carry, jnp.zeros((), bool)))
    result = jnp.where(active_of(c), diffrax.RESULTS.max_steps_reached._value, c["result"])
    tfinal, yfinal = c["tprev"], c["y"]

    event_mask = None
    if event is not None:
        event_mask = c["ev_mask"]

        def root_find(_):
            def member(pr, a, m, tprev, tnext, d, y, nsteps):
                interp = interpolation(tprev, tnext, d)

                def fn(t, _):
                    return jnp.where(m, event.cond_fn(t, interp.evaluate(t), a), tnext - t)

                sol = optx.root_find(fn, event.root_finder, y0=tnext,
                                     options=dict(lower=tprev, upper=tnext), throw=False)
                ok = sol.result == optx.RESULTS.successful
                y_at = jtu.tree_map(lambda u, v: jnp.where(nsteps == 0, u, v), y, interp.evaluate(sol.value))
                return sol.value, y_at, ok, diffrax.RESULTS.promote(sol.result)._value

            _, _, ev_dense, _, _ = take_step(c["ev_y"], c["ev_tprev"], c["ev_tnext"], c["ev_sstate"],
                                             c["ev_made_jump"])
            t_ev, y_ev, ok, code = vm(member, event_mask, c["ev_tprev"], c["ev_tnext"], ev_dense,
                                      yfinal, c["num_steps"])
            return (jnp.where(event_mask, t_ev, tfinal), _where(event_mask, y_ev, yfinal),
                    jnp.where(event_mask & ~ok, code, result))

        tfinal, yfinal, result = jax.lax.cond(jnp.any(event_mask), root_find,
                                              lambda _: (tfinal, yfinal, result), None)

    if ends_only:
        last = vm(lambda pr, a, t, yy: sub.fn(t, yy, a), tfinal, yfinal)
        ts = jnp.stack([problem.t0 + 0.0 * tfinal, tfinal])
        ys = jtu.tree_map(lambda u, v: jnp.stack([u, v]), first, last)
    else:
        rows = jnp.arange(n_ts)[:, None]
        ts = jnp.where(rows < c["save_index"][None], problem.sub.ts, jnp.inf)
        ys = c["ys"]
        if event is not None:  # nothing saved after a guard's event time
            late = ts > tfinal[None]
            ts = jnp.where(late, jnp.inf, ts)
            ys = jtu.tree_map(
                lambda a: jnp.where(late.reshape(late.shape[:1] + (1,) * (a.ndim - 2) + late.shape[1:]),
                                    jnp.inf, a), ys)
    out = _lanes_first(dict(
        ts=ts, ys=ys, t_final=tfinal, y_end=yfinal,
        num_steps=c["num_steps"], num_accepted_steps=c["num_accepted"],
        num_rejected_steps=c["num_rejected"], event_mask=event_mask,
    ))
    out["result"] = eqx.tree_at(lambda r: r._value, diffrax.RESULTS.successful, result)  # [B]
    return out, bad
