"""Constrained Lagrangian systems with equations of motion derived by autodiff.

Given, in generalized coordinates q (n of them),

* kinetic energy T(q, q') (quadratic in q'), potential V(q),
* velocity constraints  c(t, q, q') = A(t, q) q' + a(t, q) = 0   (Pfaffian;
  nonholonomic, or momentum constraints),
* position constraints  phi(t, q) = 0   (holonomic; enforced at acceleration level),
* generalized forces    F(t, q, q', u),

the Lagrange–d'Alembert equations are

    M(q) q'' = dL/dq - (d/dq dT/dq') q' + F + A_all^T lam,
    A_all q'' + b = 0,

with M = d^2 T / dq'^2, A_all the Jacobian of all velocity-level constraints
(c, and dphi/dt = phi_q q' + phi_t) with respect to q', and b their
acceleration-level remainder. M, the Coriolis/centrifugal terms, A_all and b all
come from jax (Hessian, jvp); q'' and the multipliers lam come from the KKT
system [[M, A^T], [A, 0]] (q'', -lam) = (rhs, -b). Optional Baumgarte
stabilization replaces ``A q'' + b = 0`` by ``d/dt c + 2 alpha c + beta^2 phi = 0``.

The state is the flat vector x = (q, q').
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np

from .. import _args as Vd
from ._kkt import (
    REGULARITY_HINTS,
    kkt_accelerations,
    kkt_matrix,
    metric_projection,
    newton_project,
    regularity_margins,
)
from ..errors import ParameterError
from .system import AbstractSystem

__all__ = ["ConstrainedLagrangian", "Lagrangian"]


def baumgarte_pair(owner, gains):
    """(alpha, beta) [1/s]: two finite, non-negative Baumgarte gains."""
    try:
        a, b = gains
    except (TypeError, ValueError):
        raise Vd.ParameterError(f"{owner}: baumgarte must be a pair (alpha, beta) of gains [1/s], got {gains!r}",
                                "baumgarte", gains) from None
    return tuple(float(Vd.positive(n, v, allow_zero=True, owner=owner, as_float=True, shape=(), what="Baumgarte gain [1/s]"))
                 for n, v in (("baumgarte[0]", a), ("baumgarte[1]", b)))


class ConstrainedLagrangian(AbstractSystem):
    """Abstract constrained Lagrangian system; subclasses define the energies.

    Override ``kinetic_energy(q, qd)`` and any of ``potential_energy(q)``,
    ``velocity_constraints(t, q, qd)`` (affine in qd), ``position_constraints(t, q)``,
    ``generalized_force(t, q, qd, u)``. Set ``n`` (number of coordinates).
    """

    n: eqx.AbstractVar[int]
    regularity_hints = REGULARITY_HINTS
    # The engine's vector field (mass matrix and constraint Jacobian by autodiff, a KKT
    # solve) is large: tracing it once per step instead of once per stage shortens the
    # compile of every shipped scene's first simulate(), most for the largest vector
    # fields, at the same or lower run time (benchmarks/compile_times.py measures it).
    large_vector_field = True

    # ----------------------------------------------------------- to override
    def kinetic_energy(self, q, qd):
        raise NotImplementedError

    def potential_energy(self, q):
        return jnp.zeros((), dtype=q.dtype)

    def velocity_constraints(self, t, q, qd):
        return jnp.zeros((0,), dtype=q.dtype)

    def position_constraints(self, t, q):
        return jnp.zeros((0,), dtype=q.dtype)

    def generalized_force(self, t, q, qd, u):
        return jnp.zeros_like(q)

    # Baumgarte gains (alpha, beta); (0, 0) means exact index reduction.
    baumgarte: tuple[float, float] = eqx.field(default=(0.0, 0.0), static=True)

    # ------------------------------------------------------------- derived
    def split(self, x):
        return x[: self.n], x[self.n :]

    def lagrangian(self, q, qd):
        return self.kinetic_energy(q, qd) - self.potential_energy(q)

    def momentum(self, q, qd):
        """p = dT/dq'."""
        return jax.grad(self.kinetic_energy, argnums=1)(q, qd)

    def mass_matrix(self, q):
        """M(q) = d^2 T / dq'^2 (T is quadratic in q', so any q' gives the same M)."""
        return _mass_matrix(self, q)

    def _all_velocity_constraints(self, t, q, qd):
        c = self.velocity_constraints(t, q, qd)
        phi_dot = jax.jvp(
            lambda tt, qq: self.position_constraints(tt, qq),
            (jnp.asarray(t, q.dtype), q),
            (jnp.ones((), q.dtype), qd),
        )[1]
        return jnp.concatenate([jnp.atleast_1d(c), jnp.atleast_1d(phi_dot)])

    def constraint_jacobian(self, t, q):
        """A_all(t, q): Jacobian of all velocity-level constraints w.r.t. q'."""
        return _constraint_jacobian(self, jnp.asarray(t, q.dtype), q)

    def dynamics_terms(self, t, q, qd, u):
        """(M, rhs, A, b): the pieces of the KKT system at (t, q, q')."""
        rhs, b = self._rhs_terms(t, q, qd, u)
        return self.mass_matrix(q), rhs, self.constraint_jacobian(t, q), b

    def _rhs_terms(self, t, q, qd, u):
        """(rhs, b): the velocity-dependent parts of the KKT system (M and A depend on
        (t, q) only)."""
        dLdq = jax.grad(self.lagrangian, argnums=0)(q, qd)
        # (d/dq dT/dq') q' by a forward-mode directional derivative
        dpdq_qd = jax.jvp(lambda qq: self.momentum(qq, qd), (q,), (qd,))[1]
        if u is None:
            u = jnp.zeros((self.control_dim,), q.dtype)
        rhs = dLdq - dpdq_qd + self.generalized_force(t, q, qd, u)
        # b = d/dt c at fixed q'' = 0: derivative of c along (t, q) -> (1, q')
        tt = jnp.asarray(t, q.dtype)
        b = jax.jvp(
            lambda s, qq: self._all_velocity_constraints(s, qq, qd),
            (tt, q),
            (jnp.ones((), q.dtype), qd),
        )[1]
        alpha, beta = self.baumgarte
        if alpha or beta:
            c = self._all_velocity_constraints(t, q, qd)
            phi = self.position_constraints(t, q)
            pad = jnp.zeros(c.shape[0] - jnp.atleast_1d(phi).shape[0], q.dtype)
            b = b + 2 * alpha * c + beta**2 * jnp.concatenate([pad, jnp.atleast_1d(phi)])
        return rhs, b

    def accelerations(self, t, q, qd, u=None):
        """(q'', lam): accelerations and constraint multipliers (force A^T lam)."""
        return kkt_accelerations(*self.dynamics_terms(t, q, qd, u))

    def inverse_dynamics(self, t, q, qd, qdd, input_matrix):
        """Inputs u and multipliers lam that produce q'' (least squares).

        Solves  M q'' - rhs(u=0) = B u + A^T lam  for (u, lam) where B is
        ``input_matrix`` (n x k: generalized force per unit input) and checks
        nothing: the caller asserts that q'' is consistent with the constraints.
        """
        M, rhs, A, _ = self.dynamics_terms(t, q, qd, None)
        lhs = M @ qdd - rhs
        G = jnp.concatenate([input_matrix, A.T], axis=1)
        sol = jnp.linalg.lstsq(G, lhs)[0]
        k = input_matrix.shape[1]
        return sol[:k], sol[k:]

    # --------------------------------------------------- AbstractSystem API
    def vector_field(self, t, x, u):
        q, qd = self.split(x)
        qdd, _ = self.accelerations(t, q, qd, u)
        return jnp.concatenate([qd, qdd])

    def constraints(self, t, x):
        q, qd = self.split(x)
        out = {}
        c = jnp.atleast_1d(self.velocity_constraints(t, q, qd))
        if c.shape[0]:
            out["velocity"] = c
        phi = jnp.atleast_1d(self.position_constraints(t, q))
        if phi.shape[0]:
            out["position"] = phi
            out["position_rate"] = self._all_velocity_constraints(t, q, qd)[c.shape[0] :]
        return out

    def regularity(self, t, x):
        q, _ = self.split(x)
        return regularity_margins(self.mass_matrix(q), self.constraint_jacobian(t, q))

    def energy(self, x):
        q, qd = self.split(x)
        return self.kinetic_energy(q, qd) + self.potential_energy(q)

    def power(self, t, x, u):
        q, qd = self.split(x)
        return jnp.dot(self.generalized_force(t, q, qd, u), qd)

    def fixed_components(self, fixed) -> tuple[np.ndarray, np.ndarray]:
        """(positions, velocities): boolean masks of the state components named by
        ``fixed`` (names from ``state_names`` or indices into x = (q, q'))."""
        owner = type(self).__name__
        names = tuple(self.state_names)
        n = self.n
        if isinstance(fixed, (str, int, np.integer)):
            fixed = (fixed,)
        mask = np.zeros(2 * n, bool)
        for item in fixed:
            if isinstance(item, str):
                if item not in names:
                    raise ParameterError(
                        f"{owner}.project: fixed={fixed!r} names {item!r}, which is not a state component; "
                        f"state_names = {names or '() (pass state_names= or use indices 0..2n-1)'}",
                        "fixed", fixed)
                mask[names.index(item)] = True
            elif isinstance(item, (int, np.integer)) and not isinstance(item, bool) and -2 * n <= item < 2 * n:
                mask[int(item)] = True
            else:
                raise ParameterError(
                    f"{owner}.project: fixed={fixed!r} holds {item!r}; each entry must be a state name or an "
                    f"index into x = (q, q') in 0..{2 * n - 1}", "fixed", fixed)
        return mask[:n], mask[n:]

    def project(self, t, x, fixed=None):
        """Consistent state near ``x``.

        Without ``fixed``: the nearest one, by minimum-norm Newton on phi(q) = 0, then
        the kinetic-metric projection of q' onto A_all q' + a = 0 (every component
        may move).

        With ``fixed`` (state names, or indices into x = (q, q')): the components
        named stay exactly as given and the others are solved for, so that a user
        chooses the independent coordinates (a bicycle's lean, steer and forward
        speed) and gets the dependent ones. Positions: Newton steps on phi(q) = 0
        in the free positions only (minimum norm among them; 8 steps, quadratic
        convergence from a nearby guess). Velocities: the constraints are affine in
        q', so one solve gives the free velocities exactly, with the smallest
        correction in the kinetic metric restricted to them (unique when as many
        velocities are free as there are constraints). The free columns of the
        constraint Jacobians must have full row rank, else the fixed values are
        inconsistent with the constraints and the result is not finite; check
        ``constraint_residual`` of the result.
        """
        q, qd = self.split(x)
        if fixed is not None:
            return self._project_fixed(t, q, qd, *self.fixed_components(fixed))
        q = self._project_q(t, q)
        A = self.constraint_jacobian(t, q)
        if A.shape[0]:
            r = self._all_velocity_constraints(t, q, qd)
            qd = qd + metric_projection(self.mass_matrix(q), A, r)
        return jnp.concatenate([q, qd])

    def _project_q(self, t, q):
        phi0 = jnp.atleast_1d(self.position_constraints(t, q))
        if phi0.shape[0]:
            q = newton_project(lambda qq: jnp.atleast_1d(self.position_constraints(t, qq)), q)
        return q

    # ---------------------------------- the projection split for projected solves
    @property
    def splits_projection(self) -> bool:
        """Whether a projected solve may split ``project`` in two: the positions after
        each step (``project_positions``), the velocities at the next step's first
        stage (``projected_field``), where the step evaluates M(q) and A(q) at the
        projected positions anyway. True unless a subclass redefines the vector field,
        the dynamics or the projection (then the solve projects with ``project``)."""
        cls, base = type(self), ConstrainedLagrangian
        return all(getattr(cls, k) is getattr(base, k)
                   for k in ("vector_field", "project", "dynamics_terms", "accelerations", "_rhs_terms"))

    def project_positions(self, t, x):
        """``project``'s first half: the positions onto phi(t, q) = 0 (minimum-norm Newton),
        the velocities as given."""
        q, qd = self.split(x)
        return jnp.concatenate([self._project_q(t, q), qd])

    def projected_field(self, t, x, apply, control=None):
        """``project``'s second half and the vector field, from one evaluation of M(q),
        A(q) and one LU factorization of the KKT matrix: where ``apply`` (a bool),
        x' = (q, q' + dv) with dv the kinetic-metric projection of q' onto the
        velocity constraints (as ``project`` computes it), else x' = x; then the
        vector field at x' with u = control(t, x') (None: no input).
        Returns (x', vector field, u)."""
        q, qd = self.split(x)
        M, A = self.mass_matrix(q), self.constraint_jacobian(t, q)
        n, m = M.shape[0], A.shape[0]
        lu = jax.scipy.linalg.lu_factor(kkt_matrix(M, A))
        if m:
            r = self._all_velocity_constraints(t, q, qd)
            dv = jax.scipy.linalg.lu_solve(lu, jnp.concatenate([jnp.zeros(n, M.dtype), -r]))[:n]
            qd = jnp.where(apply, qd + dv, qd)
        xp = jnp.concatenate([q, qd])
        u = None if control is None else control(t, xp)
        rhs, b = self._rhs_terms(t, q, qd, u)
        qdd = jax.scipy.linalg.lu_solve(lu, jnp.concatenate([rhs, -b]) if m else rhs)[:n]
        return xp, jnp.concatenate([qd, qdd]), u

    def _project_fixed(self, t, q, qd, fixed_q, fixed_v):
        owner = type(self).__name__
        free_q, free_v = np.flatnonzero(~fixed_q), np.flatnonzero(~fixed_v)
        phi0 = jnp.atleast_1d(self.position_constraints(t, q))
        if phi0.shape[0]:
            if free_q.size < phi0.shape[0]:
                raise ParameterError(
                    f"{owner}.project: {phi0.shape[0]} position constraints but only {free_q.size} free positions "
                    "to satisfy them; fix fewer positions", "fixed", None)
            sub = lambda z: jnp.atleast_1d(self.position_constraints(t, q.at[free_q].set(z)))  # noqa: E731
            q = q.at[free_q].set(newton_project(sub, q[free_q], iterations=8))
        A = self.constraint_jacobian(t, q)
        if A.shape[0]:
            if free_v.size < A.shape[0]:
                raise ParameterError(
                    f"{owner}.project: {A.shape[0]} velocity-level constraints but only {free_v.size} free "
                    "velocities to satisfy them; fix fewer velocities", "fixed", None)
            r = self._all_velocity_constraints(t, q, qd)
            M = self.mass_matrix(q)
            qd = qd.at[free_v].add(metric_projection(M[np.ix_(free_v, free_v)], A[:, free_v], r))
        return jnp.concatenate([q, qd])


