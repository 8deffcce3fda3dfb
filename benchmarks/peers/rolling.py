"""Benchmark peers for the rolling scenes (plain NumPy/SciPy and Numba).

Reference implementations *outside JAX* of two problems nhjax solves, for the
work-precision comparison of ``../rolling_work_precision.py``
(``/work/shared/BENCHMARKS.md``): what a typical user gets from
``scipy.integrate.solve_ivp``, and what a compiled (Numba) adaptive
Dormand-Prince 5(4) with diffrax's step-size control achieves.

1. Rolling disk (seed 002, 9.37-9.44), minimal coordinates
---------------------------------------------------------
State ``y = (x1, x2, phi, theta, psi, x1', x2', phi', theta', psi')`` as in
``nhjax.scenes.RollingDisk`` (parameters ``p = (m, r, g, J1, J2)``). With the
rolling constraints x' = r psi' (cos phi, sin phi) substituted, the kinetic
energy of the disk is

    T* = I/2 (psi' - sin(theta) phi')^2 + K/2 theta'^2 + J2/2 cos^2(theta) phi'^2,
    I = m r^2 + J1,   K = m r^2 + J2,   V = m g r cos(theta),

and Chaplygin's equations (the Lagrangian does not depend on x; the constraint
coefficients depend on phi only; the momentum of the contact point across the
rolling direction is m r cos(theta) theta' on the constraint) read, with
s = sin(theta), c = cos(theta), w = psi' - s phi':

    theta'' = (m g r s - I c w phi' - J2 s c phi'^2) / K
    phi''   = theta' (J1 w + 2 J2 s phi') / (J2 c)
    psi''   = m r^2 c theta' phi' / I + c theta' phi' + s phi''
    x1''    = r (psi'' cos(phi) - psi' phi' sin(phi))
    x2''    = r (psi'' sin(phi) + psi' phi' cos(phi))

(the x-rows are the derivatives of the constraints, so the 10-component field
equals ``RollingDisk().vector_field`` on every consistent state; the benchmark
script checks this to 1e-12 on random states). The circular motion of the seed
(theta0 = 0.25, q0 = 2.17080452, J1 = 0.35, J2 = 0.5) is an exact solution:
``disk_exact``.

2. Spherical shell with a top, no torque (seed 003, sec. 1)
-----------------------------------------------------------
State ``x = (omega, Omega, gamma, alpha, beta, x, y)`` (17) as in
``nhjax.scenes.ShellWithTopReduced``; the right-hand side is a port of its
``forced_vector_field`` with zero torque: the reduced system (1.11)

    (J + mu mt a a^T) omega' = -omega x J omega + mu mt ((omega x v_c), gamma) a + mt g a,
    a = gamma x c,  v_c = omega x c,
    gamma' = gamma x omega,  alpha' = alpha x omega,  beta' = beta x omega,

with the shell's angular velocity DOmega = -(mu/Rs) gamma x D v_c,
Omega' = DOmega - omega x Omega, and the contact point x' = (V, alpha),
y' = (V, beta), V = Rs Omega x gamma. Parameters: ``shell_params``.

Contents
--------
``DISK_DEFAULT``, ``disk_params``, ``disk_circular_state``, ``disk_period``,
``disk_exact``, ``disk_rhs_numpy``, ``disk_rhs_numba``;
``SHELL_DEFAULT``, ``shell_params``, ``shell_initial_state``, ``shell_period``,
``shell_rhs_numpy``, ``shell_rhs_numba``, ``shell_energy``, ``shell_K_space``;
``solve_scipy`` (timed ``solve_ivp``), ``make_dp54`` (a Numba DP5 integrator
for any ``@njit`` right-hand side ``rhs(t, y, p, out)``, with dense output),
``dp54_disk`` / ``dp54_shell`` and the wrapper ``solve_numba``.

The Numba integrator is the design of ``falling_cat.py`` (same tableau
constants, imported from there; same diffrax-0.7.2 PID rules, documented in
``falling_cat.dp54_solve``), made generic in the right-hand side, plus Hairer's
4th-order continuous extension of DOPRI5 (the one SciPy's RK45 uses) to report
states at requested times without changing the steps.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit
from scipy.integrate import solve_ivp

_HERE = Path(__file__).resolve().parent
if str(_HERE) not in sys.path:
    sys.path.insert(0, str(_HERE))
import falling_cat as _fc  # noqa: E402  (tableau constants and _rms)

__all__ = [
    "DISK_DEFAULT",
    "SHELL_DEFAULT",
    "DEFAULT_MAX_STEPS",
    "disk_params",
    "disk_circular_state",
    "disk_period",
    "disk_exact",
    "disk_rhs_numpy",
    "disk_rhs_numba",
    "shell_params",
    "shell_initial_state",
    "shell_period",
    "shell_rhs_numpy",
    "shell_rhs_numba",
    "shell_energy",
    "shell_K_space",
    "solve_scipy",
    "make_dp54",
    "dp54_disk",
    "dp54_shell",
    "solve_numba",
]

DEFAULT_MAX_STEPS = 2_000_000

# ======================================================================================
# 1. Rolling disk
# ======================================================================================

#: The seed's circular motion (Table 9.1): J1 about the axis, J2 about a diameter,
#: in units m = r = g = 1; ten orbits.
DISK_DEFAULT = {
    "m": 1.0,
    "r": 1.0,
    "g": 1.0,
    "J1": 0.35,
    "J2": 0.5,
    "theta0": 0.25,
    "q0": 2.17080452,
    "orbits": 10,
}

DISK_PARAM_NAMES = ("m", "r", "g", "J1", "J2")


def disk_params(case=DISK_DEFAULT):
    """``p = (m, r, g, J1, J2)`` as a float64 array."""
    return np.array([float(case[k]) for k in DISK_PARAM_NAMES])


def _disk_rate(case):
    """Rolling rate psi' of the circular motion (RollingDisk.circular_rate)."""
    m, r, g, J1, J2 = disk_params(case)
    th, q = float(case["theta0"]), float(case["q0"])
    s, c = math.sin(th), math.cos(th)
    den = (m * r * r + J1) * c * q * r - (m * r * r + J1 - J2) * s * c * (q * r) ** 2
    return math.sqrt(m * g * r * s / den)


