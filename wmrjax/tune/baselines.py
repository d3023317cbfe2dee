r"""Derivative-free baselines on the same terms as the gradient tuner.

Both search the same unconstrained parameters ``raw`` of the same :class:`wmrjax.tune.GainFamily`
(frozen entries stay at their initial values), are scored by the same training objective
(:func:`wmrjax.tune.loop.objective`: mean valid loss plus the failure penalty, plus the certificate
term when weighted) on the same training scenarios, and are charged the same way: one rollout
is one scenario simulated once, so a candidate costs ``n_train`` rollouts.

* :func:`random_search` -- positive parameters log-uniform in a box (rates in
  ``[search_low, search_high]`` 1/s, dampings in [0.3, 3] and above ``min_damping``), every knot of a
  schedule independently;
* :func:`cma_es` -- CMA-ES (Hansen's, from the ``cmaes`` package: ask/tell on NumPy arrays;
  the candidates of a generation are simulated in one batched, compiled call), started at the
  paper's gains with step ``cma_sigma`` in the unconstrained parameters;
* :func:`optuna_tpe` and :func:`optuna_cmaes` -- Optuna's TPE sampler and its CMA-ES sampler,
  what a user reaching for a tuning library would pick, through Optuna's ask-and-tell interface
  on the free unconstrained parameters in a box (random search's box mapped through
  :meth:`wmrjax.tune.GainFamily.raw_from_positive`, widened to hold the initial gains); both are told
  the initial gains first (enqueued trial 0), then ask a batch of trials at a time, simulate it
  in one batched call and tell the objectives.

Every baseline takes two optional callbacks, so that it runs under the same terms as the
gradient tuner:

* ``feasible(raw) -> bool``: a candidate it rejects is not simulated and scores +inf (a
  certified-region requirement, :func:`requirement_check`); it is charged like the others, so the
  rollout count is the number of candidates tried times ``n_train``;
* ``scenarios_for(batch_index) -> Scenario batch``: batch ``k`` of candidates (a generation of
  CMA-ES, ``batch`` candidates of the others) is scored on that draw instead of the fixed
  training set (the resampled variant; ``evaluate`` is then called as
  ``evaluate(raws, scenarios=...)``).
"""

from __future__ import annotations

import time
import warnings
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class BaselineRun(NamedTuple):
    """One seed of one baseline (plain Python values: JSON-ready)."""

    method: str
    seed: int
    best_loss: float  # best training objective found
    best_raw: list  # its unconstrained parameters
    rollouts_to_best: int  # rollouts spent when it was found
    rollouts: int  # rollouts spent in all
    best_so_far: list  # best objective after each candidate
    rollouts_per_candidate: int
    # wall seconds from the run's start until each candidate's batch was scored (sampler included)
    seconds: list | None = None
    # [candidate index, raw] at each new best: the best-so-far parameters after any candidate
    improvements: list | None = None


TOLD_CAP = 1e12  # what a sampler is told for a rejected or failed candidate (+inf breaks its ranking)


def candidate_evaluator(objective_fn: Callable, shape, chunk: int = 16, compiler_options: dict | None = None):
    """``evaluate(raws, scenarios) -> objectives (N,)``: ``objective_fn(raw, scenarios)`` of N
    candidates ``raws (N, *shape)``, in compiled chunks of ``chunk`` (one program for any N and
    for every scenario set of one size; the last chunk is padded with copies of the first
    candidate). Non-finite objectives come back as +inf.

    ``objective_fn`` may also return ``(objective, aux)``: ``evaluate(raws, scenarios,
    with_aux=True)`` then returns ``(objectives, aux)`` with aux's leaves stacked along a
    leading axis N (numpy), from the same program. ``compiler_options`` go to ``jax.jit``
    (the command line passes :data:`wmrjax.tune.loop.LOOP_COMPILE`).
    """
    batched = jax.jit(jax.vmap(objective_fn, in_axes=(0, None)), compiler_options=compiler_options)

    def evaluate(raws, scenarios, with_aux: bool = False):
        raws = np.asarray(raws, float).reshape((-1,) + tuple(shape))
        n = raws.shape[0]
        pad = (-n) % chunk
        full = np.concatenate([raws, np.repeat(raws[:1], pad, axis=0)]) if pad else raws
        outs = [batched(jnp.asarray(full[i : i + chunk]), scenarios) for i in range(0, full.shape[0], chunk)]
        vals, aux = zip(*outs) if isinstance(outs[0], tuple) else (outs, None)
        v = np.concatenate([np.asarray(x) for x in vals])[:n]
        v = np.where(np.isfinite(v), v, np.inf)
        if not with_aux:
            return v
        if aux is None:
            raise ValueError("with_aux=True needs an objective_fn that returns (objective, aux)")
        return v, jax.tree_util.tree_map(lambda *xs: np.concatenate([np.asarray(x) for x in xs])[:n], *aux)

    return evaluate


