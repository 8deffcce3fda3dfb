"""Optimal-control problems on nhjax systems.

    minimize    Phi(x(T)) + int_0^T L(t, x, u) dt
    subject to  x' = f(t, x, u)  (the nhjax system),  x(0) = x0,
                psi(x(T)) = 0    (terminal equality constraints),
                u_lower <= u <= u_upper.

``OCP`` holds the data; ``rollout`` simulates a control and returns the
trajectory with its cost and terminal-constraint residual (the running cost is
integrated as an extra state component, to the solver's tolerance).

Compiled once per problem structure: every number of an OCP (x0, the horizon T,
the arrays inside its cost and constraint modules, the system's parameters) is an
array leaf of the pytree, so the solvers' compiled programs (``compiled`` below)
take them as arguments and a solve with other values runs the same program
(``TRACES`` counts the traces). The programs carry no host callbacks (equinox's
runtime errors are traced as NaN outputs, which the solvers read as failures), so
they can be kept for the next process: ``compiled`` takes them from nhjax's program
cache (``nhjax._programs``), whose stored executables a new process loads without
tracing, lowering or compiling. The solvers' own bookkeeping between those programs
(iterates, multipliers, tests of convergence) is numpy on the host: an eager jax
operation would be one more program to trace and look up in every new process.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu

import collections
import concurrent.futures
import contextlib
import functools
import os
import sys

import numpy as np

import nhjax
from nhjax import _programs
from nhjax import _validate as V
from nhjax.errors import NhjaxError, OutsideChartError, ProblemError
from nhjax.integrate import progress as progress_meter
from nhjax.lie import Euclidean
from nhjax.mechanics import AbstractSystem

__all__ = ["OCP", "ProblemError", "TRACES", "rollout"]

#: Traces of controls' compiled programs, by function name (a counter incremented in
#: the traced Python body: a solve with new values of the same structure adds nothing).
TRACES = collections.Counter()


def nan_errors(mode: str = "nan"):
    """equinox's runtime errors (eqx.error_if in diffrax, optimistix, lineax and
    simulate's checks) traced as NaN outputs instead of host callbacks, in this thread,
    while the programs of ``compiled`` are traced (``nhjax._programs.errors``). A program
    with a host callback is never kept in JAX's persistent cache; the solvers here read
    NaN/inf as a failed trial (the line searches back off) and report it.

    ``mode="off"``: no checks at all, for batched programs: under vmap an equinox
    check fails every member when one fails (its predicate is reduced over the batch),
    whereas a solve that stops early leaves its unreached saves at inf, which fails
    that member's trial only."""
    return _programs.errors(mode)


def host_array(x):
    """A concrete number or array as a float64 jax array, handed over from numpy
    (``nhjax._args.to_device``): ``jnp.asarray`` on a Python number (or on an array
    without a dtype) runs an eager program, one more to lower in every new process."""
    return V.to_device(x)


