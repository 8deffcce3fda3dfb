"""Work-precision of the rolling scenes in each formulation, against SciPy and Numba (issue #3).

Measured in one run on one machine (/work/shared/BENCHMARKS.md): for every
formulation (nhjax) and peer (SciPy ``solve_ivp`` RK45/DOP853 on a NumPy
right-hand side, a Numba-compiled adaptive Dormand-Prince 5(4) with diffrax's
step-size control, see ``peers/rolling.py``) and every rtol = atol in
1e-3 .. 1e-12: the error, accepted steps (SciPy: also right-hand-side
evaluations, since DOP853 rejects many steps at loose tolerances), and the
median wall time of >= 5 solves (and >= 0.5 s of solving) after compile. A
combination is skipped when one solve would take more than 10 s (predicted
from the previous tolerance with the method's order, or measured): on the
reference machine (2 cores, shared) this drops SciPy RK45 on the shell and
ShellWithTopLagrangian at rtol 1e-11 and 1e-12 (11-25 s per solve each,
depending on the load), which with a 60 s limit and 120 s long runs made the
whole run 31 min; with 10 s and 90 s it takes about 16 min. The skipped cells
are listed in the output. The load average at start and end is printed and
stored in the JSON.

nhjax is timed as the solve jitted end to end,
``jax.jit(lambda x0, rtol: nhjax.simulate(..., saveat=2, diagnostics=False,
track_work=False).xs)`` (rtol traced: one compile per formulation); its compile
time is the first call minus a later one. Errors and step counts come from a
separate, untimed run that saves at many times (same steps: saving uses dense
output and does not clip steps; the row's ``timed_vs_measured`` is the largest
difference between the final states of the two runs, which checks this). Default solver everywhere (``nhjax.RKMK45``:
DP5(4), on SO(3) parts its Munthe-Kaas version) plus diffrax Dopri8 for two
vector-state formulations and ``nhjax.RKMK87`` (8th order, Munthe-Kaas) for
``ShellWithTop``.

Scene 1 -- rolling disk (seed 002), circular motion of the tests: J1 = 0.35,
J2 = 0.5, theta0 = 0.25, q0 = 2.17080452, ten orbits (t = 79.77). This is an
exact solution (contact point on the circle of radius 1/q0, constant tilt and
rates), used as the reference. Formulations: ``RollingDisk`` (minimal
coordinates, equations by autodiff), the same with Dopri8, and
``RollingDiskQuaternion`` (R^3 x S^3, position constraints, projected after
every step: simulate's default). Peers integrate the hand-derived minimal
equations (checked here against ``RollingDisk().vector_field`` to 1e-12 on
random consistent states). Errors: final-state error = max abs error of the
physical state at t = 10 orbits (contact point, centre, rotation matrix, centre
velocity, spatial angular velocity), comparable across coordinates; radius =
max over 1001 saved times of | |contact point| - 1/q0 |; energy drift (relative).

Scene 2 -- spherical shell with a top, no torque (seed 003), ShellWithTopReduced's
default parameters (a general top), omega0 = (2, -1, 3), ten turns of the top
(a turn = 2 pi / |omega0| = 1.679 s). Formulations: ``ShellWithTopReduced``
(17-vector, hand equations; default: frame (alpha, beta, gamma) projected onto
SO(3) after every step), the same unprojected, the same with Dopri8,
``ShellWithTop`` (Hamel equations by autodiff on R^2 x SO(3) x SO(3), RKMK45)
and ``ShellWithTopLagrangian`` (rotation vectors on the engine). All start from
the same physical state (the shell's attitude: identity). Peers integrate the
reduced equations. Reference: SciPy DOP853 at 1e-13 on the reduced equations,
checked against nhjax Dopri8 at 1e-13. Errors: final error = max abs error of
(omega, gamma, contact point) at t = 10 turns; drifts over 501 saved times of
the total energy (relative to kinetic energy + mt g |c|), |K| (Chaplygin's
vector, relative) and |gamma|^2 (absolute), evaluated on every formulation's
states mapped to the reduced 17-vector.

Long runs: drift of energy and |K| per 1000 turns of the top for
ShellWithTopReduced and ShellWithTop at rtol = atol = 1e-10, running as many
turns as fit in about 90 s each (in segments) and extrapolating the drift
linearly (least-squares slope of drift against turns).

Writes experiments/out/bench/rolling_work_precision.{csv,json,png}.
"""

from __future__ import annotations

import csv
import json
import os
import platform
import sys
import time
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import nhjax
from nhjax.lie import so3
from nhjax.scenes import (
    RollingDisk,
    ShellWithTop,
    ShellWithTopLagrangian,
    ShellWithTopReduced,
)

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "peers"))
sys.path.insert(0, str(HERE))
import rolling as peers  # noqa: E402
import _timing  # noqa: E402

