"""Traced programs kept on disk, so that a new process skips tracing too.

JAX's persistent compilation cache (``_cache.py``) keeps compiled XLA programs, but
every new process still traces and lowers a solve before it can look one up: for a
first ``simulate()`` that is most of its time once the cache is warm. This module
keeps the lowered program itself (``jax.export``, serialized StableHLO) under a key
that fingerprints everything the tracing depended on:

* the Python structure of the arguments, with the shapes and dtypes of their arrays
  (values do not enter a trace: they are arguments of the program);
* every static value in them (numbers, strings, the fields of equinox modules and
  dataclasses), and the code of every function and class they hold. Classes and
  functions of nhjax and of the libraries it builds on are identified by name,
  since the versions of those libraries and the source of nhjax are in the key;
  anything else (a user's Lagrangian, a control written in a notebook) by its
  bytecode, its constants, its closure and the globals it refers to, recursively;
* the versions of jax, jaxlib, diffrax, equinox, optimistix, lineax, optax, numpy,
  the hash of nhjax's and controls' own source files and the JAX settings that
  change a trace.

Whatever the fingerprint cannot vouch for (an object it does not know how to read,
a global that is neither data, module, function nor class) makes the call
uncacheable: it is then traced as usual, so a stale program is never used. Beside
each program its compiled executable is kept (``*.exe``: XLA's serialized
executable, under the program's key plus the machine's: jaxlib's XLA, XLA_FLAGS, the
CPU's instruction sets, the compiler options), so a warm process loads that directly
instead of deserializing, lowering and looking the program up in JAX's cache (a
good part of a warm first ``simulate()``); without it the program is called through
``jax.export`` and compiled, with JAX's persistent cache off for that compile (an
executable from there, or compiled after one in the same process, would be stored
broken), and its executable stored. Only calls made
on concrete values use this path; under an outer ``jax.jit`` or ``jax.grad``
nothing changes.

Files live in ``<compilation cache>/nhjax-programs`` (``NHJAX_CACHE_DIR``; ``=0``
turns both caches off), capped at ``MAX_BYTES`` (oldest files go first).

The cache directory is trusted like code: an executable is machine code, and JAX's
serialized executables are pickles. Directories are created 0700; a file is read back
only if this user owns it and its directory and neither group nor others can write
that directory (``trusted``; otherwise it is ignored with one warning, and the program
traced again); output structures are written as JSON where they are builtin
containers (pickle only for others, such as equinox modules). ``nhjax._cache`` leaves
JAX's compilation cache off on a directory that fails the same test.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import enum
import functools
import gc
import hashlib
import importlib.metadata
import json
import os
import pickle
import re
import threading
import types
import weakref
from pathlib import Path
from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from . import _cache

FORMAT = 2
MAX_BYTES = 256 * 2**20
#: Modules whose classes and functions are identified by name (their code is covered
#: by the versions and the source hash in the key).
LIBRARIES = ("nhjax", "controls", "jax", "jaxlib", "diffrax", "equinox", "optimistix", "lineax",
             "optax", "numpy", "builtins", "functools", "operator", "math", "typing", "abc", "lax")
_PACKAGES = ("jax", "jaxlib", "diffrax", "equinox", "optimistix", "lineax", "optax", "numpy")

#: Counters the tests read: programs loaded from disk (``loaded``; executables among
#: them: ``executables``), traced and stored, compiled by XLA, uncacheable calls.
STATS = {"loaded": 0, "stored": 0, "compiled": 0, "uncacheable": 0, "executables": 0}
_MEMORY: dict[str, Callable] = {}
_LOCK = threading.Lock()


class Uncacheable(Exception):
    """The fingerprint cannot vouch for an object: trace as usual."""


def directory() -> Path | None:
    """Where programs are kept (None: caching is off)."""
    return _directory(jax.config.jax_compilation_cache_dir, os.environ.get("NHJAX_PROGRAM_CACHE", "1"))


@functools.lru_cache(maxsize=8)
def _directory(base, switch) -> Path | None:  # asked on every call: a Path costs ~50 us
    if not base or switch.strip().lower() in ("0", "off", "false", "no"):
        return None
    return Path(base) / "nhjax-programs"


@functools.lru_cache(maxsize=1)
def _environment() -> str:
    h = hashlib.sha256()
    for pkg in _PACKAGES:
        try:
            h.update(f"{pkg}={importlib.metadata.version(pkg)};".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{pkg}=?;".encode())
    for root in _source_roots():
        for path in sorted(root.rglob("*.py")):
            h.update(f"{root.name}/{path.relative_to(root)}".encode())
            h.update(path.read_bytes())
    for name in ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion",
                 "jax_numpy_rank_promotion", "jax_default_prng_impl"):
        h.update(f"{name}={getattr(jax.config, name, None)};".encode())
    h.update(str(jax.default_backend()).encode())
    return h.hexdigest()


def _source_roots() -> list[Path]:
    """The folders of this project's packages whose functions the fingerprint identifies
    by name (nhjax, and controls beside it when installed): their source is in the key."""
    import importlib.util

    roots = [Path(__file__).resolve().parent]
    spec = importlib.util.find_spec("controls")
    if spec is not None and spec.submodule_search_locations:
        roots.append(Path(next(iter(spec.submodule_search_locations))).resolve())
    return roots


@functools.lru_cache(maxsize=1)
def _machine() -> str:
    """What a compiled executable depends on beyond its program: the XLA inside jaxlib,
    XLA_FLAGS, and the CPU's instruction sets (code compiled for AVX-512 must not be
    loaded on a CPU without it, e.g. from a cache directory shared across a cluster)."""
    h = hashlib.sha256()
    try:
        h.update(str(jax.devices()[0].client.platform_version).encode())
    except Exception:  # noqa: BLE001 - no backend information: the versions still count
        pass
    h.update(os.environ.get("XLA_FLAGS", "").encode())
    flags = ""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line for line in f if line.startswith(("flags", "Features"))), "")
    except OSError:
        import platform

        flags = f"{platform.machine()}:{platform.processor()}"
    h.update(" ".join(sorted(flags.split())).encode())
    return h.hexdigest()[:24]


def _is_library(module: str | None) -> bool:
    return bool(module) and module.split(".")[0] in LIBRARIES


def _code(code: types.CodeType, fp) -> str:
    consts = ",".join(_code(c, fp) if isinstance(c, types.CodeType) else fp(c) for c in code.co_consts)
    return f"code({code.co_code.hex()};{consts};{code.co_names};{code.co_varnames};{code.co_freevars})"


class _Fingerprint:
    """Walks objects into a string. Arrays that are leaves of the call's arguments
    (``dynamic``: ids of the arrays the program takes as inputs) count by shape and
    dtype; any other array (a global, a closure constant, a static field) is baked into
    the trace, so its values count too."""

    def __init__(self, dynamic=frozenset()):
        self.seen: dict[int, str] = {}
        self.dynamic = dynamic

    def __call__(self, obj: Any) -> str:
        if obj is None or isinstance(obj, (bool, int, float, complex, str, bytes)):
            return f"{type(obj).__name__}:{obj!r}"
        if isinstance(obj, (jax.Array, np.ndarray, np.generic)) or isinstance(obj, jax.ShapeDtypeStruct):
            head = f"array({np.dtype(obj.dtype).str}{tuple(obj.shape)}"
            if id(obj) in self.dynamic or isinstance(obj, jax.ShapeDtypeStruct):
                return head + ")"  # an input of the program (a tracer too): its shape counts
            if isinstance(obj, jax.core.Tracer):
                raise Uncacheable("traced value")
            return head + ":" + hashlib.sha256(np.ascontiguousarray(np.asarray(obj)).tobytes()).hexdigest() + ")"
        key = id(obj)
        if key in self.seen:  # cycles, shared objects
            return self.seen[key]
        self.seen[key] = f"ref{len(self.seen)}"
        out = self._compound(obj)
        self.seen[key] = out
        return out

    def _compound(self, obj):
        if isinstance(obj, (tuple, list)):
            return f"{type(obj).__name__}(" + ",".join(map(self, obj)) + ")"
        if isinstance(obj, dict):
            return "dict(" + ",".join(f"{self(k)}:{self(v)}" for k, v in sorted(obj.items(), key=lambda kv: repr(kv[0]))) + ")"
        if isinstance(obj, (frozenset, set)):
            return "set(" + ",".join(sorted(map(self, obj))) + ")"
        if isinstance(obj, type):
            return self._class(obj)
        if isinstance(obj, types.ModuleType):
            return f"module:{obj.__name__}"
        if isinstance(obj, np.dtype):
            return f"dtype:{obj.str}"
        if isinstance(obj, enum.Enum):
            return f"enum:{self._class(type(obj))}.{obj.name}"
        if isinstance(obj, (staticmethod, classmethod)):
            return f"{type(obj).__name__}({self(obj.__func__)})"
        if isinstance(obj, property):
            return f"property({self(obj.fget)};{self(obj.fset)})"
        if isinstance(obj, functools.partial):
            return f"partial({self(obj.func)};{self(obj.args)};{self(obj.keywords)})"
        if isinstance(obj, types.MethodType):
            return f"method({self(obj.__func__)};{self(obj.__self__)})"
        if isinstance(obj, (types.FunctionType, types.BuiltinFunctionType)):
            return self._function(obj)
        wrapped = getattr(obj, "__wrapped__", None) or getattr(obj, "method", None)
        if callable(obj) and callable(wrapped) and not isinstance(obj, eqx.Module):
            # jax.jit-ed functions, equinox's method wrappers: what they wrap
            return f"wrapper:{type(obj).__qualname__}({self(wrapped)})"
        if isinstance(obj, jtu.PyTreeDef):
            return f"treedef:{obj}"
        if isinstance(obj, eqx.Module) or dataclasses.is_dataclass(obj):
            fields = ",".join(f"{f.name}={self(getattr(obj, f.name, None))}" for f in dataclasses.fields(obj))
            return f"{self._class(type(obj))}({fields})"
        if _is_library(type(obj).__module__) and hasattr(obj, "__dict__"):
            # a library object that is not a dataclass: its class and state
            return f"{self._class(type(obj))}{self(vars(obj))}"
        raise Uncacheable(f"cannot fingerprint {type(obj).__qualname__}")

    def _class(self, cls) -> str:
        name = f"{cls.__module__}.{cls.__qualname__}"
        if _is_library(cls.__module__):
            return f"class:{name}"
        # a user's class: its own methods and attributes, and its bases
        body = {k: v for k, v in vars(cls).items()
                if (not k.startswith("__") or k in ("__call__", "__init__")) and k != "_abc_impl"}
        bases = ",".join(self._class(b) for b in cls.__bases__)
        return f"class:{name}[{bases}]{self(body)}"

    def _function(self, fn) -> str:
        module = getattr(fn, "__module__", None)
        name = f"{module}.{getattr(fn, '__qualname__', getattr(fn, '__name__', '?'))}"
        if _is_library(module) and "<lambda>" not in name and "<locals>" not in name:
            return f"fn:{name}"
        code = getattr(fn, "__code__", None)
        if code is None:
            owner = getattr(fn, "__self__", None)  # a C method: tuple.__new__, np.ndarray.sum
            where = owner.__module__ if isinstance(owner, type) else getattr(owner, "__name__", None)
            if isinstance(fn, types.BuiltinFunctionType) and _is_library(where):
                return f"builtin:{where}.{fn.__qualname__}"
            raise Uncacheable(f"cannot read the code of {name}")
        parts = [f"fn:{name}", _code(code, self)]
        globs = getattr(fn, "__globals__", {})
        for g in _global_names(code):
            if g in globs:
                parts.append(f"{g}={self(globs[g])}")
        if fn.__closure__:
            parts.append("closure(" + ",".join(self(c.cell_contents) for c in fn.__closure__) + ")")
        parts.append(self(fn.__defaults__))
        parts.append(self(fn.__kwdefaults__))
        return "|".join(parts)


def _global_names(code: types.CodeType):
    names = set(code.co_names)
    for c in code.co_consts:
        if isinstance(c, types.CodeType):
            names |= set(_global_names(c))
    return sorted(names)


# ------------------------------------------------------------------ equinox's error mode
# equinox's runtime checks (eqx.error_if in diffrax, optimistix, lineax and nhjax's own
# argument checks) are traced as host callbacks ("raise", equinox's default), NaN outputs
# ("nan": controls' programs, which JAX can then keep on disk) or nothing ("off": a
# solve's own diffrax checks, batched programs). equinox reads its mode from one module
# global (EQX_ON_ERROR); nhjax never changes that global. It keeps its own mode instead,
# per thread, as a JAX configuration state that is part of JAX's trace context and of
# its jit dispatch key: a function traced in one mode (a check, or diffrax's jitted solve
# around it) is never reused from JAX's in-memory caches in another (without the dispatch
# key, a jitted function compiled in one thread's "nan" mode answered another thread's
# call in "raise" from its C++ cache), and threads that trace at once (the
# solvers on a threads-only Dask cluster) each trace in their own mode. equinox's check
# is routed through ``error_mode`` (``_route_checks``, once at import).
_MODES = ("default", "raise", "nan", "off", "breakpoint")


def _mode_state():
    """The thread-local mode: a JAX config state in the trace context and the jit key
    ("default": as equinox is configured); a plain thread-local stack if this JAX has no
    such states."""
    try:
        from jax._src import config as jax_config

        state = jax_config.config_states.get("nhjax_error_mode")
        if state is None:
            state = jax_config.enum_state(
                "nhjax_error_mode", list(_MODES), "default", include_in_jit_key=True, include_in_trace_context=True,
                help="equinox's runtime-error mode while nhjax traces (set by nhjax per thread)")
        return state
    except (ImportError, AttributeError, TypeError):  # another JAX: per thread, outside the trace context
        return _LocalMode()


class _LocalMode(threading.local):
    """The fallback of ``_mode_state``: ``.value`` and ``state(mode)`` as a context."""

    def __init__(self):
        self.stack = []

    @property
    def value(self):
        return self.stack[-1] if self.stack else "default"

    @contextlib.contextmanager
    def __call__(self, mode):
        self.stack.append(mode)
        try:
            yield
        finally:
            self.stack.pop()


_MODE = _mode_state()


def error_mode() -> str:
    """equinox's runtime-error mode in force in this thread: the innermost ``errors``
    context's, else equinox's own setting (EQX_ON_ERROR, "raise" by default)."""
    mode = _MODE.value
    if mode != "default":
        return mode
    from equinox import _errors

    return str(getattr(_errors, "EQX_ON_ERROR", "raise"))


_error_mode = error_mode  # (for the functions below whose parameter is named error_mode)


@contextlib.contextmanager
def errors(mode: str | None):
    """equinox's checks traced in ``mode`` ("raise", "nan" or "off"; None: as they are)
    in this thread until the context closes. Contexts nest; other threads keep theirs."""
    if mode is None:
        yield
        return
    if mode not in _MODES[1:]:
        raise ValueError(f"error mode must be one of {_MODES[1:]}, got {mode!r}")
    with _MODE(mode):
        yield


def error_checks(on: bool):
    """equinox's runtime errors as configured (on) or off while a solve is traced."""
    return errors(None if on else "off")


