"""Throughput of simulate_batch on a Dask LocalCluster (1 and 2 worker processes),
the overhead per chunk, and an estimate of scaling to N machines.

Batch: the knife-edge skate on a plane tilted by 90 degrees (seed 002, Fig. 9.1),
B members with random speed, spin and heading, t1 = 60 s, rtol = atol = 1e-10, each
against its exact cycloid (Skate.exact_solution): the error column is the worst
final-state error over the members. The same batch is run
  * locally: simulate_batch(workers=1) on all members (one process, one thread);
  * locally in the dask chunking: one simulate_batch(workers=1) per chunk in a loop
    (what the workers do, without dask);
  * on a LocalCluster with 1 and 2 worker processes (1 thread each), chunks of
    ``--chunk`` members, after a warm-up run that compiles on every worker.
Overhead per chunk: 64 tiny chunks (8 members, t1 = 0.01 s) on 1 worker against the
same chunks in a local loop, difference / 64 (the big run's difference is printed too,
but it mixes the overhead with the machine's load).

Scaling estimate for N machines of w workers: t(N) ~ t_chunk_compute * ceil(chunks /
(N w)) + overhead * chunks / (N w) + compile once per worker process (in parallel),
as long as the scheduler keeps up (a few thousand tasks per second) and the
results (B x saved states) fit through the client's network link.

Usage: nhjax bench dask_throughput, or python benchmarks/dask_throughput.py [--members B]
[--chunk C] [--t1 S] (needs nhjax[dask]).
Writes experiments/out/bench/dask_throughput.json.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np


def _members(skate, n, seed=0):
    rng = np.random.default_rng(seed)
    return np.stack([np.asarray(skate.initial_state(speed=v, phi_dot=w, phi=p))
                     for v, w, p in zip(rng.uniform(-1, 1, n), rng.uniform(-2, 2, n), rng.uniform(0, 6, n))])


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=4096)
    ap.add_argument("--chunk", type=int, default=256)
    ap.add_argument("--t1", type=float, default=60.0)
    ap.add_argument("--out", default="experiments/out/bench")
    a, _ = ap.parse_known_args(argv)  # `nhjax bench dask_throughput` passes the benchmark's name along

    from dask.distributed import Client, LocalCluster

    import nhjax
    from nhjax.integrate.distributed import simulate_batch_on_client
    from nhjax.scenes.skate import Skate

    skate = Skate(beta=np.pi / 2)
    X0 = _members(skate, a.members)
    exact = np.stack([np.asarray(skate.exact_solution(a.t1, x)) for x in X0])
    opts = dict(saveat=2, rtol=1e-10, atol=1e-10, workers=1, on_error="return")
    err = lambda tr: float(np.max(np.abs(np.asarray(tr.x_final) - exact)))  # noqa: E731
    chunks = -(-a.members // a.chunk)
    print(f"skate batch: {a.members} members, t1 = {a.t1} s, rtol = atol = 1e-10, {chunks} chunks of {a.chunk}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")

    rows = {}
    nhjax.simulate_batch(skate, X0[: a.chunk], a.t1, **opts)  # compile
    local, t_local = _timed(lambda: nhjax.simulate_batch(skate, X0, a.t1, **opts))
    rows["local, one call"] = (t_local, err(local))
    _, t_loop = _timed(lambda: [nhjax.simulate_batch(skate, X0[i:i + a.chunk], a.t1, **opts)
                                for i in range(0, a.members, a.chunk)])
    rows["local, chunk loop"] = (t_loop, err(local))
    for n in (1, 2):
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None) as cl, \
                Client(cl) as client:
            kw = dict(chunk_members=a.chunk, **opts)
            _, t_warm = _timed(lambda: simulate_batch_on_client(client, skate, X0, a.t1, **kw))
            tr, t = _timed(lambda: simulate_batch_on_client(client, skate, X0, a.t1, **kw))
            same = float(np.max(np.abs(np.asarray(tr.xs) - np.asarray(local.xs))))
            rows[f"dask, {n} worker{'s' if n > 1 else ''}"] = (t, err(tr))
            if n == 1:  # overhead per task, measured on tiny chunks (8 members, t1 = 0.01 s)
                tiny = dict(opts, chunk_members=8)
                simulate_batch_on_client(client, skate, X0[:512], 0.01, **tiny)
                _, t_tiny = _timed(lambda: simulate_batch_on_client(client, skate, X0[:512], 0.01, **tiny))
                nhjax.simulate_batch(skate, X0[:8], 0.01, **opts)
                _, t_tiny_loop = _timed(lambda: [nhjax.simulate_batch(skate, X0[i:i + 8], 0.01, **opts)
                                                 for i in range(0, 512, 8)])
                tiny_overhead = (t_tiny - t_tiny_loop) / 64
                print(f"  tiny chunks: 64 chunks of 8 members, t1 = 0.01 s: dask {t_tiny * 1e3:.0f} ms, "
                      f"local loop {t_tiny_loop * 1e3:.0f} ms -> overhead {tiny_overhead * 1e3:.1f} ms per chunk")
            print(f"  {n} worker(s): first run (compiles on the workers) {t_warm:.2f} s; "
                  f"max |dask - local| = {same:.1e}")
    print(f"{'run':22s} {'time [s]':>9s} {'members/s':>10s} {'max error':>10s}")
    for k, (t, e) in rows.items():
        print(f"{k:22s} {t:9.3f} {a.members / t:10.0f} {e:10.1e}")
    overhead = tiny_overhead
    chunk_compute = t_loop / chunks
    speedup = rows["dask, 1 worker"][0] / rows["dask, 2 workers"][0]
    big = (rows["dask, 1 worker"][0] - t_loop) / chunks
    print(f"overhead per chunk: {overhead * 1e3:.1f} ms from tiny chunks ({big * 1e3:.1f} ms from the big run); "
          f"chunk compute {chunk_compute * 1e3:.1f} ms; "
          f"2 workers / 1 worker speed-up {speedup:.2f}x on {os.cpu_count()} cores")
    for N in (1, 4, 16, 64):
        w = 2 * N
        est = chunk_compute * np.ceil(chunks / w) + max(overhead, 0) * chunks / w
        print(f"  estimate, {N:2d} machine(s) x 2 workers: {est:.2f} s for this batch "
              f"({a.members / est:.0f} members/s; chunks per worker {chunks / w:.1f})")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "dask_throughput.json").write_text(json.dumps(dict(
        members=a.members, chunk=a.chunk, t1=a.t1, rows={k: dict(seconds=t, max_error=e) for k, (t, e) in rows.items()},
        overhead_per_chunk_s=overhead, overhead_per_chunk_big_run_s=big, chunk_compute_s=chunk_compute, speedup_2_over_1=speedup,
        load_average=os.getloadavg()[0], cores=os.cpu_count()), indent=1))


if __name__ == "__main__":
    main()