OUT = HERE.parent / "experiments" / "out" / "bench"
RTOLS = [10.0**-k for k in range(3, 13)]
MAX_SOLVE_SECONDS = 10.0
MAX_STEPS = 1_000_000
LONG_RUN_SECONDS = 90.0
E3 = jnp.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------- timing
def median_time(fn, min_repeats=5):
    return _timing.median_time(fn, repeats=min_repeats, min_total=0.5)


def wall(fn):
    t = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t


class Sweep:
    """Runs one solver over RTOLS with the MAX_SOLVE_SECONDS rule; ``measure(rtol)`` returns a row
    dict (errors, steps) and ``timed(rtol)`` one solve (for the median)."""

    def __init__(self, scene, solver, kind, compile_seconds=0.0, order=5):
        self.scene, self.solver, self.kind = scene, solver, kind
        self.compile_seconds, self.growth = compile_seconds, 10 ** (1 / order) * 1.15
        self.rows, self.skipped = [], []

    def run(self, measure, timed):
        last = None
        for rtol in RTOLS:
            if last is not None and last * self.growth > MAX_SOLVE_SECONDS:
                self.skipped.append(dict(scene=self.scene, solver=self.solver, rtol=rtol,
                                         reason=f"predicted {last * self.growth:.0f} s per solve"))
                continue
            _, first = wall(lambda: timed(rtol))
            if first > MAX_SOLVE_SECONDS:
                self.skipped.append(dict(scene=self.scene, solver=self.solver, rtol=rtol,
                                         reason=f"one solve took {first:.0f} s"))
                last = first
                continue
            row = measure(rtol)
            sec = median_time(lambda: timed(rtol))
            row.update(scene=self.scene, solver=self.solver, kind=self.kind, rtol=rtol, seconds=sec,
                       compile_seconds=self.compile_seconds)
            self.rows.append(row)
            last = sec
            print(f"  {self.solver:34s} rtol {rtol:7.0e}  err {row['error']:9.2e}  steps {row['steps']:7d}  "
                  f"{sec * 1e3:10.3f} ms", flush=True)
        return self.rows


def jit_solver(system, t1, *, solver=None, project_steps=None):
    """The timed nhjax program: x0, rtol -> saved states at t0 and t1."""
    kw = {} if solver is None else {"solver": solver}
    if project_steps is not None:
        kw["project_steps"] = project_steps

    @jax.jit
    def run(x0, rtol):
        return nhjax.simulate(system, x0, t1, saveat=2, rtol=rtol, atol=rtol, diagnostics=False,
                              track_work=False, max_steps=MAX_STEPS, **kw).xs

    return run


def final_diff(timed_xs, saved_xs):
    """Largest difference between the final states of the timed run (saveat=2) and the
    measured run (dense saves): they take the same steps, so this should be ~0."""
    a = jax.tree_util.tree_leaves(jax.tree_util.tree_map(lambda v: v[-1], timed_xs))
    b = jax.tree_util.tree_leaves(jax.tree_util.tree_map(lambda v: v[-1], saved_xs))
    return float(max(np.abs(np.asarray(x) - np.asarray(y)).max() for x, y in zip(a, b)))


def compile_seconds(run, x0):
    _, first = wall(lambda: run(x0, 1e-6))
    later = median_time(lambda: run(x0, 1e-6), min_repeats=3)
    return max(first - later, 0.0)


# =========================================================================== scene 1: disk
DISK = peers.DISK_DEFAULT


def disk_models():
    c = DISK
    disk = RollingDisk(m=c["m"], r=c["r"], g=c["g"], J1=c["J1"], J2=c["J2"])
    return disk, disk.quaternion_model()


def check_disk_equations(disk, n=50, seed=0):
    """Hand equations (peers) against the engine's vector field on random consistent
    states; returns the largest relative difference (asserted < 1e-12)."""
    rng = np.random.default_rng(seed)
    p = peers.disk_params(DISK)
    field = jax.jit(lambda x: disk.vector_field(0.0, x, None))
    worst = 0.0
    for _ in range(n):
        v = rng.normal(size=8)
        v[3] = rng.uniform(-1.3, 1.3)  # tilt inside the chart
        x = np.asarray(disk.initial_state(*v[:5], phi_dot=v[5], theta_dot=v[6], psi_dot=v[7]))
        f_engine = np.asarray(field(x))
        f_np = peers.disk_rhs_numpy(0.0, x, p)
        f_nb = np.empty(10)
        peers.disk_rhs_numba(0.0, x, p, f_nb)
        scale = np.abs(f_engine).max()
        worst = max(worst, np.abs(f_np - f_engine).max() / scale, np.abs(f_nb - f_engine).max() / scale)
    assert worst < 1e-12, f"hand disk equations differ from RollingDisk.vector_field by {worst:.1e}"
    return worst


def disk_physical_min(disk):
    """Minimal state (10,) -> (contact xy, centre u, R (9), u', w_space)."""

    def phys(x):
        q, qd = x[:5], x[5:]
        (R, u), (Rd, ud) = jax.jvp(disk.pose, (q,), (qd,))
        return jnp.concatenate([x[:2], u, R.ravel(), ud, so3.vee(Rd @ R.T)])

    return jax.jit(jax.vmap(phys))


