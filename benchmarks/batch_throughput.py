"""Batch throughput, single-trajectory speed, first-call time and gradient cost (issue 13 goals).

The work users run, on the torque-driven falling cat (Iwai 7.14-7.15; peer: the
Numba Dormand-Prince 5(4) of benchmarks/peers/falling_cat.py, same step-size
control), rtol = atol = 1e-8, in one run, peers and nhjax timed in interleaved
rounds (medians), load average printed at start and end:

* **unequal batches** (the workload of issue 13): I1 = 1, lam = 0.4, B = 0.5,
  u = (0.3 sin 2t, 0.2 cos 3t), T = 10 s, initial states uniform in theta in
  [0.5, 1.5], chi in [-1, 1], theta' and chi' in [-1, 1]; members whose motion
  reaches the singular chart (sin theta = 0, where the peer would integrate
  garbage) are drawn again. Members need many-fold different step counts (the
  distribution is printed). nhjax.simulate_batch on defaults as a user writes
  them (saveat=2, diagnostics on) and lean (diagnostics off) against numba
  prange on all cores, 1, 64, 1024 and 16384 members, worst final-state error of
  each against SciPy DOP853 1e-13 references of 32 random members, peak memory;
* the **uniform batch** of the earlier benchmark (the default case with small
  perturbations: near-identical step counts), 1024 members, labelled as the
  friendly case;
* **single trajectory** after compile: jax.jit(simulate(...).xs[-1]) on defaults
  (101 saved times, work tracked) and lean (saveat=2, track_work=False,
  diagnostics=False) against numba, x0 a jax array (as inside a jitted optimizer;
  the same call with a numpy x0, which adds a host-to-device copy, is printed too);
* **first simulate()** in a fresh process, cold and warm (a second process with
  the persistent compilation cache), from benchmarks/compile_times.py;
* **gradient** of a terminal cost (psi(T)^2) in the 2 torque amplitudes by
  jax.grad, as a ratio to one forward solve, for each adjoint, with its error
  against central differences.

Writes experiments/out/bench/batch_throughput.{json,png} and prints the goals table.
"""

from __future__ import annotations

import json
import os
import platform
import resource
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
from _timing import median_time  # noqa: E402

OUT = HERE.parent / "experiments" / "out" / "bench"
TOL = 1e-8


def case():
    c = peers.CAT_DEFAULT
    cat = FallingCat(I1=c["I1"], lam=c["lam"], B=c["B"])
    ctrl = nhjax.Sinusoids([c["a0"], 0.0], [c["a1"], c["a2"]], [c["w1"], c["w2"]], [0.0, np.pi / 2])
    return cat, ctrl, jnp.asarray(c["y0"], float), float(c["t1"])


#: The unequal workload: parameters of the cat and of the torques (as the peer's case dict).
UNEQUAL = dict(peers.CAT_DEFAULT, I1=1.0, lam=0.4, B=0.5, a0=0.0, a1=0.3, w1=2.0, a2=0.2, w2=3.0)


def unequal_case():
    c = UNEQUAL
    cat = FallingCat(I1=c["I1"], lam=c["lam"], B=c["B"])
    ctrl = nhjax.Sinusoids([c["a0"], 0.0], [c["a1"], c["a2"]], [c["w1"], c["w2"]], [0.0, np.pi / 2])
    return cat, ctrl, float(c["t1"])


def unequal_states(cat, ctrl, t1, B, seed=0):
    """B random initial states of the unequal workload whose motions stay in the chart."""
    rng = np.random.default_rng(seed)
    out, redrawn = [], 0
    while len(out) < B:
        n = max(64, int(1.1 * (B - len(out))))
        Y = np.zeros((n, 5))
        Y[:, 0] = rng.uniform(0.5, 1.5, n)
        Y[:, 1] = rng.uniform(-1, 1, n)
        Y[:, 3] = rng.uniform(-1, 1, n)
        Y[:, 4] = rng.uniform(-1, 1, n)
        tr = nhjax.simulate_batch(cat, Y, t1, control=ctrl, rtol=TOL, atol=TOL, diagnostics=False,
                                  on_error="return")
        ok = np.asarray(tr.ok)
        redrawn += int((~ok).sum())
        out.extend(Y[ok])
    return np.asarray(out[:B]), redrawn


ROUNDS = 3  # interleaved rounds of nhjax and numba timings (medians over rounds)


