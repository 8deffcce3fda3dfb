r"""Box-constrained quadratic programs of the MPC's horizon problems: one interior-point
iteration, two ways of solving its linear systems.

The problem, in the input steps d (n numbers):

    minimize  g.d + d.H.d / 2   s.t.  A d = b,  lo <= d <= hi,

H symmetric positive definite. ``_interior_point`` is a primal-dual interior-point
method with Mehrotra's predictor-corrector (Nocedal & Wright, Numerical Optimization,
2nd ed., Algorithm 16.4), finished by one equality-constrained solve on its active set
(a "polish", so that converged iterates sit exactly on their active bounds). It sees the
problem only through a few operators (H d - A^T y, A d, the Newton system's factor
and solve, the polish), supplied by:

* ``box_qp``: H, A as dense matrices; each Newton system is one LU factorization of
  the (n + m_eq) KKT matrix. Few, large operations: the fastest for one problem.
* ``stage_qp``: the problem in the stage-wise form of a horizon (multiple shooting),

      minimize   sum_k [ x_k.Qss_k.x_k / 2 + x_k.Qsu_k.u_k + u_k.Quu_k.u_k / 2
                         + qs_k.x_k + qu_k.u_k ] + x_N.P.x_N / 2 + p.x_N
      subject to x_0 = e0,  x_{k+1} = A_k x_k + B_k u_k + c_k  (k = 0 .. N-1),
                 C x_N = b,  lo_k <= u_k <= hi_k,

  which is the dense problem above after eliminating the states (condensing: d = u
  flattened, H = G^T blockdiag(Q) G + ..., ``controls.mpc``'s module docstring). Each
  Newton system is solved by the discrete Riccati recursion (Rao, Wright & Rawlings,
  "Application of interior-point methods to model predictive control", JOTA 99, 1998):
  a backward sweep of small (n x n, m x m) matrix products per stage, O(N (n + m)^3)
  work instead of O((N m)^3), and no LAPACK call: the m x m inverses are unrolled
  Cholesky factorizations (``_spd_inverse``). Many small operations: under ``vmap``
  over a batch of problems (a batch of closed loops) they become element-wise loops
  over the batch, which XLA vectorizes, where a batch of dense LU factorizations is
  one LAPACK call per member. A terminal equality (m_eq > 0) is handled by the
  Riccati solution's linear response to its multipliers (one more sweep per
  constraint, then an m_eq x m_eq system).

Both return the same point (up to rounding): the same iteration, the same stopping test.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["box_qp", "stage_qp"]


# ------------------------------------------------------------------ LAPACK, one matrix at a time
# jaxlib 0.10's batched LAPACK kernels split a large batch into tasks on XLA's CPU thread
# pool and wait for them from a thread of that pool: two programs doing so at once (the
# threads of closed_loop_batch(workers=...) or of a Dask worker) can hold every pool
# thread waiting, and hang. Under vmap these run a lax.map of unbatched calls instead,
# which jaxlib runs inline (the same LAPACK work: a batched call loops over the matrices).
@jax.custom_batching.sequential_vmap
def _lu_factor(K):
    return jax.scipy.linalg.lu_factor(K)


@jax.custom_batching.sequential_vmap
def _lu_solve(lu, piv, r):
    return jax.scipy.linalg.lu_solve((lu, piv), r)


@jax.custom_batching.sequential_vmap
def _solve(K, r):
    return jnp.linalg.solve(K, r)


@jax.custom_batching.sequential_vmap
def _inv(M):
    return jnp.linalg.inv(M)


def _inv_each(M):
    """The inverses of the matrices M (..., m, m), one LAPACK call per matrix."""
    if M.ndim == 2:
        return _inv(M)
    return jax.vmap(_inv)(M.reshape((-1,) + M.shape[-2:])).reshape(M.shape)


# ------------------------------------------------------------------ the iteration
def _interior_point(ops, g, b, lo, hi, *, reg, max_iter, tol):
    """Mehrotra's predictor-corrector on  min g.d + d.H.d/2, A d = b, lo <= d <= hi.

    ops : dict of
        ``hd_aty(d, y)`` -> (H d - A^T y, A d);
        ``factor(sig)`` -> the factor of [[H + diag(sig), -A^T], [A, -reg I]];
        ``solve(fac, r1, r2)`` -> (dd, dy) with (H + diag(sig)) dd - A^T dy = r1,
            A dd - reg dy = r2;
        ``polish(fixed, bound)`` -> (d, y): the solution of the problem with d_i = bound_i
            on ``fixed`` and A d = b held exactly (no regularization), or NaN.
    reg : the regularization of the KKT matrix's multiplier block (m_eq > 0).

    Returns (d, y, ok, iterations): the step, the multipliers of A d = b
    (H d + g - A^T y - z_lo + z_hi = 0 with the bound multipliers z >= 0), and whether
    the scaled residuals and the complementarity reached ``tol``."""
    n, me = g.shape[0], b.shape[0]
    L, U = jnp.isfinite(lo), jnp.isfinite(hi)
    any_bound = jnp.any(L) | jnp.any(U)
    n_bounds = jnp.maximum(jnp.sum(L) + jnp.sum(U), 1)
    # an interior start: 0 pulled inside the box by a tenth of its width (at most 1)
    width = jnp.where(L & U, hi - lo, 1.0)
    margin = 0.1 * jnp.minimum(width, 1.0)
    d0 = jnp.clip(jnp.zeros(n), jnp.where(L, lo + margin, -jnp.inf), jnp.where(U, hi - margin, jnp.inf))
    zl0, zu0 = jnp.where(L, 1.0, 0.0), jnp.where(U, 1.0, 0.0)
    gscale = 1.0 + jnp.max(jnp.abs(g))
    bscale = 1.0 + (jnp.max(jnp.abs(b)) if me else 0.0)

    def parts(d, y, zl, zu):
        sl = jnp.where(L, d - jnp.where(L, lo, 0.0), 1.0)
        su = jnp.where(U, jnp.where(U, hi, 0.0) - d, 1.0)
        hd, ad = ops["hd_aty"](d, y)
        rd = hd + g - zl + zu
        re = ad - b
        mu = (jnp.sum(jnp.where(L, sl * zl, 0.0)) + jnp.sum(jnp.where(U, su * zu, 0.0))) / n_bounds
        return sl, su, rd, re, mu

    def error(rd, re, mu):
        err = jnp.maximum(jnp.max(jnp.abs(rd)) / gscale, mu)
        return jnp.maximum(err, jnp.max(jnp.abs(re)) / bscale) if me else err

    def step_length(v, dv, mask):
        ratio = jnp.where(mask & (dv < 0), -v / jnp.where(dv < 0, dv, -1.0), jnp.inf)
        return jnp.minimum(1.0, 0.995 * jnp.min(ratio, initial=jnp.inf))

    def body(carry):
        d, y, zl, zu, k, _, (sl, su, rd, re, mu) = carry
        sig = jnp.where(L, zl / sl, 0.0) + jnp.where(U, zu / su, 0.0)
        fac = ops["factor"](sig)

        def direction(rcl, rcu):
            r1 = -rd + jnp.where(L, rcl / sl, 0.0) - jnp.where(U, rcu / su, 0.0)
            dd, dy = ops["solve"](fac, r1, -re)
            dzl = jnp.where(L, (rcl - zl * dd) / sl, 0.0)
            dzu = jnp.where(U, (rcu + zu * dd) / su, 0.0)
            return dd, dy, dzl, dzu

        def length(dd, dzl, dzu):
            return jnp.minimum(jnp.minimum(step_length(sl, dd, L), step_length(su, -dd, U)),
                               jnp.minimum(step_length(zl, dzl, L), step_length(zu, dzu, U)))

        # predictor (affine scaling), then the corrector with centring sigma = (mu_aff / mu)^3
        dd, dy, dzl, dzu = direction(-sl * zl, -su * zu)
        a = length(dd, dzl, dzu)
        mu_aff = (jnp.sum(jnp.where(L, (sl + a * dd) * (zl + a * dzl), 0.0))
                  + jnp.sum(jnp.where(U, (su - a * dd) * (zu + a * dzu), 0.0))) / n_bounds
        sigma = jnp.where(any_bound, (mu_aff / jnp.where(mu > 0, mu, 1.0)) ** 3, 0.0)
        dd2, dy2, dzl2, dzu2 = direction(sigma * mu - sl * zl - dd * dzl, sigma * mu - su * zu + dd * dzu)
        a = length(dd2, dzl2, dzu2)
        d, y, zl, zu = d + a * dd2, y + a * dy2, zl + a * dzl2, zu + a * dzu2
        pr = parts(d, y, zl, zu)
        return d, y, zl, zu, k + 1, error(*pr[2:]), pr

    def cond(carry):
        *_, k, err, _ = carry
        return (k < max_iter) & (err > tol)  # NaN stops the loop too (NaN > tol is False)

    y0 = jnp.zeros(me)
    p0 = parts(d0, y0, zl0, zu0)
    d, y, zl, zu, k, err, (sl, su, *_) = jax.lax.while_loop(
        cond, body, (d0, y0, zl0, zu0, 0, error(*p0[2:]), p0))
    ok = (err <= tol) & jnp.all(jnp.isfinite(d))

    # polish: the interior point stays off an active bound by ~mu / z; one solve with the
    # bounds whose multiplier exceeds their slack held exactly puts it on the bound (kept
    # when it is feasible and its bound multipliers have the right signs)
    act_l, act_u = L & (zl > sl), U & (zu > su) & ~(L & (zl > sl))
    fixed = act_l | act_u
    bound = jnp.where(act_l, jnp.where(L, lo, 0.0), jnp.where(act_u, jnp.where(U, hi, 0.0), 0.0))
    dp, yp = ops["polish"](fixed, bound)
    hd, ad = ops["hd_aty"](dp, yp)
    z = hd + g  # z_lo - z_hi on the fixed components, 0 on the free ones
    good = (jnp.all(jnp.isfinite(dp)) & jnp.all(jnp.isfinite(yp))
            & jnp.all(jnp.where(L & ~fixed, dp >= lo - 1e-14 * (1 + jnp.abs(lo)), True))
            & jnp.all(jnp.where(U & ~fixed, dp <= hi + 1e-14 * (1 + jnp.abs(hi)), True))
            & jnp.all(jnp.where(act_l, z >= -tol * gscale, True)) & jnp.all(jnp.where(act_u, z <= tol * gscale, True)))
    if me:
        good = good & (jnp.max(jnp.abs(ad - b)) <= tol * bscale)
    use = ok & good
    return jnp.where(use, dp, d), jnp.where(use, yp, y), ok, k


# ------------------------------------------------------------------ dense
def box_qp(H, g, A, b, lo, hi, *, max_iter=50, tol=1e-11):
    """Solve  min g.d + d.H.d / 2  s.t.  A d = b,  lo <= d <= hi  (H symmetric positive
    definite; lo, hi may hold -inf / inf; lo < hi) by a primal-dual interior-point
    iteration with Mehrotra's predictor-corrector (N&W Algorithm 16.4), traceable
    (a ``lax.while_loop`` of at most ``max_iter`` iterations, each one LU factorization
    of the (n + m_eq) KKT matrix and two solves). The interior point stays off an
    active bound by about mu / z; a last KKT solve with the bounds whose multiplier
    exceeds their slack held exactly (and A d = b without the iteration's
    regularization) replaces it when that point is feasible and its bound multipliers
    have the right signs. A must have full row rank.

    Returns (d, y, ok, iterations): the step, the multipliers of A d = b (H d + g -
    A^T y - z_lo + z_hi = 0 with the bound multipliers z >= 0), and whether the scaled
    residuals and the complementarity reached ``tol`` (False for an infeasible QP)."""
    n, me = g.shape[0], b.shape[0]
    reg = 1e-13 * (1.0 + jnp.max(jnp.abs(jnp.diag(H))))

    def factor(sig):
        K = jnp.block([[H + jnp.diag(sig), -A.T], [A, -reg * jnp.eye(me)]])
        return _lu_factor(K)

    def solve(lu, r1, r2):
        sol = _lu_solve(*lu, jnp.concatenate([r1, r2]))
        return sol[:n], sol[n:]

    def polish(fixed, bound):
        Hf = jnp.where(fixed[:, None], jnp.eye(n), H)
        Af = jnp.where(fixed[:, None], 0.0, -A.T)
        K = jnp.block([[Hf, Af], [A, jnp.zeros((me, me))]])
        sol = _solve(K, jnp.concatenate([jnp.where(fixed, bound, -g), b]))
        return sol[:n], sol[n:]

    ops = dict(hd_aty=lambda d, y: (H @ d - A.T @ y, A @ d), factor=factor, solve=solve, polish=polish)
    return _interior_point(ops, g, b, lo, hi, reg=reg, max_iter=max_iter, tol=tol)


# ------------------------------------------------------------------ stage-wise (Riccati)
def _spd_inverse(M):
    """The inverse of the symmetric positive definite matrices M (..., m, m), by a
    Cholesky factorization M = L L^T unrolled over the m^2 entries (element-wise
    operations on the leading axes, which XLA vectorizes over a batch; no LAPACK call).
    For m > 8 (the unrolled program would grow as m^3), LAPACK, one matrix at a time."""
    m = M.shape[-1]
    if m > 8:
        return _inv_each(M)
    Lf = [[None] * m for _ in range(m)]
    for j in range(m):
        s = M[..., j, j] - sum((Lf[j][k] ** 2 for k in range(j)), jnp.zeros(M.shape[:-2], M.dtype))
        Lf[j][j] = jnp.sqrt(s)
        for i in range(j + 1, m):
            t = M[..., i, j] - sum((Lf[i][k] * Lf[j][k] for k in range(j)), jnp.zeros(M.shape[:-2], M.dtype))
            Lf[i][j] = t / Lf[j][j]
    # W = L^{-1} (lower triangular) by forward substitution, then M^{-1} = W^T W
    W = [[None] * m for _ in range(m)]
    for i in range(m):
        W[i][i] = 1.0 / Lf[i][i]
        for j in range(i):
            W[i][j] = -sum(Lf[i][k] * W[k][j] for k in range(j, i)) / Lf[i][i]
    zero = jnp.zeros(M.shape[:-2], M.dtype)
    inv = [[sum((W[k][i] * W[k][j] for k in range(max(i, j), m)), zero) for j in range(m)] for i in range(m)]
    return jnp.stack([jnp.stack(row, -1) for row in inv], -2)


def _mm(a, b):
    """a @ b for small matrices as a broadcast product and a sum: one element-wise loop
    that XLA fuses and, under vmap, vectorizes over the batch (a batched dot of tiny
    matrices runs as one small matrix product per member)."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _mv(a, v):
    """a @ v for a small matrix a, as ``_mm``."""
    return jnp.sum(a * v[..., None, :], axis=-1)


