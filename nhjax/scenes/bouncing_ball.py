r"""A ball bouncing on a vibrating table under gravity: Ibort et al. (seed 004), example 10.2.

Model
-----
A point mass m [kg] moves on a vertical line, height x [m], under gravity
g [m/s^2]; the table's surface moves as x_W(t) = A sin(omega t) (amplitude
A [m], angular frequency omega [rad/s]) and is infinitely heavy (M >> 1 in the
seed). The seed's Lagrangian and one-sided constraint:

    L = m/2 v^2 - m g x,        psi(t, x) = x - A sin(omega t) >= 0.

At an impact time t_i the velocity jumps by the seed's rule with restitution
alpha in [0, 1],

    v1(t_i) - x_W'(t_i) = -alpha (v0(t_i) - x_W'(t_i)),  i.e.
    v1(t_i) = (1 + alpha) A omega cos(omega t_i) - alpha v0(t_i),

which is what the affine projector (18) gives for this constraint
(``nhjax.mechanics.impacts``). Between impacts the flight is an exact
parabola, x(t) = x_i + v_i (t - t_i) - g (t - t_i)^2 / 2, so any Runge-Kutta
method of order >= 2 integrates it to round-off: ``simulate_impacts``'s impact
times are the roots of the exact flight to round-off, which
``reference_impacts`` (NumPy, independent of JAX: bracketing on the exact
parabola and bisection) checks.

The seed's high-bounce map (flight long compared with the table's motion, so
the table is taken at x = 0 for the flight: t_{i+1} - t_i = 2 v_i / g and
v0(t_{i+1}) = -v1(t_i)):

    f(t, v) = (t + 2 v / g,  alpha v + (1 + alpha) A omega cos(omega t + 2 omega v / g)),

``high_bounce_map`` / ``high_bounce_orbit``. Its dimensionless control
parameter is the table's normalized acceleration Gamma = A omega^2 / g
(``gamma``). With Gamma < 1 the table never accelerates downwards faster than
g: a chattering ball comes to rest on it (``simulate_impacts`` ends the Zeno
sequence in resting contact) and stays; with Gamma > 1 a resting ball is
released where the table's acceleration passes -g (the contact multiplier
mu = m (g - A omega^2 sin(omega t)) crosses zero).

Parameters: g [m/s^2] >= 0 (default 9.81), A [m] >= 0 (default 0.01),
omega [rad/s] > 0 (default 2 pi 10), restitution alpha in [0, 1] (default 0.8),
m [kg] > 0 (default 1). State x = (x, x'). ``event_resolution`` (a quarter
of the table's period) is the default largest step of ``simulate_impacts`` so
that its dense-output samples resolve the table's motion.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..mechanics import ConstrainedLagrangian
from ._validate import in_range, positive, real, to_device

__all__ = ["BouncingBall"]


class BouncingBall(ConstrainedLagrangian):
    """Ball on a table x_W = A sin(omega t) under gravity (seed 004, ex. 10.2); see the module docstring."""

    g: jax.Array
    A: jax.Array
    omega: jax.Array
    restitution: jax.Array
    m: jax.Array
    n: int = eqx.field(static=True, default=1)

    state_names: ClassVar[tuple] = ("x", "x_dot")
    control_dim: ClassVar[int] = 0

    def __init__(self, g=9.81, A=0.01, omega=2 * np.pi * 10, restitution=0.8, m=1.0):
        positive("g", g, allow_zero=True)
        positive("A", A, allow_zero=True)
        positive("omega", omega)
        positive("m", m)
        in_range("restitution", restitution, 0.0, 1.0, owner="BouncingBall", what="coefficient of restitution")
        self.g, self.A, self.omega, self.restitution, self.m = (
            to_device(v) for v in (g, A, omega, restitution, m))
        self.n = 1

    # ---------------------------------------------------------------- model
    def kinetic_energy(self, q, qd):
        return 0.5 * self.m * qd[0] ** 2

    def potential_energy(self, q):
        return self.m * self.g * q[0]

    def table(self, t):
        """Table height x_W(t) = A sin(omega t) [m]."""
        return self.A * jnp.sin(self.omega * t)

    def table_velocity(self, t):
        return self.A * self.omega * jnp.cos(self.omega * t)

    def unilateral_constraints(self, t, q):
        return jnp.stack([q[0] - self.table(t)])

    @property
    def gamma(self):
        """Normalized table acceleration Gamma = A omega^2 / g."""
        return self.A * self.omega**2 / self.g

    @property
    def event_resolution(self):
        """Largest step [s] for simulate_impacts: a quarter of the table's period."""
        return 2 * np.pi / float(self.omega) / 4 if not isinstance(self.omega, jax.core.Tracer) else None

    def initial_state(self, height=0.1, velocity=0.0, t0=0.0):
        """State at t0 with the ball ``height`` [m] above the table's surface and
        velocity ``velocity`` [m/s]."""
        owner = "BouncingBall.initial_state"
        height = positive("height", height, allow_zero=True, owner=owner, what="above the table [m]")
        velocity = real("velocity", velocity, owner=owner, what="[m/s]")
        t0 = real("t0", t0, owner=owner, what="[s]")
        if any(isinstance(v, jax.core.Tracer) for v in (height, velocity, t0, self.A, self.omega)):
            return jnp.stack([self.table(t0) + jnp.asarray(height, float), jnp.asarray(velocity, float)])
        # concrete numbers: computed on the host (eager jnp operations are programs compiled
        # per process)
        table = np.asarray(self.A) * np.sin(np.asarray(self.omega) * np.asarray(t0))
        return to_device(np.stack([table + np.asarray(height), np.asarray(velocity)]))

    def invariants(self, x):
        return {}

    # ---------------------------------------------------------------- closed forms
    def rebound(self, t, v0):
        """Velocity after an impact at time t with approach velocity v0 (seed 10.2)."""
        return (1 + self.restitution) * self.table_velocity(t) - self.restitution * v0

    def high_bounce_map(self, t, v):
        """The seed's map f(t, v) = (t + 2v/g, alpha v + (1+alpha) A omega cos(omega t + 2 omega v/g))
        on (impact time, departure velocity)."""
        t1 = t + 2 * v / self.g
        return t1, self.restitution * v + (1 + self.restitution) * self.A * self.omega * jnp.cos(self.omega * t1)

    def high_bounce_orbit(self, t0, v0, n):
        """n iterates of the high-bounce map from (t0, v0): arrays (times, departure velocities)."""
        def step(c, _):
            c = self.high_bounce_map(*c)
            return c, c

        _, (ts, vs) = jax.lax.scan(step, (jnp.asarray(t0, float), jnp.asarray(v0, float)), None, length=n)
        return ts, vs

    def flight(self, t, t_i, x_i, v_i):
        """Exact free flight from (t_i, x_i, v_i): (x(t), x'(t))."""
        s = t - t_i
        return x_i + v_i * s - 0.5 * self.g * s**2, v_i - self.g * s

    def reference_impacts(self, t0, x0, v0, n, dt_scan=None):
        """Impacts of the exact motion by NumPy: exact parabolas between impacts, each
        next impact the first sign change of the gap on a grid of spacing ``dt_scan``
        (default 1/400 of the table's period) refined by bisection to round-off.

        Independent of JAX and of simulate_impacts; no resting contact (stops after n
        impacts). Returns dict of arrays: times, v_pre, v_post, x (impact heights)."""
        g, A, w, al = (float(v) for v in (self.g, self.A, self.omega, self.restitution))
        dt = (2 * np.pi / w) / 400 if dt_scan is None else dt_scan
        t_i, x_i, v_i = float(t0), float(x0), float(v0)
        out = {k: np.full(n, np.nan) for k in ("times", "v_pre", "v_post", "x")}

        def gap(t):
            s = t - t_i
            return x_i + v_i * s - 0.5 * g * s * s - A * np.sin(w * t)

        for i in range(n):
            # scan ahead in blocks for the first negative gap
            start, found = t_i, None
            while found is None:
                grid = start + dt * np.arange(1, 4097)
                d = gap(grid)
                neg = np.flatnonzero(d < 0)
                if neg.size:
                    j = neg[0]
                    found = (grid[j - 1] if j > 0 else start, grid[j])
                start = grid[-1]
                if start - t_i > 1e6 * dt:
                    return out
            lo, hi = found
            for _ in range(200):
                mid = 0.5 * (lo + hi)
                if mid == lo or mid == hi:
                    break
                if gap(mid) >= 0:
                    lo = mid
                else:
                    hi = mid
            t_n = lo if abs(gap(lo)) <= abs(gap(hi)) else hi
            s = t_n - t_i
            v_pre = v_i - g * s
            v_post = (1 + al) * A * w * np.cos(w * t_n) - al * v_pre
            out["times"][i], out["v_pre"][i], out["v_post"][i] = t_n, v_pre, v_post
            out["x"][i] = A * np.sin(w * t_n)
            t_i, x_i, v_i = t_n, A * np.sin(w * t_n), v_post
        return out
