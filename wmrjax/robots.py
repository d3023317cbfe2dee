r"""The five generic types of wheeled mobile robots (paper §2, Tables 1-2).

A robot *type* is a static description (which :math:`\Sigma(\beta)`, how many steering
angles); its *geometry* is a pytree of arrays that can be batched and differentiated.
All models are pure functions of one unbatched state; batch them with ``jax.vmap``.

State and input conventions (Remarks 3-4, eqs 5-8):

* kinematic state ``X = (x, y, theta, beta...)``, shape ``(3 + delta_s,)``; units m, m, rad, rad;
* velocity input ``u = (eta..., zeta...)``, shape ``(delta_m + delta_s,)``;
* torque-level (dynamic) state ``(X, u)`` and input ``v = du/dt`` (eq 8).

The frame convention is the paper's: for type (2,0), ``xdot = -eta1 sin(theta)``,
``ydot = eta1 cos(theta)`` -- the forward axis is the body's x2 axis.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from wmrjax import _hoist, _math
from wmrjax._validate import check_finite, check_number, check_shape, concrete


class Geometry(NamedTuple):
    """Geometric constants of a robot, a pytree of scalars (batchable, differentiable).

    Attributes:
      L: the constant L of Table 2 for types (1,1), (1,2) [m]: distance from P to the
        master steering wheel (1,1), half-axle length (1,2). Unused by other types.
      e: distance from P to the controlled point P' (eq 9) [m].
      delta: polar angle of P' in the body frame (eq 9) [rad].
    """

    L: jnp.ndarray | float = 1.0
    e: jnp.ndarray | float = 0.0
    delta: jnp.ndarray | float = 0.0


def _sigma_30(beta, g):
    del beta, g
    return jnp.eye(3)


def _sigma_20(beta, g):
    del beta, g
    return jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])


def _sigma_21(beta, g):
    del g
    s, c = _math.sincos(beta[0])
    z, o = jnp.zeros_like(s), jnp.ones_like(s)
    return jnp.stack([jnp.stack([-s, z]), jnp.stack([c, z]), jnp.stack([z, o])])


def _sigma_11(beta, g):
    s, c = _math.sincos(beta[0])
    return jnp.stack([jnp.zeros_like(s), g.L * s, c])[:, None]


def _sigma_12(beta, g):
    s1, c1 = _math.sincos(beta[0])
    s2, c2 = _math.sincos(beta[1])
    return jnp.stack(
        [
            -2.0 * g.L * s1 * s2,
            g.L * (s1 * c2 + c1 * s2),  # L sin(beta1 + beta2)
            s2 * c1 - c2 * s1,
        ]
    )[:, None]  # sin(beta2 - beta1)


@dataclasses.dataclass(frozen=True)
class RobotType:
    """A static robot type ``(delta_m, delta_s)``: hashable, never a pytree leaf."""

    delta_m: int
    delta_s: int
    _sigma: Callable = dataclasses.field(repr=False, compare=False)

    @property
    def name(self) -> str:
        """The type's name, ``"(delta_m,delta_s)"``."""
        return f"({self.delta_m},{self.delta_s})"

    @property
    def n_state(self) -> int:
        """Dimension of the kinematic state X (Remark 3)."""
        return 3 + self.delta_s

    @property
    def n_input(self) -> int:
        """Number of velocity inputs (Remark 4)."""
        return self.delta_m + self.delta_s

    @property
    def omnidirectional(self) -> bool:
        """True for type (3,0)."""
        return self.delta_m == 3

    def __str__(self) -> str:
        return self.name


TYPES: dict[str, RobotType] = {
    t.name: t
    for t in (
        RobotType(3, 0, _sigma_30),
        RobotType(2, 0, _sigma_20),
        RobotType(2, 1, _sigma_21),
        RobotType(1, 1, _sigma_11),
        RobotType(1, 2, _sigma_12),
    )
}


def robot_type(kind) -> RobotType:
    """Look up a robot type.

    Args:
      kind: a :class:`RobotType`, a tuple ``(2, 0)``, or a string ``"(2,0)"``/``"2,0"``/``"20"``.

    Raises:
      ValueError: for anything that is not one of the five types of Proposition 1.
    """
    if isinstance(kind, RobotType):
        return kind
    key = None
    if isinstance(kind, tuple) and len(kind) == 2:
        key = f"({kind[0]},{kind[1]})"
    elif isinstance(kind, str):
        s = kind.replace(" ", "").strip("()")
        if len(s) == 2 and s.isdigit():
            s = f"{s[0]},{s[1]}"
        key = f"({s})"
    if key not in TYPES:
        raise ValueError(
            f"unknown robot type {kind!r}; expected one of {sorted(TYPES)} (delta_m, delta_s) as in Proposition 1"
        )
    return TYPES[key]


def check_geometry(geometry: Geometry) -> None:
    """ValueError unless ``geometry`` is a :class:`Geometry` of finite real scalars with L >= 0 [m]."""
    if not isinstance(geometry, Geometry):
        raise ValueError(f"geometry must be a wmrjax.Geometry, got {type(geometry).__name__}")
    for name, val in geometry._asdict().items():
        check_number(f"geometry.{name}", val, "a real scalar [m or rad]")
        if concrete(val) is not None and jnp.ndim(val) != 0:
            raise ValueError(f"geometry.{name} must be a scalar, got shape {jnp.shape(val)}")
        check_finite(f"geometry.{name}", val)
    L = concrete(geometry.L)
    if L is not None and float(L) < 0:  # a negative length is a mirrored robot, not this one
        raise ValueError(
            f"geometry.L is a length (the distance from the body's reference point to the "
            f"steering wheels) and must be >= 0 [m], got {float(L)}; mirror the frame instead"
        )


