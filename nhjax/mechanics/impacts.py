r"""One-sided constraints and impulsive jumps: the affine projector of Ibort et al. (seed 004).

A system with impacts is a constrained Lagrangian (``ConstrainedLagrangian``:
kinetic metric M(q) = d^2T/dq'^2, permanent Pfaffian constraints
A(t, q) q' + a(t, q) = 0, rolling included) plus k one-sided holonomic
constraints that may move in time (seed sec. 8, 9: "mixed constraints"),

    psi_a(t, q) >= 0,   a = 1..k        (admissible side: psi >= 0),

declared by the system as ``unilateral_constraints(t, q)`` together with a
coefficient of restitution per contact, ``restitution`` (scalar or (k,),
each in [0, 1]). ``WithContacts(system, psi, restitution)`` adds them to any
``ConstrainedLagrangian`` (a user's ``Lagrangian`` included), so a Lagrangian
plus a one-sided constraint gets impacts from ``nhjax.simulate_impacts``.

Kinematics of a contact (all by autodiff):
    J = dpsi/dq (k x n),   j = dpsi/dt,
    normal velocity  Psi = J q' + j   (seed: the instantaneous constraint
    Psi = psi^c, the complete lift of sec. 8),
    normal acceleration  Psi' = J q'' + c(t, q, q').

The jump (seed sec. 7, eqs. (15)-(18)). Write g^{-1} = M^{-1}, Phi_kappa^A = A
(all permanent constraints, nonholonomic and differentiated holonomic),
C_AB = A M^{-1} A^T. The impulsive constraints, projected along the permanent
ones, are

    beta   = J - J M^{-1} A^T C^{-1} A           (rows beta^a_kappa),
    betabar = j - J M^{-1} A^T C^{-1} a          (in the seed: betabar^a),
    C'      = beta M^{-1} beta^T                 (C'_ab, invertible when the
                                                  rows of [A; J] are independent)

and, if the impulsive constraints remain after the impulse (a plastic impact),
the momentum after the impulse is (17)

    p1 = p0 - beta^T C'^{-1} (beta M^{-1} p0 + betabar)  =  P p0 + c     (18)

with the linear part P = I - beta^T C'^{-1} beta M^{-1} a projector (P^2 = P)
and the affine part c = -beta^T C'^{-1} betabar: the "affine projector" P'.
With restitution alpha_a the same impulse direction is scaled,

    p1 = p0 - beta^T C'^{-1} diag(1 + alpha) (beta v0 + betabar),

which is the generalized Newton law Psi_a(v1) = -alpha_a Psi_a(v0) for every
contact in the impact and keeps A v1 + a = 0 (A M^{-1} beta^T = 0): the
rolling constraints are kept through the jump. alpha = 0 is (17), alpha = 1 is
the seed's elastic "projector" of examples 10.1 (ii) and 10.3 (twice the
plastic correction). On a fixed wall (j = 0, a = 0) the elastic jump keeps the
kinetic energy exactly: v1 is the M-orthogonal reflection of v0.

The impulse on contact a is mu_a = -(C'^{-1} diag(1 + alpha)(beta v0 +
betabar))_a (the generalized impulse is J^T mu + A^T lambda); mu_a >= 0
pushes into the admissible side. When several contacts are in one impact, a
contact whose impulse comes out negative (it would pull) is dropped from the
impact and the jump recomputed (``impact_velocities``: at most k rounds).

Persistent (resting, sliding, sticking) contact: a contact whose constraint
remains (psi_a = 0 and Psi_a = 0, e.g. after a plastic impact) is enforced as
a bilateral constraint at acceleration level, with multiplier mu_a (force J^T
mu) from the KKT system of ``contact_dynamics``; it lasts while mu_a >= 0
(compressive) and is released where mu_a crosses zero. This is the Chetaev
bundle of sec. 8 with the boundary component switched on.

Seed conventions re-derived: the seed writes the circle of example 10.1 as
psi = x^2 + y^2 - f(t) <= 0; here every one-sided constraint is psi >= 0
(the admissible side positive), so the circle is psi = f(t) - x^2 - y^2.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._args import function, in_range
from .._linalg import SMALL, solve as small_solve
from ..errors import ParameterError
from .lagrangian import ConstrainedLagrangian

__all__ = [
    "WithContacts",
    "affine_projector",
    "contact_dynamics",
    "contact_kinematics",
    "impact_geometry",
    "impact_velocities",
    "restitution_of",
]


def _as_float(t, q):
    return jnp.asarray(t, q.dtype)


def restitution_of(system, k):
    """The restitution coefficients of ``system`` as a (k,) array (a scalar is shared)."""
    alpha = getattr(system, "restitution", None)
    if alpha is None:
        raise TypeError(
            f"{type(system).__name__} has no 'restitution': give the system a restitution "
            "coefficient in [0, 1] (scenes take restitution=..., WithContacts(system, psi, "
            "restitution=...)) or pass restitution= to simulate_impacts"
        )
    return jnp.broadcast_to(jnp.asarray(alpha, float), (k,))


def contact_kinematics(system, t, q, qd):
    """(psi, J, Psi): gaps psi(t, q) (k,), their Jacobian J = dpsi/dq (k, n) and the
    normal velocities Psi = J q' + dpsi/dt (k,)."""
    t = _as_float(t, q)

    def psi_of(tt, qq):
        return jnp.atleast_1d(system.unilateral_constraints(tt, qq))

    psi, Psi = jax.jvp(psi_of, (t, q), (jnp.ones((), q.dtype), qd))
    J = jax.jacfwd(lambda qq: psi_of(t, qq))(q)
    return psi, J, Psi


