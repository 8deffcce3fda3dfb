"""Spherical-robot steering (design card, issue 5): ShellWithTop from rest at the origin
to rest at a target, minimizing the internal-torque effort int |tau|^2 dt.

Default robot (nhjax.scenes.ShellWithTop(): shell ms = 1 kg, Rs = 0.2 m; top mt = 2 kg,
It = diag(0.01, 0.012, 0.008) kg m^2, centre of mass 0.08 m below the hinge), target
(0.5, 0.3) m, T = 3 s: about five periods of the top's pendulum modes (9.4 and 10.0
rad/s), a peak tilt of ~15 degrees.

Method: direct single shooting over Chebyshev controls (degree 12 per torque
component, 39 parameters) with ``controls.tasks.solve_direct_newton`` (feasible-path
Newton: Gauss-Newton restoration onto the terminal constraints, Newton tangent steps
with the Lagrangian's Hessian by differences of reverse-mode gradients), started from
the minimum-effort control of the problem linearized at rest (``linear_guess``).

The optimum is re-simulated at rtol = atol = 1e-12 and checked: terminal position and
velocities, the rolling residual along the whole motion, Chaplygin's vector balance
K(t) - K(0) = -int R_top tau dt, and energy - work.

Pontryagin (unless --no-pontryagin): the same problem on the reduced vector state
(``sphere_steering_reduced``: ShellWithTopReduced's hand-derived equations, no shell
attitude), indirect single shooting with Levenberg–Marquardt from the costates of the
direct optimum (``controls.pmp_residual``); its cost is the continuous optimum, a
lower bound for every parametrization.

Writes steer_sphere.{png,json,gif} to ``--out`` (default: ./steer_sphere/).
Usage: nhjax run steer_sphere [--target X Y] [--T SEC] [--degree N] [--heading RAD]
       [--no-pontryagin] [--out DIR]
"""

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import controls
from controls.tasks import (
    linear_guess,
    rolling_residual,
    simulate_with_impulse,
    solve_direct_newton,
    sphere_steering,
    sphere_steering_reduced,
    top_heading,
)
from controls import newton as nt
from nhjax.scenes import ShellWithTop

OUT = Path("steer_sphere")  # under the working directory


def warm_up(ocp, param, z, rtol):
    """Compile (first call of) every function the solver runs; returns the seconds spent."""
    t0 = time.perf_counter()
    sh = nt._Shooting(ocp, param, jnp.asarray(rtol, float), jnp.asarray(rtol, float))
    w = jnp.ones(ocp.n_constraints + 1)
    jax.block_until_ready(nt._values_jit(sh, z))
    jax.block_until_ready(nt._values_and_jacobian(sh, z))
    # the reduced Hessian differences the gradient along the P - m null-space directions
    jax.block_until_ready(nt._lagrangian_gradients(sh, jnp.stack([z] * (z.shape[0] - ocp.n_constraints)), w))
    jax.block_until_ready(nt._control_cost_hessian(ocp, param, z))
    return time.perf_counter() - t0