def disk_circular_state(case=DISK_DEFAULT):
    """Contact at (0, -1/q0), heading e1, tilt theta0, the balancing rolling rate."""
    r, th, q = float(case["r"]), float(case["theta0"]), float(case["q0"])
    s0 = _disk_rate(case)
    return np.array([0.0, -1.0 / q, 0.0, th, 0.0, r * s0, 0.0, q * r * s0, 0.0, s0])


def disk_period(case=DISK_DEFAULT):
    """Time of one orbit, 2 pi / phi'."""
    return 2 * math.pi / (float(case["q0"]) * float(case["r"]) * _disk_rate(case))


def disk_exact(t, case=DISK_DEFAULT):
    """Exact state(s) of the circular motion at time(s) ``t`` (shape (..., 10))."""
    t = np.asarray(t, float)
    r, th, q = float(case["r"]), float(case["theta0"]), float(case["q0"])
    s0 = _disk_rate(case)
    W = q * r * s0
    phi = W * t
    z = np.zeros_like(t)
    return np.stack(
        [np.sin(phi) / q, -np.cos(phi) / q, phi, z + th, s0 * t,
         r * s0 * np.cos(phi), r * s0 * np.sin(phi), z + W, z, z + s0],
        axis=-1,
    )  # fmt: skip


