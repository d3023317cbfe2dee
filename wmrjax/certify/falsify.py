r"""Falsification: gradient search through the simulated closed loop for initial errors that
come within eps of the singular set; an upper bound on every certified radius."""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax._validate import check_int, check_positive
from wmrjax.certify.empirical import check_vectors, distance_along, min_distance, n_steps_for, run_from_error
from wmrjax.certify.exact_map import slice_basis
from wmrjax.certify.lemma2 import check_dynamic, check_lemma2_args
from wmrjax.controllers.dynamic import DynamicLinearization, DynamicParams



class Falsification(NamedTuple):
    """Result of :func:`falsify` at one radius."""

    initial_errors: jnp.ndarray   # (S, r m) final iterate of every start
    distance: jnp.ndarray         # (S,) min_t dist(zeta(t), S) (margin for (1,2)) of each
    best: jnp.ndarray             # index of the worst case found


def falsify(ctrl: DynamicLinearization, params: DynamicParams, *, t_final: float, radius, starts, dt: float,
            basis="full", steps: int = 60, learning_rate: float = 0.1, n_windows: int = 8) -> Falsification:
    r"""Gradient search for the worst initial error on the sphere :math:`\|\tilde\zeta_0\| = \rho`.

    Minimises :math:`\min_t \mathrm{dist}(\zeta(t), S)` over the simulated closed loop (reverse-mode
    through the RK4 scan) with optax Adam on an unconstrained :math:`u`, mapped to the sphere by
    :math:`\tilde\zeta_0 = \rho P u / \|u\|` (projection), from every start at once (vmapped).
    Random sampling misses thin unsafe cones; following the gradient does not need to hit them.

    A single objective :math:`\min_{t\in[0,T]}` has one dominant basin (the time at which most
    directions come closest), and thin cones at other times are missed. So start i minimises
    the distance over its own window of the horizon, window ``i % n_windows`` of
    ``n_windows`` equal ones: every part of the horizon is searched. Adam's step decays
    100-fold over the run, so iterates settle inside eps-thin sets.

    Args:
      t_final: horizon [s]; dt: RK4 step of the search [s].
      radius: sphere radius rho.
      starts: (S, k) initial directions in slice coordinates (need not be normalised).
      basis: slice, see :func:`slice_basis`.
      steps, learning_rate: Adam iterations and initial step size (on the unit sphere).
      n_windows: number of time windows the starts are spread over.
    """
    check_dynamic(ctrl, params)
    n_steps = n_steps_for(t_final, dt)
    P = slice_basis(ctrl, basis)
    check_positive("radius", radius)
    check_vectors("starts", starts, P.shape[1], "initial directions in slice coordinates", nonzero=True)
    steps = check_int("steps", steps, 1)
    n_windows = check_int("n_windows", n_windows, 1)
    check_positive("learning_rate", learning_rate)
    branch = jnp.asarray(float(ctrl.reference_branch(params)))
    u0 = jnp.asarray(starts)
    edges = jnp.linspace(0.0, dt * n_steps, n_windows + 1)
    win = jnp.arange(u0.shape[0]) % n_windows
    windows = jnp.stack([edges[win] - 0.5 * dt, edges[win + 1] + 0.5 * dt], axis=1)
    us, vals = _falsify(ctrl, params, jnp.asarray(radius, dtype=u0.dtype), u0 / jnp.linalg.norm(u0, axis=1, keepdims=True),
                        windows, P, branch, dt, n_steps, steps, learning_rate)
    errs = radius * (us / jnp.linalg.norm(us, axis=1, keepdims=True)) @ P.T
    return Falsification(errs, vals, jnp.argmin(vals))


@functools.partial(jax.jit, static_argnums=(0, 7, 8, 9, 10))
def _falsify(ctrl, params, radius, us, windows, P, branch, dt, n_steps, steps, learning_rate):
    import optax

    opt = optax.adam(optax.exponential_decay(learning_rate, steps, 0.01))

    def objective(u, window):
        e0 = radius * (P @ (u / jnp.linalg.norm(u)))
        tr, _ = run_from_error(ctrl, params, e0, branch, dt, n_steps, 1)
        inside = (tr.t[1:] >= window[0]) & (tr.t[:-1] <= window[1])
        dist, valid = distance_along(ctrl, params, tr, chord=True)
        d = jnp.min(jnp.where(valid & inside, dist, jnp.inf))
        return jnp.where(tr.diagnostics.failed, 0.0, d)

    vg = jax.vmap(jax.value_and_grad(objective))

    def step(c, _):
        us, state, best_u, best_v = c
        v, g = vg(us, windows)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        better = v < best_v
        best_u = jnp.where(better[:, None], us, best_u)
        best_v = jnp.where(better, v, best_v)
        with jax.numpy_dtype_promotion("standard"):   # optax mixes its int32 step count with floats
            upd, state = opt.update(g, state, us)
        us = optax.apply_updates(us, upd)
        us = us / jnp.linalg.norm(us, axis=1, keepdims=True)
        return (us, state, best_u, best_v), None

    init = (us, opt.init(us), us, jnp.full(us.shape[0], jnp.inf))
    (us, _, best_u, best_v), _ = jax.lax.scan(step, init, None, length=steps)
    v_last = jax.vmap(objective)(us, windows)
    better = v_last < best_v
    return jnp.where(better[:, None], us, best_u), jnp.where(better, v_last, best_v)


