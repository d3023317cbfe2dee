r"""Dynamic feedback linearization for posture tracking (paper §5, Table 4, Props 7-9).

Each row of Table 4 is a :class:`DynamicExtension`: the linearizing outputs, the
compensator states that delay some input combinations, and how the new inputs U drive
the plant. Everything else -- the diffeomorphism :math:`\zeta = \Psi(X_e)`, the
decoupling matrix :math:`K(X_e)` and drift, the auxiliary law (49) -- is produced by the
generic engine of :mod:`wmrjax.linearize`, at velocity level (kinematic model 5) and at
torque level (model 8) by the cascade of Lemma 1: the torque-level extension appends the
velocity-level new inputs U to the state and takes :math:`V = \dot U` as input, with the
same outputs, relative degrees one higher, and the same decoupling matrix.

Extended state ``z`` (unbatched vector):

* velocity level: ``z = (X, c)``; plant input ``u = plant_input(X, c, U)``;
* torque level: ``z = (X, c, U)``; plant input ``v = du/dt`` along the flow.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math, linearize, robots
from wmrjax._validate import check_finite, check_positive, check_shape, concrete
from wmrjax.references import Reference, taylor
from wmrjax.robots import Geometry, RobotType

# |det K| below this is treated as singular inside the law (the division is clamped);
# runs report the true margin so such events are flagged.
DET_FLOOR = 1e-12


@dataclasses.dataclass(frozen=True)
class DynamicExtension:
    """One row of Table 4 (static description).

    Attributes:
      robot: the robot type.
      n_comp: number of compensator states c.
      comp_names: their names (for reports).
      relative_degree: r of every output at velocity level.
      outputs: ``(xi, geometry) -> Y`` linearizing outputs, function of the posture only.
      plant_input: ``(X, c, U, geometry) -> u``, affine in U.
      compensator: ``(X, c, U, geometry) -> dc/dt``, affine in U.
      regularity: Table 4's condition (with errata), for messages.
      psi_inverse: closed form ``(zeta, branch, geometry) -> z`` at velocity level, on the
        branch where :attr:`branch_quantity` has the sign ``branch`` (+1 or -1).
      from_physical: ``(X, u, geometry) -> (c, U)``: compensator state and new inputs
        matching a physical state (posture, steering angles, wheel velocities u) with the
        compensator at rest (its time derivative zero).
      branch_quantity: ``(z, geometry) -> scalar`` whose sign labels the branch of Psi^-1
        (Remark 17): chi1 for (2,0) and (1,1), eta1 for (2,1) and (1,2).
      extra_margin: optional ``(z, geometry) -> scalar`` multiplying |det K| in the
        singularity margin (the (1,1) lever L sin(beta) + e cos(beta), errata).
      angle_outputs: which outputs are angles (theta for (2,1), (1,2)): their zeroth-order
        error is wrapped to [-pi, pi) so a reference heading given modulo 2 pi is tracked
        without a spurious turn (errata: integrate angles unwrapped, wrap only errors).
    """

    robot: RobotType
    n_comp: int
    comp_names: tuple
    relative_degree: int
    outputs: Callable = dataclasses.field(repr=False)
    plant_input: Callable = dataclasses.field(repr=False)
    compensator: Callable = dataclasses.field(repr=False)
    regularity: str = ""
    psi_inverse: Optional[Callable] = dataclasses.field(default=None, repr=False)
    from_physical: Optional[Callable] = dataclasses.field(default=None, repr=False)
    branch_quantity: Optional[Callable] = dataclasses.field(default=None, repr=False)
    extra_margin: Optional[Callable] = dataclasses.field(default=None, repr=False)
    angle_outputs: tuple = ()

    @property
    def n_outputs(self) -> int:
        return self.robot.n_input  # square: m outputs, m new inputs


# --- Table 4 rows --------------------------------------------------------------------

def _out_axle_point(xi, g):
    s, c = _math.sincos(xi[2])
    return jnp.stack([xi[0] + g.e * c, xi[1] + g.e * s])


def _pi_20(X, c, U, g):  # (eta1, eta2) = (chi1 - e eta2, eta2), new inputs U = (U1, eta2)
    return jnp.stack([c[0] - g.e * U[1], U[1]])


def _comp_20(X, c, U, g):  # chi1' = U1 (eq 37)
    return U[:1]


def _psi_inv_20(zeta, branch, g):
    """Lemma 3 with the errata: theta = atan2(-h1', h2') on S+, chi1 = +-|h'|."""
    hd = zeta[1]
    theta = jnp.arctan2(-branch * hd[0], branch * hd[1])
    s, c = _math.sincos(theta)
    chi1 = branch * jnp.sqrt(hd[0] ** 2 + hd[1] ** 2)
    return jnp.stack([zeta[0, 0] - g.e * c, zeta[0, 1] - g.e * s, theta, chi1])


