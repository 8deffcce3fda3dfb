"""Ball rolling inside a cone (seed 002, Fig. 9.5): the path in the seed's (alpha, rho) coordinates.

The seed's data for Fig. 9.5 did not survive extraction except gamma = 1; we take a
solid ball (J = 2/5 m r^2, m = r = g = 1) started at rho = 3 with rho' = 0.5 (rolling
up), alpha' = 0.3 and spin 1 rad/s about the normal. As the seed describes, the ball
rolls up until its upward velocity vanishes, rolls down in an arc and climbs again,
like the skate's cycloid. Beside the path: the heights it returns to against the
turning points of the reduced radial motion (nhjax.scenes.ball_in_cone), the time
between greatest heights against the quadrature period, the azimuth advance per period,
and the drift of the three integrals (energy, L = D^2 alpha', N). Solved with
simulate()'s default solver at rtol = atol = 1e-10 over 10 radial periods. Writes ball_in_cone.{png,json} to ``--out`` (default: ./ball_in_cone/).
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

import nhjax
from nhjax.scenes.ball_in_cone import BallInCone

OUT = Path("ball_in_cone")  # under the working directory
START = dict(rho=3.0, alpha=0.0, rho_dot=0.5, alpha_dot=0.3, spin=1.0)


def extrema(ts, y, sign=1):
    """Local maxima of sign*y refined by a parabola through the three samples around
    each: (times, values)."""
    y = sign * np.asarray(y)
    i = np.nonzero((y[1:-1] > y[:-2]) & (y[1:-1] >= y[2:]))[0] + 1
    h = ts[1] - ts[0]
    a, b, c = y[i - 1], y[i], y[i + 1]
    d = 0.5 * (a - c) / (a - 2 * b + c)
    return ts[i] + d * h, sign * (b - 0.25 * (a - c) * d)


def main(out=OUT, rtol=1e-10, periods=10, saveat=20001):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ball = BallInCone(gamma=1.0)
    x0 = ball.initial_state(**START)
    T, dalpha = ball.radial_period(x0), ball.precession_per_period(x0)
    dmin, dmax = ball.turning_points(x0)
    start = time.perf_counter()
    tr = nhjax.simulate(ball, x0, periods * T, saveat=saveat, rtol=rtol, atol=rtol)
    seconds = time.perf_counter() - start
    ts = np.asarray(tr.ts)
    D = np.hypot(tr["u1"], tr["u2"])
    rho, alpha = (np.asarray(v) for v in ball.polar(np.asarray(tr.xs).T))
    alpha = np.unwrap(alpha)
    t_hi, d_hi = extrema(ts, D)
    _, d_lo = extrema(ts, D, sign=-1)
    a_hi = np.interp(t_hi, ts, alpha)
    summary = dict(
        start=START, gamma=1.0, J=0.4, rtol=rtol, atol=rtol, radial_periods=periods,
        solve_seconds_incl_compile=seconds, steps=int(tr.num_accepted_steps),
        D_min_exact=dmin, D_max_exact=dmax, height_max_exact=float(ball.height(dmax)),
        height_max_err=float(np.abs(ball.height(d_hi) - ball.height(dmax)).max()),
        height_min_err=float(np.abs(ball.height(d_lo) - ball.height(dmin)).max()),
        radial_period_exact=T, radial_period_err=float(np.abs(np.diff(t_hi) - T).max()),
        precession_exact=dalpha, precession_err=float(np.abs(np.diff(a_hi) - dalpha).max()),
        invariant_drift={k: float(v) for k, v in tr.invariant_drift.items()},
        constraint_drift={k: float(v) for k, v in tr.constraint_drift.items()},
    )
    print(f"ball in cone, gamma = 1, start {START}; rtol = atol = {rtol:g}, {periods} radial periods, "
          f"{summary['steps']} steps, {seconds:.2f} s incl. compile")
    print(f"  greatest height  exact {summary['height_max_exact']:.10f}   max error over the returns "
          f"{summary['height_max_err']:.1e}   (least height: {summary['height_min_err']:.1e})")
    print(f"  radial period    exact {T:.10f}   max error {summary['radial_period_err']:.1e}")
    print(f"  alpha advance    exact {dalpha:.10f}   max error {summary['precession_err']:.1e}")
    print("  integral drift   " + ", ".join(f"{k} {v:.1e}" for k, v in summary["invariant_drift"].items()))
    print("  constraints      " + ", ".join(f"{k} {v:.1e}" for k, v in summary["constraint_drift"].items()))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 4.8), gridspec_kw=dict(width_ratios=[2, 1]))
    a.plot(alpha, rho, "b-", lw=1)
    cg, sg = np.cos(1.0), np.sin(1.0)
    for d, lab in ((dmax, "turning points of the reduced motion"), (dmin, None)):
        a.axhline((d + cg) / sg, color="r", ls="--", lw=0.8, label=lab)
    a.plot([alpha[0]], [rho[0]], "ko", ms=4, label="start")
    a.set(xlabel="alpha [rad]", ylabel="rho [m]", title="Fig. 9.5: ball inside a cone, path in (alpha, rho)")
    a.legend(fontsize=8)
    for k, v in tr.invariants.items():
        v = np.asarray(v)
        b.semilogy(ts, np.abs(v - v[0]) + 1e-18, lw=0.8, label=k)
    b.set(xlabel="t [s]", ylabel="|I(t) - I(0)|", title=f"integrals (rtol = {rtol:g})")
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "ball_in_cone.png", dpi=120)
    summary["path"] = dict(t=ts[::10].tolist(), alpha=alpha[::10].tolist(), rho=rho[::10].tolist())
    (out / "ball_in_cone.json").write_text(json.dumps(summary, indent=1))
    print(f"wrote {out / 'ball_in_cone.png'} and {out / 'ball_in_cone.json'}")
    return summary


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT,
                    help="folder for the figure and the table (default: ./ball_in_cone)")
    main(ap.parse_args().out)