def _free_mask(family):
    mask = np.ones(family.size, bool)
    mask[list(family.frozen)] = False
    return mask


def _record(method, seed, vals, raws, per, seconds=None):
    best_so_far = np.minimum.accumulate(vals)
    i = int(np.argmin(vals))
    # a new best is strictly below every earlier candidate (the first candidate always is one)
    new = [k for k in range(len(vals)) if k == 0 or vals[k] < best_so_far[k - 1]]
    return BaselineRun(
        method,
        int(seed),
        float(vals[i]),
        np.asarray(raws[i]).tolist(),
        (i + 1) * per,
        len(vals) * per,
        best_so_far.tolist(),
        per,
        None if seconds is None else [float(t) for t in seconds],
        [[k, np.asarray(raws[k]).tolist()] for k in new],
    )


def _score(evaluate, raws, k: int, feasible, scenarios_for):
    """Objectives of batch ``k`` of candidates ``raws``: +inf where ``feasible`` rejects one (not
    simulated), on ``scenarios_for(k)`` when given (the resampled variant)."""
    raws = np.asarray(raws, float)
    ok = np.ones(len(raws), bool) if feasible is None else np.array([bool(feasible(r)) for r in raws])
    v = np.full(len(raws), np.inf)
    if ok.any():
        v[ok] = evaluate(raws[ok]) if scenarios_for is None else evaluate(raws[ok], scenarios=scenarios_for(k))
    return v


def log_box(family, low: float, high: float):
    """``(lo, hi)``, each of shape ``family.shape``: the log of random search's positive box (rates
    in [low, high] 1/s, dampings in [0.3, 3] and above ``min_damping``)."""
    kinds = family.kinds()
    lo = np.where(kinds == "damping", np.log(max(0.3, 1.01 * family.min_damping)), np.log(low))
    hi = np.where(kinds == "damping", np.log(max(3.0, 2.0 * family.min_damping)), np.log(high))
    return lo, hi


def raw_box(family, raw0, low: float, high: float):
    """``(lo, hi)`` flat: random search's box in the unconstrained parameters (the map is
    increasing), widened to hold ``raw0`` (a sampler's initial point must lie in its domain)."""
    lo, hi = log_box(family, low, high)
    r_lo = np.asarray(family.raw_from_positive(np.exp(lo)), float).reshape(-1)
    r_hi = np.asarray(family.raw_from_positive(np.exp(hi)), float).reshape(-1)
    x0 = np.asarray(raw0, float).reshape(-1)
    return np.minimum(r_lo, x0), np.maximum(r_hi, x0)


