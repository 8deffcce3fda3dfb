"""Grids of optimal-control problems in one call: Pontryagin shooting
(``solve_pontryagin_batch``) and the direct method (``solve_direct_batch``) on many
problems of one structure at once.

``solve_pontryagin_batch(ocps, p0_guess, nu_guess)`` takes a list of ``OCP``s that
differ in numbers only (x0, targets, the horizon T, weights, the system's parameters),
or their stack (``stack_members``), and solves them all in one compiled program: the members' numbers are stacked on a
leading axis and ``solve_pontryagin``'s whole root find (``_indirect_body``: Newton or
Levenberg–Marquardt on the shooting residual, the extremal and its cost) runs over
them, ``lanes`` members side by side (vmapped; by default one) and the groups one
after another.
Within a group the iteration runs until every member has stopped; a member that
stopped keeps its values (JAX's batched while loop selects them), so it is the same
solve as alone, to rounding. The program is one per structure and batch size and is
kept in nhjax's program cache like ``solve_pontryagin``'s.

Each member gets a status, ``converged`` / ``max_iterations`` / ``stalled`` /
``non_finite`` / ``non_finite_input``, with a reason; a member that fails does not
spoil the others (the ODE solves and the linear algebra are per member; a member
whose numbers or guesses are NaN/inf is not run at all and is flagged instead).

Members that differ in structure (other state or constraint sizes, another running
cost or system type, another integer setting) cannot share a program: ``GridError``
names the first member and the field that differ, before any numerics.

``solve_direct_batch(ocps, param, guess)`` runs ``solve_direct_sqp``'s iteration
(``controls.sqp.sqp_iteration``, a generator that asks for the points it needs
simulated) on every member on the host, and simulates the points of all members still
iterating in one compiled program per round (``_values_and_jacobian_batch``: the
shooting's values and Jacobian, vmapped over ``lanes`` members). The QPs, line
searches and Hessian updates stay per member, so each member takes the iterates it
takes alone.
"""

from __future__ import annotations

import dataclasses
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from .pontryagin import (
    HamiltonianSystem,
    _check_pontryagin,
    _indirect_body,
    _root_options,
    _Shooting,
    _shooting_converged,
)
from ._result import DirectResult
from .newton import _control_cost_hessian
from .newton import _Shooting as _DirectShooting
from nhjax import _validate as V

from .problem import (OCP, ProblemError, Progress, as_problem_error, batch_workers, check_tolerances, compiled,
                      host_array, run_in_shares)
from .sqp import _check_sqp, parameter_bounds, sqp_iteration

__all__ = ["BatchResult", "DirectBatchResult", "GridError", "solve_direct_batch", "solve_pontryagin_batch",
           "stack_members"]

#: The statuses a member can end with.
STATUSES = ("converged", "max_iterations", "stalled", "non_finite", "non_finite_input")


class GridError(ProblemError):
    """Members of a batch that differ in structure (not only in numbers)."""


def _is_number(x) -> bool:
    """A leaf that may differ between members: an array, or a Python/NumPy float (a
    scene's parameter). Integers and booleans are structure (sizes, switches)."""
    if isinstance(x, (bool, np.bool_)):
        return False
    if eqx.is_array(x):
        return True
    return isinstance(x, (float, np.floating))


def _kind(x):
    """(shape, True) for a number leaf, (None, False) for any other: what members must share."""
    return (np.shape(x), True) if _is_number(x) else (None, False)


def _path_name(path) -> str:
    return "".join(str(k) for k in path) or "(the member itself)"