def branched_error_if(x, pred, index, msgs, on_error: str = "default"):
    """``equinox.branched_error_if`` in ``on_error`` ("default": ``error_mode()``). In the
    modes that show no message ("off": no check; "nan": NaN outputs) a traced check
    skips what equinox does for a message at every check it traces: formatting every
    frame of the Python stack (tens of milliseconds in a solve traced inside an
    optimizer's program), which only "raise" shows. The program is the same as
    equinox's."""
    from equinox import _errors

    if on_error == "default":
        on_error = error_mode()
    if on_error in ("off", "nan") and isinstance(pred, jax.core.Tracer):
        if on_error == "off":
            return x
        try:
            from equinox.internal import unvmap_any, unvmap_max

            dynamic, static = eqx.partition(x, eqx.is_array)
            if jtu.tree_leaves(dynamic):
                index = index if isinstance(index, int) else unvmap_max(index)
                dynamic = _errors._error(dynamic, unvmap_any(pred), index, msgs=msgs, on_error="nan", stack=[])
                return eqx.combine(dynamic, static)
        except (ImportError, AttributeError, TypeError):  # another equinox: its own way
            pass
    if _EQX_JIT_CHECK is not None and any(eqx.is_array(leaf) for leaf in jtu.tree_leaves((x, pred, index))):
        return _EQX_JIT_CHECK(x, pred, index, msgs, on_error=on_error)  # equinox's own (not routed again)
    return eqx.branched_error_if(x, pred, index, msgs, on_error=on_error)


