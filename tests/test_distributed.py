"""simulate_batch on a Dask LocalCluster (2 worker processes): the joined result and
the per-member statuses equal the local simulate_batch run, and a chunk whose worker
is killed mid-run is recomputed on another worker with nothing lost.

Slow (each worker process compiles the chunk program once): ``make test-all``."""

from __future__ import annotations

import os
import signal
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dask.distributed")

import cloudpickle  # noqa: E402
from dask.distributed import Client, LocalCluster  # noqa: E402

import jax  # noqa: E402
import nhjax  # noqa: E402
from nhjax.integrate.distributed import simulate_batch_on_client  # noqa: E402
from nhjax.scenes.skate import Skate  # noqa: E402

pytestmark = pytest.mark.slow
cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the on_chunk hook below runs on workers

SKATE = Skate(beta=np.pi / 2)
OPTS = dict(saveat=5, rtol=1e-10, atol=1e-10)


def _members(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.stack([np.asarray(SKATE.initial_state(speed=v, phi_dot=w, phi=p))
                     for v, w, p in zip(rng.uniform(-1, 1, n), rng.uniform(-2, 2, n), rng.uniform(0, 6, n))])


@pytest.fixture(scope="module")
def client():
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as c:
        yield c


def _same(a, b):
    for k in ("ts", "xs", "t_final", "x_end"):
        np.testing.assert_allclose(np.asarray(getattr(a, k)), np.asarray(getattr(b, k)), rtol=0, atol=1e-12)
    for k in b.invariants:
        np.testing.assert_allclose(np.asarray(a.invariants[k]), np.asarray(b.invariants[k]), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(a.status), np.asarray(b.status))
    assert a.reasons == b.reasons


def test_equals_local_run_with_statuses(client):
    X0 = _members(100)
    X0[37, 3] += 0.5  # off the constraint: "bad x0" for member 37, in the second chunk
    local = nhjax.simulate_batch(SKATE, X0, 12.0, on_error="return", **OPTS)
    dist = simulate_batch_on_client(client, SKATE, X0, 12.0, chunk_members=32, on_error="return", **OPTS)
    assert len(dist) == 100 and not local.ok[37] and list(local.reasons) == [37]
    _same(dist, local)
    # the exact cycloid: every ok member agrees with Skate.exact_solution
    exact = np.stack([np.asarray(SKATE.exact_solution(12.0, x)) for x in X0])
    assert np.max(np.abs(np.asarray(dist.x_final)[dist.ok] - exact[dist.ok])) < 1e-7
    with pytest.raises(nhjax.BatchError, match="37"):
        simulate_batch_on_client(client, SKATE, X0, 12.0, chunk_members=32, **OPTS)
    # back-to-back calls with the same system (its broadcast copy must not be released
    # by the previous call's cleanup: "lost dependencies")
    for _ in range(3):
        _same(simulate_batch_on_client(client, SKATE, X0, 12.0, chunk_members=32, on_error="return", **OPTS), local)
    # the same through simulate_batch(client=...)
    _same(nhjax.simulate_batch(SKATE, X0, 12.0, client=client, on_error="return", **OPTS), local)


def _slow_start(marks, index):
    """on_chunk hook: record (chunk, worker pid) and hold chunk 1 for a while so that the
    test can kill its worker while it runs."""
    Path(marks, f"{index}-{os.getpid()}-{time.monotonic_ns()}").touch()
    if index == 1:
        time.sleep(4.0)


def test_killed_worker_chunk_is_recomputed(client, tmp_path):
    import functools

    X0 = _members(96, seed=1)
    local = nhjax.simulate_batch(SKATE, X0, 12.0, on_error="return", **OPTS)
    hook = functools.partial(_slow_start, str(tmp_path))
    with ThreadPoolExecutor(1) as pool:
        fut = pool.submit(simulate_batch_on_client, client, SKATE, X0, 12.0, chunk_members=32, on_error="return",
                          on_chunk=hook, **OPTS)
        deadline = time.monotonic() + 120
        while not list(tmp_path.glob("1-*")) and time.monotonic() < deadline:
            time.sleep(0.05)
        (first,) = tmp_path.glob("1-*")
        victim = int(first.name.split("-")[1])
        os.kill(victim, signal.SIGKILL)  # the worker process running chunk 1 dies mid-chunk
        dist = fut.result(timeout=300)
    attempts = sorted(tmp_path.glob("1-*"))
    assert len(attempts) >= 2, attempts  # chunk 1 started again ...
    assert any(int(p.name.split("-")[1]) != victim for p in attempts)  # ... in another process
    _same(dist, local)  # and nothing was lost


# ---------------------------------------------------------------- a batch of OC problems
def _sqrt_or_fail(x):
    if x < 0:
        raise ValueError(f"negative point {x}")
    return float(np.sqrt(x))


def _roots_or_fail(points):
    if any(isinstance(x, str) for x in points):
        raise TypeError("not a number in this sub-grid")
    return [{"root": float(np.sqrt(x)), "status": "converged"} if x >= 0
            else {"root": None, "status": "negative", "reason": "no real root"} for x in points]


def test_grid_map_keeps_order_and_statuses(client):
    from controls.distributed import map_on_client

    grid = [4.0, -1.0, 9.0, 2.0, 16.0]
    r = map_on_client(client, _sqrt_or_fail, grid, points_per_task=2)
    assert r.status == ["ok", "error", "ok", "ok", "ok"]
    assert "negative point -1.0" in r.errors[1]
    assert r.values[0] == 2.0 and r.values[2] == 3.0 and r.values[3] == np.sqrt(2.0) and r.values[4] == 4.0


def test_batched_map_carries_member_statuses_and_failed_tasks(client):
    """A batched map: one call per task's sub-grid; a member's own status reaches the
    grid, and a task whose call raises marks each of its points as an error."""
    from controls.distributed import map_on_client

    r = map_on_client(client, _roots_or_fail, [4.0, -1.0, 9.0, "x", 16.0], points_per_task=2, batched=True)
    assert r.status == ["ok", "negative", "error", "error", "ok"]
    assert r.values[0]["root"] == 2.0 and r.values[4]["root"] == 4.0 and r.errors[1] == "no real root"
    assert "not a number" in r.errors[2] and r.errors[2] == r.errors[3]


def test_somersaults_over_turn_angles_equal_local_solves(client):
    """Pontryagin somersaults for two turn angles on the workers against the same solves
    here: the same costs to 1e-12 (relative), every terminal violation tiny."""
    from controls.distributed import _somersault_turn, somersault_turns

    turns = [-np.pi, -2.5, -2.8]
    r = somersault_turns(client, turns)  # (a sub-grid per worker, each in batched calls)
    assert r.status == ["ok", "ok", "ok"], r.errors
    for turn, v in zip(turns, r.values):
        here = _somersault_turn(turn)
        assert abs(v["cost"] - here["cost"]) <= 1e-12 * abs(here["cost"])
        assert v["violation"] < 1e-9


def test_closed_loops_on_worker_processes_equal_the_local_batch(client):
    """closed_loop_batch_on_client on the two worker processes (the controller, plant
    and problem pickled to them): the torque-driven cat's shrinking-horizon landing from
    six perturbed starts, in chunks of four (the last padded), against the local
    closed_loop_batch of the same members: inputs, states and costs to 1e-10."""
    import controls
    from controls.distributed import closed_loop_batch_on_client
    from controls.tasks import torque_somersault
    from nhjax.scenes import FallingCat

    cat = FallingCat()
    task = torque_somersault(cat, 0.6, -np.pi, 2.0)
    ocp = controls.OCP(cat, task.x0, 2.0, task.running_cost, terminal_constraints=task.terminal_constraints,
                       u_lower=-2.0, u_upper=2.0)
    mpc = controls.MPC(ocp, 0.2, 10, mode="rti", horizon="shrinking", terminal="penalty", terminal_weight=1e4)
    rng = np.random.default_rng(5)
    X = np.asarray(task.x0) + np.concatenate([rng.uniform(-0.05, 0.05, (6, 2)), np.zeros((6, 1)),
                                              rng.uniform(-0.2, 0.2, (6, 2))], axis=1)
    local = controls.closed_loop_batch(mpc, cat, X, 10, group=2)
    far = closed_loop_batch_on_client(client, mpc, cat, X, 10, group=2, chunk_members=4)
    for a, b in zip(jax.tree_util.tree_leaves(far), jax.tree_util.tree_leaves(local)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-10)
    assert np.ptp(np.asarray(local.trajectory.xs[:, -1, 2])) > 0  # the members differ
