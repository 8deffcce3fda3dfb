"""nhjax's program cache (nhjax/_programs.py): traced programs kept on disk under a
fingerprint of everything the trace depended on. What could go wrong is a stale
program: these tests change what a trace depends on (a user's code, a global it
reads, a static number, an array baked into the trace) and check that the key moves,
and that what the key ignores (values of the program's inputs) gives the same
results as tracing afresh."""

import json
import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax import _programs
from nhjax.scenes import FallingCat


def _user_function(source: str, name: str, **globals_):
    namespace = {"jnp": jnp, **globals_}
    exec(textwrap.dedent(source), namespace)  # a function as a notebook cell defines it
    return namespace[name]


def test_key_moves_with_code_globals_and_baked_values_not_with_inputs():
    x = jnp.ones(3)
    f = _user_function("def f(x):\n    return x * 2.0\n", "f")
    same = _user_function("def f(x):\n    return x * 2.0\n", "f")
    edited = _user_function("def f(x):\n    return x * 3.0\n", "f")
    key = _programs.fingerprint(f, (x,))
    assert _programs.fingerprint(same, (x,)) == key  # same code, another object: same program
    assert _programs.fingerprint(edited, (x,)) != key  # the edited cell
    assert _programs.fingerprint(f, (2 * x,)) == key  # input values are not in the trace
    assert _programs.fingerprint(f, (jnp.ones(4),)) != key  # shapes are

    g1 = _user_function("def g(x):\n    return x * SCALE\n", "g", SCALE=2.0)
    g2 = _user_function("def g(x):\n    return x * SCALE\n", "g", SCALE=2.5)
    assert _programs.fingerprint(g1, (x,)) != _programs.fingerprint(g2, (x,))  # a global it reads

    h1 = _user_function("def h(x):\n    return M @ x\n", "h", M=np.eye(3))
    h2 = _user_function("def h(x):\n    return M @ x\n", "h", M=2 * np.eye(3))
    assert _programs.fingerprint(h1, (x,)) != _programs.fingerprint(h2, (x,))  # an array baked in

    helper1 = _user_function("def helper(x):\n    return x + 1.0\n", "helper")
    helper2 = _user_function("def helper(x):\n    return x - 1.0\n", "helper")
    k1 = _user_function("def k(x):\n    return helper(x)\n", "k", helper=helper1)
    k2 = _user_function("def k(x):\n    return helper(x)\n", "k", helper=helper2)
    assert _programs.fingerprint(k1, (x,)) != _programs.fingerprint(k2, (x,))  # a function it calls

    # a module's parameters as arrays are inputs; its Python numbers are static (baked in)
    assert _programs.fingerprint(FallingCat(lam=0.4)) == _programs.fingerprint(FallingCat(lam=0.5))
    assert _programs.fingerprint(FallingCat(chart_eps=1e-3)) != _programs.fingerprint(FallingCat(chart_eps=2e-3))
    # arrays as module fields are inputs of the program
    s1 = nhjax.Sinusoids(jnp.zeros(2), jnp.ones(2), jnp.ones(2), jnp.zeros(2))
    s2 = nhjax.Sinusoids(jnp.zeros(2), 2 * jnp.ones(2), jnp.ones(2), jnp.zeros(2))
    assert _programs.fingerprint(s1) == _programs.fingerprint(s2)


def test_objects_it_cannot_read_are_traced_as_usual():
    class Opaque:  # no dataclass, no module of a library: the fingerprint cannot vouch for it
        def __init__(self):
            self.scale = 2.0

    obj = Opaque()
    fn = _user_function("def f(x):\n    return x * OBJ.scale\n", "f", OBJ=obj)
    with pytest.raises(_programs.Uncacheable):
        _programs.fingerprint(fn, (jnp.ones(2),))
    before = _programs.STATS["uncacheable"]
    out = _programs.call("test-opaque", fn, (jnp.ones(2),))
    assert _programs.STATS["uncacheable"] == before + 1
    np.testing.assert_array_equal(out, 2.0 * np.ones(2))


