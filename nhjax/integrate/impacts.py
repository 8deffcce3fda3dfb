r"""``nhjax.simulate_impacts``: event-driven integration with state resets in one jitted solve.

diffrax has no state-reset events, so the loop is ours: one ``lax.while_loop``
whose every iteration takes one step of a diffrax solver (``solver.step``,
``PIDController.adapt_step_size`` and the solver's dense interpolation are
diffrax's own) and is in one of two phases:

* **stepping**: an ordinary adaptive step. After an accepted step the event
  functions are sampled on its dense output (``event_samples`` points, the
  last the step's end): for a free contact e_a = psi_a(t, q), for a persistent
  one e_a = mu_a (its compressive multiplier). The first sample where some e_a
  < -tol brackets an event [s_i, s_j], s_i the last sample before it (or the
  step's start) where the crossing gaps are still >= 0 (samples in between lie
  in the graze band, already past the root); the step is then *not* taken and
  the loop switches to
* **locating**: Newton's method on G(tau) = min_a e_a(tau, y(tau)) over the
  bracketed events, where y(tau) is a genuine Runge-Kutta step from the last
  accepted point to tau (not the interpolant: the event state has the full
  order of the method), G' its total time derivative (for a gap, the normal
  velocity Psi = J q' + psi_t; for a multiplier, a jvp along the flow),
  safeguarded by bisection on the bracket. It starts at the bracket's right
  end and stops when the Newton correction is below 2 ulp of tau: the impact
  time is the root of the computed trajectory to round-off.

At the root the reset is applied (``nhjax.mechanics.impacts``): contacts
approaching (Psi < 0) get the seed's affine-projector jump (eq. (17)/(18))
with their restitution, persistent contacts and the permanent constraints
(rolling) are kept through it; a persistent contact whose multiplier reached
zero is released (no jump). Then the loop resumes stepping from the root with
the step size the controller last proposed, the solver's FSAL stage recomputed.

Rules (documented behaviour)
----------------------------
* Rest (ends Zeno sequences): after an impact, a contact whose rebound normal
  velocity Psi+ <= ``rest_velocity`` is made plastic (Psi+ = 0) and becomes
  *persistent* if its multiplier in that mode is compressive (mu > 0), else it
  is released (free motion that separates). A ball chattering on a table thus
  ends in resting contact after finitely many impacts, at the time of the first
  impact slower than ``rest_velocity``: the accumulation time of the exact
  Zeno sequence is later by at most 2 rest_velocity / (a (1 - alpha)) for
  normal deceleration a. With ``rest_velocity=0`` chattering runs into
  ``max_impacts``.
* Plastic impacts (alpha = 0) follow the same rule: the constraint persists
  (sticking to a moving wall, sliding on a moving circle) while mu > 0 and is
  released where mu crosses zero (-``release_tol``).
* Grazing: a crossing shallower than ``graze_tol`` (in psi's units) between
  samples is not an event; an event located with Psi >= 0 (tangential touch)
  gives no impulse and is handled by the rest rule. A step that *ends* inside that
  band (-graze_tol <= psi < 0) while the contact still approaches faster than
  ``rest_velocity`` ended just past an impact: that is an event, located in the
  step's last sample interval, so that every impact time is the root of the
  computed flight whatever the step boundaries (a flight that is a multiple of the
  largest step ends within round-off of its impact).
* Contact events: every rest (a contact becoming persistent, at t0 or at an impact)
  and release is a row of the event record (``event_times``, ``event_rest``,
  ``event_release``, ``event_states``), 2 (max_impacts + 1) rows.
* Simultaneous events: every bracketed contact whose e_a is within its
  tolerance at the root takes part (a multi-contact impact by the projector,
  contacts that would pull are dropped); later ones in the same step are
  found by the next steps.
* Bound: at most ``max_impacts`` impacts (status "max_impacts"; the loop stops
  there, never hangs), at most ``max_steps`` loop iterations (steps and Newton
  iterations together), and 500 iterations without progress in time (status
  "stalled": impacts accumulating at a Zeno point below round-off).
* The dense output used for sampling can miss a crossing that begins and ends
  between two samples; ``dtmax`` (default: the system's ``event_resolution``,
  e.g. a fraction of a vibrating wall's period) bounds the step so that samples
  resolve the wall's motion.

Gradients
---------
By default the loop is a ``lax.while_loop``: forward mode (``jax.jvp``,
``jax.jacfwd``) goes through it, reverse mode does not (JAX has no reverse rule
for while loops). With ``adjoint="reverse"`` it is an
``equinox.internal.while_loop(kind="checkpointed", max_steps=max_steps)`` (as
diffrax's RecursiveCheckpointAdjoint: recursive checkpointing, the forward loop
recomputed piecewise in the backward pass) and the solver's stage loop a bounded
one, so ``jax.grad`` / ``jax.vjp`` go through the impacts (and forward mode does
not). Forward mode suits a handful of differentiated inputs, reverse mode a
scalar loss of many. The impact-time dependence
(the saltation correction) is in the derivative: the root tau* carries the
implicit derivative dtau* = -dG/G' (one Newton step whose value is exactly
zero), the event state y(tau*) + f dtau*, and every later step starts from it.
Step sizes proposed by the controller are constants to the derivative (as in
diffrax), so the derivative is that of the discrete method.

Energy bookkeeping: the state carries W, the work of all forces outside T and V
(inputs, permanent and contact constraint forces: F.q' + lam.(A q') + mu.(J q')),
and every jump's energy change is recorded, so
``energy_error = E(t1) - E(t0) - W - sum of jumps`` checks the integration for
any system whose T and V do not depend on time.
"""

from __future__ import annotations

import dataclasses
import functools

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

from .. import _primitive, _programs
from .._validate import (abstract_call, axes_dict, check_saveat, choice, first_failures, integer, positive,
                         solver_settings, time_span, to_device)
from ..errors import (BoundaryError, ConstraintViolationError, IntegrationError, ParameterError, StateError,
                      SystemKindError)
from ._batch_types import BatchError, MemberStatuses
from .lockstep import lazy_cond
from .simulate import _save_times
from ..mechanics.impacts import (
    _contact_kkt,
    _impact_from_geometry,
    contact_kinematics,
    impact_geometry,
    kkt_solve,
    restitution_of,
    small_kkt,
)

__all__ = ["ImpactBatchTrajectory", "ImpactTrajectory", "STATUS", "simulate_batch_impacts", "simulate_impacts",
           "simulate_impacts_batch", "solve_impacts"]

#: ``ImpactTrajectory.status`` codes; 5 ("bad input") only in a batch: a member whose
#: start or parameters failed the checks, not solved.
STATUS = {0: "success", 1: "max_impacts", 2: "max_steps", 3: "nonfinite", 4: "stalled", 5: "bad input"}
BAD_INPUT = 5
# loop iterations without progress in time after which the solve is declared stalled
_STALL = 500


class ImpactTrajectory(eqx.Module):
    """A motion with impacts, its events and the diagnostics that qualify it.

    Fields (N = max_impacts, k = number of one-sided constraints, x = (q, q'))
    ------
    ts, xs : saved times and states (NaN rows past the end of the solve); saved
        states at an impact time are its left limits.
    work : W at the saved times (work of forces outside T and V, see module doc).
    t_final, x_final : where the solve ended (t1, or the last impact if stopped).
    num_impacts : impacts recorded (<= N).
    impact_times (N,) : impact times (NaN past num_impacts).
    impact_contacts (N, k) : which contacts took part.
    x_pre, x_post (N, 2n) : states just before / after each impact (same q).
    normal_velocity_pre, normal_velocity_post (N, k) : Psi = J q' + psi_t.
    impulses (N, k) : mu_a (>= 0, along J^T).
    energy_pre, energy_post (N,) : energy before and after each impact.
    energy_jumps : sum of the energy changes of all jumps.
    energy_error : E(t_final) - E(t0) - W - energy_jumps (0 up to integration error
        when T and V do not depend on time).
    persistent (k,) : contacts persistent at the end; rest_times (k,): last time
        each became persistent (NaN: never); release_times (k,): last time each was
        released (NaN: never); num_releases.
    event_times (M,), event_rest (M, k), event_release (M, k), event_states (M, 2n) :
        every contact event (a contact coming to rest, at t0 or at an impact, or being
        released) in order: its time, which contacts came to rest and which were
        released, and the state just after it; M = 2 (max_impacts + 1) rows, NaN past
        num_events (the count of all events; more than M only if contacts came to rest
        without impacts, then the rows hold the first M).
    min_gap (k,) : smallest psi of free contacts at the accepted steps' ends
        (penetration, if negative).
    constraint_residual : max |A q' + a| at step ends (permanent constraints).
    contact_residual : max |psi|, |Psi| of persistent contacts at step ends.
    num_steps, num_accepted_steps, num_rejected_steps : loop iterations and steps.
    status : 0 success, 1 max_impacts reached, 2 max_steps exhausted, 3 NaN/inf,
        4 stalled (no progress in time over 500 loop iterations: a Zeno point).
    """

    ts: jax.Array
    xs: jax.Array
    work: jax.Array
    t_final: jax.Array
    x_final: jax.Array
    num_impacts: jax.Array
    impact_times: jax.Array
    impact_contacts: jax.Array
    x_pre: jax.Array
    x_post: jax.Array
    normal_velocity_pre: jax.Array
    normal_velocity_post: jax.Array
    impulses: jax.Array
    energy_pre: jax.Array
    energy_post: jax.Array
    energy_jumps: jax.Array
    energy_error: jax.Array
    persistent: jax.Array
    rest_times: jax.Array
    release_times: jax.Array
    num_releases: jax.Array
    event_times: jax.Array
    event_rest: jax.Array
    event_release: jax.Array
    event_states: jax.Array
    num_events: jax.Array
    min_gap: jax.Array
    constraint_residual: jax.Array
    contact_residual: jax.Array
    num_steps: jax.Array
    num_accepted_steps: jax.Array
    num_rejected_steps: jax.Array
    status: jax.Array
    n: int = eqx.field(static=True, default=0)
    state_names: tuple = eqx.field(static=True, default=())

    def __getitem__(self, name: str):
        if name not in self.state_names:
            raise KeyError(f"no state component '{name}'; have {self.state_names}")
        return self.xs[..., self.state_names.index(name)]

    @property
    def velocities_pre(self):
        return self.x_pre[..., self.n :]

    @property
    def velocities_post(self):
        return self.x_post[..., self.n :]

    def summary(self) -> str:
        k = int(self.num_impacts)
        lines = [
            f"t_final = {float(self.t_final):.10g}  status: {STATUS[int(self.status)]}  "
            f"impacts: {k}  releases: {int(self.num_releases)}",
            f"  steps: {int(self.num_accepted_steps)} accepted, {int(self.num_rejected_steps)} "
            f"rejected, {int(self.num_steps)} loop iterations",
            f"  energy: jumps {float(self.energy_jumps):.6g}, bookkeeping error "
            f"{float(self.energy_error):.2e}",
            f"  min gap {np.asarray(self.min_gap)}, permanent-constraint residual "
            f"{float(self.constraint_residual):.2e}, contact residual {float(self.contact_residual):.2e}",
        ]
        if bool(np.any(np.asarray(self.persistent))):
            lines.append(f"  persistent contacts at the end: {np.flatnonzero(np.asarray(self.persistent)).tolist()}")
        return "\n".join(lines)


