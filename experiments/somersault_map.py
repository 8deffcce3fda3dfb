"""A map of optimal somersaults: the chart somersault's least vibrational energy and
peak input over a grid of turn angles x initial bends, 256 problems in one call.

Problem (``controls.tasks.velocity_somersault_chart``, seed 000 (7.1), (4.8)): the
velocity-controlled cat in Iwai's chart, x = (theta, chi, psi), starts bent at
theta0 and returns to it after chi winds once (T = 2 s) while psi turns by ``turn``;
least int I1 [(1 + B s^2) theta'^2 + lam s^2/D chi'^2] dt. Every member is solved by
Pontryagin shooting, all at once (``controls.solve_pontryagin_batch``: one compiled
program for the grid, run on both cores as two shares of the members), by
continuation in the turn: each member starts from the fixed-theta loop's exact
extremal (``fixed_theta_costates``), whose turn is the loop's holonomy
-2 pi f(theta0), and walks to its own turn in ``--stages`` batched solves, each
warm-started from the last, at rtol = atol = 1e-8 and a shooting tolerance of
1e-6, then polishes the final turn at ``solve_pontryagin``'s defaults
(rtol = atol = 1e-11, tol = 1e-10).

Peer, in the same run (``--no-ipopt`` skips it; needs casadi, the ``peers`` extra,
and a source checkout): CasADi + IPOPT on the same problems one by one
(benchmarks/peers/casadi_somersault.py ``build_grid``: multiple shooting, N
piecewise-linear intervals, RK4 x 4, exact Hessian, built once with (theta0, turn)
as parameters), each member warm-started from its neighbour's solution along a
snake through the grid (the first from the fixed-theta loop). First on N = 40, then
on grids refined until IPOPT's costs are ours to 1e-8 relative on every member (the
same optima: N = 80, then the N its observed convergence order predicts).

Writes ``DIR/somersault_map.json`` (``turns``, ``bends``, ``costs`` and
``peak_inputs`` [bend][turn], ``status`` per member, ``batch_seconds_first``: the
continuation with its compile, ``batch_seconds``: the same again after compile, the
median of three runs (``batch_seconds_rounds``);
IPOPT on N = 40: ``ipopt_seconds`` (its solves of the 256), ``ipopt_build_seconds``,
``max_rel_diff_vs_ipopt``, ``throughput_vs_ipopt``; ``ipopt_grids``: every grid
tried (N, seconds, largest and median relative difference); ``ipopt_equal_accuracy``:
the first grid within 1e-8 of our costs on every member and the throughput against
it; the load average) and ``DIR/somersault_map.png`` (heat maps of cost and peak
input with the fixed-theta loop's turn marked: the members on that curve are solved
by the loop itself).

Usage: nhjax run somersault_map [--out DIR] [--n 16] [--stages 4] [--no-ipopt]
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

import equinox as eqx
import numpy as np

import controls
from controls.tasks import fixed_theta_costates, velocity_somersault_chart
from nhjax.scenes import FallingCatKinematic

from ._peers import import_peers

T = 2.0
EQUAL_ACCURACY = 1e-8  # the "same optima": IPOPT's grid is refined until its costs are ours to this
BENDS = (0.4, 1.0)  # theta0 [rad]
TURNS = (-4.0, -2.0)  # turn of psi [rad]


def holonomy(cat, theta0):
    """The fixed-theta loop's turn -2 pi f(theta0) [rad] (chi winds once)."""
    th = np.asarray(theta0, float)
    c, s = np.cos(th), np.sin(th)
    return -2 * np.pi * cat.lam * c / (s * s + cat.lam * c * c)


def solve_map(cat, bends, turns, stages, progress=False):
    """Every (bend, turn) member by batched continuation from the fixed-theta loop:
    the last stage's ``BatchResult`` and the seconds of the whole walk."""
    TH, TU = (a.ravel() for a in np.meshgrid(bends, turns, indexing="ij"))
    start = time.perf_counter()
    hol = holonomy(cat, TH)
    p0, nu = zip(*(fixed_theta_costates(cat, th, T) for th in TH))
    z = np.concatenate([np.stack(p0), np.stack(nu)], axis=1)
    # the grid as one stack of problems: one problem built and checked, the members'
    # starts and targets set for all at once (the members differ in these numbers only)
    base = velocity_somersault_chart(cat, TH[0], TU[0], T)
    grid = controls.stack_members([base] * TH.size)
    x0s = np.stack([TH, np.zeros_like(TH), np.zeros_like(TH)], axis=1)
    final = np.stack([TH, np.full_like(TH, 2 * np.pi), TU], axis=1)
    grid = eqx.tree_at(lambda g: (g.x0, g.terminal_constraints.target), grid, (x0s, final))
    for k in range(1, stages + 2):
        # the stages walk at loose tolerances (the way there needs no accuracy: fewer ODE
        # steps); the last solve polishes the final turn at solve_pontryagin's defaults
        tols = dict(rtol=1e-8, atol=1e-8, tol=1e-6) if k <= stages else {}
        targets = final.copy()
        targets[:, 2] = hol + (TU - hol) * min(k, stages) / stages
        stage = eqx.tree_at(lambda g: g.terminal_constraints.target, grid, targets)
        r = controls.solve_pontryagin_batch(stage, z[:, :3], z[:, 3:], progress=progress, **tols)
        # a member that failed at a stage keeps its last good start (its status says so at the end)
        z = np.where(r.converged[:, None], np.concatenate([r.p0, r.nu], axis=1), z)
    return r, time.perf_counter() - start


