"""``nhjax.simulate``: integrate any nhjax system with diffrax and report its accuracy.

One call runs one jitted ``diffrax.diffeqsolve`` and returns a ``Trajectory``
that carries, next to the states, the evidence of how good they are: accepted
and rejected steps, the largest constraint residual seen, the drift of every
invariant the system declares, and (under a control) the drift of energy minus
the work of the inputs.

Bad input and failures raise, with the time they happened:

* an initial state off its constraint manifold -> ``ConstraintViolationError``
  (or pass ``project=True``);
* a chart guard crossing zero -> ``ChartSingularityError`` (or
  ``on_guard="stop"`` to get the trajectory up to the chart's edge);
* max_steps exhausted, NaN/inf in the vector field -> ``IntegrationError``.

When simulate() is itself traced (inside jit, vmap or grad) these checks
become ``equinox.error_if`` runtime errors (same wording, without the time).
"""

from __future__ import annotations

import collections
import functools
import dataclasses
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import optimistix as optx

from .. import _primitive, _programs
from .._validate import (
    as_state,
    check_control,
    check_saveat,
    check_state,
    choice,
    error_if,
    first_error_if,
    member_report,
    raise_for_report,
    runtime_checks,
    simulate_memory,
    solver_settings,
    time_span,
    time_span_check,
    to_device,
)
from ..errors import (
    ChartSingularityError,
    IntegrationError,
    ParameterError,
    SystemKindError,
    TimeSpanError,
)
from ..lie.spaces import Euclidean, is_space
from ..mechanics.system import AbstractSystem
from .adjoint import DiscreteAdjoint, _Problem, _save_state, discrete_solve
from .one_function import as_one_function, under_differentiation
from .progress import SimulatedTimeMeter
from .projection import ProjectedSolver
from .rkmk import LieODETerm, RKMK45, _AbstractRKMK

__all__ = ["Trajectory", "simulate"]


class Trajectory(eqx.Module):
    """States at the saved times, with the diagnostics that qualify them.

    Fields
    ------
    ts, xs : saved times and states (xs stacks the state pytree along axis 0).
    us : the control at the saved times (None without a control).
    work : work done by the inputs since t0 (None unless tracked).
    invariants : name -> values at the saved times.
    invariant_drift : name -> max |I(t) - I(t0)| over the saved times.
    constraint_drift : name -> max |residual| over the saved times.
    num_steps, num_accepted_steps, num_rejected_steps : solver statistics.
    t_final : time the solve ended (t1 unless stopped by a guard).
    guard : name of the chart guard that stopped the solve ("" if none).
    """

    ts: jax.Array
    xs: Any
    us: Any
    work: Any
    invariants: dict
    invariant_drift: dict
    constraint_drift: dict
    num_steps: jax.Array
    num_accepted_steps: jax.Array
    num_rejected_steps: jax.Array
    t_final: jax.Array
    x_end: Any
    result: Any
    event_mask: Any
    state_names: tuple = eqx.field(static=True, default=())
    guard: str = eqx.field(static=True, default="")

    def __getitem__(self, name: str):
        """Component of a flat state by name, e.g. ``traj["theta"]``."""
        if name not in self.state_names:
            raise KeyError(f"no state component '{name}'; have {self.state_names}")
        return self.xs[..., self.state_names.index(name)]

    @property
    def x_final(self):
        return jtu.tree_map(lambda a: a[-1], self.xs)

    def summary(self) -> str:
        """Human-readable diagnostics."""
        lines = [
            f"t_final = {float(self.t_final):.6g}   steps: {int(self.num_accepted_steps)} "
            f"accepted, {int(self.num_rejected_steps)} rejected"
        ]
        for k, v in self.constraint_drift.items():
            lines.append(f"  constraint '{k}': max |residual| = {float(v):.2e}")
        for k, v in self.invariant_drift.items():
            lines.append(f"  invariant '{k}': max drift = {float(v):.2e}")
        if self.guard:
            lines.append(f"  stopped by chart guard '{self.guard}'")
        return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class _Static:
    track_work: bool
    guard_names: tuple[str, ...]
    max_steps: int
    progress: bool
    state_names: tuple[str, ...]
    project_steps: bool = False
    ends_only: bool = False
    diagnostics: bool = True
    # diffrax's own runtime checks (equinox error_if: host callbacks) in the program; off
    # for eager calls, whose inputs simulate() has checked, so that the program has no
    # host callback and JAX's persistent cache keeps it
    runtime_checks: bool = True
    # the work rides as the last entry of a flat state vector (1-D Euclidean states):
    # one array through the solver instead of a (state, work) pair, which costs about
    # as much per step as the state itself on small systems
    flat_work: bool = False
    # equinox's runtime-error mode when a traced call was made (controls traces with
    # errors as NaN): part of the key of the nested jit, so a trace made in one mode is
    # never reused in another
    error_mode: str = ""
    # a projected solve's saved states are projected in its program; False: the caller
    # projects them (an eager call, in its second program: see simulate)
    project_saved: bool = True
    # the solve as one compiled function (one_function.py); off where it only adds tracing:
    # the forward pass of reverse mode differentiates the unwrapped program anyway
    one_function: bool = True


def _is_traced(*trees) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jtu.tree_leaves(trees))


def _all_euclidean(spaces) -> bool:
    return all(isinstance(s, Euclidean) for s in jtu.tree_leaves(spaces, is_leaf=is_space))


def _max_abs(a):
    a = jnp.asarray(a)
    return jnp.max(jnp.abs(a)) if a.size else jnp.zeros(())


def _vf_body(static: _Static, t, y, args):
    system, control = args
    x = _state_part(y, static)
    u = None if control is None else control(t, x)
    return _rate(static, system, t, x, u, system.vector_field(t, x, u))


@functools.lru_cache(maxsize=64)
def _vector_field(static: _Static):
    """The solver's vector field (state, and the power when the work is tracked).

    It is a nested jit: a solve evaluates the vector field in ~26 places (RK stages,
    the initial step, dense output, the event, each traced again by diffrax), and a
    nested jit traces it once per argument shape and reuses that jaxpr everywhere, which
    cuts the tracing of a solve (the time to a first simulate() that no compilation
    cache can store). XLA inlines the call, so the compiled program is unchanged."""
    return eqx.filter_jit(functools.partial(_vf_body, static))


def _entry_body(static: _Static, t, y, args, apply):
    """The vector field with the velocity projection of a split projected solve (see
    ``ProjectedSolver``): (y', f(t, y')), y' = y with its velocities projected where
    ``apply``; the work, when tracked, rides along."""
    system, control = args
    x = _state_part(y, static)
    xp, dx, u = system.projected_field(t, x, apply, control)
    return _replace_state(y, xp, static), _rate(static, system, t, xp, u, dx)


@functools.lru_cache(maxsize=64)
def _entry_field(static: _Static):
    """``_entry_body`` as a nested jit (as ``_vector_field``)."""
    return eqx.filter_jit(functools.partial(_entry_body, static))


@functools.lru_cache(maxsize=64)
def _split_vector_field(static: _Static):
    """The vector field of a split projected solve: ``_entry_field`` without the
    projection (``apply`` a traced False, so that the stage scan's call and this one
    share one trace; XLA drops the projection here)."""
    entry = _entry_field(static)

    def vf(t, y, args):
        return entry(t, y, args, jnp.zeros((), bool))[1]

    return vf


