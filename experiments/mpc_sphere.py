"""The spherical robot follows a moving target around a figure-eight by model-predictive
control, pushed at t = 5 s, with a top 10% heavier than the controller's model.

Task (``controls.tasks.sphere_tracking``; seed 003 sec. 1 with the internal torque):
the reduced robot (``ReducedSteering`` of ``nhjax.scenes.ShellWithTop()``) starts at
rest at the origin and tracks r(t) = A (sin(w t), sin(2 w t) / 2), A = 0.5 m,
w = 2 pi / 20 s, for one lap (20 s), with the running cost
100 |(x, y) - r(t)|^2 + 0.1 |omega|^2 + |tau|^2 and torques |tau_i| <= 1 N m.

Controller: ``controls.MPC(ocp, period=0.05, intervals=20, mode="rti")``: horizon
1 s on 20 intervals (RK4, piecewise-constant torque), one SQP step per period.
Plant: the same equations with the top's mass and inertia 10% larger, advanced by
RK4 at the model's step; at t = 5 s a push changes the shell centre's velocity by
0.3 m/s along the top's x axis (``controls.tasks.shell_push``). ``--plant full``:
the plant is instead the whole robot (``ShellWithTop``: both attitudes on SO(3),
its equations derived by nhjax from the Lagrangian and the rolling constraint, an
independent model of the same physics), stepped by RKMK4 and measured into the
reduced state (``closed_loop(..., measure=...)``); the push is the same change of
the shell's angular velocity, applied to its state. The loop is stepped
from Python (``closed_loop(..., timing=True)``): each period's solve is one compiled
call, timed after compile.

Peer, in the same run (``--no-ipopt`` skips it; needs casadi, the ``peers`` extra, and
a source checkout): ``benchmarks/peers/casadi_mpc_sphere.py``, the same horizon
problem (multiple shooting, the same RK4 map and cost quadrature), IPOPT with the
exact Hessian warm-started from the shifted previous solution and multipliers,
against the same plant and push.

Writes ``DIR/mpc_sphere.json`` (``period_ms_median``, ``period_ms_max``,
``casadi_period_ms_median``, ``closed_loop_cost``, ``casadi_closed_loop_cost``,
``tracking_error_after_push_m``: the largest error from 2 s after the push to the
end, ``load_average``, and more: the compile time, fallbacks, the time the error
takes to come back under 2 cm), ``DIR/mpc_sphere.png`` (path, tracking error,
torques, solve time per period) and ``DIR/mpc_sphere.gif`` (the robot seen from
above chasing the target, the push drawn as an arrow; ``--no-animation`` skips it).

Usage: nhjax run mpc_sphere [--out DIR] [--laps 1] [--plant reduced|full] [--no-ipopt] [--no-animation]
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import controls
from controls.tasks import ReducedSteering, shell_push, sphere_steering_reduced, sphere_tracking
from nhjax.scenes import ShellWithTop

from ._peers import import_peers

PERIOD, INTERVALS, HORIZON = 0.05, 20, 1.0
PUSH_TIME, PUSH_DV = 5.0, (0.3, 0.0)  # [s], [m/s]
HEAVIER = 1.1  # the plant's top: mass and inertia


def setup(plant_kind="reduced"):
    """(robot, its tracking OCP, the MPC, the plant: the heavier robot in the reduced
    equations, or the whole heavier robot for ``plant_kind="full"``)."""
    robot = ShellWithTop()
    ocp = sphere_tracking(robot, horizon=HORIZON)
    mpc = controls.MPC(ocp, PERIOD, INTERVALS, mode="rti")
    heavy = ShellWithTop(mt=robot.mt * HEAVIER, It=np.asarray(robot.It) * HEAVIER)
    if plant_kind == "full":
        return robot, ocp, mpc, heavy
    plant = sphere_steering_reduced(heavy, (0.0, 0.0), HORIZON).system
    assert isinstance(plant, ReducedSteering)
    return robot, ocp, mpc, plant


def reduced_of(y):
    """The reduced state (omega, Omega in the top's axes, the rows gamma, alpha, beta of
    R_top, xy) of the whole robot's state ((xy, R_shell, R_top), (xy', Omega_body,
    omega_top))."""
    (xy, Rsh, Rt), v = y
    return jnp.concatenate([v[5:8], Rt.T @ (Rsh @ v[2:5]), Rt[2], Rt[0], Rt[1], xy])


def full_push(robot, dv):
    """The push of ``shell_push`` on the whole robot's state: the same change of the
    shell's angular velocity, dOmega = e3 x dv / Rs in the top's axes (dv in its x, y
    axes), with the centre's velocity from rolling, dV = dOmega_space x Rs e3."""
    Rs = float(robot.Rs)
    d_top = shell_push(robot, dv)[3:6]  # the reduced push: dOmega in the top's axes

    def push(y):
        (xy, Rsh, Rt), v = y
        dW = Rt @ d_top
        dV = jnp.cross(dW, jnp.array([0.0, 0.0, Rs]))
        return (xy, Rsh, Rt), v + jnp.concatenate([dV[:2], Rsh.T @ dW, jnp.zeros(3)])

    return push


