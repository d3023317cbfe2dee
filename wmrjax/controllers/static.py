r"""Static feedback linearization (paper §4): posture tracking for the omnidirectional type
(3,0) (Prop 3, eqs 12-14) and point tracking for the restricted types (Table 3, Props 4-5,
eqs 20-28; Remark 11 at velocity level).

Each row of Table 3 is a :class:`Table3Row` built by keyword: the outputs
:math:`z_1 = h(\xi, \beta)` as an :class:`wmrjax.controllers.law.Extension` with no
compensator (its new inputs are the plant's own inputs), and the per-type facts (the
nonlinear coordinates :math:`z_3`, the regularity condition and the geometry it needs,
the free steering channel and its singular angles, a default geometry). The same generic
law as the dynamic controllers (:class:`wmrjax.controllers.law.LinearizingLaw`) derives
the decoupling matrix K of eq (22) and the drift g of eq (23) by autodiff. So

* velocity level (Remark 11): :math:`u = K^{-1}(\dot z_{1,ref} - \Lambda \tilde z_1)`, error
  :math:`\dot{\tilde z}_1 + \Lambda\tilde z_1 = 0`;
* torque level (27)-(28), with the errata's tildes:
  :math:`v = K^{-1}(w - g)`, :math:`w = \ddot z_{1,ref} - k_1\dot{\tilde z}_1 - k_0\tilde z_1`
  (:math:`k_1 = \Lambda_1+\Lambda_2`, :math:`k_0 = \Lambda_1\Lambda_2` for real poles).

For (3,0) the outputs are the posture itself: (12) and its velocity counterpart
:math:`\eta_{ref} = R(\theta)[\dot\xi_{ref} - \Lambda_1\tilde\xi]` (eq 14), with the reference-model
state :math:`\tilde\sigma = R^T(\theta)(\eta - \eta_{ref})` exposed by :meth:`StaticLinearization.sigma_tilde`.

The nonlinear coordinates :math:`z_3 = k(\xi, \beta)` of Table 3 are not controlled; Prop 5
bounds them when :math:`\dot z_{1,ref}` is :math:`L^1`. They are reported: every run's
:class:`InternalDynamics` (in ``Trajectory.diagnostics.internal``) gives the final heading
error relative to the reference heading and :math:`\|z_3\|`, and flags a robot that tracks
its point while it has turned round. The steering outputs of (2,1) (beta) and (1,2)
(beta2) are free channels: a :class:`Steering` reference (default: the angle that
maximises ``|det K|``) keeps the law away from its singular set.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math, robots
from wmrjax._validate import concrete
from wmrjax.controllers.dynamic import dynamic_linearization
from wmrjax.controllers.law import (
    Extension,
    Level,
    LinearizingController,
    Requirement,
    Task,
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

# --- steering references -------------------------------------------------------------


def _const(t, params):
    return params + 0.0 * t


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Steering:
    """Reference of the free steering output (beta for (2,1), beta2 for (1,2)) [rad].

    Attributes:
      params: pytree of arrays for ``fn``.
      fn: static ``(t, params) -> scalar`` (a module-level function); default a constant.
    """

    params: Any
    fn: Callable = dataclasses.field(default=_const, metadata=dict(static=True))

    def __call__(self, t):
        """The steering reference at time ``t`` [s]."""
        return self.fn(t, self.params)


def steering_constant(value) -> Steering:
    """A constant steering reference [rad]."""
    return Steering(jnp.asarray(value, dtype=jnp.result_type(float)))


# --- Table 3 --------------------------------------------------------------------------


def _h_30(X, g):
    del g
    return X[:3]


def _h_20(X, g):  # x + e cos(theta + delta), y + e sin(theta + delta)
    s, c = _math.sincos(X[2] + g.delta)
    return jnp.stack([X[0] + g.e * c, X[1] + g.e * s])


def _h_21(X, g):
    return jnp.concatenate([_h_20(X, g), X[3:4]])


def _h_11(X, g):  # x + L sin th + e cos(th + b), y - L cos th + e sin(th + b)
    s, c = _math.sincos(X[2])
    sb, cb = _math.sincos(X[2] + X[3])
    return jnp.stack([X[0] + g.L * s + g.e * cb, X[1] - g.L * c + g.e * sb])


def _h_12(X, g):  # x + L cos th - e sin(th + b1), y + L sin th + e cos(th + b1), beta2
    s, c = _math.sincos(X[2])
    sb, cb = _math.sincos(X[2] + X[3])
    return jnp.stack([X[0] + g.L * c - g.e * sb, X[1] + g.L * s + g.e * cb, X[4]])


def _steer_21(g):
    return jnp.asarray(g.delta) + 0.5 * math.pi


def _steer_12(g):
    del g
    return 0.5 * math.pi


def _steer_level_21(beta, delta):
    return np.abs(np.sin(beta - delta))


def _steer_level_12(beta, delta):
    del delta
    return np.abs(np.sin(beta))


_E = Requirement("e", "nonzero", "Table 3: det K is proportional to e")
_L = Requirement("L", "nonzero", "Table 3: det K is proportional to L")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Table3Row:
    r"""One row of Table 3 (or Prop 3 for (3,0)) and the per-type facts of its static law.

    Attributes:
      extension: the outputs :math:`z_1 = h(\xi, \beta)` (no compensator, U = u).
      tracks: :class:`Task`: the posture ((3,0), Prop 3) or a point (Table 3).
      z3: state indices of the nonlinear coordinates :math:`z_3 = k(\xi, \beta)`.
      regularity: Table 3's last column (errata determinant).
      requires: geometry :class:`Requirement` s of that condition.
      steering_index: which output is a free steering channel (None: none).
      default_steering: ``geometry -> angle`` maximising ``|det K|`` on that channel.
      steering_level: ``(beta, delta) -> |.|`` (NumPy) vanishing where the steering
        reference makes K singular; ``steering_condition`` says it in words.
      default_geometry: the geometry used by the examples and experiments.
    """

    extension: Extension
    tracks: Task = Task.POINT
    z3: tuple = ()
    regularity: str
    requires: tuple = ()
    steering_index: Optional[int] = None
    default_steering: Optional[Callable] = dataclasses.field(default=None, repr=False)
    steering_level: Optional[Callable] = dataclasses.field(default=None, repr=False)
    steering_condition: str = ""
    default_geometry: Geometry = Geometry()

    @property
    def robot(self) -> RobotType:
        """The robot type of the law's row."""
        return self.extension.robot