def _phys_20(X, u, g):
    return jnp.stack([u[0] + g.e * u[1]]), jnp.stack([jnp.zeros_like(u[0]), u[1]])


def _out_posture(xi, g):
    del g
    return xi


def _pi_21(X, c, U, g):  # u = (eta1, eta2, zeta1); compensator (eta1, eta2), U = (eta1', eta2', zeta1)
    return jnp.stack([c[0], c[1], U[2]])


def _comp_21(X, c, U, g):
    return U[:2]


def _psi_inv_21(zeta, branch, g):
    """(x, y, theta) and their rates: theta + beta is the direction of motion of P."""
    del g
    x, y, th = zeta[0]
    xd, yd, thd = zeta[1]
    course = jnp.arctan2(-branch * xd, branch * yd)
    beta = _math.wrap_angle(course - th)
    return jnp.stack([x, y, th, beta, branch * jnp.sqrt(xd**2 + yd**2), thd])


def _phys_21(X, u, g):
    return u[:2], jnp.stack([jnp.zeros_like(u[0]), jnp.zeros_like(u[0]), u[2]])


def _pi_11(X, c, U, g):  # u = (eta1, zeta1); compensator (eta1, chi2); U = (U2 = chi2', zeta1)
    return jnp.stack([c[0], U[1]])


def _lever_11(beta, g):
    s, co = _math.sincos(beta)
    return g.L * s + g.e * co, g.L * co - g.e * s   # chi1 = eta1 * lever, and d lever / d beta


def _comp_11(X, c, U, g):
    lever, dlever = _lever_11(X[3], g)
    eta1_dot = (c[1] - c[0] * U[1] * dlever) / _math.safe_divisor(lever, DET_FLOOR)  # Table 4 footnote
    return jnp.stack([eta1_dot, U[0]])


def _psi_inv_11(zeta, branch, g):
    """h = P' on the fixed axle: chi1 = +-|h'|, theta from h', then beta and eta1 from
    theta' = eta1 cos(beta) and chi1 - e theta' = eta1 L sin(beta), with eta1 > 0."""
    hd, hdd = zeta[1], zeta[2]
    th = jnp.arctan2(-branch * hd[0], branch * hd[1])
    s, c = _math.sincos(th)
    chi1 = branch * jnp.sqrt(hd[0] ** 2 + hd[1] ** 2)
    chi2 = -s * hdd[0] + c * hdd[1]                  # h'' = chi2 (-s, c) - chi1 theta' (c, s)
    thd = -(c * hdd[0] + s * hdd[1]) / chi1
    a, b = (chi1 - g.e * thd) / g.L, thd             # eta1 sin(beta), eta1 cos(beta)
    beta = jnp.arctan2(a, b)
    eta1 = jnp.sqrt(a**2 + b**2)
    return jnp.stack([zeta[0, 0] - g.e * c, zeta[0, 1] - g.e * s, th, beta, eta1, chi2])


def _phys_11(X, u, g):
    lever, dlever = _lever_11(X[3], g)
    # chi2 = eta1' lever + eta1 zeta1 dlever with eta1' = 0
    return jnp.stack([u[0], u[0] * u[1] * dlever]), jnp.stack([jnp.zeros_like(u[0]), u[1]])


def _margin_11(z, g):
    return _lever_11(z[3], g)[0]


def _out_12(xi, g):
    s, c = _math.sincos(xi[2] + g.delta)
    return jnp.stack([xi[0] + g.e * c, xi[1] + g.e * s, xi[2]])


def _pi_12(X, c, U, g):  # u = (eta1, zeta1, zeta2); compensator eta1; U = (eta1', zeta1, zeta2)
    return jnp.stack([c[0], U[1], U[2]])


