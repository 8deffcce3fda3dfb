"""``nhjax.simulate_batch`` in this process: many trajectories at once, on all local CPU cores.

A batch varies any of the initial state, the system's parameters and the
control's parameters (leading axis 0 of the arrays of the batched ones, chosen
with ``in_axes``). Each member gets its own adaptive step sizes, so it is solved
to the same tolerance, and to the same result, as a single ``simulate()`` call.

How it runs: the batch is cut into chunks of at most ``chunk_size`` members, at
least one per worker. A chunk is one compiled program (``lockstep.py``): it
checks every member's initial state, then steps ``lanes`` members together, each
with its own step size, with the member axis last so that the stage arithmetic
vectorizes, and float64 sin/cos evaluated by vectorizable polynomials
(``fast_trig.py``; a chunk whose arguments leave their exact range, |x| > 8.2e5,
is solved again with the C library's). When a member ends, its lane takes the
next member of the chunk, so members that need many times the steps of others
do not hold the rest up. When an ``adjoint`` is given the chunk is vmapped
``diffrax.diffeqsolve`` instead (differentiable, every member stepped until the
slowest ends). Chunks are dispatched to every local CPU device, or, with a
single device, to ``workers`` threads that run compiled chunks concurrently
(XLA releases the GIL). Memory stays bounded: a chunk holds only its working
state, and only the requested saved times are kept. Values a user varies
(initial states, parameters, control coefficients, tolerances, times, the
number of members up to a chunk's capacity) are arguments of the compiled
chunk: a new batch of the same structure runs without tracing again.

Results: a ``BatchTrajectory`` with every member's status ("ok", "guard",
"max_steps", "non-finite", "solver failure", "bad x0") and reason. By default
bad initial states (NaN, constraint violation, outside a chart, ill-posed),
failed solves and members stopped by a chart guard raise ``BatchError`` listing
member indices, reasons and times; ``on_error="return"`` returns them instead,
with the other members intact (a sweep's mode).
"""

from __future__ import annotations

import collections
import dataclasses
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from .._validate import (
    as_state,
    axes_dict,
    check_control,
    check_memory,
    check_saveat,
    check_state,
    choice,
    integer,
    member_failures,
    member_report,
    save_times_count,
    solver_settings,
    time_span,
    to_device,
)
from .. import _programs
from ..errors import ParameterError, StateError
from . import progress as progress_meter
from ._batch_types import BAD_X0, GUARD, MAX_STEPS, NONFINITE, OK, SOLVER, BatchError, BatchTrajectory
from .impacts import simulate_batch_impacts
from .lockstep import _lanes_last, lockstep_solve, vmap_lanes
from .simulate import (
    Trajectory,
    _build_problem,
    _configure,
    _defines_power,
    _drifting_constraints,
    _finish,
    _from_plain,
    _guard_of,
    _reports_accuracy,
    _solve,
    _to_plain,
)

__all__ = ["simulate_batch_local"]


def _batch_size(args, axes, in_axes, owner):
    """The number of members: the common leading size of the batched arguments' arrays
    (ParameterError naming the argument when one has none or they disagree; none at
    all is refused too)."""
    sizes = {}
    for name, arg, ax in zip(("system", "x0", "control"), args, axes):
        if ax is None:
            continue
        leaves = [a for a in jtu.tree_leaves(arg) if hasattr(a, "shape")]
        if not leaves:
            raise ParameterError(f"{owner}: in_axes marks '{name}' as batched but it has no arrays", "in_axes",
                                 in_axes)
        for a in leaves:
            if a.ndim == 0:
                raise ParameterError(
                    f"{owner}: '{name}' is batched but has a scalar leaf: every array needs the batch "
                    "axis. Build the batch with nhjax.stack([member, ...]) or "
                    "equinox.filter_vmap(lambda p: Scene(param=p))(params)", "in_axes", in_axes)
            sizes.setdefault(a.shape[0], name)
    if len(sizes) != 1:
        raise ParameterError(
            f"{owner}: batched arguments disagree on the batch size: "
            + ", ".join(f"{n} has {b}" for b, n in sizes.items()), "in_axes", in_axes)
    B = next(iter(sizes))
    if B == 0:
        raise ParameterError(f"{owner}: the batch has no members ({sizes[0]} has a leading axis of length 0): "
                             "pass at least one", sizes[0])
    return B


