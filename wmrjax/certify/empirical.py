r"""Empirical checks of the certificates by batch simulation: (53) and regularity inside a ball
(:func:`verify`), the distance to the singular set along runs (:func:`min_distance`), and the
empirical safe radius per direction (:func:`empirical_radius`)."""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax._validate import check_int, check_positive, concrete
from wmrjax.certify.exact_map import singular_rows
from wmrjax.certify.lemma2 import check_dynamic, check_lemma2_args
from wmrjax.controllers import Space, Task, place
from wmrjax.controllers.dynamic import DynamicLinearization, DynamicParams
from wmrjax.simulate import batch_map, fixed_blocks, simulate

# Runs per compiled block, whatever the batch: a block shrunk to fit small batches was a second
# program of the same closed loop to compile (docs/benchmarks.md has its cost in the (1,2)
# certification); 256 keeps the padding of the small batches (rays, samples) cheap.
ROLLOUT_BLOCK = 256
# Runs per block of the fine confirmations (the falsifier's failures, the tuner's worst errors:
# a handful of runs at a tenth of the step, 10 times the steps): a 256-run block would simulate
# the padding 10 times longer than the runs; they share one lean program (``shared=False``)
CONFIRM_BLOCK = 16
# The confirmations' RK4 step as a fraction of the search's: one expression for both, since the
# step is a static argument of the compiled program (0.1 * dt and dt / 10 differ in the last bit
# for some dt, e.g. 0.05 s, which would compile the same program twice)
CONFIRM_DT_FACTOR = 0.1


def check_vectors(name: str, x, width: int, what: str, nonzero: bool = False) -> np.ndarray:
    """ValueError unless ``x`` is a non-empty (N, width) real finite array (rows nonzero if asked)."""
    v = concrete(x)
    if v is None:
        return x
    v = np.asarray(v)
    if v.ndim != 2 or v.shape[0] < 1 or v.shape[1] != width:
        raise ValueError(f"{name} must have shape (N, {width}) with N >= 1 ({what}), got shape {v.shape}")
    if not np.isrealobj(v) or not np.issubdtype(v.dtype, np.number) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be real and finite ({what})")
    if nonzero and np.any(np.linalg.norm(v, axis=1) == 0):
        raise ValueError(f"{name} has a zero row: every row is a direction ({what})")
    return v


def error_width(ctrl) -> int:
    """Size r m of an initial error in Table 4 ordering."""
    return ctrl.relative_degree * ctrl.m


def check_runs(ctrl, params, t_final, dt, initial_errors, save_every) -> tuple[int, int]:
    """The checks of a batch of runs from initial errors: ``(n_steps, save_every)`` or ValueError."""
    check_dynamic(ctrl, params)
    n_steps = n_steps_for(t_final, dt)
    check_vectors("initial_errors", initial_errors, error_width(ctrl), "initial errors, Table 4 ordering")
    return n_steps, check_int("save_every", save_every, 1)


def n_steps_for(t_final: float, dt: float, dt_name: str = "dt") -> int:
    """Number of RK4 steps covering [0, t_final] with step dt (ValueError for a bad pair)."""

    def real_scalar(v):
        a = np.asarray(v) if not isinstance(v, bool) else np.asarray(None)
        return a.ndim == 0 and a.dtype.kind in "iuf"

    if not (real_scalar(t_final) and real_scalar(dt)) or not (
        np.isfinite(dt) and dt > 0 and np.isfinite(t_final) and t_final > 0
    ):
        raise ValueError(
            f"t_final and {dt_name} must be finite real numbers > 0 [s], got t_final = {t_final!r}, {dt_name} = {dt!r}"
        )
    n = int(round(t_final / dt))
    if n < 1:
        raise ValueError(f"{dt_name} = {dt} s is longer than the horizon t_final = {t_final} s")
    return n


