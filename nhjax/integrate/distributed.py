"""``simulate_batch`` on a Dask distributed cluster: chunks to workers, one result back.

``simulate_batch_on_client(client, system, x0, t1, ...)`` splits the members of a
batch into chunks of ``chunk_members``, submits one task per chunk to a
``dask.distributed.Client`` (each task is an ordinary local ``simulate_batch`` on the
worker, which compiles the chunk program once per worker process and keeps it), and
joins the chunks' results, in member order, into one ``BatchTrajectory`` with the
per-member statuses and reasons (member numbers are those of the whole batch).

Nothing is lost when a worker dies: the scheduler reschedules the tasks that were on
it (Dask's own recovery, up to ``distributed.scheduler.allowed-failures`` times), and
``retries`` reruns a chunk whose task raised (e.g. a worker out of memory). A member
that fails numerically is not an error of its chunk: the workers always run with
``on_error="return"``, and ``on_error``/``on_guard`` are applied here to the joined
batch exactly as ``simulate_batch`` applies them (BatchError naming the members).

Each member's solve does not depend on which chunk it is in (the solver steps each
member on its own), so the result equals the local ``simulate_batch`` run of the same
batch (to round-off; tests/test_distributed.py checks 1e-12).

Point it at a real cluster by giving a client connected to that cluster's scheduler,
``Client("tcp://scheduler:8786")``; every worker needs nhjax installed (the same
version) and ``JAX_ENABLE_X64`` is set by importing nhjax. Choose chunks big enough
that a chunk's solve time dwarfs the per-task overhead (a few ms on a LocalCluster,
see benchmarks/dask_throughput.py) and at least a few per worker so the scheduler can
balance them.

Requires the ``dask`` extra: ``pip install 'nhjax[dask]'``.
"""

from __future__ import annotations

import dataclasses
import uuid

import jax
import jax.tree_util as jtu
import numpy as np

from .._validate import axes_dict
from ..errors import ParameterError
from ._batch_types import BatchError, BatchTrajectory
from ._local_batch import simulate_batch_local

__all__ = ["simulate_batch_on_client"]


def _axes(in_axes):
    d = axes_dict(in_axes, ("system", "x0", "control"), owner="simulate_batch_on_client", default={"x0": 0})
    return d


def _size(tree):
    sizes = {int(np.shape(a)[0]) for a in jtu.tree_leaves(tree) if np.ndim(a)}
    if len(sizes) != 1:
        raise ParameterError(f"simulate_batch_on_client: batched arguments must share one leading member axis, "
                             f"got sizes {sorted(sizes)}", "x0", None)
    return sizes.pop()


def _slice(tree, lo, hi):
    return jtu.tree_map(lambda a: np.asarray(a)[lo:hi] if hasattr(a, "shape") and np.ndim(a) else a, tree)


def _run_chunk(index, system, x0, control, t1, kwargs, on_chunk):
    """On a worker: the chunk's simulate_batch, as host numpy arrays (cheap to send)."""
    if on_chunk is not None:
        on_chunk(index)
    traj = simulate_batch_local(system, x0, t1, control=control, on_error="return", on_guard="stop",
                                progress=False, **kwargs)
    return jax.device_get(traj)


def _join(parts, sizes):
    """One BatchTrajectory from the chunks' (in member order); reasons renumbered."""
    fields = [f.name for f in dataclasses.fields(BatchTrajectory)]
    static = {"reasons", "guard", "state_names"}
    arrays = {}
    for name in fields:
        if name in static:
            continue
        vals = [getattr(p, name) for p in parts]
        arrays[name] = jtu.tree_map(lambda *a: np.concatenate([np.asarray(v) for v in a]), *vals)
    reasons, offset = {}, 0
    for p, n in zip(parts, sizes):
        reasons.update({offset + int(k): v for k, v in p.reasons.items()})
        offset += n
    guards = sorted({g.strip() for p in parts for g in p.guard.split(",") if g.strip()})
    arrays = jax.device_put(arrays)
    return BatchTrajectory(**arrays, reasons=reasons, guard=", ".join(guards), state_names=parts[0].state_names)


