"""Control parametrizations: a flat parameter vector <-> a control signal u(t).

Each parametrization knows its number of parameters, builds the control
``signal(params)`` (an equinox module callable as u(t, x), differentiable in the
parameters), maps control bounds to parameter bounds where that is exact, and
fits its parameters to a given function of time (for initial guesses).

* ``PiecewiseConstant(n, T, dim)``: n equal intervals on [0, T].
* ``PiecewiseLinear(n, T, dim)``: n + 1 equally spaced knots.
* ``CubicSpline(n, T, dim)``: natural cubic spline through n + 1 knots.
* ``Fourier(n, T, dim)``: a0 + sum_k a_k cos(2 pi k t/T) + b_k sin(2 pi k t/T), k <= n;
  spectrally accurate for smooth periodic controls.
* ``Chebyshev(n, T, dim)``: sum_{k <= n} c_k T_k(2 t/T - 1); spectrally accurate
  for smooth controls that need not be periodic (most optimal controls).

Bounds (u_lower <= u <= u_upper) are exact box constraints on the knots of the
piecewise constant and linear parametrizations; the others reject bounds.

The horizon T [s] is a 0-d array leaf (the knots and the Chebyshev/Fourier time
scaling are t = t0 + T s for a fixed grid in s): parametrizations of different T
but the same n and dim share the solvers' compiled programs.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from nhjax.integrate.signals import PiecewiseConstant as _PC
from nhjax.integrate.signals import PiecewiseLinear as _PL

from nhjax import _validate as V
from nhjax._validate import is_traced
from nhjax.errors import ProblemError

from .problem import as_problem_error, compiled, host_array

__all__ = ["Chebyshev", "CubicSpline", "Fourier", "Parametrization", "PiecewiseConstant", "PiecewiseLinear"]


def _device(a):
    """``host_array`` for a host (numpy) array; a tracer as it is."""
    return host_array(a) if isinstance(a, np.ndarray) else a


def _horizon(T):
    return jnp.asarray(T, float) if is_traced(T) else host_array(T)


def _knots(param):
    """The n + 1 equally spaced knots of ``param`` over [t0, t0 + T]."""
    if not is_traced(param.T):
        return _device(np.linspace(param.t0, param.t0 + float(param.T), param.n + 1))
    return jnp.linspace(param.t0, param.t0 + param.T, param.n + 1)


class Parametrization(eqx.Module):
    """``Kind(n, T, dim, t0=0.0)``: n intervals (or the degree, for the spectral ones:
    ``MIN_N`` is the least), horizon T [s] > 0 from t0 [s], dim inputs. Checked on
    construction, T by the rules ``simulate`` applies to its time span (a finite real
    number of seconds, not a string); ProblemError (controls' error class) otherwise."""

    n: int = eqx.field(static=True)
    T: jax.Array = eqx.field(converter=_horizon)
    dim: int = eqx.field(static=True)
    t0: float = eqx.field(static=True, default=0.0)

    MIN_N = 1
    #: whether the signal is piecewise between its n + 1 knots (not smooth at them)
    PIECEWISE = False

    def __init__(self, n, T, dim, t0=0.0):
        owner = type(self).__name__
        with as_problem_error():
            self.n = V.integer("n", n, minimum=self.MIN_N, owner=owner,
                               what="degree" if self.MIN_N == 0 else "number of intervals")
            self.T = V.duration("T", T, owner=owner)
            self.dim = V.integer("dim", dim, minimum=1, owner=owner, what="number of inputs")
            self.t0 = V.real("t0", t0, owner=owner, shape=(), as_float=True, what="start of the horizon [s]") \
                if not is_traced(t0) else t0

    @property
    def size(self) -> int:
        raise NotImplementedError

    def signal(self, params):
        raise NotImplementedError

    def param_bounds(self, u_lower, u_upper):
        raise ProblemError(
            f"{type(self).__name__} cannot impose control bounds exactly; use "
            "PiecewiseConstant or PiecewiseLinear for a bounded control"
        )

    def jump_times(self):
        """Times inside the horizon where the signal is not smooth (the inner knots of a
        piecewise one, ``PIECEWISE``), at which a solve should end its steps; None for a
        smooth basis (Chebyshev, Fourier)."""
        return _knots(self)[1:-1] if self.PIECEWISE else None

    def sample_times(self):
        """Times at which ``fit`` samples a target function."""
        return np.linspace(self.t0, self.t0 + float(self.T), 4 * self.size // max(self.dim, 1) + 8)

    def fit(self, u_fn):
        """Least-squares parameters whose signal best matches u_fn(t) (shape (dim,))."""
        owner = f"{type(self).__name__}.fit"
        with as_problem_error():
            V.function("u_fn", u_fn, owner=owner, signature="u_fn(t) -> (dim,) inputs")
        try:
            out = jax.eval_shape(u_fn, jax.ShapeDtypeStruct((), jnp.float64))
        except Exception as e:  # noqa: BLE001 - the user's function: say what it is for
            raise ProblemError(f"{owner}: u_fn(t) could not be evaluated on a scalar time t [s]: "
                               f"{type(e).__name__}: {e}") from None
        if getattr(out, "shape", None) != (self.dim,):
            raise ProblemError(f"{owner}: u_fn(t) must return the {self.dim} inputs, shape ({self.dim},), got "
                               f"{getattr(out, 'shape', type(out).__name__)}")
        ts = self.sample_times()
        # (the user's function runs eagerly: a jit of it would compile again for every new
        # function object, such as a lambda written in the call)
        us = np.asarray(jax.vmap(u_fn)(jax.device_put(ts)), float)
        bad = ~np.all(np.isfinite(us), axis=1)
        if bad.any():
            raise ProblemError(f"{owner}: u_fn(t) returned NaN or inf at t = {float(ts[bad][0]):g} s (and "
                               f"{int(bad.sum()) - 1} more of the {ts.size} sample times in [{float(ts[0]):g}, "
                               f"{float(ts[-1]):g}]); the fitted inputs must be finite over the horizon")
        return fit_samples(self, ts, us)

    def _check(self, params):
        """``params`` of the right shape: a float64 numpy array when it has a value (the
        signals reshape it on the host and hand it over by ``_device``), else the tracer."""
        if is_traced(params):
            params = jnp.asarray(params)
        else:
            # (concrete also under a caller's jax.jit that closes over params: the check's
            # operations are then evaluated, not staged into the caller's program)
            with as_problem_error(), jax.ensure_compile_time_eval():
                params = np.asarray(V.real("params", params, owner=f"{type(self).__name__}.signal"))
        if params.shape != (self.size,):
            raise ProblemError(
                f"{type(self).__name__}(n={self.n}, dim={self.dim}) takes {self.size} "
                f"parameters, got shape {params.shape}"
            )
        return params


@compiled(quick=True)
def _fit_basis(param, ts):
    """(basis, offset): the signal at the times ts (N,), flattened, is basis @ p + offset
    (every parametrization here is linear in its parameters)."""

    def sig(p):
        return jax.vmap(lambda t: param.signal(p)(t, None))(ts).reshape(-1)

    p0 = jnp.zeros(param.size)
    return jax.jacfwd(sig)(p0), sig(p0)


def prepare_fit(param) -> bool:
    """Trace the basis program of ``param.fit`` (at its sample times) now and compile it
    in the background (``nhjax._programs.prepare``)."""
    return _fit_basis.prepare(param, np.asarray(param.sample_times(), float))


def fit_samples(param, ts, us):
    """Least-squares parameters of ``param`` whose signal matches the samples us (N, dim)
    at the times ts (N,): the basis from one compiled program per parametrization
    structure, the small least-squares solve on the host (numpy's LAPACK)."""
    basis, offset = (np.asarray(a) for a in _fit_basis(param, np.asarray(ts, float)))
    return host_array(np.linalg.lstsq(basis, np.reshape(np.asarray(us, float), -1) - offset, rcond=None)[0])


class PiecewiseConstant(Parametrization):
    PIECEWISE = True

    @property
    def size(self):
        return self.n * self.dim

    def signal(self, params):
        params = self._check(params)
        return _PC(_knots(self), _device(params.reshape(self.n, self.dim)))

    def param_bounds(self, u_lower, u_upper):
        return jnp.tile(jnp.asarray(u_lower, float), self.n), jnp.tile(jnp.asarray(u_upper, float), self.n)


class PiecewiseLinear(Parametrization):
    PIECEWISE = True

    @property
    def size(self):
        return (self.n + 1) * self.dim

    def signal(self, params):
        params = self._check(params)
        return _PL(_knots(self), _device(params.reshape(self.n + 1, self.dim)))

    def param_bounds(self, u_lower, u_upper):
        k = self.n + 1
        return jnp.tile(jnp.asarray(u_lower, float), k), jnp.tile(jnp.asarray(u_upper, float), k)


class _SplineSignal(eqx.Module):
    ts: jax.Array
    values: jax.Array  # (n+1, dim)
    second: jax.Array  # (n+1, dim): second derivatives at the knots

    def __call__(self, t, x=None):
        h = self.ts[1] - self.ts[0]
        i = jnp.clip(jnp.floor((t - self.ts[0]) / h).astype(int), 0, self.ts.shape[0] - 2)
        a = (self.ts[i + 1] - t) / h
        b = 1.0 - a
        y0, y1 = self.values[i], self.values[i + 1]
        m0, m1 = self.second[i], self.second[i + 1]
        return a * y0 + b * y1 + ((a**3 - a) * m0 + (b**3 - b) * m1) * h**2 / 6.0


class CubicSpline(Parametrization):
    PIECEWISE = True

    @property
    def size(self):
        return (self.n + 1) * self.dim

    def signal(self, params):
        params = self._check(params)
        ts = _knots(self)
        y = jnp.asarray(params.reshape(self.n + 1, self.dim))
        h = self.T / self.n
        n = self.n
        # natural spline: M_0 = M_n = 0, tridiagonal system for the interior second derivatives
        if n > 1:
            A = (jnp.diag(jnp.full(n - 1, 4.0)) + jnp.diag(jnp.ones(n - 2), 1) + jnp.diag(jnp.ones(n - 2), -1))
            rhs = 6.0 / h**2 * (y[2:] - 2 * y[1:-1] + y[:-2])
            inner = jnp.linalg.solve(A, rhs)
        else:  # two knots: the natural spline is the straight line between them
            inner = jnp.zeros((0, self.dim))
        M = jnp.concatenate([jnp.zeros((1, self.dim)), inner, jnp.zeros((1, self.dim))])
        return _SplineSignal(ts, y, M)


class _FourierSignal(eqx.Module):
    coeffs: jax.Array  # (2n+1, dim): a0, a1..an, b1..bn
    omega: jax.Array
    t0: float = eqx.field(static=True)

    def __call__(self, t, x=None):
        n = (self.coeffs.shape[0] - 1) // 2
        k = jnp.arange(1, n + 1)
        ph = self.omega * k * (t - self.t0)
        basis = jnp.concatenate([jnp.ones(1), jnp.cos(ph), jnp.sin(ph)])
        return basis @ self.coeffs


class Fourier(Parametrization):
    MIN_N = 0  # the degree: 0 is a constant control

    @property
    def size(self):
        return (2 * self.n + 1) * self.dim

    def signal(self, params):
        params = self._check(params)
        omega = 2 * np.pi / self.T if is_traced(self.T) else host_array(2 * np.pi / np.asarray(self.T))
        return _FourierSignal(_device(params.reshape(2 * self.n + 1, self.dim)), omega, self.t0)


class _ChebyshevSignal(eqx.Module):
    coeffs: jax.Array  # (n+1, dim)
    t0: float = eqx.field(static=True)
    T: jax.Array

    def __call__(self, t, x=None):
        s = jnp.clip(2.0 * (t - self.t0) / self.T - 1.0, -1.0, 1.0)
        n = self.coeffs.shape[0]
        basis = [jnp.ones_like(s), s]
        for _ in range(2, n):
            basis.append(2 * s * basis[-1] - basis[-2])
        return jnp.stack(basis[:n]) @ self.coeffs


class Chebyshev(Parametrization):
    MIN_N = 0  # the degree: 0 is a constant control

    @property
    def size(self):
        return (self.n + 1) * self.dim

    def signal(self, params):
        params = self._check(params)
        return _ChebyshevSignal(_device(params.reshape(self.n + 1, self.dim)), self.t0, self.T)
