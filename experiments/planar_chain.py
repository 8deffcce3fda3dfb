"""Planar chains reduced by symmetry (seed 001): geometry, holonomy and optimal control.

1. Geometry of a 3-link chain (``PlanarChain``, zero momentum): the local
   connection A(phi) (the turn per unit joint motion) and its curvature F12 over
   the joint angles (phi1, phi2), as gait designers draw them; closed joint loops
   simulated against the turn Stokes predicts from F12 (exact: abelian).
2. Reorientation at zero momentum, rest to rest, least int |u|^2 (joint torques):
   the direct method (feasible-path Newton over Chebyshev torques, from a
   circular joint loop sized by Stokes) and Pontryagin shooting from the direct
   optimum's costates; their costs side by side, ``pmp_residual`` of both.
3. Thruster steering: the chain with a thruster per body moves from rest to rest
   at a target pose (x, y, angle), least int |u|^2 (torques and thrusts): the
   Newton direct method from zero inputs, Pontryagin from its costates.

Writes to ``--out`` (default: ./planar_chain/) planar_chain_geometry.png, planar_chain_reorientation.png,
planar_chain_steering.png, planar_chain.json and planar_chain.gif (the
reorientation, then the steering).

Usage: nhjax run planar_chain [--out DIR] [--no-animation] [--turn RAD] [--T S] [--degree N]
                              [--target X Y ANGLE]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import controls
import nhjax
from controls.tasks import chain_loop_guess, chain_loop_path, chain_radius_for_turn, chain_reorientation, chain_steering
from nhjax.mechanics.reduction import EllipseLoop, curvature_integral
from nhjax.scenes import PlanarChain

PHI0 = (0.5, 0.5)


def timed(fn):
    t = time.perf_counter()
    r = fn()
    return r, time.perf_counter() - t


# ------------------------------------------------------------------ drawing
def chain_segments(chain, x):
    """Endpoints (N, 2, 2) of the bodies drawn as rods between their hinges."""
    th, pos = chain.body_poses(x)
    ho, hi = np.asarray(chain.shape_map.hinge_out), np.asarray(chain.shape_map.hinge_in)
    N = chain.n_bodies
    segs = []
    for i in range(N):
        a = hi[i - 1] if i > 0 else -ho[0]
        b = ho[i] if i < N - 1 else -hi[N - 2]
        R = np.array([[np.cos(th[i]), -np.sin(th[i])], [np.sin(th[i]), np.cos(th[i])]])
        segs.append([np.asarray(pos[i]) + R @ a, np.asarray(pos[i]) + R @ b])
    return np.array(segs)


def draw_chain(ax, chain, x, color="tab:blue", alpha=1.0, thrust=None, lw=4):
    segs = chain_segments(chain, x)
    for s in segs:
        ax.plot(s[:, 0], s[:, 1], "-", color=color, lw=lw, alpha=alpha, solid_capstyle="round")
    joints = np.asarray(chain.joints(x))
    ax.plot(joints[:, 0], joints[:, 1], "o", color="k", ms=3, alpha=alpha)
    if thrust is not None:
        th, pos = chain.body_poses(x)
        axes = np.asarray(chain.inputs.thruster_axes)
        for i, F in enumerate(thrust):
            R = np.array([[np.cos(th[i]), -np.sin(th[i])], [np.sin(th[i]), np.cos(th[i])]])
            d = 0.3 * F * (R @ axes[i])
            ax.arrow(float(pos[i][0]), float(pos[i][1]), float(d[0]), float(d[1]), color="tab:red", width=0.01,
                     alpha=alpha)


# ------------------------------------------------------------------ 1. geometry
def geometry(chain, out, n_grid=41):
    g = np.linspace(-np.pi, np.pi, n_grid)
    P = jnp.asarray(np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2))
    A, F = jax.jit(jax.vmap(lambda r: (chain.connection(r)[0], chain.curvature(r)[0, 0, 1])))(P)
    A = np.asarray(A).reshape(n_grid, n_grid, 2)
    F = np.asarray(F).reshape(n_grid, n_grid)
    # closed loops: simulated turn (velocity control) against Stokes
    kin = chain.kinematic()
    loops = []
    for centre, a, b in (((1.0, 0.8), 1.4, 1.0), ((-1.5, -1.0), 0.8, 1.2), ((0.5, 0.5), 0.3, 0.3), ((0.0, 0.0), 2.0, 2.0)):
        c = jnp.asarray(centre)
        x0 = kin.initial_state(c + jnp.array([a, 0.0]))
        ctrl = _LoopRate(jnp.asarray(a), jnp.asarray(b))
        tr = nhjax.simulate(kin, x0, 1.0, control=ctrl, rtol=1e-12, atol=1e-12, saveat=201)
        stokes = -float(curvature_integral(kin, EllipseLoop(c, a, b), c, n=48)[0])
        turn = float(tr.xs[-1, 0] - tr.xs[0, 0])
        loops.append(dict(centre=list(centre), a=a, b=b, simulated=turn, stokes=stokes, error=abs(turn - stokes),
                          path=np.asarray(tr.xs[:, 1:]).tolist()))
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 5.2), layout="constrained")
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    G1, G2 = np.meshgrid(g, g, indexing="ij")
    s = slice(None, None, 2)
    ax1.quiver(G1[s, s], G2[s, s], -A[s, s, 0], -A[s, s, 1], np.hypot(A[s, s, 0], A[s, s, 1]), cmap="viridis")
    ax1.set(xlabel=r"$\phi_1$ [rad]", ylabel=r"$\phi_2$ [rad]", aspect="equal",
            title=r"(a) connection: $\dot\theta = -A(\phi)\,\dot\phi$; arrows $-A$ (turn per unit joint motion)")
    lim = np.max(np.abs(F))
    im = ax2.pcolormesh(G1, G2, F, cmap="RdBu_r", vmin=-lim, vmax=lim, shading="auto")
    ax2.contour(G1, G2, F, levels=[0.0], colors="k", linewidths=0.8)
    fig.colorbar(im, ax=ax2, label=r"$F_{12}$ [rad / rad$^2$]")
    for lp in loops:
        p = np.asarray(lp["path"])
        ax2.plot(p[:, 0], p[:, 1], "-", color="k", lw=1)
        ax2.annotate(f"{lp['simulated']:+.3f}", p[0], fontsize=8)
    ax2.set(xlabel=r"$\phi_1$ [rad]", ylabel=r"$\phi_2$ [rad]", aspect="equal",
            title="(b) curvature; loops (ccw) labelled with their simulated turn [rad]")
    fig.savefig(out / "planar_chain_geometry.png", dpi=120)
    return loops


class _LoopRate(eqx.Module):
    a: jax.Array
    b: jax.Array

    def __call__(self, t, x):
        w = 2 * jnp.pi
        return jnp.stack([-self.a * w * jnp.sin(w * t), self.b * w * jnp.cos(w * t)])


# ------------------------------------------------------------------ 2. reorientation
def solve_both(ocp, param, guess):
    """Direct (feasible-path Newton) then Pontryagin (Levenberg-Marquardt) from the direct
    optimum's costates; pmp_residual of both; times after compile are second solves."""
    d, t_d = timed(lambda: controls.solve_direct_newton(ocp, param, guess))
    res_d = controls.pmp_residual(ocp, d.control)
    ind, t_i = timed(lambda: controls.solve_pontryagin(ocp, res_d["ps"][-1], res_d["multipliers"], solver="lm"))
    res_i = controls.pmp_residual(ocp, extremal_control(ind, ocp.T))
    d2, t_d2 = timed(lambda: controls.solve_direct_newton(ocp, param, guess))
    ind2, t_i2 = timed(lambda: controls.solve_pontryagin(ocp, res_d["ps"][-1], res_d["multipliers"], solver="lm"))
    info = dict(
        cost_direct=d.cost, cost_pontryagin=ind.cost, relative_difference=abs(d.cost - ind.cost) / abs(ind.cost),
        violation_direct=d.violation, violation_pontryagin=ind.violation, shooting_residual=ind.residual,
        converged_direct=d.converged, converged_pontryagin=ind.converged, iterations_direct=d.iterations,
        iterations_pontryagin=ind.iterations, stationarity_direct=res_d["stationarity"],
        stationarity_pontryagin=res_i["stationarity"], hamiltonian_variation_pontryagin=res_i["hamiltonian_variation"],
        seconds_direct_first=t_d, seconds_direct_again=t_d2, seconds_pontryagin_first=t_i,
        seconds_pontryagin_again=t_i2, parameters=int(param.size))
    return d, ind, res_d, info