def single(cat, ctrl, x0, t1, case):
    """One trajectory after compile: jitted simulate on defaults and lean vs numba."""
    ref = peers.reference_solution(dict(case, y0=tuple(np.asarray(x0))))
    t = time.perf_counter()
    first = nhjax.simulate(cat, x0, t1, control=ctrl, rtol=TOL, atol=TOL)
    compile_s = time.perf_counter() - t
    runs = {
        "defaults": jax.jit(lambda x: nhjax.simulate(cat, x, t1, control=ctrl, rtol=TOL, atol=TOL).xs[-1]),
        "lean": jax.jit(lambda x: nhjax.simulate(cat, x, t1, control=ctrl, rtol=TOL, atol=TOL, saveat=2,
                                                  track_work=False, diagnostics=False).xs[-1]),
    }
    # the solve's time: x0 already on the device, as inside a jitted optimizer (a numpy
    # x0 adds a host-to-device copy per call, timed separately below)
    xd = jnp.asarray(x0, float)
    errors = {k: float(np.max(np.abs(np.asarray(f(xd)) - ref))) for k, f in runs.items()}
    p, y0 = peers.case_params(case), np.asarray(x0, float)
    ynb, nacc, _ = peers.dp54_numba(y0, t1, TOL, TOL, p)
    times = {k: [] for k in [*runs, "defaults, numpy x0", "numba"]}
    for _ in range(ROUNDS):
        for k, f in runs.items():
            times[k].append(median_time(lambda f=f: f(xd)))
        times["defaults, numpy x0"].append(median_time(lambda: runs["defaults"](y0)))
        times["numba"].append(median_time(lambda: peers.dp54_numba(y0, t1, TOL, TOL, p)))
    med = {k: float(np.median(v)) for k, v in times.items()}
    eager = median_time(lambda: nhjax.simulate(cat, x0, t1, control=ctrl, rtol=TOL, atol=TOL).xs)
    return dict(
        compile_seconds=compile_s, simulate_seconds=eager, jit_seconds=med["defaults"],
        jit_numpy_input_seconds=med["defaults, numpy x0"],
        jit_lean_seconds=med["lean"], jit_error=errors["defaults"], jit_lean_error=errors["lean"],
        steps=int(first.num_accepted_steps), numba_seconds=med["numba"],
        numba_error=float(np.max(np.abs(ynb - ref))), numba_steps=int(nacc),
    )


#: Fresh processes the single-trajectory timing runs in: on this kind of machine the
#: same jitted program's time varies more from one process to the next than within
#: one, so the median process is reported and all are kept in the JSON.
SINGLE_PROCESSES = 5