#: equinox's own traced check, before ``_route_checks`` put ``branched_error_if`` in its place.
_EQX_JIT_CHECK = None


def _route_checks():
    """Route equinox's own traced checks (``branched_error_if_impl_jit``, which
    ``eqx.error_if`` and ``eqx.branched_error_if`` call with on_error="default") through
    ``branched_error_if``, so that they follow this thread's ``error_mode``; and its
    untraced ones (``branched_error_if_impl``, for Python booleans) likewise. Nothing is
    done if equinox has no such functions (another version: its checks then follow
    EQX_ON_ERROR only)."""
    global _EQX_JIT_CHECK
    from equinox import _errors

    jit_impl = getattr(_errors, "branched_error_if_impl_jit", None)
    plain_impl = getattr(_errors, "branched_error_if_impl", None)
    if jit_impl is None or plain_impl is None or getattr(jit_impl, "_nhjax", False):
        return
    _EQX_JIT_CHECK = jit_impl

    def routed(x, pred, index, msgs, *, on_error="default"):
        return branched_error_if(x, pred, index, msgs, on_error)

    def routed_plain(x, pred, index, msgs, *, on_error="default"):
        return plain_impl(x, pred, index, msgs, on_error=error_mode() if on_error == "default" else on_error)

    routed._nhjax = routed_plain._nhjax = True
    _errors.branched_error_if_impl_jit = routed
    _errors.branched_error_if_impl = routed_plain


_route_checks()


def fingerprint(*objs, error_mode: str | None = None) -> str:
    """The cache key of a call on ``objs`` (raises Uncacheable when it cannot be made).
    ``error_mode``: equinox's error mode the function sets for itself while it is traced
    (default: the mode in force now)."""
    h = hashlib.sha256()
    h.update(f"format={FORMAT};env={_environment()};errors={error_mode or _error_mode()};".encode())
    dynamic = frozenset(id(x) for x in jtu.tree_leaves(objs) if eqx.is_array(x))
    h.update(_Fingerprint(dynamic)(objs).encode())
    return h.hexdigest()


_TRACING = threading.local()


@contextlib.contextmanager
def stored_trace():
    """Marks the trace of a program that is being stored (its calls of other stored
    programs are traced into it: ``tracing_stored``)."""
    _TRACING.depth = getattr(_TRACING, "depth", 0) + 1
    try:
        yield
    finally:
        _TRACING.depth -= 1


def tracing_stored() -> bool:
    """Whether this thread is tracing a program to be stored (``stored_trace``)."""
    return getattr(_TRACING, "depth", 0) > 0


def program_key(name: str, fn: Callable, args: tuple, error_mode: str | None = None, options: dict | None = None):
    """The name of ``fn``'s program on ``args``'s structure, compiled with ``options``
    (raises Uncacheable)."""
    key = f"{name}-{fingerprint(name, fn, args, error_mode=error_mode)}"
    if options:
        key += "-" + hashlib.sha256(repr(sorted(options.items())).encode()).hexdigest()[:12]
    return key


