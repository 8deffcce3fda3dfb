"""Spherical-robot steering (issue 5): controls (nhjax) against CasADi + IPOPT.

Problem: ``controls.tasks.sphere_steering(ShellWithTop(), (0.5, 0.3), 3.0)`` --
the default robot from rest at the origin (top hanging) to rest at (0.5, 0.3) m
in T = 3 s, minimizing int |tau|^2 dt [N^2 m^2 s], tau the internal torque (top
axes); 10 terminal constraints (xy - target, Omega, omega, E^T gamma). The
reference for every cost below is the continuous optimum from Pontryagin's
conditions measured in this run (``REFERENCE_COST`` if that row fails).

Peer (``peers/casadi_steering.py``): CasADi + IPOPT on the reduced vector form
(``sphere_steering_reduced``: ShellWithTopReduced's hand-derived equations, 17
states), multiple shooting on N = 30, 60 equal intervals, piecewise-constant
("pc") or piecewise-linear ("pl") controls, M RK4 substeps per interval
expanded to SX, exact Hessian, IPOPT tol 1e-10. The CasADi dynamics and
terminal constraints (and their NumPy copies) are checked against
``ReducedSteering.vector_field`` / ``ReducedSteeringTarget`` at random points
(to 1e-12), and the initial state against the OCP's, before anything is timed.
Two starts per configuration: "linear" (the controls of ``linear_guess`` --
the minimum-effort control of the problem linearized at rest, fitted to
Chebyshev(12) -- sampled at the control times, and the node states from
integrating them with the NLP's own RK4 map) and "cold" (zero torque, node
states at rest on the straight line to the target). For each: the IPOPT cost
and its relative difference from the reference, the NLP's constraint
violation, the cost and terminal violation of its control re-simulated on the
continuous reduced system (SciPy DOP853 at 1e-12, restarted per interval),
iterations, build time (symbolics + nlpsol) and the median wall time of >= 5
solves (linear start) or 3 solves (cold start).

Ours (``controls``), each timed after a first (compiling) call as the median of
3 further calls:

* direct: ``solve_direct_newton(sphere_steering(...), Chebyshev(n, T, 3),
  linear_guess(ocp, param))`` for n = 6 and 12 (single shooting on SO(3) x
  SO(3) by RKMK, feasible-path Newton), and n = 6 again at the looser ``LOOSE``
  tolerances (IPOPT's terminal accuracy); its control re-simulated with
  ``controls.rollout`` at 1e-12 for the achieved cost and violation;
* Pontryagin: ``controls.pmp_residual`` of the Chebyshev(12) optimum on the
  reduced problem for costates and multipliers, then ``solve_pontryagin(...,
  solver="lm")`` (as in tests/test_steering.py::
  test_pontryagin_agrees_with_the_direct_optimum). Its time is the
  solve_pontryagin call only; ``pipeline_seconds`` adds the direct
  Chebyshev(12) solve and the pmp_residual call it starts from.

Time ratio = seconds / seconds of CasADi's most accurate configuration
(smallest terminal violation of the re-simulated control; linear start), for
every row, all measured in this one run; build time of ours = first call minus
the median (mostly the compile). Writes
experiments/out/bench/steering_peer.{csv,json}. Skips with a message if casadi
is not installed (``pip install 'casadi>=3.6,<4'``, extra ``peers``).

Goals table (issue 16): the first answer of ``solve_direct_newton`` with
Chebyshev(6) controls from ``linear_guess`` in a fresh process, cold (empty
temporary JAX cache via NHJAX_CACHE_DIR) and warm (a second process with the same
cache), with the after-compile time (median of 2 further solves), cost and
violation (children: ``python benchmarks/steering_peer.py --first-answer TASK``;
the machinery is somersault_peer's). ``--goals``: only that table.

Usage: python benchmarks/steering_peer.py [--quick | --goals]   (--quick: N = 30 only,
no Pontryagin; for trying the script, not for the README)
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
TARGET, T = (0.5, 0.3), 3.0
#: The continuous optimum (Pontryagin on the reduced problem; used only when that row fails here).
REFERENCE_COST = 0.08128805397807
CONFIGS = [  # (N, controls, RK4 substeps)
    (30, "pc", 4), (30, "pl", 4), (60, "pc", 4), (60, "pl", 4), (60, "pl", 8),
]
QUICK_CONFIGS = [(30, "pc", 4), (30, "pl", 4)]
#: Our Chebyshev(6) solve again at looser tolerances: its control, re-simulated at 1e-12,
#: misses the target by ~1e-6, as IPOPT's finest grid's does (~3e-6): the comparison at
#: equal terminal accuracy (issue 39).
LOOSE = dict(rtol=1e-7, atol=1e-7, ctol=1e-6, gtol=1e-5)
OURS_REPEATS = 3
COLD_REPEATS = 3


def median_time(fn, repeats=5, min_total=0.5, max_repeats=50):
    ts, out, start = [], None, time.perf_counter()
    while len(ts) < repeats or (time.perf_counter() - start < min_total and len(ts) < max_repeats):
        t = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)), out


def check_formulas(cs, n=200, seed=0):
    """CasADi f, psi (and the NumPy copies) against ReducedSteering.vector_field and
    ReducedSteeringTarget, at random points: half fully random (the equations do not
    assume a unit gamma), half with a proper rotation for (alpha, beta, gamma)."""
    import jax
    import jax.numpy as jnp

    from controls.tasks import sphere_steering_reduced
    from nhjax.lie import so3
    from nhjax.scenes import ShellWithTop

    robot = ShellWithTop()
    for k in ("ms", "Rs", "Is", "mt", "g"):
        assert float(getattr(robot, k)) == cs.ROBOT[k], k
    assert np.array_equal(np.asarray(robot.It), np.asarray(cs.ROBOT["It"])), "It"
    assert np.array_equal(np.asarray(robot.c), np.asarray(cs.ROBOT["c"])), "c"
    red = sphere_steering_reduced(robot, TARGET, T)
    assert np.array_equal(np.asarray(red.x0), cs.initial_state()), "initial state"
    plane = np.asarray(red.terminal_constraints.plane)
    f, psi = cs.steering_functions(plane=plane)
    field = jax.jit(lambda x, u: red.system.vector_field(0.0, x, u))
    term = jax.jit(lambda x: red.terminal_constraints(x))
    rng = np.random.default_rng(seed)
    worst = dict(vector_field_max_rel=0.0, terminal_max_abs=0.0, numpy_max_rel=0.0)
    for i in range(n):
        x = rng.normal(size=17)
        if i % 2:
            R = np.asarray(so3.exp(jnp.asarray(rng.normal(size=3))))
            x[0:6] *= 3.0
            x[6:15] = np.concatenate([R[2], R[0], R[1]])
        u = rng.normal(size=3)
        fj = np.asarray(field(jnp.asarray(x), jnp.asarray(u)))
        pj = np.asarray(term(jnp.asarray(x)))
        scale = np.abs(fj).max()
        worst["vector_field_max_rel"] = max(worst["vector_field_max_rel"],
                                            np.abs(np.asarray(f(x, u)).ravel() - fj).max() / scale)
        worst["terminal_max_abs"] = max(worst["terminal_max_abs"], np.abs(np.asarray(psi(x)).ravel() - pj).max(),
                                        np.abs(cs.terminal_numpy(x, plane=plane) - pj).max())
        worst["numpy_max_rel"] = max(worst["numpy_max_rel"], np.abs(cs.rhs_numpy(x, u) - fj).max() / scale)
    assert max(worst.values()) < 1e-12, worst
    worst["points"] = n
    return worst, plane


def linear_guess_signal(param_degree=12):
    """t -> linear_guess's torque (fitted to Chebyshev(param_degree)), and its fit seconds."""
    import jax

    import controls
    from controls.tasks import linear_guess, sphere_steering
    from nhjax.scenes import ShellWithTop

    ocp = sphere_steering(ShellWithTop(), TARGET, T)
    param = controls.Chebyshev(param_degree, T, 3)
    t = time.perf_counter()
    p = linear_guess(ocp, param)
    sig = jax.jit(lambda s: param.signal(p)(s, None))
    return (lambda s: np.asarray(sig(s))), time.perf_counter() - t