def stack_members(members, *, owner: str = "stack_members", what: str = "member"):
    """One pytree whose number leaves (arrays and floats, ``_is_number``) are the
    members' leaves stacked on a new leading axis; everything else must be equal
    across members. Raises ``GridError`` naming the first member and field that
    differ (types, tree structure, an array's shape, a non-number leaf).

    Stacked ``OCP``s are a grid that ``solve_pontryagin_batch`` takes in place of their
    list; a field can then be set for every member at once, e.g. B targets from one
    problem stacked B times::

        grid = controls.stack_members([ocp] * B)
        grid = eqx.tree_at(lambda g: g.terminal_constraints.target, grid, targets)  # (B, m)
    """
    members = list(members)
    if not members:
        raise ProblemError(f"{owner}: no {what}s: pass a non-empty list")
    first = members[0]
    flat0, tree0 = jtu.tree_flatten(first)
    kinds0 = [_kind(v) for v in flat0]
    flats = [flat0]
    for member in members[1:]:
        flat, tree = jtu.tree_flatten(member)
        flats.append(flat)
        if (type(member) is not type(first) or tree != tree0 or len(flat) != len(flat0)
                or any(_kind(v) != k for v, k in zip(flat, kinds0))
                or any(not k[1] and not _same(v, v0) for v, v0, k in zip(flat, flat0, kinds0))):
            break
    else:
        return jtu.tree_unflatten(tree0, [np.stack([np.asarray(f[k]) for f in flats]) if kinds0[k][1] else flat0[k]
                                          for k in range(len(flat0))])
    # a member differs: find and name the first difference
    leaves0, tree0 = jtu.tree_flatten_with_path(first)
    for i, member in enumerate(members[1:], start=1):
        if type(member) is not type(first):
            raise GridError(f"{owner}: {what} {i} is a {type(member).__name__}, {what} 0 a "
                            f"{type(first).__name__}: a batch holds problems of one structure")
        leaves, tree = jtu.tree_flatten_with_path(member)
        paths0, paths = [p for p, _ in leaves0], [p for p, _ in leaves]
        if paths != paths0:
            other = _first_type_difference(member, first)
            if other is not None:  # e.g. another system class: say which, not the first leaf that moved
                where, ta, tb = other
                raise GridError(f"{owner}: {what} {i}'s {where} is a {ta}, {what} 0's a {tb}: a batch holds "
                                "problems of one structure (the same classes; they may differ in numbers only)")
            diff = next((a for a, b in zip(paths, paths0) if a != b), None)
            where = _path_name(diff) if diff is not None else f"{len(paths)} leaves against {len(paths0)}"
            raise GridError(f"{owner}: {what} {i} differs from {what} 0 in structure at {where}: a batch holds "
                            "problems that differ in numbers only (x0, targets, T, weights, parameters)")
        for (path, a), (_, b) in zip(leaves, leaves0):
            name = _path_name(path)
            if _is_number(a) != _is_number(b):
                raise GridError(f"{owner}: {what} {i}'s {name} is a {type(a).__name__}, {what} 0's a "
                                f"{type(b).__name__}")
            if _is_number(a):
                sa, sb = np.shape(a), np.shape(b)
                if sa != sb:
                    raise GridError(f"{owner}: {what} {i}'s {name} has shape {sa}, {what} 0's {sb}: a batch "
                                    "holds problems of one structure (state, control and constraint sizes)")
            elif not _same(a, b):
                raise GridError(f"{owner}: {what} {i}'s {name} is {a!r}, {what} 0's {b!r}: this setting is "
                                "part of the problem's structure (one compiled program per value)")
        if tree != tree0:  # static fields of modules (after the leaves agree)
            raise GridError(f"{owner}: {what} {i} differs from {what} 0 in a static setting of its modules "
                            f"({_first_static_difference(member, first)}): one compiled program per value")
    raise GridError(f"{owner}: the {what}s differ in structure")  # (not reached: a difference is named above)


def _same(a, b) -> bool:
    try:
        return bool(a == b)
    except Exception:  # noqa: BLE001 (an object without a truthy ==: compare identity)
        return a is b


def _first_type_difference(a, b, path=""):
    """(path, type of a, type of b) at the first node, walking the fields of modules and
    dataclasses and the entries of dicts, lists and tuples in order, where a and b are
    of different classes (two numbers of different kinds do not count: they may differ);
    None if there is none."""
    if _is_number(a) and _is_number(b):
        return None
    if type(a) is not type(b):
        return path or "(the member itself)", type(a).__name__, type(b).__name__
    if dataclasses.is_dataclass(a):
        items = [(f".{f.name}", getattr(a, f.name, None), getattr(b, f.name, None)) for f in dataclasses.fields(a)]
    elif isinstance(a, dict) and list(a) == list(b):
        items = [(f"[{k!r}]", a[k], b[k]) for k in a]
    elif isinstance(a, (list, tuple)) and len(a) == len(b):
        items = [(f"[{j}]", x, y) for j, (x, y) in enumerate(zip(a, b))]
    else:
        return None
    for name, x, y in items:
        found = _first_type_difference(x, y, path + name)
        if found is not None:
            return found
    return None