def sample_sphere(key, n, dim):
    """Points (n of them) uniformly on the unit sphere in R^dim."""
    x = jax.random.normal(key, (n, dim))
    return x / jnp.linalg.norm(x, axis=1, keepdims=True)


class Verification(NamedTuple):
    """Per-run results of :func:`verify`, each (N,)."""

    norm0: jnp.ndarray  # ||initial error||
    violation_53: jnp.ndarray  # (53) violated at some valid sample
    singular: jnp.ndarray  # the run failed (or started on the other branch)
    max_ratio: jnp.ndarray  # max_t ||err(t)|| / (K2(t) ||err(0)||)
    min_margin: jnp.ndarray  # min_t |det K|


def verify(
    ctrl: DynamicLinearization,
    params: DynamicParams,
    *,
    t_final: float,
    initial_errors,
    k2,
    dt: float,
    save_every: int = 10,
    tol: float = 1e-6,
) -> Verification:
    r"""Simulate from :math:`\zeta(0) = \zeta_{ref}(0) + \tilde\zeta_0` and check (53) and regularity.

    Args:
      ctrl: a dynamic linearizing law.
      params: its parameters.
      t_final: horizon [s].
      initial_errors: (N, r*m) initial errors (Table 4 ordering, see ``ctrl.error``).
      k2: ``ts -> K2(ts)``, the bound to check.
      dt: integration step [s].
      save_every: saving stride [steps].
      tol: absolute slack for (53), covering integration error.

    Returns:
      :class:`Verification`.
    """
    if not callable(k2):
        raise ValueError(f"k2 must be a function ts -> K2(ts), got {type(k2).__name__}")
    return verify_all(
        ctrl,
        params,
        t_final=t_final,
        initial_errors=initial_errors,
        k2s={"k2": k2},
        dt=dt,
        save_every=save_every,
        tol=tol,
    )["k2"]


def verify_all(
    ctrl: DynamicLinearization,
    params: DynamicParams,
    *,
    t_final: float,
    initial_errors,
    k2s: dict,
    dt: float,
    save_every: int = 10,
    tol: float = 1e-6,
) -> dict:
    """:func:`verify` for several K2 bounds on the same runs (simulated once).

    Args:
      ctrl: a dynamic linearizing law.
      params: its parameters.
      t_final: horizon [s].
      initial_errors: (N, r*m) initial errors (Table 4 ordering, see ``ctrl.error``).
      k2s: name -> ``ts -> K2(ts)``.
      dt: integration step [s].
      save_every: saving stride [steps].
      tol: absolute slack for (53), covering integration error.

    Returns:
      name -> :class:`Verification`.
    """
    n_steps, save_every = check_runs(ctrl, params, t_final, dt, initial_errors, save_every)
    if not isinstance(k2s, dict) or not k2s or not all(callable(f) for f in k2s.values()):
        raise ValueError(f"k2 must be a function ts -> K2(ts) (k2s: a non-empty dict of them), got {k2s!r}")
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be finite and >= 0, got {tol!r}")
    n_saves = n_steps // save_every
    ts = dt * save_every * jnp.arange(n_saves + 1, dtype=jnp.result_type(float))
    ts = ts.at[-1].set(dt * n_steps)
    k2v = np.stack([np.asarray(f(ts)) for f in k2s.values()])  # every bound on the saved grid
    if len(k2v) > _N_BOUNDS:
        raise ValueError(f"verify_all checks at most {_N_BOUNDS} K2 bounds at once, got {len(k2v)}")
    st = _blocked(ctrl, params, initial_errors, dt, n_steps, save_every, 4, ROLLOUT_BLOCK, k2v, tol)
    return {
        name: Verification(
            jnp.asarray(st.norm0),
            jnp.asarray(st.violation[:, i]),
            jnp.asarray(st.failed),
            jnp.asarray(st.ratio[:, i]),
            jnp.asarray(st.min_margin),
        )
        for i, name in enumerate(k2s)
    }


# --- running the real closed loop from initial errors ---------------------------------------


