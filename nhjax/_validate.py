"""The one validation layer: every constructor and entry point of nhjax and controls
checks what it is given here, before any number reaches the numerics.

It is two modules: the checks of arguments that need no knowledge of systems
(parameters, inertias, group elements) are ``nhjax._args``, below
``nhjax.mechanics``, which uses them; this module adds the checks of states and
starts, which recognise the mechanics' system classes, and re-exports ``_args``.

What is checked, and where
--------------------------
* Parameters (``real``, ``positive``, ``in_range``, ``integer``, ``choice``,
  ``vector``, ``inertia_tensor``, ``principal_moments``): finiteness, sign and
  range, and for inertias physical realizability in one place (``inertias``,
  ``moment_triangle``: positive (semi)definite, each principal moment at most the sum
  of the other two; ``ball_moment``: 0 < J <= 2/3 m r^2; ``axisymmetric_moments``:
  axial <= 2 x transverse, <= m r^2), named by the argument the user passed (``mass must be positive, got 0``),
  checked on concrete values (arrays: every element, so batched parameters are
  checked member by member). A parameter passed as a tracer (a system built inside
  jit/vmap/grad) cannot be inspected and passes; those systems are built from
  values that were checked when they entered.
* States (``check_state``): the structure and shapes of a state against the
  system's declaration (``spaces``, ``state_names``, the Lagrangian's ``n``, a
  LieLagrangian's configuration parts) -- static, raised while tracing too.
* Values of a state (``member_report``, jit- and vmap-able, one member at a
  time): finiteness; membership of group-valued parts (rotation matrices with
  R^T R = I and det R = +1, unit quaternions, SE(2) poses) within a tolerance, or
  their projection onto the group; constraint residuals (after a projection that
  iterates to tolerance with a bound, when asked); chart guards; regularity
  margins; the control's value at t0. ``raise_for_report`` turns the numbers into
  the named errors of ``nhjax.errors`` (concrete values), ``runtime_checks`` into
  ``equinox.error_if`` runtime errors with the same words (traced values), and
  ``member_failures`` into one reason per failing member of a batch.
* Time spans and saved times (``time_span``, ``save_times``), solver settings
  (``solver_settings``) and memory (``check_memory``: a request that would need
  more than the available RAM fails before allocating).

Every error derives from ``nhjax.NhjaxError`` and from ValueError/TypeError
(``nhjax.errors``), so code catching ValueError keeps working.
"""

from __future__ import annotations

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from .errors import (
    ConstraintViolationError,
    ControlError,
    GroupMembershipError,
    OutsideChartError,
    ParameterError,
    ProjectionError,
    RegularityError,
    ResourceError,
    StateError,
    TimeSpanError,
)
from .lie.spaces import SO3Body, is_space
from .mechanics.lagrangian import ConstrainedLagrangian
from .mechanics.lie_lagrangian import LieLagrangian
from .mechanics.system import AbstractSystem

# the argument checks (nhjax/_args.py), re-exported: integrate, scenes and controls take
# every check from here; nhjax.mechanics, below this module, takes them from _args
from ._args import (  # noqa: F401
    _as_real,
    axisymmetric_moments,
    ball_moment,
    branched_error_if,
    _check_group_value,
    choice,
    error_if,
    first_error_if,
    function,
    _group_message,
    _GROUP_NAMES,
    _group_parts,
    group_residual,
    _GROUP_SHAPES,
    GROUP_TOL,
    in_range,
    inertia_tensor,
    inertias,
    integer,
    _is_group,
    is_traced,
    _map_groups,
    MAX_PROJECTIONS,
    moment_triangle,
    on_host,
    _path_name,
    positive,
    principal_moments,
    project_group,
    real,
    rotation,
    shell_moment,
    _show,
    single_member,
    stacked,
    to_device,
    unit_quaternion,
    vector,
    _where,
)

@eqx.filter_jit
def _applied(fn, *args):
    return fn(*args)


