r"""A linearizing law run by a digital controller: sampled, held, noisy, saturated, mismatched.

:func:`sampled` wraps a static or dynamic linearizing controller into the closed loop a
robot runs: every ``steps_per_sample`` integration steps the controller *samples* -- it
measures the posture (and steering angles) with additive noise and, at torque level, the
wheel velocities; it evaluates the law with its *nominal* geometry; and it holds the
command (zero-order hold) until the next sample. The plant integrates the held command,
scaled and saturated (:math:`\operatorname{clip}(s \odot u, -\bar u, \bar u)`), with its
own geometry. The controller's own state (a dynamic law's compensator, and at torque level
its commanded velocities) advances as a digital integrator: its rate, computed at the
sample, is held over the period, and the next sample first advances it by that rate times
the period (between samples the controller state is held).

It is one :func:`wmrjax.simulate`-able system: the sample is its discrete transition
(:meth:`SampledLoop.sample`), which ``simulate`` applies at the start of every period of
``steps_per_sample`` steps (the first at ``t0``, the last one period before the end), so a
sampled-data run has the same RK4 step, the same failure rule and the same
:class:`wmrjax.Diagnostics` as every other run. The margin a step reports is the one of the
last sample (what the controller saw): a run fails when a sample's :math:`|\det K|` reaches
``margin_floor`` or its sign changes between two samples. Each sample also records the
output error of the true (noise-free) state, for losses and reports.

With no noise, no mismatch, no limits and a short period this is the controller's own
continuous closed loop (tested).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import robots
from wmrjax._validate import check_int, concrete
from wmrjax.controllers.law import Aux, Level
from wmrjax.controllers.plant import PlantLoop, PlantParams
from wmrjax.robots import Geometry
from wmrjax.system import ClosedLoop


class SampledState(NamedTuple):
    r"""State of a :class:`SampledLoop` (a pytree; every leaf real).

    Attributes:
      plant: (n_plant,) the plant's posture and steering angles X; at torque level followed by
        its wheel velocities u [m, rad; m/s, rad/s].
      controller: (n_c,) the law's state beyond X (compensator; at torque level also its
        commanded velocities U), as the controller last set it; empty for static velocity laws.
      rate: (n_c,) the controller state's rate computed at the last sample, held; the next sample
        first advances ``controller`` by ``rate`` times the time since this one.
      t_sample: () the time of the last sample [s].
      command: (n_input,) the law's command at the last sample (u at velocity level, v = du/dt at
        torque level), held; the plant receives ``clip(scale * command, -limit, limit)``.
      regularity: () the law's signed regularity function (det K) at the last sample, held.
      error: (r * m,) the output error :math:`\Psi(X, c) - \zeta_{ref}(t)` of the true state
        (no noise) at the last sample, rows of derivative order flattened; held.
    """

    plant: Any
    controller: Any
    rate: Any
    t_sample: Any
    command: Any
    regularity: Any
    error: Any


class SampledParams(NamedTuple):
    """Parameters of a :class:`SampledLoop` (a pytree: vmap/grad it).

    Attributes:
      plant: :class:`wmrjax.PlantParams` (the law's parameters, the plant's geometry, input scale
        and limits).
      noise: (n_samples, n_X) measurement noise added to X at each sample [m, m, rad, rad...];
        row k is used at sample k (clamped to the last row). Zeros: exact measurements.
    """

    plant: PlantParams
    noise: Any


@dataclasses.dataclass(frozen=True)
class SampledLoop(ClosedLoop):
    """A linearizing controller run at a fixed period with a zero-order hold (static, hashable).

    Build it with :func:`sampled`; simulate it with :func:`wmrjax.simulate`, with ``z0`` from
    :meth:`initial_state` and ``n_steps`` a multiple of :attr:`steps_per_sample`.
    """

    ctrl: Any
    steps_per_sample: int

    @property
    def robot(self):
        """The robot type of the law."""
        return self.ctrl.robot

    @property
    def level(self):
        """The law's level."""
        return self.ctrl.level

    @property
    def sample_every(self) -> int:
        """Integration steps per controller period (read by :func:`wmrjax.simulate`)."""
        return self.steps_per_sample

    @property
    def _torque(self) -> bool:
        return self.ctrl.level == Level.TORQUE

    @property
    def n_controller(self) -> int:
        """The size of the law's own (controller) state."""
        return self.ctrl.n_state - self.robot.n_state

    @property
    def n_plant(self) -> int:
        """The plant's state size: the posture, and the wheel velocities at torque level."""
        return self.robot.n_state + (self.robot.n_input if self._torque else 0)

    @property
    def n_state(self) -> int:
        """The loop's state size: :class:`SampledState`'s leaves (plant, controller and its rate, sample time, command, regularity, error jet)."""
        return self.n_plant + 2 * self.n_controller + self.robot.n_input + 2 + self.ctrl.m * self.ctrl.relative_degree

    def law_state(self, z: SampledState):
        """The controller's state ``(X, controller)`` (true X, no noise); batched states keep their axes."""
        return jnp.concatenate([z.plant[..., : self.robot.n_state], z.controller], axis=-1)

    def params(
        self, law_params, *, input_limit=None, input_scale=1.0, geometry: Geometry | None = None, noise=None
    ) -> SampledParams:
        """Build and validate :class:`SampledParams`.

        Args:
          law_params: the controller's params (from its ``.params()``).
          input_limit: the plant's input limits (:meth:`wmrjax.PlantLoop.params`).
          input_scale: the plant's input scales (the same).
          geometry: the plant's geometry (the same).
          noise: (n_samples, n_X) measurement noise per sample (see :func:`measurement_noise`);
            None: exact measurements.

        Raises:
          ValueError: bad limits, scales or geometry; noise of the wrong width or not finite.
        """
        plant = PlantLoop(self.ctrl).params(
            law_params, input_limit=input_limit, input_scale=input_scale, geometry=geometry
        )
        nX = self.robot.n_state
        if noise is None:
            noise = jnp.zeros((1, nX), jnp.result_type(float))
        nv = concrete(noise)
        if nv is not None:
            nv = np.asarray(nv)
            if nv.ndim != 2 or nv.shape[1] != nX or nv.shape[0] < 1:
                raise ValueError(
                    f"noise must have shape (n_samples, {nX}) (one row of measurement noise on X = "
                    f"({', '.join(self.ctrl.state_names[:nX])}) per sample), got {nv.shape}"
                )
            if not np.all(np.isfinite(nv)):
                raise ValueError("noise must be finite")
        return SampledParams(plant, jnp.asarray(noise, jnp.result_type(float)))

    def initial_state(self, z_law, params: SampledParams) -> SampledState:
        r"""The loop's state from the controller's ``z_law`` (X and its own state); at torque level
        the plant's wheel velocities start at the law's, :math:`u = \pi(X, c, U)`. The held values
        are zero until :func:`wmrjax.simulate` takes the first sample, at ``t0``. Pure: jit/vmap it."""
        nX = self.robot.n_state
        z_law = jnp.asarray(z_law, jnp.result_type(float))
        plant = z_law[:nX]
        if self._torque:
            law, g = self.ctrl.law, params.plant.law.geometry
            nv = law.n_velocity_state
            u = law.extension.plant_input(z_law[:nX], z_law[nX:nv], z_law[nv:], g)
            plant = jnp.concatenate([plant, u])
        c = z_law[nX:]
        nu, ne = self.robot.n_input, self.ctrl.m * self.ctrl.relative_degree
        zero = jnp.zeros((), z_law.dtype)
        return SampledState(
            plant, c, jnp.zeros_like(c), zero, jnp.zeros(nu, z_law.dtype), zero, jnp.zeros(ne, z_law.dtype)
        )

    def applied(self, z: SampledState, params: SampledParams):
        """The plant's true input: the held command scaled and saturated."""
        p = params.plant
        return jnp.clip(p.input_scale * z.command, -p.input_limit, p.input_limit)

    def held(self, z: SampledState) -> SampledState:
        """Which leaves are held between samples (all but the plant's): ``simulate`` integrates
        only the others over a period."""
        return SampledState(False, *([True] * (len(SampledState._fields) - 1)))

    def vector_field(self, t, z: SampledState, params: SampledParams):
        """``dz/dt`` between samples (the plant under the held input; everything else held) and
        :class:`wmrjax.Aux` (the applied input, the last sample's margin)."""
        nX = self.robot.n_state
        a = self.applied(z, params)
        g = params.plant.geometry
        if self._torque:
            dplant = jnp.concatenate([robots.kinematic(self.robot, z.plant[:nX], z.plant[nX:], g), a])
        else:
            dplant = robots.kinematic(self.robot, z.plant, a, g)
        dz = SampledState(dplant, *(jnp.zeros_like(x) for x in z[1:]))
        return dz, Aux(a, jnp.abs(z.regularity), z.regularity)

    def sample(self, k, t, z: SampledState, params: SampledParams, jet=None) -> SampledState:
        """Sample ``k`` at time ``t``: measure, evaluate the law, hold its command and rate (and
        record the true state's output error); ``jet``: the reference's jet at ``t`` where the
        caller has it (:meth:`wmrjax.controllers.law.LinearizingController.control_and_error`)."""
        ctrl, law = self.ctrl, self.ctrl.law
        nX = self.robot.n_state
        g = params.plant.law.geometry
        noise = jax.lax.dynamic_index_in_dim(params.noise, jnp.minimum(k, params.noise.shape[0] - 1), keepdims=False)
        c = z.controller + (t - z.t_sample) * z.rate  # the digital integrator's step
        z = z._replace(controller=c)
        zm = jnp.concatenate([z.plant[:nX] + noise, c])
        if self._torque:
            zm = law.lift_measured(zm, z.plant[nX:], g)  # measured wheel velocities
        U, regularity, error = ctrl.control_and_error(t, zm, self.law_state(z), params.plant.law, jet)
        command = law.plant_control(zm, U, g)
        rate = law.field(zm, U, g)[nX:]
        error = error.reshape(-1)
        return SampledState(
            z.plant, zm[nX:], rate, jnp.asarray(t, zm.dtype), command, jnp.asarray(regularity, zm.dtype), error
        )

    def final_report(self, t, z, params: SampledParams):
        """The law's final report, on the law's part of the state."""
        report = self.ctrl.final_report
        return None if report is None else report(t, self.law_state(z), params.plant.law)

    def reference_jet_floats(self) -> int:
        """The controller's reference check (the loop checks its law's reference)."""
        return self.ctrl.reference_jet_floats()

    def check_run(self, params, *, t0, dt, n_steps: int) -> None:
        """The controller's checks on its parameters, and a whole number of periods."""
        if not isinstance(params, SampledParams):
            raise ValueError(
                f"params must be the SampledParams of this loop (build them with its .params()), "
                f"got {type(params).__name__}"
            )
        if n_steps % self.steps_per_sample:
            raise ValueError(
                f"n_steps = {n_steps} is not a whole number of controller periods of {self.steps_per_sample} steps"
            )
        self.ctrl.check_run(params.plant.law, t0=t0, dt=dt, n_steps=n_steps)


