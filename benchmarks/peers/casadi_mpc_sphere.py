r"""CasADi + IPOPT peer of the sphere MPC (issue 42): the same receding-horizon
controller as ``controls.MPC`` on ``controls.tasks.sphere_tracking``, written the
way control researchers write it in CasADi.

Horizon problem (the same discretization as ``controls.MPC(ocp, 0.05, 20)`` with
``substeps=1``): multiple shooting on N intervals of h = T / N, node states X_0..X_N
and piecewise-constant torques U_k as NLP variables, X_0 = the measurement, the
continuity conditions X_{k+1} = F(X_k, U_k; t_k) with F one RK4 step of the reduced
equations (``casadi_steering.steering_functions``) carrying the running cost

    L(t, x, u) = w_p |(x, y) - r(t)|^2 + w_s |omega|^2 + w_u |tau|^2

as an extra state (so the NLP's cost is the same RK4 quadrature as ``controls.MPC``'s),
r(t) the figure-eight of ``controls.tasks.FigureEight``; bounds |tau_i| <= bound.
The measurement and the period's start time are NLP parameters: the solver is built
once. Each period IPOPT (exact Hessian, ``ipopt_tol``) starts from the previous
solution shifted by one interval (the tail repeats the last torque and its state is
the last node's RK4 step), with the previous multipliers (``lam_x0``, ``lam_g0``)
and IPOPT's warm-start options.

``closed_loop`` runs it against the plant advanced by the same RK4 map of the plant's
parameters (one step per interval, the push added at the start of the step that
contains its time, as ``controls.closed_loop`` does), and returns the plant's states,
the applied torques, the closed-loop cost int L dt and IPOPT's wall time per period.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from casadi_steering import ROBOT, NU, NX, initial_state, steering_functions  # benchmarks/peers on sys.path

__all__ = ["build", "closed_loop"]


def _rk4(f, cost, h):
    """One RK4 step (x, u, t) -> (x+, int L dt) of x' = f(x, u) with L(t, x, u) alongside."""
    x, u, t = ca.SX.sym("x", NX), ca.SX.sym("u", NU), ca.SX.sym("t")

    def g(tt, xx):
        return f(xx, u), cost(tt, xx, u)

    k1x, k1j = g(t, x)
    k2x, k2j = g(t + h / 2, x + h / 2 * k1x)
    k3x, k3j = g(t + h / 2, x + h / 2 * k2x)
    k4x, k4j = g(t + h, x + h * k3x)
    return ca.Function("F", [x, u, t], [x + h / 6 * (k1x + 2 * k2x + 2 * k3x + k4x),
                                        h / 6 * (k1j + 2 * k2j + 2 * k3j + k4j)])


def tracking_cost(amplitude, period, weights, centre=(0.0, 0.0)):
    """L(t, x, u) as a CasADi expression builder (``controls.tasks.TrackingCost``)."""
    wp, ws, wu = weights
    w = 2 * np.pi / period

    def L(t, x, u):
        r = ca.vertcat(centre[0] + amplitude * ca.sin(w * t), centre[1] + amplitude * 0.5 * ca.sin(2 * w * t))
        e = x[15:17] - r
        return wp * ca.dot(e, e) + ws * ca.dot(x[0:3], x[0:3]) + wu * ca.dot(u, u)

    return L


