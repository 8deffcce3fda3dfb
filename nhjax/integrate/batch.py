"""``nhjax.simulate_batch``: many trajectories at once, on all local CPU cores.

A batch varies any of the initial state, the system's parameters and the
control's parameters (leading axis 0 of the arrays of the batched ones, chosen
with ``in_axes``). Each member gets its own adaptive step sizes, so it is solved
to the same tolerance, and to the same result, as a single ``simulate()`` call.

How it runs: the batch is cut into equal chunks of at most ``chunk_size``
members, and into at least one chunk per worker (whole rounds of ``workers``
chunks). A chunk is one compiled lock-step solve (``lockstep.py``): all its
members step together, each with its own step size (finished ones idle), with
the batch axis last so that the stage arithmetic vectorizes, and float64
sin/cos evaluated by vectorizable polynomials (``fast_trig.py``; a chunk whose
arguments leave their exact range, |x| > 8.2e5, is solved again with the C
library's). When an ``adjoint`` is given the chunk is vmapped
``diffrax.diffeqsolve`` instead (differentiable; 2-2.5x slower).
Chunks are dispatched to every local CPU device, or, with a single device, to
``workers`` threads that run compiled chunks concurrently (XLA releases the
GIL), so both cores of a laptop work. Memory stays bounded: a chunk holds only
its working state, and only the requested saved times are kept.

Measured (``benchmarks/batch_throughput.py``, falling cat, rtol 1e-8, 2 cores):
1024 members 85.5k and 92.8k trajectories/s in two runs, 16384: 108k and 109k,
against 52k/76k and 49k/68k for a numba-compiled Dormand-Prince in a parallel
loop in the same runs (vmapped diffrax: 33-39k at 1024).

Errors name the members: bad initial states (NaN, constraint violation, outside
a chart, ill-posed) and failed solves (max_steps, NaN, chart guard) raise
``BatchError`` listing member indices, reasons and times.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from ..errors import NhjaxError
from .lockstep import _lanes_last, lockstep_solve, vmap_lanes
from .simulate import _build_problem, _configure, _drifting_constraints, _finish, _initial_report, _solve

__all__ = ["BatchError", "simulate_batch", "stack"]


def stack(members):
    """Stack equally-structured systems, controls or states into one batched pytree."""
    members = list(members)
    if not members:
        raise ValueError("stack() needs at least one member")
    return jtu.tree_map(lambda *a: jnp.stack([jnp.asarray(x) for x in a]), *members)


class BatchError(NhjaxError, RuntimeError):
    """Some members of a batch failed. ``members``: indices; ``reasons``: per member;
    ``times``: time of failure per member (t0 for bad initial states);
    ``trajectory``: the batch result (None for bad initial states)."""

    def __init__(self, what, members, reasons, times, trajectory=None):
        self.members, self.reasons, self.times, self.trajectory = members, reasons, times, trajectory
        shown = "; ".join(
            f"member {m}: {r} at t = {t:.6g}" for m, r, t in list(zip(members, reasons, times))[:8]
        )
        more = f" (and {len(members) - 8} more)" if len(members) > 8 else ""
        super().__init__(f"{what} in {len(members)} member(s) of the batch: {shown}{more}")


def _batch_size(args, axes):
    sizes = {}
    for name, arg, ax in zip(("system", "x0", "control"), args, axes):
        if ax is None:
            continue
        leaves = [a for a in jtu.tree_leaves(arg) if hasattr(a, "shape")]
        if not leaves:
            raise ValueError(f"in_axes marks '{name}' as batched but it has no arrays")
        for a in leaves:
            if a.ndim == 0:
                raise ValueError(
                    f"'{name}' is batched but has a scalar leaf: every array needs the batch "
                    "axis. Build the batch with nhjax.stack([member, ...]) or "
                    "equinox.filter_vmap(lambda p: Scene(param=p))(params)"
                )
            sizes.setdefault(a.shape[0], name)
    if len(sizes) != 1:
        raise ValueError(
            "batched arguments disagree on the batch size: "
            + ", ".join(f"{n} has {b}" for b, n in sizes.items())
        )
    return next(iter(sizes))


def _take(tree, ax, sl):
    if ax is None:
        return tree
    return jtu.tree_map(lambda a: a[sl] if hasattr(a, "shape") and a.ndim else a, tree)


def _available_memory_bytes():
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


@eqx.filter_jit
def _report_chunk(system, x0, control, t0, project, axes):
    return eqx.filter_vmap(
        lambda s, x, c: _initial_report(s, c, x, t0, project), in_axes=axes
    )(system, x0, control)


@eqx.filter_jit
def _solve_chunk(system, x0, control, t0, t1, options, guard_names, axes):
    def member(s, x, c):
        solver, controller, adjoint, dt0, static, ts = _configure(s, c, x, t0, t1, guard_names, **options)
        return _solve(s, c, x, t0, t1, ts, solver, controller, adjoint, dt0, static)

    return eqx.filter_vmap(member, in_axes=axes)(system, x0, control)


@eqx.filter_jit
def _lockstep_chunk(system, x0, control, t0, t1, options, guard_names, axes, fast_trig):
    """One chunk by the lock-step integrator (lockstep.py): the same steps per member as
    _solve_chunk, batch axis last inside. Returns (trajectories, trig_out_of_range)."""
    def build(s, x, c):
        solver, controller, _, dt0, st, ts = _configure(s, c, x, t0, t1, guard_names, **options)
        return _build_problem(s, c, x, t0, t1, ts, solver, controller, dt0, st) + (st,)

    # static (a dataclass, not an array) passes through vmap_lanes unbatched
    problem, y0, static = vmap_lanes(build, tuple(None if ax is None else 0 for ax in axes))(
        system, x0, control)
    args = (system if axes[0] is None else _lanes_last(system),
            control if axes[2] is None else _lanes_last(control))
    args_axes = (None if axes[0] is None else -1, None if axes[2] is None else -1)
    sol, bad = lockstep_solve(problem, y0, args, args_axes, fast_trig=fast_trig)
    traj = eqx.filter_vmap(
        lambda s, x, c, so: _finish(s, c, x, t0, so, static), in_axes=axes + (0,)
    )(system, x0, control, sol)
    return traj, bad


#: XLA options for the lock-step chunks (profiled per kernel with jax.profiler, cat,
#: 1024 members, one thread): 512-bit vectors where the CPU has them (AVX-512; ignored
#: elsewhere): 18.0 -> 15.1 ms; and no YNNPACK fusions: XLA turned each member's error
#: norm into a YNNPACK dot that took 10-25 % of the loop (4096 members: 50 -> 38 ms).
#: An XLA that does not know an option compiles without it.
_COMPILER_OPTIONS = {"xla_cpu_prefer_vector_width": 512, "xla_cpu_experimental_ynn_fusion_type": ""}


def _compile(lowered, options):
    try:
        return lowered.compile(compiler_options=options)
    except Exception:  # an option this XLA does not have
        if not options:
            raise
        return _compile(lowered, dict(list(options.items())[:-1]))


#: Fewest members per chunk for which splitting a batch across workers pays (measured on
#: the falling cat, rtol 1e-8, 2 cores, idle: B = 1024 as one chunk 14.5k traj/s, as
#: two 28.8k; B = 128: 14.3k as one, 10.7k as two; B = 512: 17.2k vs 19.7k).
_MIN_SPLIT = 256


@eqx.filter_jit
def _concatenate(results, B):
    """The chunks' trajectories as one, first B members (one dispatch, not one per leaf)."""
    return jtu.tree_map(lambda *a: jnp.concatenate(a)[:B], *results)


