"""The one validation layer: every constructor and entry point of nhjax and controls
checks what it is given here, before any number reaches the numerics.

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

import math
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
from .lie.spaces import SE2Body, SO3Body, SO3Spatial, UnitQuaternionBody, is_space

#: Largest |R^T R - I|, ||q| - 1| or SE(2) block error accepted in a group-valued part
#: of a state given to a constructor helper (simulate() uses its ``constraint_tol``).
GROUP_TOL = 1e-8
#: Bound on the rounds of ``system.project`` that ``project=True`` applies to x0.
MAX_PROJECTIONS = 10


# ------------------------------------------------------------------ helpers
def is_traced(*trees) -> bool:
    """Whether any leaf of ``trees`` is a JAX tracer (inside jit, vmap or grad)."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jtu.tree_leaves(trees))


def _error_mode() -> str:
    from equinox import _errors

    return getattr(_errors, "EQX_ON_ERROR", "raise")


def error_if(x, pred, msg):
    """``equinox.error_if`` with equinox's current error mode passed explicitly: the mode
    is then part of the key of equinox's cached trace of the check, so a check traced
    in one mode (callbacks by default, NaN under controls' ``nan_errors``) is never
    reused in another."""
    return branched_error_if(x, pred, 0, [msg], _error_mode())


def first_error_if(x, checks):
    """``error_if`` for several ``(pred, msg)`` checks at once: one
    ``equinox.branched_error_if`` that raises the message of the first check whose
    ``pred`` holds (anywhere in it). One check instead of one per condition: equinox reads
    the whole Python stack for every check it traces (for its error message), which
    costs more tracing time than the check itself in a deep trace such as a solve inside
    an optimizer's program."""
    checks = list(checks)
    if not checks:
        return x
    if len(checks) == 1:
        return error_if(x, *checks[0])
    preds = jnp.stack([jnp.any(jnp.asarray(p)) for p, _ in checks])
    return branched_error_if(x, jnp.any(preds), jnp.argmax(preds), [m for _, m in checks], _error_mode())


def branched_error_if(x, pred, index, msgs, on_error):
    """``equinox.branched_error_if(x, pred, index, msgs, on_error=on_error)``. In the
    modes that show no message (``"off"``: no check; ``"nan"``: NaN outputs, as
    controls' optimizers use it) a traced check skips what equinox does for a message
    at every check it traces: formatting every frame of the Python stack (tens of
    milliseconds in a solve traced inside an optimizer's program), which only the
    ``"raise"`` mode shows. The program is the same as equinox's."""
    if on_error in ("off", "nan") and isinstance(pred, jax.core.Tracer):
        if on_error == "off":
            return x
        try:
            from equinox import _errors
            from equinox.internal import unvmap_any, unvmap_max

            dynamic, static = eqx.partition(x, eqx.is_array)
            if jtu.tree_leaves(dynamic):
                index = index if isinstance(index, int) else unvmap_max(index)
                dynamic = _errors._error(dynamic, unvmap_any(pred), index, msgs=msgs, on_error="nan", stack=[])
                return eqx.combine(dynamic, static)
        except (ImportError, AttributeError, TypeError):  # another equinox: its own way
            pass
    return eqx.branched_error_if(x, pred, index, msgs, on_error=on_error)



def _where(owner: str) -> str:
    return f"{owner}: " if owner else ""


def _show(value) -> str:
    """A short text for a value in a message: the value as passed for scalars."""
    if isinstance(value, (bool, int, float, np.integer, np.floating)):
        return repr(value.item() if hasattr(value, "item") else value)
    try:
        a = np.asarray(value)
    except Exception:  # noqa: BLE001 - anything: show its repr
        return repr(value)
    if a.ndim == 0:
        return repr(a.item())
    if a.size <= 9:
        return np.array2string(a, precision=6, separator=", ").replace("\n", "")
    return f"an array of shape {a.shape}"


def _show_bad(value, arr: np.ndarray, bad: np.ndarray) -> str:
    """The value, or the first offending element of an array with its index."""
    if arr.ndim == 0 or arr.size <= 9:
        return _show(value)
    idx = tuple(int(i) for i in np.argwhere(bad)[0])
    return f"{float(arr[idx])!r} (element {idx} of an array of shape {arr.shape})"