# M and A as nested jits: a first simulate() needs them in the vector field, in the
# input checks' regularity margins and in the projection onto the constraints (each
# traced in a program of its own or in a loop of its own); a nested jit traces each
# once per system structure and coordinate shape and reuses that jaxpr at the other
# places. XLA inlines the calls.
@eqx.filter_jit
def _mass_matrix(system, q):
    return jax.jacfwd(system.momentum, argnums=1)(q, jnp.zeros_like(q))


@eqx.filter_jit
def _constraint_jacobian(system, t, q):
    return jax.jacfwd(lambda v: system._all_velocity_constraints(t, q, v))(jnp.zeros_like(q))


def _state_names(owner, names, n):
    """() or 2n names for x = (q, q'): n coordinate names get '<name>_dot' velocities."""
    if names is None:
        return ()
    if isinstance(names, str) or not all(isinstance(v, str) for v in names):
        raise ParameterError(f"{owner}: state_names must be a sequence of strings, got {names!r}",
                             "state_names", names)
    names = tuple(names)
    if isinstance(n, int) and len(names) == n:
        names = names + tuple(f"{v}_dot" for v in names)
    if not isinstance(n, int) or len(names) != 2 * n:
        raise ParameterError(
            f"{owner}: state_names has {len(names)} entries; give n = {n} coordinate names (velocities become "
            f"'<name>_dot') or all 2n = {2 * n if isinstance(n, int) else '2n'} names of x = (q, q')",
            "state_names", names)
    if len(set(names)) != len(names):
        raise ParameterError(f"{owner}: state_names must be distinct, got {names!r}", "state_names", names)
    return names


