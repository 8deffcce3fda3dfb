"""The falling cat's somersault as optimal-control problems (seed 000, secs. 4 and 7).

Velocity control (7.1), minimizing the vibrational energy (4.8)
int I1 [(1 + B s^2) theta'^2 + lam s^2/D chi'^2] dt, whose Pontryagin
Hamiltonian is Iwai's (7.6) (here in the minimum convention, with H_min =
-H_Iwai at the optimum):

* ``velocity_somersault_chart``: in Iwai's chart (theta, chi, psi); the shape
  returns (theta(T) = theta0) after chi winds ``windings`` times, and psi turns
  by ``turn`` (this fixes the representative of psi and the winding).
* ``velocity_somersault_smooth``: in coordinates smooth at the straight cat
  (``FallingCatSmooth``: w = theta (cos chi, sin chi), phi = psi + chi); the
  shape returns (w(T) = w(0)) and the fiber turns by ``turn + 2 pi j``: the
  optimizer chooses how often chi winds, and j picks the class modulo 2 pi.

Torque control (7.14)-(7.15): ``torque_somersault``, rest to rest, minimizing
int |u|^2 dt.

``somersault_free_winding`` solves the smooth problem from several starting
loops (each winding chi any number of times, one of them a poor pick), keeps
the best, reports the winding it found and polishes it by Pontryagin shooting
from the costates of the direct optimum.

``fixed_theta_costates`` gives the exact extremal of the chart problem when the
turn is the holonomy of the fixed-theta loop (-2 pi f(theta0) per winding): the
start of a continuation in the turn.
"""

from __future__ import annotations

import dataclasses
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from nhjax.scenes import FallingCat, FallingCatKinematic
from nhjax.scenes.falling_cat import FallingCatSmooth

from .._result import DirectResult
from ..direct import solve_direct
from ..parametrize import Chebyshev, Parametrization, fit_samples, prepare_fit
from ..pontryagin import IndirectResult, pmp_residual, prepare_pmp_residual, prepare_pontryagin, solve_pontryagin
from nhjax import _validate as V

from ..problem import OCP, ProblemError, as_problem_error, compiled, host_array, prepare_saved_path, saved_path
from ..sqp import prepare_direct_sqp


def _task_inputs(owner, cat, kind, theta0, turn, windings=None, chart=True):
    """Entry checks of the somersault tasks: the cat's type, a starting bend inside the
    chart (0 < theta0 < pi) or any finite one (smooth coordinates), a finite turn."""
    if not isinstance(cat, kind):
        raise ProblemError(f"{owner}: cat must be an nhjax.scenes.{kind.__name__}, got {type(cat).__name__}")
    with as_problem_error():
        if chart:
            V.in_range("theta0", theta0, 0.0, np.pi, lo_closed=False, hi_closed=False, owner=owner, shape=(),
                       what="half bend angle inside Iwai's chart [rad]")
        else:
            V.real("theta0", theta0, owner=owner, shape=(), what="half bend angle [rad]")
        V.real("turn", turn, owner=owner, shape=(), what="turn of the cat about e2 [rad]")
        if windings is not None:
            V.real("windings", windings, owner=owner, shape=(), what="turns of the twist chi")


def _guess_inputs(owner, param, dim, T, system="the cat"):
    """Entry checks of the starting guesses: ``param`` a controls parametrization of
    ``dim`` inputs (those ``system`` takes), the horizon T [s] (``V.duration``). Returns
    T as a float."""
    if not isinstance(param, Parametrization):
        raise ProblemError(f"{owner}: param must be a control parametrization (controls.Chebyshev, "
                           f"PiecewiseLinear, ...), got {type(param).__name__}")
    if param.dim != dim:
        raise ProblemError(f"{owner}: the parametrization has {param.dim} inputs, {system} takes {dim}: build it "
                           f"with dim={dim} (e.g. {type(param).__name__}({param.n}, T, {dim}))")
    with as_problem_error():
        return V.duration("T", T, owner=owner)

__all__ = [
    "Effort",
    "TerminalTarget",
    "Vibrational",
    "FreeWindingResult",
    "fixed_theta_costates",
    "loop_guess",
    "torque_loop_guess",
    "smooth_to_chart",
    "somersault_free_winding",
    "torque_somersault",
    "velocity_somersault_chart",
    "velocity_somersault_smooth",
]


