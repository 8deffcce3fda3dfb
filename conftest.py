"""Set-up for every test the default run collects: tests/, notebooks/ (nbmake) and the
Python blocks of README.md and docs/ (pytest-markdown-docs)."""

import os
import tempfile

# The tests check results, not speed, and most of their time is XLA compiling programs
# that run once: LLVM's cheaper pipeline (no optimization passes) and XLA's older loop
# emitters instead of its fusion emitters (what nhjax already compiles its eager solves
# and quick programs with: _programs.SOLVE_OPTIONS, QUICK_OPTIONS) take much less CPU
# for the same programs. The arithmetic is the same up to the last bits (e.g. where the
# optimized build fuses a multiply-add). Set before JAX starts its backend (it reads
# XLA_FLAGS once); subprocesses and notebook kernels inherit it. Settings already in
# XLA_FLAGS are kept.
_TEST_FLAGS = {"xla_backend_optimization_level": "0", "xla_llvm_disable_expensive_passes": "true",
               "xla_cpu_use_fusion_emitters": "false"}
_flags = os.environ.get("XLA_FLAGS", "")
os.environ["XLA_FLAGS"] = " ".join([_flags] + [f"--{k}={v}" for k, v in _TEST_FLAGS.items() if k not in _flags]).strip()

import jax
import pytest

import nhjax  # noqa: F401  (switches float64 on)

# Many tests compile the same XLA programs through different Python callables; a
# persistent cache lets the second one load instead of compiling. One directory for
# both pytest-xdist workers, so that a program one worker stored (nhjax's program
# cache, under this directory) is loaded by the other: nhjax writes its entries
# atomically (a temporary file, then a rename); JAX's own entries are written in
# place, and a half-written one that the other worker reads is a warning and a compile.
jax.config.update("jax_compilation_cache_dir", os.path.join(tempfile.gettempdir(), "nhjax-test-xla-cache"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


@pytest.hookimpl(wrapper=True)
def pytest_collect_file(file_path, parent):
    """pytest-markdown-docs runs the Python blocks of Markdown files; it would also import
    every Python file under the test paths to look for blocks in their docstrings (there
    are none: the docstrings are not Markdown pages), which costs seconds per worker."""
    collectors = yield
    if file_path.suffix == ".py":
        collectors = [c for c in collectors if type(c).__name__ != "MarkdownDocstringCodeModule"]
    return collectors
