r"""The loop the user has: what each certificate covers, and the falsifier on the problem's plant.

A certificate of :mod:`wmrjax.certify` is a claim about one closed loop. The exact map and
Lemma 2 are about the *nominal continuous* loop: the law's own model, exact actuators,
continuous feedback. A problem's ``[plant]`` describes another loop: saturating actuators
(``input_limit``), a digital controller with a zero-order hold (``control_period``),
actuators and geometry that differ from the law's (``input_scale``, ``geometry_scale``) and
measurement noise (``noise_std``). A run of that loop from inside the nominal certificate
can fail (issue 54: a 20 Hz hold on the S-path fails at 0.98 of the nominal radius).

* :class:`Feature` names what a loop has beyond the nominal one, :func:`plant_features` lists a
  problem's, and :class:`Kind` says how a radius is known (proved for every initial error of
  the ball, proved at a grid's times only, attained by an initial error that fails, or estimated
  from simulations);
* :func:`real_loop_falsified_radius` searches the problem's own loop (every listed plant value,
  with its period, noise realisations and a worst case of the noise within its bound,
  :func:`wmrjax.certify.worst_noise`) for initial errors that come within eps of the singular
  set: an upper bound on the radius any certificate of that loop can have;
* :func:`problem_certificate` is the problem's certificate per slice: a radius only where a
  proof covers every feature of its plant, labelled with what it covers, beside the real
  loop's falsified radius.

Proofs cover input limits (:func:`wmrjax.certify.saturation_free_radius`), geometry ranges on
robots whose kinematics do not depend on the geometry (:func:`inert_features`: the loop is the
nominal one) and, for a continuous controller at velocity level, input-scale and geometry
ranges with limits (:func:`wmrjax.certify.mismatch_radius`). A loop with a feature no proof covers (a digital
controller, noise, mismatch at torque level) gets no proved radius (``radius`` None, the
features listed as not covered) and the real loop's falsified radius, so that the nominal
radius is never printed as the answer for a loop it does not describe.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import robots
from wmrjax._validate import check_int, check_positive
from wmrjax.certify.deviation import Mismatch, mismatch_radius
from wmrjax.certify.empirical import sample_sphere
from wmrjax.certify.exact_map import Slice, singular_rows, slice_basis
from wmrjax.certify.lemma2 import check_dynamic
from wmrjax.certify.reach import NOISE_BOUND, SingularDistance, held_reach_radius
from wmrjax.certify.saturation import saturation_free_radius
from wmrjax.certify.worst_noise import NOISE_STEPS, noise_runs, worst_noise
from wmrjax.controllers import Space, Task, place
from wmrjax.controllers.law import Level
from wmrjax.simulate import fixed_blocks


class Feature(enum.StrEnum):
    """What a closed loop has; a certificate ``covers`` a list of them."""

    NOMINAL = "nominal"  # the law's own model, exact actuators, continuous feedback
    INPUT_LIMIT = "input_limit"  # saturating actuators
    CONTROL_PERIOD = "control_period"  # a digital controller: sampled, zero-order hold
    INPUT_SCALE = "input_scale"  # actuators that scale the command
    GEOMETRY_SCALE = "geometry_scale"  # a plant geometry other than the law's
    NOISE = "noise"  # measurement noise


class Kind(enum.StrEnum):
    """How a radius is known."""

    PROVED = "proved"  # every initial error of the ball keeps eps away at every t of [0, T]
    PROVED_ON_TIME_GRID = "proved_on_time_grid"  # as PROVED, at the times of a grid only
    ATTAINED = "attained"  # an initial error at this radius comes within eps: an upper bound
    ESTIMATED = "estimated"  # from simulations: an upper bound (falsified) or a sampled radius


def plant_features(setting) -> tuple:
    """The :class:`Feature` s of a problem's ``[plant]`` beyond the nominal loop (empty: none).

    Args:
      setting: a :class:`wmrjax.problem.Setting`.
    """
    if not setting.plant:
        return ()
    pv = setting.axis("plant").payload
    out = []
    if np.isfinite(np.asarray(pv["limit"])).any():
        out.append(Feature.INPUT_LIMIT)
    if setting.control_period is not None:
        out.append(Feature.CONTROL_PERIOD)
    if np.any(np.asarray(pv["input_scale"]) != 1.0):
        out.append(Feature.INPUT_SCALE)
    if np.any(np.asarray(pv["geometry_scale"]) != 1.0):
        out.append(Feature.GEOMETRY_SCALE)
    if any(setting.noise_std):
        out.append(Feature.NOISE)
    return tuple(out)


def inert_features(setting) -> dict:
    """The plant features of a problem that cannot change its loop, each with the reason: a
    ``geometry_scale`` range on a robot whose kinematics do not depend on L and e
    (:func:`wmrjax.robots.kinematics_use_geometry`, read from the model's program: types (3,0),
    (2,0), (2,1)). The law computes with its own geometry whatever the plant's, so every plant
    of such a range runs the loop of the nominal geometry exactly, and a proof of that loop
    covers the range.

    Args:
      setting: a :class:`wmrjax.problem.Setting`.

    Returns:
      ``{Feature: reason}`` (empty: every feature of the plant acts on its loop).
    """
    robot = setting.ctrl.robot
    if Feature.GEOMETRY_SCALE in plant_features(setting) and not robots.kinematics_use_geometry(robot):
        return {
            Feature.GEOMETRY_SCALE: (
                f"the {robot.name} kinematics do not depend on L and e (wmrjax.robots.kinematics_use_geometry): "
                "every plant geometry of the range moves as the law's model"
            )
        }
    return {}


class RealLoopFalsified(NamedTuple):
    """Result of :func:`real_loop_falsified_radius` (None where nothing failed).

    Attributes:
      radius: the smallest radius at which a run of the problem's loop came within eps of the
        singular set (or failed), confirmed at a quarter of the step: an upper bound of any
        certificate of that loop (estimated: the search may miss smaller failures).
      initial_error: (r m,) that run's initial error (full output-error coordinates).
      plant: that run's plant (input limit, input scale, geometry scale, noise realisation).
      distance: its confirmed min_t distance to the singular set (0: the run failed).
      searched_up_to: the largest radius simulated.
      rollouts: runs simulated (confirmations included).
      variants: plant values times noise realisations searched (the loops that differ:
        :func:`distinct_loops`).
      noise: how the noise was searched (a sentence), or None without noise.
      worst_noise: the worst-case noise stage (:func:`wmrjax.certify.worst_noise`): its bound, radii and
        distances, and the radius it confirmed (None: without noise, or not run).
    """

    radius: float | None
    initial_error: np.ndarray | None
    plant: dict | None
    distance: float | None
    searched_up_to: float
    rollouts: int
    variants: int
    noise: str | None
    worst_noise: dict | None = None

    def summary(self) -> dict:
        """Plain JSON."""
        return {
            "radius": self.radius,
            "initial_error": None if self.initial_error is None else [float(v) for v in self.initial_error],
            "plant": self.plant,
            "distance": self.distance,
            "searched_up_to": self.searched_up_to,
            "rollouts": self.rollouts,
            "variants": self.variants,
            "noise": self.noise,
            "worst_noise": self.worst_noise,
            "kind": str(Kind.ESTIMATED),
        }


N_DIRECTIONS = 24
"""The real loop's falsifier's random directions per slice, by default."""


def real_loop_falsified_radius(
    setting,
    params,
    *,
    eps: float,
    r_max: float,
    basis=Slice.FULL,
    directions=(),
    n_directions: int = N_DIRECTIONS,
    n_grid: int = 8,
    n_noise: int = 2,
    n_bisect: int = 8,
    n_refine: int = 4,
    seed: int = 0,
    noise_bound: float = NOISE_BOUND,
    noise_steps: int = NOISE_STEPS,
) -> RealLoopFalsified:
    r"""Search the problem's own closed loop for initial errors that come within eps of the
    singular set: the real loop's falsified radius (an upper bound, estimated).

    The loop is :meth:`wmrjax.problem.Setting.run`'s: the law with the problem's gains, closed
    around its plant (limits, input and geometry scales, a zero-order hold at its period,
    measurement noise). Every listed plant value is searched (a list of scales: every value,
    its range's ends included; values that cannot change the loop, a geometry the kinematics
    ignore, once: :func:`distinct_loops`), each with ``n_noise`` Gaussian noise realisations
    (seeds from ``[plant] noise_seed``) when the plant has noise, then the worst case within
    ``noise_bound`` noise_std (the held reach's bound) on the smallest failure's ray
    (:func:`worst_noise`). Initial errors are ``rho P d`` for unit directions d of the slice
    (``directions`` first, e.g. the nominal exact map's worst error, then ``n_directions``
    random ones); the distance to the singular set is measured at every RK4 step (at every
    sample of a digital controller: what it sees).

    Stages: every direction and plant variant on a grid of ``n_grid`` radii up to ``r_max`` (a
    given error's ray also at :data:`FINE_AROUND` times its norm); the ``n_refine`` (direction,
    variant) pairs failing at the smallest radius are bisected ``n_bisect`` times between their
    last safe and first failing radius; the smallest failure is confirmed at a quarter of the step.

    Args:
      setting: the problem's :class:`wmrjax.problem.Setting` (one value per axis but the plant's).
      params: the law's parameters (``setting.params(gains=...)``).
      eps: the margin [zeta units].
      r_max: the largest radius searched.
      basis: the slice (:func:`wmrjax.certify.slice_basis`).
      directions: (n, r m) initial errors whose directions are searched first (projected on the slice).
      n_directions: random directions of the slice searched after ``directions``.
      n_grid: radii of the first grid, up to ``r_max``.
      n_noise: Gaussian noise realisations per plant value (with noise).
      n_bisect: bisection steps of each refined pair.
      n_refine: (direction, variant) pairs failing at the smallest radius that are bisected.
      seed: the search's PRNG seed.
      noise_bound: the worst-case noise stage's bound, in multiples of ``noise_std``.
      noise_steps: its gradient steps (0: the stage is not run).

    Returns:
      :class:`RealLoopFalsified`.
    """
    ctrl = setting.ctrl
    check_dynamic(ctrl, params)
    check_positive("eps", eps)
    check_positive("r_max", r_max)
    sizes = dict(n_directions=n_directions, n_grid=n_grid, n_noise=n_noise, n_bisect=n_bisect, n_refine=n_refine)
    _check_sizes(**sizes, noise_steps=noise_steps)
    check_positive("noise_bound", noise_bound)
    P = np.asarray(slice_basis(ctrl, basis))
    dirs, own = _directions(P, directions, n_directions, seed)
    variants, noise = _variants(setting, n_noise, distinct=True)
    search = _Search(setting, params, P, eps)
    cands = _grid_failures(search, dirs, own, variants, r_max, n_grid)
    worst = functools.partial(_worst_case, search, dirs, variants, noise_bound, noise_steps)
    if not cands:
        none = RealLoopFalsified(None, None, None, None, float(r_max), search.rollouts, len(variants), noise)
        return worst(none, 0, 0)
    cands = sorted(cands)[:n_refine]
    hi, lo = np.array([c[0] for c in cands]), np.array([c[1] for c in cands])
    which_d, which_v = [c[2] for c in cands], [variants[c[3]] for c in cands]
    for _ in range(n_bisect):
        mid = 0.5 * (lo + hi)
        fail = search.distances(dirs[which_d], mid, which_v) < eps
        lo, hi = np.where(fail, lo, mid), np.where(fail, mid, hi)
    return worst(*_confirmed(search, dirs, cands, hi, variants, r_max, noise))


def planned_runs(
    setting,
    *,
    n_known: int = 2,
    n_directions: int = N_DIRECTIONS,
    n_grid: int = 8,
    n_noise: int = 2,
    n_bisect: int = 8,
    n_refine: int = 4,
    noise_steps: int = NOISE_STEPS,
) -> int:
    """The runs :func:`real_loop_falsified_radius` makes on one slice with these sizes (the
    confirmation taken as one run, a gradient step of the worst-case noise stage as one run per
    radius; :func:`problem_certificate` searches two slices), from ``n_known`` given failures'
    rays and the setting's plant variants: for a size estimate."""
    variants = _variants(setting, n_noise, distinct=True)[0]
    worst = len(WORST_FRACTIONS) * (noise_steps + 2) if noise_steps and variants[0].noise is not None else 0
    grid = (n_known + n_directions) * len(variants) * n_grid + n_known * len(variants) * len(FINE_AROUND)
    return grid + n_refine * n_bisect + 1 + worst


