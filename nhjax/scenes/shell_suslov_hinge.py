r"""A spherical shell rolling on a plane with a body inside on a nonholonomic hinge.

Seed 003 (Bizyaev, Borisov & Mamaev, Regul. Chaotic Dyn. 19 (2014) 198–213),
section 2, eqs. (2.1)–(2.9).

Model
-----
* Shell: homogeneous spherical shell, mass ``ms`` [kg], central inertia
  ``Is`` E [kg m^2] (default 2/3 ms Rs^2), radius ``Rs`` [m], rolling without
  slipping on a horizontal plane.
* Inner body: mass ``mt`` [kg], principal moments ``inertia`` = (I1, I2, I3)
  [kg m^2]; its centre of mass coincides with the shell's centre C (so gravity
  does no work and does not enter). It is held by sharp wheels (Vagner's
  "nonholonomic hinge") that forbid relative rotation about the axis e fixed in
  the body, e = e3 (a principal axis, as in the seed):

      (2.1)/(2.2)  (Omega - omega, e) = Omega3 - omega3 = 0,   V = Rs Omega x gamma.

Only the total mass m = ms + mt enters the dynamics.

Vectors are in the inner body's principal axes: omega (body), Omega (shell)
angular velocities, V velocity of C, gamma upward vertical, alpha, beta the
space axes Ox, Oy; D a = a' + omega x a.

Re-derivation. With N the contact force and lambda e, -lambda e the hinge's
reaction torques on the shell and on the body,

    m DV = N,   Is DOmega = -Rs gamma x N + lambda e,   I omega' + omega x I omega = -lambda e.

Eliminating N with DV = Rs DOmega x gamma gives (2.4):

    II DOmega = lambda e,   II = (Is + m Rs^2) E - m Rs^2 gamma gamma^T,
    I omega' = I omega x omega - lambda e,   gamma' = gamma x omega,
    lambda = Is (Is + m Rs^2) ((I1 - I2) omega1 omega2 + I3 (omega1 Omega2 - omega2 Omega1))
             / (Is (Is + m Rs^2 + I3) + m Rs^2 I3 gamma3^2)

(lambda from d/dt (Omega3 - omega3) = 0 with II^{-1} = (E + m Rs^2/Is gamma gamma^T)
/ (Is + m Rs^2); the seed's sign of lambda is the opposite convention, and its
(II Omega)' = (II Omega) x omega - lambda e is the same equation since D gamma = 0).
The angular momentum about the contact point (2.5), M = II Omega + I omega,
obeys M' = M x omega: it is fixed in space.

Integrals (2.6)-(2.7): F0 = gamma^2 = 1, F1 = Omega3 - omega3 = 0, F2 = M^2,
F3 = (M, gamma), F4 = I1 (I1 - I3) omega1^2 + I2 (I2 - I3) omega2^2, and the energy
E = 1/2 (Omega, II Omega) + 1/2 (omega, I omega) (the kinetic energy
1/2 m V^2 + 1/2 Is Omega^2 + 1/2 (omega, I omega) with V = Rs Omega x gamma).
M's space components (M, alpha), (M, beta) are invariants too.

Invariant measure (2.8): rho d^3Omega d^3omega d^3gamma with
rho = (Is (Is + m Rs^2 + I3) + m Rs^2 I3 gamma3^2)^(1/2) = Delta^(1/2), as in the
seed (``invariant_measure_density``; the tests check div(rho f) = 0 by autodiff,
also off the hinge constraint).

Reconstruction: alpha' = alpha x omega, beta' = beta x omega, and the contact
point follows the centre, x' = (V, alpha), y' = (V, beta).

State of ``ShellWithSuslovHinge`` (17 components), same layout as
``ShellWithTopReduced``:

    x = (omega(3) [rad/s], Omega(3) [rad/s], gamma(3), alpha(3), beta(3), x, y [m])

Zero angular momentum (sec. 2.4, (2.9)): with M = 0, Omega = -II^{-1} I omega, and
the constraint Omega3 = omega3 gives omega3 = -m Rs^2 gamma3 (I1 omega1 gamma1 +
I2 omega2 gamma2) / Delta, Delta = Is (Is + m Rs^2 + I3) + m Rs^2 I3 gamma3^2;
then I1 omega1' = (I2 - I3) omega2 omega3, I2 omega2' = (I3 - I1) omega1 omega3,
gamma' = gamma x omega (the seed's signs are partly lost in extraction).
``ShellWithSuslovHingeZeroMomentum`` integrates this system, state
(omega1, omega2, gamma(3), alpha(3), beta(3), x, y), with integrals F0, F4, E
and the invariant measure (1/rho) d omega1 d omega2 d^3 gamma = Delta^(-1/2) ...
(checked by autodiff in the tests).
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from .. import _programs
from .. import _validate as V
from ..mechanics import AbstractSystem
from .shell_with_top import (
    as_matrix,
    attitude_value,
    frame_residual,
    project_frame,
)

__all__ = ["ShellWithSuslovHinge", "ShellWithSuslovHingeZeroMomentum"]

E3 = np.array([0.0, 0.0, 1.0])  # numpy: no program to compile at import


def _principal_moments(name, v, owner=""):
    return V.principal_moments(
        name, v, owner=owner, diagonal_reason="the hinge axis e = e3 is a principal axis of the inner body "
        "(seed 003, sec. 2)")


class _HingeParameters(AbstractSystem):
    ms: jax.Array
    Is: jax.Array
    Rs: jax.Array
    mt: jax.Array
    inertia: jax.Array

    def __init__(self, ms=1.0, Rs=0.2, Is=None, mt=0.5, inertia=(2e-3, 3e-3, 4e-3)):
        owner = type(self).__name__
        self.ms = V.positive("ms", ms, owner=owner, what="mass of the shell [kg]")
        self.Rs = V.positive("Rs", Rs, owner=owner, what="radius of the shell [m]")
        self.Is = V.shell_moment(Is, self.ms, self.Rs, owner=owner)
        self.mt = V.positive("mt", mt, owner=owner, what="mass of the inner body [kg]")
        self.inertia = _principal_moments("inertia", inertia, owner=owner)

    @property
    def m(self):
        """Total mass ms + mt [kg]."""
        return self.ms + self.mt

    def II(self, gamma):
        """(Is + m Rs^2) E - m Rs^2 gamma gamma^T (2.4) [kg m^2]."""
        mR2 = self.m * self.Rs**2
        return (self.Is + mR2) * jnp.eye(3) - mR2 * jnp.outer(gamma, gamma)

    def delta(self, gamma):
        """Is (Is + m Rs^2 + I3) + m Rs^2 I3 gamma3^2 [kg^2 m^4] (denominator of (2.4))."""
        mR2 = self.m * self.Rs**2
        I3 = self.inertia[2]
        return self.Is * (self.Is + mR2 + I3) + mR2 * I3 * gamma[2] ** 2


class ShellWithSuslovHinge(_HingeParameters):
    """Shell on a plane with an inner body on a nonholonomic hinge: (2.4) with
    reconstruction. See the module docstring for parameters, units, state."""

    state_names: ClassVar[tuple] = (
        "omega1", "omega2", "omega3",
        "Omega1", "Omega2", "Omega3",
        "gamma1", "gamma2", "gamma3",
        "alpha1", "alpha2", "alpha3",
        "beta1", "beta2", "beta3",
        "x", "y",
    )  # fmt: skip
    control_dim: ClassVar[int] = 0

    @staticmethod
    def split(x):
        """(omega, Omega, gamma, alpha, beta, xy)."""
        return x[0:3], x[3:6], x[6:9], x[9:12], x[12:15], x[15:17]

    def hinge_torque(self, x):
        """lambda [N m]: reaction torque lambda e on the shell, -lambda e on the body."""
        om, Om, ga, *_ = self.split(x)
        I1, I2, I3 = self.inertia
        a = self.Is + self.m * self.Rs**2
        num = self.Is * a * ((I1 - I2) * om[0] * om[1] + I3 * (om[0] * Om[1] - om[1] * Om[0]))
        return num / self.delta(ga)

    def vector_field(self, t, x, u):
        om, Om, ga, al, be, _ = self.split(x)
        lam = self.hinge_torque(x)
        I = self.inertia
        dom = (jnp.cross(I * om, om) - lam * E3) / I
        a = self.Is + self.m * self.Rs**2
        # II^{-1} e = (e + m Rs^2 / Is gamma3 gamma) / (Is + m Rs^2)
        DOm = lam * (E3 + self.m * self.Rs**2 / self.Is * ga[2] * ga) / a
        dOm = DOm - jnp.cross(om, Om)
        V = self.Rs * jnp.cross(Om, ga)
        return jnp.concatenate(
            [dom, dOm, jnp.cross(ga, om), jnp.cross(al, om), jnp.cross(be, om), jnp.stack([V @ al, V @ be])]
        )

    # ------------------------------------------------------------ integrals
    def angular_momentum(self, x):
        """M = II Omega + I omega (2.5), body axes [kg m^2/s]."""
        om, Om, ga, *_ = self.split(x)
        return self.II(ga) @ Om + self.inertia * om

    def angular_momentum_space(self, x):
        _, _, ga, al, be, _ = self.split(x)
        M = self.angular_momentum(x)
        return jnp.stack([M @ al, M @ be, M @ ga])

    def energy(self, x):
        """E (2.7) = 1/2 (Omega, II Omega) + 1/2 (omega, I omega) [J]."""
        om, Om, ga, *_ = self.split(x)
        return 0.5 * Om @ self.II(ga) @ Om + 0.5 * om @ (self.inertia * om)

    def kinetic_energy_bodies(self, x):
        """1/2 m V^2 + 1/2 Is Omega^2 + 1/2 (omega, I omega), V = Rs Omega x gamma [J]."""
        om, Om, ga, *_ = self.split(x)
        V = self.Rs * jnp.cross(Om, ga)
        return 0.5 * (self.m * V @ V + self.Is * Om @ Om + om @ (self.inertia * om))

    def F4(self, x):
        """I1 (I1 - I3) omega1^2 + I2 (I2 - I3) omega2^2 (2.6) [kg^2 m^4/s^2]."""
        I1, I2, I3 = self.inertia
        om = x[0:3]
        return I1 * (I1 - I3) * om[0] ** 2 + I2 * (I2 - I3) * om[1] ** 2

    def invariant_measure_density(self, x):
        """rho of (2.8): Delta(gamma)^(1/2) (see the module docstring)."""
        return jnp.sqrt(self.delta(x[6:9]))

    def invariants(self, x):
        om, Om, ga, *_ = self.split(x)
        M = self.angular_momentum(x)
        Ms = self.angular_momentum_space(x)
        return {
            "F0_gamma_sq": ga @ ga,
            "F1_suslov": Om[2] - om[2],
            "F2_M_sq": M @ M,
            "F3_M_gamma": Ms[2],
            "F4": self.F4(x),
            "M_x": Ms[0],
            "M_y": Ms[1],
        }

    def constraints(self, t, x):
        om, Om, ga, al, be, _ = self.split(x)
        return {"suslov": (Om[2] - om[2])[None], "frame": frame_residual(ga, al, be)}

    def project(self, t, x):
        """Orthonormalize the frame; Omega3 = omega3 := their average weighted by
        (II_33, I3) (the kinetic-metric projection if II's off-diagonal terms are ignored)."""
        om, Om, ga, al, be, xy = self.split(x)
        ga, al, be = project_frame(ga, al, be)
        w1, w2 = self.II(ga)[2, 2], self.inertia[2]
        s = (w1 * Om[2] + w2 * om[2]) / (w1 + w2)
        return jnp.concatenate([om.at[2].set(s), Om.at[2].set(s), ga, al, be, xy])

    # ------------------------------------------------------------ initial states
    def initial_state(self, omega, Omega12=(0.0, 0.0), attitude=None, position=(0.0, 0.0)):
        """omega: body angular velocity [rad/s] (body axes); Omega12: the shell's
        angular velocity components along the body's e1, e2 [rad/s] (Omega3 = omega3
        by the hinge); attitude: body -> space (None, rotation vector or matrix);
        position: contact point (x, y) [m]."""
        owner = "ShellWithSuslovHinge.initial_state"
        a = attitude_value(attitude, owner=owner)
        om = V.vector("omega", omega, 3, owner=owner, what="body angular velocity [rad/s]")
        O12 = V.vector("Omega12", Omega12, 2, owner=owner, what="shell angular velocity along e1, e2 [rad/s]")
        pos = V.vector("position", position, 2, owner=owner, what="contact point (x, y) [m]")
        # concrete numbers: one compiled program instead of eager operations
        return _programs.small_call("ShellWithSuslovHinge.initial_state", _hinge_state, self, a, om, O12, pos)

    def initial_state_zero_momentum(self, omega12, attitude=None, position=(0.0, 0.0)):
        """The state with M = 0 and body rates (omega1, omega2) [rad/s]: omega3 and
        Omega follow from M = 0 and the hinge (sec. 2.4)."""
        owner = "ShellWithSuslovHinge.initial_state_zero_momentum"
        a = attitude_value(attitude, owner=owner)
        zm = ShellWithSuslovHingeZeroMomentum(self.ms, self.Rs, self.Is, self.mt, self.inertia)
        o12 = V.vector("omega12", omega12, 2, owner=owner, what="body rates (omega1, omega2) [rad/s]")
        pos = V.vector("position", position, 2, owner=owner, what="contact point (x, y) [m]")
        return _programs.small_call("ShellWithSuslovHinge.initial_state_zero_momentum", _zero_momentum_state, zm,
                                    a, o12, pos)


def _hinge_state(system, attitude, om, O12, pos):
    """``ShellWithSuslovHinge.initial_state``'s state from its checked numbers (Omega3 =
    omega3 by the hinge)."""
    R = as_matrix(attitude)
    Om = jnp.stack([O12[0], O12[1], om[2]])
    return jnp.concatenate([om, Om, R[2], R[0], R[1], pos])


def _zero_momentum_state(zm, attitude, o12, pos):
    """``initial_state_zero_momentum``'s state: omega3 and Omega from M = 0 and the hinge
    (``zm``: the zero-momentum model with the same parameters)."""
    R = as_matrix(attitude)
    om, Om = zm.velocities(o12, R[2])
    return jnp.concatenate([om, Om, R[2], R[0], R[1], pos])


class ShellWithSuslovHingeZeroMomentum(_HingeParameters):
    """The zero-momentum system (2.9) with reconstruction; state
    (omega1, omega2, gamma(3), alpha(3), beta(3), x, y). See the module docstring."""

    state_names: ClassVar[tuple] = (
        "omega1", "omega2",
        "gamma1", "gamma2", "gamma3",
        "alpha1", "alpha2", "alpha3",
        "beta1", "beta2", "beta3",
        "x", "y",
    )  # fmt: skip
    control_dim: ClassVar[int] = 0

    @staticmethod
    def split(x):
        """(omega12, gamma, alpha, beta, xy)."""
        return x[0:2], x[2:5], x[5:8], x[8:11], x[11:13]

    def velocities(self, omega12, gamma):
        """(omega, Omega) in body axes with M = 0 and Omega3 = omega3."""
        I1, I2, _ = self.inertia
        mR2 = self.m * self.Rs**2
        w3 = -mR2 * gamma[2] * (I1 * omega12[0] * gamma[0] + I2 * omega12[1] * gamma[1]) / self.delta(gamma)
        om = jnp.stack([omega12[0], omega12[1], w3])
        L = self.inertia * om
        Om = -(L + mR2 / self.Is * jnp.dot(gamma, L) * gamma) / (self.Is + mR2)
        return om, Om

    def vector_field(self, t, x, u):
        o12, ga, al, be, _ = self.split(x)
        om, Om = self.velocities(o12, ga)
        I1, I2, I3 = self.inertia
        d1 = (I2 - I3) * om[1] * om[2] / I1
        d2 = (I3 - I1) * om[0] * om[2] / I2
        V = self.Rs * jnp.cross(Om, ga)
        return jnp.concatenate(
            [jnp.stack([d1, d2]), jnp.cross(ga, om), jnp.cross(al, om), jnp.cross(be, om), jnp.stack([V @ al, V @ be])]
        )

    def full_state(self, x):
        """The ``ShellWithSuslovHinge`` state of this zero-momentum state."""
        o12, ga, al, be, xy = self.split(x)
        om, Om = self.velocities(o12, ga)
        return jnp.concatenate([om, Om, ga, al, be, xy])

    def energy(self, x):
        """E (2.7) with Omega = -II^{-1} I omega [J]."""
        o12, ga, *_ = self.split(x)
        om, Om = self.velocities(o12, ga)
        return 0.5 * Om @ self.II(ga) @ Om + 0.5 * om @ (self.inertia * om)

    def F4(self, x):
        I1, I2, I3 = self.inertia
        return I1 * (I1 - I3) * x[0] ** 2 + I2 * (I2 - I3) * x[1] ** 2

    def invariant_measure_density(self, x):
        """Density of the invariant measure in (omega1, omega2, gamma): Delta^(-1/2)."""
        return self.delta(x[2:5]) ** -0.5

    def invariants(self, x):
        ga = x[2:5]
        return {"F0_gamma_sq": ga @ ga, "F4": self.F4(x)}

    def constraints(self, t, x):
        _, ga, al, be, _ = self.split(x)
        return {"frame": frame_residual(ga, al, be)}

    def project(self, t, x):
        o12, ga, al, be, xy = self.split(x)
        ga, al, be = project_frame(ga, al, be)
        return jnp.concatenate([o12, ga, al, be, xy])

    def initial_state(self, omega12, attitude=None, position=(0.0, 0.0)):
        """Body rates (omega1, omega2) [rad/s], attitude body -> space, contact point [m]."""
        owner = "ShellWithSuslovHingeZeroMomentum.initial_state"
        a = attitude_value(attitude, owner=owner)
        o12 = V.vector("omega12", omega12, 2, owner=owner, what="body rates (omega1, omega2) [rad/s]")
        pos = V.vector("position", position, 2, owner=owner, what="contact point (x, y) [m]")
        return _programs.small_call("ShellWithSuslovHingeZeroMomentum.initial_state", _reduced_zm_state, self, a,
                                    o12, pos)


def _reduced_zm_state(system, attitude, o12, pos):
    """``ShellWithSuslovHingeZeroMomentum.initial_state``'s state from its checked numbers."""
    R = as_matrix(attitude)
    return jnp.concatenate([o12, R[2], R[0], R[1], pos])
