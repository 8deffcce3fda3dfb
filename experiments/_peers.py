"""The experiments' peers: CasADi models in ``benchmarks/peers`` of a source checkout
(casadi itself is the optional ``peers`` extra). Not an experiment (its name starts
with ``_``)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path


def import_peers(*names: str):
    """The modules ``names`` of benchmarks/peers: (modules, "") or (None, why they are
    not available)."""
    here = Path(__file__).resolve().parents[1] / "benchmarks" / "peers"
    if not here.is_dir():
        return None, "the CasADi peer lives in a source checkout (benchmarks/peers)"
    if str(here) not in sys.path:
        sys.path.insert(0, str(here))
    try:
        return [importlib.import_module(name) for name in names], ""
    except ImportError as e:
        return None, f"casadi is not installed ({e}); pip install -e '.[peers]'"
