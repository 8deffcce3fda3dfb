"""Compile once per problem structure: a second solve with other numbers (initial state,
target, horizon T, cost weight, a system parameter, guess, tolerances) traces nothing
and finds the optimum of the new numbers (minimum-energy double integrator, closed
form); the compiled programs carry no host callbacks (so JAX's persistent cache keeps
them); the progress line ends full when a solve converges and short when it does not."""

import importlib
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import controls
from controls import direct, pontryagin
from controls.problem import TRACES, nan_errors
from nhjax.mechanics import AbstractSystem

# the module (nhjax.integrate re-exports a function of the same name)
nsim = importlib.import_module("nhjax.integrate.simulate")


class ScaledIntegrator(AbstractSystem):
    """q'' = b u (b: a system parameter, an array leaf)."""

    b: jax.Array
    control_dim = 1
    state_names = ("q", "v")

    def vector_field(self, t, x, u):
        return jnp.stack([x[1], self.b * u[0]])


class WeightedEffort(eqx.Module):
    w: jax.Array

    def __call__(self, t, x, u):
        return 0.5 * self.w * u @ u


class Target(eqx.Module):
    x: jax.Array

    def __call__(self, x):
        return x - self.x


def problem(x0, target, T, w, b):
    return controls.OCP(ScaledIntegrator(jnp.asarray(b, float)), jnp.asarray(x0, float), T,
                        running_cost=WeightedEffort(jnp.asarray(w, float)),
                        terminal_constraints=Target(jnp.asarray(target, float)))


def exact_cost(x0, target, T, w, b):
    """min 0.5 w int u^2 s.t. q'' = b u: 0.5 w / b^2 d^T W^-1 d, d = x(T) - e^{AT} x0,
    W the controllability Gramian of the double integrator over [0, T]."""
    q0, v0 = x0
    d = np.asarray(target, float) - np.array([q0 + v0 * T, v0])
    W = np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
    return 0.5 * w / b**2 * d @ np.linalg.solve(W, d)


def counts():
    return dict(TRACES), nsim.TRACES["solve"]


class PartialTarget(eqx.Module):
    """Three constraints: q(T), v(T) and q(T) + v(T) at their targets."""

    x: jax.Array

    def __call__(self, x):
        return jnp.concatenate([x - self.x, (x - self.x).sum(keepdims=True)])


def test_an_ocps_structural_checks_are_kept_beside_the_programs(tmp_path, monkeypatch):
    """An OCP checks that its parts fit (abstract evaluations of the model, costs and
    constraints) and counts its constraints once per structure; the answers are kept
    with the stored programs, so that a new process (here: the memory cleared) neither
    traces the model for them nor gets another structure's answer, and a bad problem
    is still refused."""
    from controls import problem as PR
    from nhjax import _programs

    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    traced = []
    real = jax.eval_shape
    monkeypatch.setattr(jax, "eval_shape", lambda *a, **k: traced.append(1) or real(*a, **k))

    def new_process():  # only the disk remains
        monkeypatch.setattr(PR, "_SHAPES_CHECKED", set())
        monkeypatch.setattr(PR, "_N_CONSTRAINTS", {})
        monkeypatch.setattr(_programs, "_META", {})
        traced.clear()

    new_process()
    ocp = problem([0.0, 0.0], [1.0, 0.0], 1.0, 1.0, 2.0)
    assert ocp.n_constraints == 2 and len(traced) >= 2  # shapes checked, constraints counted
    new_process()
    again = problem([0.3, -1.0], [2.0, 0.5], 2.0, 3.0, 0.5)  # other numbers, same structure
    assert again.n_constraints == 2 and traced == []
    new_process()
    three = controls.OCP(ScaledIntegrator(jnp.asarray(1.0)), jnp.zeros(2), 1.0, running_cost=WeightedEffort(
        jnp.asarray(1.0)), terminal_constraints=PartialTarget(jnp.ones(2)))
    assert three.n_constraints == 3 and traced  # another structure: its own answer
    new_process()
    with pytest.raises(controls.ProblemError, match="x0 does not fit ScaledIntegrator"):
        problem([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], 1.0, 1.0, 2.0)