def abstract_call(fn, *args):
    """``jax.eval_shape(fn, *args)`` (nothing runs), traced once per structure: ``fn`` a
    function or a system's bound method (``plant.vector_field``: the system's arrays
    are then arguments of the trace, not constants in it), the arrays in ``args`` (or
    ``jax.ShapeDtypeStruct``s) arguments, everything else static. A closure over a system
    would be traced again on every call, e.g. on each eager call with a new system of the
    same kind."""
    return eqx.filter_eval_shape(_applied, fn, *args)


def _describe_spaces(spaces) -> str:
    def one(sp):
        return _GROUP_NAMES.get(type(sp), "array")

    leaves, treedef = jtu.tree_flatten(spaces, is_leaf=is_space)
    return str(jtu.tree_unflatten(treedef, [one(s) for s in leaves])).replace("'", "")


def _describe_state(x) -> str:
    leaves, treedef = jtu.tree_flatten(x)
    return str(jtu.tree_unflatten(treedef, [f"shape {tuple(np.shape(a))}" for a in leaves])).replace("'", "")


def _fix_hint(system) -> str:
    name = type(system).__name__
    if hasattr(system, "initial_state"):
        return f" Build it with {name}.initial_state(...)."
    return ""


def check_state(system, x, *, name="x0", owner="simulate"):
    """Structure, shapes and lengths of state ``x`` against what ``system`` declares.

    Static (shapes only), so it runs while tracing too. Raises StateError naming the
    argument, what was expected and what was given.
    """
    sysname = type(system).__name__
    spaces = system.spaces
    try:
        jtu.tree_map(lambda sp, sub: None, spaces, x, is_leaf=is_space)
    except (ValueError, TypeError):
        raise StateError(
            f"{_where(owner)}{name} does not have the structure of {sysname}'s state: expected "
            f"{_describe_spaces(spaces)}, got {_describe_state(x)}.{_fix_hint(system)}", name) from None
    for part, sp, leaf in _group_parts(spaces, x, name):
        want = _GROUP_SHAPES[type(sp)]
        if not hasattr(leaf, "shape") or tuple(leaf.shape) != want:
            raise StateError(
                f"{_where(owner)}{part} must be a {'x'.join(map(str, want))} element of "
                f"{_GROUP_NAMES[type(sp)]} for {sysname}, got "
                f"{('shape ' + str(tuple(leaf.shape))) if hasattr(leaf, 'shape') else type(leaf).__name__}."
                f"{_fix_hint(system)}", part)
    for leaf in jtu.tree_leaves(x):
        if hasattr(leaf, "dtype") and not (jnp.issubdtype(leaf.dtype, jnp.floating)
                                           or jnp.issubdtype(leaf.dtype, jnp.integer)):
            raise StateError(f"{_where(owner)}{name} must hold real numbers, got dtype {leaf.dtype}", name)
    names = tuple(getattr(system, "state_names", ()) or ())
    single = len(jtu.tree_leaves(x)) == 1 and hasattr(x, "shape")
    if names:
        if not single:
            raise StateError(
                f"{_where(owner)}{name} must be one array of {len(names)} components {names} for {sysname}, "
                f"got {_describe_state(x)}.{_fix_hint(system)}", name)
        if tuple(x.shape) != (len(names),):
            raise StateError(
                f"{_where(owner)}{name} has shape {tuple(x.shape)}; {sysname} expects {len(names)} components "
                f"{names}.{_fix_hint(system)}", name)
    if isinstance(system, ConstrainedLagrangian) and not names:
        n = int(system.n)
        if not single or tuple(x.shape) != (2 * n,):
            got = f"shape {tuple(x.shape)}" if single else _describe_state(x)
            raise StateError(
                f"{_where(owner)}{name} must be the flat state (q, q') of length 2 n = {2 * n} for {sysname} "
                f"with n = {n} coordinates, got {got}", name)
    if isinstance(system, LieLagrangian):
        g, v = x
        sizes = []
        for sp, part in zip(system.config_spaces, g):
            sizes.append(3 if _is_group(sp) else int(np.prod(np.shape(part))))
        if not hasattr(v, "shape") or tuple(v.shape) != (sum(sizes),):
            parts = ", ".join(f"{_GROUP_NAMES.get(type(sp), 'R^' + str(s))}: {s}"
                              for sp, s in zip(system.config_spaces, sizes))
            raise StateError(
                f"{_where(owner)}{name}[1] (the velocity) must have {sum(sizes)} entries for {sysname}, "
                f"one per direction of the configuration ({parts}); got "
                f"{('shape ' + str(tuple(v.shape))) if hasattr(v, 'shape') else type(v).__name__}."
                f"{_fix_hint(system)}", f"{name}[1]")