def _invariant_table(owner, arg, table):
    """((key, fn), ...) from {name: fn(q, qd)} or {name: (fn(q, qd), unit)}; the key
    carries the unit as 'name [unit]', which is how it appears in summary()."""
    if table is None:
        return ()
    if not isinstance(table, dict):
        raise ParameterError(
            f"{owner}: {arg} must be a dict name -> fn(q, qd) or name -> (fn(q, qd), unit), got {table!r}",
            arg, table)
    out = []
    for name, entry in table.items():
        fn, unit = (entry if isinstance(entry, tuple) else (entry, ""))
        if not callable(fn) or not isinstance(unit, str) or not isinstance(name, str):
            raise ParameterError(
                f"{owner}: {arg}[{name!r}] must be fn(q, qd) -> scalar or a pair (fn, 'unit'), got {entry!r}",
                arg, table)
        out.append((f"{name} [{unit}]" if unit else name, fn))
    return tuple(out)


def _output_shape(fn, *args):
    """The shape of ``fn(*args)`` by abstract evaluation (nothing runs), or None when it
    cannot be told here (the function fails on placeholder arguments, or returns
    something other than one array): the solve then reports what goes wrong."""
    try:
        out = jax.eval_shape(fn, *args)
    except Exception:  # noqa: BLE001 - whatever it is, the solve meets it with its own words
        return None
    return tuple(out.shape) if isinstance(out, jax.ShapeDtypeStruct) else None


