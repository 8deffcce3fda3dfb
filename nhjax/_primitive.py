"""Stored programs under JAX's transformations: one primitive behind every public path.

``nhjax._programs`` keeps a traced program on disk and runs it on concrete arrays.
Here such a program becomes a JAX primitive (``program_p``), so that a call made
inside ``jax.grad``, ``jax.vjp``, ``jax.jacrev``, ``jax.jvp``, ``jax.jacfwd`` or
``jax.linearize`` on concrete values runs stored programs too, instead of tracing
the function (a solve: seconds) again in every new process:

* evaluation: the program's executable (``_programs.keyed_executable``);
* forward mode: a second program, the JVP of the function in the inputs that carry
  tangents, built from its *forward variant* (the same computation set up for
  forward mode, e.g. a solve with ``diffrax.ForwardMode``, whose loop JAX can push
  tangents through);
* reverse mode: two programs, the forward pass of ``jax.vjp`` of the *reverse
  variant* (e.g. a solve with ``nhjax.DiscreteAdjoint``), which returns the outputs
  and the residuals the backward pass needs, and the backward pass from those
  residuals and the output cotangents. The residuals stay on the device between the
  two; outputs that get no cotangent (diagnostics nobody differentiates) are zero
  constants in the backward program, and a call whose outputs get none skips it;
* ``jax.vmap`` (e.g. of the tangents of ``jax.jacfwd``, the cotangents of
  ``jax.jacrev``): the program of ``jax.vmap`` of the function (a batch of one, as
  ``jax.jacfwd`` in one number makes: the function itself on the squeezed inputs);
* inside ``jax.jit`` (reached through a derived program): the stored StableHLO module,
  which XLA inlines.

Each derived program is itself stored, under its parent's key and what derives it
(which inputs carry tangents, which outputs cotangents, the batch axes), so a second
process traces and compiles none of them. ``call`` binds the primitive only when
every input's value is known (a concrete array, or a tracer of ``jax.grad``/
``jax.jvp`` over one, as in an eager ``jax.grad(f)(p)``); under ``jax.jit`` or
``jax.vmap`` of unknown values it traces the function into the caller's program, as
before, and a function that cannot be exported (host callbacks) or fingerprinted is
traced as usual.

JAX internals used here (checked against jax 0.10): ``jax._src.core.to_concrete_value``
(the value under a tracer of differentiation) and ``jax._src.interpreters.ad``'s
``primitive_linearizations`` and ``fallback_linearize_rule`` (reverse mode through
JAX's direct linearization); everything else is ``jax.extend`` and
``jax.interpreters``.
"""

from __future__ import annotations

import hashlib
from typing import Callable

import equinox as eqx
import jax
import jax.extend as jex
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.interpreters import ad, batching, mlir

from . import _programs

try:  # the internals this module needs (see the module docstring)
    from jax._src import core as _core
    from jax._src.interpreters import ad as _ad

    _to_concrete = _core.to_concrete_value
    _LINEARIZATIONS = getattr(_ad, "primitive_linearizations", None)
    _fallback_linearize = getattr(_ad, "fallback_linearize_rule", None)
except ImportError:  # another JAX: every call traces as usual
    _to_concrete = None
    _LINEARIZATIONS = _fallback_linearize = None

__all__ = ["call", "concrete", "has_values", "program_p"]

#: Programs bound through the primitive and derived from them, by kind (tests read it).
BOUND = {"call": 0, "jvp": 0, "fwd": 0, "bwd": 0, "vmap": 0}


# ------------------------------------------------------------------ values
def _value(x):
    """The concrete value of a leaf (itself, or under a tracer of differentiation), or
    None if it is not known (under jit or vmap)."""
    if not isinstance(x, jax.core.Tracer):
        return x
    if _to_concrete is None:
        return None
    try:
        return _to_concrete(x)
    except Exception:  # noqa: BLE001 - a tracer that cannot tell: unknown
        return None