# the search's sizes and their least values (n_refine: the failures refined, at least the first)
SIZE_FLOORS = {"n_directions": 0, "n_grid": 1, "n_noise": 1, "n_bisect": 0, "n_refine": 1, "noise_steps": 0}


def _grid_failures(search, dirs, own, variants, r_max: float, n_grid: int) -> list:
    """:func:`_first_failures` of every direction and variant on the grid of ``n_grid`` radii up to
    ``r_max`` (a given error's ray, of norm ``own`` > 0, also at :data:`FINE_AROUND` times it)."""
    grid = r_max * np.arange(1, n_grid + 1) / n_grid
    # the exact map's worst error fails only within a few per mille beyond its norm: the ray
    # grazes the eps-ball of the singular set there
    rays = [np.unique(np.concatenate([grid, n * FINE_AROUND])) if n > 0 else grid for n in own]
    pairs = [(d, v, r) for d in range(len(dirs)) for v in range(len(variants)) for r in rays[d]]
    d_i, v_i, r_i = (np.array(x) for x in zip(*pairs))
    bad = search.distances(dirs[d_i], r_i, [variants[k] for k in v_i]) < search.eps
    return _first_failures(bad, d_i, v_i, r_i)


def _check_sizes(**sizes) -> None:
    """ValueError naming the first of the search's sizes that is not an integer >= its floor."""
    for name, v in sizes.items():
        check_int(name, v, SIZE_FLOORS[name])