def main(target=(0.5, 0.3), T=3.0, degree=12, heading=None, out=OUT, rtol=1e-10, pontryagin=True):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    robot = ShellWithTop()
    ocp = sphere_steering(robot, target, T, heading=heading)
    param = controls.Chebyshev(degree, T, 3)

    t0 = time.perf_counter()
    guess = linear_guess(ocp, param)
    t_guess = time.perf_counter() - t0
    t_compile = warm_up(ocp, param, guess, rtol)
    res = solve_direct_newton(ocp, param, guess, rtol=rtol, atol=rtol, ctol=1e-10, gtol=1e-7, verbose=True)
    print(f"direct (feasible-path Newton, Chebyshev degree {degree}, {param.size} parameters): {res.message}")
    print(f"  cost int |tau|^2 dt = {res.cost:.12g} N^2 m^2 s   violation {res.violation:.2e}   "
          f"stationarity {res.history['stationarity'][-1]:.2e}   iterations {res.iterations}")
    print(f"  wall time after compile {res.seconds:.1f} s   compile {t_compile:.1f} s   "
          f"linear guess {t_guess:.1f} s (its compile included)")

    # ------------------------------------------------------- tight re-simulation and checks
    n_save = 601
    t0 = time.perf_counter()
    traj = simulate_with_impulse(ocp, res.control, saveat=n_save)
    t_check = time.perf_counter() - t0
    x, impulse = traj.xs
    (xy, Rsh, Rt), v = x
    ts = np.asarray(traj.ts)
    us = np.asarray(jax.vmap(lambda t: res.control(t, None))(traj.ts))
    roll = np.asarray(rolling_residual(robot, x, traj.ts))
    K = jax.vmap(lambda a, b, c, w: robot.chaplygin_vector(((a, b, c), w)))(xy, Rsh, Rt, v)
    tilt = np.degrees(np.arccos(np.clip(np.asarray(Rt[:, 2, 2]), -1.0, 1.0)))
    x_end = jax.tree_util.tree_map(lambda a: a[-1], x)
    summary = {
        "target_m": list(map(float, target)), "T_s": T, "heading_rad": heading,
        "parametrization": f"Chebyshev degree {degree} x 3 ({param.size} parameters)",
        "solver": "controls.tasks.solve_direct_newton", "converged": res.converged, "message": res.message,
        "cost_N2m2s": res.cost, "constraint_violation": res.violation,
        "stationarity": res.history["stationarity"][-1], "iterations": res.iterations,
        "cost_history": res.history["cost"], "stationarity_history": res.history["stationarity"],
        "wall_s_after_compile": res.seconds, "compile_s": t_compile, "linear_guess_s": t_guess,
        "guess_cost_linearized_problem": float(np.trapezoid(
            (np.asarray(jax.vmap(lambda t: param.signal(guess)(t, None))(traj.ts)) ** 2).sum(1), ts)),
        "check_rtol": 1e-12, "check_saved_points": n_save, "check_simulate_s": t_check,
        "final_position_error_m": float(jnp.linalg.norm(xy[-1] - jnp.asarray(target))),
        "final_max_abs_velocity": float(jnp.max(jnp.abs(v[-1]))),
        "final_top_vertical_error": float(jnp.linalg.norm(Rt[-1][2] - jnp.array([0.0, 0.0, 1.0]))),
        "final_top_heading_rad": float(top_heading(ocp, x_end)),
        "max_rolling_residual_m_per_s": float(np.abs(roll).max()),
        "chaplygin_balance_error": float(jnp.max(jnp.abs(K - K[0] + impulse))),
        "net_torque_impulse_space": np.asarray(impulse[-1]).tolist(),
        "energy_minus_work_drift_J": float(traj.invariant_drift["energy - work"]),
        "net_work_J": float(traj.work[-1]), "max_work_J": float(np.abs(np.asarray(traj.work)).max()),
        "max_tilt_deg": float(tilt.max()), "max_speed_m_per_s": float(jnp.max(jnp.linalg.norm(v[:, :2], axis=1))),
        "max_abs_torque_Nm": np.abs(us).max(0).tolist(),
        "total_s": time.perf_counter() - t_all,
    }
    print(f"  check at rtol 1e-12 ({n_save} points): |xy(T) - target| = {summary['final_position_error_m']:.1e} m, "
          f"max |v(T)| = {summary['final_max_abs_velocity']:.1e}, max rolling residual "
          f"{summary['max_rolling_residual_m_per_s']:.1e} m/s, Chaplygin balance {summary['chaplygin_balance_error']:.1e}, "
          f"energy - work drift {summary['energy_minus_work_drift_J']:.1e} J, net work {summary['net_work_J']:.1e} J")
    print(f"  peak tilt of the top {summary['max_tilt_deg']:.1f} deg, peak speed {summary['max_speed_m_per_s']:.3f} m/s")

    ind = None
    if pontryagin:
        ind = indirect(robot, target, T, heading, res, summary)
    figures(robot, ocp, target, ts, xy, Rt, v, us, tilt, summary, out, ind)
    summary["total_s"] = time.perf_counter() - t_all
    with open(out / "steer_sphere.json", "w") as f:
        json.dump(summary, f, indent=1)
    print(f"wrote {out / 'steer_sphere.png'}, {out / 'steer_sphere.json'}, {out / 'steer_sphere.gif'} "
          f"({summary['total_s']:.0f} s in all)")
    return summary