def has_values(*trees) -> bool:
    """Whether every array leaf of ``trees`` has a known value: concrete, or a tracer
    of ``jax.grad``/``jax.jvp`` (and the like) around a concrete value."""
    return all(_value(x) is not None for x in jtu.tree_leaves(trees) if isinstance(x, jax.core.Tracer))


def concrete(tree):
    """``tree`` with every tracer replaced by its known value (``has_values`` must hold):
    what eager checks read under ``jax.grad``."""
    return jtu.tree_map(lambda x: _value(x) if isinstance(x, jax.core.Tracer) else x, tree)


def _is_float(aval) -> bool:
    return jnp.issubdtype(aval.dtype, jnp.inexact)


def _tangent_aval(aval):
    return aval.to_tangent_aval() if hasattr(aval, "to_tangent_aval") else aval.at_least_vspace()


def _spec_of(aval) -> jax.ShapeDtypeStruct:
    return jax.ShapeDtypeStruct(aval.shape, aval.dtype)


def _key(*parts) -> str:
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:40]


# ------------------------------------------------------------------ programs
def _aval(x):
    a = jax.typeof(x) if hasattr(jax, "typeof") else jax.core.get_aval(x)
    return jax.core.ShapedArray(tuple(a.shape), a.dtype)


class Spec:
    """One program: a function of a flat list of arrays returning a flat list, the
    shapes it is called on, and its key in the program cache. Equal (and hashed) by key:
    the primitive's parameter.

    Its outputs' shapes are recorded whenever its function is traced, in whatever trace
    (inside a derivative's or a batch's program too: there the function sees its own
    shapes), and kept on disk beside the programs (``_programs.store_meta``): so a
    derivative's program tells its parent's outputs, and a new process knows them
    without tracing. ``root``: the program whose outputs this one's are (a variant:
    the same computation set up for forward or reverse mode); its traces record them."""

    def __init__(self, name: str, key: str, fn: Callable, in_avals, options=None, *, root=None,
                 transpose=None, errors_off=False, box=None):
        self.name, self.key = name, key
        self.errors_off = errors_off  # traced with equinox's runtime checks off, derivatives too
        self.in_avals = tuple(in_avals)
        self.options = dict(options or {})
        self.root = root
        self.transpose = transpose  # how to transpose a program linear in its last inputs
        self.box = {} if box is None else box  # the caller's output structure, set when traced
        self.forward = None  # Spec of the forward variant (None: this one)
        self.reverse = None  # callable nz -> Spec of the reverse variant (None: this one)
        self._out_avals = None
        self._derived = {}
        self.primals = None  # a JVP program with its outputs: (inputs, the parent) whose outputs come first
        self.lazy = False  # reverse mode through the JVP's transpose, only where a cotangent comes
        self.max_tangents = 0  # reverse mode in up to this many input numbers: by forward mode

        def traced(*args):
            with _programs.error_checks(not errors_off), _programs.stored_trace():
                out = list(fn(*args))
            self._record(out)
            return out

        self.fn = traced

    def __hash__(self):
        return hash(self.key)

    def __eq__(self, other):
        return isinstance(other, Spec) and other.key == self.key

    def __repr__(self):
        return f"Spec({self.name}, {self.key[:12]})"

    # ---------------------------------------------------- what the program is
    def _record(self, out):
        if self._out_avals is None:
            self._out_avals = tuple(_aval(x) for x in out)
            _programs.store_meta(self.key, self.box.get("out_def"), self._out_avals)
        if self.root is not None:
            self.root._record(out)

    @property
    def out_avals(self):
        """Shapes and dtypes of the outputs: recorded, stored, or traced now."""
        if self._out_avals is None:
            meta = _programs.keyed_meta(self.key)
            if meta is not None:
                self._out_avals = tuple(jax.core.ShapedArray(shape, np.dtype(dt)) for shape, dt in meta[1])
                if meta[0] is not None:
                    self.box.setdefault("out_def", meta[0])
            else:  # exported now (what a jit's lowering needs next anyway), or loaded
                exported = self.exported()
                if self._out_avals is None:  # loaded: no trace recorded them
                    self._out_avals = tuple(jax.core.ShapedArray(a.shape, a.dtype) for a in exported.out_avals)
                    out_def = _programs.keyed_out_def(self.key)
                    if out_def is not None and out_def.num_leaves == len(self._out_avals) and self.root is None:
                        self.box.setdefault("out_def", out_def)
        return self._out_avals

    @property
    def out_def(self):
        """The caller's output structure (top-level programs)."""
        if "out_def" not in self.box:
            self.out_avals  # noqa: B018 - recorded with them
        return self.box["out_def"]

    def exported(self):
        # (lowering traces too: the impl rules of equinox's primitives, e.g. lineax's solve)
        with _programs.error_checks(not self.errors_off):
            out = _programs.keyed_exported(self.key, self.fn, [_spec_of(a) for a in self.in_avals],
                                           lambda: self.box.get("out_def"))
        if out is None:
            raise _Unexportable(self.name)
        return out

    def run(self, args):
        with _programs.error_checks(not self.errors_off):
            exe = _programs.keyed_executable(self.key, self.fn, [_spec_of(a) for a in self.in_avals],
                                             self.options, lambda: self.box.get("out_def"))
        if exe is None:
            raise _Unexportable(self.name)
        return exe(*args)

    def derive(self, kind, params, make):
        """The derived program ``kind`` with ``params``, made once per process."""
        spec = self._derived.get((kind, params))
        if spec is None:
            spec = make()
            self._derived[(kind, params)] = spec
        return spec

    def _child(self, kind, params, fn, avals, **kw):
        """A derived program, named by its parent's name (a variant's, where the program
        is built from one: see ``params``) and what derives it."""
        name = f"{self.name}.{kind}"
        base = self.key if self.forward is None or kind != "jvp" else ""
        return Spec(name, f"{name}-" + _key(base, kind, params), fn, avals, self.options,
                    errors_off=self.errors_off, **kw)

    # ---------------------------------------------------- derived programs
    def jvp(self, nz: tuple, with_primal: bool = False):
        """(*primals, *tangents of the inputs where nz) -> tangents of the float outputs
        (``with_primal``: the outputs before them, computed once with the tangents), from
        the forward variant. Without the outputs it is linear in the tangents."""

        def make():
            src = self.forward or self
            idx = [i for i, z in enumerate(nz) if z]

            def fn(*args):
                primals, tangents = list(args[:len(nz)]), args[len(nz):]

                def of(*v):
                    full = list(primals)
                    for i, x in zip(idx, v):
                        full[i] = x
                    return src.fn(*full)

                out, tout = jax.jvp(of, tuple(primals[i] for i in idx), tuple(tangents))
                touts = [t for o, t in zip(out, tout) if jnp.issubdtype(o.dtype, jnp.inexact)]
                return list(out) + touts if with_primal else touts

            avals = self.in_avals + tuple(_tangent_aval(self.in_avals[i]) for i in idx)
            spec = self._child("jvp", (nz, with_primal, src.key), fn, avals,
                               transpose=None if with_primal else _JvpTranspose(self, nz))
            if with_primal:
                spec.primals = (len(nz), self)
            return spec

        return self.derive("jvp", (nz, with_primal), make)

    def fwd(self, nz: tuple):
        """(*primals) -> (*outputs, *residuals) of ``jax.vjp`` of the reverse variant in
        the inputs where nz."""

        def make():
            src = self.reverse(nz) if self.reverse is not None else self
            return _Forward(self, src, nz)

        return self.derive("fwd", nz, make)

    def unbatched(self, axes: tuple) -> int:
        """How many leading outputs stay unbatched under ``jax.vmap`` with ``in_axes=axes``:
        a JVP program's outputs when only tangents are batched (``jax.jacfwd``: the
        outputs once, concrete under it); all others are batched."""
        if self.primals is None:
            return 0
        n_in, parent = self.primals
        return 0 if any(ax is not None for ax in axes[:n_in]) else len(parent.out_avals)

    def vmap(self, axes: tuple, size: int):
        """The program of ``jax.vmap(fn, in_axes=axes)`` (outputs batched on axis 0 but
        for the ``unbatched`` leading ones)."""

        def make():
            avals = tuple(a if ax is None else a.update(shape=a.shape[:ax] + (size,) + a.shape[ax:])
                          for a, ax in zip(self.in_avals, axes))

            def split(*a):
                out = self.fn(*a)
                n = self.unbatched(axes)  # known now: the trace just recorded it
                return out[:n], out[n:]

            def fn(*args):
                if size == 1:
                    # a batch of one (jax.jacfwd or forward-mode reverse in one number):
                    # the program itself on the squeezed inputs. Batching a solve's loop
                    # takes longer to trace and compile than the loop (a while loop's
                    # predicate and every branch become selects) and computes the same
                    head, tail = split(*[a if ax is None else jnp.squeeze(a, ax) for a, ax in zip(args, axes)])
                    return list(head) + [x[None] for x in tail]
                head, tail = jax.vmap(split, in_axes=axes, out_axes=(None, 0))(*args) if self.primals else \
                    jax.vmap(split, in_axes=axes)(*args)
                return list(head) + list(tail)

            return self._child("vmap", (axes, size), fn, avals)

        return self.derive("vmap", (axes, size), make)


