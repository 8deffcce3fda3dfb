"""The falling cat's velocity-controlled somersault: controls (nhjax) against CasADi + IPOPT.

Problem: ``controls.tasks.velocity_somersault_chart(FallingCatKinematic(), 0.6,
-pi, 2.0)`` -- Iwai's chart, x = (theta, chi, psi), u = (theta', chi'),
x(0) = (0.6, 0, 0), x(2) = (0.6, 2 pi, -pi), minimizing the vibrational energy.
Its optimum, 0.36024448721 (Pontryagin shooting; the direct Chebyshev(10)
solution agrees to 2e-10 relative), is the reference for every cost below.

Peer (``peers/casadi_somersault.py``): CasADi + IPOPT, multiple shooting on
N = 20, 40, 80 equal intervals, piecewise-constant ("pc") or piecewise-linear
("pl") controls, each interval integrated by 4 RK4 substeps (exact Hessian,
expanded to SX) or by CVODES at 1e-10 (L-BFGS Hessian); IPOPT tol 1e-10; warm
start from the fixed-theta loop. The CasADi dynamics and running cost are
checked against ``FallingCatKinematic.vector_field`` / ``vibrational_power`` at
random points (to 1e-12) before anything is timed. For each configuration:
the IPOPT cost and its relative difference from the reference, the NLP's
constraint violation, the cost and terminal violation of its control
re-simulated on the continuous system (SciPy DOP853 1e-12), iterations, build
time (symbolics + nlpsol) and the median wall time of >= 5 solves from the
warm start.

Ours (``controls``), called as in tests/test_controls.py::
test_somersault_direct_and_pontryagin_agree, each timed after a first
(compiling) call as the median of 3 further calls:

* Pontryagin: ``controls.continuation`` of ``solve_pontryagin`` over 4 turns
  from the fixed-theta loop's holonomy to -pi, started from the loop's exact
  costates (the whole pipeline), and a single ``solve_pontryagin`` straight at
  -pi from the same costates;
* direct: ``solve_direct`` with ``Chebyshev(10, T, 2)`` controls (single
  shooting, augmented Lagrangian + L-BFGS) from the loop's controls.

Time ratio = seconds / seconds of CasADi's most accurate RK4 configuration
(smallest error of the re-simulated cost), for every row, all measured in this
one run; build time of ours = first call minus the median (the compile; the
single Pontryagin solve reuses what the continuation compiled). Writes
experiments/out/bench/somersault_peer.{csv,json}. Skips with a message if
casadi is not installed (``pip install 'casadi>=3.6,<4'``, extra ``peers``).
"""

from __future__ import annotations

import csv
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "experiments" / "out" / "bench"
REFERENCE_COST = 0.36024448721
CONFIGS = [  # (integrator, controls, N)
    ("rk4", "pc", 20), ("rk4", "pc", 40), ("rk4", "pc", 80),
    ("rk4", "pl", 20), ("rk4", "pl", 40), ("rk4", "pl", 80),
    ("cvodes", "pc", 20), ("cvodes", "pl", 20),
]
OURS_REPEATS = 3


def median_time(fn, repeats=5, min_total=0.5, max_repeats=50):
    ts, out, start = [], None, time.perf_counter()
    while len(ts) < repeats or (time.perf_counter() - start < min_total and len(ts) < max_repeats):
        t = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)), out


def rel(cost):
    return (cost - REFERENCE_COST) / REFERENCE_COST


def check_formulas(cs, cat, n=200, seed=0):
    """CasADi f, L against FallingCatKinematic.vector_field / vibrational_power."""
    import jax
    import jax.numpy as jnp

    f, L = cs.cat_functions()
    field = jax.jit(lambda x, u: cat.vector_field(0.0, x, u))
    power = jax.jit(lambda x, u: cat.vibrational_power(x, u))
    rng = np.random.default_rng(seed)
    worst_f = worst_L = worst_np = 0.0
    for _ in range(n):
        x = np.array([rng.uniform(0.05, np.pi - 0.05), rng.uniform(-7, 7), rng.uniform(-7, 7)])
        u = rng.normal(size=2) * 3
        fj, Lj = np.asarray(field(jnp.asarray(x), jnp.asarray(u))), float(power(jnp.asarray(x), jnp.asarray(u)))
        fc, Lc = np.asarray(f(x, u)).ravel(), float(L(x, u))
        worst_f = max(worst_f, np.abs(fc - fj).max() / max(np.abs(fj).max(), 1e-300))
        worst_L = max(worst_L, abs(Lc - Lj) / max(abs(Lj), 1e-300))
        worst_np = max(worst_np, np.abs(cs.rhs_numpy(x, u) - fj).max() / np.abs(fj).max(),
                       abs(cs.cost_rate_numpy(x, u) - Lj) / abs(Lj))
    assert max(worst_f, worst_L, worst_np) < 1e-12, (worst_f, worst_L, worst_np)
    return dict(vector_field_max_rel=worst_f, vibrational_power_max_rel=worst_L, numpy_max_rel=worst_np, points=n)


