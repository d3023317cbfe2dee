r"""Falsification: search through the simulated closed loop for initial errors that come within
eps of the singular set; an upper bound on every certified radius.

:func:`falsified_radius` needs nothing but the closed loop and the distance to the singular
set: no exact map, no known worst case. Per radius it combines three stages, each covering
what the others miss, and every failure it reports is confirmed on a ten times finer
simulation:

1. *instantaneous*: minimise the distance at t = 0 over the sphere directly (no rollout):
   a failure visible at the initial state, such as a velocity error cancelling the
   reference's velocity, is found exactly;
2. *global sampling*: many random directions on the sphere, simulated once (forward only),
   ranked by their distance within each time window of the horizon;
3. *gradient refinement* (:func:`falsify`): Adam on the sphere through the simulated loop,
   from the best of both stages per window and from the previous radius's iterates.

The radius is then searched by bisection, and each confirmed failure is pulled in along
its own ray (the smallest failing radius on a grid of the ray, refined), which moves the
upper end of the bracket further than halving would."""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from wmrjax._validate import check_int, check_positive
from wmrjax.certify.empirical import (
    CONFIRM_BLOCK,
    CONFIRM_DT_FACTOR,
    check_vectors,
    compile_window_distances,
    distance_along,
    n_steps_for,
    run_from_error,
    window_distances,
)
from wmrjax.certify.exact_map import Slice, slice_basis, square_basis
from wmrjax.certify.lemma2 import check_dynamic, check_lemma2_args
from wmrjax.controllers.dynamic import DynamicLinearization, DynamicParams
from wmrjax.simulate import batch_map

SEARCH_WINDOWS = 4  # time windows of falsified_radius's samples and gradient starts, by default


class Falsification(NamedTuple):
    """Result of :func:`falsify` at one radius."""

    initial_errors: jnp.ndarray  # (S, r m) final iterate of every start
    distance: jnp.ndarray  # (S,) min_t dist(zeta(t), S) of each (0: the run failed)
    best: jnp.ndarray  # index of the worst case found


def falsify(
    ctrl: DynamicLinearization,
    params: DynamicParams,
    *,
    t_final: float,
    radius,
    starts,
    dt: float,
    basis=Slice.FULL,
    steps: int = 60,
    learning_rate: float = 0.1,
    n_windows: int = 8,
    windows=None,
) -> Falsification:
    r"""Gradient search for the worst initial error on the sphere :math:`\|\tilde\zeta_0\| = \rho`.

    Minimises :math:`\min_t \mathrm{dist}(\zeta(t), S)` over the simulated closed loop (forward-mode
    sensitivities through the RK4 scan, one per slice coordinate) with optax Adam on an unconstrained :math:`u`, mapped to the sphere by
    :math:`\tilde\zeta_0 = \rho P u / \|u\|` (projection), from every start at once (vmapped).
    Random sampling misses thin unsafe cones; following the gradient does not need to hit them.

    A single objective :math:`\min_{t\in[0,T]}` has one dominant basin (the time at which most
    directions come closest), and thin cones at other times are missed. So start i minimises
    the distance over its own window of the horizon, window ``i % n_windows`` of
    ``n_windows`` equal ones: every part of the horizon is searched. Adam's step decays
    100-fold over the run, so iterates settle inside eps-thin sets.

    Args:
      ctrl: a dynamic linearizing law.
      params: its parameters.
      t_final: horizon [s].
      dt: RK4 step of the search [s].
      radius: sphere radius rho.
      starts: (S, k) initial directions in slice coordinates (need not be normalised).
      basis: slice, see :func:`slice_basis`.
      steps: Adam iterations.
      learning_rate: Adam's initial step size (on the unit sphere).
      n_windows: number of time windows the starts are spread over.
      windows: (S, 2) explicit time window [s] of each start instead (overrides ``n_windows``).
    """
    check_dynamic(ctrl, params)
    n_steps = n_steps_for(t_final, dt)
    P = slice_basis(ctrl, basis)
    check_positive("radius", radius)
    check_vectors("starts", starts, P.shape[1], "initial directions in slice coordinates", nonzero=True)
    steps = check_int("steps", steps, 1)
    n_windows = check_int("n_windows", n_windows, 1)
    check_positive("learning_rate", learning_rate)
    u0 = jnp.asarray(starts)
    if windows is None:
        edges = jnp.linspace(0.0, dt * n_steps, n_windows + 1)
        win = jnp.arange(u0.shape[0]) % n_windows
        windows = jnp.stack([edges[win] - 0.5 * dt, edges[win + 1] + 0.5 * dt], axis=1)
    else:
        windows = jnp.asarray(check_vectors("windows", windows, 2, "time windows [s] of the starts"))
        if windows.shape[0] != u0.shape[0] or not bool(jnp.all(windows[:, 0] <= windows[:, 1])):
            raise ValueError(
                f"windows must be ({u0.shape[0]}, 2) intervals [t0, t1] with t0 <= t1 [s], one per start, "
                f"got shape {windows.shape}"
            )
    Q = square_basis(P)  # every slice through one compiled program: directions padded with zeros
    args = _search_args(ctrl, params, radius, u0, windows, Q)
    us, vals = _falsify(*args, dt, n_steps, steps, learning_rate)
    errs = radius * (us / jnp.linalg.norm(us, axis=1, keepdims=True)) @ Q.T
    return Falsification(errs, vals, jnp.argmin(vals))


