"""Grids of optimal-control problems: one batched call against the same solves one by one.

Workload (the labelled friendly one: every member converges from the same start):
B chart somersaults (``controls.tasks.velocity_somersault_chart``, the
velocity-controlled cat in Iwai's chart, T = 2 s) with bends theta0 evenly in
[0.5, 0.8] rad, each turned 0.2 rad past its fixed-theta loop's holonomy, so that
every member needs several iterations.

* direct: ``controls.solve_direct_batch`` (SQP, Chebyshev(10) inputs, from the
  loop's inputs) against ``solve_direct_sqp`` on each member in a Python loop;
* Pontryagin: ``controls.solve_pontryagin_batch`` against ``solve_pontryagin`` on
  each member, both from the loop's exact costates.

Both sides run in one process, after a first (compiling) call of each, in
interleaved rounds (batch, loop, batch, loop, ...); a time is the median over the
rounds. The error column is the largest relative difference between the batch's and
the loop's optimal costs (each member's batch solve is meant to be its solve alone).
Writes experiments/out/bench/ocp_batch.json with the load average.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent.parent / "experiments" / "out" / "bench"
SIZES = (16, 64)
ROUNDS = 3
T = 2.0


def members(cat, B):
    from controls.tasks import velocity_somersault_chart

    bends = np.linspace(0.5, 0.8, B)
    c, s = np.cos(bends), np.sin(bends)
    holonomy = -2 * np.pi * cat.lam * c / (s * s + cat.lam * c * c)
    return bends, [velocity_somersault_chart(cat, th, h - 0.2, T) for th, h in zip(bends, holonomy)]


def workloads(B):
    """{name: (batch call, loop call, costs of a result of each)}."""
    import jax.numpy as jnp

    import controls
    from controls.tasks import fixed_theta_costates
    from nhjax.scenes import FallingCatKinematic

    cat = FallingCatKinematic()
    bends, ocps = members(cat, B)
    param = controls.Chebyshev(10, T, 2)
    guess = np.asarray(param.fit(lambda t: jnp.array([0.0, 2 * np.pi / T])))
    p0, nu = (np.stack(a) for a in zip(*(fixed_theta_costates(cat, th, T) for th in bends)))
    return {
        "direct (SQP, Chebyshev(10))": (
            lambda: controls.solve_direct_batch(ocps, param, guess, progress=False),
            lambda: [controls.solve_direct_sqp(o, param, guess, progress=False) for o in ocps],
        ),
        "Pontryagin (Newton shooting)": (
            lambda: controls.solve_pontryagin_batch(ocps, p0, nu, progress=False),
            lambda: [controls.solve_pontryagin(o, p, n, progress=False) for o, p, n in zip(ocps, p0, nu)],
        ),
    }


def measure(B):
    rows = []
    for name, (batch, loop) in workloads(B).items():
        t = time.perf_counter()
        rb = batch()
        first_batch = time.perf_counter() - t
        t = time.perf_counter()
        rl = loop()
        first_loop = time.perf_counter() - t
        costs = np.array([r.cost for r in rl])
        tb, tl = [], []
        for _ in range(ROUNDS):
            t = time.perf_counter()
            batch()
            tb.append(time.perf_counter() - t)
            t = time.perf_counter()
            loop()
            tl.append(time.perf_counter() - t)
        row = dict(method=name, members=B, converged_batch=int(np.sum(rb.converged)),
                   converged_loop=int(sum(bool(r.converged) for r in rl)),
                   batch_seconds=statistics.median(tb), loop_seconds=statistics.median(tl),
                   speedup=statistics.median(tl) / statistics.median(tb),
                   batch_seconds_first=first_batch, loop_seconds_first=first_loop,
                   max_rel_cost_diff=float(np.max(np.abs(rb.cost - costs) / np.abs(costs))),
                   load_average=os.getloadavg()[0])
        print(f"{name:30s} B={B:3d}  batch {row['batch_seconds']:.3f} s  loop {row['loop_seconds']:.3f} s  "
              f"x{row['speedup']:.2f}  (first: {first_batch:.1f} / {first_loop:.1f} s)  converged "
              f"{row['converged_batch']}/{row['converged_loop']}  max rel cost diff {row['max_rel_cost_diff']:.1e}  "
              f"load {row['load_average']:.2f}", flush=True)
        rows.append(row)
    return rows


def main():
    load_start = os.getloadavg()
    print(f"load average at start: {load_start[0]:.2f}; the friendly workload (every member from the same "
          f"kind of start converges); times after a first call, median of {ROUNDS} interleaved rounds")
    rows = [r for B in SIZES for r in measure(B)]
    OUT.mkdir(parents=True, exist_ok=True)
    meta = dict(command="python benchmarks/ocp_batch.py", platform=platform.platform(), cpu_count=os.cpu_count(),
                load_average_start=load_start, load_average_end=os.getloadavg(),
                measured=time.strftime("%Y-%m-%d %H:%M"), workload="friendly: chart somersaults, 0.2 rad past "
                "each bend's loop holonomy, every member from its loop")
    (OUT / "ocp_batch.json").write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))
    print(f"wrote {OUT / 'ocp_batch.json'}")


if __name__ == "__main__":
    main()