def casadi_rows(cs, configs, plane, u_of_t):
    rows = []
    for N, ctl, M in configs:
        nlp = cs.build(N=N, controls=ctl, substeps=M, plane=plane)
        for start in ("linear", "cold"):
            w0 = cs.warm_start(nlp, start, u_of_t)
            first = cs.solve(nlp, w0)  # first call: any lazy set-up of the solver
            if start == "linear":
                sec, r = median_time(lambda: cs.solve(nlp, w0))
            else:
                sec, r = median_time(lambda: cs.solve(nlp, w0), repeats=COLD_REPEATS, min_total=0.0)
            assert abs(r["cost"] - first["cost"]) <= 1e-12 * abs(first["cost"])
            ev = cs.evaluate(nlp, r)
            row = dict(
                solver="CasADi+IPOPT", method=f"MS N={N}, {ctl}, RK4 x{M}, exact Hessian, {start} start",
                controls=ctl, N=N, substeps=M, start=start, n_variables=nlp["n_variables"],
                cost=r["cost"], violation=r["violation"], resim_cost=ev["cost"], resim_violation=ev["violation"],
                closed_form_cost=cs.control_cost(nlp, r["U"]), iterations=r["iterations"], status=r["status"],
                seconds=sec, first_call_seconds=first["seconds"], build_seconds=nlp["build_seconds"],
            )
            rows.append(row)
            print(f"  {row['method']:55s} cost {row['cost']:.10f} viol {row['violation']:.0e} | resim cost "
                  f"{row['resim_cost']:.10f} viol {row['resim_violation']:.1e} | it {row['iterations']:3d} "
                  f"{r['status']:18s} {sec * 1e3:9.1f} ms  build {nlp['build_seconds']:.1f} s", flush=True)
    return rows