def _first_static_difference(a, b) -> str:
    """Where a and b (of equal leaves) first differ in a static setting: the field
    whose subtree differs, down to the static field itself (its two values)."""
    if dataclasses.is_dataclass(a) and type(a) is type(b):
        for f in dataclasses.fields(a):
            va, vb = getattr(a, f.name, None), getattr(b, f.name, None)
            if f.metadata.get("static", False) and not _same(va, vb):
                return f"{type(a).__name__}.{f.name}: {va!r} against {vb!r}"
            if jtu.tree_structure(va) != jtu.tree_structure(vb):
                inner = _first_static_difference(va, vb)
                return f"{type(a).__name__}.{f.name}" + (f" > {inner}" if inner else "")
    return ""


class _Statuses:
    """What both batch results answer from their ``status`` array: ``converged``,
    ``len()`` and ``counts()`` over the statuses the class names (``STATUS_NAMES``)."""

    STATUS_NAMES: tuple = ()

    @property
    def converged(self) -> np.ndarray:
        return self.status == "converged"

    def __len__(self) -> int:
        return len(self.status)

    def counts(self) -> dict:
        """How many members ended with each status."""
        return {s: int(np.sum(self.status == s)) for s in self.STATUS_NAMES if np.any(self.status == s)}


def _problem_list(ocps, owner):
    """The batch's problems as a non-empty list of ``OCP``s (one OCP: a list of one)."""
    if not isinstance(ocps, OCP):
        try:
            ocps = list(ocps)
        except TypeError:
            raise ProblemError(f"{owner}: the problems must be a list of controls.OCP (or one OCP, or a stack of "
                               f"them), got {type(ocps).__name__}") from None
    else:
        ocps = [ocps]
    if not ocps:
        raise ProblemError(f"{owner}: no problems: pass a non-empty list of OCPs")
    for i, o in enumerate(ocps):
        if not isinstance(o, OCP):
            raise ProblemError(f"{owner}: member {i} is a {type(o).__name__}, not a controls.OCP")
    return ocps


def _stacked_problem(ocps, owner):
    """(stack, its first member, B) when ``ocps`` is a stack of problems
    (``stack_members``: an OCP whose vector x0 has a leading member axis, as no OCP
    built by ``OCP(...)`` has), else None. Every number leaf of a stack must have the
    members on axis 0 (``GridError`` naming the first that has not)."""
    if not (isinstance(ocps, OCP) and getattr(ocps.x0, "ndim", 1) == 2):
        return None
    B = int(ocps.x0.shape[0])
    for path, leaf in jtu.tree_flatten_with_path(ocps)[0]:
        if _is_number(leaf) and (np.ndim(leaf) == 0 or np.shape(leaf)[0] != B):
            raise GridError(f"{owner}: a stack of {B} problems (x0 of shape {tuple(ocps.x0.shape)}) has "
                            f"{_path_name(path)} of shape {np.shape(leaf)}: every number of a stack has the "
                            f"{B} members on axis 0 (build it with controls.stack_members)")
    if B == 0:
        raise ProblemError(f"{owner}: a stack of no problems: pass a non-empty list of OCPs")
    first = jtu.tree_map(lambda a: a[0] if _is_number(a) else a, ocps)
    return ocps, first, B


@dataclasses.dataclass(frozen=True)
class BatchResult(_Statuses):
    """Outcome of ``solve_pontryagin_batch``, member by member (axis 0 is the member).

    p0 : (B, n) initial costates [cost units per state unit]; nu : (B, m) multipliers.
    cost : (B,) Phi(x(T)) + int_0^T L dt along each member's extremal.
    violation : (B,) max |psi(x(T))| at each extremal's end.
    residual : (B,) max |shooting residual| at each member's last point.
    iterations : (B,) Newton / Levenberg–Marquardt steps each member took.
    status : (B,) one of ``STATUSES``; ``converged`` (B,) bool is status == "converged".
    reasons : one sentence per member ("" when converged).
    xs : (B, 401, 2n) each extremal's (x, p) at ``ts``; controls : (B, 401, k) u* there.
    ts : (B, 401) the saved times (each member's own [0, T]).
    started_from : (B,) -1 for a member solved from its own guess, else the index of
        the neighbour whose solution started it (``grid`` continuation).
    seconds : wall time of the call (the compile included on a first call) [s].
    NaN rows for members that were not run (``non_finite_input``).
    """

    p0: np.ndarray
    nu: np.ndarray
    cost: np.ndarray
    violation: np.ndarray
    residual: np.ndarray
    iterations: np.ndarray
    status: np.ndarray
    reasons: list
    xs: np.ndarray
    ts: np.ndarray
    controls: np.ndarray
    started_from: np.ndarray
    seconds: float

    STATUS_NAMES = STATUSES