def run_from_error(ctrl, params, e0, branch, dt, n_steps, save_every):
    """Simulate from the initial error ``e0``. No error-estimate tolerance: these runs measure the
    approach to the singular set, where the law's 1 / det K terms make any fixed step locally
    inaccurate; singular states and crossings of the singular set are flagged as always, and the
    falsifier confirms its failures on a ten times finer step."""
    z0 = place(ctrl, params, e0, Space.OUTPUT, Task.POSTURE, branch)
    return simulate(ctrl, z0, params, dt=dt, n_steps=n_steps, save_every=save_every, error_tol=math.inf), z0


def distance_along(ctrl, params, tr, chord=False, within=1.0):
    """Per saved interval, dist(zeta(t), singular set) at its samples. Returns
    ``(distance (N-1,), valid (N-1,))``.

    With ``chord`` (linear singular sets), minimised over the chord between the two samples
    instead: the velocity of the output point can sweep past zero between samples, and the
    chord sees that, for the falsifier's gradient. The chord cuts inside the curve by
    O(dt^2), so it may under-estimate; failures are therefore always confirmed on samples,
    which over-estimate. For (1,2)'s curved set the samples' distances are used, capped at
    ``within`` (``ctrl.singular_distance``: a local search, ten times cheaper than the
    global one and exact below the cap; None: uncapped)."""
    valid = tr.valid[1:] & tr.valid[:-1]
    rows = singular_rows(ctrl)
    if rows is None:
        d = jax.vmap(lambda z: ctrl.singular_distance(ctrl.psi(z, params), params, within))(tr.state)
        return jnp.minimum(d[1:], d[:-1]), valid
    v = jax.vmap(lambda z: ctrl.psi(z, params).reshape(-1))(tr.state)[:, jnp.asarray(rows)]
    if not chord:
        return jnp.minimum(jnp.linalg.norm(v[1:], axis=1), jnp.linalg.norm(v[:-1], axis=1)), valid
    a, d = v[:-1], v[1:] - v[:-1]
    s = jnp.clip(-jnp.sum(a * d, axis=1) / jnp.maximum(jnp.sum(d * d, axis=1), 1e-300), 0.0, 1.0)
    return jnp.linalg.norm(a + s[:, None] * d, axis=1), valid


class Distances(NamedTuple):
    """Per-run results of :func:`min_distance`, each (N,)."""

    distance: jnp.ndarray  # min_t dist(zeta(t), S) over the samples (capped at 1 for (1,2)); 0: failed
    singular: jnp.ndarray  # flagged by the simulator (or started on the other branch)


def min_distance(
    ctrl: DynamicLinearization,
    params: DynamicParams,
    *,
    t_final: float,
    initial_errors,
    dt: float,
    save_every: int = 1,
    block: int = ROLLOUT_BLOCK,
    shared: bool = True,
) -> Distances:
    r"""Simulate from :math:`\zeta_{ref}(0) + \tilde\zeta_0` and return, per run,
    :math:`\min_t \mathrm{dist}(\zeta(t), S)` and whether the simulator flagged it singular.

    The distance is ``ctrl.singular_distance`` of the output jet (Remark 16); for (1,2), to its
    curved singular set, capped at 1 (exact below: see :func:`distance_along`). The runs go
    through :func:`window_distances`: fixed-size blocks, one compiled program whatever N is.

    Args:
      ctrl: a dynamic linearizing law.
      params: its parameters.
      t_final: horizon [s].
      initial_errors: (N, r m) initial errors.
      dt: RK4 step [s].
      save_every: stride of the distance's samples [steps].
      block: runs per compiled call (:func:`window_distances`'s; a few fine runs:
        :data:`CONFIRM_BLOCK`, the falsifier's confirmations' program).
      shared: :func:`window_distances`'s (False for those confirmations).

    Returns:
      :class:`Distances`.
    """
    n_steps, save_every = check_runs(ctrl, params, t_final, dt, initial_errors, save_every)
    _check_block(block, shared)
    per, fail, _ = window_distances(
        ctrl, params, initial_errors, dt=dt, n_steps=n_steps, save_every=save_every, block=block, shared=shared
    )
    return Distances(jnp.asarray(np.where(fail, 0.0, per.min(axis=1))), jnp.asarray(fail))