@pytest.mark.slow  # (stored solver programs: test_a_new_process_loads_the_solvers_programs_instead_of_tracing_them; the LQ optimum: test_controls.py::test_lq_both_methods_reach_the_analytic_optimum; make test-all)
def test_new_numbers_do_not_retrace_and_reach_their_own_optimum():
    first = ((0.0, 0.0), (1.0, 0.0), 1.0, 1.0, 1.0)
    second = ((0.3, -0.5), (1.4, 0.2), 1.7, 2.5, 0.8)  # every number changed, T too
    n = 4
    for k, case in enumerate((first, second)):
        ocp = problem(*case)
        T = case[2]
        param = controls.PiecewiseLinear(n, T, 1)  # the optimal u is linear in t: exact here
        guess = jnp.full(param.size, 0.1 * k)
        before = counts()
        d = controls.solve_direct(ocp, param, guess, rtol=1e-10 * (1 + k), atol=1e-10, progress=False)
        res = controls.pmp_residual(ocp, d.control)  # multipliers fitted: the costate sweep uses T
        ind = controls.solve_pontryagin(ocp, progress=False)
        if k:  # the second solve ran the programs the first one compiled
            assert counts() == before, (before, counts())
        want = exact_cost(*case)
        assert d.converged and d.violation < 1e-8
        np.testing.assert_allclose(d.cost, want, rtol=1e-8)
        assert ind.converged and ind.violation < 1e-9
        np.testing.assert_allclose(ind.cost, want, rtol=1e-10)
        assert res["stationarity"] < 1e-4
        np.testing.assert_allclose(res["multipliers"], ind.nu, rtol=1e-6)


@pytest.mark.slow  # (stored solver programs in a new process: test_a_new_process_loads_the_solvers_programs_instead_of_tracing_them; make test-all)
def test_prepared_solver_programs_are_the_ones_the_solvers_call(tmp_path, monkeypatch):
    """prepare_pontryagin and prepare_pmp_residual trace the programs that
    solve_pontryagin and pmp_residual then call (compiled in the background
    meanwhile): the solvers trace nothing more, and find the closed-form optimum."""
    from nhjax import _programs

    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})

    class Prepared(ScaledIntegrator):  # a structure no other test has compiled
        pass

    case = ((0.1, 0.0), (1.2, -0.3), 1.3, 1.5, 0.9)
    base = problem(*case)
    ocp = controls.OCP(Prepared(base.system.b), base.x0, base.T, running_cost=base.running_cost,
                       terminal_constraints=base.terminal_constraints)
    param = controls.PiecewiseLinear(4, ocp.T, 1)
    before = dict(TRACES)
    assert controls.pontryagin.prepare_pontryagin(ocp)
    assert controls.pontryagin.prepare_pontryagin(ocp, quick=True)
    assert controls.pontryagin.prepare_pmp_residual(ocp, param.signal(np.zeros(param.size)))
    prepared = dict(TRACES)
    for name in ("_indirect", "_indirect_quick", "_costate_sweep"):
        assert prepared.get(name, 0) == before.get(name, 0) + 1, name
    ind = controls.solve_pontryagin(ocp, progress=False)
    quick = controls.solve_pontryagin(ocp, progress=False, quick=True)
    d = controls.solve_direct(ocp, param, jnp.zeros(param.size), progress=False)
    res = controls.pmp_residual(ocp, d.control)
    after = dict(TRACES)
    for name in ("_indirect", "_indirect_quick", "_costate_sweep"):
        assert after[name] == prepared[name], (name, prepared, after)
    want = exact_cost(*case)
    assert ind.converged and quick.converged
    np.testing.assert_allclose(ind.cost, want, rtol=1e-10)
    np.testing.assert_allclose(quick.cost, want, rtol=1e-10)
    assert res["stationarity"] < 1e-4
    np.testing.assert_allclose(res["multipliers"], ind.nu, rtol=1e-6)


@pytest.mark.slow  # (a program with a host callback is not stored: test_a_new_process_loads_the_solvers_programs_instead_of_tracing_them would see it compiled again; make test-all)
def test_compiled_programs_have_no_host_callbacks():
    """The merit/gradient program of solve_direct and the whole Pontryagin solve lower
    without host callbacks (equinox's runtime errors are traced as NaN); the same merit
    with equinox's default error mode does contain one (so the check can fail)."""
    ocp = problem((0.0, 0.0), (1.0, 0.0), 1.0, 1.0, 1.0)
    param = controls.PiecewiseLinear(4, 1.0, 1)
    tr = direct._Transcription(ocp, param, jnp.asarray(1e-10), jnp.asarray(1e-10), 1)
    args = (tr, jnp.zeros(param.size), jnp.zeros(2), jnp.asarray(1.0))
    with nan_errors():
        ours = direct._merit_and_grad.jitted.lower(*args).as_text()
    assert "callback" not in ours
    # control: equinox's default error mode puts host callbacks in the same merit (a
    # system class of its own, so that no trace cached above is reused)
    class Checked(ScaledIntegrator):
        pass

    checked = controls.OCP(
        Checked(jnp.asarray(1.0)), ocp.x0, ocp.T, running_cost=ocp.running_cost,
        terminal_constraints=ocp.terminal_constraints)
    tr_c = direct._Transcription(checked, param, jnp.asarray(1e-10), jnp.asarray(1e-10), 1)
    with_checks = eqx.filter_jit(lambda tr, z, lam, rho: jax.value_and_grad(tr.merit, has_aux=True)(z, lam, rho))
    assert "callback" in with_checks.lower(tr_c, *args[1:]).as_text()

    ham = pontryagin.HamiltonianSystem(ocp)
    sh = pontryagin._Shooting(ham, jnp.asarray(1e-11), jnp.asarray(1e-11), 1)
    with nan_errors():
        text = pontryagin._indirect.jitted.lower(sh, jnp.zeros(4), jnp.asarray(1e-10),
                                                 jnp.asarray(100), False).as_text()
    assert "callback" not in text