@compiled(errors="off")  # (equinox's checks would fail every member when one fails)
def _indirect_batch(sh, ocps, z0, tol, max_steps, damped: bool, lanes: int):
    """``_indirect_body`` of the shooting ``sh`` with its problem replaced by each
    member of ``ocps`` (every array leaf with the member on axis 0; ``z0`` likewise):
    one program for the whole grid, ``lanes`` members at a time in lockstep (vmapped),
    the groups one after another (``jax.lax.map``)."""
    dynamic, static = eqx.partition(ocps, eqx.is_array)

    def one(args):
        d, z = args
        member = eqx.tree_at(lambda s: s.ham.ocp, sh, eqx.combine(d, static))
        return _indirect_body(member, z, tol, max_steps, damped, one_solve=False)

    return jax.lax.map(one, (dynamic, z0), batch_size=lanes)


def _screen(stacked, z0, owner):
    """Members whose numbers (the stacked pytree's number leaves) or starting guesses
    (rows of ``z0``) hold NaN/inf are flagged, not run: their rows are filled with the
    first finite member's (the program needs some numbers there). Returns (the stacked
    pytree on the device, z0, finite (B,) bool)."""
    B = z0.shape[0]
    numbers = [leaf for leaf in jtu.tree_leaves(stacked) if _is_number(leaf) and np.ndim(leaf) >= 1]
    finite = np.all(np.isfinite(z0), axis=1)
    for leaf in numbers:
        finite &= np.all(np.isfinite(np.asarray(leaf).reshape(B, -1)), axis=1)
    if not finite.any():
        raise ProblemError(f"{owner}: every member has NaN/inf numbers or guesses: nothing to solve")
    if not finite.all():
        donor = int(np.argmax(finite))
        stacked = jtu.tree_map(lambda a: np.where(finite.reshape((B,) + (1,) * (np.ndim(a) - 1)), a, a[donor])
                               if _is_number(a) and np.ndim(a) >= 1 else a, stacked)
        z0 = np.where(finite[:, None], z0, z0[donor])
    stacked = jtu.tree_map(lambda a: jax.device_put(a) if isinstance(a, np.ndarray) else a, stacked)
    return stacked, z0, finite


def _guesses(name, guess, B, size, owner):
    if guess is None:
        return np.zeros((B, size))
    wanted = (f"{owner}: {name} must have shape ({size},) (the same for every member) or ({B}, {size}) "
              f"(one row per member)")
    if isinstance(guess, (list, tuple)):  # one row per member, as a list: rows of one length
        shapes = [np.shape(g) for g in guess]
        if len(set(shapes)) > 1:
            raise ProblemError(f"{wanted}; got a list of rows of shapes {', '.join(str(s) for s in shapes)}")
    with as_problem_error():  # (real numbers; NaN/inf pass: such a member is flagged, not run)
        g = np.asarray(V._as_real(name, guess, owner, "starting guess"), float)
    if g.shape == (size,):
        return np.broadcast_to(g, (B, size)).copy()
    if g.shape != (B, size):
        raise ProblemError(f"{wanted}, got {g.shape}")
    return g