def ours_rows(pontryagin=True):
    import jax.numpy as jnp

    import controls
    from controls.tasks import linear_guess, solve_direct_newton, sphere_steering, sphere_steering_reduced
    from nhjax.scenes import ShellWithTop

    robot = ShellWithTop()
    ocp = sphere_steering(robot, TARGET, T)
    red = sphere_steering_reduced(robot, TARGET, T)
    rows, results = [], {}

    def timed(name, method, fn, note=None):
        t = time.perf_counter()
        try:
            fn()  # first call: compiles
        except Exception as e:  # noqa: BLE001 -- report, do not stop the benchmark
            print(f"  {name} ({method}): failed: {type(e).__name__}: {e}", flush=True)
            rows.append(dict(solver=name, method=method, status=f"failed: {type(e).__name__}: {e}"))
            return None, None
        first_s = time.perf_counter() - t
        from _timing import settle

        settle()  # after compile: the solver's background compiles done too
        sec, r = median_time(fn, repeats=OURS_REPEATS, min_total=0.0)
        row = dict(solver=name, method=method, cost=float(r.cost), violation=float(r.violation),
                   iterations=int(r.iterations), status="converged" if r.converged else r.message,
                   seconds=sec, first_call_seconds=first_s, build_seconds=max(first_s - sec, 0.0))
        if note:
            row["note"] = note
        rows.append(row)
        return row, r

    for n, tols in ((6, {}), (6, LOOSE), (12, {})):
        param = controls.Chebyshev(n, T, 3)
        t = time.perf_counter()
        guess = linear_guess(ocp, param)
        guess_s = time.perf_counter() - t
        tag = "" if not tols else f" at rtol {tols['rtol']:g}, ctol {tols['ctol']:g}, gtol {tols['gtol']:g}"
        row, r = timed("controls.solve_direct_newton",
                       f"Chebyshev({n}) x 3{tag}, single shooting (RKMK), feasible-path Newton, linear start",
                       lambda param=param, guess=guess, tols=tols: solve_direct_newton(ocp, param, guess,
                                                                                       progress=False, **tols))
        if row is None:
            continue
        if not tols:
            results[n] = r
        _, J, psi = controls.rollout(ocp, r.control, rtol=1e-12, atol=1e-12)
        row.update(resim_cost=float(J), resim_violation=float(jnp.max(jnp.abs(psi))), linear_guess_seconds=guess_s)
        print(f"  {row['method']:80s} cost {row['cost']:.10f} viol {row['violation']:.0e} | resim cost "
              f"{row['resim_cost']:.10f} viol {row['resim_violation']:.1e} | it {row['iterations']:3d} "
              f"{row['status']:10s} {row['seconds']:8.2f} s (first call {row['first_call_seconds']:.1f} s)", flush=True)

    if pontryagin and 12 in results:
        r12 = results[12]
        t = time.perf_counter()
        pmp = controls.pmp_residual(red, r12.control, rtol=1e-10, atol=1e-10)
        pmp_first = time.perf_counter() - t
        pmp_s, pmp = median_time(lambda: controls.pmp_residual(red, r12.control, rtol=1e-10, atol=1e-10),
                                 repeats=OURS_REPEATS, min_total=0.0)

        def pontryagin_solve():
            return controls.solve_pontryagin(red, pmp["ps"][-1], pmp["multipliers"], solver="lm", rtol=1e-11,
                                             atol=1e-11, tol=1e-10, max_steps=60, progress=False)

        row, r = timed("controls.solve_pontryagin",
                       "reduced state, single shooting, LM from the Chebyshev(12) optimum's costates",
                       pontryagin_solve,
                       note="starts from pmp_residual of the direct Chebyshev(12) optimum; pipeline_seconds = "
                            "that direct solve + pmp_residual + this solve (medians)")
        if row is not None:
            direct12 = next(x for x in rows if x["method"].startswith("Chebyshev(12)"))
            row.update(shooting_residual=float(r.residual), pmp_residual_seconds=pmp_s,
                       pmp_residual_first_call_seconds=pmp_first,
                       pipeline_seconds=direct12["seconds"] + pmp_s + row["seconds"])
            print(f"  {row['method']:80s} cost {row['cost']:.10f} viol {row['violation']:.0e} residual "
                  f"{r.residual:.0e} it {row['iterations']:3d} {row['status']:10s} {row['seconds']:8.2f} s "
                  f"(first call {row['first_call_seconds']:.1f} s; pmp_residual {pmp_s:.1f} s, first "
                  f"{pmp_first:.1f} s)", flush=True)
    return rows