def casadi_rows(cs):
    rows = []
    for integrator, ctl, N in CONFIGS:
        nlp = cs.build(N=N, controls=ctl, integrator=integrator)
        first = cs.solve(nlp)  # first call: any lazy set-up of the solver
        sec, r = median_time(lambda: cs.solve(nlp))
        assert abs(r["cost"] - first["cost"]) <= 1e-12 * abs(first["cost"])
        ev = cs.evaluate(nlp, r)
        row = dict(
            solver="CasADi+IPOPT", method=f"multiple shooting N={N}, {ctl} controls, "
            + ("RK4 x4 substeps, exact Hessian" if integrator == "rk4" else "CVODES 1e-10, L-BFGS Hessian"),
            integrator=integrator, controls=ctl, N=N, n_variables=nlp["n_variables"],
            cost=r["cost"], rel_diff=rel(r["cost"]), violation=r["violation"],
            resim_cost=ev["cost"], resim_rel_diff=rel(ev["cost"]), resim_violation=ev["violation"],
            iterations=r["iterations"], status=r["status"], seconds=sec, first_call_seconds=first["seconds"],
            build_seconds=nlp["build_seconds"],
        )
        rows.append(row)
        print(f"  {row['method']:58s} cost {row['cost']:.11f} rel {row['rel_diff']:+.1e} viol "
              f"{row['violation']:.0e} | resim rel {row['resim_rel_diff']:+.1e} viol {row['resim_violation']:.0e} | "
              f"it {row['iterations']:3d} {r['status']:26s} {sec * 1e3:9.2f} ms  build {nlp['build_seconds']:.2f} s",
              flush=True)
    return rows


def ours_rows():
    import jax.numpy as jnp

    import controls
    from controls.tasks import fixed_theta_costates, velocity_somersault_chart
    from nhjax.scenes import FallingCatKinematic

    cat, th0, T = FallingCatKinematic(), 0.6, 2.0
    loop_turn = float(-2 * np.pi * cat.f(th0))
    p0, nu = fixed_theta_costates(cat, th0, T)
    ocp = velocity_somersault_chart(cat, th0, -np.pi, T)

    def pontryagin_chain():
        def solve(v, z):
            return controls.solve_pontryagin(velocity_somersault_chart(cat, th0, v, T), *(z or (p0, nu)))

        rs = controls.continuation(solve, np.linspace(loop_turn, -np.pi, 4))
        r = rs[-1]
        r.iterations_total = sum(x.iterations for x in rs)
        return r

    def pontryagin_single():
        r = controls.solve_pontryagin(ocp, p0, nu)
        r.iterations_total = r.iterations
        return r

    param = controls.Chebyshev(10, T, 2)
    guess = param.fit(lambda t: jnp.array([0.0, 2 * np.pi / T]))

    def direct():
        return controls.solve_direct(ocp, param, guess)

    rows = []
    for name, method, fn in (
        ("controls.solve_pontryagin", "continuation: 4 turns from the loop's holonomy to -pi, single shooting, Newton",
         pontryagin_chain),
        ("controls.solve_pontryagin", "one solve at -pi from the loop's costates, single shooting, Newton",
         pontryagin_single),
        ("controls.solve_direct", "Chebyshev(10) controls, single shooting, aug. Lagrangian + L-BFGS", direct),
    ):
        t = time.perf_counter()
        try:
            first = fn()
        except Exception as e:  # noqa: BLE001 -- report, do not stop the benchmark
            print(f"  {name} ({method}): failed: {type(e).__name__}: {e}", flush=True)
            rows.append(dict(solver=name, method=method, status=f"failed: {type(e).__name__}: {e}"))
            continue
        first_s = time.perf_counter() - t
        sec, r = median_time(fn, repeats=OURS_REPEATS, min_total=0.0)
        converged = bool(r.converged)
        iters = getattr(r, "iterations_total", r.iterations)
        row = dict(solver=name, method=method, cost=float(r.cost), rel_diff=rel(float(r.cost)),
                   violation=float(r.violation), iterations=int(iters),
                   status="converged" if converged else r.message, seconds=sec, first_call_seconds=first_s,
                   build_seconds=max(first_s - sec, 0.0))
        if hasattr(r, "residual"):
            row["shooting_residual"] = float(r.residual)
        if fn is pontryagin_single:
            row["note"] = "compiled by the continuation row (same shapes): its build time is there"
        rows.append(row)
        print(f"  {name:26s} {method:80s} cost {row['cost']:.11f} rel {row['rel_diff']:+.1e} viol "
              f"{row['violation']:.0e} it {iters:4d} {row['status']:10s} {sec:8.3f} s  (first call {first_s:.1f} s)",
              flush=True)
    return rows


