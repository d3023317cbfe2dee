r"""Scenario batches and the sampled-data rollout used for tuning.

A *scenario* is one closed-loop experiment: an initial state, a reference, the plant's true
geometry and input scale (model mismatch: wheel radius, axle length, e, L), actuator
limits (the plant saturates; the controller does not know), a sensor-noise key. The
controller runs at a fixed rate with a zero-order hold: at each sample it measures the
posture (plus noise), evaluates the linearizing law with its *nominal* geometry, and holds
the command while the plant is integrated by RK4 substeps. With no noise, no mismatch, no
limits and a fast rate this is the nominal exact-linearization loop.

All arrays are per scenario; :func:`rollout` is a pure function of one scenario, batched
with ``jax.vmap``.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

import wmrjax as w
from wmrjax import robots
from wmrjax.robots import Geometry
from tuning.losses import Metrics


class Scenario(NamedTuple):
    """One tuning scenario (a pytree; stack along a leading axis for a batch)."""

    z0: jnp.ndarray            # controller state (plant posture/steering + compensator)
    reference: object          # wmrjax.references.Reference (its params may be batched)
    plant_geometry: Geometry   # the true geometry
    input_scale: jnp.ndarray   # (n_input,) true input = scale * command (wheel radius, axle errors)
    input_limit: jnp.ndarray   # (n_input,) |true input| <= limit (inf: none)
    noise_std: jnp.ndarray     # (n_state_X,) std of the posture/steering measurement noise
    key: jnp.ndarray           # PRNG key of the noise


class RolloutConfig(NamedTuple):
    """Static rollout settings (hashable)."""

    t_final: float = 10.0
    control_dt: float = 0.05     # controller period [s] (zero-order hold)
    substeps: int = 5            # RK4 steps of the plant per controller period
    margin_safe: float = 0.2     # barrier starts below this |det K|
    margin_floor: float = 1e-6   # at or below: singular, the scenario is invalid

    @property
    def n_periods(self) -> int:
        return int(round(self.t_final / self.control_dt))


def _stack(parts, like):
    """The vector of a tuple of scalars (empty: a (0,) vector of ``like``'s dtype)."""
    return jnp.stack(parts) if parts else jnp.zeros((0,), jnp.result_type(like))


def rollout(ctrl, gains, nominal_geometry, sc: Scenario, cfg: RolloutConfig, trajectory: bool = False):
    r"""Simulate one scenario under the linearizing law; returns :class:`Metrics` (and with
    ``trajectory`` the sampled states ``(X, controller state)`` and commands).

    Velocity level: the plant is the kinematic model (5), the command the wheel velocities u.
    Torque level (Lemma 1): the plant's state is (X, u), the command :math:`v = \dot u`; at
    every sample the controller measures X (with noise) and the wheel velocities u and lifts u
    into its compensator state (:meth:`wmrjax.controllers.law.LinearizingLaw.lift_measured`), so
    saturation and mismatch act as on a robot. ``gains``: :class:`wmrjax.Gains` or a
    :class:`wmrjax.GainSchedule`. Limits, scale and noise act on the command of the level.
    """
    law = ctrl.law
    nX = ctrl.robot.n_state
    params = ctrl.params_unchecked(sc.reference, 1.0, nominal_geometry)._replace(gains=gains)
    # the loop body runs on scalars (wmrjax.scalarized), as simulate's step does: states are
    # carried as tuples of scalars, and the parameters and the scenario are taken apart once, here
    parts, rebuild = w.scalar_parts((params, sc, nominal_geometry))
    z0 = sc.z0
    xp0 = z0[:nX]
    if ctrl.level == "torque":
        nv = law.n_velocity_state
        xp0 = jnp.concatenate([xp0, law.extension.plant_input(z0[:nX], z0[nX:nv], z0[nv:], nominal_geometry)])
    acc0 = (jnp.zeros(4), jnp.asarray(jnp.inf), jnp.asarray(False))
    # the standard normal draws of every sample at once, outside the loop (the same numbers as
    # drawing them period by period; the loop body keeps only the arithmetic of the period)
    periods = jnp.arange(cfg.n_periods)
    draws = jax.vmap(lambda k: jax.random.normal(jax.random.fold_in(sc.key, k), (nX,)))(periods)
    (_, _, alive, (tot, mmin, sing), _), traj = jax.lax.scan(
        lambda carry, kd: _period(ctrl, cfg, rebuild, carry, kd, parts),
        (tuple(jnp.unstack(xp0)), tuple(jnp.unstack(z0[nX:])), jnp.asarray(True), acc0, jnp.zeros(())),
        (periods, draws))
    mean = tot / cfg.n_periods
    m = Metrics(mean[0], mean[1], mean[2], mean[3], alive, sing, mmin)
    return (m, traj) if trajectory else m


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _period(ctrl, cfg, rebuild, carry, k_draw, parts):
    """:func:`_period_on_arrays` on scalars (:func:`wmrjax.scalarized`), jitted: traced (the
    law's jets derived, scalarized and simplified) once per controller, configuration and
    argument shapes, then reused by every program of a run (gradient, validation, the
    baselines' evaluator, figures) and by their transformations: each later program traces in
    0.04 s instead of 0.4 s (section 6.1)."""
    return w.scalarized(functools.partial(_period_on_arrays, ctrl, cfg, rebuild))(carry, k_draw, parts)


def _period_on_arrays(ctrl, cfg, rebuild, carry, k_draw, parts):
    """One controller period of :func:`rollout`: sample (with noise: ``sc.noise_std`` times the
    period's standard normal draws), control, hold the command for ``cfg.substeps`` RK4 steps of
    the plant (states as tuples of scalars). Returns the next carry and the sample
    ``(z, command)`` (XLA drops it where the rollout does not keep it)."""
    law = ctrl.law
    torque = ctrl.level == "torque"
    nX = ctrl.robot.n_state
    h = cfg.control_dt / cfg.substeps

    def plant(xp, a, sc):
        """Kinematic model (5) with the plant's geometry; at torque level its velocities integrate v."""
        if torque:
            return jnp.concatenate([robots.kinematic(ctrl.robot, xp[:nX], xp[nX:], sc.plant_geometry), a])
        return robots.kinematic(ctrl.robot, xp, a, sc.plant_geometry)

    def substep(xs, a_sc):
        a, sc = a_sc
        x, a = jnp.stack(xs), jnp.stack(a)
        k1 = plant(x, a, sc)
        k2 = plant(x + 0.5 * h * k1, a, sc)
        k3 = plant(x + 0.5 * h * k2, a, sc)
        k4 = plant(x + h * k3, a, sc)
        return tuple(jnp.unstack(x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)))

    substep = w.scalarized(substep)             # the body of its own loop
    xps, cs, alive, acc, sign_prev = carry      # plant state, controller state (compensator [, U])
    k, draw = k_draw                            # period index, standard normal draws (nX,)
    params, sc, g = rebuild(parts)
    xp, c = jnp.stack(xps), _stack(cs, xps[0])
    t = k.astype(sc.noise_std.dtype) * cfg.control_dt
    X = xp[:nX]
    noise = sc.noise_std * draw
    zm = jnp.concatenate([X + noise, c])
    if torque:
        zm = law.lift_measured(zm, xp[nX:], g)     # measured wheel velocities
    U, regularity = ctrl.control_and_regularity(t, zm, params)
    margin = jnp.abs(regularity)
    sign = jnp.sign(regularity)
    crossed = sign_prev * sign < 0          # det K changed sign since the last sample: a crossing
    cmd = law.plant_control(zm, U, g)
    a_true = jnp.clip(sc.input_scale * cmd, -sc.input_limit, sc.input_limit)
    c_next = zm[nX:] + cfg.control_dt * law.field(zm, U, g)[nX:]   # digital integrator
    a_parts = (tuple(jnp.unstack(a_true)), sc)
    xs_next, _ = jax.lax.scan(lambda x, _: (substep(x, a_parts), None), xps, None, length=cfg.substeps)
    xp_next = jnp.stack(xs_next)
    z = jnp.concatenate([X, c])
    err = ctrl.error(t, z, params)[0]
    excess = jax.nn.relu(jnp.abs(sc.input_scale * cmd) - sc.input_limit)
    terms = jnp.stack([jnp.sum(err**2), jnp.sum(cmd**2), jnp.sum(jnp.where(jnp.isfinite(excess), excess, 0.0) ** 2),
                       jax.nn.relu(1.0 - margin / cfg.margin_safe) ** 2])
    regular = (margin > cfg.margin_floor) & ~crossed
    ok = (alive & jnp.all(jnp.isfinite(xp_next)) & jnp.all(jnp.isfinite(c_next)) & jnp.all(jnp.isfinite(terms))
          & regular)
    singular = alive & ~regular
    xp_keep = jnp.where(ok, xp_next, xp)                    # freeze a failed run: no NaN downstream
    c_keep = jnp.where(ok, c_next, c)
    terms = jnp.where(ok, terms, 0.0)
    acc = (acc[0] + terms, jnp.minimum(acc[1], jnp.where(alive, margin, jnp.inf)), acc[2] | singular)
    return (tuple(jnp.unstack(xp_keep)), tuple(jnp.unstack(c_keep)), ok, acc,
            jnp.where(sign != 0, sign, sign_prev)), (z, cmd)