class FalsifiedRadius(NamedTuple):
    """Result of :func:`falsified_radius` (fixed fields; None where nothing failed).

    Attributes:
      radius: smallest radius at which a confirmed failure was found (None: none).
      initial_error: (r m,) that failure's initial error (None: none).
      distance: its confirmed min_t distance to the singular set (None: none).
      rollouts: simulations used (a gradient evaluation counts one).
      bracket: (lo, hi): the last bisection bracket (None: nothing failed).
      searched_up_to: the largest radius searched.
    """

    radius: float | None
    initial_error: np.ndarray | None
    distance: float | None
    rollouts: int
    bracket: tuple | None
    searched_up_to: float


def falsified_radius(ctrl: DynamicLinearization, params: DynamicParams, *, t_final: float, eps: float, r_hi: float,
                     key, dt: float, basis="full", n_starts: int = 16, steps: int = 60, n_bisect: int = 8,
                     learning_rate: float = 0.1, r_lo: float = 0.0, n_windows: int = 4) -> FalsifiedRadius:
    """The smallest radius at which the falsifier finds a failure (dist < eps or singular), by bisection.

    Starts at ``r_hi`` (doubled up to 4 times until a failure is found), then bisects between
    ``r_lo`` (typically a certified radius) and the failing radius, warm-starting the directions.
    Any failure found is confirmed by a fresh simulation. An upper bound on the true safe radius:
    every certified radius must be below it.

    Args:
      t_final: horizon [s]; eps: the margin; r_hi: first radius tried; key: PRNG key of the starts;
      dt: RK4 step of the search [s] (failures are confirmed at dt / 10).

    Returns:
      :class:`FalsifiedRadius` (radius None if nothing failed up to 16 r_hi).
    """
    check_dynamic(ctrl, params)
    check_lemma2_args(t_final=t_final, eps=eps)
    n_steps_for(t_final, dt)
    check_positive("r_hi", r_hi)
    if not (np.isfinite(r_lo) and 0 <= r_lo < r_hi):
        raise ValueError(f"r_lo must satisfy 0 <= r_lo < r_hi = {r_hi}, got {r_lo!r}")
    n_starts = check_int("n_starts", n_starts, 1)
    check_int("steps", steps, 1)
    check_int("n_bisect", n_bisect, 0)
    check_int("n_windows", n_windows, 1)
    check_positive("learning_rate", learning_rate)
    P = slice_basis(ctrl, basis)
    if P.shape[1] == 2:     # a plane: evenly spaced angles, randomly rotated
        ang = jnp.linspace(0.0, 2.0 * math.pi, n_starts, endpoint=False) + jax.random.uniform(key, (), maxval=math.pi)
        starts = jnp.stack([jnp.cos(ang), jnp.sin(ang)], axis=1)
    else:
        starts = jax.random.normal(key, (n_starts, P.shape[1]))
    rollouts = 0

    def attempt(rad, st):
        nonlocal rollouts
        f = falsify(ctrl, params, t_final=t_final, radius=rad, starts=st, dt=dt, basis=basis, steps=steps,
                    learning_rate=learning_rate, n_windows=n_windows)
        rollouts += n_starts * (steps + 1)
        e = f.initial_errors[int(f.best)]
        # confirm on samples (which over-estimate the distance) of a ten times finer run: the
        # velocity can sweep past zero within one coarse step
        d, s = min_distance(ctrl, params, t_final=t_final, initial_errors=e[None], dt=0.1 * dt)
        ok = bool(d[0] < eps) or bool(s[0])
        dirs = jnp.einsum("nk,sn->sk", P, f.initial_errors)
        return ok, e, float(d[0]), dirs

    hi, found = float(r_hi), None
    for _ in range(5):
        ok, e, d, dirs = attempt(hi, starts)
        starts = dirs
        if ok:
            found = (hi, e, d)
            searched = hi
            break
        r_lo, hi = hi, 2.0 * hi
    if found is None:
        return FalsifiedRadius(None, None, None, rollouts, None, hi / 2.0)
    lo = r_lo
    for _ in range(n_bisect):
        mid = 0.5 * (lo + found[0])
        ok, e, d, dirs = attempt(mid, starts)
        if ok:
            found, starts = (mid, e, d), dirs
        else:
            lo = mid
    return FalsifiedRadius(found[0], np.asarray(found[1]), found[2], rollouts, (lo, found[0]), searched)