def nonfinite_components(system, x, name="x0") -> str:
    """Which components of a concrete state are NaN/inf, for messages."""
    names = tuple(getattr(system, "state_names", ()) or ())
    out = []
    for path, leaf in jtu.tree_flatten_with_path(x)[0]:
        a = np.asarray(leaf)
        bad = np.argwhere(~np.isfinite(a))
        for idx in bad[:4]:
            idx = tuple(int(i) for i in idx)
            if names and a.ndim == 1 and len(jtu.tree_leaves(x)) == 1:
                out.append(f"'{names[idx[0]]}' (index {idx[0]})")
            else:
                out.append(_path_name(name, path) + "".join(f"[{i}]" for i in idx))
    return ", ".join(out)


def requires_control_message(system) -> str:
    name = type(system).__name__
    return (f"{name} needs a control: its vector field uses the {system.control_dim} inputs u "
            f"(e.g. the shape velocities of a velocity-controlled system); pass control=u(t, x) "
            f"returning an array of {system.control_dim} entries (e.g. nhjax.PiecewiseConstant or a "
            "function)")


def check_control(system, control, *, owner="simulate"):
    """Static consistency of a control with the system (before any tracing)."""
    name = type(system).__name__
    if control is None:
        if getattr(system, "requires_control", False):
            raise ControlError(f"{_where(owner)}{requires_control_message(system)}")
        return
    if system.control_dim == 0:
        raise ControlError(f"{_where(owner)}{name} takes no control input; drop control=... (got "
                           f"{type(control).__name__})")
    if not callable(control):
        raise ControlError(
            f"{_where(owner)}control must be callable as control(t, x) -> array of {system.control_dim} "
            f"inputs, got {type(control).__name__}; wrap constant inputs as lambda t, x: u")


def _probe_missing_control(system, t0, x0):
    """At trace time: a system that declares inputs but whose vector field cannot run
    without them (u = None) gets a ControlError instead of a TypeError from inside."""
    if system.control_dim == 0 or isinstance(system, (ConstrainedLagrangian, LieLagrangian)):
        return
    try:
        jax.eval_shape(lambda: system.vector_field(t0, x0, None))
    except (TypeError, IndexError, AttributeError) as e:
        raise ControlError(requires_control_message(system)) from e


def constraint_residual(system, t, x):
    """max |residual| over all of ``system.constraints(t, x)`` (0 without constraints)."""
    cons = system.constraints(t, x)
    vals = [jnp.max(jnp.abs(jnp.asarray(v))) for v in cons.values() if jnp.size(v)]
    return jnp.max(jnp.stack(vals)) if vals else jnp.zeros(())


def project_state(system, t, x, *, tol=1e-14, max_rounds=MAX_PROJECTIONS):
    """Project ``x`` onto the system's groups and constraint manifold, iterating
    ``system.project`` until every constraint residual is <= tol (relative to the
    state's size) or ``max_rounds`` rounds have run.

    Returns (x, residual reached, rounds used). A fixed-length loop that stops
    changing x once converged: jit-, vmap- and grad-friendly.
    """
    spaces = system.spaces
    x = _map_groups(spaces, x, project_group)
    return system.project_converged(t, x, tol=tol, max_iter=max_rounds)


