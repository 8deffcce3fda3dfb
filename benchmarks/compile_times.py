"""Time to the first answer per scene and per public path, cold and warm (goals: < 3 s
cold, < 0.5 s warm).

Each scene runs in fresh Python processes, from a representative state with
default settings (rtol = atol = 1e-8, 101 saved times, diagnostics on), with
nhjax's persistent compilation cache (NHJAX_CACHE_DIR) pointed at a temporary
directory:

* cold: a process with an empty cache (what a user meets the first time):
  tracing + compiling every program + one run; the faster of two such processes,
  each with its own empty cache (the slower is printed beside it: this machine's
  speed moves by tens of percent within the hour);
* warm: a process after one that filled the cache (a notebook re-run, a script
  run again): tracing, the compiled programs loaded from the cache, one run; the
  faster of two;
* the run alone (median of 5 later calls in a warm process: in a cold one a solver
  may still be compiling a program in the background that its later calls use) and
  the accepted steps, so the first-call cost can be read against the work it buys;
* x0: the time to build the system and its start state before that call (its
  ``initial_state`` and the like), cold and warm: a user waits for it too.

Beside the registry's scenes, a system as a researcher writes it through
``nhjax.mechanics.Lagrangian``: a six-link wheeled snake (8 coordinates, 5
knife-edge constraints); the first ``simulate_batch()`` of a process (the cat,
256 members of unequal length; "steps" is then the longest member's); and every
other public path a notebook user takes (``PATH_CASES``): gradients around
``simulate`` in reverse and forward mode on its defaults (eager and under
``jax.jit``), an impact solve, its derivatives in both modes, an impact batch, a
reduced chain's solve and body states, a curvature integral. A path's row times its
whole first call (``call``), steps -1. Under ``jax.jit`` the program holds
simulate's runtime checks (host callbacks), which JAX's persistent cache does not
keep: its warm row compiles the program again (nothing of the solve is traced);
with ``EQX_ON_ERROR=nan`` it is kept too.

Writes experiments/out/bench/compile_times.{json,csv,png} and prints the table
with the load average at start and end (the machine may be shared).
"""

from __future__ import annotations

import csv
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "experiments" / "out" / "bench"