def _store(path: Path, data: bytes):
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    tmp = path.with_name(f"{path.name}.tmp{os.getpid()}-{threading.get_ident()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    files = sorted([*path.parent.glob("*.prog"), *path.parent.glob("*.exe")], key=lambda p: p.stat().st_mtime)
    total = sum(p.stat().st_size for p in files)
    while files and total > MAX_BYTES:
        oldest = files.pop(0)
        total -= oldest.stat().st_size
        oldest.unlink(missing_ok=True)


def _program(name: str, fn: Callable, args: tuple, error_mode: str | None = None, compiler_options=None,
             flat=None, background=False, trace=True):
    """(compiled caller, output treedef) of ``fn`` on ``args``'s structure, from memory,
    disk (its executable, or its program compiled) or a new export; None when it cannot
    be cached. ``flat``: ``jtu.tree_flatten(args)`` if the caller has it.
    ``background``: a compile that is needed runs in a worker thread; returns its
    future (kept in memory, where the call that needs the program waits for it), or
    what is there already (a pending future is not waited for). ``trace=False``: only
    what is stored (an executable, an exported program); None if the program would
    have to be traced."""
    folder = directory()
    if folder is None or jax.config.jax_disable_jit:
        return None
    options = dict(compiler_options or {})
    quick = _quick_key(name, fn, args, error_mode, flat, options)
    if quick is _TRACED:
        return None
    if not background and quick is not None:
        _wait_for_later(quick)
    with _LOCK:
        program = _MEMORY.get(quick) if quick is not None else None
    program = program if background else _settled(program)
    if program is not None:
        return None if program is _FAILED else program
    try:
        key = program_key(name, fn, args, error_mode, options)
    except Uncacheable:
        STATS["uncacheable"] += 1
        if quick is not None:
            with _LOCK:
                _MEMORY[quick] = _FAILED  # not again in this process
        return None
    with _LOCK:
        program = _MEMORY.get(key)
    program = program if background else _settled(program)
    if program is None:
        exe_path = folder / f"{key}-{_machine()}.exe"
        if background and exe_path.exists():
            # loading links the executable's machine code (its time grows with the
            # code's size), with the GIL released: in the background, beside the
            # caller's work and other loads
            program = _compiler().submit(_load_or_raise, exe_path)
            _LOADS.add(program)
        else:
            program = _load_executable(exe_path)
        if program is None:
            dyn, static = eqx.partition(args, eqx.is_array)
            leaves, dyn_def = jtu.tree_flatten(dyn)
            path = folder / f"{key}.prog"
            program = _load(path)
            if program is None and not trace:
                return None
            if program is None:
                program = _export(fn, static, dyn_def, leaves, path)
            if program is not _FAILED:
                specs = [jax.ShapeDtypeStruct(np.shape(x), x.dtype) for x in leaves]
                if background:
                    if quick is not None:
                        with _LOCK:
                            _OUT_DEFS[quick] = program[1]
                    program = _compiler().submit(_compile, program, specs, options, exe_path)
                else:
                    program = _compile(program, specs, options, exe_path)
    with _LOCK:
        _MEMORY[key] = program
        if quick is not None:
            _MEMORY[quick] = program
    return None if program is _FAILED else program


# ------------------------------------------------------------------ programs by key
# The primitive of ``nhjax._primitive`` names its programs (a call's, and those derived
# from it: derivatives, batches) by key, and reaches them here.
_EXPORTED: dict[str, Any] = {}


_META: dict[str, Any] = {}


# ------------------------------------------------------------------ what is read back
# The cache directory is trusted like code: an executable is machine code, and JAX's
# serialized executables (and output structures JSON cannot hold) are unpickled. So
# nhjax reads a file only if the user owns it and its directory, and no one else can
# write that directory (``trusted``); what it writes itself is JSON where it can be.
_WARNED: set = set()


def trusted(path: Path) -> bool:
    """Whether ``path`` may be read back: owned by this user, in a directory this user
    owns that neither group nor others can write. Warns once per directory otherwise."""
    try:
        # the directory as nhjax._cache requires of the cache directory, and the file its user's
        ok = _cache.own(str(path.parent)) and (not hasattr(os, "getuid") or path.stat().st_uid == os.getuid())
    except OSError:
        return False
    if not ok and str(path.parent) not in _WARNED:
        _WARNED.add(str(path.parent))
        import warnings

        warnings.warn(
            f"nhjax: ignoring files in the program cache {path.parent} that another user owns or "
            "could have written (owner, or a directory writable by group/others): the cache "
            "directory is trusted like code. Point NHJAX_CACHE_DIR at a directory of your own "
            "(mode 700), or NHJAX_CACHE_DIR=0 to turn the caches off.", RuntimeWarning, stacklevel=3)
    return ok


def _read(path: Path) -> bytes | None:
    """The bytes of a cache file, if present and ``trusted``."""
    if not path.exists() or not trusted(path):
        return None
    try:
        return path.read_bytes()
    except OSError:
        return None


def treedef_to_json(td):
    """A PyTreeDef of None, tuples, lists, dicts with string keys and leaves as JSON
    (raises TypeError for anything else)."""
    if td.num_nodes == 1 and td.num_leaves == 1 and not td.children():
        return "*"
    node_type, data = td.node_data()
    kids = [treedef_to_json(c) for c in td.children()]
    if node_type is type(None):
        return None
    if node_type is tuple:
        return {"tuple": kids}
    if node_type is list:
        return {"list": kids}
    if node_type is dict and all(isinstance(k, str) for k in data):
        return {"dict": [list(data), kids]}
    raise TypeError(f"no JSON for {node_type.__name__} nodes")


def _skeleton(j):
    if j == "*":
        return 0
    if j is None:
        return None
    if "tuple" in j:
        return tuple(_skeleton(c) for c in j["tuple"])
    if "list" in j:
        return [_skeleton(c) for c in j["list"]]
    keys, kids = j["dict"]
    return {k: _skeleton(c) for k, c in zip(keys, kids)}


def treedef_from_json(j):
    return jtu.tree_structure(_skeleton(j))


def _pack(head: dict, out_def, body: bytes = b"") -> bytes:
    """A cache file: one line of JSON (``head``, the output structure as JSON or, where
    JSON cannot hold it, its pickle's length), the pickle if any, then ``body``."""
    head = dict(head, format=FORMAT)
    pickled = b""
    if out_def is not None:
        try:
            head["out_def"] = treedef_to_json(out_def)
        except TypeError:
            pickled = pickle.dumps(out_def)
            head["pickled_out_def"] = len(pickled)
    return json.dumps(head).encode() + b"\n" + pickled + body


def _unpack(blob: bytes):
    """(head, output structure or None, body) of a file written by ``_pack``."""
    line, _, rest = blob.partition(b"\n")
    head = json.loads(line)
    if head.get("format") != FORMAT:
        raise ValueError("another format")
    n = head.get("pickled_out_def", 0)
    if n:
        out_def = pickle.loads(rest[:n])
    elif "out_def" in head:
        out_def = treedef_from_json(head["out_def"])
    else:
        out_def = None
    return head, out_def, rest[n:]


def keyed_meta(key: str):
    """(output structure or None, [(shape, dtype), ...]) of the program named ``key``, as
    recorded by a trace in this process or an earlier one (``store_meta``); None if
    unknown."""
    with _LOCK:
        meta = _META.get(key)
    if meta is None:
        folder = directory()
        if folder is None:
            return None
        blob = _read(folder / f"{key}.meta")
        if blob is None:
            return None
        try:
            head, out_def, _ = _unpack(blob)
            meta = (out_def, [(tuple(shape), dtype) for shape, dtype in head["avals"]])
        except Exception:  # noqa: BLE001 - damaged or foreign: trace
            return None
        with _LOCK:
            _META[key] = meta
    return meta


def store_meta(key: str, out_def, avals):
    """Record a program's output structure and shapes (kept beside the programs)."""
    meta = (out_def if out_def is None or _portable(out_def) else None,
            [(tuple(a.shape), np.dtype(a.dtype).str) for a in avals])
    with _LOCK:
        if key in _META:
            return
        _META[key] = meta
    folder = directory()
    if folder is not None and (meta[0] is not None or out_def is None):
        try:
            _store(folder / f"{key}.meta", _pack({"avals": meta[1]}, meta[0]))
        except (OSError, pickle.PicklingError, TypeError):
            pass


def keyed_out_def(key: str):
    """The output structure kept with the program named ``key`` (None if not stored)."""
    program = _keyed_program(key)
    return None if program is None else program[1]


def _keyed_program(key: str):
    with _LOCK:
        program = _EXPORTED.get(key)
    if program is None:
        folder = directory()
        program = _load(folder / f"{key}.prog") if folder is not None else None
        if program is not None:
            with _LOCK:
                _EXPORTED[key] = program
    return None if program is _FAILED else program


def keyed_exported(key: str, flat_fn: Callable, specs, out_def: Callable | None = None):
    """The ``jax.export.Exported`` of ``flat_fn`` (a function of a flat list of arrays
    returning a flat list) on ``specs``, from memory, disk or exported now and stored;
    None when export refuses it. ``out_def()``: the caller's output structure once
    ``flat_fn`` is traced (kept with the program, as ``call`` keeps it; default the flat
    list)."""
    program = _keyed_program(key)
    if program is None:
        with _LOCK:
            if _EXPORTED.get(key) is _FAILED:
                return None
        folder = directory()
        program = _export_flat(flat_fn, specs, None if folder is None else folder / f"{key}.prog", out_def)
        with _LOCK:
            _EXPORTED[key] = program
        if program is _FAILED:
            return None
    return program[0]


def keyed_executable(key: str, flat_fn: Callable, specs, options: dict | None = None,
                     out_def: Callable | None = None):
    """A callable running the program stored under ``key`` on flat arrays (returning a
    flat list): its executable from memory or disk, or ``keyed_exported`` compiled with
    ``options`` and stored; None when export refuses it."""
    options = dict(options or {})
    mem = ("exe", key, tuple(sorted(options.items())))
    with _LOCK:
        program = _MEMORY.get(mem)
    if program is None:
        folder = directory()  # (the options are in the key: see options_key)
        exe_path = None if folder is None else folder / f"{key}-{_machine()}.exe"
        program = _load_executable(exe_path) if exe_path is not None else None
        if program is None:
            exported = keyed_exported(key, flat_fn, specs, out_def)
            if exported is None:
                return None
            program = _compile((exported, _keyed_program(key)[1]), specs, options, exe_path)
        with _LOCK:
            _MEMORY[mem] = program
    exe = program[0]
    return lambda *a: exe(*a)


def _export_flat(flat_fn, specs, path: Path | None, out_def: Callable | None = None):
    """``flat_fn`` exported on ``specs`` and stored at ``path``: (exported, out treedef),
    or ``_FAILED``."""
    box = {}
    specs = list(specs)

    def traced(*lv):
        out = flat_fn(*lv)
        box["out_def"] = jtu.tree_structure(list(out))
        return out

    try:
        with _gc_paused():
            exported = jax.export.export(jax.jit(traced))(*specs)
    except Exception:  # noqa: BLE001 - the plain path re-raises a user's own error
        if os.environ.get("NHJAX_DEBUG_PROGRAMS"):  # why a program is traced in every process
            import traceback

            traceback.print_exc()
        STATS["uncacheable"] += 1
        return _FAILED
    out_def = (out_def and out_def()) or box["out_def"]
    if path is not None and _portable(out_def):
        try:
            _store(path, _pack({}, out_def, bytes(exported.serialize())))
            STATS["stored"] += 1
        except (OSError, pickle.PicklingError, TypeError, ImportError):
            pass  # read-only cache: keep it in memory
    return exported, out_def


def _load_or_raise(path: Path):
    """``_load_executable`` for a background load: a failure raises, so that ``_settled``
    forgets it and the caller takes the ordinary path (compile) itself."""
    program = _load_executable(path)
    if program is None:
        raise RuntimeError(f"cannot load {path}")
    return program


def _settled(program):
    """``program`` from ``_MEMORY``, waiting for it if ``prepare`` is compiling it in the
    background; None (and forgotten) if that compile failed: the caller compiles it
    again and meets the error itself."""
    if not isinstance(program, concurrent.futures.Future):
        return program
    try:
        return program.result()
    except Exception:  # noqa: BLE001
        with _LOCK:
            for k, v in list(_MEMORY.items()):
                if v is program:
                    del _MEMORY[k]
        return None


_POOLS: dict = {}  # long-lived worker threads by task: "prepare" (compiles, loads), "trace"
_POOL_LOCK = threading.Lock()  # (not _LOCK: prepare_later asks for its pool holding that)


def _pool(task: str, workers: int):
    with _POOL_LOCK:
        if task not in _POOLS:
            _POOLS[task] = concurrent.futures.ThreadPoolExecutor(max_workers=workers,
                                                                 thread_name_prefix=f"nhjax-{task}")
        return _POOLS[task]


def _compiler():
    return _pool("prepare", 2)


def prepare(name: str, fn: Callable, args: tuple, error_mode: str | None = None,
            compiler_options: dict | None = None, trace: bool = True) -> bool:
    """Get ``fn``'s program on ``args``'s structure ready before it is called: traced and
    lowered now, in the calling thread (tracing reads process-wide settings such as
    equinox's error mode, which only the caller knows to be right), and compiled by XLA
    in a background thread, which releases the GIL: a solver that will need several
    programs compiles the later ones while it compiles and runs the first (on two
    cores, the XLA time of the smaller one overlaps the other's). The call that needs it
    waits for that compile. An executable on disk is loaded in the background too
    (loading links its machine code, in a time that grows with its size); a program in
    memory is left
    alone. ``compiler_options`` as for ``call`` (the call must pass the same).
    ``trace=False``: only a stored program (its executable loaded, or its exported
    program compiled, in the background); nothing is traced. Returns whether this call
    started background work (a compile or a load)."""
    flat = jtu.tree_flatten(args)
    quick = _quick_key(name, fn, args, error_mode, flat, compiler_options)
    with _LOCK:
        if quick is _TRACED or (quick is not None and (quick in _MEMORY or quick in _LATER)):
            return False
    program = _program(name, fn, args, error_mode, compiler_options, flat=flat, background=True, trace=trace)
    return isinstance(program, concurrent.futures.Future)


_LATER: dict = {}  # quick key -> future of the thread that traces a program (prepare_later)
_LOADS: "weakref.WeakSet" = weakref.WeakSet()  # futures of background loads (not compiles)


def _stored_key(name, fn, args, error_mode, compiler_options):
    """The in-process key of a program the cache can keep; None when the cache is off,
    an argument is traced or a static value is unhashable (then calls trace as usual)."""
    if directory() is None or jax.config.jax_disable_jit:
        return None
    quick = _quick_key(name, fn, args, error_mode, None, compiler_options)
    return None if quick is _TRACED else quick


def prepare_later(name: str, fn: Callable, args: tuple, error_mode: str | None = None,
                  compiler_options: dict | None = None, context: Callable | None = None) -> bool:
    """``prepare`` with the trace too in a thread of its own (then the compile in the
    background as ``prepare``'s), for a program that a solver can do without until it is
    ready (``ready``) and whose trace would otherwise hold up the solver's first
    answer. ``context()``: a context manager entered in that thread around the trace,
    for the caller's thread-local settings that tracing reads (equinox's error mode is
    ``error_mode``, already). A call that needs the program meanwhile waits for that
    thread, then for the compile. Nothing is done when the program cache is off, the
    arguments are traced or the program is known already. Returns whether the thread
    was started."""
    quick = _stored_key(name, fn, args, error_mode, compiler_options)
    if quick is None:
        return False
    with _LOCK:
        if quick in _MEMORY or quick in _LATER:
            return False

        def trace():
            with context() if context is not None else contextlib.nullcontext():
                _program(name, fn, args, error_mode, compiler_options, background=True)

        _LATER[quick] = _pool("trace", 1).submit(trace)
    return True


def ready(name: str, fn: Callable, args: tuple, error_mode: str | None = None,
          compiler_options: dict | None = None) -> bool:
    """Whether a call of ``fn`` on ``args``'s structure now would trace and compile
    nothing: its program is in memory (compiled, or its stored executable being loaded),
    or the program cache cannot keep it (the call then traces as ``jax.jit`` does, as it
    would anyway). False while it is being traced (``prepare_later``) or compiled in the
    background, or when it is not known yet."""
    quick = _stored_key(name, fn, args, error_mode, compiler_options)
    if quick is None:
        return True
    with _LOCK:
        program = _MEMORY.get(quick)
    if program is None:
        return False
    if isinstance(program, concurrent.futures.Future):
        return program.done() or program in _LOADS
    return True


def settle():
    """Wait for this process's background work on programs (``prepare``'s compiles and
    loads, ``prepare_later``'s traces and the compiles they start): what a benchmark
    of calls "after compile" waits for first."""
    while True:
        with _LOCK:
            futures = [f for f in (*_LATER.values(), *_MEMORY.values())
                       if isinstance(f, concurrent.futures.Future) and not f.done()]
        if not futures:
            return
        concurrent.futures.wait(futures)


def _wait_for_later(quick):
    """Wait for a thread of ``prepare_later`` that traces this program (its failure is
    the caller's to meet again)."""
    with _LOCK:
        later = _LATER.get(quick)
    if later is not None:
        concurrent.futures.wait([later])


def output_structure(name: str, fn: Callable, args: tuple, error_mode: str | None = None,
                     compiler_options: dict | None = None):
    """The output treedef of the program ``prepare`` or ``call`` made for these
    arguments' structure (without waiting for a background compile; waiting for a
    background load), or None if there is none."""
    quick = _quick_key(name, fn, args, error_mode, None, compiler_options)
    if quick is None or quick is _TRACED:
        return None
    with _LOCK:
        known, program = _OUT_DEFS.get(quick), _MEMORY.get(quick)
    if known is not None:
        return known
    program = _settled(program)
    return None if program is None or program is _FAILED else program[1]


_OUT_DEFS: dict = {}  # quick key -> output treedef of a program compiling in the background


def _quick_key(name, fn, args, error_mode=None, flat=None, compiler_options=None):
    """The in-process key, as jax.jit's own cache has it: structure, shapes and dtypes,
    and the static values by hash (a global changed later in the same process is not
    seen, exactly as by jax.jit). None if a static value is unhashable; ``_TRACED`` if
    an argument is traced (a call under an outer transformation: nothing to cache)."""
    leaves, treedef = flat if flat is not None else jtu.tree_flatten(args)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return _TRACED
    desc = tuple((np.shape(x), np.dtype(x.dtype).str) if eqx.is_array(x) else x for x in leaves)
    key = ("quick", name, fn, treedef, desc, error_mode or _error_mode())
    if compiler_options:
        key += (tuple(sorted(compiler_options.items())),)
    try:
        hash(key)
    except TypeError:
        return None
    return key


def _inputs(leaves):
    """The array leaves among ``jtu.tree_leaves(args)``, in the order of the program's
    inputs (those of ``eqx.partition(args, eqx.is_array)``'s first part)."""
    return [x for x in leaves if eqx.is_array(x)]


def compiled(name: str, fn: Callable, args: tuple, compiler_options: dict | None = None):
    """Ahead-of-time: a callable equivalent to ``eqx.filter_jit(fn)`` on arguments of
    ``args``'s structure, compiled with ``compiler_options`` (options this XLA does not
    know are dropped), its program from the program cache; None when it cannot be
    cached (then compile as usual)."""
    program = _program(name, fn, args, compiler_options=compiler_options)
    if program is None:
        return None
    exe, out_def = program

    def run(*a):
        return jtu.tree_unflatten(out_def, exe(*_inputs(jtu.tree_leaves(a))))

    return run


def small_call(name: str, fn: Callable, system, *numbers):
    """``fn(system, *numbers)`` for a small one-off computation on concrete numbers (a
    scene's state from its coordinates, a change of coordinates): one program from the
    program cache, compiled with ``QUICK_OPTIONS``, instead of eager operations, each of
    which compiles a small program of its own in every new process. ``numbers``: jax
    arrays, or numbers and numpy arrays (handed over as float64 arrays without a program
    of their own). With a traced argument (under jit or vmap) it is
    ``fn(system, *numbers)`` itself, traced into the caller's program."""
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jtu.tree_leaves((system, numbers))):
        return fn(system, *numbers)
    numbers = tuple(v if isinstance(v, jax.Array) else jnp.asarray(np.asarray(v, float), float) for v in numbers)
    return call(name, fn, (system, *numbers), compiler_options=QUICK_OPTIONS)


