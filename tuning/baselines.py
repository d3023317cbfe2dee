r"""Derivative-free baselines on the same terms as the gradient tuner.

Both search the same unconstrained parameters ``raw`` of the same :class:`tuning.GainSpec`
(frozen entries stay at their initial values), are scored by the same training objective
(:func:`tuning.loop.objective`: mean valid loss plus the failure penalty, plus the certificate
term when weighted) on the same training scenarios, and are charged the same way: one rollout
is one scenario simulated once, so a candidate costs ``n_train`` rollouts.

* :func:`random_search` -- positive parameters log-uniform in a box (rates in
  ``[search_low, search_high]`` 1/s, dampings in [0.3, 3] and above ``min_damping``), every knot of a
  schedule independently;
* :func:`cma_es` -- CMA-ES (Hansen's, from the ``cmaes`` package: ask/tell on NumPy arrays;
  the candidates of a generation are simulated in one batched, compiled call), started at the
  paper's gains with step ``cma_sigma`` in the unconstrained parameters.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np



class BaselineRun(NamedTuple):
    """One seed of one baseline (plain Python values: JSON-ready)."""

    method: str
    seed: int
    best_loss: float             # best training objective found
    best_raw: list               # its unconstrained parameters
    rollouts_to_best: int        # rollouts spent when it was found
    rollouts: int                # rollouts spent in all
    best_so_far: list            # best objective after each candidate
    rollouts_per_candidate: int


def candidate_evaluator(objective_fn: Callable, shape, chunk: int = 16, compiler_options: dict | None = None):
    """``evaluate(raws, scenarios) -> objectives (N,)``: ``objective_fn(raw, scenarios)`` of N
    candidates ``raws (N, *shape)``, in compiled chunks of ``chunk`` (one program for any N and
    for every scenario set of one size; the last chunk is padded with copies of the first
    candidate). Non-finite objectives come back as +inf.

    ``objective_fn`` may also return ``(objective, aux)``: ``evaluate(raws, scenarios,
    with_aux=True)`` then returns ``(objectives, aux)`` with aux's leaves stacked along a
    leading axis N (numpy), from the same program. ``compiler_options`` go to ``jax.jit``
    (the command line passes :data:`tuning.loop.LOOP_COMPILE`).
    """
    batched = jax.jit(jax.vmap(objective_fn, in_axes=(0, None)), compiler_options=compiler_options)

    def evaluate(raws, scenarios, with_aux: bool = False):
        raws = np.asarray(raws, float).reshape((-1,) + tuple(shape))
        n = raws.shape[0]
        pad = (-n) % chunk
        full = np.concatenate([raws, np.repeat(raws[:1], pad, axis=0)]) if pad else raws
        outs = [batched(jnp.asarray(full[i:i + chunk]), scenarios) for i in range(0, full.shape[0], chunk)]
        vals, aux = zip(*outs) if isinstance(outs[0], tuple) else (outs, None)
        v = np.concatenate([np.asarray(x) for x in vals])[:n]
        v = np.where(np.isfinite(v), v, np.inf)
        if not with_aux:
            return v
        if aux is None:
            raise ValueError("with_aux=True needs an objective_fn that returns (objective, aux)")
        return v, jax.tree_util.tree_map(lambda *xs: np.concatenate([np.asarray(x) for x in xs])[:n], *aux)

    return evaluate


def _free_mask(spec):
    mask = np.ones(spec.size, bool)
    mask[list(spec.frozen)] = False
    return mask


def _record(method, seed, vals, raws, per):
    best_so_far = np.minimum.accumulate(vals)
    i = int(np.argmin(vals))
    return BaselineRun(method, int(seed), float(vals[i]), np.asarray(raws[i]).tolist(), (i + 1) * per,
                       len(vals) * per, best_so_far.tolist(), per)


def random_search(spec, evaluate, raw0, *, budget_rollouts: int, n_train: int, seed: int,
                  low: float, high: float) -> BaselineRun:
    """Candidates log-uniform in the positive-parameter box (see the module docstring)."""
    n_cand = max(1, budget_rollouts // n_train)
    rng = np.random.default_rng(seed)
    kinds = spec.kinds()
    lo = np.where(kinds == "damping", np.log(max(0.3, 1.01 * spec.min_damping)), np.log(low))
    hi = np.where(kinds == "damping", np.log(max(3.0, 2.0 * spec.min_damping)), np.log(high))
    u = rng.uniform(size=(n_cand,) + spec.shape)
    raws = np.asarray(spec.raw_from_positive(np.exp(lo + (hi - lo) * u)))
    free = _free_mask(spec).reshape(spec.shape)
    raws = np.where(free, raws, np.asarray(raw0))
    return _record("random_search", seed, evaluate(raws), raws, n_train)


def cma_es(spec, evaluate, raw0, *, budget_rollouts: int, n_train: int, seed: int, population: int,
           sigma: float) -> BaselineRun:
    """CMA-ES over the free unconstrained parameters, whole generations within the budget."""
    from cmaes import CMA

    free = _free_mask(spec)
    x0 = np.asarray(raw0, float).reshape(-1)
    n_gen = budget_rollouts // (population * n_train)
    if n_gen < 1:
        raise ValueError(f"a CMA-ES budget of {budget_rollouts} rollouts is less than one generation "
                         f"({population} x {n_train})")
    opt = CMA(mean=x0[free], sigma=sigma, population_size=population, seed=seed)
    vals, raws = [], []
    for _ in range(n_gen):
        xs = np.stack([opt.ask() for _ in range(population)])
        full = np.repeat(x0[None], population, axis=0)
        full[:, free] = xs
        v = evaluate(full.reshape((population,) + spec.shape))
        opt.tell([(x, float(min(f, 1e12))) for x, f in zip(xs, v)])
        vals.append(v)
        raws.append(full.reshape((population,) + spec.shape))
    return _record("cma_es", seed, np.concatenate(vals), np.concatenate(raws), n_train)


def rollouts_to_reach(history, target: float):
    """Rollouts after which the gradient's training objective first reached ``target`` (None: never)."""
    return next((h["rollouts"] for h in history if h["train_loss"] <= target), None)