def main():
    load_start = os.getloadavg()
    print(f"load average at start (1, 5, 15 min): {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}")
    try:
        import casadi
    except ImportError:
        print("somersault_peer: casadi is not installed -- skipped "
              "(install it with: python -m pip install 'casadi>=3.6,<4', or the extra 'peers')")
        return
    sys.path.insert(0, str(HERE / "peers"))
    import casadi_somersault as cs

    import jax

    from nhjax.scenes import FallingCatKinematic

    OUT.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    cat = FallingCatKinematic()
    for k in ("I1", "lam", "B"):
        assert float(getattr(cat, k)) == cs.CAT[k], k
    check = check_formulas(cs, cat)
    print(f"CasADi formulas vs FallingCatKinematic (200 random points): vector_field max rel "
          f"{check['vector_field_max_rel']:.1e}, vibrational_power max rel {check['vibrational_power_max_rel']:.1e}")
    print("CasADi + IPOPT (median of >= 5 solves from the loop warm start):", flush=True)
    peer = casadi_rows(cs)
    print("controls (median of 3 calls after a first, compiling call):", flush=True)
    ours = ours_rows()

    # ratios: ours against the most accurate RK4 configuration of the peer, and against each
    rk4 = [r for r in peer if r["integrator"] == "rk4"]
    best = min(rk4, key=lambda r: (abs(r["resim_rel_diff"]), r["seconds"]))
    for r in ours:
        if "seconds" in r:
            r["time_ratio_vs_casadi_best"] = r["seconds"] / best["seconds"]
    for r in peer:
        r["time_ratio_vs_casadi_best"] = r["seconds"] / best["seconds"]
    rows = peer + ours

    fields = ["solver", "method", "cost", "rel_diff", "violation", "resim_rel_diff", "resim_violation", "iterations",
              "status", "seconds", "build_seconds", "first_call_seconds", "time_ratio_vs_casadi_best", "N",
              "controls", "integrator", "n_variables", "shooting_residual", "note"]
    with open(OUT / "somersault_peer.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    load_end = os.getloadavg()
    import scipy

    meta = dict(
        problem="velocity_somersault_chart(FallingCatKinematic(), theta0=0.6, turn=-pi, T=2, windings=1)",
        reference_cost=REFERENCE_COST, formula_check=check, casadi_best=best["method"],
        machine=dict(platform=platform.platform(), python=platform.python_version(), cpu_count=os.cpu_count(),
                     jax=jax.__version__, casadi=casadi.__version__, scipy=scipy.__version__),
        command="python benchmarks/somersault_peer.py", total_seconds=time.perf_counter() - start,
        load_average_start=list(load_start), load_average_end=list(load_end),
    )
    (OUT / "somersault_peer.json").write_text(json.dumps(dict(meta=meta, rows=rows), indent=1, default=float))

    print("\n" + "=" * 150)
    print(f"Somersault in Iwai's chart, reference cost {REFERENCE_COST}; time ratio = seconds / seconds of "
          f"CasADi '{best['method']}'")
    print(f"{'solver':28s} {'method':70s} {'cost':>14s} {'rel diff':>9s} {'viol':>7s} {'it':>4s} {'time':>10s} "
          f"{'build':>7s} {'ratio':>8s}")
    for r in rows:
        if "seconds" not in r:
            print(f"{r['solver']:28s} {r['method'][:70]:70s} {r['status']}")
            continue
        print(f"{r['solver']:28s} {r['method'][:70]:70s} {r['cost']:14.11f} {r['rel_diff']:+9.1e} "
              f"{r['violation']:7.0e} {r['iterations']:4d} {r['seconds'] * 1e3:8.1f}ms {r['build_seconds']:6.2f}s "
              f"{r['time_ratio_vs_casadi_best']:8.1f}")
    for r in rows:
        if r.get("note"):
            print(f"note: {r['solver']} ({r['method'][:50]}...): {r['note']}")
    print(f"\nload average (1, 5, 15 min): start {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}, "
          f"end {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f}")
    print(f"total {meta['total_seconds']:.0f} s; written: {OUT}/somersault_peer.csv, .json")


if __name__ == "__main__":
    main()