@eqx.filter_jit
def _project_state(system, t, x):
    """``system.project(t, x)`` as a nested jit, for the same reason as ``_vector_field``:
    diffrax traces a solver's step several times (shape probes, the loop body), and the
    saved states are projected too; a nested jit traces the projection once per system
    structure and state shape, and XLA inlines it as before."""
    return system.project(t, x)


@eqx.filter_jit
def _project_positions(system, t, x):
    """``system.project_positions(t, x)`` as a nested jit (see ``_project_state``)."""
    return system.project_positions(t, x)


def _state_part(y, static: _Static):
    """The system's state in the solver's state ``y`` (which may carry the work)."""
    if static.flat_work:
        return y[:-1]
    return y[0] if static.track_work else y


def _replace_state(y, x, static: _Static):
    """The solver's state ``y`` with its system state replaced by ``x`` (the work kept)."""
    if static.flat_work:
        return jnp.concatenate([x, y[-1:]])
    return (x, y[1]) if static.track_work else x


def _rate(static: _Static, system, t, x, u, dx):
    """The solver's rate at the state x: dx, and the power of the input u where the
    work is tracked."""
    if static.flat_work:
        return jnp.concatenate([dx, jnp.reshape(system.power(t, x, u), (1,)).astype(dx.dtype)])
    if static.track_work:
        return dx, system.power(t, x, u)
    return dx


def _with_work(y, static: _Static):
    """(state, work) from the solver's state (for saved values and the final state)."""
    if static.flat_work:
        return y[:-1], y[-1]
    return y


def _diagnostics(system, control, x0, t0, ts_saved, x_safe, valid, work, track):
    """Invariants, constraint residuals and controls at the saved points."""
    invariants = dict(jax.vmap(system.invariants)(x_safe))
    if control is None:
        invariants.update(jax.vmap(system.free_invariants)(x_safe))
    if system.energy(x0) is not None and (track or control is None):
        energies = jax.vmap(system.energy)(x_safe)
        if track:
            invariants["energy - work"] = energies - jnp.where(valid, work, 0.0)
        else:
            invariants["energy"] = energies
    cons = jax.vmap(system.constraints)(ts_saved, x_safe) if system.constraints(t0, x0) else {}
    us = None
    if control is not None:
        us = jax.vmap(control)(jnp.where(valid, ts_saved, t0), x_safe)
    return invariants, cons, us


def _diagnose(system, control, x0, t0, ts_saved, xs, t_final, work, track):
    """Diagnostics on the saved points (entries past t_final are masked out):
    invariants, their drift, constraint residuals, controls."""
    valid = ts_saved <= t_final
    x_safe = jtu.tree_map(
        lambda a, a0: jnp.where(valid.reshape((-1,) + (1,) * (a.ndim - 1)), a, a0[None]), xs, x0)
    invariants, cons, us = _diagnostics(system, control, x0, t0, ts_saved, x_safe, valid, work, track)
    drift = {k: jnp.max(jnp.abs(v - v[0])) for k, v in invariants.items()}
    return invariants, drift, {k: _max_abs(v) for k, v in cons.items()}, us


def _diagnose_placeholders(system, control, x0, t0, ts, track, project, diagnostics):
    """Arguments of the eager path's second program (``_saved_eager``) with zeros for the
    solution."""
    n = ts.shape[0]
    # (host zeros put on the device: an eager jnp.zeros is a program compiled per shape)
    zeros = lambda shape, dtype: jax.device_put(np.zeros(shape, dtype))  # noqa: E731
    xs = jtu.tree_map(lambda a: zeros((n,) + jnp.shape(a), a.dtype), x0)
    x_end = jtu.tree_map(lambda a: zeros(jnp.shape(a), a.dtype), x0)
    work = zeros(n, float) if track else None
    return system, control, x0, t0, ts, xs, jnp.asarray(t0), x_end, work, track, project, diagnostics


def _warm_diagnostics(system, control, x0, t0, ts, track, project, diagnostics):
    """Compile the eager path's second program (run on zeros of the right shapes), so
    that a first simulate() compiles it while _solve compiles."""
    jax.block_until_ready(_programs.call("diagnose", _saved_eager,
                                         _diagnose_placeholders(system, control, x0, t0, ts, track, project,
                                                                diagnostics),
                                         error_mode="off", compiler_options=_programs.QUICK_OPTIONS))


_WARM_POOL = None


def _warm_pool():
    global _WARM_POOL
    if _WARM_POOL is None:
        from concurrent.futures import ThreadPoolExecutor

        _WARM_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="nhjax-compile")
    return _WARM_POOL


def _build_problem(system, control, x0, t0, t1, ts, solver, controller, dt0, static: _Static, show=False):
    """The diffrax problem of one solve: term, solver (projected if asked), controller,
    guard event, what to save. Returns (problem, y0); y0 carries the work if tracked."""
    track = static.track_work
    spaces = system.spaces
    if static.flat_work:
        y0 = jnp.concatenate([x0, jnp.zeros((1,), x0.dtype)])
    elif track:
        y0 = (x0, jnp.zeros((), x0.dtype if hasattr(x0, "dtype") else float))
        spaces = (spaces, Euclidean())
    else:
        y0 = x0
    split = static.project_steps and system.splits_projection
    term = LieODETerm(_split_vector_field(static) if split else _vector_field(static), spaces)
    if static.project_steps:

        def on_state(fn):
            def project(t, y, args):
                return _replace_state(y, fn(args[0], t, _state_part(y, static)), static)

            return project

        # split: positions after each step, velocities with the next step's first stage
        # (ProjectedSolver; where the solver cannot take that, the whole projection)
        solver = ProjectedSolver(solver, on_state(_project_state),
                                 entry=_entry_field(static) if split else None,
                                 project_positions=on_state(_project_positions) if split else None)
        # the saved states (dense output between steps) are projected too, after the
        # loop, all at once (_finish): one copy of the projection in the program, and
        # vectorized, instead of one in the save loop and one at an event
    save_fn = _save_state
    if static.flat_work:
        save_fn = lambda t, y, args: _with_work(_save_state(t, y, args), static)  # noqa: E731
    if static.ends_only:  # saveat=2: no interpolation inside the loop
        sub = diffrax.SubSaveAt(t0=True, t1=True, fn=save_fn)
    else:
        sub = diffrax.SubSaveAt(ts=ts, fn=save_fn)

    event = None
    if static.guard_names:
        # One scalar event: the smallest guard. Which guard fired is read off the
        # final state afterwards (the one closest to zero).
        def cond(t, y, args, **kwargs):
            g = args[0].guards(_state_part(y, static))
            return jnp.min(jnp.stack([g[n] for n in static.guard_names]))

        event = diffrax.Event(
            # guards only decrease through zero (they start positive and the solve stops
            # there), so the direction is known: flip=True also keeps vmapped solves valid
            cond_fn=cond, root_finder=optx.Bisection(rtol=1e-13, atol=1e-13, flip=True)
        )
    progress_meter = diffrax.NoProgressMeter()
    if static.progress:  # the bar is in the program; `show` (an array) switches it on
        progress_meter = SimulatedTimeMeter(jnp.asarray(show, bool), t0, t1)
    problem = _Problem(term=term, solver=solver, controller=controller, event=event, sub=sub,
                       progress_meter=progress_meter, t0=t0, t1=t1, dt0=dt0,
                       max_steps=static.max_steps)
    return problem, y0