def _describe(what: str) -> str:
    return f" ({what})" if what else ""


def _as_real(name, value, owner, what):
    """A float array from ``value`` (tracers pass through), or ParameterError."""
    if isinstance(value, jax.core.Tracer):
        return value
    if isinstance(value, (str, bytes)) or value is None or np.iscomplexobj(value):
        raise ParameterError(
            f"{_where(owner)}{name} must be a real number{_describe(what)}, got {value!r}", name, value)
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError(
            f"{_where(owner)}{name} must be a real number{_describe(what)}, got {value!r}", name, value
        ) from None


def _check_shape(name, arr, shape, owner, what):
    if shape is not None and tuple(np.shape(arr)) != tuple(shape):
        kind = ("a scalar" if shape == () else f"a {shape[0]}-vector" if len(shape) == 1
                else f"an array of shape {tuple(shape)}")
        raise ParameterError(
            f"{_where(owner)}{name} must be {kind}{_describe(what)}, got shape {tuple(np.shape(arr))}",
            name, arr)


# ------------------------------------------------------------------ parameters
def to_device(value):
    """``value`` as a float64 JAX array. A concrete value goes to the device with
    ``jax.device_put``: an eager ``jnp.asarray`` of a host array is an XLA program of its
    own, compiled (or looked up) per shape in every new process, which a first answer pays
    for each parameter and state it converts. Tracers become ``jnp.asarray`` as usual."""
    if isinstance(value, (jax.Array, jax.core.Tracer)) and value.dtype == np.float64:
        return value  # (a tracer too: under jax.grad of a concrete value, a cast is eager work)
    if any(isinstance(v, jax.core.Tracer) for v in jtu.tree_leaves(value)):
        return jnp.asarray(value, float)
    if isinstance(value, jax.Array) and value.dtype == np.float64:
        return value
    return jax.device_put(np.asarray(value, float))


def stacked(values):
    """``jnp.stack(values)`` (floats), without an eager program when every value is
    concrete (``to_device``)."""
    if any(isinstance(v, jax.core.Tracer) for v in jtu.tree_leaves(values)):
        return jnp.stack([jnp.asarray(v, float) for v in values])
    return to_device(np.stack([np.asarray(v, float) for v in values]))


def _out(arr, as_float):
    if as_float:
        return float(arr)
    return to_device(arr)


def real(name, value, *, owner="", what="", shape=None, as_float=False):
    """``value`` as a float array after checking it is real and finite (every element).

    shape : required shape, or None for any (scalars may be batched parameters).
    as_float : return a Python float (for static settings; needs a concrete scalar).
    Tracers pass unchecked. Returns a jax array.
    """
    arr = _as_real(name, value, owner, what)
    if isinstance(arr, jax.core.Tracer):
        return to_device(arr)
    _check_shape(name, arr, shape, owner, what)
    bad = ~np.isfinite(arr)
    if bad.any():
        raise ParameterError(
            f"{_where(owner)}{name} must be finite{_describe(what)}, got {_show_bad(value, arr, bad)}; "
            "pass a finite number", name, value)
    return _out(arr, as_float)


def positive(name, value, *, allow_zero=False, owner="", what="", shape=None, as_float=False):
    """``value`` as a float array after checking it is finite and > 0 (>= 0 with
    ``allow_zero``), element by element. ``mass=0`` -> "mass must be positive, got 0"."""
    arr = _as_real(name, value, owner, what)
    if isinstance(arr, jax.core.Tracer):
        return to_device(arr)
    _check_shape(name, arr, shape, owner, what)
    kind = "non-negative" if allow_zero else "positive"
    bound = ">= 0" if allow_zero else "> 0"
    nonfinite = ~np.isfinite(arr)
    if nonfinite.any():
        raise ParameterError(
            f"{_where(owner)}{name} must be finite and {kind}{_describe(what)}, got "
            f"{_show_bad(value, arr, nonfinite)}; pass a finite value {bound}", name, value)
    bad = ~(arr >= 0) if allow_zero else ~(arr > 0)
    if bad.any():
        raise ParameterError(
            f"{_where(owner)}{name} must be {kind}, got {_show_bad(value, arr, bad)}{_describe(what)}; "
            f"pass a value {bound}", name, value)
    return _out(arr, as_float)