def _lagrangian_size(system, owner):
    """The number n of coordinates of a system the impact solves take (the Lagrange
    engine's: mass matrix, permanent constraints and contact multipliers by autodiff)."""
    n = getattr(system, "n", None)
    if n is None or not hasattr(system, "dynamics_terms"):
        raise SystemKindError(f"{owner} needs a ConstrainedLagrangian (mass matrix, permanent constraints and contact "
                              f"multipliers by autodiff), got {type(system).__name__}")
    return n


def _num_contacts(system, t0, x0):
    if not hasattr(system, "unilateral_constraints"):
        raise SystemKindError(
            f"{type(system).__name__} declares no one-sided constraints: define "
            "unilateral_constraints(t, q) -> gaps (admissible where >= 0), or wrap it: "
            "nhjax.mechanics.WithContacts(system, psi, restitution)"
        )
    gaps = abstract_call(system.unilateral_constraints, jax.ShapeDtypeStruct((), jnp.float64),
                         jax.ShapeDtypeStruct((system.n,), x0.dtype))
    return gaps.shape[0] if gaps.shape else 1  # (one gap as a scalar)


def _loop_options(system, t0, x0):
    """XLA's settings for an event loop of ``system`` (x0: a member's state or its shape).

    When its largest linear system, the contact KKT of n coordinates, m permanent and k
    contact constraints, is small enough for the unrolled elimination
    (``nhjax.mechanics.impacts.small_kkt``), the loop calls no LAPACK and XLA
    compiles it into one function: then its quick settings (``QUICK_OPTIONS``: LLVM
    unoptimized), under which that function compiles in less time than the kernels of
    the loop did and still runs faster than they ran (benchmarks/compile_times.py,
    benchmarks/impacts.py). Larger systems keep LAPACK, so their loop runs kernel by
    kernel, and those kernels keep LLVM's optimization (``SOLVE_OPTIONS``)."""
    return _programs.QUICK_OPTIONS if small_kkt(*_kkt_sizes(system, t0, x0)) else _programs.SOLVE_OPTIONS


#: Most lanes of an impact batch compiled with XLA's quick settings (see _loop_options).
_QUICK_LANES = 16


def _kkt_sizes(system, t0, x0):
    """(n, m, k): coordinates, permanent velocity-level constraints and contacts of the
    contact KKT (read off shapes: nothing runs; kept per structure of the system, since
    an eager simulate_impacts asks on every call)."""
    leaves, treedef = jax.tree_util.tree_flatten(system)
    # arrays and numbers by their shapes (values do not change the sizes), anything else
    # (a function among the fields) by itself
    key = (treedef, tuple(np.shape(a) if eqx.is_array_like(a) else a for a in leaves))
    try:
        return _KKT_SIZES[key]
    except (KeyError, TypeError):  # TypeError: a static field that does not hash
        pass
    q = jax.ShapeDtypeStruct((system.n,), jnp.float64)
    m = jax.eval_shape(lambda qq: system.constraint_jacobian(jnp.zeros(()), qq), q).shape[0]
    sizes = (system.n, m, _num_contacts(system, t0, x0))
    try:
        _KKT_SIZES[key] = sizes
    except TypeError:
        pass
    return sizes


_KKT_SIZES: dict = {}


def _start_residuals(system, x0, t0):
    """(psi(t0, q0), the permanent constraints' velocity residual at x0)."""
    q0, qd0 = x0[: system.n], x0[system.n:]
    return (jnp.atleast_1d(system.unilateral_constraints(t0, q0)),
            jnp.atleast_1d(system._all_velocity_constraints(t0, q0, qd0)))


def _boundary_samples(system, t0, t1) -> int:
    """Times at which ``_start_report`` samples a moving boundary's margins over [t0, t1]:
    8 per ``event_resolution`` (which resolves the boundary's motion), at least 1025,
    at most 65537, a power of two plus one (few sizes: few programs)."""
    res = getattr(system, "event_resolution", None)
    need = 1024 if not res else int(np.ceil(8 * (float(t1) - float(t0)) / float(res)))
    return int(min(max(1 << max(need - 1, 1).bit_length(), 1024), 65536)) + 1


def _start_report(system, x0, t0, t1, n_samples):
    """Everything ``simulate_impacts`` checks of one member's start, as numbers (one
    stored program; vmapped over a batch's members by ``_start_report_batch``):
    ``finite`` (x0), ``psi`` (the gaps at t0, >= 0 required), ``permanent`` (the
    permanent constraints' residual at x0), ``restitution`` (in [0, 1] required), and
    for a system with moving boundaries (``boundary_margins(t)``: name -> margin that
    must stay > 0, e.g. a moving circle's radius) each margin's smallest sample on
    ``n_samples`` times of [t0, t1] with the first sampled time at which it is <= 0."""
    psi0, res = _start_residuals(system, x0, t0)
    out = dict(finite=jnp.all(jnp.isfinite(x0)), psi=psi0, permanent=res,
               restitution=restitution_of(system, psi0.shape[0]))
    if hasattr(system, "boundary_margins"):
        ts = t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n_samples)
        margins = jax.vmap(system.boundary_margins)(ts)
        out["boundary"] = {k: dict(min=jnp.min(v), t=_first_zero(ts, v)) for k, v in margins.items()}
    return out


def _first_zero(ts, v):
    """The first time at which samples ``v`` of a margin at times ``ts`` reach <= 0, by
    linear interpolation from the last positive sample (ts[0] if the first is <= 0)."""
    i = jnp.argmax(v <= 0)
    lo = jnp.maximum(i - 1, 0)
    frac = jnp.where(i > 0, v[lo] / (v[lo] - v[i]), 0.0)
    return ts[lo] + (ts[i] - ts[lo]) * frac


def _start_report_batch(system, x0, t0, t1, n_samples, sys_axes, x_axis):
    return jax.vmap(lambda s, x: _start_report(s, x, t0, t1, n_samples), in_axes=(sys_axes, x_axis))(system, x0)


def _start_failures(report, B, constraint_tol, owner, batched=(True, True)):
    """[(member, (reason, error))] for the members whose start fails a check, in the order
    of ``simulate_impacts``'s checks: x0 finite, restitution in [0, 1], no moving boundary
    degenerating in [t0, t1], psi(t0, q0) >= -constraint_tol, the permanent constraints
    met. ``report``: ``_start_report``'s numbers with a leading member axis (numpy, all
    members at once). ``batched``: (system, x0) carry a member axis; a failed check that
    depends only on shared inputs raises its error at once (it is no member's own)."""
    r = jax.device_get(report)
    fin = np.asarray(r["finite"]).reshape(B)
    alpha = np.asarray(r["restitution"]).reshape(B, -1)
    psi = np.asarray(r["psi"]).reshape(B, -1)
    perm = np.asarray(r["permanent"]).reshape(B, -1)
    perm = np.max(np.abs(perm), axis=1) if perm.shape[1] else np.zeros(B)
    sys_b, x_b = batched

    def restitution(j):
        a = int(np.argmax(~((alpha[j] >= 0) & (alpha[j] <= 1))))
        return (f"restitution[{a}] = {float(alpha[j, a])!r} outside [0, 1]",
                ParameterError(f"{owner}: restitution must lie in [0, 1] (coefficient of restitution of every "
                               f"contact), got {alpha[j].tolist()}; pass values in that range", "restitution",
                               alpha[j]))

    def forbidden(j):
        a = int(np.argmin(psi[j]))
        return (f"x0 starts on the forbidden side of unilateral[{a}] (psi = {psi[j, a]:.3g} < 0)",
                ConstraintViolationError(f"unilateral[{a}]", float(-psi[j, a]), constraint_tol,
                                         "the initial configuration is on the forbidden side psi < 0"))

    def permanent(j):
        return (f"x0 violates the permanent constraints by {perm[j]:.3g}",
                ConstraintViolationError("permanent", float(perm[j]), constraint_tol))

    checks = [(~fin, lambda j: ("x0 contains NaN or inf", StateError(
        f"{owner}: initial state x0 contains NaN or inf; pass finite numbers", "x0")), x_b),
              (~np.all((alpha >= 0) & (alpha <= 1), axis=1), restitution, sys_b)]
    for name, b in r.get("boundary", {}).items():
        low, at = np.asarray(b["min"]).reshape(B), np.asarray(b["t"]).reshape(B)

        def boundary(j, name=name, low=low, at=at):
            return (f"moving boundary '{name}' degenerates at t ~ {at[j]:.6g} (margin {low[j]:.3g} <= 0)",
                    BoundaryError(
                        f"{owner}: the moving boundary '{name}' degenerates within [t0, t1]: its margin "
                        f"reaches {low[j]:.3g} <= 0, first at t ~ {at[j]:.6g} (e.g. a moving circle's radius "
                        "reaching 0), where no motion is defined; end the time span before then (t1) or change the "
                        "boundary's parameters", name, at[j], low[j]))

        checks.append((~(low > 0), boundary, sys_b))
    checks += [(fin & np.any(psi < -constraint_tol, axis=1), forbidden, x_b or sys_b),
               (fin & (perm > constraint_tol), permanent, x_b or sys_b)]
    for mask, what, member_own in checks:
        if mask.any() and not member_own:
            raise what(int(np.argmax(mask)))[1]
    return first_failures([(mask, what) for mask, what, _ in checks], B)


#: ImpactTrajectory's array fields (what the stored program returns)
_FIELDS = tuple(f.name for f in dataclasses.fields(ImpactTrajectory) if f.name not in ("n", "state_names"))


def _solve_plain(system, x0, t1, t0, ts, solver, rtol, atol, dt0, dtmax, max_steps, max_impacts, rest_velocity,
                 graze_tol, release_tol, event_samples, adjoint):
    """``solve_impacts`` with positional arguments, its arrays in a dict (the stored
    program of ``simulate_impacts``)."""
    tr = solve_impacts(system, x0, t1, t0=t0, ts=ts, solver=solver, rtol=rtol, atol=atol, dt0=dt0, dtmax=dtmax,
                       max_steps=max_steps, max_impacts=max_impacts, rest_velocity=rest_velocity,
                       graze_tol=graze_tol, release_tol=release_tol, event_samples=event_samples,
                       adjoint=adjoint)
    return {k: getattr(tr, k) for k in _FIELDS}


#: reverse mode in at most this many numbers runs forward mode (nhjax._primitive.call):
#: the event loop's tangents compile in a fraction of the checkpointed loop's backward pass
_MAX_TANGENTS = 4


def _with_adjoint(adjoint, args, nz=None):
    """``_solve_plain``'s arguments with another adjoint (the same values): "forward" for
    jax.jvp / jax.jacfwd, "reverse" for jax.grad / jax.jacrev."""
    return (*args[:-1], adjoint)


def _event_capacity(max_impacts: int) -> int:
    """Rows of the contact-event record: a contact comes to rest at an impact (or at t0)
    and is released once per rest, so 2 (max_impacts + 1) rows hold every event of a
    solve that stops at max_impacts."""
    return 2 * int(max_impacts) + 2