def member_report(system, control, x0, t0, project=False, max_rounds=MAX_PROJECTIONS):
    """Everything there is to check about one initial state, as numbers (jit- and
    vmap-able: call it per member and vmap it over a batch).

    Returns (x0, report): x0 projected if ``project``; report a dict with
    ``finite`` (bool), ``control_finite`` (bool), ``group`` (part -> residual),
    ``group_det`` (part -> det of its rotation block), ``constraints`` (name ->
    max |residual|), ``guards`` (name -> value), ``margins`` (name -> regularity
    margin), ``projections`` (rounds of projection used). Shape errors of the
    control and a missing control raise while tracing (they depend on shapes only).
    """
    report = {}
    if control is not None:
        u0 = control(t0, x0)
        shape = jnp.shape(u0)
        if shape != (system.control_dim,):
            raise ControlError(
                f"control(t, x) returned shape {shape}; {type(system).__name__} has "
                f"{system.control_dim} inputs: return an array of shape ({system.control_dim},)"
            )
        report["control_finite"] = jnp.all(jnp.isfinite(u0))
    else:
        _probe_missing_control(system, t0, x0)
        report["control_finite"] = jnp.asarray(True)
    report["finite"] = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in jtu.tree_leaves(x0)]))
    rounds = jnp.zeros((), jnp.int32)
    if project:
        x0, _, rounds = project_state(system, t0, x0, max_rounds=max_rounds)
    report["projections"] = rounds
    parts = _group_parts(system.spaces, x0)
    report["group"], report["group_det"] = {}, {}
    for name, sp, leaf in parts:
        r, d = group_residual(sp, leaf)
        report["group"][name], report["group_det"][name] = r, d
    report["constraints"] = {k: _max_abs(v) for k, v in system.constraints(t0, x0).items()}
    report["guards"] = dict(system.guards(x0))
    # the regularity margins are a check, not an output: out of the derivative (their SVD
    # has no forward-mode rule, which would make every gradient through x0 fail)
    report["margins"] = dict(system.regularity(t0, jax.lax.stop_gradient(x0)))
    return x0, report


def _max_abs(a):
    a = jnp.asarray(a)
    return jnp.max(jnp.abs(a)) if a.size else jnp.zeros(())


def raise_for_report(report, system, *, x0=None, constraint_tol=1e-8, project=False, t0=0.0,
                     owner="simulate", name="x0"):
    """Raise the named error for the first failed check of a concrete ``member_report``."""
    r = jax.device_get(report)
    sysname = type(system).__name__
    if not bool(r["finite"]):
        where = nonfinite_components(system, x0, name) if x0 is not None else ""
        raise StateError(
            f"{_where(owner)}initial state {name} contains NaN or inf" + (f" at {where}" if where else "")
            + "; pass finite numbers", name)
    if not bool(r["control_finite"]):
        raise ControlError(f"{_where(owner)}control(t0, x0) returned NaN or inf at t0 = {float(t0):g}; the "
                           "control must be finite where the motion starts")
    for part, res in r["group"].items():
        det = float(r["group_det"][part])
        res = float(res)
        g = _group_space_of(system, part, name)
        if not (np.isfinite(res) and res <= constraint_tol and det > 0):
            msg = _group_message(part, g, res, det, constraint_tol, owner, projected=project and det > 0)
            if project and det > 0 and np.isfinite(res):
                raise ProjectionError(part, res, constraint_tol, int(r["projections"]))
            raise GroupMembershipError(msg, part, res, constraint_tol)
    def constraint_failure(cname, res):
        if project:
            hint = ""
            if type(system).project is AbstractSystem.project:
                hint = f"{sysname} defines no project(): project=True cannot move the state"
            return ProjectionError(cname, res, constraint_tol, int(r["projections"]), hint)
        return ConstraintViolationError(cname, res, constraint_tol)

    for cname, res in r["constraints"].items():
        if float(res) > constraint_tol:
            raise constraint_failure(cname, float(res))
    for gname, g in r["guards"].items():
        if not g > 0:
            raise outside_chart(system, gname, g, owner=owner, name=name, t0=t0)
    for cname, res in r["constraints"].items():  # NaN residuals (e.g. at a chart's edge): after the guards
        if not float(res) <= constraint_tol:
            raise constraint_failure(cname, float(res))
    for mname, margin in r["margins"].items():  # after the guards: outside a chart, say that first
        if not margin > 0:
            raise RegularityError(mname, float(margin), system.regularity_hints.get(mname, ""))