def call(name: str, fn: Callable, args: tuple, error_mode: str | None = None, fallback: Callable | None = None,
         compiler_options: dict | None = None):
    """``fn(*args)`` (a jax-traceable function returning a pytree of arrays in builtin
    containers), with its traced program taken from / kept in the program cache.
    ``compiler_options``: XLA's, for the cached program (e.g. ``QUICK_OPTIONS``; the
    fallback compiles with XLA's defaults).

    Equivalent to ``eqx.filter_jit(fn)(*args)``; falls back to that (or to
    ``fallback(*args)``, e.g. the caller's own jitted ``fn``) when caching is off or
    the arguments cannot be fingerprinted. ``error_mode``: the equinox error mode
    ``fn`` sets for itself while traced (then the mode in force, which another thread
    may be changing, is not read)."""
    flat = jtu.tree_flatten(args)  # once, for the key and the inputs
    program = _program(name, fn, args, error_mode, compiler_options, flat=flat)
    if program is None:
        return (fallback or eqx.filter_jit(fn))(*args)
    caller, out_def = program
    return jtu.tree_unflatten(out_def, caller(*_inputs(flat[0])))


_TRACED = object()  # the call is under an outer trace

#: XLA settings for programs that run once per call on a few hundred numbers (the input
#: checks, the diagnostics of a solve): compiling takes about half the time (LLVM at its
#: lowest optimization, XLA's older loop emitters), the program runs ~2x slower, and its
#: numbers may differ from a default compile in the last bits. The solves themselves
#: keep XLA's defaults.
QUICK_OPTIONS = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}