class _Unexportable(Exception):
    """jax.export refused the function (a host callback, an effect): trace it as usual."""


class _Forward(Spec):
    """The forward pass of reverse mode (``Spec.fwd``); ``bwd(ct_nz)`` its backward pass."""

    def __init__(self, parent: Spec, src: Spec, nz: tuple):
        idx = [i for i, z in enumerate(nz) if z]
        self.parent, self.nz, self.idx, self.res_box = parent, nz, idx, {}

        def fn(*primals):
            def of(*v):
                full = list(primals)
                for i, x in zip(idx, v):
                    full[i] = x
                return src.fn(*full)

            out, vjp = jax.vjp(of, *[primals[i] for i in idx])
            res, self.res_box["res_def"] = jtu.tree_flatten(vjp)
            return list(out) + [jnp.asarray(r) for r in res]

        name = f"{parent.name}.fwd"
        super().__init__(name, f"{name}-" + _key("fwd", nz, src.key), fn, parent.in_avals,
                         parent.options, errors_off=parent.errors_off)

    @property
    def n_out(self):
        return len(self.parent.out_avals)

    def res_def(self):
        if "res_def" not in self.res_box:  # loaded from disk: trace it for the residuals' structure
            jax.eval_shape(self.fn, *[_spec_of(a) for a in self.in_avals])
        return self.res_box["res_def"]

    def lin(self):
        """(*residuals, *tangents) -> output tangents: only ever transposed (reverse mode)."""

        def make():
            res_avals = self.out_avals[self.n_out:]
            avals = res_avals + tuple(_tangent_aval(self.parent.in_avals[i]) for i in self.idx)

            def fn(*args):
                raise NotImplementedError(
                    "nhjax: a linearization made for reverse mode was evaluated forward; use jax.jvp")

            spec = self._child("lin", (), fn, avals, transpose=_LinTranspose(self, len(res_avals)))
            spec._out_avals = tuple(_tangent_aval(a) for a in self.parent.out_avals if _is_float(a))
            return spec

        return self.derive("lin", (), make)

    def bwd(self, ct_nz: tuple):
        """(*residuals, *cotangents of the float outputs where ct_nz) -> cotangents of
        the inputs where nz."""

        def make():
            out_avals = self.parent.out_avals
            n_res = len(self.out_avals) - len(out_avals)
            floats = [i for i, a in enumerate(out_avals) if _is_float(a)]

            def fn(*args):
                res, cts = args[:n_res], iter(args[n_res:])
                vjp = jtu.tree_unflatten(self.res_def(), list(res))
                full = []
                for i, a in enumerate(out_avals):
                    if not _is_float(a):
                        full.append(np.zeros(a.shape, jax.dtypes.float0))
                    elif ct_nz[floats.index(i)]:
                        full.append(next(cts))
                    else:
                        full.append(jnp.zeros(a.shape, a.dtype))
                return list(vjp(full))

            avals = self.out_avals[len(out_avals):] + tuple(
                _tangent_aval(out_avals[i]) for k, i in enumerate(floats) if ct_nz[k])
            return self._child("bwd", ct_nz, fn, avals)

        return self.derive("bwd", ct_nz, make)