def _search_args(ctrl, params, radius, u0, windows, Q) -> tuple:
    """:func:`_falsify`'s array arguments (before its static ones) for the starts ``u0`` (S, k)."""
    branch = jnp.asarray(float(ctrl.reference_branch(params)))
    u = _pad(u0 / jnp.linalg.norm(u0, axis=1, keepdims=True), Q)
    return ctrl, params, jnp.asarray(radius, dtype=u0.dtype), u, windows, Q, branch


@functools.partial(jax.jit, static_argnums=(0, 7, 8, 9, 10))
def _falsify(ctrl, params, radius, us, windows, P, branch, dt, n_steps, steps, learning_rate):
    opt = optax.adam(optax.exponential_decay(learning_rate, steps, 0.01))

    def objective(u, window):
        e0 = radius * (P @ (u / jnp.linalg.norm(u)))
        tr, _ = run_from_error(ctrl, params, e0, branch, dt, n_steps, 1)
        inside = (tr.t[1:] >= window[0]) & (tr.t[:-1] <= window[1])
        dist, valid = distance_along(ctrl, params, tr, chord=True)
        d = jnp.min(jnp.where(valid & inside, dist, jnp.inf))
        return jnp.where(tr.diagnostics.failed, 0.0, d)

    def value_and_grad(u, window):
        # forward mode over the (at most r m) directions: one jvp per direction sharing the primal
        # run; it compiles about twice as fast as reverse mode through the rollout
        eye = jnp.eye(u.shape[0], dtype=u.dtype)
        vals, tangents = jax.vmap(lambda v: jax.jvp(lambda x: objective(x, window), (u,), (v,)))(eye)
        return vals[0], tangents

    vg = lambda us, windows: batch_map(value_and_grad, us, windows, chunk=64)

    def step(c, _):
        us, state, best_u, best_v = c
        v, g = vg(us, windows)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        better = v < best_v
        best_u = jnp.where(better[:, None], us, best_u)
        best_v = jnp.where(better, v, best_v)
        with jax.numpy_dtype_promotion("standard"):  # optax mixes its int32 step count with floats
            upd, state = opt.update(g, state, us)
        us = optax.apply_updates(us, upd)
        us = us / jnp.linalg.norm(us, axis=1, keepdims=True)
        return (us, state, best_u, best_v), None

    init = (us, opt.init(us), us, jnp.full(us.shape[0], jnp.inf))
    # one iteration more than Adam's steps: its value (and best) is the last iterate's, its update
    # unused; the objective is traced and compiled once, inside the forward-mode program
    (_, _, best_u, best_v), _ = jax.lax.scan(step, init, None, length=steps + 1)
    return best_u, best_v


