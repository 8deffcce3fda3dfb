"""Parametrized open-loop control signals u(t), usable as ``control=`` in simulate().

Each signal is an ``equinox.Module``: its arrays are parameters that jit, vmap
and grad see (differentiate a simulation with respect to them), and it is
callable as ``signal(t, x)`` (x is ignored) like any nhjax control. Signals
that are not smooth in t expose ``breakpoints`` so that simulate() puts steps
exactly there instead of stepping across a kink.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

__all__ = ["PiecewiseConstant", "PiecewiseLinear", "Sinusoids"]


class Sinusoids(eqx.Module):
    """u_i(t) = offset_i + amplitude_i sin(omega_i t + phase_i), one term per input.

    All parameters have shape (k,) for k inputs (units of the input; omega in rad/s).
    """

    offset: jax.Array
    amplitude: jax.Array
    omega: jax.Array
    phase: jax.Array

    def __init__(self, offset, amplitude, omega, phase=None):
        self.offset = jnp.atleast_1d(jnp.asarray(offset, float))
        self.amplitude = jnp.atleast_1d(jnp.asarray(amplitude, float))
        self.omega = jnp.atleast_1d(jnp.asarray(omega, float))
        self.phase = (
            jnp.zeros_like(self.omega) if phase is None else jnp.atleast_1d(jnp.asarray(phase, float))
        )
        shapes = {a.shape for a in (self.offset, self.amplitude, self.omega, self.phase)}
        if len(shapes) != 1:
            raise ValueError(f"Sinusoids parameters must share one shape (k,), got {shapes}")

    def __call__(self, t, x=None):
        return self.offset + self.amplitude * jnp.sin(self.omega * t + self.phase)


def _check_knots(ts, values):
    ts = jnp.asarray(ts, float)
    values = jnp.asarray(values, float)
    if values.ndim == 1:
        values = values[:, None]
    if ts.ndim != 1 or values.shape[0] != ts.shape[0]:
        raise ValueError(
            f"knot times (shape {ts.shape}) and values (shape {values.shape}) must agree "
            "on the first axis"
        )
    return ts, values


class PiecewiseLinear(eqx.Module):
    """Linear interpolation of ``values`` (n, k) at knot times ``ts`` (n,); constant outside."""

    ts: jax.Array
    values: jax.Array

    def __init__(self, ts, values):
        self.ts, self.values = _check_knots(ts, values)

    @property
    def breakpoints(self):
        return self.ts[1:-1]

    def __call__(self, t, x=None):
        return jax.vmap(lambda v: jnp.interp(t, self.ts, v), in_axes=1)(self.values)


class PiecewiseConstant(eqx.Module):
    """values[i] on [ts[i], ts[i+1]); ``values`` has shape (n-1, k) for n knot times."""

    ts: jax.Array
    values: jax.Array

    def __init__(self, ts, values):
        ts = jnp.asarray(ts, float)
        values = jnp.asarray(values, float)
        if values.ndim == 1:
            values = values[:, None]
        if values.shape[0] != ts.shape[0] - 1:
            raise ValueError("PiecewiseConstant needs one value row per interval (n-1 rows for n times)")
        self.ts, self.values = ts, values

    @property
    def breakpoints(self):
        return self.ts[1:-1]

    def __call__(self, t, x=None):
        i = jnp.clip(jnp.searchsorted(self.ts, t, side="right") - 1, 0, self.values.shape[0] - 1)
        return self.values[i]