def _project_saved(system, x0, t0, ts_saved, xs, t_end, x_end):
    """A projected solve's saved states (dense output between projected steps) and its
    final state ``x_end`` (at ``t_end``; a split projection leaves its velocities to the
    step that would follow) onto the constraints; rows never reached (t = inf) stay as
    they are. Returns (xs, x_end)."""

    def onto(t, x):
        reached = jnp.isfinite(t)
        # unreached rows are projected from x0 (finite: no NaN in a derivative) and dropped
        safe = jtu.tree_map(lambda a, b: jnp.where(reached, a, b), x, x0)
        p = _project_state(system, jnp.where(reached, t, t0), safe)
        return jtu.tree_map(lambda a, b: jnp.where(reached, a, b), p, x)

    # a loop over the rows, not vmap: the batched projection (batched Jacobians and
    # LAPACK solves) is a second, larger program beside the step's own projection;
    # one row at a time reuses the step's projection, a smaller program to compile for
    # the scenes with constraints (BallInCone, ThreeCylinders), at the price of a slightly
    # longer run (benchmarks/compile_times.py measures both)
    rows = (jnp.concatenate([ts_saved, jnp.reshape(t_end, (1,)).astype(ts_saved.dtype)]),
            jtu.tree_map(lambda a, b: jnp.concatenate([a, b[None]]), xs, x_end))
    out = jax.lax.map(lambda row: onto(*row), rows)
    return jtu.tree_map(lambda a: a[:-1], out), jtu.tree_map(lambda a: a[-1], out)


def _finish(system, control, x0, t0, sol, static: _Static):
    """The Trajectory of one solve from its raw output ``sol`` (``_Problem.run``'s dict)."""
    track = static.track_work
    ts_saved, ys, t_final = sol["ts"], sol["ys"], sol["t_final"]
    x_end = _state_part(sol["y_end"], static)
    if track:
        xs, work = ys
    else:
        xs, work = ys, None
    if static.project_steps and static.project_saved:
        xs, x_end = _project_saved(system, x0, t0, ts_saved, xs, t_final, x_end)

    invariants, drift, constraint_drift, us = {}, {}, {}, None
    if static.diagnostics:
        invariants, drift, constraint_drift, us = _diagnose(
            system, control, x0, t0, ts_saved, xs, t_final, work, track)
    return Trajectory(
        ts=ts_saved,
        xs=xs,
        us=us,
        work=work,
        invariants=invariants,
        invariant_drift=drift,
        constraint_drift=constraint_drift,
        num_steps=sol["num_steps"],
        num_accepted_steps=sol["num_accepted_steps"],
        num_rejected_steps=sol["num_rejected_steps"],
        t_final=t_final,
        x_end=x_end,
        result=sol["result"],
        event_mask=sol["event_mask"],
        state_names=static.state_names,
    )


#: Traces of the solve program (tests count them: a solve with new values of the same
#: structure must not trace again).
TRACES = collections.Counter()


def _solve_impl(system, control, x0, t0, t1, ts, solver, controller, adjoint, dt0, static: _Static, show=False):
    TRACES["solve"] += 1
    if (static.one_function and not static.progress
            and isinstance(adjoint, (diffrax.RecursiveCheckpointAdjoint, DiscreteAdjoint))):
        # one compiled function instead of a kernel sequence (see one_function); not for
        # adjoints that support forward mode, which a custom VJP would block
        return as_one_function(_solve_body, system, control, x0, t0, t1, ts, solver, controller, adjoint, dt0,
                               static, show)
    return _solve_body(system, control, x0, t0, t1, ts, solver, controller, adjoint, dt0, static, show)


def _solve_body(system, control, x0, t0, t1, ts, solver, controller, adjoint, dt0, static: _Static, show=False):
    problem, y0 = _build_problem(system, control, x0, t0, t1, ts, solver, controller, dt0, static, show)
    with _error_checks(static.runtime_checks):
        if isinstance(adjoint, DiscreteAdjoint):
            sol = discrete_solve((y0, (system, control)), problem, adjoint)
        else:
            sol, _ = problem.run(y0, (system, control), record=False, adjoint=adjoint)
    return _finish(system, control, x0, t0, sol, static)


_solve = eqx.filter_jit(_solve_impl)

#: Trajectory fields that the cached program returns (the static ones come from _Static).
_DYNAMIC_FIELDS = ("ts", "xs", "us", "work", "invariants", "invariant_drift", "constraint_drift", "num_steps",
                   "num_accepted_steps", "num_rejected_steps", "t_final", "x_end", "event_mask")


def _to_plain(traj: Trajectory) -> dict:
    """A Trajectory's arrays in builtin containers (what the program cache stores)."""
    out = {k: getattr(traj, k) for k in _DYNAMIC_FIELDS}
    out["result"] = traj.result._value
    return out


def _from_plain(out: dict, state_names, cls=None) -> Trajectory:
    out = dict(out)
    result = eqx.tree_at(lambda r: r._value, diffrax.RESULTS.successful, out.pop("result"))
    return (cls or Trajectory)(**out, result=result, state_names=state_names)


def _solve_plain(*args):
    return _to_plain(_solve_impl(*args))


def _solve_cached(*args, adjoint_given=True, on_guard="raise"):
    """A solve on known values (concrete, or under ``jax.grad``/``jax.jvp`` of concrete
    values) through nhjax's stored programs (``nhjax._primitive``): a new process whose
    programs are on disk does not trace them again, nor their derivatives."""
    static = args[10]
    if static.progress:  # a host callback in the loop: jax.export cannot keep that program
        return _solve(*args)
    mode = None if static.runtime_checks else "off"  # _solve_impl traces with checks off
    return _from_plain(_primitive.call("simulate", _solve_plain, args, error_mode=mode,
                                       options=_programs.SOLVE_OPTIONS, forward=_forward_variant,
                                       reverse=functools.partial(_reverse_variant, adjoint_given, on_guard),
                                       variant_key=(adjoint_given, on_guard),
                                       # the default adjoint: reverse mode in up to 4 numbers by
                                       # forward mode (as DiscreteAdjoint's "tangents"), with
                                       # jax.jacfwd's program
                                       max_tangents=0 if adjoint_given else DiscreteAdjoint().max_tangents,
                                       fallback=lambda *a: _to_plain(_solve(*a))),
                       static.state_names)


def _forward_variant(args):
    """The solve set up for forward mode (jax.jvp, jax.jacfwd): diffrax's ForwardMode,
    whose plain while loop JAX pushes tangents through (the adjoints differentiate in
    reverse mode only). The same steps and values."""
    return (*args[:8], diffrax.ForwardMode(), *args[9:])


