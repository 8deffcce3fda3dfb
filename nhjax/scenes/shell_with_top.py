r"""A spherical shell rolling on a plane with a rigid body ("top") hinged at its centre.

Seed 003 (I. A. Bizyaev, A. V. Borisov, I. S. Mamaev, *The dynamics of
nonholonomic systems consisting of a spherical shell with a moving rigid body
inside*, Regul. Chaotic Dyn. 19 (2014) 198–213), section 1, eqs. (1.1)–(1.15).

Model
-----
* Shell: homogeneous spherical shell of mass ``ms`` [kg], central inertia
  ``Is`` E [kg m^2] (default: thin shell, 2/3 ms Rs^2), outer radius ``Rs`` [m],
  rolling without slipping on a horizontal plane.
* Top: rigid body of mass ``mt`` [kg], inertia tensor ``It`` [kg m^2] (3x3
  symmetric positive definite, about its centre of mass G, top axes), on an
  ideal spherical hinge at the shell centre C; ``c`` [m] is the constant vector
  C -> G in the top's axes.
* Gravity ``g`` [m/s^2] (default 9.81) acts downwards.

All vectors are components in the top's axes. omega: angular velocity of the
top; Omega: angular velocity of the shell; V: velocity of C; v_c = omega x c;
gamma: the upward vertical unit vector; alpha, beta: the space axes Ox, Oy.
D a = a' + omega x a is the time derivative seen from space (D gamma = 0).

Re-derivation (the extracted seed text is garbled in several formulas; every
equation below was re-derived from the constraints and the Newton–Euler
equations, with F the hinge force on the top and N the contact force):

    (1.1)  v_G = V + omega x c           (hinge)
    (1.2)  V = Rs Omega x gamma          (no slip: V + Omega x (-Rs gamma) = 0)
    (1.3)  ms DV = N - F - ms g gamma,   Is DOmega = -Rs gamma x N,
           mt D v_G = F - mt g gamma,    It omega' + omega x It omega = F x c.

The vertical part of the shell's Euler equation gives the constant spin
Omega_z = (Omega, gamma) and (1.5) reads  Omega = Rs^{-1} gamma x V + Omega_z gamma
(the seed's "R0^{-1}" is Rs^{-1}). The horizontal part with DV = Rs DOmega x gamma
gives (1.8)

    DV = -mu pi_gamma(D v_c),   mu = mt Rs^2 / (Is + (ms + mt) Rs^2),

pi_gamma(a) = gamma x (a x gamma) = a - (a, gamma) gamma (the seed writes I0 for
the shell's inertia Is in mu). Hence Chaplygin's vector (1.9)

    K = V + mu pi_gamma(v_c),   DK = 0,   (K, gamma) = 0,

is fixed in space and horizontal. Eliminating F from the top's equations:

    (1.11)  J omega' + omega x J omega = mu mt (D v_c, gamma) gamma x c + mt g gamma x c,
            gamma' = gamma x omega,
            J = It + (1 - mu) mt (c^2 E - c c^T)

(the seed drops the factor mu in front of (D v_c, gamma)). Because
(D v_c, gamma) = -(a, omega') + (omega x v_c, gamma) with a = gamma x c, the
system is solved as (J + mu mt a a^T) omega' = -omega x J omega
+ mu mt (omega x v_c, gamma) a + mt g a. The shell's angular velocity obeys

    DOmega = -(mu / Rs) gamma x D v_c        (vertical part zero).

Integrals of the reduced system: F0 = (gamma, gamma) = 1, the area integral
F1 = (J omega, gamma), and the energy

    E = 1/2 (omega, J omega) + 1/2 mu mt (v_c, gamma)^2 + mt g (c, gamma)

(again with the factor mu the seed's E lacks). The total mechanical energy of
the two bodies is  E_total = E + 1/2 Is Omega_z^2 + 1/2 (mt / mu) |K|^2
(``energy`` computes E_total directly from the velocities of both bodies).

Reconstruction (1.12): alpha' = alpha x omega, beta' = beta x omega, and the
contact point (x, y) moves with the centre, x' = (V, alpha), y' = (V, beta).
The seed chooses Ox along K, K = |K| alpha, so that x' = |K| - mu (v_c, alpha),
y' = -mu (v_c, beta); here (alpha, beta) is any horizontal pair and K's space
components (K, alpha), (K, beta) are invariants.

Integrable cases (sec. 1.3): Euler, c = 0: F2 = |J omega|^2 (``euler_integral``);
Lagrange, It axisymmetric about c: F2 = (J omega, c/|c|) (``lagrange_integral``,
the seed's M3 for c = (0, 0, c3), I1 = I2). Both are added to ``invariants``
when the parameters (concrete, not traced) fit the case.

Theorem 1 (isomorphism with a ball with displaced centre of mass on a smooth
plane, Lagrangian (1.13): L = 1/2 (omega, I omega) + 1/2 m (omega, a x gamma)^2
- m g_b (a, gamma)). The reduced energy above is that Lagrangian's energy for

    I = J,   m = mu mt,   a = c,   g_b = g / mu

(the seed's parameter map is garbled; gravity has to be rescaled, or
equivalently a = sqrt(mu) c, m = mt, g_b = g / sqrt(mu)).
``smooth_plane_ball_parameters`` returns this map; the tests check that the
smooth-plane ball's Euler–Lagrange equations give the same omega'.

Internal torque (for steering; not a control of this class, whose invariants
hold only for free motion): with a torque tau on the top and -tau on the shell
(top axes), ``forced_vector_field`` integrates

    J omega' + omega x J omega = mu mt (D v_c, gamma) gamma x c + mt g gamma x c
                                 + tau - mt kappa (tau x gamma) x c,
    DOmega = -(mu/Rs) gamma x D v_c - pi_gamma(tau) / I_c - (tau, gamma) gamma / Is,
    I_c = Is + (ms + mt) Rs^2,   kappa = Rs / I_c,

so that DK = -kappa tau x gamma, d/dt Omega_z = -(tau, gamma) / Is,
d/dt (J omega, gamma) = (tau, gamma) - mt kappa ((tau x gamma) x c, gamma), and the
power of the inputs is (tau, omega - Omega). The vertical angular momentum about
the contact point, (L_P, gamma) = Is Omega_z + (J omega, gamma) + mt (c x K, gamma),
changes at the rate -mt (V x v_c, gamma) whatever the torque (no external
vertical moment about P); for c = 0 it is conserved under any internal torque.
``ShellWithTopLagrangian`` is the same system derived by the engine from the
two rigid bodies in space (with the torque as a generalized force); the tests
compare both, torque terms included.

State of ``ShellWithTopReduced`` (17 components):

    x = (omega(3) [rad/s], Omega(3) [rad/s], gamma(3), alpha(3), beta(3), x, y [m])

Omega is the shell's angular velocity in the top's axes: it carries Omega_z
and K, so both are checked by the integration rather than assumed.
(alpha, beta, gamma) are the rows of the rotation matrix top -> space.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _programs
from .. import _validate as V
from ..lie import so3
from ..mechanics import AbstractSystem, ConstrainedLagrangian

__all__ = ["ShellWithTopLagrangian", "ShellWithTopReduced"]

E_X = np.array([1.0, 0.0, 0.0])  # numpy: no program to compile at import
E_Y = np.array([0.0, 1.0, 0.0])  # numpy: no program to compile at import
E_Z = np.array([0.0, 0.0, 1.0])  # numpy: no program to compile at import


# ---------------------------------------------------------------- shared helpers
def _is_concrete(*vals) -> bool:
    return not any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(vals))


def _positive(name, v, owner=""):
    return V.positive(name, v, owner=owner)


def _inertia_tensor(name, v, owner=""):
    """3x3 symmetric positive definite tensor from a 3x3 array or 3 principal moments."""
    return V.inertia_tensor(name, v, owner=owner)


def _vector3(name, v, owner=""):
    return V.vector(name, v, 3, owner=owner)


def attitude_value(attitude, name="attitude", owner=""):
    """An attitude (top axes -> space) as given, checked: None (the identity matrix), a
    rotation vector (3,) [rad] or a 3x3 rotation matrix (R^T R = I within 1e-9, det +1).
    ``as_matrix`` turns it into the matrix (inside a state's program: see
    ``nhjax._programs.small_call``)."""
    if attitude is None:
        return np.eye(3)
    R = V._as_real(name, attitude, owner, "a rotation vector (3,) or a 3x3 rotation matrix")
    if np.shape(R) == (3,):
        return V.vector(name, R, 3, owner=owner)
    if np.shape(R) != (3, 3):
        raise V.ParameterError(
            f"{owner + ': ' if owner else ''}{name} must be a rotation vector (3,) or a 3x3 rotation matrix, "
            f"got shape {np.shape(R)}", name, attitude)
    return V.rotation(name, R, owner=owner, tol=1e-9)


def as_matrix(attitude):
    """The rotation matrix of an ``attitude_value``: exp of a rotation vector (3,), a
    matrix as it is."""
    return so3.exp(attitude) if jnp.shape(attitude) == (3,) else jnp.asarray(attitude)


def frame_residual(gamma, alpha, beta):
    """(alpha, beta, gamma) must be the rows of a rotation matrix: Q Q^T - I (upper
    triangle, 6 numbers) and gamma - alpha x beta (orientation)."""
    Q = jnp.stack([alpha, beta, gamma])
    G = Q @ Q.T - jnp.eye(3)
    iu = jnp.triu_indices(3)
    return jnp.concatenate([G[iu], gamma - jnp.cross(alpha, beta)])


def project_frame(gamma, alpha, beta):
    """Nearest rotation (polar decomposition) to the rows (alpha, beta, gamma)."""
    Q = jnp.stack([alpha, beta, gamma])
    U, _, Vt = jnp.linalg.svd(Q)
    R = U @ Vt
    return R[2], R[0], R[1]


def _pi(gamma, a):
    """Horizontal part pi_gamma(a) = a - (a, gamma) gamma (|gamma| = 1)."""
    return a - jnp.dot(a, gamma) * gamma


# ---------------------------------------------------------------- reduced model

def _shell_and_top(owner, ms, Rs, Is, mt, It, c, g):
    """The shell's and the top's parameters, checked (shared by the models here)."""
    ms = V.positive("ms", ms, owner=owner, what="mass of the shell [kg]")
    Rs = V.positive("Rs", Rs, owner=owner, what="radius of the shell [m]")
    Is = V.shell_moment(Is, ms, Rs, owner=owner)
    mt = V.positive("mt", mt, owner=owner, what="mass of the top [kg]")
    It = V.inertia_tensor("It", It, owner=owner)
    c = V.vector("c", c, 3, owner=owner, what="hinge to the top's centre of mass, top axes [m]")
    g = V.positive("g", g, allow_zero=True, owner=owner, what="gravity [m/s^2]")
    return ms, Rs, Is, mt, It, c, g

class ShellWithTopReduced(AbstractSystem):
    """Spherical shell with a top on a spherical hinge: reduced system (1.11) with
    reconstruction (1.5), (1.8), (1.12). See the module docstring.

    Parameters: ms, Is, Rs, mt, It, c, g (units in the module docstring).
    Defaults: ms = 1 kg, Rs = 0.2 m, Is = 2/3 ms Rs^2 (thin shell), mt = 0.5 kg,
    It = diag(2, 3, 4) 1e-3 kg m^2, c = (0.01, 0, -0.06) m, g = 9.81 m/s^2.
    """

    ms: jax.Array
    Is: jax.Array
    Rs: jax.Array
    mt: jax.Array
    It: jax.Array
    c: jax.Array
    g: jax.Array
    case: str = eqx.field(static=True, default="general")

    state_names: ClassVar[tuple] = (
        "omega1", "omega2", "omega3",
        "Omega1", "Omega2", "Omega3",
        "gamma1", "gamma2", "gamma3",
        "alpha1", "alpha2", "alpha3",
        "beta1", "beta2", "beta3",
        "x", "y",
    )  # fmt: skip
    control_dim: ClassVar[int] = 0

    def __init__(
        self,
        ms=1.0,
        Rs=0.2,
        Is=None,
        mt=0.5,
        It=(2e-3, 3e-3, 4e-3),
        c=(0.01, 0.0, -0.06),
        g=9.81,
        case="auto",
    ):
        owner = "ShellWithTopReduced"
        self.ms, self.Rs, self.Is, self.mt, self.It, self.c, self.g = _shell_and_top(
            owner, ms, Rs, Is, mt, It, c, g)
        V.choice("case", case, ("auto", "general", "euler", "lagrange"), owner=owner)
        if case == "auto":
            case = self._detect_case()
        self.case = case

    def _detect_case(self, tol=1e-12):
        if not _is_concrete(self.It, self.c):
            return "general"
        c = np.asarray(self.c)
        It = np.asarray(self.It)
        scale = np.abs(It).max()
        if np.linalg.norm(c) == 0.0:
            return "euler"
        e = c / np.linalg.norm(c)
        # It axisymmetric about e: It = A E + (C - A) e e^T
        C = e @ It @ e
        A = 0.5 * (np.trace(It) - C)
        if np.abs(It - (A * np.eye(3) + (C - A) * np.outer(e, e))).max() <= tol * scale:
            return "lagrange"
        return "general"

    # ------------------------------------------------------------ parameters
    @property
    def I_contact(self):
        """Is + (ms + mt) Rs^2 [kg m^2]: the shell's inertia about the contact point
        with the total mass at its centre (denominator of mu; the seed's "I0" in
        (1.8) is the shell's Is)."""
        return self.Is + (self.ms + self.mt) * self.Rs**2

    @property
    def mu(self):
        """mu = mt Rs^2 / (Is + (ms + mt) Rs^2) (1.8) [-]."""
        return self.mt * self.Rs**2 / self.I_contact

    @property
    def J(self):
        """J = It + (1 - mu) mt (c^2 E - c c^T) (1.11) [kg m^2]."""
        c = self.c
        return self.It + (1 - self.mu) * self.mt * (jnp.dot(c, c) * jnp.eye(3) - jnp.outer(c, c))

    def smooth_plane_ball_parameters(self):
        """Theorem 1: (I, m, a, g_b) of the ball with displaced centre on a smooth
        plane (1.13)-(1.14) whose equations for (omega, gamma) are (1.11)."""
        return {"I": self.J, "m": self.mu * self.mt, "a": self.c, "g": self.g / self.mu}

    # ------------------------------------------------------------ state access
    @staticmethod
    def split(x):
        """(omega, Omega, gamma, alpha, beta, xy)."""
        return x[0:3], x[3:6], x[6:9], x[9:12], x[12:15], x[15:17]

    def contact_velocity(self, x):
        """V = Rs Omega x gamma: velocity of the shell centre (top axes) [m/s]."""
        _, Om, ga, *_ = self.split(x)
        return self.Rs * jnp.cross(Om, ga)

    def chaplygin_vector(self, x):
        """K = V + mu pi_gamma(omega x c) (1.9), top axes [m/s]."""
        om, _, ga, *_ = self.split(x)
        return self.contact_velocity(x) + self.mu * _pi(ga, jnp.cross(om, self.c))

    def chaplygin_vector_space(self, x):
        """K in space axes (constant)."""
        _, _, ga, al, be, _ = self.split(x)
        K = self.chaplygin_vector(x)
        return jnp.stack([K @ al, K @ be, K @ ga])

    def shell_spin(self, x):
        """Omega_z = (Omega, gamma) [rad/s] (constant)."""
        return jnp.dot(x[3:6], x[6:9])

    def shell_angular_velocity_space(self, x):
        """Omega in space axes [rad/s] (1.5)."""
        _, Om, ga, al, be, _ = self.split(x)
        return jnp.stack([Om @ al, Om @ be, Om @ ga])

    def attitude(self, x):
        """Rotation matrix top -> space (rows alpha, beta, gamma)."""
        _, _, ga, al, be, _ = self.split(x)
        return jnp.stack([al, be, ga])

    # ------------------------------------------------------------ dynamics
    def _omega_dot(self, om, ga, tau):
        J, c, mt, mu = self.J, self.c, self.mt, self.mu
        a = jnp.cross(ga, c)
        vc = jnp.cross(om, c)
        A = J + mu * mt * jnp.outer(a, a)
        rhs = (
            -jnp.cross(om, J @ om)
            + mu * mt * jnp.dot(jnp.cross(om, vc), ga) * a
            + mt * self.g * a
            + tau
            - mt * (self.Rs / self.I_contact) * jnp.cross(jnp.cross(tau, ga), c)
        )
        return jnp.linalg.solve(A, rhs)

    def reduced_vector_field(self, omega, gamma):
        """(omega', gamma') of the closed system (1.11)."""
        dom = self._omega_dot(omega, gamma, jnp.zeros(3, omega.dtype))
        return dom, jnp.cross(gamma, omega)

    def forced_vector_field(self, t, x, tau):
        """x' with an internal torque tau (top axes, N m): +tau on the top, -tau on the shell."""
        om, Om, ga, al, be, _ = self.split(x)
        tau = jnp.asarray(tau, x.dtype)
        dom = self._omega_dot(om, ga, tau)
        vc = jnp.cross(om, self.c)
        Dvc = jnp.cross(dom, self.c) + jnp.cross(om, vc)
        DOm = (
            -(self.mu / self.Rs) * jnp.cross(ga, Dvc)
            - _pi(ga, tau) / self.I_contact
            - jnp.dot(tau, ga) * ga / self.Is
        )
        dOm = DOm - jnp.cross(om, Om)
        V = self.Rs * jnp.cross(Om, ga)
        return jnp.concatenate(
            [
                dom,
                dOm,
                jnp.cross(ga, om),
                jnp.cross(al, om),
                jnp.cross(be, om),
                jnp.stack([V @ al, V @ be]),
            ]
        )

    def vector_field(self, t, x, u):
        return self.forced_vector_field(t, x, jnp.zeros(3, x.dtype))

    def torque_power(self, x, tau):
        """Power of the internal torque, (tau, omega - Omega) [W]."""
        return jnp.dot(tau, x[0:3] - x[3:6])

    # ------------------------------------------------------------ invariants
    def reduced_energy(self, x):
        """E of (1.11): 1/2 (omega, J omega) + 1/2 mu mt (v_c, gamma)^2 + mt g (c, gamma) [J]."""
        om, _, ga, *_ = self.split(x)
        vg = jnp.dot(jnp.cross(om, self.c), ga)
        return 0.5 * om @ self.J @ om + 0.5 * self.mu * self.mt * vg**2 + self.mt * self.g * jnp.dot(self.c, ga)

    def energy(self, x):
        """Total mechanical energy of shell and top, from their velocities [J]."""
        om, Om, ga, *_ = self.split(x)
        V = self.Rs * jnp.cross(Om, ga)
        vG = V + jnp.cross(om, self.c)
        T = (
            0.5 * self.ms * V @ V
            + 0.5 * self.Is * Om @ Om
            + 0.5 * self.mt * vG @ vG
            + 0.5 * om @ self.It @ om
        )
        return T + self.mt * self.g * jnp.dot(self.c, ga)

    def area_integral(self, x):
        """F1 = (J omega, gamma) [kg m^2/s]."""
        return jnp.dot(self.J @ x[0:3], x[6:9])

    def contact_angular_momentum(self, x):
        """L_P: angular momentum of both bodies about the contact point P = C - Rs gamma
        (a moving geometric point), top axes [kg m^2/s]. (L_P, gamma) =
        Is Omega_z + (J omega, gamma) + mt (c x K, gamma); its rate is
        -mt (V x v_c, gamma), with or without an internal torque."""
        om, Om, ga, *_ = self.split(x)
        V = self.Rs * jnp.cross(Om, ga)
        vG = V + jnp.cross(om, self.c)
        rP = self.Rs * ga  # from P to C
        return (
            self.Is * Om
            + self.ms * jnp.cross(rP, V)
            + self.It @ om
            + self.mt * jnp.cross(rP + self.c, vG)
        )

    def euler_integral(self, x):
        """|J omega|^2 [kg^2 m^4/s^2]: conserved when c = 0 (Euler case)."""
        M = self.J @ x[0:3]
        return M @ M

    def lagrange_integral(self, x):
        """(J omega, c/|c|) [kg m^2/s]: conserved when It is axisymmetric about c
        (Lagrange case; the seed's M3 for c = (0, 0, c3), I1 = I2)."""
        n = jnp.linalg.norm(self.c)
        e = jnp.where(n > 0, self.c / jnp.where(n > 0, n, 1.0), E_Z)
        return jnp.dot(self.J @ x[0:3], e)

    def invariants(self, x):
        ga = x[6:9]
        K = self.chaplygin_vector_space(x)
        out = {
            "gamma_sq": ga @ ga,
            "area": self.area_integral(x),
            "reduced_energy": self.reduced_energy(x),
            "shell_spin": self.shell_spin(x),
            "K_x": K[0],
            "K_y": K[1],
        }
        if self.case == "euler":
            out["euler_M2"] = self.euler_integral(x)
        elif self.case == "lagrange":
            out["lagrange_M3"] = self.lagrange_integral(x)
        return out

    def constraints(self, t, x):
        _, _, ga, al, be, _ = self.split(x)
        return {"frame": frame_residual(ga, al, be)}

    def project(self, t, x):
        om, Om, ga, al, be, xy = self.split(x)
        ga, al, be = project_frame(ga, al, be)
        return jnp.concatenate([om, Om, ga, al, be, xy])

    # ------------------------------------------------------------ initial state
    def initial_state(self, omega, attitude=None, shell_velocity=(0.0, 0.0), shell_spin=0.0, position=(0.0, 0.0)):
        """State from physical quantities.

        omega : angular velocity of the top in its own axes [rad/s];
        attitude : rotation top axes -> space (None, rotation vector, or 3x3 matrix);
        shell_velocity : horizontal velocity (vx, vy) of the shell centre in space [m/s];
        shell_spin : Omega_z, the shell's spin about the vertical [rad/s];
        position : contact point (x, y) [m].
        The shell's angular velocity follows from (1.5): Omega = gamma x V / Rs + Omega_z gamma.
        """
        owner = "ShellWithTopReduced.initial_state"
        a = attitude_value(attitude, owner=owner)
        v = V.vector("shell_velocity", shell_velocity, 2, owner=owner, what="(vx, vy) [m/s]")
        spin = V.real("shell_spin", shell_spin, owner=owner, shape=())
        om = V.vector("omega", omega, 3, owner=owner, what="angular velocity of the top, its axes [rad/s]")
        pos = V.vector("position", position, 2, owner=owner, what="contact point (x, y) [m]")
        # concrete numbers: one compiled program instead of eager operations (small programs
        # compiled in every new process)
        return _programs.small_call("ShellWithTopReduced.initial_state", _reduced_state, self, a, v, spin, om, pos)


def _reduced_state(system, attitude, v, spin, om, pos):
    """``ShellWithTopReduced.initial_state``'s state from its checked numbers: the shell's
    angular velocity from (1.5), Omega = gamma x V / Rs + Omega_z gamma."""
    R = as_matrix(attitude)
    al, be, ga = R[0], R[1], R[2]
    Vc = R.T @ jnp.stack([v[0], v[1], jnp.zeros(())])
    Om = jnp.cross(ga, Vc) / system.Rs + spin * ga
    return jnp.concatenate([om, Om, ga, al, be, pos])


# ---------------------------------------------------------------- engine model
class ShellWithTopLagrangian(ConstrainedLagrangian):
    """The same shell and top from first principles, for the engine.

    Coordinates q = (xc, yc, theta_s(3), theta_t(3)): the horizontal position of
    the shell centre [m] and rotation vectors of shell and top (R = exp(hat(theta)),
    body -> space) [rad]; the centre's height is Rs. T is the kinetic energy of
    both bodies in space, V = mt g z_G, the no-slip constraint is written in space,
    xc' - (Rs omega_s x e_z)_x = 0, yc' - (Rs omega_s x e_z)_y = 0, and the
    internal torque u (top axes) enters as the generalized force of the power
    (R_t u, omega_t - omega_s) (space axes). The chart is singular at
    |theta| = 2 pi (dexp is not invertible there): the guards "shell rotation
    vector" and "top rotation vector" stop a simulation at |theta| = 2 pi -
    ``chart_eps`` [rad] with a ``ChartSingularityError`` (default chart_eps =
    0.1; chart_eps = 0 turns the guards off: the adaptive step then crosses the
    pole of dexp^-1 with whatever error that costs, as the work-precision
    benchmark does over 10 turns). ``reduced_state(q, qd)`` maps to ``ShellWithTopReduced``'s state.
    """

    ms: jax.Array
    Is: jax.Array
    Rs: jax.Array
    mt: jax.Array
    It: jax.Array
    c: jax.Array
    g: jax.Array
    n: int = eqx.field(static=True, default=8)
    chart_eps: float = eqx.field(static=True, default=0.1)

    guard_hints: ClassVar[dict] = {
        k: f"the {k} approaches |theta| = 2 pi, where the rotation-vector chart is singular; "
        "simulate long or fast-spinning motions with ShellWithTop (attitudes on SO(3)) or "
        "ShellWithTopReduced, or restart from the equivalent rotation vector theta (1 - 2 pi/|theta|)"
        for k in ("shell rotation vector", "top rotation vector")
    }
    guard_arguments: ClassVar[dict] = {"shell rotation vector": "attitude", "top rotation vector": "attitude"}

    state_names: ClassVar[tuple] = (
        "xc", "yc", "ths1", "ths2", "ths3", "tht1", "tht2", "tht3",
        "xc_dot", "yc_dot", "ths1_dot", "ths2_dot", "ths3_dot", "tht1_dot", "tht2_dot", "tht3_dot",
    )  # fmt: skip
    control_dim: ClassVar[int] = 3

    def __init__(self, ms=1.0, Rs=0.2, Is=None, mt=0.5, It=(2e-3, 3e-3, 4e-3), c=(0.01, 0.0, -0.06), g=9.81,
                 chart_eps=0.1):
        owner = "ShellWithTopLagrangian"
        self.ms, self.Rs, self.Is, self.mt, self.It, self.c, self.g = _shell_and_top(
            owner, ms, Rs, Is, mt, It, c, g)
        self.n = 8
        self.chart_eps = float(V.in_range("chart_eps", chart_eps, 0.0, 2 * np.pi, hi_closed=False, owner=owner, as_float=True,
                                          shape=(), what="margin of the rotation-vector guards [rad], 0: no guard"))

    def guards(self, x):
        """Distance [rad] of each rotation vector from the singular sphere |theta| = 2 pi,
        less chart_eps: positive inside the chart."""
        if self.chart_eps == 0.0:  # no guard: the step-size control crosses the dexp pole
            return {}
        lim = 2 * np.pi - self.chart_eps
        norm = lambda v: jnp.sqrt(v @ v + 1e-300)  # noqa: E731  (finite derivative at 0)
        return {"shell rotation vector": lim - norm(x[2:5]), "top rotation vector": lim - norm(x[5:8])}

    @classmethod
    def from_reduced(cls, red: ShellWithTopReduced):
        return cls(ms=red.ms, Rs=red.Rs, Is=red.Is, mt=red.mt, It=red.It, c=red.c, g=red.g)

    def _kinematics(self, q, qd):
        """(R_s, R_t, omega_s in space, omega_t in top axes, r_C', r_G')."""

        def poses(q):
            rC = jnp.stack([q[0], q[1], self.Rs])
            Rs_, Rt = so3.exp(q[2:5]), so3.exp(q[5:8])
            return Rs_, Rt, rC + Rt @ self.c

        (Rs_, Rt, _), (dRs, dRt, drG) = jax.jvp(poses, (q,), (qd,))
        w_s = so3.vee(dRs @ Rs_.T)
        w_t = so3.vee(Rt.T @ dRt)
        drC = jnp.stack([qd[0], qd[1], jnp.zeros((), q.dtype)])
        return Rs_, Rt, w_s, w_t, drC, drG

    def kinetic_energy(self, q, qd):
        _, _, w_s, w_t, drC, drG = self._kinematics(q, qd)
        return 0.5 * (
            self.ms * drC @ drC + self.Is * w_s @ w_s + self.mt * drG @ drG + w_t @ self.It @ w_t
        )

    def potential_energy(self, q):
        return self.mt * self.g * (so3.exp(q[5:8]) @ self.c)[2]

    def velocity_constraints(self, t, q, qd):
        _, _, w_s, _, drC, _ = self._kinematics(q, qd)
        slip = drC - self.Rs * jnp.cross(w_s, E_Z)
        return slip[:2]

    def generalized_force(self, t, q, qd, u):
        def power(v):
            _, Rt, w_s, w_t, _, _ = self._kinematics(q, v)
            return jnp.dot(u, w_t - Rt.T @ w_s)

        return jax.grad(power)(jnp.zeros_like(qd)) if u is not None else jnp.zeros_like(q)

    def reduced_state(self, q, qd):
        """The 17-component state of ``ShellWithTopReduced`` at (q, q')."""
        _, Rt, w_s, w_t, _, _ = self._kinematics(q, qd)
        Om = Rt.T @ w_s
        return jnp.concatenate([w_t, Om, Rt[2], Rt[0], Rt[1], q[0:2]])
