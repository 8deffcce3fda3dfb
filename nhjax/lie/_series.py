"""Gradient-safe evaluation of the even functions that appear in Lie-group formulas.

Rodrigues' formula, dexp and dexp^-1 all need coefficients like sin(t)/t or
(1 - (t/2) cot(t/2)) / t^2, written in terms of t^2 = |w|^2. Near t = 0 their
closed forms are 0/0 and, even where they are finite, lose digits to
cancellation (and their autodiff derivatives lose more). Below ``SMALL2`` we
switch to a Taylor polynomial in t^2 that is exact to float64 there, and feed
the closed form a harmless dummy value so that neither branch of the
``jnp.where`` produces NaN in forward or reverse mode.
"""

from __future__ import annotations

import jax.numpy as jnp

# Switch to series for t^2 < SMALL2 (t < 0.1). Series below keep terms up to t^10,
# so the truncation error there is below 1e-22 (relative), while the closed
# forms above the switch lose at most ~1e-14 relative in first derivatives.
SMALL2 = 1e-2


def _poly(t2, coeffs):
    out = jnp.zeros_like(t2) + coeffs[-1]
    for c in reversed(coeffs[:-1]):
        out = out * t2 + c
    return out


def _safe(t2):
    small = t2 < SMALL2
    t2s = jnp.where(small, 1.0, t2)
    return small, t2s, jnp.sqrt(t2s)


def sinc(t2):
    """sin(t)/t as a function of t^2."""
    small, t2s, t = _safe(t2)
    series = _poly(t2, [1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880, -1 / 39916800])
    return jnp.where(small, series, jnp.sin(t) / t)


def cosc(t2):
    """(1 - cos t)/t^2 = 2 sin^2(t/2)/t^2 as a function of t^2 (no cancellation)."""
    small, t2s, t = _safe(t2)
    series = _poly(t2, [1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800, -1 / 479001600])
    return jnp.where(small, series, 2.0 * jnp.sin(0.5 * t) ** 2 / t2s)


def sinc3(t2):
    """(t - sin t)/t^3 = (1 - sinc)/t^2 as a function of t^2."""
    small, t2s, t = _safe(t2)
    series = _poly(
        t2, [1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800, -1 / 6227020800]
    )
    return jnp.where(small, series, (t - jnp.sin(t)) / (t2s * t))


def dexpinv_coeff(t2):
    """(1 - (t/2) cot(t/2)) / t^2 as a function of t^2 (the so(3) dexp^-1 coefficient).

    Series from x cot x = sum (-1)^n 2^{2n} B_{2n} x^{2n} / (2n)! with x = t/2:
    1/12 + t^2/720 + t^4/30240 + t^6/1209600 + t^8/47900160 + ...
    Singular at t = 2 pi (where dexp is not invertible).
    """
    small, t2s, t = _safe(t2)
    series = _poly(
        t2,
        [1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160, 691 / 1307674368000],
    )
    half = 0.5 * t
    closed = (1.0 - half * jnp.cos(half) / jnp.sin(half)) / t2s
    return jnp.where(small, series, closed)


def half_sinc(t2):
    """sin(t/2)/t as a function of t^2 (quaternion exponential)."""
    return 0.5 * sinc(0.25 * t2)


def cos_half(t2):
    """cos(t/2) as a function of t^2 (differentiable at t = 0)."""
    small, t2s, t = _safe(t2)
    series = _poly(t2, [1.0, -1 / 8, 1 / 384, -1 / 46080, 1 / 10321920, -1 / 3715891200])
    return jnp.where(small, series, jnp.cos(0.5 * t))


def half_cot(t2):
    """(t/2) cot(t/2) as a function of t^2 (SE(2) logarithm)."""
    return 1.0 - t2 * dexpinv_coeff(t2)