class Vibrational(eqx.Module):
    """Running cost: the vibrational energy rate (4.8) of a velocity-controlled cat."""

    system: object

    def __call__(self, t, x, u):
        return self.system.vibrational_power(x, u)


class Effort(eqx.Module):
    """Running cost |u|^2."""

    def __call__(self, t, x, u):
        return u @ u


class TerminalTarget(eqx.Module):
    """Terminal constraints x(T) - target (an array: a new target does not recompile)."""

    target: jax.Array

    def __call__(self, x):
        return x - self.target


def velocity_somersault_chart(cat: FallingCatKinematic, theta0, turn, T, windings=1) -> OCP:
    """Chart problem: x = (theta, chi, psi), x0 = (theta0, 0, 0); at T: theta = theta0,
    chi = 2 pi windings, psi = turn."""
    _task_inputs("velocity_somersault_chart", cat, FallingCatKinematic, theta0, turn, windings)
    target = host_array([theta0, 2 * np.pi * windings, turn])
    return OCP(cat, host_array([theta0, 0.0, 0.0]), T,
               running_cost=Vibrational(cat), terminal_constraints=TerminalTarget(target))


def velocity_somersault_smooth(cat: FallingCatSmooth, theta0, turn, T, j=0) -> OCP:
    """Smooth problem: x = (w1, w2, phi), x0 = (theta0, 0, 0); at T: w = (theta0, 0) and
    phi = turn + 2 pi j."""
    _task_inputs("velocity_somersault_smooth", cat, FallingCatSmooth, theta0, turn, j, chart=False)
    target = host_array([theta0, 0.0, turn + 2 * np.pi * j])
    return OCP(cat, host_array([theta0, 0.0, 0.0]), T,
               running_cost=Vibrational(cat), terminal_constraints=TerminalTarget(target))


def torque_somersault(cat: FallingCat, theta0, turn, T, windings=1) -> OCP:
    """Rest to rest under torques: x = (theta, chi, psi, theta', chi'); cost int |u|^2."""
    _task_inputs("torque_somersault", cat, FallingCat, theta0, turn, windings)
    target = V.stacked([theta0, 2 * np.pi * windings, turn, 0.0, 0.0])
    return OCP(cat, cat.initial_state(theta0), T, running_cost=Effort(),
               terminal_constraints=TerminalTarget(target))


def fixed_theta_costates(cat: FallingCatKinematic, theta0, T, windings=1):
    """Exact (p(0), nu) of the chart problem whose turn is -2 pi windings f(theta0).

    Along theta = theta0, chi' = c = 2 pi windings / T, stationarity of H = L + p.f in
    u2 and dH/dtheta = 0 (so p_theta stays 0) give
        p_psi = I1 c (lam s^2/D)' / f',   p_chi = f p_psi - 2 I1 (lam s^2/D) c,
    and the costates are constant; nu = p(T) (no terminal cost).
    """
    owner = "fixed_theta_costates"
    _task_inputs(owner, cat, FallingCatKinematic, theta0, 0.0, windings)
    with as_problem_error():
        T = V.duration("T", T, owner=owner)
    p = _fixed_theta_costates(cat, np.asarray(theta0, float), np.asarray(2 * np.pi * windings / T, float))
    return p, p


@compiled(quick=True)
def _fixed_theta_costates(cat, theta0, c):
    """p(0) of ``fixed_theta_costates`` for chi' = c [rad/s] (one program, not an eager
    operation per term)."""
    g = lambda th: cat.lam * jnp.sin(th) ** 2 / cat.D(th)  # noqa: E731
    p_psi = cat.I1 * c * jax.grad(g)(theta0) / cat.curvature(theta0)
    p_chi = cat.f(theta0) * p_psi - 2 * cat.I1 * g(theta0) * c
    return jnp.stack([jnp.zeros(()), p_chi, p_psi])


@compiled(quick=True)
def _fiber_coefficient(cat, theta0):
    """f(theta0), as one program (not an eager operation per term)."""
    return cat.f(theta0)