def test_cached_call_equals_plain_jit(tmp_path, monkeypatch):
    """A program exported, stored, loaded back and called gives bit-identical results
    to eqx.filter_jit on the same function, for new input values too."""
    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    fn = _user_function(
        "def f(p, x):\n    return {'y': jnp.sin(p.amplitude) * x, 'n': jnp.sum(x ** 2)}\n", "f")
    p = nhjax.Sinusoids(jnp.zeros(2), jnp.array([0.3, 0.2]), jnp.ones(2), jnp.zeros(2))
    x = jnp.array([1.0, -2.0])
    stored = _programs.STATS["stored"]
    out = _programs.call("test-roundtrip", fn, (p, x))
    assert _programs.STATS["stored"] == stored + 1 and len(list(tmp_path.glob("*.prog"))) == 1
    monkeypatch.setattr(_programs, "_MEMORY", {})  # as a new process: only the disk remains
    loaded = _programs.STATS["loaded"]
    x2 = jnp.array([0.5, 4.0])
    again = _programs.call("test-roundtrip", fn, (p, x2))
    assert _programs.STATS["loaded"] == loaded + 1
    ref = eqx.filter_jit(fn)(p, x2)
    np.testing.assert_array_equal(again["y"], ref["y"])
    np.testing.assert_array_equal(again["n"], ref["n"])
    np.testing.assert_array_equal(out["y"], eqx.filter_jit(fn)(p, x)["y"])


def test_a_damaged_executable_is_compiled_again(tmp_path, monkeypatch):
    """A stored executable that does not load (damaged, or from another jaxlib) is
    ignored: the program is compiled again from its stored trace, with the same results."""
    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    fn = _user_function("def g(x):\n    return {'y': jnp.cos(x) * x}\n", "g")
    x = jnp.array([0.25, -1.5, 3.0])
    first = _programs.call("test-exe", fn, (x,))
    exes = list(tmp_path.glob("*.exe"))
    assert len(exes) == 1
    monkeypatch.setattr(_programs, "_MEMORY", {})
    n_exe = _programs.STATS["executables"]
    again = _programs.call("test-exe", fn, (x,))  # the stored executable, loaded
    assert _programs.STATS["executables"] == n_exe + 1
    np.testing.assert_array_equal(again["y"], first["y"])
    exes[0].write_bytes(b"not an executable")
    monkeypatch.setattr(_programs, "_MEMORY", {})
    loaded = _programs.STATS["loaded"]
    third = _programs.call("test-exe", fn, (x,))
    assert _programs.STATS["executables"] == n_exe + 1 and _programs.STATS["loaded"] == loaded + 1  # the .prog
    np.testing.assert_array_equal(third["y"], first["y"])


def test_programs_with_batched_lapack_calls_run_one_at_a_time(tmp_path, monkeypatch):
    """A program that calls LAPACK on a batch of matrices (a vmapped solve) is detected
    in its compiled HLO, the flag is kept with its stored executable, and the program
    runs under nhjax's lock (compiled or loaded back): jaxlib 0.10's batched kernels
    block a thread of XLA's pool, and two such programs at once could hold every pool
    thread. A single solve or plain arithmetic is not flagged and runs without the lock.
    The results are plain jit's, bit for bit."""
    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    rng = np.random.default_rng(0)
    A, b = jnp.asarray(rng.standard_normal((3, 4, 4)) + 4 * np.eye(4)), jnp.asarray(rng.standard_normal((3, 4)))
    batched = _user_function("def f(A, b):\n    return {'x': jax.vmap(jnp.linalg.solve)(A, b)}\n", "f", jax=jax)
    single = _user_function("def g(A, b):\n    return {'x': jnp.linalg.solve(A[0], b[0])}\n", "g")
    plain = _user_function("def h(A, b):\n    return {'x': jnp.sin(A).sum(0) @ b[0]}\n", "h")
    assert _programs.batched_lapack(jax.jit(batched).lower(A, b).compile())
    assert not _programs.batched_lapack(jax.jit(single).lower(A, b).compile())
    assert not _programs.batched_lapack(jax.jit(plain).lower(A, b).compile())
    held = []

    class Spy:  # the lock, recording whether it was taken
        def __enter__(self):
            held.append(True)

        def __exit__(self, *exc):
            return False

    monkeypatch.setattr(_programs, "_BATCHED_LAPACK", Spy())
    for name, fn, locked in (("b", batched, True), ("s", single, False), ("p", plain, False)):
        for fresh in (True, False):  # compiled here, then loaded back from disk
            if not fresh:
                monkeypatch.setattr(_programs, "_MEMORY", {})
            held.clear()
            out = _programs.call(f"test-lapack-{name}", fn, (A, b))
            assert held == ([True] if locked else []), (name, fresh)
            np.testing.assert_array_equal(out["x"], jax.jit(fn)(A, b)["x"])
    heads = [_programs._unpack(_programs._read(p))[0] for p in sorted(tmp_path.glob("*.exe"))]
    assert sorted(h["batched_lapack"] for h in heads) == [False, False, True]