def _refuse_single_state(system, x0, owner):
    """StateError when ``x0``, batched along axis 0, is one state of ``system`` and its
    rows are not (a single member's shape): they would be taken as members of the
    wrong shape. (A system whose states may have any shape passes both tests: nothing
    is refused here.)"""
    try:
        check_state(system, x0, owner=owner)
    except StateError:
        return  # not a single state: the members' shapes are checked as usual
    try:
        check_state(system, _take(x0, 0, 0), owner=owner)
        return
    except (StateError, IndexError):
        pass
    shape = f"shape {tuple(np.shape(x0))}" if hasattr(x0, "shape") else "a single state"
    raise StateError(f"{owner}: x0 ({shape}) is one state of {type(system).__name__}, not a batch: pass one row per "
                     "member, a leading member axis (x0[None] for a batch of one), or in_axes={'x0': None} to give "
                     "every member this start", "x0")


def _take(tree, ax, sl):
    if ax is None:
        return tree
    return jtu.tree_map(lambda a: a[sl] if hasattr(a, "shape") and a.ndim else a, tree)


#: Traces of the chunk programs (tests count them: a batch with new values of the same
#: structure must reuse the compiled program without tracing again).
TRACES = collections.Counter()


def _report_and_configure(system, x0, control, t0, tol, project, options, axes):
    """Inside a chunk's trace: every member's initial-state report (nhjax._validate's
    member_report, vmapped: finiteness, group membership, constraints, chart guards,
    regularity, the control at t0; projected if asked), the members not to solve
    (``skip``), and the options with the structural defaults resolved (guard names,
    projection after each step)."""
    x0p, report = eqx.filter_vmap(
        lambda s, x, c: member_report(s, c, x, t0, project), in_axes=axes
    )(system, x0, control)
    skip = ~report["finite"] | ~report["control_finite"]
    for part in report["group"]:
        skip = skip | ~(report["group"][part] <= tol) | ~(report["group_det"][part] > 0)
    for r in report["constraints"].values():
        skip = skip | ~(r <= tol)
    for m in report["margins"].values():
        skip = skip | ~(m > 0)
    for g in report["guards"].values():
        skip = skip | ~(g > 0)
    if options["project_steps"] is None:
        options = dict(options, project_steps=_drifting_constraints(report["constraints"]))
    axes = (axes[0], 0, axes[2])  # the checked (maybe projected) x0 has a member axis
    return x0p, report, skip, tuple(report["guards"]), options, axes


@eqx.filter_jit
def _solve_chunk(system, x0, control, n, t0, t1, tol, project, options, axes):
    """One chunk by vmapped diffeqsolve (differentiable; the path when an adjoint is
    given). Returns (trajectories, initial-state report, False)."""
    TRACES["vmapped"] += 1
    del n  # every member is solved (padding too)
    x0, report, _, guard_names, options, axes = _report_and_configure(system, x0, control, t0, tol, project,
                                                                      options, axes)

    def member(s, x, c):
        solver, controller, adjoint, dt0, static, ts = _configure(s, c, x, t0, t1, guard_names, **options)
        return _solve(s, c, x, t0, t1, ts, solver, controller, adjoint, dt0, static)

    return eqx.filter_vmap(member, in_axes=axes)(system, x0, control), report, jnp.zeros((), bool)