class _LinTranspose:
    """Transpose of ``_Forward.lin``: the backward program."""

    def __init__(self, forward: _Forward, n_res: int):
        self.forward, self.n_res = forward, n_res

    def __call__(self, cts, args):
        res, tangents = args[:self.n_res], args[self.n_res:]
        ct_nz = tuple(type(c) is not ad.Zero for c in cts)
        if not any(ct_nz):
            return [None] * len(res) + [ad.Zero(t.aval) for t in tangents]
        bwd = self.forward.bwd(ct_nz)
        BOUND["bwd"] += 1
        out = program_p.bind(*res, *[c for c in cts if type(c) is not ad.Zero], spec=bwd)
        return [None] * len(res) + list(out)


class _JvpTranspose:
    """Transpose of ``Spec.jvp`` (linear in its tangents): reverse mode of the parent,
    for the paths that transpose a JVP (``jax.linear_transpose`` of ``jax.linearize``)."""

    def __init__(self, parent: Spec, nz: tuple):
        self.parent, self.nz = parent, nz

    def __call__(self, cts, args):
        n = len(self.nz)
        primals, tangents = args[:n], args[n:]
        ct_nz = tuple(type(c) is not ad.Zero for c in cts)
        if not any(ct_nz):
            return [None] * n + [ad.Zero(t.aval) for t in tangents]
        fwd = self.parent.fwd(self.nz)
        outs = program_p.bind(*primals, spec=fwd)
        res = outs[fwd.n_out:]
        out = program_p.bind(*res, *[c for c in cts if type(c) is not ad.Zero], spec=fwd.bwd(ct_nz))
        return [None] * n + list(out)