def _reverse_variant(adjoint_given, on_guard, args, nz):
    """The solve set up for reverse mode (jax.grad, jax.vjp, jax.jacrev). With the default
    adjoint: ``DiscreteAdjoint`` (the exact derivative of the same discrete solution at a
    few forward solves, where differentiating diffrax's loop costs a hundred or more)
    whenever it applies: an explicit solver, times and save times not differentiated, no
    chart guard that may stop the solve (whose event time it holds fixed)."""
    adjoint, solver, static = args[8], args[6], args[10]
    static = dataclasses.replace(static, one_function=False)
    keep = (*args[:10], static, *args[11:])
    if adjoint_given or not isinstance(adjoint, diffrax.RecursiveCheckpointAdjoint):
        return keep
    times = any(jtu.tree_leaves((nz[3], nz[4], nz[5], nz[9])))
    if times or not _is_explicit(solver) or (on_guard == "stop" and static.guard_names):
        return keep
    return (*args[:8], DiscreteAdjoint(max_steps=static.max_steps), args[9], static, *args[11:])


def _with_diagnostics(traj, system, control, x0, t0a, static):
    """``traj`` (a solve without them) with its saved states projected (a projected solve)
    and its diagnostics, from the second program (``_saved_eager``)."""
    project_saved = static.project_steps
    if not (project_saved or static.diagnostics):
        return traj
    xs, x_end, diag = _primitive.call(
        "diagnose", _saved_eager,
        (system, control, x0, t0a, traj.ts, traj.xs, traj.t_final, traj.x_end, traj.work, static.track_work,
         project_saved, static.diagnostics), error_mode="off", options=_programs.QUICK_OPTIONS,
        lazy=not project_saved)  # (a projection's states are differentiated: the loss reads them)
    if project_saved:  # (else the same arrays: the solve's stay, for a shorter derivative)
        traj = dataclasses.replace(traj, xs=xs, x_end=x_end)
    if static.diagnostics:
        invariants, drift, cons, us = diag
        traj = dataclasses.replace(traj, invariants=invariants, invariant_drift=drift, constraint_drift=cons, us=us)
    return traj


def _saved_eager(system, control, x0, t0, ts, xs, t_final, x_end, work, track, project, diagnostics):
    """An eager call's second program, run on the solve's saved states: their
    projection (``project``: a projected solve) and the diagnostics, traced without
    equinox's runtime checks (eager calls: checked states), compiled with XLA's quick
    settings. Returns (xs, x_end, diagnostics or None). The saved states' projection is a
    second copy of the step's: here it compiles beside the solve's program, and in
    less time, for a slower run of that loop over the saved states."""
    with _error_checks(False):
        if project:
            xs, x_end = _project_saved(system, x0, t0, ts, xs, t_final, x_end)
        return xs, x_end, (_diagnose(system, control, x0, t0, ts, xs, t_final, work, track) if diagnostics
                           else None)


_error_checks = _programs.error_checks


def _save_times(saveat, t0, t1, runtime_errors=False):
    """Save times from ``saveat`` (already checked by the entry point's check_saveat);
    traced times are checked by a runtime error if ``runtime_errors``."""
    if saveat is None:
        saveat = 101
    if isinstance(saveat, (int, np.integer)):
        if _is_traced(t0, t1):
            return jnp.linspace(t0, t1, int(saveat))
        # (to_device: an eager jnp operation would be one more program in a new process)
        return to_device(np.linspace(float(t0), float(t1), int(saveat)))
    ts = to_device(saveat)
    if _is_traced(ts, t0, t1):
        if not runtime_errors:
            return ts
        # a runtime error here, outside the solve (which runs without diffrax's own
        # checks: see simulate)
        bad = jnp.any(ts[1:] < ts[:-1]) | (ts[0] < t0) | (ts[-1] > t1)
        return error_if(ts, bad, "nhjax.simulate: saveat times must be sorted and lie in [t0, t1]")
    tsn = np.asarray(ts)
    if np.any(np.diff(tsn) < 0) or tsn[0] < float(t0) - 1e-12 or tsn[-1] > float(t1) + 1e-12:
        raise TimeSpanError(
            f"simulate: saveat times must be sorted and lie in [t0, t1] = [{float(t0)}, {float(t1)}]; "
            f"got {tsn.size} times from {tsn.min():.6g} to {tsn.max():.6g}"
        )
    return ts


#: member_report compiled (one program per system structure, control and projection flag)
_member_report = eqx.filter_jit(member_report)


@dataclasses.dataclass(frozen=True, eq=False)
class _Call:
    """One ``simulate()`` call after the checks of its arguments (``_checked``).

    ``traced``: values unknown (under the user's ``jax.jit`` or ``jax.vmap``): the
    checks of x0's values become runtime errors and the solve is part of the caller's
    program. Otherwise every value is known (concrete, or under ``jax.grad`` /
    ``jax.jvp`` of concrete values: ``differentiated``), the named errors are raised
    before the solve runs, and the programs come from the program cache when
    ``stored`` (``NHJAX_CACHE_DIR`` on)."""

    system: Any
    control: Any
    x0: Any
    t0: Any  # as given (messages, the traced time span's check)
    t1: Any
    t0a: Any  # on the device
    t1a: Any
    differentiated: bool
    traced: bool
    stored: bool
    project: bool
    constraint_tol: Any
    on_guard: str


@dataclasses.dataclass(frozen=True, eq=False)
class _Plan:
    """The static configuration of one solve (``_planned``): what its program is
    traced for. ``inline``: traced into the caller's program as it stands (no stored
    program: the cache off, a progress bar's host callback, or inside a stored
    program's own trace)."""

    ts: Any
    solver: Any
    controller: Any
    adjoint: Any
    dt0: Any
    static: _Static
    show: Any
    adjoint_given: bool
    inline: bool


def _checked(system, x0, t1, *, t0, control, saveat, rtol, atol, dt0, max_steps, adjoint, project,
             constraint_tol, on_guard) -> _Call:
    """Stage 1 of ``simulate``: every check that the arguments' types, shapes and known
    values answer on the host (``nhjax._validate``'s named errors), once, before any
    program is traced; and whether the values are known."""
    choice("on_guard", on_guard, ("raise", "stop"), owner="simulate")
    if not isinstance(system, AbstractSystem):
        raise ParameterError(
            f"simulate: system must be an nhjax system (nhjax.mechanics.AbstractSystem, e.g. a scene or a "
            f"Lagrangian), got {type(system).__name__}", "system", system)
    solver_settings(rtol=rtol, atol=atol, dt0=dt0, max_steps=max_steps, constraint_tol=constraint_tol)
    # a traced time span is checked with the solve's result (one runtime check: see
    # _runtime_checks)
    t0, t1 = time_span(t0, t1, owner="simulate", runtime=False)
    check_saveat(saveat, t0, t1, owner="simulate")
    # traced tolerances or saved times (e.g. jax.jit over rtol) also make the whole call traced
    numbers = (x0, t0, t1, system, control, rtol, atol, dt0, None if isinstance(saveat, int) else saveat)
    differentiated = _is_traced(numbers)
    # under jax.grad / jax.jvp of concrete values the values are known: checked as in an
    # eager call, and the solve and its derivatives are stored programs (nhjax._primitive);
    # only under jit or vmap is the call traced
    traced = differentiated and not _primitive.has_values(numbers)
    x0 = as_state(system, x0, owner="simulate")
    simulate_memory(system, x0, saveat, stores_steps=differentiated and isinstance(adjoint, DiscreteAdjoint),
                    max_steps=max_steps if max_steps is not None else getattr(adjoint, "max_steps", None))
    check_state(system, x0, owner="simulate")
    check_control(system, control, owner="simulate")
    return _Call(system, control, x0, t0, t1, to_device(t0), to_device(t1), differentiated, traced,
                 _programs.directory() is not None, bool(project), constraint_tol, on_guard)