def disk_physical_quat(quat):
    def phys(y):
        p = y[3:7] / jnp.linalg.norm(y[3:7])
        R = so3.quat_to_matrix(p)
        w = 2 * so3.quat_mul(y[10:14], so3.quat_conj(p))[1:]
        return jnp.concatenate([quat.contact_point(y[:7])[:2], y[:3], R.ravel(), y[7:10], w])

    return jax.jit(jax.vmap(phys))


def disk_scene():
    print("\n=== Scene 1: rolling disk, circular motion, 10 orbits", flush=True)
    disk, quat = disk_models()
    hand_check = check_disk_equations(disk)
    print(f"hand-derived disk equations vs RollingDisk.vector_field (50 random consistent states): "
          f"max rel. diff {hand_check:.1e}")
    p = peers.disk_params(DISK)
    x0 = peers.disk_circular_state(DISK)
    assert np.abs(x0 - np.asarray(disk.circular_state(DISK["theta0"], DISK["q0"]))).max() == 0.0
    period = peers.disk_period(DISK)
    T = DISK["orbits"] * period
    ts = np.linspace(0.0, T, 1001)
    y0 = disk.to_quaternion_state(jnp.asarray(x0))
    phys_min, phys_quat = disk_physical_min(disk), disk_physical_quat(quat)
    exact = peers.disk_exact(ts, DISK)
    P_exact_T = np.asarray(phys_min(jnp.asarray(exact[-1:])))[0]
    map_check = float(np.abs(np.asarray(phys_quat(y0[None])) - np.asarray(phys_min(jnp.asarray(x0)[None]))).max())
    R0 = 1.0 / DISK["q0"]
    E0 = float(disk.energy(jnp.asarray(x0)))
    energy_min = jax.jit(jax.vmap(disk.energy))
    energy_quat = jax.jit(jax.vmap(quat.energy))

    def errors_min(Xs, energies=None):
        Xs = np.asarray(Xs)
        P_T = np.asarray(phys_min(jnp.asarray(Xs[-1:])))[0]
        E = np.asarray(energy_min(jnp.asarray(Xs))) if energies is None else energies
        return dict(error=float(np.abs(P_T - P_exact_T).max()),
                    radius=float(np.abs(np.hypot(Xs[:, 0], Xs[:, 1]) - R0).max()),
                    energy=float(np.abs(E - E0).max() / abs(E0)),
                    state_error=float(np.abs(Xs[-1] - exact[-1]).max()))

    def errors_quat(Ys):
        Ys = jnp.asarray(Ys)
        P = np.asarray(phys_quat(Ys))
        E = np.asarray(energy_quat(Ys))
        return dict(error=float(np.abs(P[-1] - P_exact_T).max()),
                    radius=float(np.abs(np.hypot(P[:, 0], P[:, 1]) - R0).max()),
                    energy=float(np.abs(E - E0).max() / abs(E0)), state_error=float("nan"))

    # references: the exact solution; a DOP853 run and an nhjax Dopri8 run at 1e-13 against it
    dop = peers.solve_scipy(peers.disk_rhs_numpy, x0, T, "DOP853", 1e-13, 1e-13, p, t_eval=ts)
    d8 = nhjax.simulate(disk, x0, T, saveat=ts, solver=diffrax.Dopri8(), rtol=1e-13, atol=1e-13, max_steps=MAX_STEPS)
    ref_checks = {
        "hand_equations_vs_engine_max_rel": hand_check,
        "physical_state_minimal_vs_quaternion_at_t0": map_check,
        "scipy_DOP853_1e-13_vs_exact": errors_min(dop["ys"]),
        "nhjax_Dopri8_1e-13_vs_exact": errors_min(d8.xs),
    }
    print("reference = exact circular motion; at 1e-13: DOP853 final err "
          f"{ref_checks['scipy_DOP853_1e-13_vs_exact']['error']:.1e}, radius "
          f"{ref_checks['scipy_DOP853_1e-13_vs_exact']['radius']:.1e}; nhjax Dopri8 final err "
          f"{ref_checks['nhjax_Dopri8_1e-13_vs_exact']['error']:.1e}, radius "
          f"{ref_checks['nhjax_Dopri8_1e-13_vs_exact']['radius']:.1e}")

    rows, skipped, compiles = [], [], {}

    # --- peers
    for method, order in (("RK45", 5), ("DOP853", 8)):
        def measure(rtol, method=method):
            out = peers.solve_scipy(peers.disk_rhs_numpy, x0, T, method, rtol, rtol, p)
            dense = peers.solve_scipy(peers.disk_rhs_numpy, x0, T, method, rtol, rtol, p, t_eval=ts)
            return dict(errors_min(dense["ys"]), steps=out["nsteps"], nfev=out["nfev"], note="solve_ivp, NumPy RHS")

        sw = Sweep("disk", f"scipy {method}", "peer", order=order)
        rows += sw.run(measure, lambda rtol, method=method: peers.solve_scipy(
            peers.disk_rhs_numpy, x0, T, method, rtol, rtol, p)["y1"])
        skipped += sw.skipped

    _, first = wall(lambda: peers.solve_numba(peers.dp54_disk, x0, T, 1e-6, 1e-6, p, t_save=ts))
    _, first2 = wall(lambda: peers.solve_numba(peers.dp54_disk, x0, T, 1e-6, 1e-6, p))
    compiles["numba DP5"] = first - first2

    def measure_numba(rtol):
        y1, n_acc, n_rej, Ys = peers.solve_numba(peers.dp54_disk, x0, T, rtol, rtol, p, t_save=ts)
        return dict(errors_min(Ys), steps=n_acc, note="@njit DP5(4), diffrax PID rules")

    sw = Sweep("disk", "numba DP5", "peer", compile_seconds=compiles["numba DP5"])
    rows += sw.run(measure_numba, lambda rtol: peers.solve_numba(peers.dp54_disk, x0, T, rtol, rtol, p)[0])
    skipped += sw.skipped

    # --- nhjax
    formulations = [
        ("RollingDisk", disk, jnp.asarray(x0), {}, errors_min, 5, "minimal coordinates, RKMK45 (= DP5)"),
        ("RollingDisk Dopri8", disk, jnp.asarray(x0), {"solver": diffrax.Dopri8()}, errors_min, 8,
         "minimal coordinates, diffrax Dopri8"),
        ("RollingDiskQuaternion", quat, y0, {}, errors_quat, 5,
         "R^3 x S^3, RKMK45, projected after each step (default), no Baumgarte terms (default)"),
    ]
    for name, system, z0, kw, errs, order, note in formulations:
        run = jit_solver(system, T, **kw)
        compiles[name] = compile_seconds(run, z0)
        print(f"  {name}: compile {compiles[name]:.1f} s", flush=True)

        def measure(rtol, system=system, z0=z0, kw=kw, errs=errs, note=note, run=run):
            tr = nhjax.simulate(system, z0, T, saveat=ts, rtol=rtol, atol=rtol, max_steps=MAX_STEPS, **kw)
            e = errs(tr.xs)
            cons = {k: float(v) for k, v in tr.constraint_drift.items()}
            return dict(e, steps=int(tr.num_accepted_steps), rejected=int(tr.num_rejected_steps),
                        constraint_drift=cons, timed_vs_measured=final_diff(run(z0, rtol), tr.xs), note=note)

        sw = Sweep("disk", f"nhjax {name}", "nhjax", compile_seconds=compiles[name], order=order)
        rows += sw.run(measure, lambda rtol, run=run, z0=z0: run(z0, rtol))
        skipped += sw.skipped

    return dict(rows=rows, skipped=skipped, compile_seconds=compiles, reference_checks=ref_checks,
                case=dict(DISK, t1=T, period=period, rolling_rate=float(x0[9]), x0=x0.tolist()))