def reorientation(chain, turn, T, degree):
    phi0 = jnp.asarray(PHI0)
    radius, orientation = chain_radius_for_turn(chain, turn, phi0)
    ocp = chain_reorientation(chain, turn, T, phi0)
    param = controls.Chebyshev(degree, T, 2)
    guess = chain_loop_guess(chain, param, phi0, T, radius, orientation=orientation)
    d, ind, res_d, info = solve_both(ocp, param, guess)
    path = chain_loop_path(phi0, radius, (1.0, 1.0), orientation, T)
    loop = np.asarray(jax.vmap(lambda t: path(t)[0])(jnp.linspace(0, T, 101)))
    info.update(turn=turn, T=T, phi0=list(PHI0), start_loop_radius=radius, chebyshev_degree=degree)
    return dict(ocp=ocp, direct=d, indirect=ind, res_direct=res_d, loop=loop, info=info)


def reorientation_figure(chain, r, path):
    from matplotlib.figure import Figure

    ind, d = r["indirect"], r["direct"]
    ts, xs, us = np.asarray(ind.trajectory.ts), np.asarray(ind.trajectory.xs), np.asarray(ind.controls)
    n = chain.k
    g = np.linspace(-1.0, 2.5, 61)
    P = jnp.asarray(np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2))
    F = np.asarray(jax.jit(jax.vmap(lambda q: chain.curvature(q)[0, 0, 1]))(P)).reshape(61, 61)
    fig = Figure(figsize=(12, 8), layout="constrained")
    ax = fig.add_subplot(2, 2, 1)
    lim = np.max(np.abs(F))
    G1, G2 = np.meshgrid(g, g, indexing="ij")
    ax.pcolormesh(G1, G2, F, cmap="RdBu_r", vmin=-lim, vmax=lim, shading="auto")
    ax.plot(r["loop"][:, 0], r["loop"][:, 1], "--", color="gray", label="start: Stokes-sized circle")
    ax.plot(xs[:, 1], xs[:, 2], "-", color="k", label="optimal joint path")
    ax.plot(xs[0, 1], xs[0, 2], "ko")
    ax.set(xlabel=r"$\phi_1$ [rad]", ylabel=r"$\phi_2$ [rad]", aspect="equal",
           title="(a) joint loop over the curvature $F_{12}$")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(2, 2, 2)
    ax.plot(ts, xs[:, 0], label="angle")
    for k in range(n):
        ax.plot(ts, xs[:, 1 + k], label=f"phi{k + 1}")
    ax.set(xlabel="t [s]", ylabel="[rad]", title=f"(b) turn {r['info']['turn']} rad at zero momentum")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(2, 2, 3)
    ud = np.asarray(jax.vmap(lambda t: d.control(t, None))(jnp.asarray(ts)))
    for k in range(n):
        ax.plot(ts, us[:, k], label=f"T{k + 1} Pontryagin")
        ax.plot(ts, ud[:, k], "--", label=f"T{k + 1} direct")
    ax.set(xlabel="t [s]", ylabel="joint torque [N m]",
           title=f"(c) costs {r['info']['cost_direct']:.10f} (direct), {r['info']['cost_pontryagin']:.10f}")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(2, 2, 4)
    snaps = np.linspace(0, len(ts) - 1, 7).astype(int)
    for j, i in enumerate(snaps):
        x = chain.join(None, xs[i, :1], xs[i, 1:1 + n], xs[i, 1 + n:1 + 2 * n])
        draw_chain(ax, chain, x, color=f"C{j}", alpha=0.8, lw=3)
    ax.set(aspect="equal", xlabel="x [m]", ylabel="y [m]", title="(d) the chain at 7 times (C0 first)")
    for a in fig.axes[1:3]:
        a.grid(alpha=0.3)
    fig.savefig(path, dpi=120)