def _first_failures(bad, d_i, v_i, r_i) -> list:
    """Per (direction, variant) pair with a failing run: ``(first failing radius, the last safe
    radius below it (0: none), direction, variant)``, from the runs' flags ``bad`` at the pairs'
    indices ``d_i``, ``v_i`` and increasing radii ``r_i``."""
    out = []
    for d, v in sorted(set(zip(d_i.tolist(), v_i.tolist()))):
        on = (d_i == d) & (v_i == v)
        if bad[on].any():
            k = int(np.argmax(bad[on]))
            out.append((r_i[on][k], r_i[on][k - 1] if k else 0.0, d, v))
    return out


# radii around a given initial error's norm searched on its ray (besides the common grid)
FINE_AROUND = np.array([0.999, 1.0005, 1.001, 1.002, 1.005, 1.01, 1.02, 1.05])


def _confirmed(search, dirs, cands, hi, variants, r_max, noise) -> tuple[RealLoopFalsified, int, int]:
    """The smallest failure of the bisected candidates ``cands`` (at radii ``hi``) confirmed at a
    quarter of the step; one that does not confirm falls back to its failing grid radius, confirmed.
    With its direction's and variant's indices (the first candidate's where none confirms)."""
    for k in np.argsort(hi):
        first, _, d, v = cands[k]
        for rad in (hi[k], first):
            (dist,) = search.distances(dirs[[d]], np.array([rad]), [variants[v]], fine=True)
            if dist < search.eps:
                found = RealLoopFalsified(
                    float(rad),
                    np.asarray(search.P @ (rad * dirs[d])),
                    variants[v].summary(),
                    float(dist),
                    float(r_max),
                    search.rollouts,
                    len(variants),
                    noise,
                )
                return found, d, v
    none = RealLoopFalsified(None, None, None, None, float(r_max), search.rollouts, len(variants), noise)
    return none, cands[0][2], cands[0][3]


WORST_FRACTIONS = np.array([0.8, 0.9, 0.95, 0.97, 0.98, 0.99, 0.995, 1.0])
"""The radii of the worst-case noise stage, as fractions of the smallest failure's (one batch)."""