def _structure(call: _Call):
    """(guard names, whether to project after each step): what the solve's program needs
    to know of the system before x0's values are checked. Known values with the program
    cache on: from the output structure of the checks' program (``member_report``), which
    is traced here (a control's shape errors raise here) and compiled in the background,
    or loaded from disk without a trace; otherwise from shapes (``_check_structure``)."""
    if call.stored and not call.traced:
        args = _primitive.concrete((call.system, call.control, call.x0, call.t0a, call.project))
        _programs.prepare("report", member_report, args, compiler_options=_programs.QUICK_OPTIONS)
        out_def = _programs.output_structure("report", member_report, args, compiler_options=_programs.QUICK_OPTIONS)
        if out_def is not None:
            _, report = jtu.tree_unflatten(out_def, [None] * out_def.num_leaves)  # the report's names
            return tuple(report["guards"]), _drifting_constraints(report["constraints"])
    return _check_structure(call.system, call.x0, call.t0a)


def _checked_values(system, control, x0, t0, constraint_tol, project, t0_given):
    """Stage 3's first program: the checks of x0's values (finite, on its group and
    constraints, inside its chart: ``member_report``). Returns (x0, projected if
    ``project``; the report).

    Known values: the report's program runs (from the program cache) and the named
    errors of ``nhjax.errors`` are raised for what it found, before the solve runs; a
    differentiated x0 keeps its derivative (with ``project``, the projection is
    differentiated). Unknown values (under jit or vmap): the same words as runtime
    errors. ``t0`` on the device; ``t0_given`` as the user gave it (messages)."""
    args = (system, control, x0, t0, project)
    if not _primitive.has_values(args):
        x0p, report = _member_report(*args)
        return runtime_checks(x0p, report, constraint_tol=constraint_tol, project=project), report
    known = _primitive.concrete(args)
    x0p, report = _programs.call("report", member_report, known, fallback=_member_report,
                                 compiler_options=_programs.QUICK_OPTIONS)
    raise_for_report(report, known[0], x0=known[2], constraint_tol=constraint_tol, project=project,
                     t0=_primitive.concrete(t0_given))
    if _is_traced(args):  # under jax.grad / jax.jvp: the derivative flows through x0
        x0p = _primitive.call("report", member_report, args, options=_programs.QUICK_OPTIONS,
                              fallback=_member_report)[0] if project else x0
    return x0p, report


def _check_inputs(system, control, x0, t0, constraint_tol, project):
    """The checks of x0 and the control that ``simulate`` makes, host-side and of values,
    on their own: returns (x0, maybe projected; guard names; whether the system has
    constraints to project onto after each step)."""
    check_state(system, x0, owner="simulate")
    check_control(system, control, owner="simulate")
    x0p, report = _checked_values(system, control, x0, to_device(t0), constraint_tol, project, t0)
    return x0p, tuple(report["guards"]), _drifting_constraints(report["constraints"])


def _planned(call: _Call, *, saveat, solver, rtol, atol, dt0, max_steps, stepsize_controller, jump_ts,
             adjoint, project_steps, track_work, progress, diagnostics) -> _Plan:
    """Stage 2 of ``simulate``: the static configuration of the solve (``_configure``,
    shared with ``simulate_batch``) and how its program runs."""
    guard_names, constrained = _structure(call)
    if project_steps is None:
        project_steps = constrained
    adjoint_given = adjoint is not None
    solver, controller, adjoint, dt0, static, ts = _configure(
        call.system, call.control, call.x0, call.t0, call.t1, guard_names, saveat=saveat, solver=solver,
        rtol=rtol, atol=atol, dt0=dt0, max_steps=max_steps, stepsize_controller=stepsize_controller,
        jump_ts=jump_ts, adjoint=adjoint, project_steps=project_steps, track_work=track_work,
        progress=bool(progress), diagnostics=diagnostics, runtime_errors=True, single=True,
    )
    # diffrax's own runtime checks (save times, dt0) stay out of the solve's program:
    # _configure made them (eager: raised; traced: runtime errors outside the solve), so
    # the solve has no host callback and compiles into one function (see one_function)
    static = dataclasses.replace(static, runtime_checks=False)
    # The progress bar is a host callback in the loop: a program with it is never kept in
    # JAX's persistent cache and XLA does not compile its small loops as one function,
    # so it is compiled in only when asked for (once per structure and process).
    inline = call.traced and (static.progress or not call.stored or _programs.tracing_stored())
    if inline:
        static = dataclasses.replace(static, error_mode=_programs.error_mode())
    return _Plan(ts, solver, controller, adjoint, dt0, static, np.asarray(bool(progress)), adjoint_given, inline)


def _run(call: _Call, plan: _Plan) -> Trajectory:
    """Stage 3 of ``simulate``: its programs, in order: the checks of x0's values
    (``_checked_values``), the solve, and the diagnostics with a projected solve's
    projection of its saved states (``_saved_eager``, a second program run on the
    solution). Known values with the program cache on: every program is traced (or
    loaded) first, one after the other (tracing holds the GIL), and compiled in the
    background as soon as it is traced (XLA releases it); then the checks run, and
    raise, before the solve runs. With the cache off the diagnostics compile in a
    thread while the solve compiles."""
    static = plan.static
    core = dataclasses.replace(static, diagnostics=False, project_saved=False)
    second = static.project_steps or static.diagnostics

    def solve_args(x0):
        return (call.system, call.control, x0, call.t0a, call.t1a, plan.ts, plan.solver, plan.controller,
                plan.adjoint, plan.dt0)

    def diagnosed(traj, x0):
        return _with_diagnostics(traj, call.system, call.control, x0, call.t0a, static)

    def cached(x0):
        return _solve_cached(*solve_args(x0), core, plan.show, adjoint_given=plan.adjoint_given,
                             on_guard=call.on_guard)

    def checked():
        return _checked_values(call.system, call.control, call.x0, call.t0a, call.constraint_tol, call.project,
                               call.t0)[0]

    if call.traced:
        x0 = checked()
        if plan.inline:
            if under_differentiation(solve_args(x0)):
                # differentiated in an outer trace: traced here, once. A nested jit would
                # trace the primal solve first and then linearize it; the one-function
                # wrapper would trace it once more (see one_function)
                return _solve_impl(*solve_args(x0), dataclasses.replace(static, one_function=False), plan.show)
            return _solve(*solve_args(x0), static, plan.show)
        # the stored programs, inlined by XLA (nothing of the solve is traced)
        return diagnosed(cached(x0), x0)
    if call.stored:
        if not static.progress:
            _programs.prepare("simulate", _solve_plain, (*solve_args(call.x0), core, plan.show),
                              error_mode="off", compiler_options=_programs.SOLVE_OPTIONS)
        if second:
            _programs.prepare("diagnose", _saved_eager,
                              _diagnose_placeholders(call.system, call.control, call.x0, call.t0a, plan.ts,
                                                     static.track_work, static.project_steps, static.diagnostics),
                              error_mode="off", compiler_options=_programs.QUICK_OPTIONS)
    x0 = checked()
    warm = None
    if second and not (call.stored or call.differentiated):  # compiled in a thread while the solve compiles
        # (not under jax.grad / jax.jvp: their tracers cannot enter another thread, and the
        # diagnostics are then differentiated as part of the caller's trace, not this program)
        warm = _warm_pool().submit(_warm_diagnostics, call.system, call.control, x0, call.t0a, plan.ts,
                                   static.track_work, static.project_steps, static.diagnostics)
    traj = cached(x0)
    if warm is not None:
        warm.result()
    return diagnosed(traj, x0)


