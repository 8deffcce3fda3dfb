"""``nhjax.simulate_batch``: many trajectories at once, on all local CPU cores or on the
workers of a Dask cluster.

The entry point dispatches once, at the top: with a ``client`` to
``distributed.py`` (whose workers each run the local batch), otherwise to
``_local_batch.py`` (the lock-step chunks, or the impact batch for systems with
one-sided constraints); how a local batch runs is told there. The result types live
in ``_batch_types.py``, below all three paths.
"""

from __future__ import annotations

import jax.numpy as jnp
import jax.tree_util as jtu

from ._batch_types import STATUSES, BatchError, BatchTrajectory, MemberStatuses
from ._local_batch import simulate_batch_local
from .distributed import simulate_batch_on_client

__all__ = ["BatchError", "BatchTrajectory", "MemberStatuses", "STATUSES", "simulate_batch", "stack"]


def stack(members):
    """Stack equally-structured systems, controls or states into one batched pytree."""
    members = list(members)
    if not members:
        raise ValueError("stack() needs at least one member")
    return jtu.tree_map(lambda *a: jnp.stack([jnp.asarray(x) for x in a]), *members)


def simulate_batch(
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
    client=None,
    **impact_options,
) -> BatchTrajectory:
    """Simulate a batch of trajectories; returns a ``BatchTrajectory`` whose arrays have a
    leading member axis (``traj.xs[i]`` is member i's saved states) and per-member
    statuses.

    in_axes : dict with keys among "system", "x0", "control" giving 0 (batched along
        axis 0) or None; default ``{"x0": 0}``.
    chunk_size : at most this many members per compiled chunk (bounds memory). A batch
        of at least 64 x ``workers`` members is split into at least ``workers`` chunks.
        A chunk's capacity is a power of two (or chunk_size): batches of other sizes up
        to it reuse the compiled program.
    lanes : members stepped together in a chunk (default: an eighth of a chunk's
        members, 32 to 128, at most all of them); when one ends, its lane takes the
        next member.
    workers : concurrent chunks (default: the number of local devices, or 2 threads
        on a single CPU device when the machine has at least 2 cores).
    progress : tqdm bar over chunks (default: on for more than 4 chunks).
    saveat : as in simulate(); default 2 (t0 and t1), the cheap choice for big batches.
    rtol, atol : as in simulate(); default 1e-8 (1e-10 for systems with one-sided
        constraints, as ``simulate_impacts``).
    on_guard : "raise" (BatchError naming the members a chart guard stopped) or "stop".
    track_work : integrate the work of the inputs for an energy - work report. Default:
        only when the system has no invariant or constraint of its own to report (the
        work costs an extra state component in every step).
    on_error : "raise" (default: BatchError when a member's initial state is bad or its
        solve failed) or "return" (nothing raises: every member's status is in
        ``traj.status`` / ``traj.reasons``, with its time in ``traj.t_final``; the other
        members' results are intact). Members with a bad initial state are not solved.
    client : a ``dask.distributed.Client``: the batch's chunks run on its workers and
        come back joined in member order (``nhjax.integrate.distributed.
        simulate_batch_on_client``: a lost worker's chunks are rerun; the ``dask`` extra).
    impact_options : for systems with one-sided constraints (``unilateral_constraints``:
        bouncing balls, moving walls), which go to the lock-step impact batch
        (``nhjax.simulate_impacts_batch``, returning an ``ImpactBatchTrajectory``: the
        same per-member ``status``, ``reasons``, ``ok`` and ``summary()``, with the
        statuses of impact solves): ``max_impacts``, ``on_max_impacts``,
        ``rest_velocity``, ... Their members' starts are checked as
        ``simulate_impacts`` checks one, before any solve.
    Other arguments as ``nhjax.simulate``.
    """
    options = dict(
        t0=t0, control=control, in_axes=in_axes, chunk_size=chunk_size, lanes=lanes, workers=workers,
        saveat=saveat, solver=solver, rtol=rtol, atol=atol, dt0=dt0, max_steps=max_steps,
        stepsize_controller=stepsize_controller, jump_ts=jump_ts, adjoint=adjoint, project=project,
        project_steps=project_steps, constraint_tol=constraint_tol, on_guard=on_guard, on_error=on_error,
        track_work=track_work, diagnostics=diagnostics, **impact_options)
    if client is not None:
        return simulate_batch_on_client(client, system, x0, t1, progress=bool(progress), **options)
    return simulate_batch_local(system, x0, t1, progress=progress, **options)
