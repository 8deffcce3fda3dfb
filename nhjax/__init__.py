"""nhjax: geometric and nonholonomic mechanics in JAX.

Simulate constrained mechanical systems (Lagrangians with Pfaffian
constraints, rigid bodies on Lie groups), differentiate through the
simulations, and hand them to the optimal-control package ``controls``.

float64 is switched on here, once, for the whole process: every result nhjax
reports assumes it. So is XLA's compilation of small while loops as one function
(``_xla_flags.py``: a small system's time-stepping loop runs as one function
instead of launching its kernels one by one; import nhjax before the first JAX
computation for it to apply), and JAX's persistent
compilation cache in a user cache directory (``_cache.py``; ``NHJAX_CACHE_DIR``
moves it, ``NHJAX_CACHE_DIR=0`` turns it off).
"""

import jax as _jax

from . import _cache, _xla_flags

_xla_flags.configure()
_jax.config.update("jax_enable_x64", True)
_cache.configure()

from . import lie, mechanics, scenes  # noqa: E402
from .errors import (  # noqa: E402
    BoundaryError,
    ChartSingularityError,
    ConstraintViolationError,
    ControlError,
    GroupMembershipError,
    IntegrationError,
    NhjaxError,
    OutsideChartError,
    ParameterError,
    ProblemError,
    ProjectionError,
    RegularityError,
    ResourceError,
    StateError,
    SystemKindError,
    TimeSpanError,
)
from .integrate import (  # noqa: E402
    BatchError,
    BatchTrajectory,
    DiscreteAdjoint,
    ImpactBatchTrajectory,
    ImpactTrajectory,
    RKMK4,
    RKMK45,
    RKMK87,
    PiecewiseConstant,
    PiecewiseLinear,
    Sinusoids,
    Trajectory,
    simulate,
    simulate_batch,
    simulate_impacts,
    simulate_impacts_batch,
    stack,
)

__all__ = [
    "BatchError",
    "BatchTrajectory",
    "BoundaryError",
    "DiscreteAdjoint",
    "ChartSingularityError",
    "ConstraintViolationError",
    "ControlError",
    "GroupMembershipError",
    "ImpactBatchTrajectory",
    "ImpactTrajectory",
    "IntegrationError",
    "NhjaxError",
    "OutsideChartError",
    "ParameterError",
    "ProblemError",
    "ProjectionError",
    "ResourceError",
    "StateError",
    "SystemKindError",
    "TimeSpanError",
    "PiecewiseConstant",
    "PiecewiseLinear",
    "RegularityError",
    "RKMK4",
    "RKMK45",
    "RKMK87",
    "Sinusoids",
    "Trajectory",
    "lie",
    "mechanics",
    "scenes",
    "simulate",
    "simulate_batch",
    "simulate_impacts",
    "simulate_impacts_batch",
    "stack",
]
__version__ = "0.1.0"
