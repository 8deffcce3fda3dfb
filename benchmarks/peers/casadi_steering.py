r"""CasADi + IPOPT peer for spherical-robot steering (issue 5).

The peer of ``controls`` (``/work/shared/BENCHMARKS.md``: "for optimal control:
CasADi (with IPOPT) on the same discretized problem, multiple shooting -- what
control researchers reach for"), for the problem of
``controls.tasks.sphere_steering_reduced(ShellWithTop(), target=(0.5, 0.3), T=3)``:

    minimize   int_0^T |tau|^2 dt,
    subject to x' = f(x, tau),  x(0) = rest at the origin with the top hanging,
               psi(x(T)) = (xy - target, Omega, omega, E^T gamma) = 0   (10 equations),

on the 17-component reduced state of ``nhjax.scenes.ShellWithTopReduced``

    x = (omega(3), Omega(3), gamma(3), alpha(3), beta(3), x, y),

omega, Omega the angular velocities of top and shell [rad/s] and gamma, alpha,
beta the rows of R_top (all in the top's axes), (x, y) the contact point [m];
tau [N m] the internal torque (top axes: +tau on the top, -tau on the shell).
The equations are seed 003's (1.11) with the torque terms
(``ShellWithTopReduced.forced_vector_field``), written here again in CasADi
symbolics (``steering_functions``) and in NumPy (``rhs_numpy``):

    J = It + (1 - mu) mt (|c|^2 E - c c^T),   mu = mt Rs^2 / I_c,
    I_c = Is + (ms + mt) Rs^2,   kappa = Rs / I_c,   a = gamma x c,   v_c = omega x c,
    (J + mu mt a a^T) omega' = -omega x J omega + mu mt ((omega x v_c), gamma) a
                               + mt g a + tau - mt kappa (tau x gamma) x c,
    D v_c = omega' x c + omega x v_c,
    Omega' = -(mu / Rs) gamma x D v_c - pi_gamma(tau) / I_c - (tau, gamma) gamma / Is
             - omega x Omega,
    gamma' = gamma x omega,  alpha' = alpha x omega,  beta' = beta x omega,
    (x, y)' = ((V, alpha), (V, beta)),   V = Rs Omega x gamma,

pi_gamma(a) = a - (a, gamma) gamma. The 3x3 solve for omega' uses
Sherman–Morrison on the constant J (its inverse is a numeric matrix), so the
expression graph stays small for the exact Hessian. E (3x2) is an orthonormal
basis of the plane orthogonal to gamma(0) (for the default robot, c along -e3,
gamma(0) = e3 and the constraint says gamma_1 = gamma_2 = 0 up to the basis).

Transcription (``build``): multiple shooting on N equal intervals; the node
states X_0..X_N (17 x (N + 1)) and the controls are the NLP variables; X_0 = x0,
psi(X_N) = 0 and the continuity conditions X_{k+1} = F(X_k, U_k) are equality
constraints. Controls piecewise constant (one value per interval, ``"pc"``) or
piecewise linear (values at the N + 1 nodes, ``"pl"``). F is M RK4 substeps
expanded to SX; IPOPT gets the exact Hessian of the Lagrangian. The cost
int |tau|^2 dt is integrated in closed form on each interval (pc: h |U_k|^2,
pl: h/3 (|a|^2 + a.b + |b|^2)); RK4 would give the same number (Simpson's rule
is exact for quadratics in t), so the NLP cost is exactly the cost of its
control, and only the terminal violation carries the integrator's error.

Warm starts (``warm_start``): "linear": the controls sampled from the
minimum-effort control of the problem linearized at rest (``controls.tasks.
linear_guess``, supplied by the caller as a function of t) and the node states
from integrating it with the same RK4 map (continuity holds at the start, the
terminal constraints do not); "cold": zero controls and the node states at
rest with the contact point on the straight line from the origin to the target.

``evaluate`` re-simulates the optimal piecewise control on the continuous
reduced system with SciPy DOP853 at 1e-12, restarted at every interval, and
reports the terminal violation it really achieves.
"""

from __future__ import annotations

import math
import time

import casadi as ca
import numpy as np
from scipy.integrate import solve_ivp

__all__ = [
    "ROBOT",
    "PROBLEM",
    "derived",
    "hanging_attitude",
    "initial_state",
    "plane_basis",
    "steering_functions",
    "rhs_numpy",
    "terminal_numpy",
    "build",
    "warm_start",
    "solve",
    "evaluate",
]