def _contact_rates(system, t, q, qd):
    """(J, Psi, c): Jacobian, normal velocities, and the acceleration remainder c
    with Psi' = J q'' + c (the derivative of Psi along (1, q') at fixed q')."""
    t = _as_float(t, q)

    def Psi_of(tt, qq):
        return jax.jvp(
            lambda s, x: jnp.atleast_1d(system.unilateral_constraints(s, x)),
            (tt, qq), (jnp.ones((), q.dtype), qd),
        )[1]

    Psi, c = jax.jvp(Psi_of, (t, q), (jnp.ones((), q.dtype), qd))
    J = jax.jacfwd(lambda qq: jnp.atleast_1d(system.unilateral_constraints(t, qq)))(q)
    return J, Psi, c


def _permanent(system, t, q):
    """(A, a): all permanent velocity-level constraints A q' + a = 0."""
    A = system.constraint_jacobian(t, q)
    a = system._all_velocity_constraints(t, q, jnp.zeros_like(q))
    return A, a


def small_kkt(n: int, m: int, k: int) -> bool:
    """Whether the contact KKT of n coordinates, m permanent and k contact constraints
    (the largest linear system of an impact solve) is small enough for the unrolled
    elimination (``nhjax._linalg.solve``); then every solve of the event loop is one, the
    loop calls no LAPACK and XLA compiles it into one function."""
    return n + m + k <= SMALL


def kkt_solve(n: int, m: int, k: int):
    """The linear solve for an impact's systems of these sizes: the unrolled elimination
    where ``small_kkt``, LAPACK (``jnp.linalg.solve``) otherwise."""
    return small_solve if small_kkt(n, m, k) else jnp.linalg.solve


def _solver(M, A, J):
    """``kkt_solve`` for M (n x n), A (m x n) and J (k x n)."""
    return kkt_solve(M.shape[0], A.shape[0], J.shape[0])


def _projected_rows(M, A, a, J, j):
    """(beta, betabar): the impulsive rows projected along the permanent constraints
    (seed sec. 7: beta = Psi_kappa - C^AB Phi^A_kappa Phi^B_mu Psi_chi g^chi mu)."""
    solve = _solver(M, A, J)
    Minv_AT = solve(M, A.T) if A.shape[0] else None
    if A.shape[0] == 0:
        return J, j
    C = A @ Minv_AT
    JMinvAT = J @ Minv_AT
    X = solve(C.T, JMinvAT.T).T  # J M^-1 A^T C^-1
    return J - X @ A, j - X @ a


def _masked_solve(C, rhs, mask, solve):
    """Solve C z = rhs on the rows/columns where mask is True; z = 0 elsewhere."""
    m = mask.astype(C.dtype)
    Cm = C * m[:, None] * m[None, :] + jnp.diag(1.0 - m)
    return solve(Cm, rhs * m) * m


