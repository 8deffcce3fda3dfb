"""Runge–Kutta–Munthe-Kaas (RKMK) solvers that plug into diffrax.

diffrax integrates in a vector space; rotations integrated there drift off
SO(3). An RKMK method (Munthe-Kaas 1998; Iserles, Munthe-Kaas, Nørsett & Zanna,
Acta Numerica 2000, sec. 4) writes each group-valued part of the state as
y(t) = y0 . exp(sigma(t)) over one step, integrates the algebra coordinates
sigma with an ordinary Runge–Kutta tableau, using

    sigma' = dexp^{-1}_sigma( v(t, y0 . exp(sigma)) ),      sigma(t0) = 0,

and maps back with the exponential. Every stage and every step is an exact group
element, so ``R^T R = I`` holds to round-off however long the run. With the
exact dexp^{-1} (closed form on SO(3) and SE(2)) the method keeps the order of
its tableau.

How each part of the state moves is given by a pytree of
``nhjax.lie.AbstractSpace`` objects carried by ``LieODETerm`` (``Euclidean``
parts are plain RK). Dense output (``SaveAt(ts=...)``, events) is computed in
sigma and retracted, so interpolated states are on the group too.

Solvers:

* ``RKMK45``: Dormand–Prince 5(4) tableau (Shampine's coefficients, FSAL),
  adaptive (works with ``diffrax.PIDController``), 4th-order dense output.
* ``RKMK87``: Prince & Dormand's 8(7) pair (RK8(7)13M, with the stage at the new
  point appended as a 14th, FSAL, stage: diffrax's ``Dopri8`` tableau), adaptive;
  7th-order dense output (diffrax's 5th-order interpolant, bootstrapped twice).
* ``RKMK4``: the classical 4th-order tableau, fixed step (``ConstantStepSize``).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, ClassVar

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from diffrax import AbstractLocalInterpolation, AbstractTerm

from ..lie.spaces import Euclidean, is_space

__all__ = ["LieODETerm", "RKMK4", "RKMK45", "RKMK87"]


class LieODETerm(AbstractTerm):
    """An ODE term whose state has group-valued parts.

    ``vector_field(t, y, args)`` returns, for each part of y, its velocity as
    described by the matching entry of ``spaces`` (a pytree prefix of y made of
    ``nhjax.lie`` spaces; ``Euclidean()`` for ordinary parts).
    """

    vector_field: Callable
    spaces: Any = Euclidean()

    def vf(self, t, y, args):
        return self.vector_field(t, y, args)

    def contr(self, t0, t1, **kwargs):
        return t1 - t0

    def prod(self, vf, control):
        return jtu.tree_map(lambda v: control * v, vf)


def _unwrapped(terms):
    """The term inside diffeqsolve's ``WrapTerm`` (a ``term`` and a time ``direction``)."""
    if hasattr(terms, "term") and hasattr(terms, "direction"):
        return terms.term
    return terms


def _entry_in_direction(entry, direction, t, y, args, apply):
    return entry(t * direction, y, args, apply)


def _spaces_of(terms) -> Any:
    # diffrax wraps terms (e.g. to flip the direction of time); look through wrappers.
    while not hasattr(terms, "spaces") and hasattr(terms, "term"):
        terms = terms.term
    return getattr(terms, "spaces", Euclidean())


def _map(fn, spaces, *trees):
    return jtu.tree_map(fn, spaces, *trees, is_leaf=is_space)


def _lincomb(coeffs, ks, h):
    """h * sum_j coeffs[j] * ks[j] over pytrees (skipping exact zeros)."""
    terms = [(float(c), k) for c, k in zip(coeffs, ks) if float(c) != 0.0]
    if not terms:
        return jtu.tree_map(lambda k: jnp.zeros_like(h * k), ks[0])

    def comb(*leaves):
        out = terms[0][0] * leaves[0]
        for (c, _), leaf in zip(terms[1:], leaves[1:]):
            out = out + c * leaf
        return h * out

    return jtu.tree_map(comb, *[k for _, k in terms])