def outside_chart(system, guard, value, *, owner="", name="x0", t0=0.0, cls=OutsideChartError):
    """The error for a start outside ``system``'s chart (its guard ``guard`` at ``value``
    <= 0), wherever it is found: ``OutsideChartError`` (or a subclass ``cls``) naming the
    argument ``name`` that put the start there, with the scene's hint for that guard."""
    arg = system.guard_arguments.get(guard)
    via = f"; {arg} of {type(system).__name__}.initial_state sets it" if arg and arg != name else ""
    return cls(
        guard, float(t0), f"{_where(owner)}the start is already outside the chart of {type(system).__name__}: "
        f"guard '{guard}' = {float(value):.3g} <= 0 (set by {name}{via}). " + system.guard_hints.get(guard, ""),
        name=name)


def chart_argument(system, guard, margin, *, owner="", name=""):
    """A scene's own check, in ``initial_state``, of an argument that sets chart guard
    ``guard``: ``margin`` (the guard's value for that argument, host-side numbers, no
    program) must be > 0, else the ``OutsideChartError`` that ``simulate`` raises for the
    state. Traced values pass (the solve's guard catches them)."""
    if is_traced(margin):
        return
    if not np.all(np.asarray(margin, float) > 0):
        raise outside_chart(system, guard, np.min(np.asarray(margin, float)), owner=owner, name=name)


def _group_space_of(system, part, name):
    for p, sp, _ in _group_parts_names(system.spaces, name):
        if p == part:
            return sp
    return SO3Body()


def _group_parts_names(spaces, name):
    flat, _ = jtu.tree_flatten_with_path(spaces, is_leaf=is_space)
    return [(_path_name(name, path), sp, None) for path, sp in flat if _is_group(sp)]


def runtime_checks(x0, report, *, constraint_tol, project, owner="nhjax.simulate", name="x0"):
    """The checks of ``raise_for_report`` as one runtime check on x0 (``first_error_if``:
    the words of the first failing condition; for traced values: inside jit, vmap or
    grad). Chart guards and regularity margins are left to the solve (its guard event
    and NaN checks)."""
    checks = [
        (~report["finite"], f"{owner}: initial state {name} contains NaN or inf; pass finite numbers"),
        (~report["control_finite"],
         f"{owner}: control(t0, x0) returned NaN or inf; the control must be finite where the motion starts"),
    ]
    for part in report["group"]:
        bad = ~(report["group"][part] <= constraint_tol) | ~(report["group_det"][part] > 0)
        checks.append((bad, f"{owner}: {part} is not on its group (rotation error beyond constraint_tol, or det <= 0)"
                       + ("" if project else "; pass project=True to simulate() to replace it by the nearest group "
                          "element")))
    for cname, res in report["constraints"].items():
        if project:
            msg = (f"{owner}: projecting the initial state did not converge: constraint '{cname}' still "
                   "exceeds constraint_tol; start from a state closer to the constraint manifold")
        else:
            msg = (f"{owner}: initial state violates constraint '{cname}' beyond constraint_tol. Pass "
                   "project=True to simulate() to project it onto the constraint manifold, or fix the initial state")
        checks.append((~(res <= constraint_tol), msg))
    return first_error_if(x0, checks)