# =========================================================================== scene 2: shell
SHELL = peers.SHELL_DEFAULT


def shell_models():
    c = SHELL
    kw = dict(ms=c["ms"], Rs=c["Rs"], Is=c["Is"], mt=c["mt"], It=np.asarray(c["It"]), c=c["c"], g=c["g"])
    red = ShellWithTopReduced(case="general", **kw)
    # chart_eps = 0: no chart guard, so the rotation vectors may cross |theta| = 2 pi over
    # the 10 turns (the default guard stops there; see ShellWithTopLagrangian)
    lag = ShellWithTopLagrangian(ms=red.ms, Rs=red.Rs, Is=red.Is, mt=red.mt, It=red.It, c=red.c, g=red.g,
                                 chart_eps=0.0)
    return red, ShellWithTop(**kw), lag


def check_shell_equations(red, n=50, seed=1):
    rng = np.random.default_rng(seed)
    p = peers.shell_params(SHELL)
    field = jax.jit(lambda x: red.vector_field(0.0, x, None))
    worst = 0.0
    for _ in range(n):
        x = np.asarray(red.initial_state(rng.normal(size=3) * 3, attitude=rng.normal(size=3),
                                         shell_velocity=rng.normal(size=2) * 0.3, shell_spin=rng.normal(),
                                         position=rng.normal(size=2)))
        f = np.asarray(field(x))
        f_np = peers.shell_rhs_numpy(0.0, x, p)
        f_nb = np.empty(17)
        peers.shell_rhs_numba(0.0, x, p, f_nb)
        scale = np.abs(f).max()
        worst = max(worst, np.abs(f_np - f).max() / scale, np.abs(f_nb - f).max() / scale)
    assert worst < 1e-12, f"NumPy shell equations differ from ShellWithTopReduced by {worst:.1e}"
    return worst


def robot_state(rob, x):
    """ShellWithTop state from the reduced 17-vector (shell attitude: identity)."""
    Rt = jnp.stack([x[9:12], x[12:15], x[6:9]])  # rows alpha, beta, gamma: top -> space
    Om_space = Rt @ x[3:6]
    V = jnp.cross(Om_space, rob.Rs * E3)  # rolling: V = Omega x (Rs e3)
    return (x[15:17], jnp.eye(3), Rt), jnp.concatenate([V[:2], Om_space, x[0:3]])


