"""The linear algebra shared by the Lagrangian engines: KKT solves, metric
projection, and the regularity conditions of constrained mechanics."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def kkt_matrix(M, A):
    """[[M, A^T], [A, 0]] (M itself without constraints, A with no rows)."""
    m = A.shape[0]
    if m == 0:
        return M
    return jnp.block([[M, A.T], [A, jnp.zeros((m, m), M.dtype)]])


def kkt_accelerations(M, rhs, A, b):
    """Solve [[M, A^T], [A, 0]] (v', -lam) = (rhs, -b); returns (v', lam)."""
    n, m = M.shape[0], A.shape[0]
    if m == 0:
        return jnp.linalg.solve(M, rhs), jnp.zeros((0,), M.dtype)
    sol = jnp.linalg.solve(kkt_matrix(M, A), jnp.concatenate([rhs, -b]))
    return sol[:n], -sol[n:]


def metric_projection(M, A, residual):
    """The correction dv, smallest in the metric M, with A dv = -residual.

    Solved as the KKT system [[M, A^T], [A, 0]] (dv, mu) = (0, -residual), which
    needs M positive definite only on ker A (as for quaternion coordinates, whose
    kinetic metric is degenerate along p).
    """
    n = M.shape[0]
    return jnp.linalg.solve(kkt_matrix(M, A), jnp.concatenate([jnp.zeros(n, M.dtype), -residual]))[:n]


def regularity_margins(M, A):
    """Relative margins (positive = regular) of the two conditions under which the
    constrained equations are well posed (Rabier & Rheinboldt, chs. 6-7): the
    constraint Jacobian has full row rank, and the kinetic metric is positive
    definite on the admissible velocities (its null space)."""
    m, n = A.shape
    if m == 0:
        ev = jnp.linalg.eigvalsh(0.5 * (M + M.T))
        return {"kinetic_metric": ev[0] / ev[-1] - 1e-12}
    U, s, Vt = jnp.linalg.svd(A)
    rank_margin = s[-1] / s[0] - 1e-10
    N = Vt[m:].T  # basis of ker A (meaningful when A has full rank)
    Mr = N.T @ M @ N
    ev = jnp.linalg.eigvalsh(0.5 * (Mr + Mr.T)) if n > m else jnp.ones(1)
    return {"constraint_rank": rank_margin, "kinetic_metric": ev[0] / jnp.abs(ev[-1]) - 1e-12}


REGULARITY_HINTS = {
    "constraint_rank": (
        "the constraint Jacobian (velocity constraints and differentiated position "
        "constraints) has dependent rows at this state: remove redundant constraints or "
        "move away from the configuration where they become dependent"
    ),
    "kinetic_metric": (
        "the kinetic energy is degenerate on the admissible velocities (the constrained "
        "mass matrix is singular): some admissible motion carries no inertia"
    ),
}


def newton_project(phi, x, iterations=4):
    """Minimum-norm Newton steps onto {phi = 0}: x <- x - A^T (A A^T)^-1 phi(x), A = dphi/dx.

    From a state within a step's local error of the manifold this converges
    quadratically; a fixed number of iterations keeps it jit- and vmap-friendly.
    """
    def step(_, x):
        r = phi(x)
        A = jax.jacfwd(phi)(x)
        return x - A.T @ jnp.linalg.solve(A @ A.T, r)

    return jax.lax.fori_loop(0, iterations, step, x)