def member_failures(report, *, constraint_tol, project=False, n=None):
    """One reason per failing member of a batched ``member_report`` (leading axis =
    members): [(index, reason)], the first failing check of each member, in the words
    of ``raise_for_report``. For ``simulate_batch``."""
    r = jax.device_get(report)
    B = int(np.shape(r["finite"])[0]) if n is None else n
    checks = [(~np.asarray(r["finite"][:B], bool), lambda j: "x0 contains NaN or inf"),
              (~np.asarray(r["control_finite"][:B], bool), lambda j: "control(t0, x0) returned NaN or inf")]
    for part in r["group"]:
        res, det = np.asarray(r["group"][part][:B]), np.asarray(r["group_det"][part][:B])
        checks.append((~(res <= constraint_tol) | ~(det > 0),
                       lambda j, p=part, res=res, det=det: (
                           f"{p} is not on its group (error {res[j]:.2e}, det {det[j]:.3g})"
                           + ("" if project else "; pass project=True"))))
    for k, res in r["constraints"].items():
        res = np.asarray(res[:B])
        checks.append((~(res <= constraint_tol), lambda j, k=k, res=res: (
            f"projection did not converge: constraint '{k}' still {res[j]:.2e}" if project
            else f"constraint '{k}' violated by {res[j]:.2e} (pass project=True)")))
    for k, g in r["guards"].items():
        g = np.asarray(g[:B])
        checks.append((g <= 0, lambda j, k=k: f"outside the chart ('{k}')"))
    for k, m in r["margins"].items():
        m = np.asarray(m[:B])
        checks.append((~(m > 0), lambda j, k=k: f"regularity condition '{k}' fails"))
    return first_failures(checks, B)


def first_failures(checks, B):
    """[(member, what)] for every member that fails some check, with ``what(j)`` of the
    first check it fails. ``checks``: [(mask over the B members, what)], the masks
    computed for all members at once (numpy); ``what`` is called only for failing
    members (the texts of a batch's reasons, or the errors of a single call)."""
    failing = np.zeros(B, bool)
    for mask, _ in checks:
        failing |= mask
    return [(int(j), next(what(j) for mask, what in checks if mask[j])) for j in np.nonzero(failing)[0]]


# ------------------------------------------------------------------ times
def time_span(t0, t1, *, owner="simulate", runtime=True):
    """t0 and t1 finite real scalars with t1 > t0 (concrete values); traced values
    get the same words as a runtime error (``runtime=False``: not here; the caller joins
    ``time_span_check`` to its own runtime checks). Returns (t0, t1)."""
    for nm, t in (("t0", t0), ("t1", t1)):
        _time_value(nm, t, owner)
    if not is_traced(t0, t1):
        if not float(t1) > float(t0):
            kind = "an empty time span" if float(t1) == float(t0) else "a reversed time span"
            raise TimeSpanError(
                f"{_where(owner)}t1 = {float(t1)} must be greater than t0 = {float(t0)} ({kind}); nhjax "
                "integrates forward in time: pass t1 > t0")
        return t0, t1
    if runtime:
        t1 = error_if(jnp.asarray(t1, float), *time_span_check(t0, t1, owner=owner))
    return t0, t1


def _time_value(nm, t, owner, fix="pass a finite end time (long horizons: a finite t1 with a step budget "
                                   "max_steps)"):
    """A time [s] (concrete values): a finite real scalar, not a string (TimeSpanError)."""
    if isinstance(t, jax.core.Tracer):
        return
    if isinstance(t, (str, bytes, bool)) or t is None:
        raise TimeSpanError(f"{_where(owner)}{nm} must be a time in seconds (a real number), got {t!r}")
    try:
        a = np.asarray(t, dtype=float)
    except (TypeError, ValueError):
        raise TimeSpanError(f"{_where(owner)}{nm} must be a time in seconds (a real number), got {t!r}") from None
    if a.shape != ():
        raise TimeSpanError(f"{_where(owner)}{nm} must be a scalar time, got shape {a.shape}")
    if not np.isfinite(a):
        raise TimeSpanError(f"{_where(owner)}{nm} must be a finite time, got {_show(t)}; {fix}")