def _check_outputs(owner, n, k, *, T, V, velocity_constraints, position_constraints, force, invariants):
    """ParameterError naming the function whose output has the wrong shape for n
    coordinates and k inputs (read off abstract evaluations: checked once, at
    construction, instead of failing inside autodiff's derivation of the equations)."""
    q = jax.ShapeDtypeStruct((n,), jnp.float64)
    t = jax.ShapeDtypeStruct((), jnp.float64)
    u = jax.ShapeDtypeStruct((k,), jnp.float64)
    checks = [("T", T, (q, q), "T(q, qd) must return the kinetic energy, a scalar [J]", lambda s: s == ()),
              ("V", V, (q,), "V(q) must return the potential energy, a scalar [J]", lambda s: s == ()),
              ("velocity_constraints", velocity_constraints, (t, q, q),
               "velocity_constraints(t, q, qd) must return a vector (m,) of constraint values", lambda s: len(s) <= 1),
              ("position_constraints", position_constraints, (t, q),
               "position_constraints(t, q) must return a vector (k,) of constraint values", lambda s: len(s) <= 1),
              ("force", force, (t, q, q, u), f"force(t, q, qd, u) must return the generalized force, shape ({n},)",
               lambda s: s == (n,))]
    checks += [("invariants", fn, (q, q), f"invariant {name!r}: fn(q, qd) must return a scalar", lambda s: s == ())
               for name, fn in invariants]
    for name, fn, args, what, ok in checks:
        if fn is None:
            continue
        shape = _output_shape(fn, *args)
        if shape is not None and not ok(shape):
            raise ParameterError(f"{owner}: {what}; it returns shape {shape} (with n = {n} coordinates"
                                 f"{f' and {k} inputs' if name == 'force' else ''})", name, fn)