class FalsifiedRadius(NamedTuple):
    """Result of :func:`falsified_radius` (fixed fields; None where nothing failed).

    Attributes:
      radius: smallest radius at which a confirmed failure was found (None: none): an upper
        bound of the safe radius, whose distance to it depends on the search's random draws.
      initial_error: (r m,) that failure's initial error (None: none).
      distance: its confirmed min_t distance to the singular set (None: none).
      rollouts: simulations used: sampled, gradient (one per start and iteration), confirming
        and ray runs (a fine confirming run counts one).
      bracket: (lo, hi): the last bisection bracket (None: nothing failed). ``lo`` is the
        largest radius at which the search found no failure, not a proof that none exists.
      searched_up_to: the largest radius searched.
      rollouts_by_stage: ``{"sampling", "gradient", "confirmation"}`` -> simulations, and
        ``"instantaneous"`` -> evaluations of the distance at t = 0 (no simulation).
      t_failure: time [s] at which the confirmed failure comes closest (None: none).
    """

    radius: float | None
    initial_error: np.ndarray | None
    distance: float | None
    rollouts: int
    bracket: tuple | None
    searched_up_to: float
    rollouts_by_stage: dict | None = None
    t_failure: float | None = None


def falsified_radius(
    ctrl: DynamicLinearization,
    params: DynamicParams,
    *,
    t_final: float,
    eps: float,
    key,
    dt: float,
    basis=Slice.FULL,
    r_lo: float = 0.0,
    r_hi: float | None = None,
    n_starts: int = 16,
    steps: int = 30,
    n_samples: int = 512,
    n_bisect: int = 16,
    rtol: float = 2e-3,
    learning_rate: float = 0.1,
    n_windows: int = SEARCH_WINDOWS,
) -> FalsifiedRadius:
    """The smallest radius at which the falsifier finds a confirmed failure (dist < eps or singular).

    Tries ``r_hi`` (default: twice ``r_lo``, or 1 when ``r_lo`` is 0), doubled up to 4 times
    until a failure is found, then bisects between ``r_lo`` (typically a certified radius)
    and the smallest failing radius until the bracket is narrower than ``rtol`` times it.
    Every attempt runs the three stages of the module docstring; each failure is confirmed
    by a simulation ten times finer and pulled in along its ray. The result is an upper
    bound on the true safe radius: every certified radius must lie below it.

    Args:
      ctrl: a dynamic linearizing law.
      params: its parameters.
      t_final: horizon [s].
      eps: the margin.
      key: PRNG key of the random starts and samples.
      dt: RK4 step of the search [s] (failures are confirmed at dt / 10).
      basis: slice, see :func:`slice_basis`.
      r_lo: lower end of the search (a radius known safe).
      r_hi: the first radius tried.
      n_starts: gradient starts per attempt.
      steps: their Adam iterations.
      learning_rate: Adam's initial step size.
      n_samples: random directions simulated per attempt (global stage).
      n_bisect: largest number of bisection steps.
      rtol: relative width that stops them.
      n_windows: time windows the samples are ranked in and the gradient starts spread over.

    Returns:
      :class:`FalsifiedRadius` (radius None if nothing failed up to 16 times the first radius).
    """
    # the settings the checks and the search share
    settings = dict(
        n_starts=n_starts, steps=steps, n_samples=n_samples, learning_rate=learning_rate, n_windows=n_windows
    )
    r_hi = _check_falsifier_args(
        ctrl, params, t_final=t_final, eps=eps, r_lo=r_lo, r_hi=r_hi, n_bisect=n_bisect, rtol=rtol, **settings
    )
    search = _Search(ctrl, params, t_final=t_final, eps=eps, key=key, dt=dt, basis=basis, r_lo=r_lo, **settings)
    rad, found, warm = float(r_hi), None, None
    for _ in range(5):
        found, warm = search.attempt(rad, warm)
        if found is not None:
            searched = rad
            break
        search.lo, rad = rad, 2.0 * rad
    if found is None:
        return FalsifiedRadius(None, None, None, search.rollouts(), None, rad / 2.0, search.counts, None)
    radius, error, distance, t_failure = search.bisect(found, warm, n_bisect, rtol)
    bracket = (search.lo, float(radius))
    rollouts = search.rollouts()
    return FalsifiedRadius(
        float(radius), np.asarray(error), distance, rollouts, bracket, searched, search.counts, t_failure
    )


