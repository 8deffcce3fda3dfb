"""Three rolling cylinders (seed 002, Figs. 9.6-9.7): paths of the contact points and of the
upper cylinder's centre in the (x1, x2)-plane, with the axis lines at a few times.

The seed's constants and initial conditions for Fig. 9.7 did not survive extraction, so
this uses the scene's defaults (r1 = r2 = 0.5 m, lower axes at a = pi/3, upper cylinder
m = 2 kg, J_a = 0.25, J_t = 1 kg m^2, lower m_l = 1 kg, J_l = 0.125 kg m^2) and its default
start (x = 0, theta = 2 rad, phi = 0, psi1 = -1, psi2 = 1, theta' = -0.3 rad/s, phi' = 2 rad/s):
as in the seed's figure the upper cylinder rolls towards +x1 with a decreasing axis angle
theta while both lower cylinders roll; the seed's reversal at t = 2.7 s depends on its
lost data and is not reproduced. The motion is computed twice, by the two independent
formulations (ThreeCylindersMinimal in the seed's coordinates, (9.30)-(9.31); ThreeCylinders
as three rigid bodies in (u, p) in R^3 x S^3 with 19 constraints, (9.33)-(9.36)), at
rtol = atol = 1e-12; the JSON records their largest difference, the energy drift and the
constraint residuals. Writes three_cylinders.{png,json} to ``--out`` (default: ./three_cylinders/).
"""

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np

import nhjax
from nhjax.scenes.three_cylinders import ThreeCylinders, ThreeCylindersMinimal

OUT = Path("three_cylinders")  # under the working directory
T_END = 6.0
AXIS_TIMES = (0.0, 2.0, 4.0, 6.0)