def in_range(name, value, lo=None, hi=None, *, lo_closed=True, hi_closed=True, owner="", what="",
             shape=None, as_float=False):
    """``value`` (finite, every element) within [lo, hi] (open ends with ``*_closed=False``)."""
    if isinstance(value, jax.core.Tracer):
        return jnp.asarray(value, float)
    a = _as_real(name, value, owner, what)
    real(name, a, owner=owner, what=what, shape=shape)
    bad = np.zeros(a.shape, bool)
    if lo is not None:
        bad |= ~(a >= lo) if lo_closed else ~(a > lo)
    if hi is not None:
        bad |= ~(a <= hi) if hi_closed else ~(a < hi)
    if bad.any():
        left = "-inf" if lo is None else f"{lo:g}"
        right = "inf" if hi is None else f"{hi:g}"
        interval = ("[" if lo_closed and lo is not None else "(") + f"{left}, {right}" + (
            "]" if hi_closed and hi is not None else ")")
        raise ParameterError(
            f"{_where(owner)}{name} must lie in {interval}{_describe(what)}, got {_show_bad(value, a, bad)}; "
            "pass a value in that range", name, value)
    return _out(a, as_float)


def integer(name, value, *, minimum=None, owner="", what=""):
    """``value`` as a Python int (integral floats accepted), at least ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer, float, np.floating)):
        raise ParameterError(f"{_where(owner)}{name} must be an integer{_describe(what)}, got {value!r}",
                             name, value)
    if not (math.isfinite(float(value)) and float(value) == int(value)):
        raise ParameterError(f"{_where(owner)}{name} must be an integer{_describe(what)}, got {value!r}",
                             name, value)
    v = int(value)
    if minimum is not None and v < minimum:
        raise ParameterError(
            f"{_where(owner)}{name} must be at least {minimum}{_describe(what)}, got {value!r}", name, value)
    return v


def choice(name, value, options, *, owner=""):
    """``value`` if it is one of ``options``."""
    try:
        ok = bool(value in options)
    except (TypeError, ValueError):  # unhashable, or an array (ambiguous truth value)
        ok = False
    if not ok:
        raise ParameterError(
            f"{_where(owner)}{name} must be one of {', '.join(repr(o) for o in options)}, got {value!r}",
            name, value)
    return value


def vector(name, value, n, *, owner="", what=""):
    """A finite float vector of shape (n,)."""
    return real(name, value, owner=owner, what=what, shape=(n,))


def function(name, value, *, owner="", signature="", optional=False):
    """``value`` if it is callable (or None with ``optional``); ControlError-free TypeError otherwise."""
    if value is None and optional:
        return value
    if not callable(value):
        raise ParameterError(
            f"{_where(owner)}{name} must be a callable{(' ' + signature) if signature else ''}, "
            f"got {type(value).__name__}", name, value)
    return value


def inertia_tensor(name, value, *, owner=""):
    """A 3x3 symmetric positive definite inertia tensor [kg m^2] from a 3x3 array or
    three principal moments."""
    arr = _as_real(name, value, owner, "inertia tensor [kg m^2]")
    if isinstance(arr, jax.core.Tracer):
        arr = jnp.asarray(arr, float)
        return jnp.diag(arr) if arr.shape == (3,) else arr
    if arr.shape == (3,):
        arr = np.diag(arr)
    if arr.shape != (3, 3):
        raise ParameterError(
            f"{_where(owner)}{name} must be a 3x3 inertia tensor or 3 principal moments, got shape {arr.shape}",
            name, value)
    if not np.all(np.isfinite(arr)):
        raise ParameterError(f"{_where(owner)}{name} contains NaN/inf: {_show(arr)}; pass finite moments",
                             name, value)
    if not np.allclose(arr, arr.T, rtol=1e-12, atol=1e-14 * max(np.abs(arr).max(), 1e-300)):
        raise ParameterError(
            f"{_where(owner)}{name} must be symmetric positive definite: it is not symmetric, got "
            f"{arr.tolist()}", name, value)
    ev = np.linalg.eigvalsh(arr)
    if not ev.min() > 0:
        raise ParameterError(
            f"{_where(owner)}{name} must be symmetric positive definite (eigenvalues {ev.tolist()}); "
            "every principal moment of a rigid body is > 0", name, value)
    moment_triangle(name, ev, owner=owner)
    return to_device(arr)


#: Relative slack of the realizability checks of inertias (rounding in moments computed
#: from dimensions: a thin disk or plate sits exactly on the triangle inequality's edge).
_REALIZABLE_RTOL = 1e-12


def moment_triangle(name, moments, *, owner="", value=None):
    """Principal moments (last axis: 3, any order; leading axes: members of a batch) of a
    physical rigid body obey the triangle inequality: each is at most the sum of the
    other two. (I_x = int (y^2 + z^2) dm <= int (x^2 + z^2) dm + int (x^2 + y^2) dm =
    I_y + I_z, with equality for a lamina in the y-z plane.) ParameterError otherwise;
    positivity is checked by the callers (``inertia_tensor``, ``principal_moments``,
    ``inertias``)."""
    ev = np.sort(np.asarray(moments, float), axis=-1)
    bad = ev[..., 2] > (ev[..., 0] + ev[..., 1]) * (1 + _REALIZABLE_RTOL)
    if bad.any():
        i = tuple(int(k) for k in np.argwhere(np.atleast_1d(bad))[0]) if bad.ndim else ()
        e = ev[i] if bad.ndim else ev
        where = f" (member {i[0] if len(i) == 1 else i})" if bad.ndim else ""
        raise ParameterError(
            f"{_where(owner)}{name} is not the inertia of a rigid body{where}: its largest principal moment "
            f"{e[2]:.6g} exceeds the sum {e[0] + e[1]:.6g} of the other two (principal moments {e.tolist()}); "
            "every principal moment of a body is at most the sum of the other two (equality: a flat "
            "lamina)", name, value if value is not None else moments)


def inertias(name, value, *, owner="", allow_zero=False):
    """Inertia tensors [kg m^2] of shape (..., 3, 3), every one checked at once (numpy):
    finite, symmetric, positive definite (semidefinite with ``allow_zero``: a point mass
    has zero inertia, a rod one zero moment) and obeying the triangle inequality of
    principal moments (``moment_triangle``). Returns the array (tracers pass)."""
    arr = _as_real(name, value, owner, "inertia tensors [kg m^2]")
    if isinstance(arr, jax.core.Tracer):
        return to_device(arr)
    if arr.shape[-2:] != (3, 3):
        raise ParameterError(f"{_where(owner)}{name} must hold 3x3 inertia tensors, got shape {arr.shape}",
                             name, value)
    if not np.all(np.isfinite(arr)):
        raise ParameterError(f"{_where(owner)}{name} contains NaN/inf; pass finite moments", name, value)
    scale = max(float(np.abs(arr).max(initial=0.0)), 1e-300)
    T = np.swapaxes(arr, -1, -2)
    asym = np.abs(arr - T).max(axis=(-1, -2)) > 1e-12 * scale
    if asym.any():
        i = int(np.argmax(asym.reshape(-1)))
        raise ParameterError(f"{_where(owner)}{name}[{i}] must be symmetric, got "
                             f"{arr.reshape(-1, 3, 3)[i].tolist()}", name, value)
    ev = np.linalg.eigvalsh(0.5 * (arr + T))
    low = ev[..., 0] < -1e-12 * scale if allow_zero else ~(ev[..., 0] > 0)
    if low.any():
        i = int(np.argmax(low.reshape(-1)))
        kind = "positive semidefinite (zero: a point mass)" if allow_zero else "positive definite"
        raise ParameterError(f"{_where(owner)}{name}[{i}] must be {kind}, got principal moments "
                             f"{ev.reshape(-1, 3)[i].tolist()}", name, value)
    moment_triangle(name, ev, owner=owner, value=value)
    return arr


def ball_moment(name, J, m, r, *, owner="", what="moment of inertia about a diameter [kg m^2]", label=None,
                names=("m", "r")):
    """A ball's moment of inertia about a diameter: 0 < J <= 2/3 m r^2, the thin spherical
    shell's (its mass as far out as a ball of radius r allows; a homogeneous ball has
    2/5 m r^2). ``label``: how the message writes J when the user passed something else
    (``name``, e.g. a radius of gyration k: "m k^2"). Element by element for batched
    parameters; tracers pass."""
    J = positive(name, J, owner=owner, what=what)
    if is_traced(J, m, r):
        return J
    shell = 2.0 / 3.0 * np.asarray(m, float) * np.asarray(r, float) ** 2
    bad = np.asarray(J) > shell * (1 + _REALIZABLE_RTOL)
    if bad.any():
        label = label or name
        mr = f"2/3 {names[0]} {names[1]}^2"
        raise ParameterError(
            f"{_where(owner)}{label} = {_show(J)} exceeds a thin spherical shell's {mr} = {_show(shell)}: no "
            f"ball of that mass and radius has it (a homogeneous ball has 2/5 {names[0]} {names[1]}^2); pass "
            f"0 < {label} <= {mr}", name, J, names=(name,) + tuple(names))
    return J


def shell_moment(Is, ms, Rs, *, owner=""):
    """A spherical shell's central moment Is [kg m^2]: 2/3 ms Rs^2 (a thin shell) when
    None, else 0 < Is <= 2/3 ms Rs^2 (``ball_moment``)."""
    return ball_moment("Is", 2.0 / 3.0 * ms * Rs**2 if Is is None else Is, ms, Rs, owner=owner,
                       what="central moment of inertia of the shell [kg m^2]", names=("ms", "Rs"))


def axisymmetric_moments(axial, transverse, *, names=("J_a", "J_t"), owner="", mass=None, radius=None,
                         mass_names=("m", "r")):
    """An axisymmetric body's principal moments: the axial one at most twice the
    transverse one (the triangle inequality of ``moment_triangle`` for (I_t, I_t, I_a);
    equality: a thin disk) and, given the body's mass and radius, at most m r^2 (all the
    mass on the rim). ``names``: the arguments as the user passed them (the error names
    the axial one). Element by element; tracers pass."""
    if is_traced(axial, transverse, mass, radius):
        return
    a, t = np.asarray(axial, float), np.asarray(transverse, float)
    bad = a > 2 * t * (1 + _REALIZABLE_RTOL)
    if bad.any():
        raise ParameterError(
            f"{_where(owner)}{names[0]} = {_show(axial)} exceeds twice {names[1]} = {_show(transverse)}: an "
            "axisymmetric body's axial moment is at most twice its transverse one (the triangle inequality "
            "of principal moments; a thin disk has equality)", names[0], axial, names=names)
    if mass is not None and radius is not None:
        rim = np.asarray(mass, float) * np.asarray(radius, float) ** 2
        bad = a > rim * (1 + _REALIZABLE_RTOL)
        if bad.any():
            raise ParameterError(
                f"{_where(owner)}{names[0]} = {_show(axial)} exceeds {mass_names[0]} {mass_names[1]}^2 = "
                f"{_show(rim)}: a body within radius {mass_names[1]} of its axis has an axial moment of at most "
                "that (all its mass on the rim)", names[0], axial, names=(names[0],) + tuple(mass_names))


def principal_moments(name, value, *, owner="", diagonal_reason=""):
    """Three positive principal moments (I1, I2, I3) [kg m^2]; a 3x3 array must be diagonal."""
    arr = _as_real(name, value, owner, "principal moments [kg m^2]")
    if isinstance(arr, jax.core.Tracer):
        arr = jnp.asarray(arr, float)
        return jnp.diag(arr) if arr.shape == (3, 3) else arr
    if arr.shape == (3, 3):
        if np.abs(arr - np.diag(np.diag(arr))).max() > 1e-14 * np.abs(arr).max():
            raise ParameterError(
                f"{_where(owner)}{name} must be diagonal{(': ' + diagonal_reason) if diagonal_reason else ''}; "
                "pass principal moments (I1, I2, I3)", name, value)
        arr = np.diag(arr)
    if arr.shape != (3,):
        raise ParameterError(
            f"{_where(owner)}{name} must be 3 principal moments (I1, I2, I3), got shape {arr.shape}", name, value)
    if not (np.all(np.isfinite(arr)) and np.all(arr > 0)):
        raise ParameterError(
            f"{_where(owner)}{name} must be positive principal moments, got {arr.tolist()}; pass "
            "finite values > 0", name, value)
    moment_triangle(name, arr, owner=owner, value=value)
    return to_device(arr)


# ------------------------------------------------------------------ groups
_GROUP_NAMES = {SO3Body: "SO(3)", SO3Spatial: "SO(3)", SE2Body: "SE(2)", UnitQuaternionBody: "S^3"}
_GROUP_SHAPES = {SO3Body: (3, 3), SO3Spatial: (3, 3), SE2Body: (3, 3), UnitQuaternionBody: (4,)}


def _is_group(space) -> bool:
    return type(space) in _GROUP_NAMES


def group_residual(space, a):
    """(residual, orientation) of a leaf on its group: max |R^T R - I| and det R
    (SO(3)); ||q| - 1| and 1 (S^3); the rotation block's error, the bottom row's
    distance from (0, 0, 1), and the block's det (SE(2)). jit/vmap-able."""
    if isinstance(space, UnitQuaternionBody):
        return jnp.abs(jnp.linalg.norm(a) - 1.0), jnp.ones((), a.dtype)
    if isinstance(space, SE2Body):
        A = a[:2, :2]
        r = jnp.maximum(jnp.max(jnp.abs(A.T @ A - jnp.eye(2))),
                        jnp.max(jnp.abs(a[2] - jnp.array([0.0, 0.0, 1.0]))))
        return r, jnp.linalg.det(A)
    return jnp.max(jnp.abs(a.T @ a - jnp.eye(3))), jnp.linalg.det(a)


