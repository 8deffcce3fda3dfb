"""Input checks shared by the scenes: the checks of ``nhjax._validate`` (the one
validation layer), re-exported under the names the scene modules use."""

from __future__ import annotations

from .._validate import (  # noqa: F401
    GROUP_TOL,
    axisymmetric_moments,
    ball_moment,
    chart_argument,
    choice,
    function,
    in_range,
    inertia_tensor,
    integer,
    on_host,
    positive,
    principal_moments,
    real,
    rotation,
    to_device,
    unit_quaternion,
    vector,
)