def compiled(fn=None, *, quick: bool = False, errors: str = "nan"):
    """``eqx.filter_jit(fn)``, traced under ``nan_errors`` and counted in ``TRACES``.

    Called on concrete values, the program comes from nhjax's program cache
    (``nhjax._programs``): in a new process its compiled executable is loaded from disk
    instead of tracing, lowering and compiling the solver's programs again, which is
    most of a warm first answer. Under an outer trace, or when the arguments cannot be
    fingerprinted, it is the plain ``eqx.filter_jit``.

    Otherwise XLA's settings for solves (``nhjax._programs.SOLVE_OPTIONS``: its
    older loop emitters, which compile these programs in less time and run them as
    fast; last bits may differ from a default compile, such as a user's own jit of
    the same function).

    ``quick=True`` (as ``@compiled(quick=True)``): XLA's quick settings
    (``nhjax._programs.QUICK_OPTIONS``: a shorter compile, a slower run, and last
    bits that differ from a default compile's), for programs that run a few
    times per call and whose compile the first answer waits for: the checks of a
    solution (re-simulation, costate sweep) and one-off computations (a fit's basis,
    the control cost's Hessian).

    ``errors``: equinox's error mode while the program is traced (``nan_errors``):
    "nan", or "off" for programs vmapped over members."""
    if fn is None:
        return functools.partial(compiled, quick=quick, errors=errors)
    options = _programs.QUICK_OPTIONS if quick else _programs.SOLVE_OPTIONS

    @functools.wraps(fn)
    def counted(*args, **kwargs):  # runs only while tracing
        TRACES[fn.__name__] += 1
        return fn(*args, **kwargs)

    jitted = eqx.filter_jit(counted)

    name = f"{fn.__module__}.{fn.__qualname__}"

    @functools.wraps(fn)
    def call(*args, **kwargs):
        with nan_errors(errors):
            if kwargs:
                return jitted(*args, **kwargs)
            return _programs.call(name, counted, args, error_mode=errors, fallback=jitted,
                                  compiler_options=options)

    def prepare(*args, trace=True):
        """Trace this program for ``args``'s structure now and compile it in the
        background (``nhjax._programs.prepare``), for a solver that calls it later;
        ``trace=False``: only a stored one (loaded in the background), nothing traced."""
        with nan_errors(errors):
            return _programs.prepare(name, counted, args, error_mode=errors, compiler_options=options, trace=trace)

    def prepare_later(*args):
        """``prepare`` with the trace too in a thread of its own
        (``nhjax._programs.prepare_later``), for a program that a solver can do without
        until it is ready (``ready``). Returns whether that thread was started."""
        return _programs.prepare_later(name, counted, args, error_mode=errors, compiler_options=options,
                                       context=lambda: nan_errors(errors))

    def ready(*args):
        """Whether a call on ``args``'s structure now would trace and compile nothing
        (``nhjax._programs.ready``)."""
        return _programs.ready(name, counted, args, error_mode=errors, compiler_options=options)

    call.jitted = jitted
    call.prepare = prepare
    call.prepare_later = prepare_later
    call.ready = ready
    return call


class OutsideChartProblem(OutsideChartError, ProblemError):
    """An optimal-control problem whose start lies outside its system's chart: the
    ``OutsideChartError`` that ``simulate`` raises for the same start, and a
    ``ProblemError`` (the one class controls' entry points raise)."""


@contextlib.contextmanager
def as_problem_error():
    """Re-raise the validation layer's errors (ParameterError, StateError, ...) as
    ProblemError with the same words: controls' entry points raise one error class."""
    try:
        yield
    except ProblemError:
        raise
    except NhjaxError as e:
        if isinstance(e, (ValueError, TypeError)):
            raise ProblemError(str(e)) from e
        raise


def _in_dask_worker() -> bool:
    """Whether this code runs in a Dask worker (only asked if distributed is imported)."""
    mod = sys.modules.get("distributed")
    if mod is None:
        return False
    try:
        mod.get_worker()
    except (ValueError, AttributeError):
        return False
    return True