def _polar(A):
    U, _, Vt = jnp.linalg.svd(A)
    return U @ Vt


def project_group(space, a):
    """The nearest group element (Frobenius norm): the polar factor of a rotation
    block, q / |q|. A reflection (det < 0) is left as it is (no rotation is near it)."""
    if isinstance(space, UnitQuaternionBody):
        return a / jnp.linalg.norm(a)
    if isinstance(space, SE2Body):
        A = a[:2, :2]
        P = _polar(A)
        P = jnp.where(jnp.linalg.det(P) > 0, P, A)
        return jnp.concatenate([jnp.concatenate([P, a[:2, 2:]], axis=1), jnp.array([[0.0, 0.0, 1.0]])], axis=0)
    P = _polar(a)
    return jnp.where(jnp.linalg.det(P) > 0, P, a)


def _path_name(name, path) -> str:
    out = name
    for k in path:
        if isinstance(k, jtu.SequenceKey):
            out += f"[{k.idx}]"
        elif isinstance(k, jtu.DictKey):
            out += f"[{k.key!r}]"
        elif isinstance(k, jtu.GetAttrKey):
            out += f".{k.name}"
        else:
            out += f"[{k}]"
    return out


def _group_parts(spaces, x, name="x0"):
    """[(part name, space, leaf)] for the group-valued leaves of state x."""
    out = []
    flat, _ = jtu.tree_flatten_with_path(spaces, is_leaf=is_space)
    for path, sp in flat:
        if _is_group(sp):
            leaf = x
            for k in path:
                leaf = leaf[k.idx] if isinstance(k, jtu.SequenceKey) else (
                    leaf[k.key] if isinstance(k, jtu.DictKey) else getattr(leaf, k.name))
            out.append((_path_name(name, path), sp, leaf))
    return out


