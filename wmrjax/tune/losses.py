"""Loss terms for gain tuning: the metrics of a :class:`wmrjax.Trajectory` and their weights."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import certify, linearize
from wmrjax.problem import law_state

# the barrier term starts below this |det K| (a margin of the law's regularity)
MARGIN_SAFE = 0.2
# a run whose |det K| at a sample is at or below this is singular (fails)
MARGIN_FLOOR = 1e-6


class LossWeights(NamedTuple):
    """Weights of the loss terms (all >= 0, not all zero).

    Attributes:
      tracking: time-average of ||output error||^2 (posture or point) [m^2, rad^2].
      effort: time-average of ||commanded input||^2.
      saturation: time-average of the squared excess of the command over the actuator limit.
      barrier: time-average of relu(1 - ``|det K|`` / margin_safe)^2 (singularity barrier).
      certificate: minus the Lemma 2 radius with the automatic Lyapunov K2 (maximise it).
    """

    tracking: float = 1.0
    effort: float = 1e-3
    saturation: float = 1.0
    barrier: float = 1.0
    certificate: float = 0.0

    def check(self) -> "LossWeights":
        """The weights if they are finite and >= 0, else ValueError."""
        v = np.asarray(self, dtype=float)
        if not np.all(np.isfinite(v)) or np.any(v < 0):
            raise ValueError(f"loss weights must be finite and >= 0, got {self._asdict()}")
        if not np.any(v > 0):
            raise ValueError("at least one loss weight must be > 0 (all are zero: nothing to minimise)")
        return self


class Metrics(NamedTuple):
    """Per-scenario rollout metrics (time averages over the control samples)."""

    tracking: jnp.ndarray
    effort: jnp.ndarray
    saturation: jnp.ndarray
    barrier: jnp.ndarray
    valid: jnp.ndarray  # no non-finite value, margin never at the floor
    singular: jnp.ndarray  # the margin reached the floor
    min_margin: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class SampleTerms:
    """What a tuning run saves at each sample (``simulate``'s ``save_fn``; static, hashable): the
    squared position error of the true state, the squared command, the command and the margin
    (a digital controller's loop, whose samples record their error and command), or the law's
    state (a continuous loop: the error is computed afterwards)."""

    m: int
    sampled: bool

    def __call__(self, t, z, aux):
        """What one saved sample keeps: the state, or (squared error, command, margin) of a digital controller."""
        if not self.sampled:
            return z
        return (jnp.sum(z.error[: self.m] ** 2), z.command, jnp.asarray(aux.margin))


def metrics(setting, tr, params, inputs, margin_safe: float = MARGIN_SAFE) -> Metrics:
    """The loss terms of one run: time averages over its samples (every saved time but the
    final one; a digital controller's samples when it has one), failed samples counting zero.

    Args:
      setting: the problem's :class:`wmrjax.problem.Setting`.
      tr: the run's :class:`wmrjax.Trajectory`, saved at the controller's samples with
        :class:`SampleTerms` as ``save_fn``.
      params: the law's parameters of the run (reference, gains, nominal geometry).
      inputs: the run's inputs (``input_scale``, ``limit`` of the plant).
      margin_safe: the barrier term is ``relu(1 - ``|det K|`` / margin_safe)^2``.
    """
    ctrl = setting.ctrl
    n = tr.t.shape[0] - 1
    saved = jax.tree_util.tree_map(lambda x: x[:n], tr.state)
    if setting.control_period is not None:  # the digital controller's samples record their error
        err, cmd, margin = saved
    else:
        zs = law_state(setting.system(), saved)
        err = jax.vmap(lambda t, z: jnp.sum(ctrl.error(t, z, params)[0] ** 2))(tr.t[:n], zs)
        cmd, margin = tr.control[:n], tr.margin[:n]
    excess = jax.nn.relu(jnp.abs(inputs.input_scale * cmd) - inputs.limit)
    terms = (
        err,
        jnp.sum(cmd**2, axis=-1),
        jnp.sum(jnp.where(jnp.isfinite(excess), excess, 0.0) ** 2, axis=-1),
        jax.nn.relu(1.0 - margin / margin_safe) ** 2,
    )
    valid = tr.valid[:n]
    means = [jnp.sum(jnp.where(valid, x, 0.0)) / n for x in terms]
    dg = tr.diagnostics
    ok = ~dg.failed & jnp.all(jnp.isfinite(jnp.stack(means)))
    return Metrics(*means, ok, dg.singular, dg.min_margin)


def scenario_loss(m: Metrics, w: LossWeights):
    """Weighted sum of the rollout terms for one scenario (the certificate term is added once per batch)."""
    return w.tracking * m.tracking + w.effort * m.effort + w.saturation * m.saturation + w.barrier * m.barrier


def certificate_radius(gains, m1, ts, eps):
    r"""Lemma 2 radius for these gains (differentiable in them): the automatic Lyapunov K2 for
    constant gains, :math:`K_2(t) = \|\Phi(t, 0)\|` for a :class:`wmrjax.GainSchedule`."""
    if gains.time_varying:
        k2 = certify.k2_transition(gains, ts)
    else:
        k2 = certify.k2_lyapunov(linearize.companion(gains.coeffs), ts)
    return jnp.min((m1 - eps) / k2)