# scene -> (source of the case: builds `system`, `x0`, `t1` and `control`)
CASES = {
    "FallingCat": """
system = S.FallingCat(); x0 = system.initial_state(0.8, chi_dot=0.5); t1 = 10.0
control = nhjax.Sinusoids([-0.015, 0.0], [0.04, 0.02], [1.7, 0.9], [0.0, np.pi / 2])""",
    "FallingCatAttitudes": """
system = S.FallingCat().attitude_model(); x0 = system.initial_state(0.8, chi_dot=0.5); t1 = 10.0
control = nhjax.Sinusoids([-0.015, 0.0], [0.04, 0.02], [1.7, 0.9], [0.0, np.pi / 2])""",
    "Skate": """
system = S.Skate(); x0 = system.initial_state(speed=1.0, phi_dot=2.0); t1 = 10.0""",
    "SkateSE2": """
system = S.SkateSE2(); x0 = system.initial_state(speed=1.0, phi_dot=2.0); t1 = 10.0""",
    "BallOnPlatter": """
system = S.BallOnPlatter(); x0 = system.initial_state(); t1 = 10.0""",
    "BallInCone": """
system = S.BallInCone(); x0 = system.initial_state(rho=3.0, rho_dot=0.5, alpha_dot=0.3, spin=1.0); t1 = 10.0""",
    "RollingDisk": """
system = S.RollingDisk(); x0 = system.initial_state(theta=0.3, phi_dot=0.4, theta_dot=0.2, psi_dot=1.5); t1 = 10.0""",
    "RollingDiskQuaternion": """
disk = S.RollingDisk(); system = disk.quaternion_model(); t1 = 10.0
x0 = disk.to_quaternion_state(disk.initial_state(theta=0.3, phi_dot=0.4, theta_dot=0.2, psi_dot=1.5))""",
    "TwoWheeledCart": """
system = S.TwoWheeledCart(); x0 = system.initial_state(speed=1.0, theta_dot=0.5); t1 = 10.0""",
    "ShellWithTop": """
system = S.ShellWithTop(); x0 = system.initial_state(top_omega=(0.0, 0.0, 3.0)); t1 = 3.0
control = nhjax.Sinusoids(np.zeros(3), [0.02, -0.01, 0.015], [1.1, 0.7, 2.0], [0.0, 0.4, 1.0])""",
    "ShellWithTopReduced": """
system = S.ShellWithTopReduced(); x0 = system.initial_state([1.0, 2.0, 3.0]); t1 = 10.0""",
    "ShellWithSuslovHinge": """
system = S.ShellWithSuslovHinge(); x0 = system.initial_state([0.3, 0.2, 1.0], Omega12=(0.1, -0.2)); t1 = 10.0""",
    "SuslovBundle": """
system = S.SuslovBundle(); x0 = system.initial_state([0.3, 0.2, 1.0], Omega12=(0.1, -0.2)); t1 = 10.0""",
    "user Lagrangian (8 coords, 5 constraints)": """
import jax.numpy as jnp
from nhjax.mechanics import Lagrangian
N, l, m, J = 6, 0.3, 1.0, 0.01  # links, length [m], mass [kg], inertia [kg m^2]
def centres(q):  # link centres from the first link's centre (x, y) and the link angles
    x, y, th = q[0], q[1], q[2:]
    step = jnp.stack([jnp.cos(th), jnp.sin(th)], 1) * l
    joints = jnp.concatenate([jnp.zeros((1, 2)), jnp.cumsum(0.5 * (step[:-1] + step[1:]), 0)])
    return jnp.array([x, y]) + joints
def T(q, qd):
    v = jax.jvp(centres, (q,), (qd,))[1]
    return 0.5 * m * jnp.sum(v ** 2) + 0.5 * J * jnp.sum(qd[2:] ** 2)
def knife_edges(t, q, qd):  # links 1-5 roll on knife edges: no sideways velocity
    v = jax.jvp(centres, (q,), (qd,))[1]
    th = q[2:]
    return (-jnp.sin(th) * v[:, 0] + jnp.cos(th) * v[:, 1])[:5]
system = Lagrangian(2 + N, T=T, velocity_constraints=knife_edges)
x0 = jnp.concatenate([jnp.zeros(2 + N), jnp.array([1.0, 0.0]), jnp.zeros(N)]); t1 = 5.0""",
    "RollRing": """
system = S.RollRing(); x0 = system.initial_state(); t1 = 10.0""",
    "ThreeCylinders": """
system = S.ThreeCylinders(); x0 = system.initial_state(); t1 = 6.0""",
    "ThreeCylindersMinimal": """
system = S.ThreeCylindersMinimal(); x0 = system.initial_state(); t1 = 6.0""",
}

BATCH_CASES = {
    # a batch (the first simulate_batch() of a process): 256 members of unequal length
    "FallingCat simulate_batch (256 members)": """
system = S.FallingCat(I1=1.0, lam=0.4, B=0.5); t1 = 10.0
control = nhjax.Sinusoids([0.0, 0.0], [0.3, 0.2], [2.0, 3.0], [0.0, np.pi / 2])
rng = np.random.default_rng(0)
X = np.stack([rng.uniform(0.6, 1.4, 256), rng.uniform(-1, 1, 256), np.zeros(256), rng.uniform(-0.5, 0.5, 256),
              rng.uniform(-0.5, 0.5, 256)], 1)""",
}

#: A final angle of the torque-driven cat as a function of the torque amplitudes,
#: through simulate on its defaults (and with DiscreteAdjoint): the gradient rows' setup.
_CAT_LOSS = """
system = S.FallingCat(); x0 = system.initial_state(0.8, chi_dot=0.5)
import jax.numpy as jnp
def loss(amp):
    u = nhjax.Sinusoids(jnp.zeros(2), amp, jnp.array([1.7, 0.9]), jnp.array([0.0, np.pi / 2]))
    return nhjax.simulate(system, x0, 10.0, control=u{adjoint}).xs[-1, 2]
amp = jnp.array([0.04, 0.02])
"""
_CAT_LOSS, _CAT_LOSS_DISCRETE_ADJOINT = (_CAT_LOSS.format(adjoint=a) for a in ("", ", adjoint=nhjax.DiscreteAdjoint()"))