def _map_groups(spaces, x, fn):
    """x with fn(space, leaf) applied to its group-valued leaves."""
    return jtu.tree_map(lambda sp, sub: fn(sp, sub) if _is_group(sp) else sub, spaces, x, is_leaf=is_space)


def rotation(name, value, *, owner="", tol=GROUP_TOL):
    """A 3x3 rotation matrix (R^T R = I within ``tol``, det +1), e.g. an attitude
    passed to ``initial_state``. GroupMembershipError otherwise."""
    arr = _as_real(name, value, owner, "a 3x3 rotation matrix")
    if isinstance(arr, jax.core.Tracer):
        return to_device(arr)
    if arr.shape != (3, 3):
        raise ParameterError(f"{_where(owner)}{name} must be a 3x3 rotation matrix, got shape {arr.shape}",
                             name, value)
    _check_group_value(name, SO3Body(), arr, tol, owner)
    return to_device(arr)


def unit_quaternion(name, value, *, owner="", tol=GROUP_TOL, normalize=False):
    """A unit quaternion (4,) (scalar first); ``normalize``: divide by its norm instead
    of checking it (a zero or NaN quaternion is still refused)."""
    arr = _as_real(name, value, owner, "a unit quaternion (scalar first)")
    if isinstance(arr, jax.core.Tracer):
        arr = jnp.asarray(arr, float)
        return arr / jnp.linalg.norm(arr) if normalize else arr
    if arr.shape != (4,):
        raise ParameterError(f"{_where(owner)}{name} must be a quaternion of shape (4,), got shape {arr.shape}",
                             name, value)
    if normalize:
        n = np.linalg.norm(arr)
        if not (np.isfinite(n) and n > 0):
            raise ParameterError(f"{_where(owner)}{name} must be a finite nonzero quaternion, got {_show(arr)}",
                                 name, value)
        arr = arr / n
    _check_group_value(name, UnitQuaternionBody(), arr, tol, owner)
    return to_device(arr)


