r"""Static feedback linearization (paper §4): posture tracking for the omnidirectional type
(3,0) (Prop 3, eqs 12-14) and point tracking for the restricted types (Table 3, Props 4-5,
eqs 20-28; Remark 11 at velocity level).

The same engine as the dynamic controllers (:func:`wmrjax.linearize.output_jet`) derives
the decoupling matrix K of eq (22) and the drift g of eq (23) from the Table 3 outputs
:math:`z_1 = h(\xi, \beta)` by autodiff; a "static extension" is a Table 4-style row with no
compensator whose new inputs are the plant's own inputs. So

* velocity level (Remark 11): :math:`u = K^{-1}(\dot z_{1,ref} - \Lambda \tilde z_1)`, error
  :math:`\dot{\tilde z}_1 + \Lambda\tilde z_1 = 0`;
* torque level (27)-(28), with the errata's tildes:
  :math:`v = K^{-1}(w - g)`, :math:`w = \ddot z_{1,ref} - (\Lambda_1+\Lambda_2)\dot{\tilde z}_1 - \Lambda_1\Lambda_2\tilde z_1`.

For (3,0) the outputs are the posture itself: (12) and its velocity counterpart
:math:`\eta_{ref} = R(\theta)[\dot\xi_{ref} - \Lambda_1\tilde\xi]` (eq 14), with the reference-model
state :math:`\tilde\sigma = R^T(\theta)(\eta - \eta_{ref})` exposed by :meth:`StaticLinearization.sigma_tilde`.

The nonlinear coordinates :math:`z_3 = k(\xi, \beta)` of Table 3 are not controlled; Prop 5
bounds them when :math:`\dot z_{1,ref}` is :math:`L^1`. The steering outputs of (2,1) (beta)
and (1,2) (beta2) are free channels: a :class:`Steering` reference (default: the angle that
maximises |det K|) keeps the law away from its singular set.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math, robots
from wmrjax._validate import concrete
from wmrjax.controllers.dynamic import DynamicExtension, DynamicLinearization, Gains, LEVELS
from wmrjax.references import Reference, taylor
from wmrjax.robots import Geometry


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


class Table3Row(NamedTuple):
    outputs: Callable         # (X, geometry) -> z1
    z3: tuple                 # state indices of the nonlinear coordinates k(xi, beta)
    regularity: str           # Table 3's last column (errata determinant)
    steering_index: int | None  # which output is a free steering channel
    angle_outputs: tuple = ()


TABLE3 = {
    "(3,0)": Table3Row(_h_30, (), "always regular (K = R^T(theta))", None, (2,)),
    "(2,0)": Table3Row(_h_20, (2,), "e != 0, delta != k pi (det K = e sin(delta))", None),
    "(2,1)": Table3Row(_h_21, (2,), "e != 0, delta != beta mod pi (det K = -e sin(beta - delta))", 2),
    "(1,1)": Table3Row(_h_11, (2, 3), "e != 0 (det K = e L; L != 0 too)", None),
    "(1,2)": Table3Row(_h_12, (2, 3), "e sin(beta2) != 0 (det K = 2 e L sin(beta2); L != 0 too)", 2),
}


def default_steering(robot, geometry: Geometry) -> Steering | None:
    """The steering reference maximising |det K|: beta = delta + pi/2 for (2,1), beta2 = pi/2 for (1,2)."""
    name = robots.robot_type(robot).name
    if name == "(2,1)":
        return steering_constant(jnp.asarray(geometry.delta) + 0.5 * math.pi)
    if name == "(1,2)":
        return steering_constant(0.5 * math.pi)
    return None


def _identity_input(X, c, U, g):
    return U


def _no_compensator(X, c, U, g):
    return U[:0]


def _from_physical(X, u, g):
    return u[:0], u


class StaticParams(NamedTuple):
    """Everything array-valued a static closed loop depends on (a pytree)."""

    gains: Gains
    reference: Reference
    geometry: Geometry
    steering: Steering | None = None


@dataclasses.dataclass(frozen=True)
class StaticLinearization(DynamicLinearization):
    """Static linearizing tracking law (posture for (3,0), point for the others).

    State: X at velocity level, (X, u) at torque level (model 8). Build it with
    :func:`static_linearization` or :func:`wmrjax.controller`.
    """

    task: str = "point"

    @property
    def table3(self) -> Table3Row:
        return TABLE3[self.robot.name]

    def outputs(self, z, g):
        """Table 3's linearizing outputs :math:`z_1 = h(\\xi, \\beta)` (posture for (3,0))."""
        return self.table3.outputs(z[: self.robot.n_state], g)

    def z3(self, z):
        """Table 3's nonlinear coordinates :math:`z_3 = k(\\xi, \\beta)` (theta; theta, beta(1))."""
        return z[jnp.asarray(self.table3.z3, dtype=int)] if self.table3.z3 else z[:0]

    def reference_outputs(self, t, params: StaticParams):
        """:math:`z_{1,ref}(t)`: the point's path (and steering), or the posture for (3,0)."""
        ref = params.reference
        if self.robot.name == "(3,0)":
            return ref.posture(t)
        p = ref.position(t)
        if self.table3.steering_index is None:
            return p
        return jnp.concatenate([p, jnp.atleast_1d(params.steering(t))])

    def reference_jet(self, t, params: StaticParams):
        return taylor(lambda s: self.reference_outputs(s, params), t, self.relative_degree)

    def margin(self, z, g):
        """|det K(X)| (eq 22): zero on Table 3's singular set."""
        return jnp.abs(jnp.linalg.det(self.jet(z, g)[2]))

    def sigma_tilde(self, t, z, params: StaticParams):
        r"""Reference-model state :math:`\tilde\sigma = \dot{\tilde z}_1 + \Lambda_1\tilde z_1` (eq 14:
        :math:`R^T(\theta)(\eta - \eta_{ref})` for (3,0)); zero at velocity level by construction."""
        if self.level == "velocity":
            return jnp.zeros(self.m, z.dtype)
        err = self.error(t, z, params)
        return err[1] + params.gains.poles[:, 0] * err[0]

    # -- parameters, initial states, checks --
    def params(self, reference: Reference, poles=1.0, geometry: Geometry = Geometry(), steering=None) -> StaticParams:
        """Build and validate :class:`StaticParams`.

        Args:
          reference: the point's path (P' of Table 3) via ``reference.position``; for (3,0) the
            posture ``reference.posture``.
          poles: scalar, (r,) or (m, r) positive pole magnitudes: Lambda (velocity level),
            (Lambda1, Lambda2) (torque level).
          geometry: :class:`Geometry`; (e, delta) or (L, e) place the tracked point.
          steering: :class:`Steering` for (2,1)/(1,2) (default :func:`default_steering`), a
            float (constant), or None.

        Raises:
          ValueError: non-positive poles, a geometry violating Table 3's regularity condition,
            or a steering reference on the singular set.
        """
        p = self._checked_poles(reference, poles, geometry)
        self.check_geometry_table3(geometry)
        if self.table3.steering_index is None:
            steering = None
        elif steering is None:
            steering = default_steering(self.robot, geometry)
        elif not isinstance(steering, Steering):
            steering = steering_constant(steering)
        params = StaticParams(Gains(p), reference, geometry, steering)
        if steering is not None:
            self.check_steering(params)
        return params

    def params_unchecked(self, reference: Reference, poles, geometry: Geometry, steering=None) -> StaticParams:
        r, m = self.relative_degree, self.m
        p = jnp.broadcast_to(jnp.asarray(poles, dtype=jnp.result_type(float)), (m, r))
        if self.table3.steering_index is not None and steering is None:
            steering = default_steering(self.robot, geometry)
        return StaticParams(Gains(p), reference, geometry, steering)

    def check_geometry_table3(self, g: Geometry) -> None:
        """ValueError naming the Table 3 condition the geometry violates."""
        v = {k: concrete(x) for k, x in g._asdict().items()}
        name, reg = self.robot.name, self.table3.regularity
        if name == "(3,0)":
            return
        if v["e"] is not None and float(v["e"]) == 0.0:
            raise ValueError(f"Table 3, type {name}: the regularity condition requires e != 0 ({reg}); got e = 0")
        if name == "(2,0)" and v["delta"] is not None and abs(math.sin(float(v["delta"]))) < 1e-12:
            raise ValueError(f"Table 3, type (2,0): the regularity condition requires delta != k pi ({reg}); "
                             f"got delta = {float(v['delta'])!r}: the point lies on the fixed-wheel axle")
        if name in ("(1,1)", "(1,2)") and v["L"] is not None and float(v["L"]) == 0.0:
            raise ValueError(f"Table 3, type {name}: det K vanishes with L = 0 ({reg})")

    def check_steering(self, params: StaticParams, t_final: float = 10.0, n: int = 201) -> None:
        """ValueError if the steering reference meets the singular set (delta = beta mod pi, sin beta2 = 0)."""
        ts = jnp.linspace(0.0, t_final, n)
        b = concrete(jax.vmap(params.steering)(ts))
        if b is None:
            return
        b = np.asarray(b)
        d = b - float(params.geometry.delta) if self.robot.name == "(2,1)" else b
        lev = np.abs(np.sin(d))
        if not np.all(np.isfinite(lev)) or lev.min() < 1e-6:
            i = int(np.nanargmin(lev))
            cond = "delta != beta mod pi" if self.robot.name == "(2,1)" else "sin(beta2) != 0"
            raise ValueError(f"Table 3, type {self.robot.name}: the steering reference violates {cond} at "
                             f"t = {float(ts[i]):.3g} s (steering {b[i]:.3g} rad); choose another steering reference")

    def initial_state(self, zeta0, params, branch=None):
        raise ValueError("static point tracking has no Psi^-1 (z3 is not an output): "
                         "use initial_state_from_physical(X, u, params)")

    def initial_state_from_physical(self, X, u, params: StaticParams):
        """State X (velocity level) or (X, u) (torque level) from posture/steering X and wheel velocities u.

        Raises:
          ValueError: wrong shapes, non-finite values, or a state on Table 3's singular set.
        """
        X, u = self._physical(X, u)
        z = X if self.level == "velocity" else jnp.concatenate([X, u])
        self.check_regular(z, params)
        return z

    _law = "static linearizing law"
    _table = "Table 3"

    def reference_branch(self, params) -> int:
        return 1

    def check_reference(self, params, t_final, n: int = 201, floor: float = 1e-6) -> None:
        if params.steering is not None:
            self.check_steering(params, t_final, n)

    @property
    def state_names(self) -> tuple:
        X = ("x", "y", "theta") + (("beta",) if self.robot.delta_s == 1 else ("beta1", "beta2")[: self.robot.delta_s])
        if self.level == "velocity":
            return X
        eta = tuple(f"eta{i + 1}" for i in range(self.robot.delta_m))
        zeta = tuple(f"zeta{i + 1}" for i in range(self.robot.delta_s))
        return X + eta + zeta