def _write_rows(records, rows, c, lead=()):
    """``records`` with the iteration's rows written: impact rows ("imp_" keys) at
    ``c["rec_row"]``, contact-event rows ("ev_" keys) at ``c["ev_row"]`` (out of range:
    none). ``lead``: leading indices (the lock-step batch's member slots). Contact events
    are rare (a rest, a release): their rows are written in a branch taken only by an
    iteration that has one, not scattered every iteration."""
    out = {key: records[key].at[lead + (c["rec_row"],)].set(rows[key], mode="drop")
           for key in records if not key.startswith("ev_")}
    ev = {key: records[key] for key in records if key.startswith("ev_")}
    capacity = ev["ev_t"].shape[len(lead)]

    def write(ev):
        return {key: ev[key].at[lead + (c["ev_row"],)].set(rows[key], mode="drop") for key in ev}

    return out | jax.lax.cond(jnp.any(c["ev_row"] < capacity), write, lambda ev: ev, ev)


def _ulp(t):
    t = jax.lax.stop_gradient(t)
    return jnp.spacing(jnp.abs(t)) + jnp.finfo(jnp.float64).tiny


def _machine(system, t1, *, t0=0.0, ts=None, solver=None, rtol=1e-10, atol=1e-10, dt0=None, dtmax=None,
             max_steps: int = 100_000, max_impacts: int = 1000, rest_velocity=1e-6, graze_tol=1e-12,
             release_tol=1e-10, event_samples: int = 4, locate_iterations: int = 60, reverse: bool = False,
             branch=jax.lax.cond):
    """The event loop of one member as pieces, a dict of functions:

    * ``init(x0) -> carry`` (the member's start: contact modes, controller, solver state);
    * ``body(carry) -> carry``: one loop iteration (a step or a root-finding step); an
      impact's record row is left in ``carry["rec"]`` at index ``carry["rec_row"]``
      (N: none) instead of being written into an N-row record inside the iteration;
    * ``cond(carry)``: not finished; ``records0()``: the empty N-row impact record;
      ``record(records, carry)``: writes the iteration's row;
    * ``finish_fields(carry, x0)``: the trajectory's other fields;
      ``finish(fields, records) -> ImpactTrajectory``.

    ``solve_impacts`` runs them in one while loop (``reverse``: a checkpointed one); the
    lock-step batch (``_lockstep_chunk``) runs ``body`` on many lanes at once, writes the
    rows straight into each member's slot and refills finished lanes with new members.
    ``branch``: the conditional of the iteration's branches (``jax.lax.cond``; the lock-step
    batch passes ``lockstep.lazy_cond``, which under its vmap over the lanes runs a
    branch only in the iterations where some lane takes it, where ``lax.cond`` would run
    both branches on every lane)."""
    solver = diffrax.Dopri5() if solver is None else solver
    if getattr(solver, "scan_kind", "") is None:
        # diffrax's default stage loop is a checkpointed while loop, which has no
        # forward-mode rule; a plain lax loop keeps jvp/jacfwd through the solve working,
        # a bounded loop (over the known number of stages) has a reverse-mode rule too
        solver = dataclasses.replace(solver, scan_kind="bounded" if reverse else "lax")
    dtype = jnp.zeros((), float).dtype
    t0 = jnp.asarray(t0, dtype)
    t1 = jnp.asarray(t1, dtype)
    n = system.n
    _, _, k = sizes = _kkt_sizes(system, t0, jnp.zeros(2 * n, dtype))
    solve = kkt_solve(*sizes)  # the projection's solves as the contact dynamics
    alpha = restitution_of(system, k)
    rest_velocity = jnp.asarray(rest_velocity, dtype)
    graze_tol = jnp.asarray(graze_tol, dtype)
    release_tol = jnp.asarray(release_tol, dtype)
    N = int(max_impacts)
    M = _event_capacity(N)
    m = int(event_samples)
    # ts == "steps": the state after every accepted step that ends no event (the states
    # whose residuals the result reports), in rows of their own times (at most max_steps)
    at_steps = isinstance(ts, str)
    if at_steps:
        ns = int(max_steps)
    else:
        ts = jnp.asarray(jnp.zeros((0,), dtype) if ts is None else ts, dtype)
        ns = ts.shape[0]

    def split(x):
        return x[:n], x[n:]

    def kkt(t, x, persistent):
        q, qd = split(x)
        return _kkt_once(system, t, q, qd, persistent)

    def vf(t, y, args):
        persistent = args
        qdd, _, _, power = kkt(t, y[:-1], persistent)
        return jnp.concatenate([y[n:-1], qdd, power[None]])

    def events(t, x, persistent):
        q, _ = split(x)
        psi = jnp.atleast_1d(system.unilateral_constraints(t, q))
        _, _, mu, _ = kkt(t, x, persistent)
        return jnp.where(persistent, mu, psi)

    def tolerances(persistent):
        return jnp.where(persistent, release_tol, graze_tol)

    def energy(x):
        return system.energy(x)

    term = diffrax.ODETerm(vf)
    controller = diffrax.PIDController(rtol=rtol, atol=atol, dtmax=dtmax)
    order = solver.error_order(term)

    def records0():
        """The impact record (N rows, "imp_" keys, written at ``rec_row``) and the contact
        event record (M rows, "ev_" keys, written at ``ev_row``): NaN past the last row."""
        nan = jnp.asarray(jnp.nan, dtype)
        return dict(
            imp_t=jnp.full((N,), nan), imp_mask=jnp.zeros((N, k), bool),
            imp_x_pre=jnp.full((N, 2 * n), nan), imp_x_post=jnp.full((N, 2 * n), nan),
            imp_Psi_pre=jnp.full((N, k), nan), imp_Psi_post=jnp.full((N, k), nan),
            imp_mu=jnp.full((N, k), nan), imp_E_pre=jnp.full((N,), nan), imp_E_post=jnp.full((N,), nan),
            ev_t=jnp.full((M,), nan), ev_rest=jnp.zeros((M, k), bool), ev_release=jnp.zeros((M, k), bool),
            ev_x=jnp.full((M, 2 * n), nan),
        )

    def init(x0):
        x0 = jnp.asarray(x0, dtype)
        # -- initial contact modes: resting contacts (gap ~ 0, normal velocity ~ 0, compressive)
        q0, qd0 = split(x0)
        psi0, _, Psi0 = contact_kinematics(system, t0, q0, qd0)
        cand = (psi0 <= graze_tol) & (jnp.abs(Psi0) <= rest_velocity)
        _, _, mu0, _ = kkt(t0, x0, cand)
        persistent0 = cand & (mu0 > 0)

        y0 = jnp.concatenate([x0, jnp.zeros((1,), dtype)])
        tnext, cstate = controller.init(term, t0, t1, y0, dt0, persistent0, solver.func, order)
        h0 = jax.lax.stop_gradient(jnp.minimum(tnext, t1) - t0)
        sstate = solver.init(term, t0, t0 + h0, y0, persistent0)
        nan = jnp.asarray(jnp.nan, dtype)
        zi = jnp.zeros((), jnp.int32)
        carry = dict(
            t=t0, y=y0, h=h0, cstate=cstate, sstate=sstate, made_jump=jnp.zeros((), bool),
            persistent=persistent0, phase=zi, lo=t0, hi=t0, tau=t0, evset=jnp.zeros(k, bool), iters=zi,
            n_steps=zi, n_acc=zi, n_rej=zi, n_imp=zi, n_rel=zi, status=zi, t_prog=t0, stall=zi,
            rec_row=jnp.asarray(N, jnp.int32),
            # a start in resting contact is the first contact event (row 0, written after the
            # first iteration, which keeps ev_row)
            rec=dict(jax.tree_util.tree_map(lambda a: a[0], records0()), ev_t=t0, ev_rest=persistent0,
                     ev_release=jnp.zeros(k, bool), ev_x=x0),
            ev_row=jnp.where(jnp.any(persistent0), 0, M).astype(jnp.int32),
            n_ev=jnp.any(persistent0).astype(jnp.int32),
            E_jumps=jnp.zeros((), dtype), rest_time=jnp.where(persistent0, t0, nan),
            release_time=jnp.full((k,), nan),
            min_gap=jnp.full((k,), jnp.inf, dtype), perm_res=jnp.zeros((), dtype),
            contact_res=jnp.zeros((), dtype),
            save_idx=zi, ys=jnp.full((ns, 2 * n + 1), nan),
        )
        if at_steps:
            carry["ts_steps"] = jnp.full((ns,), nan)
        carry = jax.tree_util.tree_map(jnp.asarray, carry)
        return carry


    def save(c, t_b, interp):
        """Save every pending time <= t_b from the step's dense output (none when saving
        at the steps: ``save_step``)."""
        if at_steps:
            return c["save_idx"], c["ys"]
        def cond(sc):
            idx, _ = sc
            return (idx < ns) & (ts[jnp.minimum(idx, ns - 1)] <= t_b)

        def one(sc):
            idx, ys = sc
            return idx + 1, ys.at[idx].set(interp.evaluate(ts[idx]))

        if ns == 0:
            return c["save_idx"], c["ys"]
        if reverse:  # a loop with a reverse-mode rule (at most ns saves per step)
            return eqxi.while_loop(cond, one, (c["save_idx"], c["ys"]), max_steps=ns, kind="bounded")
        return jax.lax.while_loop(cond, one, (c["save_idx"], c["ys"]))

    def save_step(o, t, y):
        """Saving at the steps: ``o`` with (t, y) in the next row."""
        if at_steps:
            i = o["save_idx"]
            o["ys"], o["ts_steps"] = o["ys"].at[i].set(y, mode="drop"), o["ts_steps"].at[i].set(t, mode="drop")
            o["save_idx"] = i + 1
        return o

    def project(t, y, persistent):
        """Put persistent contacts back on psi = 0, Psi = 0 (one Newton step on q, the
        metric-smallest velocity change that keeps A q' + a unchanged)."""
        x = y[:-1]
        q, qd = split(x)
        w = persistent.astype(dtype)
        psi, J, _ = contact_kinematics(system, t, q, qd)
        Jm = J * w[:, None]
        z = solve(Jm @ Jm.T + jnp.diag(1.0 - w), w * psi)
        q = q - Jm.T @ z
        M = system.mass_matrix(q)
        A = system.constraint_jacobian(t, q)
        _, J, Psi = contact_kinematics(system, t, q, qd)
        mA = A.shape[0]
        K = jnp.block([
            [M, A.T, (J * w[:, None]).T],
            [A, jnp.zeros((mA, mA + k), dtype)],
            [J * w[:, None], jnp.zeros((k, mA), dtype), jnp.diag(1.0 - w)],
        ])
        rhs = jnp.concatenate([jnp.zeros(n, dtype), jnp.zeros(mA, dtype), -w * Psi])
        qd = qd + solve(K, rhs)[:n]
        return jnp.concatenate([q, qd, y[-1:]])

    def residuals(t, x, persistent):
        q, qd = split(x)
        perm = system._all_velocity_constraints(t, q, qd)
        perm = jnp.max(jnp.abs(perm)) if perm.shape[0] else jnp.zeros((), dtype)
        psi, _, Psi = contact_kinematics(system, t, q, qd)
        cres = jnp.max(jnp.where(persistent, jnp.maximum(jnp.abs(psi), jnp.abs(Psi)), 0.0))
        gap = jnp.where(persistent, jnp.inf, psi)
        return perm, cres, gap

    def finalize(c, t_end, y1, interp, G, Gp, e, x_dot):
        """Apply the event at the located root t_end (state y1)."""
        persistent = c["persistent"]
        # implicit derivative of the root: value exactly 0, tangent -dG / G'
        Gp_safe = jax.lax.stop_gradient(jnp.where((Gp != 0) & jnp.isfinite(Gp), Gp, 1.0))
        corr = -G / Gp_safe
        corr = corr - jax.lax.stop_gradient(corr)
        t_star = jax.lax.stop_gradient(t_end) + corr
        y_star = y1 + jax.lax.stop_gradient(x_dot) * corr
        x_star = y_star[:-1]
        q, qd = split(x_star)
        geom = impact_geometry(system, t_star, q)
        J, j = geom[3], geom[4]
        Psi = J @ qd + j
        fire = c["evset"] & (e <= tolerances(persistent))
        fire = fire | (c["evset"] & (e == jnp.min(jnp.where(c["evset"], e, jnp.inf))))
        releasing = fire & persistent
        touching = fire & ~persistent
        hitting = touching & (Psi < 0)
        kept = persistent & ~releasing
        qd1, mu, _ = _impact_from_geometry(geom, qd, hitting, alpha, kept)
        slow = touching & (J @ qd1 + j <= rest_velocity)
        qd2, mu2, _ = _impact_from_geometry(geom, qd, hitting, jnp.where(slow, 0.0, alpha), kept | slow)
        any_slow = jnp.any(slow)
        qd_new = jnp.where(any_slow, qd2, qd1)
        mu_new = jnp.where(any_slow, mu2, mu)
        cand = kept | slow
        _, _, mu_c, _ = kkt(t_star, jnp.concatenate([q, qd_new]), cand)
        new_persistent = kept | (slow & (mu_c > 0))
        x_plus = jnp.concatenate([q, qd_new])
        Psi_post = J @ qd_new + j
        impact = jnp.any(hitting)
        E_pre, E_post = energy(x_star), energy(x_plus)
        row = jnp.where(impact, c["n_imp"], N)  # out of range: dropped
        out = dict(c)
        # the impact's record row, written by the driver (``record``) after the iteration: the
        # N-row record stays out of the iteration's conditionals (under vmap, selects that
        # would copy it every iteration)
        out["rec_row"] = row.astype(jnp.int32)
        rest_now = new_persistent & ~persistent
        release_now = persistent & ~new_persistent
        changed = jnp.any(rest_now | release_now)
        out["rec"] = dict(imp_t=t_star, imp_mask=hitting, imp_x_pre=x_star, imp_x_post=x_plus,
                          imp_Psi_pre=Psi, imp_Psi_post=Psi_post, imp_mu=mu_new, imp_E_pre=E_pre,
                          imp_E_post=E_post, ev_t=t_star, ev_rest=rest_now, ev_release=release_now, ev_x=x_plus)
        out["ev_row"] = jnp.where(changed, c["n_ev"], M).astype(jnp.int32)  # M: dropped (none, or full)
        out["n_ev"] = c["n_ev"] + changed.astype(jnp.int32)
        out["E_jumps"] = c["E_jumps"] + (E_post - E_pre)
        out["n_imp"] = c["n_imp"] + impact.astype(jnp.int32)
        out["n_rel"] = c["n_rel"] + jnp.sum(releasing).astype(jnp.int32)
        out["rest_time"] = jnp.where(new_persistent & ~persistent, t_star, c["rest_time"])
        out["release_time"] = jnp.where(persistent & ~new_persistent, t_star, c["release_time"])
        out["status"] = jnp.where(impact & (out["n_imp"] >= N), jnp.int32(1), c["status"])
        out["save_idx"], out["ys"] = save(c, t_end, interp)
        out["t"] = t_star
        out["y"] = jnp.concatenate([x_plus, y_star[-1:]])
        out["persistent"] = new_persistent
        out["made_jump"] = jnp.ones((), bool)
        out["phase"] = jnp.zeros((), jnp.int32)
        return out

    def body(c):
        c = dict(c, rec_row=jnp.asarray(N, jnp.int32),
                 ev_row=jnp.where(c["n_steps"] == 0, c["ev_row"], M).astype(jnp.int32))
        locate = c["phase"] == 1
        t = c["t"]
        persistent = c["persistent"]
        t_end = jnp.where(locate, jax.lax.stop_gradient(c["tau"]), jnp.minimum(t + c["h"], t1))
        y1, y_err, dense, s1, _ = solver.step(term, t, t_end, c["y"], persistent, c["sstate"], c["made_jump"])
        interp = solver.interpolation_cls(t0=t, t1=t_end, **dense)
        finite = jnp.all(jnp.isfinite(y1))
        y_err = jnp.where(jnp.isfinite(y_err), y_err, jnp.inf)
        keep, nt0, nt1, _, cstate1, _ = controller.adapt_step_size(
            t, t_end, c["y"], jnp.where(finite, y1, c["y"]), persistent, y_err, order, c["cstate"])
        keep = keep & finite
        dt_next = jax.lax.stop_gradient(nt1 - nt0)

        out = dict(c)
        out["n_steps"] = c["n_steps"] + 1

        # ---------------------------------------------------------------- stepping
        fr = jnp.arange(0, m + 1, dtype=dtype) / m
        s_all = t + (t_end - t) * fr  # samples, the step's start and end included

        def gap_on_dense(tt):
            return jnp.atleast_1d(system.unilateral_constraints(tt, interp.evaluate(tt)[:n]))

        gaps, rates = jax.vmap(lambda tt: jax.jvp(gap_on_dense, (tt,), (jnp.ones((), dtype),)))(s_all)
        s = s_all[1:]
        xs_s = jnp.concatenate([jax.vmap(interp.evaluate)(s[:-1])[:, :-1], y1[None, :-1]], axis=0)
        mus = branch(
            jnp.any(persistent),
            lambda _: jax.vmap(lambda tt, xx: kkt(tt, xx, persistent)[2])(s, xs_s),
            lambda _: jnp.zeros((m, k), dtype), None)
        e_s = jnp.where(persistent[None, :], mus, gaps[1:])  # (m, k) event values
        tol = tolerances(persistent)
        below = e_s < -tol[None, :]
        # A step that ends inside the graze band (-graze_tol <= psi < 0) of a contact still
        # approaching (faster than rest_velocity) ended just past an impact: that is a
        # crossing too, located in its last sample interval. Otherwise the next step would
        # start past the root and the impact would be placed at that step's start, late by
        # up to graze_tol / |Psi| (a flight that is a multiple of the largest step ends
        # within round-off of its impact).
        end_cross = ~persistent & (gaps[-1] < 0) & (rates[-1] < -rest_velocity)
        below = below.at[-1].set(below[-1] | end_cross)
        any_j = jnp.any(below, axis=1)
        crossed = jnp.any(any_j)
        j = jnp.argmax(any_j)
        # a gap that dips below -graze_tol and comes back between two samples: its rate
        # turns from < 0 to > 0 there; find that minimum (regula falsi on the rate)
        free_ok = (~persistent)[None, :] & (gaps[:-1] >= -tol) & (gaps[1:] >= -tol)
        dip = free_ok & (rates[:-1] < 0) & (rates[1:] > 0)  # (m, k) per interval
        any_i = jnp.any(dip, axis=1)
        has_dip = jnp.any(any_i) & (~crossed | (jnp.argmax(any_i) < j))
        i_d = jnp.argmax(any_i)
        a_d = jnp.argmax(dip[i_d])

        def deepest(_):
            def rate(tt):
                return jax.jvp(lambda u: gap_on_dense(u)[a_d], (tt,), (jnp.ones((), dtype),))

            def it(_, st):
                lo_, hi_, rl, rh, side = st
                tm = lo_ - rl * (hi_ - lo_) / (rh - rl)
                tm = jnp.where(jnp.isfinite(tm) & (tm > lo_) & (tm < hi_), tm, 0.5 * (lo_ + hi_))
                _, r = rate(tm)
                left = r < 0  # minimum to the right of tm
                # Illinois: halve the value kept twice on the same side
                rh = jnp.where(left & (side == 1), 0.5 * rh, rh)
                rl = jnp.where(~left & (side == -1), 0.5 * rl, rl)
                return (jnp.where(left, tm, lo_), jnp.where(left, hi_, tm), jnp.where(left, r, rl),
                        jnp.where(left, rh, r), jnp.where(left, 1, -1))

            st = (s_all[i_d], s_all[i_d + 1], rates[i_d, a_d], rates[i_d + 1, a_d], 0)
            lo_, hi_, _, _, _ = jax.lax.fori_loop(0, 12, it, st)
            tm = 0.5 * (lo_ + hi_)
            return tm, gap_on_dense(tm)

        t_min, gaps_min = branch(has_dip, deepest, lambda _: (t_end, gaps[-1]), None)
        dipped = has_dip & (gaps_min[a_d] < -tol[a_d])
        found = crossed | dipped
        # The bracket's left end: the last sample before the first one below -graze_tol at
        # which the crossing gaps are still >= 0 (samples between lie inside the graze band,
        # already past the root: a bracket starting there would put the root at its left
        # end, late by up to graze_tol / |Psi|); for multipliers, the previous sample.
        free_fire = below[j] & ~persistent
        on_side = jnp.all(jnp.where(free_fire[None, :], gaps >= 0, True), axis=1)  # (m + 1,) over s_all
        idx = jnp.arange(m + 1)
        lo = jnp.where(dipped, s_all[i_d], s_all[jnp.max(jnp.where(on_side & (idx <= j), idx, 0))])
        hi = jnp.where(dipped, t_min, s[j])
        evset0 = jnp.where(dipped, (gaps_min < -tol) & ~persistent, below[j])

        def guess(_):
            """A first root estimate on the dense output (safeguarded Newton, from hi):
            the root finder on genuine steps then needs one or two iterations."""
            def g_of(tt):
                return jnp.min(jnp.where(evset0, events(tt, interp.evaluate(tt)[:-1], persistent), jnp.inf))

            def it(_, st):
                tau, a, b = st
                gv, gd = jax.jvp(g_of, (tau,), (jnp.ones((), dtype),))
                a = jnp.where(gv < 0, a, tau)
                b = jnp.where(gv < 0, tau, b)
                tn = tau - gv / gd
                tn = jnp.where(jnp.isfinite(tn) & (tn >= a) & (tn <= b), tn, 0.5 * (a + b))
                return tn, a, b

            tau, _, _ = jax.lax.fori_loop(0, 6, it, (hi, lo, hi))
            return jax.lax.stop_gradient(tau)

        tau0 = branch(found & keep, guess, lambda _: hi, None)

        def advance(c):
            o = dict(c)
            y_new = branch(jnp.any(persistent), lambda yy: project(t_end, yy, persistent),
                           lambda yy: yy, y1)
            o["save_idx"], o["ys"] = save(c, t_end, interp)
            o["t"], o["y"], o["sstate"] = t_end, y_new, s1
            o["made_jump"] = jnp.any(persistent)
            perm, cres, gap = residuals(t_end, y_new[:-1], persistent)
            o["perm_res"] = jnp.maximum(c["perm_res"], perm)
            o["contact_res"] = jnp.maximum(c["contact_res"], cres)
            o["min_gap"] = jnp.minimum(c["min_gap"], gap)
            return save_step(o, t_end, y_new)

        def stepping(c):
            accepted = dict(c)
            accepted["n_acc"] = c["n_acc"] + 1
            accepted["h"] = dt_next
            accepted["cstate"] = cstate1
            start_locate = dict(accepted)
            start_locate.update(phase=jnp.ones((), jnp.int32), lo=jax.lax.stop_gradient(lo),
                                hi=jax.lax.stop_gradient(hi), tau=tau0,
                                evset=evset0, iters=jnp.zeros((), jnp.int32))
            rejected = dict(c)
            rejected["n_rej"] = c["n_rej"] + 1
            rejected["h"] = dt_next
            rejected["cstate"] = cstate1
            go = keep & ~found
            res = branch(go, advance, lambda cc: cc, accepted)
            res = jax.tree_util.tree_map(lambda a, b: jnp.where(keep & found, a, b), start_locate, res)
            return jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), res, rejected)

        # ---------------------------------------------------------------- locating
        def locating(c):
            evset = c["evset"]
            x_tau = y1[:-1]
            x_dot = vf(t_end, y1, persistent)
            e, de = jax.jvp(lambda tt, xx: events(tt, xx, persistent), (t_end, x_tau),
                            (jnp.ones((), dtype), x_dot[:-1]))
            masked = jnp.where(evset, e, jnp.inf)
            a_star = jnp.argmin(masked)
            G, Gp = masked[a_star], de[a_star]
            neg = G < 0
            lo_n = jnp.where(neg, c["lo"], t_end)
            hi_n = jnp.where(neg, t_end, c["hi"])
            step = -G / Gp
            tau_n = t_end + step
            small = jnp.abs(step) <= 2 * _ulp(t_end)
            bad = ~jnp.isfinite(tau_n) | (tau_n < lo_n) | (tau_n > hi_n)
            tau_n = jnp.where(bad, 0.5 * (lo_n + hi_n), tau_n)
            conv = small | (G == 0) \
                | (hi_n - lo_n <= 4 * _ulp(t_end)) | (c["iters"] + 1 >= locate_iterations) | ~finite
            moving = dict(c)
            moving.update(lo=jax.lax.stop_gradient(lo_n), hi=jax.lax.stop_gradient(hi_n),
                          tau=jax.lax.stop_gradient(tau_n), iters=c["iters"] + 1)
            return branch(conv, lambda cc: finalize(cc, t_end, y1, interp, G, Gp, e, x_dot),
                          lambda cc: moving, c)

        out = branch(locate, locating, stepping, out)
        out["status"] = jnp.where((out["status"] == 0) & ~jnp.all(jnp.isfinite(out["y"])), 3, out["status"])
        # no progress in time for _STALL iterations (e.g. a Zeno point with rest_velocity = 0)
        progressed = jax.lax.stop_gradient(out["t"]) > c["t_prog"] + 4 * _ulp(c["t_prog"])
        out["t_prog"] = jnp.where(progressed, jax.lax.stop_gradient(out["t"]), c["t_prog"])
        out["stall"] = jnp.where(progressed, 0, c["stall"] + 1)
        out["status"] = jnp.where((out["status"] == 0) & (out["stall"] >= _STALL), 4, out["status"])
        return out

    def cond(c):
        return (c["t"] < t1) & (c["status"] == 0) & (c["n_steps"] < max_steps)

    def record(records, c):
        """Write the iteration's impact row and contact-event row (if any) into the records."""
        return _write_rows(records, c["rec"], c)

    def finish_fields(c, x0):
        """The ``ImpactTrajectory`` fields other than the impact record."""
        status = jnp.where((c["status"] == 0) & (c["t"] < t1), 2, c["status"])
        x_final = c["y"][:-1]
        W = c["y"][-1]
        energy_error = energy(x_final) - energy(x0) - W - c["E_jumps"]
        saved = jnp.arange(ns) < c["save_idx"]
        return dict(
            ts=c["ts_steps"] if at_steps else jnp.where(saved, ts, jnp.nan), xs=c["ys"][:, :-1], work=c["ys"][:, -1],
            t_final=c["t"], x_final=x_final, num_impacts=c["n_imp"],
            energy_jumps=c["E_jumps"], energy_error=energy_error,
            persistent=c["persistent"], rest_times=c["rest_time"], release_times=c["release_time"],
            num_releases=c["n_rel"], num_events=c["n_ev"],
            min_gap=c["min_gap"], constraint_residual=c["perm_res"], contact_residual=c["contact_res"],
            num_steps=c["n_steps"], num_accepted_steps=c["n_acc"], num_rejected_steps=c["n_rej"],
            status=status,
        )

    def finish(fields, records):
        return ImpactTrajectory(
            **fields, impact_times=records["imp_t"], impact_contacts=records["imp_mask"],
            x_pre=records["imp_x_pre"], x_post=records["imp_x_post"],
            normal_velocity_pre=records["imp_Psi_pre"], normal_velocity_post=records["imp_Psi_post"],
            impulses=records["imp_mu"], energy_pre=records["imp_E_pre"], energy_post=records["imp_E_post"],
            event_times=records["ev_t"], event_rest=records["ev_rest"], event_release=records["ev_release"],
            event_states=records["ev_x"], n=n, state_names=tuple(getattr(system, "state_names", ()) or ()),
        )

    return dict(init=init, body=body, cond=cond, records0=records0, record=record,
                finish_fields=finish_fields, finish=finish)