def disk_rhs_numpy(t, y, p):
    """Right-hand side of the disk (see the module docstring), plain NumPy."""
    m, r, g, J1, J2 = p
    x1d, x2d, phi, th, phid, thd, psid = y[5], y[6], y[2], y[3], y[7], y[8], y[9]
    s, c = np.sin(th), np.cos(th)
    I = m * r * r + J1
    K = m * r * r + J2
    w = psid - s * phid
    thdd = (m * g * r * s - I * c * w * phid - J2 * s * c * phid**2) / K
    phidd = thd * (J1 * w + 2 * J2 * s * phid) / (J2 * c)
    psidd = m * r * r * c * thd * phid / I + c * thd * phid + s * phidd
    cp, sp = np.cos(phi), np.sin(phi)
    x1dd = r * (psidd * cp - psid * phid * sp)
    x2dd = r * (psidd * sp + psid * phid * cp)
    return np.array([x1d, x2d, phid, thd, psid, x1dd, x2dd, phidd, thdd, psidd])


@njit(cache=False, fastmath=False)
def disk_rhs_numba(t, y, p, out):
    """Same as :func:`disk_rhs_numpy`; writes into ``out``."""
    m = p[0]
    r = p[1]
    g = p[2]
    J1 = p[3]
    J2 = p[4]
    phi = y[2]
    th = y[3]
    phid = y[7]
    thd = y[8]
    psid = y[9]
    s = math.sin(th)
    c = math.cos(th)
    I = m * r * r + J1
    K = m * r * r + J2
    w = psid - s * phid
    thdd = (m * g * r * s - I * c * w * phid - J2 * s * c * phid * phid) / K
    phidd = thd * (J1 * w + 2.0 * J2 * s * phid) / (J2 * c)
    psidd = m * r * r * c * thd * phid / I + c * thd * phid + s * phidd
    cp = math.cos(phi)
    sp = math.sin(phi)
    out[0] = y[5]
    out[1] = y[6]
    out[2] = phid
    out[3] = thd
    out[4] = psid
    out[5] = r * (psidd * cp - psid * phid * sp)
    out[6] = r * (psidd * sp + psid * phid * cp)
    out[7] = phidd
    out[8] = thdd
    out[9] = psidd


# ======================================================================================
# 2. Shell with a top (no torque)
# ======================================================================================

#: ShellWithTopReduced's default parameters (a general top: neither the Euler nor the
#: Lagrange case) and a tumbling initial state; ten turns of the top, a turn being
#: 2 pi / |omega(0)|.
SHELL_DEFAULT = {
    "ms": 1.0,
    "Rs": 0.2,
    "Is": 2.0 / 3.0 * 1.0 * 0.2**2,
    "mt": 0.5,
    "It": ((2e-3, 0.0, 0.0), (0.0, 3e-3, 0.0), (0.0, 0.0, 4e-3)),
    "c": (0.01, 0.0, -0.06),
    "g": 9.81,
    # initial state
    "omega": (2.0, -1.0, 3.0),  # top, its own axes [rad/s]
    "attitude": (0.3, -0.2, 0.1),  # rotation vector top -> space [rad]
    "shell_velocity": (0.3, -0.1),  # centre, space [m/s]
    "shell_spin": 0.5,  # Omega_z [rad/s]
    "position": (0.0, 0.0),
    "orbits": 10,
}

# p layout: ms, Rs, Is, mt, g, mu, I_contact, c(3) [7:10], J (3x3, row-major) [10:19], It [19:28]


def shell_params(case=SHELL_DEFAULT):
    """Flat float64 parameter vector (ms, Rs, Is, mt, g, mu, I_contact, c, J, It)."""
    ms, Rs, Is, mt, g = (float(case[k]) for k in ("ms", "Rs", "Is", "mt", "g"))
    It = np.asarray(case["It"], float)
    c = np.asarray(case["c"], float)
    Ic = Is + (ms + mt) * Rs**2
    mu = mt * Rs**2 / Ic
    J = It + (1 - mu) * mt * (c @ c * np.eye(3) - np.outer(c, c))
    return np.concatenate([[ms, Rs, Is, mt, g, mu, Ic], c, J.ravel(), It.ravel()])