def robot_to_reduced(y):
    (xy, Rsh, Rt), v = y
    return jnp.concatenate([v[5:8], Rt.T @ Rsh @ v[2:5], Rt[2], Rt[0], Rt[1], xy])


def _body_rate_matrix(th):
    """omega_body = B(theta) theta' for R = exp(hat(theta))."""
    f = lambda thd: so3.vee(so3.exp(th).T @ jax.jvp(so3.exp, (th,), (thd,))[1])  # noqa: E731
    return jax.jacfwd(f)(jnp.zeros(3))


def lagrangian_state(lag, x):
    """ShellWithTopLagrangian state (q, q') from the reduced 17-vector (shell: identity)."""
    Rt = jnp.stack([x[9:12], x[12:15], x[6:9]])
    tht, ths = so3.log(Rt), jnp.zeros(3)
    thd_t = jnp.linalg.solve(_body_rate_matrix(tht), x[0:3])
    thd_s = jnp.linalg.solve(_body_rate_matrix(ths), Rt @ x[3:6])  # shell body = space at identity
    q = jnp.concatenate([x[15:17], ths, tht])
    qd = jnp.concatenate([jnp.zeros(2), thd_s, thd_t])
    qd = qd.at[0:2].add(-lag.velocity_constraints(0.0, q, qd))
    return jnp.concatenate([q, qd])


