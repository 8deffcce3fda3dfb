"""Long-run reliability: constraint residual and invariant drift after 1e4 periods.

Every scene of ``nhjax.scenes.REGISTRY`` at its documented default parameters and
the default ``simulate()`` settings (rtol = atol = 1e-8, the default solver and
per-step projection), from one documented motion, over ``PERIODS`` (1e4) periods of
that motion. A "period" is the motion's own period where it has one (the skate's
circle, the ball's orbit, the disk's circle, the cart's turn), else the
characteristic time named in the case (a twist or spin period 2 pi / rate). Scenes
whose free motion is unbounded (n point masses at zero angular momentum fly apart)
run under a conservative shape spring (``ShapeSpring``), whose small-oscillation
period is the period; their invariants are then energy - work and the momentum.
Reported per scene: the horizon [s], accepted steps, wall time of the solve (after
compiling it on one period: t1 is an array, so the long run reuses the program), the
largest constraint residual over 11 saved times, the largest drift of the scene's
invariants over them, absolute and relative (|I(t) - I(0)| / |I(0)| where I(0) != 0), the distance of group-valued
parts from their group at the end, and the error against the exact solution where the
scene has one.

``tests/test_long_run.py`` (slow) asserts bounds on the same runs.

Writes experiments/out/bench/long_run.{json,csv}; ``nhjax bench long_run``.
"""

from __future__ import annotations

import csv
import json
import os
import platform
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import nhjax
import nhjax.scenes as S
from nhjax._validate import _group_parts, group_residual

OUT = Path(__file__).resolve().parent.parent / "experiments" / "out" / "bench"
PERIODS = 10_000


class Twist(eqx.Module):
    """Velocity control of the cat at fixed theta: chi' = rate."""

    rate: float

    def __call__(self, t, x):
        return jnp.stack([jnp.zeros_like(t), jnp.full_like(t, self.rate)])


class Circle(eqx.Module):
    """Velocity control of the smooth cat: w runs round a circle, w' = rate (-w2, w1)."""

    rate: float

    def __call__(self, t, x):
        return self.rate * jnp.stack([-x[1], x[0]])


class ShapeSpring(eqx.Module):
    """Shape forces u = -K (r - r0) of a reduced system: the potential K |r - r0|^2 / 2 on
    the shape, so the shape oscillates about r0 and energy - work stays constant (and the
    momentum, which shape forces do not change)."""

    system: eqx.Module
    r0: jax.Array
    K: float

    def __call__(self, t, x):
        return -self.K * (self.system.split(x)[2] - self.r0)


def _three_body_spring(system):
    """The three bodies (Jacobi shape w) from w = (0.3, 0.2, 1.0) at rest, spring K = 1 to
    the unit equilateral triangle w0 = (0, 0, 1) (equal masses): w3 stays near 1, far from
    the collinear shapes (w3 = 0)."""
    x0 = system.initial_state([0.3, 0.2, 1.0], [0.2, -0.1, 0.1])
    return system, x0, ShapeSpring(system, jnp.array([0.0, 0.0, 1.0]), 1.0), 2 * np.pi / 2.0, \
        "pi s: the small-oscillation period of the shape spring (K = 1, reduced metric I/4 at w0)", None


def _chain_free():
    chain = S.PlanarChain()
    return chain, chain.initial_state([0.5, -0.4], [1.0, -0.5])


def _cat_free():
    cat = S.FallingCat()
    return cat, cat.initial_state(0.8, chi_dot=0.5)


#: The registry's scenes that simulate() integrates (the impact scenes, with one-sided
#: constraints, run through simulate_impacts: their long runs -- 1000 impacts, energy
#: bookkeeping -- are benchmarks/impacts.py and tests/test_impacts.py).
SMOOTH = [n for n, (cls, _) in S.REGISTRY.items() if not hasattr(cls, "unilateral_constraints")]


