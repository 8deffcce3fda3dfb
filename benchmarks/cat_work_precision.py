"""Work-precision of the torque-driven falling cat: nhjax against SciPy and Numba.

Same equations (Iwai 7.14-7.15), same torques, same initial state, same
reference (SciPy DOP853 at 1e-13), measured in one run on one machine
(../shared/BENCHMARKS.md). For every rtol = atol in 1e-3 .. 1e-12 and every
solver: final-state error (max abs), accepted steps, median wall time of >= 5
solves after compile. Compile times are reported separately.

nhjax is timed two ways: ``simulate()`` as a user calls it (with its input
checks and diagnostics), and the solve jitted end to end (``jax.jit`` around
``simulate``, the way it runs inside an optimizer or a batch).

Also: the cost and error of reconstructing both cylinder attitudes on SO(3)
with RKMK45, against integrating the chart coordinates (Tsit5) and forming the
attitudes from them.

Writes experiments/out/bench/cat_work_precision.{csv,json,png}.
"""

from __future__ import annotations

import csv
import json
import sys
import time
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import nhjax
from nhjax.scenes import FallingCat

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "peers"))
sys.path.insert(0, str(HERE))
import falling_cat as peers  # noqa: E402
import _timing  # noqa: E402

OUT = HERE.parent / "experiments" / "out" / "bench"
RTOLS = [10.0**-k for k in range(3, 13)]


def median_time(fn, min_total=0.2):
    return _timing.median_time(fn, min_total=min_total)


def first_call(fn):
    t = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - t


def case():
    c = peers.CAT_DEFAULT
    cat = FallingCat(I1=c["I1"], lam=c["lam"], B=c["B"])
    ctrl = nhjax.Sinusoids([c["a0"], 0.0], [c["a1"], c["a2"]], [c["w1"], c["w2"]], [0.0, np.pi / 2])
    return cat, ctrl, jnp.asarray(c["y0"], float), float(c["t1"])


def nhjax_rows(ref, solvers):
    cat, ctrl, x0, t1 = case()
    rows = []
    for name, solver in solvers.items():

        def eager(rtol, solver=solver):
            return simulate_final(cat, ctrl, x0, t1, solver, rtol)

        jitted = jax.jit(lambda x0, rtol, solver=solver: nhjax.simulate(
            cat, x0, t1, control=ctrl, solver=solver, rtol=rtol, atol=rtol, saveat=2, track_work=False).xs[-1])
        compile_eager = first_call(lambda: eager(1e-6))
        compile_jit = first_call(lambda: jitted(x0, 1e-6))
        for rtol in RTOLS:
            traj = nhjax.simulate(cat, x0, t1, control=ctrl, solver=solver, rtol=rtol, atol=rtol, saveat=2,
                                  max_steps=200_000)
            err = float(np.max(np.abs(np.asarray(traj.xs[-1]) - ref)))
            rows.append(dict(
                solver=f"nhjax {name}", rtol=rtol, error=err, steps=int(traj.num_accepted_steps),
                seconds=median_time(lambda: eager(rtol)), compile_seconds=compile_eager,
                note="simulate() call",
            ))
            rows.append(dict(
                solver=f"nhjax {name} (jit)", rtol=rtol, error=err, steps=int(traj.num_accepted_steps),
                seconds=median_time(lambda: jitted(x0, rtol)), compile_seconds=compile_jit,
                note="jax.jit(simulate)",
            ))
    return rows


def simulate_final(cat, ctrl, x0, t1, solver, rtol):
    return nhjax.simulate(cat, x0, t1, control=ctrl, solver=solver, rtol=rtol, atol=rtol, saveat=2,
                          track_work=False, max_steps=200_000).xs[-1]


def peer_rows(ref):
    rows = []
    p, y0 = peers.case_params(), peers.case_y0()
    t = time.perf_counter()
    peers.dp54_numba(y0, 10.0, 1e-6, 1e-6, p)
    numba_compile = time.perf_counter() - t
    for rtol in RTOLS:
        for method in ("RK45", "DOP853"):
            out = peers.solve_scipy(method, rtol, rtol)
            sec = median_time(lambda: peers.solve_scipy(method, rtol, rtol), min_total=0.05)
            rows.append(dict(solver=f"scipy {method}", rtol=rtol, error=float(np.max(np.abs(out["y1"] - ref))),
                             steps=int(out["nsteps"]), seconds=sec, compile_seconds=0.0, note="solve_ivp"))
        y1, nacc, _ = peers.dp54_numba(y0, 10.0, rtol, rtol, p)
        sec = median_time(lambda: peers.dp54_numba(y0, 10.0, rtol, rtol, p))
        rows.append(dict(solver="numba DP5", rtol=rtol, error=float(np.max(np.abs(y1 - ref))), steps=int(nacc),
                         seconds=sec, compile_seconds=numba_compile, note="@njit"))
    return rows