def _tv(a, v):
    """a^T @ v for a small matrix a, as ``_mm``."""
    return jnp.sum(a * v[..., :, None], axis=-2)


def _riccati_factor(Qss, Qsu, Quu, A, B, P):
    """The backward Riccati sweep of the stage problem's Newton system:
    P_N = P, and per stage (k = N-1 .. 0, M = P_{k+1})

        Huu = Quu_k + B^T M B,  Hux = Qsu_k^T + B^T M A,  K_k = -Huu^{-1} Hux,
        P_k = Qss_k + A^T M A + Hux^T K_k.

    Returns (P_1 .. P_N (N, n, n), Huu^{-1} (N, m, m), Hux (N, m, n), K (N, m, n))."""

    def back(M, k):
        BM = _mm(B[k].T, M)
        Huu = Quu[k] + _mm(BM, B[k])
        Hux = Qsu[k].T + _mm(BM, A[k])
        Hi = _spd_inverse(0.5 * (Huu + Huu.T))
        K = -_mm(Hi, Hux)
        Pk = Qss[k] + _mm(A[k].T, _mm(M, A[k])) + _mm(Hux.T, K)
        return 0.5 * (Pk + Pk.T), (M, Hi, Hux, K)

    _, (Ms, Hi, Hux, K) = jax.lax.scan(back, P, jnp.arange(A.shape[0]), reverse=True)
    return Ms, Hi, Hux, K