def shell_scene():
    print("\n=== Scene 2: shell with a top, no torque, 10 turns of the top", flush=True)
    red, rob, lag = shell_models()
    hand_check = check_shell_equations(red)
    print(f"NumPy/Numba reduced equations vs ShellWithTopReduced.vector_field: max rel. diff {hand_check:.1e}")
    p = peers.shell_params(SHELL)
    x0 = peers.shell_initial_state(SHELL)
    period = peers.shell_period(SHELL)
    T = SHELL["orbits"] * period
    ts = np.linspace(0.0, T, 501)
    yr0 = robot_state(rob, jnp.asarray(x0))
    z0 = lagrangian_state(lag, jnp.asarray(x0))
    map_checks = {
        "ShellWithTop": float(jnp.abs(robot_to_reduced(yr0) - x0).max()),
        "ShellWithTopLagrangian": float(jnp.abs(lag.reduced_state(z0[:8], z0[8:]) - x0).max()),
        "ShellWithTop_field_omega_dot": float(jnp.abs(rob.vector_field(0.0, yr0, jnp.zeros(3))[1][5:8]
                                                      - red.vector_field(0.0, jnp.asarray(x0), None)[0:3]).max()),
    }
    to_red = {
        "reduced": lambda X: np.asarray(X),
        "robot": jax.jit(jax.vmap(robot_to_reduced)),
        "lagrangian": jax.jit(jax.vmap(lambda z: lag.reduced_state(z[:8], z[8:]))),
    }
    E_kin0 = float(peers.shell_energy(x0, p) - p[3] * p[4] * (x0[6:9] @ p[7:10]))
    E_scale = E_kin0 + p[3] * p[4] * np.linalg.norm(p[7:10])
    K0 = float(np.linalg.norm(peers.shell_K_space(x0, p)))
    idx = [0, 1, 2, 6, 7, 8, 15, 16]  # omega, gamma, contact point

    ref = peers.solve_scipy(peers.shell_rhs_numpy, x0, T, "DOP853", 1e-13, 1e-13, p, t_eval=ts)["ys"]
    d8 = nhjax.simulate(red, jnp.asarray(x0), T, saveat=ts, solver=diffrax.Dopri8(), rtol=1e-13, atol=1e-13,
                        project_steps=False, max_steps=MAX_STEPS)
    ref_vs_d8 = np.abs(np.asarray(d8.xs) - ref)[:, idx]

    def errors(X):
        X = np.asarray(X)
        E = peers.shell_energy(X, p)
        K = np.linalg.norm(peers.shell_K_space(X, p), axis=-1)
        g2 = np.sum(X[:, 6:9] ** 2, -1)
        d = np.abs(X[-1] - ref[-1])
        return dict(error=float(d[idx].max()), error_omega=float(d[0:3].max()), error_gamma=float(d[6:9].max()),
                    error_contact=float(d[15:17].max()),
                    energy=float(np.abs(E - E[0]).max() / E_scale),
                    K=float(np.abs(K - K[0]).max() / K0), gamma_sq=float(np.abs(g2 - 1.0).max()))

    ref_checks = {
        "numpy_equations_vs_engine_max_rel": hand_check,
        "initial_state_maps": map_checks,
        "scipy_DOP853_1e-13_vs_nhjax_Dopri8_1e-13_final": float(ref_vs_d8[-1].max()),
        "scipy_DOP853_1e-13_vs_nhjax_Dopri8_1e-13_max_over_saved": float(ref_vs_d8.max()),
        "reference_drifts": errors(ref),
        "energy_scale_J": E_scale,
        "K0_m_per_s": K0,
    }
    print(f"reference DOP853 1e-13 vs nhjax Dopri8 1e-13 (omega, gamma, contact): final "
          f"{ref_vs_d8[-1].max():.1e}, max over saved {ref_vs_d8.max():.1e}")
    print(f"initial-state maps: {map_checks}")

    rows, skipped, compiles = [], [], {}
    for method, order in (("RK45", 5), ("DOP853", 8)):
        def measure(rtol, method=method):
            out = peers.solve_scipy(peers.shell_rhs_numpy, x0, T, method, rtol, rtol, p)
            dense = peers.solve_scipy(peers.shell_rhs_numpy, x0, T, method, rtol, rtol, p, t_eval=ts)
            return dict(errors(dense["ys"]), steps=out["nsteps"], nfev=out["nfev"],
                        note="solve_ivp, NumPy RHS (np.cross, np.linalg.solve)")

        sw = Sweep("shell", f"scipy {method}", "peer", order=order)
        rows += sw.run(measure, lambda rtol, method=method: peers.solve_scipy(
            peers.shell_rhs_numpy, x0, T, method, rtol, rtol, p)["y1"])
        skipped += sw.skipped

    _, first = wall(lambda: peers.solve_numba(peers.dp54_shell, x0, T, 1e-6, 1e-6, p, t_save=ts))
    _, first2 = wall(lambda: peers.solve_numba(peers.dp54_shell, x0, T, 1e-6, 1e-6, p))
    compiles["numba DP5"] = first - first2

    def measure_numba(rtol):
        y1, n_acc, n_rej, Ys = peers.solve_numba(peers.dp54_shell, x0, T, rtol, rtol, p, t_save=ts)
        return dict(errors(Ys), steps=n_acc, note="@njit DP5(4), diffrax PID rules")

    sw = Sweep("shell", "numba DP5", "peer", compile_seconds=compiles["numba DP5"])
    rows += sw.run(measure_numba, lambda rtol: peers.solve_numba(peers.dp54_shell, x0, T, rtol, rtol, p)[0])
    skipped += sw.skipped

    xr0 = jnp.asarray(x0)
    formulations = [
        ("ShellWithTopReduced", red, xr0, {}, "reduced", 5, "17-vector, RKMK45 (= DP5), frame projected (default)"),
        ("ShellWithTopReduced unprojected", red, xr0, {"project_steps": False}, "reduced", 5,
         "17-vector, RKMK45 (= DP5), project_steps=False"),
        ("ShellWithTopReduced Dopri8", red, xr0, {"solver": diffrax.Dopri8()}, "reduced", 8,
         "17-vector, diffrax Dopri8, frame projected (default)"),
        ("ShellWithTop", rob, yr0, {}, "robot", 5, "Hamel equations on R^2 x SO(3) x SO(3), RKMK45"),
        ("ShellWithTop RKMK87", rob, yr0, {"solver": nhjax.RKMK87(scan_stages=True)}, "robot", 8,
         "Hamel equations on R^2 x SO(3) x SO(3), RKMK87 (stages in a scan, as RKMK45's here)"),
        ("ShellWithTopLagrangian", lag, z0, {}, "lagrangian", 5, "rotation vectors on the engine, RKMK45 (= DP5), chart guard off"),
    ]
    for name, system, s0, kw, mapping, order, note in formulations:
        run = jit_solver(system, T, **kw)
        compiles[name] = compile_seconds(run, s0)
        print(f"  {name}: compile {compiles[name]:.1f} s", flush=True)

        def measure(rtol, system=system, s0=s0, kw=kw, mapping=mapping, note=note, run=run):
            tr = nhjax.simulate(system, s0, T, saveat=ts, rtol=rtol, atol=rtol, max_steps=MAX_STEPS, **kw)
            e = errors(to_red[mapping](tr.xs))
            cons = {k: float(v) for k, v in tr.constraint_drift.items()}
            row = dict(e, steps=int(tr.num_accepted_steps), rejected=int(tr.num_rejected_steps),
                       constraint_drift=cons, timed_vs_measured=final_diff(run(s0, rtol), tr.xs), note=note)
            if mapping == "lagrangian":
                row["max_rotation_vector_norm"] = float(max(np.linalg.norm(tr.xs[:, 2:5], axis=1).max(),
                                                            np.linalg.norm(tr.xs[:, 5:8], axis=1).max()))
            return row

        sw = Sweep("shell", f"nhjax {name}", "nhjax", compile_seconds=compiles[name], order=order)
        rows += sw.run(measure, lambda rtol, run=run, s0=s0: run(s0, rtol))
        skipped += sw.skipped

    return dict(rows=rows, skipped=skipped, compile_seconds=compiles, reference_checks=ref_checks,
                case=dict(SHELL, t1=T, period=period, x0=x0.tolist()),
                models=dict(red=red, rob=rob, x0=x0, yr0=yr0, period=period, p=p, E_scale=E_scale, K0=K0))