def indirect(robot, target, T, heading, res, summary):
    """Pontryagin on the reduced vector state, from the direct optimum's costates."""
    red = sphere_steering_reduced(robot, target, T, heading=heading)
    t0 = time.perf_counter()
    _, J_red, psi_red = controls.rollout(red, res.control, rtol=1e-12, atol=1e-12)
    pmp = controls.pmp_residual(red, res.control, rtol=1e-10, atol=1e-10)
    t_pmp = time.perf_counter() - t0
    ind = controls.solve_pontryagin(red, pmp["ps"][-1], pmp["multipliers"], solver="lm", rtol=1e-11,
                                    atol=1e-11, tol=1e-10, max_steps=60)
    u_dir = np.asarray(jax.vmap(lambda t: res.control(t, None))(jnp.asarray(ind.trajectory.ts)))
    summary.update({
        "reduced_replay_cost": float(J_red), "reduced_replay_violation": float(jnp.max(jnp.abs(psi_red))),
        "direct_pmp_stationarity": pmp["stationarity"],
        "direct_pmp_hamiltonian_variation": pmp["hamiltonian_variation"],
        "pontryagin_converged": ind.converged, "pontryagin_cost": ind.cost,
        "pontryagin_violation": ind.violation, "pontryagin_shooting_residual": ind.residual,
        "pontryagin_iterations": ind.iterations, "pontryagin_s_with_compile": ind.seconds,
        "pmp_residual_s_with_compile": t_pmp,
        "direct_minus_pontryagin_cost_relative": (res.cost - ind.cost) / ind.cost,
        "max_control_difference_Nm": float(np.abs(u_dir - ind.controls).max()),
    })
    print(f"  replay on the reduced hand-derived equations: cost {float(J_red):.12g}, "
          f"violation {summary['reduced_replay_violation']:.1e}")
    print(f"pontryagin (reduced vector state, LM from the direct costates): {ind.message}, cost {ind.cost:.12g}, "
          f"violation {ind.violation:.1e}, residual {ind.residual:.1e}, {ind.iterations} iterations, "
          f"{ind.seconds:.1f} s with compile")
    print(f"  direct - pontryagin = {res.cost - ind.cost:.3e} ({summary['direct_minus_pontryagin_cost_relative']:.2e} "
          f"relative; the Chebyshev controls are a restriction), max |u_direct - u_pontryagin| = "
          f"{summary['max_control_difference_Nm']:.2e} N m")
    return ind