def run_nhjax(periods, plant_kind="reduced"):
    robot, ocp, mpc, plant = setup(plant_kind)
    pushes = [(PUSH_TIME, shell_push(robot, PUSH_DV))]
    extra = {}
    if plant_kind == "full":
        x0 = np.asarray(ocp.x0)
        start = plant.initial_state(top_attitude=np.stack([x0[9:12], x0[12:15], x0[6:9]]))
        gap = float(np.abs(np.asarray(reduced_of(start)) - x0).max())
        assert gap < 1e-12, f"the whole robot's start is not the model's: {gap}"
        pushes = [(PUSH_TIME, full_push(robot, PUSH_DV))]
        extra = dict(measure=reduced_of)
    else:
        start = ocp.x0
    tic = time.perf_counter()
    loop = controls.closed_loop(mpc, plant, start, periods, pushes=pushes, timing=True, **extra)
    seconds = time.perf_counter() - tic
    ts = np.asarray(loop.trajectory.ts)
    xs = loop.trajectory.xs
    xs = np.asarray(xs) if plant_kind != "full" else np.asarray(jax.vmap(reduced_of)(xs))  # (the model's view)
    err = np.asarray(ocp.running_cost.error(ts, xs))
    return dict(ts=ts, xs=xs, us=np.asarray(loop.inputs), err=err, ms=np.asarray(loop.status.solve_ms),
                fallback=np.asarray(loop.status.fallback), qp_ok=np.asarray(loop.status.qp_ok),
                cost=float(loop.cost), seconds=seconds,
                drift={k: float(v) for k, v in loop.trajectory.constraint_drift.items()},
                ref=np.asarray(jax.vmap(ocp.running_cost.reference)(ts)))


def run_ipopt(periods):
    peers, why = import_peers("casadi_mpc_sphere", "casadi_steering")
    if peers is None:
        return None, why
    peer, ROBOT = peers[0], peers[1].ROBOT
    robot = ShellWithTop()
    tic = time.perf_counter()
    nlp = peer.build(N=INTERVALS, T=HORIZON)
    build = time.perf_counter() - tic
    heavy = dict(ROBOT, mt=ROBOT["mt"] * HEAVIER, It=(np.asarray(ROBOT["It"]) * HEAVIER).tolist())
    ts, xs, us, J, secs, stats = peer.closed_loop(nlp, heavy, periods, pushes=[(PUSH_TIME, shell_push(robot, PUSH_DV))])
    _, ocp, _, _ = setup()
    err = np.asarray(ocp.running_cost.error(ts, xs))
    return dict(ts=ts, xs=xs, us=us, err=err, ms=secs * 1e3, cost=J, build_seconds=build, statuses=stats), ""


def back_under(ts, err, after, level):
    """The first time after ``after`` from which the error stays below ``level`` [s]."""
    above = np.flatnonzero((ts > after) & (err >= level))
    return float(ts[above[-1] + 1] - after) if above.size and above[-1] + 1 < ts.size else (
        0.0 if not above.size else None)


