r"""The plant a log records: the robot type driven open loop by its logged commands.

Between two samples the plant integrates the command of the earlier one, scaled and saturated
as :class:`wmrjax.PlantLoop` applies it, :math:`\operatorname{clip}(s \odot u, -\bar u, \bar u)`,
with its own geometry (the law's L and e times ``geometry_scale``): the kinematic model (5) at
velocity level, the torque-level model (8) at torque level (state ``(X, u)``). It is a
sampled-data system of :func:`wmrjax.simulate` (a sample holds the next logged command), so the
prediction is the same RK4 run as every other job's.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from wmrjax import robots
from wmrjax.controllers.law import Aux, Level
from wmrjax.robots import Geometry, RobotType
from wmrjax.simulate import simulate
from wmrjax.system import ClosedLoop


class LoggedState(NamedTuple):
    """State of a :class:`LoggedInputs` run.

    Attributes:
      plant: (n_plant,) posture and steering angles X; at torque level followed by the
        velocities u [m, rad; m/s, rad/s].
      command: (n_input,) the logged command held since the last sample.
    """

    plant: Any
    command: Any


class InputParams(NamedTuple):
    """Parameters of a :class:`LoggedInputs` run (a pytree: differentiate it).

    Attributes:
      geometry: the plant's :class:`wmrjax.Geometry`.
      input_scale: (n_input,) true input = scale * command.
      input_limit: (n_input,) ``|true input|`` <= limit (inf: none).
      commands: (n_samples, n_input) the command of each sample; sample k holds row k.
    """

    geometry: Geometry
    input_scale: Any
    input_limit: Any
    commands: Any


@dataclasses.dataclass(frozen=True)
class LoggedInputs(ClosedLoop):
    """A robot driven open loop by a table of commands held over each period (static, hashable).

    Attributes:
      robot: the robot type.
      level: velocity (the commands are u) or torque (the commands are v = du/dt).
      steps_per_sample: RK4 steps per period.
    """

    robot: RobotType
    level: Level
    steps_per_sample: int

    @property
    def sample_every(self) -> int:
        """RK4 steps per sample (read by :func:`wmrjax.simulate`)."""
        return self.steps_per_sample

    @property
    def n_plant(self) -> int:
        """The plant's state size: the posture, and the wheel velocities at torque level."""
        return self.robot.n_state + (self.robot.n_input if self.level == Level.TORQUE else 0)

    @property
    def n_state(self) -> int:
        """The system's state size (the plant and the held input)."""
        return self.n_plant + self.robot.n_input

    @property
    def state_names(self) -> tuple:
        """The names of the state's components."""
        names = ("x", "y", "theta") + tuple(f"beta{i + 1}" for i in range(self.robot.delta_s))
        if self.level == Level.TORQUE:
            names += tuple(f"u{i + 1}" for i in range(self.robot.n_input))
        return names + tuple(f"command{i + 1}" for i in range(self.robot.n_input))

    def held(self, z: LoggedState) -> LoggedState:
        """The command is held between samples; the plant moves."""
        return LoggedState(False, True)

    def vector_field(self, t, z: LoggedState, params: InputParams):
        """The plant under the held command (scaled, clipped); the command itself held."""
        del t
        a = jnp.clip(params.input_scale * z.command, -params.input_limit, params.input_limit)
        n = self.robot.n_state
        if self.level == Level.TORQUE:
            dplant = jnp.concatenate([robots.kinematic(self.robot, z.plant[:n], z.plant[n:], params.geometry), a])
        else:
            dplant = robots.kinematic(self.robot, z.plant, a, params.geometry)
        one = jnp.ones((), a.dtype)  # no singular set: the open loop has no law to lose
        return LoggedState(dplant, jnp.zeros_like(z.command)), Aux(a, one, one)

    def sample(self, k, t, z: LoggedState, params: InputParams) -> LoggedState:
        """Sample ``k``: hold the logged command of row k."""
        del t
        row = jax.lax.dynamic_index_in_dim(
            params.commands, jnp.minimum(k, params.commands.shape[0] - 1), keepdims=False
        )
        return LoggedState(z.plant, row)


def predict(system: LoggedInputs, z0, params: InputParams, period: float):
    """The plant's state at each of the commands' samples, from ``z0`` at the first.

    Args:
      system: the open loop.
      z0: (n_plant,) the plant's state at the first sample.
      params: :class:`InputParams` with ``commands`` of shape (n_samples, n_input), n_samples >= 2.
      period: the sample period [s].

    Returns:
      (n_samples, n_plant) the plant's state at the samples (row 0 is ``z0``).
    """
    n = params.commands.shape[0]
    k = system.steps_per_sample
    z = LoggedState(jnp.asarray(z0), jnp.zeros(system.robot.n_input, jnp.result_type(z0)))
    traj = simulate(
        system, z, params, dt=period / k, n_steps=(n - 1) * k, save_every=k, margin_floor=0.0, error_tol=None
    )
    return traj.state.plant
