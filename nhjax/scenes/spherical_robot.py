r"""The spherical robot: a shell rolling without slipping, a rigid body inside, an internal torque.

Seed 003 (Bizyaev, Borisov & Mamaev, *The dynamics of nonholonomic systems
consisting of a spherical shell with a moving rigid body inside*, Regul. Chaotic
Dyn. 19 (2014) 198-213), section 1, here with an actuator: a torque between the
shell and the inner body.

Model (SI units)
----------------
Homogeneous spherical shell: mass ``ms`` [kg], radius ``Rs`` [m], central
inertia ``Is`` E [kg m^2] (default 2/3 ms Rs^2, a thin shell). Inner body ("top"):
mass ``mt``, inertia tensor ``It`` about its centre of mass G (top frame), on a
spherical hinge at the shell's centre C, with G at ``c`` from C (top frame).
Gravity ``g`` along -e3; the plane is z = 0, so C is at height Rs.

Configuration (on a Lie group, integrated by RKMK so that the attitudes stay
rotations): g = (xy in R^2 (C's horizontal position), Rs_ in SO(3) (shell
attitude), Rt in SO(3) (top attitude)); velocity v = (xy' (2), Omega (3, shell,
body frame), omega (3, top, body frame)).

    L = ms/2 |V|^2 + Is/2 |Omega|^2 + mt/2 |V + Rt (omega x c)|^2 + 1/2 omega.It omega
        - mt g (Rt c)_3,          V = (x', y', 0)

Rolling without slipping (1.2): the shell's material point at the contact,
C - Rs e3, is at rest:  V + (Rs_ Omega) x (-Rs e3) = 0, i.e.
x' = Rs (Rs_ Omega)_2, y' = -Rs (Rs_ Omega)_1. The hinge (1.1) is built into the
coordinates. Input u = tau (3) [N m], in the top's frame: +tau on the top,
-tau on the shell (generalized forces (0, 0, -Rs_^T Rt tau, tau)).

The equations of motion come from the Hamel equations by autodiff
(``nhjax.mechanics.LieLagrangian``); ``ShellWithTopReduced`` (the reduced system
(1.11)) is the independent check.

Integrals without torque: the energy; the vertical spin of the shell
(Rs_ Omega)_3; Chaplygin's vector (1.9) in space, here
K = Is Rs_ Omega + Rs e3 x (ms V + mt v_G), v_G = V + Rt (omega x c), which
obeys dK/dt = -Rt tau (so it is fixed without torque; the shell's angular
momentum balance about C, with the contact force eliminated through the
momentum balance of both bodies). With a torque, simulate() reports energy - work.
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from .. import _programs
from .. import _validate as V
from ..lie import Euclidean, SO3Body
from ..mechanics import LieLagrangian

__all__ = ["ShellWithTop"]

E3 = np.array([0.0, 0.0, 1.0])  # numpy: no program to compile at import


def _robot_state(system, xy, Rsh, Rt, Ws, wt):
    """``ShellWithTop.initial_state``'s state from its checked numbers: the centre's
    velocity from rolling, V = W x (Rs e3), and the body angular velocities."""
    Vc = jnp.cross(Ws, system.Rs * E3)
    return (xy, Rsh, Rt), jnp.concatenate([Vc[:2], Rsh.T @ Ws, Rt.T @ wt])


class ShellWithTop(LieLagrangian):
    """The spherical robot (see the module docstring): state ((xy, R_shell, R_top), v)."""

    ms: jax.Array
    Rs: jax.Array
    Is: jax.Array
    mt: jax.Array
    It: jax.Array
    c: jax.Array
    g: jax.Array

    control_dim: ClassVar[int] = 3

    def __init__(self, ms=1.0, Rs=0.2, Is=None, mt=2.0, It=((0.01, 0, 0), (0, 0.012, 0), (0, 0, 0.008)),
                 c=(0.0, 0.0, -0.08), g=9.81):
        owner = "ShellWithTop"
        self.ms = V.positive("ms", ms, owner=owner, what="mass of the shell [kg]")
        self.Rs = V.positive("Rs", Rs, owner=owner, what="radius of the shell [m]")
        self.mt = V.positive("mt", mt, owner=owner, what="mass of the top [kg]")
        self.Is = V.shell_moment(Is, self.ms, self.Rs, owner=owner)
        self.It = V.inertia_tensor("It", It, owner=owner)
        self.c = V.vector("c", c, 3, owner=owner, what="centre of the shell to the top's centre of mass, "
                          "top frame [m]")
        self.g = V.positive("g", g, allow_zero=True, owner=owner, what="gravity [m/s^2]")

    @property
    def config_spaces(self):
        return (Euclidean(), SO3Body(), SO3Body())

    # -------------------------------------------------------------- helpers
    def _parts(self, v):
        return v[:2], v[2:5], v[5:8]

    def centre_velocity(self, v):
        return jnp.concatenate([v[:2], jnp.zeros(1, v.dtype)])

    def top_com_velocity(self, g, v):
        _, _, Rt = g
        _, _, w = self._parts(v)
        return self.centre_velocity(v) + Rt @ jnp.cross(w, self.c)

    # ---------------------------------------------------------- mechanics
    def lagrangian(self, g, v):
        _, _, Rt = g
        _, W, w = self._parts(v)
        V = self.centre_velocity(v)
        vG = self.top_com_velocity(g, v)
        T = 0.5 * self.ms * V @ V + 0.5 * self.Is * W @ W + 0.5 * self.mt * vG @ vG + 0.5 * w @ self.It @ w
        return T - self.mt * self.g * (Rt @ self.c)[2]

    def velocity_constraints(self, t, g, v):
        _, Rsh, _ = g
        _, W, _ = self._parts(v)
        contact = self.centre_velocity(v) + jnp.cross(Rsh @ W, -self.Rs * E3)
        return contact[:2]

    def generalized_force(self, t, g, v, u):
        _, Rsh, Rt = g
        return jnp.concatenate([jnp.zeros(2, v.dtype), -Rsh.T @ (Rt @ u), u])

    # ------------------------------------------------------------ physics
    def initial_state(self, xy=(0.0, 0.0), shell_attitude=None, top_attitude=None,
                      shell_omega=(0.0, 0.0, 0.0), top_omega=(0.0, 0.0, 0.0)):
        """State from the centre's position [m], attitudes (3x3, default identity) and
        angular velocities in space [rad/s]; the centre's velocity follows from rolling."""
        owner = "ShellWithTop.initial_state"
        Rsh = np.eye(3) if shell_attitude is None else V.rotation("shell_attitude", shell_attitude, owner=owner)
        Rt = np.eye(3) if top_attitude is None else V.rotation("top_attitude", top_attitude, owner=owner)
        Ws = V.vector("shell_omega", shell_omega, 3, owner=owner, what="shell angular velocity in space [rad/s]")
        wt = V.vector("top_omega", top_omega, 3, owner=owner, what="top angular velocity in space [rad/s]")
        xy = V.vector("xy", xy, 2, owner=owner, what="position of the shell centre [m]")
        # concrete numbers: one compiled program instead of eager operations (small programs
        # compiled in every new process)
        return _programs.small_call("ShellWithTop.initial_state", _robot_state, self, xy, Rsh, Rt, Ws, wt)

    def chaplygin_vector(self, y):
        """K = Is Omega_space + Rs e3 x (ms V + mt v_G) in space [kg m^2/s]; dK/dt = -Rt tau."""
        g, v = y
        _, Rsh, _ = g
        _, W, _ = self._parts(v)
        P = self.ms * self.centre_velocity(v) + self.mt * self.top_com_velocity(g, v)
        return self.Is * Rsh @ W + self.Rs * jnp.cross(E3, P)

    def reduced_state(self, y):
        """(omega, gamma) of the reduced system (1.11): the top's body angular velocity
        and the vertical in the top's frame."""
        (_, _, Rt), v = y
        return self._parts(v)[2], Rt.T @ E3

    def free_invariants(self, y):
        """Integrals of the torque-free motion (simulate() reports them without a control;
        under a torque it reports energy - work)."""
        K = self.chaplygin_vector(y)
        (_, Rsh, _), v = y
        return {"K_x": K[0], "K_y": K[1], "K_z": K[2], "shell_spin_z": (Rsh @ v[2:5])[2]}

    def contact_point(self, y):
        (xy, _, _), _ = y
        return xy