def _check_falsifier_args(
    ctrl, params, *, t_final, eps, r_lo, r_hi, n_starts, steps, n_samples, n_bisect, n_windows, learning_rate, rtol
) -> float:
    """ValueError for a bad argument of :func:`falsified_radius`; returns ``r_hi`` (its default filled in)."""
    check_dynamic(ctrl, params)
    check_lemma2_args(t_final=t_final, eps=eps, reference=params.reference)
    if not (isinstance(r_lo, (int, float, np.floating, np.integer)) and np.isfinite(r_lo) and r_lo >= 0):
        raise ValueError(f"r_lo must be a finite radius >= 0, got {r_lo!r}")
    if r_hi is None:
        r_hi = 2.0 * float(r_lo) if r_lo > 0 else 1.0
    check_positive("r_hi", r_hi)
    if not r_lo < r_hi:
        raise ValueError(f"r_lo must satisfy 0 <= r_lo < r_hi = {r_hi}, got {r_lo!r}")
    for name, v, lo in (
        ("n_starts", n_starts, 1),
        ("steps", steps, 1),
        ("n_samples", n_samples, 1),
        ("n_bisect", n_bisect, 0),
        ("n_windows", n_windows, 1),
    ):
        check_int(name, v, lo)
    check_positive("learning_rate", learning_rate)
    check_positive("rtol", rtol)
    return r_hi


N_INSTANTANEOUS = 64  # random starts of the instantaneous stage (no rollout)
N_INSTANT_STARTS = 2  # its best minimisers, among a gradient stage's starts
# the bisection's first step below the smallest failure, relative to it, and its largest: at 0.5
# the step reaches no lower than the bracket's midpoint (its lower end is >= 0), i.e. plain halving
FIRST_STEP, MAX_STEP = 0.02, 0.5