def solve_impacts(
    system,
    x0,
    t1,
    *,
    t0=0.0,
    ts=None,
    solver=None,
    rtol=1e-10,
    atol=1e-10,
    dt0=None,
    dtmax=None,
    max_steps: int = 100_000,
    max_impacts: int = 1000,
    rest_velocity=1e-6,
    graze_tol=1e-12,
    release_tol=1e-10,
    event_samples: int = 4,
    locate_iterations: int = 60,
    adjoint: str = "forward",
) -> ImpactTrajectory:
    """The pure, jittable, vmappable solve behind ``simulate_impacts`` (one member).

    ``adjoint`` (static): "forward" (a ``lax.while_loop``: jax.jvp / jax.jacfwd go
    through it, jax.grad does not) or "reverse" (``equinox.internal.while_loop`` with
    ``kind="checkpointed"`` and ``max_steps``, as diffrax's RecursiveCheckpointAdjoint:
    jax.grad / jax.vjp go through it, forward mode does not). Both give the same values.

    No input checks and no exceptions: failures are in ``status``. ``ts``: 1-D array of
    save times in [t0, t1] (None: none saved; "steps": the state after each accepted step
    that ends no event, up to ``max_steps`` rows). Everything numeric may be traced
    (differentiate with jax.jvp/jacfwd); ``solver``, ``max_steps``, ``max_impacts``,
    ``event_samples``, ``locate_iterations`` and whether ``dtmax`` is None are static.
    To batch: ``jax.vmap(lambda s, x: solve_impacts(s, x, t1, **options))`` (this is
    what ``simulate_impacts_batch`` does in chunks)."""
    mc = _machine(
        system, t1, t0=t0, ts=ts, solver=solver, rtol=rtol, atol=atol, dt0=dt0, dtmax=dtmax,
        max_steps=max_steps, max_impacts=max_impacts, rest_velocity=rest_velocity, graze_tol=graze_tol,
        release_tol=release_tol, event_samples=event_samples, locate_iterations=locate_iterations,
        reverse=adjoint == "reverse")
    x0 = jnp.asarray(x0, float)

    def step(cr):
        c, records = cr
        c = mc["body"](c)
        return c, mc["record"](records, c)

    start = (mc["init"](x0), mc["records0"]())
    if adjoint == "reverse":
        # reverse mode: recursive checkpointing over at most max_steps iterations (the
        # loop's exit is the same cond, so values are those of the forward loop)
        c, records = eqxi.while_loop(lambda cr: mc["cond"](cr[0]), step, start, max_steps=int(max_steps),
                                     kind="checkpointed")
    elif adjoint == "forward":
        c, records = jax.lax.while_loop(lambda cr: mc["cond"](cr[0]), step, start)
    else:
        raise ValueError(f"solve_impacts: adjoint must be 'forward' or 'reverse', got {adjoint!r}")
    return mc["finish"](mc["finish_fields"](c, x0), records)


