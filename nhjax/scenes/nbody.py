r"""n point masses with vanishing angular momentum (seed 000, secs. 2-5).

Seed 000 (T. Iwai, *Geometric mechanics of many-body systems*, J. Comput.
Appl. Math. 140 (2002) 403-422), secs. 2-5: the centre-of-mass system of n
particles is a principal SO(3) bundle over the shape space (Prop. 1; collinear
configurations excluded, (2.3)); a local section q -> rho(q) (3.1) places a
shape in space, x = g rho(q) (3.2). With the inertia operator (3.9)
A_x(a) = sum m x x (a x x) and the vectors (3.10) m_i = sum m rho x d rho/dq^i,
vanishing total angular momentum is the connection (3.11)-(3.15)

    g^-1 g' = -R(A^-1 m_i) q'^i       (3.13, u^i = q'^i),

the metric splits into a rotational and a vibrational part (4.5), the latter

    a_ij = sum m (d rho/dq^i - A^-1 m_i x rho) . (d rho/dq^j - A^-1 m_j x rho)   (4.7),

and the optimal Hamiltonian of the velocity-controlled system with cost (4.8)
is H = a^ij P_i P_j / 2 (4.12). Lagrange's equations with torques on the shape
(5.23) are the torque-driven reduced dynamics.

``NBodyCat`` is a ``nhjax.mechanics.reduction.ReducedSystem`` (group SO(3), or
SO(2) for ``planar=True``, seed 000 end of sec. 3): the general construction by
autodiff; ``inertia_operator`` and ``m_vectors`` are the seed's (3.9)/(3.10)
written out, against which the tests hold the general connection and metric.
``ThreeBodyCat`` is the three-body example: Jacobi vectors (2.6)

    r = sqrt(m1 m2/(m1+m2)) (x2 - x1),
    s = sqrt(m3 (m1+m2)/M) (x3 - (m1 x1 + m2 x2)/(m1+m2)),

shape coordinates (2.7) w = (|r|^2 - |s|^2, 2 r.s, 2 |r x s|) (in the plane:
2 (r x s), signed), and the section r = |r| e1, s = (w2, w3)/(2|r|) in the
e1-e2 plane, |r|^2 = (|w| + w1)/2. In the plane the reduced metric is exactly
|dw|^2/(4|w|) (the Hopf map of C^2 = (r, s) onto R^3); the tests check it.

Units: masses [kg], positions [m], shape coordinates as the shape map defines
them (w: kg m^2), torques dual to the shape coordinates.
Chart: the Jacobi section is singular where r = 0 (particles 1 and 2 coincide):
guard ``jacobi_chart`` = |r|^2/|w| - eps. In space, collinear triangles (w3 = 0,
the boundary of the shape space R^3_+) are where SO(3) stops acting freely; the
guard ``collinear`` = w3/|w| - eps changes sign there, so a path through a
collinear shape is stopped even within one step (the ``locked_inertia`` guard of
every spatial ``ReducedSystem`` only touches zero there, quadratically in w3, and
stops paths that approach or end near the degenerate set).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ParameterError
from ..mechanics.reduction import _LOCKED_HINT, SO2, SO3, Bodies, ReducedSystem
from ._validate import function, in_range, integer, positive

__all__ = ["JacobiSection", "NBodyCat", "ThreeBodyCat"]


_JACOBI_HINT = (
    "the Jacobi section (2.6)-(2.7) places r along e1 and is singular where r = 0 "
    "(particles 1 and 2 coincide, w on the negative w1 axis); the shape space itself is smooth "
    "there: relabel the particles so that another pair stays apart, or lower chart_eps.")


class NBodyCat(ReducedSystem):
    """n point masses, reduced by rotations about their centre of mass.

    Parameters: ``masses`` (n,) [kg], each > 0 (n >= 3 in space, n >= 2 in the plane);
    ``shape_map(q)`` -> positions (n, 3) (or (n, 2) with ``planar=True``) [m] of the
    particles for shape q (the centre of mass is removed automatically); ``shape_dim``
    (required with a ``shape_map``); ``momentum`` "zero" (default; seed 000) or
    "spatial"/"body"; inputs: generalized forces on the shape coordinates.

    Defaults: the seed's three-body example, three unit masses [kg] placed by the
    Jacobi section (2.6)-(2.7) (``JacobiSection``, shape w = (w1, w2, w3), with its
    chart guards ``jacobi_chart`` and, in space, ``collinear`` at margin 1e-6), as
    ``ThreeBodyCat``; ``masses`` alone may then be any three positive masses. Any
    other n needs its own ``shape_map`` and ``shape_dim``.
    """

    guard_hints: ClassVar[dict] = {"locked_inertia": _LOCKED_HINT, "collinear": _LOCKED_HINT,
                                   "jacobi_chart": _JACOBI_HINT}
    guard_arguments: ClassVar[dict] = {"locked_inertia": "shape", "collinear": "shape", "jacobi_chart": "shape"}

    def __init__(self, masses=(1.0, 1.0, 1.0), shape_map: Callable | None = None, shape_dim=None, *,
                 planar=False, momentum="zero", shape_names=None, chart_guard=None, guard_eps=1e-6):
        owner = type(self).__name__
        m = positive("masses", masses, owner=owner, what="masses of the particles [kg]")
        least = 2 if planar else 3
        if m.ndim != 1 or m.shape[0] < least:
            raise ParameterError(
                f"{owner}: masses must be a 1-D array of at least {least} masses [kg] ({'in the plane' if planar else 'in space'}: "
                f"fewer particles are always collinear, where rotations do not act freely), got shape {m.shape}",
                "masses", masses)
        function("shape_map", shape_map, owner=owner, signature="q -> positions (n, 3) or (n, 2)", optional=True)
        if shape_map is None:
            if m.shape[0] != 3:
                raise ParameterError(
                    f"{owner}: {m.shape[0]} masses need a shape_map (and shape_dim); the default shape map "
                    "is the three-body Jacobi section", "shape_map", shape_map)
            if shape_dim is not None and integer("shape_dim", shape_dim, owner=owner) != 3:
                raise ParameterError(f"{owner}: the default (Jacobi) shape map has shape_dim 3, got {shape_dim!r}",
                                     "shape_dim", shape_dim)
            shape_map, shape_dim = JacobiSection(m, planar), 3
            shape_names = ("w1", "w2", "w3") if shape_names is None else shape_names
            chart_guard = _JacobiChart(1e-6, planar) if chart_guard is None else chart_guard
        elif shape_dim is None:
            raise ParameterError(f"{owner}: with a shape_map, give shape_dim (the number of shape coordinates)",
                                 "shape_dim", shape_dim)
        bodies = Bodies.point_masses(m, spatial=not planar)
        self._setup(bodies, shape_map, SO2() if planar else SO3(), shape_dim, momentum=momentum,
                    shape_names=shape_names, chart_guard=chart_guard, guard_eps=guard_eps)

    # ---------------------------------------------------------------- seed's formulas
    def inertia_operator(self, q):
        """(3.9): A(a) = sum m rho x (a x rho), as a 3x3 matrix (spatial only)."""
        rho = self.reference_poses(q)[1]
        m = self.bodies.masses
        return jnp.einsum("n,ij->ij", m * jnp.sum(rho * rho, -1), jnp.eye(3)) - jnp.einsum("n,ni,nj->ij", m, rho, rho)

    def m_vectors(self, q):
        """(3.10): m_i = sum m rho x d rho/dq^i, as columns (3, k) (spatial only)."""
        rho = self.reference_poses(q)[1]
        drho = jax.jacfwd(lambda qq: self.reference_poses(qq)[1])(q)  # (n, 3, k)
        return jnp.einsum("n,nik->ik", self.bodies.masses, jnp.cross(rho[:, :, None], drho, axisa=1, axisb=1, axisc=1))

    def seed_vibrational_metric(self, q):
        """(4.7) written out: a_ij from the vibrational displacements (spatial only)."""
        rho = self.reference_poses(q)[1]
        drho = jax.jacfwd(lambda qq: self.reference_poses(qq)[1])(q)  # (n, 3, k)
        om = jnp.linalg.solve(self.inertia_operator(q), self.m_vectors(q))  # (3, k): A^-1 m_i
        vib = drho - jnp.cross(om.T[None, :, :], rho[:, None, :], axis=-1).transpose(0, 2, 1)
        return jnp.einsum("n,nik,nil->kl", self.bodies.masses, vib, vib)

    def angular_momentum_3d(self, x):
        """Total angular momentum sum m x x x' of the reconstructed particles in space."""
        return self.momentum_map(x)