def duration(name, T, *, owner=""):
    """A horizon T [s] by the rules ``simulate`` applies to its time span: a finite real
    scalar, not a string, > 0 (TimeSpanError). Returns a float (traced values: as given)."""
    _time_value(name, T, owner, fix="pass the duration of the motion in seconds")
    if isinstance(T, jax.core.Tracer):
        return T
    if not float(T) > 0:
        raise TimeSpanError(f"{_where(owner)}{name} = {float(T)} must be positive: the horizon is the duration "
                            "of the motion in seconds")
    return float(T)


def as_state(system, x0, *, owner="simulate", xp=jnp):
    """``x0`` with every leaf a float array (``xp``: jax.numpy, or numpy for host-side
    batches). A plain sequence (a list or tuple of numbers, nested for a batch) is read as
    one array where the system's state is one array; StateError naming x0 when it holds
    something that is not real numbers."""
    flat_state = jtu.treedef_is_leaf(jtu.tree_structure(system.spaces, is_leaf=is_space))
    names = tuple(getattr(system, "state_names", ()) or ())
    what = f" {names}" if names else ""
    try:
        if flat_state and isinstance(x0, (list, tuple)):
            x0 = np.asarray(x0, float)
        return jtu.tree_map(lambda a: xp.asarray(a, dtype=float), x0)
    except (TypeError, ValueError) as e:
        raise StateError(f"{_where(owner)}x0 must be an array of real numbers{what} (or a pytree of arrays for "
                         f"{type(system).__name__}'s state): {e}", "x0") from None


def time_span_check(t0, t1, *, owner="simulate"):
    """(pred, msg): the runtime check of a traced time span (pred: t1 <= t0), for
    ``first_error_if``."""
    return (~(jnp.asarray(t1, float) > jnp.asarray(t0, float)),
            f"{_where(owner)}t1 must be greater than t0 (an empty or reversed time span); pass t1 > t0")


def save_times_count(saveat) -> int:
    """Number of saved times a ``saveat`` argument asks for (for memory estimates)."""
    if saveat is None:
        return 101
    if isinstance(saveat, (int, np.integer)) and not isinstance(saveat, bool):
        return int(saveat)
    return int(np.size(saveat)) if not is_traced(saveat) else int(np.size(saveat))


def check_saveat(saveat, t0, t1, *, owner="simulate"):
    """``saveat``: None, an int >= 2, or a 1-D array of finite sorted times in [t0, t1]."""
    if saveat is None:
        return
    if isinstance(saveat, bool):
        raise TimeSpanError(f"{_where(owner)}saveat must be an int (number of equally spaced times) or a 1-D "
                            f"array of times, got {saveat!r}")
    if isinstance(saveat, (int, np.integer)):
        if saveat < 2:
            raise TimeSpanError(f"{_where(owner)}saveat={saveat}: ask for at least 2 saved times (t0 and t1)")
        return
    if isinstance(saveat, (float, np.floating)):
        raise TimeSpanError(f"{_where(owner)}saveat must be an int (number of equally spaced times) or a 1-D "
                            f"array of times, got the float {saveat!r}; pass int({saveat!r}) saved times or an array")
    if is_traced(saveat):
        return
    try:
        ts = np.asarray(saveat, dtype=float)
    except (TypeError, ValueError):
        raise TimeSpanError(f"{_where(owner)}saveat must be an int or a 1-D array of times, got {saveat!r}") from None
    if ts.ndim != 1 or ts.shape[0] == 0:
        raise TimeSpanError(f"{_where(owner)}saveat must be an int (number of equally spaced times) or a "
                            f"non-empty 1-D array of times, got shape {ts.shape}")
    if not np.all(np.isfinite(ts)):
        raise TimeSpanError(f"{_where(owner)}saveat contains NaN or inf: pass finite times in [t0, t1]")


