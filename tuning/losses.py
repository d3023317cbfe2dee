"""Composable loss terms for gain tuning, from per-scenario rollout metrics."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from wmrjax import certify


class LossWeights(NamedTuple):
    """Weights of the loss terms (all >= 0, not all zero).

    Attributes:
      tracking: time-average of ||output error||^2 (posture or point) [m^2, rad^2].
      effort: time-average of ||commanded input||^2.
      saturation: time-average of the squared excess of the command over the actuator limit.
      barrier: time-average of relu(1 - |det K| / margin_safe)^2 (singularity barrier).
      certificate: minus the Lemma 2 radius with the automatic Lyapunov K2 (maximise it).
    """

    tracking: float = 1.0
    effort: float = 1e-3
    saturation: float = 1.0
    barrier: float = 1.0
    certificate: float = 0.0

    def check(self) -> "LossWeights":
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
    valid: jnp.ndarray          # no non-finite value, margin never at the floor
    singular: jnp.ndarray       # the margin reached the floor
    min_margin: jnp.ndarray


def scenario_loss(m: Metrics, w: LossWeights):
    """Weighted sum of the rollout terms for one scenario (the certificate term is added once per batch)."""
    return w.tracking * m.tracking + w.effort * m.effort + w.saturation * m.saturation + w.barrier * m.barrier


def certificate_radius(gains, m1, ts, eps):
    r"""Lemma 2 radius for these gains (differentiable in them): the automatic Lyapunov K2 for
    constant gains, :math:`K_2(t) = \|\Phi(t, 0)\|` for a :class:`wmrjax.GainSchedule`."""
    from wmrjax import linearize

    if gains.time_varying:
        k2 = certify.k2_transition(gains, ts)
    else:
        k2 = certify.k2_lyapunov(linearize.companion(gains.coeffs), ts)
    return jnp.min((m1 - eps) / k2)
