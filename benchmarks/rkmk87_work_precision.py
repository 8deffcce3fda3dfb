"""RKMK45 against RKMK87 at tight tolerances: accepted steps, wall time, error.

Two scenes: the spherical robot ``ShellWithTop`` (Hamel equations on
R^2 x SO(3) x SO(3), nonholonomic rolling) over 3 s with the torques of
compile_times.py's "ShellWithTop" case, and the torque-driven ``FallingCat``
(vector state: RKMK45 is DP5, RKMK87 is Dopri8) over 10 s with the torques of
cat_work_precision.py. For rtol = atol in 1e-8, 1e-10, 1e-12 and each solver,
two ways of saving:

* ``saveat=101`` (simulate's default): saved states by dense output (RKMK45: 4th
  order; RKMK87: 7th, with 8 more vector-field evaluations per step);
* ``saveat=2``: t0 and t1 only (without events XLA then drops RKMK87's dense-output
  evaluations; the cat has a chart guard, an event, so it keeps them).

Errors (max abs over all state numbers, group parts as matrices): final state, and
(saveat=101) the largest over the saved states, against RKMK87 at 1e-13 saving at
1001 times (the 101 times are every 10th); the reference's own error is estimated
by RKMK45 at 1e-13 (printed). Time: the solve jitted end to end
(``jax.jit`` around ``simulate``, rtol traced: one compile per solver and saveat),
median of 5 calls after compile, the two solvers alternating call by call in one
process (the machine is shared: the load average at start and end is printed).
Stages in a lax.scan where the system declares a large vector field, as simulate's
default RKMK45 does.

Run: ``.venv/bin/python benchmarks/rkmk87_work_precision.py``; writes
experiments/out/bench/rkmk87_work_precision.json (rows and the load average).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import nhjax
import nhjax.scenes as S

OUT = Path(__file__).resolve().parent.parent / "experiments" / "out" / "bench"
TOLS = (1e-8, 1e-10, 1e-12)
REPEATS = 5


def scenes():
    robot = S.ShellWithTop()
    robot_x0 = robot.initial_state(top_omega=(0.0, 0.0, 3.0))
    robot_u = nhjax.Sinusoids(np.zeros(3), [0.02, -0.01, 0.015], [1.1, 0.7, 2.0], [0.0, 0.4, 1.0])
    cat = S.FallingCat()
    cat_x0 = cat.initial_state(0.8, chi_dot=0.5)
    cat_u = nhjax.Sinusoids([-0.015, 0.0], [0.04, 0.02], [1.7, 0.9], [0.0, np.pi / 2])
    return [("ShellWithTop", robot, robot_x0, robot_u, 3.0), ("FallingCat", cat, cat_x0, cat_u, 10.0)]


def max_diff(a, b):
    return max(float(jnp.max(jnp.abs(u - v))) for u, v in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))


def main():
    load_start = os.getloadavg()
    print(f"load average at start: {load_start}")
    rows = []
    for scene, system, x0, u, t1 in scenes():
        scan = bool(system.large_vector_field)
        solvers = {"RKMK45": nhjax.RKMK45(scan_stages=scan), "RKMK87": nhjax.RKMK87(scan_stages=scan)}

        def solve(solver, saveat, tol):
            return nhjax.simulate(system, x0, t1, control=u, solver=solver, rtol=tol, atol=tol, saveat=saveat,
                                  diagnostics=False, track_work=False, max_steps=200_000)

        # the reference saves at 1001 times; every 10th is a saved time of the runs
        ts = np.linspace(0.0, t1, 1001)
        fine = solve(solvers["RKMK87"], ts, 1e-13)
        ref = {2: fine, 101: jax.tree_util.tree_map(lambda a: a[::10], fine.xs)}
        ref45 = solve(solvers["RKMK45"], ts[::10], 1e-13)
        print(f"\n{scene}: reference RKMK87 1e-13 vs RKMK45 1e-13: final {max_diff(fine.x_end, ref45.x_end):.1e}, "
              f"saved {max_diff(ref[101], ref45.xs):.1e}")
        for saveat in (ts[::10], 2):
            jitted = {name: jax.jit(lambda x, tol, s=s, saveat=saveat: (
                lambda tr: (tr.xs, tr.x_end, tr.num_accepted_steps))(nhjax.simulate(
                    system, x, t1, control=u, solver=s, rtol=tol, atol=tol, saveat=saveat, diagnostics=False,
                    track_work=False, max_steps=200_000))) for name, s in solvers.items()}
            compile_s = {}
            for name, fn in jitted.items():
                t = time.perf_counter()
                jax.block_until_ready(fn(x0, 1e-6))
                compile_s[name] = time.perf_counter() - t
            for tol in TOLS:
                out = {name: jax.block_until_ready(fn(x0, tol)) for name, fn in jitted.items()}
                times = {name: [] for name in jitted}
                for _ in range(REPEATS):  # alternate the solvers call by call
                    for name, fn in jitted.items():
                        t = time.perf_counter()
                        jax.block_until_ready(fn(x0, tol))
                        times[name].append(time.perf_counter() - t)
                for name in jitted:
                    xs, x_end, steps = out[name]
                    n_saved = 2 if np.ndim(saveat) == 0 else len(saveat)
                    row = dict(scene=scene, saveat=n_saved, rtol=tol, solver=name, steps=int(steps),
                               ms=1e3 * float(np.median(times[name])), compile_s=compile_s[name],
                               final_error=max_diff(x_end, fine.x_end),
                               saved_error=max_diff(xs, ref[101]) if n_saved > 2 else float("nan"))
                    rows.append(row)
                    print(f"{scene:13s} saveat={n_saved:3d} rtol={tol:.0e} {name}: {row['steps']:5d} steps "
                          f"{row['ms']:8.2f} ms  final err {row['final_error']:.1e}  saved err "
                          f"{row['saved_error']:.1e}  (first call {row['compile_s']:.1f} s)", flush=True)
    load_end = os.getloadavg()
    print(f"\nload average at end: {load_end}")
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "rkmk87_work_precision.json"
    path.write_text(json.dumps(dict(load_average=dict(start=load_start, end=load_end), rows=rows), indent=1))
    print(f"wrote {path}")
    return rows


if __name__ == "__main__":
    main()
