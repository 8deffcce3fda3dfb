"""Bouncing ball on a vibrating table (seed 004, ex. 10.2): bifurcation diagram over Gamma = A w^2/g, phase portraits, the high-bounce map, an animation.

All motions are exact-impact simulations (``nhjax.simulate_impacts``; free flights are
parabolas, integrated to round-off; impacts by the seed's affine projector with
restitution alpha; chattering ends in resting contact and the ball is released where the
table's acceleration passes -g). Outputs in ``--out`` (default: ./bouncing_ball/):

* bouncing_ball_bifurcation.png: impact phase (w t mod 2 pi) / 2 pi and normalized
  rebound velocity v w / g of the impacts after a transient, over Gamma, for thousands of
  amplitudes in one batched call (``nhjax.simulate_impacts_batch``); the period-1 orbit's
  existence (Gamma_1 = pi (1 - alpha)/(1 + alpha)) and period-doubling thresholds
  (Gamma_2 = sqrt(Gamma_1^2 + (2 (1 + alpha^2)/(1 + alpha)^2)^2)) from the high-bounce
  analysis are drawn for comparison;
* bouncing_ball_phase.png: x - x_W versus x' for three Gamma (period 1, period 2,
  chaotic), and the impact map (phase, velocity) of the exact motion next to the seed's
  high-bounce map from the same start;
* bouncing_ball.gif: ball and table over a few periods;
* bouncing_ball.json: parameters, thresholds, members, wall time, load average.

Options: --members N (default 2000), --alpha a (default 0.5), --no-figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import nhjax
from nhjax.scenes import BouncingBall

G, W = 9.81, 2 * np.pi  # table period 1 s


def thresholds(alpha):
    g1 = np.pi * (1 - alpha) / (1 + alpha)
    g2 = np.sqrt(g1**2 + (2 * (1 + alpha**2) / (1 + alpha) ** 2) ** 2)
    return g1, g2


def bifurcation(members, alpha, transient=100, record=60, periods=150.0):
    gam = np.linspace(0.9, 4.0, members)
    ball = BouncingBall(g=G, A=1.0, omega=W, restitution=alpha)
    balls = eqx.tree_at(lambda s: s.A, ball, jnp.asarray(gam * G / W**2))
    x0 = jnp.array([1e-3, 0.0])
    t = time.perf_counter()
    tr = nhjax.simulate_impacts_batch(balls, x0, periods, in_axes={"system": ["A"]},
                                      max_impacts=transient + record, rest_velocity=1e-4,
                                      on_max_impacts="stop", on_error="return")
    wall = time.perf_counter() - t
    times = np.asarray(tr.impact_times)
    v = np.asarray(tr.velocities_post[..., 0])
    n = np.asarray(tr.num_impacts)
    phase, vel, gg = [], [], []
    for i in range(members):
        sl = slice(min(transient, max(n[i] - record, 0)), n[i])
        phase.append(np.mod(W * times[i, sl], 2 * np.pi) / (2 * np.pi))
        vel.append(v[i, sl] * W / G)
        gg.append(np.full(phase[-1].shape, gam[i]))
    status = np.bincount(np.asarray(tr.status), minlength=6)
    return dict(gamma=np.concatenate(gg), phase=np.concatenate(phase), velocity=np.concatenate(vel),
                wall=wall, status=status.tolist(), rested=int(np.sum(np.asarray(tr.persistent)[:, 0])),
                steps_max=int(np.max(np.asarray(tr.num_steps))), steps_median=float(np.median(np.asarray(tr.num_steps))))


def portrait(gamma, alpha, t1=40.0, saveat=8001):
    b = BouncingBall(g=G, A=gamma * G / W**2, omega=W, restitution=alpha)
    tr = nhjax.simulate_impacts(b, b.initial_state(0.05, 0.0), t1, saveat=saveat, max_impacts=4000,
                                rest_velocity=1e-4)
    return b, tr


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--members", type=int, default=2000)
    p.add_argument("--alpha", type=float, default=0.5)
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--out", type=Path, default=Path("bouncing_ball"),
                   help="folder for the figures, the animation and the JSON (default: ./bouncing_ball)")
    args = p.parse_args(argv)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()
    g1, g2 = thresholds(args.alpha)
    bif = bifurcation(args.members, args.alpha)
    print(f"bifurcation: {args.members} amplitudes, Gamma in [0.9, 4], alpha = {args.alpha}: "
          f"{bif['wall']:.1f} s wall (compile included), status counts {bif['status']} "
          f"(0: reached t1, 1: impacts recorded), {bif['rested']} resting at the end; "
          f"loop iterations per member median {bif['steps_median']:.0f}, max {bif['steps_max']}")
    # observed period-1 window: Gamma where the last impacts all share one phase
    gam_u = np.unique(bif["gamma"])
    spread = np.array([np.ptp(bif["phase"][bif["gamma"] == gv]) if np.any(bif["gamma"] == gv) else np.nan
                       for gv in gam_u])
    period1 = gam_u[spread < 1e-6]
    obs = (float(period1.min()), float(period1.max())) if period1.size else (float("nan"), float("nan"))
    print(f"one impact phase after the transient (period 1): Gamma in [{obs[0]:.4f}, {obs[1]:.4f}] "
          f"({period1.size} amplitudes; nan: none); the high-bounce map's period-1 window is "
          f"[{g1:.4f}, {g2:.4f}] (it neglects the table's displacement and chattering)")

    portraits = {gm: portrait(gm, args.alpha) for gm in (1.3, 1.7, 3.5)}
    # exact impact map vs the seed's high-bounce map from the same first impact (chaotic case)
    b, tr = portraits[3.5]
    k = int(tr.num_impacts)
    tm, vm = b.high_bounce_orbit(tr.impact_times[0], tr.velocities_post[0, 0], k - 1)
    summary = dict(
        alpha=args.alpha, g=G, omega=W, members=args.members, gamma_range=[0.9, 4.0],
        period1_theory=[g1, g2], period1_observed=list(obs), wall_seconds=bif["wall"],
        status_counts=bif["status"], resting_at_end=bif["rested"],
        loop_iterations_median=bif["steps_median"], loop_iterations_max=bif["steps_max"],
        load_average_start=load0, load_average_end=os.getloadavg(),
        portraits={str(gm): dict(impacts=int(t.num_impacts), energy_bookkeeping_error=float(t.energy_error))
                   for gm, (_, t) in portraits.items()},
    )
    (out / "bouncing_ball.json").write_text(json.dumps(summary, indent=2))
    if args.no_figures:
        return summary

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 1, figsize=(11, 8), sharex=True)
    ax[0].plot(bif["gamma"], bif["phase"], ",k", alpha=0.5)
    ax[1].plot(bif["gamma"], bif["velocity"], ",k", alpha=0.5)
    for a in ax:
        for gv, lab in ((1.0, "Gamma = 1"), (g1, "Gamma_1"), (g2, "Gamma_2")):
            a.axvline(gv, color="r" if gv != 1.0 else "b", lw=0.7, ls="--")
    ax[0].set(ylabel="impact phase  (w t mod 2 pi) / 2 pi",
              title=f"bouncing ball, alpha = {args.alpha}: {args.members} amplitudes, exact impacts "
                    f"(dashed: Gamma = 1, and the period-1 window [Gamma_1, Gamma_2] of the high-bounce map)")
    ax[1].set(xlabel="Gamma = A w^2 / g", ylabel="rebound velocity  v w / g")
    fig.tight_layout()
    fig.savefig(out / "bouncing_ball_bifurcation.png", dpi=130)

    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    for a, (gm, (bb, t)) in zip(axes.ravel(), portraits.items()):
        ok = np.isfinite(np.asarray(t.ts))
        ts, xs = np.asarray(t.ts)[ok], np.asarray(t.xs)[ok]
        late = ts > ts[-1] / 2
        a.plot(xs[late, 0] - np.asarray(bb.table(ts[late])), xs[late, 1], "-", lw=0.5)
        a.set(xlabel="x - x_W [m]", ylabel="x' [m/s]", title=f"Gamma = {gm}: phase portrait (second half)")
    a = axes[1, 1]
    ph = np.mod(W * np.asarray(tr.impact_times[:k]), 2 * np.pi) / (2 * np.pi)
    a.plot(ph, np.asarray(tr.velocities_post[:k, 0]) * W / G, ".", ms=2, label="exact impacts")
    a.plot(np.mod(W * np.asarray(tm), 2 * np.pi) / (2 * np.pi), np.asarray(vm) * W / G, ".", ms=2,
           label="seed's high-bounce map")
    a.set(xlabel="impact phase / 2 pi", ylabel="v w / g", title="Gamma = 3.5: impact map")
    a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "bouncing_ball_phase.png", dpi=120)

    from matplotlib.animation import FuncAnimation, PillowWriter

    bb, t = portraits[1.7]
    ok = np.isfinite(np.asarray(t.ts))
    ts, xs = np.asarray(t.ts)[ok], np.asarray(t.xs)[ok]
    sel = np.flatnonzero((ts >= 30.0) & (ts <= 34.0))[::4]
    fig, a = plt.subplots(figsize=(4, 5))
    A = float(bb.A)
    top = float(np.max(xs[sel, 0])) + 0.1 * A + 0.02

    def draw(i):
        a.clear()
        j = sel[i]
        tab = float(bb.table(ts[j]))
        a.fill_between([-1, 1], [tab - 0.05, tab - 0.05], [tab, tab], color="0.5")
        a.plot([0], [xs[j, 0] + 0.01], "o", color="tab:red", ms=14)
        a.set(xlim=(-1, 1), ylim=(-A - 0.05, top + 0.02), title=f"Gamma = 1.7, t = {ts[j]:.2f} s")
        a.set_xticks([])

    FuncAnimation(fig, draw, frames=len(sel)).save(out / "bouncing_ball.gif", writer=PillowWriter(fps=25), dpi=72)
    print(f"wrote {out / 'bouncing_ball_bifurcation.png'}, bouncing_ball_phase.png, bouncing_ball.gif, bouncing_ball.json")
    return summary


if __name__ == "__main__":
    main()
