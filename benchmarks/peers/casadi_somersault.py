"""CasADi + IPOPT peer for the velocity-controlled falling-cat somersault (Iwai's chart).

The peer of ``controls`` (``/work/shared/BENCHMARKS.md``: "for optimal control:
CasADi (with IPOPT) on the same discretized problem, multiple shooting -- what
control researchers reach for"), for the problem of
``controls.tasks.velocity_somersault_chart(FallingCatKinematic(), theta0=0.6,
turn=-pi, T=2, windings=1)``:

    minimize   int_0^T L(x, u) dt,
    subject to x' = f(x, u),  x(0) = (theta0, 0, 0),  x(T) = (theta0, 2 pi, -pi),

with state x = (theta, chi, psi) [rad], control u = (theta', chi') [rad/s] and,
for s = sin(theta), c = cos(theta), D = s^2 + lam c^2, f(theta) = lam c / D
(``nhjax.scenes.FallingCatKinematic``, Iwai (7.1) and (4.8)):

    f(x, u) = (u1, u2, -f(theta) u2),
    L(x, u) = I1 [(1 + B s^2) u1^2 + lam s^2 / D u2^2]      (vibrational power).

The formulas are written here again in CasADi symbolics (``cat_functions``)
and in NumPy (``rhs_numpy``, ``cost_rate_numpy``); the benchmark script checks
them against the nhjax functions at random points.

Transcription (``build``): multiple shooting on N equal intervals, the node
states X_0..X_N and the controls are the NLP variables; X_0 = x0 and
X_N = target are equality constraints, as are the continuity conditions
X_{k+1} = F(X_k, U_k). Controls are piecewise constant (one value per interval,
``controls="pc"``) or piecewise linear (values at the N + 1 nodes, continuous,
``controls="pl"``). F and the running cost on an interval come from

* ``integrator="rk4"``: M fixed RK4 substeps on the state augmented by the cost
  quadrature, expanded to SX (IPOPT gets the exact Hessian of the Lagrangian);
* ``integrator="cvodes"``: CasADi's SUNDIALS CVODES (BDF, with the cost as a
  quadrature, rtol = atol = 1e-10); IPOPT uses a limited-memory (L-BFGS)
  Hessian here by default (``hessian="exact"`` is available: in a trial with
  N = 20, pc, it took 16 iterations and 2.6 s against 29 and 1.2 s).

The warm start is the fixed-theta loop: theta = theta0, chi = 2 pi t / T,
psi = -f(theta0) chi, u = (0, 2 pi / T).

``evaluate`` re-simulates the optimal (piecewise) control on the continuous
system with SciPy DOP853 at 1e-12, restarted at every interval, to report the
cost and terminal violation the control really achieves (the NLP cost carries
the discretization error of the integrator as well as of the control).
"""

from __future__ import annotations

import math
import time

import casadi as ca
import numpy as np
from scipy.integrate import solve_ivp

__all__ = [
    "CAT",
    "PROBLEM",
    "cat_functions",
    "rhs_numpy",
    "cost_rate_numpy",
    "build",
    "build_grid",
    "solve",
    "solve_grid_member",
    "evaluate",
]

#: FallingCatKinematic() defaults (a solid cylinder, see nhjax/scenes/falling_cat.py).
CAT = {"I1": 0.09895833333333333, "lam": 0.31578947368421056, "B": 2.5263157894736845}
#: The chart somersault: theta0, horizon T [s], turn of psi [rad], windings of chi.
PROBLEM = {"theta0": 0.6, "T": 2.0, "turn": -math.pi, "windings": 1}


def _x0(problem=PROBLEM):
    return np.array([problem["theta0"], 0.0, 0.0])


def _target(problem=PROBLEM):
    return np.array([problem["theta0"], 2 * math.pi * problem["windings"], problem["turn"]])