def _worst_case(search, dirs, variants, noise_bound: float, steps: int, found, d: int, v: int) -> RealLoopFalsified:
    """``found`` with the worst-case noise stage (a noisy digital controller only): on direction
    ``d`` and variant ``v``'s plant, at :data:`WORST_FRACTIONS` of the found radius (of the
    searched range where none failed), the noise within ``noise_bound`` noise_std that brings
    each run closest to the singular set (:func:`wmrjax.certify.worst_noise`); the smallest
    radius it fails at, confirmed with the same noise at a quarter of the step, replaces a larger
    found one."""
    s = search.setting
    if steps == 0 or variants[v].noise is None:
        return found
    top = found.searched_up_to if found.radius is None else found.radius
    radii = top * WORST_FRACTIONS
    errs = radii[:, None] * (dirs[d] @ search.P.T)
    plant = tuple(np.stack([x] * len(radii)) for x in (variants[v].limit, variants[v].input_scale))
    plant = (*plant, np.full(len(radii), float(variants[v].geometry_scale)))
    w = worst_noise(s, search.params, errs, eps=search.eps, plant=plant, noise_multiple=noise_bound, steps=steps)
    search.rollouts += len(radii) * (steps + 2)
    stage = {
        "noise_multiple": float(noise_bound),
        "steps": int(steps),
        "radii": [float(r) for r in radii],
        "distance": [float(x) for x in w.distance],
        "zero_noise": [float(x) for x in w.zero_noise],
        "radius": None,
    }
    words = f"; then the worst case within {noise_bound:g} noise_std on the smallest failure's ray ({steps} projected gradient steps)"
    out = found._replace(noise=found.noise + words, rollouts=search.rollouts, worst_noise=stage)
    for k in np.flatnonzero(w.distance < search.eps):
        dist = float(search.noise_distances(errs[[k]], tuple(x[[k]] for x in plant), w.noise[[k]])[0])
        search.rollouts += 1
        if dist < search.eps:
            stage["radius"] = float(radii[k])
            if found.radius is None or radii[k] < found.radius:
                worst = dict(variants[v].summary(), noise_realisation=f"worst within {noise_bound:g} noise_std")
                return out._replace(
                    radius=float(radii[k]), initial_error=errs[k], plant=worst, distance=dist, rollouts=search.rollouts
                )
            break
    return out._replace(rollouts=search.rollouts)