# ------------------------------------------------------------------ settings and memory
def solver_settings(*, rtol=None, atol=None, dt0=None, max_steps=None, constraint_tol=None, owner="simulate"):
    """Tolerances and step settings: finite and positive (concrete values only)."""
    for nm, v in (("rtol", rtol), ("atol", atol), ("dt0", dt0), ("constraint_tol", constraint_tol)):
        if v is None or is_traced(v):
            continue
        positive(nm, v, owner=owner, as_float=np.ndim(v) == 0)  # a check: no device array made
    if max_steps is not None:
        integer("max_steps", max_steps, minimum=1, owner=owner, what="budget of solver steps")


def available_memory() -> int:
    """Bytes of memory available to this process now (MemAvailable on Linux)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 62


#: Needs up to this many bytes are not checked (reading /proc/meminfo costs more).
_MEMORY_CHECK_FROM = 2**26


def check_memory(need_bytes, what, fix, *, owner="simulate", fraction=0.8):
    """ResourceError before allocating if ``need_bytes`` exceeds ``fraction`` of the
    available memory (needs of at most 64 MiB pass unchecked)."""
    if need_bytes <= _MEMORY_CHECK_FROM:
        return
    avail = available_memory()
    if need_bytes > fraction * avail:
        raise ResourceError(
            f"{_where(owner)}{what} would need about {need_bytes / 2**30:.3g} GiB, more than the "
            f"{avail / 2**30:.3g} GiB of memory available: {fix}", need_bytes, avail)


def simulate_memory(system, x0, saveat, *, max_steps=None, stores_steps=False, owner="simulate"):
    """Estimate of what a simulate() call keeps in memory, checked against what is
    available: the saved states with their diagnostics (states, invariants, controls,
    work: about three copies of each on the way to the user), and for a differentiated
    solve under ``DiscreteAdjoint`` the ``max_steps`` recorded states and stages."""
    n_state = sum(int(np.size(a)) for a in jtu.tree_leaves(x0))
    n_save = save_times_count(saveat)
    per_time = n_state + int(getattr(system, "control_dim", 0) or 0) + 24
    need = 8.0 * n_save * per_time * 3
    check_memory(need, f"saving {n_save} times of a state of {n_state} numbers",
                 "save fewer times (saveat=2 keeps t0 and t1; an array of the times you need), or split "
                 "the horizon into several calls", owner=owner)
    if stores_steps and max_steps is not None:
        need = 8.0 * int(max_steps) * n_state * 9
        check_memory(need, f"a differentiated solve recording max_steps={int(max_steps)} steps of "
                     f"{n_state} numbers", "lower max_steps (DiscreteAdjoint(max_steps=...)) or "
                     "differentiate shorter horizons", owner=owner)


def axes_dict(in_axes, keys, *, owner="", default=None):
    """``in_axes`` as a dict (``default`` when None): a mapping whose keys are among
    ``keys``; ParameterError naming ``in_axes`` for anything else (a list, a string, an
    unknown key)."""
    if in_axes is None:
        return dict(default or {})
    example = f"'{'x0' if 'x0' in keys else keys[0]}': 0"
    if not isinstance(in_axes, dict):
        raise ParameterError(f"{_where(owner)}in_axes must be a dict such as {{{example}}} with keys among "
                             f"{', '.join(repr(k) for k in keys)} (or None), got {in_axes!r}", "in_axes", in_axes)
    unknown = set(in_axes) - set(keys)
    if unknown:
        raise ParameterError(f"{_where(owner)}in_axes keys must be among {', '.join(repr(k) for k in keys)}; got "
                             f"{sorted(map(str, unknown))}", "in_axes", in_axes)
    return dict(in_axes)