def _horner(c, s):
    """c[0] s^(k-1) + ... + c[k-1], elementwise (vectorizes in batches)."""
    out = c[0]
    for j in range(1, c.shape[0]):
        out = out * s + c[j]
    return out


class LieInterpolation(AbstractLocalInterpolation):
    """Dense output y(t) = y0 . exp(sigma(t)) with sigma a polynomial in scaled time."""

    t0: Any
    t1: Any
    y0: Any
    coeffs: Any  # pytree shaped like sigma, each leaf with a leading polynomial axis
    spaces: Any

    def evaluate(self, t0, t1=None, left=True):
        del left
        if t1 is not None:
            return jtu.tree_map(lambda a, b: b - a, self.evaluate(t0), self.evaluate(t1))
        s = (t0 - self.t0) / (self.t1 - self.t0)

        sigma = jtu.tree_map(lambda c: _horner(c, s), self.coeffs)
        return _map(lambda sp, y, sg: sp.retract(y, sg), self.spaces, self.y0, sigma)


@dataclasses.dataclass(frozen=True)
class _Tableau:
    c: np.ndarray
    a: tuple
    b: np.ndarray
    b_err: np.ndarray | None
    c_mid: np.ndarray | None
    order: int
    fsal: bool
    # continuous extension sigma(s) = s * sum_i p_i(s) h k_i, s = (t - t0)/h in [0, 1]:
    # row i holds p_i's coefficients, highest power first (None: c_mid's quartic, or
    # else the cubic Hermite)
    dense: np.ndarray | None = None
    # order of the dense output (its local error is O(h^(dense_order + 1)))
    dense_order: int = 0
    # bootstrapping of the dense output (see _bootstrap): interior nodes s_j in (0, 1)
    # and the matrix taking the data to the polynomial's coefficients, and how many
    # rounds (each raises the order by one, at len(nodes) more evaluations)
    boot_nodes: np.ndarray | None = None
    boot_matrix: np.ndarray | None = None
    boot_rounds: int = 0