def test_the_hamiltonian_flow_compiles_without_lapack_as_one_function():
    """u* solves H_uu du = -H_u at every vector-field evaluation of the extremal. With
    LAPACK's solve there, XLA could not compile the extremal's time-stepping loop as one
    function; nhjax._linalg.solve keeps LAPACK out (the torque-free double integrator's
    flow is linear: its x(T) is checked against the matrix exponential)."""
    import nhjax

    ocp = problem((0.0, 0.0), (1.0, 0.0), 1.0, 1.0, 1.0)
    ham = pontryagin.HamiltonianSystem(ocp)
    y0 = jnp.array([0.1, -0.2, 0.6, 0.3])  # (q, v, p_q, p_v)
    run = jax.jit(lambda y: nhjax.simulate(ham, y, 1.0, saveat=11, rtol=1e-12, atol=1e-12, diagnostics=False).xs)
    text = run.lower(y0).compile().as_text()
    assert "custom_call_target=\"lapack" not in text
    assert "xla_cpu_small_call" in text
    # u* = -p_v (w = b = 1): q' = v, v' = -p_v, p_q' = 0, p_v' = -p_q
    A = np.array([[0, 1, 0, 0], [0, 0, 0, -1], [0, 0, 0, 0], [0, 0, -1, 0]], float)
    np.testing.assert_allclose(run(y0)[-1], jax.scipy.linalg.expm(jnp.asarray(A)) @ y0, rtol=0, atol=1e-10)


@pytest.mark.parametrize("optimizer", ["sqp", pytest.param("lbfgs", marks=pytest.mark.slow)])
def test_progress_line_ends_full_when_converged(capsys, optimizer):
    ocp = problem((0.0, 0.0), (1.0, 0.0), 1.0, 1.0, 1.0)
    param = controls.PiecewiseLinear(4, 1.0, 1)
    d = controls.solve_direct(ocp, param, progress=True, optimizer=optimizer)
    err = capsys.readouterr().err
    last = err.replace("\r", "\n").strip().splitlines()[-1]
    assert d.converged and "100%" in last and "violation" in last, last
    done = d.history["outer"][-1] if optimizer == "lbfgs" else len(d.history["cost"])
    assert f"{done}/{done}" in last  # the bar was shortened to the iterations used
    # stops early (one outer iteration; or a violation tolerance no solve meets): a short bar
    early = dict(max_outer=1) if optimizer == "lbfgs" else dict(max_inner=2, ctol=1e-300)
    d = controls.solve_direct(ocp, param, progress=True, optimizer=optimizer, **early)
    last = capsys.readouterr().err.replace("\r", "\n").strip().splitlines()[-1]
    assert not d.converged and "not converged" in last, last
    controls.solve_direct(ocp, param, progress=False, optimizer=optimizer)
    assert capsys.readouterr().err == ""


def test_progress_line_says_it_is_starting_and_stays_off_in_dask_workers(monkeypatch):
    """Before the first iteration (while the solver's programs compile) the line says so,
    and the word goes with the first report, or at the end if nothing was reported. In a
    Dask worker the default line is off (every worker's bar would print on the client);
    an explicit label still shows."""
    import types

    from controls.problem import Progress

    bar = Progress(True, 3, "t")
    assert "compiles" in bar.bar.postfix
    bar.update(cost=1.0)
    assert "compiles" not in bar.bar.postfix and "cost" in bar.bar.postfix
    bar.finish(True)
    quiet = Progress(True, 1, "t")
    quiet.finish(True)
    assert not quiet.bar.postfix

    def no_worker():
        raise ValueError("No worker found")

    monkeypatch.setitem(sys.modules, "distributed", types.SimpleNamespace(get_worker=no_worker))
    assert Progress(True, 1, "t").bar is not None  # distributed imported, but not in a worker
    monkeypatch.setitem(sys.modules, "distributed", types.SimpleNamespace(get_worker=lambda: object()))
    assert Progress(True, 1, "t").bar is None
    assert Progress("labelled", 1, "t").bar is not None