def batch_workers(workers, B, unit, owner):
    """The number of threads a batched solver runs its members in: ``workers`` checked
    (an integer >= 1), or by default 2 where this process may use two or more CPUs and
    runs outside a Dask worker (whose cluster already shares the cores), else 1; never
    more than the batch has units of ``unit`` members (its vmapped groups)."""
    if workers is None:
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        workers = 2 if cpus >= 2 and not _in_dask_worker() else 1
    else:
        with as_problem_error():
            workers = V.integer("workers", workers, minimum=1, owner=owner)
    return max(1, min(workers, -(-B // unit)))


def run_in_shares(program, args_of, members, B, workers, unit, name="nhjax-batch"):
    """``program(*args_of(part))`` over B members cut into ``workers`` equal shares of
    whole units, ``part`` being ``members`` (a pytree whose array leaves carry the member
    axis first; other leaves are shared) at the share's members (host-side numpy
    indexing; past B, copies of the share's first member). The shares run at once in
    threads of this process, each result copied to the host, and are joined in member
    order (the padding dropped): one compiled program (the shares have one shape) that
    XLA runs on both cores, releasing the GIL. With one worker: ``program(*args_of(part))``
    on all members, as it is. ``program`` is a ``compiled`` function (its ``prepare``
    traces it once before the threads start)."""

    def part(idx):
        return jtu.tree_map(lambda a: np.asarray(a)[idx] if hasattr(a, "shape") and np.ndim(a) else a, members)

    if workers == 1:
        return program(*args_of(part(np.arange(B))))
    share = -(-(-(-B // unit)) // workers) * unit
    args = []
    for lo in range(0, B, share):
        idx = np.arange(lo, lo + share)
        args.append(args_of(part(np.where(idx < B, idx, lo))))
    program.prepare(*args[0])  # traced here once; the threads wait for its compile
    with concurrent.futures.ThreadPoolExecutor(len(args), thread_name_prefix=name) as pool:
        parts = list(pool.map(lambda a: jax.device_get(program(*a)), args))
    return jtu.tree_map(lambda *a: np.concatenate(a)[:B], *parts)


class Progress:
    """One progress line (tqdm.auto: a text bar in terminals, a widget in notebooks) over
    a solve: the bar counts outer iterations (or Newton iterations), the postfix shows
    the latest iteration number, cost, violation, merit or stationarity and step.
    ``finish(converged)`` closes it: a converged solve ends a full (green) bar however
    few of the allowed iterations it took; an unconverged one stays short (red in
    notebooks). ``on=False``: every method does nothing; a string ``on`` is the bar's
    label instead of ``desc``. ``on=True`` inside a Dask worker is off (the workers'
    bars would all print on the client); a string ``on`` still shows there.

    Until the first iteration reports, the postfix says that a first call compiles: the
    solver's programs are traced and compiled (or loaded) before it can count anything."""

    STARTING = progress_meter.STARTING

    def __init__(self, on, total, desc):
        self.bar, self.steps = None, 0
        if isinstance(on, str):
            desc = on
        elif on and _in_dask_worker():
            on = False
        if on:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, desc=desc, unit="it", leave=True, dynamic_ncols=True)
            self.bar.set_postfix_str(self.STARTING)

    def inner(self, merit, gnorm, step):
        """One inner step (merit value, gradient norm, accepted step length or None)."""
        self.steps += 1
        if self.bar is not None:
            post = {"step": self.steps, "merit": f"{merit:.8g}", "|grad|": f"{gnorm:.1e}"}
            if step is not None:
                post["eta"] = f"{step:.2g}"
            self.bar.set_postfix(post, refresh=False)
            self.bar.update(0)  # redraws at most every mininterval (0.1 s)

    def update(self, **post):
        """One outer iteration done, with the numbers to show."""
        if self.bar is not None:
            self.bar.set_postfix({k: (f"{v:.8g}" if isinstance(v, float) else v) for k, v in post.items()},
                                 refresh=False)
            self.bar.update(1)

    def finish(self, converged):
        if self.bar is None:
            return
        notebook = hasattr(self.bar, "container")  # tqdm.notebook's widget
        if self.bar.postfix and self.STARTING in self.bar.postfix:
            self.bar.set_postfix_str("", refresh=False)  # nothing reported: no stale word
        if converged and self.bar.n < (self.bar.total or 0):
            self.bar.total = self.bar.n
            if notebook:  # the widget's maximum too
                self.bar.container.children[1].max = self.bar.n
        if not converged:
            self.bar.set_description(f"{self.bar.desc}: not converged", refresh=False)
        self.bar.close()
        if not converged and notebook:  # red even when every allowed iteration ran
            self.bar.disp(bar_style="danger", check_delay=False)


_N_CONSTRAINTS: dict = {}
_SHAPES_CHECKED: set = set()


def _structural_answer(fn, args):
    """The abstract outputs [(shape, dtype), ...] of ``fn(*args)``, a structural question
    answered by tracing (``fn`` returns a list of ``jax.ShapeDtypeStruct``, or raises),
    kept beside the stored programs (``nhjax._programs.store_meta``) under the key a
    program of the same structure would have (its code, the code and constants of the
    objects in ``args``, the shapes of their arrays): a new process reads the answer
    instead of tracing the model again. Where the fingerprint cannot vouch for an
    object, every process traces."""
    try:
        key = _programs.program_key(f"{fn.__module__}.{fn.__qualname__}", fn, args)
    except _programs.Uncacheable:
        key = None
    meta = None if key is None else _programs.keyed_meta(key)
    if meta is not None:
        return meta[1]
    avals = fn(*args)
    if key is not None:
        _programs.store_meta(key, None, avals)
    return [(tuple(a.shape), np.dtype(a.dtype).str) for a in avals]


def _check_shapes_traced(system, x0, running_cost, terminal_cost, terminal_constraints):
    """The OCP's parts fit together: the state x0 fits the system (its vector field
    returns the same structure), the costs are scalars, the constraints a 1-D array
    (abstract evaluations: nothing runs). Returns no outputs ([]) or raises."""
    u = jax.ShapeDtypeStruct((system.control_dim,), jnp.float64)  # abstract: no eager program
    names = system.state_names
    if names and getattr(x0, "shape", None) != (len(names),):
        raise ProblemError(
            f"x0 does not fit {type(system).__name__}: it has shape "
            f"{getattr(x0, 'shape', None)}, the state is {names}"
        )
    try:
        dx = jax.eval_shape(lambda u: system.vector_field(0.0, x0, u), u)
    except Exception as e:  # noqa: BLE001 - re-raised with the cause attached
        raise ProblemError(f"x0 does not fit {type(system).__name__}: {e}") from e
    if jtu.tree_structure(dx) != jtu.tree_structure(x0):
        raise ProblemError(f"x0 does not fit {type(system).__name__}: its vector field "
                           "returns a differently structured state")
    L = jax.eval_shape(lambda u: running_cost(0.0, x0, u), u)
    if L.shape != ():
        raise ProblemError(f"running_cost(t, x, u) must return a scalar, got shape {L.shape}")
    if terminal_cost is not None:
        P = jax.eval_shape(lambda: terminal_cost(x0))
        if P.shape != ():
            raise ProblemError(f"terminal_cost(x) must return a scalar, got shape {P.shape}")
    if terminal_constraints is not None:
        c = jax.eval_shape(lambda: terminal_constraints(x0))
        if len(c.shape) != 1:
            raise ProblemError(f"terminal_constraints(x) must return a 1-D array, got shape {c.shape}")
    return []


def _constraint_shape(terminal_constraints, x0):
    """[the shape and dtype of terminal_constraints(x0)] (abstract: nothing runs)."""
    return [jax.eval_shape(lambda: terminal_constraints(x0))]


def _structure_key(tree):
    """A key of ``tree``'s structure for the caches of structural answers: the tree,
    its arrays' shapes and dtypes, and its other leaves themselves (a function that is
    no pytree, e.g. a lambda, is its own leaf: keyed by identity; unhashable leaves
    make the key unhashable, and the callers then do not cache)."""
    return (jtu.tree_structure(tree),
            tuple((np.shape(a), a.dtype) if eqx.is_array(a) else a for a in jtu.tree_leaves(tree)))


def check_tolerances(owner, **tols):
    """Positive finite tolerances (and integer budgets, passed as (value, 'int'))."""
    with as_problem_error():
        for name, v in tols.items():
            if isinstance(v, tuple):
                V.integer(name, v[0], minimum=v[2] if len(v) > 2 else 1, owner=owner)
            elif v is not None:
                # as a host float (a device array per check would be a dispatch per solve);
                # tracers pass unchecked either way
                V.positive(name, v, owner=owner, shape=(), as_float=True)


def check_ocp(ocp, owner):
    if not isinstance(ocp, OCP):
        raise ProblemError(f"{owner}: the problem must be a controls.OCP, got {type(ocp).__name__}")


def check_parametrization(param, ocp, owner):
    """A controls.parametrize object whose signal covers [0, T] with the system's inputs."""
    for attr in ("dim", "size", "signal", "T"):
        if not hasattr(param, attr):
            raise ProblemError(
                f"{owner}: param must be a control parametrization (controls.PiecewiseLinear, Chebyshev, "
                f"...), got {type(param).__name__}")
    if param.dim != ocp.system.control_dim:
        raise ProblemError(
            f"{owner}: the parametrization has {param.dim} inputs, {type(ocp.system).__name__} takes "
            f"{ocp.system.control_dim}"
        )
    if V.is_traced(param.T, ocp.T):
        return
    t0, T, horizon = float(getattr(param, "t0", 0.0)), float(param.T), float(ocp.T)
    if t0 > 1e-12 * max(1.0, horizon) or t0 + T < horizon * (1 - 1e-12):
        raise ProblemError(
            f"{owner}: the parametrization covers [{t0:g}, {t0 + T:g}] but the problem's horizon is "
            f"[0, {float(ocp.T):g}]: build it with T = {float(ocp.T):g} (e.g. {type(param).__name__}(n, "
            f"{float(ocp.T):g}, "
            f"{param.dim}))")


def check_guess(name, guess, shape, owner):
    """A finite guess of the given shape (None passes)."""
    if guess is None:
        return None
    with as_problem_error():
        g = V.real(name, guess, owner=owner)
    if g.shape != tuple(shape):
        raise ProblemError(f"{name} has shape {g.shape}, the {owner} takes {tuple(shape)}")
    return g


def _x0_numbers(system, x0):
    """(max |residual| per constraint, value per chart guard) of the system at x0."""
    return ({k: V._max_abs(v) for k, v in system.constraints(0.0, x0).items()}, dict(system.guards(x0)))


class OCP(eqx.Module):
    """An optimal-control problem (see the module docstring).

    running_cost(t, x, u) -> scalar; terminal_cost(x) -> scalar (or None);
    terminal_constraints(x) -> (m,) array (or None). Callables may be plain
    functions or equinox modules (whose arrays are then parameters: a new target
    held in a module does not recompile; a number closed over by a plain function
    is part of the program, so changing it compiles anew).

    T [s] is stored as a 0-d float64 array (a leaf): a new horizon runs the same
    compiled programs (the solvers' time grids scale with T). ``float(ocp.T)``
    gives the number.
    """

    system: AbstractSystem
    x0: Any
    T: jax.Array
    running_cost: Callable
    terminal_cost: Callable | None = None
    terminal_constraints: Callable | None = None
    u_lower: Any = None
    u_upper: Any = None

    def __init__(self, system, x0, T, running_cost, terminal_cost=None, terminal_constraints=None,
                 u_lower=None, u_upper=None):
        owner = "OCP"
        if not isinstance(system, AbstractSystem):
            raise ProblemError(f"{owner}: system must be an nhjax system (a scene, a Lagrangian, ...), got "
                               f"{type(system).__name__}")
        if system.control_dim == 0:
            raise ProblemError(f"{type(system).__name__} has no control inputs to optimize")
        if V.is_traced(T):
            T = jnp.asarray(T, float)
            if T.shape != ():
                raise ProblemError(f"{owner}: the horizon T must be a scalar, got shape {T.shape}")
        else:
            with as_problem_error():  # the rules simulate applies to its time span
                T = host_array(V.duration("T", T, owner=owner))
        with as_problem_error():
            V.function("running_cost", running_cost, owner=owner, signature="running_cost(t, x, u) -> scalar")
            V.function("terminal_cost", terminal_cost, owner=owner, signature="terminal_cost(x) -> scalar",
                       optional=True)
            V.function("terminal_constraints", terminal_constraints, owner=owner,
                       signature="terminal_constraints(x) -> (m,)", optional=True)
        self.system = system
        with as_problem_error():  # the rules of simulate: a plain list is read as one array
            self.x0 = V.as_state(system, x0, owner=owner)
        self.T = T
        self.running_cost = running_cost
        self.terminal_cost = terminal_cost
        self.terminal_constraints = terminal_constraints
        k = system.control_dim
        self.u_lower = self._bound("u_lower", u_lower, k)
        self.u_upper = self._bound("u_upper", u_upper, k)
        if (self.u_lower is None) != (self.u_upper is None):
            raise ProblemError("give both u_lower and u_upper, or neither (use -inf or inf for a free side)")
        if self.u_lower is not None and not V.is_traced(self.u_lower, self.u_upper):
            lo, hi = np.asarray(self.u_lower), np.asarray(self.u_upper)
            if np.any(lo >= hi):
                i = int(np.argmax(lo >= hi))
                raise ProblemError(
                    f"every lower control bound must be below the upper one: input {i} has u_lower = "
                    f"{lo[i]:g} >= u_upper = {hi[i]:g}; swap them or widen the box")
        self._check_shapes()
        self._check_x0()

    @staticmethod
    def _bound(name, value, k):
        if value is None:
            return None
        try:
            b = (jnp.broadcast_to(jnp.asarray(value, float), (k,)) if V.is_traced(value)
                 else host_array(np.broadcast_to(np.asarray(value, float), (k,))))
        except (TypeError, ValueError):
            raise ProblemError(f"OCP: {name} must be a number or an array of {k} numbers (one per input), "
                               f"got {value!r}") from None
        if not V.is_traced(b) and np.any(np.isnan(np.asarray(b))):
            raise ProblemError(f"OCP: {name} contains NaN; pass numbers (or -inf/inf for an unbounded side)")
        return b

    def _check_x0(self):
        """x0 against the system: structure and shapes, finiteness, group membership,
        constraints and chart guards (concrete x0 only)."""
        if V.is_traced(self.x0, self.system):
            return
        with as_problem_error():
            V.check_state(self.system, self.x0, owner="OCP")
            leaves = [np.asarray(a) for a in jtu.tree_leaves(self.x0)]
            if not all(np.all(np.isfinite(a)) for a in leaves):
                raise ProblemError(f"OCP: x0 contains NaN or inf at "
                                   f"{V.nonfinite_components(self.system, self.x0)}; pass finite numbers")
            for part, sp, leaf in V._group_parts(self.system.spaces, self.x0):
                V._check_group_value(part, sp, np.asarray(leaf), 1e-8, "OCP")
        # constraints and guards in one program (from the program cache in a new process)
        constraints, guards = jax.device_get(_programs.call("ocp_x0", _x0_numbers, (self.system, self.x0)))
        for name, r in constraints.items():
            r = float(r)
            if not r <= 1e-8:
                raise ProblemError(
                    f"OCP: x0 violates constraint '{name}' of {type(self.system).__name__}: |residual| = "
                    f"{r:.3e} > 1e-8; start from a consistent state (the scene's initial_state, or "
                    "system.project(0.0, x0))")
        for name, g in guards.items():
            if not float(g) > 0:  # the error simulate() raises for the same start
                raise V.outside_chart(self.system, name, g, owner="OCP", name="x0", cls=OutsideChartProblem)

    def _check_shapes(self):
        # a structural question: answered once per structure (otherwise three traces of
        # the model per problem, and a grid of problems builds hundreds)
        key = _structure_key((self.system, self.x0, self.running_cost, self.terminal_cost,
                              self.terminal_constraints))
        try:
            if key in _SHAPES_CHECKED:
                return
        except TypeError:  # unhashable leaves or static fields: check every time
            key = None
        # (and once per structure across processes: for a large model the trace is most
        # of a warm OCP's set-up)
        _structural_answer(_check_shapes_traced, (self.system, self.x0, self.running_cost, self.terminal_cost,
                                                  self.terminal_constraints))
        if key is not None:
            _SHAPES_CHECKED.add(key)

    @property
    def n_constraints(self) -> int:
        if self.terminal_constraints is None:
            return 0
        # a structural question, asked by every solve: traced once per structure
        # (a function that is no pytree, e.g. a lambda, is its own leaf: keyed by identity)
        key = _structure_key((self.terminal_constraints, self.x0))
        try:
            return _N_CONSTRAINTS[key]
        except (KeyError, TypeError):
            pass
        [(shape, _)] = _structural_answer(_constraint_shape, (self.terminal_constraints, self.x0))
        m = shape[0]
        try:
            _N_CONSTRAINTS[key] = m
        except TypeError:  # unhashable static fields: no caching
            pass
        return m

    def terminal(self, x):
        """(Phi(x), psi(x)) with zeros where absent."""
        phi = jnp.zeros(()) if self.terminal_cost is None else self.terminal_cost(x)
        psi = jnp.zeros((0,)) if self.terminal_constraints is None else self.terminal_constraints(x)
        return phi, psi


class CostAugmented(AbstractSystem):
    """The system with its running cost integrated alongside: state (x, J)."""

    system: AbstractSystem
    running_cost: Callable

    @property
    def control_dim(self):  # type: ignore[override]
        return self.system.control_dim

    @property
    def spaces(self):
        return (self.system.spaces, Euclidean())

    @property
    def large_vector_field(self):  # type: ignore[override]
        return self.system.large_vector_field

    def vector_field(self, t, y, u):
        x, _ = y
        return self.system.vector_field(t, x, u), self.running_cost(t, x, u)

    def constraints(self, t, y):
        return self.system.constraints(t, y[0])

    def guards(self, y):
        return self.system.guards(y[0])

    def energy(self, y):
        return self.system.energy(y[0])

    def power(self, t, y, u):
        return self.system.power(t, y[0], u)


class _OnState(eqx.Module):
    control: Any

    @property
    def breakpoints(self):
        return getattr(self.control, "breakpoints", None)

    def __call__(self, t, y):
        return self.control(t, y[0])


def rollout(ocp: OCP, control, *, rtol=1e-9, atol=1e-9, saveat=2, max_steps=None, adjoint=None,
            diagnostics=False, **kw):
    """Simulate ``control`` (callable u(t, x)) on the problem.

    Returns (traj, cost, psi): the trajectory of (x, J) pairs, the total cost
    Phi(x(T)) + J(T), and the terminal-constraint residual. Reverse-mode
    gradients go through ``nhjax.DiscreteAdjoint`` unless ``adjoint`` says
    otherwise (``max_steps`` None: that adjoint's budget, 4096 steps).
    """
    check_ocp(ocp, "rollout")
    if not callable(control):
        raise ProblemError(f"rollout: control must be callable as u(t, x), got {type(control).__name__}")
    if adjoint is None:
        adjoint = nhjax.DiscreteAdjoint()
    aug = CostAugmented(ocp.system, ocp.running_cost)
    y0 = (ocp.x0, host_array(0.0))
    traj = nhjax.simulate(aug, y0, ocp.T, control=_OnState(control), rtol=rtol, atol=atol,
                          saveat=saveat, max_steps=max_steps, adjoint=adjoint, track_work=False,
                          diagnostics=diagnostics, **kw)
    end = _terminal_values if V.is_traced(ocp, traj.xs) else _terminal_values_program
    return (traj, *end(ocp, traj.xs))


def _terminal_values(ocp, xs):
    """(Phi(x(T)) + J(T), psi(x(T))) from the saved states (x, J)."""
    xT, JT = jtu.tree_map(lambda a: a[-1], xs)
    phi, psi = ocp.terminal(xT)
    return phi + JT, psi


# on concrete values one program, where eager slicing and arithmetic would be one
# program each to lower in a new process
_terminal_values_program = compiled(_terminal_values)


@compiled(quick=True)
def _saved_path(ocp, control, rtol, atol, n_points):
    traj, _, _ = rollout(ocp, control, rtol=rtol, atol=atol, saveat=n_points)
    return traj.ts, traj.xs[0]


def saved_path(ocp: OCP, control, *, rtol, atol, n_points, owner):
    """(ts, xs): the times and states x of ``rollout(ocp, control, saveat=n_points)``
    (numpy), as one compiled program without simulate()'s eager input checks (for
    callers whose problem and control are checked already), which
    ``prepare_saved_path`` can start compiling before it is needed. A failed
    simulation raises ProblemError."""
    ts, xs = (np.asarray(a) for a in _saved_path(ocp, control, host_array(rtol), host_array(atol), n_points))
    if not np.all(np.isfinite(xs)):
        raise ProblemError(f"{owner}: the simulation of the control failed (non-finite states; too many "
                           f"steps at rtol={rtol}, atol={atol}?)")
    return ts, xs


def prepare_saved_path(ocp: OCP, control, *, rtol, atol, n_points) -> bool:
    """Trace ``saved_path``'s program for this problem and a control of ``control``'s
    structure now and compile it in the background (``nhjax._programs.prepare``)."""
    return _saved_path.prepare(ocp, control, host_array(rtol), host_array(atol), n_points)