def cat_functions(cat=CAT):
    """CasADi Functions ``f(x, u) -> x'`` and ``L(x, u) -> vibrational power`` (SX)."""
    I1, lam, B = cat["I1"], cat["lam"], cat["B"]
    x = ca.SX.sym("x", 3)
    u = ca.SX.sym("u", 2)
    s, c = ca.sin(x[0]), ca.cos(x[0])
    D = s * s + lam * c * c
    fth = lam * c / D
    xdot = ca.vertcat(u[0], u[1], -fth * u[1])
    L = I1 * ((1 + B * s * s) * u[0] ** 2 + lam * s * s / D * u[1] ** 2)
    return ca.Function("f", [x, u], [xdot], ["x", "u"], ["xdot"]), ca.Function("L", [x, u], [L], ["x", "u"], ["L"])


def rhs_numpy(x, u, cat=CAT):
    lam = cat["lam"]
    s, c = math.sin(x[0]), math.cos(x[0])
    return np.array([u[0], u[1], -lam * c / (s * s + lam * c * c) * u[1]])


def cost_rate_numpy(x, u, cat=CAT):
    I1, lam, B = cat["I1"], cat["lam"], cat["B"]
    s, c = math.sin(x[0]), math.cos(x[0])
    return I1 * ((1 + B * s * s) * u[0] ** 2 + lam * s * s / (s * s + lam * c * c) * u[1] ** 2)


def _interval_map(N, T, controls, integrator, substeps, cat, cvodes_tol):
    """Function F(x, ua, ub) -> (x_end, cost) over one interval of length T/N, with
    u(tau) = ua (pc) or ua + (ub - ua) tau / h (pl), tau in [0, h]."""
    f, L = cat_functions(cat)
    h = T / N
    x = ca.SX.sym("x", 3)
    ua = ca.SX.sym("ua", 2)
    ub = ca.SX.sym("ub", 2)

    def u_at(tau):
        return ua if controls == "pc" else ua + (ub - ua) * (tau / h)

    if integrator == "rk4":
        dt = h / substeps
        xk, q = x, 0
        for j in range(substeps):
            t0 = j * dt
            k1, l1 = f(xk, u_at(t0)), L(xk, u_at(t0))
            xm = xk + dt / 2 * k1
            k2, l2 = f(xm, u_at(t0 + dt / 2)), L(xm, u_at(t0 + dt / 2))
            xm = xk + dt / 2 * k2
            k3, l3 = f(xm, u_at(t0 + dt / 2)), L(xm, u_at(t0 + dt / 2))
            xe = xk + dt * k3
            k4, l4 = f(xe, u_at(t0 + dt)), L(xe, u_at(t0 + dt))
            xk = xk + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            q = q + dt / 6 * (l1 + 2 * l2 + 2 * l3 + l4)
        return ca.Function("F", [x, ua, ub], [xk, q], ["x", "ua", "ub"], ["xf", "qf"])
    if integrator == "cvodes":
        tau = ca.SX.sym("t")
        p = ca.vertcat(ua, ub)
        uu = ua if controls == "pc" else ua + (ub - ua) * (tau / h)
        dae = {"x": x, "p": p, "t": tau, "ode": f(x, uu), "quad": L(x, uu)}
        I = ca.integrator("I", "cvodes", dae, 0.0, h, {"abstol": cvodes_tol, "reltol": cvodes_tol})
        # MX wrapper with the same signature as the RK4 map
        xm, uam, ubm = ca.MX.sym("x", 3), ca.MX.sym("ua", 2), ca.MX.sym("ub", 2)
        r = I(x0=xm, p=ca.vertcat(uam, ubm))
        return ca.Function("F", [xm, uam, ubm], [r["xf"], r["qf"]], ["x", "ua", "ub"], ["xf", "qf"])
    raise ValueError(f"integrator must be 'rk4' or 'cvodes', not {integrator!r}")