def case(name):
    """(system, x0, control, period [s], what the period is, exact(t, x_end) error fn or None)."""
    if name == "FallingCat":
        cat, x0 = _cat_free()
        return cat, x0, None, 2 * np.pi / 0.5, "2 pi / chi'(0), torque-free", None
    if name == "FallingCatAttitudes":
        cat, _ = _cat_free()
        att = cat.attitude_model()
        return att, att.initial_state(0.8, chi_dot=0.5), None, 2 * np.pi / 0.5, "2 pi / chi'(0), torque-free", None
    if name == "FallingCatLagrangian":
        cat, x = _cat_free()
        lag = S.FallingCatLagrangian()
        return lag, jnp.concatenate([x[:3], cat.velocities(x)]), None, 2 * np.pi / 0.5, \
            "2 pi / chi'(0), torque-free", None
    if name == "FallingCatReduced":
        cat = S.FallingCatReduced()
        return cat, cat.initial_state(0.8, chi_dot=0.5), None, 2 * np.pi / 0.5, "2 pi / chi'(0), torque-free", None
    if name in ("NBodyCat", "ThreeBodyCat"):
        return _three_body_spring(getattr(S, name)())
    if name == "PlanarChain":
        chain, x0 = _chain_free()
        return chain, x0, None, 2 * np.pi, "2 pi / phi1'(0), torque-free (3 rods, phi = (0.5, -0.4), " \
            "phi' = (1, -0.5))", None
    if name == "PlanarChainUnreduced":
        chain, x0 = _chain_free()
        un = S.PlanarChainUnreduced()
        return un, chain.unreduced_state(x0), None, 2 * np.pi, "2 pi / phi1'(0), torque-free (PlanarChain's " \
            "motion in R^9 with hinge constraints)", None
    if name == "FallingCatKinematic":
        cat = S.FallingCatKinematic()
        x0 = cat.initial_state(0.8)

        def err(t, x):  # psi = -f(theta0) chi exactly; chi = rate t
            return max(abs(float(x[1]) - 2 * np.pi * t), abs(float(x[2]) + float(cat.f(0.8)) * 2 * np.pi * t))
        return cat, x0, Twist(2 * np.pi), 1.0, "one twist of chi (chi' = 2 pi rad/s)", err
    if name == "FallingCatSmooth":
        cat = S.FallingCatSmooth()
        x0 = cat.initial_state(0.8)
        k = float(cat.coefficients(x0[:2])[0])

        def err(t, x):  # |w| = 0.8 rotating at 1 rad/s, phi' = k theta^2
            w = 0.8 * np.array([np.cos(t), np.sin(t)])
            return max(float(np.abs(np.asarray(x[:2]) - w).max()), abs(float(x[2]) - 0.8 * k * 0.8 * t))
        return cat, x0, Circle(1.0), 2 * np.pi, "one loop of the shape w round the origin", err
    if name == "Skate":
        sk = S.Skate()
        x0 = sk.initial_state(speed=-4.0, phi_dot=2.0)
        return sk, x0, None, np.pi, "the circle of radius 2 (seed 002, 9.1)", \
            lambda t, x: float(jnp.max(jnp.abs(x - sk.exact_solution(t, x0))[:2]))
    if name == "SkateSE2":
        sk = S.SkateSE2()
        x0 = sk.initial_state(speed=-4.0, phi_dot=2.0)
        flat = sk.skate().initial_state(speed=-4.0, phi_dot=2.0)
        return sk, x0, None, np.pi, "the circle of radius 2 (seed 002, 9.1)", \
            lambda t, x: float(jnp.max(jnp.abs(x[0][0][:2, 2] - sk.skate().exact_solution(t, flat)[:2])))
    if name == "BallOnPlatter":
        b = S.BallOnPlatter()
        x0 = b.initial_state()
        return b, x0, None, 2 * np.pi / float(b.turn_rate), "one orbit of the centre (2 pi / kappa)", \
            lambda t, x: float(jnp.max(jnp.abs(x[:2] - b.exact_solution(t, x0)[0])))
    if name == "BallInCone":
        b = S.BallInCone()
        x0 = b.initial_state(rho=3.0, rho_dot=0.5, alpha_dot=0.3, spin=1.0)
        d0 = float(jnp.hypot(x0[0], x0[1]))

        def err(t, x):  # t1 is a whole number of radial periods: D (hence the height) is back to D(0)
            return abs(float(jnp.hypot(x[0], x[1])) - d0)
        return b, x0, None, b.radial_period(x0), "one radial period (greatest height to greatest height)", err
    if name == "RollRing":
        rr = S.RollRing()
        # the seed's drive (tilt up, hold, tilt back by t = 7.1 s), then the mechanism rings
        # down through the damper; invariant: E + dissipated - supplied
        period = 2 * np.pi * float(np.sqrt((rr.m_s + rr.m1 + rr.m2) / rr.gamma))
        return rr, rr.initial_state(), None, period, \
            "2 pi sqrt((m_s + m1 + m2) / gamma), the absorber's spring period", None
    if name in ("ThreeCylinders", "ThreeCylindersMinimal"):
        c = getattr(S, name)()
        # no exact solution; the upper cylinder rolls off along e1 while its axis angle
        # settles (2 -> 1.456 rad), the lower ones keep rolling: bounded speeds, no guard
        return c, c.initial_state(), None, np.pi, "one turn of the upper cylinder at its initial spin (2 pi / phi'(0))", None
    if name in ("RollingDisk", "RollingDiskQuaternion"):
        d = S.RollingDisk()
        theta0, q = 0.25, 2.17080452
        xd = d.circular_state(theta0, q)
        period = d.circular_period(theta0, q)
        if name == "RollingDisk":
            def err(t, x):  # contact point on the circle of radius 1/q about the origin
                return abs(float(jnp.hypot(x[0], x[1])) - 1 / q)
            return d, xd, None, period, "one circuit of the seed's circle (theta0 = 0.25, q = 2.1708)", err
        dq = d.quaternion_model()

        def errq(t, x):
            c = dq.contact_point(x[:7])
            return abs(float(jnp.hypot(c[0], c[1])) - 1 / q)
        return dq, d.to_quaternion_state(xd), None, period, \
            "one circuit of the seed's circle (theta0 = 0.25, q = 2.1708)", errq
    if name == "TwoWheeledCart":
        c = S.TwoWheeledCart()
        x0 = c.initial_state(speed=1.0, theta_dot=0.5)
        return c, x0, None, 2 * np.pi / 0.5, "one turn of the heading (theta' = 0.5)", \
            lambda t, x: float(jnp.max(jnp.abs(x[:2] - c.exact_solution(t, x0)[:2])))
    if name == "ShellWithTop":
        r = S.ShellWithTop()
        return r, r.initial_state(shell_omega=(0.5, 0.0, 0.2), top_omega=(1.0, 0.5, 3.0)), None, 2 * np.pi / 3.0, \
            "one spin of the top (2 pi / 3 s), torque-free, rolling and wobbling", None
    if name == "ShellWithTopReduced":
        r = S.ShellWithTopReduced()
        w = np.array([1.0, 2.0, 3.0])
        return r, r.initial_state(w), None, 2 * np.pi / np.linalg.norm(w), "2 pi / |omega(0)|", None
    if name == "ShellWithTopLagrangian":
        r = S.ShellWithTopLagrangian()
        x0 = jnp.zeros(16).at[5].set(0.3)  # the top tilted 0.3 rad from hanging, at rest: it rocks
        return r, x0, None, 1.0, "1 s (the top rocks; the rotation-vector chart ends at |theta| = 2 pi)", None
    if name == "ShellWithSuslovHinge":
        h = S.ShellWithSuslovHinge()
        return h, h.initial_state([0.3, 0.2, 1.0], Omega12=(0.1, -0.2)), None, 2 * np.pi, \
            "2 pi / omega3(0)", None
    if name == "ShellWithSuslovHingeZeroMomentum":
        h = S.ShellWithSuslovHingeZeroMomentum()
        return h, h.initial_state((0.3, 0.2)), None, 2 * np.pi / 0.3, "2 pi / omega1(0)", None
    if name == "SuslovBundle":
        b = S.SuslovBundle()
        return b, b.initial_state([0.3, 0.2, 1.0], Omega12=(0.1, -0.2)), None, 2 * np.pi, "2 pi / omega3(0)", None
    raise KeyError(name)