# Dormand–Prince 5(4), Shampine's form with FSAL (Hairer, Nørsett & Wanner I, Table 5.2),
# and Shampine's mid-point coefficients for the 4th-order continuous extension.
_DOPRI5 = _Tableau(
    c=np.array([0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0]),
    a=(
        (),
        (1 / 5,),
        (3 / 40, 9 / 40),
        (44 / 45, -56 / 15, 32 / 9),
        (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
        (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
        (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
    ),
    b=np.array([35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0]),
    b_err=np.array(
        [
            35 / 384 - 5179 / 57600,
            0.0,
            500 / 1113 - 7571 / 16695,
            125 / 192 - 393 / 640,
            -2187 / 6784 + 92097 / 339200,
            11 / 84 - 187 / 2100,
            -1 / 40,
        ]
    ),
    c_mid=np.array(
        [
            6025192743 / 30085553152 / 2,
            0.0,
            51252292925 / 65400821598 / 2,
            -2691868925 / 45128329728 / 2,
            187940372067 / 1594534317056 / 2,
            -1776094331 / 19743644256 / 2,
            11237099 / 235043384 / 2,
        ]
    ),
    order=5,
    fsal=True,
    dense_order=4,
)

_RK4 = _Tableau(
    c=np.array([0.0, 0.5, 0.5, 1.0]),
    a=((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0)),
    b=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
    b_err=None,
    c_mid=None,
    order=4,
    fsal=False,
    dense_order=3,
)


def _hermite_birkhoff_matrix(nodes) -> np.ndarray:
    """The matrix taking the data (q'(0), q(1), q'(1), q'(s_1), ..., q'(s_m)) to the
    coefficients a_1 .. a_D (powers 1 .. D, D = m + 3) of the polynomial q with q(0) = 0
    that meets them (Hermite-Birkhoff interpolation: values at the ends, derivatives at
    the ends and at the interior nodes)."""
    m = np.arange(1, len(nodes) + 4)
    rows = [m * (m == 1), np.ones(m.size), m * 1.0] + [m * s ** (m - 1) for s in nodes]
    return np.linalg.inv(np.array(rows))


# Interior nodes of the bootstrap: equispaced. (Symmetric node sets of odd size make
# the problem singular: the polynomial q' vanishing at 0, the nodes and 1 then
# integrates to zero. With these four the interpolant's weights sum in absolute value
# to at most 1.18 on [0, 1]: no amplification of the data's errors.)
_BOOT_NODES = np.array([0.2, 0.4, 0.6, 0.8])


def _dopri8_tableau() -> _Tableau:
    """Prince & Dormand's RK8(7)13M pair (J. Comput. Appl. Math. 7 (1981) 67-75) as
    diffrax ships it (``diffrax.Dopri8.tableau``), with its continuous extension
    (``diffrax.Dopri8.interpolation_cls.eval_coeffs``, after Bogacki & Shampine,
    Comput. Math. Appl. 20 (1990) 15-24). diffrax appends a 14th stage at (t1, y1)
    whose row is the 8th-order weights: the pair's 13 stages plus FSAL, 13 new
    evaluations per step. The interpolant uses that 14th stage; its order is 5 (local
    error O(h^6), measured in test_rkmk87_dense_output_is_seventh_order), raised to 7
    by two rounds of bootstrapping (``_AbstractRKMK._bootstrap``, 8 more evaluations).
    Read from diffrax at import and checked, not retyped."""
    bt = diffrax.Dopri8.tableau
    c = np.concatenate([[0.0], np.asarray(bt.c, float)])
    a = ((),) + tuple(tuple(float(x) for x in row) for row in bt.a_lower)
    b = np.asarray(bt.b_sol, float)
    b_err = np.asarray(bt.b_error, float)
    dense = np.asarray(diffrax.Dopri8.interpolation_cls.eval_coeffs, float)
    n = len(c)
    if not (n == 14 and len(a) == n and b.shape == b_err.shape == (n,) and dense.shape[0] == n
            and c[-1] == 1.0 and np.array_equal(np.asarray(a[-1]), b[:-1]) and b[-1] == 0.0
            and np.allclose([np.sum(r) for r in a[1:]], c[1:], rtol=0, atol=1e-14)
            and np.allclose(dense.sum(axis=1), b, rtol=0, atol=1e-12)):
        raise ImportError("diffrax.Dopri8's tableau is not the 14-stage FSAL form nhjax.RKMK87 was built on")
    # The published interpolation coefficients end at sum_i p_i(1) k_i, which differs
    # from the step's b by up to 1e-12 (they are rounded decimals): put the difference
    # into the leading coefficient, so that the interpolant ends at the step's solution
    # to round-off (the bootstrap starts from it).
    dense = dense.copy()
    dense[:, 0] += b - dense.sum(axis=1)
    return _Tableau(c=c, a=a, b=b, b_err=b_err, c_mid=None, order=8, fsal=True, dense=dense, dense_order=7,
                    boot_nodes=_BOOT_NODES, boot_matrix=_hermite_birkhoff_matrix(_BOOT_NODES), boot_rounds=2)


_DOPRI8 = _dopri8_tableau()


def _stages_scanned(self, terms, spaces, t0, h, y0, args, f0, redo=None, entry=None):
    """The stage loop as a lax.scan: the vector field is traced once instead of once
    per stage (much faster to compile for large vector fields). ``f0=None``: the first
    stage's vector field, f(t0, y0), is evaluated by the scan too (its first iteration,
    at y0 itself), so a step that must recompute it -- after a projection -- still
    holds one copy of the vector field instead of two (compile time and the size of
    the program, which is also what loading it from the cache costs). ``redo`` (a
    scalar bool, with ``f0``): the scan runs from the first stage, which takes ``f0``
    unless ``redo`` -- then it evaluates f(t0, y0) there, behind a ``lax.cond`` -- so
    the first step of a solve needs no separate evaluation of the vector field
    before the loop (one copy of it fewer in the program).

    ``entry(t, y, args, apply) -> (y', f(t, y'))`` (with ``f0=None``): the vector field
    that may first move its state (a projection, where ``apply``); the first stage
    applies it, and the step then runs from y' instead of y0. Returns the stages' ks,
    the last stage's f and sigma, and the step's start (y0, or y')."""
    tab = self.tableau
    n = len(tab.c)
    A = np.zeros((n, n))
    for i, ai in enumerate(tab.a):
        A[i, : len(ai)] = ai
    A, c = jnp.asarray(A), jnp.asarray(tab.c)
    first = 0 if (f0 is None or redo is not None) else 1
    given = f0
    if f0 is None:
        f0 = jax.eval_shape(lambda: terms.vf(t0, y0, args))
        f0 = jtu.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), f0)
    ks0 = jtu.tree_map(lambda k: jnp.zeros((n,) + k.shape, k.dtype), f0)
    if first == 1:  # the scan starts at stage 1: stage 0 is the given f0
        ks0 = jtu.tree_map(lambda K, k: K.at[0].set(k), ks0, f0)

    if entry is not None and first != 0:
        raise ValueError("a stage scan with an entry map evaluates its first stage itself (f0=None, redo=None)")

    def body(carry, i):
        ks, _, _, y_start = carry
        sigma_i = jtu.tree_map(lambda K: h * jnp.tensordot(A[i], K, axes=1), ks)
        y_i = _map(lambda sp, y, s: sp.retract(y, s), spaces, y_start, sigma_i)
        if first == 0:  # stage 0 at y0 exactly (not y0 retracted by a zero sigma)
            y_i = jtu.tree_map(lambda a, b: jnp.where(i == 0, a, b), y_start, y_i)
        if entry is not None:  # the first stage moves the step's start
            y_moved, f_i = entry(t0 + c[i] * h, y_i, args, i == 0)
            y_start = jtu.tree_map(lambda a, b: jnp.where(i == 0, a, b), y_moved, y_start)
        elif redo is None:
            f_i = terms.vf(t0 + c[i] * h, y_i, args)
        else:
            f_i = jax.lax.cond((i == 0) & ~redo, lambda: given, lambda: terms.vf(t0 + c[i] * h, y_i, args))
        k_i = _map(lambda sp, s, f: sp.dexpinv(s, f), spaces, sigma_i, f_i)
        if first == 0:  # k_1 = dexpinv_0(f0) = f0
            k_i = jtu.tree_map(lambda a, b: jnp.where(i == 0, a, b), f_i, k_i)
        ks = jtu.tree_map(lambda K, k: K.at[i].set(k), ks, k_i)
        return (ks, f_i, sigma_i, y_start), None

    init = (ks0, f0, jtu.tree_map(jnp.zeros_like, f0), y0)
    (ks, f_last, sigma_last, y0), _ = jax.lax.scan(body, init, jnp.arange(first, n))
    return [jtu.tree_map(lambda K, j=j: K[j], ks) for j in range(n)], f_last, sigma_last, y0


class _AbstractRKMK(diffrax.AbstractSolver):
    term_structure: ClassVar = AbstractTerm
    interpolation_cls: ClassVar = LieInterpolation
    tableau: ClassVar[_Tableau]
    # Run the stages as a lax.scan (compile the vector field once, not once per stage):
    # worth it for large vector fields, e.g. autodiff-derived multibody dynamics.
    scan_stages: bool = eqx.field(default=False, static=True)
    # False promises that the vector field has no jumps (no jump_ts): the FSAL stage
    # is then always reused. Under vmap a lax.cond runs both branches, so this saves
    # one vector-field evaluation per step in batches.
    jumps: bool = eqx.field(default=True, static=True)
    # With scan_stages and an FSAL tableau: the state carries (first step?, f0) and the
    # stage scan evaluates the first stage itself where needed (see _stages_scanned),
    # instead of init evaluating the vector field before the loop. For single solves:
    # in a lock-step batch, refilled lanes would make every lane evaluate it again.
    first_stage_in_scan: bool = eqx.field(default=False, static=True)
    _stages_scanned = _stages_scanned

    def _flagged(self):
        return self.first_stage_in_scan and self.scan_stages and self.tableau.fsal

    def order(self, terms):
        return self.tableau.order

    def init(self, terms, t0, t1, y0, args):
        if self._flagged():
            f0 = jax.eval_shape(lambda: terms.vf(t0, y0, args))
            return jnp.ones((), bool), jtu.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), f0)
        if self.tableau.fsal:
            return terms.vf(t0, y0, args)
        return None

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        # a nested jit: diffrax traces a solver's step several times per solve (its loop
        # body once to see what it makes static, again for the loop, and for dense output
        # at an event); one trace per argument structure is reused for the others, and
        # XLA inlines the call
        return _nested_step(self, terms, t0, t1, y0, args, solver_state, made_jump)

    def can_enter(self, terms) -> bool:
        """Whether ``step_with_entry`` applies: stages in a scan, on a ``LieODETerm``
        (or diffeqsolve's wrapper of one, which only scales time by the direction)."""
        return self.scan_stages and isinstance(_unwrapped(terms), LieODETerm)

    def step_with_entry(self, terms, t0, t1, y0, args, solver_state, entry):
        """A step that starts anew (as ``step`` with ``made_jump=True``) whose first
        stage is ``entry(t0, y0, args, True) -> (y0', f(t0, y0'))``: the step runs from
        y0' (e.g. y0 with its velocities projected, computed together with the vector
        field there; see ``ProjectedSolver``). Needs ``can_enter(terms)``."""
        return _nested_step(self, terms, t0, t1, y0, args, solver_state, True, entry)

    def _step(self, terms, t0, t1, y0, args, solver_state, made_jump, entry=None):
        tab = self.tableau
        spaces = _spaces_of(terms)
        h = t1 - t0
        redo = None
        if entry is not None:
            if terms is not _unwrapped(terms):  # diffeqsolve's WrapTerm: t -> direction * t
                entry = functools.partial(_entry_in_direction, entry, terms.direction)
            if self._flagged():
                solver_state = solver_state[1]
            f0 = None
        elif self._flagged():
            first, solver_state = solver_state
            # one flag for the whole step, also under jax.vmap (as diffrax's FSAL solvers:
            # a batched flag would turn the scan's lax.cond into a select that always
            # evaluates the first stage)
            redo = eqxi.unvmap_any(jnp.any(first) | jnp.any(made_jump))
            f0 = solver_state
        elif self.scan_stages and made_jump is True:
            # every step starts anew (ProjectedSolver says so with a literal True): the
            # scan evaluates the first stage too
            f0 = None
        elif tab.fsal and self.jumps:
            # made_jump is one flag, or one per member in a lock-step batch
            # (nhjax.integrate.lockstep, batch axis last): recompute where a member jumped
            f0 = jax.lax.cond(
                jnp.any(made_jump),
                lambda: jtu.tree_map(lambda f, s: jnp.where(made_jump, f, s),
                                     terms.vf(t0, y0, args), solver_state),
                lambda: solver_state,
            )
        elif tab.fsal:
            f0 = solver_state
        else:
            f0 = terms.vf(t0, y0, args)
        if self.scan_stages:
            ks, f_last, sigma_last, y0 = self._stages_scanned(terms, spaces, t0, h, y0, args, f0, redo, entry)
        else:
            ks = [f0]  # k_1 = dexpinv_0(f0) = f0
            f_last, sigma_last = f0, None
            for ci, ai in zip(tab.c[1:], tab.a[1:]):
                sigma_i = _lincomb(ai, ks, h)
                y_i = _map(lambda sp, y, s: sp.retract(y, s), spaces, y0, sigma_i)
                f_last = terms.vf(t0 + ci * h, y_i, args)
                ks.append(_map(lambda sp, s, f: sp.dexpinv(s, f), spaces, sigma_i, f_last))
                sigma_last = sigma_i
        if tab.fsal:
            # Last stage sits at t1 with a_last == b: its sigma is the step's sigma.
            sigma = sigma_last
            f1 = f_last
            k_end = ks[-1]
        else:
            sigma = _lincomb(tab.b, ks, h)
            f1 = None
        y1 = _map(lambda sp, y, s: sp.retract(y, s), spaces, y0, sigma)

        if tab.b_err is not None:
            dsig = _lincomb(tab.b_err, ks, h)
            y_error = _map(lambda sp, y, s: sp.ambient(y, s), spaces, y0, dsig)
        else:
            y_error = None

        if tab.dense is not None:
            # sigma(s) = s * sum_i p_i(s) h k_i: one coefficient per power of s, and a zero
            # constant term (sigma(0) = 0)
            coeffs = jtu.tree_map(
                lambda *cs: jnp.stack(cs),
                *[_lincomb(tab.dense[:, j], ks, h) for j in range(tab.dense.shape[1])],
                jtu.tree_map(jnp.zeros_like, sigma),
            )
        elif tab.c_mid is not None:
            sig_mid = _lincomb(tab.c_mid, ks, h)
            coeffs = jtu.tree_map(
                lambda s, m, k0, k1: _quartic(s, m, h * k0, h * k1),
                sigma, sig_mid, ks[0], k_end,
            )
        else:
            f_end = terms.vf(t1, y1, args)
            k_end = _map(lambda sp, s, f: sp.dexpinv(s, f), spaces, sigma, f_end)
            coeffs = jtu.tree_map(
                lambda s, k0, k1: _cubic(s, h * k0, h * k1), sigma, ks[0], k_end
            )
        if tab.boot_rounds and getattr(self, "bootstrap", True):
            coeffs = self._bootstrap(terms, spaces, t0, h, y0, args, sigma, ks[0], ks[-1], coeffs)
        dense_info = dict(y0=y0, coeffs=coeffs, spaces=spaces)
        if self._flagged():
            f1 = (jnp.zeros((), bool), f1)
        return y1, y_error, dense_info, f1, diffrax.RESULTS.successful

    def _bootstrap(self, terms, spaces, t0, h, y0, args, sigma, k0, k1, coeffs):
        """Raise the order of the dense output by bootstrapping (Enright, Jackson,
        Norsett & Thomsen, "Interpolants for Runge-Kutta formulas", ACM TOMS 12 (1986)
        193-218): with an interpolant u of
        order p (local error O(h^(p+1))), the algebra velocity h F(s_j, u(s_j)) at the
        nodes s_j is within O(h^(p+2)) of sigma'(s_j); the polynomial q of degree m + 3
        through sigma(0) = 0, sigma(1) and the slopes at 0, 1 (h k_1, and h k_end of the
        FSAL stage at the new point) and at the m nodes is then of order min(m + 3, p + 1).
        Per round m vector-field evaluations (one vmapped call): from the 5th-order
        Dopri8 interpolant, two rounds with m = 4 give order 7, the local error of the
        embedded 7th-order solution that the step-size control holds at tolerance.

        ``coeffs``: the starting polynomial (highest power first, constant last);
        returns q's coefficients in the same form (degree m + 3)."""
        tab = self.tableau
        nodes = jnp.asarray(tab.boot_nodes)
        M = jnp.asarray(tab.boot_matrix)
        degree = M.shape[0]

        def slope(s, sig):  # h dexpinv_sigma(f(t0 + s h, y0 . exp(sigma))), the data q'(s)
            y = _map(lambda sp, a, b: sp.retract(a, b), spaces, y0, sig)
            f = terms.vf(t0 + s * h, y, args)
            return jtu.tree_map(lambda k: h * k, _map(lambda sp, a, b: sp.dexpinv(a, b), spaces, sig, f))

        def one_round(coeffs):
            sig_nodes = jax.vmap(lambda s: jtu.tree_map(lambda c: _horner(c, s), coeffs))(nodes)
            d_nodes = jax.vmap(slope)(nodes, sig_nodes)

            def fit(k0, s1, k1, d):
                # q = s sigma_1 + (the fit to the data less that line's): the matrix's
                # entries reach 3e3 (monomials on [0, 1]), so the line, the bulk of sigma
                # over a step, stays out of the product and of its rounding
                data = jnp.concatenate([(h * k0 - s1)[None], jnp.zeros_like(s1)[None], (h * k1 - s1)[None],
                                        d - s1[None]])
                a = jnp.tensordot(M, data, axes=1).at[0].add(s1)  # powers 1 .. degree
                return jnp.concatenate([a[::-1], jnp.zeros_like(s1)[None]])

            return jtu.tree_map(fit, k0, sigma, k1, d_nodes)

        # the starting polynomial padded to the bootstrap's degree (one carry shape)
        coeffs = jtu.tree_map(
            lambda c: jnp.concatenate([jnp.zeros((degree + 1 - c.shape[0],) + c.shape[1:], c.dtype), c]), coeffs)
        if self.scan_stages:  # one copy of the vector field for all rounds
            coeffs, _ = jax.lax.scan(lambda c, _: (one_round(c), None), coeffs, None, length=tab.boot_rounds)
        else:
            for _ in range(tab.boot_rounds):
                coeffs = one_round(coeffs)
        return coeffs