def extremal_control(ind, T, degree=60):
    """The Pontryagin extremal's controls (401 samples) as a Chebyshev series of
    ``degree`` fitted by least squares (spectrally accurate for smooth controls, unlike
    an interpolant, whose kinks pmp_residual would measure)."""
    param = controls.Chebyshev(degree, T, ind.controls.shape[1])
    ts = jnp.asarray(ind.trajectory.ts)
    basis = jax.jacfwd(lambda p: jax.vmap(lambda t: param.signal(p)(t, None))(ts).reshape(-1))(jnp.zeros(param.size))
    coef = jnp.linalg.lstsq(basis, jnp.asarray(ind.controls).reshape(-1))[0]
    return param.signal(coef)


# ------------------------------------------------------------------ 3. steering
def steering(target, T, degree):
    chain = PlanarChain(thrusters=True)
    phi0 = jnp.asarray(PHI0)
    ocp = chain_steering(chain, target, T, phi0)
    param = controls.Chebyshev(degree, T, chain.control_dim)
    d, ind, res_d, info = solve_both(ocp, param, jnp.zeros(param.size))
    info.update(target=list(target), T=T, phi0=list(PHI0), chebyshev_degree=degree, start="zero inputs")
    return dict(chain=chain, ocp=ocp, direct=d, indirect=ind, info=info)