_CHILD = """
import json, sys, importlib
import numpy as np, jax, nhjax
from nhjax import _programs
from nhjax.scenes import FallingCat
sim = importlib.import_module("nhjax.integrate.simulate")
cat = FallingCat(lam=0.4)
ctrl = nhjax.Sinusoids([0.0, 0.0], [0.3, 0.2], [2.0, 3.0], [0.0, np.pi / 2])
tr = nhjax.simulate(cat, cat.initial_state(0.9, chi_dot=0.3), 3.0, control=ctrl)
X = np.stack([np.asarray(cat.initial_state(th, chi_dot=0.3)) for th in np.linspace(0.7, 1.1, 6)])
bt = nhjax.simulate_batch(cat, X, 3.0, control=ctrl, saveat=2)
batch = importlib.import_module("nhjax.integrate._local_batch")
print(json.dumps(dict(xs=np.asarray(tr.xs).tolist(), drift={k: float(v) for k, v in tr.invariant_drift.items()},
                      batch=np.asarray(bt.x_final).tolist(), steps=np.asarray(bt.num_accepted_steps).tolist(),
                      traces=sim.TRACES["solve"], batch_traces=batch.TRACES["lockstep"], stats=_programs.STATS)))
"""


def _run_child(tmp_path):
    env = dict(os.environ, NHJAX_CACHE_DIR=str(tmp_path), JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_a_new_process_loads_the_solve_instead_of_tracing_it(tmp_path):
    """Two fresh processes share a cache directory: the second traces no solve and no
    batch chunk, loads their programs, and returns the first one's trajectory,
    diagnostics and batch members bit for bit."""
    first, second = _run_child(tmp_path), _run_child(tmp_path)
    assert first["traces"] == 1 and first["batch_traces"] == 1
    assert first["stats"]["stored"] >= 4  # report, solve, diagnostics, batch chunk
    assert second["traces"] == 0 and second["batch_traces"] == 0
    assert second["stats"]["loaded"] >= 4 and second["stats"]["stored"] == 0
    assert second["stats"]["executables"] >= 4  # compiled code loaded as it is: no lowering, no compile
    assert second["xs"] == first["xs"] and second["drift"] == first["drift"]
    assert second["batch"] == first["batch"] and second["steps"] == first["steps"]
    assert len(set(first["steps"])) > 1  # members of different lengths


_LAPACK_CHILD = """
import json, sys
import numpy as np, nhjax
from nhjax import _programs
from nhjax.scenes import BouncingBall
ball = BouncingBall()
tr = nhjax.simulate_impacts(ball, ball.initial_state(0.1), 1.0)
imported = "scipy.linalg" in sys.modules
import scipy.linalg.cython_lapack as lapack_module  # afterwards, imported the usual way
import scipy.linalg
print(json.dumps(dict(xs=np.asarray(tr.xs).tolist(), times=np.asarray(tr.impact_times).tolist(),
                      scipy_linalg=imported, attribute=scipy.linalg.cython_lapack is lapack_module,
                      stats=_programs.STATS)))
"""


@pytest.mark.slow  # (a warm start's import cost, in new processes; stored solves: test_a_new_process_loads_the_solve_instead_of_tracing_it; make test-all)
def test_a_loaded_program_that_calls_lapack_runs_without_importing_scipy_linalg(tmp_path):
    """The impact solve's program calls LAPACK (its projections solve linear systems).
    A second process loads it and initializes jaxlib's LAPACK kernels from SciPy's
    cython_blas / cython_lapack modules alone (_programs._preload_scipy_lapack), not
    through the scipy.linalg package: it gives the first process's results bit for bit
    and has not imported scipy.linalg; an import of SciPy's module afterwards is the
    usual one."""
    env = dict(os.environ, NHJAX_CACHE_DIR=str(tmp_path), JAX_PLATFORMS="cpu")
    runs = [json.loads(subprocess.run([sys.executable, "-c", _LAPACK_CHILD], capture_output=True, text=True,
                                      env=env, check=True).stdout.strip().splitlines()[-1]) for _ in range(2)]
    first, second = runs
    assert second["stats"]["executables"] >= 1 and second["stats"]["stored"] == 0
    assert not second["scipy_linalg"] and second["attribute"]
    assert second["xs"] == first["xs"] and second["times"] == first["times"] and len(first["times"]) >= 2


@pytest.mark.slow
def test_a_new_process_compiles_again_what_lost_its_executable(tmp_path):
    """Executables gone (an older cache, or evicted) while the traces stay: the next
    process compiles each program again (JAX's cache off: an executable from there, or
    compiled after one in the same process, would load broken) and stores it, and the
    one after loads them; both give the first process's results bit for bit."""
    first = _run_child(tmp_path)
    exes = sorted(p.name for p in (tmp_path / "nhjax-programs").glob("*.exe"))
    assert exes
    for exe in exes:
        (tmp_path / "nhjax-programs" / exe).unlink()
    third, fourth = _run_child(tmp_path), _run_child(tmp_path)
    for later in (third, fourth):
        assert later["traces"] == 0 and later["xs"] == first["xs"] and later["batch"] == first["batch"]
        assert later["steps"] == first["steps"] and later["drift"] == first["drift"]
    assert sorted(p.name for p in (tmp_path / "nhjax-programs").glob("*.exe")) == exes
    assert third["stats"]["executables"] == 0 and fourth["stats"]["executables"] >= 4


def test_tracing_pauses_the_cycle_collector_and_restores_it(tmp_path, monkeypatch):
    """The collector is off while a program is traced and back as it was afterwards (on,
    or off if the user had turned it off)."""
    import gc

    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    seen = []
    fn = _user_function("def h(x):\n    seen.append(gc.isenabled())\n    return {'y': 2 * x}\n", "h",
                        seen=seen, gc=gc)
    was = gc.isenabled()
    try:
        for state in (True, False):
            (gc.enable if state else gc.disable)()
            seen.clear()
            monkeypatch.setattr(_programs, "_MEMORY", {})
            _programs.call(f"test-gc-{state}", fn, (jnp.arange(3.0) + state,))
            assert seen and not any(seen)  # traced with the collector off
            assert gc.isenabled() is state
    finally:
        (gc.enable if was else gc.disable)()


def test_the_key_covers_the_source_of_controls_too(tmp_path, monkeypatch):
    """controls' functions are fingerprinted by name, so its source must be in the key:
    an edit there (a solver's program changed) gives new keys."""
    from pathlib import Path

    import controls

    assert Path(controls.__file__).resolve().parent in _programs._source_roots()
    pkg = tmp_path / "controls"
    pkg.mkdir()
    (pkg / "solver.py").write_text("def step(x):\n    return x\n")
    monkeypatch.setattr(_programs, "_source_roots", lambda: [pkg])
    try:
        _programs._environment.cache_clear()
        before = _programs._environment()
        (pkg / "solver.py").write_text("def step(x):\n    return 2 * x\n")
        _programs._environment.cache_clear()
        assert _programs._environment() != before
    finally:
        monkeypatch.undo()
        _programs._environment.cache_clear()


def test_prepare_traces_now_compiles_in_the_background_and_the_call_uses_it(tmp_path, monkeypatch):
    """prepare() exports the program in the calling thread and compiles it in a worker
    thread; the later call waits for that compile instead of tracing again, with results
    equal to plain jit. A prepared compile that fails is compiled again by the call."""
    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    fn = _user_function("def h(x, y):\n    return {'z': jnp.tanh(x) @ y}\n", "h")
    x, y = jnp.linspace(-1.0, 2.0, 6).reshape(2, 3), jnp.array([0.5, -1.0, 2.0])
    stored = _programs.STATS["stored"]
    assert _programs.prepare("test-prepare", fn, (x, y))
    assert _programs.STATS["stored"] == stored + 1  # exported (traced) here, once
    assert not _programs.prepare("test-prepare", fn, (x + 1.0, y))  # same structure: nothing new
    pending = [v for v in _programs._MEMORY.values() if hasattr(v, "result")]
    assert pending, "the compile runs in the background"
    x2 = x * 3.0
    out = _programs.call("test-prepare", fn, (x2, y))
    assert _programs.STATS["stored"] == stored + 1  # the call did not trace it again
    np.testing.assert_array_equal(out["z"], eqx.filter_jit(fn)(x2, y)["z"])

    # a new process (nothing in memory): the executable on disk is loaded in the
    # background, the call uses it and nothing is traced or compiled again
    monkeypatch.setattr(_programs, "_MEMORY", {})
    loaded, compiled_before = _programs.STATS["loaded"], _programs.STATS["compiled"]
    assert _programs.prepare("test-prepare", fn, (x, y))
    again = _programs.call("test-prepare", fn, (x2, y))
    assert _programs.STATS["loaded"] == loaded + 1
    assert (_programs.STATS["stored"], _programs.STATS["compiled"]) == (stored + 1, compiled_before)
    np.testing.assert_array_equal(again["z"], out["z"])
    # a damaged executable: the background load fails and the call compiles it anew
    monkeypatch.setattr(_programs, "_MEMORY", {})
    for exe in tmp_path.glob("test-prepare-*.exe"):
        exe.write_bytes(b"not an executable")
    assert _programs.prepare("test-prepare", fn, (x, y))
    again = _programs.call("test-prepare", fn, (x2, y))
    assert _programs.STATS["compiled"] == compiled_before + 1
    np.testing.assert_array_equal(again["z"], out["z"])

    # a background compile that fails: the call compiles the program itself
    monkeypatch.setattr(_programs, "_MEMORY", {})
    real_compile = _programs._compile

    def broken(*a, **k):
        raise RuntimeError("compile failed in the background")

    monkeypatch.setattr(_programs, "_compile", broken)
    fn2 = _user_function("def k(x):\n    return {'z': jnp.exp(x) - x}\n", "k")
    assert _programs.prepare("test-prepare-fail", fn2, (y,))
    monkeypatch.setattr(_programs, "_compile", real_compile)
    again = _programs.call("test-prepare-fail", fn2, (y,))
    np.testing.assert_array_equal(again["z"], eqx.filter_jit(fn2)(y)["z"])


def test_prepare_later_traces_in_a_thread_and_ready_says_when_a_call_would_not_wait(tmp_path, monkeypatch):
    """prepare(trace=False) takes only a stored program (nothing is traced); prepare_later()
    traces the program in a thread of its own, then compiles it in the background:
    meanwhile ``ready`` is false, prepare() and prepare_later() start nothing new, and a
    call waits for that thread instead of tracing again, with results equal to plain
    jit. In a new process prepare(trace=False) loads the stored executable, and the
    program is ready without a trace or a compile."""
    import threading

    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    monkeypatch.setattr(_programs, "_LATER", {})
    fn = _user_function("def g(x, y):\n    return {'z': jnp.cos(x) @ y + jnp.sum(x)}\n", "g")
    x, y = jnp.linspace(-1.0, 2.0, 6).reshape(2, 3), jnp.array([0.5, -1.0, 2.0])
    gate, traced_in = threading.Event(), []
    real_export = _programs._export

    def gated_export(*a, **k):  # the trace, held until the test lets it go on
        traced_in.append(threading.current_thread().name)
        assert gate.wait(60)
        return real_export(*a, **k)

    monkeypatch.setattr(_programs, "_export", gated_export)
    stored = _programs.STATS["stored"]
    assert not _programs.prepare("test-later", fn, (x, y), trace=False)  # nothing stored: nothing done
    assert not traced_in and not _programs.ready("test-later", fn, (x, y))
    assert _programs.prepare_later("test-later", fn, (x, y))
    assert not _programs.ready("test-later", fn, (x, y))
    assert not _programs.prepare_later("test-later", fn, (x + 1.0, y))  # under way already
    assert not _programs.prepare("test-later", fn, (x, y))  # not traced a second time here
    out = {}
    caller = threading.Thread(target=lambda: out.update(z=_programs.call("test-later", fn, (2.0 * x, y))["z"]))
    caller.start()
    caller.join(0.5)
    assert caller.is_alive() and not _programs.ready("test-later", fn, (x, y))  # the call waits
    gate.set()
    caller.join(120)
    assert not caller.is_alive() and _programs.ready("test-later", fn, (x, y))
    assert len(traced_in) == 1 and traced_in[0].startswith("nhjax-trace")
    assert _programs.STATS["stored"] == stored + 1
    np.testing.assert_array_equal(out["z"], eqx.filter_jit(fn)(2.0 * x, y)["z"])

    # a new process: the stored executable is loaded, nothing traced or compiled
    monkeypatch.setattr(_programs, "_MEMORY", {})
    monkeypatch.setattr(_programs, "_LATER", {})
    compiled = _programs.STATS["compiled"]
    assert not _programs.ready("test-later", fn, (x, y))
    assert _programs.prepare("test-later", fn, (x, y), trace=False)
    assert _programs.ready("test-later", fn, (x, y))  # (a load does not make a call wait long)
    _programs.settle()  # the background load, waited for
    assert all(f.done() for f in _programs._MEMORY.values() if hasattr(f, "done"))
    again = _programs.call("test-later", fn, (2.0 * x, y))
    assert len(traced_in) == 1 and _programs.STATS["compiled"] == compiled
    np.testing.assert_array_equal(again["z"], out["z"])
    assert not _programs.prepare_later("test-later", fn, (x, y))  # in memory: nothing to do
    assert not _programs._LATER


def test_quick_options_are_a_program_of_their_own_and_prepare_passes_them_on(tmp_path, monkeypatch):
    """A program compiled with QUICK_OPTIONS (how the input checks and diagnostics of an
    eager simulate() are compiled) is kept beside, not instead of, its default compile:
    prepare() with the options is what the call with them uses (one compile between
    them), a call without them compiles the default one, and both agree with plain jit
    to rounding (the options may change the arithmetic's order, so not bit for bit)."""
    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    fn = _user_function("def q(x, y):\n    return {'z': jnp.sin(x) @ jnp.exp(y) / (1.0 + jnp.sum(x * x))}\n", "q")
    x, y = jnp.linspace(-1.0, 2.0, 12).reshape(4, 3), jnp.array([0.5, -1.0, 2.0])
    compiled = _programs.STATS["compiled"]
    assert _programs.prepare("test-quick", fn, (x, y), compiler_options=_programs.QUICK_OPTIONS)
    quick = _programs.call("test-quick", fn, (x, y), compiler_options=_programs.QUICK_OPTIONS)
    assert _programs.STATS["compiled"] == compiled + 1
    plain = _programs.call("test-quick", fn, (x, y))
    assert _programs.STATS["compiled"] == compiled + 2
    assert len(list(tmp_path.glob("test-quick-*.exe"))) == 2  # two executables, one trace
    ref = eqx.filter_jit(fn)(x, y)["z"]
    np.testing.assert_array_equal(plain["z"], ref)
    np.testing.assert_allclose(quick["z"], ref, rtol=1e-14, atol=1e-15)


@pytest.mark.slow  # (stored solves in a new process: test_a_new_process_loads_the_solve_instead_of_tracing_it; make test-all)
def test_scene_states_from_numbers_are_one_cached_program_and_the_traced_ones_agree(tmp_path, monkeypatch):
    """Scene helpers that build a state from numbers (small_call): with concrete numbers
    one program, stored in the cache and loaded back by a new process without a trace;
    traced numbers (vmap) take the plain operations; the states agree to rounding."""
    import jax

    from nhjax.scenes import (
        BallInCone,
        BallOnPlatter,
        FallingCat,
        RollingDisk,
        ShellWithSuslovHinge,
        ShellWithTop,
        ShellWithTopReduced,
        SuslovBundle,
        ThreeCylinders,
    )

    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    cone, platter, disk, cyl = BallInCone(), BallOnPlatter(), RollingDisk(), ThreeCylinders()
    cat = FallingCat().attitude_model()
    robot, reduced, hinge, bundle = ShellWithTop(), ShellWithTopReduced(), ShellWithSuslovHinge(), SuslovBundle()

    def flat(out):  # a state, or a tuple of state parts (the cat's attitudes)
        return np.concatenate([np.ravel(np.asarray(a)) for a in jax.tree_util.tree_leaves(out)])
    q = [0.9, 0.1, -0.2, 0.3]
    cases = [  # (eager helper, the same under vmap over one number, values of that number)
        (lambda r: cone.initial_state(r, 0.3, -0.2, 0.4, 0.7, attitude=q), [2.5, 3.0]),
        (lambda u: platter.initial_state(u, 0.2, 0.1, -0.3, 2.0, attitude=q), [0.5, -1.0]),
        (lambda s: disk.to_quaternion_state(disk.initial_state(theta=0.3, phi_dot=0.4, psi_dot=s)), [1.5, -0.7]),
        (lambda th: cyl.initial_state(theta=th, phi_dot=1.2), [2.0, 0.4]),
        (lambda c: cat.initial_state(0.8, chi=c, psi=0.3, chi_dot=0.5), [0.2, -1.0]),
        (lambda w: robot.initial_state(shell_omega=(0.1, -0.2, 0.3), top_omega=jnp.stack([0.0, w, 3.0]),
                                       top_attitude=np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])),
         [3.0, -1.0]),
        (lambda w: reduced.initial_state(jnp.stack([1.0, w, 3.0]), attitude=[0.1, -0.2, 0.3], shell_velocity=(0.2, 0.1),
                                         shell_spin=0.4), [2.0, -0.5]),
        (lambda w: hinge.initial_state_zero_momentum(jnp.stack([w, 0.2]), attitude=[0.3, 0.1, -0.2]), [0.3, 1.1]),
        (lambda w: bundle.initial_state(jnp.stack([0.3, w, 1.0]), Omega12=(0.1, -0.2),
                                        attitude=np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])),
         [0.2, -0.4]),
    ]
    stored = _programs.STATS["stored"]
    eager = [np.stack([flat(f(v)) for v in vals]) for f, vals in cases]
    assert _programs.STATS["stored"] == stored + len(cases)  # one program per helper, for both values
    monkeypatch.setattr(_programs, "_MEMORY", {})  # as a new process: only the disk remains
    loaded = _programs.STATS["loaded"]
    again = [np.stack([flat(f(v)) for v in vals]) for f, vals in cases]
    assert _programs.STATS["loaded"] == loaded + len(cases)
    for (f, vals), e, a in zip(cases, eager, again):
        np.testing.assert_array_equal(a, e)
        traced = jax.vmap(f)(jnp.asarray(vals))
        traced = np.stack([flat(jax.tree_util.tree_map(lambda a, k=k: a[k], traced)) for k in range(len(vals))])
        np.testing.assert_allclose(traced, e, rtol=0, atol=1e-14)