def build(N=20, T=1.0, bound=1.0, amplitude=0.5, period=20.0, weights=(100.0, 0.1, 1.0), robot=ROBOT,
          ipopt_tol=1e-8, max_iter=100):
    """The horizon NLP as a CasADi solver with parameters (measurement (17), t0)."""
    f, _ = steering_functions(robot, {"target": (0.0, 0.0), "T": T})
    h = T / N
    F = _rk4(f, tracking_cost(amplitude, period, weights), h)
    X = ca.SX.sym("X", NX, N + 1)
    U = ca.SX.sym("U", NU, N)
    p = ca.SX.sym("p", NX + 1)
    y, t0 = p[:NX], p[NX]
    J, g = 0, [X[:, 0] - y]
    for k in range(N):
        xn, jk = F(X[:, k], U[:, k], t0 + k * h)
        J += jk
        g.append(xn - X[:, k + 1])
    w = ca.vertcat(ca.vec(X), ca.vec(U))
    nlp = {"x": w, "f": J, "g": ca.vertcat(*g), "p": p}
    opts = {"ipopt.tol": ipopt_tol, "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
            "ipopt.max_iter": max_iter, "expand": True, "ipopt.warm_start_init_point": "yes",
            "ipopt.warm_start_bound_push": 1e-8, "ipopt.warm_start_mult_bound_push": 1e-8,
            "ipopt.mu_init": 1e-5}
    solver = ca.nlpsol("mpc", "ipopt", nlp, opts)
    nX = NX * (N + 1)
    lbx = np.concatenate([np.full(nX, -np.inf), np.full(NU * N, -bound)])
    ubx = np.concatenate([np.full(nX, np.inf), np.full(NU * N, bound)])
    return dict(solver=solver, F=F, N=N, h=h, lbx=lbx, ubx=ubx, ng=NX * (N + 1), nX=nX,
                cost=tracking_cost(amplitude, period, weights))


def closed_loop(mpc, plant_robot, periods, pushes=(), x0=None):
    """(ts, xs, us, cost, seconds per period, statuses) of the CasADi MPC against the
    plant ``plant_robot`` (a ROBOT-like dict), pushes as (time, increment (17,)) pairs."""
    N, h, nX = mpc["N"], mpc["h"], mpc["nX"]
    solver = mpc["solver"]
    fp, _ = steering_functions(plant_robot, {"target": (0.0, 0.0), "T": 1.0})
    # the plant carries the controller's running cost (the closed-loop cost), with its own dynamics
    Fp = _rk4(fp, mpc["cost"], h)
    x = initial_state(ROBOT) if x0 is None else np.asarray(x0, float)
    Xg = np.tile(x[:, None], (1, N + 1))
    Ug = np.zeros((NU, N))
    lam_x, lam_g = np.zeros(nX + NU * N), np.zeros(mpc["ng"])
    xs, us, secs, stats, J = [x.copy()], [], [], [], 0.0
    for j in range(periods):
        t = j * h
        tic = time.perf_counter()
        sol = solver(x0=np.concatenate([Xg.T.ravel(), Ug.T.ravel()]), p=np.concatenate([x, [t]]), lbx=mpc["lbx"],
                     ubx=mpc["ubx"], lbg=0.0, ubg=0.0, lam_x0=lam_x, lam_g0=lam_g)
        secs.append(time.perf_counter() - tic)
        stats.append(solver.stats()["return_status"])
        w = np.asarray(sol["x"]).ravel()
        Xs = w[:nX].reshape(N + 1, NX).T
        Us = w[nX:].reshape(N, NU).T
        lam_x, lam_g = np.asarray(sol["lam_x"]).ravel(), np.asarray(sol["lam_g"]).ravel()
        u = Us[:, 0]
        for tp, dx in pushes:
            if t <= tp < t + h:
                x = x + np.asarray(dx, float)
        xn, dj = Fp(x, u, t)
        x, J = np.asarray(xn).ravel(), J + float(dj)
        xs.append(x.copy()), us.append(u.copy())
        # shift by one interval; the tail repeats the last torque
        last = np.asarray(mpc["F"](Xs[:, -1], Us[:, -1], t + (N + 1) * h)[0]).ravel()
        Xg = np.column_stack([Xs[:, 1:], last])
        Ug = np.column_stack([Us[:, 1:], Us[:, -1:]])
        lam_x = np.concatenate([_shift(lam_x[:nX], NX), _shift(lam_x[nX:], NU)])
        lam_g = _shift(lam_g, NX)
    ts = np.arange(periods + 1) * h
    return ts, np.array(xs), np.array(us), J, np.array(secs), stats


def _shift(v, k):
    return np.concatenate([v[k:], v[-k:]])