class JacobiSection(eqx.Module):
    """Section (2.6)-(2.7) of the three-body problem: shape w -> particle positions."""

    masses: jax.Array
    planar: bool = eqx.field(static=True, default=False)

    def __call__(self, w):
        m1, m2, m3 = self.masses[0], self.masses[1], self.masses[2]
        M = m1 + m2 + m3
        n = jnp.sqrt(w @ w)
        rr = jnp.sqrt(0.5 * (n + w[0]))
        r = jnp.stack([rr, jnp.zeros_like(rr)])
        s = jnp.stack([w[1], w[2]]) / (2 * rr)
        mu1 = jnp.sqrt(m1 * m2 / (m1 + m2))
        mu2 = jnp.sqrt(m3 * (m1 + m2) / M)
        c12 = -m3 / M * s / mu2
        x1 = c12 - m2 / (m1 + m2) * r / mu1
        x2 = c12 + m1 / (m1 + m2) * r / mu1
        x3 = (m1 + m2) / M * s / mu2
        pos = jnp.stack([x1, x2, x3])
        if self.planar:
            return pos
        return jnp.concatenate([pos, jnp.zeros((3, 1), pos.dtype)], 1)


class _JacobiChart(eqx.Module):
    eps: float = eqx.field(static=True)
    planar: bool = eqx.field(static=True, default=False)

    def __call__(self, w):
        n = jnp.sqrt(w @ w)
        out = {"jacobi_chart": 0.5 * (n + w[0]) / n - self.eps}
        if not self.planar:
            out["collinear"] = w[2] / n - self.eps
        return out