def _static_extension(rt) -> DynamicExtension:
    row = TABLE3[rt.name]
    return DynamicExtension(rt, 0, (), 1, row.outputs, _identity_input, _no_compensator, row.regularity,
                            None, _from_physical, None, None, row.angle_outputs)


STATIC_EXTENSIONS = {name: _static_extension(robots.TYPES[name]) for name in TABLE3}


def static_linearization(robot, level: str = "velocity") -> StaticLinearization:
    """The static linearizing law: Prop 3 posture tracking for (3,0), Table 3 point tracking otherwise.

    Args:
      robot: any of the five types.
      level: "velocity" (kinematic model 5; Remark 11, eq 14) or "torque" (model 8; eqs 12, 27-28).
    """
    rt = robots.robot_type(robot)
    if level not in LEVELS:
        raise ValueError(f"level must be one of {LEVELS}, got {level!r}")
    return StaticLinearization(STATIC_EXTENSIONS[rt.name], level, "posture" if rt.omnidirectional else "point")


TASKS = ("posture", "point")


def controller(robot, level: str = "velocity", task: str = "posture"):
    """The uniform entry point: a closed loop for (robot type, level, task).

    * ``task="posture"``: (3,0) -> static linearization (Prop 3, eqs 12/14); restricted types
      -> dynamic linearization (Table 4, Prop 8).
    * ``task="point"``: restricted types -> static linearization of Table 3 (Props 4-5,
      Remark 11). For (3,0) point tracking is a special case of posture tracking: ask for that.

    The returned object's ``params(reference, poles, geometry, ...)`` builds the parameters,
    ``initial_state_from_physical(X, u, params)`` an initial state, and its ``vector_field``
    runs under :func:`wmrjax.simulate` (vmap over states, references, gains, geometry).
    """
    from wmrjax.controllers.dynamic import dynamic_linearization

    rt = robots.robot_type(robot)
    if task not in TASKS:
        raise ValueError(f"task must be one of {TASKS}, got {task!r}")
    if level not in LEVELS:
        raise ValueError(f"level must be one of {LEVELS}, got {level!r}")
    if rt.omnidirectional:
        if task == "point":
            raise ValueError("type (3,0) is omnidirectional: use task='posture' (Prop 3), which includes the point")
        return static_linearization(rt, level)
    return dynamic_linearization(rt, level) if task == "posture" else static_linearization(rt, level)
