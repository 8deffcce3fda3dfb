"""The falling cat lands turned by pi under model-predictive control, from perturbed
starts and with inertia errors between model and plant: 256 closed loops in one call.

Task (``controls.tasks.torque_somersault``, seed 000 (7.14)-(7.15)): the torque-driven
cat at zero angular momentum, x = (theta, chi, psi, theta', chi'), nominally from rest
bent by theta0 = 0.6 rad to x(T) = (0.6, 2 pi, -pi, 0, 0) at T = 2 s (chi winds once,
psi turns by -pi), least int |u|^2 dt.

Controller: ``controls.MPC(ocp, period=0.05, intervals=40, mode="rti",
horizon="shrinking", terminal="penalty", terminal_weight=1e6, hessian="exact",
disturbance_gain=0.5)``: the landing time is fixed, so the horizon shrinks to it;
one SQP step per period (the QP solved by the Riccati recursion over the 40
intervals, ``qp="auto"``); the terminal conditions are a
penalty 1e6 |S (x(T) - target)|^2, S = diag(1, 1, 10, 1, 1) (the turn weighted above the
shape; a hard constraint of 5 equations is unreachable with the 2 inputs of the last
interval), torques |u_i| <= 1 N m (``--bound``: without a bound the last intervals of
the shrinking horizon spend large torques on the final state). The first plan of every
member is the nominal open-loop optimum of the same discretization (converged horizon
solves, continued in the penalty's weight 1e2, 1e4, 1e6 from the fixed-theta loop's
torques).

Why the disturbance observer (offset-free MPC, ``disturbance_gain``): with the plant's
inertias equal to the model's, every member lands within 1e-7 degrees; with the +-10%
errors, a controller that trusts its model predicts the plant's shape accelerations
and the turn rate psi' = -f(theta) chi' wrongly all along (a plant with larger I1 and
lam needs more torque to stop chi, and turns psi more per chi), notices the effect
only once it has shown in the state, and is left in the last few periods with more
to correct than the 1 N m torques can do (the failing members saturated both torques
over their last 3-5 periods and overshot the turn). The observer compares each
measurement with the model's prediction over the last period and adds half of the
unexplained rate to the model's vector field as a constant over the horizon
(``controls.MPC``'s ``disturbance_gain``): the prediction then carries the model
error, and the controller brakes in time. Gain 0.5 rather than 1: the estimate is the
last period's error, which lags the torques that cause it; a half update damps that
lag (``--disturbance-gain`` compares).

Members (``--members``, default 256; a fixed seed): start theta0 + U(-0.1, 0.1) rad,
chi U(-0.2, 0.2) rad, shape rates U(-0.3, 0.3) rad/s, psi = 0; the plant's I1, lam and B
each scaled by U(0.9, 1.1) (the model keeps the nominal ones). All members run in one
compiled program (``controls.closed_loop_batch``: groups of 4 members vmapped together,
the groups one after the other inside the program, in ``--workers`` threads that each run
an equal share of the members: by default 2 on two or more CPUs); the same loops one by one
(``controls.closed_loop``, the compiled loop reused) give ``sequential_seconds``,
measured on ``--sequential`` members (default 32) and scaled to all, said so in the JSON.
Both are timed in two rounds interleaved (batch, sample, batch, sample; the machine may
be shared), the best of each kept.

Success: the plant's final psi within 1 degree of -pi. Writes ``DIR/mpc_cat.json``
(``success_rate``, ``final_attitude_error_deg_max`` over the successful members,
``batch_seconds``, ``sequential_seconds`` and how they were measured, effort, fallbacks,
load average) and ``DIR/mpc_cat.png`` (histograms of the final attitude error, the
effort and the final shape error) and ``DIR/mpc_cat.gif`` (the closed loop of the member
that lands farthest from the target turn, drawn with its own plant's cylinders;
``--no-animation`` skips it).

Usage: nhjax run mpc_cat [--out DIR] [--members 256] [--sequential 32] [--bound 1] [--mode rti]
                        [--disturbance-gain 0.5] [--workers N] [--no-animation]
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import controls
from controls.tasks import torque_somersault
from nhjax.scenes import FallingCat

TH0, T, TURN = 0.6, 2.0, -np.pi
PERIOD, INTERVALS = 0.05, 40  # [s]; the horizon T on INTERVALS intervals, one per period
SUCCESS_DEG = 1.0
WEIGHT = 1e6  # the terminal penalty w |x(T) - target|^2
HESSIAN = "exact"
DISTURBANCE_GAIN = 0.5  # the observer's gain on every state component (--disturbance-gain)
MODE = "rti"  # (--mode)
BOUND = 1.0  # |u_i| <= BOUND [N m] (--bound)
SCALE = (1.0, 1.0, 10.0, 1.0, 1.0)
BATCH_GROUP = 4  # members vmapped together in closed_loop_batch (its ``group``)
ROUNDS = 2  # interleaved timing rounds (batch, then the sample one by one)  # of (theta, chi, psi, theta', chi') - target in the penalty


class LandingTarget(eqx.Module):
    """Terminal conditions scale * (x(T) - target): the attitude psi weighted above the
    shape (the landing's purpose is the turn)."""

    target: jax.Array
    scale: jax.Array

    def __call__(self, x):
        return self.scale * (x - self.target)


def setup(bound=None, mode=None, disturbance_gain=None):
    bound = BOUND if bound is None else bound
    mode = MODE if mode is None else mode
    gain = DISTURBANCE_GAIN if disturbance_gain is None else disturbance_gain
    cat = FallingCat()
    nominal = torque_somersault(cat, TH0, TURN, T)
    ocp = controls.OCP(cat, nominal.x0, T, nominal.running_cost,
                       terminal_constraints=LandingTarget(nominal.terminal_constraints.target, jnp.asarray(SCALE)),
                       u_lower=-bound, u_upper=bound)
    mpc = controls.MPC(ocp, PERIOD, INTERVALS, mode=mode, horizon="shrinking", terminal="penalty",
                       terminal_weight=WEIGHT, hessian=HESSIAN, disturbance_gain=gain)
    return cat, ocp, mpc


def nominal_plan(ocp):
    """The nominal open-loop optimum of the MPC's discretization (converged mode), from
    the fixed-theta loop's torques sampled at the intervals' midpoints."""
    cat = ocp.system
    # torque_loop_guess's torques (theta held at theta0 while chi winds once, rest to rest)
    t = (np.arange(INTERVALS) + 0.5) * T / INTERVALS
    sn, co, D = np.sin(TH0), np.cos(TH0), float(cat.D(TH0))
    I1, lam, c = float(cat.I1), float(cat.lam), 2 * np.pi / T
    chid, chidd = c * (1 - np.cos(c * t)), c * c * np.sin(c * t)
    guess = np.stack([-2 * I1 * lam**2 * sn * co / D**2 * chid**2, 2 * I1 * lam * sn**2 / D * chidd], 1)
    # continuation in the penalty's weight (the same compiled solve: the weight is an array)
    solve = eqx.filter_jit(lambda m, p, y: m.solve(p, y, 0.0))
    plan = None
    for w in (1e2, 1e4, WEIGHT):
        conv = controls.MPC(ocp, PERIOD, INTERVALS, mode="converged", horizon="shrinking", terminal="penalty",
                            terminal_weight=w, max_iter=100, hessian="exact")
        plan, status = solve(conv, conv.init(u_guess=guess if plan is None else np.asarray(plan.u)), ocp.x0)
    return np.asarray(plan.u), status


def members(n, seed=0):
    rng = np.random.default_rng(seed)
    X = np.zeros((n, 5))
    X[:, 0] = TH0 + rng.uniform(-0.1, 0.1, n)
    X[:, 1] = rng.uniform(-0.2, 0.2, n)
    X[:, 3:] = rng.uniform(-0.3, 0.3, (n, 2))
    scales = rng.uniform(0.9, 1.1, (n, 3))
    return X, scales


def plants(cat, scales):
    cats = [FallingCat(I1=cat.I1 * a, lam=cat.lam * b, B=cat.B * c) for a, b, c in scales]
    return cats, jax.tree_util.tree_map(lambda *a: jnp.stack(a), *cats)


def figure(err_deg, effort, shape_err, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    ax[0].hist(err_deg, bins=40)
    ax[0].axvline(SUCCESS_DEG, color="r", ls="--", label=f"{SUCCESS_DEG:g} deg")
    ax[0].set(xlabel="|psi(T) + pi| [deg]", ylabel="members", title="final attitude error")
    ax[0].legend()
    ax[1].hist(effort, bins=40)
    ax[1].set(xlabel="int |u|^2 dt [N^2 m^2 s]", title="effort")
    ax[2].hist(shape_err, bins=40)
    ax[2].set(xlabel="max |(theta, chi)(T) - target| [rad]", title="final shape error")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="mpc_cat", help="folder for the outputs (default: ./mpc_cat)")
    ap.add_argument("--members", type=int, default=256, help="closed loops in the batch")
    ap.add_argument("--sequential", type=int, default=32, help="members also run one by one (timed, scaled)")
    ap.add_argument("--bound", type=float, default=BOUND, help="torque bound |u_i| [N m] (default 1)")
    ap.add_argument("--mode", choices=("rti", "converged"), default=MODE, help="MPC mode (default rti)")
    ap.add_argument("--disturbance-gain", type=float, default=DISTURBANCE_GAIN,
                    help=f"the disturbance observer's gain in [0, 1] (0: off; default {DISTURBANCE_GAIN:g})")
    ap.add_argument("--workers", type=int, default=None,
                    help="threads of the batch (default: closed_loop_batch's, 2 on two or more CPUs)")
    ap.add_argument("--no-animation", action="store_true", help="skip the GIF")
    a = ap.parse_args()
    if a.members < 1 or not 1 <= a.sequential <= a.members:
        ap.error("--members >= 1 and 1 <= --sequential <= --members")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()
    if not a.bound > 0:
        ap.error("--bound must be positive")
    if not 0 <= a.disturbance_gain <= 1:
        ap.error("--disturbance-gain must lie in [0, 1]")
    if a.workers is not None and a.workers < 1:
        ap.error("--workers must be at least 1")
    cat, ocp, mpc = setup(a.bound, a.mode, a.disturbance_gain)
    u0, st = nominal_plan(ocp)
    print(f"nominal plan: converged {bool(st.converged)} in {int(st.iterations)} iterations, cost {float(st.cost):.6g}")
    X, scales = members(a.members)
    cats, stacked = plants(cat, scales)
    periods = INTERVALS  # period = interval: the whole shrinking horizon
    def run_batch():
        return controls.closed_loop_batch(mpc, stacked, X, periods, in_axes={"plant": 0}, u_guess=u0,
                                          group=BATCH_GROUP, workers=a.workers)

    def run_alone(i):
        return controls.closed_loop(mpc, cats[i], X[i], periods, u_guess=u0)

    tic = time.perf_counter()
    batch = run_batch()
    jax.block_until_ready(batch.inputs)
    first = time.perf_counter() - tic
    # one by one: the loop's program compiled first (not timed)
    jax.block_until_ready(run_alone(0).inputs)
    # interleaved rounds (the machine is shared: a round of each, twice), the best of each
    batch_times, samples = [], []
    for _ in range(ROUNDS):
        tic = time.perf_counter()
        batch = run_batch()
        jax.block_until_ready(batch.inputs)
        batch_times.append(time.perf_counter() - tic)
        tic = time.perf_counter()
        for i in range(a.sequential):
            alone = run_alone(i)
            jax.block_until_ready(alone.inputs)
        samples.append(time.perf_counter() - tic)
    batch_seconds, sample = min(batch_times), min(samples)
    sequential_seconds = sample * a.members / a.sequential
    check = float(np.abs(np.asarray(alone.inputs) - np.asarray(batch.inputs[a.sequential - 1])).max())

    xT = np.asarray(batch.trajectory.xs[:, -1])
    err_deg = np.degrees(np.abs(xT[:, 2] - TURN))
    ok = err_deg < SUCCESS_DEG
    shape_err = np.abs(xT[:, :2] - [TH0, 2 * np.pi]).max(1)
    effort = np.asarray(batch.cost)
    info = dict(command="nhjax run mpc_cat " + " ".join(sys.argv[1:]), members=a.members, periods=periods,
                period_s=PERIOD, intervals=INTERVALS, T=T, theta0=TH0, turn=TURN, mode=a.mode, horizon="shrinking",
                torque_bound=a.bound, hessian=HESSIAN, psi_scale=SCALE[2], disturbance_gain=a.disturbance_gain,
                qp_single=mpc._qp_kind(), qp_batch="riccati", batch_group=BATCH_GROUP,
                batch_workers=a.workers if a.workers is not None else "closed_loop_batch's default (2 threads on 2+ CPUs)",
                terminal=f"penalty {WEIGHT:g}", success_threshold_deg=SUCCESS_DEG,
                success_rate=float(ok.mean()),
                final_attitude_error_deg_max=float(err_deg[ok].max()) if ok.any() else None,
                final_attitude_error_deg_median=float(np.median(err_deg)),
                final_shape_error_rad_max=float(shape_err.max()),
                effort_median=float(np.median(effort)), effort_max=float(effort.max()),
                nominal_open_loop_cost=float(st.cost),
                fallbacks=int(np.asarray(batch.status.fallback).sum()),
                qp_failures=int((~np.asarray(batch.status.qp_ok)).sum()),
                batch_seconds_first_with_compile=first, batch_seconds=batch_seconds,
                sequential_seconds=sequential_seconds,
                sequential_measured=f"{a.sequential} of {a.members} loops one by one with closed_loop (compiled "
                                    f"before timing, QP {mpc._qp_kind()}), {sample:.3f} s, scaled by "
                                    f"{a.members}/{a.sequential}; the best of {ROUNDS} rounds interleaved with "
                                    "the batch's",
                batch_seconds_rounds=batch_times, sequential_sample_seconds_rounds=samples,
                batch_speedup=sequential_seconds / batch_seconds,
                batch_vs_alone_max_input_difference=check)
    print(f"{a.members} loops: success {ok.mean():.1%} (|psi(T) + pi| < {SUCCESS_DEG:g} deg), max error among the "
          f"successful {info['final_attitude_error_deg_max']} deg; batch {batch_seconds:.2f} s "
          f"({first:.1f} s with compile), one by one {sequential_seconds:.2f} s (scaled from {a.sequential}); "
          f"fallbacks {info['fallbacks']}")
    load_end = os.getloadavg()
    info.update(load_average=[load_start[0], load_end[0]], load_average_start=list(load_start),
                load_average_end=list(load_end))
    (out / "mpc_cat.json").write_text(json.dumps(info, indent=1))
    figure(err_deg, effort, shape_err, out / "mpc_cat.png")
    if not a.no_animation:
        from nhjax import plotting

        worst = int(np.argmax(err_deg))
        ts = np.asarray(batch.trajectory.ts)
        ts = ts[worst] if ts.ndim == 2 else ts
        plotting.somersault_animation(cats[worst], ts, np.asarray(batch.trajectory.xs[worst])[:, :3],
                                      out / "mpc_cat.gif", frames=40)
        print(f"animation: member {worst}, the farthest from the target turn "
              f"(|psi(T) + pi| = {err_deg[worst]:.3f} deg)")
    print(f"load average {load_start[0]:.2f} -> {load_end[0]:.2f}; wrote {out}/mpc_cat.json, .png"
          + ("" if a.no_animation else " and .gif"))


if __name__ == "__main__":
    main()