def steering_figure(r, path):
    from matplotlib.figure import Figure

    chain, ind = r["chain"], r["indirect"]
    n = len(chain.flat_names)  # the extremal's states are (x, p)
    ts, xs, us = np.asarray(ind.trajectory.ts), np.asarray(ind.trajectory.xs)[:, :n], np.asarray(ind.controls)
    fig = Figure(figsize=(12, 4.5), layout="constrained")
    ax = fig.add_subplot(1, 3, 1)
    for j, i in enumerate(np.linspace(0, len(ts) - 1, 6).astype(int)):
        draw_chain(ax, chain, jnp.asarray(xs[i]), color=f"C{j}", alpha=0.8, lw=3, thrust=us[i, chain.k:])
    ax.plot(xs[:, 0], xs[:, 1], "k-", lw=1, label="centre of mass")
    ax.set(aspect="equal", xlabel="x [m]", ylabel="y [m]", title=f"(a) to pose {r['info']['target']}")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(1, 3, 2)
    for k, name in enumerate(chain.flat_names[:3 + chain.k]):
        ax.plot(ts, xs[:, k], label=name)
    ax.set(xlabel="t [s]", title="(b) pose and joint angles")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(1, 3, 3)
    for k in range(us.shape[1]):
        ax.plot(ts, us[:, k], label=(f"T{k + 1} [N m]" if k < chain.k else f"F{k - chain.k + 1} [N]"))
    ax.set(xlabel="t [s]", title=f"(c) inputs; cost {r['info']['cost_pontryagin']:.8f}")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=120)


def animation(frames_list, path, fps=12):
    """GIF of a list of (chain, xs, title) runs, one after the other."""
    from matplotlib.animation import FuncAnimation, PillowWriter
    from matplotlib.figure import Figure

    seq = [(ch, x, title) for ch, xs, title in frames_list for x in xs]
    allsegs = np.concatenate([chain_segments(ch, x).reshape(-1, 2) for ch, x, _ in seq])
    lo, hi = allsegs.min(0) - 0.2, allsegs.max(0) + 0.2
    fig = Figure(figsize=(5, 5))
    ax = fig.add_subplot()

    def draw(i):
        ax.clear()
        ch, x, title = seq[i]
        draw_chain(ax, ch, x)
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), aspect="equal", title=title)

    FuncAnimation(fig, draw, frames=len(seq)).save(path, writer=PillowWriter(fps=fps), dpi=70)


# ------------------------------------------------------------------ main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="planar_chain", help="folder for the outputs (default: ./planar_chain)")
    ap.add_argument("--no-animation", action="store_true")
    ap.add_argument("--turn", type=float, default=0.2)
    ap.add_argument("--T", type=float, default=3.0)
    ap.add_argument("--degree", type=int, default=40)
    ap.add_argument("--target", type=float, nargs=3, default=(0.5, 0.3, 0.3))
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load = [os.getloadavg()[0]]
    chain = PlanarChain(group="SO2")
    summary = {}
    loops, t = timed(lambda: geometry(chain, out))
    summary["holonomy_loops"] = [{k: v for k, v in lp.items() if k != "path"} for lp in loops]
    print(f"geometry: {len(loops)} loops, worst |simulated - Stokes| = {max(lp['error'] for lp in loops):.1e} rad "
          f"({t:.1f} s)", flush=True)
    r = reorientation(chain, args.turn, args.T, args.degree)
    summary["reorientation"] = r["info"]
    _print("reorientation", r["info"])
    reorientation_figure(chain, r, out / "planar_chain_reorientation.png")
    s = steering(tuple(args.target), args.T, 12)
    summary["steering"] = s["info"]
    _print("steering", s["info"])
    steering_figure(s, out / "planar_chain_steering.png")
    load.append(os.getloadavg()[0])
    summary["load_average"] = load
    (out / "planar_chain.json").write_text(json.dumps(summary, indent=1, default=float))
    if not args.no_animation:
        n = chain.k
        xr = np.asarray(r["indirect"].trajectory.xs)[::10]
        frames = [(chain, [chain.join(None, x[:1], x[1:1 + n], x[1 + n:1 + 2 * n]) for x in xr], "reorientation"),
                  (s["chain"], [jnp.asarray(x[:len(s["chain"].flat_names)])
                                for x in np.asarray(s["indirect"].trajectory.xs)[::10]], "steering")]
        animation(frames, out / "planar_chain.gif")
    print(f"load average {load[0]:.2f} -> {load[1]:.2f}; written: {out}/planar_chain_geometry.png, "
          "planar_chain_reorientation.png, planar_chain_steering.png, planar_chain.json"
          + ("" if args.no_animation else ", planar_chain.gif"))


def _print(name, info):
    print(f"{name}: cost direct {info['cost_direct']:.12f}, Pontryagin {info['cost_pontryagin']:.12f} "
          f"(rel. diff. {info['relative_difference']:.1e}); violation {info['violation_direct']:.1e} / "
          f"{info['violation_pontryagin']:.1e}; stationarity (pmp_residual) {info['stationarity_direct']:.1e} / "
          f"{info['stationarity_pontryagin']:.1e}; time direct {info['seconds_direct_first']:.1f} s first, "
          f"{info['seconds_direct_again']:.1f} s again; Pontryagin {info['seconds_pontryagin_first']:.1f} s / "
          f"{info['seconds_pontryagin_again']:.1f} s", flush=True)


if __name__ == "__main__":
    main()