def solve_pontryagin_batch(
    ocps,
    p0_guess=None,
    nu_guess=None,
    *,
    solver: str = "newton",
    u_star: str = "quadratic",
    rtol: float = 1e-11,
    atol: float = 1e-11,
    tol: float = 1e-10,
    max_steps: int = 25,
    max_ode_steps: int = 2048,
    lanes: int = 1,
    grid: tuple | None = None,
    grid_rounds: int = 8,
    progress: bool = True,
    workers: int | None = None,
) -> BatchResult:
    """Single-shooting Pontryagin solves of many problems of one structure in one program.

    ocps : a list of B ``OCP``s that differ in numbers only (``GridError`` otherwise), or
        their stack (``controls.stack_members(ocps)``: every number with the members on
        axis 0), in which a field can be set for the whole grid at once
        (``eqx.tree_at(lambda s: s.terminal_constraints.target, stack, targets)``, with
        ``targets`` (B, m)) instead of rebuilding B problems. A stack's members are
        checked as one structure and for finite numbers, not one by one as OCPs (a
        start outside a chart shows in that member's status).
    p0_guess : (n,) the same costate guess for every member, or (B, n) one per member
        (default zeros); nu_guess : (m,) or (B, m) likewise for the multipliers.
    solver, u_star, rtol, atol, tol : as ``solve_pontryagin`` (shared).
    max_steps, max_ode_steps : budgets of root-finding steps and of ODE steps of each
        extremal solve, smaller than ``solve_pontryagin``'s (100 and 100 000): the
        members run in lockstep (the batched loops run until every member is done),
        so a member that wanders (Newton far from any root, an extremal that turns
        stiff) would hold up the whole grid for as long as it takes. Newton from a
        good start (a neighbour, a continuation stage) converges in well under 25
        steps; a member over either budget stops with its status saying so.
    lanes : members solved side by side (vmapped, in lockstep: a group takes its
        slowest member's iterations and ODE steps); the groups run one after
        another in the same program. Default 1, each member's loops on their own:
        on the somersault grids, vmapped lanes ran no faster where the members take
        the same steps, and slower where they differ (the map over turns and bends:
        a group waits for its slowest member, and the batched loops select instead of
        branching).
    grid : the members' grid shape (members in C order over it, e.g. (16, 16) for
        16 x 16 problems), for continuation along the grid: after the first pass,
        each member that did not converge is solved again from the solution of its
        nearest converged neighbour (grid distance, |di| + |dj| + ...), round after
        round while a round converges more members (at most ``grid_rounds``; each
        round reruns the batch's program, in which converged members stop after one
        step). ``BatchResult.started_from`` says which neighbour each member's
        answer started from. "converged" means an extremal (Pontryagin's conditions
        hold), as in ``solve_pontryagin``; a start far from the optimum can reach
        another one: the bent cat (theta0 = 1) turning by -4 rad reached one of
        4.6 J s straight from its loop, against 0.48 J s by continuation in the turn
        (experiments/somersault_map.py walks the turn in stages).
    progress : a progress line when the batch ends, with the status counts.
    workers : threads that run shares of the members at once, each share the same
        compiled program (default: 2 where the process may use two or more CPUs, 1
        inside a Dask worker, never more than the batch has groups of ``lanes``
        members). A member's answer does not depend on the share it ran in (to the
        last bit).

    Each member's answer is that of ``solve_pontryagin`` on it alone with the same
    options (the same iteration, vmapped). Returns a ``BatchResult``; nothing is raised
    for a member that fails: its status and reason say why.
    """
    owner = "solve_pontryagin_batch"
    t_start = time.perf_counter()
    given = _stacked_problem(ocps, owner)
    if given is None:
        ocps = _problem_list(ocps, owner)
        for o in ocps:
            _check_pontryagin(o, owner, solver, u_star)
    else:
        _check_pontryagin(given[1], owner, solver, u_star)
    check_tolerances(owner, rtol=rtol, atol=atol, tol=tol, max_steps=(max_steps, "int"),
                     max_ode_steps=(max_ode_steps, "int"), lanes=(lanes, "int"), grid_rounds=(grid_rounds, "int"))
    if given is None:
        stacked = stack_members(ocps, owner=owner, what="problem")  # structure first, before any numerics
        first, B = ocps[0], len(ocps)
    else:
        stacked, first, B = given
    coords = None if grid is None else _grid_coordinates(grid, B, owner)
    lanes = min(int(lanes), B)
    workers = batch_workers(workers, B, lanes, owner)
    rt, at = host_array(rtol), host_array(atol)
    sh = _Shooting(HamiltonianSystem(first, u_star), rt, at, 1, int(max_ode_steps))
    n, m = first.x0.shape[0], first.n_constraints
    P0, NU = _guesses("p0_guess", p0_guess, B, n, owner), _guesses("nu_guess", nu_guess, B, m, owner)
    z0 = np.concatenate([P0, NU], axis=1)
    stacked, z0, finite = _screen(stacked, z0, owner)
    bar = Progress(progress, 1, f"Pontryagin batch of {B} ({'Newton' if solver == 'newton' else 'Levenberg-Marquardt'})")
    options = (*_root_options(tol, max_steps, solver), lanes)

    def args_of(part):
        problems, z0 = part
        return (sh, jtu.tree_map(lambda a: jax.device_put(a) if isinstance(a, np.ndarray) else a, problems), z0, *options)

    def run(z0):
        # (every array of the stack has the members on axis 0)
        z, res, steps, traj, us, cost, viol = run_in_shares(_indirect_batch, args_of, (stacked, z0), B, workers, lanes)
        out = [np.array(a, float) for a in (z, res, cost, viol, traj.xs, traj.ts, us)]
        return [*out, np.array(steps)]

    z, res, cost, viol, xs, ts, us, steps = run(z0)
    started_from = np.full(B, -1)
    if coords is not None:
        for _ in range(int(grid_rounds)):
            ok = finite & _shooting_converged(res, tol)
            failed = finite & ~ok
            if not failed.any() or not ok.any():
                break
            # each failed member from its nearest converged neighbour's solution; the
            # converged ones from their own (they stop after one step)
            dist = np.abs(coords[failed][:, None, :] - coords[ok][None, :, :]).sum(-1)
            nearest = np.flatnonzero(ok)[np.argmin(dist, axis=1)]
            start = z.copy()
            start[failed] = z[nearest]
            again = run(np.where(finite[:, None], start, z0))
            gained = failed & _shooting_converged(again[1], tol)
            if not gained.any():
                break
            for mine, new in zip((z, res, cost, viol, xs, ts, us, steps), again):
                mine[gained] = new[gained]
            started_from[gained] = nearest[gained[failed]]
    status, reasons = _statuses(z, res, steps, finite, tol, max_steps, solver)
    bad = ~finite
    for a in (z, res, cost, viol, xs, us):
        a[bad] = np.nan
    result = BatchResult(p0=z[:, :n], nu=z[:, n:n + m], cost=cost, violation=viol, residual=res, iterations=steps,
                         status=status, reasons=reasons, xs=xs, ts=ts, controls=us, started_from=started_from,
                         seconds=time.perf_counter() - t_start)
    bar.update(**{k.replace("_", " "): v for k, v in result.counts().items()})
    bar.finish(bool(result.converged.all()))
    return result