def _group_message(name, space, residual, det, tol, owner, projected=False):
    g = _GROUP_NAMES[type(space)]
    if not np.isfinite(residual):
        return f"{_where(owner)}{name} contains NaN or inf; it must lie on {g}"
    if det <= 0:
        return (f"{_where(owner)}{name} is not on {g}: its rotation block has det = {det:.3g} "
                "(a reflection or a singular matrix), which no projection turns into a rotation; "
                "fix the orientation (e.g. negate one axis)")
    what = {"SO(3)": "|R^T R - I|", "SE(2)": "|A^T A - I| (A the rotation block; bottom row (0, 0, 1))",
            "S^3": "||q| - 1|"}[g]
    if projected:
        return (f"{_where(owner)}{name} is still off {g} after projection: {what} = {residual:.3e} "
                f"> tol = {tol:.1e}")
    return (f"{_where(owner)}{name} is not on {g}: {what} = {residual:.3e} > tol = {tol:.1e}; "
            "pass project=True to simulate() to replace it by the nearest group element, or fix it")


def _check_group_value(name, space, arr, tol, owner):
    r, d = (float(v) for v in group_residual(space, jnp.asarray(arr)))
    if not (np.isfinite(r) and r <= tol and d > 0):
        raise GroupMembershipError(_group_message(name, space, r, d, tol, owner), name, r, tol)