def _check_settings(owner, *, rtol=None, atol=None, dt0=None, dtmax=None, constraint_tol=None, **options):
    """The settings of an impact solve, as ``simulate_impacts`` and the batches check them
    (before any numerics): tolerances and steps finite and positive, the event thresholds
    finite and >= 0, the budgets integers >= 1, no option ``solve_impacts`` does not take."""
    unknown = sorted(set(options) - set(_SETTINGS) - {"t0", "solver", "adjoint"})
    if unknown:
        raise ParameterError(f"{owner}: unknown option(s) {unknown}; the impact solve takes "
                             f"{', '.join(_SETTINGS)}, rtol, atol, dt0, dtmax, solver", unknown[0], None)
    solver_settings(rtol=rtol, atol=atol, dt0=dt0, constraint_tol=constraint_tol, owner=owner)
    if dtmax is not None and not isinstance(dtmax, jax.core.Tracer):
        positive("dtmax", dtmax, owner=owner, what="largest step [s]", as_float=np.ndim(dtmax) == 0)
    for name, what in _SETTINGS.items():
        v = options.get(name)
        if v is None or isinstance(v, jax.core.Tracer):
            continue
        if what is int:
            integer(name, v, minimum=1, owner=owner)
        else:
            positive(name, v, allow_zero=True, owner=owner, what=what, as_float=np.ndim(v) == 0)


#: settings of ``solve_impacts`` checked by ``_check_settings``: budgets (int) and event
#: thresholds (finite, >= 0)
_SETTINGS = {"max_steps": int, "max_impacts": int, "event_samples": int, "locate_iterations": int,
             "rest_velocity": "rebound normal velocity below which a contact rests",
             "graze_tol": "gap below which a crossing counts [psi units]",
             "release_tol": "multiplier below which a persistent contact is released"}


def _as_states(x0, owner, xp=np):
    """x0 as a float array (``xp``: numpy for host-side batches, jax.numpy for a solve),
    or StateError naming it."""
    if isinstance(x0, (str, bytes)) or x0 is None:
        raise StateError(f"{owner}: x0 must be an array of real numbers (q, q'), got {x0!r}", "x0")
    try:
        return xp.asarray(x0, float) if xp is np else to_device(x0)
    except (TypeError, ValueError) as e:
        raise StateError(f"{owner}: x0 must be an array of real numbers (q, q'): {e}", "x0") from None


def _concrete(*trees) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves(trees))


_solve_jit = eqx.filter_jit(solve_impacts)
#: the contact KKT solve (vector field, events, jumps) as a nested jit: traced once per
#: solve (and differentiated once under jvp) instead of at each of its call sites
_kkt_once = eqx.filter_jit(_contact_kkt)
_solve_plain_jit = eqx.filter_jit(_solve_plain)


def _with_contacts(system, unilateral, restitution):
    from ..mechanics.impacts import WithContacts

    if unilateral is not None:
        return WithContacts(system, unilateral, 1.0 if restitution is None else restitution)
    if restitution is not None:
        if getattr(system, "restitution", None) is None:
            raise TypeError(f"{type(system).__name__} has no restitution field to replace")
        return eqx.tree_at(lambda s: s.restitution, system, jnp.asarray(restitution, float))
    return system


_STATUS_MSG = {
    1: ("max_impacts={N} impacts reached before t1 (a Zeno sequence? raise rest_velocity so that "
        "chattering ends in resting contact, or raise max_impacts, or pass on_max_impacts='stop')"),
    2: "max_steps={S} exhausted (raise max_steps, or loosen rtol/atol)",
    3: "the state became NaN/inf (check the model's domain and the contact geometry)",
    4: ("the solve stalled: no progress in time over many iterations (a Zeno point: impacts "
        "accumulating; raise rest_velocity so that chattering ends in resting contact)"),
}


