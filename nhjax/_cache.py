"""JAX's persistent compilation cache, on by default for nhjax.

A first ``simulate()`` of a scene compiles XLA programs for seconds; a second
process (a notebook re-run, a script run again) loads them from disk instead.
``import nhjax`` points JAX's cache at a user cache directory unless the user
configured one already:

* ``NHJAX_CACHE_DIR=/some/dir`` puts it elsewhere;
* ``NHJAX_CACHE_DIR=0`` (or ``off``) leaves JAX's cache off;
* default: ``$XDG_CACHE_HOME/nhjax/xla`` (``~/.cache/nhjax/xla``).

Every program is kept, however fast it compiled (``NHJAX_CACHE_MIN_SECONDS``,
default 0: JAX's default of 1 s would skip most of a solve's programs, and even the
tiny programs of eager jax operations between compiled solves -- an optimizer's
bookkeeping runs a hundred of them -- load from disk faster than they compile), and
the directory is capped at ``NHJAX_CACHE_MAX_BYTES`` (default 2 GiB; JAX evicts the
least recently used entries). JAX keys each entry by the program, the compiler
options and flags and the jax/jaxlib versions, so a stale entry is never used.
What this cache cannot keep is tracing and lowering, which every new process would
do again: nhjax keeps its traced programs beside it (``_programs.py``).

The directory is trusted like code (JAX loads executables from it): it is created
0700, and one that another user owns or that group/others can write is refused with a
warning (both caches stay off).
"""

from __future__ import annotations

import os

import jax

DEFAULT_MIN_SECONDS = 0.0
DEFAULT_MAX_BYTES = 2 * 2**30


def default_dir(environ=os.environ) -> str:
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "nhjax", "xla")


def own(path: str) -> bool:
    """Whether ``path`` is this user's and only this user can write it (the test for a
    cache directory, here and for each file's directory in ``nhjax._programs``)."""
    if not hasattr(os, "getuid"):
        return True
    st = os.stat(path)
    return st.st_uid == os.getuid() and not st.st_mode & 0o022


def configure(environ=os.environ) -> str | None:
    """Turn JAX's persistent cache on (see the module docstring). Returns the directory
    in use, or None when it is off."""
    raw = environ.get("NHJAX_CACHE_DIR", "").strip()
    if raw.lower() in ("0", "off", "false", "no"):
        return None
    current = jax.config.jax_compilation_cache_dir
    if current:  # the user's own choice stands
        return current
    path = raw or default_dir(environ)
    try:
        os.makedirs(path, exist_ok=True, mode=0o700)
    except OSError:  # read-only home, say: no cache rather than no nhjax
        return None
    if not own(path):
        import warnings

        warnings.warn(f"nhjax: the cache directory {path} belongs to another user or is writable by "
                      "group/others; JAX's compilation cache and nhjax's programs stay off (the cache "
                      "directory is trusted like code: point NHJAX_CACHE_DIR at a directory of your own)",
                      RuntimeWarning, stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    min_s = float(environ.get("NHJAX_CACHE_MIN_SECONDS", DEFAULT_MIN_SECONDS))
    if jax.config.jax_persistent_cache_min_compile_time_secs == 1.0:  # JAX's default
        jax.config.update("jax_persistent_cache_min_compile_time_secs", min_s)
    if jax.config.jax_compilation_cache_max_size == -1:
        jax.config.update("jax_compilation_cache_max_size", int(environ.get("NHJAX_CACHE_MAX_BYTES", DEFAULT_MAX_BYTES)))
    return path