def _grid_coordinates(grid, B, owner):
    """(B, d) integer coordinates of the members on a grid of shape ``grid`` (C order)."""
    items = list(np.ravel(grid)) if isinstance(grid, np.ndarray) else grid if isinstance(grid, (tuple, list)) else (grid,)
    with as_problem_error():
        shape = tuple(V.integer("grid", g, minimum=1, owner=owner, what="the grid's shape: a tuple of positive "
                                                                        "integers") for g in items)
    if not shape or min(shape) < 1 or int(np.prod(shape)) != B:
        raise ProblemError(f"{owner}: grid {shape} does not hold the {B} members (its product must be {B})")
    return np.stack(np.unravel_index(np.arange(B), shape), axis=1)


def _statuses(z, res, steps, finite, tol, max_steps, solver):
    """Each member's status and reason from its outputs (``solve_pontryagin``'s test of
    convergence: a finite residual below 1e3 tol)."""
    B = len(res)
    status, reasons = np.empty(B, dtype=object), []
    for i in range(B):
        if not finite[i]:
            s, why = "non_finite_input", "its numbers or guesses hold NaN/inf; not solved"
        elif not (np.all(np.isfinite(z[i])) and np.isfinite(res[i])):
            s, why = "non_finite", ("the iteration left the region where the extremal can be integrated or "
                                    "diverged to NaN/inf" + ("; try solver='lm' or a closer guess"
                                                             if solver == "newton" else "; try a closer guess"))
        elif _shooting_converged(res[i], tol):
            s, why = "converged", ""
        elif steps[i] >= max_steps:
            s, why = "max_iterations", f"{max_steps} steps taken, shooting residual still {res[i]:.2e}"
        else:
            s, why = "stalled", (f"stopped at shooting residual {res[i]:.2e} > 1e3 tol: a step led to an extremal "
                                 "that cannot be integrated (within max_ode_steps), or the steps stopped "
                                 "shrinking (no root near this start, a singular Jacobian); try "
                                 + ("solver='lm', " if solver == "newton" else "") + "a closer guess or "
                                 "continuation from an easier member")
        status[i] = s
        reasons.append(why)
    return status.astype(str), reasons


# ------------------------------------------------------------------ the direct method
#: The statuses a member of ``solve_direct_batch`` can end with.
DIRECT_STATUSES = ("converged", "max_iterations", "stalled", "infeasible", "non_finite", "non_finite_input")