def figures(robot, ocp, target, ts, xy, Rt, v, us, tilt, summary, out, ind=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

    xy, Rt, v = np.asarray(xy), np.asarray(Rt), np.asarray(v)
    Rs = float(robot.Rs)
    c = np.asarray(robot.c)
    bob = np.einsum("nij,j->ni", Rt, c)  # hinge -> top's centre of mass, space axes [m]
    fwd = np.einsum("nij,j->ni", Rt, np.asarray(ocp.terminal_constraints.forward))

    fig, ax = plt.subplots(3, 2, figsize=(11, 11.5))
    a = ax[0, 0]
    a.plot(xy[:, 0], xy[:, 1], "C0", label="contact point")
    a.plot(xy[:, 0] + bob[:, 0], xy[:, 1] + bob[:, 1], "C1", lw=0.8, label="top's centre of mass (plan)")
    a.plot(0, 0, "ko", label="start")
    a.plot(*target, "r*", ms=12, label="target")
    for k in np.linspace(0, len(xy) - 1, 7).astype(int):
        a.add_patch(plt.Circle(xy[k], Rs, fill=False, color="0.6", lw=0.7))
    a.set_aspect("equal")
    a.set_xlabel("x [m]")
    a.set_ylabel("y [m]")
    a.legend(fontsize=8, loc="upper left")
    a.set_title(f"path, T = {summary['T_s']:g} s, cost {summary['cost_N2m2s']:.6g} N$^2$m$^2$s")
    a = ax[0, 1]
    for i in range(3):
        a.plot(ts, us[:, i], label=f"$\\tau_{i + 1}$ (top axes)")
    if ind is not None:
        t_ind = np.asarray(ind.trajectory.ts)
        for i in range(3):
            a.plot(t_ind, ind.controls[:, i], "k:", lw=1, label="Pontryagin" if i == 0 else None)
    a.set_xlabel("t [s]")
    a.set_ylabel("torque [N m]")
    a.legend(fontsize=8)
    a.set_title("optimal internal torque")
    a = ax[1, 0]
    a.plot(ts, v[:, 0], label="$\\dot x$ [m/s]")
    a.plot(ts, v[:, 1], label="$\\dot y$ [m/s]")
    a.plot(ts, np.linalg.norm(v[:, 2:5], axis=1) * Rs, label="$R_s|\\Omega|$ [m/s]", ls="--")
    a.plot(ts, np.linalg.norm(v[:, 5:8], axis=1), label="$|\\omega|$ top [rad/s]")
    a.set_xlabel("t [s]")
    a.legend(fontsize=8)
    a.set_title("velocities (all vanish at T)")
    a = ax[1, 1]
    a.plot(ts, tilt, label="tilt of the top [deg]")
    a.plot(ts, np.degrees(np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0]))), label="top's heading [deg]")
    a.set_xlabel("t [s]")
    a.legend(fontsize=8)
    a.set_title("top attitude")
    # costates of the Pontryagin extremal (reduced state: omega, Omega in the top's axes,
    # ..., xy); the optimal torque is u* = -(1/2) B(x)^T p, built from p_omega and p_Omega
    if ind is not None:
        t_ind = np.asarray(ind.trajectory.ts)
        n = ind.trajectory.xs.shape[1] // 2
        p = np.asarray(ind.trajectory.xs)[:, n:]
        for k, (a, sl, name) in enumerate(((ax[2, 0], slice(0, 3), "\\omega"), (ax[2, 1], slice(3, 6), "\\Omega"))):
            for i in range(3):
                a.plot(t_ind, p[:, sl][:, i], label=f"$p_{{{name}_{i + 1}}}$")
            a.set_xlabel("t [s]")
            a.set_ylabel("costate [N$^2$m$^2$s$^2$/rad]")
            a.legend(fontsize=8)
        ax[2, 0].set_title("costates of the top's angular velocity (Pontryagin)")
        ax[2, 1].set_title("costates of the shell's angular velocity")
        ax[2, 1].text(0.02, 0.02, f"$p_{{xy}}$ = ({p[0, -2]:.3g}, {p[0, -1]:.3g}) (constant)", fontsize=8,
                      transform=ax[2, 1].transAxes)
    else:
        for a in ax[2]:
            a.text(0.5, 0.5, "costates: run with Pontryagin", ha="center", transform=a.transAxes)
            a.set_axis_off()
    fig.tight_layout()
    fig.savefig(out / "steer_sphere.png", dpi=110)
    plt.close(fig)

    # animation: the robot seen from above (shell circle, the top's pendulum and heading)
    frames = np.linspace(0, len(ts) - 1, 60).astype(int)
    fig, a = plt.subplots(figsize=(5.0, 4.0))
    lo = np.minimum(xy.min(0), [0, 0]) - 1.3 * Rs
    hi = np.maximum(xy.max(0), target) + 1.3 * Rs
    a.set_xlim(lo[0], hi[0])
    a.set_ylim(lo[1], hi[1])
    a.set_aspect("equal")
    a.plot(*target, "r*", ms=10)
    a.set_xlabel("x [m]")
    a.set_ylabel("y [m]")
    trail, = a.plot([], [], "C0", lw=1)
    shell = plt.Circle(xy[0], Rs, fill=False, color="k")
    a.add_patch(shell)
    pend, = a.plot([], [], "C1-o", ms=4, lw=2)
    head, = a.plot([], [], "C2-", lw=1.5)
    title = a.set_title("")
    scale = Rs / np.linalg.norm(c) if np.linalg.norm(c) > 0 else 1.0

    def draw(k):
        trail.set_data(xy[: k + 1, 0], xy[: k + 1, 1])
        shell.center = tuple(xy[k])
        pend.set_data([xy[k, 0], xy[k, 0] + scale * bob[k, 0]], [xy[k, 1], xy[k, 1] + scale * bob[k, 1]])
        head.set_data([xy[k, 0], xy[k, 0] + 0.8 * Rs * fwd[k, 0]], [xy[k, 1], xy[k, 1] + 0.8 * Rs * fwd[k, 1]])
        title.set_text(f"t = {ts[k]:.2f} s   tilt {tilt[k]:.1f} deg")
        return trail, shell, pend, head, title

    a.text(0.02, 0.02, "orange: top's centre of mass (tilt x Rs/|c|)\ngreen: top's heading", fontsize=7,
           transform=a.transAxes)
    fig.tight_layout()
    anim = FuncAnimation(fig, draw, frames=frames, blit=False)
    anim.save(out / "steer_sphere.gif", writer=PillowWriter(fps=15), dpi=72)
    plt.close(fig)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--target", type=float, nargs=2, default=(0.5, 0.3), help="target (x, y) [m]")
    ap.add_argument("--T", type=float, default=3.0, help="horizon [s]")
    ap.add_argument("--degree", type=int, default=12, help="Chebyshev degree of each torque component")
    ap.add_argument("--heading", type=float, default=None, help="final yaw of the top [rad] (optional)")
    ap.add_argument("--no-pontryagin", action="store_true", help="skip the indirect method")
    ap.add_argument("--out", type=Path, default=OUT, help="folder for the outputs (default: ./steer_sphere)")
    a = ap.parse_args()
    main(target=tuple(a.target), T=a.T, degree=a.degree, heading=a.heading, out=a.out,
         pontryagin=not a.no_pontryagin)
