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
  shooting) from the loop's controls, on its defaults (SQP with damped-BFGS
  Hessians) and with ``optimizer="lbfgs"`` (augmented Lagrangian + L-BFGS).

Goals table (issue 16): each task's first answer in a fresh process ("cold":
an empty temporary JAX cache directory via NHJAX_CACHE_DIR; "warm": a second
fresh process with the same directory), the process wall time (interpreter,
imports, problem set-up, compile and solve) and the solve call alone, and the
after-compile time (median of 2 further solves in the warm process), with the
cost, its relative difference from the reference and the violation. Tasks: the
chart somersault by ``solve_direct`` (Chebyshev(10), from the loop) and by
``solve_pontryagin`` (one solve at -pi from the loop's costates), the
free-winding somersault (``somersault_free_winding`` in smooth coordinates,
starts 1, 0, -1, 2, Pontryagin polish) and the torque somersault
(``solve_direct``, Chebyshev(12), from ``torque_loop_guess``). A child is run as
``python benchmarks/somersault_peer.py --first-answer TASK``. ``--goals``: only
the goals table (no CasADi rows).

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
            return controls.solve_pontryagin(velocity_somersault_chart(cat, th0, v, T), *(z or (p0, nu)),
                                             progress=False)

        rs = controls.continuation(solve, np.linspace(loop_turn, -np.pi, 4))
        r = rs[-1]
        r.iterations_total = sum(x.iterations for x in rs)
        return r

    def pontryagin_single():
        r = controls.solve_pontryagin(ocp, p0, nu, progress=False)
        r.iterations_total = r.iterations
        return r

    param = controls.Chebyshev(10, T, 2)
    guess = param.fit(lambda t: jnp.array([0.0, 2 * np.pi / T]))

    def direct():  # defaults: SQP
        return controls.solve_direct(ocp, param, guess, progress=False)

    def direct_lbfgs():
        return controls.solve_direct(ocp, param, guess, progress=False, optimizer="lbfgs")

    rows = []
    for name, method, fn in (
        ("controls.solve_pontryagin", "continuation: 4 turns from the loop's holonomy to -pi, single shooting, Newton",
         pontryagin_chain),
        ("controls.solve_pontryagin", "one solve at -pi from the loop's costates, single shooting, Newton",
         pontryagin_single),
        ("controls.solve_direct", "Chebyshev(10) controls, single shooting, defaults (SQP, damped BFGS)", direct),
        ("controls.solve_direct", "Chebyshev(10) controls, single shooting, optimizer='lbfgs' (aug. Lagrangian)",
         direct_lbfgs),
    ):
        t = time.perf_counter()
        try:
            fn()  # first call: compiles
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


# --------------------------------------------------------------- first answer (issue 16)
GOALS = {  # task: (goal cold [s], goal warm [s])
    "chart_direct": (5.0, 1.0), "chart_pontryagin": (5.0, 1.0), "free_winding": (5.0, 1.0),
    "torque_direct": (15.0, None),
}
TASK_TEXT = {
    "chart_direct": "chart somersault, solve_direct Chebyshev(10), loop start",
    "chart_pontryagin": "chart somersault, solve_pontryagin at -pi from the loop's costates",
    "free_winding": "free-winding somersault (4 starts + Pontryagin polish)",
    "torque_direct": "torque somersault, solve_direct Chebyshev(12), loop torques",
}


def first_answer_task(task):
    """Child process: build and solve ``task`` once (the first answer), then twice more
    (after compile); print one JSON line."""
    t_start = time.perf_counter()
    import jax.numpy as jnp

    import controls
    from controls.tasks import (
        fixed_theta_costates,
        somersault_free_winding,
        torque_loop_guess,
        torque_somersault,
        velocity_somersault_chart,
    )
    from nhjax.scenes import FallingCat, FallingCatKinematic
    from nhjax.scenes.falling_cat import FallingCatSmooth

    t_import = time.perf_counter() - t_start
    cat, th0, T = FallingCatKinematic(), 0.6, 2.0

    def solve():
        if task == "chart_direct":
            ocp = velocity_somersault_chart(cat, th0, -np.pi, T)
            param = controls.Chebyshev(10, T, 2)
            r = controls.solve_direct(ocp, param, param.fit(lambda t: jnp.array([0.0, 2 * np.pi / T])),
                                      progress=False)
            return r.cost, r.violation, r.converged, REFERENCE_COST
        if task == "chart_pontryagin":
            ocp = velocity_somersault_chart(cat, th0, -np.pi, T)
            r = controls.solve_pontryagin(ocp, *fixed_theta_costates(cat, th0, T), progress=False)
            return r.cost, r.violation, r.converged, REFERENCE_COST
        if task == "free_winding":
            r = somersault_free_winding(FallingCatSmooth(cat.I1, cat.lam, cat.B), th0, -np.pi, T, progress=False)
            return r.indirect.cost, r.indirect.violation, bool(r.indirect.converged), REFERENCE_COST
        if task == "torque_direct":
            tcat = FallingCat.from_dimensions(1.0, 1.0, 0.25)
            param = controls.Chebyshev(12, T, 2)
            ocp = torque_somersault(tcat, th0, -np.pi, T)
            r = controls.solve_direct(ocp, param, torque_loop_guess(tcat, param, th0, T), progress=False)
            return r.cost, r.violation, r.converged, None
        raise SystemExit(f"unknown task {task}")

    report_first_answer(task, t_import, solve)


def report_first_answer(task, t_import, solve, reference=None):
    """In the child: time ``solve()`` (the first answer: tracing, compiling, solving) and
    two more calls (after compile), and print the FIRST_ANSWER line that
    run_first_answer reads. ``solve`` returns (cost, violation, converged) and optionally
    the reference cost (else ``reference``)."""
    t = time.perf_counter()
    cost, viol, conv, *rest = solve()
    first = time.perf_counter() - t
    first_cpu = time.process_time()  # CPU of this process (all threads) up to the first answer
    ref = rest[0] if rest and rest[0] is not None else reference
    from _timing import settle

    settle()  # after compile: the solver's background compiles done too
    after = []
    for _ in range(2):
        t = time.perf_counter()
        solve()
        after.append(time.perf_counter() - t)
    print("FIRST_ANSWER " + json.dumps(dict(
        task=task, import_seconds=t_import, first_seconds=first, first_cpu_seconds=first_cpu,
        after_seconds=float(np.median(after)),
        cost=float(cost), violation=float(viol), converged=bool(conv),
        rel_diff=None if ref is None else (float(cost) - ref) / ref)), flush=True)


def run_first_answer(script, task, cache_dir, timeout=1800):
    """``python script --first-answer task`` in a fresh process with NHJAX_CACHE_DIR=cache_dir:
    the child's JSON with the process wall time added (None fields if it failed)."""
    import subprocess

    import resource

    env = dict(os.environ, NHJAX_CACHE_DIR=cache_dir)
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    p = subprocess.run([sys.executable, str(script), "--first-answer", task], env=env, capture_output=True,
                       text=True, timeout=timeout)
    wall = time.perf_counter() - t
    ru2 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru2.ru_utime - ru.ru_utime) + (ru2.ru_stime - ru.ru_stime)
    for line in p.stdout.splitlines():
        if line.startswith("FIRST_ANSWER "):
            out = json.loads(line[len("FIRST_ANSWER "):])
            out["process_seconds"] = wall
            out["process_cpu_seconds"] = cpu
            return out
    tail = (p.stderr or p.stdout).strip().splitlines()[-3:]
    return dict(task=task, process_seconds=wall, failed=" | ".join(tail))


