"""Input checks shared by the scenes: clear ValueErrors that name the field."""

from __future__ import annotations

import jax


def positive(name, value, allow_zero=False):
    """Raise ValueError unless ``value`` is > 0 (>= 0 with ``allow_zero``); traced values pass."""
    if isinstance(value, jax.core.Tracer):
        return
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    ok = v >= 0 if allow_zero else v > 0
    if not ok or v != v or v == float("inf"):
        kind = "non-negative" if allow_zero else "positive"
        raise ValueError(f"{name} must be finite and {kind}, got {value}")