def _row(kind, outputs, **facts) -> Table3Row:
    return Table3Row(
        extension=Extension(
            robot=robots.TYPES[kind], outputs=outputs, relative_degree=1, angle_outputs=facts.pop("angle_outputs", ())
        ),
        **facts,
    )


TABLE3: dict[str, Table3Row] = {
    row.robot.name: row
    for row in (
        _row("(3,0)", _h_30, angle_outputs=(2,), tracks=Task.POSTURE, regularity="always regular (K = R^T(theta))"),
        _row(
            "(2,0)",
            _h_20,
            z3=(2,),
            regularity="e != 0, delta != k pi (det K = e sin(delta))",
            requires=(
                _E,
                Requirement(
                    "delta",
                    "sin_nonzero",
                    "Table 3: det K = e sin(delta); the point must not lie on the fixed-wheel axle",
                ),
            ),
            default_geometry=Geometry(e=0.3, delta=0.5 * math.pi),
        ),
        _row(
            "(2,1)",
            _h_21,
            z3=(2,),
            regularity="e != 0, delta != beta mod pi (det K = -e sin(beta - delta))",
            requires=(_E,),
            steering_index=2,
            default_steering=_steer_21,
            steering_level=_steer_level_21,
            steering_condition="delta != beta mod pi",
            default_geometry=Geometry(e=0.3, delta=0.5 * math.pi),
        ),
        _row(
            "(1,1)",
            _h_11,
            z3=(2, 3),
            regularity="e != 0 (det K = e L; L != 0 too)",
            requires=(_E, _L),
            default_geometry=Geometry(L=1.0, e=0.3),
        ),
        _row(
            "(1,2)",
            _h_12,
            z3=(2, 3),
            regularity="e sin(beta2) != 0 (det K = 2 e L sin(beta2); L != 0 too)",
            requires=(_E, _L),
            steering_index=2,
            default_steering=_steer_12,
            steering_level=_steer_level_12,
            steering_condition="sin(beta2) != 0",
            default_geometry=Geometry(L=0.5, e=0.3),
        ),
    )
}
"""Table 3 (and Prop 3 for (3,0)): robot type name -> its static linearization's :class:`Table3Row`."""


