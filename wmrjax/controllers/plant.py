r"""A linearizing law driving a plant it does not know exactly: actuator limits and mismatch.

:func:`with_plant` wraps a static or dynamic linearizing controller into a closed loop
whose *plant* saturates its inputs, scales them (wheel-radius or axle errors) and has its
own geometry, while the law keeps computing with its nominal model and its own compensator
(the law does not know). With no limits, unit scale and the nominal geometry, the closed
loop is the controller's own (tested to RK4 accuracy).

* Velocity level: the law's plant input :math:`u = \pi(X, c, U)` is applied as
  :math:`\operatorname{clip}(s \odot u, -\bar u, \bar u)` to the kinematic model (5) with the
  plant's geometry; the compensator :math:`\dot c` integrates the law's U unchanged.
* Torque level, static laws: the state ``(X, u)`` is the plant's own, so the law measures
  u; the plant integrates :math:`\dot u = \operatorname{clip}(s \odot v, -\bar v, \bar v)`.
* Torque level, dynamic laws: the law's state ``(X, c, U)`` carries its compensator and its
  commanded velocities; the plant's wheel velocities are an extra state ``u_plant``
  (appended last), driven by the saturated torque v, and the plant moves with them. The
  law measures X and, by default (``velocity_feedback="measured"``), the wheel velocities:
  before each evaluation it lifts ``u_plant`` into its state
  (:meth:`wmrjax.controllers.law.LinearizingLaw.lift_measured`), so saturation and mismatch
  act on it as on a real robot; the entries u does not determine keep integrating. With
  ``"internal"`` its compensator integrates its own commands only, as the paper's dynamic
  extension does. Both are the controller's own closed loop at nominal conditions (tested).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from wmrjax import robots
from wmrjax._validate import concrete
from wmrjax.controllers.law import Aux, Level
from wmrjax.robots import Geometry
from wmrjax.system import ClosedLoop


class PlantParams(NamedTuple):
    """Parameters of a :class:`PlantLoop` (a pytree: vmap/grad it).

    Attributes:
      law: the wrapped controller's parameters (its nominal geometry, gains, reference).
      geometry: the plant's true :class:`wmrjax.Geometry`.
      input_scale: (n_input,) true input = scale * command (1: exact actuators).
      input_limit: (n_input,) ``|true input_i|`` <= limit_i [m/s, rad/s at velocity level;
        their time derivatives at torque level] (inf: no limit).
    """

    law: Any
    geometry: Geometry
    input_scale: Any
    input_limit: Any


@dataclasses.dataclass(frozen=True)
class PlantLoop(ClosedLoop):
    """A linearizing controller closed around a saturating, mismatched plant (static, hashable).

    Build it with :func:`with_plant`; simulate it with :func:`wmrjax.simulate` like the
    controller itself (``z0`` from :meth:`initial_state`).
    """

    ctrl: Any
    velocity_feedback: str = "measured"

    @property
    def robot(self):
        """The robot type of the law."""
        return self.ctrl.robot

    @property
    def level(self) -> str:
        """The law's level."""
        return self.ctrl.level

    @property
    def _plant_velocity_state(self) -> bool:
        """Dynamic torque-level laws: the plant's wheel velocities are an extra state."""
        return self.ctrl.level == Level.TORQUE and self.ctrl.law.extension.n_comp > 0

    @property
    def n_state(self) -> int:
        """The loop's state size: the law's, and the plant's own wheel velocities where it has them."""
        return self.ctrl.n_state + (self.robot.n_input if self._plant_velocity_state else 0)

    @property
    def state_names(self) -> tuple:
        """The names of the state's components."""
        names = tuple(self.ctrl.state_names)
        if self._plant_velocity_state:
            names += tuple(f"u_plant{i + 1}" for i in range(self.robot.n_input))
        return names

    def law_state(self, z):
        """The wrapped controller's state (drops ``u_plant``); ``z``: (..., n_state)."""
        return z[..., : self.ctrl.n_state]

    def params(self, law_params, *, input_limit=None, input_scale=1.0, geometry: Geometry | None = None) -> PlantParams:
        """Build and validate :class:`PlantParams`.

        Args:
          law_params: the controller's params (from its ``.params()``).
          input_limit: None (no limit), a scalar, or (n_input,) limits > 0 (inf: none).
          input_scale: a scalar or (n_input,) factors > 0.
          geometry: the plant's geometry (default: the law's nominal one).

        Raises:
          ValueError: limits or scales that are not positive, or of the wrong length.
        """
        self.ctrl.check_params(law_params)
        nu = self.robot.n_input
        dtype = jnp.result_type(float)
        limit = np.inf if input_limit is None else input_limit
        out = []
        for name, v in (("input_limit", limit), ("input_scale", input_scale)):
            a = np.asarray(v, float) if concrete(v) is not None else None
            if a is not None:
                if a.ndim > 1 or (a.ndim == 1 and a.shape[0] != nu):
                    raise ValueError(
                        f"{name} must be a scalar or have {nu} entries (one per input of type "
                        f"{self.robot.name}), got shape {a.shape}"
                    )
                if np.any(np.isnan(a)) or np.any(a <= 0) or (name == "input_scale" and not np.all(np.isfinite(a))):
                    raise ValueError(
                        f"{name} must be > 0 per input"
                        + (" (inf: no limit)" if name == "input_limit" else " and finite")
                        + f", got {a.tolist()}"
                    )
            out.append(jnp.broadcast_to(jnp.asarray(v, dtype), (nu,)))
        g = law_params.geometry if geometry is None else geometry
        robots.check_geometry(g)
        return PlantParams(law_params, g, out[1], out[0])

    def initial_state(self, z_law, params: PlantParams):
        r"""The loop's state from the controller's: at torque level (dynamic laws) the plant's
        wheel velocities start at the law's, :math:`u = \pi(X, c, U)`."""
        if not self._plant_velocity_state:
            return z_law
        law = self.ctrl.law
        n, nv = self.robot.n_state, law.n_velocity_state
        u = law.extension.plant_input(z_law[:n], z_law[n:nv], z_law[nv:], params.law.geometry)
        return jnp.concatenate([z_law, u])

    def vector_field(self, t, z, params: PlantParams):
        """Closed-loop ``dz/dt`` and :class:`wmrjax.Aux` (the plant's true input, the law's margin)."""
        law, ctrl = self.ctrl.law, self.ctrl
        g = params.law.geometry
        n, nl = self.robot.n_state, ctrl.n_state
        zl = z[:nl]
        if self._plant_velocity_state and self.velocity_feedback == "measured":
            zl = law.lift_measured(zl, z[nl:], g)  # the law measures the wheel velocities
        U, reg = ctrl.control_and_regularity(t, zl, params.law)
        scale, limit = params.input_scale, params.input_limit

        def actuate(cmd):
            return jnp.clip(scale * cmd, -limit, limit)

        if ctrl.level == Level.VELOCITY:
            u = actuate(law.plant_control(zl, U, g))
            xdot = robots.kinematic(self.robot, zl[:n], u, params.geometry)
            cdot = law.extension.compensator(zl[:n], zl[n:], U, g)
            zdot = jnp.concatenate([xdot, cdot]) if law.extension.n_comp else xdot
            return zdot, Aux(u, jnp.abs(reg), reg)
        v = actuate(law.plant_control(zl, U, g))
        if not self._plant_velocity_state:  # static: (X, u) is the plant's own state
            zdot = robots.dynamic(self.robot, zl, v, params.geometry)
            return zdot, Aux(v, jnp.abs(reg), reg)
        u_plant = z[nl:]
        zdot_law = law.field(zl, U, g)  # the law's compensator and commanded velocities
        xdot = robots.kinematic(self.robot, zl[:n], u_plant, params.geometry)
        return jnp.concatenate([xdot, zdot_law[n:], v]), Aux(v, jnp.abs(reg), reg)

    def final_report(self, t, z, params: PlantParams):
        """The law's final report, on the law's part of the state."""
        report = self.ctrl.final_report
        return None if report is None else report(t, self.law_state(z), params.law)

    def reference_jet_floats(self) -> int:
        """The controller's reference check (the loop checks its law's reference)."""
        return self.ctrl.reference_jet_floats()

    def check_run(self, params, *, t0, dt, n_steps: int) -> None:
        """The controller's checks on ``params.law`` (and that these are :class:`PlantParams`)."""
        if not isinstance(params, PlantParams):
            raise ValueError(
                f"params must be the PlantParams of this loop (build them with its .params()), "
                f"got {type(params).__name__}"
            )
        self.ctrl.check_run(params.law, t0=t0, dt=dt, n_steps=n_steps)


