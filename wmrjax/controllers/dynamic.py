r"""Dynamic feedback linearization for posture tracking (paper §5, Table 4, Props 7-9).

Each row of Table 4 is a :class:`Table4Row`, built by keyword: the mechanics of the
extension (:class:`wmrjax.controllers.law.Extension`: outputs, compensator, how the new
inputs drive the plant) and every fact that differs by robot type -- the regularity
condition, the closed-form :math:`\Psi^{-1}`, the branch rule (Remark 17), the pieces of
the singular set and the distance to it in :math:`\zeta` coordinates (Remark 16, which
gives :math:`M_1`), the geometry the law needs, and a default geometry for examples.
Everything else -- :math:`\zeta = \Psi(X_e)`, K and the drift, the auxiliary law (49) --
comes from the one generic law of :mod:`wmrjax.controllers.law`, at velocity and torque
level (Lemma 1).

Extended state ``z`` (unbatched vector):

* velocity level: ``z = (X, c)``; plant input ``u = plant_input(X, c, U)``;
* torque level: ``z = (X, c, U)``; plant input ``v = du/dt`` along the flow.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math, robots
from wmrjax._validate import check_finite, check_real, check_shape, concrete
from wmrjax.controllers.law import (
    DET_FLOOR,
    Extension,
    Level,
    LinearizingController,
    Requirement,
    check_level,
    check_reference_type,
    check_requirements,
    make_gains,
    physical_state_names,
    validated_physical,
)
from wmrjax.gains import Gains
from wmrjax.references import Reference, taylor
from wmrjax.robots import Geometry, RobotType

# --- Table 4: the extensions -------------------------------------------------------------


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


def _out_posture(X, g):
    del g
    return X[:3]


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
    return g.L * s + g.e * co, g.L * co - g.e * s  # chi1 = eta1 * lever, and d lever / d beta


def _comp_11(X, c, U, g):
    lever, dlever = _lever_11(X[3], g)
    eta1_dot = (c[1] - c[0] * U[1] * dlever) / _math.safe_divisor(lever, DET_FLOOR)  # Table 4 footnote
    return jnp.stack([eta1_dot, U[0]])


def _psi_inv_11(zeta, branch, g):
    """The law's state (posture and compensator) from the output jet, with h = P' on the fixed axle: chi1 = +-|h'|, theta from h', then beta and eta1 from
    theta' = eta1 cos(beta) and chi1 - e theta' = eta1 L sin(beta), with eta1 > 0."""
    hd, hdd = zeta[1], zeta[2]
    th = jnp.arctan2(-branch * hd[0], branch * hd[1])
    s, c = _math.sincos(th)
    chi1 = branch * jnp.sqrt(hd[0] ** 2 + hd[1] ** 2)
    chi2 = -s * hdd[0] + c * hdd[1]  # h'' = chi2 (-s, c) - chi1 theta' (c, s)
    thd = -(c * hdd[0] + s * hdd[1]) / chi1
    a, b = (chi1 - g.e * thd) / g.L, thd  # eta1 sin(beta), eta1 cos(beta)
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
    vb1, vb2 = c * xd + s * yd, -s * xd + c * yd  # body-frame velocity of P
    v1x, v1y = vb1, vb2 + thd * g.L  # wheel 1 at (L, 0)
    v2x, v2y = vb1, vb2 - thd * g.L  # wheel 2 at (-L, 0)
    b1 = jnp.arctan(-v1x / v1y)  # direction mod pi, in (-pi/2, pi/2)
    b2 = jnp.arctan(-v2x / v2y)
    s1, c1 = _math.sincos(b1)
    s2, c2 = _math.sincos(b2)
    mu1 = -s1 * v1x + c1 * v1y  # signed speed of wheel 1 = 2 L eta1 sin b2
    eta1 = mu1 / (2.0 * g.L * s2)
    # branch: flipping beta1 by pi flips the sign of eta1 (Sigma -> -Sigma)
    flip = jnp.sign(eta1) != branch
    b1 = jnp.where(flip, b1 - jnp.pi * jnp.sign(b1 + 1e-300), b1)
    eta1 = jnp.where(flip, -eta1, eta1)
    return jnp.stack([x, y, th, b1, b2, eta1])


def _phys_12(X, u, g):
    return u[:1], jnp.stack([jnp.zeros_like(u[0]), u[1], u[2]])


def _chi1_11(z, g):
    return z[4] * _lever_11(z[3], g)[0]


def _first_comp(z, g, n_x):
    return z[n_x]  # first compensator state: chi1 (2,0), eta1 (2,1), (1,2)


# --- Table 4: the singular sets (Remark 16) -----------------------------------------------


def _distance_point_speed(jet, g, within=None):
    r"""Distance in :math:`\zeta` coordinates to :math:`\{\dot h_1 = \dot h_2 = 0\}` (the output
    point at rest): :math:`\|\dot h\|` (Lemma 3, eq 59), for (2,0), (2,1), (1,1). At torque
    level the higher rows can be matched on the singular set, so the same formula holds.
    With ``within``, :math:`\min(d, \text{within})`."""
    del g
    d = jnp.sqrt(jnp.sum(jet[1, :2] ** 2))
    return d if within is None else jnp.minimum(d, within)


def _distance_lateral_velocity(jet, g, within=None):
    r"""Distance in :math:`\zeta` coordinates to the singular set of (1,2).

    :math:`\eta_1\sin\beta_1\sin\beta_2 = 0` exactly when the body-frame lateral velocity of
    P vanishes (both wheels' lateral components equal it), i.e. on the curved hypersurface
    :math:`\sigma(\zeta) = \cos\theta\,\dot h_1 + \sin\theta\,\dot h_2 + e\sin\delta\,\dot\theta = 0`.
    For fixed :math:`\theta` it is a hyperplane in :math:`(\dot h_1, \dot h_2, \dot\theta)` with
    normal :math:`(\cos\theta, \sin\theta, e\sin\delta)`, so
    :math:`d^2 = \min_\theta (\theta - \theta_0)^2 + \sigma_\theta(\zeta)^2 / (1 + e^2\sin^2\delta)`,
    a one-dimensional minimisation (grid over a full turn, then golden section).

    With ``within`` (a static float), returns :math:`\min(d, w)` with ``w = within``, several
    times cheaper: only headings within w of :math:`\theta_0` are searched (a 21-point grid,
    then four safeguarded Newton steps with the closed-form derivatives instead of 60
    golden-section steps). That is exact: a heading further away contributes at least
    :math:`w^2` to :math:`d^2`. Rollouts measuring the approach to the singular set use it.
    """
    es = g.e * jnp.sin(g.delta)
    th_r, v = jet[0, 2], jet[1]
    c2 = 1.0 + es**2

    def d2(dth):
        s, c = jnp.sin(th_r + dth), jnp.cos(th_r + dth)
        sig = c * v[0] + s * v[1] + es * v[2]
        return dth**2 + sig**2 / c2

    if within is None:
        grid = jnp.linspace(-math.pi, math.pi, 721)
        vals = jax.vmap(d2)(grid)
        i = jnp.argmin(vals)
        lo, hi = grid[jnp.maximum(i - 1, 0)], grid[jnp.minimum(i + 1, grid.shape[0] - 1)]
        lo, hi = _math.golden_section(d2, lo, hi, 60)
        return jnp.sqrt(jnp.minimum(d2(0.5 * (lo + hi)), vals[i]))
    half = min(math.pi, float(within))
    grid = jnp.linspace(-half, half, 21)
    vals = jax.vmap(d2)(grid)
    i = jnp.argmin(vals)
    h = grid[1] - grid[0]
    lo, hi = grid[i] - h, grid[i] + h
    x = grid[i]
    for _ in range(4):  # Newton on d2' = 2 x + 2 sig sig' / c2, safeguarded to the bracket
        s, c = jnp.sin(th_r + x), jnp.cos(th_r + x)
        sig = c * v[0] + s * v[1] + es * v[2]
        dsig = -s * v[0] + c * v[1]
        g1 = 2.0 * x + 2.0 * sig * dsig / c2
        g2 = 2.0 + 2.0 * (dsig**2 - sig * (sig - es * v[2])) / c2
        step = jnp.where(g2 > 0, -g1 / jnp.where(g2 > 0, g2, 1.0), -jnp.sign(g1) * 0.25 * h)
        x = jnp.clip(x + step, lo, hi)
    return jnp.minimum(jnp.sqrt(jnp.minimum(d2(x), vals[i])), within)


def _families_first_comp(n_x):
    return lambda g: [(n_x, 0.0)]


def _families_11(g):
    return [(4, 0.0), (3, jnp.arctan2(-g.e, g.L))]  # eta1 = 0; lever L sin(beta) + e cos(beta) = 0


def _families_12(g):
    return [(5, 0.0), (3, 0.0), (4, 0.0)]  # eta1 = 0, beta1 = 0, beta2 = 0


_L_NONZERO = Requirement("L", "nonzero", "Table 4: det K is proportional to L")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Table4Row:
    """One row of Table 4 and every per-type fact the dynamic law and its certificates need.

    Attributes:
      extension: outputs, compensator and plant input (:class:`Extension`).
      regularity: Table 4's condition (with errata), for messages.
      psi_inverse: closed form ``(zeta, branch, geometry) -> z`` at velocity level, on the
        branch where :attr:`branch_quantity` has the sign ``branch`` (+1 or -1).
      from_physical: ``(X, u, geometry) -> (c, U)``: compensator state and new inputs
        matching a physical state with the compensator at rest (its derivative zero).
      branch_quantity: ``(z, geometry) -> scalar`` whose sign labels the branch (Remark 17).
      branch_name: its name ("chi1" or "eta1").
      branch_follows_heading: True where the branch is the sign of the velocity along the
        heading ((2,0), (1,1)): a reference heading offset by pi (moving backwards) is on
        branch -1. False where the heading is an output ((2,1), (1,2)).
      singular_families: ``geometry -> [(state index, pinned value), ...]``: the pieces of
        the singular set (Remark 16's numerical M1 searches each).
      singular_set_is_linear: True where the singular set in zeta coordinates is the linear
        subspace {velocity of the output point = 0} (exact-map radius applies).
      singular_distance: ``(jet, geometry, within=None) -> scalar``: distance from the output
        jet (rows 0 and 1 used) to the singular set in zeta coordinates; M1 of the reference.
        With a float ``within``, ``min(distance, within)``, which may be cheaper.
      requires: geometry :class:`Requirement` s of the regularity condition.
      default_geometry: the geometry used by the examples and experiments [m, m, rad].
      paper_geometry: the geometry of the paper's own examples of this type (§6: (2,0) with
        e = 0), None where the paper has none.
      default_heading_offset: a reference heading offset [rad] keeping the reference
        regular on the default geometry (non-zero where a crab angle is needed).
    """

    extension: Extension
    regularity: str
    psi_inverse: Callable = dataclasses.field(repr=False)
    from_physical: Callable = dataclasses.field(repr=False)
    branch_quantity: Callable = dataclasses.field(repr=False)
    branch_name: str
    branch_follows_heading: bool
    singular_families: Callable = dataclasses.field(repr=False)
    singular_set_is_linear: bool
    singular_distance: Callable = dataclasses.field(repr=False)
    requires: tuple = ()
    default_geometry: Geometry = Geometry()
    paper_geometry: Geometry | None = None
    default_heading_offset: float = 0.0

    @property
    def robot(self) -> RobotType:
        """The robot type of the law's row."""
        return self.extension.robot


TABLE4: dict[str, Table4Row] = {
    row.robot.name: row
    for row in (
        Table4Row(
            extension=Extension(
                robot=robots.TYPES["(2,0)"],
                outputs=_out_axle_point,
                relative_degree=2,
                n_comp=1,
                comp_names=("chi1",),
                plant_input=_pi_20,
                compensator=_comp_20,
            ),
            regularity="chi1 = eta1 + e eta2 != 0",
            psi_inverse=_psi_inv_20,
            from_physical=_phys_20,
            branch_quantity=functools.partial(_first_comp, n_x=3),
            branch_name="chi1",
            branch_follows_heading=True,
            singular_families=_families_first_comp(3),
            singular_set_is_linear=True,
            singular_distance=_distance_point_speed,
            default_geometry=Geometry(e=0.2),
            paper_geometry=Geometry(e=0.0),
        ),
        Table4Row(
            extension=Extension(
                robot=robots.TYPES["(2,1)"],
                outputs=_out_posture,
                relative_degree=2,
                n_comp=2,
                comp_names=("eta1", "eta2"),
                plant_input=_pi_21,
                compensator=_comp_21,
                angle_outputs=(2,),
            ),
            regularity="eta1 != 0",
            psi_inverse=_psi_inv_21,
            from_physical=_phys_21,
            branch_quantity=functools.partial(_first_comp, n_x=4),
            branch_name="eta1",
            branch_follows_heading=False,
            singular_families=_families_first_comp(4),
            singular_set_is_linear=True,
            singular_distance=_distance_point_speed,
            default_geometry=Geometry(),
            default_heading_offset=0.3,
        ),
        Table4Row(
            extension=Extension(
                robot=robots.TYPES["(1,1)"],
                outputs=_out_axle_point,
                relative_degree=3,
                n_comp=2,
                comp_names=("eta1", "chi2"),
                plant_input=_pi_11,
                compensator=_comp_11,
                extra_margin=_margin_11,
            ),
            regularity="eta1 (L sin beta + e cos beta) != 0 (errata: Table 4 prints only eta1 != 0)",
            psi_inverse=_psi_inv_11,
            from_physical=_phys_11,
            branch_quantity=_chi1_11,
            branch_name="chi1",
            branch_follows_heading=True,
            singular_families=_families_11,
            singular_set_is_linear=True,
            singular_distance=_distance_point_speed,
            requires=(_L_NONZERO,),
            default_geometry=Geometry(L=1.0, e=0.3),
        ),
        Table4Row(
            extension=Extension(
                robot=robots.TYPES["(1,2)"],
                outputs=_out_12,
                relative_degree=2,
                n_comp=1,
                comp_names=("eta1",),
                plant_input=_pi_12,
                compensator=_comp_12,
                angle_outputs=(2,),
            ),
            regularity="L eta1 sin(beta1) sin(beta2) != 0",
            psi_inverse=_psi_inv_12,
            from_physical=_phys_12,
            branch_quantity=functools.partial(_first_comp, n_x=5),
            branch_name="eta1",
            branch_follows_heading=False,
            singular_families=_families_12,
            singular_set_is_linear=False,
            singular_distance=_distance_lateral_velocity,
            requires=(_L_NONZERO,),
            default_geometry=Geometry(L=0.5, e=0.3, delta=0.5),
            default_heading_offset=0.5,
        ),
    )
}
"""Table 4: robot type name -> its dynamic linearization's :class:`Table4Row`."""


# --- parameters and the controller --------------------------------------------------------


class DynamicParams(NamedTuple):
    """Everything array-valued the closed loop depends on (a pytree: vmap/grad it)."""

    gains: Gains
    reference: Reference
    geometry: Geometry


@dataclasses.dataclass(frozen=True)
class DynamicLinearization(LinearizingController):
    """A dynamic linearizing posture-tracking controller (static, hashable).

    Build it with :func:`dynamic_linearization` or :func:`wmrjax.controller`. Its
    :meth:`vector_field` is what :func:`wmrjax.simulate` integrates; the extended state
    ``z`` holds the plant state and the compensator (and at torque level the plant
    velocities through U). Methods take ``(t, z, params)`` or ``(z, params)``.
    """

    row: Table4Row
    level: Level

    _law_name = "dynamic linearizing law"
    _table = "Table 4"
    _params_type = DynamicParams

    @property
    def _reference_requirement(self) -> str:
        return self.row.regularity

    @property
    def state_names(self) -> tuple:
        """The names of the state's components: the posture, the compensator's, and at torque level the wheel inputs."""
        names = physical_state_names(self.robot) + self.row.extension.comp_names
        return names + tuple(f"U{i + 1}" for i in range(self.m)) if self.level == Level.TORQUE else names

    @property
    def velocity_level(self) -> "DynamicLinearization":
        """The same law at velocity level."""
        return DynamicLinearization(self.row, Level.VELOCITY)

    def reference_jet(self, t, params: DynamicParams):
        """``Y_ref, Y_ref', ..., Y_ref^{(r)}`` at time t, shape (r + 1, m), by autodiff."""
        ref, g = params.reference, params.geometry
        return taylor(lambda s: self.row.extension.outputs(ref.posture(s), g), t, self.relative_degree)

    def singular_distance(self, jet, params, within=None):
        """Distance from an output jet (r, m) to the singular set in zeta coordinates (Remark 16).

        ``within`` (a static float, optional): return ``min(distance, within)``, cheaper for the
        curved set of (1,2), which is then searched locally."""
        return self.row.singular_distance(jet, params.geometry, within)

    # -- parameters --
    def params(
        self, reference: Reference, poles=1.0, geometry: Geometry = Geometry(), *, gains: Gains | None = None
    ) -> DynamicParams:
        """Build and validate :class:`DynamicParams`.

        Args:
          reference: a :class:`wmrjax.references.Reference`.
          poles: scalar, (r,), or (m, r) positive real pole magnitudes (poles at ``-poles``).
          geometry: :class:`wmrjax.Geometry` (``row.default_geometry`` is the experiments' choice).
          gains: a :class:`wmrjax.Gains` instead of ``poles`` (e.g. complex pole pairs).

        Raises:
          ValueError: a bad reference, geometry or gains.
        """
        robots.check_geometry(geometry)
        check_reference_type(reference)
        check_requirements(self.row.requires, geometry, f"type {self.robot.name} ({self.row.regularity})")
        with jax.ensure_compile_time_eval():
            v0 = concrete(reference.velocity(jnp.zeros((), jnp.result_type(float))))
        if v0 is not None and not (np.all(np.isfinite(v0)) and np.hypot(*v0) > 1e-9):
            raise ValueError(
                f"reference {reference.name!r} is at rest at t = 0 (velocity {np.asarray(v0).tolist()} m/s): "
                f"Table 4 requires a moving reference ({self.row.regularity} along it); its heading "
                "is the path tangent, undefined at a stop"
            )
        return DynamicParams(make_gains(gains, poles, self.m, self.relative_degree), reference, geometry)

    def params_unchecked(self, reference: Reference, poles, geometry: Geometry) -> DynamicParams:
        """Like :meth:`params` without validation: for use inside ``vmap``/``jit`` (traced values)."""
        return DynamicParams(self._unchecked_gains(poles), reference, geometry)

    # -- Psi^-1, branches, initial states --
    def inverse_psi(self, zeta, params, branch=1.0):
        r""":math:`X_e = \Psi^{-1}(\zeta)` on a branch (Lemma 3 for (2,0); closed forms for the others).

        At torque level the first r - 1 rows give the velocity-level state, and the last
        row :math:`Y^{(r-1)} = a + K U` gives the new inputs U by the engine.

        Args:
          zeta: (r, m) output jet.
          params: the closed loop's parameters (its geometry is used).
          branch: +1 or -1, sign of :meth:`branch_quantity`.
        """
        g = params.geometry
        if self.level == Level.VELOCITY:
            return self.row.psi_inverse(zeta, branch, g)
        zv = self.row.psi_inverse(zeta[:-1], branch, g)
        return jnp.concatenate([zv, self.law.velocity_level.solve_top(zv, zeta[-1], g)])

    def branch_quantity(self, z, params):
        """The quantity whose sign is the branch (chi1 for (2,0), (1,1); eta1 for (2,1), (1,2))."""
        return self.row.branch_quantity(z, params.geometry)

    def reference_branch(self, params: DynamicParams):
        """Branch of the reference's virtual robot: +1 (it moves forward along its tangent).

        Where the branch follows the heading ((2,0), (1,1)), a heading offset of pi (moving
        backwards) gives -1. An int for a concrete offset; a traced offset (inside ``jit`` or
        ``vmap``) gives the same rule as a traced float (it used to give +1 there, so the
        reference check, a compiled program, refused every reference with offset pi).
        """
        if not self.row.branch_follows_heading:
            return 1
        off = params.reference.heading_offset
        c = concrete(off)
        if c is None:  # traced (the reference check's compiled program, vmap over offsets): the same rule
            return jnp.where(jnp.cos(off) < 0, -1.0, 1.0)
        return -1 if np.cos(float(c)) < 0 else 1

    def reference_state(self, t, params: DynamicParams):
        r""":math:`(X_e)_{ref}(t) = \Psi^{-1}(\zeta_{ref}(t))` (eq 48), on the reference's branch."""
        t = jnp.asarray(t, dtype=jnp.result_type(float))
        zeta = self.reference_jet(t, params)[: self.relative_degree]
        return self.inverse_psi(zeta, params, self.reference_branch(params))

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
        check_real("zeta0", zeta0)
        zeta0 = jnp.asarray(zeta0, dtype=jnp.result_type(float))
        check_shape("zeta0", zeta0, (self.relative_degree, self.m), "(Y, Y', ...) stacked by derivative order")
        check_finite("zeta0", zeta0)
        ref_branch = self.reference_branch(params)
        if branch is None:
            branch = ref_branch
        if concrete(ref_branch) is not None:  # a traced offset's branch is checked where it is concrete
            self._check_branch(branch, ref_branch)
        z0 = self.inverse_psi(zeta0, params, jnp.asarray(branch, jnp.result_type(float)))
        self.check_regular(z0, params)
        return z0

    def physical_state(self, X, u, params):
        """Extended state from a physical state, no checks (pure: jit/vmap it).

        The compensator starts at rest (its derivative zero); at torque level the plant's
        velocities enter through U.
        """
        c, U = self.row.from_physical(X, u, params.geometry)
        return jnp.concatenate([X, c] + ([U] if self.level == Level.TORQUE else []))

    def initial_state_from_physical(self, X, u, params: DynamicParams):
        """Extended state from a physical state: posture and steering X, wheel velocities u.

        Works under ``jax.vmap``/``jit`` (the checks then apply to concrete values only)
        and compiles once per controller.

        Raises:
          ValueError: wrong shapes, non-finite values, a singular state, or a branch that
            differs from the reference's (Remark 17).
        """
        X, u = validated_physical(self.robot, X, u)
        z, q = _physical_jit(self, X, u, params)
        self.check_regular(z, params)
        qc = concrete(q)
        if qc is not None:
            self._check_branch(1 if qc >= 0 else -1, self.reference_branch(params))
        return z

    def _check_branch(self, branch, ref_branch):
        if branch not in (1, -1, 1.0, -1.0):
            raise ValueError(f"branch must be +1 or -1 (sign of the longitudinal velocity), got {branch!r}")
        if int(branch) != ref_branch:
            raise ValueError(
                f"initial branch {int(branch):+d} differs from the reference's branch {ref_branch:+d} "
                f"(sign of {self.row.branch_name}); Remark 17: robot and reference must be on the same branch"
            )

    def reference_margins(self, params: DynamicParams, t_final, n: int = 201, t0=0.0):
        """Margin and branch quantity of :math:`(X_e)_{ref}(t)` on a uniform grid of n times."""
        ts = jnp.linspace(t0, t_final, n)
        zr = jax.vmap(lambda t: self.reference_state(t, params))(ts)
        return (
            ts,
            jax.vmap(lambda z: self.margin(z, params))(zr),
            jax.vmap(lambda z: self.branch_quantity(z, params))(zr),
        )

    def reference_regularity(self, t, params: DynamicParams):
        """Margin and branch quantity of the reference's extended state at time t (Lemma 2, condition 2)."""
        z = self.reference_state(t, params)
        return self.margin(z, params), self.branch_quantity(z, params)


@functools.partial(jax.jit, static_argnums=0)
def _physical_jit(ctrl, X, u, params):
    z = ctrl.physical_state(X, u, params)
    return z, ctrl.branch_quantity(z, params)


def dynamic_linearization(robot, level: Level | str = Level.VELOCITY) -> DynamicLinearization:
    """The dynamic linearizing posture-tracking controller of Table 4 for a robot type.

    Args:
      robot: one of "(2,0)", "(2,1)", "(1,1)", "(1,2)" (or a :class:`RobotType`).
      level: "velocity" (kinematic model 5) or "torque" (model 8, via Lemma 1).

    Raises:
      ValueError: unknown type or level, or type (3,0), which needs no dynamic extension
        (Prop 3: static linearization solves posture tracking).
    """
    rt = robots.robot_type(robot)
    if rt.name not in TABLE4:
        raise ValueError(
            f"type {rt.name} has no dynamic extension in Table 4; "
            f"expected one of {sorted(TABLE4)} (type (3,0) is statically linearizable, Prop 3)"
        )
    return DynamicLinearization(TABLE4[rt.name], check_level(level))