#: nhjax.scenes.ShellWithTop() defaults (SI units; Is = 2/3 ms Rs^2, a thin shell).
ROBOT = {
    "ms": 1.0, "Rs": 0.2, "Is": 2.0 / 3.0 * 1.0 * 0.2**2, "mt": 2.0,
    "It": ((0.01, 0.0, 0.0), (0.0, 0.012, 0.0), (0.0, 0.0, 0.008)),
    "c": (0.0, 0.0, -0.08), "g": 9.81,
}
#: target contact point [m] and horizon [s] (issue 5's example).
PROBLEM = {"target": (0.5, 0.3), "T": 3.0}
NX, NU = 17, 3


def derived(robot=ROBOT):
    """Constant matrices and scalars of the reduced equations (NumPy)."""
    ms, Rs, Is, mt, g = (float(robot[k]) for k in ("ms", "Rs", "Is", "mt", "g"))
    It = np.asarray(robot["It"], float)
    c = np.asarray(robot["c"], float)
    Ic = Is + (ms + mt) * Rs**2
    mu = mt * Rs**2 / Ic
    J = It + (1 - mu) * mt * (c @ c * np.eye(3) - np.outer(c, c))
    return dict(ms=ms, Rs=Rs, Is=Is, mt=mt, g=g, It=It, c=c, Ic=Ic, mu=mu, kappa=Rs / Ic, J=J,
                Jinv=np.linalg.inv(J))


def hanging_attitude(c):
    """Rotation (top axes -> space) taking c to straight down (Rodrigues; the identity
    for c along -e3, a half turn about x for c along +e3, the identity for c = 0)."""
    c = np.asarray(c, float)
    n = np.linalg.norm(c)
    if n == 0.0:
        return np.eye(3)
    u, d = c / n, np.array([0.0, 0.0, -1.0])
    k = np.cross(u, d)
    s, co = np.linalg.norm(k), float(u @ d)
    if s < 1e-15:
        return np.eye(3) if co > 0 else np.diag([1.0, -1.0, -1.0])
    k /= s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    th = math.atan2(s, co)
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def initial_state(robot=ROBOT):
    """Rest at the origin, the top hanging: (0, 0, gamma, alpha, beta, 0) with
    (alpha, beta, gamma) the rows of the hanging attitude."""
    R = hanging_attitude(robot["c"])
    return np.concatenate([np.zeros(6), R[2], R[0], R[1], np.zeros(2)])


def plane_basis(robot=ROBOT):
    """(3, 2) orthonormal basis E of the plane orthogonal to gamma(0) (as in
    controls.tasks.steering: QR of [gamma0, I])."""
    g0 = hanging_attitude(robot["c"])[2]
    q, _ = np.linalg.qr(np.column_stack([g0, np.eye(3)]))
    return q[:, 1:3]


def steering_functions(robot=ROBOT, problem=PROBLEM, plane=None):
    """CasADi SX Functions ``f(x, tau) -> x'`` (the reduced forced equations) and
    ``psi(x) -> terminal constraints`` (10)."""
    d = derived(robot)
    Rs, Is, mt, g, mu, Ic, kap = d["Rs"], d["Is"], d["mt"], d["g"], d["mu"], d["Ic"], d["kappa"]
    c = ca.DM(d["c"])
    J, Jinv = ca.DM(d["J"]), ca.DM(d["Jinv"])
    x = ca.SX.sym("x", NX)
    tau = ca.SX.sym("tau", NU)
    om, Om, ga, al, be = x[0:3], x[3:6], x[6:9], x[9:12], x[12:15]
    a = ca.cross(ga, c)
    vc = ca.cross(om, c)
    rhs = (-ca.cross(om, ca.mtimes(J, om)) + mu * mt * ca.dot(ca.cross(om, vc), ga) * a + mt * g * a
           + tau - mt * kap * ca.cross(ca.cross(tau, ga), c))
    # (J + m a a^T)^{-1} rhs by Sherman-Morrison, m = mu mt
    m = mu * mt
    Jr, Ja = ca.mtimes(Jinv, rhs), ca.mtimes(Jinv, a)
    dom = Jr - m * Ja * ca.dot(a, Jr) / (1 + m * ca.dot(a, Ja))
    Dvc = ca.cross(dom, c) + ca.cross(om, vc)
    pi_tau = tau - ca.dot(tau, ga) * ga
    DOm = -(mu / Rs) * ca.cross(ga, Dvc) - pi_tau / Ic - ca.dot(tau, ga) * ga / Is
    dOm = DOm - ca.cross(om, Om)
    V = Rs * ca.cross(Om, ga)
    xdot = ca.vertcat(dom, dOm, ca.cross(ga, om), ca.cross(al, om), ca.cross(be, om), ca.dot(V, al), ca.dot(V, be))
    f = ca.Function("f", [x, tau], [xdot], ["x", "tau"], ["xdot"])
    E = ca.DM(plane_basis(robot) if plane is None else np.asarray(plane, float))
    target = ca.DM(np.asarray(problem["target"], float))
    psi = ca.vertcat(x[15:17] - target, Om, om, ca.mtimes(E.T, ga))
    return f, ca.Function("psi", [x], [psi], ["x"], ["psi"])