# ------------------------------------------------------------------ states
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
    from .mechanics.lagrangian import ConstrainedLagrangian
    from .mechanics.lie_lagrangian import LieLagrangian

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
    from .mechanics.lagrangian import ConstrainedLagrangian
    from .mechanics.lie_lagrangian import LieLagrangian

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
            from .mechanics.system import AbstractSystem

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


_REFERENCE_SHAPES: dict = {}


def single_member(system, *, owner=""):
    """Refuse a system that holds a batch of parameter sets (an array parameter with a
    leading member axis, e.g. built for ``simulate_batch`` by ``nhjax.stack``) where one
    member is needed (a scene's ``initial_state``): ParameterError naming the field. A
    field is batched when it has more axes than in the scene built with its defaults."""
    cls = type(system)
    if cls not in _REFERENCE_SHAPES:
        try:  # the default scene's structure, traced (nothing computed, nothing compiled)
            ref = jax.eval_shape(cls)
            _REFERENCE_SHAPES[cls] = (jtu.tree_structure(ref), [len(a.shape) for a in jtu.tree_leaves(ref)])
        except Exception:  # noqa: BLE001 - no defaults to compare with: nothing to check
            _REFERENCE_SHAPES[cls] = None
    ref = _REFERENCE_SHAPES[cls]
    if ref is None or is_traced(system):
        return
    flat, treedef = jtu.tree_flatten_with_path(system)
    if treedef != ref[0]:
        return
    for (path, leaf), nd in zip(flat, ref[1]):
        if np.ndim(leaf) > nd:
            field = _path_name("", path).lstrip(".")
            raise ParameterError(
                f"{_where(owner)}{cls.__name__} holds a batch of {np.shape(leaf)[0]} parameter sets ({field} has "
                f"shape {np.shape(leaf)}), and a state is one member's: build the state with one member's "
                f"{cls.__name__} (e.g. {cls.__name__}({field}=...) with a scalar), or vmap initial_state over "
                "the members", field, leaf)


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