#: Cold processes per task, each with its own empty cache: the one with the faster first
#: answer counts, the other's solve time is printed beside it (this machine's speed
#: moves by tens of percent within the hour).
COLD_RUNS = 2


def goals_rows(script, tasks, goals, texts):
    """Cold (empty cache; the faster of ``COLD_RUNS`` processes) and warm (the last cold
    one's cache, new process) first answers per task."""
    import shutil
    import tempfile

    rows = []
    for task in tasks:
        load = os.getloadavg()[0]
        colds = []
        for k in range(COLD_RUNS):
            cache = tempfile.mkdtemp(prefix=f"nhjax-goals-{task}-")
            try:
                colds.append(run_first_answer(script, task, cache))
                if k == COLD_RUNS - 1:
                    warm = run_first_answer(script, task, cache)
            finally:
                shutil.rmtree(cache, ignore_errors=True)
        done = [c for c in colds if "failed" not in c]
        cold = min(done, key=lambda c: c["first_seconds"]) if done else colds[0]
        cold["other_cold_solve_seconds"] = [c.get("first_seconds") for c in colds if c is not cold]
        row = dict(task=task, what=texts[task], goal_cold=goals[task][0], goal_warm=goals[task][1], load=load,
                   cold=cold, warm=warm)
        rows.append(row)
        print_goal_row(row)
    return rows


