"""Roll-ring transmission (seed 002, Fig. 9.3): the dynamic behaviour of the model under the
seed's drive moment.

The seed's data for Fig. 9.3 did not survive extraction except the switching times of the
drive and the scale a = 1e-3 of the moment; the model's form of (9.8) and the parameter
values are ours (nhjax.scenes.roll_ring, module docstring). From rest, the moment tilts
the rings (0 -> 0.1 rad over 0.4-2.1 s), holds them, and tilts them back (5.4-7.1 s);
while tilted, the shaft drives the ring body along it at c tan(beta); the shock absorber
follows through the spring-damper and the double pendulum swings. Plotted against t:
the drive v(t), the tilt beta, the positions u_r and u_s, the pendulum angles, and the
energy ledgers (mechanical energy E, dissipated D, supplied W, and the drift of
E + D - W). Solved with simulate()'s default solver at rtol = atol = 1e-10 over 10 s,
with steps landing on the 16 kinks of N(t) (jump_ts=RollRing.kink_times()).
Writes roll_ring.{png,json} to ``--out`` (default: ./roll_ring/).
"""

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import nhjax
from nhjax.scenes.roll_ring import SWITCH_TIMES, RollRing, drive_profile

OUT = Path("roll_ring")  # under the working directory


def main(out=OUT, rtol=1e-10, t_end=10.0, saveat=2001):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rr = RollRing()
    x0 = rr.initial_state()
    start = time.perf_counter()
    tr = nhjax.simulate(rr, x0, t_end, saveat=saveat, rtol=rtol, atol=rtol, jump_ts=rr.kink_times())
    seconds = time.perf_counter() - start
    ts, xs = np.asarray(tr.ts), np.asarray(tr.xs)
    E = np.asarray(jax.vmap(rr.mechanical_energy)(tr.xs))
    D, W = xs[:, 18], xs[:, 19]
    bal = E + D - W
    summary = dict(
        t_end=t_end, rtol=rtol, atol=rtol, steps=int(tr.num_accepted_steps), solve_seconds_incl_compile=seconds,
        params={k: float(getattr(rr, k)) for k in ("m_r", "J_r", "m_s", "m1", "m2", "l1", "l2", "gamma", "delta",
                                                   "g", "drive_speed", "moment_scale")},
        switch_times=list(SWITCH_TIMES), beta_max=float(xs[:, 1].max()), u_r_end=float(xs[-1, 0]),
        u_s_end=float(xs[-1, 2]), dissipated_end=float(D[-1]), supplied_end=float(W[-1]),
        energy_balance_drift=float(np.abs(bal - bal[0]).max()),
        constraint_drift={k: float(v) for k, v in tr.constraint_drift.items()},
    )
    print(f"roll-ring, seed's drive, {t_end} s, rtol = atol = {rtol:g}, {summary['steps']} steps, "
          f"{seconds:.1f} s incl. compile")
    print(f"  tilt held at {summary['beta_max']:.6f} rad; ring body travelled {summary['u_r_end']:.6f} m, "
          f"absorber at {summary['u_s_end']:.6f} m")
    print(f"  supplied {summary['supplied_end']:.3e} J, dissipated {summary['dissipated_end']:.3e} J, "
          f"drift of E + D - W {summary['energy_balance_drift']:.1e} J")
    print("  constraints " + ", ".join(f"{k} {v:.1e}" for k, v in summary["constraint_drift"].items()))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 2, figsize=(12, 7.5), sharex=True)
    a = ax[0, 0]
    a.plot(ts, np.asarray(drive_profile(jnp.asarray(ts))), "k-", lw=1, label="v(t) = N(t) / a")
    a.plot(ts, 10 * xs[:, 1], "b-", lw=1, label="10 beta [rad]")
    a.set(title="drive and tilt of the rings")
    a.legend(fontsize=8)
    a = ax[0, 1]
    a.plot(ts, xs[:, 0], "b-", lw=1, label="u_r, ring body [m]")
    a.plot(ts, xs[:, 2], "r--", lw=1, label="u_s, shock absorber [m]")
    a.set(title="positions along the shaft")
    a.legend(fontsize=8)
    a = ax[1, 0]
    a.plot(ts, xs[:, 5], "g-", lw=1, label="alpha1 [rad]")
    a.plot(ts, xs[:, 8], "m-", lw=1, label="alpha2 [rad]")
    a.set(xlabel="t [s]", title="double pendulum")
    a.legend(fontsize=8)
    a = ax[1, 1]
    a.plot(ts, E - E[0], "k-", lw=1, label="E(t) - E(0)")
    a.plot(ts, D, "r-", lw=1, label="dissipated D(t)")
    a.plot(ts, W, "b-", lw=1, label="supplied W(t)")
    a.plot(ts, 1e6 * (bal - bal[0]), "c-", lw=0.8, label="1e6 x (E + D - W drift)")
    a.set(xlabel="t [s]", ylabel="[J]", title="energy balance")
    a.legend(fontsize=8)
    fig.suptitle("Fig. 9.3: dynamic behaviour of the roll-ring model (our parameters; the seed's are lost)")
    fig.tight_layout()
    fig.savefig(out / "roll_ring.png", dpi=120)
    summary["series"] = dict(t=ts[::4].tolist(), **{n: xs[::4, i].tolist() for i, n in (
        (0, "u_r"), (1, "beta"), (2, "u_s"), (5, "alpha1"), (8, "alpha2"), (18, "dissipated"), (19, "supplied"))})
    (out / "roll_ring.json").write_text(json.dumps(summary, indent=1))
    print(f"wrote {out / 'roll_ring.png'} and {out / 'roll_ring.json'}")
    return summary


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT,
                    help="folder for the figure and the table (default: ./roll_ring)")
    main(ap.parse_args().out)