_CHILD = """
import json, sys
import jax.numpy as jnp, numpy as np
sys.path.insert(0, {tests!r})
import controls
from controls.problem import TRACES
from nhjax import _programs
from test_controls import DoubleIntegrator, HalfSquare, Target

ocp = controls.OCP(DoubleIntegrator(), jnp.zeros(2), 1.0, running_cost=HalfSquare(),
                   terminal_constraints=Target(jnp.array([1.0, 0.0])))
param = controls.PiecewiseLinear(4, 1.0, 1)
d = controls.solve_direct(ocp, param, param.fit(lambda t: jnp.array([1.0 - 2.0 * t])), progress=False)
ind = controls.solve_pontryagin(ocp, progress=False)
print(json.dumps(dict(direct=[d.cost, d.violation, np.asarray(d.params).tolist()],
                      indirect=[ind.cost, ind.violation, np.asarray(ind.p0).tolist(),
                                np.asarray(ind.trajectory.xs).tolist()],
                      status=str(ind.trajectory.result), traces=sum(TRACES.values()), stats=_programs.STATS)))
"""


def test_a_new_process_loads_the_solvers_programs_instead_of_tracing_them(tmp_path):
    """solve_direct and solve_pontryagin in two fresh processes on one cache directory:
    the second traces none of controls' programs (it loads their executables, among
    them the Pontryagin solve, whose outputs hold equinox enumerations) and gives the
    first one's optimum bit for bit; both reach the closed-form optimum."""
    import json
    import os
    import subprocess
    import sys

    env = dict(os.environ, NHJAX_CACHE_DIR=str(tmp_path), JAX_PLATFORMS="cpu")

    def run():
        child = _CHILD.format(tests=os.path.dirname(os.path.abspath(__file__)))
        out = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, env=env, check=True)
        return json.loads(out.stdout.strip().splitlines()[-1])

    first, second = run(), run()
    want = exact_cost((0.0, 0.0), (1.0, 0.0), 1.0, 1.0, 1.0)
    np.testing.assert_allclose(first["direct"][0], want, rtol=1e-8)
    np.testing.assert_allclose(first["indirect"][0], want, rtol=1e-10)
    assert first["traces"] >= 4  # merit and gradient, direction, fit, Pontryagin solve, ...
    assert second["traces"] == 0, second
    assert second["stats"]["executables"] >= 4 and second["stats"]["stored"] == 0
    assert second["direct"] == first["direct"] and second["indirect"] == first["indirect"]
    assert second["status"] == first["status"]


def test_error_modes_are_per_thread_and_part_of_the_trace():
    """equinox's error mode is nhjax's per thread (``nhjax._programs.errors``, which
    ``nan_errors`` is): two threads whose contexts overlap (as the solvers of a
    threads-only Dask cluster's workers do) call one jitted ``eqx.error_if`` on a bad
    input in turn, while both contexts are open, and each gets its own mode's program:
    NaN in "nan", the input in "off". The main thread's call after theirs, still while
    they are open, raises: neither program is reused outside its mode, neither from
    JAX's trace caches nor from its jit dispatch cache (which answered it with the "nan"
    program before the mode was part of the jit key). Nested contexts come back to the
    outer one, and equinox's own global setting was never changed."""
    import threading

    from equinox import _errors

    from controls.problem import nan_errors
    from nhjax import _programs

    before = _errors.EQX_ON_ERROR
    checked = jax.jit(lambda x: eqx.error_if(x, x < 0, "negative input"))
    both_in, done = threading.Barrier(3, timeout=20), threading.Barrier(3, timeout=20)
    turns = {"nan": threading.Event(), "off": threading.Event(), "main": threading.Event()}
    seen = {}

    def run(mode, after):
        with nan_errors(mode):
            both_in.wait()  # the other thread's context is open too
            turns[mode].wait(20)
            seen[mode] = (_programs.error_mode(), float(checked(jnp.asarray(-1.0))))
            turns[after].set()
            done.wait()

    threads = [threading.Thread(target=run, args=("nan", "off")), threading.Thread(target=run, args=("off", "main"))]
    for t in threads:
        t.start()
    try:
        both_in.wait()
        turns["nan"].set()  # "nan" calls first, then "off", then this thread
        assert turns["main"].wait(20)
        with pytest.raises(Exception, match="negative input"):  # as configured, the others' programs cached
            checked(jnp.asarray(-1.0)).block_until_ready()
    finally:
        done.wait()
        for t in threads:
            t.join(20)
    assert seen["off"] == ("off", -1.0)
    assert seen["nan"][0] == "nan" and np.isnan(seen["nan"][1])
    with pytest.raises(Exception, match="negative input"):
        checked(jnp.asarray(-1.0)).block_until_ready()
    with nan_errors("off"):
        with nan_errors("nan"):
            assert _programs.error_mode() == "nan"
        assert _programs.error_mode() == "off"
    assert _programs.error_mode() == before == _errors.EQX_ON_ERROR
