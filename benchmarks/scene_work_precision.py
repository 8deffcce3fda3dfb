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

Seed 002's scenes of issue 18 (BallInCone, RollRing, ThreeCylinders,
ThreeCylindersMinimal) are also solved with SciPy's ``solve_ivp`` (RK45 and DOP853, the
same rtol = atol) on the same vector field (jitted, called from NumPy once per
stage, no projection: SciPy integrates the index-reduced ODE as it is), against the
same reference; its wall time is that of the whole solve_ivp call. A case may set
``jump_ts`` (RollRing: the kinks of its drive moment), passed to simulate(); SciPy
has no such option and steps across them.

``python benchmarks/scene_work_precision.py [scene ...]`` runs the named scenes only
(then the output files get the suffix ``_subset``).

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
# cases of this benchmark only (compile_times.py is not ours to edit); same format as CASES
EXTRA_CASES = {  # work-precision only: RollRing's steps land on the kinks of its drive moment
    "RollRing": """
system = S.RollRing(); x0 = system.initial_state(); t1 = 10.0; jump_ts = system.kink_times()""",
}
ALL_CASES = {**CASES, **EXTRA_CASES}
SCIPY_SCENES = ("BallInCone", "RollRing", "ThreeCylinders", "ThreeCylindersMinimal")


def build(name):
    ns = dict(np=np, nhjax=nhjax, S=S, control=None)
    exec(ALL_CASES[name], ns)  # noqa: S102  (our own registry of cases)
    return ns["system"], ns["x0"], float(ns["t1"]), ns["control"], ns.get("jump_ts")


def scipy_rows(name, system, x0, t1, ref, second, ref_err):
    """SciPy solve_ivp (RK45, DOP853) on the system's vector field, error at t1 against ref."""
    import time

    from scipy.integrate import solve_ivp

    f = jax.jit(lambda t, x: system.vector_field(t, x, None))
    x0n = np.asarray(x0, dtype=float)
    rhs = lambda t, x: np.asarray(f(t, x))  # noqa: E731
    solve_ivp(rhs, (0.0, 1e-3 * t1), x0n, method="RK45", rtol=1e-3, atol=1e-3)  # compile and warm up, untimed
    rows = []
    for method in ("RK45", "DOP853"):
        for tol in TOLS:
            start = time.perf_counter()
            sol = solve_ivp(rhs, (0.0, t1), x0n, method=method, rtol=tol, atol=tol)
            seconds = time.perf_counter() - start
            err = float(np.max(np.abs(sol.y[:, -1] - np.asarray(ref)))) if sol.success else float("nan")
            rows.append(dict(scene=name, solver=f"SciPy {method}", rtol=tol, error=err,
                             steps=int(sol.t.size - 1), seconds=seconds, reference_check=second,
                             reference_disagreement=ref_err))
    return rows


def timed(fn):
    return median_time(fn, repeats=3, min_total=0.2, max_repeats=50)


def scene_rows(name):
    system, x0, t1, control, jump_ts = build(name)
    flat = all(isinstance(s, nhjax.lie.Euclidean) for s in jax.tree_util.tree_leaves(
        system.spaces, is_leaf=nhjax.lie.spaces.is_space))

    def runner(solver):
        @jax.jit
        def run(tol):
            tr = nhjax.simulate(system, x0, t1, control=control, rtol=tol, atol=tol, saveat=2,
                                solver=solver, diagnostics=False, max_steps=400_000, jump_ts=jump_ts)
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
    if name in SCIPY_SCENES and control is None and flat:
        rows += scipy_rows(name, system, x0, t1, ref, second, ref_err)
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


def main(names=None):
    OUT.mkdir(parents=True, exist_ok=True)
    names = names or list(ALL_CASES)
    suffix = "" if set(names) == set(ALL_CASES) else "_subset"
    load_start = os.getloadavg()
    rows = []
    print(f"{'scene':24s} {'solver':18s} " + " ".join(f"{t:>18g}" for t in TOLS))
    for name in names:
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
    meta = dict(command=" ".join(["python benchmarks/scene_work_precision.py"] + (names if suffix else [])),
                platform=platform.platform(),
                cpu_count=os.cpu_count(), load_average_start=list(load_start), load_average_end=list(load_end))
    (OUT / f"scene_work_precision{suffix}.json").write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))
    with open(OUT / f"scene_work_precision{suffix}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(rows, OUT / f"scene_work_precision{suffix}.png")
    print(f"load average start {load_start[0]:.2f}, end {load_end[0]:.2f}; "
          f"written: {OUT}/scene_work_precision{suffix}.json, .csv, .png")


if __name__ == "__main__":
    # scene names (others, e.g. "scene_work_precision" from `nhjax bench`, are ignored)
    main([a for a in sys.argv[1:] if a in ALL_CASES] or None)
