"""Rolling disk (seed 002, Fig. 9.9): slow straight rolling with a tiny tilt leans over and curves away; a disk that does not roll falls flat and the chart guard stops it.

Seed: J1 = 0.35, J2 = 0.5, rolling rate 0.3, initial tilt 1e-5. The tilt grows
at the rate of linear theory, the path curves away from the straight line, and
the seed stops when the tilt passes pi/2. In the exact model (minimal
coordinates and the (u, p) rigid body agree) the rolling disk leans over to a
largest tilt below pi/2 and rights itself again (its Chaplygin integrals keep
cos(theta) away from 0 while it rolls); a disk started without rolling tips over
its edge, reaches the edge of the chart at the exact fall time, and
``simulate(on_guard="stop")`` returns the motion up to there.
Writes rolling_disk_falls.{png,csv} to ``--out`` (default: ./rolling_disk_falls/).
"""

import argparse
import csv
from pathlib import Path

import jax
import numpy as np

import nhjax
from nhjax.scenes.rolling_disk import RollingDisk

OUT = Path("rolling_disk_falls")  # under the working directory


def fall_time(disk, theta0):
    """Exact time for a non-rolling disk to tip from theta0 to cos(theta) = chart_eps."""
    k = 2 * float(disk.m * disk.g * disk.r / (disk.J2 + disk.m * disk.r**2))
    theta_f = np.arccos(disk.chart_eps)
    y, w = np.polynomial.legendre.leggauss(400)
    Y = np.sqrt(theta_f - theta0)
    y = 0.5 * Y * (y + 1)
    return 0.5 * Y * np.sum(w * 2 * y / np.sqrt(k * (np.cos(theta0) - np.cos(theta0 + y**2))))


def main(out=OUT):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    disk = RollingDisk(J1=0.35, J2=0.5)
    quat = disk.quaternion_model()
    s, th0 = 0.3, 1e-5
    x0 = disk.initial_state(theta=th0, psi_dot=s)
    t1 = 32.0
    tr = nhjax.simulate(disk, x0, t1, saveat=3201, rtol=1e-11, atol=1e-13)
    tq = nhjax.simulate(quat, disk.to_quaternion_state(x0), t1, saveat=3201, rtol=1e-11, atol=1e-13)
    ts = np.asarray(tr.ts)
    theta = np.asarray(tr["theta"])
    tilt_of = jax.jit(jax.vmap(quat.tilt))
    tilt_q = np.asarray(tilt_of(tq.xs))
    contact_q = np.asarray(jax.jit(jax.vmap(lambda y: quat.contact_point(y[:7])[:2]))(tq.xs))
    i_max = int(np.argmax(theta))
    m, r, g, J1, J2 = (float(v) for v in (disk.m, disk.r, disk.g, disk.J1, disk.J2))
    lam2 = (m * g * r - (m * r * r + J1) * J1 * s * s / J2) / (m * r * r + J2)
    c = (m * r * r + J1) * J1 * s * s / (J2 * (m * r * r + J2))
    linear = th0 * ((1 + c / lam2) * np.cosh(np.sqrt(lam2) * ts) - c / lam2)

    # the disk that does not roll: falls flat, stopped by the chart guard
    x_tip = disk.initial_state(theta=0.01)
    tip = nhjax.simulate(disk, x_tip, 20.0, saveat=3201, rtol=1e-11, atol=1e-13, on_guard="stop")
    tip_q = nhjax.simulate(quat, disk.to_quaternion_state(x_tip), 20.0, saveat=3201, rtol=1e-11, atol=1e-13, on_guard="stop")
    t_exact = fall_time(disk, 0.01)
    try:
        nhjax.simulate(disk, x_tip, 20.0, saveat=3201, rtol=1e-11, atol=1e-13)
    except nhjax.ChartSingularityError as e:
        message = str(e)

    summary = dict(
        rolling_rate=s, initial_tilt=th0, growth_rate_linear=float(np.sqrt(lam2)),
        max_tilt=float(theta[i_max]), time_of_max_tilt=float(ts[i_max]),
        max_tilt_quaternion=float(tilt_q.max()),
        max_centre_difference_models=float(np.abs(
            np.asarray(tq.xs[:, :3]) - np.asarray(jax.jit(jax.vmap(disk.centre))(tr.xs))).max()),
        tip_guard=tip.guard, tip_stop_time=float(tip.t_final),
        tip_stop_time_quaternion=float(tip_q.t_final), tip_exact_fall_time=float(t_exact),
        energy_drift=float(tr.invariant_drift["energy"]),
    )
    with open(out / "rolling_disk_falls.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "x1", "x2", "theta", "theta_linear_theory", "tilt_quaternion_model"])
        for k in range(0, len(ts), 8):
            w.writerow([ts[k], float(tr["x1"][k]), float(tr["x2"][k]), theta[k], linear[k], tilt_q[k]])
    with open(out / "rolling_disk_falls_summary.csv", "w", newline="") as f:
        w = csv.writer(f)
        for k, v in summary.items():
            w.writerow([k, v])
    for k, v in summary.items():
        print(f"  {k:32s} {v}")
    print("  guard message:", message)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b, d) = plt.subplots(1, 3, figsize=(16, 4.8))
    upto = ts <= ts[i_max] + 2.0
    a.plot(tr["x1"][upto], tr["x2"][upto], "b-", lw=1.5, label="contact point, minimal model")
    a.plot(contact_q[upto, 0], contact_q[upto, 1], "r--", lw=1, label="contact point, (u, p) model")
    a.plot(tr["x1"][i_max], tr["x2"][i_max], "ko", label=f"largest tilt {theta[i_max]:.3f} rad")
    a.set(xlabel="x1", ylabel="x2", title="Fig. 9.9: rolling at psi' = 0.3 from tilt 1e-5")
    a.legend(fontsize=8)
    a.set_aspect("equal")
    b.semilogy(ts, np.abs(theta), "b-", lw=1.2, label="tilt, minimal model")
    b.semilogy(ts, tilt_q, "r--", lw=1, label="tilt, (u, p) model")
    b.semilogy(ts, np.where(linear < 3, linear, np.nan), "k:", lw=1.5, label="linear theory")
    b.axhline(np.pi / 2, color="0.5", lw=0.8)
    b.text(1, 1.7, "flat: pi/2", fontsize=8)
    b.set(xlabel="t", ylabel="|theta| [rad]", title="the tilt grows, then the rolling disk rights itself", ylim=(5e-6, 4))
    b.legend(fontsize=8, loc="lower right")
    d.plot(tip.ts, tip["theta"], "b-", lw=1.5, label="minimal model (stopped by guard)")
    d.plot(tip_q.ts, tilt_of(tip_q.xs), "r--", lw=1, label="(u, p) model")
    d.axvline(t_exact, color="k", lw=0.8, ls=":", label=f"exact fall time {t_exact:.6f}")
    d.axhline(np.pi / 2, color="0.5", lw=0.8)
    d.set(xlabel="t", ylabel="theta [rad]", title="a disk that does not roll falls flat")
    d.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(out / "rolling_disk_falls.png", dpi=120)
    print(f"wrote {out / 'rolling_disk_falls.png'} and the CSVs")
    return summary


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT,
                    help="folder for the figure and the table (default: ./rolling_disk_falls)")
    main(ap.parse_args().out)