@dataclasses.dataclass(frozen=True)
class DirectBatchResult(_Statuses):
    """Outcome of ``solve_direct_batch``, member by member (axis 0 is the member).

    params : (B, P) each member's optimal control parameters.
    cost : (B,) Phi(x(T)) + int_0^T L dt at them; violation : (B,) max |psi(x(T))|.
    multipliers : (B, m) lam (dJ + lam . dpsi = 0 over the parameters not at a bound).
    iterations : (B,) SQP iterations each member took.
    status : (B,) one of ``DIRECT_STATUSES``: "converged"; "max_iterations";
        "stalled" (the line search found no decrease); "infeasible" (the linearized
        terminal constraints cannot be met: within the control bounds, or at all where
        their Jacobian is rank deficient at the member's point); "non_finite"
        (the cost or constraints, or their derivatives, are not finite or all zero at
        the member's guess); "non_finite_input" (NaN/inf in its numbers or guess: not
        run). ``converged`` (B,) bool is status == "converged".
    reasons : one sentence per member ("" when converged).
    results : each member's ``DirectResult`` (as ``solve_direct_sqp`` returns it: its
        control, message and history), None for a member that was not solved.
    rounds : the batched evaluations the call made (every member that was still
        iterating had one point simulated in each).
    seconds : wall time of the call (the compile included on a first call) [s].
    NaN rows for members that were not solved.
    """

    params: np.ndarray
    cost: np.ndarray
    violation: np.ndarray
    multipliers: np.ndarray
    iterations: np.ndarray
    status: np.ndarray
    reasons: list
    results: list
    rounds: int
    seconds: float

    STATUS_NAMES = DIRECT_STATUSES


@compiled(errors="off")  # (equinox's checks would fail every member when one fails)
def _values_and_jacobian_batch(sh, ocps, params, Z, lanes: int):
    """``controls.newton._values_and_jacobian`` of the shooting ``sh`` with its problem
    and parametrization replaced by each member's (``ocps``, ``params``: array leaves
    with the member on axis 0; rows of ``Z`` the points): (Y, D), rows NaN for a member
    whose simulation did not reach T (max steps, a guard) or is not finite. ``lanes``
    members side by side (vmapped), the groups one after another (``jax.lax.map``)."""
    ocp_dynamic, ocp_static = eqx.partition(ocps, eqx.is_array)
    param_dynamic, param_static = eqx.partition(params, eqx.is_array)

    def one(args):
        od, pd, z = args
        member = eqx.tree_at(lambda s: (s.ocp, s.param), sh,
                             (eqx.combine(od, ocp_static), eqx.combine(pd, param_static)))
        y, vjp, solved = jax.vjp(lambda z: member.values(z, tangents=True, solved=True), z, has_aux=True)
        D = jax.vmap(vjp)(jnp.eye(y.shape[0], dtype=y.dtype))[0]
        good = solved & jnp.all(jnp.isfinite(y)) & jnp.all(jnp.isfinite(D))
        return jnp.where(good, y, jnp.nan), jnp.where(good, D, jnp.nan)

    return jax.lax.map(one, (ocp_dynamic, param_dynamic, Z), batch_size=lanes)


def _direct_status(result):
    """(status, reason) of one member's ``DirectResult``."""
    if result.converged:
        return "converged", ""
    msg = result.message
    if msg.startswith("the linearized terminal constraints"):
        return "infeasible", msg
    if msg.startswith("line search failed"):
        return "stalled", msg
    return "max_iterations", f"{msg}: violation {result.violation:.2e} after {result.iterations} iterations"


