"""The demo behind ``nhjax demo --holonomy``.

(``nhjax demo`` itself optimizes the somersault: that uses ``controls``, so it is the
experiment ``nhjax.experiments.optimal_somersault``, run by the CLI.)

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


def somersault(out="somersault", rtol=1e-10, atol=1e-10, figures=True, turn=np.pi):
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