def loop_guess(param, theta0, T, winding):
    """Parameters of ``param`` (smooth inputs u = w') fitted to a starting loop.

    winding != 0: the fixed-theta loop |w| = theta0 run ``winding`` times (chi
    advances 2 pi winding); winding = 0: a circle of radius theta0/3 through
    w(0) = (theta0, 0) that does not enclose the straight cat (chi returns).
    """
    owner = "loop_guess"
    T = _guess_inputs(owner, param, 2, T)
    with as_problem_error():
        theta0 = V.real("theta0", theta0, owner=owner, shape=(), as_float=True, what="radius of the loop in w [rad]")
        winding = V.real("winding", winding, owner=owner, shape=(), as_float=True, what="turns of the loop")
    # sampled in numpy: in a new process each eager jax operation is a program to lower
    r, c = (theta0, 2 * np.pi * winding / T) if winding else (theta0 / 3, 2 * np.pi / T)
    ts = param.sample_times()
    return fit_samples(param, ts, r * c * np.stack([-np.sin(c * ts), np.cos(c * ts)], axis=1))


def smooth_to_chart(xs):
    """Iwai's (theta, chi, psi) [rad] along a path (N, 3) of (w1, w2, phi): theta = |w|,
    chi = the unwrapped polar angle of w, psi = phi - chi (valid where theta > 0)."""
    xs = jnp.asarray(xs)
    theta = jnp.linalg.norm(xs[:, :2], axis=1)
    chi = jnp.unwrap(jnp.arctan2(xs[:, 1], xs[:, 0]))
    return jnp.stack([theta, chi, xs[:, 2] - chi], axis=1)


@dataclasses.dataclass
class FreeWindingResult:
    """Outcome of ``somersault_free_winding``.

    best: the direct optimum of least cost; ocp: its problem (the class j of the
    fiber target it reached); winding: how often its shape path winds about the
    straight cat (chi's advance / 2 pi); min_theta: the least bend along it [rad];
    starts: one summary per starting loop; indirect: the Pontryagin polish (None if
    not asked), cost_agreement: |J_direct - J_indirect| / J_indirect.
    """

    best: DirectResult
    ocp: OCP
    winding: float
    min_theta: float
    starts: list
    indirect: IndirectResult | None
    cost_agreement: float
    stationarity: float
    seconds: float


def somersault_free_winding(cat: FallingCatSmooth, theta0, turn, T, *, param=None,
                            start_windings=(1, 0, -1, 2), polish=True, rtol=1e-10, atol=1e-10,
                            n_check=201, progress=True, **direct_kw) -> FreeWindingResult:
    """The velocity-controlled somersault with the winding left to the optimizer.

    For every starting loop (``loop_guess`` with each of ``start_windings``) the fiber
    target phi(T) = turn + 2 pi j takes the class j nearest to where that loop ends
    (a loop winding k times ends at 2 pi k (1 - f(theta0))), and ``solve_direct``
    runs from it. The cheapest converged optimum wins; its winding is measured on
    the solved path. With ``polish``, Pontryagin shooting starts from the costates
    that ``pmp_residual`` recovers from the direct optimum, and the two costs are
    compared. Every start solves the same problem structure (only the fiber target and
    the guess differ, both arrays), so the direct method compiles once for all starts.
    start_windings : the starting loops, by whole turns of the twist chi (integers, at
        least one). No start converging raises ``ProblemError`` with each start's
        iterations and violation.
    n_check : saved points of each start's re-simulation, on which the winding and the
        smallest theta are measured (the default, pmp_residual's n_points, lets the
        check of the winner reuse that simulation's compiled program).
    progress : one progress line per start (and one for the polish); False: none.
    """
    t_start = time.perf_counter()
    start_windings = _start_windings(start_windings)
    param = Chebyshev(10, T, 2) if param is None else param
    # every program the task needs is traced first (the problems of all starts share one
    # structure; only the fiber target differs), and each compiled, or loaded from the
    # program cache, in the background while the next is traced: the starting loops'
    # fit, the direct method's, the polish's (the longest compile after the direct
    # method's, so it starts early; with XLA's quick settings, as it runs once from a
    # close start), the check's re-simulation, and last the costate sweep's, the quickest
    # to compile (the last compile is the one the task waits for)
    shape = velocity_somersault_smooth(cat, theta0, turn, T)
    prepare_fit(param)
    if direct_kw.get("optimizer", "auto") in ("auto", "sqp") and direct_kw.get("shooting") in (None, "single"):
        prepare_direct_sqp(shape, param, rtol=rtol, atol=atol)
    if polish:
        prepare_pontryagin(shape, quick=True)
    signal = param.signal(np.zeros(param.size))
    prepare_saved_path(shape, signal, rtol=rtol, atol=atol, n_points=n_check)
    prepare_pmp_residual(shape, signal)
    f0 = float(_fiber_coefficient(cat, np.asarray(theta0, float)))
    starts, best, best_ocp = [], None, None
    problems = {0: shape}  # by fiber class j
    for k in start_windings:
        phi_end = 2 * np.pi * k * (1 - f0) if k else 0.0
        j = int(np.round((phi_end - turn) / (2 * np.pi)))
        if j not in problems:
            problems[j] = velocity_somersault_smooth(cat, theta0, turn, T, j=j)
        ocp = problems[j]
        d = solve_direct(ocp, param, loop_guess(param, theta0, T, k), rtol=rtol, atol=atol,
                         progress=f"start winding {k:+d}" if progress else False, **direct_kw)
        ws = saved_path(ocp, d.control, rtol=rtol, atol=atol, n_points=n_check,
                        owner="somersault_free_winding")[1][:, :2]
        info = dict(start_winding=k, j=j, cost=d.cost, violation=d.violation, converged=d.converged,
                    iterations=d.iterations, winding=float(cat.winding(ws)),
                    min_theta=float(np.min(np.linalg.norm(ws, axis=1))), seconds=d.seconds)
        starts.append(info)
        if d.converged and (best is None or d.cost < best.cost):
            best, best_ocp, best_info = d, ocp, info
    if best is None:
        tried = "; ".join(f"winding {s['start_winding']:+d}: {s['iterations']} iterations, violation "
                          f"{s['violation']:.1e}" for s in starts)
        raise ProblemError(
            f"somersault_free_winding: no start converged ({tried}): try other start_windings, a longer T, "
            f"or more iterations (max_inner=..., solve_direct's)")
    ind, agree, stat = None, float("nan"), float("nan")
    res = pmp_residual(best_ocp, best.control)
    stat = res["stationarity"]
    if polish:
        ind = solve_pontryagin(best_ocp, res["ps"][-1], res["multipliers"], quick=True,
                               progress="Pontryagin polish" if progress else False)
        agree = abs(best.cost - ind.cost) / abs(ind.cost)
    return FreeWindingResult(best=best, ocp=best_ocp, winding=best_info["winding"],
                             min_theta=best_info["min_theta"], starts=starts, indirect=ind,
                             cost_agreement=agree, stationarity=stat,
                             seconds=time.perf_counter() - t_start)