def rotation(theta):
    """R(theta) of eq (2), shape (3, 3)."""
    s, c = _math.sincos(theta)
    z, o = jnp.zeros_like(s), jnp.ones_like(s)
    return jnp.stack([jnp.stack([c, s, z]), jnp.stack([-s, c, z]), jnp.stack([z, z, o])])


def sigma(robot: RobotType, beta, geometry: Geometry):
    r"""The matrix :math:`\Sigma(\beta)` of Table 2, shape ``(3, delta_m)``."""
    return robot._sigma(beta, geometry)


def input_matrix(robot: RobotType, X, geometry: Geometry):
    r"""B(X) of eqs (6)-(7): :math:`\mathrm{blockdiag}(R^T(\theta)\Sigma(\beta), I)`.

    Args:
      robot: the robot type.
      X: kinematic state, shape ``(3 + delta_s,)``.
      geometry: :class:`Geometry`.

    Returns:
      Array of shape ``(3 + delta_s, delta_m + delta_s)``.
    """
    beta = X[3:]
    top = _math.matmul(rotation(X[2]).T, sigma(robot, beta, geometry))
    if robot.delta_s == 0:
        return top
    ds = robot.delta_s
    top = jnp.concatenate([top, jnp.zeros((3, ds), top.dtype)], axis=1)
    bottom = jnp.concatenate([jnp.zeros((ds, robot.delta_m), top.dtype), jnp.eye(ds, dtype=top.dtype)], axis=1)
    return jnp.concatenate([top, bottom], axis=0)


def body_velocity(robot: RobotType, X, eta, geometry: Geometry):
    r"""Posture velocity in the body frame, :math:`R(\theta)\dot\xi = \Sigma(\beta)\eta`, shape (3,)."""
    return _math.matvec(sigma(robot, X[3:], geometry), eta)


def rotate_to_world(theta, v_body):
    r""":math:`R^T(\theta) v` for a body-frame posture velocity ``v`` (3,)."""
    s, c = _math.sincos(theta)
    return jnp.stack([c * v_body[0] - s * v_body[1], s * v_body[0] + c * v_body[1], v_body[2]])


def kinematic(robot: RobotType, X, u, geometry: Geometry):
    r"""Kinematic model (5): ``Xdot = B(X) u``.

    Computed as :math:`R^T(\theta)\Sigma(\beta)\eta` and :math:`\dot\beta = \zeta`
    without forming B(X) (which :func:`input_matrix` returns): small matrices under
    ``vmap`` do not fuse on CPU.

    Args:
      robot: robot type.
      X: state ``(3 + delta_s,)``.
      u: velocity input ``(delta_m + delta_s,)`` [m/s or rad/s].
      geometry: :class:`Geometry`.

    Returns:
      ``Xdot``, shape ``(3 + delta_s,)``.
    """
    eta, zeta = u[: robot.delta_m], u[robot.delta_m :]
    xi_dot = rotate_to_world(X[2], body_velocity(robot, X, eta, geometry))
    return jnp.concatenate([xi_dot, zeta]) if robot.delta_s else xi_dot


def dynamic(robot: RobotType, state, v, geometry: Geometry):
    """Torque-level model (8): ``Xdot = B(X) u, udot = v`` with ``state = (X, u)``.

    Args:
      robot: robot type.
      state: ``(X, u)`` concatenated, shape ``(3 + 2 delta_s + delta_m,)``.
      v: torque-homogeneous input, shape ``(delta_m + delta_s,)``.
      geometry: :class:`Geometry`.

    Returns:
      ``(Xdot, udot)`` concatenated, same shape as ``state``.
    """
    n = robot.n_state
    X, u = state[:n], state[n:]
    return jnp.concatenate([kinematic(robot, X, u, geometry), v])


@functools.cache
def kinematics_use_geometry(robot: RobotType) -> bool:
    r"""Whether the kinematic model (5) of ``robot`` depends on its geometry's L and e at all.

    Read from the model's own program, not from a table: :func:`kinematic` (which
    :func:`dynamic` and every plant the simulator runs call) is traced with L and e as inputs,
    and JAX's partial evaluation (:func:`wmrjax._hoist.depends_on`, the cut the simulator's
    hoisting uses) says which outputs need them: an output it computes without them cannot move
    with L or e (it may say True where a derivative happens to vanish, never False where the
    model moves). Types (3,0), (2,0) and (2,1) give False (:math:`\Sigma` has no L; e only places
    the controlled point, which the law computes with its own geometry), (1,1) and (1,2) True.

    Args:
      robot: the robot type.

    Returns:
      False when no plant geometry (L, e, any values) changes :math:`\dot X` for any state and
      input: a plant whose geometry differs from the law's moves as the law's model.
    """
    X, u = jnp.zeros(robot.n_state), jnp.zeros(robot.n_input)
    closed = jax.make_jaxpr(lambda L, e: kinematic(robot, X, u, Geometry(L=L, e=e)))(1.0, 0.0)
    return any(_hoist.depends_on(closed, (True, True)))


def check_model_args(robot, X, u, geometry, *, torque: bool = False) -> RobotType:
    """Validate arguments of :func:`kinematic`/:func:`dynamic` on concrete values."""
    robot = robot_type(robot)
    check_geometry(geometry)
    n = robot.n_state + (robot.n_input if torque else 0)
    check_shape("state", X, (n,), "(X, u) for the torque-level model" if torque else "X = (x, y, theta, beta...)")
    check_shape("control", u, (robot.n_input,), "(eta..., zeta...)" if not torque else "v = du/dt")
    check_finite("state", X)
    check_finite("control", u)
    return robot