def _comp_12(X, c, U, g):
    return U[:1]


def _psi_inv_12(zeta, branch, g):
    """Wheel i sits at body (+-L, 0) and moves along (-sin beta_i, cos beta_i) with speed
    2 L eta1 sin(beta_other); angles are taken in (-pi/2, pi/2] and eta1 follows."""
    h1, h2, th = zeta[0]
    hd1, hd2, thd = zeta[1]
    sp, cp = _math.sincos(th + g.delta)
    x, y = h1 - g.e * cp, h2 - g.e * sp
    xd, yd = hd1 + g.e * sp * thd, hd2 - g.e * cp * thd
    s, c = _math.sincos(th)
    vb1, vb2 = c * xd + s * yd, -s * xd + c * yd          # body-frame velocity of P
    v1x, v1y = vb1, vb2 + thd * g.L                        # wheel 1 at (L, 0)
    v2x, v2y = vb1, vb2 - thd * g.L                        # wheel 2 at (-L, 0)
    b1 = jnp.arctan(-v1x / v1y)                            # direction mod pi, in (-pi/2, pi/2)
    b2 = jnp.arctan(-v2x / v2y)
    s1, c1 = _math.sincos(b1)
    s2, c2 = _math.sincos(b2)
    mu1 = -s1 * v1x + c1 * v1y                             # signed speed of wheel 1 = 2 L eta1 sin b2
    eta1 = mu1 / (2.0 * g.L * s2)
    # branch: flipping beta1 by pi flips the sign of eta1 (Sigma -> -Sigma)
    flip = jnp.sign(eta1) != branch
    b1 = jnp.where(flip, b1 - jnp.pi * jnp.sign(b1 + 1e-300), b1)
    eta1 = jnp.where(flip, -eta1, eta1)
    return jnp.stack([x, y, th, b1, b2, eta1])


def _phys_12(X, u, g):
    return u[:1], jnp.stack([jnp.zeros_like(u[0]), u[1], u[2]])


def _first_comp(n_x):
    return lambda z, g: z[n_x]          # first compensator state: chi1 (2,0), eta1 otherwise


def _chi1_11(z, g):
    return z[4] * _lever_11(z[3], g)[0]


EXTENSIONS: dict[str, DynamicExtension] = {
    "(2,0)": DynamicExtension(robots.TYPES["(2,0)"], 1, ("chi1",), 2, _out_axle_point, _pi_20, _comp_20,
                              "chi1 = eta1 + e eta2 != 0", _psi_inv_20, _phys_20, _first_comp(3)),
    "(2,1)": DynamicExtension(robots.TYPES["(2,1)"], 2, ("eta1", "eta2"), 2, _out_posture, _pi_21, _comp_21,
                              "eta1 != 0", _psi_inv_21, _phys_21, _first_comp(4), angle_outputs=(2,)),
    "(1,1)": DynamicExtension(robots.TYPES["(1,1)"], 2, ("eta1", "chi2"), 3, _out_axle_point, _pi_11, _comp_11,
                              "eta1 (L sin beta + e cos beta) != 0 (errata: Table 4 prints only eta1 != 0)",
                              _psi_inv_11, _phys_11, _chi1_11, _margin_11),
    "(1,2)": DynamicExtension(robots.TYPES["(1,2)"], 1, ("eta1",), 2, _out_12, _pi_12, _comp_12,
                              "L eta1 sin(beta1) sin(beta2) != 0", _psi_inv_12, _phys_12, _first_comp(5),
                              angle_outputs=(2,)),
}


# --- gains and parameters -----------------------------------------------------------

class Gains(NamedTuple):
    """Closed-loop poles of the linear error dynamics (Prop 8, eq 49 with the errata sign).

    Attributes:
      poles: (m, r) positive reals; output i's error obeys
        :math:`\\prod_j (d/dt + \\lambda_{ij}) \\tilde Y_i = 0`: Hurwitz by construction.
      coeffs: optional (m, r) coefficients overriding the poles (see :meth:`coefficients`).
    """

    poles: jnp.ndarray
    coeffs: Optional[jnp.ndarray] = None

    def coefficients(self):
        """(m, r) coefficients ``k[i, j]`` of ``d^j/dt^j`` (eq 49 errata, eq 13 for r = 2).

        From the real poles, unless ``coeffs`` (any Hurwitz coefficients, e.g. complex
        poles from the tuner's damping parameterisation) is given.
        """
        if self.coeffs is not None:
            return self.coeffs
        return linearize.monic_coefficients(self.poles)