def rkmk_rows():
    """Attitudes of both cylinders: RKMK45 on SO(3) vs Tsit5 in the chart, against a 1e-13 chart run."""
    cat, ctrl, x0, t1 = case()
    ref = nhjax.simulate(cat, x0, t1, control=ctrl, rtol=1e-13, atol=1e-13, saveat=2, solver=diffrax.Dopri8())
    Rref = cat.poses(ref.xs[-1, :3])[0]
    att = cat.attitude_model()
    y0 = att.initial_state(float(x0[0]), chi_dot=float(x0[4]))
    rows = []
    for rtol in (1e-4, 1e-6, 1e-8, 1e-10, 1e-12):
        def run_att():
            return nhjax.simulate(att, y0, t1, control=ctrl, rtol=rtol, atol=rtol, saveat=2, track_work=False)

        def run_chart():
            return nhjax.simulate(cat, x0, t1, control=ctrl, rtol=rtol, atol=rtol, saveat=2, track_work=False)

        ta, tc = run_att(), run_chart()
        Ra = jnp.stack([ta.xs[0][-1], ta.xs[1][-1]])
        Rc = cat.poses(tc.xs[-1, :3])[0]
        rows.append(dict(
            rtol=rtol,
            rkmk_error=float(jnp.max(jnp.abs(Ra - Rref))), rkmk_steps=int(ta.num_accepted_steps),
            rkmk_seconds=median_time(run_att),
            rkmk_orthogonality=float(jnp.max(jnp.abs(jnp.einsum("nji,njk->nik", Ra, Ra) - jnp.eye(3)))),
            chart_error=float(jnp.max(jnp.abs(Rc - Rref))), chart_steps=int(tc.num_accepted_steps),
            chart_seconds=median_time(run_chart),
        ))
    return rows


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    for solver in dict.fromkeys(r["solver"] for r in rows):
        rs = [r for r in rows if r["solver"] == solver]
        ax.loglog([r["seconds"] for r in rs], [max(r["error"], 1e-16) for r in rs], "o-", label=solver, ms=3)
    ax.set_xlabel("wall time per solve after compile [s]")
    ax.set_ylabel("final-state error (max abs)")
    ax.set_title("Falling cat (Iwai 7.14-7.15), T = 10 s, rtol = atol = 1e-3 .. 1e-12")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    ref = peers.reference_solution()
    solvers = {"Tsit5": diffrax.Tsit5(), "Dopri5": diffrax.Dopri5(), "Dopri8": diffrax.Dopri8(),
               "RKMK45": nhjax.RKMK45(), "RKMK87": nhjax.RKMK87()}
    rows = peer_rows(ref) + nhjax_rows(ref, solvers)
    with open(OUT / "cat_work_precision.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    att = rkmk_rows()
    (OUT / "cat_work_precision.json").write_text(json.dumps(dict(work_precision=rows, attitudes=att), indent=1))
    plot(rows, OUT / "cat_work_precision.png")

    print(f"{'solver':24s} {'rtol':>7s} {'error':>9s} {'steps':>6s} {'time':>10s} {'compile':>8s}")
    for r in rows:
        print(f"{r['solver']:24s} {r['rtol']:7.0e} {r['error']:9.2e} {r['steps']:6d} "
              f"{r['seconds'] * 1e3:8.3f}ms {r['compile_seconds']:7.2f}s")
    print("\nattitudes of both cylinders at T = 10 s: RKMK45 on SO(3) vs Tsit5 chart + formula")
    print(f"{'rtol':>7s} {'RKMK err':>9s} {'steps':>6s} {'time':>9s} {'|gTg-I|':>8s} | {'chart err':>9s} {'steps':>6s} {'time':>9s}")
    for r in att:
        print(f"{r['rtol']:7.0e} {r['rkmk_error']:9.2e} {r['rkmk_steps']:6d} {r['rkmk_seconds'] * 1e3:7.2f}ms "
              f"{r['rkmk_orthogonality']:8.1e} | {r['chart_error']:9.2e} {r['chart_steps']:6d} "
              f"{r['chart_seconds'] * 1e3:7.2f}ms")
    print(f"\nwritten: {OUT}/cat_work_precision.csv, .json, .png")


if __name__ == "__main__":
    main()