VELOCITY_FEEDBACK = ("measured", "internal")


def with_plant(ctrl, velocity_feedback: str = "measured") -> PlantLoop:
    """Close a static or dynamic linearizing controller around a plant with actuator limits,
    input-scale errors and its own geometry (:class:`PlantLoop`; the law does not know).

    ``velocity_feedback`` (dynamic laws at torque level): "measured" lifts the plant's wheel
    velocities into the law's state before every evaluation; "internal" lets the law integrate
    its own commanded velocities (module docstring).

    Example::

        loop = wmrjax.with_plant(ctrl)
        lp = loop.params(params, input_limit=[5.5, 1.0], input_scale=[1.05, 0.95])
        traj = wmrjax.simulate(loop, loop.initial_state(z0, lp), lp, dt=0.01, n_steps=1000)
    """
    if not hasattr(ctrl, "law") or not hasattr(ctrl, "control_and_regularity"):
        raise ValueError(f"with_plant wraps a static or dynamic linearizing controller, got {type(ctrl).__name__}")
    if velocity_feedback not in VELOCITY_FEEDBACK:
        raise ValueError(f"velocity_feedback must be one of {VELOCITY_FEEDBACK}, got {velocity_feedback!r}")
    return PlantLoop(ctrl, velocity_feedback)