_POOLS: dict = {}
_COMPILED: dict = {}  # chunk programs by argument structure (lowering again cost ~0.5 ms a call)


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
    """One long-lived pool per worker count (starting threads cost ~2.5 ms per call)."""
    if workers not in _POOLS:
        _POOLS[workers] = ThreadPoolExecutor(workers, thread_name_prefix="nhjax-batch")
    return _POOLS[workers]


def simulate_batch(
    system,
    x0,
    t1,
    *,
    t0=0.0,
    control=None,
    in_axes=None,
    chunk_size: int = 1024,
    workers: int | None = None,
    progress: bool | None = None,
    saveat=2,
    solver=None,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    dt0=None,
    max_steps: int | None = None,
    stepsize_controller=None,
    jump_ts=None,
    adjoint=None,
    project: bool = False,
    project_steps: bool | None = None,
    constraint_tol: float = 1e-8,
    on_guard: str = "raise",
    track_work: bool | None = None,
    diagnostics: bool = True,
):
    """Simulate a batch of trajectories; returns a ``Trajectory`` whose arrays have a
    leading batch axis (``traj.xs[i]`` is member i's saved states).

    in_axes : dict with keys among "system", "x0", "control" giving 0 (batched along
        axis 0) or None; default ``{"x0": 0}``.
    chunk_size : at most this many members per compiled chunk (bounds memory; a batch
        of at least 256 x ``workers`` members is split into at least ``workers`` equal
        chunks; the last chunk is padded).
    workers : concurrent chunks (default: the number of local devices, or 2 threads
        on a single CPU device when the machine has at least 2 cores).
    progress : tqdm bar over chunks (default: on for more than 4 chunks).
    saveat : as in simulate(); default 2 (t0 and t1), the cheap choice for big batches.
    Other arguments as ``nhjax.simulate``.
    """
    if on_guard not in ("raise", "stop"):
        raise ValueError("on_guard must be 'raise' or 'stop'")
    axes_d = {"x0": 0} if in_axes is None else dict(in_axes)
    unknown = set(axes_d) - {"system", "x0", "control"}
    if unknown:
        raise ValueError(f"in_axes keys must be among 'system', 'x0', 'control'; got {sorted(unknown)}")
    for k, v in axes_d.items():
        if v not in (0, None):
            raise ValueError(f"in_axes['{k}'] must be 0 or None, got {v}")
    x0 = jtu.tree_map(lambda a: jnp.asarray(a, float), x0)
    axes = (axes_d.get("system"), axes_d.get("x0"), axes_d.get("control"))
    B = _batch_size((system, x0, control), axes)
    if not float(t1) > float(t0):
        raise ValueError(f"t1 = {float(t1)} must be greater than t0 = {float(t0)}")

    # Static checks on one member (shapes, control signature) through simulate's own checks.
    ex_sys, ex_x0, ex_ctrl = (_take(a, ax, 0) for a, ax in zip((system, x0, control), axes))
    names = ex_sys.state_names
    if names and hasattr(ex_x0, "shape") and ex_x0.shape != (len(names),):
        raise ValueError(
            f"each member's x0 has shape {ex_x0.shape}; {type(ex_sys).__name__} expects "
            f"{len(names)} components {names}"
        )
    if ex_ctrl is not None and ex_sys.control_dim == 0:
        raise ValueError(f"{type(ex_sys).__name__} takes no control input")

    options = dict(
        saveat=saveat, solver=solver, rtol=rtol, atol=atol, dt0=dt0, max_steps=max_steps,
        stepsize_controller=stepsize_controller, jump_ts=jump_ts, adjoint=adjoint,
        project_steps=project_steps, track_work=track_work, progress=False,
        diagnostics=diagnostics,
    )
    t0a, t1a = jnp.asarray(t0, float), jnp.asarray(t1, float)
    # Memory: the saved states of the whole batch must fit.
    n_save = saveat if isinstance(saveat, int) else len(np.asarray(saveat))
    state_bytes = sum(np.asarray(a).size for a in jtu.tree_leaves(ex_x0)) * 8
    need = B * n_save * state_bytes * 3  # states, plus invariants/us/work headroom
    avail = _available_memory_bytes()
    if need > 0.8 * avail:
        raise MemoryError(
            f"the batch would keep about {need / 2**30:.1f} GiB of saved states "
            f"({B} members x {n_save} saved times x {state_bytes} bytes), more than the "
            f"{avail / 2**30:.1f} GiB available: save fewer times (saveat=2 keeps t0 and t1) "
            "or split the batch"
        )

    devices = jax.local_devices()
    if workers is None:
        workers = len(devices) if len(devices) > 1 else (2 if (os.cpu_count() or 1) >= 2 else 1)
    workers = max(1, int(workers))
    # At least one chunk per worker once chunks keep >= _MIN_SPLIT members (a batch of
    # <= chunk_size members as ONE chunk left the second core idle; smaller chunks lose
    # more to dispatch than the second core gains), then equal chunks of ceil(B / n).
    n_chunks = max(-(-B // max(1, int(chunk_size))), min(workers, B // _MIN_SPLIT))
    if n_chunks % workers and n_chunks > workers:  # whole rounds: no worker waits on a last odd chunk
        n_chunks += workers - n_chunks % workers
    chunk = -(-B // n_chunks)
    starts = list(range(0, B, chunk))
    if progress is None:
        progress = len(starts) > 4

    def pad(tree, ax, lo):
        if ax is None:
            return tree
        if lo == 0 and chunk == B:
            return tree
        # host-side slices (numpy): an eager jax slice is a dispatch of ~0.15 ms per leaf
        if lo + chunk <= B:
            return jtu.tree_map(lambda a: np.asarray(a)[lo:lo + chunk] if hasattr(a, "shape") and a.ndim else a, tree)
        idx = np.minimum(np.arange(lo, lo + chunk), B - 1)  # pad the last chunk with copies
        return jtu.tree_map(lambda a: np.asarray(a)[idx] if hasattr(a, "shape") and a.ndim else a, tree)

    def chunk_args(lo, device):
        args = [pad(a, ax, lo) for a, ax in zip((system, x0, control), axes)]
        if len(devices) > 1:
            args = [jax.device_put(a, device) if ax is not None else a for a, ax in zip(args, axes)]
        return args

    # 1. initial states, all members (the chunks' arguments are kept for the solves)
    guard_names = None
    bad = []
    padded = {}
    for i, lo in enumerate(starts):
        s, x, c = padded[i] = chunk_args(lo, devices[i % len(devices)])
        _, finite, residuals, guards, margins = _report_chunk(s, x, c, t0a, project, axes)
        finite, residuals, guards, margins = jax.device_get((finite, residuals, guards, margins))
        guard_names = tuple(guards)
        if project_steps is None:
            project_steps = _drifting_constraints(residuals)
            options["project_steps"] = project_steps
        n = min(chunk, B - lo)
        checks = [(~np.asarray(finite[:n], bool), lambda j: "x0 contains NaN or inf")]
        checks += [(np.asarray(r[:n]) > constraint_tol,
                    lambda j, k=k, r=r: f"constraint '{k}' violated by {r[j]:.2e} (pass project=True)")
                   for k, r in residuals.items()]
        checks += [(~(np.asarray(m[:n]) > 0), lambda j, k=k: f"regularity condition '{k}' fails")
                   for k, m in margins.items()]
        checks += [(np.asarray(g[:n]) <= 0, lambda j, k=k: f"outside the chart ('{k}')")
                   for k, g in guards.items()]
        failing = np.zeros(n, bool)
        for mask, _ in checks:
            failing |= mask
        for j in np.nonzero(failing)[0]:
            reason = next(why(j) for mask, why in checks if mask[j])  # the first check that fails
            bad.append((lo + int(j), reason))
    if bad:
        m, r = zip(*bad)
        raise BatchError("bad initial states", list(m), list(r), [float(t0)] * len(m))

    # 2. the solves, chunk by chunk, on all cores
    lock = threading.Lock()
    results = [None] * len(starts)

    def chunk_inputs(i):
        s, x, c = padded.pop(i)
        if project:
            x = eqx.filter_vmap(lambda ss, xx: ss.project(t0a, xx), in_axes=(axes[0], 0))(s, x)
        return s, x, c

    # The lock-step integrator unless the batch is to be differentiated (an adjoint was
    # given): vmapped diffrax then. Its float64 sin/cos are vectorized (fast_trig.py); a
    # chunk whose arguments left their exact range is re-run with the library ones.
    lockstep = adjoint is None
    if lockstep:
        def call(fn, s, x, c, fast):
            return fn(s, x, c, t0a, t1a, options, guard_names, axes, fast)
    else:
        def call(fn, s, x, c, fast):
            return fn(s, x, c, t0a, t1a, options, guard_names, axes), False
    chunk_fn = _lockstep_chunk if lockstep else _solve_chunk

    # Compile once, ahead of time, before any concurrency (every chunk has the same
    # shapes); with several devices, jit compiles per device on first use instead.
    solve, first_inputs = chunk_fn, None
    if len(devices) == 1:
        first_inputs = chunk_inputs(0)  # kept for run(0): padded (and projected) once
        extra = (True,) if lockstep else ()
        all_args = (*first_inputs, t0a, t1a, options, guard_names, axes, *extra)
        key = _compile_key(chunk_fn, all_args)
        solve = _COMPILED.get(key) if key is not None else None
        if solve is None:
            solve = _compile(chunk_fn.lower(*all_args), _COMPILER_OPTIONS if lockstep else {})
            if key is not None:
                if len(_COMPILED) >= 32:  # keep the 32 newest programs
                    _COMPILED.pop(next(iter(_COMPILED)))
                _COMPILED[key] = solve

    def run(i):
        s, x, c = first_inputs if (i == 0 and first_inputs is not None) else chunk_inputs(i)
        out, bad = call(solve, s, x, c, True)
        if bool(bad):  # some sin/cos argument beyond fast_trig.LIMIT: exact library functions
            out, _ = call(chunk_fn, s, x, c, False)
        out = jax.block_until_ready(out)
        if len(devices) > 1:  # gather on the first device (concatenated below)
            out = jax.device_put(out, devices[0])
        with lock:
            results[i] = out
        return i

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=B, desc="nhjax batch", unit="traj")
    def done(i):
        if bar is not None:
            bar.update(min(chunk, B - starts[i]))

    if len(devices) > 1:
        done(run(0))  # compiles (on device 0) before any concurrency
    first = 1 if len(devices) > 1 else 0
    if workers > 1 and len(starts) - first > 1:
        for i in _pool(workers).map(run, range(first, len(starts))):
            done(i)
    else:
        for i in range(first, len(starts)):
            done(run(i))
    if bar is not None:
        bar.close()

    if len(results) == 1 and chunk == B:
        traj = results[0]
    else:
        traj = _concatenate(results, B)
    _check_results(traj, guard_names, on_guard)
    return traj


def _check_results(traj, guard_names, on_guard):
    result, t_final = jax.device_get((traj.result._value, traj.t_final))
    ok = int(diffrax.RESULTS.successful._value)
    ev = int(diffrax.RESULTS.event_occurred._value)
    failed = np.nonzero((result != ok) & (result != ev))[0]
    if failed.size:
        known = {
            int(diffrax.RESULTS.max_steps_reached._value): "max_steps exhausted (or NaN/inf ahead)",
            int(diffrax.RESULTS.dt_min_reached._value): "minimum step size reached",
        }
        reasons = [known.get(int(result[i]), f"solver failure (diffrax code {int(result[i])})") for i in failed]
        raise BatchError("failed solves", failed.tolist(), reasons, t_final[failed].tolist(), traj)
    stopped = np.nonzero(result == ev)[0]
    if stopped.size and on_guard == "raise":
        raise BatchError(
            "a chart guard stopped the solve (pass on_guard='stop' to keep these members)",
            stopped.tolist(), [f"guard of {guard_names}" for _ in stopped], t_final[stopped].tolist(), traj,
        )
