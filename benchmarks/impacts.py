"""Impacts (seed 004): impact-time and state error against closed forms over 1000 impacts,
nhjax.simulate_impacts next to scipy's solve_ivp with events, with times; throughput of a
batch of bouncers on all cores; compile times. Load average printed at start and end.

Cases
-----
* floor: elastic ball on a fixed floor (A = 0), 1000 impacts; exact impact n at
  T (2n - 1), T = sqrt(2 h / g); state error = max |v_pre + sqrt(2 g h)|.
* table: ball on a vibrating table (Gamma = 4, alpha = 0.8, chaotic), 1000 impacts;
  "local" errors: each impact time against the root of the exact parabola from the
  solver's own previous post-impact state (NumPy bisection, BouncingBall.reference_impacts),
  since chaos amplifies any difference between two runs.
* numba: benchmarks/peers/impacts.py, a compiled event loop with the same method (Dormand-
  Prince 5(4), Newton on genuine steps for the impact time, the seed's jump), same rtol/atol
  and largest step.
* scipy: solve_ivp (DOP853 and RK45) with a terminal event psi = 0 (direction -1), the jump
  applied in a Python loop between segments (what a user would write), same rtol/atol.

Timing: median of >= 3 runs after compile, nhjax and scipy interleaved in one process.
Writes experiments/out/bench/impacts.json.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import nhjax
from nhjax import _programs
from nhjax.integrate.impacts import solve_impacts
from nhjax.scenes import BouncingBall, RollingSphereWall

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _timing import median_time  # noqa: E402

sys.path.insert(0, str(HERE / "peers"))
from impacts import bounce as numba_bounce  # noqa: E402  (benchmarks/peers/impacts.py)

OUT = HERE.parent / "experiments" / "out" / "bench"
G = 9.81
N_IMP = 1000
TOL = 1e-10


def scipy_bouncer(ball: BouncingBall, x0, v0, n, method, rtol=TOL, atol=TOL):
    """n impacts by solve_ivp with a terminal event and the seed's jump in a Python loop."""
    from scipy.integrate import solve_ivp

    g, A, w, al = (float(v) for v in (ball.g, ball.A, ball.omega, ball.restitution))

    def f(t, y):
        return [y[1], -g]

    def gap(t, y):
        return y[0] - A * np.sin(w * t)

    gap.terminal, gap.direction = True, -1
    t, y = 0.0, np.array([x0, v0], float)
    times, vpre, post = np.empty(n), np.empty(n), np.empty((n, 2))
    for i in range(n):
        t_end = t + 100.0
        # skip the root at the start (the ball sits on the table after a jump)
        sol = solve_ivp(f, (t, t_end), y, method=method, rtol=rtol, atol=atol, events=gap,
                        first_step=None, dense_output=False)
        if not sol.t_events[0].size:
            return times[:i], vpre[:i], post[:i]
        te = sol.t_events[0][0]
        ye = sol.y_events[0][0]
        if te <= t + 1e-12:  # the event at the segment's start: step past it
            sol = solve_ivp(f, (t + 1e-9, t_end), y + np.array([y[1] * 1e-9, -g * 1e-9]), method=method,
                            rtol=rtol, atol=atol, events=gap)
            if not sol.t_events[0].size:  # lost the ball below the table: stop here
                return times[:i], vpre[:i], post[:i]
            te, ye = sol.t_events[0][0], sol.y_events[0][0]
        v1 = (1 + al) * A * w * np.cos(w * te) - al * ye[1]
        times[i], vpre[i] = te, ye[1]
        t, y = te, np.array([A * np.sin(w * te), v1])
        post[i] = y
    return times, vpre, post


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()
    print(f"load average at start: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f} ({os.cpu_count()} cores)")
    rows = []

    # ------------------------------------------------------------- floor, exact closed form
    floor = BouncingBall(A=0.0, omega=2 * np.pi, restitution=1.0)
    h = 1.0
    T = np.sqrt(2 * h / G)
    t1 = (2 * N_IMP) * T  # the 1000th impact at T (2 N - 1)
    exact_t = T * (2 * np.arange(1, N_IMP + 1) - 1)

    def nh(ball, x0, t1):
        f = eqx.filter_jit(lambda b, x: solve_impacts(b, x, t1, max_impacts=N_IMP + 1, rtol=TOL, atol=TOL,
                                                      dtmax=None))
        return f

    f_floor = nh(floor, None, t1)
    x0 = jnp.array([h, 0.0])
    t = time.perf_counter()
    tr = jax.block_until_ready(f_floor(floor, x0))
    compile_floor = time.perf_counter() - t
    n = min(int(tr.num_impacts), N_IMP)
    err_t = float(np.max(np.abs(np.asarray(tr.impact_times[:n]) - exact_t[:n])))
    err_v = float(np.max(np.abs(np.asarray(tr.velocities_pre[:n, 0]) + np.sqrt(2 * G * h))))
    t_nh = median_time(lambda: f_floor(floor, x0), repeats=3)
    rows.append(dict(case="floor", method="nhjax simulate_impacts (Dopri5)", impacts=n, impact_time_error=err_t,
                     velocity_error=err_v, energy_error=float(tr.energy_error), seconds=t_nh,
                     compile_seconds=compile_floor))
    # the Numba event loop (same DP5 + Newton on genuine steps), largest step as nhjax's
    pf = np.array([G, 0.0, float(floor.omega), 1.0])
    nb = lambda: numba_bounce(np.array([h, 0.0]), 0.0, t1, pf, N_IMP, TOL, TOL, np.inf, 1e-3)  # noqa: E731
    t = time.perf_counter()
    nb()
    compile_nb = time.perf_counter() - t
    times, vpre, _, k_nb, _, _ = nb()
    rows.append(dict(case="floor", method="numba DP5 event loop (peers/impacts.py)", impacts=int(k_nb),
                     impact_time_error=float(np.max(np.abs(times[:k_nb] - exact_t[:k_nb]))),
                     velocity_error=float(np.max(np.abs(vpre[:k_nb] + np.sqrt(2 * G * h)))),
                     energy_error=float("nan"), seconds=median_time(nb, repeats=3), compile_seconds=compile_nb))
    for method in ("DOP853", "RK45"):
        tt = time.perf_counter()
        times, vpre, _ = scipy_bouncer(floor, h, 0.0, N_IMP, method)
        dt = time.perf_counter() - tt
        rows.append(dict(case="floor", method=f"scipy solve_ivp {method} + events", impacts=len(times),
                         impact_time_error=float(np.max(np.abs(times - exact_t[:len(times)]))),
                         velocity_error=float(np.max(np.abs(vpre + np.sqrt(2 * G * h)))), energy_error=float("nan"),
                         seconds=dt, compile_seconds=0.0))

    # ------------------------------------------------------------- vibrating table, local errors
    table = BouncingBall(A=0.01, omega=2 * np.pi * 10, restitution=0.8)
    dtmax = table.event_resolution
    f_table = eqx.filter_jit(lambda b, x: solve_impacts(b, x, 600.0, max_impacts=N_IMP, rtol=TOL, atol=TOL,
                                                        dtmax=dtmax))
    x0 = table.initial_state(0.1, 0.0)
    t = time.perf_counter()
    tr = jax.block_until_ready(f_table(table, x0))
    compile_table = time.perf_counter() - t
    n = int(tr.num_impacts)

    def local_errors(times, post, vpre):
        et, ev = [], []
        for i in range(0, len(times) - 1, 5):
            ref = table.reference_impacts(times[i], post[i, 0], post[i, 1], 1)
            et.append(abs(ref["times"][0] - times[i + 1]))
            ev.append(abs(ref["v_pre"][0] - vpre[i + 1]))
        return float(np.max(et)), float(np.max(ev))

    et, ev = local_errors(np.asarray(tr.impact_times[:n]), np.asarray(tr.x_post[:n]),
                         np.asarray(tr.velocities_pre[:n, 0]))
    t_nh = median_time(lambda: f_table(table, x0), repeats=3)
    rows.append(dict(case="table", method="nhjax simulate_impacts (Dopri5)", impacts=n, impact_time_error=et,
                     velocity_error=ev, energy_error=float(tr.energy_error), seconds=t_nh,
                     compile_seconds=compile_table, status=int(tr.status)))
    pt = np.array([G, float(table.A), float(table.omega), float(table.restitution)])
    nb = lambda: numba_bounce(np.asarray(x0, float), 0.0, 600.0, pt, N_IMP, TOL, TOL, dtmax, 1e-3)  # noqa: E731
    nb()
    times, vpre, post, k_nb, st_nb, _ = nb()
    et, ev = local_errors(times[:k_nb], post[:k_nb], vpre[:k_nb])
    rows.append(dict(case="table", method="numba DP5 event loop (peers/impacts.py)", impacts=int(k_nb),
                     impact_time_error=et, velocity_error=ev, energy_error=float("nan"),
                     seconds=median_time(nb, repeats=3), compile_seconds=0.0, status=int(st_nb)))
    for method in ("DOP853", "RK45"):
        tt = time.perf_counter()
        times, vpre, post = scipy_bouncer(table, 0.1, 0.0, N_IMP, method)
        dt = time.perf_counter() - tt
        et, ev = local_errors(times, post, vpre)
        rows.append(dict(case="table", method=f"scipy solve_ivp {method} + events", impacts=len(times),
                         impact_time_error=et, velocity_error=ev, energy_error=float("nan"), seconds=dt,
                         compile_seconds=0.0))

    print(f"\n{N_IMP} impacts, rtol = atol = {TOL:g}; errors: floor vs the closed form, table 'local' "
          "(each flight vs the exact parabola's root)")
    print(f"{'case':6s} {'method':38s} {'impacts':>7s} {'t error':>9s} {'v error':>9s} {'time [s]':>9s} {'compile':>8s}")
    for r in rows:
        print(f"{r['case']:6s} {r['method']:38s} {r['impacts']:7d} {r['impact_time_error']:9.1e} "
              f"{r['velocity_error']:9.1e} {r['seconds']:9.4f} {r['compile_seconds']:8.1f}")

    # ------------------------------------------------------------- batch throughput
    batch = []
    rng = np.random.default_rng(0)
    # lock-step lanes refilled from the member queue; chunks: one per core
    for B, lanes in ((256, 16), (1024, 16), (1024, 64)):
        gam = rng.uniform(1.5, 4.0, B)
        ball = BouncingBall(A=1.0, omega=2 * np.pi, restitution=0.8)
        balls = eqx.tree_at(lambda s: s.A, ball, jnp.asarray(gam * G / (2 * np.pi) ** 2))
        run = lambda: nhjax.simulate_impacts_batch(balls, jnp.array([0.05, 0.0]), 20.0,  # noqa: E731
                                                   in_axes={"system": ["A"]}, max_impacts=200, lanes=lanes,
                                                   on_max_impacts="stop", on_error="return")
        t = time.perf_counter()
        out = run()
        first = time.perf_counter() - t
        t = time.perf_counter()
        out = run()
        sec = time.perf_counter() - t
        iters = np.asarray(out.num_steps)
        imps = np.asarray(out.num_impacts)
        # impact-time error of the batch: each flight's impact against the exact parabola's
        # root (NumPy) from the member's own previous post-impact state, 16 members
        errs = []
        for i in np.linspace(0, B - 1, 16).astype(int):
            bi = BouncingBall(A=float(gam[i] * G / (2 * np.pi) ** 2), omega=2 * np.pi, restitution=0.8)
            ti, xp = np.asarray(out.impact_times[i]), np.asarray(out.x_post[i])
            rebound = np.asarray(out.normal_velocity_post[i][:, 0]) > 1e-9  # a free flight follows
            for j in range(min(int(imps[i]), 30) - 1):
                if not rebound[j]:  # came to rest on the table: no parabola to compare with
                    continue
                ref = bi.reference_impacts(ti[j], xp[j, 0], xp[j, 1], 1)
                if np.isfinite(ref["times"][0]):
                    errs.append(abs(ref["times"][0] - ti[j + 1]))
        err = float(np.max(errs)) if errs else float("nan")
        batch.append(dict(members=B, lanes=lanes, seconds=sec, first_call_seconds=first, members_per_second=B / sec,
                          impacts_per_second=float(imps.sum() / sec), impact_time_error=err,
                          loop_iterations=dict(min=int(iters.min()), median=float(np.median(iters)),
                                               max=int(iters.max())),
                          status_counts=np.bincount(np.asarray(out.status), minlength=6).tolist()))
        print(f"batch {B:5d} bouncers (Gamma in [1.5, 4], 20 table periods, {lanes} lanes per core): {sec:.2f} s -> "
              f"{B / sec:.0f} members/s, {imps.sum() / sec:.0f} impacts/s (first call {first:.1f} s); "
              f"impact-time error {err:.1e} s; loop iterations per member min/median/max "
              f"{iters.min()}/{np.median(iters):.0f}/{iters.max()}")

    # ------------------------------------------------------------- compile times
    compiles = {}
    for name, sysm, x in (("BouncingBall", table, table.initial_state(0.1, 0.0)),
                          ("RollingSphereWall", RollingSphereWall(V=0.05), RollingSphereWall().initial_state())):
        f = jax.jit(lambda s, xx: solve_impacts(s, xx, 2.0, max_impacts=64))
        t = time.perf_counter()
        lowered = f.lower(sysm, x)
        t_l = time.perf_counter() - t
        # XLA's own compile: with JAX's persistent cache off (an earlier run's executable
        # in it would make this a load; JAX settles its switch once per process, which
        # nhjax._programs holds off while it compiles a program of its own)
        with _programs._jax_cache_off():
            t_c = time.perf_counter()
            lowered.compile()
            t_c = time.perf_counter() - t_c
        compiles[name] = dict(trace_lower=t_l, compile=t_c)
        print(f"compile {name}: trace+lower {t_l:.1f} s, XLA compile {compiles[name]['compile']:.1f} s")

    load1 = os.getloadavg()
    print(f"load average at end: {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    meta = dict(command="python benchmarks/impacts.py", platform=platform.platform(), cpu_count=os.cpu_count(),
                load_average_start=list(load0), load_average_end=list(load1), measured=time.strftime("%Y-%m-%d %H:%M"))
    (OUT / "impacts.json").write_text(json.dumps(dict(meta=meta, rows=rows, batch=batch, compile=compiles), indent=2))
    print(f"wrote {OUT / 'impacts.json'}")


if __name__ == "__main__":
    main()
