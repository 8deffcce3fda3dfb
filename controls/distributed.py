"""A batch of optimal-control problems on a Dask distributed cluster.

``map_on_client(client, fn, grid)`` evaluates a user callable ``fn(point)`` at every
point of a grid (e.g. solve the somersault for each turn angle) on the workers of a
``dask.distributed.Client`` and returns the results in grid order, each with its
status: a point whose ``fn`` raised does not stop the sweep; its status says why.
Points are grouped into tasks of ``points_per_task`` so that each worker compiles the
problem once and reuses it for its next points (an OC solve compiles for tens of
seconds; grouping also amortizes the per-task overhead). A lost worker's tasks are
rescheduled by Dask; ``retries`` reruns a task that raised outside ``fn``.

``closed_loop_batch_on_client(client, mpc, plant, x0s, periods, ...)`` runs
``controls.closed_loop_batch`` in chunks of members on the workers and joins the
chunks into one ``ClosedLoop`` in member order (issue 42: a thousand closed loops and
more).

``somersault_turns`` is the example from the issue: the velocity-controlled falling
cat's optimal somersault for each turn angle, by Pontryagin shooting (continuation
from the fixed-theta loop), as a grid sweep whose workers each solve a sub-grid in
batched calls (``map_on_client(..., batched=True)`` with
``controls.solve_pontryagin_batch``).

This lives in ``controls`` (not ``nhjax.integrate.distributed``) because the
simulator package imports nothing from ``controls``. Requires ``nhjax[dask]``.
"""

from __future__ import annotations

import dataclasses
import traceback
import uuid
from typing import Any, Callable

__all__ = ["GridResult", "closed_loop_batch_on_client", "map_on_client", "somersault_turns"]


@dataclasses.dataclass(frozen=True)
class GridResult:
    """The sweep's outcome, in grid order: ``values[i]`` is ``fn(grid[i])`` (None where it
    raised), ``status[i]`` is "ok" or "error" (or, in a batched map, a member's own
status such as "non_finite"), ``errors[i]`` the traceback text or reason ("" if
    ok)."""

    grid: list
    values: list
    status: list
    errors: list

    @property
    def ok(self) -> list:
        return [s == "ok" for s in self.status]


def _run_points(fn, points):
    out = []
    for p in points:
        try:
            out.append(("ok", fn(p), ""))
        except Exception:  # noqa: BLE001 (one bad grid point must not end the sweep)
            out.append(("error", None, traceback.format_exc()))
    return out


def _run_batch(fn, points):
    """A sub-grid through one batched call: ``fn(points)`` returns one value per point;
    a value that is a dict with a "status" other than "converged" carries that status
    (and its "reason") into the grid's; if ``fn`` raises, every point of the task says so."""
    try:
        values = list(fn(points))
    except Exception:  # noqa: BLE001 (one bad sub-grid must not end the sweep)
        return [("error", None, traceback.format_exc())] * len(points)
    if len(values) != len(points):
        msg = f"the batched function returned {len(values)} values for {len(points)} points"
        return [("error", None, msg)] * len(points)
    out = []
    for v in values:
        status = v.get("status", "converged") if isinstance(v, dict) else "converged"
        out.append(("ok", v, "") if status == "converged" else (status, v, v.get("reason", "")))
    return out