def window_distances(
    ctrl,
    params,
    initial_errors,
    *,
    dt: float,
    n_steps: int,
    save_every: int = 1,
    n_windows: int = 4,
    block: int = ROLLOUT_BLOCK,
    shared: bool = True,
):
    """Per run: the smallest distance to the singular set in each of ``n_windows`` equal windows
    of the horizon (samples), whether it failed, and the time of its closest approach.

    The batch is cut into blocks of ``block`` runs (the last one padded), so every batch size
    shares one compiled program (below); each block is spread over the
    host devices (:func:`wmrjax.batch_map`). The certification stages (empirical radius,
    falsifier sampling and confirmation, slice map) all run through it.

    With ``shared`` (the default) the runs go through the empirical check's program
    (:func:`verify_all`: the output error measured too, against no bound), compiled once for
    both; ``shared=False`` compiles a program without the output error, for runs the empirical
    check does not share a program with: the fine confirmations at ``CONFIRM_DT_FACTOR * dt``
    (the falsifier's failures, the tuner's worst errors), in blocks of :data:`CONFIRM_BLOCK`.
    One compiled program per (closed loop, dt, n_steps, save_every, n_windows, block, shared).

    Returns:
      ``(minima (N, n_windows), failed (N,), t_closest (N,))`` as NumPy arrays (failed runs:
      minima 0, t_closest the failure time).
    """
    k2v = None if shared else np.zeros((0, n_steps // save_every + 1))
    st = _blocked(ctrl, params, initial_errors, dt, n_steps, save_every, n_windows, block, k2v, 0.0)
    return st.window_minima, st.failed, st.t_closest


_N_BOUNDS = 4  # K2 bounds one compiled program checks (unused rows: an infinite bound)


class _Stats(NamedTuple):
    """What :func:`_rollout_stats` measures per run (NumPy arrays with a leading run axis)."""

    window_minima: np.ndarray  # (N, W) smallest distance to the singular set per window (0: failed)
    failed: np.ndarray  # (N,) flagged singular / non-finite, or started on the other branch
    t_closest: np.ndarray  # (N,) time of the closest approach (of the failure, for failed runs)
    norm0: np.ndarray  # (N,) ||initial error||
    violation: np.ndarray  # (N, K) (53) violated at a valid sample, per bound
    ratio: np.ndarray  # (N, K) max_t ||err(t)|| / (K2(t) ||err(0)||), per bound
    min_margin: np.ndarray  # (N,) min_t |det K|


def _blocked(ctrl, params, initial_errors, dt, n_steps, save_every, n_windows, block, k2v, tol) -> _Stats:
    """:func:`_rollout_stats` over fixed-size blocks (the last padded): one compiled program per
    (closed loop, dt, n_steps, save_every, block), whatever the batch size and the bounds."""
    errs = np.asarray(initial_errors, dtype=np.result_type(float))
    head, tail = _program_args(ctrl, params, dt, n_steps, save_every, n_windows, k2v, tol, errs.dtype)
    return _Stats(*fixed_blocks(lambda e: _rollout_stats(*head, e, *tail), [errs], block))


def _program_args(ctrl, params, dt, n_steps, save_every, n_windows, k2v, tol, dtype) -> tuple[tuple, tuple]:
    """:func:`_rollout_stats`'s arguments before and after its block of initial errors."""
    n_saved = n_steps // save_every + 1
    # K2 bounds given as none at all (an empty k2v): a program without the output error
    rows = 0 if k2v is not None and len(k2v) == 0 else _N_BOUNDS
    bounds = np.full((rows, n_saved), np.inf)
    if k2v is not None:
        bounds[: len(k2v)] = k2v
    branch = jnp.asarray(float(ctrl.reference_branch(params)))
    return (ctrl, params), (jnp.asarray(bounds), jnp.asarray(tol, dtype), branch, dt, n_steps, save_every, n_windows)


def _check_block(block, shared) -> None:
    """ValueError for a bad ``block`` (an integer >= 1) or ``shared`` (a bool)."""
    check_int("block", block, 1)
    if not isinstance(shared, bool):
        raise ValueError(f"shared must be True or False, got {shared!r}")


def compile_window_distances(ctrl, params, *, dt: float, n_steps: int, n_windows: int = 4, block: int, shared: bool):
    """Compile :func:`window_distances`'s program for these settings without running it (its
    first call then finds it compiled): to compile ahead, e.g. on another thread while
    something else computes. Arguments as :func:`window_distances`'s (``save_every`` 1)."""
    check_dynamic(ctrl, params)
    _check_block(block, shared)
    for name, v in (("n_steps", n_steps), ("n_windows", n_windows)):
        check_int(name, v, 1)
    check_positive("dt", dt)
    k2v = None if shared else np.zeros((0, n_steps + 1))
    dtype = np.result_type(float)
    head, tail = _program_args(ctrl, params, dt, n_steps, 1, n_windows, k2v, 0.0, dtype)
    _rollout_stats.lower(*head, jnp.zeros((block, error_width(ctrl)), dtype), *tail).compile()


@functools.partial(jax.jit, static_argnums=(0, 6, 7, 8, 9))
def _rollout_stats(ctrl, params, errs, k2, tol, branch, dt, n_steps, save_every, n_windows):
    """Every batch measurement of the certification stages from one rollout per initial error."""
    edges = jnp.linspace(0.0, dt * n_steps, n_windows + 1)

    def one(e0):
        tr, z0 = run_from_error(ctrl, params, e0, branch, dt, n_steps, save_every)
        dist, valid = distance_along(ctrl, params, tr)
        d = jnp.where(valid, dist, jnp.inf)
        mid = 0.5 * (tr.t[1:] + tr.t[:-1])
        inside = (mid[None] >= edges[:-1, None]) & (mid[None] <= edges[1:, None])
        per = jnp.min(jnp.where(inside, d[None], jnp.inf), axis=1)
        fail = tr.diagnostics.failed | (ctrl.branch_quantity(z0, params) * branch <= 0)
        i = jnp.argmin(d)
        n0 = jnp.linalg.norm(e0)
        viol, ratio = _bound_checks(ctrl, params, tr, k2 * n0, tol)
        return (
            jnp.where(fail, 0.0, per),
            fail,
            jnp.where(fail, tr.diagnostics.t_failure, tr.t[i]),
            n0,
            viol,
            ratio,
            tr.diagnostics.min_margin,
        )

    return batch_map(one, errs, chunk=64)


def _bound_checks(ctrl, params, tr, bound, tol):
    """(53) against every bound ``bound`` (K, T) on the saved grid of the run ``tr``: per bound,
    whether it is violated at a valid sample and the largest ratio ||error|| / bound. With no
    bound (K = 0) the output error is not evaluated: one placeholder column ``(False, 0)`` (the
    batch over runs needs a non-empty axis)."""
    if bound.shape[0] == 0:
        return jnp.zeros((1,), dtype=bool), jnp.zeros((1,), dtype=bound.dtype)
    err = jax.vmap(lambda t, z: ctrl.error(t, z, params).reshape(-1))(tr.t, tr.state)
    nrm = jnp.linalg.norm(err, axis=1)
    viol = jnp.any(tr.valid[None] & (nrm[None] > bound + tol), axis=1)
    ratio = jnp.max(jnp.where(tr.valid[None], nrm[None] / jnp.maximum(bound, 1e-300), 0.0), axis=1)
    return viol, ratio


# the empirical radius's search (its defaults): radii on the first grid, dips refined per ray,
# golden-section rounds per dip, bisection steps (wmrjax.certify.budget counts its runs with them)
RADIUS_GRID, RADIUS_DIPS, RADIUS_GOLDEN, RADIUS_BISECT = 48, 3, 16, 14


class EmpiricalRadius(NamedTuple):
    """Result of :func:`empirical_radius`."""

    per_direction: np.ndarray  # (D,) first failing radius per ray (inf: none up to r_max)
    radius: float  # min over the rays
    worst_direction: np.ndarray  # (r m,) the ray attaining it
    n_runs: int  # simulations used


def empirical_radius(
    ctrl: DynamicLinearization,
    params: DynamicParams,
    *,
    t_final: float,
    eps: float,
    directions,
    r_max: float,
    dt: float,
    n_grid: int = RADIUS_GRID,
    n_dips: int = RADIUS_DIPS,
    n_golden: int = RADIUS_GOLDEN,
    n_bisect: int = RADIUS_BISECT,
) -> EmpiricalRadius:
    r"""Empirical safe radius per direction by simulation: the smallest :math:`\rho \le` ``r_max``
    at which the run from :math:`\rho d` comes within ``eps`` of the singular set (or is flagged).

    Along a ray, :math:`m(\rho) = \min_t \mathrm{dist}(\zeta(t), S)` dips below eps only on a
    narrow interval (past it, the velocity of the output point swings around zero instead of
    through it), which a plain grid misses. So: sample m on ``n_grid`` radii, minimise it by
    golden section inside the brackets of the first ``n_dips`` local minima, and bisect for the
    first crossing of eps. All rounds are vmapped over (direction, dip). Rays that never fail
    report ``inf``.

    Args:
      ctrl: a dynamic linearizing law.
      params: its parameters.
      t_final: horizon [s].
      eps: the margin.
      directions: (D, r m) unit vectors.
      r_max: largest radius searched.
      dt: RK4 step [s].
      n_grid: radii sampled per ray.
      n_dips: local minima of m per ray refined.
      n_golden: golden-section iterations per dip.
      n_bisect: bisection steps for the first crossing of eps.

    Returns:
      :class:`EmpiricalRadius`.
    """
    dirs, n_grid = _check_radius_args(
        ctrl, params, t_final, eps, directions, r_max, dt, n_grid, n_dips=n_dips, n_golden=n_golden, n_bisect=n_bisect
    )
    D = dirs.shape[0]
    g = np.linspace(0.0, r_max, n_grid + 1)[1:]
    runs = 0

    def m_of(dd, rr):
        nonlocal runs
        runs += rr.size
        d, s = min_distance(ctrl, params, t_final=t_final, initial_errors=dd * rr[:, None], dt=dt)
        return np.where(np.asarray(s), 0.0, np.asarray(d))

    m = m_of(np.repeat(dirs, n_grid, axis=0), np.tile(g, D)).reshape(D, n_grid)
    lo, hi = _dip_brackets(m, g, n_dips)
    dd = np.repeat(dirs, n_dips, axis=0)
    r_star = _golden_minima(m_of, dd, lo.reshape(-1), hi.reshape(-1), n_golden)
    dips = m_of(dd, r_star) < eps
    # first crossing of eps: below every failing dip, and below the first failing grid radius
    first = np.where((m < eps).any(axis=1), (m < eps).argmax(axis=1), -1)
    g0 = np.concatenate([[0.0], g])
    cand_lo = np.concatenate([lo.reshape(-1), g0[np.maximum(first, 0)]])
    cand_hi = np.concatenate([np.where(dips, r_star, np.inf), np.where(first >= 0, g[np.maximum(first, 0)], np.inf)])
    cand_d = np.concatenate([dd, dirs])
    owner = np.concatenate([np.repeat(np.arange(D), n_dips), np.arange(D)])
    live = np.isfinite(cand_hi)
    cl, ch = cand_lo[live], cand_hi[live]
    for _ in range(n_bisect if live.any() else 0):
        mid = 0.5 * (cl + ch)
        fail = m_of(cand_d[live], mid) < eps
        ch, cl = np.where(fail, mid, ch), np.where(fail, cl, mid)
    per = np.full(D, np.inf)
    np.minimum.at(per, owner[live], ch)
    k = int(np.argmin(per))
    return EmpiricalRadius(per, float(per[k]), dirs[k], runs)


def _check_radius_args(ctrl, params, t_final, eps, directions, r_max, dt, n_grid, **rounds) -> tuple[np.ndarray, int]:
    """ValueError for a bad argument of :func:`empirical_radius`; returns ``(directions, n_grid)``
    checked (``rounds``: ``n_dips``, ``n_golden``, ``n_bisect``, each at least 1)."""
    check_dynamic(ctrl, params)
    check_lemma2_args(t_final=t_final, eps=eps, reference=params.reference)
    n_steps_for(t_final, dt)
    check_positive("r_max", r_max)
    n_grid = check_int("n_grid", n_grid, 2)
    for k, v in rounds.items():
        check_int(k, v, 1)
    dirs = check_vectors("directions", directions, error_width(ctrl), "unit directions of initial errors", nonzero=True)
    return dirs, n_grid


def _dip_brackets(m, g, n_dips: int) -> tuple[np.ndarray, np.ndarray]:
    """Brackets ``(lo, hi)``, each (D, n_dips), of grid radii around the ``n_dips`` deepest local
    minima of each ray's sampled distances ``m`` (D, n_grid) on the radii ``g`` (a ray with fewer
    local minima repeats its last one)."""
    D, n_grid = m.shape
    padded = np.concatenate([np.full((D, 1), np.inf), m, np.full((D, 1), np.inf)], axis=1)
    is_min = (padded[:, 1:-1] <= padded[:, :-2]) & (padded[:, 1:-1] <= padded[:, 2:])
    lo = np.zeros((D, n_dips))
    hi = np.zeros((D, n_dips))
    for k in range(D):
        idx = np.where(is_min[k])[0]
        idx = list(idx[np.argsort(m[k, idx])][:n_dips])
        idx += [idx[-1]] * (n_dips - len(idx))
        lo[k] = [g[j - 1] if j > 0 else 0.0 for j in idx]
        hi[k] = [g[min(j + 1, n_grid - 1)] for j in idx]
    return lo, hi


GOLDEN_FRACTION = 0.5 * (math.sqrt(5.0) - 1.0)  # golden section: the bracket shrinks by this per round


def _golden_minima(m_of, dd, a, b, n_golden: int) -> np.ndarray:
    """Golden-section minimisation of ``m_of`` along each ray ``dd[i]`` inside ``[a[i], b[i]]``, all
    brackets in one batch per round: the centres of the final brackets, after ``n_golden``
    shrinks. Each round keeps one interior point and its value (the golden ratio puts it where
    the next round needs it) and simulates only the other: two runs per ray in the first round, one in
    each of the others."""
    x1, x2 = b - GOLDEN_FRACTION * (b - a), a + GOLDEN_FRACTION * (b - a)
    f12 = m_of(np.concatenate([dd, dd]), np.concatenate([x1, x2]))
    f1, f2 = f12[: len(a)], f12[len(a) :]
    for k in range(n_golden):
        left = f1 <= f2  # the minimum lies in [a, x2]: x1 becomes its upper interior point
        a, b = np.where(left, a, x1), np.where(left, x2, b)
        if k == n_golden - 1:
            break
        new = np.where(left, b - GOLDEN_FRACTION * (b - a), a + GOLDEN_FRACTION * (b - a))
        f_new = m_of(dd, new)
        x1, x2, f1, f2 = (
            np.where(left, new, x2),
            np.where(left, x1, new),
            np.where(left, f_new, f2),
            np.where(left, f1, f_new),
        )
    return 0.5 * (a + b)