def invariant_drift(traj):
    """(absolute, relative): max over the invariants of max_t |I(t) - I(0)|, and the
    same divided by |I(0)| over the invariants with |I(0)| > 1e-8 (nan if none: e.g.
    the cat's angular momentum, which is zero)."""
    vals = {k: np.asarray(v) for k, v in traj.invariants.items()}
    ab = [float(np.abs(v - v[0]).max()) for v in vals.values()]
    rel = [float(np.abs(v - v[0]).max() / abs(v[0])) for v in vals.values() if abs(v[0]) > 1e-8]
    return max(ab, default=0.0), max(rel, default=float("nan"))


def run(name, periods=PERIODS):
    """One long run: a dict of the figures described in the module docstring."""
    system, x0, control, period, what, err = case(name)
    t1 = periods * period
    kw = dict(control=control, saveat=11, max_steps=50_000_000)
    nhjax.simulate(system, x0, jnp.asarray(period), **kw)  # compile (t1 is an array: reused)
    start = time.perf_counter()
    traj = nhjax.simulate(system, x0, jnp.asarray(t1), **kw)
    jax.block_until_ready(traj.xs)
    seconds = time.perf_counter() - start
    group = 0.0
    for _, sp, leaf in _group_parts(system.spaces, traj.x_end):
        group = max(group, float(group_residual(sp, leaf)[0]))
    cons = max([float(v) for v in traj.constraint_drift.values()], default=0.0)
    return {
        "scene": name, "period_s": float(period), "period_is": what, "periods": periods, "t1_s": float(t1),
        "steps": int(traj.num_accepted_steps), "rejected": int(traj.num_rejected_steps), "seconds": seconds,
        "constraint_residual": cons, "invariant_drift_abs": invariant_drift(traj)[0],
        "invariant_drift_rel": invariant_drift(traj)[1],
        "invariants": sorted(traj.invariants), "group_residual": group,
        "exact_error": None if err is None else float(err(float(t1), traj.x_end)),
    }


