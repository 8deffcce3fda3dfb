"""Lock-step batch integrator: many solves of one problem, stepped together, batch axis last.

Why not ``vmap`` of ``diffrax.diffeqsolve``: on the CPU it is no faster per
member-step than a scalar compiled loop, for four reasons (found by profiling:
perf, XLA's optimized HLO, per-kernel traces with jax.profiler):

1. the batch axis leads (``[B, n]``), so each vector-field fusion builds its
   ``[B, n]`` output by a concatenate along the short minor axis: XLA's loop
   emitter evaluates it element by element, recomputes shared subexpressions
   for each of the n components and does not vectorize;
2. float64 ``sin``/``cos`` are scalar C-library calls per element, see
   ``fast_trig``;
3. the vmapped while loop carries and selects diffrax's whole loop state
   (saving, events, progress meter, dense-output bookkeeping) every step;
4. a vmapped loop runs until its slowest member ends: members that need a tenth
   of its steps idle for the rest.

Here the loop is ours and holds only what a step needs; every array keeps the
member axis last (``[n, L]``: each state component is a contiguous vector over
the L lanes, so the stage arithmetic fuses and vectorizes); the pieces of a
step are diffrax's own, vmapped over the lanes: ``solver.step``,
``controller.init``/``adapt_step_size``, the solver's dense interpolation, the
event's root find. So each member takes exactly the steps a single
``simulate()`` takes, and saves, stops at guards and fails the same way
(``tests/test_batch.py`` compares them member by member).

Lanes and the queue: every member's start (initial step, controller and FSAL
state: diffeqsolve's initialisation) is computed for the whole chunk at once;
the members wait in a queue, those with the smallest first step first (they
tend to need the most steps, and a long member started late would leave the
other lanes idle at the end); L lanes step together; a member that ends (t1
reached, guard, failure, step budget) stays in its lane until R = L/16 lanes
are idle, then every idle lane writes its member's results into the member's
own slot and takes the next member of the queue. Once the queue is empty and at
most L/4 lanes still run, those members are finished one at a time in a one-lane
loop: a step of the lanes costs as much with one member running as with L, so a few
long members would otherwise keep every lane stepping. The stepping loop carries
only the lanes, so it stays small (XLA compiles it into one function,
nhjax/_xla_flags.py); a guard's dense output is recomputed after the loop for the
members that stopped, instead of being stored every step.

Not covered (``simulate_batch`` falls back to vmapped diffrax): differentiation
(the loop has no reverse-mode rule). sin/cos inside a while loop or a conditional
keep libm's functions (inside a scan, such as the RKMK stage scan of
``large_vector_field`` systems, they are replaced too).
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import optimistix as optx

from ..lie.spaces import AbstractSpace, Euclidean, is_space
from .clip_floor import prev_floats
from .fast_trig import with_fast_trig
from .projection import ProjectedSolver
from .rkmk import LieODETerm, _AbstractRKMK

__all__ = ["lazy_cond", "lockstep_solve", "vmap_lanes"]


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


def lazy_cond(pred, true_fn, false_fn, *operands):
    """``jax.lax.cond(pred, true_fn, false_fn, *operands)`` for code vmapped over lanes.

    Under ``jax.vmap`` with a per-lane predicate, ``lax.cond`` becomes a select: both
    branches run on every lane at every call. Here ``false_fn`` runs as before and
    ``true_fn`` behind a conditional on whether the predicate holds for *some* lane
    (``equinox.internal.unvmap_any``, a predicate that stays unbatched under vmap), its
    results then selected lane by lane: a rarely taken, costly branch (an impact's root
    find, a dip search) costs nothing in the steps where no lane takes it, and each lane
    gets what ``lax.cond`` would give it. Without vmap both branches' work is that of a
    ``lax.cond`` plus ``false_fn`` where the predicate holds: for vmapped code only."""
    if_false = false_fn(*operands)

    def with_true(if_false):
        return jtu.tree_map(lambda a, b: jnp.where(pred, a, b), true_fn(*operands), if_false)

    return jax.lax.cond(eqxi.unvmap_any(pred), with_true, lambda if_false: if_false, if_false)


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


def _clip_to_end(tprev, tnext, t1, t1_clip_floor, keep_step):
    # diffrax's rule (diffrax/_integrate.py): within 100 ulp of t1, step to t1 exactly.
    clip = tnext > t1_clip_floor
    tclip = jnp.where(keep_step, t1, tprev + 0.5 * (t1 - tprev))
    return jnp.where(clip, tclip, tnext)


def _take(tree, idx):
    """Array leaves ``[..., M]`` -> ``[..., K]`` at member indices ``idx`` ``[K]`` (clipped)."""
    return jtu.tree_map(lambda a: jnp.take(a, idx, axis=-1, mode="clip"), tree)


class _Rows:
    """Packs the array leaves of a tree like ``example`` (leaves ``[..., N]``, any N) into
    one ``[rows, N]`` array per dtype, and back. A refill moves a whole lane's state (tens
    of leaves) in one gather or scatter per dtype instead of one per leaf: XLA's CPU
    runtime pays for each kernel it dispatches, and a refill of one per leaf was ~100."""

    def __init__(self, example):
        leaves, self.treedef = jtu.tree_flatten(example)
        self.spec, rows = [], {}
        for a in leaves:
            dt = jnp.dtype(a.dtype)
            n = int(np.prod(a.shape[:-1], dtype=int))
            self.spec.append((dt, rows.get(dt, 0), n, a.shape[:-1]))
            rows[dt] = rows.get(dt, 0) + n

    def pack(self, tree):
        groups = {}
        for (dt, _, n, shape), a in zip(self.spec, jtu.tree_leaves(tree)):
            groups.setdefault(dt, []).append(jnp.reshape(jnp.asarray(a, dt), (n, a.shape[-1])))
        return {dt: jnp.concatenate(parts, axis=0) for dt, parts in groups.items()}

    def unpack(self, packed):
        leaves = [jnp.reshape(packed[dt][r0:r0 + n], shape + packed[dt].shape[-1:])
                  for dt, r0, n, shape in self.spec]
        return jtu.tree_unflatten(self.treedef, leaves)


def _put(tree, idx, vals):
    """Array leaves ``[..., M]`` with ``vals`` ``[..., K]`` written at ``idx`` ``[K]``;
    out-of-range indices are dropped (indices must be unique: callers give the dropped
    entries distinct out-of-range values)."""
    return jtu.tree_map(lambda a, v: a.at[..., idx].set(v, mode="drop", unique_indices=True), tree, vals)


#: Largest per-lane saved-states buffer (bytes, all lanes) kept in the lanes (see lane_saves).
_LANE_SAVES_BYTES = 65536


def lockstep_solve(problem, y0, args, args_axes, *, n_members=None, skip=None, lanes=None, fast_trig=True):
    """Solve the members of ``problem`` (an ``adjoint._Problem`` whose array leaves carry a
    trailing member axis of size M) from ``y0`` (leaves ``[..., M]``) with ``args``
    batched along their last axis where ``args_axes`` says -1 (None: shared).

    ``lanes`` (L <= M, default M) members are stepped at once; when a member ends, its
    lane takes the next member of the queue (members ``0 .. n_members - 1`` in order,
    except those marked in ``skip``, which are not solved). Returns ``(out, bad)``:
    ``out`` is ``_Problem.run``'s dict with a leading member axis on every leaf; ``bad``
    is True when a replaced sin/cos saw an argument beyond ``fast_trig.LIMIT`` (re-run
    with ``fast_trig=False``)."""
    M = jtu.tree_leaves(problem.t1)[0].shape[-1]
    L = M if lanes is None else max(1, min(int(lanes), M))
    R = max(1, L // 16)  # idle lanes that trigger a refill (which fills every idle lane)
    solver, term, event, sub = problem.solver, problem.term, problem.event, problem.sub
    ends_only = sub.ts is None
    successful = diffrax.RESULTS.successful._value
    ok_event = diffrax.RESULTS.event_occurred._value
    max_steps = problem.max_steps
    args_axes = tuple(args_axes)
    member = jnp.arange(M)

    not_run = member >= (M if n_members is None else n_members)
    if skip is not None:
        not_run = not_run | skip
    n_run = jnp.sum(~not_run).astype(jnp.int32)

    def vm(f, pr, a, *per_member):
        """``f(problem, args, *xs)`` per member; every array argument has a trailing member
        axis (any width), args where args_axes says -1."""
        return vmap_lanes(f, (-1, args_axes) + (-1,) * len(per_member))(pr, a, *per_member)

    # diffeqsolve's controller set-up (time runs forwards), once per member
    problem = eqx.tree_at(lambda p: p.controller, problem,
                          vm(lambda pr, a: pr.controller.wrap(1), problem, args))
    pr_arr, pr_static = eqx.partition(problem, eqx.is_array)
    args_parts = [eqx.partition(a, eqx.is_array) if ax is not None else (None, a)
                  for a, ax in zip(args, args_axes)]
    args_arr = tuple(p[0] for p in args_parts)

    def problem_of(arr):
        return eqx.combine(arr, pr_static)

    def args_of(arr):
        return tuple(a if ax is None else eqx.combine(d, p[1])
                     for d, ax, p, a in zip(arr, args_axes, args_parts, args))

    # The step itself: nhjax's Runge-Kutta-Munthe-Kaas solvers are written leaf by leaf
    # with elementwise stage arithmetic, so they run on whole [..., L] arrays (per-member
    # step sizes broadcast along the trailing axis): only the vector field, the group
    # operations and a projection are vmapped. That keeps every state component a
    # contiguous [L] vector through the stages. Other diffrax solvers: vmapped per member.
    inner = solver.solver if isinstance(solver, ProjectedSolver) else solver
    batch_level = isinstance(inner, _AbstractRKMK)
    if batch_level:
        spaces_b = jtu.tree_map(lambda sp: sp if isinstance(sp, Euclidean) else _LanesSpace(sp),
                                term.spaces, is_leaf=is_space)
        term_b = LieODETerm(vmap_lanes(term.vector_field, (-1, -1, args_axes)), spaces_b)
        solver_b = solver
        if isinstance(solver, ProjectedSolver):
            split = solver.entry is not None
            solver_b = ProjectedSolver(
                inner, vmap_lanes(solver.project, (-1, -1, args_axes)),
                entry=vmap_lanes(solver.entry, (-1, -1, args_axes, None)) if split else None,
                project_positions=vmap_lanes(solver.project_positions, (-1, -1, args_axes)) if split else None)

    dense_static = []  # the dense output's non-array part, recorded by take_step's first trace

    def interpolation(t0_, t1_, dense_arrays):
        # per member; dense_arrays: the array part of the step's dense_info
        d = eqx.combine(dense_arrays, dense_static[0])
        if batch_level:
            d = dict(d, spaces=term.spaces)
        return solver.interpolation_cls(t0=t0_, t1=t1_, **d)

    def take_step(pr, a, y, tprev, tnext, sstate, made_jump):
        """One step of every lane: (y1, y_err, dense arrays, solver state, result)."""
        if batch_level:
            out = solver_b.step(term_b, tprev, tnext, y, a, sstate, made_jump)
        else:
            out = vm(lambda pr_, a_, yy, tp, tn, ss, mj: solver.step(term, tp, tn, yy, a_, ss, mj),
                     pr, a, y, tprev, tnext, sstate, made_jump)
        y1, y_err, dense, s1, sres = out
        dense_arr, dstat = eqx.partition(dense, eqx.is_array)
        if not dense_static:
            dense_static.append(dstat)
        sres = jnp.broadcast_to(sres._value, tprev.shape)
        return y1, y_err, dense_arr, s1, sres

    # -- a member's start (diffeqsolve's initialisation) --
    def init(pr, a, y):
        tnext, cstate = pr.controller.init(term, pr.t0, pr.t1, y, pr.dt0, a, solver.func,
                                           solver.error_order(term))
        tnext = jnp.minimum(tnext, pr.t1)
        sstate = solver.init(term, pr.t0, tnext, y, a)
        ev = None if event is None else event.cond_fn(pr.t0, y, a)
        as_arrays = lambda tree: jtu.tree_map(jnp.asarray, tree)  # noqa: E731 (Python scalars too)
        return tnext, as_arrays(cstate), as_arrays(sstate), prev_floats(pr.t1, 100), ev

    # Per-member results, filled in as members end (solved members overwrite these).
    t0_m = problem.t0 + jnp.zeros(M)
    zeros_m = jnp.zeros(M, jnp.int32)
    out = dict(t_final=t0_m, y_end=y0, num_steps=zeros_m, num_accepted=zeros_m, num_rejected=zeros_m,
               result=jnp.full(M, diffrax.RESULTS.internal_error._value, jnp.int32))
    if not ends_only:
        n_ts = sub.ts.shape[0]
        out["save_index"] = zeros_m
    if event is not None:
        out.update(ev_mask=jnp.zeros(M, bool), ev_tprev=t0_m, ev_tnext=t0_m, ev_y=y0,
                   ev_made_jump=jnp.zeros(M, bool))

    # Every member's start, computed once for the chunk (vectorized); lanes gather it.
    starts = vm(init, problem, args, y0)
    # The queue: members to solve (skipped members and padding beyond n_members at the
    # back), those with the smallest first step first: they tend to need the most steps,
    # and a long member started early does not leave the lanes idle at the end.
    h0 = starts[0] - problem.t0
    order = jnp.lexsort((jnp.where(jnp.isnan(h0), jnp.inf, h0), not_run)).astype(jnp.int32)

    # Lanes: a member index (M: empty), that member's problem and args, its solver state.
    # Every member's start values in one table per dtype (a refill gathers its columns).
    start_rows = _Rows((pr_arr, args_arr, y0, starts))
    start_table = start_rows.pack((pr_arr, args_arr, y0, starts))

    lane_saves = False
    if not ends_only:  # the saved states
        ex = vm(lambda pr, a, yy: sub.fn(pr.t0, yy, a), problem, args, y0)

        def no_saves(K):
            return jtu.tree_map(lambda e: jnp.full((n_ts,) + e.shape[:-1] + (K,), jnp.inf, e.dtype), ex)

        # Few saved times: each lane keeps its member's saved states, written by a select
        # and moved to the member's slot when it ends, so that the stepping loop has no
        # scatter (XLA compiles no loop with a scatter into one function). Many: a select
        # over all of them per save costs more than the kernels, and the lanes write into
        # the members' slots directly (a scatter per save).
        row_bytes = sum(int(np.prod(e.shape[:-1], dtype=int)) * e.dtype.itemsize for e in jtu.tree_leaves(ex))
        lane_saves = n_ts * row_bytes * L <= _LANE_SAVES_BYTES

    def start_values(new):
        """Lane values of members ``new`` ``[K]`` at their start (diffeqsolve's initialisation)."""
        pr, a, y, (tnext, cstate, sstate, floor, ev) = start_rows.unpack(
            {dt: jnp.take(tab, new, axis=-1, mode="clip") for dt, tab in start_table.items()})
        t0 = problem_of(pr).t0 + 0.0 * tnext
        f, zi = jnp.zeros(new.shape, bool), jnp.zeros(new.shape, jnp.int32)
        vals = dict(mem=new, pr=pr, a=a, y=y, tprev=t0, tnext=tnext, sstate=sstate, cstate=cstate,
                    floor=floor, made_jump=f, result=jnp.full(new.shape, successful, jnp.int32),
                    num_steps=zi, num_accepted=zi, num_rejected=zi)
        if not ends_only:
            vals["save_index"] = zi
        if lane_saves:
            vals["ys"] = no_saves(new.shape[0])
        if event is not None:
            vals.update(ev_value=ev, ev_mask=f, ev_tprev=t0, ev_tnext=tnext, ev_y=y, ev_sstate=sstate,
                        ev_made_jump=f)
        return vals

    lane = jnp.arange(L)
    c = start_values(order[lane])  # the first L members of the queue (L <= M)
    c["mem"] = jnp.where(lane < n_run, c["mem"], M)
    c["next"] = jnp.minimum(n_run, L)
    if event is not None:
        out["ev_sstate"] = jtu.tree_map(lambda s: jnp.zeros(s.shape[:-1] + (M,), s.dtype), c["sstate"])
    if lane_saves:
        out["ys"] = no_saves(M)
    elif not ends_only:
        c["ys"] = no_saves(M)

    def active_of(c):
        t1 = problem_of(c["pr"]).t1
        return ((c["mem"] < M) & (c["tprev"] < t1) & (c["result"] == successful)
                & (c["num_steps"] < max_steps))

    out_rows = _Rows(out)

    def retire(c, outp, which):
        """Write the lanes where ``which`` [L] holds a member into its results (``outp``:
        the results packed by out_rows); empty those lanes."""
        has = which & (c["mem"] < M)
        running = (c["tprev"] < problem_of(c["pr"]).t1) & (c["result"] == successful)
        vals = dict(t_final=c["tprev"], y_end=c["y"], num_steps=c["num_steps"],
                    num_accepted=c["num_accepted"], num_rejected=c["num_rejected"],
                    result=jnp.where(running, diffrax.RESULTS.max_steps_reached._value, c["result"]))
        if not ends_only:
            vals["save_index"] = c["save_index"]
        if lane_saves:
            vals["ys"] = c["ys"]
        if event is not None:
            vals.update(ev_mask=c["ev_mask"], ev_tprev=c["ev_tprev"], ev_tnext=c["ev_tnext"],
                        ev_y=c["ev_y"], ev_sstate=c["ev_sstate"], ev_made_jump=c["ev_made_jump"])
        col = jnp.where(has, c["mem"], M + lane)  # out of range: dropped (and unique)
        packed = out_rows.pack({k: vals[k] for k in out})
        outp = {dt: outp[dt].at[:, col].set(packed[dt], mode="drop", unique_indices=True) for dt in outp}
        return dict(c, mem=jnp.where(has, M, c["mem"])), outp

    def refill(state):
        """Retire the idle lanes and start the next members of the queue in them (the k-th
        idle lane takes the k-th next member)."""
        c, outp = state
        idle = ~active_of(c)
        c, outp = retire(c, outp, idle)
        q = c["next"] + jnp.cumsum(idle) - 1
        valid = idle & (q < n_run)
        vals = start_values(order[jnp.minimum(q, M - 1)])
        c = dict(c)
        c.update(_where(valid, vals, {k: c[k] for k in vals}))
        c["next"] = c["next"] + jnp.sum(valid).astype(jnp.int32)
        return c, outp

    def want_refill(c):
        return (c["next"] < n_run) & (jnp.sum(~active_of(c)) >= R)

    # -- step-size control (per member) --
    def member_adapt(pr, a, y, y1, y_err, tprev, tnext, cstate):
        y_err = jtu.tree_map(lambda e: jnp.where(jnp.isnan(e), jnp.inf, e), y_err)
        keep, tp, tn, mj, c1, cres = pr.controller.adapt_step_size(
            tprev, tnext, y, y1, a, y_err, solver.error_order(term), cstate)
        return keep, tp, tn, jnp.asarray(mj), c1, cres._value

    def body(c):
        """One step of every active lane (finished and empty lanes keep their state)."""
        active = active_of(c)
        pr, a = problem_of(c["pr"]), args_of(c["a"])
        y1, y_err, dense, s1, sres = take_step(pr, a, c["y"], c["tprev"], c["tnext"], c["sstate"],
                                               c["made_jump"])
        keep, tp, tn, mj, c1, cres = vm(member_adapt, pr, a, c["y"], y1, y_err, c["tprev"], c["tnext"],
                                        c["cstate"])
        tp = jnp.minimum(tp, pr.t1)
        tn = _clip_to_end(tp, tn, pr.t1, c["floor"], keep)
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
            def save_time(idx):  # each lane's next save time
                return jnp.take_along_axis(pr.sub.ts, jnp.minimum(idx, n_ts - 1)[None], 0)[0]

            def pending(sc):
                idx = sc[0]
                return active & keep & (idx < n_ts) & (save_time(idx) <= c["tnext"])

            def save_one(sc):
                idx, ys = sc
                pend = pending(sc)
                t_s = save_time(idx)

                def value(pr_, a_, t0_, t1_, d, t):
                    return sub.fn(t, interpolation(t0_, t1_, d).evaluate(t), a_)

                vals = vm(value, pr, a, c["tprev"], c["tnext"], dense, t_s)
                row = jnp.where(pend, idx, n_ts)  # out of range: not written
                if lane_saves:
                    hit = jnp.arange(n_ts)[:, None] == row[None, :]  # [n_ts, K]
                    ys = jtu.tree_map(
                        lambda buf, v: jnp.where(hit.reshape((n_ts,) + (1,) * (buf.ndim - 2) + hit.shape[1:]),
                                                 v[None], buf),
                        ys, vals)
                else:
                    col = jnp.where(pend, c["mem"], M + jnp.arange(idx.shape[0]))  # unique, also where dropped
                    ys = jtu.tree_map(
                        lambda buf, v: buf.at[row, ..., col].set(jnp.moveaxis(v, -1, 0), mode="drop",
                                                                 unique_indices=True),
                        ys, vals)
                return idx + pend, ys

            idx, ys = jax.lax.while_loop(lambda sc: jnp.any(pending(sc)), save_one,
                                         (c["save_index"], c["ys"]))
            new["save_index"], new["ys"] = idx, ys

        if event is not None:
            val = vm(lambda pr_, a_, t, yy: event.cond_fn(t, yy, a_), pr, a, tp, new["y"])
            mask = jnp.sign(c["ev_value"]) != jnp.sign(val)
            res = jnp.where(mask, ok_event, res)
            new["ev_value"], new["ev_mask"] = val, mask
            new["ev_tprev"], new["ev_tnext"] = c["tprev"], c["tnext"]
            new["ev_y"], new["ev_sstate"], new["ev_made_jump"] = c["y"], c["sstate"], c["made_jump"]
        new["result"] = res
        lane_keys = [k for k in new if k not in ("ys", "save_index", "next", "mem", "pr", "a")]
        for k in lane_keys:
            new[k] = _where(active, new[k], c[k])
        return new

    step_fn = with_fast_trig(body, c, trig=fast_trig)

    def steps(lc):
        c, bad = lc
        c, b = step_fn(c)
        return c, bad | b

    # The tail: once the queue is empty and at most T lanes still run, those members are
    # finished one at a time in a one-lane loop. A step of the lanes costs as much with one
    # member running as with all L; the one-lane loop, compiled into one function like the
    # lanes' (nhjax/_xla_flags.py), costs a fraction of it per step, so a few long members
    # no longer keep L lanes stepping for the last hundreds of steps. Not when the lanes
    # write saved states into the members' slots: with that scatter the one-lane loop runs
    # kernel by kernel and costs about what a step of the lanes does.
    T = L // 4 if (L >= 8 and (ends_only or lane_saves)) else 0

    def in_tail(c):
        return (c["next"] >= n_run) & (jnp.sum(active_of(c)) <= T)

    def run_lanes(state):
        """Step the lanes until enough of them are idle to be refilled (or, once the queue
        is empty, until at most T run), then refill."""
        c, out, bad = state
        c, bad = jax.lax.while_loop(
            lambda lc: jnp.any(active_of(lc[0])) & ~want_refill(lc[0]) & ~lc[1] & ~in_tail(lc[0]),
            steps, (c, bad))
        c, out = jax.lax.cond(want_refill(c), refill, lambda st: st, (c, out))
        return c, out, bad

    def queue_left(state):
        c, _, bad = state
        return (jnp.any(active_of(c)) | (c["next"] < n_run)) & ~bad & ~in_tail(c)

    c, outp, bad = jax.lax.while_loop(queue_left, run_lanes, (c, out_rows.pack(out), jnp.zeros((), bool)))

    if T:
        # every entry of c is per lane here (the saved states too, when any) but the queue's
        # position, which the body leaves alone
        lane_part = lambda c: {k: v for k, v in c.items() if k != "next"}  # noqa: E731

        def finish_one(i, c):
            j = tail_lanes[i]

            def run(c):
                one = dict(_take(lane_part(c), j[None]), next=c["next"])
                one = jax.lax.while_loop(lambda o: jnp.any(active_of(o)), body, one)
                return dict(c, **_put(lane_part(c), j[None], lane_part(one)))

            return jax.lax.cond(j < L, run, lambda c: c, c)

        tail_lanes = jnp.nonzero(active_of(c) & ~bad, size=T, fill_value=L)[0]
        c = jax.lax.fori_loop(0, T, finish_one, c)
    c, outp = retire(c, outp, jnp.ones(L, bool))
    o = out_rows.unpack(outp)
    tfinal, yfinal, result = o["t_final"], o["y_end"], o["result"]

    event_mask = None
    if event is not None:
        event_mask = o["ev_mask"]
        # the event step of each member that had one, taken again for its dense output
        def root_find(_):
            def member_root(pr, a, m, tprev, tnext, d, y, nsteps):
                interp = interpolation(tprev, tnext, d)

                def fn(t, _):
                    return jnp.where(m, event.cond_fn(t, interp.evaluate(t), a), tnext - t)

                sol = optx.root_find(fn, event.root_finder, y0=tnext,
                                     options=dict(lower=tprev, upper=tnext), throw=False)
                ok = sol.result == optx.RESULTS.successful
                y_at = jtu.tree_map(lambda u, v: jnp.where(nsteps == 0, u, v), y, interp.evaluate(sol.value))
                return sol.value, y_at, ok, diffrax.RESULTS.promote(sol.result)._value

            _, _, ev_dense, _, _ = take_step(problem, args, o["ev_y"], o["ev_tprev"], o["ev_tnext"],
                                             o["ev_sstate"], o["ev_made_jump"])
            t_ev, y_ev, ok, code = vm(member_root, problem, args, event_mask, o["ev_tprev"], o["ev_tnext"],
                                      ev_dense, yfinal, o["num_steps"])
            return (jnp.where(event_mask, t_ev, tfinal), _where(event_mask, y_ev, yfinal),
                    jnp.where(event_mask & ~ok, code, result))

        tfinal, yfinal, result = jax.lax.cond(jnp.any(event_mask), root_find,
                                              lambda _: (tfinal, yfinal, result), None)

    if ends_only:
        first = vm(lambda pr, a, yy: sub.fn(pr.t0, yy, a), problem, args, y0)
        last = vm(lambda pr, a, t, yy: sub.fn(t, yy, a), problem, args, tfinal, yfinal)
        ts = jnp.stack([t0_m, tfinal])
        ys = jtu.tree_map(lambda u, v: jnp.stack([u, v]), first, last)
    else:
        rows = jnp.arange(n_ts)[:, None]
        ts = jnp.where(rows < o["save_index"][None], problem.sub.ts, jnp.inf)
        ys = o["ys"] if lane_saves else c["ys"]
        if event is not None:  # nothing saved after a guard's event time
            late = ts > tfinal[None]
            ts = jnp.where(late, jnp.inf, ts)
            ys = jtu.tree_map(
                lambda a: jnp.where(late.reshape(late.shape[:1] + (1,) * (a.ndim - 2) + late.shape[1:]),
                                    jnp.inf, a), ys)
    out = _lanes_first(dict(
        ts=ts, ys=ys, t_final=tfinal, y_end=yfinal,
        num_steps=o["num_steps"], num_accepted_steps=o["num_accepted"],
        num_rejected_steps=o["num_rejected"], event_mask=event_mask,
    ))
    out["result"] = eqx.tree_at(lambda r: r._value, diffrax.RESULTS.successful, result)  # [M]
    return out, bad