def _rodrigues(w):
    w = np.asarray(w, float)
    t = np.linalg.norm(w)
    W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if t < 1e-8:
        return np.eye(3) + W + 0.5 * W @ W
    return np.eye(3) + np.sin(t) / t * W + (1 - np.cos(t)) / t**2 * (W @ W)


def shell_initial_state(case=SHELL_DEFAULT):
    """17-component state (ShellWithTopReduced.initial_state, in NumPy)."""
    R = _rodrigues(case["attitude"])
    al, be, ga = R[0], R[1], R[2]
    vx, vy = case["shell_velocity"]
    V = R.T @ np.array([vx, vy, 0.0])
    Om = np.cross(ga, V) / float(case["Rs"]) + float(case["shell_spin"]) * ga
    return np.concatenate([np.asarray(case["omega"], float), Om, ga, al, be, np.asarray(case["position"], float)])


def shell_period(case=SHELL_DEFAULT):
    """One turn of the top: 2 pi / |omega(0)| [s]."""
    return 2 * math.pi / float(np.linalg.norm(case["omega"]))


def shell_rhs_numpy(t, x, p):
    """Right-hand side of the torque-free shell with top, written the NumPy way."""
    Rs, mt, g, mu, c = p[1], p[3], p[4], p[5], p[7:10]
    J = p[10:19].reshape(3, 3)
    om, Om, ga, al, be = x[0:3], x[3:6], x[6:9], x[9:12], x[12:15]
    a = np.cross(ga, c)
    vc = np.cross(om, c)
    A = J + mu * mt * np.outer(a, a)
    rhs = -np.cross(om, J @ om) + mu * mt * np.dot(np.cross(om, vc), ga) * a + mt * g * a
    dom = np.linalg.solve(A, rhs)
    Dvc = np.cross(dom, c) + np.cross(om, vc)
    dOm = -(mu / Rs) * np.cross(ga, Dvc) - np.cross(om, Om)
    V = Rs * np.cross(Om, ga)
    return np.concatenate(
        [dom, dOm, np.cross(ga, om), np.cross(al, om), np.cross(be, om), [V @ al, V @ be]]
    )