def ipopt_map(bends, turns, N=40):
    """IPOPT on each member one by one along a snake through the grid (N piecewise-linear
    intervals), each from its neighbour's solution: costs [bend][turn], success, the
    solves' seconds, the build's."""
    peers, why = import_peers("casadi_somersault")
    if peers is None:
        return None, why
    (peer,) = peers
    nlp = peer.build_grid(N=N, controls="pl", substeps=4, T=T)
    costs = np.full((len(bends), len(turns)), np.nan)
    success = np.zeros_like(costs, dtype=bool)
    seconds, w = 0.0, None
    for i, th in enumerate(bends):
        order = range(len(turns)) if i % 2 == 0 else range(len(turns) - 1, -1, -1)
        for j in order:
            w0 = peer.loop_start(nlp, float(th)) if w is None else w
            r = peer.solve_grid_member(nlp, float(th), float(turns[j]), w0)
            seconds += r["seconds"]
            costs[i, j], success[i, j] = r["cost"], r["success"]
            if r["success"]:
                w = r["w"]
    return dict(N=N, costs=costs, success=success, seconds=seconds, build_seconds=nlp["build_seconds"]), ""


def ipopt_grids(bends, turns, ours, converged, accuracy=EQUAL_ACCURACY, largest=400):
    """IPOPT's map on grids of N = 40, 80, then the N its convergence order predicts for a
    largest relative cost difference from ours of ``accuracy`` (rounded up to a multiple
    of 20, at least 100; 40 more while it misses, up to ``largest``): one row per grid (N, seconds,
    build seconds, successes, largest and median relative difference over the members
    both solved). Its cost converges to the continuous optimum that our shooting meets
    (to ~1e-11) as the grid is refined, at about the fourth order in N (RK4; more RK4
    substeps per interval did not shrink the difference, the intervals did)."""
    rows = []

    def run(N):
        ip, why = ipopt_map(bends, turns, N)
        if ip is None:
            return why
        both = converged & ip["success"]
        rel = np.abs(ours - ip["costs"]) / np.abs(ip["costs"])
        rows.append(dict(N=N, seconds=ip["seconds"], build_seconds=ip["build_seconds"],
                         succeeded=int(ip["success"].sum()), costs=ip["costs"].tolist(),
                         success=ip["success"].tolist(),
                         max_rel_diff=float(rel[both].max()) if both.any() else float("nan"),
                         median_rel_diff=float(np.median(rel[both])) if both.any() else float("nan")))
        print(f"IPOPT one by one (N = {N} pl, RK4 x 4, neighbour warm starts): {ip['seconds']:.2f} s (build "
              f"{ip['build_seconds']:.2f} s), {rows[-1]['succeeded']} succeeded; largest relative cost difference "
              f"from ours {rows[-1]['max_rel_diff']:.1e}", flush=True)
        return ""

    why = run(40)
    if why:
        return None, why
    if rows[-1]["max_rel_diff"] > accuracy:
        run(80)
        e40, e80 = rows[0]["max_rel_diff"], rows[1]["max_rel_diff"]
        N = 80
        if e80 > accuracy:
            order = np.log2(e40 / e80) if e40 > e80 > 0 else 2.0
            N = int(min(largest, max(100, 20 * np.ceil(80 * (e80 / accuracy) ** (1 / order) / 20))))
            run(N)
        while rows[-1]["max_rel_diff"] > accuracy and N + 40 <= largest:
            N += 40
            run(N)
    return rows, ""