def _wrapped(call: _Call, plan: _Plan, traj: Trajectory) -> Trajectory:
    """Stage 4 of ``simulate``: the solve's outcome read. Known values: a chart guard's
    stop or a failed solve raises (``ChartSingularityError``, ``IntegrationError``, with
    the trajectory up to there) or truncates (``on_guard="stop"``); traced: the same
    as one runtime check on the outputs users read."""
    if call.traced:
        span = time_span_check(call.t0, call.t1, owner="simulate") if _is_traced(call.t0, call.t1) else None
        return _runtime_checks(traj, plan.static, call.on_guard, span)
    return _eager_checks(traj, call.system, call.control, plan.static, call.on_guard)


def _configure(system, control, x0, t0, t1, guard_names, *, saveat, solver, rtol, atol, dt0,
               max_steps, stepsize_controller, jump_ts, adjoint, project_steps, track_work, progress,
               diagnostics=True, runtime_errors=False, single=False):
    """Resolve solver, step-size controller, adjoint, save times and the static
    configuration of a solve (shared by simulate and simulate_batch). ``runtime_errors``:
    traced save times and dt0 get the checks diffrax would make, as runtime errors
    (simulate's solve runs without diffrax's own). ``single``: one trajectory (the
    default solver then evaluates its first stage inside its stage scan; see
    RKMK45's first_stage_in_scan)."""
    spaces = system.spaces
    euclid = _all_euclidean(spaces)
    if jump_ts is None and control is not None and hasattr(control, "breakpoints"):
        jump_ts = control.breakpoints
    if solver is None:
        # Dormand-Prince 5(4) as a fused nhjax solver (on vector states RKMK45 is plain
        # DP5); its stages run as a scan for large vector fields.
        # (a projection after each step invalidates the stored FSAL stage: jumps=True
        # lets ProjectedSolver ask for it to be recomputed)
        solver = RKMK45(
            scan_stages=system.large_vector_field,
            jumps=jump_ts is not None or bool(project_steps),
            first_stage_in_scan=single,
        )
    elif not euclid and not isinstance(solver, _AbstractRKMK):
        raise SystemKindError(
            f"{type(system).__name__} has group-valued state parts; "
            f"{type(solver).__name__} would integrate them in ambient coordinates and "
            "drift off the group. Use nhjax.RKMK45() or nhjax.RKMK87() (adaptive) or nhjax.RKMK4() (fixed step)."
        )
    if track_work is None:
        track_work = control is not None and _defines_power(system)
    flat_work = bool(track_work) and euclid and isinstance(x0, (jax.Array, np.ndarray)) and jnp.ndim(x0) == 1
    if stepsize_controller is None:
        if isinstance(solver, diffrax.AbstractAdaptiveSolver):
            # Tolerances as arrays: changing them does not recompile. The work of the
            # inputs, when tracked, stays out of the error norm: the steps (and so the
            # states) are those of the same solve without it.
            stepsize_controller = diffrax.PIDController(
                rtol=to_device(rtol), atol=to_device(atol), jump_ts=jump_ts,
                norm=(_flat_state_norm if flat_work else _state_norm) if track_work else optx.rms_norm,
            )
        else:
            if dt0 is None:
                raise ValueError(
                    f"{type(solver).__name__} is a fixed-step solver: pass dt0 (the step)"
                )
            stepsize_controller = diffrax.ConstantStepSize()
    if adjoint is None:
        adjoint = diffrax.RecursiveCheckpointAdjoint()
    if isinstance(adjoint, DiscreteAdjoint):
        if max_steps is None:
            max_steps = adjoint.max_steps
        if not _is_explicit(solver):
            raise SystemKindError(
                f"DiscreteAdjoint differentiates explicit Runge-Kutta steps; {type(solver).__name__} "
                "is not one (use diffrax.RecursiveCheckpointAdjoint())"
            )
    elif max_steps is None:
        max_steps = 100_000

    static = _Static(
        track_work=bool(track_work),
        guard_names=guard_names,
        max_steps=int(max_steps),
        progress=bool(progress),
        state_names=tuple(system.state_names),
        project_steps=bool(project_steps),
        ends_only=isinstance(saveat, (int, np.integer)) and int(saveat) == 2,
        diagnostics=bool(diagnostics),
        flat_work=flat_work,
    )
    ts = _save_times(saveat, t0, t1, runtime_errors)
    if dt0 is not None:
        traced_dt0 = _is_traced(dt0)
        dt0 = jnp.asarray(dt0, float)
        if runtime_errors and traced_dt0:  # concrete values: checked by solver_settings
            dt0 = error_if(dt0, ~(dt0 > 0), "nhjax.simulate: dt0 must be positive (nhjax integrates forward in time)")
    return solver, stepsize_controller, adjoint, dt0, static, ts