PATH_CASES = {
    # every other public path a notebook user takes, each from its first call: gradients
    # around simulate (reverse and forward mode, on simulate's defaults), impacts and their
    # derivatives and batches, the reduction geometry; ``call`` is what is timed
    "jax.grad through simulate (FallingCat, defaults)": _CAT_LOSS + "call = lambda: jax.grad(loss)(amp)",
    "jax.jacfwd through simulate (FallingCat, defaults)": _CAT_LOSS + "call = lambda: jax.jacfwd(loss)(amp)",
    "jax.jit(jax.grad) through simulate (FallingCat, defaults)": _CAT_LOSS + "call = (lambda f: lambda: f(amp))(jax.jit(jax.grad(loss)))",
    "jax.grad through simulate (DiscreteAdjoint)": _CAT_LOSS_DISCRETE_ADJOINT + "call = lambda: jax.grad(loss)(amp)",
    "simulate_impacts (BouncingBall, 2 s)": """
system = S.BouncingBall(); x0 = system.initial_state(0.1)
call = lambda: nhjax.simulate_impacts(system, x0, 2.0)""",
    "jax.jacfwd of the first impact time": """
import jax.numpy as jnp
system = S.BouncingBall()
first_impact = lambda h: nhjax.simulate_impacts(system, jnp.stack([h, 0.0]), 0.5, saveat=0,
                                                max_impacts=8).impact_times[0]
call = lambda: jax.jacfwd(first_impact)(0.1)""",
    "jax.grad of the first impact time (adjoint='reverse')": """
import jax.numpy as jnp
system = S.BouncingBall()
first_impact = lambda h: nhjax.simulate_impacts(system, jnp.stack([h, 0.0]), 0.5, saveat=0, max_impacts=8,
                                                adjoint="reverse").impact_times[0]
call = lambda: jax.grad(first_impact)(0.1)""",
    "simulate_batch of 64 bouncing balls": """
system = S.BouncingBall(); X = np.stack([np.linspace(0.05, 0.2, 64), np.zeros(64)], 1)
call = lambda: nhjax.simulate_batch(system, X, 2.0)""",
    "PlanarChain under torques, then body_states": """
import jax.numpy as jnp
system = S.PlanarChain(); x0 = system.initial_state(phi=[0.3, -0.2])
u = nhjax.Sinusoids(jnp.zeros(2), jnp.array([0.2, -0.1]), jnp.array([1.0, 1.5]), jnp.zeros(2))
def call():
    tr = nhjax.simulate(system, x0, 5.0, control=u)
    return system.body_states(tr.xs[-1])""",
    "curvature_integral of a 3-link chain gait": """
import jax.numpy as jnp
from nhjax.mechanics import curvature_integral
from nhjax.mechanics.reduction import EllipseLoop
system = S.PlanarChain(momentum="zero").kinematic(); c = jnp.array([1.0, 0.8])
call = lambda: curvature_integral(system, EllipseLoop(c, 0.5, 0.3), c)""",
    # optimal-control tasks (the issue-39 tasks; their after-compile figures and the peers'
    # are in somersault_peer.py and steering_peer.py)
    "OC: chart somersault, solve_direct then solve_pontryagin": """
import jax.numpy as jnp, controls
from controls.tasks import fixed_theta_costates, velocity_somersault_chart
cat, th0, T = S.FallingCatKinematic(), 0.6, 2.0
def call():
    ocp = velocity_somersault_chart(cat, th0, -np.pi, T)
    param = controls.Chebyshev(10, T, 2)
    d = controls.solve_direct(ocp, param, param.fit(lambda t: jnp.array([0.0, 2 * np.pi / T])), progress=False)
    p = controls.solve_pontryagin(ocp, *fixed_theta_costates(cat, th0, T), progress=False)
    return np.array([d.cost, p.cost])""",
    "OC: 64 chart somersaults, solve_pontryagin_batch": """
import controls
from controls.tasks import fixed_theta_costates, velocity_somersault_chart
cat, T = S.FallingCatKinematic(), 2.0
bends = np.linspace(0.5, 0.8, 64)
def call():
    hol = -2 * np.pi * cat.lam * np.cos(bends) / (np.sin(bends) ** 2 + cat.lam * np.cos(bends) ** 2)
    ocps = [velocity_somersault_chart(cat, th, h - 0.2, T) for th, h in zip(bends, hol)]
    p0, nu = zip(*(fixed_theta_costates(cat, th, T) for th in bends))
    return controls.solve_pontryagin_batch(ocps, np.stack(p0), np.stack(nu), progress=False).cost""",
    "OC: 64 chart somersaults, solve_direct_batch, Chebyshev(10)": """
import jax.numpy as jnp, controls
from controls.tasks import velocity_somersault_chart
cat, T = S.FallingCatKinematic(), 2.0
bends = np.linspace(0.5, 0.8, 64)
def call():
    hol = -2 * np.pi * cat.lam * np.cos(bends) / (np.sin(bends) ** 2 + cat.lam * np.cos(bends) ** 2)
    ocps = [velocity_somersault_chart(cat, th, h - 0.2, T) for th, h in zip(bends, hol)]
    param = controls.Chebyshev(10, T, 2)
    guess = param.fit(lambda t: jnp.array([0.0, 2 * np.pi / T]))
    return controls.solve_direct_batch(ocps, param, guess, progress=False).cost""",
    "OC: sphere steering, solve_direct_newton, Chebyshev(6)": """
import controls
from controls.tasks import linear_guess, sphere_steering
def call():
    ocp = sphere_steering(S.ShellWithTop(), (-0.3, 0.4), 3.0)
    param = controls.Chebyshev(6, 3.0, 3)
    return np.array(controls.solve_direct_newton(ocp, param, linear_guess(ocp, param), progress=False).cost)""",
    "OC: 3-link chain reorientation by 0.2 rad, Chebyshev(12)": """
import jax.numpy as jnp, controls
from controls.tasks import chain_loop_guess, chain_radius_for_turn, chain_reorientation
chain, phi0, T = S.PlanarChain(group="SO2"), jnp.array([0.5, 0.5]), 3.0
def call():
    radius, orientation = chain_radius_for_turn(chain, 0.2, phi0)
    ocp = chain_reorientation(chain, 0.2, T, phi0)
    param = controls.Chebyshev(12, T, 2)
    guess = chain_loop_guess(chain, param, phi0, T, radius, orientation=orientation)
    return np.array(controls.solve_direct_newton(ocp, param, guess, progress=False).cost)""",
    "OC: torque somersault, solve_direct then solve_pontryagin, Chebyshev(12)": """
import controls
from controls.tasks import torque_loop_guess, torque_somersault
cat, th0, T = S.FallingCat.from_dimensions(1.0, 1.0, 0.25), 0.6, 2.0
def call():
    ocp = torque_somersault(cat, th0, -np.pi, T)
    param = controls.Chebyshev(12, T, 2)
    d = controls.solve_direct(ocp, param, torque_loop_guess(cat, param, th0, T), progress=False)
    res = controls.pmp_residual(ocp, d.control)
    p = controls.solve_pontryagin(ocp, res["ps"][-1], res["multipliers"], progress=False)
    return np.array([d.cost, p.cost])""",
    "OC: free-winding somersault (smooth coordinates), two starts and the polish": """
from controls.tasks import somersault_free_winding
from nhjax.scenes.falling_cat import FallingCatSmooth
chart = S.FallingCatKinematic(); cat = FallingCatSmooth(chart.I1, chart.lam, chart.B)
call = lambda: np.array(somersault_free_winding(cat, 0.6, -np.pi, 2.0, start_windings=(0, 1), progress=False).best.cost)""",
    "OC: thruster chain steering, solve_direct_newton, Chebyshev(12)": """
import jax.numpy as jnp, controls
from controls.tasks import chain_steering
chain, phi0, T = S.PlanarChain(thrusters=True), jnp.array([0.5, 0.5]), 3.0
def call():
    ocp = chain_steering(chain, (0.5, 0.3, 0.3), T, phi0)
    param = controls.Chebyshev(12, T, chain.control_dim)
    return np.array(controls.solve_direct_newton(ocp, param, jnp.zeros(param.size), progress=False).cost)""",
    # closed-loop MPC (issue 42; the per-period figures and the CasADi peer are in nhjax run mpc_sphere)
    "OC: sphere MPC closed loop, RTI, 1 s / 20 intervals, 20 periods": """
import controls
from controls.tasks import sphere_tracking
def call():
    ocp = sphere_tracking(S.ShellWithTop())
    mpc = controls.MPC(ocp, 0.05, 20, mode="rti")
    return controls.closed_loop(mpc, ocp.system, ocp.x0, 20).inputs""",
}

