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
import numpy as np

from .._validate import real, to_device
from ..errors import ParameterError

__all__ = ["PiecewiseConstant", "PiecewiseLinear", "Sinusoids"]


def _at_least_1d(a):
    """``jnp.atleast_1d`` without an eager program for concrete arrays (one compiled per
    shape in each new process otherwise)."""
    if jnp.ndim(a) >= 1 and isinstance(a, (jax.Array, jax.core.Tracer)):
        return a
    if isinstance(a, jax.core.Tracer):
        return jnp.atleast_1d(a)
    return to_device(np.atleast_1d(np.asarray(a)))


class Sinusoids(eqx.Module):
    """u_i(t) = offset_i + amplitude_i sin(omega_i t + phase_i), one term per input.

    All parameters have shape (k,) for k inputs (units of the input; omega in rad/s).
    """

    offset: jax.Array
    amplitude: jax.Array
    omega: jax.Array
    phase: jax.Array

    def __init__(self, offset, amplitude, omega, phase=None):
        owner = "Sinusoids"
        self.offset = _at_least_1d(real("offset", offset, owner=owner, what="input units"))
        self.amplitude = _at_least_1d(real("amplitude", amplitude, owner=owner, what="input units"))
        self.omega = _at_least_1d(real("omega", omega, owner=owner, what="angular frequency [rad/s]"))
        self.phase = (to_device(np.zeros(jnp.shape(self.omega))) if phase is None
                      else _at_least_1d(real("phase", phase, owner=owner, what="[rad]")))
        shapes = {a.shape for a in (self.offset, self.amplitude, self.omega, self.phase)}
        if len(shapes) != 1:
            raise ParameterError(
                "Sinusoids: offset, amplitude, omega and phase must share one shape (k,) for k inputs, "
                f"got shapes {sorted(shapes)}", "amplitude", amplitude)

    def __call__(self, t, x=None):
        return self.offset + self.amplitude * jnp.sin(self.omega * t + self.phase)


def _check_knots(ts, values, owner, rows_per_knot=0):
    """Knot times (finite, increasing) and values (finite, one row per knot, or per
    interval with rows_per_knot=-1), as float arrays; tracers pass unchecked."""
    ts = jnp.atleast_1d(real("ts", ts, owner=owner, what="knot times [s]"))
    values = real("values", values, owner=owner, what="input values at the knots")
    if values.ndim == 1:
        values = values[:, None]
    need = ts.shape[0] + rows_per_knot
    if ts.ndim != 1 or values.ndim != 2 or values.shape[0] != need:
        rows = "one value row per knot time" if rows_per_knot == 0 else "one value row per interval (n - 1 rows for n times)"
        raise ParameterError(
            f"{owner}: values must have {rows}: knot times of shape {tuple(ts.shape)} and values of shape "
            f"{tuple(values.shape)} do not agree", "values", values)
    if not isinstance(ts, jax.core.Tracer) and np.any(np.diff(np.asarray(ts)) <= 0):
        raise ParameterError(f"{owner}: knot times ts must increase strictly, got {np.asarray(ts)}", "ts", ts)
    return ts, values


class PiecewiseLinear(eqx.Module):
    """Linear interpolation of ``values`` (n, k) at knot times ``ts`` (n,); constant outside."""

    ts: jax.Array
    values: jax.Array

    def __init__(self, ts, values):
        self.ts, self.values = _check_knots(ts, values, "PiecewiseLinear")

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
        self.ts, self.values = _check_knots(ts, values, "PiecewiseConstant", rows_per_knot=-1)

    @property
    def breakpoints(self):
        return self.ts[1:-1]

    def __call__(self, t, x=None):
        i = jnp.clip(jnp.searchsorted(self.ts, t, side="right") - 1, 0, self.values.shape[0] - 1)
        return self.values[i]