def _quartic(s1, smid, f0, f1):
    """Quartic in scaled time through 0, smid (at 1/2), s1 with end slopes f0, f1."""
    a = 2 * (f1 - f0) - 8 * s1 + 16 * smid
    b = 5 * f0 - 3 * f1 + 14 * s1 - 32 * smid
    c = f1 - 4 * f0 - 5 * s1 + 16 * smid
    return jnp.stack([a, b, c, f0, jnp.zeros_like(s1)])


def _cubic(s1, f0, f1):
    """Cubic Hermite in scaled time through 0 and s1 with end slopes f0, f1."""
    a = f0 + f1 - 2 * s1
    b = -2 * f0 - f1 + 3 * s1
    return jnp.stack([a, b, f0, jnp.zeros_like(s1)])


class RKMK45(_AbstractRKMK, diffrax.AbstractAdaptiveSolver):
    """Adaptive Munthe-Kaas method on the Dormand–Prince 5(4) tableau (order 5).

    Use with ``diffrax.PIDController``; the error estimate is taken in the
    algebra and mapped to the state's ambient coordinates at the step start.
    """

    tableau: ClassVar[_Tableau] = _DOPRI5


class RKMK87(_AbstractRKMK, diffrax.AbstractAdaptiveSolver):
    """Adaptive Munthe-Kaas method on Prince & Dormand's 8(7) pair (order 8).

    The tableau is diffrax's ``Dopri8`` (RK8(7)13M, J. Comput. Appl. Math. 7 (1981)
    67-75, with an appended FSAL stage): 13 vector-field evaluations per step. On
    vector-space states it is ``diffrax.Dopri8`` with a better dense output. Use with
    ``diffrax.PIDController``; the error estimate (of the 7th-order embedded
    solution) is taken in the algebra and mapped to ambient coordinates at the step
    start, as in ``RKMK45``. Fewer steps than ``RKMK45`` at tight tolerances
    (rtol, atol <= 1e-9).

    Dense output (saved times, events): diffrax's continuous extension of Dopri8
    (Bogacki & Shampine 1990) is of order 5 only, its error between steps far above
    the steps' own at tight tolerances. Here it is bootstrapped twice in the algebra
    coordinates (Enright et al. 1986; ``_bootstrap``): 8 more vector-field
    evaluations per step (two calls, each vectorised over 4 points) for a 7th-order
    interpolant, whose local error O(h^8) is that of the embedded solution the
    step-size control holds at tolerance. A solve that saves only its ends
    (``simulate(saveat=2)``) and has no events does not use it, and XLA drops those
    evaluations; ``bootstrap=False`` leaves them out of the program altogether (its
    tracing and compiling take about a third longer with them), for solves that use
    no dense output: its dense output is then diffrax's 5th-order one.
    """

    tableau: ClassVar[_Tableau] = _DOPRI8
    bootstrap: bool = eqx.field(default=True, static=True)


class RKMK4(_AbstractRKMK):
    """Classical 4th-order Munthe-Kaas method; fixed steps (``ConstantStepSize``)."""

    tableau: ClassVar[_Tableau] = _RK4


@eqx.filter_jit
def _nested_step(solver, terms, t0, t1, y0, args, solver_state, made_jump, entry=None):
    """``solver._step`` as a nested jit (see ``_AbstractRKMK.step``); Python values among
    the arguments (e.g. a literal ``made_jump``, the entry map) stay static."""
    return solver._step(terms, t0, t1, y0, args, solver_state, made_jump, entry)