class DynamicParams(NamedTuple):
    """Everything array-valued the closed loop depends on (a pytree: vmap/grad it)."""

    gains: Gains
    reference: Reference
    geometry: Geometry


class Aux(NamedTuple):
    """What a closed-loop evaluation reports besides the state derivative."""

    control: jnp.ndarray   # plant input: u (velocity level) or v (torque level)
    margin: jnp.ndarray    # |det K(X_e)|, the singularity margin (Remark 14)


@dataclasses.dataclass(frozen=True)
class DynamicLinearization:
    """A dynamic linearizing posture-tracking controller (static, hashable).

    Build it with :func:`dynamic_linearization`. Its :meth:`vector_field` is what
    :func:`wmrjax.simulate` integrates; the extended state ``z`` holds the plant state
    and the compensator (and at torque level the plant velocities through U).
    """

    extension: DynamicExtension
    level: str  # "velocity" | "torque"

    # -- static sizes --
    @property
    def robot(self) -> RobotType:
        return self.extension.robot

    @property
    def m(self) -> int:
        return self.extension.n_outputs

    @property
    def relative_degree(self) -> int:
        return self.extension.relative_degree + (1 if self.level == "torque" else 0)

    @property
    def n_state(self) -> int:
        n = self.robot.n_state + self.extension.n_comp
        return n + (self.m if self.level == "torque" else 0)

    @property
    def state_names(self) -> tuple:
        X = ("x", "y", "theta") + (("beta",) if self.robot.delta_s == 1 else ("beta1", "beta2")[: self.robot.delta_s])
        names = X + self.extension.comp_names
        return names + tuple(f"U{i + 1}" for i in range(self.m)) if self.level == "torque" else names

    # -- dynamics of the extended system --
    def _velocity_field(self, zv, U, g):
        n = self.robot.n_state
        X, c = zv[:n], zv[n:]
        u = self.extension.plant_input(X, c, U, g)
        return jnp.concatenate([robots.kinematic(self.robot, X, u, g), self.extension.compensator(X, c, U, g)])

    def field(self, z, U, g):
        """Extended dynamics ``dz/dt = F(z) + G(z) U`` (U: new inputs of this level)."""
        if self.level == "velocity":
            return self._velocity_field(z, U, g)
        nv = self.n_state - self.m
        return jnp.concatenate([self._velocity_field(z[:nv], z[nv:], g), U])

    def plant_control(self, z, U, g):
        """The physical input: u (velocity level) or v = du/dt (torque level, by jvp)."""
        n = self.robot.n_state
        pi = lambda X, c, Uv: self.extension.plant_input(X, c, Uv, g)
        if self.level == "velocity":
            return pi(z[:n], z[n:], U)
        nv = self.n_state - self.m
        zdot = self.field(z, U, g)
        return jax.jvp(pi, (z[:n], z[n:nv], z[nv:]), (zdot[:n], zdot[n:nv], U))[1]

    def outputs(self, z, g):
        return self.extension.outputs(z[:3], g)

    def jet(self, z, g):
        """``(zeta, a, K)`` of :func:`wmrjax.linearize.output_jet` at ``z``."""
        return linearize.output_jet(lambda x, U: self.field(x, U, g), lambda x: self.outputs(x, g),
                                    z, self.m, self.relative_degree)

    def psi(self, z, g):
        r"""The diffeomorphism :math:`\zeta = \Psi(X_e)` (eq 35), shape (r, m)."""
        return self.jet(z, g)[0]

    def reference_jet(self, t, params: DynamicParams):
        """``Y_ref, Y_ref', ..., Y_ref^{(r)}`` at time t, shape (r + 1, m), by autodiff."""
        ref, g = params.reference, params.geometry
        return taylor(lambda s: self.extension.outputs(ref.posture(s), g), t, self.relative_degree)

    def control(self, t, z, params: DynamicParams):
        """New input U (Prop 8) and the margin ``|det K|``.

        Returns:
          ``(U, margin)``; the division by ``det K`` is clamped at :data:`DET_FLOOR`.
        """
        g = params.geometry
        zeta, a, K = self.jet(z, g)
        yref = self.reference_jet(t, params)
        r = self.relative_degree
        k = params.gains.coefficients()            # (m, r)
        err = self._wrap_error(zeta - yref[:r])    # (r, m)
        w = yref[r]
        for j in range(r):                         # eq (49), errata sign
            w = w - k[:, j] * err[j]
        num, det = _math.adjugate_solve(K, w - a)
        return num / _math.safe_divisor(det, DET_FLOOR), self._margin(z, det, g)

    def _margin(self, z, det, g):
        m = jnp.abs(det)
        if self.extension.extra_margin is not None:
            m = m * jnp.abs(self.extension.extra_margin(z, g))
        return m

    def margin(self, z, g):
        """Singularity margin at ``z``: |det K(X_e)| (times |L sin b + e cos b| for (1,1)); 0 on the singular set."""
        return self._margin(z, jnp.linalg.det(self.jet(z, g)[2]), g)

    def vector_field(self, t, z, params: DynamicParams):
        """Closed-loop ``dz/dt`` and :class:`Aux` (plant input, margin)."""
        U, margin = self.control(t, z, params)
        g = params.geometry
        return self.field(z, U, g), Aux(self.plant_control(z, U, g), margin)

    # -- error coordinates --
    def _wrap_error(self, err):
        for i in self.extension.angle_outputs:
            err = err.at[0, i].set(_math.wrap_angle(err[0, i]))
        return err

    def error(self, t, z, params: DynamicParams):
        r""":math:`\tilde\zeta = \Psi(z) - \zeta_{ref}(t)`, shape (r, m); angle outputs wrapped."""
        return self._wrap_error(self.psi(z, params.geometry) - self.reference_jet(t, params)[: self.relative_degree])

    def error_matrix(self, gains: Gains):
        """Matrix A with :math:`\\dot{\\tilde\\zeta} = A \\tilde\\zeta` on ``error(...).reshape(-1)``."""
        return linearize.companion(gains.coefficients())

    # -- parameters and initial states --
    def params(self, reference: Reference, poles=1.0, geometry: Geometry = Geometry()) -> DynamicParams:
        """Build and validate :class:`DynamicParams`.

        Args:
          reference: a :class:`wmrjax.references.Reference`.
          poles: scalar, (r,), or (m, r) positive pole magnitudes (poles at ``-poles``).
          geometry: :class:`wmrjax.Geometry`.
        """
        p = self._checked_poles(reference, poles, geometry)
        self._check_geometry_regular(geometry)
        return DynamicParams(Gains(p), reference, geometry)

    def _checked_poles(self, reference, poles, geometry):
        """Validate the geometry, the reference type and the poles; return poles as (m, r)."""
        robots.check_geometry(geometry)
        if not isinstance(reference, Reference):
            raise ValueError(f"reference must be a wmrjax.references.Reference, got {type(reference).__name__}")
        r, m = self.relative_degree, self.m
        p = jnp.asarray(poles, dtype=jnp.result_type(float))
        if p.ndim == 0:
            p = jnp.full((m, r), p)
        elif p.shape == (r,):
            p = jnp.broadcast_to(p, (m, r))
        check_shape("poles", p, (m, r), f"one pole magnitude per output and derivative order, r = {r}")
        check_positive("poles (closed-loop poles are at -poles; they must be > 0 for a Hurwitz error dynamics)", p)
        return p

    def params_unchecked(self, reference: Reference, poles, geometry: Geometry) -> DynamicParams:
        """Like :meth:`params` without validation: for use inside ``vmap``/``jit`` (traced values)."""
        r, m = self.relative_degree, self.m
        p = jnp.broadcast_to(jnp.asarray(poles, dtype=jnp.result_type(float)), (m, r))
        return DynamicParams(Gains(p), reference, geometry)

    def _check_geometry_regular(self, g: Geometry) -> None:
        v = {k: concrete(x) for k, x in g._asdict().items()}
        if self.robot.name in ("(1,1)", "(1,2)") and v["L"] is not None and float(v["L"]) == 0.0:
            raise ValueError(f"geometry.L must be non-zero for type {self.robot.name} (Table 4: {self.extension.regularity})")

    @property
    def velocity_level(self) -> "DynamicLinearization":
        return DynamicLinearization(self.extension, "velocity")

    def inverse_psi(self, zeta, geometry: Geometry, branch=1.0):
        r""":math:`X_e = \Psi^{-1}(\zeta)` on a branch (Lemma 3 for (2,0); closed forms for the others).

        At torque level the first r - 1 rows give the velocity-level state, and the last
        row :math:`Y^{(r-1)} = a + K U` gives the new inputs U by the engine.

        Args:
          zeta: (r, m) output jet.
          geometry: :class:`Geometry`.
          branch: +1 or -1, sign of :meth:`branch_quantity`.
        """
        ext = self.extension
        if self.level == "velocity":
            return ext.psi_inverse(zeta, branch, geometry)
        vel = self.velocity_level
        zv = ext.psi_inverse(zeta[:-1], branch, geometry)
        _, a, K = vel.jet(zv, geometry)
        num, det = _math.adjugate_solve(K, zeta[-1] - a)
        return jnp.concatenate([zv, num / _math.safe_divisor(det, DET_FLOOR)])

    def branch_quantity(self, z, geometry: Geometry):
        """The quantity whose sign is the branch (chi1 for (2,0), (1,1); eta1 for (2,1), (1,2))."""
        return self.extension.branch_quantity(z, geometry)

    def reference_branch(self, params: DynamicParams) -> int:
        """Branch of the reference's virtual robot: +1 (it moves forward along its tangent).

        For (2,0) and (1,1), a heading offset of pi (moving backwards) gives -1.
        """
        off = concrete(params.reference.heading_offset)
        if self.robot.name in ("(2,0)", "(1,1)") and off is not None and np.cos(float(off)) < 0:
            return -1
        return 1

    def reference_state(self, t, params: DynamicParams):
        r""":math:`(X_e)_{ref}(t) = \Psi^{-1}(\zeta_{ref}(t))` (eq 48), on the reference's branch."""
        t = jnp.asarray(t, dtype=jnp.result_type(float))
        zeta = self.reference_jet(t, params)[: self.relative_degree]
        return self.inverse_psi(zeta, params.geometry, float(self.reference_branch(params)))

    def initial_state(self, zeta0, params: DynamicParams, branch=None):
        r"""Extended state from an initial output jet, :math:`X_e(0) = \Psi^{-1}(\zeta(0))`.

        Args:
          zeta0: (r, m) initial outputs and derivatives; for (2,0) at velocity level
            ``[[x', y'], [x'_dot, y'_dot]]`` of the point P' (= (x, y, xdot, ydot) for e = 0).
          params: the closed loop's :class:`DynamicParams` (geometry, reference).
          branch: +1 or -1 (sign of chi1 or eta1, Lemma 3); default: the reference's
            branch (Remark 17: robot and reference must share it).

        Raises:
          ValueError: if ``zeta0`` is on the singular set or on the other branch than the reference.
        """
        zeta0 = jnp.asarray(zeta0, dtype=jnp.result_type(float))
        check_shape("zeta0", zeta0, (self.relative_degree, self.m), "(Y, Y', ...) stacked by derivative order")
        check_finite("zeta0", zeta0)
        ref_branch = self.reference_branch(params)
        if branch is None:
            branch = ref_branch
        self._check_branch(branch, ref_branch)
        z0 = self.inverse_psi(zeta0, params.geometry, float(branch))
        self.check_regular(z0, params)
        return z0

    def initial_state_from_physical(self, X, u, params: DynamicParams):
        """Extended state from a physical state: posture and steering X, wheel velocities u.

        The compensator starts at rest (its derivative zero); at torque level the plant's
        velocities are part of the state.

        Raises:
          ValueError: wrong shapes, non-finite values, a singular state, or a branch that
            differs from the reference's (Remark 17).
        """
        X, u = self._physical(X, u)
        c, U = self.extension.from_physical(X, u, params.geometry)
        z = jnp.concatenate([X, c] + ([U] if self.level == "torque" else []))
        self.check_regular(z, params)
        q = float(self.branch_quantity(z, params.geometry))
        self._check_branch(1 if q >= 0 else -1, self.reference_branch(params))
        return z

    def _physical(self, X, u):
        """Validated (X, u): posture and steering angles, wheel velocities."""
        X = jnp.asarray(X, dtype=jnp.result_type(float))
        u = jnp.asarray(u, dtype=jnp.result_type(float))
        check_shape("X", X, (self.robot.n_state,), "(x, y, theta, beta...)")
        check_shape("u", u, (self.robot.n_input,), "(eta..., zeta...) wheel velocities")
        check_finite("X", X)
        check_finite("u", u)
        return X, u

    def _check_branch(self, branch, ref_branch):
        if branch not in (1, -1, 1.0, -1.0):
            raise ValueError(f"branch must be +1 or -1 (sign of the longitudinal velocity), got {branch!r}")
        if int(branch) != ref_branch:
            raise ValueError(
                f"initial branch {int(branch):+d} differs from the reference's branch {ref_branch:+d} "
                f"(sign of {'chi1' if self.robot.name in ('(2,0)', '(1,1)') else 'eta1'}); "
                "Remark 17: robot and reference must be on the same branch")

    def check_regular(self, z, params: DynamicParams, name: str = "initial state") -> None:
        """Raise ValueError if ``z`` is on (or numerically at) the singular set of Table 4."""
        zc = concrete(z)
        if zc is None:
            return
        check_shape(name, zc, (self.n_state,), " ".join(self.state_names))
        check_finite(name, zc)
        m = float(self.margin(jnp.asarray(zc), params.geometry))
        if not m > 1e3 * DET_FLOOR:
            raise ValueError(
                f"{name} is on the singular set of the {self._law} for type {self.robot.name}: "
                f"margin |det K| = {m:.3g}; {self._table} requires {self.extension.regularity}")

    _law = "dynamic linearizing law"
    _table = "Table 4"

    def reference_margins(self, params: DynamicParams, t_final, n: int = 201, t0=0.0):
        """Margin and branch quantity of :math:`(X_e)_{ref}(t)` on a uniform grid of n times."""
        ts = jnp.linspace(t0, t_final, n)
        zr = jax.vmap(lambda t: self.reference_state(t, params))(ts)
        g = params.geometry
        return ts, jax.vmap(lambda z: self.margin(z, g))(zr), jax.vmap(lambda z: self.branch_quantity(z, g))(zr)

    def check_reference(self, params: DynamicParams, t_final, n: int = 201, floor: float = 1e-6) -> None:
        """Raise ValueError if the reference reaches the singular set on [0, t_final].

        The reference's own extended state must stay regular (Lemma 2, condition 2) and
        on one branch (Remark 17); a reference that stops (zero speed) fails.
        """
        ts, m, q = (np.asarray(a) for a in self.reference_margins(params, t_final, n))
        bad = ~np.isfinite(m) | (m <= floor) | (np.sign(q) != self.reference_branch(params))
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(
                f"reference {params.reference.name!r} reaches the singular set of type {self.robot.name} at "
                f"t = {ts[i]:.3g} s (margin {m[i]:.3g}); Table 4 requires {self.extension.regularity} along "
                "the reference (it must not stop or reverse)")


LEVELS = ("velocity", "torque")


def dynamic_linearization(robot, level: str = "velocity") -> DynamicLinearization:
    """The dynamic linearizing posture-tracking controller of Table 4 for a robot type.

    Args:
      robot: one of "(2,0)", "(2,1)", "(1,1)", "(1,2)" (or a :class:`RobotType`).
      level: "velocity" (kinematic model 5) or "torque" (model 8, via Lemma 1).

    Raises:
      ValueError: unknown type or level, or type (3,0), which needs no dynamic extension
        (Prop 3: static linearization solves posture tracking).
    """
    rt = robots.robot_type(robot)
    if rt.name not in EXTENSIONS:
        raise ValueError(f"type {rt.name} has no dynamic extension in Table 4; "
                         f"expected one of {sorted(EXTENSIONS)} (type (3,0) is statically linearizable, Prop 3)")
    if level not in LEVELS:
        raise ValueError(f"level must be one of {LEVELS}, got {level!r}")
    return DynamicLinearization(EXTENSIONS[rt.name], level)