#: The chart somersault with both solvers' programs prepared first (controls.prepare_*:
#: traced at once, compiled side by side in the background; docs/guides/optimal-control.md),
#: its row beside the chart's
_CHART = "OC: chart somersault, solve_direct then solve_pontryagin"
_PARAM_LINE = "    param = controls.Chebyshev(10, T, 2)\n"
assert _PARAM_LINE in PATH_CASES[_CHART]
_PREPARED = PATH_CASES[_CHART].replace(_PARAM_LINE, _PARAM_LINE + "    controls.prepare_direct_sqp(ocp, param)\n"
                                                                  "    controls.prepare_pontryagin(ocp)\n")
_rows = list(PATH_CASES.items())
_at = list(PATH_CASES).index(_CHART) + 1
PATH_CASES = dict(_rows[:_at] + [("OC: chart somersault, the same with the polish prepared "
                                  "(prepare_direct_sqp, prepare_pontryagin)", _PREPARED)] + _rows[_at:])

CHILD = """
import time, json
t_import = time.perf_counter()
import numpy as np, jax
import nhjax
import nhjax.scenes as S
t_import = time.perf_counter() - t_import
control = None
t_state = time.perf_counter()
{case}
jax.block_until_ready(X if "X" in globals() else x0 if "x0" in globals() else 0)
t_state = time.perf_counter() - t_state
if "call" in globals():  # a path: its own call
    pass
elif "X" in globals():  # a batch case
    call = lambda: nhjax.simulate_batch(system, X, t1, control=control, on_error="return")
else:
    call = lambda: nhjax.simulate(system, x0, t1, control=control)
t = time.perf_counter()
tr = call()
jax.block_until_ready(tr)
first_call_s = time.perf_counter() - t
runs = []
for _ in range(5):
    t = time.perf_counter()
    jax.block_until_ready(call())
    runs.append(time.perf_counter() - t)
steps = int(np.max(tr.num_accepted_steps)) if hasattr(tr, "num_accepted_steps") else -1
print(json.dumps(dict(first_call_s=first_call_s, run_s=float(np.median(runs)), import_s=t_import, state_s=t_state,
                      steps=steps, t1=float(globals().get("t1", float("nan"))))))
"""