def affine_projector(system, t, q, mask=None):
    """The seed's affine projector (18) on momenta at (t, q): ``(P, c)`` with
    p1 = P p0 + c for a plastic impact of the contacts in ``mask`` (default: all),
    keeping the permanent constraints. P is a projector (P @ P = P)."""
    M = system.mass_matrix(q)
    A, a = _permanent(system, t, q)
    _, J, Psi0 = contact_kinematics(system, t, q, jnp.zeros_like(q))  # Psi at q' = 0 is j
    beta, betabar = _projected_rows(M, A, a, J, Psi0)
    k = J.shape[0]
    mask = jnp.ones(k, bool) if mask is None else jnp.asarray(mask, bool)
    solve = _solver(M, A, J)
    Minv_bT = solve(M, beta.T)
    Cp = beta @ Minv_bT
    m = mask.astype(M.dtype)
    Cm = Cp * m[:, None] * m[None, :] + jnp.diag(1.0 - m)
    G = solve(Cm, (beta * m[:, None]))  # C'^-1 beta (masked rows)
    n = q.shape[0]
    P = jnp.eye(n, dtype=M.dtype) - beta.T @ G @ jnp.linalg.inv(M)
    c = -beta.T @ _masked_solve(Cp, betabar, mask, solve)
    return P, c


def _jump(M, A, a, J, j, qd, mask, alpha):
    """Velocities after an impact of the contacts in ``mask`` (restitution alpha (k,)),
    keeping A q' + a = 0; returns (qd1, mu) with mu the impulses (0 off the mask)."""
    beta, betabar = _projected_rows(M, A, a, J, j)
    solve = _solver(M, A, J)
    Minv_bT = solve(M, beta.T)
    Cp = beta @ Minv_bT
    rate = beta @ qd + betabar  # = Psi(v0) when A v0 + a = 0
    nu = _masked_solve(Cp, (1.0 + alpha) * rate, mask, solve)
    qd1 = qd - Minv_bT @ nu
    return qd1, -nu


def impact_geometry(system, t, q):
    """(M, A, a, J, j): everything an impact at (t, q) needs (mass matrix, permanent
    constraints A q' + a = 0, contact Jacobian J and psi_t = j)."""
    M = system.mass_matrix(q)
    A, a = _permanent(system, t, q)
    _, J, j = contact_kinematics(system, t, q, jnp.zeros_like(q))
    return M, A, a, J, j


def _impact_from_geometry(geom, qd, mask, alpha, keep):
    M, A, a, J, j = geom
    k = J.shape[0]
    mask = jnp.asarray(mask, bool)
    keep = jnp.zeros(k, bool) if keep is None else jnp.asarray(keep, bool)
    alpha = jnp.where(keep & ~mask, 0.0, jnp.broadcast_to(alpha, (k,)))
    used = mask | keep

    def round_(_, used):
        _, mu = _jump(M, A, a, J, j, qd, used, alpha)
        # drop the most negative (pulling) impulse, one per round
        worst = jnp.argmin(jnp.where(used, mu, jnp.inf))
        pulls = mu[worst] < -1e-14 * (1.0 + jnp.max(jnp.abs(mu)))
        return used.at[worst].set(jnp.where(pulls, False, used[worst]))

    if k > 1:
        used = jax.lax.fori_loop(0, k - 1, round_, used)
    qd1, mu = _jump(M, A, a, J, j, qd, used, alpha)
    return qd1, mu, used


def impact_velocities(system, t, q, qd, mask, alpha, keep=None):
    """Post-impact velocities by the affine projector with restitution.

    ``mask`` (k,) bool: contacts in the impact; ``alpha`` (k,): their restitution;
    ``keep`` (k,) bool: contacts that are persistent (kept like permanent constraints:
    in the impact with restitution 0). A contact whose impulse comes out negative
    (pulling) is dropped and the jump recomputed, at most k - 1 times. Returns
    ``(qd1, mu, used)``: velocities, impulses per contact (>= 0), contacts that took
    part."""
    return _impact_from_geometry(impact_geometry(system, t, q), qd, mask, alpha, keep)


def contact_dynamics(system, t, q, qd, persistent, u=None):
    """Accelerations with the persistent contacts enforced: ``(qdd, lam, mu)``.

    Solves  M q'' = rhs + A^T lam + J^T mu,  A q'' + b = 0,  and for each contact a:
    J_a q'' + c_a = 0 if persistent[a], else mu_a = 0. mu_a >= 0 is compressive."""
    qdd, lam, mu, _ = _contact_kkt(system, t, q, qd, persistent, u)
    return qdd, lam, mu