def simulate_impacts(
    system,
    x0,
    t1,
    *,
    t0=0.0,
    saveat=None,
    unilateral=None,
    restitution=None,
    solver=None,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    dt0=None,
    dtmax=None,
    max_steps: int = 100_000,
    max_impacts: int = 1000,
    on_max_impacts: str = "raise",
    rest_velocity: float = 1e-6,
    graze_tol: float = 1e-12,
    release_tol: float = 1e-10,
    event_samples: int = 4,
    constraint_tol: float = 1e-8,
    adjoint: str = "forward",
) -> ImpactTrajectory:
    """Integrate a system with one-sided constraints psi(t, q) >= 0 through its impacts.

    Parameters
    ----------
    system : a ``ConstrainedLagrangian`` (state x = (q, q')) that declares
        ``unilateral_constraints(t, q)`` and ``restitution`` (the impact scenes do), or
        any ``ConstrainedLagrangian`` together with ``unilateral=psi``.
    x0 : initial state (q, q') with psi(t0, q0) >= 0 and the permanent constraints met.
        A contact with psi ~ 0, Psi ~ 0 and a compressive multiplier starts persistent.
    t1, t0 : time interval [s].
    saveat : int (that many equally spaced saved times, default 101) or 1-D array of
        times in [t0, t1]; 0: save nothing; "steps": the state after every accepted step
        that ends no event, at the step's end (``ts`` holds those times, NaN past the
        last; at most ``max_steps`` rows): the states over which ``constraint_residual``
        and ``contact_residual`` are taken.
    unilateral : psi(t, q) -> (k,) gaps (admissible where >= 0), added to ``system``
        by ``nhjax.mechanics.WithContacts``.
    restitution : alpha in [0, 1], scalar or (k,): overrides the system's.
    solver : a diffrax Runge-Kutta solver with dense output (default ``diffrax.Dopri5()``).
    rtol, atol : tolerances of the ``diffrax.PIDController``.
    dtmax : largest step [s] (default: ``system.event_resolution`` if it has one).
    max_steps : budget of loop iterations (steps and root-finding steps).
    max_impacts : size of the impact record and bound on the number of impacts.
    on_max_impacts : "raise" (IntegrationError) or "stop" (return the motion up to the
        max_impacts-th impact; ``t_final`` is its time).
    rest_velocity : rebound normal velocity below which a contact comes to rest
        (persistent contact); see the module docstring ("Rules").
    graze_tol, release_tol : detection thresholds for gaps (psi units) and for the
        multipliers of persistent contacts (force units).
    event_samples : dense-output samples per step at which events are looked for.
    constraint_tol : largest violation of psi >= 0 and of the permanent constraints
        accepted in x0.
    adjoint : "forward" (default: jax.jvp / jax.jacfwd differentiate the solve) or
        "reverse" (jax.grad / jax.vjp: the event loop is a checkpointed while loop of at
        most max_steps iterations, as diffrax's RecursiveCheckpointAdjoint). Same values.

    Notes
    -----
    Returns an ``ImpactTrajectory``. Jit, vmap and forward-mode differentiation go
    through (then failures become ``equinox.error_if`` runtime errors); for batches
    see ``simulate_impacts_batch``; the pure per-member function is ``solve_impacts``.
    """
    owner = "simulate_impacts"
    choice("on_max_impacts", on_max_impacts, ("raise", "stop"), owner=owner)
    choice("adjoint", adjoint, ("forward", "reverse"), owner=owner)
    _check_settings(owner, max_impacts=max_impacts, max_steps=max_steps, event_samples=event_samples, rtol=rtol,
                    atol=atol, dt0=dt0, dtmax=dtmax, constraint_tol=constraint_tol, rest_velocity=rest_velocity,
                    graze_tol=graze_tol, release_tol=release_tol)
    t0, t1 = time_span(t0, t1, owner=owner)
    system = _with_contacts(system, unilateral, restitution)
    x0 = _as_states(x0, owner, jnp)
    n = _lagrangian_size(system, owner)
    if x0.shape != (2 * n,):
        raise StateError(f"{owner}: x0 has shape {x0.shape}; {type(system).__name__} expects (q, q') of shape "
                         f"({2 * n},): pass the positions and then the velocities", "x0")
    k = _num_contacts(system, t0, x0)
    # known values (concrete, or under jax.grad / jax.jvp of concrete values): checked here,
    # and the solve and its derivatives are stored programs (nhjax._primitive)
    known = _primitive.has_values(system, x0, t0, t1)
    if known:
        csys, cx0, ct0, ct1 = _primitive.concrete((system, x0, t0, t1))
        report = _programs.call("impacts-start", _start_report,
                                (csys, cx0, to_device(ct0), to_device(ct1),
                                 _boundary_samples(csys, ct0, ct1)), compiler_options=_programs.QUICK_OPTIONS)
        failures = _start_failures(jax.tree_util.tree_map(lambda a: np.asarray(a)[None], report), 1,
                                   constraint_tol, owner)
        if failures:
            raise failures[0][1][1]
    if saveat is None:
        saveat = 101
    if isinstance(saveat, (int, np.integer)) and not isinstance(saveat, bool) and saveat == 0:
        ts = None  # no saved times
    elif isinstance(saveat, str):
        choice("saveat", saveat, ("steps",), owner=owner)
        ts = "steps"
    else:
        check_saveat(saveat, t0, t1, owner=owner)
        ts = _save_times(saveat, t0, t1)
    if dtmax is None:
        dtmax = getattr(system, "event_resolution", None)
    arr = lambda v: None if v is None else to_device(v)  # noqa: E731 (no recompiles)
    args = (system, x0, arr(t1), arr(t0), ts, solver, arr(rtol), arr(atol), arr(dt0), arr(dtmax), int(max_steps),
            int(max_impacts), arr(rest_velocity), arr(graze_tol), arr(release_tol), int(event_samples), adjoint)
    if known:
        out = _primitive.call("impacts", _solve_plain, args, forward=functools.partial(_with_adjoint, "forward"),
                              reverse=functools.partial(_with_adjoint, "reverse"),
                              options=_loop_options(system, t0, x0), max_tangents=_MAX_TANGENTS,
                              fallback=lambda *a: _solve_plain_jit(*a))
        traj = ImpactTrajectory(**out, n=n, state_names=tuple(getattr(system, "state_names", ()) or ()))
    else:
        traj = _solve_jit(
            system, x0, args[2], t0=args[3], ts=ts, solver=solver, rtol=args[6], atol=args[7], dt0=args[8],
            dtmax=args[9], max_steps=int(max_steps), max_impacts=int(max_impacts), rest_velocity=args[12],
            graze_tol=args[13], release_tol=args[14], event_samples=int(event_samples), adjoint=adjoint,
        )
    fatal = (2, 3, 4) if on_max_impacts == "stop" else (1, 2, 3, 4)
    if not _concrete(traj.status):
        bad = jnp.isin(traj.status, jnp.asarray(fatal))
        out = eqx.error_if((traj.x_final, traj.xs), bad, "nhjax.simulate_impacts: the solve failed "
                           "(max_impacts reached, max_steps exhausted or NaN/inf); see ImpactTrajectory.status")
        return eqx.tree_at(lambda tr: (tr.x_final, tr.xs), traj, out)
    status = int(traj.status)
    if status in fatal:
        msg = _STATUS_MSG[status].format(N=max_impacts, S=max_steps)
        raise IntegrationError(msg, float(traj.t_final), trajectory=traj)
    return traj


def _member_of(tree, axes, idx):
    """Member ``idx`` of ``tree`` (leaves with a leading member axis where ``axes`` is 0)."""
    return jax.tree_util.tree_map(lambda a, ax: a if ax is None else a[idx], tree, axes,
                                  is_leaf=lambda a: a is None)


def _lockstep_chunk_impl(system, x0, t1, n_members, sys_axes, x_axis, options, lanes):
    """Members ``0 .. n_members - 1`` of ``system`` / ``x0`` (member axis 0 where
    ``sys_axes`` / ``x_axis`` say 0; size M = the chunk's capacity) by a lock-step loop:
    ``lanes`` members step together (``_machine``'s body vmapped over the lanes, every lane
    with its own step size, impacts and contact modes); a lane whose member ended (t1,
    max_impacts, failure) stays idle until R = lanes / 16 lanes are idle, then every idle
    lane writes its member's results into the member's slot and takes the next member of
    the queue. Impact rows go straight into the member's slot of the [M, N, ...] record
    as they happen. Each member takes exactly the iterations of its own ``solve_impacts``."""
    leaves = [a for a, ax in zip(jax.tree_util.tree_leaves((system, x0)),
                                 jax.tree_util.tree_leaves((sys_axes, x_axis), is_leaf=lambda a: a is None))
              if ax is not None]
    M = leaves[0].shape[0]
    L = max(1, min(int(lanes), M))
    R = max(1, L // 16)
    n_members = jnp.asarray(n_members, jnp.int32)
    lane = jnp.arange(L, dtype=jnp.int32)
    # the branches of an iteration (a root find, a dip search, an impact) run only in the
    # iterations where some lane takes them (lazy_cond; lax.cond would run them on every lane)
    options = dict(options, branch=lazy_cond)
    mc0 = _machine(_member_of(system, sys_axes, 0), t1, **options)

    def parts(mem):
        s = _member_of(system, sys_axes, mem)
        x = x0 if x_axis is None else x0[mem]
        return x, _machine(s, t1, **options)

    def init_lane(mem):
        x, mc = parts(mem)
        return mc["init"](x)

    def body_lane(mem, c):
        _, mc = parts(mem)
        go = mc["cond"](c)
        new = mc["body"](c)
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(go, a, b), new, c)
        return new, go

    def active_lane(mem, c):
        return parts(mem)[1]["cond"](c)

    def fields_lane(mem, c):
        x, mc = parts(mem)
        return mc["finish_fields"](c, x)

    def safe(mem):  # empty lanes (member M) compute member M - 1, unused
        return jnp.minimum(mem, M - 1)

    # every member's results, filled in as members end; impact rows as they happen
    shape = jax.eval_shape(lambda c: jax.vmap(fields_lane)(lane, c), jax.eval_shape(jax.vmap(init_lane), lane))
    out = jax.tree_util.tree_map(lambda sd: jnp.zeros((M,) + sd.shape[1:], sd.dtype), shape)
    rec = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (M,) + a.shape), mc0["records0"]())

    def active_of(st):
        return (st["mem"] < n_members) & jax.vmap(active_lane)(safe(st["mem"]), st["c"])

    def want_refill(st):
        return (st["next"] < n_members) & (jnp.sum(~active_of(st)) >= R)

    def retire(st, out, which):
        """Write the lanes ``which`` (and holding a member) into their members' slots."""
        has = which & (st["mem"] < n_members)
        done = jax.vmap(fields_lane)(safe(st["mem"]), st["c"])
        dest = jnp.where(has, st["mem"], M + lane)  # out of range: dropped (unique)
        return jax.tree_util.tree_map(lambda o, v: o.at[dest].set(v, mode="drop", unique_indices=True), out, done)

    def refill(args):
        st, out, rec = args
        idle = ~active_of(st)
        out = retire(st, out, idle)
        # the k-th idle lane takes member next + k
        rank = (jnp.cumsum(idle) - 1).astype(jnp.int32)
        new_mem = jnp.where(idle, st["next"] + rank, st["mem"])
        new_mem = jnp.where(idle & (new_mem >= n_members), M, new_mem)
        fresh = jax.vmap(init_lane)(safe(new_mem))
        take = idle & (new_mem < n_members)
        c = jax.tree_util.tree_map(lambda a, b: jnp.where(take.reshape((L,) + (1,) * (a.ndim - 1)), a, b),
                                   fresh, st["c"])
        nxt = jnp.minimum(st["next"] + jnp.sum(idle).astype(jnp.int32), n_members)
        return dict(mem=new_mem, c=c, next=nxt), out, rec

    # In the stepping loop the lanes' state has the lane axis last: each state component is
    # a contiguous vector over the lanes, which XLA's elementwise loops vectorize.
    def first(tree):
        return jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 0) if a.ndim else a, tree)

    def last(tree):
        return jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1) if a.ndim else a, tree)

    def active_last(st):
        act = jax.vmap(active_lane, in_axes=(0, -1))(safe(st["mem"]), st["c"])
        return (st["mem"] < n_members) & act

    def want_refill_last(st):
        return (st["next"] < n_members) & (jnp.sum(~active_last(st)) >= R)

    def steps(sr):
        st, rec = sr
        c, go = jax.vmap(body_lane, in_axes=(0, -1), out_axes=(-1, 0))(safe(st["mem"]), st["c"])
        dest = jnp.where(go & (st["mem"] < n_members), st["mem"], M)  # out of range: dropped
        rows = first(c["rec"])
        rec = _write_rows(rec, rows, c, lead=(dest,))
        return dict(st, c=c), rec

    def run_lanes(args):
        st, out, rec = args
        st = dict(st, c=last(st["c"]))
        st, rec = jax.lax.while_loop(lambda sr: jnp.any(active_last(sr[0])) & ~want_refill_last(sr[0]), steps,
                                     (st, rec))
        st = dict(st, c=first(st["c"]))
        return jax.lax.cond(want_refill(st), refill, lambda a: a, (st, out, rec))

    def queue_left(args):
        st = args[0]
        return jnp.any(active_of(st)) | (st["next"] < n_members)

    mem0 = jnp.where(lane < n_members, lane, M)
    st = dict(mem=mem0, c=jax.vmap(init_lane)(safe(mem0)), next=jnp.minimum(n_members, L))
    st, out, rec = jax.lax.while_loop(queue_left, run_lanes, (st, out, rec))
    out = retire(st, out, jnp.ones(L, bool))  # the last members
    return mc0["finish"](out, rec)