def solve_direct_batch(
    ocps,
    param,
    guess=None,
    *,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    ctol: float = 1e-8,
    gtol: float = 1e-9,
    ftol: float = 1e-12,
    max_iter: int = 100,
    max_ode_steps: int = 20_000,
    lanes: int = 8,
    progress: bool = True,
) -> DirectBatchResult:
    """The direct method (``solve_direct_sqp``, single shooting by SQP) on many problems
    of one structure at once: the members' simulations run in one compiled program.

    ocps : a list of B ``OCP``s that differ in numbers only (x0, targets, T, weights,
        the system's parameters; ``GridError`` otherwise, before any numerics).
    param : the parametrization of the inputs, shared, or a list of B of one structure
        (e.g. each member's ``Chebyshev`` over its own horizon T).
    guess : (P,) the same start for every member, or (B, P) one per member (default
        zeros; clipped into each member's control bounds).
    rtol, atol, ctol, gtol, ftol, max_iter : as ``solve_direct_sqp`` (shared).
    max_ode_steps : the ODE step budget of each simulation (``solve_direct_sqp``'s);
        the members of a group run in lockstep, so one whose trial point needs many
        steps holds up its group that long.
    lanes : members simulated side by side (vmapped; a group takes its slowest
        member's steps); the groups run one after another in the same program.
    progress : a progress line over the rounds, with the number of members still
        iterating, and the status counts at the end.

    Each member runs ``solve_direct_sqp``'s iteration (``controls.sqp.sqp_iteration``:
    the QP, the line search, the BFGS update, on the host) on its own; whenever every
    member still iterating needs a point simulated, the points go to one program
    (``_values_and_jacobian_batch``) for all. A member's iterates are then those of
    ``solve_direct_sqp`` on it alone (to the rounding of the vmapped program). A member
    that ended, or one whose guess or numbers are NaN/inf (not run), does not hold up
    or spoil the others; its status and reason say why. Nothing is raised for a
    member that fails. Returns a ``DirectBatchResult``.
    """
    owner = "solve_direct_batch"
    t_start = time.perf_counter()
    if _stacked_problem(ocps, owner) is not None:
        raise ProblemError(f"{owner} takes a list of OCPs (each member's SQP runs on the host); a stack of "
                           "problems (controls.stack_members) is for solve_pontryagin_batch")
    ocps = _problem_list(ocps, owner)
    B = len(ocps)
    params = list(param) if isinstance(param, (list, tuple)) else [param] * B
    if len(params) != B:
        raise ProblemError(f"{owner}: {len(params)} parametrizations for {B} problems: pass one, or one per problem")
    for o, p in zip(ocps, params):
        _check_sqp(o, p, owner, rtol, atol)
    check_tolerances(owner, ctol=ctol, gtol=gtol, ftol=ftol, max_iter=(max_iter, "int"),
                     max_ode_steps=(max_ode_steps, "int"), lanes=(lanes, "int"))
    stacked = stack_members(ocps, owner=owner, what="problem")  # structure first, before any numerics
    stacked_params = stack_members(params, owner=owner, what="parametrization")
    P, m = params[0].size, ocps[0].n_constraints
    z0 = _guesses("guess", guess, B, P, owner)
    bounds = [parameter_bounds(o, p) for o, p in zip(ocps, params)]
    z0 = np.stack([np.clip(z, lo, hi) for z, (lo, hi) in zip(z0, bounds)])
    (stacked, stacked_params), z0, finite = _screen((stacked, stacked_params), z0, owner)
    sh = _DirectShooting(ocps[0], params[0], host_array(rtol), host_array(atol), int(max_ode_steps))
    lanes = min(int(lanes), B)
    bar = Progress(progress, 1, f"direct batch of {B} (SQP)")

    # one SQP iteration per member, driven in lockstep: each round simulates the point
    # every running member asked for, all in one call of the batched program
    running, requests, results, failures = {}, z0.copy(), [None] * B, {}
    for i in np.flatnonzero(finite):
        i = int(i)
        H = np.asarray(_control_cost_hessian(ocps[i], params[i], z0[i]))
        running[i] = sqp_iteration(z0[i], *bounds[i], H, ctol, gtol, ftol, max_iter, t_start)
    for i, it in running.items():
        requests[i] = next(it)
    rounds = 0
    while running:
        Y, D = (np.asarray(a) for a in _values_and_jacobian_batch(sh, stacked, stacked_params, requests, lanes))
        rounds += 1
        for i, it in list(running.items()):
            try:
                requests[i] = it.send((Y[i], D[i]))
            except StopIteration as stop:
                results[i] = stop.value
                del running[i]
            except ProblemError as e:  # the member's start: not finite, or no derivative
                failures[i] = str(e)
                del running[i]
        bar.update(round=rounds, running=len(running))

    params_out = np.full((B, P), np.nan)
    cost, viol, iters = np.full(B, np.nan), np.full(B, np.nan), np.zeros(B, int)
    lams = np.full((B, m), np.nan)
    status, reasons, direct = np.empty(B, dtype=object), [], [None] * B
    seconds = time.perf_counter() - t_start
    for i in range(B):
        if not finite[i]:
            s, why = "non_finite_input", "its numbers or guess hold NaN/inf; not solved"
        elif i in failures:
            s, why = "non_finite", failures[i]
        else:
            z, y, lam, k, conv, msg, history = results[i]
            zj = host_array(z)
            direct[i] = DirectResult(params=zj, control=params[i].signal(zj), cost=float(y[0]),
                                     violation=float(np.abs(y[1:]).max(initial=0.0)), multipliers=lam, iterations=k,
                                     converged=conv, message=msg, history=history, seconds=seconds)
            params_out[i], cost[i], viol[i], iters[i], lams[i] = z, y[0], direct[i].violation, k, lam
            s, why = _direct_status(direct[i])
        status[i] = s
        reasons.append(why)
    result = DirectBatchResult(params=params_out, cost=cost, violation=viol, multipliers=lams, iterations=iters,
                               status=status.astype(str), reasons=reasons, results=direct, rounds=rounds,
                               seconds=time.perf_counter() - t_start)
    bar.update(**{k.replace("_", " "): v for k, v in result.counts().items()})
    bar.finish(bool(result.converged.all()))
    return result
