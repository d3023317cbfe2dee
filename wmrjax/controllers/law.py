r"""What every linearizing controller shares: the closed-loop protocol and one law.

* :class:`ClosedLoop` is all :func:`wmrjax.simulate` needs: ``vector_field``, optionally
  ``post_step``, and the state's size and names.
* :class:`Extension` is the mechanics of one table row at velocity level: the outputs, the
  compensator states that delay some input combinations, and how the new inputs U drive
  the plant (Table 4). A static law (Table 3) is the same with no compensator and U = u.
* :class:`LinearizingLaw` derives everything else from an extension and a level by the
  generic engine of :mod:`wmrjax.linearize`: the diffeomorphism :math:`\zeta = \Psi(X_e)`
  (eq 35), the decoupling matrix and drift, and the auxiliary law (49) with the errata sign,
  at velocity level (kinematic model 5) and at torque level (model 8) by the cascade of
  Lemma 1: the torque-level state appends the velocity-level new inputs U and takes
  :math:`V = \dot U` as input, with the same outputs, relative degrees one higher and the
  same decoupling matrix.

:class:`wmrjax.controllers.DynamicLinearization` and
:class:`wmrjax.controllers.StaticLinearization` are siblings that each hold a law (by
composition) plus their table's per-type facts.

State ``z`` of a law (unbatched vector): ``(X, c)`` at velocity level, ``(X, c, U)`` at
torque level; the plant input is ``u = plant_input(X, c, U)`` (velocity level) or
:math:`v = \dot u` along the flow (torque level).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Callable, NamedTuple, Protocol, runtime_checkable

import jax
import jax.numpy as jnp

from wmrjax import _math, linearize, robots
from wmrjax._validate import check_finite, check_shape, concrete
from wmrjax.gains import Gains
from wmrjax.references import Reference
from wmrjax.robots import Geometry, RobotType

# |det K| below this is treated as singular inside the law (the division is clamped);
# runs report the true margin so such events are flagged.
DET_FLOOR = 1e-12

LEVELS = ("velocity", "torque")


class Aux(NamedTuple):
    """What a closed-loop evaluation reports besides the state derivative."""

    control: jnp.ndarray   # plant input: u (velocity level) or v (torque level)
    margin: jnp.ndarray    # singularity margin (|det K| for the linearizing laws; Remark 14)


@runtime_checkable
class ClosedLoop(Protocol):
    """The closed-loop protocol of :func:`wmrjax.simulate` (static, hashable objects).

    Attributes:
      n_state: size of the (flattened) state.
      state_names: one name per flattened state component.

    Methods:
      vector_field(t, z, params) -> (dz/dt, Aux): ``z`` and ``dz/dt`` share one pytree
        structure; integer leaves are discrete state (held constant by the integrator).
      post_step(t, z, params) -> z (optional): a discrete transition after every step.
    """

    n_state: int
    state_names: tuple

    def vector_field(self, t, z, params: Any) -> tuple[Any, Aux]: ...


# --- geometry requirements (keyword facts of the table rows) -------------------------------

@dataclasses.dataclass(frozen=True)
class Requirement:
    """A condition on one geometry constant, for the rows' regularity conditions.

    Attributes:
      field: "L", "e" or "delta".
      test: "nonzero" (value != 0) or "sin_nonzero" (value != k pi).
      why: the table's words, for the error message.
    """

    field: str
    test: str
    why: str

    def violated(self, g: Geometry) -> bool:
        v = concrete(getattr(g, self.field))
        if v is None:
            return False
        v = float(v)
        return v == 0.0 if self.test == "nonzero" else abs(math.sin(v)) < 1e-12


def check_requirements(requirements, g: Geometry, where: str) -> None:
    """ValueError naming the first requirement the (concrete) geometry violates."""
    for req in requirements:
        if req.violated(g):
            what = "!= 0" if req.test == "nonzero" else "!= k pi"
            raise ValueError(f"{where}: geometry.{req.field} must be {what} ({req.why}); "
                             f"got {req.field} = {float(getattr(g, req.field))!r}")


# --- the mechanics of a table row -----------------------------------------------------------

def _identity_input(X, c, U, g):
    return U


def _no_compensator(X, c, U, g):
    return U[:0]


@dataclasses.dataclass(frozen=True, kw_only=True)
class Extension:
    """A row's affine extended system at velocity level (static description).

    Attributes:
      robot: the robot type.
      outputs: ``(X, geometry) -> Y`` linearizing outputs, shape (m,).
      relative_degree: r of every output at velocity level.
      n_comp: number of compensator states c (0: static law).
      comp_names: their names (for reports).
      plant_input: ``(X, c, U, geometry) -> u``, affine in U (identity for a static law).
      compensator: ``(X, c, U, geometry) -> dc/dt``, affine in U.
      angle_outputs: which outputs are angles: their zeroth-order error is wrapped to
        [-pi, pi) (errata: integrate angles unwrapped, wrap only errors).
      extra_margin: optional ``(z, geometry) -> scalar`` multiplying |det K| in the
        singularity margin, for a singular set that |det K| alone misses (the (1,1) lever
        L sin(beta) + e cos(beta), errata).
    """

    robot: RobotType
    outputs: Callable = dataclasses.field(repr=False)
    relative_degree: int
    n_comp: int = 0
    comp_names: tuple = ()
    plant_input: Callable = dataclasses.field(default=_identity_input, repr=False)
    compensator: Callable = dataclasses.field(default=_no_compensator, repr=False)
    angle_outputs: tuple = ()
    extra_margin: Callable | None = dataclasses.field(default=None, repr=False)

    @property
    def n_outputs(self) -> int:
        return self.robot.n_input  # square: m outputs, m new inputs


@dataclasses.dataclass(frozen=True)
class LinearizingLaw:
    """The generic linearizing law of one extension at one level (static, hashable)."""

    extension: Extension
    level: str  # "velocity" | "torque"

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
    def n_velocity_state(self) -> int:
        return self.robot.n_state + self.extension.n_comp

    @property
    def n_state(self) -> int:
        return self.n_velocity_state + (self.m if self.level == "torque" else 0)

    @property
    def velocity_level(self) -> "LinearizingLaw":
        return LinearizingLaw(self.extension, "velocity")

    def _velocity_field(self, zv, U, g):
        n = self.robot.n_state
        X, c = zv[:n], zv[n:]
        u = self.extension.plant_input(X, c, U, g)
        xdot = robots.kinematic(self.robot, X, u, g)
        return jnp.concatenate([xdot, self.extension.compensator(X, c, U, g)]) if self.extension.n_comp else xdot

    def field(self, z, U, g):
        """Extended dynamics ``dz/dt = F(z) + G(z) U`` (U: new inputs of this level)."""
        if self.level == "velocity":
            return self._velocity_field(z, U, g)
        nv = self.n_velocity_state
        return jnp.concatenate([self._velocity_field(z[:nv], z[nv:], g), U])

    def plant_control(self, z, U, g):
        """The physical input: u (velocity level) or v = du/dt (torque level, by jvp)."""
        n, nv = self.robot.n_state, self.n_velocity_state
        pi = lambda X, c, Uv: self.extension.plant_input(X, c, Uv, g)
        if self.level == "velocity":
            return pi(z[:n], z[n:], U)
        zdot = self.field(z, U, g)
        return jax.jvp(pi, (z[:n], z[n:nv], z[nv:]), (zdot[:n], zdot[n:nv], U))[1]

    def outputs(self, z, g):
        return self.extension.outputs(z[: self.robot.n_state], g)

    def jet(self, z, g):
        """``(zeta, a, K)`` of :func:`wmrjax.linearize.output_jet` at ``z``."""
        return linearize.output_jet(lambda x, U: self.field(x, U, g), lambda x: self.outputs(x, g),
                                    z, self.m, self.relative_degree)

    def wrap_error(self, err):
        """Wrap the zeroth-order error of angle outputs to [-pi, pi)."""
        for i in self.extension.angle_outputs:
            err = err.at[0, i].set(_math.wrap_angle(err[0, i]))
        return err

    def margin_from_det(self, z, det, g):
        """Singularity margin from ``det K``: |det K| (times the extension's extra factor)."""
        m = jnp.abs(det)
        if self.extension.extra_margin is not None:
            m = m * jnp.abs(self.extension.extra_margin(z, g))
        return m

    def margin(self, z, g):
        """Singularity margin at ``z``; 0 on the singular set."""
        return self.margin_from_det(z, jnp.linalg.det(self.jet(z, g)[2]), g)

    def control(self, yref, z, coeffs, g):
        """New input U of the auxiliary law (49, errata sign) and the singularity margin.

        Args:
          yref: (r + 1, m) reference outputs and their derivatives up to order r.
          z: state. coeffs: (m, r) Hurwitz coefficients. g: geometry.

        Returns:
          ``(U, margin)``; the division by ``det K`` is clamped at :data:`DET_FLOOR`.
        """
        zeta, a, K = self.jet(z, g)
        r = self.relative_degree
        err = self.wrap_error(zeta - yref[:r])
        w = yref[r]
        for j in range(r):
            w = w - coeffs[:, j] * err[j]
        num, det = _math.adjugate_solve(K, w - a)
        return num / _math.safe_divisor(det, DET_FLOOR), self.margin_from_det(z, det, g)

    def closed_loop(self, yref, z, coeffs, g):
        """Closed-loop ``dz/dt`` and :class:`Aux` (plant input, margin) under :meth:`control`."""
        U, margin = self.control(yref, z, coeffs, g)
        return self.field(z, U, g), Aux(self.plant_control(z, U, g), margin)

    def error(self, yref, z, g):
        r""":math:`\Psi(z) - \zeta_{ref}`, shape (r, m), angle outputs wrapped (``yref``: (>= r, m))."""
        return self.wrap_error(self.jet(z, g)[0] - yref[: self.relative_degree])

    def solve_top(self, z, target, g):
        """U with ``Y^{(r)} = a(z) + K(z) U = target`` (clamped at :data:`DET_FLOOR`)."""
        _, a, K = self.jet(z, g)
        num, det = _math.adjugate_solve(K, target - a)
        return num / _math.safe_divisor(det, DET_FLOOR)


# --- helpers shared by the sibling controllers -------------------------------------------

def physical_state_names(robot: RobotType) -> tuple:
    """Names of the kinematic state X = (x, y, theta, beta...)."""
    beta = ("beta",) if robot.delta_s == 1 else ("beta1", "beta2")[: robot.delta_s]
    return ("x", "y", "theta") + beta


def validated_physical(robot: RobotType, X, u):
    """(X, u) as float arrays, with a ValueError for wrong shapes or non-finite values (concrete only)."""
    X = jnp.asarray(X, dtype=jnp.result_type(float))
    u = jnp.asarray(u, dtype=jnp.result_type(float))
    check_shape("X", X, (robot.n_state,), "(x, y, theta, beta...)")
    check_shape("u", u, (robot.n_input,), "(eta..., zeta...) wheel velocities")
    check_finite("X", X)
    check_finite("u", u)
    return X, u


def make_gains(gains, poles, m: int, r: int):
    """The law's :class:`wmrjax.Gains`: ``gains`` if given (checked: (m, r), Hurwitz), else real ``poles``."""
    if gains is not None:
        if not isinstance(gains, Gains):
            raise ValueError(f"gains must be a wmrjax.Gains (Hurwitz coefficients), got {type(gains).__name__}")
        return gains.check(m, r)
    if jnp.iscomplexobj(jnp.asarray(poles)):
        raise ValueError("poles must be real pole magnitudes (poles at -poles); for complex pole pairs pass "
                         "gains=wmrjax.Gains.from_damping(omega, zeta, m=...)")
    return Gains.from_poles(poles, m, r)


def check_reference_type(reference) -> None:
    if not isinstance(reference, Reference):
        raise ValueError(f"reference must be a wmrjax.references.Reference, got {type(reference).__name__}")


@functools.partial(jax.jit, static_argnums=0)
def margin_at(ctrl, z, params):
    """``ctrl.margin(z, params)``, compiled once per controller (the eager jet takes seconds)."""
    return ctrl.margin(z, params)


def check_regular(ctrl, z, params, name: str, law_name: str, table: str, regularity: str) -> None:
    """ValueError if a concrete state ``z`` is on (or numerically at) the singular set."""
    zc = concrete(z)
    if zc is None:
        return
    check_shape(name, zc, (ctrl.n_state,), " ".join(ctrl.state_names))
    check_finite(name, zc)
    m = concrete(margin_at(ctrl, jnp.asarray(zc), params))
    if m is None:           # traced parameters (e.g. vmap over geometry): checked by the caller's caller
        return
    m = float(m)
    if not m > 1e3 * DET_FLOOR:
        raise ValueError(f"{name} is on the singular set of the {law_name} for type {ctrl.robot.name}: "
                         f"margin |det K| = {m:.3g}; {table} requires {regularity}")


class LinearizingController:
    """What both sibling controllers delegate to their :class:`LinearizingLaw` (a method mixin).

    :class:`~wmrjax.controllers.DynamicLinearization` and
    :class:`~wmrjax.controllers.StaticLinearization` are frozen dataclasses with a table
    ``row`` (whose ``extension`` the law runs) and a ``level``; each adds its own reference
    jet (``reference_jet(t, params)``: Table 4's outputs of the reference posture, or Table
    3's point path), parameters, initial states and checks. Neither is a kind of the other.
    Methods take ``(t, z, params)`` or ``(z, params)``.
    """

    _law_name = ""      # for messages: "dynamic linearizing law", "static linearizing law"
    _table = ""         # "Table 4", "Table 3"

    @property
    def law(self) -> LinearizingLaw:
        """The generic law this controller runs (one implementation for both siblings)."""
        return LinearizingLaw(self.row.extension, self.level)

    @property
    def robot(self) -> RobotType:
        return self.row.robot

    @property
    def m(self) -> int:
        return self.law.m

    @property
    def relative_degree(self) -> int:
        return self.law.relative_degree

    @property
    def n_state(self) -> int:
        return self.law.n_state

    def outputs(self, z, params):
        """Linearizing outputs Y at ``z``, shape (m,)."""
        return self.law.outputs(z, params.geometry)

    def jet(self, z, params):
        """``(zeta, a, K)`` of :func:`wmrjax.linearize.output_jet` at ``z``."""
        return self.law.jet(z, params.geometry)

    def psi(self, z, params):
        r"""The output jet :math:`\zeta = \Psi(z)` (eq 35), shape (r, m)."""
        return self.law.jet(z, params.geometry)[0]

    def control(self, t, z, params):
        """New input U of eq (49) (the plant input for a static law) and the margin; the division
        by ``det K`` is clamped at :data:`DET_FLOOR`."""
        return self.law.control(self.reference_jet(t, params), z, params.gains.coeffs, params.geometry)

    def margin(self, z, params):
        """Singularity margin at ``z``: |det K| (times the row's extra factor, the (1,1) lever of
        Table 4); 0 on the singular set."""
        return self.law.margin(z, params.geometry)

    def vector_field(self, t, z, params):
        """Closed-loop ``dz/dt`` and :class:`Aux` (plant input, margin)."""
        return self.law.closed_loop(self.reference_jet(t, params), z, params.gains.coeffs, params.geometry)

    def error(self, t, z, params):
        r""":math:`\tilde\zeta = \Psi(z) - \zeta_{ref}(t)`, shape (r, m); angle outputs wrapped."""
        return self.law.error(self.reference_jet(t, params), z, params.geometry)

    def error_matrix(self, gains: Gains):
        r"""Matrix A with :math:`\dot{\tilde\zeta} = A \tilde\zeta` on ``error(...).reshape(-1)``."""
        return linearize.companion(gains.coeffs)

    def check_regular(self, z, params, name: str = "initial state") -> None:
        """Raise ValueError if a concrete ``z`` is on (or numerically at) the row's singular set."""
        check_regular(self, z, params, name, self._law_name, self._table, self.row.regularity)

    def _unchecked_gains(self, poles) -> Gains:
        """Real poles broadcast to (m, r), without validation (traced values)."""
        p = jnp.broadcast_to(jnp.asarray(poles, dtype=jnp.result_type(float)), (self.m, self.relative_degree))
        return Gains.from_poles(p)