def _lockstep_chunk_impl(system, x0, control, n, t0, t1, tol, project, options, axes, fast_trig=True, lanes=None):
    """One chunk by the lock-step integrator (lockstep.py): the same steps per member as
    _solve_chunk, batch axis last inside, ``lanes`` members at a time; the first ``n``
    members are solved (the rest is padding), members whose initial state fails the
    checks are not. Returns (trajectories, initial-state report, trig_out_of_range)."""
    TRACES["lockstep"] += 1
    x0, report, skip, guard_names, options, axes = _report_and_configure(system, x0, control, t0, tol,
                                                                         project, options, axes)

    def build(s, x, c):
        solver, controller, _, dt0, st, ts = _configure(s, c, x, t0, t1, guard_names, **options)
        return _build_problem(s, c, x, t0, t1, ts, solver, controller, dt0, st) + (st,)

    # static (a dataclass, not an array) passes through vmap_lanes unbatched
    problem, y0, static = vmap_lanes(build, tuple(None if ax is None else 0 for ax in axes))(
        system, x0, control)
    args = (system if axes[0] is None else _lanes_last(system),
            control if axes[2] is None else _lanes_last(control))
    args_axes = (None if axes[0] is None else -1, None if axes[2] is None else -1)
    sol, bad = lockstep_solve(problem, y0, args, args_axes, n_members=n, skip=skip, lanes=lanes,
                              fast_trig=fast_trig)
    traj = eqx.filter_vmap(
        lambda s, x, c, so: _finish(s, c, x, t0, so, static), in_axes=axes + (0,)
    )(system, x0, control, sol)
    return traj, report, bad


_lockstep_chunk = eqx.filter_jit(_lockstep_chunk_impl)


def _lockstep_chunk_plain(*args):
    """_lockstep_chunk with its Trajectory in builtin containers (for the program cache)."""
    traj, report, bad = _lockstep_chunk_impl(*args)
    return _to_plain(traj), report, bad


def _cached_lockstep(args, state_names):
    """The compiled lock-step chunk with its program from nhjax's program cache (a new
    process does not trace it again); None when it cannot be cached."""
    run = _programs.compiled("batch", _lockstep_chunk_plain, args, _COMPILER_OPTIONS)
    if run is None:
        return None

    def solve(*a):
        plain, report, bad = run(*a)
        return _from_plain(plain, state_names), report, bad

    return solve


#: XLA options for the lock-step chunks, chosen by profiling each kernel with
#: jax.profiler (benchmarks/batch_throughput.py measures the chunks): 512-bit vectors
#: where the CPU has them (AVX-512; ignored elsewhere), since the member axis is last and
#: the stage arithmetic vectorizes over it; and no YNNPACK fusions, which turned each
#: member's error norm into a small dot product that cost more than the arithmetic it
#: replaced. An XLA that does not know an option compiles without it.
_COMPILER_OPTIONS = {"xla_cpu_prefer_vector_width": 512, "xla_cpu_experimental_ynn_fusion_type": ""}


def _compile(lowered, options):
    """The lowered chunk compiled (options this XLA does not know dropped), run one at a
    time if it calls LAPACK on a batch of matrices (``_programs.batched_lapack``: the
    chunks run in several threads at once)."""
    try:
        exe = lowered.compile(compiler_options=options)
    except Exception:  # an option this XLA does not have
        if not options:
            raise
        return _compile(lowered, dict(list(options.items())[:-1]))
    return _programs.one_at_a_time(exe, _programs.batched_lapack(exe))


#: Fewest members per worker for which splitting a batch across workers pays (a smaller
#: batch runs as one chunk on one worker: the second dispatch costs more than it gains).
_MIN_SPLIT = 64

#: Most lanes per chunk (members stepped together). A lane costs per step whether or not
#: its member is still running, so lanes well below the members per chunk let a few long
#: members finish while the others' lanes are refilled (see _default_lanes); and a step of
#: up to ~128 lanes of a small system stays below the size up to which XLA compiles the
#: stepping loop into one function (nhjax/_xla_flags.py).
_MAX_LANES = 128