def main(names=None, periods=PERIODS):
    OUT.mkdir(parents=True, exist_ok=True)
    names = names or list(SMOOTH)
    print(f"load average at start: {os.getloadavg()}; {platform.processor() or platform.machine()}")
    print(f"{'scene':34s} {'periods':>8s} {'t1 [s]':>10s} {'steps':>9s} {'time [s]':>9s} "
          f"{'constraint':>10s} {'inv. abs':>9s} {'inv. rel':>9s} {'group':>9s} {'exact err':>9s}")
    rows = []
    for name in names:
        r = run(name, periods)
        rows.append(r)
        ex = "-" if r["exact_error"] is None else f"{r['exact_error']:.1e}"
        print(f"{name:34s} {r['periods']:8d} {r['t1_s']:10.4g} {r['steps']:9d} {r['seconds']:9.2f} "
              f"{r['constraint_residual']:10.1e} {r['invariant_drift_abs']:9.1e} {r['invariant_drift_rel']:9.1e} "
              f"{r['group_residual']:9.1e} {ex:>9s}",
              flush=True)
    print(f"load average at end: {os.getloadavg()}")
    (OUT / "long_run.json").write_text(json.dumps(rows, indent=1))
    with open(OUT / "long_run.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=[k for k in rows[0] if k != "invariants"], extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return rows


if __name__ == "__main__":
    import sys

    # scene names (others, e.g. "long_run" from `nhjax bench long_run`, are ignored) and --periods=N
    args = [a for a in sys.argv[1:] if a in SMOOTH]
    per = [int(float(a.split("=")[1])) for a in sys.argv[1:] if a.startswith("--periods=")]
    main(args or None, per[0] if per else PERIODS)
