"""Batch throughput, single-trajectory speed, compile time and gradient cost (issue 4 goals).

All on the torque-driven falling cat of benchmarks/peers/falling_cat.py, measured
in one run against the Numba Dormand-Prince 5(4) peer (single and prange batch):

* single trajectory after compile, rtol = atol = 1e-8: jax.jit(simulate) vs numba,
  both with their final-state error;
* batch throughput (trajectories/s) for 1, 64, 1024, 16384 members on all local
  cores: nhjax.simulate_batch vs numba prange, with the worst error in the batch
  (against per-member SciPy DOP853 1e-13 references on a random subset of 32),
  and the process's peak resident memory after each size (memory growth; the
  saved states are 2 x 5 float64 per member, chunks of 1024 members bound the
  working memory);
* compile time of simulate() for the scene;
* gradient of a terminal cost (psi(T)^2) in the 2 torque amplitudes by jax.grad,
  as a ratio to one forward solve, for each adjoint (nhjax.DiscreteAdjoint: its
  default, which for 2 inputs carries their tangents through the forward solve,
  and its recorded-step sweeps -- per-step VJPs, chunked forward/reverse step
  Jacobians; diffrax's recursive checkpointing and backsolve; and jax.jacfwd with
  diffrax's ForwardMode), with its error against central differences. The goals
  table gives the best jax.grad ratio and, beside it, the pure reverse sweep's.

Writes experiments/out/bench/batch_throughput.{json,png} and prints the goals table
and the load average at start and end (the machine may be shared).
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


def single(cat, ctrl, x0, t1):
    ref = peers.reference_solution()
    t = time.perf_counter()
    first = nhjax.simulate(cat, x0, t1, control=ctrl, rtol=TOL, atol=TOL)
    compile_s = time.perf_counter() - t
    eager = median_time(lambda: nhjax.simulate(cat, x0, t1, control=ctrl, rtol=TOL, atol=TOL).xs)
    run = jax.jit(lambda x: nhjax.simulate(cat, x, t1, control=ctrl, rtol=TOL, atol=TOL, saveat=2,
                                           track_work=False, diagnostics=False).xs[-1])
    y = run(x0)
    jit_s = median_time(lambda: run(x0))
    p, y0 = peers.case_params(), peers.case_y0()
    ynb, nacc, _ = peers.dp54_numba(y0, t1, TOL, TOL, p)
    nb_s = median_time(lambda: peers.dp54_numba(y0, t1, TOL, TOL, p))
    return dict(
        compile_seconds=compile_s, simulate_seconds=eager, jit_seconds=jit_s,
        jit_error=float(np.max(np.abs(np.asarray(y) - ref))), steps=int(first.num_accepted_steps),
        numba_seconds=nb_s, numba_error=float(np.max(np.abs(ynb - ref))), numba_steps=int(nacc),
    )


def batches(cat, ctrl, t1, sizes):
    p = peers.case_params()
    rows = []
    rng = np.random.default_rng(1)
    for B in sizes:
        Y0 = peers.perturbed_y0s(B, seed=0)
        X0 = jnp.asarray(Y0)
        # compile: a batch of min(B, chunk_size = 1024) members has the chunk shape the timed calls use
        nhjax.simulate_batch(cat, X0[: min(B, 1024)], t1, control=ctrl, rtol=TOL, atol=TOL,
                             track_work=False, diagnostics=False, progress=False)
        nh_s = median_time(lambda: nhjax.simulate_batch(cat, X0, t1, control=ctrl, rtol=TOL, atol=TOL,
                                                        track_work=False, diagnostics=False,
                                                        progress=False).xs, repeats=3)
        tr = nhjax.simulate_batch(cat, X0, t1, control=ctrl, rtol=TOL, atol=TOL, track_work=False,
                                  diagnostics=False, progress=False)
        # the same batch through vmapped diffeqsolve (simulate_batch's path when an adjoint is
        # given): the lock-step integrator's gain, measured in the same run
        vm_kw = dict(control=ctrl, rtol=TOL, atol=TOL, track_work=False, diagnostics=False, progress=False,
                     adjoint=diffrax.RecursiveCheckpointAdjoint())
        nhjax.simulate_batch(cat, X0[: min(B, 1024)], t1, **vm_kw)
        vm_s = median_time(lambda: nhjax.simulate_batch(cat, X0, t1, **vm_kw).xs, repeats=3)
        peers.dp54_numba_batch(Y0[:2], t1, TOL, TOL, p)
        nb_s = median_time(lambda: peers.dp54_numba_batch(Y0, t1, TOL, TOL, p), repeats=3)
        Ynb, _ = peers.dp54_numba_batch(Y0, t1, TOL, TOL, p)
        idx = rng.choice(B, size=min(B, 32), replace=False)
        worst_nh = worst_nb = 0.0
        for i in idx:
            ref = peers.reference_solution(dict(peers.CAT_DEFAULT, y0=tuple(Y0[i])))
            worst_nh = max(worst_nh, float(np.max(np.abs(np.asarray(tr.xs[i, -1]) - ref))))
            worst_nb = max(worst_nb, float(np.max(np.abs(Ynb[i] - ref))))
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB -> MiB (Linux)
        rows.append(dict(batch=B, nhjax_seconds=nh_s, numba_seconds=nb_s, nhjax_traj_per_s=B / nh_s,
                         nhjax_vmapped_diffrax_traj_per_s=B / vm_s,
                         numba_traj_per_s=B / nb_s, nhjax_worst_error=worst_nh, numba_worst_error=worst_nb,
                         saved_bytes_per_member=int(2 * 5 * 8), peak_rss_mib_so_far=rss))
        print(f"  B={B:6d}: nhjax {B / nh_s:10.0f} traj/s (worst err {worst_nh:.1e}; vmapped diffrax {B / vm_s:8.0f})   "
              f"numba prange {B / nb_s:10.0f} traj/s (worst err {worst_nb:.1e})   "
              f"peak RSS so far {rss:.0f} MiB", flush=True)
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

    fig, ax = plt.subplots(figsize=(6, 4))
    B = [r["batch"] for r in rows]
    ax.loglog(B, [r["nhjax_traj_per_s"] for r in rows], "o-", label="nhjax simulate_batch")
    ax.loglog(B, [r["nhjax_vmapped_diffrax_traj_per_s"] for r in rows], "^:", label="vmapped diffeqsolve")
    ax.loglog(B, [r["numba_traj_per_s"] for r in rows], "s--", label="numba DP5, prange")
    ax.set(xlabel="batch size", ylabel="trajectories per second",
           title=f"falling cat, T = 10 s, rtol = atol = {TOL:g}, {jax.local_device_count()} device(s)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()
    print(f"load average at start (1, 5, 15 min): {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}",
          flush=True)
    cat, ctrl, x0, t1 = case()
    print("single trajectory:")
    s = single(cat, ctrl, x0, t1)
    print(f"  jax.jit(simulate) {s['jit_seconds'] * 1e3:.3f} ms (err {s['jit_error']:.1e}, {s['steps']} steps); "
          f"simulate() call {s['simulate_seconds'] * 1e3:.2f} ms; numba {s['numba_seconds'] * 1e3:.3f} ms "
          f"(err {s['numba_error']:.1e}, {s['numba_steps']} steps); compile {s['compile_seconds']:.2f} s")
    print("batches:")
    b = batches(cat, ctrl, t1, [1, 64, 1024, 16384])
    print("gradient of psi(T)^2 in the torque amplitudes:")
    g = gradients(cat, ctrl, x0, t1)
    print(f"  forward solve {g['forward_seconds'] * 1e3:.3f} ms (a jitted call that does nothing: "
          f"{g['dispatch_seconds'] * 1e3:.3f} ms); medians over {g['rounds']} interleaved rounds")
    for r in g["rows"]:
        if "unsupported" in r:
            continue
        print(f"  {r['adjoint']:46s} {r['ratio_to_forward']:6.2f} x forward   rel. error vs FD {r['error_vs_fd']:.1e}"
              f"   (compile {r['compile_seconds']:.1f} s)")
    b1024 = [r for r in b if r["batch"] == 1024][0]
    best_grad = min(r["ratio_to_forward"] for r in g["rows"]
                    if r["adjoint"].startswith("reverse") and "ratio_to_forward" in r)
    sweep = [r["ratio_to_forward"] for r in g["rows"] if "'vjp'" in r["adjoint"] and "ratio_to_forward" in r]
    goals = [
        ("single trajectory vs numba (goal <= 2x)", s["jit_seconds"] / s["numba_seconds"]),
        ("batch 1024 throughput vs numba prange (goal >= 1x)", b1024["nhjax_traj_per_s"] / b1024["numba_traj_per_s"]),
        ("compile time of simulate, s (goal < 3)", s["compile_seconds"]),
        ("jax.grad gradient / forward (goal <= 3x)", best_grad),
    ]
    if sweep:
        goals.append(("  backward sweep of recorded steps (jacobians='vjp')", sweep[0]))
    print("\ngoals:")
    for name, v in goals:
        print(f"  {name:52s} {v:8.2f}")
    load_end = os.getloadavg()
    meta = dict(command="python benchmarks/batch_throughput.py", platform=platform.platform(),
                cpu_count=os.cpu_count(), jax=jax.__version__, load_average_start=list(load_start),
                load_average_end=list(load_end))
    (OUT / "batch_throughput.json").write_text(json.dumps(
        dict(meta=meta, single=s, batches=b, gradients=g, goals=dict(goals), devices=jax.local_device_count()),
        indent=1))
    print(f"load average (1, 5, 15 min): start {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}, "
          f"end {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f}")
    plot(b, OUT / "batch_throughput.png")
    print(f"written: {OUT}/batch_throughput.json, .png")


if __name__ == "__main__":
    main()