GOALS = {"steer_newton6": (30.0, 5.0)}
TASK_TEXT = {"steer_newton6": "steering, solve_direct_newton Chebyshev(6), linear start"}


def first_answer_task(task):
    """Child process: the steering task's first answer, then two more solves (after compile)."""
    t_start = time.perf_counter()
    import controls
    from controls.tasks import linear_guess, solve_direct_newton, sphere_steering
    from nhjax.scenes import ShellWithTop

    t_import = time.perf_counter() - t_start
    if task != "steer_newton6":
        raise SystemExit(f"unknown task {task}")

    def solve():
        ocp = sphere_steering(ShellWithTop(), TARGET, T)
        param = controls.Chebyshev(6, T, 3)
        r = solve_direct_newton(ocp, param, linear_guess(ocp, param), progress=False)
        return r.cost, r.violation, r.converged

    sys.path.insert(0, str(HERE))
    from somersault_peer import report_first_answer

    report_first_answer(task, t_import, solve, reference=REFERENCE_COST)


def goals(peer_text=""):
    sys.path.insert(0, str(HERE))
    from somersault_peer import goals_rows, print_goal_header

    print("first answer (issue 16 goals: cold <= 30 s, warm <= 5 s), cold = fresh process + empty cache dir "
          "(the faster of two; 'other': the other's solve time), warm = a process after one that filled the cache; "
          "rel diff against the continuous optimum:", flush=True)
    print_goal_header(peer_text)
    return goals_rows(Path(__file__).resolve(), list(GOALS), GOALS, TASK_TEXT)


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if "--first-answer" in argv:
        first_answer_task(argv[argv.index("--first-answer") + 1])
        return
    if "--goals" in argv:
        goals()
        return
    quick = "--quick" in argv
    load_start = os.getloadavg()
    print(f"load average at start (1, 5, 15 min): {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}")
    try:
        import casadi
    except ImportError:
        print("steering_peer: casadi is not installed -- skipped "
              "(install it with: python -m pip install 'casadi>=3.6,<4', or the extra 'peers')")
        return
    sys.path.insert(0, str(HERE / "peers"))
    import casadi_steering as cs

    import jax

    OUT.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    check, plane = check_formulas(cs)
    print(f"CasADi formulas vs ReducedSteering / ReducedSteeringTarget ({check['points']} random points): "
          f"vector field max rel {check['vector_field_max_rel']:.1e}, terminal constraints max abs "
          f"{check['terminal_max_abs']:.1e}, NumPy copy max rel {check['numpy_max_rel']:.1e}")
    u_of_t, guess_s = linear_guess_signal()
    print(f"linear_guess (Chebyshev(12) fit) for the CasADi warm start: {guess_s:.1f} s with its compile")
    print("CasADi + IPOPT (median of >= 5 solves from the linear start, 3 from the cold start):", flush=True)
    peer = casadi_rows(cs, QUICK_CONFIGS if quick else CONFIGS, plane, u_of_t)
    print("controls (median of 3 calls after a first, compiling call):", flush=True)
    ours = ours_rows(pontryagin=not quick)
    goal_rows = [] if quick else goals()

    pmp_row = next((r for r in ours if r["solver"] == "controls.solve_pontryagin" and "cost" in r
                    and r["status"] == "converged"), None)
    reference = pmp_row["cost"] if pmp_row else REFERENCE_COST
    reference_from = "solve_pontryagin in this run" if pmp_row else "REFERENCE_COST (earlier Pontryagin run)"
    warm = [r for r in peer if r["start"] == "linear"]
    best = min(warm, key=lambda r: (r["resim_violation"], r["seconds"]))
    rows = peer + ours
    for r in rows:
        if "seconds" in r:
            r["time_ratio_vs_casadi_best"] = r["seconds"] / best["seconds"]
            r["rel_diff"] = (r["cost"] - reference) / reference
            if "resim_cost" in r:
                r["resim_rel_diff"] = (r["resim_cost"] - reference) / reference

    fields = ["solver", "method", "cost", "rel_diff", "violation", "resim_cost", "resim_rel_diff", "resim_violation",
              "iterations", "status", "seconds", "build_seconds", "first_call_seconds", "time_ratio_vs_casadi_best",
              "N", "controls", "substeps", "start", "n_variables", "shooting_residual", "pipeline_seconds",
              "pmp_residual_seconds", "linear_guess_seconds", "note"]
    name = "steering_peer_quick" if quick else "steering_peer"
    with open(OUT / f"{name}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    load_end = os.getloadavg()
    import scipy

    meta = dict(
        problem=f"sphere_steering(ShellWithTop(), target={TARGET}, T={T}) (CasADi: sphere_steering_reduced)",
        reference_cost=reference, reference_from=reference_from, formula_check=check,
        casadi_best=best["method"], casadi_linear_start="linear_guess fitted to Chebyshev(12)",
        machine=dict(platform=platform.platform(), python=platform.python_version(), cpu_count=os.cpu_count(),
                     jax=jax.__version__, casadi=casadi.__version__, scipy=scipy.__version__),
        command="python benchmarks/steering_peer.py" + (" --quick" if quick else ""),
        total_seconds=time.perf_counter() - start, load_average_start=list(load_start),
        load_average_end=list(load_end),
    )
    (OUT / f"{name}.json").write_text(json.dumps(dict(meta=meta, rows=rows, goals=goal_rows), indent=1,
                                                 default=float))

    print("\n" + "=" * 168)
    print(f"Spherical-robot steering, reference cost {reference:.12g} ({reference_from}); time ratio = seconds / "
          f"seconds of CasADi '{best['method']}'")
    print(f"{'solver':28s} {'method':62s} {'cost':>12s} {'rel diff':>9s} {'viol':>7s} {'resim viol':>10s} "
          f"{'resim rel':>9s} {'it':>4s} {'time':>10s} {'build':>7s} {'ratio':>7s}")
    for r in rows:
        if "seconds" not in r:
            print(f"{r['solver']:28s} {r['method'][:62]:62s} {r['status']}")
            continue
        rv = f"{r['resim_violation']:10.1e}" if "resim_violation" in r else f"{'-':>10s}"
        rr = f"{r['resim_rel_diff']:+9.1e}" if "resim_rel_diff" in r else f"{'-':>9s}"
        tm = f"{r['seconds'] * 1e3:8.1f}ms" if r["seconds"] < 10 else f"{r['seconds']:9.1f}s"
        print(f"{r['solver']:28s} {r['method'][:62]:62s} {r['cost']:12.10f} {r['rel_diff']:+9.1e} "
              f"{r['violation']:7.0e} {rv} {rr} {r['iterations']:4d} {tm:>10s} {r['build_seconds']:6.1f}s "
              f"{r['time_ratio_vs_casadi_best']:7.1f}")
    for r in rows:
        if r.get("note"):
            print(f"note: {r['solver']} ({r['method'][:50]}...): {r['note']}")
    if goal_rows:
        sys.path.insert(0, str(HERE))
        from somersault_peer import print_goal_header, print_goal_row

        print(f"\nGoals (issue 16): steering first answer cold <= 30 s, warm <= 5 s; direct after compile <= 2x "
              f"IPOPT's solve ({best['seconds']:.2f} s here: <= {2 * best['seconds']:.2f} s), Pontryagin <= IPOPT")
        print_goal_header("")
        for g in goal_rows:
            print_goal_row(g)
    print(f"\nload average (1, 5, 15 min): start {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}, "
          f"end {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f}")
    print(f"total {meta['total_seconds']:.0f} s; written: {OUT}/{name}.csv, .json")


if __name__ == "__main__":
    main()