def test_the_cache_reads_back_only_what_this_user_wrote(tmp_path, monkeypatch):
    """The cache directory is trusted like code (executables, and JAX's pickled ones): a
    file another user owns, or any file in a directory others can write, is ignored with
    a warning (the program is traced again); directories are created 0700; output
    structures of builtin containers are stored as JSON, not pickle."""
    import json as json_
    import warnings

    folder = tmp_path / "programs"
    monkeypatch.setattr(_programs, "directory", lambda: folder)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    monkeypatch.setattr(_programs, "_WARNED", set())
    fn = _user_function("def h(x):\n    return {'y': jnp.sin(x), 'z': (x, None)}\n", "h")
    x = jnp.array([0.5, -1.0])
    first = _programs.call("test-trust", fn, (x,))
    assert (folder.stat().st_mode & 0o777) == 0o700
    prog = next(folder.glob("*.prog"))
    head = json_.loads(prog.read_bytes().partition(b"\n")[0])  # no pickle for {'y': *, 'z': (*, None)}
    assert "pickled_out_def" not in head
    assert _programs.treedef_from_json(head["out_def"]) == jax.tree_util.tree_structure(first)

    def read_back():
        monkeypatch.setattr(_programs, "_MEMORY", {})
        loaded, stored = _programs.STATS["loaded"], _programs.STATS["stored"]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            again = _programs.call("test-trust", fn, (x,))
        np.testing.assert_array_equal(again["y"], first["y"])
        return _programs.STATS["loaded"] - loaded, _programs.STATS["stored"] - stored, caught

    assert read_back()[:2] == (1, 0)  # its own files: the executable loaded, nothing traced
    folder.chmod(0o777)  # others could have planted anything
    n_loaded, n_stored, caught = read_back()
    assert n_loaded == 0 and n_stored >= 1 and any("trusted like code" in str(w.message) for w in caught)
    folder.chmod(0o700)
    monkeypatch.setattr(_programs, "_WARNED", set())
    if os.getuid() == 0:  # a file of another user (only root can make one here)
        for f in folder.iterdir():
            os.chown(f, 12345, 12345)
        n_loaded, n_stored, caught = read_back()
        assert n_loaded == 0 and n_stored >= 1 and any("another user" in str(w.message) for w in caught)