def figure(bends, turns, costs, peaks, status, hol, path):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.6), layout="constrained")
    failed = status != "converged"
    for k, (values, title, unit) in enumerate(((costs, "least vibrational energy", "J s"),
                                               (peaks, "peak input max |u(t)|", "rad/s"))):
        ax = fig.add_subplot(1, 2, k + 1)
        m = ax.pcolormesh(turns, bends, np.ma.masked_where(failed, values), shading="nearest", cmap="viridis")
        fig.colorbar(m, ax=ax, label=f"[{unit}]")
        inside = (hol >= turns.min()) & (hol <= turns.max())
        ax.plot(hol[inside], bends[inside], "w--", lw=1.5,
                label=r"fixed-$\theta$ loop's turn $-2\pi f(\theta_0)$")
        if failed.any():
            fi, fj = np.nonzero(failed)
            ax.plot(turns[fj], bends[fi], "rx", ms=6, label="not converged")
        ax.set(xlabel="turn of psi [rad]", ylabel=r"initial bend $\theta_0$ [rad]",
               title=f"({'ab'[k]}) {title}")
        ax.legend(loc="upper right", fontsize=8)
    fig.suptitle(f"chart somersault, chi winds once (T = {T:g} s): {status.size} problems in one batched call")
    fig.savefig(path, dpi=110)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="somersault_map", help="folder for the outputs (default: ./somersault_map)")
    ap.add_argument("--n", type=int, default=16, help="grid points per axis (n x n problems)")
    ap.add_argument("--stages", type=int, default=4, help="continuation stages from the fixed-theta loop")
    ap.add_argument("--no-ipopt", action="store_true", help="skip the CasADi + IPOPT peer")
    a = ap.parse_args()
    if a.n < 2 or a.stages < 1:
        ap.error("--n must be >= 2 and --stages >= 1")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()
    cat = FallingCatKinematic()
    bends, turns = np.linspace(*BENDS, a.n), np.linspace(*TURNS, a.n)
    r, first = solve_map(cat, bends, turns, a.stages, progress=True)
    # after compile: the median of three runs (a run's time varies by tens of percent on a
    # shared machine)
    rounds = []
    for _ in range(3):
        r, seconds = solve_map(cat, bends, turns, a.stages)
        rounds.append(seconds)
    again = float(np.median(rounds))
    shape = (a.n, a.n)
    costs, status = r.cost.reshape(shape), r.status.reshape(shape)
    peaks = np.linalg.norm(r.controls, axis=-1).max(axis=-1).reshape(shape)
    print(f"{r.status.size} problems, {a.stages} continuation stages: {r.counts()}; "
          f"{first:.2f} s with the compile, {again:.3f} s after it, the median of "
          + ", ".join(f"{x:.3f}" for x in rounds) + f" ({again / r.status.size * 1e3:.2f} ms a problem)")
    info = dict(command="nhjax run somersault_map " + " ".join(sys.argv[1:]), T=T, stages=a.stages,
                turns=turns.tolist(), bends=bends.tolist(), costs=costs.tolist(), peak_inputs=peaks.tolist(),
                status=status.tolist(), iterations_last_stage=r.iterations.reshape(shape).tolist(),
                max_shooting_residual=float(np.nanmax(r.residual)), max_violation=float(np.nanmax(r.violation)),
                batch_seconds_first=first, batch_seconds=again, batch_seconds_rounds=rounds)
    if not a.no_ipopt:
        rows, why = ipopt_grids(bends, turns, costs, status == "converged")
        if rows is None:
            print(f"IPOPT peer skipped: {why}")
            info["ipopt_skipped"] = why
        else:
            quick = rows[0]
            info.update(ipopt_seconds=quick["seconds"], ipopt_build_seconds=quick["build_seconds"],
                        ipopt_costs=quick["costs"], ipopt_success=quick["success"],
                        max_rel_diff_vs_ipopt=quick["max_rel_diff"], throughput_vs_ipopt=quick["seconds"] / again,
                        ipopt_grids=[{k: v for k, v in r.items() if k not in ("costs", "success")} for r in rows])
            print(f"batch throughput {quick['seconds'] / again:.1f}x IPOPT's on N = 40 (largest cost difference "
                  f"{quick['max_rel_diff']:.1e})")
            equal = next((r for r in rows if r["max_rel_diff"] <= EQUAL_ACCURACY), None)
            if equal is not None:
                info["ipopt_equal_accuracy"] = dict(N=equal["N"], seconds=equal["seconds"],
                                                    max_rel_diff=equal["max_rel_diff"],
                                                    throughput=equal["seconds"] / again)
                print(f"at equal accuracy (IPOPT within {EQUAL_ACCURACY:g} of our optimum on every member, "
                      f"N = {equal['N']}): batch throughput {equal['seconds'] / again:.1f}x IPOPT's")
    load_end = os.getloadavg()
    info.update(load_average_start=list(load_start), load_average_end=list(load_end))
    (out / "somersault_map.json").write_text(json.dumps(info, indent=1))
    figure(bends, turns, costs, peaks, status, holonomy(cat, bends), out / "somersault_map.png")
    print(f"load average {load_start[0]:.2f} -> {load_end[0]:.2f}; wrote {out}/somersault_map.json and .png")


if __name__ == "__main__":
    main()