def simulate_batch_on_client(client, system, x0, t1, *, control=None, in_axes=None, chunk_members=None,
                             retries=2, on_error="raise", on_guard="raise", progress=False, on_chunk=None,
                             **kwargs) -> BatchTrajectory:
    """``simulate_batch`` with its chunks run on the workers of a ``dask.distributed.Client``.

    client : a ``dask.distributed.Client`` (a LocalCluster's or a real cluster's).
    system, x0, t1, control, in_axes : as ``simulate_batch`` (members along axis 0).
    chunk_members : members per task (default: the batch split into 4 tasks per worker,
        at least 64 members each). Every chunk but the last has this size, so a worker
        compiles the chunk program once.
    retries : reruns of a chunk whose task raised (a lost worker's chunks are
        rescheduled by Dask in any case).
    on_error, on_guard : as ``simulate_batch``, applied to the joined batch.
    progress : a tqdm bar over members, advanced as chunks come back.
    on_chunk : optional callable ``on_chunk(index)`` run on the worker at the start of
        every attempt of chunk ``index`` (logging; a rerun calls it again).
    kwargs : every other ``simulate_batch`` keyword (saveat, rtol, atol, solver, lanes,
        workers per process, ...), passed to each chunk.

    Returns the ``BatchTrajectory`` of the whole batch, members in order.
    """
    from dask.distributed import as_completed

    if on_error not in ("raise", "return"):
        raise ParameterError(f"simulate_batch_on_client: on_error must be 'raise' or 'return', got {on_error!r}",
                             "on_error", on_error)
    if on_guard not in ("raise", "stop"):
        raise ParameterError(f"simulate_batch_on_client: on_guard must be 'raise' or 'stop', got {on_guard!r}",
                             "on_guard", on_guard)
    for k in ("progress", "on_error", "on_guard"):
        kwargs.pop(k, None)
    axes = _axes(in_axes)
    args = {"system": system, "x0": x0, "control": control}
    batched = {k: v for k, v in args.items() if axes.get(k) == 0 and v is not None}
    B = _size(list(batched.values()))
    if chunk_members is None:
        n_workers = max(1, len(client.scheduler_info().get("workers", {})))
        chunk_members = max(64, -(-B // (4 * n_workers)))
    chunk_members = int(chunk_members)
    if chunk_members < 1:
        raise ParameterError(f"simulate_batch_on_client: chunk_members must be a positive integer, got "
                             f"{chunk_members}", "chunk_members", chunk_members)
    starts = list(range(0, B, chunk_members))
    sizes = [min(chunk_members, B - lo) for lo in starts]
    if in_axes is not None:
        kwargs["in_axes"] = in_axes
    # Unbatched arguments travel inside every task (not scattered once): scattered data
    # lives only on workers, and a lost worker can take the last copy with it, which
    # would cancel every chunk that needs it; in the task they are re-sent on a rerun.
    shared = {k: v for k, v in args.items() if k not in batched}
    tag = uuid.uuid4().hex[:8]
    futures = []
    for i, lo in enumerate(starts):
        part = {k: _slice(v, lo, lo + sizes[i]) for k, v in batched.items()}
        a = {**shared, **part}
        futures.append(client.submit(_run_chunk, i, a["system"], a["x0"], a.get("control"), t1, kwargs, on_chunk,
                                     key=f"nhjax-chunk-{tag}-{i}", retries=retries, pure=False))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=B, desc="nhjax batch (dask)", unit="traj")
    parts = [None] * len(futures)
    index = {f.key: i for i, f in enumerate(futures)}
    for fut in as_completed(futures):
        i = index[fut.key]
        parts[i] = fut.result()
        if bar is not None:
            bar.update(sizes[i])
    if bar is not None:
        bar.close()
    traj = _join(parts, sizes)
    if on_error == "return":
        return traj
    t_final = np.asarray(traj.t_final)

    def fail(what, mask):
        members = np.nonzero(mask)[0].tolist()
        raise BatchError(what, members, [traj.reasons.get(m, "") for m in members],
                         [float(t_final[m]) for m in members], traj)

    if traj.failed.any():
        fail("failed solves (or bad initial states)", traj.failed)
    if traj.stopped.any() and on_guard == "raise":
        fail("a chart guard stopped the solve (pass on_guard='stop' to keep these members)", traj.stopped)
    return traj