def single_in_processes(x0, t1, n=SINGLE_PROCESSES):
    """single() of the unequal case from ``x0``, each in a fresh Python process; the
    process with the median defaults/numba ratio, with every process's figures."""
    import subprocess

    code = ("import sys, json; sys.path[:0] = [{here!r}, {peers!r}]; import numpy as np, batch_throughput as bt; "
            "cat, ctrl, t1 = bt.unequal_case(); "
            "print(json.dumps(bt.single(cat, ctrl, np.array({x0!r}), {t1!r}, bt.UNEQUAL)))").format(
        here=str(HERE), peers=str(HERE / "peers"), x0=[float(v) for v in x0], t1=float(t1))
    runs = []
    for _ in range(n):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    runs.sort(key=lambda r: r["jit_seconds"] / r["numba_seconds"])
    return dict(runs[len(runs) // 2], processes=runs)


def _worst_errors(Y0, traj, Ynb, case, t1, rng, n=32):
    idx = rng.choice(len(Y0), size=min(len(Y0), n), replace=False)
    worst_nh = worst_nb = 0.0
    for i in idx:
        ref = peers.reference_solution(dict(case, y0=tuple(Y0[i])))
        worst_nh = max(worst_nh, float(np.max(np.abs(np.asarray(traj.x_final[i]) - ref))))
        worst_nb = max(worst_nb, float(np.max(np.abs(Ynb[i] - ref))))
    return worst_nh, worst_nb


def batches(cat, ctrl, t1, sizes, case, Y0_all, label, vmapped_at=(1024,)):
    """Throughput per batch size: simulate_batch on defaults and lean, numba prange,
    (and vmapped diffrax at some sizes), interleaved rounds; worst errors; step counts."""
    p = peers.case_params(case)
    rows = []
    rng = np.random.default_rng(1)
    for B in sizes:
        Y0 = Y0_all[:B]
        calls = {
            "defaults": lambda: nhjax.simulate_batch(cat, Y0, t1, control=ctrl, rtol=TOL, atol=TOL).xs,
            "lean": lambda: nhjax.simulate_batch(cat, Y0, t1, control=ctrl, rtol=TOL, atol=TOL,
                                                 diagnostics=False).xs,
            "numba": lambda: peers.dp54_numba_batch(Y0, t1, TOL, TOL, p),
        }
        if B in vmapped_at:  # simulate_batch's path when an adjoint is given
            calls["vmapped diffrax"] = lambda: nhjax.simulate_batch(
                cat, Y0, t1, control=ctrl, rtol=TOL, atol=TOL, diagnostics=False,
                adjoint=diffrax.RecursiveCheckpointAdjoint()).xs
        for f in calls.values():  # compile / warm up
            f()
        times = {k: [] for k in calls}
        for _ in range(ROUNDS):
            for k, f in calls.items():
                times[k].append(median_time(f, repeats=3))
        med = {k: float(np.median(v)) for k, v in times.items()}
        tr = nhjax.simulate_batch(cat, Y0, t1, control=ctrl, rtol=TOL, atol=TOL)
        Ynb, nb_steps = peers.dp54_numba_batch(Y0, t1, TOL, TOL, p)
        worst_nh, worst_nb = _worst_errors(Y0, tr, Ynb, case, t1, rng)
        steps = np.asarray(tr.num_accepted_steps)
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB -> MiB (Linux)
        row = dict(workload=label, batch=B, steps_min=int(steps.min()), steps_median=float(np.median(steps)),
                   steps_max=int(steps.max()), numba_steps_median=float(np.median(nb_steps)),
                   nhjax_worst_error=worst_nh, numba_worst_error=worst_nb, peak_rss_mib_so_far=rss,
                   **{f"{k.replace(' ', '_')}_traj_per_s": B / v for k, v in med.items()})
        row["defaults_vs_numba"] = row["defaults_traj_per_s"] / row["numba_traj_per_s"]
        row["lean_vs_numba"] = row["lean_traj_per_s"] / row["numba_traj_per_s"]
        rows.append(row)
        vm = (f"; vmapped diffrax {row['vmapped_diffrax_traj_per_s']:7.0f}" if "vmapped diffrax" in med else "")
        print(f"  {label} B={B:6d}: steps {row['steps_min']}-{row['steps_max']} (median {row['steps_median']:.0f}); "
              f"nhjax defaults {row['defaults_traj_per_s']:8.0f}/s ({row['defaults_vs_numba']:.2f}x numba), "
              f"lean {row['lean_traj_per_s']:8.0f}/s ({row['lean_vs_numba']:.2f}x), numba prange "
              f"{row['numba_traj_per_s']:8.0f}/s{vm}; worst error nhjax {worst_nh:.1e}, numba {worst_nb:.1e}; "
              f"peak RSS {rss:.0f} MiB", flush=True)
    return rows


#: rounds of gradient timings: every function is timed once per round, in turn, and its
#: median over the rounds is reported (calls of 0.05-0.2 ms drift by 30 % and more within
#: a run on this machine; timing the forward solve once, then each gradient after it, let
#: that drift into the ratios)
GRADIENT_ROUNDS = 5


def gradients(cat, ctrl, x0, t1):
    def terminal(amp, adjoint):
        c = nhjax.Sinusoids(ctrl.offset, amp, ctrl.omega, ctrl.phase)
        tr = nhjax.simulate(cat, x0, t1, control=c, rtol=1e-10, atol=1e-10, saveat=2, track_work=False,
                            diagnostics=False, adjoint=adjoint)
        return tr.xs[-1, 2] ** 2

    amp = ctrl.amplitude
    fwd = jax.jit(lambda a: terminal(a, diffrax.RecursiveCheckpointAdjoint()))
    fwd(amp)
    floor = jax.jit(lambda a: a.sum())  # a jitted call that does nothing: the per-call dispatch
    floor(amp)
    h = 1e-6
    fd = np.array([(fwd(amp + h * e) - fwd(amp - h * e)) / (2 * h) for e in np.eye(2)])
    rows, timed = [], {"forward": fwd, "dispatch": floor}
    for name, adj, mode in [
        ("reverse, nhjax.DiscreteAdjoint() (auto: tangents)", nhjax.DiscreteAdjoint(), "rev"),
        ("reverse, DiscreteAdjoint(jacobians='vjp')", nhjax.DiscreteAdjoint(jacobians="vjp"), "rev"),
        ("reverse, DiscreteAdjoint(jacobians='forward')", nhjax.DiscreteAdjoint(jacobians="forward"), "rev"),
        ("reverse, DiscreteAdjoint(jacobians='reverse')", nhjax.DiscreteAdjoint(jacobians="reverse"), "rev"),
        ("reverse, recursive checkpoint", diffrax.RecursiveCheckpointAdjoint(), "rev"),
        ("reverse, backsolve", diffrax.BacksolveAdjoint(), "rev"),
        ("forward mode", diffrax.ForwardMode(), "fwd"),
    ]:
        f = (jax.jit(jax.grad(lambda a, adj=adj: terminal(a, adj))) if mode == "rev"
             else jax.jit(jax.jacfwd(lambda a, adj=adj: terminal(a, adj))))
        t = time.perf_counter()
        try:
            g = jax.block_until_ready(f(amp))
        except NotImplementedError as e:  # e.g. diffrax's backsolve with saveat subs
            rows.append(dict(adjoint=name, unsupported=str(e).splitlines()[0]))
            print(f"  {name}: not supported here ({str(e).splitlines()[0]})")
            continue
        timed[name] = f
        rows.append(dict(adjoint=name, compile_seconds=time.perf_counter() - t,
                         error_vs_fd=float(np.max(np.abs(np.asarray(g) - fd)) / np.max(np.abs(fd)))))
    times = {k: [] for k in timed}
    for _ in range(GRADIENT_ROUNDS):
        for k, f in timed.items():
            times[k].append(median_time(lambda f=f: f(amp)))
    t_fwd = float(np.median(times["forward"]))
    for r in rows:
        if r["adjoint"] in times:
            t_g = float(np.median(times[r["adjoint"]]))
            r.update(ratio_to_forward=t_g / t_fwd, gradient_seconds=t_g)
    return dict(forward_seconds=t_fwd, dispatch_seconds=float(np.median(times["dispatch"])),
                rounds=GRADIENT_ROUNDS, rows=rows)


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    un = [r for r in rows if r["workload"] == "unequal"]
    B = [r["batch"] for r in un]
    ax.loglog(B, [r["defaults_traj_per_s"] for r in un], "o-", label="nhjax simulate_batch, defaults")
    ax.loglog(B, [r["lean_traj_per_s"] for r in un], "o--", label="nhjax, diagnostics off")
    ax.loglog(B, [r["numba_traj_per_s"] for r in un], "s-", label="numba DP5, prange")
    for r in rows:
        if r["workload"] == "uniform":
            ax.plot(r["batch"], r["defaults_traj_per_s"], "^", color="C0", label="nhjax, uniform batch (friendly)")
            ax.plot(r["batch"], r["numba_traj_per_s"], "^", color="C2", label="numba, uniform batch")
    ax.set(xlabel="batch size", ylabel="trajectories per second",
           title=f"falling cat, members with unequal step counts, rtol = {TOL:g}, {os.cpu_count()} cores")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def first_call():
    """Cold and warm first simulate() of the cat in fresh processes (compile_times.py)."""
    import compile_times

    return compile_times.measure("FallingCat")


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()
    print(f"load average at start (1, 5, 15 min): {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}",
          flush=True)
    cat, ctrl, t1 = unequal_case()
    Y0_all, redrawn = unequal_states(cat, ctrl, t1, 16384)
    print(f"unequal workload: 16384 initial states ({redrawn} members that reached sin(theta) = 0 drawn again)")
    print("single trajectory (unequal case, x0 = its first member):")
    s = single_in_processes(Y0_all[0], t1)
    print(f"  jax.jit(simulate) defaults {s['jit_seconds'] * 1e3:.3f} ms (err {s['jit_error']:.1e}), lean "
          f"{s['jit_lean_seconds'] * 1e3:.3f} ms (err {s['jit_lean_error']:.1e}), {s['steps']} steps "
          f"(x0 a jax array; a numpy x0 on defaults: {s['jit_numpy_input_seconds'] * 1e3:.3f} ms); "
          f"numba {s['numba_seconds'] * 1e3:.3f} ms (err {s['numba_error']:.1e}, {s['numba_steps']} steps); "
          f"eager simulate() {s['simulate_seconds'] * 1e3:.2f} ms; first call in this process "
          f"{s['compile_seconds']:.2f} s")
    print("  defaults / numba in each of the fresh processes: "
          + ", ".join(f"{r['jit_seconds'] / r['numba_seconds']:.2f}" for r in s["processes"]) + " (the median counts)")
    print("batches, unequal members (the work users run):")
    rows = batches(cat, ctrl, t1, [1, 64, 1024, 16384], UNEQUAL, Y0_all, "unequal")
    print("batch, uniform members (the friendly case):")
    ucat, uctrl, _, ut1 = case()
    rows += batches(ucat, uctrl, ut1, [1024], peers.CAT_DEFAULT, peers.perturbed_y0s(1024, seed=0), "uniform",
                    vmapped_at=())
    print("first simulate() in a fresh process (FallingCat, cold / warm with the persistent cache):")
    fc = first_call()
    print(f"  cold {fc.get('first_call_s', float('nan')):.2f} s, warm {fc.get('warm_first_call_s', float('nan')):.2f} s")
    print("gradient of psi(T)^2 in the torque amplitudes (default case, rtol 1e-10):")
    gcat, gctrl, gx0, gt1 = case()
    g = gradients(gcat, gctrl, gx0, gt1)
    print(f"  forward solve {g['forward_seconds'] * 1e3:.3f} ms (a jitted call that does nothing: "
          f"{g['dispatch_seconds'] * 1e3:.3f} ms); medians over {g['rounds']} interleaved rounds")
    for r in g["rows"]:
        if "unsupported" in r:
            continue
        print(f"  {r['adjoint']:46s} {r['ratio_to_forward']:6.2f} x forward   rel. error vs FD {r['error_vs_fd']:.1e}"
              f"   (compile {r['compile_seconds']:.1f} s)")
    by = {(r["workload"], r["batch"]): r for r in rows}
    best_grad = min(r["ratio_to_forward"] for r in g["rows"]
                    if r["adjoint"].startswith("reverse") and "ratio_to_forward" in r)
    goals = [
        ("unequal batch 1024, defaults, x numba prange (goal >= 2)", by[("unequal", 1024)]["defaults_vs_numba"]),
        ("unequal batch 16384, defaults, x numba prange (goal >= 2)", by[("unequal", 16384)]["defaults_vs_numba"]),
        ("  the same, diagnostics off: 1024", by[("unequal", 1024)]["lean_vs_numba"]),
        ("  the same, diagnostics off: 16384", by[("unequal", 16384)]["lean_vs_numba"]),
        ("  uniform batch 1024 (friendly), defaults", by[("uniform", 1024)]["defaults_vs_numba"]),
        ("jitted single solve on defaults / numba (goal <= 1.5)", s["jit_seconds"] / s["numba_seconds"]),
        ("  lean options", s["jit_lean_seconds"] / s["numba_seconds"]),
        ("jax.grad gradient / forward (goal <= 3)", best_grad),
        ("first simulate(), cold, s (goal < 3)", fc.get("first_call_s", float("nan"))),
        ("first simulate(), warm, s (goal < 0.5)", fc.get("warm_first_call_s", float("nan"))),
    ]
    print("\ngoals:")
    for name, v in goals:
        print(f"  {name:58s} {v:8.2f}")
    load_end = os.getloadavg()
    meta = dict(command="python benchmarks/batch_throughput.py", platform=platform.platform(),
                cpu_count=os.cpu_count(), jax=jax.__version__, load_average_start=list(load_start),
                load_average_end=list(load_end), redrawn_members=redrawn)
    (OUT / "batch_throughput.json").write_text(json.dumps(
        dict(meta=meta, single=s, batches=rows, first_call=fc, gradients=g, goals=dict(goals),
             devices=jax.local_device_count()), indent=1))
    print(f"load average (1, 5, 15 min): start {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}, "
          f"end {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f}")
    plot(rows, OUT / "batch_throughput.png")
    print(f"written: {OUT}/batch_throughput.json, .png")


if __name__ == "__main__":
    main()