def rhs_numpy(x, tau, robot=ROBOT, _d={}):
    """The same equations in NumPy (for the re-simulation)."""
    key = id(robot)
    if key not in _d:
        _d[key] = derived(robot)
    d = _d[key]
    c, J = d["c"], d["J"]
    om, Om, ga, al, be = x[0:3], x[3:6], x[6:9], x[9:12], x[12:15]
    a = np.cross(ga, c)
    vc = np.cross(om, c)
    mt, mu = d["mt"], d["mu"]
    rhs = (-np.cross(om, J @ om) + mu * mt * np.dot(np.cross(om, vc), ga) * a + mt * d["g"] * a
           + tau - mt * d["kappa"] * np.cross(np.cross(tau, ga), c))
    dom = np.linalg.solve(J + mu * mt * np.outer(a, a), rhs)
    Dvc = np.cross(dom, c) + np.cross(om, vc)
    tg = tau @ ga
    DOm = -(mu / d["Rs"]) * np.cross(ga, Dvc) - (tau - tg * ga) / d["Ic"] - tg * ga / d["Is"]
    V = d["Rs"] * np.cross(Om, ga)
    return np.concatenate([dom, DOm - np.cross(om, Om), np.cross(ga, om), np.cross(al, om), np.cross(be, om),
                           [V @ al, V @ be]])


def terminal_numpy(x, robot=ROBOT, problem=PROBLEM, plane=None):
    E = plane_basis(robot) if plane is None else np.asarray(plane, float)
    return np.concatenate([x[15:17] - np.asarray(problem["target"], float), x[3:6], x[0:3], E.T @ x[6:9]])


def _interval_map(N, T, controls, substeps, f):
    """F(x, ua, ub) -> x_end over one interval of length h = T/N by ``substeps`` RK4
    steps, with tau(s) = ua (pc) or ua + (ub - ua) s / h (pl), s in [0, h]."""
    h = T / N
    x = ca.SX.sym("x", NX)
    ua = ca.SX.sym("ua", NU)
    ub = ca.SX.sym("ub", NU)

    def u_at(s):
        return ua if controls == "pc" else ua + (ub - ua) * (s / h)

    dt = h / substeps
    xk = x
    for j in range(substeps):
        t0 = j * dt
        k1 = f(xk, u_at(t0))
        k2 = f(xk + dt / 2 * k1, u_at(t0 + dt / 2))
        k3 = f(xk + dt / 2 * k2, u_at(t0 + dt / 2))
        k4 = f(xk + dt * k3, u_at(t0 + dt))
        xk = xk + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("F", [x, ua, ub], [xk], ["x", "ua", "ub"], ["xf"])


def build(N=30, controls="pc", substeps=4, robot=ROBOT, problem=PROBLEM, plane=None, ipopt_tol=1e-10,
          max_iter=500):
    """Multiple-shooting NLP and its IPOPT solver (exact Hessian, expanded SX).
    Returns a dict with the solver, bounds, index helpers, the interval map ``F``
    and ``build_seconds`` (symbolics + nlpsol)."""
    if controls not in ("pc", "pl"):
        raise ValueError("controls must be 'pc' or 'pl'")
    start = time.perf_counter()
    T = float(problem["T"])
    f, psi = steering_functions(robot, problem, plane)
    F = _interval_map(N, T, controls, substeps, f)
    h = T / N
    nU = N if controls == "pc" else N + 1
    X = ca.SX.sym("X", NX, N + 1)
    U = ca.SX.sym("U", NU, nU)
    J = 0
    g = [X[:, 0] - initial_state(robot)]
    for k in range(N):
        ua = U[:, k]
        ub = U[:, k] if controls == "pc" else U[:, k + 1]
        J = J + (h * ca.sumsqr(ua) if controls == "pc" else h / 3 * (ca.sumsqr(ua) + ca.dot(ua, ub) + ca.sumsqr(ub)))
        g.append(F(X[:, k], ua, ub) - X[:, k + 1])
    g.append(psi(X[:, N]))
    w = ca.vertcat(ca.vec(X), ca.vec(U))
    G = ca.vertcat(*g)
    nlp = {"x": w, "f": J, "g": G}
    opts = {"ipopt.tol": ipopt_tol, "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
            "ipopt.max_iter": max_iter, "expand": True}
    solver = ca.nlpsol("S", "ipopt", nlp, opts)
    build_seconds = time.perf_counter() - start
    ng = int(G.shape[0])
    return dict(solver=solver, F=F, lbg=np.zeros(ng), ubg=np.zeros(ng), N=N, nU=nU, T=T, controls=controls,
                substeps=substeps, n_variables=int(w.shape[0]), n_constraints=ng, build_seconds=build_seconds,
                robot=robot, problem=problem, plane=plane)


