r"""Free motion of two bodies joined by a nonholonomic hinge (generalized Suslov problem).

Seed 003 (Bizyaev, Borisov & Mamaev, Regul. Chaotic Dyn. 19 (2014) 198–213),
section 3, eqs. (3.1)–(3.8).

Model
-----
A balanced bundle in free space (its centre of mass C moves uniformly and is
taken at rest): an outer body with spherical inertia ``Is`` E [kg m^2] and an
inner body with inertia tensor ``inertia`` [kg m^2] (3x3 symmetric positive
definite, about C, in the inner body's axes; 3 numbers = principal moments),
both turning about C. The nonholonomic hinge forbids relative rotation about
the axis e = e3 fixed in the inner body (Suslov's constraint):

    f0 = Omega3 - omega3 = 0,

omega, Omega the angular velocities of the inner and outer bodies, both in the
inner body's axes; D a = a' + omega x a.

Equations (3.3), re-derived from Euler's equations with the hinge reaction
torques +lambda e (outer body) and -lambda e (inner body):

    Omega' = Omega x omega + (lambda / Is) e,
    omega' = I^{-1} (I omega x omega - lambda e),
    lambda = (I^{-1}(I omega x omega) - Omega x omega, e) / (1/Is + (I^{-1} e, e))

(the seed writes the multiplier with the opposite sign convention). The total
angular momentum (3.4) M = Is Omega + I omega obeys M' = M x omega (fixed in
space); the kinetic energy (3.2) T = 1/2 Is Omega^2 + 1/2 (omega, I omega) is
conserved on the constraint.

Principal case (I = diag(I1, I2, I3), e a principal axis), (3.5): in
x5 = (Omega1, Omega2, omega1, omega2, omega3), Omega3 = omega3,

    Omega1' = omega3 (Omega2 - omega2),   Omega2' = -omega3 (Omega1 - omega1),
    omega1' = -b omega2 omega3,           omega2' = a omega1 omega3,
    omega3' = [(1 - ab)(Omega1 omega2 - Omega2 omega1) - c (a - b) omega1 omega2]
              / ((1 - ab)(1 + c)),
    a = (I3 - I1)/I2,   b = (I3 - I2)/I1,   c = I3/Is

(re-derived; the extraction loses the fraction bars and some signs). Note
(a - b)/(1 - ab) = (I2 - I1)/I3, regular also for a flat body (1 - ab = 0).
Extra integral (3.6): F2 = a omega1^2 + b omega2^2 (= -F4/(I1 I2) of sec. 2).
Hamiltonian (3.7):

    H = 1/2 (Omega1^2 + Omega2^2)/(1 + c)
        + 1/2 c ((1 - a) omega1^2 + (1 - b) omega2^2) / ((1 - ab)(1 + c)) + 1/2 omega3^2
      = T / (Is + I3)

(c (1 - a)/((1 - ab)(1 + c)) = I1/(Is + I3); ``hamiltonian`` uses the regular
form). Lie–Poisson bracket (3.8) of rank 2:
{Omega1, omega3} = Omega2 - omega2, {Omega2, omega3} = -(Omega1 - omega1),
{omega1, omega3} = -b omega2, {omega2, omega3} = a omega1 (``poisson_tensor``),
so that x5' = J(x5) grad H. Its global Casimirs are C1 = F2 and
C2 = (1 - ab)(Omega1^2 + Omega2^2) + omega1^2 + omega2^2 - 2 (1 - a) Omega1 omega1
- 2 (1 - b) Omega2 omega2 (the seed's C2 divided by (1 - ab); re-derived from
{C2, omega3} = 0), both first integrals of (3.5).

Reconstruction (remark after (3.4)): the space axes in body components obey
alpha' = alpha x omega, beta' = beta x omega, gamma' = gamma x omega.

State of ``SuslovBundle`` (15 components):

    x = (omega(3) [rad/s], Omega(3) [rad/s], gamma(3), alpha(3), beta(3))

(gamma is the space axis Oz; there is no gravity in this problem).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _programs
from .. import _validate as V
from ..mechanics import AbstractSystem
from .shell_with_top import (
    _is_concrete,
    as_matrix,
    attitude_value,
    frame_residual,
    project_frame,
)

__all__ = ["SuslovBundle"]

E3 = np.array([0.0, 0.0, 1.0])  # numpy: no program to compile at import


class SuslovBundle(AbstractSystem):
    """Two bodies on a nonholonomic hinge in free space, (3.3); the principal case
    (3.5)-(3.8) adds F2 (3.6), H (3.7) and the Casimir C2 to the invariants.
    Defaults: Is = 0.02 kg m^2, inertia = diag(0.01, 0.015, 0.02) kg m^2.
    See the module docstring."""

    Is: jax.Array
    inertia: jax.Array
    principal: bool = eqx.field(static=True, default=False)

    state_names: ClassVar[tuple] = (
        "omega1", "omega2", "omega3",
        "Omega1", "Omega2", "Omega3",
        "gamma1", "gamma2", "gamma3",
        "alpha1", "alpha2", "alpha3",
        "beta1", "beta2", "beta3",
    )  # fmt: skip
    control_dim: ClassVar[int] = 0

    def __init__(self, Is=0.02, inertia=(0.01, 0.015, 0.02)):
        self.Is = V.positive("Is", Is, owner="SuslovBundle", what="moment of inertia of the outer body [kg m^2]")
        self.inertia = V.inertia_tensor("inertia", inertia, owner="SuslovBundle")
        principal = False
        if _is_concrete(self.inertia):
            a = np.asarray(self.inertia)
            principal = bool(np.abs(a - np.diag(np.diag(a))).max() <= 1e-14 * np.abs(a).max())
        self.principal = principal

    @staticmethod
    def split(x):
        """(omega, Omega, gamma, alpha, beta)."""
        return x[0:3], x[3:6], x[6:9], x[9:12], x[12:15]

    # ------------------------------------------------------------ dynamics (3.3)
    def hinge_torque(self, x):
        """lambda [N m]: torque +lambda e on the outer body, -lambda e on the inner one."""
        om, Om, *_ = self.split(x)
        I = self.inertia
        Iinv_e = jnp.linalg.solve(I, E3)
        free = jnp.linalg.solve(I, jnp.cross(I @ om, om))
        return (free - jnp.cross(Om, om))[2] / (1.0 / self.Is + Iinv_e[2])

    def vector_field(self, t, x, u):
        om, Om, ga, al, be = self.split(x)
        lam = self.hinge_torque(x)
        I = self.inertia
        dom = jnp.linalg.solve(I, jnp.cross(I @ om, om) - lam * E3)
        dOm = jnp.cross(Om, om) + lam / self.Is * E3
        return jnp.concatenate([dom, dOm, jnp.cross(ga, om), jnp.cross(al, om), jnp.cross(be, om)])

    # ------------------------------------------------------------ principal case
    @property
    def abc(self):
        """(a, b, c) of (3.5): a = (I3 - I1)/I2, b = (I3 - I2)/I1, c = I3/Is."""
        I1, I2, I3 = jnp.diag(self.inertia)
        return (I3 - I1) / I2, (I3 - I2) / I1, I3 / self.Is

    @staticmethod
    def principal_coordinates(x):
        """x5 = (Omega1, Omega2, omega1, omega2, omega3), the variables of (3.5)."""
        return jnp.stack([x[3], x[4], x[0], x[1], x[2]])

    def principal_vector_field(self, x5):
        """(3.5) in x5 (principal case; a, b, c form, with (a - b)/(1 - ab) = (I2 - I1)/I3)."""
        O1, O2, w1, w2, w3 = x5
        a, b, c = self.abc
        I1, I2, I3 = jnp.diag(self.inertia)
        ratio = (I2 - I1) / I3  # = (a - b)/(1 - ab)
        return jnp.stack(
            [
                w3 * (O2 - w2),
                -w3 * (O1 - w1),
                -b * w2 * w3,
                a * w1 * w3,
                ((O1 * w2 - O2 * w1) - c * ratio * w1 * w2) / (1 + c),
            ]
        )

    def hamiltonian5(self, x5):
        """H of (3.7) in x5 (= T / (Is + I3)) [1/s^2]."""
        O1, O2, w1, w2, w3 = x5
        I1, I2, I3 = jnp.diag(self.inertia)
        c = I3 / self.Is
        return 0.5 * (O1**2 + O2**2) / (1 + c) + 0.5 * (I1 * w1**2 + I2 * w2**2) / (self.Is + I3) + 0.5 * w3**2

    def poisson_tensor(self, x5):
        """The Lie–Poisson tensor (3.8) at x5 (rank 2)."""
        O1, O2, w1, w2, _ = x5
        a, b, _ = self.abc
        col = jnp.stack([O2 - w2, -(O1 - w1), -b * w2, a * w1])  # {x_i, omega3}
        J = jnp.zeros((5, 5), x5.dtype)
        J = J.at[:4, 4].set(col)
        return J.at[4, :4].set(-col)

    def F2(self, x):
        """a omega1^2 + b omega2^2 (3.6) [1/s^2] (principal case)."""
        a, b, _ = self.abc
        return a * x[0] ** 2 + b * x[1] ** 2

    def hamiltonian(self, x):
        """H (3.7) [1/s^2] (principal case)."""
        return self.hamiltonian5(self.principal_coordinates(x))

    def casimir_C2(self, x):
        """(1 - ab)(Omega1^2 + Omega2^2) + omega1^2 + omega2^2 - 2(1-a) Omega1 omega1
        - 2(1-b) Omega2 omega2 [1/s^2] (principal case)."""
        a, b, _ = self.abc
        w1, w2, O1, O2 = x[0], x[1], x[3], x[4]
        return (1 - a * b) * (O1**2 + O2**2) + w1**2 + w2**2 - 2 * (1 - a) * O1 * w1 - 2 * (1 - b) * O2 * w2

    # ------------------------------------------------------------ integrals
    def angular_momentum(self, x):
        """M = Is Omega + I omega (3.4), inner body axes [kg m^2/s]."""
        om, Om, *_ = self.split(x)
        return self.Is * Om + self.inertia @ om

    def angular_momentum_space(self, x):
        _, _, ga, al, be = self.split(x)
        M = self.angular_momentum(x)
        return jnp.stack([M @ al, M @ be, M @ ga])

    def energy(self, x):
        """T (3.2) [J]."""
        om, Om, *_ = self.split(x)
        return 0.5 * self.Is * Om @ Om + 0.5 * om @ self.inertia @ om

    def invariants(self, x):
        om, Om, *_ = self.split(x)
        M = self.angular_momentum(x)
        Ms = self.angular_momentum_space(x)
        out = {
            "F0_suslov": Om[2] - om[2],
            "F1_M_sq": M @ M,
            "M_x": Ms[0],
            "M_y": Ms[1],
            "M_z": Ms[2],
        }
        if self.principal:
            out["F2"] = self.F2(x)
            out["H"] = self.hamiltonian(x)
            out["C2"] = self.casimir_C2(x)
        return out

    def constraints(self, t, x):
        om, Om, ga, al, be = self.split(x)
        return {"suslov": (Om[2] - om[2])[None], "frame": frame_residual(ga, al, be)}

    def project(self, t, x):
        """Orthonormalize the frame; Omega3 = omega3 := (Is Omega3 + I33 omega3)/(Is + I33)."""
        om, Om, ga, al, be = self.split(x)
        ga, al, be = project_frame(ga, al, be)
        I33 = self.inertia[2, 2]
        s = (self.Is * Om[2] + I33 * om[2]) / (self.Is + I33)
        return jnp.concatenate([om.at[2].set(s), Om.at[2].set(s), ga, al, be])

    def initial_state(self, omega, Omega12=(0.0, 0.0), attitude=None):
        """omega: inner body's angular velocity [rad/s] (its axes); Omega12: the
        outer body's angular velocity along e1, e2 [rad/s] (Omega3 = omega3 by the
        hinge); attitude: inner body -> space (None, rotation vector or matrix)."""
        owner = "SuslovBundle.initial_state"
        a = attitude_value(attitude, owner=owner)
        om = V.vector("omega", omega, 3, owner=owner, what="inner body's angular velocity [rad/s]")
        O12 = V.vector("Omega12", Omega12, 2, owner=owner, what="outer body's angular velocity along e1, e2 [rad/s]")
        # concrete numbers: one compiled program instead of eager operations
        return _programs.small_call("SuslovBundle.initial_state", _bundle_state, self, a, om, O12)


def _bundle_state(system, attitude, om, O12):
    """``SuslovBundle.initial_state``'s state from its checked numbers (Omega3 = omega3
    by the hinge)."""
    R = as_matrix(attitude)
    Om = jnp.stack([O12[0], O12[1], om[2]])
    return jnp.concatenate([om, Om, R[2], R[0], R[1]])
