"""A progress bar over simulated time for ``simulate(progress=True)``.

diffrax's ``TqdmProgressMeter`` shows percent per second; this bar counts
simulated seconds (t0 to t1). It is switched by an array (``show``), so one
compiled program serves calls with and without a bar.
Host side: tqdm (``tqdm.auto``: a widget in notebooks, text in terminals),
updated from the solve through ``jax.experimental.io_callback`` every
``every`` steps.
"""

from __future__ import annotations

import itertools
import threading
from typing import Any

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import io_callback

__all__ = ["SimulatedTimeMeter"]

#: What a bar counting chunks or iterations says until its first count: for a new
#: structure its programs are traced and compiled (or loaded) first (simulate_batch's
#: bar and controls' solver lines).
STARTING = "starting (the first call of a structure compiles its programs)"

_BARS: dict = {}
_LOCK = threading.Lock()
_IDS = itertools.count()


def _open(t0, t1):
    from tqdm.auto import tqdm

    t0, t1 = float(t0), float(t1)
    bar = tqdm(total=t1 - t0, unit="s", desc="nhjax.simulate", leave=True,
               bar_format="{desc}: t = {n:.4g} of {total:.4g} s |{bar}| [{elapsed}<{remaining}]")
    with _LOCK:
        i = next(_IDS)
        _BARS[i] = (bar, t0)
    return np.int32(i)


def _update(i, progress):
    with _LOCK:
        entry = _BARS.get(int(i))
    if entry is not None:
        bar, _ = entry
        bar.n = min(bar.total, float(progress) * bar.total)
        bar.refresh()
    return np.int32(i)


def _close(i, progress):
    with _LOCK:
        entry = _BARS.pop(int(i), None)
    if entry is not None:
        bar, _ = entry
        bar.n = min(bar.total, float(progress) * bar.total)
        bar.close()
    return np.int32(i)


class _State(eqx.Module):
    idx: Any
    step: Any
    progress: Any


class SimulatedTimeMeter(diffrax.AbstractProgressMeter):
    """A tqdm bar over simulated time, shown when ``show`` (a bool array) is True."""

    show: Any
    t0: Any
    t1: Any
    every: int = eqx.field(static=True, default=20)

    def _when(self, pred, fn, *args):
        # nonbatchable: under vmap one bar for the batch, driven by its slowest member
        pred = eqxi.nonbatchable(eqxi.unvmap_any(pred))
        return jax.lax.cond(pred, lambda: io_callback(fn, jax.ShapeDtypeStruct((), jnp.int32), *args),
                            lambda: jnp.asarray(args[0], jnp.int32) if fn is not _open else jnp.int32(-1))

    def init(self) -> _State:
        idx = self._when(self.show, _open, self.t0, self.t1)
        return _State(idx=idx, step=jnp.array(0), progress=jnp.array(0.0))

    def step(self, state: _State, progress) -> _State:
        progress = eqxi.unvmap_min(progress) if hasattr(eqxi, "unvmap_min") else -eqxi.unvmap_max(-progress)
        due = self.show & (state.step % self.every == 0)
        idx = self._when(due, _update, state.idx, progress)
        return _State(idx=idx, step=state.step + 1, progress=progress)

    def close(self, state: _State):
        self._when(self.show, _close, state.idx, state.progress)