def default_steering(robot, geometry: Geometry) -> Steering | None:
    """The steering reference maximising ``|det K|``: beta = delta + pi/2 for (2,1), beta2 = pi/2 for (1,2)."""
    row = TABLE3[robots.robot_type(robot).name]
    return None if row.default_steering is None else steering_constant(row.default_steering(geometry))


class StaticParams(NamedTuple):
    """Everything array-valued a static closed loop depends on (a pytree)."""

    gains: Gains
    reference: Reference
    geometry: Geometry
    steering: Steering | None = None


class InternalDynamics(NamedTuple):
    """The uncontrolled part of a static point-tracking loop at one time (Table 3's z3).

    Attributes:
      heading_error: robot heading minus the reference heading (path tangent in the
        paper's convention, plus the reference's heading offset), wrapped to [-pi, pi) [rad].
      z3_norm: ||z3|| (theta and the non-output steering angle, unwrapped) [rad].
      turned_round: ``|heading_error|`` > pi/2: the point is tracked with the robot facing
        backwards (the law cannot see it; Prop 5 only bounds z3).
    """

    heading_error: jnp.ndarray
    z3_norm: jnp.ndarray
    turned_round: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class StaticLinearization(LinearizingController):
    """Static linearizing tracking law (posture for (3,0), point for the others).

    State: X at velocity level, (X, u) at torque level (model 8). Build it with
    :func:`static_linearization` or :func:`wmrjax.controller`. A sibling of
    :class:`wmrjax.controllers.DynamicLinearization`: both run a
    :class:`wmrjax.controllers.law.LinearizingLaw`.
    """

    row: Table3Row
    level: str

    _law_name = "static linearizing law"
    _table = "Table 3"
    _params_type = StaticParams

    @property
    def task(self) -> Task:
        """What the law tracks (a point or a posture)."""
        return self.row.tracks

    @property
    def state_names(self) -> tuple:
        """The names of the state's components."""
        X = physical_state_names(self.robot)
        if self.level == Level.VELOCITY:
            return X
        eta = tuple(f"eta{i + 1}" for i in range(self.robot.delta_m))
        zeta = tuple(f"zeta{i + 1}" for i in range(self.robot.delta_s))
        return X + eta + zeta

    def z3(self, z):
        r"""Table 3's nonlinear coordinates :math:`z_3 = k(\xi, \beta)` (theta; theta, beta(1))."""
        return z[jnp.asarray(self.row.z3, dtype=int)] if self.row.z3 else z[:0]

    def reference_outputs(self, t, params: StaticParams):
        """:math:`z_{1,ref}(t)`: the point's path (and steering), or the posture for (3,0)."""
        ref = params.reference
        if self.row.tracks == Task.POSTURE:
            return ref.posture(t)
        p = ref.position(t)
        if self.row.steering_index is None:
            return p
        return jnp.concatenate([p, jnp.atleast_1d(params.steering(t))])

    def reference_jet(self, t, params: StaticParams):
        """The reference's output jet at ``t`` [s]: (r + 1, m)."""
        return taylor(lambda s: self.reference_outputs(s, params), t, self.relative_degree)

    def sigma_tilde(self, t, z, params: StaticParams):
        r"""Reference-model state :math:`\tilde\sigma = \dot{\tilde z}_1 + \Lambda_1\tilde z_1` (eq 14:
        :math:`R^T(\theta)(\eta - \eta_{ref})` for (3,0)); zero at velocity level by construction.

        :math:`\Lambda_1` is the slower real root of each output's polynomial
        (:meth:`wmrjax.Gains.cascade_pole`): the coefficients do not remember in which order
        two real poles were given, so the slower one is the reference model's (eq 14) and the
        faster one the inner loop's. NaN for complex poles, which have no real cascade.
        """
        if self.level == Level.VELOCITY:
            return jnp.zeros(self.m, z.dtype)
        err = self.error(t, z, params)
        return err[1] + params.gains.cascade_pole() * err[0]

    def internal_dynamics(self, t, z, params: StaticParams) -> InternalDynamics:
        """Heading error relative to the reference and ||z3|| at ``(t, z)`` (:class:`InternalDynamics`)."""
        dth = _math.wrap_angle(z[2] - params.reference.posture(t)[2])
        z3 = self.z3(z)
        return InternalDynamics(dth, jnp.sqrt(jnp.sum(z3 * z3)), jnp.abs(dth) > 0.5 * math.pi)

    def final_report(self, t, z, params: StaticParams) -> InternalDynamics:
        """What :func:`wmrjax.simulate` records in ``diagnostics.internal`` at the final state."""
        return self.internal_dynamics(t, z, params)

    # -- parameters, initial states, checks --
    def params(
        self,
        reference: Reference,
        poles=1.0,
        geometry: Geometry = Geometry(),
        steering=None,
        *,
        gains: Gains | None = None,
    ) -> StaticParams:
        """Build and validate :class:`StaticParams`.

        Args:
          reference: the point's path (P' of Table 3) via ``reference.position``; for (3,0) the
            posture ``reference.posture``.
          poles: scalar, (r,) or (m, r) positive pole magnitudes: Lambda (velocity level),
            (Lambda1, Lambda2) (torque level).
          geometry: :class:`Geometry`; (e, delta) or (L, e) place the tracked point
            (``row.default_geometry`` is the experiments' choice).
          steering: :class:`Steering` for (2,1)/(1,2) (default :func:`default_steering`), a
            float (constant), or None.
          gains: a :class:`wmrjax.Gains` instead of ``poles``.

        Raises:
          ValueError: a bad reference or gains, a geometry violating Table 3's regularity
            condition, or a steering reference on the singular set.
        """
        robots.check_geometry(geometry)
        check_reference_type(reference)
        check_requirements(self.row.requires, geometry, f"Table 3, type {self.robot.name} ({self.row.regularity})")
        g = make_gains(gains, poles, self.m, self.relative_degree)
        if self.row.steering_index is None:
            steering = None
        elif steering is None:
            steering = default_steering(self.robot, geometry)
        elif not isinstance(steering, Steering):
            steering = steering_constant(steering)
        params = StaticParams(g, reference, geometry, steering)
        if steering is not None:
            self.check_steering(params)
        return params

    def params_unchecked(self, reference: Reference, poles, geometry: Geometry, steering=None) -> StaticParams:
        """The parameters without the checks of :meth:`params` (inside a transformation)."""
        if self.row.steering_index is not None and steering is None:
            steering = default_steering(self.robot, geometry)
        return StaticParams(self._unchecked_gains(poles), reference, geometry, steering)

    def check_steering(self, params: StaticParams, t_final: float = 10.0, n: int = 201) -> None:
        """ValueError if the steering reference meets the singular set (delta = beta mod pi, sin beta2 = 0)."""
        ts = jnp.linspace(0.0, t_final, n)
        b = concrete(jax.vmap(params.steering)(ts))
        if b is None:
            return
        delta = concrete(params.geometry.delta)
        if delta is None:
            return
        b = np.asarray(b)
        lev = self.row.steering_level(b, float(delta))
        if not np.all(np.isfinite(lev)) or lev.min() < 1e-6:
            i = int(np.nanargmin(lev))
            raise ValueError(
                f"Table 3, type {self.robot.name}: the steering reference violates "
                f"{self.row.steering_condition} at t = {float(ts[i]):.3g} s (steering {b[i]:.3g} rad); "
                "choose another steering reference"
            )

    def physical_state(self, X, u, params):
        """State X (velocity level) or (X, u) (torque level), no checks (pure)."""
        del params
        return X if self.level == Level.VELOCITY else jnp.concatenate([X, u])

    def initial_state_from_physical(self, X, u, params: StaticParams):
        """State X (velocity level) or (X, u) (torque level) from posture/steering X and wheel velocities u.

        Works under ``jax.vmap``/``jit`` (checks apply to concrete values only).

        Raises:
          ValueError: wrong shapes, non-finite values, or a state on Table 3's singular set.
        """
        X, u = validated_physical(self.robot, X, u)
        z = self.physical_state(X, u, params)
        self.check_regular(z, params)
        return z

    def reference_branch(self, params) -> int:
        """Static laws have one branch."""
        del params
        return 1

    def reference_regularity(self, t, params: StaticParams):
        """The steering reference at time t (its level is taken in :meth:`_reference_level`), or 1."""
        one = jnp.ones((), jnp.result_type(float))
        return (params.steering(t) if params.steering is not None else one), one

    def _reference_level(self, raw, params):
        if params.steering is None:
            return raw
        delta = concrete(params.geometry.delta)
        return raw if delta is None else self.row.steering_level(np.asarray(raw), float(delta))

    @property
    def _reference_requirement(self) -> str:
        return self.row.steering_condition or "a regular reference"