# ------------------------------------------------------------------ the primitive
program_p = jex.core.Primitive("nhjax_program")
program_p.multiple_results = True


def _impl(*args, spec):
    return spec.run(args)


def _abstract_eval(*avals, spec):
    return [a.update(weak_type=False) if hasattr(a, "update") else a for a in spec.out_avals]


def _lowering(ctx, *args, spec):
    exported = spec.exported()
    return mlir.lower_fun(lambda *a: exported.call(*a), multiple_results=True)(ctx, *args)


def _tangents(spec, touts):
    """The output tangents: ``touts`` for the float outputs, symbolic zeros elsewhere."""
    it = iter(touts)
    return [next(it) if _is_float(a) else ad.Zero(_tangent_aval(a)) for a in spec.out_avals]


def _jvp(primals, tangents, *, spec):
    nz = tuple(type(t) is not ad.Zero and _is_float(spec.in_avals[i]) for i, t in enumerate(tangents))
    if not any(nz):
        out = program_p.bind(*primals, spec=spec)
        return out, [ad.Zero(_tangent_aval(a)) for a in spec.out_avals]
    BOUND["jvp"] += 1
    # forward mode: outputs and tangents from one program (the tangents need the
    # outputs' computation anyway); its trace records the outputs' shapes
    outs = program_p.bind(*primals, *[t for t, z in zip(tangents, nz) if z], spec=spec.jvp(nz, True))
    n_out = len(spec.out_avals)
    return outs[:n_out], _tangents(spec, outs[n_out:])