@njit(cache=False, fastmath=False)
def shell_rhs_numba(t, x, p, out):
    """Same as :func:`shell_rhs_numpy`, scalar code; writes into ``out``."""
    Rs = p[1]
    mt = p[3]
    g = p[4]
    mu = p[5]
    c0, c1, c2 = p[7], p[8], p[9]
    w0, w1, w2 = x[0], x[1], x[2]
    O0, O1, O2 = x[3], x[4], x[5]
    g0, g1, g2 = x[6], x[7], x[8]
    # a = gamma x c, vc = omega x c
    a0 = g1 * c2 - g2 * c1
    a1 = g2 * c0 - g0 * c2
    a2 = g0 * c1 - g1 * c0
    v0 = w1 * c2 - w2 * c1
    v1 = w2 * c0 - w0 * c2
    v2 = w0 * c1 - w1 * c0
    # J omega
    Jw0 = p[10] * w0 + p[11] * w1 + p[12] * w2
    Jw1 = p[13] * w0 + p[14] * w1 + p[15] * w2
    Jw2 = p[16] * w0 + p[17] * w1 + p[18] * w2
    # (omega x vc, gamma)
    u0 = w1 * v2 - w2 * v1
    u1 = w2 * v0 - w0 * v2
    u2 = w0 * v1 - w1 * v0
    k = mu * mt * (u0 * g0 + u1 * g1 + u2 * g2) + mt * g
    r0 = -(w1 * Jw2 - w2 * Jw1) + k * a0
    r1 = -(w2 * Jw0 - w0 * Jw2) + k * a1
    r2 = -(w0 * Jw1 - w1 * Jw0) + k * a2
    # A = J + mu mt a a^T, solved by the adjugate (symmetric positive definite 3x3)
    s = mu * mt
    A00 = p[10] + s * a0 * a0
    A01 = p[11] + s * a0 * a1
    A02 = p[12] + s * a0 * a2
    A10 = p[13] + s * a1 * a0
    A11 = p[14] + s * a1 * a1
    A12 = p[15] + s * a1 * a2
    A20 = p[16] + s * a2 * a0
    A21 = p[17] + s * a2 * a1
    A22 = p[18] + s * a2 * a2
    C00 = A11 * A22 - A12 * A21
    C01 = A12 * A20 - A10 * A22
    C02 = A10 * A21 - A11 * A20
    det = A00 * C00 + A01 * C01 + A02 * C02
    inv = 1.0 / det
    d0 = (C00 * r0 + (A02 * A21 - A01 * A22) * r1 + (A01 * A12 - A02 * A11) * r2) * inv
    d1 = (C01 * r0 + (A00 * A22 - A02 * A20) * r1 + (A02 * A10 - A00 * A12) * r2) * inv
    d2 = (C02 * r0 + (A01 * A20 - A00 * A21) * r1 + (A00 * A11 - A01 * A10) * r2) * inv
    # D vc = omega' x c + omega x vc
    e0 = d1 * c2 - d2 * c1 + u0
    e1 = d2 * c0 - d0 * c2 + u1
    e2 = d0 * c1 - d1 * c0 + u2
    f = -mu / Rs
    out[0] = d0
    out[1] = d1
    out[2] = d2
    out[3] = f * (g1 * e2 - g2 * e1) - (w1 * O2 - w2 * O1)
    out[4] = f * (g2 * e0 - g0 * e2) - (w2 * O0 - w0 * O2)
    out[5] = f * (g0 * e1 - g1 * e0) - (w0 * O1 - w1 * O0)
    # gamma, alpha, beta: b' = b x omega
    for j in range(3):
        b0 = x[6 + 3 * j]
        b1 = x[7 + 3 * j]
        b2 = x[8 + 3 * j]
        out[6 + 3 * j] = b1 * w2 - b2 * w1
        out[7 + 3 * j] = b2 * w0 - b0 * w2
        out[8 + 3 * j] = b0 * w1 - b1 * w0
    # V = Rs Omega x gamma; x' = (V, alpha), y' = (V, beta)
    V0 = Rs * (O1 * g2 - O2 * g1)
    V1 = Rs * (O2 * g0 - O0 * g2)
    V2 = Rs * (O0 * g1 - O1 * g0)
    out[15] = V0 * x[9] + V1 * x[10] + V2 * x[11]
    out[16] = V0 * x[12] + V1 * x[13] + V2 * x[14]


def shell_energy(X, p):
    """Total mechanical energy of shell and top at states X (..., 17) (NumPy)."""
    ms, Rs, Is, mt, g = p[0], p[1], p[2], p[3], p[4]
    c, It = p[7:10], p[19:28].reshape(3, 3)
    X = np.asarray(X)
    om, Om, ga = X[..., 0:3], X[..., 3:6], X[..., 6:9]
    V = Rs * np.cross(Om, ga)
    vG = V + np.cross(om, c)
    T = 0.5 * (ms * np.sum(V * V, -1) + Is * np.sum(Om * Om, -1) + mt * np.sum(vG * vG, -1)
               + np.einsum("...i,ij,...j->...", om, It, om))
    return T + mt * g * (ga @ c)


def shell_K_space(X, p):
    """Chaplygin's vector K = V + mu pi_gamma(omega x c) (1.9) in space axes (..., 3) [m/s]."""
    Rs, mu, c = p[1], p[5], p[7:10]
    X = np.asarray(X)
    om, Om, ga, al, be = X[..., 0:3], X[..., 3:6], X[..., 6:9], X[..., 9:12], X[..., 12:15]
    vc = np.cross(om, c)
    K = Rs * np.cross(Om, ga) + mu * (vc - np.sum(vc * ga, -1, keepdims=True) * ga)
    return np.stack([np.sum(K * al, -1), np.sum(K * be, -1), np.sum(K * ga, -1)], -1)