def _riccati_sweep(fac, A, B, qs, qu, p, c, x0):
    """The stage problem's solution for the factor ``fac`` (``_riccati_factor``) and the
    linear terms qs (N, n), qu (N, m), p (n,), the affine terms c (N, n) and the start
    x0: the backward sweep of the affine part, p_k = qs_k + A^T (p_{k+1} + M c) + Hux^T
    kff_k with kff_k = -Huu^{-1} (qu_k + B^T (p_{k+1} + M c_k)), then the forward
    rollout u_k = K_k x_k + kff_k. Returns (u (N, m), x (N+1, n))."""
    Ms, Hi, Hux, K = fac

    def back(pn, k):
        v = pn + _mv(Ms[k], c[k])
        kff = -_mv(Hi[k], qu[k] + _tv(B[k], v))
        return qs[k] + _tv(A[k], v) + _tv(Hux[k], kff), kff

    _, kff = jax.lax.scan(back, p, jnp.arange(A.shape[0]), reverse=True)

    def fwd(x, k):
        u = _mv(K[k], x) + kff[k]
        return _mv(A[k], x) + _mv(B[k], u) + c[k], (x, u)

    xN, (xs, us) = jax.lax.scan(fwd, x0, jnp.arange(A.shape[0]))
    return us, jnp.concatenate([xs, xN[None]])


