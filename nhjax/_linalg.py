"""Linear solves of tiny systems inside time-stepping loops, without LAPACK.

On the CPU, ``jnp.linalg.solve`` calls LAPACK (getrf + trsm) through XLA custom
calls. A loop that contains one is not compiled by XLA as one function (see
``nhjax._xla_flags``): it runs kernel by kernel, and once its buffers pass 512 bytes
XLA's CPU runtime hands the kernels of every iteration to a thread pool. The
Hamiltonian flow of Pontryagin's principle solves H_uu du = -H_u for u* at every
vector-field evaluation (k x k, k = the number of controls); with this solve the
extremal's loops compile as one function.

``solve`` is Gaussian elimination with partial pivoting (the algorithm of LAPACK's
getrf/getrs, with its backward stability) in jnp operations, unrolled over the
static size; above ``SMALL`` unknowns it is ``jnp.linalg.solve``. The impact solves
of small systems use it too (``nhjax.mechanics.impacts.small_kkt``: a contact KKT of
at most ``SMALL`` unknowns), so that their event loop compiles as one function. The
Lagrange engine of ``simulate`` keeps LAPACK: its loops are too large to compile as one
function anyway, and there the unrolled elimination made programs slower to compile
and no faster.
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["solve", "SMALL"]

#: Largest system solved by the unrolled elimination (its trace grows as n^2 ops).
SMALL = 8


def solve(a, b):
    """``jnp.linalg.solve(a, b)`` for one square ``a`` ``[n, n]`` and ``b`` ``[n]`` or
    ``[n, k]``; batch with vmap. A singular ``a`` gives inf/NaN, as LAPACK does."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    n = a.shape[-1]
    if a.ndim != 2 or a.shape[0] != n or b.ndim not in (1, 2) or b.shape[0] != n or n > SMALL:
        return jnp.linalg.solve(a, b)
    if n == 0:
        return b
    dtype = jnp.result_type(a, b)
    vector = b.ndim == 1
    m = jnp.concatenate([a.astype(dtype), (b[:, None] if vector else b).astype(dtype)], axis=1)
    rows = jnp.arange(n)
    for j in range(n - 1):
        # partial pivoting: the row (j..n-1) with the largest |m[i, j]| comes to row j
        p = j + jnp.argmax(jnp.abs(m[j:, j]))
        at_p = (rows == p)[:, None]
        row_p = jnp.sum(jnp.where(at_p, m, 0.0), axis=0)
        row_j = m[j]
        m = jnp.where(at_p, row_j[None], m).at[j].set(row_p)
        factors = m[j + 1:, j] / m[j, j]
        m = m.at[j + 1:].add(-factors[:, None] * m[j][None])
    # back substitution on the upper-triangular part
    x = [None] * n
    for i in range(n - 1, -1, -1):
        acc = m[i, n:]
        for k in range(i + 1, n):
            acc = acc - m[i, k] * x[k]
        x[i] = acc / m[i, i]
    out = jnp.stack(x)
    return out[:, 0] if vector else out