def build(N=40, controls="pc", integrator="rk4", substeps=4, problem=PROBLEM, cat=CAT,
          ipopt_tol=1e-10, cvodes_tol=1e-10, hessian=None):
    """Multiple-shooting NLP and its IPOPT solver. Returns a dict with the solver, the
    bounds, the warm start ``w0``, index helpers and ``build_seconds`` (symbolic
    construction plus ``nlpsol``)."""
    if controls not in ("pc", "pl"):
        raise ValueError("controls must be 'pc' or 'pl'")
    start = time.perf_counter()
    T = float(problem["T"])
    F = _interval_map(N, T, controls, integrator, substeps, cat, cvodes_tol)
    Sym = ca.MX if integrator == "cvodes" else ca.SX
    nU = N if controls == "pc" else N + 1
    X = Sym.sym("X", 3, N + 1)
    U = Sym.sym("U", 2, nU)
    J = 0
    g = [X[:, 0] - _x0(problem)]
    for k in range(N):
        ua = U[:, k]
        ub = U[:, k] if controls == "pc" else U[:, k + 1]
        xf, qf = F(X[:, k], ua, ub)
        J = J + qf
        g.append(xf - X[:, k + 1])
    g.append(X[:, N] - _target(problem))
    w = ca.vertcat(ca.vec(X), ca.vec(U))
    nlp = {"x": w, "f": J, "g": ca.vertcat(*g)}
    opts = {"ipopt.tol": ipopt_tol, "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
            "ipopt.max_iter": 500}
    if integrator == "rk4":
        opts["expand"] = True
    hessian = hessian or ("exact" if integrator == "rk4" else "limited-memory")
    if hessian == "limited-memory":
        opts["ipopt.hessian_approximation"] = "limited-memory"
    solver = ca.nlpsol("S", "ipopt", nlp, opts)
    build_seconds = time.perf_counter() - start
    # warm start: the fixed-theta loop
    th0 = float(problem["theta0"])
    c = 2 * math.pi * problem["windings"] / T
    ts = np.linspace(0.0, T, N + 1)
    fth = cat["lam"] * math.cos(th0) / (math.sin(th0) ** 2 + cat["lam"] * math.cos(th0) ** 2)
    X0 = np.stack([np.full(N + 1, th0), c * ts, -fth * c * ts])
    U0 = np.stack([np.zeros(nU), np.full(nU, c)])
    w0 = np.concatenate([X0.ravel(order="F"), U0.ravel(order="F")])
    ng = 3 * (N + 2)
    return dict(solver=solver, w0=w0, lbg=np.zeros(ng), ubg=np.zeros(ng), N=N, nU=nU, T=T,
                controls=controls, integrator=integrator, substeps=substeps if integrator == "rk4" else None,
                n_variables=int(w.shape[0]), n_constraints=ng, build_seconds=build_seconds,
                hessian=hessian)


def build_grid(N=40, controls="pl", substeps=4, T=2.0, windings=1, cat=CAT, ipopt_tol=1e-10):
    """The chart somersault's multiple-shooting NLP (RK4 substeps, exact Hessian) with
    (theta0, turn) as NLP parameters: one build serves a grid of problems (as a
    researcher would write it for a sweep), each solved by ``solve_grid_member``."""
    if controls not in ("pc", "pl"):
        raise ValueError("controls must be 'pc' or 'pl'")
    start = time.perf_counter()
    F = _interval_map(N, T, controls, "rk4", substeps, cat, None)
    nU = N if controls == "pc" else N + 1
    X, U, P = ca.SX.sym("X", 3, N + 1), ca.SX.sym("U", 2, nU), ca.SX.sym("P", 2)
    J = 0
    g = [X[:, 0] - ca.vertcat(P[0], 0, 0)]
    for k in range(N):
        xf, qf = F(X[:, k], U[:, k], U[:, k] if controls == "pc" else U[:, k + 1])
        J = J + qf
        g.append(xf - X[:, k + 1])
    g.append(X[:, N] - ca.vertcat(P[0], 2 * math.pi * windings, P[1]))
    opts = {"ipopt.tol": ipopt_tol, "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
            "ipopt.max_iter": 500, "expand": True}
    solver = ca.nlpsol("S", "ipopt", {"x": ca.vertcat(ca.vec(X), ca.vec(U)), "f": J, "g": ca.vertcat(*g), "p": P},
                       opts)
    return dict(solver=solver, N=N, nU=nU, T=T, controls=controls, windings=windings, cat=cat,
                ng=3 * (N + 2), build_seconds=time.perf_counter() - start)