def _linearize(is_vjp, nzs, *primals, spec):
    nz = tuple(bool(z) and _is_float(spec.in_avals[i]) for i, z in enumerate(nzs))
    if not any(nz) or spec.transpose is not None:
        return _fallback_linearize(program_p, is_vjp, nzs, *primals, spec=spec)
    if not is_vjp or spec.lazy:
        # jax.linearize, or reverse mode of a program whose outputs seldom get a cotangent
        # (diagnostics): the outputs from its own program, and the tangent map as the
        # linear JVP program, whose transpose (reverse mode's programs) runs only for
        # outputs that do get a cotangent
        lin = spec.jvp(nz)

        def linearized(residuals, *tangents):
            return _tangents(spec, program_p.bind(*residuals, *[t for t, z in zip(tangents, nz) if z], spec=lin))

        out = program_p.bind(*primals, spec=spec)
        return out, [_is_float(a) for a in spec.out_avals], list(primals), linearized
    sizes = [int(np.prod(spec.in_avals[i].shape)) for i, z in enumerate(nz) if z]
    if sum(sizes) <= spec.max_tangents:
        return _linearize_by_tangents(spec, nz, sizes, primals)
    fwd = spec.fwd(nz)
    BOUND["fwd"] += 1
    outs = program_p.bind(*primals, spec=fwd)  # (its trace, if any, records the outputs' shapes)
    n_out = fwd.n_out
    lin = fwd.lin()

    def linearized(residuals, *tangents):
        return _tangents(spec, program_p.bind(*residuals, *[t for t, z in zip(tangents, nz) if z], spec=lin))

    return list(outs[:n_out]), [_is_float(a) for a in spec.out_avals], list(outs[n_out:]), linearized


def _linearize_by_tangents(spec, nz, sizes, primals):
    """Reverse mode in few inputs by forward mode (see ``call``): the outputs and their
    Jacobian in the D input numbers from the batched JVP program; the tangent map, the
    Jacobian's product with the tangents, is ordinary (transposable) JAX."""
    D = sum(sizes)
    idx = [i for i, z in enumerate(nz) if z]
    basis, start = [], 0
    for i, size in zip(idx, sizes):  # the unit vectors of the D numbers, input by input
        e = np.zeros((D, size))
        e[start:start + size] = np.eye(size)
        basis.append(jnp.asarray(e.reshape((D,) + tuple(spec.in_avals[i].shape)), spec.in_avals[i].dtype))
        start += size
    BOUND["jvp"] += 1
    jac = spec.jvp(nz, True).vmap((None,) * len(nz) + (0,) * len(idx), D)
    outs = program_p.bind(*primals, *basis, spec=jac)
    n_out = len(spec.out_avals)
    out_nz = [_is_float(a) for a in spec.out_avals]

    def linearized(J, *tangents):
        t = jnp.concatenate([jnp.reshape(tangents[i], (-1,)) for i in idx])
        return _tangents(spec, [jnp.tensordot(t, j, axes=1) for j in J])

    return list(outs[:n_out]), out_nz, list(outs[n_out:]), linearized


def _transpose(cts, *args, spec):
    if spec.transpose is None:
        raise NotImplementedError(f"nhjax: the program {spec.name} is not linear: it has no transpose")
    return spec.transpose(list(cts), list(args))


def _batch(args, dims, *, spec):
    axes = tuple(None if d is None or not isinstance(d, int) else int(d) for d in dims)  # not mapped: None
    size = next(a.shape[d] for a, d in zip(args, axes) if d is not None)
    BOUND["vmap"] += 1
    out = program_p.bind(*args, spec=spec.vmap(axes, size))
    n = spec.unbatched(axes)
    return out, [None] * n + [0] * (len(out) - n)