#: XLA settings for an eager simulate()'s solve: XLA's older loop emitters instead of
#: its fusion emitters. On the registry's scenes the solve compiles in less time and
#: runs as fast (LLVM keeps its default optimization, which the run time needs; the
#: README's compile_times section has the figures); the last bits of the results
#: differ from a default compile, such as the one of a user's ``jax.jit(simulate)``.
#: An XLA without the option compiles with its defaults.
SOLVE_OPTIONS = {"xla_cpu_use_fusion_emitters": False}


def _pickle_equinox_missing():
    """Pickle equinox's MISSING sentinel (in the tree structure of every equinox module)
    as a reference to the module's singleton: pickled by value it comes back as a new
    object, and the structure no longer unflattens (``_portable`` guards the rest)."""
    import copyreg

    try:
        from equinox._module import _flatten
    except ImportError:  # another equinox: _portable keeps such structures in memory
        return
    if isinstance(getattr(_flatten, "MISSING", None), getattr(_flatten, "_Missing", ())):
        copyreg.pickle(_flatten._Missing, lambda obj: "MISSING")


_pickle_equinox_missing()


def _portable(out_def) -> bool:
    """Whether an output structure comes back equal from pickle (else its program is kept
    in memory only: a new process could not rebuild its outputs)."""
    try:
        return pickle.loads(pickle.dumps(out_def)) == out_def
    except Exception:  # noqa: BLE001
        return False