def loop_start(nlp, theta0):
    """The fixed-theta loop at ``theta0`` as a start of ``build_grid``'s NLP."""
    N, nU, T, cat = nlp["N"], nlp["nU"], nlp["T"], nlp["cat"]
    c = 2 * math.pi * nlp["windings"] / T
    fth = cat["lam"] * math.cos(theta0) / (math.sin(theta0) ** 2 + cat["lam"] * math.cos(theta0) ** 2)
    ts = np.linspace(0.0, T, N + 1)
    X0 = np.stack([np.full(N + 1, theta0), c * ts, -fth * c * ts])
    U0 = np.stack([np.zeros(nU), np.full(nU, c)])
    return np.concatenate([X0.ravel(order="F"), U0.ravel(order="F")])


def solve_grid_member(nlp, theta0, turn, w0):
    """One member of ``build_grid``'s family from the start ``w0``: cost, success,
    iterations, the solution vector (a neighbour's warm start) and the call's time."""
    S = nlp["solver"]
    t = time.perf_counter()
    sol = S(x0=w0, p=[theta0, turn], lbg=np.zeros(nlp["ng"]), ubg=np.zeros(nlp["ng"]))
    seconds = time.perf_counter() - t
    st = S.stats()
    return dict(cost=float(sol["f"]), success=bool(st["success"]), iterations=int(st["iter_count"]),
                w=np.asarray(sol["x"]).ravel(), violation=float(np.abs(np.asarray(sol["g"])).max()),
                seconds=seconds)


def solve(nlp):
    """One IPOPT solve from the warm start. Returns a dict with cost, constraint
    violation (max |g|), iterations, status, controls (2, nU), node states (3, N+1)
    and the wall time of the call."""
    S = nlp["solver"]
    t = time.perf_counter()
    sol = S(x0=nlp["w0"], lbg=nlp["lbg"], ubg=nlp["ubg"])
    seconds = time.perf_counter() - t
    st = S.stats()
    w = np.asarray(sol["x"]).ravel()
    N, nU = nlp["N"], nlp["nU"]
    X = w[: 3 * (N + 1)].reshape(N + 1, 3).T
    U = w[3 * (N + 1):].reshape(nU, 2).T
    return dict(cost=float(sol["f"]), violation=float(np.abs(np.asarray(sol["g"])).max()),
                iterations=int(st["iter_count"]), success=bool(st["success"]), status=str(st["return_status"]),
                U=U, X=X, seconds=seconds)


def evaluate(nlp, result, problem=PROBLEM, cat=CAT, tol=1e-12):
    """Cost and terminal violation of the NLP's optimal control applied to the
    continuous system (SciPy DOP853 at ``tol``, restarted at each interval)."""
    N, T, U = nlp["N"], nlp["T"], result["U"]
    h = T / N
    y = np.concatenate([_x0(problem), [0.0]])
    for k in range(N):
        ua = U[:, k]
        ub = U[:, k] if nlp["controls"] == "pc" else U[:, k + 1]

        def rhs(t, z, ua=ua, ub=ub, t0=k * h):
            u = ua + (ub - ua) * ((t - t0) / h)
            return np.concatenate([rhs_numpy(z[:3], u, cat), [cost_rate_numpy(z[:3], u, cat)]])

        s = solve_ivp(rhs, (k * h, (k + 1) * h), y, method="DOP853", rtol=tol, atol=tol)
        y = s.y[:, -1]
    return dict(cost=float(y[3]), violation=float(np.abs(y[:3] - _target(problem)).max()), xT=y[:3].tolist())