def map_on_client(client, fn: Callable[[Any], Any], grid, *, points_per_task: int | None = 1, retries: int = 2,
                  progress: bool = False, batched: bool = False) -> GridResult:
    """``fn`` at every point of ``grid`` on the workers of ``client``; see the module docstring.

    fn : picklable callable (module-level function or a functools.partial of one);
        its return value must be picklable (numbers, numpy arrays, dicts of them).
    grid : a sequence of points (any picklable objects).
    points_per_task : consecutive points evaluated by one task (and one worker); None:
        the grid split evenly over the cluster's workers (one task each).
    retries : reruns of a task that raised (worker-level failures).
    progress : a tqdm bar over points.
    batched : ``fn`` takes a task's list of points and returns a list of values (e.g.
        one ``controls.solve_pontryagin_batch`` for the whole sub-grid); a value that
        is a dict with a "status" other than "converged" makes that the point's status.
    """
    from dask.distributed import as_completed

    grid = list(grid)
    if not callable(fn):
        raise TypeError(f"map_on_client: fn must be callable, got {fn!r}")
    if points_per_task is None:
        workers = max(1, len(client.scheduler_info().get("workers", {})))
        points_per_task = max(1, -(-len(grid) // workers))
    if int(points_per_task) < 1:
        raise ValueError(f"map_on_client: points_per_task must be a positive integer, got {points_per_task!r}")
    k = int(points_per_task)
    groups = [grid[i:i + k] for i in range(0, len(grid), k)]
    tag = uuid.uuid4().hex[:8]
    futures = [client.submit(_run_batch if batched else _run_points, fn, g, key=f"controls-grid-{tag}-{i}", retries=retries, pure=False)
               for i, g in enumerate(groups)]
    index = {f.key: i for i, f in enumerate(futures)}
    done = [None] * len(futures)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(grid), desc="grid (dask)", unit="point")
    for fut in as_completed(futures):
        i = index[fut.key]
        done[i] = fut.result()
        if bar is not None:
            bar.update(len(groups[i]))
    if bar is not None:
        bar.close()
    flat = [r for group in done for r in group]
    return GridResult(grid=grid, values=[r[1] for r in flat], status=[r[0] for r in flat],
                      errors=[r[2] for r in flat])


def _somersault_turn(turn, theta0=0.6, T=2.0, steps=4):
    """One grid point: cost, violation and iterations of the Pontryagin optimum for ``turn``."""
    import numpy as np

    import controls
    from controls.tasks import fixed_theta_costates, velocity_somersault_chart
    from nhjax.scenes import FallingCatKinematic

    cat = FallingCatKinematic()
    p0, nu = fixed_theta_costates(cat, theta0, T)
    start = float(-2 * np.pi * cat.f(theta0))
    path = controls.continuation(
        lambda v, z: controls.solve_pontryagin(velocity_somersault_chart(cat, theta0, v, T), *(z or (p0, nu))),
        np.linspace(start, float(turn), steps))
    r = path[-1]
    return {"turn": float(turn), "cost": float(r.cost), "violation": float(r.violation),
            "iterations": int(r.iterations)}


def _somersault_turns_batch(turns, theta0=0.6, T=2.0, steps=4):
    """A sub-grid of turns in one batched call per continuation stage
    (``controls.solve_pontryagin_batch``): one dict per turn as ``_somersault_turn``'s,
    with the member's status and reason."""
    import numpy as np

    import controls
    from controls.tasks import fixed_theta_costates, velocity_somersault_chart
    from nhjax.scenes import FallingCatKinematic

    cat = FallingCatKinematic()
    p0, nu = (np.asarray(a) for a in fixed_theta_costates(cat, theta0, T))
    start, turns = float(-2 * np.pi * cat.f(theta0)), np.asarray(turns, float)
    z = np.tile(np.concatenate([p0, nu]), (len(turns), 1))
    for v in np.linspace(0.0, 1.0, steps)[1:] if steps > 1 else [1.0]:
        r = controls.solve_pontryagin_batch([velocity_somersault_chart(cat, theta0, start + v * (t - start), T)
                                             for t in turns], z[:, :3], z[:, 3:], progress=False)
        z = np.where(r.converged[:, None], np.concatenate([r.p0, r.nu], axis=1), z)
    return [{"turn": float(t), "cost": float(r.cost[i]), "violation": float(r.violation[i]),
             "iterations": int(r.iterations[i]), "status": str(r.status[i]), "reason": r.reasons[i]}
            for i, t in enumerate(turns)]


def somersault_turns(client, turns, *, theta0=0.6, T=2.0, points_per_task=None, progress=False) -> GridResult:
    """The velocity-controlled cat's optimal somersault (least vibrational energy (4.8),
    chi winding once, bent by ``theta0`` [rad] at both ends, ``T`` [s]) for each turn of
    psi in ``turns`` [rad], solved by Pontryagin shooting on the workers of ``client``:
    each worker's sub-grid (``points_per_task`` turns; default an even split) through
    batched continuation from the fixed-theta loop (``controls.solve_pontryagin_batch``).
    Each value is a dict with the turn, cost [J s], terminal violation, iterations,
    status and reason; a member that did not converge has that status in the grid."""
    import functools

    return map_on_client(client, functools.partial(_somersault_turns_batch, theta0=theta0, T=T), turns,
                         points_per_task=points_per_task, progress=progress, batched=True)


def _closed_loop_chunk(index, mpc, plant, X, periods, kwargs, on_chunk):
    """On a worker: one chunk's ``closed_loop_batch``, as host arrays (cheap to send)."""
    import jax

    from .mpc import closed_loop_batch

    if on_chunk is not None:
        on_chunk(index)
    return jax.device_get(closed_loop_batch(mpc, plant, X, periods, **kwargs))


def closed_loop_batch_on_client(client, mpc, plant, x0s, periods, *, in_axes=None, t0=0.0, u_guess=None,
                                pushes=None, force_noise=0.0, measurement_noise=0.0, keys=None,
                                plant_substeps=None, group=4, measure=None, chunk_members=None, retries=2,
                                progress=False, on_chunk=None):
    """``controls.closed_loop_batch`` with its members split into chunks that run on the
    workers of a ``dask.distributed.Client``, joined into one ``ClosedLoop`` (arrays
    with a leading member axis, members in order).

    Every argument from ``mpc`` to ``measure`` is ``closed_loop_batch``'s and is checked
    here, before any task is sent (``MPCError`` as there). With ``measure`` (a plant with
    a state of its own, e.g. the cat on SO(3) x SO(3)), ``x0s`` is the plant's state with
    the members on axis 0 of every part, and the pushes, (time, function of the plant's
    state) pairs, go to every chunk as they are. Each member's loop does not
    depend on the others (``closed_loop_batch`` runs them side by side), so the result
    equals the local ``closed_loop_batch`` of the same members (to round-off;
    tests/test_mpc.py checks it on a threads-only cluster, tests/test_distributed.py on
    worker processes).

    client : a ``dask.distributed.Client`` (a LocalCluster's or a real cluster's; every
        worker needs nhjax and controls installed, the same version).
    chunk_members : members per task (default: the batch split into two chunks per
        worker, rounded up to a multiple of ``group``). The last chunk is padded with
        copies of its first member (dropped from the result), so every task has the same
        shapes and a worker compiles the chunk program once.
    retries : reruns of a chunk whose task raised (a lost worker's chunks are
        rescheduled by Dask in any case).
    progress : a tqdm bar over members, advanced as chunks come back.
    on_chunk : optional callable ``on_chunk(index)`` run on the worker at the start of
        every attempt of chunk ``index``.

    Threads: a worker with several threads runs several chunks in one process at once.
    The controller keeps batched LAPACK calls out of its programs for that reason (its
    Hessian floors and QP solves run one matrix at a time under vmap), and nhjax runs
    any stored program that makes such calls (a plant's, say) one at a time
    (``nhjax._programs.batched_lapack``); tests/test_mpc.py runs two batches at once.
    """
    import jax
    import jax.tree_util as jtu
    import numpy as np
    from dask.distributed import as_completed

    from .mpc import MPCError, _batch_inputs, _start_time

    owner = "closed_loop_batch_on_client"
    t0 = _start_time(t0, owner)
    plant_axis, periods, plant_substeps, group, X, fsd, msd, key_data, push_t, push_dx, _ = _batch_inputs(
        mpc, plant, x0s, periods, in_axes, pushes, force_noise, measurement_noise, keys, plant_substeps, group, owner,
        measure)
    B = jtu.tree_leaves(X)[0].shape[0]
    if chunk_members is None:
        workers = max(1, len(client.scheduler_info().get("workers", {})))
        chunk_members = -(-B // (2 * workers))
        chunk_members = -(-chunk_members // group) * group
    elif isinstance(chunk_members, bool) or not isinstance(chunk_members, (int, np.integer)) or chunk_members < 1:
        raise MPCError(f"{owner}: chunk_members must be an integer >= 1 (members per task), got {chunk_members!r}")
    if isinstance(retries, bool) or not isinstance(retries, (int, np.integer)) or retries < 0:
        raise MPCError(f"{owner}: retries must be an integer >= 0, got {retries!r}")
    chunk_members = int(chunk_members)
    n_chunks = -(-B // chunk_members)
    pad = n_chunks * chunk_members - B

    def padded(a):
        a = np.asarray(a)
        return np.concatenate([a, np.repeat(a[:1], pad, axis=0)]) if pad else a

    def chunk(a, i):
        return a[i * chunk_members:(i + 1) * chunk_members]

    members = dict(X=jtu.tree_map(padded, X), keys=padded(jax.device_get(key_data)), times=padded(push_t),
                   kicks=padded(push_dx))
    plant_arrays = None
    if plant_axis == 0:
        import equinox as eqx

        arrays, static = eqx.partition(plant, eqx.is_array)
        plant_arrays = jtu.tree_map(padded, jax.device_get(arrays))
    shared = dict(in_axes=in_axes, t0=t0, u_guess=u_guess, force_noise=fsd, measurement_noise=msd,
                  plant_substeps=plant_substeps, group=min(group, chunk_members), measure=measure)
    tag = uuid.uuid4().hex[:8]
    futures = []
    for i in range(n_chunks):
        part = plant if plant_arrays is None else eqx.combine(jtu.tree_map(lambda a: chunk(a, i), plant_arrays),
                                                               static)
        per_member_pushes = (chunk(members["times"], i), chunk(members["kicks"], i))
        kwargs = dict(shared, keys=chunk(members["keys"], i),
                      pushes=pushes if measure is not None else per_member_pushes)
        X_i = jtu.tree_map(lambda a: chunk(a, i), members["X"])
        futures.append(client.submit(_closed_loop_chunk, i, mpc, part, X_i, periods, kwargs,
                                     on_chunk, key=f"controls-loops-{tag}-{i}", retries=int(retries), pure=False))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=B, desc="closed loops (dask)", unit="loop")
    parts = [None] * n_chunks
    index = {f.key: i for i, f in enumerate(futures)}
    for fut in as_completed(futures):
        i = index[fut.key]
        parts[i] = fut.result()
        if bar is not None:
            bar.update(min(chunk_members, B - i * chunk_members))
    if bar is not None:
        bar.close()
    joined = jtu.tree_map(lambda *a: np.concatenate([np.asarray(v) for v in a])[:B], *parts)
    return jax.device_put(joined)