class _Search:
    """One falsification's state: the closed loop and settings, the PRNG keys still unused, the
    rollouts spent per stage (``counts``) and the largest radius known safe so far (``lo``).
    Its methods are the stages of :func:`falsified_radius`."""

    def __init__(
        self, ctrl, params, *, t_final, eps, key, dt, basis, n_starts, steps, n_samples, learning_rate, n_windows, r_lo
    ):
        self.ctrl, self.params, self.t_final, self.eps, self.dt, self.basis = ctrl, params, t_final, eps, dt, basis
        self.n_starts, self.steps, self.n_samples = n_starts, steps, n_samples
        self.learning_rate, self.n_windows = learning_rate, n_windows
        self.n_steps = n_steps_for(t_final, dt)
        self.fine = CONFIRM_DT_FACTOR * dt
        self.n_fine = n_steps_for(t_final, self.fine)
        P = slice_basis(ctrl, basis)
        self.k, self.Pn, self.Q = P.shape[1], np.asarray(P), square_basis(P)
        self.keys = iter(jax.random.split(key, 64))
        self.counts = {"instantaneous": 0, "sampling": 0, "gradient": 0, "confirmation": 0}
        self.lo = float(r_lo)

    def rollouts(self) -> int:
        """Rollouts spent (the instantaneous stage simulates nothing)."""
        return sum(v for n, v in self.counts.items() if n != "instantaneous")

    def confirm(self, errs):
        """Fine runs (blocks of :data:`CONFIRM_BLOCK`: most calls confirm 8 candidates or fewer) of
        initial errors: (failed, distance, time of the closest approach)."""
        per, s, t = window_distances(
            self.ctrl, self.params, errs, dt=self.fine, n_steps=self.n_fine, block=CONFIRM_BLOCK, shared=False
        )
        self.counts["confirmation"] += len(per)
        d = per.min(axis=1)
        return (d < self.eps) | s, np.where(s, 0.0, d), t

    def along_rays(self, errs, lo, hi, d_hi, t_hi):
        """Per failing error (its radius ``hi`` fails, its confirmed distance ``d_hi`` and time
        ``t_hi``), the smallest confirmed failing radius on its ray, three rounds of an 8-point
        grid between ``lo`` and the current failing radius: ``(radius, point, distance, time)``,
        the point being the initial error simulated at that radius (no run repeated)."""
        u = errs / np.linalg.norm(errs, axis=1, keepdims=True)
        lo = np.full(len(u), float(lo))
        hi = np.full(len(u), float(hi))
        point, d_hi, t_hi = np.array(errs, dtype=float), np.asarray(d_hi, float), np.asarray(t_hi, float)
        frac = np.arange(1, 9) / 8.0
        rows = np.arange(len(u))
        for _ in range(3):
            rs = lo[:, None] + (hi - lo)[:, None] * frac[None]  # (n, 8)
            pts = rs[..., None] * u[:, None, :]  # (n, 8, r m)
            fail, d, t = (x.reshape(rs.shape) for x in self.confirm(pts.reshape(-1, u.shape[1])))
            j = np.argmax(fail, axis=1)
            any_fail = fail.any(axis=1)
            prev = np.where(j > 0, rs[rows, np.maximum(j - 1, 0)], lo)
            hi = np.where(any_fail, rs[rows, j], hi)
            point = np.where(any_fail[:, None], pts[rows, j], point)
            d_hi, t_hi = np.where(any_fail, d[rows, j], d_hi), np.where(any_fail, t[rows, j], t_hi)
            lo = np.where(any_fail, prev, rs[:, -2])
        return hi, point, d_hi, t_hi

    def on_sphere(self, dirs, rad):
        """(N, k) slice directions -> (N, r m) initial errors of norm ``rad``."""
        dirs = np.asarray(dirs)
        return rad * (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)) @ self.Pn.T

    def settle(self, cands, rad):
        """Confirm the (at most 8) best candidates at ``rad`` (a coarse failure may be spurious); pull
        the two best confirmed failures in along their rays. (radius, error, distance, t) or None."""
        cands = cands[:8]
        fail, d, t = self.confirm(cands)
        if not fail.any():
            return None
        first = np.where(fail)[0][:2]
        r_ray, point, d_ray, t_ray = self.along_rays(cands[first], self.lo, rad, d[first], t[first])
        j = int(np.argmin(r_ray))
        return float(r_ray[j]), point[j], float(d_ray[j]), float(t_ray[j])

    def cheap_stages(self, rad):
        """Stages 1 and 2 at one radius: the instantaneous distance at t = 0 over the sphere (no
        rollout) and global sampling ranked per time window. ``(u_inst, d_inst, dirs, per_win)``."""
        u_inst, d_inst = _instantaneous(
            self.ctrl,
            self.params,
            jnp.asarray(rad),
            self.Q,
            _pad(jax.random.normal(next(self.keys), (N_INSTANTANEOUS, self.k)), self.Q),
            200,
            self.learning_rate,
        )
        self.counts["instantaneous"] += N_INSTANTANEOUS * 201
        best_inst = np.argsort(np.asarray(d_inst))[:N_INSTANT_STARTS]
        u_inst, d_inst = np.asarray(u_inst)[best_inst, : self.k], np.asarray(d_inst)[best_inst]
        dirs = np.asarray(jax.random.normal(next(self.keys), (self.n_samples, self.k)))
        per_win, _, _ = window_distances(
            self.ctrl,
            self.params,
            self.on_sphere(dirs, rad),
            dt=self.dt,
            n_steps=self.n_steps,
            n_windows=self.n_windows,
        )
        self.counts["sampling"] += self.n_samples
        return u_inst, d_inst, dirs, per_win

    def bisect(self, found, warm, n_bisect: int, rtol: float):
        """At most ``n_bisect`` attempts between the largest radius known safe (``lo``, moved up
        by them) and the smallest confirmed failure ``found`` (from :meth:`settle`), until the
        bracket is narrower than ``rtol`` times its upper end: the smallest failure found."""
        step = FIRST_STEP
        for _ in range(n_bisect):
            lo, hi = self.lo, found[0]
            if hi - lo <= rtol * hi:
                break
            # a step below the smallest failure that doubles while failures keep being found, and
            # halving once one is not: the bracket shrinks fast whether or not its lower end (often
            # a loose certified radius) is near the answer
            mid = max(0.5 * (lo + hi), (1.0 - step) * hi)
            new, warm = self.attempt(mid, warm)
            if new is not None:
                found, step = new, min(2.0 * step, MAX_STEP)
            else:
                self.lo = mid
        return found

    def attempt(self, rad, warm):
        """The three stages at one radius: ((radius <= rad, error, distance) or None, warm directions).
        The gradient stage runs only when the cheap stages find no confirmed failure."""
        u_inst, d_inst, dirs, per_win = self.cheap_stages(rad)
        best_samples = np.argsort(per_win.min(axis=1))[:2]
        cheap = np.concatenate([u_inst, dirs[best_samples]])
        order = np.argsort(np.concatenate([d_inst, per_win.min(axis=1)[best_samples]]))
        found = self.settle(self.on_sphere(cheap[order], rad), rad)
        if found is not None:
            return found, warm
        errs = self.gradient_stage(rad, warm, u_inst, dirs, per_win)
        order = np.argsort(np.asarray(errs[1]))
        return self.settle(errs[0][order], rad), errs[0] @ self.Pn

    def gradient_stage(self, rad, warm, u_inst, dirs, per_win):
        """Stage 3, gradient refinement from the best samples of every window, the instantaneous
        minimisers (on the first interval) and the previous attempt's iterates (on the whole
        horizon); a fixed number of starts (one compiled program): slots without a warm start get
        samples. ``(final initial errors, their distances)``."""
        n_w, dt = self.n_windows, self.dt
        n_slots = self.n_starts // 4
        n_warm = 0 if warm is None else min(len(warm), n_slots)
        n_samp = gradient_starts(self.n_starts, n_w) - len(u_inst) - n_warm
        ranked = np.argsort(per_win, axis=0)
        wins = np.arange(n_samp) % n_w
        starts = [dirs[ranked[i // n_w, w]] for i, w in enumerate(wins)] + list(u_inst)
        edges = np.linspace(0.0, dt * self.n_steps, n_w + 1)
        windows = [(edges[w] - 0.5 * dt, edges[w + 1] + 0.5 * dt) for w in wins] + [(-0.5 * dt, 0.5 * dt)] * len(u_inst)
        if n_warm:
            starts += list(warm[:n_warm])
            windows += [(-0.5 * dt, dt * self.n_steps + 0.5 * dt)] * n_warm
        f = falsify(
            self.ctrl,
            self.params,
            t_final=self.t_final,
            radius=rad,
            starts=np.stack(starts),
            dt=dt,
            basis=self.basis,
            steps=self.steps,
            learning_rate=self.learning_rate,
            windows=np.asarray(windows),
        )
        self.counts["gradient"] += len(starts) * (self.steps + 1)
        return np.asarray(f.initial_errors), np.asarray(f.distance)


def gradient_starts(n_starts: int, n_windows: int) -> int:
    """Starts of a gradient stage (one compiled program): the best samples of every window (at
    least one each), the instantaneous minimisers and a quarter ``n_starts`` of warm slots."""
    n_slots = n_starts // 4
    return max(n_starts - N_INSTANT_STARTS - n_slots, n_windows) + n_slots + N_INSTANT_STARTS


def compile_search(
    ctrl: DynamicLinearization,
    params: DynamicParams,
    *,
    t_final: float,
    dt: float,
    n_starts: int = 16,
    steps: int = 30,
    learning_rate: float = 0.1,
    n_windows: int = SEARCH_WINDOWS,
) -> None:
    """Compile the two programs of :func:`falsified_radius` (same arguments) that its first
    stages do not: the gradient stage's and the fine confirmations' (blocks of
    :data:`CONFIRM_BLOCK` at ``CONFIRM_DT_FACTOR * dt``), without running them; the search then
    finds them compiled. :func:`wmrjax.certify.analyse` calls it on a thread of its own while
    the certificates compute."""
    check_dynamic(ctrl, params)
    n_steps = n_steps_for(t_final, dt)
    for name, v in (("n_starts", n_starts), ("steps", steps), ("n_windows", n_windows)):
        check_int(name, v, 1)
    check_positive("learning_rate", learning_rate)
    fine = CONFIRM_DT_FACTOR * dt
    compile_window_distances(
        ctrl, params, dt=fine, n_steps=n_steps_for(t_final, fine), block=CONFIRM_BLOCK, shared=False
    )
    Q = square_basis(slice_basis(ctrl, Slice.FULL))
    S = gradient_starts(n_starts, n_windows)
    args = _search_args(ctrl, params, 1.0, jnp.ones((S, Q.shape[1])), jnp.zeros((S, 2)), Q)
    _falsify.lower(*args, dt, n_steps, steps, learning_rate).compile()


def _pad(u, Q):
    """(S, k) slice directions padded with zeros to (S, n) (they stay zero: Q's extra columns are)."""
    return jnp.concatenate([u, jnp.zeros((u.shape[0], Q.shape[1] - u.shape[1]), u.dtype)], axis=1)


@functools.partial(jax.jit, static_argnums=(0, 5, 6))
def _instantaneous(ctrl, params, radius, P, us, steps, learning_rate):
    """Adam on the sphere for the distance of zeta_ref(0) + radius P u/|u| to the singular set (no rollout)."""
    r = ctrl.relative_degree
    jet0 = ctrl.reference_jet(jnp.zeros((), us.dtype), params)[:r]

    def objective(u):
        e0 = radius * (P @ (u / jnp.linalg.norm(u)))
        # the whole distance, not one capped at 1: beyond a cap the objective is flat, and the
        # starts that began farther than it from the singular set never moved (on section 6.1's
        # full ball at twice the Lemma 2 radius, 63 or 64 of the 64 starts for each of five seeds)
        return ctrl.singular_distance(jet0 + e0.reshape(jet0.shape), params)

    opt = optax.adam(optax.exponential_decay(learning_rate, steps, 0.01))
    vg = jax.vmap(jax.value_and_grad(objective))

    def step(c, _):
        us, state = c
        _, g = vg(us)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        with jax.numpy_dtype_promotion("standard"):
            upd, state = opt.update(g, state, us)
        us = optax.apply_updates(us, upd)
        return (us / jnp.linalg.norm(us, axis=1, keepdims=True), state), None

    us = us / jnp.linalg.norm(us, axis=1, keepdims=True)
    (us, _), _ = jax.lax.scan(step, (us, opt.init(us)), None, length=steps)
    return us, jax.vmap(objective)(us)