def simulate(
    system,
    x0,
    t1,
    *,
    t0=0.0,
    control=None,
    saveat=None,
    solver=None,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    dt0=None,
    max_steps: int | None = None,
    stepsize_controller=None,
    jump_ts=None,
    adjoint=None,
    project: bool = False,
    project_steps: bool | None = None,
    constraint_tol: float = 1e-8,
    on_guard: str = "raise",
    track_work: bool | None = None,
    progress: bool = False,
    diagnostics: bool = True,
) -> Trajectory:
    """Integrate ``system`` from ``x0`` at ``t0`` to ``t1``.

    Parameters
    ----------
    system : an ``nhjax.mechanics.AbstractSystem`` (a scene, a Lagrangian, ...).
    x0 : initial state (flat array for most scenes; a pytree with group parts for
        Lie-group states).
    control : None, or a callable ``control(t, x) -> u`` with ``system.control_dim``
        entries. Equinox modules work too, and their arrays are differentiable
        parameters. A control with a ``breakpoints`` attribute (times where it
        is not smooth) gets steps placed exactly there.
    saveat : int (that many equally spaced times, default 101) or 1-D array of times.
    solver : a diffrax solver; default ``nhjax.RKMK45()``: Dormand-Prince 5(4),
        which on group-valued state parts is the Munthe-Kaas method (with its
        stages in a lax.scan when the system declares a large vector field).
        ``nhjax.RKMK87()`` (Prince-Dormand 8(7), Munthe-Kaas on group-valued parts,
        7th-order dense output) takes far fewer steps at tight tolerances (rtol,
        atol <= 1e-9); pass ``RKMK87(scan_stages=True)`` for large vector fields.
    rtol, atol : tolerances of the default ``diffrax.PIDController``.
    dt0 : initial step; required (and the step) for fixed-step solvers.
    max_steps : budget of solver steps; exhausting it raises ``IntegrationError``.
        Default 100 000, or ``DiscreteAdjoint.max_steps`` (4096) with that adjoint,
        whose differentiated solves store max_steps states.
    jump_ts : times at which the vector field is not smooth (steps land there).
    adjoint : how reverse mode (``jax.grad``, ``jax.vjp``, ``jax.jacrev``) differentiates
        the solve: ``nhjax.DiscreteAdjoint()`` (the discrete adjoint of the
        Runge-Kutta steps: the same gradient as differentiating diffrax's loop, at a
        few forward solves; explicit solvers only), or a diffrax adjoint. Default
        (None): ``DiscreteAdjoint`` wherever it applies (an explicit solver, t0, t1,
        saveat and dt0 not differentiated, no chart guard that may stop the solve),
        else ``diffrax.RecursiveCheckpointAdjoint()``. Forward mode (``jax.jvp``,
        ``jax.jacfwd``) works whatever the adjoint: it runs the solve set up with
        ``diffrax.ForwardMode()``, the same steps and values. This holds for calls on
        known values, eager or under ``jax.grad`` and the like (see below); under
        ``jax.jit`` or ``jax.vmap`` the solve is traced with the adjoint as given
        (default ``RecursiveCheckpointAdjoint``; pass ``diffrax.ForwardMode()`` for
        forward mode there), and so it is with nhjax's program cache off
        (``NHJAX_PROGRAM_CACHE=0``), where every call is traced as usual.
    project : project x0 onto the constraint manifold instead of rejecting it.
    project_steps : project the state onto the constraint manifold after every
        step (``ProjectedSolver``), and the saved and final states too; removes the
        drift of the index-reduced equations at the cost of a projection per step
        (for a ``ConstrainedLagrangian``: positions after the step, velocities
        with the next step's first stage, which has M and A there; see
        ``splits_projection``). Default:
        on when the system has position (holonomic) or other non-velocity
        constraints (e.g. unit quaternions), off for purely nonholonomic ones.
    constraint_tol : largest constraint residual accepted in x0.
    on_guard : "raise" (ChartSingularityError) or "stop" (return the trajectory
        up to where a chart guard crossed zero; ``traj.guard`` names it).
    track_work : integrate the work of the inputs and report energy - work (default:
        whenever a control is given and the system defines power()). The work stays
        out of the step-size control, so the states are those of the solve without it.
    progress : show a progress bar over simulated time (tqdm; in notebooks a widget).
        The bar is a host callback in the solve's loop, so the first call with it
        compiles a second program (kept for later calls in the process; JAX's
        persistent cache does not keep programs with host callbacks).
    diagnostics : compute invariants, constraint residuals and the controls at the
        saved times (False: a smaller program, e.g. inside an optimizer).

    Notes
    -----
    What the extras cost (``benchmarks/batch_throughput.py`` measures them):

    * saved times: one dense-output evaluation (a polynomial, and an exponential on
      group parts) per saved time, inside the step that passes it; ``saveat=2`` keeps
      t0 and t1 and interpolates nothing. The solve, with its save buffers, is
      compiled as one function (``nhjax.integrate.one_function``), so a longer save
      buffer does not add a per-call cost of XLA's kernel scheduling.
    * ``track_work``: one more integrated component (the power of the inputs), which
      stays out of the error norm, so the steps are those of the solve without it.
    * ``diagnostics``: the invariants, constraint residuals and controls evaluated
      at every saved time after the solve (vectorized): proportional to the saved
      times, and a second, small program for eager calls (compiled, like the input
      checks, with XLA's quick settings: ``nhjax._programs.QUICK_OPTIONS``).
    * a projected solve (``project_steps``) also projects its saved states, one at a
      time after the loop (a loop, not vmap: a smaller program). An eager call does
      that in its diagnostics program, with XLA's quick settings: it compiles beside
      the solve and in less time, and runs slower than in the solve's program would.
    * ``progress``: a host callback in the loop, and a second compiled program.

    A first eager call traces its programs (input checks, solve, diagnostics with
    the saved states' projection) one after the other and compiles each in the
    background as soon as it is traced; the checks run, and raise, before the solve
    runs. Its solve is compiled with XLA's older loop emitters
    (``nhjax._programs.SOLVE_OPTIONS``: a shorter compile, the same run time); under
    ``jax.jit`` the solve is part of the caller's program and compiled with the
    caller's settings, so the last bits of its results may differ from an eager
    call's.

    Stored programs. The programs of an eager call are kept on disk
    (``NHJAX_CACHE_DIR``): a new process neither traces nor compiles them again. The
    same holds under ``jax.grad``, ``jax.vjp``, ``jax.jacrev``, ``jax.jvp``,
    ``jax.jacfwd`` and ``jax.linearize`` of a function around ``simulate`` called on
    concrete values: the values are checked as in an eager call (the named errors,
    with the time), and the solve's derivative programs (forward mode; reverse mode's
    forward pass with its residuals, and its backward pass) are stored too
    (``nhjax._primitive``). Under ``jax.jit`` or ``jax.vmap`` the call is traced into
    the caller's program: its checks are then runtime errors (host callbacks), which
    JAX's persistent cache does not keep, so such a program is compiled in every new
    process. With ``progress=True`` the loop holds a host callback too and is traced
    as usual.
    """
    call = _checked(system, x0, t1, t0=t0, control=control, saveat=saveat, rtol=rtol, atol=atol, dt0=dt0,
                    max_steps=max_steps, adjoint=adjoint, project=project, constraint_tol=constraint_tol,
                    on_guard=on_guard)
    plan = _planned(call, saveat=saveat, solver=solver, rtol=rtol, atol=atol, dt0=dt0, max_steps=max_steps,
                    stepsize_controller=stepsize_controller, jump_ts=jump_ts, adjoint=adjoint,
                    project_steps=project_steps, track_work=track_work, progress=progress, diagnostics=diagnostics)
    return _wrapped(call, plan, _run(call, plan))


def _state_norm(y):
    """RMS norm of the state part of (state, work): the error norm when work is tracked."""
    return optx.rms_norm(y[0])


def _flat_state_norm(y):
    """RMS norm of the state part of [state, work] (the flat layout)."""
    return optx.rms_norm(y[:-1])


def _is_explicit(solver):
    while isinstance(solver, ProjectedSolver):
        solver = solver.solver
    return isinstance(solver, (_AbstractRKMK, diffrax.AbstractERK))


def _drifting_constraints(residuals) -> bool:
    """Whether the system has constraints worth projecting onto after each step by
    default: every kind but pure velocity (nonholonomic) constraints, whose drift
    grows only linearly and whose projection can excite neutral modes (the
    rolling disk's circle: 2e-8 radius error unprojected, 4e-7 projected)."""
    return any(name != "velocity" for name in residuals)