def _control_times(nlp):
    """Where the controls are sampled: interval midpoints (pc) or nodes (pl)."""
    N, T = nlp["N"], nlp["T"]
    h = T / N
    return (np.arange(N) + 0.5) * h if nlp["controls"] == "pc" else np.linspace(0.0, T, N + 1)


def warm_start(nlp, kind="linear", u_of_t=None):
    """Initial NLP point. ``kind="linear"``: U = u_of_t at the control times (u_of_t
    : t -> (3,) torque, e.g. the signal of ``linear_guess``), X from integrating it
    with the NLP's RK4 map. ``kind="cold"``: U = 0, X at rest with the contact point
    on the straight line to the target. Returns the vector w0."""
    N, nU = nlp["N"], nlp["nU"]
    x0 = initial_state(nlp["robot"])
    if kind == "linear":
        U = np.stack([np.asarray(u_of_t(t), float) for t in _control_times(nlp)], axis=1)
        X = np.zeros((NX, N + 1))
        X[:, 0] = x0
        for k in range(N):
            ub = U[:, k] if nlp["controls"] == "pc" else U[:, k + 1]
            X[:, k + 1] = np.asarray(nlp["F"](X[:, k], U[:, k], ub)).ravel()
    elif kind == "cold":
        U = np.zeros((NU, nU))
        X = np.repeat(x0[:, None], N + 1, axis=1)
        X[15:17] = np.outer(np.asarray(nlp["problem"]["target"], float), np.linspace(0.0, 1.0, N + 1))
    else:
        raise ValueError("kind must be 'linear' or 'cold'")
    return np.concatenate([X.ravel(order="F"), U.ravel(order="F")])


def solve(nlp, w0):
    """One IPOPT solve from w0. Returns a dict with cost, constraint violation (max
    |g|), iterations, status, controls U (3, nU), node states X (17, N+1) and the
    wall time of the call."""
    S = nlp["solver"]
    t = time.perf_counter()
    sol = S(x0=w0, lbg=nlp["lbg"], ubg=nlp["ubg"])
    seconds = time.perf_counter() - t
    st = S.stats()
    w = np.asarray(sol["x"]).ravel()
    N, nU = nlp["N"], nlp["nU"]
    X = w[: NX * (N + 1)].reshape(N + 1, NX).T
    U = w[NX * (N + 1):].reshape(nU, NU).T
    return dict(cost=float(sol["f"]), violation=float(np.abs(np.asarray(sol["g"])).max()),
                iterations=int(st["iter_count"]), success=bool(st["success"]), status=str(st["return_status"]),
                U=U, X=X, w=w, seconds=seconds)


def control_cost(nlp, U):
    """int |tau|^2 dt of the piecewise control, in closed form."""
    h = nlp["T"] / nlp["N"]
    if nlp["controls"] == "pc":
        return float(h * (U**2).sum())
    a, b = U[:, :-1], U[:, 1:]
    return float(h / 3 * ((a * a).sum() + (a * b).sum() + (b * b).sum()))


def evaluate(nlp, result, tol=1e-12):
    """Cost and terminal violation of the NLP's control applied to the continuous
    reduced system (SciPy DOP853 at ``tol``, restarted at each interval); the cost
    is integrated alongside as a check of the closed form."""
    N, T, U = nlp["N"], nlp["T"], result["U"]
    robot = nlp["robot"]
    h = T / N
    y = np.concatenate([initial_state(robot), [0.0]])
    for k in range(N):
        ua = U[:, k]
        ub = U[:, k] if nlp["controls"] == "pc" else U[:, k + 1]

        def rhs(t, z, ua=ua, ub=ub, t0=k * h):
            u = ua + (ub - ua) * ((t - t0) / h)
            return np.concatenate([rhs_numpy(z[:NX], u, robot), [u @ u]])

        s = solve_ivp(rhs, (k * h, (k + 1) * h), y, method="DOP853", rtol=tol, atol=tol)
        y = s.y[:, -1]
    psi = terminal_numpy(y[:NX], robot, nlp["problem"], nlp["plane"])
    return dict(cost=float(y[NX]), violation=float(np.abs(psi).max()), xT=y[:NX].tolist())