def _pow2ceil(n: int) -> int:
    return 1 << max(0, int(n) - 1).bit_length()


def _default_lanes(capacity: int) -> int:
    """Lanes for a chunk of ``capacity`` members. A chunk's time is about
    max(total steps / lanes, steps of its longest member) x (cost of one step of all
    lanes); a step's cost per lane falls with the lanes (vectorization) down to about 32
    lanes, and the last few members of a chunk are finished one lane at a time
    (lockstep.py). An eighth of the members, 32 to _MAX_LANES (at most the chunk's
    members), keeps the first term near the second for step counts that differ many-fold
    (chosen by timing lane counts on the cat's unequal batches of
    benchmarks/batch_throughput.py)."""
    return int(min(capacity, _MAX_LANES, max(32, _pow2ceil(capacity // 8))))


def _plan(B: int, workers: int, chunk_size: int):
    """(capacity, members per chunk, chunk starts): chunks of at most ``chunk_size``
    members, at least one per worker once there are _MIN_SPLIT members per worker, in
    whole rounds of ``workers``; the capacity is a power of two (or chunk_size), so
    that batches of other sizes reuse the compiled chunk."""
    per_worker = -(-B // workers) if B >= workers * _MIN_SPLIT else B
    capacity = max(1, min(int(chunk_size), _pow2ceil(per_worker)))
    n_chunks = -(-B // capacity)
    if n_chunks > workers and n_chunks % workers:
        n_chunks += workers - n_chunks % workers
    size = -(-B // n_chunks)
    return capacity, size, list(range(0, B, size))


_POOLS: dict = {}
_COMPILED: dict = {}  # chunk programs by argument structure (not lowered again on every call)


def _compile_key(fn, args):
    """Hashable description of everything the compiled chunk depends on: the pytree
    structure, array shapes and dtypes, and the values of non-array leaves; None if
    some leaf is unhashable (then no caching)."""
    leaves, treedef = jtu.tree_flatten(args)
    desc = tuple((jnp.shape(a), jnp.result_type(a)) if eqx.is_array(a) else a for a in leaves)
    key = (fn, treedef, desc)
    try:
        hash(key)
    except TypeError:
        return None
    return key


def _pool(workers: int) -> ThreadPoolExecutor:
    """One long-lived pool per worker count: threads started once, not on every call."""
    if workers not in _POOLS:
        _POOLS[workers] = ThreadPoolExecutor(workers, thread_name_prefix="nhjax-batch")
    return _POOLS[workers]


def simulate_batch_local(
    system,
    x0,
    t1,
    *,
    t0=0.0,
    control=None,
    in_axes=None,
    chunk_size: int = 8192,
    lanes: int | None = None,
    workers: int | None = None,
    progress: bool | None = None,
    saveat=2,
    solver=None,
    rtol: float | None = None,
    atol: float | None = None,
    dt0=None,
    max_steps: int | None = None,
    stepsize_controller=None,
    jump_ts=None,
    adjoint=None,
    project: bool = False,
    project_steps: bool | None = None,
    constraint_tol: float = 1e-8,
    on_guard: str = "raise",
    on_error: str = "raise",
    track_work: bool | None = None,
    diagnostics: bool = True,
    **impact_options,
) -> BatchTrajectory:
    """``simulate_batch`` in this process (no ``client``): systems with one-sided
    constraints go to the lock-step impact batch, the others to the chunks of this
    module. Arguments and result as ``nhjax.simulate_batch``."""
    owner = "simulate_batch"
    if hasattr(system, "unilateral_constraints"):
        return simulate_batch_impacts(
            system, x0, t1, t0=t0, control=control, in_axes=in_axes, chunk_size=chunk_size, lanes=lanes,
            workers=workers, progress=progress, saveat=saveat, solver=solver, rtol=rtol, atol=atol, dt0=dt0,
            max_steps=max_steps, stepsize_controller=stepsize_controller, jump_ts=jump_ts, adjoint=adjoint,
            project=project, project_steps=project_steps, constraint_tol=constraint_tol, on_guard=on_guard,
            on_error=on_error, track_work=track_work, diagnostics=diagnostics, **impact_options)
    if impact_options:
        raise TypeError(f"simulate_batch got unexpected keyword arguments {sorted(impact_options)} "
                        f"({type(system).__name__} has no one-sided constraints, for which they would be meant)")
    choice("on_guard", on_guard, ("raise", "stop"), owner=owner)
    choice("on_error", on_error, ("raise", "return"), owner=owner)
    rtol = 1e-8 if rtol is None else rtol
    atol = 1e-8 if atol is None else atol
    solver_settings(rtol=rtol, atol=atol, dt0=dt0, max_steps=max_steps, constraint_tol=constraint_tol, owner=owner)
    t0, t1 = time_span(t0, t1, owner=owner)
    check_saveat(saveat, t0, t1, owner=owner)
    axes_d = axes_dict(in_axes, ("system", "x0", "control"), owner=owner, default={"x0": 0})
    for k, v in axes_d.items():
        if v not in (0, None):
            raise ParameterError(f"{owner}: in_axes['{k}'] must be 0 (batched along axis 0) or None (shared), "
                                 f"got {v!r}", "in_axes", in_axes)
    x0 = as_state(system, x0, owner=owner, xp=np)
    axes = (axes_d.get("system"), axes_d.get("x0"), axes_d.get("control"))
    if axes[1] == 0:
        _refuse_single_state(system, x0, owner)
    B = _batch_size((system, x0, control), axes, in_axes, owner)
    if lanes is not None:
        lanes = integer("lanes", lanes, minimum=1, owner=owner)
    chunk_size = integer("chunk_size", chunk_size, minimum=1, owner=owner)
    if workers is not None:
        workers = integer("workers", workers, minimum=1, owner=owner, what="concurrent chunks")

    # Static checks on one member (structure, shapes, control signature); the values of
    # every member are checked inside the chunks (member_report).
    ex_sys, ex_x0, ex_ctrl = (_take(a, ax, 0) for a, ax in zip((system, x0, control), axes))
    check_state(ex_sys, ex_x0, name="each member's x0", owner=owner)
    check_control(ex_sys, ex_ctrl, owner=owner)

    if track_work is None:
        # energy - work is the batch's accuracy report of last resort: the work is an extra
        # state component (a third more time per step on the cat), so it is tracked by
        # default only when the system reports no invariant and no constraint of its own
        track_work = (ex_ctrl is not None and _defines_power(ex_sys)
                      and not _reports_accuracy(ex_sys, jtu.tree_map(to_device, ex_x0), to_device(t0)))
    # Values a user varies enter the compiled chunk as arrays (new values: no new trace);
    # numpy ones, since every eager jnp.asarray is a dispatch of its own.
    arr = lambda v: None if v is None else np.asarray(v, float)  # noqa: E731
    options = dict(
        saveat=saveat if isinstance(saveat, (int, np.integer)) else arr(saveat), solver=solver,
        rtol=arr(rtol), atol=arr(atol), dt0=arr(dt0), max_steps=max_steps,
        stepsize_controller=stepsize_controller, jump_ts=arr(jump_ts), adjoint=adjoint,
        project_steps=project_steps, track_work=track_work, progress=False, diagnostics=diagnostics,
    )
    t0a, t1a, tol = np.asarray(t0, float), np.asarray(t1, float), np.asarray(constraint_tol, float)
    # Memory: the saved states of the whole batch must fit (ResourceError, a MemoryError).
    n_save = save_times_count(saveat)
    state_bytes = sum(np.asarray(a).size for a in jtu.tree_leaves(ex_x0)) * 8
    check_memory(B * n_save * state_bytes * 3,  # states, plus invariants/us/work headroom
                 f"keeping the saved states ({B} members x {n_save} saved times x {state_bytes} bytes)",
                 "save fewer times (saveat=2 keeps t0 and t1) or split the batch", owner=owner)

    devices = jax.local_devices()
    if workers is None:
        workers = len(devices) if len(devices) > 1 else (2 if (os.cpu_count() or 1) >= 2 else 1)
    capacity, size, starts = _plan(B, workers, chunk_size)
    if progress is None:
        progress = len(starts) > 4

    # The lock-step integrator unless the batch is to be differentiated (an adjoint was
    # given): vmapped diffrax then. Its float64 sin/cos are vectorized (fast_trig.py); a
    # chunk whose arguments left their exact range is re-run with the library ones.
    lockstep = adjoint is None
    n_lanes = None
    if lockstep:
        n_lanes = min(capacity, int(lanes) if lanes is not None else _default_lanes(capacity))
        chunk_fn = _lockstep_chunk

        def call(fn, s, x, c, n, fast):
            return fn(s, x, c, n, t0a, t1a, tol, project, options, axes, fast, n_lanes)
    else:
        chunk_fn = _solve_chunk

        def call(fn, s, x, c, n, fast):
            return fn(s, x, c, n, t0a, t1a, tol, project, options, axes)

    def chunk_args(i):
        """Chunk i's members, padded to the capacity with copies of its last member
        (host-side numpy: an eager jax slice would be a dispatch of its own per leaf)."""
        lo = starts[i]
        n = min(size, B - lo)
        idx = np.minimum(np.arange(lo, lo + capacity), lo + n - 1)
        out = []
        for a, ax in zip((system, x0, control), axes):
            if ax is not None and not (lo == 0 and n == capacity == B):
                a = jtu.tree_map(lambda v: np.asarray(v)[idx] if hasattr(v, "shape") and v.ndim else v, a)
                if len(devices) > 1:
                    a = jax.device_put(a, devices[i % len(devices)])
            out.append(a)
        return (*out, np.int32(n))

    # Compile once, ahead of time, before any concurrency (every chunk has the same
    # shapes); with several devices, jit compiles per device on first use instead.
    solve = chunk_fn
    first = chunk_args(0)
    if len(devices) == 1:
        all_args = (*first[:3], jax.device_put(first[3]), t0a, t1a, tol, project, options, axes)
        all_args += (True, n_lanes) if lockstep else ()
        key = _compile_key(chunk_fn, all_args)
        solve = _COMPILED.get(key) if key is not None else None
        if solve is None:
            if lockstep:  # its traced program from nhjax's program cache when it can be
                solve = _cached_lockstep(all_args, tuple(ex_sys.state_names))
            if solve is None:
                solve = _compile(chunk_fn.lower(*all_args), _COMPILER_OPTIONS if lockstep else {})
            if key is not None:
                if len(_COMPILED) >= 32:  # keep the 32 newest programs
                    _COMPILED.pop(next(iter(_COMPILED)))
                _COMPILED[key] = solve

    lock = threading.Lock()
    results = [None] * len(starts)

    def run(i):
        s, x, c, n = first if i == 0 else chunk_args(i)
        out, report, bad = call(solve, s, x, c, n, True)
        if lockstep and bool(bad):  # some sin/cos argument beyond fast_trig.LIMIT: library functions
            out, report, _ = call(chunk_fn, s, x, c, n, False)
        out, report = jax.device_get((out, report))  # numpy (joined and cut on the host)
        with lock:
            results[i] = (out, report, int(n))
        return i

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=B, desc="nhjax batch", unit="traj")
        bar.set_postfix_str(progress_meter.STARTING)  # until the first chunk is back

    def done(i):
        if bar is not None:
            if bar.postfix:
                bar.set_postfix_str("", refresh=False)
            bar.update(results[i][2])

    if len(devices) > 1:
        done(run(0))  # compiles (on device 0) before any concurrency
    rest = range(1 if len(devices) > 1 else 0, len(starts))
    if workers > 1 and len(rest) > 1:
        for i in _pool(workers).map(run, rest):
            done(i)
    else:
        for i in rest:
            done(run(i))
    if bar is not None:
        bar.close()

    # join the chunks' members (padding dropped) on the host, then back to jax arrays
    def join(*parts):
        return np.concatenate([p[:n] for p, (_, _, n) in zip(parts, results)])

    traj, report = jtu.tree_map(join, *[(r[0], r[1]) for r in results])
    return _statuses(traj, report, system, axes, on_guard, on_error, float(t0), float(constraint_tol), project)


def _statuses(traj, report, system, axes, on_guard, on_error, t0, tol, project):
    """Per-member statuses and reasons from the joined results on the host (``traj``'s
    leaves numpy arrays); returns them as a ``BatchTrajectory`` of jax arrays, or raises
    BatchError as on_guard/on_error ask."""
    B = len(report["finite"])
    result = np.asarray(traj.result._value)
    status = np.full(B, OK, np.int8)
    reasons = dict(member_failures(report, constraint_tol=tol, project=project))
    bad_x0 = np.zeros(B, bool)
    bad_x0[list(reasons)] = True
    status[bad_x0] = BAD_X0
    ev = int(diffrax.RESULTS.event_occurred._value)
    ok_code = int(diffrax.RESULTS.successful._value)
    solved = ~bad_x0
    fin = np.ones(B, bool)
    for a in jtu.tree_leaves(traj.x_end):
        fin &= np.isfinite(np.asarray(a)).reshape(B, -1).all(1)
    stopped = solved & (result == ev)
    status[stopped] = GUARD
    maxed = solved & (result == int(diffrax.RESULTS.max_steps_reached._value))
    status[maxed] = MAX_STEPS
    other = solved & (result != ok_code) & (result != ev) & ~maxed
    status[other] = SOLVER
    status[solved & ~fin & ((result == ok_code) | (result == ev))] = NONFINITE
    guard_names = tuple(report["guards"])
    used = set()
    x_end = jax.device_get(traj.x_end)
    for j in np.nonzero(stopped)[0]:
        name = _guard_of(_take(system, axes[0], j), guard_names, jtu.tree_map(lambda a: a[j], x_end))
        used.add(name)
        reasons[int(j)] = f"stopped by chart guard '{name}'"
    for j in np.nonzero(maxed)[0]:
        reasons[int(j)] = "max_steps exhausted (or NaN/inf ahead)"
    for j in np.nonzero(other)[0]:
        reasons[int(j)] = ("minimum step size reached" if result[j] == int(diffrax.RESULTS.dt_min_reached._value)
                           else f"solver failure (diffrax code {int(result[j])})")
    for j in np.nonzero(status == NONFINITE)[0]:
        reasons[int(j)] = "state became NaN/inf"
    traj = jax.device_put(traj)
    traj = BatchTrajectory(**{f.name: getattr(traj, f.name) for f in dataclasses.fields(Trajectory)}
                           | dict(guard=", ".join(sorted(used)), status=status, reasons=reasons))
    if on_error == "return":
        return traj
    t_final = np.asarray(traj.t_final)

    def fail(what, mask):
        members = np.nonzero(mask)[0].tolist()
        raise BatchError(what, members, [reasons[m] for m in members],
                         [t0 if status[m] == BAD_X0 else float(t_final[m]) for m in members], traj)

    if bad_x0.any():
        fail("bad initial states", bad_x0)
    if (status >= MAX_STEPS).any():
        fail("failed solves", status >= MAX_STEPS)
    if stopped.any() and on_guard == "raise":
        fail("a chart guard stopped the solve (pass on_guard='stop' to keep these members)", stopped)
    return traj