def print_goal_header(peer_label):
    print(f"{'task':64s} {'cold: process/solve/CPU [s]':>31s} {'other':>6s} {'warm: process/solve/CPU [s]':>31s} "
          f"{'after compile':>14s} {'cost':>15s} {'rel diff':>9s} {'viol':>7s} {'load':>5s}   {peer_label}")


def print_goal_row(r, peer=""):
    c, w = r["cold"], r["warm"]
    for x in (c, w):  # CPU up to the first answer when the child reports it, else the whole process
        x.setdefault("first_cpu_seconds", x.get("process_cpu_seconds"))
    if "failed" in c or "failed" in w:
        print(f"{r['what'][:64]:64s} failed: {c.get('failed') or w.get('failed')}", flush=True)
        return
    gc = f"<= {r['goal_cold']:g}" if r["goal_cold"] else ""
    gw = f"<= {r['goal_warm']:g}" if r["goal_warm"] else ""
    rd = f"{w['rel_diff']:+9.1e}" if w.get("rel_diff") is not None else f"{'':>9s}"
    other = "/".join(f"{x:.1f}" for x in c.get("other_cold_solve_seconds") or [] if x is not None)
    print(f"{r['what'][:64]:64s} {c['process_seconds']:6.1f} /{c['first_seconds']:5.1f} /{c['first_cpu_seconds']:5.1f}"
          f" {gc:>8s} {other:>6s} {w['process_seconds']:6.1f} /{w['first_seconds']:5.1f} /{w['first_cpu_seconds']:5.1f} {gw:>8s}"
          f" {w['after_seconds']:12.3f} s "
          f"{w['cost']:15.11f} {rd} {w['violation']:7.0e} {r['load']:5.2f}   {peer}", flush=True)


def main():
    if "--first-answer" in sys.argv:
        first_answer_task(sys.argv[sys.argv.index("--first-answer") + 1])
        return
    if "--goals" in sys.argv:
        print("First answer (issue 16 goals), cold = fresh process + empty cache dir (the faster of two; 'other': "
              "the other's solve time), warm = a process after one that filled the cache:")
        print_goal_header("")
        goals_rows(Path(__file__).resolve(), list(GOALS), GOALS, TASK_TEXT)
        return
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
    print("first answer (issue 16 goals), cold = fresh process + empty cache dir (the faster of two; 'other': "
          "the other's solve time), warm = a process after one that filled the cache:", flush=True)
    print_goal_header("")
    goals = goals_rows(Path(__file__).resolve(), list(GOALS), GOALS, TASK_TEXT)

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
    (OUT / "somersault_peer.json").write_text(json.dumps(dict(meta=meta, rows=rows, goals=goals), indent=1,
                                                         default=float))

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
    ipopt = f"CasADi+IPOPT '{best['method'][:40]}': build {best['build_seconds']:.2f} s + solve {best['seconds']:.3f} s"
    print("\nGoals (issue 16): first answer cold <= 5 s, warm <= 1 s (torque: cold <= 15 s); after compile: "
          "direct no slower than IPOPT, Pontryagin faster. " + ipopt)
    print_goal_header("")
    for g in goals:
        print_goal_row(g)
    print(f"\nload average (1, 5, 15 min): start {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}, "
          f"end {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f}")
    print(f"total {meta['total_seconds']:.0f} s; written: {OUT}/somersault_peer.csv, .json")


if __name__ == "__main__":
    main()