def static_linearization(robot, level: Level | str = Level.VELOCITY) -> StaticLinearization:
    """The static linearizing law: Prop 3 posture tracking for (3,0), Table 3 point tracking otherwise.

    Args:
      robot: any of the five types.
      level: "velocity" (kinematic model 5; Remark 11, eq 14) or "torque" (model 8; eqs 12, 27-28).
    """
    rt = robots.robot_type(robot)
    return StaticLinearization(TABLE3[rt.name], check_level(level))


def check_task(task) -> Task:
    """``task`` (a :class:`Task` or its name) as a :class:`Task`; ValueError otherwise."""
    try:
        return Task(task)
    except (ValueError, TypeError):
        raise ValueError(f"task must be one of {tuple(str(t) for t in Task)}, got {task!r}") from None


def controller(robot, level: Level | str = Level.VELOCITY, task: Task | str = Task.POSTURE):
    """The uniform entry point: a closed loop for (robot type, level, task).

    * ``task="posture"``: (3,0) -> static linearization (Prop 3, eqs 12/14); restricted types
      -> dynamic linearization (Table 4, Prop 8).
    * ``task="point"``: restricted types -> static linearization of Table 3 (Props 4-5,
      Remark 11). For (3,0) point tracking is a special case of posture tracking: ask for that.

    The returned object's ``params(reference, poles, geometry, ...)`` builds the parameters,
    ``initial_state_from_physical(X, u, params)`` an initial state, and its ``vector_field``
    runs under :func:`wmrjax.simulate` (vmap over states, references, gains, geometry).
    """
    rt = robots.robot_type(robot)
    task, level = check_task(task), check_level(level)
    if rt.omnidirectional:
        if task == Task.POINT:
            raise ValueError("type (3,0) is omnidirectional: use task='posture' (Prop 3), which includes the point")
        return static_linearization(rt, level)
    return dynamic_linearization(rt, level) if task == Task.POSTURE else static_linearization(rt, level)
