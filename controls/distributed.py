"""A batch of optimal-control problems on a Dask distributed cluster.

``map_on_client(client, fn, grid)`` evaluates a user callable ``fn(point)`` at every
point of a grid (e.g. solve the somersault for each turn angle) on the workers of a
``dask.distributed.Client`` and returns the results in grid order, each with its
status: a point whose ``fn`` raised does not stop the sweep; its status says why.
Points are grouped into tasks of ``points_per_task`` so that each worker compiles the
problem once and reuses it for its next points (an OC solve compiles for tens of
seconds; grouping also amortizes the per-task overhead). A lost worker's tasks are
rescheduled by Dask; ``retries`` reruns a task that raised outside ``fn``.

``somersault_turns`` is the example from the issue: the velocity-controlled falling
cat's optimal somersault for each turn angle, by Pontryagin shooting (continuation
from the fixed-theta loop), as a grid sweep.

This lives in ``controls`` (not ``nhjax.integrate.distributed``) because the
simulator package imports nothing from ``controls``. Requires ``nhjax[dask]``.
"""

from __future__ import annotations

import dataclasses
import traceback
import uuid
from typing import Any, Callable

__all__ = ["GridResult", "map_on_client", "somersault_turns"]


@dataclasses.dataclass(frozen=True)
class GridResult:
    """The sweep's outcome, in grid order: ``values[i]`` is ``fn(grid[i])`` (None where it
    raised), ``status[i]`` is "ok" or "error", ``errors[i]`` the traceback text ("" if
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


def map_on_client(client, fn: Callable[[Any], Any], grid, *, points_per_task: int = 1, retries: int = 2,
                  progress: bool = False) -> GridResult:
    """``fn`` at every point of ``grid`` on the workers of ``client``; see the module docstring.

    fn : picklable callable (module-level function or a functools.partial of one);
        its return value must be picklable (numbers, numpy arrays, dicts of them).
    grid : a sequence of points (any picklable objects).
    points_per_task : consecutive points evaluated by one task (and one worker).
    retries : reruns of a task that raised (worker-level failures).
    progress : a tqdm bar over points.
    """
    from dask.distributed import as_completed

    grid = list(grid)
    if not callable(fn):
        raise TypeError(f"map_on_client: fn must be callable, got {fn!r}")
    if int(points_per_task) < 1:
        raise ValueError(f"map_on_client: points_per_task must be a positive integer, got {points_per_task!r}")
    k = int(points_per_task)
    groups = [grid[i:i + k] for i in range(0, len(grid), k)]
    tag = uuid.uuid4().hex[:8]
    futures = [client.submit(_run_points, fn, g, key=f"controls-grid-{tag}-{i}", retries=retries, pure=False)
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


def somersault_turns(client, turns, *, theta0=0.6, T=2.0, points_per_task=1, progress=False) -> GridResult:
    """The velocity-controlled cat's optimal somersault (least vibrational energy (4.8),
    chi winding once, bent by ``theta0`` [rad] at both ends, ``T`` [s]) for each turn of
    psi in ``turns`` [rad], solved by Pontryagin shooting on the workers of ``client``.
    Each value is a dict with the turn, cost [J s], terminal violation and iterations."""
    import functools

    return map_on_client(client, functools.partial(_somersault_turn, theta0=theta0, T=T), turns,
                         points_per_task=points_per_task, progress=progress)
