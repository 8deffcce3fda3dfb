"""The somersault tasks of the controls package, each solved by both methods.

1. chart: velocity-controlled, Iwai's chart, chi winds once, psi turns by -pi
   (Pontryagin by continuation in the turn from the fixed-theta loop, then the
   direct method from that loop);
2. torque: torque-controlled (7.14)-(7.15), rest to rest, psi turns by -pi,
   least int |u|^2 (direct from the fixed-theta twist, then Pontryagin from the
   direct optimum's costates).

For each: final cost of both methods and their relative difference, terminal
violation, iterations, wall time after compile and time with compile (the first
solve); a figure (trajectory, controls of both methods, costates), a JSON
summary and an animation in ``--out`` (default: ./somersault_tasks/). (The free-winding problem in
smooth coordinates is what `nhjax demo` runs.)

Usage: nhjax run somersault_tasks [--out DIR] [--no-animation]
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
    fixed_theta_costates,
    torque_loop_guess,
    torque_somersault,
    velocity_somersault_chart,
)
from nhjax import plotting
from nhjax.scenes import FallingCat, FallingCatKinematic

TH0, T, TURN = 0.6, 2.0, -np.pi


def timed(fn):
    t = time.perf_counter()
    r = fn()
    return r, time.perf_counter() - t


def figure(name, ts, xs, us, ps, us_direct, ulabel, path):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 7.5), layout="constrained")
    ax = fig.add_subplot(2, 2, 1, projection="polar")
    ax.plot(xs[:, 1], xs[:, 0], color="tab:purple")
    ax.plot(xs[0, 1], xs[0, 0], "ko", label="start")
    ax.set_rmax(1.15 * xs[:, 0].max())
    ax.set_title(r"(a) shape path: radius $\theta$, angle $\chi$ [rad]", size=10)
    ax.legend(loc="lower left", bbox_to_anchor=(-0.2, -0.1), fontsize=8)
    ax = fig.add_subplot(2, 2, 2)
    for k, lab in enumerate((r"$\theta$", r"$\chi$", r"$\psi$")):
        ax.plot(ts, xs[:, k], label=lab)
    ax.set(xlabel="t [s]", ylabel="[rad]", title="(b) Iwai's chart coordinates")
    ax.legend()
    ax = fig.add_subplot(2, 2, 3)
    for k in range(us.shape[1]):
        ax.plot(ts, us[:, k], label=f"$u_{k + 1}$ Pontryagin")
        ax.plot(ts, us_direct[:, k], "k--", lw=0.8, label="direct" if k == 0 else None)
    ax.set(xlabel="t [s]", ylabel=ulabel, title="(c) optimal controls")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(2, 2, 4)
    for k in range(ps.shape[1]):
        ax.plot(ts, ps[:, k], label=f"$p_{k + 1}$")
    ax.set(xlabel="t [s]", ylabel="costate", title="(d) costates of the extremal")
    ax.legend(fontsize=8)
    for a in fig.axes[1:]:
        a.grid(alpha=0.3)
    fig.suptitle(name)
    fig.savefig(path, dpi=110)


def report(name, ocp, direct, d_first, d_again, ind, i_first, i_again, res):
    s = dict(
        task=name, cost_direct=direct.cost, cost_pontryagin=ind.cost,
        cost_relative_difference=abs(direct.cost - ind.cost) / abs(ind.cost),
        violation_direct=direct.violation, violation_pontryagin=ind.violation,
        iterations_direct=direct.iterations, iterations_pontryagin=ind.iterations,
        seconds_direct_first=d_first, seconds_direct_after_compile=d_again,
        seconds_pontryagin_first=i_first, seconds_pontryagin_after_compile=i_again,
        stationarity_of_direct=res["stationarity"],
    )
    print(f"{name}:")
    for k, v in s.items():
        if k != "task":
            print(f"  {k:34s} {v:.12g}" if isinstance(v, float) else f"  {k:34s} {v}")
    return s


def chart_task():
    cat = FallingCatKinematic()
    loop_turn = float(-2 * np.pi * cat.f(TH0))
    p0, nu = fixed_theta_costates(cat, TH0, T)

    def indirect():
        def solve(v, z):
            return controls.solve_pontryagin(velocity_somersault_chart(cat, TH0, v, T), *(z or (p0, nu)))

        return controls.continuation(solve, np.linspace(loop_turn, TURN, 4))[-1]

    ind, i_first = timed(indirect)
    _, i_again = timed(indirect)
    ocp = velocity_somersault_chart(cat, TH0, TURN, T)
    param = controls.Chebyshev(10, T, 2)
    guess = param.fit(lambda t: jnp.array([0.0, 2 * np.pi / T]))
    d, d_first = timed(lambda: controls.solve_direct(ocp, param, guess))
    _, d_again = timed(lambda: controls.solve_direct(ocp, param, guess))
    res = controls.pmp_residual(ocp, d.control)
    return cat, ocp, d, d_first, d_again, ind, i_first, i_again, res


def torque_task():
    cat = FallingCat.from_dimensions(1.0, 1.0, 0.25)
    ocp = torque_somersault(cat, TH0, TURN, T)
    param = controls.Chebyshev(12, T, 2)
    guess = torque_loop_guess(cat, param, TH0, T)
    d, d_first = timed(lambda: controls.solve_direct(ocp, param, guess, progress=True))
    _, d_again = timed(lambda: controls.solve_direct(ocp, param, guess))
    res = controls.pmp_residual(ocp, d.control)
    ind, i_first = timed(lambda: controls.solve_pontryagin(ocp, res["ps"][-1], res["multipliers"]))
    _, i_again = timed(lambda: controls.solve_pontryagin(ocp, res["ps"][-1], res["multipliers"]))
    return cat, ocp, d, d_first, d_again, ind, i_first, i_again, res


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="somersault_tasks", help="folder for the outputs (default: ./somersault_tasks)")
    ap.add_argument("--no-animation", action="store_true")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    geo = FallingCat.from_dimensions(1.0, 1.0, 0.25)
    summaries = []
    for name, task, ulabel in (("chart", chart_task, "shape velocity [rad/s]"),
                               ("torque", torque_task, "torque [N m]")):
        cat, ocp, d, d_first, d_again, ind, i_first, i_again, res = task()
        summaries.append(report(name, ocp, d, d_first, d_again, ind, i_first, i_again, res))
        n = ocp.x0.shape[0]
        ts = np.asarray(ind.trajectory.ts)
        xs, ps = np.asarray(ind.trajectory.xs[:, :n]), np.asarray(ind.trajectory.xs[:, n:])
        us_direct = np.asarray(jax.vmap(lambda t: d.control(t, None))(jnp.asarray(ts)))
        figure(f"somersault, {name} task: cost {ind.cost:.10f} (Pontryagin), {d.cost:.10f} (direct)",
               ts, xs, np.asarray(ind.controls), ps, us_direct, ulabel, out / f"somersault_{name}.png")
        if not a.no_animation:
            plotting.somersault_animation(geo, ts, xs[:, :3], out / f"somersault_{name}.gif", frames=30)
    (out / "somersault_tasks.json").write_text(json.dumps(summaries, indent=2))
    kinds = "{png,gif}" if not a.no_animation else "png"
    print(f"wrote {out}/somersault_{{chart,torque}}.{kinds} and somersault_tasks.json")


if __name__ == "__main__":
    main()
