"""The demos behind ``nhjax demo``.

``optimal_somersault`` (the default): optimize the somersault, then show it
(see its docstring).

``somersault``: the falling cat turns by pi at zero angular momentum. The shape
loop (bend, twist once, unbend) is chosen from the closed-form holonomy
-2 pi f(theta1) so that psi turns by exactly pi; the torques come from the
inverse of (7.14). The run reports the achieved turn against the closed form,
the total angular momentum of the two cylinders computed in 3-D (from the
chart, and from attitudes integrated on SO(3) with RKMK), the work-energy
balance, and the time, and writes figures to ``out``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .integrate import simulate
from .lie import so3
from .scenes import FallingCat, ShapeLoopTorque


def _timed(fn):
    t = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t


def somersault(out="experiments/out", rtol=1e-10, atol=1e-10, figures=True, turn=np.pi):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cat = FallingCat.from_dimensions(mass=1.0, length=1.0, radius=0.25)
    loop = ShapeLoopTorque.for_turn(cat, turn, theta0=0.15)
    T = float(loop.duration)
    x0 = cat.initial_state(float(loop.theta0))
    print("nhjax demo: the falling cat turns a somersault at zero angular momentum")
    print(
        f"  cylinders: mass 1 kg, length 1 m, radius 0.25 m -> I1 = {float(cat.I1):.5f} kg m^2, "
        f"lam = {float(cat.lam):.5f}, B = {float(cat.B):.5f}"
    )
    print(
        f"  shape loop: bend theta 0.150 -> {float(loop.theta1):.6f} rad, twist chi by 2 pi, unbend; "
        f"T = {T:g} s; closed form turn -2 pi f(theta1) = {float(loop.turn):.12f} rad"
    )

    run = lambda: simulate(cat, x0, T, control=loop, rtol=rtol, atol=atol, saveat=201)  # noqa: E731
    traj, t_first = _timed(run)
    traj, t_run = _timed(run)
    achieved = float(traj["psi"][-1] - traj["psi"][0])
    err = achieved - float(loop.turn)
    L_chart = max(float(jnp.max(jnp.abs(v))) for k, v in traj.invariants.items() if k.startswith("angular"))

    # The same motion with both attitudes integrated on SO(3) by RKMK45.
    att = cat.attitude_model()
    ctrl = att.wrap_control(loop)
    run_att = lambda: simulate(att, att.initial_state(float(loop.theta0)), T, control=ctrl,  # noqa: E731
                               rtol=rtol, atol=atol, saveat=201)
    tatt, t_att_first = _timed(run_att)
    tatt, t_att = _timed(run_att)
    g1, g2, _ = tatt.xs
    Rs = jax.vmap(lambda x: cat.poses(x[:3])[0])(traj.xs)
    att_dev = float(jnp.max(jnp.abs(jnp.stack([g1, g2], 1) - Rs)))
    orth = float(jnp.max(jnp.abs(jnp.einsum("nji,njk->nik", g1, g1) - jnp.eye(3))))
    L_att = max(float(jnp.max(jnp.abs(v))) for k, v in tatt.invariants.items() if k.startswith("angular"))
    rot = np.asarray(so3.log(g1[-1] @ g1[0].T))
    angle = float(np.linalg.norm(rot))
    off_axis = float(np.linalg.norm(rot / angle - np.sign(rot[1]) * np.array([0.0, 1.0, 0.0])))

    print(f"  achieved turn of psi   : {achieved:.12f} rad   (error vs closed form {err:+.2e})")
    print(
        f"  rotation of cylinder 1 : {angle:.9f} rad about an axis {off_axis:.1e} off e2 "
        "(start to end, RKMK attitudes)"
    )
    print(f"  |angular momentum|     : <= {L_chart:.1e} (chart)  <= {L_att:.1e} (RKMK attitudes) kg m^2/s")
    print(f"  energy - work drift    : {float(traj.invariant_drift['energy - work']):.1e} J")
    print(f"  RKMK vs chart attitudes: {att_dev:.1e} max entry difference, |g^T g - I| <= {orth:.1e}")
    print(
        f"  steps {int(traj.num_accepted_steps)} accepted / {int(traj.num_rejected_steps)} rejected "
        f"at rtol = atol = {rtol:g}"
    )
    print(
        f"  time: {t_run * 1e3:.2f} ms per solve after compile ({t_first:.2f} s first call); "
        f"RKMK {t_att * 1e3:.2f} ms ({t_att_first:.2f} s first call)"
    )
    summary = dict(
        closed_form_turn=float(loop.turn), achieved_turn=achieved, error=err,
        theta1=float(loop.theta1), angular_momentum_max_chart=L_chart,
        angular_momentum_max_rkmk=L_att, energy_minus_work_drift=float(traj.invariant_drift["energy - work"]),
        rkmk_vs_chart=att_dev, steps=int(traj.num_accepted_steps), rtol=rtol,
        seconds_per_solve=t_run, seconds_first_call=t_first,
    )
    (out / "somersault.json").write_text(json.dumps(summary, indent=2))
    if figures:
        from . import plotting

        plotting.somersault_figure(cat, traj, path=out / "somersault_3d.png")
        plotting.shape_path_figure(cat, traj, path=out / "somersault_shape.png", closed_form_turn=float(loop.turn))
        print(f"  figures: {out / 'somersault_3d.png'}, {out / 'somersault_shape.png'}")
    return summary


def optimal_somersault(out="experiments/out", figures=True, theta0=0.6, T=2.0, turn=np.pi,
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

    from .scenes.falling_cat import FallingCatSmooth

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
          "the first solve compiles (about a minute) ...", flush=True)
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

    again, t_pmp = _timed(lambda: solve_pontryagin(ocp, ind.p0, ind.nu))
    print(f"  Pontryagin solve after compile: {t_pmp * 1e3:.1f} ms; whole optimization {r.seconds:.1f} s "
          "(compile included)")

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

        from . import plotting

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