def _child(name: str, cache_dir: str) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD.format(case={**CASES, **BATCH_CASES, **PATH_CASES}[name])], capture_output=True,
                         text=True, env=dict(os.environ, NHJAX_CACHE_DIR=cache_dir))
    if out.returncode != 0:
        return dict(error=out.stderr.strip().splitlines()[-1])
    return json.loads(out.stdout.strip().splitlines()[-1])


#: Cold processes (each with its own empty cache) and warm processes per case; the
#: fastest of each counts (the others were slowed by whatever else the machine ran;
#: all are in the JSON output and the slowest cold one is printed beside it).
COLD_RUNS = 2
WARM_RUNS = 2


def measure(name: str) -> dict:
    """Cold and warm first call of one case: ``COLD_RUNS`` processes each with a fresh
    cache, then ``WARM_RUNS`` processes sharing the last one's."""
    colds = []
    for k in range(COLD_RUNS):
        with tempfile.TemporaryDirectory(prefix="nhjax-cache-") as cache:
            cold = _child(name, cache)
            if "error" in cold:
                return dict(scene=name, **cold)
            colds.append(cold)
            if k < COLD_RUNS - 1:
                continue
            warm = [_child(name, cache) for _ in range(WARM_RUNS)]
    bad = [w for w in warm if "error" in w]
    if bad:
        return dict(scene=name, **bad[0])
    best = dict(min(colds, key=lambda c: c["first_call_s"]))
    best["cold_run_s"] = best.pop("run_s")
    return dict(scene=name, **best, run_s=min(w["run_s"] for w in warm), cold_runs_s=[c["first_call_s"] for c in colds],
                warm_first_call_s=min(w["first_call_s"] for w in warm), warm_runs_s=[w["first_call_s"] for w in warm],
                warm_state_s=min(w["state_s"] for w in warm))


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = [r for r in rows if "error" not in r]
    fig, ax = plt.subplots(figsize=(7, 0.35 * len(rows) + 1.2))
    names = [r["scene"] for r in rows]
    y = np.arange(len(rows))
    ax.barh(y - 0.2, [r["first_call_s"] for r in rows], height=0.4, label="first call, cold")
    ax.barh(y + 0.2, [r["warm_first_call_s"] for r in rows], height=0.4, label="first call, warm (cache)")
    ax.set_yticks(y, names)
    ax.axvline(3.0, color="k", ls="--", lw=1, label="goals: 3 s cold, 0.5 s warm")
    ax.axvline(0.5, color="k", ls=":", lw=1)
    ax.set(xlabel="seconds", title="first answer per scene and path (fresh processes)")
    ax.invert_yaxis()
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()
    rows = []
    print(f"{'scene or path':52s} {'cold s':>7s} {'(slowest)':>9s} {'warm s':>7s} {'run ms':>9s} {'steps':>6s} "
          f"{'x0 cold/warm s':>15s} {'load':>10s}")
    names = sys.argv[1:] or [*CASES, *BATCH_CASES, *PATH_CASES]
    known = [*CASES, *BATCH_CASES, *PATH_CASES]
    unknown = sorted(set(names) - set(known))
    if unknown:
        raise SystemExit(f"unknown cases {unknown}; known: {known}")
    for name in names:
        load = os.getloadavg()[0]
        r = measure(name)
        r["load_average"] = [load, os.getloadavg()[0]]
        rows.append(r)
        if "error" in r:
            print(f"{name:52s} failed: {r['error']}")
            continue
        r["compile_s"] = r["first_call_s"] - r["run_s"]
        print(f"{name:52s} {r['first_call_s']:7.2f} {max(r['cold_runs_s']):9.2f} {r['warm_first_call_s']:7.2f} "
              f"{r['run_s'] * 1e3:9.2f} {r['steps']:6d} {r['state_s']:7.2f}/{r['warm_state_s']:.2f} "
              f"{r['load_average'][0]:5.2f}-{r['load_average'][1]:.2f}", flush=True)
    load_end = os.getloadavg()
    ok = [r for r in rows if "error" not in r]
    print(f"cold under 3 s: {sum(r['first_call_s'] < 3 for r in ok)} of {len(ok)}; warm under 0.5 s: "
          f"{sum(r['warm_first_call_s'] < 0.5 for r in ok)} of {len(ok)}; "
          f"load average start {load_start[0]:.2f}, end {load_end[0]:.2f}")
    if sys.argv[1:]:  # a subset: printed, the full run's outputs are kept
        return
    meta = dict(command="python benchmarks/compile_times.py", platform=platform.platform(),
                cpu_count=os.cpu_count(), load_average_start=list(load_start), load_average_end=list(load_end),
                measured=time.strftime("%Y-%m-%d %H:%M"))
    (OUT / "compile_times.json").write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))
    with open(OUT / "compile_times.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["scene", "first_call_s", "warm_first_call_s", "compile_s", "run_s", "steps", "t1",
                                          "import_s", "state_s", "warm_state_s"],
                           extrasaction="ignore")
        w.writeheader()
        w.writerows(ok)
    plot(rows, OUT / "compile_times.png")
    print(f"written: {OUT}/compile_times.json, .csv, .png")


if __name__ == "__main__":
    main()
