"""The falling cat's optimal somersault, optimized then shown (``nhjax demo``).

Task (seed 000, sec. 7; ``controls.tasks``): the velocity-controlled cat starts
bent by theta0, returns to that shape after T and has turned by ``turn`` about
e2 at zero angular momentum with the least vibrational energy (4.8). The best
direct optimum is polished by Pontryagin shooting and the two costs compared;
then the motion is shown in 3-D. Writes optimal_somersault.{json,png,gif} and
optimal_somersault_3d.png to ``--out`` (default: ./optimal_somersault/).

This lives in experiments/ rather than in the ``nhjax`` package because it uses
``controls``: the simulator imports nothing from the optimal-control layer.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from nhjax.lie import so3
from nhjax.scenes import FallingCat
from nhjax.scenes.falling_cat import FallingCatSmooth


def _timed(fn):
    t = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t


def optimal_somersault(out="optimal_somersault", figures=True, theta0=0.6, T=2.0, turn=np.pi,
                       start_windings=(1, 0, -1)):
    """``nhjax demo``: optimize the somersault, then show it.

    Task (seed 000, sec. 7; ``controls.tasks``): the velocity-controlled cat
    (cylinders of 1 kg, 1 m, radius 0.25 m) starts bent by ``theta0`` [rad],
    returns to that shape after ``T`` [s] and has turned by ``turn`` [rad] about
    e2, at zero angular momentum, with the least vibrational energy (4.8). It is
    posed in coordinates smooth at the straight cat, so the optimizer chooses how
    often the twist chi winds; several starting loops are tried (one that does not
    wind at all). The best direct optimum (Chebyshev inputs, augmented Lagrangian)
    is polished by Pontryagin shooting from its own costates, and the two costs
    are compared. Then the optimal motion is shown: the turn, the rotation of a
    cylinder and the total angular momentum computed in 3-D from the two bodies,
    figures, an animation and a JSON summary in ``out``.
    """
    from controls.tasks import smooth_to_chart, somersault_free_winding

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    geo = FallingCat.from_dimensions(mass=1.0, length=1.0, radius=0.25)
    cat = FallingCatSmooth(geo.I1, geo.lam, geo.B, geo.mass)
    print("nhjax demo: the falling cat's optimal somersault (least vibrational energy, zero angular momentum)")
    print(
        f"  cylinders: mass 1 kg, length 1 m, radius 0.25 m -> I1 = {float(geo.I1):.5f} kg m^2, "
        f"lam = {float(geo.lam):.5f}, B = {float(geo.B):.5f}"
    )
    print(f"  task: start and end bent by theta0 = {theta0} rad, turn by {turn:.6f} rad about e2 in T = {T} s")
    print(f"  optimizing from {len(start_windings)} starting loops (chi winding {start_windings}); "
          "the first solve compiles (seconds; a new process loads the compiled programs) ...", flush=True)
    r = somersault_free_winding(cat, theta0, turn, T, start_windings=start_windings)
    print("  start winding | target class j | cost [J s]       | violation | iterations | found winding | min theta | time [s]")
    for s in r.starts:
        print(f"  {s['start_winding']:13d} | {s['j']:15d} | {s['cost']:.12f} | {s['violation']:9.1e} | "
              f"{s['iterations']:10d} | {s['winding']:+13.6f} | {s['min_theta']:9.4f} | {s['seconds']:8.2f}")
    ind = r.indirect
    ocp = r.ocp
    print(f"  best: winding {r.winding:+.6f}; direct cost {r.best.cost:.12f}, Pontryagin cost {ind.cost:.12f} "
          f"(relative difference {r.cost_agreement:.1e})")
    print(f"  terminal violation: direct {r.best.violation:.1e}, Pontryagin {ind.violation:.1e}; "
          f"Pontryagin shooting residual {ind.residual:.1e} after {ind.iterations} Newton steps; "
          f"stationarity of the direct optimum {r.stationarity:.1e}")
    from controls import solve_pontryagin

    # the polish's own program (quick=True, compiled for the polish): a solve from its answer
    again, t_pmp = _timed(lambda: solve_pontryagin(ocp, ind.p0, ind.nu, quick=True, progress=False))
    print(f"  Pontryagin solve after compile (the polish's program, from its answer): {t_pmp * 1e3:.1f} ms; "
          f"whole optimization {r.seconds:.1f} s (compile included)")

    # ---- show: the optimal motion in Iwai's chart and in 3-D
    ts = np.asarray(ind.trajectory.ts)
    xs = jnp.asarray(ind.trajectory.xs[:, :3])
    ps = np.asarray(ind.trajectory.xs[:, 3:])
    us = jnp.asarray(ind.controls)
    qs = smooth_to_chart(xs)

    def qdot(x, u, q):
        w = x[:2]
        th2 = w @ w
        k, _, _ = cat.coefficients(w)
        chid = (w[0] * u[1] - w[1] * u[0]) / th2
        return jnp.stack([w @ u / jnp.sqrt(th2), chid, k * (w[0] * u[1] - w[1] * u[0]) - chid])

    qds = jax.vmap(qdot)(xs, us, qs)
    Ls = jax.vmap(geo.angular_momentum_3d)(qs, qds)
    L_max = float(jnp.max(jnp.abs(Ls)))
    scale = float(jnp.max(jnp.abs(jax.vmap(lambda q, qd: geo.kinetics().angular_momentum(q, qd * jnp.array([1.0, 1.0, 0.0])))(qs, qds))))
    R0, R1 = geo.poses(qs[0])[0][0], geo.poses(qs[-1])[0][0]
    rot = np.asarray(so3.log(R1 @ R0.T))
    angle = float(np.linalg.norm(rot))
    axis_off = float(np.linalg.norm(rot / angle - np.sign(rot[1]) * np.array([0.0, 1.0, 0.0])))
    psi_turn = float(qs[-1, 2] - qs[0, 2])
    print(f"  shape returns: |w(T) - w(0)| = {float(jnp.linalg.norm(xs[-1, :2] - xs[0, :2])):.1e} rad; "
          f"psi turns by {psi_turn:+.12f} rad, the target modulo 2 pi (chi wound {float(qs[-1, 1] - qs[0, 1]) / (2 * np.pi):+.6f} times)")
    print(f"  cylinder 1 rotates by {angle:.12f} rad about an axis {axis_off:.1e} off e2 (from its 3-D attitudes)")
    print(f"  total angular momentum of the two cylinders in 3-D: <= {L_max:.1e} kg m^2/s "
          f"(shape motion alone would carry {scale:.2f})")
    summary = dict(
        theta0=theta0, T=T, turn=turn, starts=r.starts, winding=r.winding, min_theta=r.min_theta,
        cost_direct=r.best.cost, cost_pontryagin=ind.cost, cost_agreement=r.cost_agreement,
        violation_direct=r.best.violation, violation_pontryagin=ind.violation,
        shooting_residual=ind.residual, stationarity_direct=r.stationarity,
        pontryagin_iterations=ind.iterations, pontryagin_seconds_after_compile=t_pmp,
        optimization_seconds_with_compile=r.seconds, psi_turn=psi_turn, cylinder_rotation=angle,
        rotation_axis_off_e2=axis_off, angular_momentum_max=L_max,
    )
    (out / "optimal_somersault.json").write_text(json.dumps(summary, indent=2))
    if figures:
        from types import SimpleNamespace

        from nhjax import plotting

        us_direct = np.asarray(jax.vmap(lambda t: r.best.control(t, None))(jnp.asarray(ts)))
        plotting.optimal_somersault_figure(ts, qs, us, ps, us_direct, turn=psi_turn,
                                           path=out / "optimal_somersault.png")
        plotting.somersault_figure(geo, SimpleNamespace(ts=ts, xs=np.asarray(qs)),
                                   path=out / "optimal_somersault_3d.png")
        print("  writing the animation ...", flush=True)
        plotting.somersault_animation(geo, ts, qs, out / "optimal_somersault.gif")
        print(f"  figures: {out / 'optimal_somersault.png'}, {out / 'optimal_somersault_3d.png'}, "
              f"{out / 'optimal_somersault.gif'}")
    return summary


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="optimal_somersault", help="folder for the figures and the JSON (default: ./optimal_somersault)")
    ap.add_argument("--no-figures", action="store_true")
    ap.add_argument("--theta0", type=float, default=0.6, help="bend at start and end [rad]")
    ap.add_argument("--T", type=float, default=2.0, help="duration [s]")
    ap.add_argument("--turn", type=float, default=np.pi, help="turn about e2 [rad]")
    a = ap.parse_args(argv)
    optimal_somersault(out=a.out, figures=not a.no_figures, theta0=a.theta0, T=a.T, turn=a.turn)


if __name__ == "__main__":
    main()