def _start_windings(start_windings):
    """``start_windings`` as a tuple of ints (at least one): each names a starting loop,
    which winds the twist chi that many whole turns."""
    owner = "somersault_free_winding"
    if isinstance(start_windings, (str, bytes)) or not np.iterable(start_windings):
        raise ProblemError(f"{owner}: start_windings must be a sequence of integers (the chi windings of the "
                           f"starting loops, e.g. (1, 0, -1)), got {start_windings!r}")
    with as_problem_error():
        windings = tuple(V.integer(f"start_windings[{i}]", k, owner=owner, what="whole turns of the twist chi")
                         for i, k in enumerate(start_windings))
    if not windings:
        raise ProblemError(f"{owner}: start_windings is empty: name at least one starting loop, e.g. (1, 0, -1)")
    return windings


def torque_loop_guess(cat: FallingCat, param, theta0, T, windings=1):
    """Parameters of ``param`` fitted to the torques (7.14)-(7.15) that hold theta at
    ``theta0`` while chi runs 2 pi ``windings`` times from rest to rest,
    chi'(t) = c (1 - cos(2 pi t / T)), c = 2 pi windings / T: u1 balances the
    centrifugal term, u2 = 2 I1 lam s^2 / D chi''. A rest-to-rest motion that
    turns psi by -2 pi windings f(theta0): a start for the torque somersault."""
    owner = "torque_loop_guess"
    _task_inputs(owner, cat, FallingCat, theta0, 0.0, windings)
    T = _guess_inputs(owner, param, 2, T)
    # sampled in numpy (as loop_guess): eager jax operations would each be a program to
    # lower in a new process
    theta0 = float(theta0)
    s, co = np.sin(theta0), np.cos(theta0)
    D = s * s + float(cat.lam) * co * co  # cat.D(theta0), (6.6), on the host
    I1, lam = float(cat.I1), float(cat.lam)
    c, w = 2 * np.pi * windings / T, 2 * np.pi / T
    ts = param.sample_times()
    chid, chidd = c * (1 - np.cos(w * ts)), c * w * np.sin(w * ts)
    us = np.stack([-2 * I1 * lam**2 * s * co / D**2 * chid**2, 2 * I1 * lam * s**2 / D * chidd], axis=1)
    return fit_samples(param, ts, us)