def measurement_noise(key, std, n_samples: int, n_state: int):
    """(n_samples, n_state) Gaussian measurement noise: row k is ``std * normal(fold_in(key, k))``.

    Args:
      key: a ``jax.random`` key.
      std: (n_std,) standard deviations of the first n_std components of X (x, y [m], theta,
        steering angles [rad]); the others are measured exactly.
      n_samples: samples of the run (static).
      n_state: components of X (static).
    """
    std = jnp.asarray(std, jnp.result_type(float))
    full = jnp.zeros(n_state, std.dtype).at[: std.shape[0]].set(std)
    draws = jax.vmap(lambda k: jax.random.normal(jax.random.fold_in(key, k), (n_state,), std.dtype))(
        jnp.arange(n_samples)
    )
    return full * draws


def sampled(ctrl, steps_per_sample: int) -> SampledLoop:
    """Run a static or dynamic linearizing controller at a fixed period with a zero-order hold
    (:class:`SampledLoop`): ``simulate(loop, ..., dt=period / steps_per_sample)``.

    Example::

        loop = wmrjax.sampled(ctrl, steps_per_sample=5)          # 20 Hz at dt = 0.01 s
        sp = loop.params(params, input_limit=[5.5, 1.0], noise=noise)
        traj = wmrjax.simulate(loop, loop.initial_state(z0, sp), sp, dt=0.01, n_steps=1000)   # samples at t0 first

    Raises:
      ValueError: not a linearizing controller, a static law at torque level (its plant state is
        the law's own), or ``steps_per_sample < 1``.
    """
    if not hasattr(ctrl, "law") or not hasattr(ctrl, "control_and_regularity"):
        raise ValueError(f"sampled wraps a static or dynamic linearizing controller, got {type(ctrl).__name__}")
    if ctrl.level == Level.TORQUE and ctrl.law.extension.n_comp == 0:
        raise ValueError(
            "a sampled-data loop at torque level needs a dynamic law (its state carries the measured "
            "wheel velocities); a static law's torque-level state is the plant's own"
        )
    return SampledLoop(ctrl, check_int("steps_per_sample", steps_per_sample, 1))
