"""Checks of arguments and parameters that need no knowledge of systems: numbers, signs
and ranges, integers and choices, functions, inertias, group elements (rotations, unit
quaternions), a system holding one member; and the runtime-error helpers
(``error_if``, ``first_error_if``).

This is the lower half of nhjax's validation (see ``nhjax._validate`` for what is
checked where): it imports only ``nhjax.errors`` and ``nhjax.lie``, so that
``nhjax.mechanics`` can check its constructors' arguments with it while
``nhjax._validate``, which checks states against the mechanics' system classes, sits
above ``nhjax.mechanics``. ``nhjax._validate`` re-exports every name here.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from ._programs import branched_error_if
from .errors import GroupMembershipError, ParameterError
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


def error_if(x, pred, msg):
    """``equinox.error_if`` in this thread's error mode (``_programs.error_mode``:
    callbacks by default, NaN under controls' ``nan_errors``)."""
    return branched_error_if(x, pred, 0, [msg])


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
    return branched_error_if(x, jnp.any(preds), jnp.argmax(preds), [m for _, m in checks])


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
    try:  # (np.iscomplexobj converts: a ragged sequence raises there)
        bad = isinstance(value, (str, bytes)) or value is None or np.iscomplexobj(value)
    except (TypeError, ValueError):
        bad = True
    if bad:
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
    return jax.device_put(np.asarray(value, float))


def stacked(values):
    """``jnp.stack(values)`` (floats), without an eager program when every value is
    concrete (``to_device``)."""
    if any(isinstance(v, jax.core.Tracer) for v in jtu.tree_leaves(values)):
        return jnp.stack([jnp.asarray(v, float) for v in values])
    return to_device(np.stack([np.asarray(v, float) for v in values]))


def on_host(fn, *args):
    """``fn(xp, *args)``: with ``xp = numpy`` on the host when no argument is traced (the
    result, a pytree of arrays, then sent to the device as float64 by ``to_device``), with
    ``xp = jax.numpy`` under a trace. For the few operations of a start state or of derived
    parameters: each eager ``jnp`` operation is an XLA program of its own, compiled (or
    looked up) in every new process before the first answer. ``args``: numbers and arrays
    (or pytrees of them); ``fn`` uses only functions that numpy and jax.numpy share."""
    leaves = jtu.tree_leaves(args)
    if any(isinstance(v, jax.core.Tracer) for v in leaves):
        return fn(jnp, *args)
    host = jtu.tree_map(lambda v: np.asarray(v, float), args)
    return jtu.tree_map(to_device, fn(np, *host))


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
    if Is is None:  # on the host where the numbers are concrete (no eager programs)
        Is = 2.0 / 3.0 * ms * Rs**2 if is_traced(ms, Rs) else 2.0 / 3.0 * np.asarray(ms) * np.asarray(Rs) ** 2
    return ball_moment("Is", Is, ms, Rs, owner=owner,
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


def group_residual(space, a, xp=jnp):
    """(residual, orientation) of a leaf on its group: max |R^T R - I| and det R
    (SO(3)); ||q| - 1| and 1 (S^3); the rotation block's error, the bottom row's
    distance from (0, 0, 1), and the block's det (SE(2)). jit/vmap-able; ``xp=np``
    computes it on the host (a concrete value: no eager programs)."""
    if isinstance(space, UnitQuaternionBody):
        return xp.abs(xp.linalg.norm(a) - 1.0), xp.ones((), a.dtype)
    if isinstance(space, SE2Body):
        A = a[:2, :2]
        r = xp.maximum(xp.max(xp.abs(A.T @ A - xp.eye(2))),
                       xp.max(xp.abs(a[2] - xp.asarray([0.0, 0.0, 1.0]))))
        return r, xp.linalg.det(A)
    return xp.max(xp.abs(a.T @ a - xp.eye(3))), xp.linalg.det(a)


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
    r, d = (float(v) for v in group_residual(space, np.asarray(arr, float), xp=np))
    if not (np.isfinite(r) and r <= tol and d > 0):
        raise GroupMembershipError(_group_message(name, space, r, d, tol, owner), name, r, tol)


# ------------------------------------------------------------------ states

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