class ThreeBodyCat(NBodyCat):
    """Three point masses, shape w = (w1, w2, w3) of (2.7), zero angular momentum.

    In space (default) w3 = 2|r x s| > 0 (w3 -> 0: collinear, the bundle degenerates);
    ``planar=True``: in the plane, rotations SO(2), w3 = 2 r x s of either sign.
    """

    def __init__(self, masses=(1.0, 1.0, 1.0), *, planar=False, momentum="zero", chart_eps=1e-6,
                 guard_eps=1e-6):
        m = positive("masses", masses, owner="ThreeBodyCat", shape=(3,), what="masses of the three particles [kg]")
        chart_eps = in_range("chart_eps", chart_eps, 0.0, 1.0, hi_closed=False, owner="ThreeBodyCat", shape=(),
                             as_float=True, what="margin of the jacobi_chart and collinear guards")
        NBodyCat.__init__(self, m, JacobiSection(m, planar), 3, planar=planar, momentum=momentum,
                          shape_names=("w1", "w2", "w3"), chart_guard=_JacobiChart(float(chart_eps), planar),
                          guard_eps=guard_eps)

    @staticmethod
    def shape_of(positions, masses):
        """w (2.7) of particle positions (3, 3) [or (3, 2)], via the Jacobi vectors (2.6)."""
        x = jnp.asarray(positions, float)
        m1, m2, m3 = masses
        M = m1 + m2 + m3
        r = np.sqrt(m1 * m2 / (m1 + m2)) * (x[1] - x[0])
        s = np.sqrt(m3 * (m1 + m2) / M) * (x[2] - (m1 * x[0] + m2 * x[1]) / (m1 + m2))
        if x.shape[1] == 2:
            w3 = 2 * (r[0] * s[1] - r[1] * s[0])
        else:
            w3 = 2 * jnp.linalg.norm(jnp.cross(r, s))
        return jnp.stack([r @ r - s @ s, 2 * r @ s, w3])