_lockstep_chunk_jit = eqx.filter_jit(_lockstep_chunk_impl)


def _lockstep_chunk_plain(*args):
    tr = _lockstep_chunk_impl(*args)
    return {k: getattr(tr, k) for k in _FIELDS}


def _lockstep_chunk(*args, compiler_options=None):
    """``_lockstep_chunk_impl`` as a stored program (a new process loads it, traces nothing),
    compiled with ``compiler_options`` (``_loop_options``)."""
    out = _programs.call("impacts-batch", _lockstep_chunk_plain, args, compiler_options=compiler_options,
                         fallback=lambda *a: _lockstep_chunk_plain_jit(*a))
    system = args[0]
    return ImpactTrajectory(**out, n=system.n, state_names=tuple(getattr(system, "state_names", ()) or ()))


_lockstep_chunk_plain_jit = eqx.filter_jit(_lockstep_chunk_plain)


class ImpactBatchTrajectory(MemberStatuses, ImpactTrajectory):
    """The result of an impact batch (``simulate_impacts_batch``, or ``simulate_batch`` on
    a system with one-sided constraints): every field of ``ImpactTrajectory`` with a
    leading member axis, and the batch interface of ``simulate_batch``'s
    ``BatchTrajectory`` (``nhjax.integrate.batch.MemberStatuses``).

    status : codes into ``STATUS``: 0 "success" (reached t1), 1 "max_impacts", 2
        "max_steps", 3 "nonfinite", 4 "stalled", 5 "bad input" (the member's start or
        parameters failed the checks of ``simulate_impacts``; not solved: its numbers are
        NaN, its counts 0, its ``t_final`` t0).
    reasons : member -> text, for every member that did not reach t1.
    Masks ``ok`` (reached t1), ``stopped`` (ended at max_impacts with
    ``on_max_impacts="stop"``), ``failed`` (anything else); ``status_names()``,
    ``counts()``, ``summary()``.
    """

    reasons: dict = eqx.field(static=True, default_factory=dict)
    stop_codes: tuple = eqx.field(static=True, default=())

    STATUS_NAMES = tuple(STATUS[i] for i in range(len(STATUS)))

    @property
    def stopped(self):
        return np.isin(np.asarray(self.status), self.stop_codes)

    def summary(self, show: int = 8) -> str:
        """How many members reached t1, which did not and why, and the spread of impacts,
        steps and accuracy diagnostics over the members that did."""
        ok = self.ok | self.stopped
        lines = [f"{len(self)} members: " + ", ".join(f"{k} {v}" for k, v in self.counts().items())]
        if ok.any():
            for label, v in (("impacts", self.num_impacts), ("steps (accepted)", self.num_accepted_steps)):
                v = np.asarray(v)[ok]
                lines.append(f"  {label} (members that ran): min {v.min()}, median {int(np.median(v))}, max {v.max()}")
            for label, v in (("energy bookkeeping error", np.abs(np.asarray(self.energy_error))),
                             ("permanent-constraint residual", np.asarray(self.constraint_residual)),
                             ("contact residual", np.asarray(self.contact_residual))):
                lines.append(f"  {label}: max {v[ok].max():.2e} (median {np.median(v[ok]):.2e})")
            lines.append(f"  smallest gap: {np.asarray(self.min_gap)[ok].min():.3g}")
        return "\n".join(lines + self._reason_lines(show))


def _batch_axes(system, x0, in_axes, owner):
    """(system axes pytree, x0 axis, batch size) from ``in_axes`` (see
    ``simulate_impacts_batch``), with x0's shape checked against the system's (q, q')."""
    in_axes = axes_dict(in_axes, ("system", "x0"), owner=owner)
    x_axis = in_axes.get("x0", 0 if x0.ndim == 2 else None)
    if x_axis not in (0, None):
        raise ParameterError(f"{owner}: in_axes['x0'] must be 0 or None, got {x_axis!r}", "in_axes", in_axes)
    n = _lagrangian_size(system, owner)
    want = (2 * n,) if x_axis is None else (x0.shape[0] if x0.ndim else 0, 2 * n)
    if x0.shape != want or (x_axis == 0 and x0.ndim != 2):
        per = f"({2 * n},) shared by every member" if x_axis is None else f"(members, {2 * n}), one row per member"
        raise StateError(f"{owner}: x0 has shape {x0.shape}; {type(system).__name__} expects (q, q') of shape {per} "
                         "(in_axes['x0'] says which): pass the positions and then the velocities", "x0")
    sys_axes = in_axes.get("system", None)
    if isinstance(sys_axes, (list, tuple)) and all(isinstance(nm, str) for nm in sys_axes):
        names = tuple(sys_axes)
        for nm in names:
            if not hasattr(system, nm):
                raise ParameterError(f"{owner}: in_axes['system'] names '{nm}', which {type(system).__name__} "
                                     "does not have", "in_axes", in_axes)
        sys_axes = jax.tree_util.tree_map(lambda _: None, system)
        sys_axes = eqx.tree_at(lambda s: tuple(getattr(s, nm) for nm in names), sys_axes,
                               tuple(0 for _ in names), is_leaf=lambda a: a is None)
    elif sys_axes == 0:
        sys_axes = jax.tree_util.tree_map(lambda a: 0 if eqx.is_array(a) else None, system)
    elif sys_axes is None:
        sys_axes = jax.tree_util.tree_map(lambda _: None, system)
    sizes = set()
    if x_axis is not None:
        sizes.add(x0.shape[x_axis])
    for a, ax in zip(jax.tree_util.tree_leaves(system), jax.tree_util.tree_leaves(sys_axes, is_leaf=lambda a: a is None)):
        if ax is not None:
            if not np.ndim(a):
                raise ParameterError(f"{owner}: a batched field of {type(system).__name__} is a scalar: every "
                                     "batched field needs the member axis first", "in_axes", in_axes)
            sizes.add(np.shape(a)[ax])
    if len(sizes) != 1:
        raise ParameterError(f"{owner}: batched inputs must share one batch size; got sizes {sorted(sizes)} "
                             "(check in_axes: which of system / x0 carry a leading member axis)", "in_axes", in_axes)
    B = sizes.pop()
    if B == 0:
        raise ParameterError(f"{owner}: the batch has no members (a leading member axis of length 0): pass at "
                             "least one", "x0" if x_axis is not None else "system")
    return sys_axes, x_axis, B


def _members_of(system, x0, sys_axes, x_axis, idx):
    """Members ``idx`` (host-side numpy indexing) of the batched parts of system and x0."""
    s = jax.tree_util.tree_map(lambda a, ax: a if ax is None else np.asarray(a)[idx], system, sys_axes,
                               is_leaf=lambda a: a is None)
    return s, (x0 if x_axis is None else np.asarray(x0)[idx])