_FAILED = object()  # export refused this function (e.g. a host callback): trace as usual


def _load(path: Path):
    blob = _read(path)
    if blob is None:
        return None
    try:
        _, head, body = _unpack(blob)
        exported = jax.export.deserialize(bytearray(body))
    except Exception:  # a damaged or foreign file: trace again (and overwrite it)
        return None
    STATS["loaded"] += 1
    return exported, head


def _compile(program, specs, options: dict, exe_path: Path):
    """The exported program compiled (with ``options``; those this XLA does not know are
    dropped) and its executable stored at ``exe_path``: (executable, out treedef)."""
    exported, out_def = program
    lowered = jax.jit(exported.call).lower(*specs)
    options = dict(options)
    _watch_cache_hits()
    _HITS.count = 0
    while True:
        try:
            with _jax_cache_off():
                exe = lowered.compile(compiler_options=options or None)
            break
        except Exception:  # noqa: BLE001 - an option this XLA does not have
            if not options:
                raise
            options.pop(next(reversed(options)))
    STATS["compiled"] += 1
    uses_lapack, batched = _lapack_calls(exe)
    if _HITS.count or not _portable(out_def):
        # JAX's persistent cache had it after all (another JAX keeps its switch
        # elsewhere): an executable loaded from there serializes into one that misses
        # kernels when loaded again (jaxlib 0.10), so keep none; nor one whose outputs a
        # new process could not rebuild
        return one_at_a_time(exe, batched), out_def
    try:
        from jax.experimental import serialize_executable

        payload, in_tree, out_tree = serialize_executable.serialize(exe)
        examples = [jtu.tree_unflatten(t, [0] * t.num_leaves) for t in (in_tree, out_tree)]
        devices = [d.id for d in exe.runtime_executable().local_devices()]
        # JAX's serialized executable is a pickle itself: read back only when trusted
        _store(exe_path, _pack({"lapack": uses_lapack, "batched_lapack": batched, "devices": devices},
                               out_def, pickle.dumps((examples, payload))))
    except Exception:  # noqa: BLE001 - an executable that cannot be serialized: JAX's cache still has it
        pass
    return one_at_a_time(exe, batched), out_def


_HITS = threading.local()  # JAX persistent-cache hits of this thread's current compile
def _jax_cache_off():
    """JAX's persistent cache switched off (for every thread) while a program whose
    executable this module stores is compiled: an executable JAX's cache hands back,
    and even one compiled afterwards in the same process, serializes into one that
    misses kernels when loaded (jaxlib 0.10). Other threads' compiles meanwhile skip
    JAX's cache: slower, never wrong."""
    switch = _jax_cache_switch()
    return switch.off() if switch is not None else contextlib.nullcontext()


@functools.lru_cache(maxsize=1)
def _jax_cache_switch():
    """JAX's persistent-cache switch as a _HeldOff (None if this JAX keeps it elsewhere)."""
    try:
        from jax._src import compilation_cache as cc

        cc.is_cache_used(jax.devices()[0].client)  # settles whether JAX's cache is on at all
        usable = getattr(cc, "_cache_checked", False) and isinstance(getattr(cc, "_cache_used", None), bool)
    except Exception:  # noqa: BLE001 - another JAX: compile as it does
        return None
    return _HeldOff(lambda: cc._cache_used, lambda on: setattr(cc, "_cache_used", on)) if usable else None


@functools.lru_cache(maxsize=1)
def _watch_cache_hits():
    """Count JAX's persistent-cache hits per thread (its monitoring events are recorded
    in the thread that compiles)."""

    def listener(event, **kwargs):
        if event == "/jax/compilation_cache/cache_hits":
            _HITS.count = getattr(_HITS, "count", 0) + 1

    jax.monitoring.register_event_listener(listener)


#: Held while a program that calls a LAPACK kernel on a batch of matrices runs.
_BATCHED_LAPACK = threading.Lock()

_BATCH_SHAPE = re.compile(r"(?:f32|f64|c64|c128)\[\d+,\d+,\d+")


def batched_lapack(exe) -> bool:
    """Whether a compiled program (its optimized HLO) calls a LAPACK kernel on a batch of
    matrices (an operand of rank 3 or more: a vmapped solve, eigh, SVD, ...).

    jaxlib 0.10's batched LAPACK kernels split a large batch into tasks on XLA's CPU
    thread pool and block the pool thread they run on until those tasks finish. Two
    such programs running at once (the chunks of ``simulate_batch`` in its worker
    threads, the shares of ``closed_loop_batch``, a Dask worker's threads) can hold
    every thread of the pool waiting and hang; seen with the constrained scenes'
    lock-step chunks (LU of 128 KKT matrices, SVD in the member checks). nhjax runs
    such programs one at a time (``one_at_a_time``)."""
    return _lapack_calls(exe)[1]


