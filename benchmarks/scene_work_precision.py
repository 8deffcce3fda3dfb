"""Work-precision of simulate() on every scene of the compile-time registry.

For each scene of benchmarks/compile_times.py (same states, horizons and
controls), rtol = atol swept from 1e-4 to 1e-12 with the default solver
(RKMK45: Dormand-Prince 5(4), Munthe-Kaas on group-valued parts, projected
after each step where the scene has position constraints), and for flat states
also diffrax's Dopri8. Reported per run: final-state error (max abs over the
flattened final state, rotation matrices entry-wise) against a reference,
accepted steps, wall time of the jitted solve (median of >= 3 after compile).

Reference: RKMK45 at rtol = atol = 1e-13, checked against a second method
(Dopri8 at 1e-13 for flat states, RKMK45 at 3e-14 for group-valued ones); the
disagreement of the two is printed as the reference's own error bar.

Writes experiments/out/bench/scene_work_precision.{json,csv,png}.
"""

from __future__ import annotations

import csv
import json
import os
import platform
import sys
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import nhjax
import nhjax.scenes as S
from jax.flatten_util import ravel_pytree

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _timing import median_time  # noqa: E402
from compile_times import CASES  # noqa: E402

OUT = HERE.parent / "experiments" / "out" / "bench"
TOLS = [1e-4, 1e-6, 1e-8, 1e-10, 1e-12]


def build(name):
    ns = dict(np=np, nhjax=nhjax, S=S, control=None)
    exec(CASES[name], ns)  # noqa: S102  (our own registry of cases)
    return ns["system"], ns["x0"], float(ns["t1"]), ns["control"]


def timed(fn):
    return median_time(fn, repeats=3, min_total=0.2, max_repeats=50)


def scene_rows(name):
    system, x0, t1, control = build(name)
    flat = all(isinstance(s, nhjax.lie.Euclidean) for s in jax.tree_util.tree_leaves(
        system.spaces, is_leaf=nhjax.lie.spaces.is_space))

    def runner(solver):
        @jax.jit
        def run(tol):
            tr = nhjax.simulate(system, x0, t1, control=control, rtol=tol, atol=tol, saveat=2,
                                solver=solver, diagnostics=False, max_steps=400_000)
            return ravel_pytree(tr.x_end)[0], tr.num_accepted_steps
        return run

    default = runner(None)
    ref, _ = default(1e-13)
    if flat:
        check, _ = runner(diffrax.Dopri8())(1e-13)
        second = "Dopri8 1e-13"
    else:
        check, _ = default(3e-14)
        second = "RKMK45 3e-14"
    ref_err = float(jnp.max(jnp.abs(ref - check)))
    rows = []
    solvers = [("RKMK45 (default)", default)] + ([("Dopri8", runner(diffrax.Dopri8()))] if flat else [])
    for sname, run in solvers:
        for tol in TOLS:
            y, steps = run(tol)
            rows.append(dict(scene=name, solver=sname, rtol=tol, error=float(jnp.max(jnp.abs(y - ref))),
                             steps=int(steps), seconds=timed(lambda: run(tol)), reference_check=second,
                             reference_disagreement=ref_err))
    return rows


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    cols = 4
    fig, axes = plt.subplots(-(-len(scenes) // cols), cols, figsize=(14, 3 * -(-len(scenes) // cols)))
    for ax, sc in zip(axes.ravel(), scenes):
        for sname in dict.fromkeys(r["solver"] for r in rows if r["scene"] == sc):
            rr = [r for r in rows if r["scene"] == sc and r["solver"] == sname]
            ax.loglog([r["seconds"] for r in rr], [max(r["error"], 1e-16) for r in rr], "o-", label=sname)
        ax.set_title(sc, fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(scenes):]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7)
    fig.supxlabel("wall time of the jitted solve [s]")
    fig.supylabel("final-state error")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()
    rows = []
    print(f"{'scene':24s} {'solver':18s} " + " ".join(f"{t:>18g}" for t in TOLS))
    for name in CASES:
        try:
            rr = scene_rows(name)
        except Exception as e:  # a scene that cannot reach a tolerance is reported, not fatal
            print(f"{name:24s} failed: {type(e).__name__}: {str(e).splitlines()[0]}")
            continue
        rows += rr
        for sname in dict.fromkeys(r["solver"] for r in rr):
            cells = [f"{r['error']:8.1e}/{r['seconds'] * 1e3:7.2f}ms" for r in rr if r["solver"] == sname]
            print(f"{name:24s} {sname:18s} " + " ".join(cells), flush=True)
        print(f"{'':24s} reference vs {rr[0]['reference_check']}: {rr[0]['reference_disagreement']:.1e}")
    load_end = os.getloadavg()
    meta = dict(command="python benchmarks/scene_work_precision.py", platform=platform.platform(),
                cpu_count=os.cpu_count(), load_average_start=list(load_start), load_average_end=list(load_end))
    (OUT / "scene_work_precision.json").write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))
    with open(OUT / "scene_work_precision.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(rows, OUT / "scene_work_precision.png")
    print(f"load average start {load_start[0]:.2f}, end {load_end[0]:.2f}; "
          f"written: {OUT}/scene_work_precision.json, .csv, .png")


if __name__ == "__main__":
    main()