def _directions(P, directions, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(dirs, norms)``: (D, k) unit directions of the slice, the given initial errors projected on
    it, then ``n`` random ones; and (D,) the given errors' norms in the slice (0 for the random)."""
    given = np.asarray(directions, float).reshape(-1, P.shape[0]) @ P if len(directions) else np.zeros((0, P.shape[1]))
    norms = np.linalg.norm(given, axis=1)
    keep = np.isfinite(norms) & (norms > 0)
    given, norms = given[keep] / norms[keep, None], norms[keep]
    rand = np.asarray(sample_sphere(jax.random.PRNGKey(seed), n, P.shape[1])) if n else np.zeros((0, P.shape[1]))
    return np.concatenate([given, rand]), np.concatenate([norms, np.zeros(len(rand))])


def real_loop_distances(setting, params, initial_errors, *, plant: int = 0, noise_realisation: int = 0) -> np.ndarray:
    """min_t distance to the singular set (0: the run failed) of runs of the problem's own loop.

    Args:
      setting: the problem's :class:`wmrjax.problem.Setting`.
      params: the law's parameters.
      initial_errors: (N, r m) output errors (full coordinates) at t = 0.
      plant: the row of the setting's plant axis (its listed values' product).
      noise_realisation: which Gaussian realisation of the noise (ignored without noise).

    Returns:
      (N,) distances, measured as in :func:`real_loop_falsified_radius`.
    """
    errs = np.asarray(initial_errors, float)
    n = setting.ctrl.relative_degree * setting.ctrl.m
    if errs.ndim != 2 or errs.shape[1] != n:
        raise ValueError(f"initial_errors must be (N, {n}) output errors (rows of derivative order), got {errs.shape}")
    variants, _ = _variants(setting, noise_realisation + 1)
    per_row = len(variants) // len(np.asarray(setting.axis("plant").payload["input_scale"]))
    check_int("plant", plant, 0)
    if plant * per_row >= len(variants):
        raise ValueError(f"plant must index the setting's {len(variants) // per_row} plant values, got {plant}")
    v = variants[plant * per_row + (noise_realisation if per_row > 1 else 0)]
    search = _Search(setting, params, np.eye(n), 0.0)
    norms = np.linalg.norm(errs, axis=1)
    dirs = errs / np.where(norms > 0, norms, 1.0)[:, None]
    return search.distances(dirs, norms, [v] * len(errs))


class _Variant(NamedTuple):
    """One plant value of the problem's axis, with one noise realisation."""

    index: int  # row of the plant axis
    limit: np.ndarray
    input_scale: np.ndarray  # (n_input,)
    geometry_scale: float
    noise: int | None  # realisation (None: no noise)

    def summary(self) -> dict:
        return {
            "input_limit": [float(v) if np.isfinite(v) else None for v in self.limit],
            "input_scale": [float(v) for v in np.asarray(self.input_scale)],
            "geometry_scale": float(self.geometry_scale),
            "noise_realisation": self.noise,
        }


def _variants(setting, n_noise: int, distinct: bool = False) -> tuple[list, str | None]:
    """Every plant value of the setting's axis times the noise realisations (with ``distinct``,
    those that run different loops: :func:`distinct_loops`), and how noise was searched."""
    pv = setting.axis("plant").payload
    noisy = bool(setting.plant and setting.control_period is not None and any(setting.noise_std))
    reals = list(range(n_noise)) if noisy else [None]
    rows = range(len(np.asarray(pv["input_scale"])))
    out = [
        _Variant(i, np.asarray(pv["limit"])[i], pv["input_scale"][i], pv["geometry_scale"][i], k)
        for i in rows
        for k in reals
    ]
    out = distinct_loops(setting, out) if distinct else out
    noise = (
        f"{n_noise} Gaussian realisations of std {list(setting.noise_std)} per plant value (not a worst case)"
        if noisy
        else None
    )
    return out, noise


def distinct_loops(setting, variants: list) -> list:
    """The plant variants that run different loops, in their order: where the plant's geometry
    cannot change the loop (:func:`inert_features`), plants that differ in their geometry scale
    alone run the same loop to the last bit, and the first of them is searched for all."""
    if Feature.GEOMETRY_SCALE not in inert_features(setting):
        return variants
    seen, out = set(), []
    for v in variants:
        key = (tuple(np.asarray(v.limit, float)), tuple(np.asarray(v.input_scale, float)), v.noise)
        if key not in seen:
            seen.add(key)
            out.append(v)
    return out


class _Search:
    """Batched runs of the problem's loop from initial errors ``rho P d``: their min distance."""

    BLOCK = 256  # runs per compiled call (the last block padded): one program whatever the count

    def __init__(self, setting, params, P, eps: float):
        self.setting, self.params, self.P, self.eps = setting, params, P, float(eps)
        self.fine = _finer(setting)
        self.rollouts = 0
        self.base = setting.run_inputs(0)
        self.branch = float(setting.ctrl.reference_branch(params))
        g = params.geometry
        self.geometry = type(g)(*(float(v) for v in g))
        self.key = jax.random.PRNGKey(setting.noise_seed)

    def distances(self, dirs, radii, variants, fine: bool = False) -> np.ndarray:
        """(N,) min_t distance (0: failed) of the runs from ``radii[i] * P @ dirs[i]`` on ``variants[i]``."""
        s = self.fine if fine else self.setting
        errs = np.asarray(radii, float)[:, None] * (np.asarray(dirs) @ self.P.T)
        lim = np.stack([v.limit for v in variants]).astype(float)
        sc = np.array([[*np.asarray(v.input_scale), v.geometry_scale] for v in variants], float)
        nk = np.array([0 if v.noise is None else v.noise for v in variants], np.int32)
        self.rollouts += len(errs)
        dist_fn = SingularDistance(s.system(), s.ctrl, self.geometry)
        program = lambda *b: (_runs(s, dist_fn, self.base, self.params, self.branch, self.key, *b),)
        block = min(self.BLOCK, len(errs))
        return fixed_blocks(program, (errs, lim, sc, nk), block)[0]

    def noise_distances(self, errs, plant, noise) -> np.ndarray:
        """(N,) min_t distance (0: failed) at a quarter of the step of the runs from the output errors
        ``errs`` on ``plant`` (limit, input scale, geometry scale rows) with the given noise."""
        s = self.fine
        dist_fn = SingularDistance(s.system(), s.ctrl, self.geometry)
        sc = np.concatenate([plant[1], plant[2][:, None]], axis=1)
        return np.asarray(noise_runs(s, dist_fn, s.run_inputs(0), self.params, self.branch, errs, plant[0], sc, noise))


@functools.lru_cache(maxsize=8)
def _finer(setting):
    """``setting`` at a quarter of its step (the same controller period), one object per setting:
    the confirmation's program is compiled once for both slices, not once per search."""
    return dataclasses.replace(setting, dt=setting.dt / 4, n_steps=setting.n_steps * 4)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _runs(setting, dist_fn, base, params, branch, key, errs, lim, sc, nk):
    """min_t distance to the singular set (0: failed) of the runs of ``setting``'s loop from the
    output errors ``errs`` with plant limits ``lim``, scales ``sc`` (input, geometry) and noise
    realisations ``nk`` (one compiled program per setting, step and block size); a row of ``sc``
    is the input scales (one per input) then the geometry scale."""
    ctrl = setting.ctrl

    def one(e0, limit, scales, k):
        z0 = place(ctrl, params, e0, Space.OUTPUT, Task.POSTURE, branch)
        p = base._replace(z0=z0, limit=limit, input_scale=scales[:-1], geometry_scale=scales[-1])
        tr, _ = setting.run(
            p,
            save_every=setting.steps_per_sample or 1,
            error_tol=math.inf,
            noise_key=jax.random.fold_in(key, k),
            save_fn=dist_fn,
        )
        d = jnp.min(jnp.where(tr.valid, tr.state, jnp.inf))
        return jnp.where(tr.diagnostics.failed, 0.0, d)

    return jax.vmap(one)(errs, lim, sc, nk)


# every radius of the certification's summary: what loop it covers and how it is known
RADIUS_LABELS = {
    "radius_paper": Kind.PROVED_ON_TIME_GRID,
    "radius_lyapunov": Kind.PROVED_ON_TIME_GRID,
    "radius_exact_norm": Kind.PROVED_ON_TIME_GRID,
    "radius_exact_map": Kind.ATTAINED,
    "radius_exact_map_lower_bound": Kind.PROVED,
    "radius_exact_map_position_slice": Kind.ATTAINED,
    "radius_exact_map_position_slice_lower_bound": Kind.PROVED,
    "empirical_radius_position_slice": Kind.ESTIMATED,
}


def radius_labels(block: dict) -> dict:
    """``{key: {"covers": ["nominal"], "kind": ...}}`` for every radius of a nominal
    certification's summary block (:meth:`wmrjax.certify.CertificationReport.summary`) present
    in it: Lemma 2 (min of F over a time grid), the exact map (attained, and its proved lower
    bound), the empirical radius and the falsified ones (estimated)."""
    out = {k: {"covers": [str(Feature.NOMINAL)], "kind": str(kind)} for k, kind in RADIUS_LABELS.items() if k in block}
    for k in ("falsified_full", "falsified_position_slice"):
        if k in block:
            out[k] = {"covers": [str(Feature.NOMINAL)], "kind": str(Kind.ESTIMATED)}
    return out


SLICES = {Slice.FULL: "radius_exact_map", Slice.POSITION: "radius_exact_map_position_slice"}


def problem_certificate(
    setting,
    params,
    exact: dict,
    *,
    eps: float,
    falsified: dict | None = None,
    seed: int = 0,
    log=None,
    falsify: bool = True,
    noise_bound: float = NOISE_BOUND,
    **search,
) -> dict:
    """The problem's certificate per slice (``full``, ``position``): the radius a proof gives for
    the loop the problem describes, what it covers, and the real loop's falsified radius.

    Without a ``[plant]`` the problem's loop is the nominal one: its radius is the exact map's
    proved lower bound (``covers`` ["nominal"], ``kind`` "proved"). With input limits the
    saturation-free radius (:func:`wmrjax.certify.saturation_free_radius`) is computed and
    reported (``saturation_free``) where limits are the plant's only feature, and the problem's
    radius is the smaller of it and the exact map's proved bound (``covers`` ["nominal",
    "input_limit"], ``kind`` "proved", ``bound_by`` which of the two). With input-scale or
    geometry ranges (and limits) on a continuous velocity-level loop, the radius is
    :func:`wmrjax.certify.mismatch_radius` over the plant's range (:func:`plant_range`;
    ``bound_by`` "mismatch_tube" or "mismatch_exact_map", a ``mismatch`` block with the
    deviation bound). A feature that cannot change the loop (:func:`inert_features`: a geometry
    range on a robot whose kinematics have no L and e) is covered by the proof of the loop
    without it: it is listed in ``covers`` and, with its reason, in ``inert``. For any other
    feature (a controller period, noise, mismatch at torque level) no proof in this package
    covers it yet: ``radius`` and ``kind`` are None,
    ``not_covered`` lists the features, and the nominal radius is reported beside it as the
    nominal loop's.

    Args:
      setting: the problem's :class:`wmrjax.problem.Setting`.
      params: the law's parameters.
      exact: slice -> :class:`wmrjax.certify.ExactMapRadius` of the nominal loop.
      eps: the margin.
      seed: the falsifier's seed.
      log: progress messages (or None).
      falsified: slice -> the nominal falsifier's :class:`wmrjax.certify.FalsifiedRadius` (or
        None): the problem loop's falsified radius where it is the nominal loop; with a plant,
        its failure's ray is searched first with the exact map's worst error's.
      falsify: run the real loop's falsifier (False: ``falsified_radius`` and ``falsified`` None).
      noise_bound: the measurement noise a digital controller's proof covers, in multiples of
        ``noise_std`` (:func:`wmrjax.certify.held_reach_radius`).
      search: :func:`real_loop_falsified_radius`'s sizes.

    Returns:
      Plain JSON: per slice ``radius``, ``worst_error``, ``covers``, ``not_covered``, ``kind``,
      ``falsified_radius`` and ``falsified`` (the real loop's search), ``nominal_radius``; and
      ``loop`` (the features of the problem's loop).
    """
    features, inert = plant_features(setting), inert_features(setting)
    out = {"loop": [str(f) for f in features] or [str(Feature.NOMINAL)]}
    for basis, em in exact.items():
        nominal = float(em.radius) if em.lower_bound is None else float(em.lower_bound)
        kind = Kind.ATTAINED if em.lower_bound is None else Kind.PROVED
        block = {"nominal_radius": nominal, "nominal_kind": str(kind)}
        if not features:
            block.update(
                radius=nominal,
                worst_error=[float(v) for v in np.asarray(em.worst_error)],
                covers=[str(Feature.NOMINAL)],
                not_covered=[],
                kind=str(kind),
                falsified_radius=None if (falsified or {}).get(basis) is None else falsified[basis].radius,
            )
            out[basis] = block
            continue
        block.update(_proved_block(setting, params, basis, em, eps, nominal, kind, features, inert, log, noise_bound))
        if not falsify or not np.isfinite(float(em.radius)):  # not asked, or no scale to search
            block.update(falsified_radius=None, falsified=None)
        else:
            known = (falsified or {}).get(basis)
            block.update(_falsified_block(setting, params, basis, em, eps, known, seed, log, noise_bound, search))
        out[basis] = block
    return out


def _proved_block(
    setting, params, basis: str, em, eps: float, nominal: float, kind, features, inert, log, noise_bound
) -> dict:
    """A slice's proved radius of a loop with a plant (its ``features``), from the proof that covers
    the features acting on it (the ``inert`` ones, :func:`inert_features`, are covered by the same proof)."""
    active = tuple(f for f in features if f not in inert)
    sat = _saturation_free(setting, params, basis, active, log)
    block = _plant_radius(em, nominal, kind, sat, features, active)
    if inert:
        block["inert"] = {str(f): why for f, why in inert.items()}
    if block["radius"] is None and kind == Kind.PROVED and _mismatch_covered(setting, params, active):
        block.update(_mismatch_block(setting, params, basis, features, em, eps, log))
    if block["radius"] is None and kind == Kind.PROVED and Feature.CONTROL_PERIOD in active:
        block.update(_held_block(setting, params, basis, features, active, nominal, eps, noise_bound, log))
    return block


def _held_block(setting, params, basis: str, features, active, nominal: float, eps: float, noise_bound, log) -> dict:
    """The problem certificate's fields from :func:`wmrjax.certify.held_reach_radius`: the digital
    controller's loop enclosed period by period, up to the nominal exact map's proved radius."""
    if log is not None:
        log(f"  held reach ({basis}): enclosing the sampled loop period by period (the first slice compiles)")
    hr = held_reach_radius(
        setting, params, slice_basis(setting.ctrl, basis), eps=eps, r_max=nominal, noise_multiple=noise_bound, log=log
    )
    proved = hr.radius > 0
    if log is not None:
        why = (
            ""
            if proved
            else f" (fails from the smallest radius tried, {hr.failed_radius:.3g}: {hr.reason} at t = {hr.failed_at:g} s)"
        )
        log(f"  held reach ({basis}): proved {hr.radius:.4g}{why}")
    summary = dict(hr.summary(), covers=[str(Feature.NOMINAL), *(str(f) for f in features)], kind=str(Kind.PROVED))
    return {
        "radius": hr.radius if proved else None,
        "worst_error": None,
        "covers": summary["covers"] if proved else [],
        "not_covered": [] if proved else [str(f) for f in active],
        "kind": str(Kind.PROVED) if proved else None,
        "bound_by": "held_reach",
        "held_reach": summary,
    }


def _falsified_block(
    setting, params, basis: str, em, eps: float, nominal_falsified, seed: int, log, noise_bound, search
) -> dict:
    """The problem loop's falsified radius of a slice, searched up to 1.1 times the nominal exact
    map's radius from the known failures' rays first."""
    f = real_loop_falsified_radius(
        setting,
        params,
        eps=eps,
        r_max=1.1 * max(float(em.radius), 1e-12),
        basis=basis,
        directions=_known_failures(em, nominal_falsified),
        seed=seed,
        noise_bound=noise_bound,
        **search,
    )
    if log is not None:
        log(f"  problem's loop ({basis}): falsified radius {f.radius} ({f.rollouts} runs, {f.variants} plant variants)")
    return {"falsified_radius": f.radius, "falsified": f.summary()}


def tightest_limits(setting) -> np.ndarray:
    """(n_input,) the smallest of the ``[plant]``'s listed ``input_limit`` values per input (inf:
    none): a loop within them is within every listed plant's."""
    n = setting.ctrl.robot.n_input
    return np.min(np.asarray(setting.axis("plant").payload["limit"], float).reshape(-1, n), axis=0)


def _saturation_free(setting, params, basis: str, features, log):
    """The saturation-free radius of a slice under the plant's tightest listed limits, where input
    limits are the only feature (of ``features``: those that act on the loop) (None otherwise:
    with a hold, mismatch or noise no proof uses it yet, and its programs take tens of seconds to
    compile)."""
    if tuple(features) != (Feature.INPUT_LIMIT,):
        return None
    limits = tightest_limits(setting)
    sat = saturation_free_radius(setting.ctrl, params, limits, t_final=setting.t_final, basis=basis)
    if log is not None:
        log(
            f"  saturation-free radius ({basis}): proved {sat.lower_bound:.4g}, attained {sat.upper_bound:.4g} "
            f"(limits {limits.tolist()}, {sat.boxes} time boxes)"
        )
    return sat


def _plant_radius(em, nominal: float, kind, sat, features, active) -> dict:
    """The problem certificate's fields for a loop with a plant: a proved radius where the only
    feature acting on the loop (``active``; the others are inert, :func:`inert_features`) is
    input limits (the smaller of the exact map's and the saturation-free radius: inside both, the
    saturated loop is the nominal one) or none (the exact map's radius, of its ``kind``, as for a
    problem without a plant), none otherwise. ``covers`` lists every feature of the plant
    (``features``), the inert ones included."""
    block = {"saturation_free": None if sat is None else _saturation_summary(sat)}
    limits_proved = tuple(active) == (Feature.INPUT_LIMIT,) and kind == Kind.PROVED
    if active and not limits_proved:
        block.update(radius=None, worst_error=None, covers=[], not_covered=[str(x) for x in active], kind=None)
        return block
    binding_sat = sat is not None and sat.lower_bound < nominal
    worst = sat.worst_error if binding_sat else np.asarray(em.worst_error)
    block.update(
        radius=nominal if sat is None else min(nominal, sat.lower_bound),
        worst_error=None if worst is None else [float(v) for v in np.asarray(worst)],
        covers=[str(Feature.NOMINAL), *(str(f) for f in features)],
        not_covered=[],
        kind=str(kind),
        bound_by="saturation_free" if binding_sat else "exact_map",
    )
    return block


# what the continuous loop's mismatch bound (wmrjax.certify.mismatch_radius) covers
MISMATCH_FEATURES = frozenset({Feature.INPUT_LIMIT, Feature.INPUT_SCALE, Feature.GEOMETRY_SCALE})


def _mismatch_covered(setting, params, features) -> bool:
    """Whether the mismatch bound covers the loop: a continuous controller at velocity level with
    a linear singular set and constant gains, whose plant features are limits and scales only."""
    return (
        set(features) <= MISMATCH_FEATURES
        and bool(set(features) - {Feature.INPUT_LIMIT})
        and setting.ctrl.level == Level.VELOCITY
        and singular_rows(setting.ctrl) is not None
        and not params.gains.time_varying
    )


def plant_range(setting) -> Mismatch:
    """The plant axis's values as one range: the tightest listed limits, and each scale between
    its listed values' smallest and largest (a proof over the range covers every listed plant)."""
    pv = setting.axis("plant").payload
    nu = setting.ctrl.robot.n_input
    limit = np.min(np.asarray(pv["limit"], float).reshape(-1, nu), axis=0)
    scale = np.asarray(pv["input_scale"], float).reshape(-1, nu)
    geo = np.asarray(pv["geometry_scale"], float).reshape(-1)
    return Mismatch(limit, (scale.min(axis=0), scale.max(axis=0)), (float(geo.min()), float(geo.max())))


def _mismatch_block(setting, params, basis: str, features, em, eps: float, log) -> dict:
    """The problem certificate's fields from :func:`wmrjax.certify.mismatch_radius` over the
    plant's range (:func:`plant_range`)."""
    rng = plant_range(setting)
    if log is not None:
        log(f"  mismatch radius ({basis}): enclosing the plant's deviation over its range (the first slice compiles)")
    mr = mismatch_radius(
        setting.ctrl, params, rng, t_final=setting.t_final, eps=eps, basis=basis, n_t=len(np.asarray(em.ts)), nominal=em
    )
    if log is not None:
        log(
            f"  mismatch radius ({basis}): proved {mr.lower_bound:.4g} (deviation <= {mr.deviation_bound:.3g}, "
            f"margin eps + {mr.singular_margin:.3g}, bound by {mr.bound_by})"
        )
    worst = mr.worst_error if mr.bound_by == "exact_map" else None
    return {
        "radius": mr.lower_bound,
        "worst_error": None if worst is None else [float(v) for v in np.asarray(worst)],
        "covers": [str(Feature.NOMINAL), *(str(f) for f in features)],
        "not_covered": [],
        "kind": str(Kind.PROVED),
        "bound_by": "mismatch_" + mr.bound_by,
        "mismatch": _mismatch_summary(mr, rng),
    }


def _finite(v):
    """A float, or None where it is not finite (plain JSON has no inf)."""
    return float(v) if np.isfinite(v) else None


def _mismatch_summary(mr, rng: Mismatch) -> dict:
    return {
        "lower_bound": mr.lower_bound,
        "rate_bound": _finite(mr.rate_bound),
        "deviation_bound": _finite(mr.deviation_bound),
        "singular_margin": _finite(mr.singular_margin),
        "tube": _finite(mr.tube),
        "gain_integrals": [float(v) for v in mr.gains],
        "tube_radius": mr.tube_radius,
        "exact_map_lower_bound_at_margin": mr.exact_lower_bound,
        "bound_by": mr.bound_by,
        "time_boxes": mr.boxes,
        "range": {
            "input_limit": [_finite(v) for v in rng.input_limit],
            "input_scale": [[float(v) for v in end] for end in rng.input_scale],
            "geometry_scale": [float(v) for v in rng.geometry_scale],
        },
        "kind": str(Kind.PROVED),
    }


def _saturation_summary(sat) -> dict:
    return {
        "lower_bound": sat.lower_bound,
        "upper_bound": None if not np.isfinite(sat.upper_bound) else sat.upper_bound,
        "worst_error": None if sat.worst_error is None else [float(v) for v in sat.worst_error],
        "worst_time": sat.worst_time,
        "time_boxes": sat.boxes,
        "covers": [str(Feature.NOMINAL), str(Feature.INPUT_LIMIT)],
        "kind": str(Kind.PROVED),
        "upper_bound_kind": str(Kind.ATTAINED),
    }


def _known_failures(em, nominal_falsified) -> list:
    """The nominal loop's known worst initial errors of a slice: the exact map's, and the nominal
    falsifier's failure where it found one (the real loop's search starts on their rays)."""
    out = [np.asarray(em.worst_error)]
    if nominal_falsified is not None and nominal_falsified.initial_error is not None:
        out.append(np.asarray(nominal_falsified.initial_error))
    return out


def problem_alarms(problem_block: dict) -> list:
    """A message per slice whose proved problem radius is above the problem loop's falsified
    radius: a proof contradicted by a run of the loop it covers (an alarm: exit status 1)."""
    msgs = []
    for basis in SLICES:
        b = problem_block.get(basis)
        if b is None or b.get("radius") is None or b.get("falsified_radius") is None:
            continue
        if b["radius"] > b["falsified_radius"]:
            msgs.append(
                f"PROBLEM CERTIFICATE CONTRADICTED ({basis}): proved radius {b['radius']:.6g} for "
                f"{', '.join(b['covers'])}, but a run of that loop from radius {b['falsified_radius']:.6g} "
                "comes within eps of the singular set"
            )
    return msgs


def plant_warnings(problem_block: dict) -> list:
    """A message per slice whose nominal radius is above the problem loop's falsified radius: the
    nominal certificate does not hold for the loop the problem describes (a warning, not an alarm:
    it is a certificate of another loop)."""
    msgs = []
    for basis in SLICES:
        b = problem_block.get(basis)
        if b is None or b.get("falsified_radius") is None:
            continue
        if b["nominal_radius"] > b["falsified_radius"]:
            p = b["falsified"]["plant"]
            msgs.append(
                f"the nominal {basis} radius {b['nominal_radius']:.4g} does not hold for this problem's loop "
                f"({', '.join(problem_block['loop'])}): a run of it from radius {b['falsified_radius']:.4g} comes within "
                f"eps of the singular set (plant {p})"
            )
    return msgs