# ======================================================================================
# SciPy
# ======================================================================================


def solve_scipy(rhs, y0, t1, method, rtol, atol, p, t_eval=None, t0=0.0):
    """``scipy.integrate.solve_ivp(rhs, (t0, t1), y0, method, rtol, atol, args=(p,))``.

    Only the ``solve_ivp`` call is timed. Returns a dict with ``y1`` (final state),
    ``ys`` (states at ``t_eval``, shape (len(t_eval), n), or None), ``nfev``,
    ``nsteps`` (accepted steps) and ``seconds``.
    """
    start = time.perf_counter()
    sol = solve_ivp(rhs, (t0, t1), y0, method=method, rtol=rtol, atol=atol, args=(p,), t_eval=t_eval)
    seconds = time.perf_counter() - start
    if not sol.success:
        raise RuntimeError(f"solve_ivp({method}) failed: {sol.message}")
    if t_eval is None:
        y1, ys, nsteps = sol.y[:, -1].copy(), None, len(sol.t) - 1
    else:
        # with t_eval, sol.t holds the requested times; count steps from the solver
        y1, ys, nsteps = sol.y[:, -1].copy(), sol.y.T.copy(), None
    return {"y1": y1, "ys": ys, "nfev": int(sol.nfev), "nsteps": nsteps, "seconds": seconds}


# ======================================================================================
# Numba: Dormand-Prince 5(4) for any right-hand side, with dense output
# ======================================================================================

# Hairer's continuous extension of DOPRI5 (order 4), as in SciPy's RK45:
# y(t + th h) = y + h sum_i k_i (P_i1 th + P_i2 th^2 + P_i3 th^3 + P_i4 th^4).
_P = np.array(
    [
        [1.0, -8048581381 / 2820520608, 8663915743 / 2820520608, -12715105075 / 11282082432],
        [0.0, 0.0, 0.0, 0.0],
        [0.0, 131558114200 / 32700410799, -68118460800 / 10900136933, 87487479700 / 32700410799],
        [0.0, -1754552775 / 470086768, 14199869525 / 1410260304, -10690763975 / 1880347072],
        [0.0, 127303824393 / 49829197408, -318862633887 / 49829197408, 701980252875 / 199316789632],
        [0.0, -282668133 / 205662961, 2019193451 / 616988883, -1453857185 / 822651844],
        [0.0, 40617522 / 29380423, -110615467 / 29380423, 69997945 / 29380423],
    ]
)