# =========================================================================== long runs
def long_run(name, system, s0, to_reduced, period, p, E_scale, K0, rtol=1e-10, budget=LONG_RUN_SECONDS):
    """Segments of whole turns of the top until ``budget`` seconds are used; the
    drift of energy and |K| is fitted linearly against the number of turns."""

    @jax.jit
    def segment(s, t0, t1):
        tr = nhjax.simulate(system, s, t1, t0=t0, saveat=2, rtol=rtol, atol=rtol, diagnostics=False,
                            track_work=False, max_steps=20_000_000)
        return jax.tree_util.tree_map(lambda a: a[-1], tr.xs), tr.num_accepted_steps

    x_red0 = np.asarray(to_reduced(s0))
    E_0 = float(peers.shell_energy(x_red0, p))
    K_0 = float(np.linalg.norm(peers.shell_K_space(x_red0, p)))
    _, c_time = wall(lambda: segment(s0, 0.0, period))  # compile (+ one turn, discarded)
    # size the segments: ~1/12 of the budget each
    _, t10 = wall(lambda: segment(s0, 0.0, 10 * period))
    per_turn = t10 / 10
    seg_turns = max(10, int(budget / 12 / per_turn))
    s, turns, steps, elapsed = s0, 0, 0, 0.0
    hist = [(0, 0.0, 0.0, 0.0)]
    while elapsed < budget:
        t0, t1 = turns * period, (turns + seg_turns) * period
        (s, n), dt = wall(lambda s=s, t0=t0, t1=t1: segment(s, t0, t1))
        elapsed += dt
        turns += seg_turns
        steps += int(n)
        xr = np.asarray(to_reduced(s))
        dE = (float(peers.shell_energy(xr, p)) - E_0) / E_scale
        dK = (float(np.linalg.norm(peers.shell_K_space(xr, p))) - K_0) / K0
        hist.append((turns, dE, dK, float(abs(xr[6:9] @ xr[6:9] - 1))))
    h = np.array(hist)
    slope_E = float(np.linalg.lstsq(h[:, :1], h[:, 1], rcond=None)[0][0]) * 1000
    slope_K = float(np.linalg.lstsq(h[:, :1], h[:, 2], rcond=None)[0][0]) * 1000
    out = dict(formulation=name, rtol=rtol, turns=int(turns), seconds=elapsed, steps=steps,
               compile_plus_one_turn_seconds=c_time, steps_per_turn=steps / turns,
               energy_drift_per_1000_turns=slope_E, K_drift_per_1000_turns=slope_K,
               energy_drift_final=float(h[-1, 1]), K_drift_final=float(h[-1, 2]),
               gamma_sq_error_final=float(h[-1, 3]),
               max_abs_energy_drift=float(np.abs(h[:, 1]).max()), max_abs_K_drift=float(np.abs(h[:, 2]).max()),
               history=h.tolist())
    print(f"  {name:22s}: {turns} turns in {elapsed:.0f} s ({steps / turns:.0f} steps/turn); drift per 1000 turns "
          f"(linear fit, relative): energy {slope_E:+.2e}, |K| {slope_K:+.2e}; at the end: energy "
          f"{h[-1, 1]:+.2e}, |K| {h[-1, 2]:+.2e}", flush=True)
    return out


def long_runs(models):
    print(f"\n=== Long runs: rtol = atol = 1e-10, about {LONG_RUN_SECONDS:.0f} s each", flush=True)
    red, rob, x0 = models["red"], models["rob"], models["x0"]
    args = (models["period"], models["p"], models["E_scale"], models["K0"])
    return [
        long_run("ShellWithTopReduced", red, jnp.asarray(x0), lambda s: s, *args),
        long_run("ShellWithTop", rob, models["yr0"], robot_to_reduced, *args),
    ]