def figure(r, ip, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 2, figsize=(11, 8))
    a = ax[0, 0]
    a.plot(r["ref"][:, 0], r["ref"][:, 1], "k--", lw=1, label="target r(t)")
    a.plot(r["xs"][:, 15], r["xs"][:, 16], lw=1.5, label="robot (nhjax MPC)")
    if ip:
        a.plot(ip["xs"][:, 15], ip["xs"][:, 16], lw=1, alpha=0.7, label="robot (CasADi + IPOPT MPC)")
    k = np.searchsorted(r["ts"], PUSH_TIME)
    a.plot(r["xs"][k, 15], r["xs"][k, 16], "rv", label=f"push at {PUSH_TIME:g} s")
    a.set(xlabel="x [m]", ylabel="y [m]", title="contact point", aspect="equal")
    a.legend(fontsize=8)
    a = ax[0, 1]
    a.semilogy(r["ts"], np.maximum(r["err"], 1e-6), label="nhjax")
    if ip:
        a.semilogy(ip["ts"], np.maximum(ip["err"], 1e-6), alpha=0.7, label="CasADi + IPOPT")
    a.axvline(PUSH_TIME, color="r", lw=0.8)
    a.axhline(0.02, color="k", ls=":", lw=0.8, label="2 cm")
    a.set(xlabel="t [s]", ylabel="|(x, y) - r(t)| [m]", title="tracking error")
    a.legend(fontsize=8)
    a = ax[1, 0]
    tu = r["ts"][:-1]
    for i in range(3):
        a.step(tu, r["us"][:, i], where="post", lw=1, label=f"tau_{i + 1}")
    a.set(xlabel="t [s]", ylabel="N m", title="internal torque (top axes)")
    a.legend(fontsize=8)
    a = ax[1, 1]
    a.plot(tu, r["ms"], ".", ms=2, label="nhjax (RTI)")
    if ip:
        a.plot(tu, ip["ms"], ".", ms=2, label="CasADi + IPOPT")
    a.set(xlabel="t [s]", ylabel="ms", yscale="log", title="solve time per period (after compile)")
    a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def animation(r, robot, path, frames=100, fps=10):
    """GIF of the closed loop seen from above: the shell (a circle of radius Rs about
    the contact point), its trail, the moving target on its figure-eight, the top's
    centre of mass (the offset R_top c projected on the plane, drawn at Rs/|c| scale so
    that its tilt shows) and, for a second after the push, an arrow from the shell's
    centre along the velocity change."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.animation import FuncAnimation, PillowWriter
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    ts, xs, ref, err = r["ts"], r["xs"], r["ref"], r["err"]
    xy = xs[:, 15:17]
    c = np.asarray(robot.c)
    # rows alpha, beta of R_top (state 9:12, 12:15): the plane components of R_top c
    bob = np.stack([xs[:, 9:12] @ c, xs[:, 12:15] @ c], 1) * (float(robot.Rs) / max(np.linalg.norm(c), 1e-12))
    Rs = float(robot.Rs)
    k_push = int(np.searchsorted(ts, PUSH_TIME))
    dv = np.asarray(PUSH_DV, float)
    # the push's velocity change along the top's x axis at that moment, in the plane
    alpha, beta = xs[k_push, 9:12], xs[k_push, 12:15]
    push_dir = np.array([alpha[0] * dv[0] + alpha[1] * dv[1], beta[0] * dv[0] + beta[1] * dv[1]])
    push_dir = push_dir / max(np.linalg.norm(push_dir), 1e-12)
    sel = np.unique(np.linspace(0, len(ts) - 1, frames).astype(int))

    fig = Figure(figsize=(5.2, 4.2))
    a = fig.add_subplot()
    pts = np.concatenate([xy, ref])
    lo, hi = pts.min(0) - 1.4 * Rs, pts.max(0) + 1.4 * Rs
    a.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), xlabel="x [m]", ylabel="y [m]", aspect="equal")
    a.plot(ref[:, 0], ref[:, 1], "k--", lw=0.8)
    trail, = a.plot([], [], "C0", lw=1.2)
    target, = a.plot([], [], "r*", ms=10)
    shell = Circle(tuple(xy[0]), Rs, fill=False, color="k")
    a.add_patch(shell)
    top, = a.plot([], [], "C1-o", ms=4, lw=2)
    arrow = a.annotate("", xy=(0, 0), xytext=(0, 0), arrowprops=dict(arrowstyle="-|>", color="r", lw=2),
                       annotation_clip=False)
    title = a.set_title("")
    a.text(0.02, 0.02, "red star: target r(t); orange: top's centre of mass; red arrow: push", fontsize=7,
           transform=a.transAxes)

    def draw(i):
        k = sel[i]
        trail.set_data(xy[:k + 1, 0], xy[:k + 1, 1])
        target.set_data([ref[k, 0]], [ref[k, 1]])
        shell.center = tuple(xy[k])
        top.set_data([xy[k, 0], xy[k, 0] + bob[k, 0]], [xy[k, 1], xy[k, 1] + bob[k, 1]])
        pushing = k_push <= k and ts[k] < PUSH_TIME + 1.0  # shown for a second
        arrow.set_visible(bool(pushing))
        if pushing:
            arrow.xy = tuple(xy[k] + Rs * push_dir)
            arrow.set_position(tuple(xy[k]))
        title.set_text(f"t = {ts[k]:5.2f} s   error {err[k] * 100:5.1f} cm" + ("   push" if pushing else ""))

    FuncAnimation(fig, draw, frames=len(sel)).save(path, writer=PillowWriter(fps=fps), dpi=72)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="mpc_sphere", help="folder for the outputs (default: ./mpc_sphere)")
    ap.add_argument("--laps", type=float, default=1.0, help="laps of the figure-eight (20 s each)")
    ap.add_argument("--plant", choices=("reduced", "full"), default="reduced",
                    help="the plant: the reduced equations (default) or the whole robot on SO(3) x SO(3)")
    ap.add_argument("--no-ipopt", action="store_true", help="skip the CasADi + IPOPT peer")
    ap.add_argument("--no-animation", action="store_true", help="skip the GIF")
    a = ap.parse_args()
    if not a.laps > PUSH_TIME / 20.0 + 0.1:
        ap.error("--laps must run past the push (more than 0.35)")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    periods = int(round(a.laps * 20.0 / PERIOD))
    load_start = os.getloadavg()
    r = run_nhjax(periods, a.plant)
    after = r["ts"] >= PUSH_TIME + 2.0
    info = dict(command="nhjax run mpc_sphere " + " ".join(sys.argv[1:]), periods=periods, period_s=PERIOD,
                horizon_s=HORIZON, intervals=INTERVALS, mode="rti", push_time_s=PUSH_TIME, push_dv_m_s=PUSH_DV,
                plant_top_scale=HEAVIER, plant=a.plant,
                period_ms_median=float(np.median(r["ms"])), period_ms_max=float(np.max(r["ms"])),
                period_ms_p95=float(np.percentile(r["ms"], 95)),
                closed_loop_cost=r["cost"], tracking_error_after_push_m=float(r["err"][after].max()),
                tracking_error_peak_after_push_m=float(r["err"][r["ts"] >= PUSH_TIME].max()),
                seconds_back_under_2cm=back_under(r["ts"], r["err"], PUSH_TIME, 0.02),
                fallbacks=int(r["fallback"].sum()), qp_failures=int((~r["qp_ok"]).sum()),
                loop_seconds_with_compile=r["seconds"], plant_constraint_drift=r["drift"])
    print(f"nhjax RTI: {np.median(r['ms']):.2f} ms median, {np.max(r['ms']):.2f} ms max per period; "
          f"closed-loop cost {r['cost']:.6g}; error after push + 2 s <= {info['tracking_error_after_push_m'] * 100:.2f} cm"
          f" (peak {info['tracking_error_peak_after_push_m'] * 100:.1f} cm); fallbacks {info['fallbacks']}")
    ip = None
    if not a.no_ipopt:
        ip, why = run_ipopt(periods)
        if ip is None:
            print(f"IPOPT peer skipped: {why}")
            info["casadi_skipped"] = why
        else:
            info.update(casadi_period_ms_median=float(np.median(ip["ms"])), casadi_period_ms_max=float(np.max(ip["ms"])),
                        casadi_closed_loop_cost=ip["cost"],
                        casadi_tracking_error_after_push_m=float(ip["err"][ip["ts"] >= PUSH_TIME + 2.0].max()),
                        casadi_build_seconds=ip["build_seconds"],
                        casadi_not_solved=int(sum(s != "Solve_Succeeded" for s in ip["statuses"])),
                        speedup_vs_casadi=float(np.median(ip["ms"]) / np.median(r["ms"])),
                        cost_rel_diff_vs_casadi=float((r["cost"] - ip["cost"]) / ip["cost"]))
            print(f"CasADi + IPOPT: {info['casadi_period_ms_median']:.2f} ms median per period; closed-loop cost "
                  f"{ip['cost']:.6g} ({info['cost_rel_diff_vs_casadi']:+.2%} for nhjax); nhjax per period "
                  f"{info['speedup_vs_casadi']:.1f}x faster")
    load_end = os.getloadavg()
    info.update(load_average=[load_start[0], load_end[0]], load_average_start=list(load_start),
                load_average_end=list(load_end))
    (out / "mpc_sphere.json").write_text(json.dumps(info, indent=1))
    figure(r, ip, out / "mpc_sphere.png")
    if not a.no_animation:
        animation(r, ShellWithTop(), out / "mpc_sphere.gif")
    print(f"load average {load_start[0]:.2f} -> {load_end[0]:.2f}; wrote {out}/mpc_sphere.json, .png"
          + ("" if a.no_animation else " and .gif"))


if __name__ == "__main__":
    main()