program_p.def_impl(_impl)
program_p.def_abstract_eval(_abstract_eval)
mlir.register_lowering(program_p, _lowering)
ad.primitive_jvps[program_p] = _jvp
ad.primitive_transposes[program_p] = _transpose
batching.primitive_batchers[program_p] = _batch
if _LINEARIZATIONS is not None and _fallback_linearize is not None:
    _LINEARIZATIONS[program_p] = _linearize


# ------------------------------------------------------------------ entry
_SPECS: dict = {}


def call(name: str, fn: Callable, args: tuple, *, options: dict | None = None, error_mode: str | None = None,
         forward: Callable | None = None, reverse: Callable | None = None, variant_key=(),
         lazy: bool = False, max_tangents: int = 0, fallback: Callable | None = None):
    """``fn(*args)`` through the program cache, under any differentiation of concrete values.

    ``fn``: a jax-traceable function returning a pytree of arrays in builtin containers;
    arrays in ``args`` are its inputs, everything else is static. Concrete ``args``: the
    stored program runs (``_programs.call``). Tracers of ``jax.grad``/``jax.jvp``/...
    around concrete values: the primitive is bound, and its derivatives are stored
    programs (module docstring). ``forward(args)`` / ``reverse(args, nz)``: the
    arguments of the forward- and reverse-mode variants (same array structure; ``nz``:
    ``args`` with True where an array carries a tangent, False elsewhere); default
    ``args``; ``variant_key``: whatever else the variants depend on (hashable; part of
    the in-memory lookup of the call's programs, whose disk names come from the variants'
    own arguments). ``lazy``:
    reverse mode runs the function's own program and differentiates only when a cotangent
    reaches its outputs (for outputs that are seldom differentiated). ``max_tangents``:
    reverse mode in at most that many input numbers runs forward mode instead (the JVP
    program batched over the input basis, the program ``jax.jacfwd`` runs, and the
    backward pass a product with that Jacobian): for a solve, as many tangent solves as
    inputs instead of a recording forward pass and a backward one, and one compiled
    program for both modes. Anything else (values under jit or vmap, the cache off, an unexportable or
    unreadable function): ``fallback(*args)`` if given, else ``fn(*args)`` traced into
    the caller's program."""
    leaves = jtu.tree_leaves(args)
    if not any(isinstance(x, jax.core.Tracer) for x in leaves):
        return _programs.call(name, fn, args, error_mode=error_mode, fallback=fallback, compiler_options=options)
    plain = fallback or fn
    if (_to_concrete is None or _programs.directory() is None or jax.config.jax_disable_jit
            or _programs.tracing_stored()):
        # (inside a stored program's own trace a nested one would only add a layer)
        return plain(*args)
    spec = _spec(name, fn, args, options, error_mode, forward, reverse, variant_key)
    if spec is None:
        return plain(*args)
    spec.lazy, spec.max_tangents = lazy, int(max_tangents)
    dyn = [x for x in leaves if eqx.is_array(x)]
    try:
        BOUND["call"] += 1
        out = program_p.bind(*dyn, spec=spec)
    except _Unexportable:
        _SPECS[(_quick(name, fn, args, options, error_mode), variant_key)] = None
        return plain(*args)
    return jtu.tree_unflatten(spec.out_def, out)


def _quick(name, fn, args, options, error_mode):
    leaves, treedef = jtu.tree_flatten(args)
    desc = tuple((tuple(x.shape), np.dtype(x.dtype).str) if eqx.is_array(x) else x for x in leaves)
    return (name, fn, treedef, desc, tuple(sorted((options or {}).items())), error_mode or _programs.error_mode())


def _spec(name, fn, args, options, error_mode, forward, reverse, variant_key):
    """The Spec of ``fn`` on ``args``'s structure (None: cannot be cached)."""
    try:
        quick = (_quick(name, fn, args, options, error_mode), variant_key)
        hash(quick)
    except TypeError:
        quick = None
    if quick is not None and quick in _SPECS:
        return _SPECS[quick]
    spec = _make_spec(name, fn, args, options, error_mode, forward, reverse)
    if quick is not None:
        _SPECS[quick] = spec
    return spec


