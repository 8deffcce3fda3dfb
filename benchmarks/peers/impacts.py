"""Numba peer for the impact benchmark (``../impacts.py``): the bouncing ball on a vibrating
table (seed 004, ex. 10.2) by a compiled event loop outside JAX.

The same numerical method as ``nhjax.simulate_impacts`` with its default solver, written
by hand in Numba for this one system:

* Dormand-Prince 5(4) (``diffrax.Dopri5``'s tableau), error norm RMS of
  err / (atol + rtol max(|y0|, |y1|)), step factor 0.9 err^(-1/5) clipped to [0.2, 10]
  (an I controller; diffrax's PIDController with its default coefficients is one), largest
  step ``dtmax``;
* events: after each accepted step the gap psi = x - A sin(omega t) is sampled at
  ``samples`` points of the step's cubic Hermite interpolant (exact for the parabolic
  flights); the first sample with psi < -graze_tol brackets the impact;
* root finding as nhjax does it: Newton on G(tau) = psi(tau, y(tau)) where y(tau) is a
  genuine DP5 step from the last accepted point to tau (not the interpolant), G' = x' -
  A omega cos(omega tau), safeguarded by bisection on the bracket, stopped when the
  Newton correction is below 2 ulp of tau;
* the jump v1 = (1 + alpha) A omega cos(omega t) - alpha v0 (the seed's projector for this
  constraint); the position is kept (as nhjax does).

Not covered (the peer stops instead): resting contact (a rebound slower than
``rest_velocity`` ends the run) and gaps that dip below the table and come back between
two samples. State y = (x, x'); parameters p = (g, A, omega, alpha).

``bounce(y0, t0, t1, p, n_max, rtol, atol, dtmax, ...)`` returns (impact times, velocities
before, states after, number of impacts, status), status 0: reached t1 or n_max impacts,
1: came to rest, 2: step budget exhausted.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# Dormand-Prince 5(4) tableau (as diffrax.Dopri5)
_C = np.array([0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0])
_A = np.zeros((7, 7))
_A[1, 0] = 1 / 5
_A[2, :2] = [3 / 40, 9 / 40]
_A[3, :3] = [44 / 45, -56 / 15, 32 / 9]
_A[4, :4] = [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729]
_A[5, :5] = [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656]
_A[6, :6] = [35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84]
_B = _A[6].copy()
_B_ERR = _B - np.array([5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40])


@njit(cache=True)
def _rhs(t, y, p, out):
    out[0] = y[1]
    out[1] = -p[0]


@njit(cache=True)
def _gap(t, x, p):
    return x - p[1] * np.sin(p[2] * t)


@njit(cache=True)
def _gap_rate(t, v, p):
    return v - p[1] * p[2] * np.cos(p[2] * t)


@njit(cache=True)
def _step(t, y, f0, h, p, K, y1, err):
    """One DP5 step from (t, y) with f0 = f(t, y): y1, the error estimate, K[6] = f(t+h, y1)."""
    n = y.shape[0]
    K[0, :] = f0
    tmp = np.empty(n)
    for s in range(1, 7):
        for i in range(n):
            acc = 0.0
            for j in range(s):
                acc += _A[s, j] * K[j, i]
            tmp[i] = y[i] + h * acc
        _rhs(t + _C[s] * h, tmp, p, K[s])
    for i in range(n):
        acc = 0.0
        e = 0.0
        for j in range(7):
            acc += _B[j] * K[j, i]
            e += _B_ERR[j] * K[j, i]
        y1[i] = y[i] + h * acc
        err[i] = h * e


@njit(cache=True)
def _hermite(t0, h, y0, f0, y1, f1, s, i):
    th = (s - t0) / h
    h00 = 2 * th**3 - 3 * th**2 + 1
    h10 = th**3 - 2 * th**2 + th
    h01 = -2 * th**3 + 3 * th**2
    h11 = th**3 - th**2
    return h00 * y0[i] + h10 * h * f0[i] + h01 * y1[i] + h11 * h * f1[i]


@njit(cache=True)
def bounce(y0, t0, t1, p, n_max, rtol, atol, dtmax, h0, samples=4, graze_tol=1e-12, rest_velocity=1e-6,
           max_steps=10_000_000):
    n = 2
    times = np.full(n_max, np.nan)
    v_pre = np.full(n_max, np.nan)
    post = np.full((n_max, n), np.nan)
    K = np.empty((7, n))
    y = y0.copy()
    y1 = np.empty(n)
    err = np.empty(n)
    f0 = np.empty(n)
    _rhs(t0, y, p, f0)
    t = t0
    h = min(h0, dtmax)
    k = 0
    steps = 0
    status = 0
    while t < t1 and k < n_max:
        steps += 1
        if steps > max_steps:
            status = 2
            break
        hh = min(h, t1 - t)
        _step(t, y, f0, hh, p, K, y1, err)
        s2 = 0.0
        for i in range(n):
            sc = atol + rtol * max(abs(y[i]), abs(y1[i]))
            s2 += (err[i] / sc) ** 2
        en = np.sqrt(s2 / n)
        fac = 10.0 if en == 0.0 else min(10.0, max(0.2, 0.9 * en ** (-0.2)))
        if en > 1.0:
            h = hh * fac
            continue
        # accepted: look for a crossing on the Hermite interpolant
        f1 = K[6].copy()
        lo = t
        hi = -1.0
        for j in range(1, samples + 1):
            s = t + hh * j / samples
            xs = y1[0] if j == samples else _hermite(t, hh, y, f0, y1, f1, s, 0)
            if _gap(s, xs, p) < -graze_tol:
                hi = s
                break
            lo = s
        if hi < 0.0:
            t = t + hh
            y[:] = y1
            f0[:] = f1
            h = min(hh * fac, dtmax)
            continue
        # Newton on genuine DP5 steps from t, safeguarded by bisection on [lo, hi]
        tau = hi
        for _ in range(60):
            _step(t, y, f0, tau - t, p, K, y1, err)
            G = _gap(tau, y1[0], p)
            Gp = _gap_rate(tau, y1[1], p)
            if G < 0:
                hi = tau
            else:
                lo = tau
            dt = -G / Gp if Gp != 0.0 else np.inf
            if abs(dt) <= 2 * np.spacing(abs(tau)) or G == 0.0 or hi - lo <= 4 * np.spacing(abs(tau)):
                break
            tn = tau + dt
            if not (np.isfinite(tn) and lo <= tn <= hi):
                tn = 0.5 * (lo + hi)
            tau = tn
        A, w, al = p[1], p[2], p[3]
        v0 = y1[1]
        v1 = (1 + al) * A * w * np.cos(w * tau) - al * v0
        times[k] = tau
        v_pre[k] = v0
        y[0] = y1[0]
        y[1] = v1
        post[k, 0] = y[0]
        post[k, 1] = y[1]
        k += 1
        t = tau
        _rhs(t, y, p, f0)
        h = min(hh * fac, dtmax)
        if v1 - A * w * np.cos(w * tau) <= rest_velocity:
            status = 1
            break
    return times, v_pre, post, k, status, steps
