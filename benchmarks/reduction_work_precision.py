"""Work-precision of the reduced planar chain against the unreduced one (issue 15).

The same motion two ways: ``PlanarChain`` (reduced by SE(2): state (x, y, angle,
phi, phi', J), 3 + 2(N-1) + 3 numbers, equations from the connection by
autodiff) and ``PlanarChainUnreduced`` (N free bodies in R^3N with 2(N-1) hinge
constraints, index-reduced, KKT solve and a projection after every step, by the
engine). Three links with joint torques and thrusters, nonzero momentum, T = 5 s;
rtol = atol from 1e-4 to 1e-12 with the default solver (Dormand-Prince 5(4)).

Error: max abs over the bodies' final poses and velocities (x_i, y_i, theta_i and
rates) against a reference: the reduced chain at 1e-13 with diffrax's Dopri8,
checked against the unreduced one at 1e-13 (their disagreement is printed as the
reference's own error bar). Time: median wall time of the jitted solve after
compile (>= 3 runs). Compile: the first call of the jitted solve (trace + XLA)
per system. Then the same for an N = 5 chain (compile and one tolerance).

Writes experiments/out/bench/reduction_work_precision.{json,csv,png}; prints the
load average at the start and the end (the machine may be shared).
"""

from __future__ import annotations

import csv
import json
import os
import platform
import sys
import time
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import nhjax
from nhjax.scenes import PlanarChain

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _timing import median_time  # noqa: E402

OUT = HERE.parent / "experiments" / "out" / "bench"
TOLS = [1e-4, 1e-6, 1e-8, 1e-10, 1e-12]
T1 = 5.0


def case(N):
    rng = np.random.default_rng(N)
    ch = PlanarChain(masses=rng.uniform(0.6, 1.4, N), lengths=rng.uniform(0.6, 1.2, N), thrusters=True)
    phi0 = rng.uniform(-0.6, 0.6, N - 1)
    x0 = ch.initial_state(phi0, rng.normal(size=N - 1) * 0.3, pose=[0.1, -0.2, 0.3], momentum=[0.2, -0.1, 0.5])
    nu = ch.control_dim
    control = nhjax.Sinusoids(np.zeros(nu), rng.uniform(-0.3, 0.3, nu), rng.uniform(0.5, 2.0, nu),
                              rng.uniform(0, 3, nu))
    return ch, x0, control


def runners(ch, x0, control):
    un = ch.unreduced()
    y0 = ch.unreduced_state(x0)

    def make(system, start, solver=None, bodies=None):
        @jax.jit
        def run(tol):
            tr = nhjax.simulate(system, start, T1, control=control, rtol=tol, atol=tol, saveat=2, solver=solver,
                                diagnostics=False, max_steps=400_000)
            end = tr.x_end if bodies is None else bodies(tr.x_end)
            return end, tr.num_accepted_steps
        return run

    return {
        "reduced": make(ch, x0, bodies=ch.unreduced_state),
        "unreduced": make(un, y0),
        "reduced Dopri8": make(ch, x0, diffrax.Dopri8(), bodies=ch.unreduced_state),
        "unreduced Dopri8": make(un, y0, diffrax.Dopri8()),
    }


def compile_time(run, tol=1e-8):
    t = time.perf_counter()
    jax.block_until_ready(run(tol))
    return time.perf_counter() - t


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()
    print(f"load average at start: {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}")
    ch, x0, control = case(3)
    runs = runners(ch, x0, control)
    compiles = {name: compile_time(run) for name, run in runs.items()}
    ref, _ = runs["reduced Dopri8"](1e-13)
    check, _ = runs["unreduced Dopri8"](1e-13)
    ref_err = float(jnp.max(jnp.abs(ref - check)))
    print(f"reference (reduced, Dopri8, 1e-13) vs unreduced (Dopri8, 1e-13): {ref_err:.1e}")
    rows = []
    print(f"{'system':18s} {'rtol':>7s} {'error':>9s} {'steps':>6s} {'time':>10s}")
    for name in ("reduced", "unreduced", "reduced Dopri8", "unreduced Dopri8"):
        run = runs[name]
        for tol in TOLS:
            y, steps = run(tol)
            secs = median_time(lambda: run(tol), repeats=3, min_total=0.2, max_repeats=30)
            rows.append(dict(system=name, N=3, rtol=tol, error=float(jnp.max(jnp.abs(y - ref))), steps=int(steps),
                             seconds=secs, compile_seconds=compiles[name], reference_disagreement=ref_err))
            print(f"{name:18s} {tol:7.0e} {rows[-1]['error']:9.1e} {int(steps):6d} {secs * 1e3:8.2f}ms", flush=True)
    for name in runs:
        print(f"compile (first jitted call) {name:18s} {compiles[name]:6.1f} s")
    # N = 5: compile and speed at one tolerance, error against its own Dopri8 1e-13 reference
    ch5, x05, control5 = case(5)
    runs5 = runners(ch5, x05, control5)
    ref5 = runs5["reduced Dopri8"](1e-13)[0]
    for name in ("reduced", "unreduced"):
        c = compile_time(runs5[name])
        for tol in (1e-8, 1e-10):
            y, steps = runs5[name](tol)
            secs = median_time(lambda: runs5[name](tol), repeats=3, min_total=0.2, max_repeats=30)
            rows.append(dict(system=name, N=5, rtol=tol, error=float(jnp.max(jnp.abs(y - ref5))), steps=int(steps),
                             seconds=secs, compile_seconds=c, reference_disagreement=float("nan")))
            print(f"N = 5 {name:12s} rtol {tol:.0e}: error {rows[-1]['error']:.1e}, {int(steps)} steps, "
                  f"{secs * 1e3:.2f} ms; compile {c:.1f} s", flush=True)
    load_end = os.getloadavg()
    meta = dict(command="python benchmarks/reduction_work_precision.py", platform=platform.platform(),
                cpu_count=os.cpu_count(), load_average_start=list(load_start), load_average_end=list(load_end),
                horizon=T1, reference="reduced PlanarChain, Dopri8, rtol = atol = 1e-13")
    (OUT / "reduction_work_precision.json").write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))
    with open(OUT / "reduction_work_precision.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(rows, OUT / "reduction_work_precision.png")
    print(f"load average at end: {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f}; "
          f"written: {OUT}/reduction_work_precision.json, .csv, .png")


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for name in dict.fromkeys(r["system"] for r in rows):
        rr = [r for r in rows if r["system"] == name and r["N"] == 3]
        ax.loglog([r["seconds"] for r in rr], [max(r["error"], 1e-16) for r in rr], "o-", label=name)
    ax.set(xlabel="wall time of the jitted solve [s]", ylabel="max error of the bodies' final state",
           title="3-link chain, T = 5 s: reduced (SE(2)) vs unreduced (R^9 + hinges)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
