"""Two-wheeled cart on an inclined plane (seed 002, Fig. 9.12): up the slope, back down, cusps on one line, against the closed form.

The seed's data a = 0.5, Jc = 1, Jw = 0.5, g = 0.3 (units m, r); its initial
conditions (9.52) are garbled in our copy, so the cart starts at the origin
heading up the slope (e1) at speed 0.3 and turning left at 0.25 rad/s. The
engine's motion is compared with the closed form (a skate with effective slope
acceleration m g sin(beta)/(m + 2 Jw/r^2)); cusps, energy and turning rate are
reported. Writes two_wheeled_cart.{png,csv} to ``--out`` (default: ./two_wheeled_cart/).
"""

import argparse
import csv
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import nhjax
from nhjax.scenes.two_wheeled_cart import TwoWheeledCart

OUT = Path("two_wheeled_cart")  # under the working directory


def main(out=OUT):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cart = TwoWheeledCart(a=0.5, Jc=1.0, Jw=0.5, g=0.3)
    x0 = cart.initial_state(speed=0.3, theta_dot=0.25)
    t1 = 3 * 2 * np.pi / 0.25
    tr = nhjax.simulate(cart, x0, t1, saveat=3001, rtol=1e-8, atol=1e-12)
    exact = cart.exact_solution(tr.ts, x0)
    err = np.abs(np.asarray(tr.xs - exact)).max(axis=0)
    cusps = cart.cusp_times(x0, t1)
    xc = np.asarray(cart.exact_solution(jnp.asarray(cusps), x0))
    with open(out / "two_wheeled_cart.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(list(cart.state_names) + ["t", "speed", "exact_x1", "exact_x2"])
        for k in range(0, len(tr.ts), 5):
            w.writerow(list(np.asarray(tr.xs[k])) + [float(tr.ts[k]), float(cart.speed(tr.xs[k])),
                                                     float(exact[k, 0]), float(exact[k, 1])])
    G = float(cart.slope_acceleration)
    print(f"effective slope acceleration G = m g sin(beta)/(m + 2 Jw/r^2) = {G:.4f}")
    print(f"max |engine - closed form| per component at rtol 1e-8: {err.max():.2e} "
          f"(x1 {err[0]:.1e}, x2 {err[1]:.1e}, wheels {err[3]:.1e}, {err[4]:.1e})")
    print(f"energy drift {float(tr.invariant_drift['energy']):.1e}, turning-rate drift "
          f"{float(tr.invariant_drift['turn_rate']):.1e}, max constraint {float(tr.constraint_drift['velocity']):.1e}")
    print(f"cusps at t = {np.round(cusps, 4)}")
    print(f"  all at x1 = {xc[:, 0].round(12)} (energy: M v0^2/(2 m g sin beta) = 0.3)")
    print(f"  x2 = {xc[:, 1].round(4)}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 5))
    a.plot(exact[:, 1], exact[:, 0], "-", color="0.8", lw=5, label="closed form")
    a.plot(tr["x2"], tr["x1"], "b-", lw=1, label="engine (Tsit5, rtol 1e-8)")
    a.plot(xc[:, 1], xc[:, 0], "rv", ms=7, label="cusps (the cart stops and reverses)")
    a.plot([0], [0], "go", label="start, heading up the slope")
    a.set(xlabel="x2", ylabel="x1 (e1 uphill)", title="Fig. 9.12: two-wheeled cart on an inclined plane")
    a.legend(fontsize=8, loc="lower left")
    ts = np.asarray(tr.ts)
    b.plot(ts, cart.speed(tr.xs.T), "b-", lw=1, label="speed along the axis v")
    b.plot(ts, tr["phi_l_dot"], "g--", lw=1, label="left wheel phi_l'")
    b.plot(ts, tr["phi_r_dot"], "m--", lw=1, label="right wheel phi_r'")
    for t in cusps:
        b.axvline(t, color="r", lw=0.5)
    b.axhline(0, color="k", lw=0.5)
    b.set(xlabel="t", ylabel="rate", title="v changes sign at the cusps; the wheels keep different rates")
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "two_wheeled_cart.png", dpi=120)
    print(f"wrote {out / 'two_wheeled_cart.png'} and {out / 'two_wheeled_cart.csv'}")
    return err


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT,
                    help="folder for the figure and the table (default: ./two_wheeled_cart)")
    main(ap.parse_args().out)