def random_search(
    family,
    evaluate,
    raw0,
    *,
    budget_rollouts: int,
    n_train: int,
    seed: int,
    low: float,
    high: float,
    batch: int = 16,
    feasible: Callable | None = None,
    scenarios_for: Callable | None = None,
) -> BaselineRun:
    """Candidates log-uniform in the positive-parameter box (see the module docstring), scored
    ``batch`` at a time (the same candidates for any ``batch``: they are drawn at once)."""
    t0 = time.perf_counter()
    n_cand = max(1, budget_rollouts // n_train)
    rng = np.random.default_rng(seed)
    lo, hi = log_box(family, low, high)
    u = rng.uniform(size=(n_cand,) + family.shape)
    raws = np.asarray(family.raw_from_positive(np.exp(lo + (hi - lo) * u)))
    free = _free_mask(family).reshape(family.shape)
    raws = np.where(free, raws, np.asarray(raw0))
    vals, secs = [], []
    for k, i in enumerate(range(0, n_cand, batch)):
        vals.append(_score(evaluate, raws[i : i + batch], k, feasible, scenarios_for))
        secs += [time.perf_counter() - t0] * len(vals[-1])
    return _record("random_search", seed, np.concatenate(vals), raws, n_train, secs)


def cma_es(
    family,
    evaluate,
    raw0,
    *,
    budget_rollouts: int,
    n_train: int,
    seed: int,
    population: int,
    sigma: float,
    feasible: Callable | None = None,
    scenarios_for: Callable | None = None,
) -> BaselineRun:
    """CMA-ES over the free unconstrained parameters, whole generations within the budget (one
    generation is one batch of ``scenarios_for``)."""
    from cmaes import CMA  # optional dependency (the cli extra): only the CMA-ES baseline needs it

    t0 = time.perf_counter()
    free = _free_mask(family)
    x0 = np.asarray(raw0, float).reshape(-1)
    n_gen = budget_rollouts // (population * n_train)
    if n_gen < 1:
        raise ValueError(
            f"a CMA-ES budget of {budget_rollouts} rollouts is less than one generation ({population} x {n_train})"
        )
    opt = CMA(mean=x0[free], sigma=sigma, population_size=population, seed=seed)
    vals, raws, secs = [], [], []
    for k in range(n_gen):
        xs = np.stack([opt.ask() for _ in range(population)])
        full = np.repeat(x0[None], population, axis=0)
        full[:, free] = xs
        v = _score(evaluate, full.reshape((population,) + family.shape), k, feasible, scenarios_for)
        opt.tell([(x, float(min(f, TOLD_CAP))) for x, f in zip(xs, v)])
        vals.append(v)
        raws.append(full.reshape((population,) + family.shape))
        secs += [time.perf_counter() - t0] * population
    return _record("cma_es", seed, np.concatenate(vals), np.concatenate(raws), n_train, secs)


def optuna_tpe(
    family,
    evaluate,
    raw0,
    *,
    budget_rollouts: int,
    n_train: int,
    seed: int,
    low: float,
    high: float,
    batch: int = 16,
    feasible: Callable | None = None,
    scenarios_for: Callable | None = None,
) -> BaselineRun:
    """Optuna's TPE sampler (its defaults, ``seed``) on the free unconstrained parameters in
    :func:`raw_box`, ``batch`` trials asked, simulated together and told at a time."""
    import optuna  # optional dependency (the cli extra): only the Optuna baseline needs it

    sampler = optuna.samplers.TPESampler(seed=seed)
    lo, hi = raw_box(family, raw0, low, high)
    return _optuna(
        "optuna_tpe",
        sampler,
        family,
        evaluate,
        raw0,
        (lo, hi),
        budget_rollouts=budget_rollouts,
        n_train=n_train,
        seed=seed,
        batch=batch,
        feasible=feasible,
        scenarios_for=scenarios_for,
    )


def optuna_cmaes(
    family,
    evaluate,
    raw0,
    *,
    budget_rollouts: int,
    n_train: int,
    seed: int,
    population: int,
    sigma: float,
    low: float,
    high: float,
    feasible: Callable | None = None,
    scenarios_for: Callable | None = None,
) -> BaselineRun:
    """Optuna's CMA-ES sampler started at ``raw0`` with population ``population``, one generation
    asked, simulated together and told at a time, in :func:`raw_box`.

    Optuna scales the box to [0, 1] per parameter and takes ``sigma0`` there: ``sigma`` in the
    unconstrained parameters becomes ``sigma`` over the narrowest side of the box (so no parameter
    starts with a step below ``sigma``, the step of :func:`cma_es`).
    """
    import optuna  # optional dependency (the cli extra): only the Optuna baseline needs it

    lo, hi = raw_box(family, raw0, low, high)
    free = _free_mask(family)
    x0 = {f"raw_{i}": float(v) for i, v in enumerate(np.asarray(raw0, float).reshape(-1)) if free[i]}
    with warnings.catch_warnings():  # x0 and sigma0 are deprecated (still in 5.x): the user's choice here
        warnings.simplefilter("ignore")
        sampler = optuna.samplers.CmaEsSampler(
            x0=x0, sigma0=float(sigma / np.min((hi - lo)[free])), seed=seed, popsize=population, n_startup_trials=1
        )
    return _optuna(
        "optuna_cmaes",
        sampler,
        family,
        evaluate,
        raw0,
        (lo, hi),
        budget_rollouts=budget_rollouts,
        n_train=n_train,
        seed=seed,
        batch=population,
        feasible=feasible,
        scenarios_for=scenarios_for,
    )


def _optuna(
    method: str,
    sampler,
    family,
    evaluate,
    raw0,
    box,
    *,
    budget_rollouts: int,
    n_train: int,
    seed: int,
    batch: int,
    feasible,
    scenarios_for,
) -> BaselineRun:
    """An Optuna study by ask and tell: trial 0 is ``raw0`` (enqueued, scored alone: a sampler
    that needs a completed trial, as the CMA-ES sampler does, then models from it), then batches
    of ``batch`` trials until ``budget_rollouts // n_train`` candidates; batch ``k`` of
    ``scenarios_for`` is the k-th scored."""
    import optuna  # optional dependency (the cli extra): only the Optuna baseline needs it

    t0 = time.perf_counter()
    optuna.logging.set_verbosity(optuna.logging.WARNING)  # no line per trial
    free = _free_mask(family)
    x0 = np.asarray(raw0, float).reshape(-1)
    names = [f"raw_{i}" for i in np.flatnonzero(free)]
    lo, hi = box
    dists = {
        n: optuna.distributions.FloatDistribution(float(lo[i]), float(hi[i]))
        for n, i in zip(names, np.flatnonzero(free))
    }
    study = optuna.create_study(direction="minimize", sampler=sampler)
    study.enqueue_trial({n: float(x0[i]) for n, i in zip(names, np.flatnonzero(free))})
    n_cand = max(1, budget_rollouts // n_train)
    sizes = [1] + [min(batch, n_cand - i) for i in range(1, n_cand, batch)]
    vals, raws, secs = [], [], []
    with warnings.catch_warnings():  # optuna's experimental-feature warnings, once per trial
        warnings.simplefilter("ignore")
        for k, size in enumerate(sizes):
            trials = [study.ask(dists) for _ in range(size)]
            full = np.repeat(x0[None], size, axis=0)
            full[:, free] = [[t.params[n] for n in names] for t in trials]
            full = full.reshape((size,) + family.shape)
            v = _score(evaluate, full, k, feasible, scenarios_for)
            for t, f in zip(trials, v):
                study.tell(t, float(min(f, TOLD_CAP)))
            vals.append(v)
            raws.append(full)
            secs += [time.perf_counter() - t0] * size
    return _record(method, seed, np.concatenate(vals), np.concatenate(raws), n_train, secs)


def requirement_check(kept) -> Callable:
    """``feasible(raw) -> bool`` of a resolved requirement (:func:`wmrjax.tune.loop.keep`): the
    radius it keeps (:func:`wmrjax.tune.certified.radius_function`) at or above the required one."""
    return lambda raw: bool(kept.radius.value(jnp.asarray(raw)) >= kept.required)


def rollouts_to_reach(history, target: float):
    """Rollouts after which the gradient's training objective first reached ``target`` (None: never)."""
    return next((h["rollouts"] for h in history if h["train_loss"] <= target), None)