def _contact_kkt(system, t, q, qd, persistent, u=None):
    """contact_dynamics plus the power of all generalized forces that are not in T and V:
    F.q' + lam.(A q') + mu.(J q') (inputs, permanent and contact constraint forces)."""
    M, rhs, A, b = system.dynamics_terms(t, q, qd, u)
    J, _, c = _contact_rates(system, t, q, qd)
    n, m, k = M.shape[0], A.shape[0], J.shape[0]
    w = jnp.asarray(persistent, bool).astype(M.dtype)
    top = jnp.concatenate([M, -A.T, -J.T], axis=1)
    mid = jnp.concatenate([A, jnp.zeros((m, m + k), M.dtype)], axis=1)
    bot = jnp.concatenate([J * w[:, None], jnp.zeros((k, m), M.dtype), jnp.diag(1.0 - w)], axis=1)
    K = jnp.concatenate([top, mid, bot], axis=0)
    sol = _solver(M, A, J)(K, jnp.concatenate([rhs, -b, -w * c]))
    qdd, lam, mu = sol[:n], sol[n : n + m], sol[n + m :]
    if u is None:
        u = jnp.zeros((system.control_dim,), q.dtype)
    power = jnp.dot(system.generalized_force(t, q, qd, u), qd) + jnp.dot(lam, A @ qd) + jnp.dot(mu, J @ qd)
    return qdd, lam, mu, power


class WithContacts(ConstrainedLagrangian):
    """``system`` (a ``ConstrainedLagrangian``) with one-sided constraints psi(t, q) >= 0.

    ``psi(t, q) -> (k,)`` (or a scalar), ``restitution``: scalar or (k,) in [0, 1].
    Everything else (energies, permanent constraints, forces) is ``system``'s. ``psi``
    may be an equinox Module (its arrays are then differentiable parameters); a plain
    function's closed-over numbers are constants."""

    system: ConstrainedLagrangian
    psi: Callable
    restitution: jax.Array
    n: int = eqx.field(static=True)
    baumgarte: tuple[float, float] = eqx.field(default=(0.0, 0.0), static=True)

    def __init__(self, system, psi, restitution=1.0):
        if not isinstance(system, ConstrainedLagrangian):
            raise ParameterError(
                f"WithContacts needs a ConstrainedLagrangian (mass matrix and constraints by "
                f"autodiff, e.g. nhjax.mechanics.Lagrangian), got {type(system).__name__}", "system", system)
        function("psi", psi, owner="WithContacts", signature="psi(t, q) -> gaps (admissible where >= 0)")
        in_range("restitution", restitution, 0.0, 1.0, owner="WithContacts", what="coefficient of restitution")
        self.system, self.psi = system, psi
        self.restitution = jnp.asarray(restitution, float)
        self.n = system.n
        self.baumgarte = tuple(system.baumgarte)

    @property
    def state_names(self):  # type: ignore[override]
        return self.system.state_names

    @property
    def control_dim(self):  # type: ignore[override]
        return self.system.control_dim

    def unilateral_constraints(self, t, q):
        return jnp.atleast_1d(self.psi(t, q))

    def kinetic_energy(self, q, qd):
        return self.system.kinetic_energy(q, qd)

    def potential_energy(self, q):
        return self.system.potential_energy(q)

    def velocity_constraints(self, t, q, qd):
        return self.system.velocity_constraints(t, q, qd)

    def position_constraints(self, t, q):
        return self.system.position_constraints(t, q)

    def generalized_force(self, t, q, qd, u):
        return self.system.generalized_force(t, q, qd, u)

    def invariants(self, x):
        return self.system.invariants(x)


def oscillation_resolution(amplitude, omega):
    """Largest step [s] for a wall oscillating as amplitude * sin(omega t): an eighth of
    its period, so that no impact slips between steps (None if it does not oscillate,
    or if the values are traced)."""
    if isinstance(omega, jax.core.Tracer) or isinstance(amplitude, jax.core.Tracer):
        return None
    if float(amplitude) == 0 or float(omega) == 0:
        return None
    return float(2 * np.pi / abs(float(omega)) / 8)