def main(out=OUT, rtol=1e-12, t_end=T_END, saveat=601):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    mn, up = ThreeCylindersMinimal(), ThreeCylinders()
    kw = dict(saveat=saveat, rtol=rtol, atol=rtol, on_guard="stop")
    runs = {}
    for name, sys_ in (("minimal", mn), ("up", up)):
        start = time.perf_counter()
        tr = nhjax.simulate(sys_, sys_.initial_state(), t_end, **kw)
        runs[name] = (tr, time.perf_counter() - start)
    trm, tru = runs["minimal"][0], runs["up"][0]
    ts = np.asarray(trm.ts)
    ym = np.asarray(trm.xs)
    y, yd = jax.vmap(up.to_minimal)(tru.xs)
    yu = np.concatenate([np.asarray(y), np.asarray(yd)], axis=1)
    yu[:, 3] = np.unwrap(yu[:, 3])
    diff = np.abs(yu - ym).max(axis=0)
    z1, z2 = (np.asarray(z) for z in jax.vmap(mn.contact_points)(trm.xs[:, :6]))
    summary = dict(
        t_end=t_end, rtol=rtol, atol=rtol, start=dict(x1=0.0, x2=0.0, theta=2.0, phi=0.0, psi1=-1.0, psi2=1.0,
                                                      theta_dot=-0.3, phi_dot=2.0),
        params=dict(r1=0.5, r2=0.5, a=float(np.pi / 3), m=2.0, J_a=0.25, J_t=1.0, m_l=1.0, J_l=0.125, J_lt=0.5),
        formulations_max_difference=dict(zip(mn.state_names, diff.tolist())),
        formulations_max_difference_all=float(diff.max()),
        steps=dict(minimal=int(trm.num_accepted_steps), up=int(tru.num_accepted_steps)),
        solve_seconds_incl_compile=dict(minimal=runs["minimal"][1], up=runs["up"][1]),
        energy_drift=dict(minimal=float(trm.invariant_drift["energy"]), up=float(tru.invariant_drift["energy"])),
        constraint_drift=dict(minimal={k: float(v) for k, v in trm.constraint_drift.items()},
                              up={k: float(v) for k, v in tru.constraint_drift.items()}),
        guard=dict(minimal=trm.guard, up=tru.guard),
    )
    print(f"three cylinders, default start, {t_end} s, rtol = atol = {rtol:g}")
    print(f"  (u, p) model vs minimal model: max difference {summary['formulations_max_difference_all']:.1e} "
          f"over the 12 minimal state components")
    print(f"  energy drift  minimal {summary['energy_drift']['minimal']:.1e}   (u, p) {summary['energy_drift']['up']:.1e}")
    print("  constraints   minimal " + ", ".join(f"{k} {v:.1e}" for k, v in summary["constraint_drift"]["minimal"].items())
          + "   (u, p) " + ", ".join(f"{k} {v:.1e}" for k, v in summary["constraint_drift"]["up"].items()))
    print(f"  steps minimal {summary['steps']['minimal']}, (u, p) {summary['steps']['up']}; seconds incl. compile "
          f"{runs['minimal'][1]:.1f}, {runs['up'][1]:.1f}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw=dict(width_ratios=[2, 1]))
    a.plot(ym[:, 0], ym[:, 1], "k-", lw=1.5, label="centre x of the upper cylinder")
    a.plot(z1[:, 0], z1[:, 1], "b-", lw=1, label="contact point z1 (lower cylinder 1)")
    a.plot(z2[:, 0], z2[:, 1], "r-", lw=1, label="contact point z2 (lower cylinder 2)")
    (d1, d2), (n1, n2) = (tuple(np.asarray(v) for v in pair) for pair in mn.lower_axes())
    for k, tk in enumerate(AXIS_TIMES):
        i = int(np.argmin(np.abs(ts - tk)))
        th = ym[i, 2]
        e = np.array([np.cos(th), np.sin(th)])
        ends = np.array([z1[i, :2], z2[i, :2]])
        s = (ends - ym[i, :2]) @ e
        lo, hi = min(s.min(), 0) - 0.5, max(s.max(), 0) + 0.5
        seg = ym[i, :2] + np.outer([lo, hi], e)
        a.plot(seg[:, 0], seg[:, 1], "g-", lw=2, alpha=0.6, label="upper axis at t = " +
               ", ".join(f"{t:g}" for t in AXIS_TIMES) + " s" if k == 0 else None)
        a.annotate(f"t={ts[i]:g}", seg[1], fontsize=8, color="g")
        for d, nv, psi, c in ((d1, n1, ym[i, 4], "b"), (d2, n2, ym[i, 5], "r")):
            p0 = float(mn.r1) * psi * nv[:2]
            line = p0 + np.outer([-6, 6], d[:2])
            a.plot(line[:, 0], line[:, 1], c + ":", lw=0.6, alpha=0.5)
    a.set(xlabel="x1 [m]", ylabel="x2 [m]", title="Fig. 9.7: paths of the contact points and of the centre",
          aspect="equal")
    xs_all = np.concatenate([ym[:, 0], z1[:, 0], z2[:, 0]])
    ys_all = np.concatenate([ym[:, 1], z1[:, 1], z2[:, 1]])
    a.set_xlim(xs_all.min() - 1, xs_all.max() + 1)
    a.set_ylim(ys_all.min() - 1, ys_all.max() + 1)
    a.legend(fontsize=8, loc="best")
    b.semilogy(np.asarray(tru.ts), np.abs(yu - ym).max(axis=1) + 1e-18, lw=0.8, label="(u, p) vs minimal, max over y, y'")
    for name, tr in (("minimal", trm), ("(u, p)", tru)):
        v = np.asarray(tr.invariants["energy"])
        b.semilogy(np.asarray(tr.ts), np.abs(v - v[0]) + 1e-18, lw=0.8, label=f"|E(t) - E(0)|, {name}")
    b.set(xlabel="t [s]", title=f"two formulations, rtol = {rtol:g}")
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "three_cylinders.png", dpi=120)
    summary["path"] = dict(t=ts[::5].tolist(), x1=ym[::5, 0].tolist(), x2=ym[::5, 1].tolist(),
                           theta=ym[::5, 2].tolist(), z1=z1[::5, :2].tolist(), z2=z2[::5, :2].tolist())
    (out / "three_cylinders.json").write_text(json.dumps(summary, indent=1))
    print(f"wrote {out / 'three_cylinders.png'} and {out / 'three_cylinders.json'}")
    return summary


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT,
                    help="folder for the figure and the table (default: ./three_cylinders)")
    main(ap.parse_args().out)