def one_at_a_time(exe, batched: bool = True):
    """``exe`` (a callable program) run under a process-wide lock, to completion, when
    ``batched`` (see ``batched_lapack``); ``exe`` itself otherwise."""
    if not batched:
        return exe

    def run(*args):
        with _BATCHED_LAPACK:
            return jax.block_until_ready(exe(*args))

    return run


def _lapack_calls(exe) -> tuple[bool, bool]:
    """(whether a compiled program calls LAPACK at all, whether on a batch of matrices:
    ``batched_lapack``), from one reading of its HLO text. The first decides whether
    ``_initialize_lapack`` must run before the program is loaded (otherwise a warm
    process need not import what that takes)."""
    try:
        text = exe.as_text()
    except Exception:  # noqa: BLE001 - no text: assume it does, both
        return True, True
    calls = [line for line in text.splitlines() if 'custom_call_target="lapack' in line]
    return "lapack" in text.lower(), any(_BATCH_SHAPE.search(line) for line in calls)


@contextlib.contextmanager
def _scipy_lapack_alone():
    """While inside: SciPy's ``cython_blas`` and ``cython_lapack`` extension modules
    (where jaxlib's LAPACK initialization takes its routines from) loaded by
    themselves, so that the initialization does not import the ``scipy.linalg``
    package around them. That package imports most of SciPy (0.4 s on the development
    machine, 0.8 s under load), which the warm first answers of the scenes whose
    programs solve linear systems waited for. On leaving, the two leave ``sys.modules``
    again: a later ``import scipy.linalg.cython_lapack`` gets the same module (Cython
    keeps one per process) and sets it on its package as usual. Nothing is done when
    ``scipy.linalg`` is imported already or the modules are not where SciPy keeps them
    (the initialization then imports them the usual way)."""
    import importlib.util
    import sys

    added = []
    try:
        if "scipy.linalg" not in sys.modules:
            import scipy

            folder = Path(scipy.__file__).parent / "linalg"
            for name in ("cython_blas", "cython_lapack"):  # (lapack's module uses blas's)
                full = f"scipy.linalg.{name}"
                files = sorted(folder.glob(f"{name}.*.so")) + sorted(folder.glob(f"{name}.*.pyd"))
                if full in sys.modules or not files:
                    continue
                spec = importlib.util.spec_from_file_location(full, files[0])
                module = importlib.util.module_from_spec(spec)
                sys.modules[full] = module
                added.append(full)
                spec.loader.exec_module(module)
    except Exception:  # noqa: BLE001 - the initialization imports them itself
        for full in added:
            sys.modules.pop(full, None)
        added = []
    try:
        yield
    finally:
        for full in added:
            sys.modules.pop(full, None)


@functools.lru_cache(maxsize=1)
def _initialize_lapack():
    """jaxlib's LAPACK kernels look their routines up when a program using them is
    first lowered; a loaded executable is never lowered, and calling its LAPACK
    kernels uninitialized crashes the process. Initialize them as lowering does (with
    SciPy's LAPACK modules loaded by themselves: ``_scipy_lapack_alone``)."""
    try:
        from jax._src.lax import linalg

        with _scipy_lapack_alone():
            linalg.initialize_lapack()
    except Exception:  # noqa: BLE001 - another jax: lower a small LAPACK call instead
        import jax.numpy as jnp

        jax.jit(jnp.linalg.solve).lower(np.eye(2), np.ones(2))


def _load_executable(path: Path):
    """(executable, out treedef) stored at ``path``, or None (absent, damaged, or one
    this jaxlib cannot load: the program is compiled again)."""
    blob = _read(path)
    if blob is None:
        return None
    try:
        from jax.experimental import serialize_executable

        head, out_def, body = _unpack(blob)
        examples, payload = pickle.loads(body)
        lapack, device_ids = head["lapack"], head["devices"]
        in_tree, out_tree = (jtu.tree_structure(e) for e in examples)
        if lapack:
            _initialize_lapack()
        # the devices it was compiled for (jax.jit's default device); left to itself the
        # loader would spread it over every local device and refuse one-device inputs
        by_id = {d.id: d for d in jax.local_devices()}
        exe = serialize_executable.deserialize_and_load(payload, in_tree, out_tree,
                                                        execution_devices=[by_id[i] for i in device_ids])
    except Exception:  # noqa: BLE001
        return None
    STATS["loaded"] += 1
    STATS["executables"] += 1
    # (files stored before the flag existed: any LAPACK call counts as batched)
    return one_at_a_time(exe, head.get("batched_lapack", lapack)), out_def


class _HeldOff:
    """A process-wide on/off setting held off while any thread is inside ``off()``
    (counted, so concurrent users nest) and restored as it was after the last one."""

    def __init__(self, read: Callable[[], bool], write: Callable[[bool], None]):
        self.read, self.write, self.depth, self.saved = read, write, 0, None

    @contextlib.contextmanager
    def off(self):
        with _LOCK:
            self.depth += 1
            if self.depth == 1:
                self.saved = self.read()
                self.write(False)
        try:
            yield
        finally:
            with _LOCK:
                self.depth -= 1
                if self.depth == 0:
                    self.write(self.saved)


_GC = _HeldOff(gc.isenabled, lambda on: gc.enable() if on else gc.disable())


def _gc_paused():
    """Python's cycle collector off while a program is traced: tracing allocates
    millions of short-lived objects, and the full collections they trigger walk every
    live object of the process (JAX's and the user's) again and again. Nothing is
    lost: reference counting frees as usual, and cycles are collected once the
    collector is back on (after the last of concurrent traces)."""
    return _GC.off()


def _export(fn, static, dyn_def, leaves, path: Path):
    box = {}

    def flat(*lv):
        with stored_trace():
            out = fn(*eqx.combine(jtu.tree_unflatten(dyn_def, lv), static))
        out_leaves, box["out_def"] = jtu.tree_flatten(out)
        return out_leaves

    specs = [jax.ShapeDtypeStruct(np.shape(x), x.dtype) for x in leaves]
    try:
        with _gc_paused():
            exported = jax.export.export(jax.jit(flat))(*specs)
    except Exception:  # noqa: BLE001 - the plain path re-raises a user's own error
        STATS["uncacheable"] += 1
        return _FAILED
    if not _portable(box["out_def"]):
        return exported, box["out_def"]  # kept in memory only
    try:
        _store(path, _pack({}, box["out_def"], bytes(exported.serialize())))
        STATS["stored"] += 1
    except (OSError, pickle.PicklingError, TypeError, ImportError):
        pass  # read-only cache: keep it in memory
    return exported, box["out_def"]