def stage_qp(Q, q, A, B, c, e0, P, p, C, b, lo, hi, *, max_iter=50, tol=1e-11):
    """Solve the stage-wise QP of a horizon (module docstring) by ``box_qp``'s
    interior-point iteration with each Newton system solved by the Riccati recursion.

    Q : (N, n + m, n + m) stage Hessians [[Qss, Qsu], [Qsu^T, Quu]] (positive
        definite in u, positive semidefinite overall); q : (N, n + m) their gradients;
    A, B, c : (N, n, n), (N, n, m), (N, n) the linearized dynamics; e0 : (n,) x_0;
    P, p : (n, n), (n,) the terminal Hessian and gradient; C, b : (m_eq, n), (m_eq,)
    the terminal equalities C x_N = b; lo, hi : (N, m) bounds on u (may be +-inf).

    Returns (u (N, m), x (N+1, n), y (m_eq,), ok, iterations): ``box_qp``'s answer on
    the condensed problem (the same d = u flattened, the same multipliers y of the
    condensed equalities C x_N(d) = b, the same ``ok``), and the states x of u."""
    N, n = A.shape[0], A.shape[1]
    m, me = B.shape[2], b.shape[0]
    Qss, Qsu, Quu = Q[:, :n, :n], Q[:, :n, n:], Q[:, n:, n:]
    qs, qu = q[:, :n], q[:, n:]
    zN, zn, zm = jnp.zeros((N, n)), jnp.zeros(n), jnp.zeros((N, m))

    def adjoint(x, u, lamN, rs):
        """B_k^T lam_{k+1} for lam_N given, lam_k = Qss x_k + Qsu u_k + rs_k + A^T lam_{k+1}."""
        def back(lam, k):
            return _mv(Qss[k], x[k]) + _mv(Qsu[k], u[k]) + rs[k] + _tv(A[k], lam), _tv(B[k], lam)

        _, blam = jax.lax.scan(back, lamN, jnp.arange(N), reverse=True)
        return blam

    def rollout(u, c_, x0):
        def fwd(x, k):
            return _mv(A[k], x) + _mv(B[k], u[k]) + c_[k], x

        xN, xs = jax.lax.scan(fwd, x0, jnp.arange(N))
        return jnp.concatenate([xs, xN[None]])

    # the condensed gradient g (the gradient at u = 0) and right-hand side b - C x_N(0)
    x_aff = rollout(zm, c, e0)
    g = (jnp.einsum("kij,ki->kj", Qsu, x_aff[:-1]) + qu
         + adjoint(x_aff, zm, P @ x_aff[-1] + p, qs)).reshape(-1)
    b_c = b - C @ x_aff[-1]

    def hd_aty(d, y):
        u = d.reshape(N, m)
        x = rollout(u, zN, zn)
        hd = jnp.einsum("kij,ki->kj", Qsu, x[:-1]) + jnp.einsum("kij,kj->ki", Quu, u) \
            + adjoint(x, u, P @ x[-1] - C.T @ y, zN)
        return hd.reshape(-1), C @ x[-1]

    reg = 1e-13 * (1.0 + jnp.maximum(jnp.max(jnp.abs(jnp.diagonal(Quu, axis1=1, axis2=2))),
                                     jnp.max(jnp.abs(jnp.diag(P)))))

    def factor(sig):
        Quu_s = Quu + jax.vmap(jnp.diag)(sig.reshape(N, m))
        fac = _riccati_factor(Qss, Qsu, Quu_s, A, B, P)
        if not me:
            return fac, None
        resp = jax.vmap(lambda cj: _riccati_sweep(fac, A, B, zN, zm, -cj, zN, zn))(C)
        Wu, WxN = resp[0], resp[1][:, -1]
        return fac, (_inv(C @ WxN.T - reg * jnp.eye(me)), Wu, WxN)

    def solve(facs, r1, r2):
        fac, eq = facs
        u0, x0s = _riccati_sweep(fac, A, B, zN, -r1.reshape(N, m), zn, zN, zn)
        if not me:
            return u0.reshape(-1), jnp.zeros(0)
        Sinv, Wu, WxN = eq
        dy = Sinv @ (r2 - C @ x0s[-1])
        return (u0 + jnp.einsum("j,jkm->km", dy, Wu)).reshape(-1), dy

    def polish(fixed, bound):
        # the fixed inputs become constants: their columns of B and Qsu move into c and qs,
        # their rows of Quu into qu; each is then its own decoupled variable with u_i = bound_i
        fx, bd = fixed.reshape(N, m), bound.reshape(N, m)
        cross = fx[:, :, None] | fx[:, None, :]
        Quu_f = jnp.where(cross, 0.0, Quu) + jax.vmap(jnp.diag)(jnp.where(fx, 1.0, 0.0))
        qu_f = jnp.where(fx, -bd, qu + jnp.einsum("kij,kj->ki", jnp.where(fx[:, None, :], Quu, 0.0), bd))
        Qsu_f = jnp.where(fx[:, None, :], 0.0, Qsu)
        qs_f = qs + jnp.einsum("kij,kj->ki", Qsu, jnp.where(fx, bd, 0.0))
        B_f = jnp.where(fx[:, None, :], 0.0, B)
        c_f = c + jnp.einsum("kij,kj->ki", B, jnp.where(fx, bd, 0.0))
        fac = _riccati_factor(Qss, Qsu_f, Quu_f, A, B_f, P)
        u0, xs = _riccati_sweep(fac, A, B_f, qs_f, qu_f, p, c_f, e0)
        if not me:
            return u0.reshape(-1), jnp.zeros(0)
        resp = jax.vmap(lambda cj: _riccati_sweep(fac, A, B_f, zN, zm, -cj, zN, zn))(C)
        Wu, WxN = resp[0], resp[1][:, -1]
        y = _solve(C @ WxN.T, b - C @ xs[-1])
        return (u0 + jnp.einsum("j,jkm->km", y, Wu)).reshape(-1), y

    ops = dict(hd_aty=hd_aty, factor=factor, solve=solve, polish=polish)
    d, y, ok, k = _interior_point(ops, g, b_c, lo.reshape(-1), hi.reshape(-1), reg=reg, max_iter=max_iter, tol=tol)
    u = d.reshape(N, m)
    return u, rollout(u, c, e0), y, ok, k
