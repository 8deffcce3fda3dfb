"""Benchmark peers for the torque-driven falling cat (plain NumPy/SciPy and Numba).

These are *reference implementations outside JAX* of the same problem that nhjax
solves, meant for ``../shared/BENCHMARKS.md``-style comparisons: how accurate and
how fast is the answer a typical user would get from SciPy, and what does a
hand-written, compiled (Numba) adaptive integrator with the *same step-size
controller as diffrax* achieve, per solve and per trajectory in a batch.

The model is Iwai's falling cat, equations (7.14)-(7.15), driven by two joint
torques.  Parameters ``I1, lam, B``; state ``y = (theta, chi, psi, thetadot,
chidot)``.  With ``s = sin(theta)``, ``c = cos(theta)``, ``D = s**2 + lam*c**2``
and ``f = lam*c/D``::

    theta'    = thetadot
    chi'      = chidot
    psi'      = -f * chidot
    thetadot' = (-2 I1 B s c thetadot**2 + 2 I1 lam**2 s c / D**2 chidot**2 + u1)
                / (2 I1 (1 + B s**2))
    chidot'   = (-4 I1 lam**2 s c / D**2 thetadot chidot + u2) / (2 I1 lam s**2 / D)

with the benchmark torques ``u1(t) = a0 + a1 sin(w1 t)``, ``u2(t) = a2 cos(w2 t)``.

Contents
--------
``CAT_DEFAULT``
    The default benchmark case (a solid cylinder of mass 1, length 1, radius 0.25
    with the joint at its end), as a plain dict.  Treat it as read-only; derive
    variants with ``dict(CAT_DEFAULT, y0=...)``.
``case_params(case)``
    The float64 parameter vector ``(I1, lam, B, a0, a1, w1, a2, w2)`` used by all
    right-hand sides below.
``rhs_numpy`` / ``solve_scipy``
    The plain NumPy right-hand side and a timed ``scipy.integrate.solve_ivp`` call.
``dp54_solve`` / ``dp54_numba`` / ``dp54_numba_batch``
    A Numba Dormand-Prince 5(4) integrator (FSAL) whose step control replicates
    ``diffrax.PIDController(rtol, atol)`` with its default coefficients (diffrax
    0.7.2; see ``dp54_solve`` for the exact rules), single and ``prange``-batched.
    By default it uses the standard DP error estimate and Hairer's initial step;
    ``diffrax_error=True, dt0=DIFFRAX_DT0`` reproduces diffrax's Dopri5 step
    sequence exactly (diffrax's error estimate is 2/3 of the standard one and its
    first step is 0.01 -- see ``dp54_solve``).
``reference_solution(case)``
    SciPy DOP853 at ``rtol = atol = 1e-13``, used to measure errors.

Running this file (``python falling_cat.py``) prints an accuracy/speed table.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit, prange
from scipy.integrate import solve_ivp

__all__ = [
    "CAT_DEFAULT",
    "PARAM_NAMES",
    "case_params",
    "case_y0",
    "rhs_numpy",
    "solve_scipy",
    "rhs_numba",
    "dp54_solve",
    "dp54_numba",
    "dp54_numba_batch",
    "DEFAULT_MAX_STEPS",
    "DIFFRAX_DT0",
    "reference_solution",
    "perturbed_y0s",
]

# --------------------------------------------------------------------------------------
# The benchmark case
# --------------------------------------------------------------------------------------

#: Default benchmark case.  I1, lam, B are those of a solid cylinder (mass 1,
#: length 1, radius 0.25, joint at its end).  ``theta`` stays in about
#: [0.70, 0.95] on [0, 10] and the final ``psi`` is about -1.92.
CAT_DEFAULT = {
    "I1": 0.09895833333333333,
    "lam": 0.31578947368421056,
    "B": 2.5263157894736845,
    # torques: u1 = a0 + a1 sin(w1 t), u2 = a2 cos(w2 t)
    "a0": -0.015,
    "a1": 0.04,
    "w1": 1.7,
    "a2": 0.02,
    "w2": 0.9,
    # (theta, chi, psi, thetadot, chidot) at t0
    "y0": (0.8, 0.0, 0.0, 0.0, 0.5),
    "t0": 0.0,
    "t1": 10.0,
}

#: Order of the entries of the parameter vector built by :func:`case_params`.
PARAM_NAMES = ("I1", "lam", "B", "a0", "a1", "w1", "a2", "w2")


def case_params(case=CAT_DEFAULT):
    """Parameter vector ``(I1, lam, B, a0, a1, w1, a2, w2)`` as float64 array."""
    return np.array([float(case[k]) for k in PARAM_NAMES], dtype=np.float64)


def case_y0(case=CAT_DEFAULT):
    """Initial state of ``case`` as a fresh float64 array of shape (5,)."""
    return np.array(case["y0"], dtype=np.float64)


# --------------------------------------------------------------------------------------
# Plain NumPy / SciPy
# --------------------------------------------------------------------------------------


def rhs_numpy(t, y, p):
    """Right-hand side written the way most NumPy users would write it.

    ``p`` is the parameter vector from :func:`case_params`.
    """
    I1, lam, B, a0, a1, w1, a2, w2 = p
    theta, chi, psi, thetadot, chidot = y
    s = np.sin(theta)
    c = np.cos(theta)
    D = s**2 + lam * c**2
    f = lam * c / D
    u1 = a0 + a1 * np.sin(w1 * t)
    u2 = a2 * np.cos(w2 * t)
    g = lam**2 * s * c / D**2
    thetaddot = (-2 * I1 * B * s * c * thetadot**2 + 2 * I1 * g * chidot**2 + u1) / (
        2 * I1 * (1 + B * s**2)
    )
    chiddot = (-4 * I1 * g * thetadot * chidot + u2) / (2 * I1 * lam * s**2 / D)
    return np.array([thetadot, chidot, -f * chidot, thetaddot, chiddot])


def solve_scipy(method, rtol, atol, case=CAT_DEFAULT):
    """Solve ``case`` on [t0, t1] with ``scipy.integrate.solve_ivp``.

    ``method`` is e.g. ``"RK45"``, ``"DOP853"`` or ``"Radau"``.  Only the
    ``solve_ivp`` call is timed (``time.perf_counter``).

    Returns a dict with ``y1`` (final state, ndarray (5,)), ``nfev``, ``nsteps``
    (accepted steps, i.e. ``len(sol.t) - 1``), ``njev``, ``nlu`` and ``seconds``.
    """
    p = case_params(case)
    y0 = case_y0(case)
    span = (float(case["t0"]), float(case["t1"]))
    start = time.perf_counter()
    sol = solve_ivp(rhs_numpy, span, y0, method=method, rtol=rtol, atol=atol, args=(p,))
    seconds = time.perf_counter() - start
    if not sol.success:
        raise RuntimeError(f"solve_ivp({method}) failed: {sol.message}")
    return {
        "y1": sol.y[:, -1].copy(),
        "nfev": int(sol.nfev),
        "nsteps": len(sol.t) - 1,
        "njev": int(sol.njev),
        "nlu": int(sol.nlu),
        "seconds": seconds,
    }


def reference_solution(case=CAT_DEFAULT):
    """Final state of ``case`` from SciPy DOP853 at ``rtol = atol = 1e-13``."""
    return solve_scipy("DOP853", 1e-13, 1e-13, case)["y1"]


# --------------------------------------------------------------------------------------
# Numba: right-hand side
# --------------------------------------------------------------------------------------


@njit(cache=False, fastmath=False)
def rhs_numba(t, y, p, out):
    """Right-hand side; writes ``dy/dt`` into ``out`` (no allocation)."""
    I1 = p[0]
    lam = p[1]
    B = p[2]
    theta = y[0]
    thetadot = y[3]
    chidot = y[4]
    s = math.sin(theta)
    c = math.cos(theta)
    D = s * s + lam * c * c
    f = lam * c / D
    u1 = p[3] + p[4] * math.sin(p[5] * t)
    u2 = p[6] * math.cos(p[7] * t)
    g = lam * lam * s * c / (D * D)
    out[0] = thetadot
    out[1] = chidot
    out[2] = -f * chidot
    out[3] = (-2.0 * I1 * B * s * c * thetadot * thetadot + 2.0 * I1 * g * chidot * chidot + u1) / (
        2.0 * I1 * (1.0 + B * s * s)
    )
    out[4] = (-4.0 * I1 * g * thetadot * chidot + u2) / (2.0 * I1 * lam * s * s / D)


# --------------------------------------------------------------------------------------
# Numba: Dormand-Prince 5(4)
# --------------------------------------------------------------------------------------

# Dormand & Prince (1980) tableau, as published (also Hairer-Norsett-Wanner I,
# table II.5.2).  Stage 7 is evaluated at (t + h, y1): first same as last (FSAL).
_C2, _C3, _C4, _C5 = 1.0 / 5.0, 3.0 / 10.0, 4.0 / 5.0, 8.0 / 9.0
_A21 = 1.0 / 5.0
_A31, _A32 = 3.0 / 40.0, 9.0 / 40.0
_A41, _A42, _A43 = 44.0 / 45.0, -56.0 / 15.0, 32.0 / 9.0
_A51, _A52, _A53, _A54 = 19372.0 / 6561.0, -25360.0 / 2187.0, 64448.0 / 6561.0, -212.0 / 729.0
_A61, _A62, _A63, _A64, _A65 = (
    9017.0 / 3168.0,
    -355.0 / 33.0,
    46732.0 / 5247.0,
    49.0 / 176.0,
    -5103.0 / 18656.0,
)
# 5th-order weights (= row 7 of A); b2 = b7 = 0.
_B1, _B3, _B4, _B5, _B6 = 35.0 / 384.0, 500.0 / 1113.0, 125.0 / 192.0, -2187.0 / 6784.0, 11.0 / 84.0
# Embedded 4th-order weights.
_BH1, _BH3, _BH4, _BH5, _BH6, _BH7 = (
    5179.0 / 57600.0,
    7571.0 / 16695.0,
    393.0 / 640.0,
    -92097.0 / 339200.0,
    187.0 / 2100.0,
    1.0 / 40.0,
)
# Error weights  E = b - bhat  (error of the propagated 5th-order solution).
_E1 = _B1 - _BH1
_E3 = _B3 - _BH3
_E4 = _B4 - _BH4
_E5 = _B5 - _BH5
_E6 = _B6 - _BH6
_E7 = -_BH7
# diffrax's Dopri5 (like torchdiffeq) embeds a *different* 4th-order solution,
# bhat' = (1951/21600, 0, 22642/50085, 451/720, -12231/42400, 649/6300, 1/60)
# = b/3 + 2 bhat/3, so its error estimate is exactly 2/3 of the one above and it
# takes ~(2/3)**(1/5) = 0.92 times as many steps.  Used with diffrax_error=True.
_DE1 = _B1 - 1951.0 / 21600.0
_DE3 = _B3 - 22642.0 / 50085.0
_DE4 = _B4 - 451.0 / 720.0
_DE5 = _B5 - -12231.0 / 42400.0
_DE6 = _B6 - 649.0 / 6300.0
_DE7 = -1.0 / 60.0

# diffrax.PIDController defaults and Dopri5's error order.
_SAFETY = 0.9
_FACTORMIN = 0.2
_FACTORMAX = 10.0
_ERROR_ORDER = 5.0
#: Default cap on attempted (accepted + rejected) steps, as diffrax's max_steps.
DEFAULT_MAX_STEPS = 4096
#: The first step diffrax 0.7.2 actually takes with ``dt0=None``: ``diffeqsolve``
#: wraps the ODETerm in a WrapTerm, so ``_select_initial_step``'s
#: ``isinstance(terms, ODETerm)`` test fails and it returns 0.01.
DIFFRAX_DT0 = 0.01


@njit(cache=False, fastmath=False)
def _rms(x):
    acc = 0.0
    for i in range(x.size):
        acc += x[i] * x[i]
    return math.sqrt(acc / x.size)


@njit(cache=False, fastmath=False)
def _initial_step(t0, y0, f0, rtol, atol, p, ytmp, f1, scaled):
    """Hairer's initial step heuristic, exactly as diffrax's ``_select_initial_step``.

    ``ytmp``, ``f1``, ``scaled`` are scratch arrays.  Costs one RHS evaluation.
    """
    n = y0.size
    for i in range(n):
        scaled[i] = y0[i] / (atol + abs(y0[i]) * rtol)
    d0 = _rms(scaled)
    for i in range(n):
        scaled[i] = f0[i] / (atol + abs(y0[i]) * rtol)
    d1 = _rms(scaled)
    if d0 < 1e-5 or d1 < 1e-5:
        h0 = 1e-6
    else:
        h0 = 0.01 * (d0 / d1)
    for i in range(n):
        ytmp[i] = y0[i] + h0 * f0[i]
    rhs_numba(t0 + h0, ytmp, p, f1)
    for i in range(n):
        scaled[i] = (f1[i] - f0[i]) / (atol + abs(y0[i]) * rtol)
    d2 = _rms(scaled) / h0
    max_d = max(d1, d2)
    if max_d <= 1e-15:
        h1 = max(1e-6, h0 * 1e-3)
    else:
        h1 = (0.01 / max_d) ** (1.0 / _ERROR_ORDER)
    return min(100.0 * h0, h1)


@njit(cache=False, fastmath=False)
def dp54_solve(y0, t0, t1, rtol, atol, p, max_steps, dt0, diffrax_error):
    """Adaptive Dormand-Prince 5(4) from ``t0`` to ``t1 > t0``.

    Step control replicates ``diffrax.diffeqsolve(..., Dopri5(), dt0=None,
    stepsize_controller=PIDController(rtol, atol))`` (diffrax 0.7.2):

    * error ratio ``r = RMS_i( err_i / (atol + rtol * max(|y0_i|, |y1_i|)) )``
      with ``err`` the embedded 5(4) difference, ``y1`` the 5th-order solution;
      the step is accepted iff ``r < 1``;
    * ``factor = 0.9 * r**(-1/5)`` clipped to ``[1, 10]`` after an accepted step
      and to ``[0.2, 0.9]`` after a rejected one (diffrax's
      ``factormin = where(keep, 1, 0.2)``, ``factormax = where(keep, 10, 0.9)``);
      the next step is ``factor`` times the step just attempted;
    * if the next step end lies within 100 ULPs of ``t1`` or beyond, it becomes
      ``t1`` after an accepted step, or the midpoint to ``t1`` after a rejected one;
    * initial step ``dt0`` if ``dt0 > 0``, else Hairer's heuristic
      :func:`_initial_step` (the formula of diffrax's ``_select_initial_step``
      and SciPy's ``select_initial_step``);
    * ``max_steps`` bounds accepted + rejected steps, as in diffrax.

    ``diffrax_error=False`` uses the standard Dormand-Prince error estimate
    (b - bhat of the published tableau, as Hairer's DOPRI5 and SciPy's RK45);
    ``diffrax_error=True`` uses diffrax's Dopri5 ``b_error`` (2/3 of it).  With
    ``diffrax_error=True, dt0=DIFFRAX_DT0`` the accepted/rejected step counts
    equal diffrax 0.7.2's ``Dopri5()`` + ``PIDController(rtol, atol)`` with
    ``dt0=None`` (checked on this problem for rtol = atol = 1e-3 ... 1e-12;
    final states agree to ~1e-14).

    Only deliberate difference: a non-finite error ratio is treated as a
    rejection with the minimum factor 0.2 (diffrax would propagate the NaN).

    Returns ``(y1, n_accepted, n_rejected, exhausted)``; if ``exhausted`` is True,
    ``y1`` is the state reached when ``max_steps`` ran out.
    """
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

    if diffrax_error:
        e1, e3, e4, e5, e6, e7 = _DE1, _DE3, _DE4, _DE5, _DE6, _DE7
    else:
        e1, e3, e4, e5, e6, e7 = _E1, _E3, _E4, _E5, _E6, _E7

    rhs_numba(t0, y, p, k1)
    if dt0 > 0.0:
        h = dt0
    else:
        h = _initial_step(t0, y, k1, rtol, atol, p, ytmp, k2, scaled)

    t1_clip_floor = t1
    for _ in range(100):
        t1_clip_floor = np.nextafter(t1_clip_floor, -np.inf)

    t = t0
    tnext = min(t0 + h, t1)
    n_acc = 0
    n_rej = 0
    while t < t1:
        if n_acc + n_rej >= max_steps:
            return y, n_acc, n_rej, True
        h = tnext - t

        for i in range(n):
            ytmp[i] = y[i] + h * (_A21 * k1[i])
        rhs_numba(t + _C2 * h, ytmp, p, k2)
        for i in range(n):
            ytmp[i] = y[i] + h * (_A31 * k1[i] + _A32 * k2[i])
        rhs_numba(t + _C3 * h, ytmp, p, k3)
        for i in range(n):
            ytmp[i] = y[i] + h * (_A41 * k1[i] + _A42 * k2[i] + _A43 * k3[i])
        rhs_numba(t + _C4 * h, ytmp, p, k4)
        for i in range(n):
            ytmp[i] = y[i] + h * (_A51 * k1[i] + _A52 * k2[i] + _A53 * k3[i] + _A54 * k4[i])
        rhs_numba(t + _C5 * h, ytmp, p, k5)
        for i in range(n):
            ytmp[i] = y[i] + h * (
                _A61 * k1[i] + _A62 * k2[i] + _A63 * k3[i] + _A64 * k4[i] + _A65 * k5[i]
            )
        rhs_numba(tnext, ytmp, p, k6)
        for i in range(n):
            y1[i] = y[i] + h * (
                _B1 * k1[i] + _B3 * k3[i] + _B4 * k4[i] + _B5 * k5[i] + _B6 * k6[i]
            )
        rhs_numba(tnext, y1, p, k7)

        for i in range(n):
            err = h * (
                e1 * k1[i] + e3 * k3[i] + e4 * k4[i] + e5 * k5[i] + e6 * k6[i] + e7 * k7[i]
            )
            scaled[i] = err / (atol + rtol * max(abs(y[i]), abs(y1[i])))
        ratio = _rms(scaled)

        keep = ratio < 1.0
        if keep:
            if ratio == 0.0:
                factor = _FACTORMAX
            else:
                factor = min(max(_SAFETY * ratio ** (-1.0 / _ERROR_ORDER), 1.0), _FACTORMAX)
        elif math.isfinite(ratio):
            factor = min(max(_SAFETY * ratio ** (-1.0 / _ERROR_ORDER), _FACTORMIN), _SAFETY)
        else:
            factor = _FACTORMIN
        dt = h * factor

        if keep:
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
    return y, n_acc, n_rej, False


@njit(cache=False, fastmath=False)
def dp54_numba(
    y0,
    t1,
    rtol,
    atol,
    params,
    t0=0.0,
    max_steps=DEFAULT_MAX_STEPS,
    dt0=0.0,
    diffrax_error=False,
):
    """Single solve from ``t0`` (default 0) to ``t1``; see :func:`dp54_solve`.

    ``params`` is the vector from :func:`case_params`.  Returns
    ``(y1, n_accepted, n_rejected)``; raises ``RuntimeError`` if ``max_steps``
    (accepted + rejected) is exhausted -- use :func:`dp54_solve` to get the flag
    instead.
    """
    y1, n_acc, n_rej, exhausted = dp54_solve(
        y0, t0, t1, rtol, atol, params, max_steps, dt0, diffrax_error
    )
    if exhausted:
        raise RuntimeError("dp54_numba: max_steps exhausted")
    return y1, n_acc, n_rej


@njit(cache=False, fastmath=False, parallel=True)
def dp54_numba_batch(
    Y0,
    t1,
    rtol,
    atol,
    params,
    t0=0.0,
    max_steps=DEFAULT_MAX_STEPS,
    dt0=0.0,
    diffrax_error=False,
):
    """Independent adaptive solves of the rows of ``Y0`` (N, 5), parallel over rows.

    Each trajectory runs exactly the arithmetic of :func:`dp54_numba` with its own
    step sizes.  Returns ``(Y1 (N, 5), steps (N,))`` where ``steps`` holds the
    accepted step counts; a trajectory that exhausts ``max_steps`` gets a NaN row
    in ``Y1`` and ``steps = -1``.
    """
    N = Y0.shape[0]
    Y1 = np.empty_like(Y0)
    steps = np.empty(N, dtype=np.int64)
    for j in prange(N):
        y1, n_acc, _n_rej, exhausted = dp54_solve(
            Y0[j], t0, t1, rtol, atol, params, max_steps, dt0, diffrax_error
        )
        if exhausted:
            Y1[j, :] = np.nan
            steps[j] = -1
        else:
            Y1[j, :] = y1
            steps[j] = n_acc
    return Y1, steps


# --------------------------------------------------------------------------------------
# Self-check / benchmark table
# --------------------------------------------------------------------------------------


def _median_seconds(timed_run, min_repeats=5, min_total=0.25, max_repeats=200):
    """Median of ``timed_run()`` (which runs once and returns its seconds) over at
    least ``min_repeats`` runs, more while the total is under ``min_total``
    seconds (capped at ``max_repeats``)."""
    times = []
    while len(times) < min_repeats or (sum(times) < min_total and len(times) < max_repeats):
        times.append(timed_run())
    return float(np.median(times))


def _wall(fn):
    """``timed_run`` for :func:`_median_seconds`: wall time of one ``fn()`` call."""

    def timed_run():
        start = time.perf_counter()
        fn()
        return time.perf_counter() - start

    return timed_run


def perturbed_y0s(n, case=CAT_DEFAULT, seed=0, dtheta=0.05, dchidot=0.1):
    """``n`` initial states: ``case["y0"]`` with uniform offsets in
    ``[-dtheta, dtheta]`` on theta and ``[-dchidot, dchidot]`` on chidot."""
    rng = np.random.default_rng(seed)
    Y0 = np.tile(case_y0(case), (n, 1))
    Y0[:, 0] += rng.uniform(-dtheta, dtheta, n)
    Y0[:, 4] += rng.uniform(-dchidot, dchidot, n)
    return Y0


def _fmt_time(s):
    if s < 1e-3:
        return f"{s * 1e6:8.1f} us"
    if s < 1.0:
        return f"{s * 1e3:8.2f} ms"
    return f"{s:8.3f} s "


def main():
    import numba

    case = CAT_DEFAULT
    p = case_params(case)
    y0 = case_y0(case)
    t1 = float(case["t1"])
    ref = reference_solution(case)
    ref_check = solve_scipy("DOP853", 3e-14, 3e-14, case)["y1"]
    print("Falling cat (Iwai 7.14-7.15), default case, t in [0, 10]")
    print(f"reference (DOP853 1e-13) y1 = {np.array2string(ref, precision=12)}")
    print(f"reference vs DOP853 3e-14: max-abs diff {np.max(np.abs(ref - ref_check)):.1e}")
    print(f"numba {numba.__version__}, threads {numba.get_num_threads()}")

    # --- compile times -------------------------------------------------------------
    start = time.perf_counter()
    dp54_numba(y0, t1, 1e-8, 1e-8, p)
    first = time.perf_counter() - start
    later = _median_seconds(_wall(lambda: dp54_numba(y0, t1, 1e-8, 1e-8, p)))
    print(f"numba compile dp54_numba       : {first - later:7.2f} s (first call {first:.2f} s)")
    Yb = perturbed_y0s(4, case)
    start = time.perf_counter()
    dp54_numba_batch(Yb, t1, 1e-8, 1e-8, p)
    first = time.perf_counter() - start
    later = _median_seconds(_wall(lambda: dp54_numba_batch(Yb, t1, 1e-8, 1e-8, p)))
    print(f"numba compile dp54_numba_batch : {first - later:7.2f} s (first call {first:.2f} s)")

    # --- accuracy / time per single solve ------------------------------------------
    print()
    print("Single solve, rtol = atol; err = max-abs final-state error vs reference;")
    print("time = median wall time per solve (>= 5 runs; numba after compile, incl. dispatch;")
    print("scipy: the solve_ivp call only)")
    header = f"{'rtol':>7} | {'method':<12} | {'err':>8} | {'time':>11} | {'nfev':>6} | {'acc/rej':>9}"
    print(header)
    print("-" * len(header))
    for k in range(3, 13):
        tol = 10.0**-k
        for method in ("RK45", "DOP853"):
            out = solve_scipy(method, tol, tol, case)
            err = np.max(np.abs(out["y1"] - ref))
            # time of the solve_ivp call only, as reported by solve_scipy
            sec = _median_seconds(lambda m=method: solve_scipy(m, tol, tol, case)["seconds"])
            print(
                f"{tol:7.0e} | {'scipy ' + method:<12} | {err:8.1e} | {_fmt_time(sec)} | "
                f"{out['nfev']:6d} | {out['nsteps']:>9d}"
            )
        for label, kw, init_fevals in (
            ("numba DP5", {}, 2),
            ("numba DPdx", {"dt0": DIFFRAX_DT0, "diffrax_error": True}, 1),
        ):
            y1, n_acc, n_rej = dp54_numba(y0, t1, tol, tol, p, **kw)
            err = np.max(np.abs(y1 - ref))
            sec = _median_seconds(_wall(lambda kw=kw: dp54_numba(y0, t1, tol, tol, p, **kw)))
            nfev = init_fevals + 6 * (n_acc + n_rej)
            print(
                f"{tol:7.0e} | {label:<12} | {err:8.1e} | {_fmt_time(sec)} | "
                f"{nfev:6d} | {f'{n_acc}/{n_rej}':>9}"
            )
    print("scipy acc/rej column: accepted steps only.  numba DPdx = diffrax mode")
    print("(diffrax_error=True, dt0=0.01): same steps as diffrax 0.7.2 Dopri5 + PIDController.")

    # --- batch throughput -----------------------------------------------------------
    tol = 1e-8
    print()
    print(f"Batch (numba prange, {numba.get_num_threads()} threads), rtol = atol = {tol:.0e}; y0 with")
    print("theta += U(-0.05, 0.05), chidot += U(-0.1, 0.1), seed 0; worst err over a random")
    print("subset of <= 32 members vs per-member DOP853 1e-13")
    header = f"{'N':>6} | {'time':>11} | {'traj/s':>9} | {'steps min/med/max':>17} | {'worst err':>9}"
    print(header)
    print("-" * len(header))
    rng = np.random.default_rng(1)
    for N in (1, 64, 1024, 16384):
        Y0 = perturbed_y0s(N, case, seed=0)
        Y1, steps = dp54_numba_batch(Y0, t1, tol, tol, p)
        sec = _median_seconds(_wall(lambda: dp54_numba_batch(Y0, t1, tol, tol, p)))
        subset = rng.choice(N, size=min(N, 32), replace=False)
        worst = max(
            np.max(np.abs(Y1[j] - reference_solution(dict(case, y0=tuple(Y0[j])))))
            for j in subset
        )
        st = f"{steps.min()}/{int(np.median(steps))}/{steps.max()}"
        print(f"{N:6d} | {_fmt_time(sec)} | {N / sec:9.3g} | {st:>17} | {worst:9.1e}")


if __name__ == "__main__":
    main()