def simulate_impacts_batch(system, x0, t1, *, in_axes=None, chunk_size=None, lanes: int = 16, workers=None,
                           saveat=0, on_error: str = "raise", on_max_impacts: str = "raise",
                           constraint_tol: float = 1e-8, **options) -> ImpactBatchTrajectory:
    """Many impact solves at once, by a lock-step loop with a member queue.

    Before any solve, every member's start and parameters get the checks of
    ``simulate_impacts`` (all members at once, one program): x0 finite, restitution in
    [0, 1], no moving boundary degenerating in [t0, t1], psi(t0, q0) >= -constraint_tol,
    the permanent constraints met. A check that fails on shared inputs (not batched)
    raises the named error ``simulate_impacts`` raises; a member that fails one is not
    solved: status "bad input" and its reason in ``reasons``.

    The members are cut into chunks (default: one per worker), each a compiled program
    run on its own thread (default: one per CPU core; XLA releases the GIL while a
    compiled chunk runs). In a chunk ``lanes`` members step together (the event loop of
    ``solve_impacts``, one iteration per lane and loop pass, each lane with its own step
    size, impacts and contact modes); when a member ends, its lane takes the next member
    of the chunk, so members that need many more iterations than others (chattering,
    many impacts) do not hold the rest up. Each member's result is that of its own
    ``solve_impacts`` (same steps, same root finds).

    ``in_axes``: dict with keys "system" and "x0" (0 for batched along axis 0, None for
    shared). For the system also a list of field names whose arrays carry the member
    axis, e.g. ``{"system": ["A"]}`` with ``eqx.tree_at(lambda s: s.A, ball, amplitudes)``
    to vary only the amplitude, or a pytree of axes.
    Default: x0 batched if it is 2-D, the system shared. ``chunk_size``: most members per
    compiled chunk (the batch is split into at least one chunk per worker). ``lanes``: members
    stepped together per chunk. ``saveat``: 0 (nothing saved, default) or an int / 1-D
    array of save times as in ``simulate_impacts``; other keyword arguments are
    ``solve_impacts``'s (default rtol = atol = 1e-10, as ``simulate_impacts``).

    ``on_error``: "raise" (default: ``BatchError`` naming the members with bad inputs,
    before anything is solved, or whose solve failed) or "return" (a sweep: nothing
    raises, every member's status and reason are in the result). ``on_max_impacts``:
    "raise" (reaching max_impacts is a failure, as in ``simulate_impacts``) or "stop"
    (the member ends there: ``stopped``, e.g. to record a fixed number of impacts).
    Returns an ``ImpactBatchTrajectory``: the fields of ``ImpactTrajectory`` with a
    leading member axis, and ``status``, ``reasons``, ``ok``, ``summary()``.
    """
    import os
    from concurrent.futures import ThreadPoolExecutor

    owner = "simulate_impacts_batch"
    choice("on_error", on_error, ("raise", "return"), owner=owner)
    choice("on_max_impacts", on_max_impacts, ("raise", "stop"), owner=owner)
    t0 = options.get("t0", 0.0)
    t0, t1 = time_span(t0, t1, owner=owner)
    if chunk_size is not None:
        chunk_size = integer("chunk_size", chunk_size, minimum=1, owner=owner)
    lanes = integer("lanes", lanes, minimum=1, owner=owner)
    if workers is not None:
        workers = integer("workers", workers, minimum=1, owner=owner, what="concurrent chunks")
    if not (isinstance(saveat, (int, np.integer)) and not isinstance(saveat, bool) and saveat == 0):
        check_saveat(saveat, t0, t1, owner=owner)
    _check_settings(owner, constraint_tol=constraint_tol, **options)
    options = {k_: int(v) if _SETTINGS.get(k_) is int else v for k_, v in options.items()}
    x0 = _as_states(x0, owner)
    sys_axes, x_axis, B = _batch_axes(system, x0, in_axes, owner)
    k = _num_contacts(system, t0, jax.ShapeDtypeStruct((2 * system.n,), jnp.float64))
    del k  # (a system without one-sided constraints is refused there)

    # -- every member's start, checked at once (one program) before any solve
    sys0 = _members_of(system, x0, sys_axes, x_axis, 0)[0]
    n_samples = _boundary_samples(sys0, t0, t1)
    report = _programs.call("impacts-start-batch", _start_report_batch,
                            (system, x0, to_device(t0), to_device(t1), n_samples, sys_axes,
                             x_axis), compiler_options=_programs.QUICK_OPTIONS)
    batched = (any(ax is not None for ax in jax.tree_util.tree_leaves(sys_axes)), x_axis is not None)
    failures = _start_failures(report, B, float(constraint_tol), owner, batched)
    reasons = {j: why for j, (why, _) in failures}
    if failures and on_error == "raise":
        members = [j for j, _ in failures]
        raise BatchError("bad inputs", members, [reasons[j] for j in members], [float(t0)] * len(members))
    good = np.setdiff1d(np.arange(B), np.asarray(list(reasons), int))

    ts = None if isinstance(saveat, (int, np.integer)) and saveat == 0 else _save_times(saveat, t0, t1)
    if "dtmax" not in options:
        options["dtmax"] = getattr(sys0, "event_resolution", None)
    opts = {k_: (to_device(v) if isinstance(v, float) else v) for k_, v in options.items()}
    opts["ts"] = ts
    # the quick settings only while the lanes' stepping loop stays small enough for XLA to
    # compile it into one function (16 lanes of a ball do, 64 do not: their loop then runs
    # kernel by kernel, and those kernels run faster optimized; benchmarks/impacts.py)
    loop_options = (_loop_options(sys0, t0, jax.ShapeDtypeStruct((2 * system.n,), jnp.float64))
                    if lanes <= _QUICK_LANES else _programs.SOLVE_OPTIONS)
    workers = (os.cpu_count() or 1) if workers is None else workers
    t1a = to_device(t1)

    def run_members(system, x0, B):
        """Solve the B members of system / x0 (all of them good) in chunks."""
        chunk = -(-B // workers)  # at least one chunk per worker
        if chunk_size is not None:
            chunk = min(chunk, chunk_size)
        chunk = int(max(1, min(chunk, B)))
        starts = list(range(0, B, chunk))
        # Members are dealt to the chunks in turn (chunk j: members j, j + W, ...): a sweep over a
        # sorted parameter has its slow members (chattering, many impacts) side by side, and
        # contiguous chunks would give one worker most of them.
        W = len(starts)
        perm = np.concatenate([np.arange(j, B, W) for j in range(W)])

        def run(lo):
            # chunk members perm[lo .. lo+chunk-1]; a short last chunk is padded with copies of
            # its last member, which are not solved
            s, x = _members_of(system, x0, sys_axes, x_axis, perm[np.minimum(np.arange(lo, lo + chunk), B - 1)])
            return jax.device_get(_lockstep_chunk(s, x, t1a, np.int32(min(chunk, B - lo)), sys_axes, x_axis, opts,
                                                  lanes, compiler_options=loop_options))

        first = run(starts[0])  # compile once, then the rest concurrently
        with ThreadPoolExecutor(max_workers=workers) as pool:
            rest = list(pool.map(run, starts[1:]))
        sizes_ = [min(chunk, B - lo) for lo in starts]
        inv = np.argsort(perm)
        return jax.tree_util.tree_map(
            lambda *a: np.concatenate([np.asarray(x)[:sz] for x, sz in zip(a, sizes_)])[inv],
            *[eqx.partition(o, eqx.is_array)[0] for o in [first] + rest])

    if good.size:
        solved = run_members(*_members_of(system, x0, sys_axes, x_axis, good), good.size)
        if good.size < B:
            solved = jax.tree_util.tree_map(lambda a: _scatter(a, good, B), solved)
    else:  # nothing to solve: the fields' shapes without a solve
        settings = {k_: v for k_, v in options.items() if k_ in _SETTINGS or k_ in ("solver", "dtmax")}
        shape = jax.eval_shape(lambda: _solve_plain(
            sys0, jnp.zeros(2 * system.n), t1a, jnp.asarray(t0, float), ts, settings.get("solver"), 1e-10, 1e-10,
            None, settings.get("dtmax"), settings.get("max_steps", 100_000), settings.get("max_impacts", 1000), 1e-6,
            1e-12, 1e-10, settings.get("event_samples", 4), "forward"))
        solved = {k_: _scatter(np.zeros(v.shape, v.dtype)[None], np.zeros(0, int), B) for k_, v in shape.items()}
    return _impact_statuses(solved, reasons, system, t0, on_error, on_max_impacts,
                            int(options.get("max_impacts", 1000)), int(options.get("max_steps", 100_000)))


def _scatter(a, rows, B):
    """A (B, ...) array with ``a``'s rows at ``rows`` and the other members' rows empty:
    NaN (floats), 0 (integers), False."""
    a = np.asarray(a)
    fill = np.nan if np.issubdtype(a.dtype, np.floating) else 0
    out = np.full((B,) + a.shape[1:], fill, a.dtype)
    out[rows] = a[: len(rows)]
    return out


def _impact_statuses(fields, reasons, system, t0, on_error, on_max_impacts, max_impacts, max_steps):
    """The batch result from the members' fields (numpy, leading member axis; members in
    ``reasons`` were not solved), with a reason for every member that did not reach t1;
    raises BatchError for failed members when ``on_error="raise"``."""
    fields = {k: np.asarray(v) for k, v in (fields.items() if isinstance(fields, dict) else
                                             ((f, getattr(fields, f)) for f in _FIELDS))}
    bad = np.zeros(len(fields["status"]), bool)
    bad[list(reasons)] = True
    fields["status"] = np.where(bad, BAD_INPUT, fields["status"]).astype(np.int32)
    fields["t_final"] = np.where(bad, float(t0), fields["t_final"])
    reasons = dict(reasons)
    stop = (1,) if on_max_impacts == "stop" else ()
    for j in np.nonzero(~bad & (fields["status"] != 0))[0]:
        code = int(fields["status"][j])
        reasons[int(j)] = (f"stopped after max_impacts={max_impacts} impacts" if code in stop
                           else _STATUS_MSG[code].format(N=max_impacts, S=max_steps))
    # (jax.device_put, not jnp.asarray: an eager jnp.asarray of a host array is a program
    # compiled per shape and dtype, seconds for a result's thirty-odd fields in a new process)
    traj = ImpactBatchTrajectory(**jax.device_put(fields), n=system.n,
                                 state_names=tuple(getattr(system, "state_names", ()) or ()), reasons=reasons,
                                 stop_codes=stop)
    failed = np.nonzero(traj.failed)[0].tolist()
    if on_error == "raise" and failed:
        raise BatchError("failed solves", failed, [reasons[m] for m in failed],
                         [float(np.asarray(traj.t_final)[m]) for m in failed], traj)
    return traj


def simulate_batch_impacts(system, x0, t1, *, t0=0.0, control=None, in_axes=None, chunk_size: int = 8192,
                           lanes=None, workers=None, progress=None, saveat=2, solver=None, rtol=None,
                           atol=None, dt0=None, max_steps=None, stepsize_controller=None, jump_ts=None,
                           adjoint=None, project: bool = False, project_steps=None, constraint_tol: float = 1e-8,
                           on_guard: str = "raise", on_error: str = "raise", track_work=None,
                           diagnostics: bool = True, **impact_options) -> ImpactBatchTrajectory:
    """``simulate_batch``'s signature for systems with one-sided constraints (those that
    define ``unilateral_constraints``): the lock-step impact batch
    (``simulate_impacts_batch``). ``in_axes`` takes ``simulate_batch``'s {"system": 0 /
    None, "x0": 0 / None}; ``saveat``, ``rtol``, ``atol`` (default 1e-10, as
    ``simulate_impacts``), ``dt0``, ``solver``, ``max_steps``, ``chunk_size``, ``lanes``,
    ``workers``, ``constraint_tol`` and ``on_error`` mean what they mean there; further
    keyword arguments (``max_impacts``, ``on_max_impacts``, ``rest_velocity``, ...) are
    ``simulate_impacts_batch``'s. Returns an ``ImpactBatchTrajectory`` (per-member
    ``status`` and ``reasons``, ``ok``, ``summary()``). Arguments without a meaning for
    impacts (controls, adjoints, jump times, projection, a custom step-size controller)
    raise a ParameterError naming them."""
    owner = "simulate_batch (a system with one-sided constraints)"
    unsupported = dict(control=control, stepsize_controller=stepsize_controller, jump_ts=jump_ts,
                       adjoint=adjoint, project_steps=project_steps)
    for name, v in unsupported.items():
        if v is not None:
            raise ParameterError(f"{owner}: {name}={v!r} is not supported for impact systems; leave it None "
                                 "(or call nhjax.simulate_impacts_batch directly)", name, v)
    if project:
        raise ParameterError(f"{owner}: project=True is not supported for impact systems; persistent contacts "
                             "are projected by the event loop itself", "project", project)
    choice("on_guard", on_guard, ("raise", "stop"), owner=owner)
    axes = axes_dict(in_axes, ("system", "x0", "control"), owner=owner, default={"x0": 0})
    opts = dict(impact_options, t0=t0, rtol=1e-10 if rtol is None else rtol, atol=1e-10 if atol is None else atol,
                dt0=dt0, solver=solver)
    if max_steps is not None:
        opts["max_steps"] = max_steps
    return simulate_impacts_batch(system, x0, t1, in_axes=axes, chunk_size=chunk_size,
                                  lanes=16 if lanes is None else lanes, workers=workers, saveat=saveat,
                                  on_error=on_error, constraint_tol=constraint_tol, **opts)