def make_dp54(rhs):
    """A Numba DP5(4) solver for the ``@njit`` right-hand side ``rhs(t, y, p, out)``.

    Returns ``solve(y0, t0, t1, rtol, atol, p, max_steps, dt0, diffrax_error, t_save)``
    -> ``(y1, n_accepted, n_rejected, exhausted, Y_save)``. Steps, error norm,
    step-size control and end-of-interval clipping are those of
    ``falling_cat.dp54_solve`` (diffrax 0.7.2 ``PIDController`` defaults); see its
    docstring. ``t_save`` (sorted, in [t0, t1]; may be empty) are reported by
    Hairer's 4th-order dense output, which does not change the steps.
    """
    A21 = _fc._A21
    A31, A32 = _fc._A31, _fc._A32
    A41, A42, A43 = _fc._A41, _fc._A42, _fc._A43
    A51, A52, A53, A54 = _fc._A51, _fc._A52, _fc._A53, _fc._A54
    A61, A62, A63, A64, A65 = _fc._A61, _fc._A62, _fc._A63, _fc._A64, _fc._A65
    C2, C3, C4, C5 = _fc._C2, _fc._C3, _fc._C4, _fc._C5
    B1, B3, B4, B5, B6 = _fc._B1, _fc._B3, _fc._B4, _fc._B5, _fc._B6
    E = (_fc._E1, _fc._E3, _fc._E4, _fc._E5, _fc._E6, _fc._E7)
    DE = (_fc._DE1, _fc._DE3, _fc._DE4, _fc._DE5, _fc._DE6, _fc._DE7)
    SAFETY, FMIN, FMAX, ORDER = _fc._SAFETY, _fc._FACTORMIN, _fc._FACTORMAX, _fc._ERROR_ORDER
    P = _P.copy()
    rms = _fc._rms

    @njit(cache=False, fastmath=False)
    def initial_step(t0, y0, f0, rtol, atol, p, ytmp, f1, scaled):
        # Hairer's heuristic, as falling_cat._initial_step and diffrax's _select_initial_step
        n = y0.size
        for i in range(n):
            scaled[i] = y0[i] / (atol + abs(y0[i]) * rtol)
        d0 = rms(scaled)
        for i in range(n):
            scaled[i] = f0[i] / (atol + abs(y0[i]) * rtol)
        d1 = rms(scaled)
        if d0 < 1e-5 or d1 < 1e-5:
            h0 = 1e-6
        else:
            h0 = 0.01 * (d0 / d1)
        for i in range(n):
            ytmp[i] = y0[i] + h0 * f0[i]
        rhs(t0 + h0, ytmp, p, f1)
        for i in range(n):
            scaled[i] = (f1[i] - f0[i]) / (atol + abs(y0[i]) * rtol)
        d2 = rms(scaled) / h0
        max_d = max(d1, d2)
        if max_d <= 1e-15:
            h1 = max(1e-6, h0 * 1e-3)
        else:
            h1 = (0.01 / max_d) ** (1.0 / ORDER)
        return min(100.0 * h0, h1)

    @njit(cache=False, fastmath=False)
    def solve(y0, t0, t1, rtol, atol, p, max_steps, dt0, diffrax_error, t_save):
        n = y0.size
        y = y0.copy()
        y1 = np.empty(n)
        ytmp = np.empty(n)
        scaled = np.empty(n)
        k1 = np.empty(n)
        k2 = np.empty(n)
        k3 = np.empty(n)
        k4 = np.empty(n)
        k5 = np.empty(n)
        k6 = np.empty(n)
        k7 = np.empty(n)
        n_save = t_save.size
        Ys = np.full((n_save, n), np.nan)
        js = 0
        while js < n_save and t_save[js] <= t0:
            Ys[js, :] = y0
            js += 1
        if diffrax_error:
            e1, e3, e4, e5, e6, e7 = DE
        else:
            e1, e3, e4, e5, e6, e7 = E

        rhs(t0, y, p, k1)
        if dt0 > 0.0:
            h = dt0
        else:
            h = initial_step(t0, y, k1, rtol, atol, p, ytmp, k2, scaled)
        t1_clip_floor = t1
        for _ in range(100):
            t1_clip_floor = np.nextafter(t1_clip_floor, -np.inf)

        t = t0
        tnext = min(t0 + h, t1)
        n_acc = 0
        n_rej = 0
        while t < t1:
            if n_acc + n_rej >= max_steps:
                return y, n_acc, n_rej, True, Ys
            h = tnext - t
            for i in range(n):
                ytmp[i] = y[i] + h * (A21 * k1[i])
            rhs(t + C2 * h, ytmp, p, k2)
            for i in range(n):
                ytmp[i] = y[i] + h * (A31 * k1[i] + A32 * k2[i])
            rhs(t + C3 * h, ytmp, p, k3)
            for i in range(n):
                ytmp[i] = y[i] + h * (A41 * k1[i] + A42 * k2[i] + A43 * k3[i])
            rhs(t + C4 * h, ytmp, p, k4)
            for i in range(n):
                ytmp[i] = y[i] + h * (A51 * k1[i] + A52 * k2[i] + A53 * k3[i] + A54 * k4[i])
            rhs(t + C5 * h, ytmp, p, k5)
            for i in range(n):
                ytmp[i] = y[i] + h * (A61 * k1[i] + A62 * k2[i] + A63 * k3[i] + A64 * k4[i] + A65 * k5[i])
            rhs(tnext, ytmp, p, k6)
            for i in range(n):
                y1[i] = y[i] + h * (B1 * k1[i] + B3 * k3[i] + B4 * k4[i] + B5 * k5[i] + B6 * k6[i])
            rhs(tnext, y1, p, k7)
            for i in range(n):
                err = h * (e1 * k1[i] + e3 * k3[i] + e4 * k4[i] + e5 * k5[i] + e6 * k6[i] + e7 * k7[i])
                scaled[i] = err / (atol + rtol * max(abs(y[i]), abs(y1[i])))
            ratio = rms(scaled)
            keep = ratio < 1.0
            if keep:
                if ratio == 0.0:
                    factor = FMAX
                else:
                    factor = min(max(SAFETY * ratio ** (-1.0 / ORDER), 1.0), FMAX)
            elif math.isfinite(ratio):
                factor = min(max(SAFETY * ratio ** (-1.0 / ORDER), FMIN), SAFETY)
            else:
                factor = FMIN
            dt = h * factor
            if keep:
                # dense output at the requested times inside (t, tnext]
                while js < n_save and t_save[js] <= tnext:
                    if t_save[js] == tnext:
                        Ys[js, :] = y1
                    else:
                        th = (t_save[js] - t) / h
                        q1 = th
                        q2 = th * th
                        q3 = q2 * th
                        q4 = q3 * th
                        for i in range(n):
                            acc = 0.0
                            acc += k1[i] * (P[0, 0] * q1 + P[0, 1] * q2 + P[0, 2] * q3 + P[0, 3] * q4)
                            acc += k3[i] * (P[2, 0] * q1 + P[2, 1] * q2 + P[2, 2] * q3 + P[2, 3] * q4)
                            acc += k4[i] * (P[3, 0] * q1 + P[3, 1] * q2 + P[3, 2] * q3 + P[3, 3] * q4)
                            acc += k5[i] * (P[4, 0] * q1 + P[4, 1] * q2 + P[4, 2] * q3 + P[4, 3] * q4)
                            acc += k6[i] * (P[5, 0] * q1 + P[5, 1] * q2 + P[5, 2] * q3 + P[5, 3] * q4)
                            acc += k7[i] * (P[6, 0] * q1 + P[6, 1] * q2 + P[6, 2] * q3 + P[6, 3] * q4)
                            Ys[js, i] = y[i] + h * acc
                    js += 1
                t = tnext
                for i in range(n):
                    y[i] = y1[i]
                    k1[i] = k7[i]  # FSAL
                n_acc += 1
            else:
                n_rej += 1
            t = min(t, t1)
            tn = t + dt
            if tn > t1_clip_floor:
                tn = t1 if keep else t + 0.5 * (t1 - t)
            tnext = tn
        return y, n_acc, n_rej, False, Ys

    return solve


dp54_disk = make_dp54(disk_rhs_numba)
dp54_shell = make_dp54(shell_rhs_numba)

_NO_SAVE = np.empty(0)


def solve_numba(solver, y0, t1, rtol, atol, p, t_save=None, t0=0.0, max_steps=DEFAULT_MAX_STEPS,
                dt0=0.0, diffrax_error=False):
    """Run a ``make_dp54`` solver; returns ``(y1, n_accepted, n_rejected, Y_save)``
    (``Y_save`` None without ``t_save``); raises RuntimeError if max_steps ran out."""
    ts = _NO_SAVE if t_save is None else np.ascontiguousarray(t_save, dtype=np.float64)
    y1, n_acc, n_rej, exhausted, Ys = solver(
        np.ascontiguousarray(y0, dtype=np.float64), float(t0), float(t1), float(rtol), float(atol),
        p, int(max_steps), float(dt0), bool(diffrax_error), ts,
    )
    if exhausted:
        raise RuntimeError("numba DP5: max_steps exhausted")
    return y1, int(n_acc), int(n_rej), (None if t_save is None else Ys)