class Lagrangian(ConstrainedLagrangian):
    """A ConstrainedLagrangian from plain functions (quick user-defined systems).

    ``Lagrangian(n=2, T=lambda q, qd: ..., V=..., velocity_constraints=...,
    position_constraints=..., force=lambda t, q, qd, u: ..., control_dim=k,
    state_names=("th1", "th2"), invariants={"L": (lambda q, qd: ..., "kg m^2/s")})``.
    The functions may close over arrays (then those are constants to jit/grad)
    or be equinox Modules (then their arrays are traced parameters).

    ``state_names``: n coordinate names (the velocities are then named
    '<name>_dot') or all 2n names of x = (q, q'); ``traj["th1"]`` and
    ``project(t, x, fixed=("th1", ...))`` use them.
    ``invariants``: quantities conserved for every input, name -> fn(q, qd) or
    name -> (fn(q, qd), unit); simulate() reports their values and drift like a
    shipped scene's, under the key 'name [unit]' (so ``summary()`` shows the unit).
    ``free_invariants``: the same for quantities conserved only without inputs.
    """

    n: int = eqx.field(static=True)
    T: Callable = None
    V: Callable | None = None
    vel_c: Callable | None = None
    pos_c: Callable | None = None
    force: Callable | None = None
    n_controls: int = eqx.field(default=0, static=True)
    baumgarte: tuple[float, float] = eqx.field(default=(0.0, 0.0), static=True)
    state_names: tuple = eqx.field(default=(), static=True)
    user_invariants: tuple = ()
    user_free_invariants: tuple = ()

    def __init__(
        self,
        n,
        T,
        V=None,
        velocity_constraints=None,
        position_constraints=None,
        force=None,
        control_dim=0,
        baumgarte=(0.0, 0.0),
        state_names=None,
        invariants=None,
        free_invariants=None,
    ):
        owner = "Lagrangian"
        self.state_names = _state_names(owner, state_names, int(n) if isinstance(n, (int, np.integer)) else n)
        self.user_invariants = _invariant_table(owner, "invariants", invariants)
        self.user_free_invariants = _invariant_table(owner, "free_invariants", free_invariants)
        self.n = Vd.integer("n", n, minimum=1, owner=owner, what="number of generalized coordinates")
        self.T = Vd.function("T", T, owner=owner, signature="T(q, qd) -> kinetic energy")
        self.V = Vd.function("V", V, owner=owner, signature="V(q) -> potential energy", optional=True)
        self.force = Vd.function("force", force, owner=owner, signature="force(t, q, qd, u) -> (n,)", optional=True)
        self.vel_c = Vd.function("velocity_constraints", velocity_constraints, owner=owner,
                                 signature="velocity_constraints(t, q, qd) -> (m,)", optional=True)
        self.pos_c = Vd.function("position_constraints", position_constraints, owner=owner,
                                 signature="position_constraints(t, q) -> (k,)", optional=True)
        self.n_controls = Vd.integer("control_dim", control_dim, minimum=0, owner=owner, what="number of inputs")
        if self.n_controls and force is None:
            raise Vd.ParameterError(
                f"{owner}: control_dim={self.n_controls} but no force(t, q, qd, u) to feed the inputs into; "
                "pass force=... or control_dim=0", "control_dim", control_dim)
        self.baumgarte = baumgarte_pair(owner, baumgarte)
        _check_outputs(owner, self.n, self.n_controls, T=T, V=V, velocity_constraints=velocity_constraints,
                       position_constraints=position_constraints, force=force,
                       invariants=self.user_invariants + self.user_free_invariants)

    @property
    def control_dim(self):  # type: ignore[override]
        return self.n_controls

    def kinetic_energy(self, q, qd):
        return self.T(q, qd)

    def potential_energy(self, q):
        return self.V(q) if self.V is not None else jnp.zeros((), q.dtype)

    def velocity_constraints(self, t, q, qd):
        return self.vel_c(t, q, qd) if self.vel_c is not None else jnp.zeros((0,), q.dtype)

    def position_constraints(self, t, q):
        return self.pos_c(t, q) if self.pos_c is not None else jnp.zeros((0,), q.dtype)

    def generalized_force(self, t, q, qd, u):
        return self.force(t, q, qd, u) if self.force is not None else jnp.zeros_like(q)

    def invariants(self, x):
        q, qd = self.split(x)
        return {k: jnp.asarray(fn(q, qd)) for k, fn in self.user_invariants}

    def free_invariants(self, x):
        q, qd = self.split(x)
        return {k: jnp.asarray(fn(q, qd)) for k, fn in self.user_free_invariants}
