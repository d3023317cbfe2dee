r"""The measurement noise within a bound that brings a digital controller's loop closest to the
singular set: a worst case searched by projected gradient (issue 54, item 4).

The held reach (:func:`wmrjax.certify.held_reach_radius`) covers every noise sequence with
:math:`|n_{k,i}| \le \bar n_i` (``noise_multiple`` times ``noise_std``); Gaussian realisations
of the noise, what the real loop's falsifier draws first, are not that set's worst case (and
can leave it). This searches the set itself: the run is differentiable in the noise added at
each sample, so from zero noise it takes ``steps`` signed-gradient steps on a soft minimum of
the run's distance to the singular set, each projected back on the box (the projected
gradient method of adversarial search; its step halves every third of the steps), and keeps
the noise of the smallest distance met. That is a local search: the distance it finds is one
that noise within the bound attains (an upper bound of the worst case, estimated), never a
bound of it.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax._validate import check_int, check_positive
from wmrjax.certify.reach import NOISE_BOUND, SingularDistance
from wmrjax.controllers import Space, Task, place

NOISE_STEPS = 24
"""Projected signed-gradient steps of the search, by default."""
FIRST_STEP = 0.25
"""The first step, as a fraction of the bound (halved after each third of the steps)."""


class WorstNoise(NamedTuple):
    """Result of :func:`worst_noise` (arrays, one row per initial error).

    Attributes:
      distance: (N,) the smallest min_t distance to the singular set met (0: the run failed),
        with the noise ``noise``: attained by noise within the bound (estimated worst case).
      noise: (N, n_samples, n_X) that noise, row k added to the posture measured at sample k.
      zero_noise: (N,) the same runs' distance without noise.
    """

    distance: np.ndarray
    noise: np.ndarray
    zero_noise: np.ndarray


def worst_noise(
    setting,
    params,
    initial_errors,
    *,
    eps: float,
    plant=None,
    noise_multiple: float = NOISE_BOUND,
    steps: int = NOISE_STEPS,
) -> WorstNoise:
    """The noise within ``noise_multiple`` times ``noise_std`` that brings runs of the problem's
    digital controller closest to the singular set, searched from zero noise (module docstring).

    Args:
      setting: the problem's :class:`wmrjax.problem.Setting` (a ``control_period`` and a
        ``noise_std``).
      params: the law's parameters.
      initial_errors: (N, r m) output errors the runs start from (placed on the reference's
        branch, as the falsifier places them).
      eps: the margin [zeta units]; the soft minimum's temperature is eps / 5.
      plant: ``(limit, input_scale, geometry_scale)`` of the runs' plant, each (N, n_input),
        (N, n_input), (N,); None: the problem's first plant value.
      noise_multiple: the bound, in multiples of ``noise_std`` per component.
      steps: gradient steps (0: the zero noise only).

    Returns:
      :class:`WorstNoise`.

    Raises:
      ValueError: no digital controller or no noise; bad sizes (before compiling).
    """
    if not setting.plant or setting.control_period is None or not any(setting.noise_std):
        raise ValueError(
            "worst_noise needs a problem with a control_period and a noise_std (a noisy digital controller)"
        )
    check_positive("eps", eps)
    check_positive("noise_multiple", noise_multiple)
    check_int("steps", steps, 0)
    errs = np.asarray(initial_errors, float)
    n = setting.ctrl.relative_degree * setting.ctrl.m
    if errs.ndim != 2 or errs.shape[1] != n:
        raise ValueError(f"initial_errors must be (N, {n}) output errors, got shape {errs.shape}")
    lim, sc = _plant_rows(setting, plant, len(errs))
    bound = noise_multiple * np.asarray(setting.noise_std, float)
    g = params.geometry
    dist_fn = SingularDistance(setting.system(), setting.ctrl, type(g)(*(float(v) for v in g)))
    branch = float(setting.ctrl.reference_branch(params))
    out = _worst_runs(
        setting, dist_fn, int(steps), float(eps) / 5.0, setting.run_inputs(0), params, branch, errs, lim, sc, bound
    )
    return WorstNoise(*(np.asarray(v) for v in out))


def _plant_rows(setting, plant, count: int):
    """(limit (N, n_input), scales (N, n_input + 1)) of the runs: ``plant``, or the first plant value."""
    nu = setting.ctrl.robot.n_input
    if plant is None:
        pv = setting.axis("plant").payload
        one = (
            np.asarray(pv["limit"], float).reshape(-1, nu)[0],
            np.asarray(pv["input_scale"][0], float),
            pv["geometry_scale"][0],
        )
        plant = tuple(np.broadcast_to(np.asarray(v, float), (count, *np.shape(v))) for v in one)
    limit, input_scale, geometry_scale = (np.asarray(v, float) for v in plant)
    if limit.shape != (count, nu) or input_scale.shape != (count, nu) or geometry_scale.shape != (count,):
        raise ValueError(
            f"plant must be (limit (N, {nu}), input_scale (N, {nu}), geometry_scale (N,)) for N = {count} runs, "
            f"got shapes {limit.shape}, {input_scale.shape}, {geometry_scale.shape}"
        )
    return limit, np.concatenate([input_scale, geometry_scale[:, None]], axis=1)


def _distances(setting, dist_fn, base, params, branch, temperature: float, e0, limit, scales):
    """The run from ``e0`` as a function of its noise: ``noise -> (soft min, min)`` of its distance
    to the singular set (min 0: the run failed)."""
    z0 = place(setting.ctrl, params, e0, Space.OUTPUT, Task.POSTURE, branch)
    p = base._replace(z0=z0, limit=limit, input_scale=scales[:-1], geometry_scale=scales[-1])

    def distances(noise):
        tr, _ = setting.run(p, error_tol=math.inf, noise=noise, save_fn=dist_fn)
        d = jnp.where(tr.valid, tr.state, jnp.inf)
        hard = jnp.where(tr.diagnostics.failed, 0.0, jnp.min(d))
        # a soft minimum: its gradient weighs every sample near the closest, not the argmin alone
        soft = -temperature * jax.scipy.special.logsumexp(-jnp.where(jnp.isfinite(d), d, 1e3) / temperature)
        return soft, hard

    return distances


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3))
def _worst_runs(setting, dist_fn, steps: int, temperature: float, base, params, branch, errs, lim, sc, bound):
    """(distance, noise, zero-noise distance) per run: the projected signed-gradient search."""

    def one(e0, limit, scales):
        distances = _distances(setting, dist_fn, base, params, branch, temperature, e0, limit, scales)
        grad = jax.value_and_grad(distances, has_aux=True)

        def step(i, carry):
            noise, best, best_noise = carry
            (_, hard), g = grad(noise)
            better = hard < best
            best, best_noise = jnp.where(better, hard, best), jnp.where(better, noise, best_noise)
            size = FIRST_STEP * 0.5 ** (i // max(1, -(-steps // 3)))
            g = jnp.where(jnp.isfinite(g), g, 0.0)  # a failed run's gradient: no step
            return jnp.clip(noise - size * bound * jnp.sign(g), -bound, bound), best, best_noise

        zero = jnp.zeros(setting.noise_shape)
        _, zero_d = distances(zero)
        noise, best, best_noise = jax.lax.fori_loop(0, steps, step, (zero, zero_d, zero))
        _, last = distances(noise)
        better = last < best
        return jnp.where(better, last, best), jnp.where(better, noise, best_noise), zero_d

    return jax.vmap(one)(errs, lim, sc)


@functools.partial(jax.jit, static_argnums=(0, 1))
def noise_runs(setting, dist_fn, base, params, branch, errs, lim, sc, noise):
    """(N,) min_t distance (0: failed) of runs with the given noise ((N, n_samples, n_X)): a
    search's result re-run, e.g. at a finer step (the same samples)."""

    def one(e0, limit, scales, n):
        return _distances(setting, dist_fn, base, params, branch, 1.0, e0, limit, scales)(n)[1]

    return jax.vmap(one)(errs, lim, sc, noise)