def _flat_fn(fn, args, box):
    """``fn`` as a function of the flat list of ``args``'s arrays; its output structure
    goes to ``box`` when it is traced."""
    dyn, static = eqx.partition(args, eqx.is_array)
    dyn_def = jtu.tree_structure(dyn)

    def flat(*lv):
        out = fn(*eqx.combine(jtu.tree_unflatten(dyn_def, list(lv)), static))
        out_leaves, box["out_def"] = jtu.tree_flatten(out)
        return out_leaves

    return flat


def _make_spec(name, fn, args, options, error_mode, forward, reverse):
    """The Spec of ``fn`` on ``args``: nothing is traced here (the first program that runs
    traces, and records the outputs' shapes for the others)."""
    try:  # (the eager path's name: the same program on disk)
        key = _programs.program_key(name, fn, args, error_mode, options)
    except _programs.Uncacheable:
        _programs.STATS["uncacheable"] += 1
        return None
    avals = [jax.core.ShapedArray(tuple(x.shape), x.dtype) for x in jtu.tree_leaves(args) if eqx.is_array(x)]
    off = error_mode == "off"
    box = {}
    spec = Spec(name, key, _flat_fn(fn, args, box), avals, options, errors_off=off, box=box)
    if forward is not None:  # variants share the box: the same outputs
        # named by what they are (calls that differ only in what their variants replace,
        # e.g. the adjoint, share them and the programs derived from them)
        fargs = forward(args)
        fkey = _programs.program_key(f"{name}.forward", fn, fargs, error_mode, options)
        spec.forward = Spec(f"{name}.forward", fkey, _flat_fn(fn, fargs, box), avals, options,
                            errors_off=off, root=spec, box=box)
    if reverse is not None:
        dyn, static = eqx.partition(args, eqx.is_array)
        dyn_def = jtu.tree_structure(dyn)

        def reverse_spec(nz):
            rargs = reverse(args, eqx.combine(jtu.tree_unflatten(dyn_def, list(nz)), static))
            rkey = _programs.program_key(f"{name}.reverse", fn, rargs, error_mode, options)
            return Spec(f"{name}.reverse", rkey, _flat_fn(fn, rargs, box), avals, options, errors_off=off,
                        root=spec, box=box)

        spec.reverse = reverse_spec
    return spec


def _as_input(v):
    """An argument of a stored method: arrays as they are, numbers and sequences as
    float64 arrays (handed over without a program of their own), None and the rest as
    static values."""
    if v is None or isinstance(v, (jax.Array, np.ndarray)) or isinstance(v, jax.core.Tracer):
        return v
    if isinstance(v, (int, float, list, tuple)) and not isinstance(v, bool):
        try:
            return jnp.asarray(np.asarray(v, float), float)
        except (TypeError, ValueError):
            return v
    return v


def stored(name: str, options: dict | None = None):
    """Decorator: ``fn(self, *args)`` (a system's geometry, say) runs as one stored
    program when its arguments' values are known (eager calls, and under ``jax.grad``
    and the like, with stored derivatives: see ``call``), instead of one small compiled
    program per operation in every new process; called while something is traced
    (inside a solve, under ``jax.jit`` or ``jax.vmap``) it is ``fn`` itself, traced
    into the caller's program."""

    def decorate(fn):
        import functools

        @functools.wraps(fn)
        def method(self, *args):
            args = tuple(_as_input(a) for a in args)
            leaves = jtu.tree_leaves((self, args))
            if any(isinstance(x, jax.core.Tracer) for x in leaves) and not has_values((self, args)):
                return fn(self, *args)
            return call(name, fn, (self, *args), options=options)

        method.plain = fn
        return method

    return decorate