def _defines_power(system) -> bool:
    return type(system).power is not AbstractSystem.power


_STRUCTURE: dict = {}


def _structural(question, system, x0, t0, answer):
    """``answer(*eqx.filter_eval_shape(question, system, x0, t0))``: a question about the
    system that shapes alone answer, traced once per system structure and state shape."""
    key = (question, jtu.tree_structure(system), jtu.tree_map(jnp.shape, x0))
    try:
        return _STRUCTURE[key]
    except (KeyError, TypeError):
        pass
    out = answer(*eqx.filter_eval_shape(question, system, x0, t0))
    try:
        _STRUCTURE[key] = out
    except TypeError:  # unhashable static fields: no caching
        pass
    return out


def _accuracy_parts(s, x, t):
    return s.invariants(x), s.constraints(t, x)


def _reports_accuracy(system, x0, t0) -> bool:
    """Whether the system declares invariants (conserved under every control) or
    constraints, whose drift simulate() reports."""
    return _structural(_accuracy_parts, system, x0, t0, lambda inv, cons: bool(inv) or bool(cons))


def _guards_and_constraints(s, x, t):
    return dict(s.guards(x)), s.constraints(t, x)


def _check_structure(system, x0, t0):
    """(guard names, whether to project after each step): what the solve's program needs
    from ``member_report``, known from shapes before the report runs."""
    return _structural(_guards_and_constraints, system, x0, t0,
                       lambda guards, cons: (tuple(guards), _drifting_constraints(cons)))


_GUARD_MSG = "nhjax.simulate: a chart guard crossed zero (the coordinates became singular)"


def _runtime_checks(traj, static, on_guard, span=None):
    """Checks for a traced simulate(): attached to the outputs users read (ts, xs, x_end)
    so that jit cannot drop them. ``span``: the time span's check (``time_span_check``)
    when t0 or t1 is traced. One runtime check for all (``first_error_if``)."""
    ok = diffrax.RESULTS.successful
    ev = diffrax.RESULTS.event_occurred
    bad = (traj.result != ok) & (traj.result != ev)
    checks = [] if span is None else [span]
    checks.append((bad, "nhjax.simulate: the solve failed (max_steps exhausted, or NaN/inf in the vector field)"))
    if on_guard == "raise" and static.guard_names:
        checks.append((traj.result == ev, _GUARD_MSG))
    out = first_error_if((traj.ts, traj.xs, traj.x_end), checks)
    return eqx.tree_at(lambda t: (t.ts, t.xs, t.x_end), traj, out)


def _truncate(traj, t_end, system=None, control=None):
    """Keep the saved points up to t_end and append the state at t_end itself."""
    ts = np.asarray(_primitive.concrete(traj.ts))
    n = int(np.searchsorted(ts, t_end, side="right"))
    append = system is not None and (n == 0 or ts[n - 1] < t_end)

    def cut(a, end=None):
        if a is None:
            return None
        a = a[:n]
        return jnp.concatenate([a, jnp.asarray(end)[None]]) if append else a

    x_end = traj.x_end
    xs = jtu.tree_map(cut, traj.xs, x_end)
    us = None
    if traj.us is not None:
        u_end = control(traj.t_final, x_end) if append else None
        us = cut(traj.us, u_end)
    invariants = {}
    for k, v in traj.invariants.items():
        end = None
        if append:
            end = system.energy(x_end) if k == "energy" else (
                np.nan if k == "energy - work" else system.invariants(x_end)[k])
        invariants[k] = cut(v, end)
    work = cut(traj.work, np.nan) if traj.work is not None else None
    return dataclasses.replace(
        traj, ts=cut(traj.ts, t_end), xs=xs, us=us, work=work, invariants=invariants
    )


def _guard_of(system, names, x):
    """The guard that stopped a solve: the one closest to zero at its final state."""
    if len(names) == 1:
        return names[0]
    g = system.guards(x)
    return min(names, key=lambda n: abs(float(g[n])))


def _eager_checks(traj, system, control, static, on_guard):
    result, t_final, leaves = jax.device_get(_primitive.concrete((traj.result, traj.t_final,
                                                                  jtu.tree_leaves(traj.xs))))
    t_final = float(t_final)
    # compared as host integers: comparing equinox's enumeration items is an eager program
    code = int(np.asarray(result._value))
    if code == diffrax.RESULTS.event_occurred._value:
        traj = _truncate(traj, t_final, system, control)
        name = _guard_of(system, static.guard_names, traj.x_end)
        traj = dataclasses.replace(traj, guard=name)
        if on_guard == "raise":
            raise ChartSingularityError(
                name, t_final, system.guard_hints.get(name, ""), trajectory=traj
            )
        return traj
    if code != diffrax.RESULTS.successful._value:
        traj = _truncate(traj, t_final, system, control)
        x_end = traj.x_end
        detail = _diagnose_failure(system, control, t_final, x_end, traj)
        if code == diffrax.RESULTS.max_steps_reached._value:
            reason = f"max_steps={static.max_steps} exhausted"
        else:
            reason = str(result.error_message if hasattr(result, "error_message") else result)
        raise IntegrationError(reason, t_final, detail, trajectory=traj)
    # Fixed-step solvers never reject: look for the first non-finite saved state.
    finite = np.all(np.stack([np.isfinite(a).reshape(a.shape[0], -1).all(1) for a in leaves]), axis=0)
    if not finite.all():
        i = int(np.argmin(finite))
        t_bad = float(traj.ts[i])
        t_ok = float(traj.ts[i - 1]) if i > 0 else float(traj.ts[0])
        raise IntegrationError(
            "state became NaN/inf", t_bad, f"it was finite at t = {t_ok:.10g}",
            trajectory=_truncate(traj, t_ok),
        )
    return traj


def _diagnose_failure(system, control, t, x, traj) -> str:
    steps = (
        f"{int(traj.num_accepted_steps)} steps accepted, "
        f"{int(traj.num_rejected_steps)} rejected"
    )
    u = None if control is None else control(t, x)
    f = system.vector_field(t, x, u)
    if not all(np.all(np.isfinite(np.asarray(a))) for a in jtu.tree_leaves(f)):
        return f"the vector field is NaN/inf at this state ({steps})"
    # Probe a little ahead along the flow: a NaN there makes every step get rejected.
    span = max(abs(float(traj.ts[-1]) - float(traj.ts[0])), 1.0)
    for h in span * 10.0 ** np.arange(-12, -2):
        xh = jtu.tree_map(lambda a, da: a + h * da, x, f)
        uh = None if control is None else control(t + h, xh)
        fh = system.vector_field(t + h, xh, uh)
        if not all(np.all(np.isfinite(np.asarray(a))) for a in jtu.tree_leaves(fh)):
            return (
                f"the vector field turns NaN/inf within dt = {h:.1e} after this time, so the "
                f"step size collapsed ({steps}); check the model's domain (a singular chart?)"
            )
    if int(traj.num_rejected_steps) > int(traj.num_accepted_steps):
        return (
            f"{steps}; the step size kept shrinking: the problem may be stiff or singular "
            "here (try looser tolerances or an implicit solver)"
        )
    return f"{steps}; the horizon needs more steps at this tolerance: raise max_steps"