# =========================================================================== output
def plot(disk, shell, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(13, 11.5))
    panels = [
        (axes[0, 0], disk["rows"], "error", "final physical-state error (max abs) vs exact",
         f"Rolling disk, circular motion, {DISK['orbits']} orbits"),
        (axes[1, 0], disk["rows"], "radius", "max | |contact point| - 1/q0 |", "Rolling disk: radius of the path"),
        (axes[0, 1], shell["rows"], "error", "final error of (omega, gamma, contact point) (max abs)",
         f"Shell with top, no torque, {SHELL['orbits']} turns of the top"),
        (axes[1, 1], shell["rows"], "energy", "max relative energy drift", "Shell with top: energy drift"),
    ]
    for i, (ax, rows, key, ylabel, title) in enumerate(panels):
        for solver in dict.fromkeys(r["solver"] for r in rows):
            rs = [r for r in rows if r["solver"] == solver]
            style = "s--" if solver.startswith(("scipy", "numba")) else "o-"
            ax.loglog([r["seconds"] for r in rs], [max(r[key], 1e-17) for r in rs], style, label=solver, ms=3)
        ax.set_xlabel("wall time per solve after compile [s]")
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        if i in (1, 3):  # one legend per scene, under its lower panel (keeps the curves visible)
            ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, frameon=False)
    fig.suptitle("rtol = atol = 1e-3 .. 1e-12 (peers dashed); nhjax jitted (saveat=2, diagnostics off); "
                 "lower left = more accurate and faster", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def print_tables(disk, shell, longs):
    print("\n" + "=" * 118)
    print("Scene 1: rolling disk, 10 orbits (t = {:.2f}); reference: exact circular motion".format(disk["case"]["t1"]))
    print(f"{'solver':34s} {'rtol':>7s} {'final err':>9s} {'radius':>9s} {'energy':>9s} {'steps':>7s} "
          f"{'time':>11s} {'compile':>8s}")
    for r in disk["rows"]:
        print(f"{r['solver']:34s} {r['rtol']:7.0e} {r['error']:9.2e} {r['radius']:9.2e} {r['energy']:9.2e} "
              f"{r['steps']:7d} {r['seconds'] * 1e3:9.3f}ms {r['compile_seconds']:7.2f}s")
    print("\nScene 2: shell with top, 10 turns of the top (t = {:.2f}); reference: DOP853 1e-13".format(
        shell["case"]["t1"]))
    print(f"{'solver':34s} {'rtol':>7s} {'final err':>9s} {'energy':>9s} {'|K|':>9s} {'gamma^2':>9s} "
          f"{'steps':>7s} {'time':>11s} {'compile':>8s}")
    for r in shell["rows"]:
        print(f"{r['solver']:34s} {r['rtol']:7.0e} {r['error']:9.2e} {r['energy']:9.2e} {r['K']:9.2e} "
              f"{r['gamma_sq']:9.2e} {r['steps']:7d} {r['seconds'] * 1e3:9.3f}ms {r['compile_seconds']:7.2f}s")
    skipped = disk["skipped"] + shell["skipped"]
    if skipped:
        print(f"\nskipped (> {MAX_SOLVE_SECONDS:.0f} s per solve):")
        for s in skipped:
            print(f"  {s['scene']:5s} {s['solver']:34s} rtol {s['rtol']:7.0e}: {s['reason']}")
    print("\ncompile times [s] (first call minus a later one; nhjax: the jitted saveat=2 program):")
    for scene in (disk, shell):
        print("  " + ", ".join(f"{k} {v:.1f}" for k, v in scene["compile_seconds"].items()))
    print("\nLong runs at rtol = atol = 1e-10 (drift relative to the energy scale / |K0|; per 1000 turns "
          "= least-squares slope x 1000, a linear extrapolation from the turns actually run):")
    for L in longs:
        print(f"  {L['formulation']:22s} {L['turns']:6d} turns in {L['seconds']:5.0f} s: energy "
              f"{L['energy_drift_per_1000_turns']:+.2e}/1000 turns (end {L['energy_drift_final']:+.2e}), |K| "
              f"{L['K_drift_per_1000_turns']:+.2e}/1000 turns (end {L['K_drift_final']:+.2e})")


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    import numba
    import scipy

    start = time.perf_counter()
    load_start = os.getloadavg()
    print(f"load average at start (1, 5, 15 min): {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}",
          flush=True)
    disk = disk_scene()
    shell = shell_scene()
    models = shell.pop("models")
    longs = long_runs(models)
    rows = disk["rows"] + shell["rows"]
    fields = ["scene", "solver", "kind", "rtol", "error", "radius", "energy", "K", "gamma_sq", "state_error",
              "error_omega", "error_gamma", "error_contact", "steps", "rejected", "nfev", "seconds", "compile_seconds",
              "timed_vs_measured",
              "max_rotation_vector_norm", "note"]
    with open(OUT / "rolling_work_precision.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    meta = dict(
        machine=dict(platform=platform.platform(), processor=platform.processor(), python=platform.python_version(),
                     jax=jax.__version__, diffrax=diffrax.__version__, numpy=np.__version__, scipy=scipy.__version__,
                     numba=numba.__version__, cpu_count=os.cpu_count()),
        command="python benchmarks/rolling_work_precision.py",
        total_seconds=time.perf_counter() - start,
        load_average_start=list(load_start),
        load_average_end=list(os.getloadavg()),
    )
    (OUT / "rolling_work_precision.json").write_text(json.dumps(
        dict(meta=meta, disk=disk, shell=shell, long_runs=longs), indent=1, default=float))
    plot(disk, shell, OUT / "rolling_work_precision.png")
    print_tables(disk, shell, longs)
    la, lb = meta["load_average_start"], meta["load_average_end"]
    print(f"\nload average (1, 5, 15 min): start {la[0]:.2f} {la[1]:.2f} {la[2]:.2f}, "
          f"end {lb[0]:.2f} {lb[1]:.2f} {lb[2]:.2f}")
    print(f"\ntotal {meta['total_seconds'] / 60:.1f} min; written: {OUT}/rolling_work_precision.csv, .json, .png")


if __name__ == "__main__":
    main()
