r"""The certified region while tuning (issue 32): a required exact-map radius kept throughout,
and every radius of the initial and the tuned gains, labelled.

The exact-map radius (:func:`wmrjax.certify.exact_map_radius`) is the largest ball of initial
output errors, in the full error space or the position slice, from which the linearized error
:math:`\tilde\zeta(t) = \Phi(t, 0)\tilde\zeta(0)` stays eps away from the singular set over the
horizon. It is a minimum over time of closed-form problems in :math:`\Phi(t, 0)` (no rollout),
so it is cheap and, for the linear singular sets of (2,0), (2,1) and (1,1), differentiable in
the gains (:func:`wmrjax.certify.differentiable_exact_map_radius`). The tuner

* starts from a point that meets the requirement (when the initial gains do not, it first climbs
  the radius's gradient until they do: :func:`restore`);
* removes from each loss gradient the part that would shrink the radius while the radius is
  within :data:`BAND` of the requirement (gradient projection on the one active constraint);
* accepts an optimizer step where the radius still meets the requirement; otherwise projects it
  back onto the requirement along the radius's gradient (a few Newton steps), or failing that
  halves it back toward the last accepted point (:func:`feasible_step`).

Every accepted point therefore holds the requirement, not just the last. On a problem whose
``[plant]`` has input limits the requirement is on the problem's loop by default
(:class:`Loop`): the radius kept is the problem certificate's under those limits, the smaller of
the exact map's proved lower bound and the saturation-free radius
(:func:`problem_radius_function`), labelled with the plant features it covers and those it does
not (noise, mismatch ranges that act on a continuous loop: no proof the tuner keeps covers them,
:func:`loop_coverage`). On a digital controller's loop (a ``control_period``) the radius kept is
the held reach's (:func:`held_radius_function`), which covers the whole plant with the noise
within ``[certify] noise_bound``: it has no gradient, so steps are halved back, never projected,
and the initial gains must meet the requirement. For (1,2), whose
singular set is curved, the radius is a branch and bound over (t, heading) with a proved lower
bound (:func:`wmrjax.certify.curved_exact_map_radius`): not differentiable, and far too slow
to evaluate at every step (thousands of boxes per round, a dozen rounds), so a
requirement on (1,2) is refused; tune without it and
certify the result (``wmrjax certify ... --gains``), or require a Lemma 2 radius
through the certificate term of the loss.
"""

from __future__ import annotations

import enum
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import certify
from wmrjax.certify import Feature, Kind, Slice
from wmrjax.certify.job import CERTIFY_KEYS, read_section
from wmrjax.certify.real_loop import inert_features, tightest_limits
from wmrjax.certify.saturation import limit_usage, saturation_free_sensitivity
from wmrjax.controllers import Space
from wmrjax.controllers.dynamic import DynamicLinearization
from wmrjax.problem import ProblemError, check_keys, positive
from wmrjax.references import FAMILIES

SLICES = tuple(Slice)
DEFAULT_EPS = CERTIFY_KEYS["eps"]  # the certification's default margin [output-error units]
BAND = 0.02  # project the gradient when the radius is within 2 % of the requirement
MAX_HALVINGS = 30  # a rejected step is halved at most this often (2^-30 of it), then not taken
HELD_HALVINGS = 3  # the same for a radius without a gradient (the held reach: a search per halving)
RESTORE_STEPS = 200  # ascent steps on the radius when the initial gains miss the requirement
RESTORE_STEP = 0.2  # their first length in the unconstrained parameters
RESTORE_MARGIN = 1e-3  # the ascent and the projection aim this fraction above the requirement
PROJECTION_STEPS = 5  # Newton steps projecting a step back onto the requirement
CACHED_POINTS = 8  # the problem loop's radii kept per point (a step evaluates one point a few times)


class Loop(enum.StrEnum):
    """The closed loop whose radius a requirement keeps."""

    PROBLEM = "problem"  # the problem's own: its [plant]'s features, as far as the tuner's proof covers them
    NOMINAL = "nominal"  # the law's nominal continuous loop (the exact map alone)


TUNER_PROOFS = frozenset({Feature.INPUT_LIMIT})
"""Plant features that a radius the tuner keeps can cover on a continuous loop (with the features
that cannot change the loop, :func:`wmrjax.certify.inert_features`): the saturation-free radius is
a few seconds a point; the mismatch tube's bisection (:func:`wmrjax.certify.mismatch_radius`) is
minutes. A digital controller's loop (a ``control_period``) is kept by the held reach instead,
which covers every feature of the plant (:data:`HELD_PROOFS`)."""

HELD_PROOFS = frozenset(Feature) - {Feature.NOMINAL}
"""What the held reach (:func:`wmrjax.certify.held_reach_radius`) covers: the sampled, held,
clipped loop of every plant of the range, with the noise within the problem's ``[certify]
noise_bound``."""


class Requirement(NamedTuple):
    """The initial errors the tuned gains must stay certified for (``[tune.requirement]``).

    Attributes:
      radius: the required exact-map radius [output-error units: m, m/s, ...]; or ``"initial"``
        (the initial gains' radius: keep the region the user has) or ``"box"`` (the smallest
        ball holding the problem's ``[initial]`` box in the slice).
      slice: ``"full"`` (every output-error component: position and velocity errors, what a
        start of the ``[initial]`` box differs in) or ``"position"`` (the position error only,
        the paper's setting).
      eps: the margin to the singular set (the problem's ``[certify] eps`` by default).
      loop: ``"problem"`` (default; :class:`Loop`): with a ``[plant]`` that has input limits the
        radius is the problem certificate's, the smaller of the exact map's and the
        saturation-free radius (both proved), and with a ``control_period`` the held reach's
        (proved); ``"nominal"``: the exact map's alone (attained), the nominal continuous loop's.
    """

    radius: float | str
    slice: str = str(Slice.FULL)
    eps: float = DEFAULT_EPS
    loop: str = str(Loop.PROBLEM)


def read(table: dict | None, certify_section: dict) -> Requirement | None:
    """The :class:`Requirement` of a ``[tune.requirement]`` table (None when absent)."""
    if not table:
        return None
    check_keys("tune.requirement", table, Requirement._fields)
    if "radius" not in table:
        raise ProblemError('[tune.requirement] radius: required (a radius >= 0, "initial" or "box")')
    r = table["radius"]
    if not (
        r in ("initial", "box")
        or (isinstance(r, (int, float)) and not isinstance(r, bool) and math.isfinite(r) and r >= 0)
    ):
        raise ProblemError(f'[tune.requirement] radius: expected a radius >= 0, "initial" or "box", got {r!r}')
    sl = table.get("slice", str(Slice.FULL))
    if sl not in SLICES:
        raise ProblemError(f"[tune.requirement] slice: expected one of {[str(s) for s in SLICES]}, got {sl!r}")
    eps = positive("tune.requirement", "eps", table.get("eps", certify_section.get("eps", DEFAULT_EPS)))
    lp = table.get("loop", str(Loop.PROBLEM))
    if lp not in tuple(Loop):
        raise ProblemError(f"[tune.requirement] loop: expected one of {[str(x) for x in Loop]}, got {lp!r}")
    # names, plain strings: a requirement's repr is part of a checkpoint's fingerprint
    return Requirement(float(r) if not isinstance(r, str) else r, str(Slice(sl)), float(eps), str(Loop(lp)))


def check(setting, family, req: Requirement | None = None) -> None:
    """ValueError when the problem has no exact-map radius to keep: a static law, a random
    reference family (no fixed reference), or type (1,2) (see the module docstring); with
    ``req`` on the problem's loop with input limits or a control period, a gain schedule (the
    saturation-free radius follows :math:`e^{At}`, constant gains)."""
    covered = loop_coverage(setting, req)[0] if req is not None else ()
    if family.knots and (str(Feature.INPUT_LIMIT) in covered or str(Feature.CONTROL_PERIOD) in covered):
        raise ValueError(
            "a requirement on the problem's loop with input limits or a control period needs constant gains "
            "(the saturation-free radius follows e^{At}, the held reach is searched below the exact map's proved "
            'radius); tune a gain schedule with [tune.requirement] loop = "nominal"'
        )
    if not isinstance(setting.ctrl, DynamicLinearization):
        raise ValueError("a certified-region requirement needs a dynamic linearizing law (only those are certified)")
    if FAMILIES[setting.data["reference"]["family"]].kind == "random":
        raise ValueError("a certified-region requirement needs a fixed reference, not a random family")
    if certify.singular_rows(setting.ctrl) is None:
        raise ValueError(
            "a certified-region requirement on type (1,2) is not supported: its exact-map radius (a "
            "curved singular set) is a branch and bound taking minutes per evaluation, without a "
            "gradient; tune without it and certify the tuned gains (wmrjax certify "
            "PROBLEM --gains gains.json), or weight the loss's certificate term (Lemma 2)"
        )


class Radius(NamedTuple):
    """The radius as the loop uses it.

    Attributes:
      value: ``raw -> radius`` (a float).
      value_and_grad: ``raw -> (radius, gradient in raw)``.
      label: what it is, for the summary.
      covers: the features of the loop it holds for (:class:`wmrjax.certify.Feature` names).
      not_covered: the problem's plant features it does not hold for.
      kind: how it is known (:class:`wmrjax.certify.Kind`).
      detail: ``raw -> dict`` of the bounds it is the smaller of and which one binds (None: one bound).
    """

    value: Callable
    value_and_grad: Callable | None
    label: str
    covers: tuple = (str(Feature.NOMINAL),)
    not_covered: tuple = ()
    kind: str = str(Kind.ATTAINED)
    detail: Callable | None = None


def loop_coverage(setting, req: Requirement) -> tuple[tuple, tuple]:
    """``(covers, not_covered)`` of the radius a requirement keeps on the problem's loop (feature
    names): the nominal loop with the features that cannot change it and, for ``loop =
    "problem"``, those of :data:`TUNER_PROOFS`; the rest of the plant's features are not covered."""
    features = certify.plant_features(setting)
    inert = inert_features(setting) if features else {}
    proved = frozenset()
    if Loop(req.loop) == Loop.PROBLEM:
        proved = HELD_PROOFS if Feature.CONTROL_PERIOD in features else TUNER_PROOFS
    covered = [f for f in features if f in inert or f in proved]
    rest = [f for f in features if f not in covered]
    return tuple(str(f) for f in (Feature.NOMINAL, *covered)), tuple(str(f) for f in rest)


def radius_function(setting, family, req: Requirement) -> Radius:
    """The radius a requirement keeps, as a function of the raw parameters of ``family``: the
    exact-map radius of the gains on the problem's reference, nominal geometry and horizon
    (:func:`wmrjax.certify.differentiable_exact_map_radius`), or with ``loop = "problem"`` the
    problem certificate's radius: on a digital controller's loop the held reach's
    (:func:`held_radius_function`), on a continuous one with input limits the smaller of the exact
    map's and the saturation-free radius (:func:`problem_radius_function`)."""
    check(setting, family, req)
    covers, not_covered = loop_coverage(setting, req)
    if str(Feature.CONTROL_PERIOD) in covers:
        return held_radius_function(setting, family, req, covers)
    if str(Feature.INPUT_LIMIT) in covers:
        return problem_radius_function(setting, family, req, covers, not_covered)
    base = setting.params()
    kw = dict(t_final=setting.t_final, eps=req.eps, basis=req.slice)
    fn = lambda raw: certify.differentiable_exact_map_radius(setting.ctrl, base._replace(gains=family.gains(raw)), **kw)
    vg = jax.jit(jax.value_and_grad(fn))
    return Radius(lambda raw: float(vg(raw)[0]), vg, f"exact map ({req.slice})", covers, not_covered)


def _point_cache(compute):
    """``compute(raw)`` kept for the last :data:`CACHED_POINTS` raw points (a step asks for one
    point's value, gradient and detail in turn; each is a search)."""
    cache: dict = {}

    def cached(raw):
        key = np.asarray(raw, float).tobytes()
        if key not in cache:
            if len(cache) >= CACHED_POINTS:
                cache.pop(next(iter(cache)))
            cache[key] = compute(raw)
        return cache[key]

    return cached


def problem_radius_function(setting, family, req: Requirement, covers, not_covered) -> Radius:
    r"""The problem certificate's radius under input limits as a function of the raw parameters:
    the smaller of the exact map's proved lower bound and the saturation-free radius's
    (:func:`wmrjax.certify.saturation_free_radius` under the plant's tightest limits), each as
    ``wmrjax certify`` computes it, so every point the tuner accepts has a proved radius at or
    above the requirement. Its gradient, a direction for the projections only, is the binding
    bound's: the exact map's envelope gradient, or the saturation-free radius's implicit one
    (:func:`wmrjax.certify.saturation.saturation_free_sensitivity`). The two bounds of a point
    are kept (:data:`CACHED_POINTS`): a step asks for one point's value and gradient in turn.
    """
    ctrl, T, base, basis = setting.ctrl, setting.t_final, setting.params(), req.slice
    limit = tightest_limits(setting)
    lim = jnp.asarray(np.where(np.isfinite(limit), limit, np.finfo(float).max))
    at = lambda raw: base._replace(gains=family.gains(raw))
    exact = lambda raw: certify.differentiable_exact_map_radius(ctrl, at(raw), t_final=T, eps=req.eps, basis=basis)
    exact_grad = jax.jit(jax.grad(exact))
    usage_grad = jax.jit(jax.grad(lambda raw, d, t, rho: limit_usage(ctrl, at(raw), lim, d, t, rho), argnums=(0, 3)))

    @_point_cache
    def bounds(raw):
        params = at(jnp.asarray(raw))
        em = certify.exact_map_radius(ctrl, params, t_final=T, eps=req.eps, basis=basis)
        return float(em.lower_bound), certify.saturation_free_radius(ctrl, params, limit, t_final=T, basis=basis)

    def value(raw):
        em, sat = bounds(raw)
        return min(em, float(sat.lower_bound))

    def value_and_grad(raw):
        em, sat = bounds(raw)
        if sat.lower_bound < em:
            return value(raw), saturation_free_sensitivity(usage_grad, sat, raw)
        return value(raw), exact_grad(jnp.asarray(raw))

    def detail(raw):
        em, sat = bounds(raw)
        by = "saturation_free" if sat.lower_bound < em else "exact_map"
        return {"exact_map": em, "saturation_free": float(sat.lower_bound), "bound_by": by}

    label = f"problem certificate ({basis}): min(exact map, saturation-free), both proved"
    return Radius(value, value_and_grad, label, covers, not_covered, str(Kind.PROVED), detail)


def held_radius_function(setting, family, req: Requirement, covers) -> Radius:
    """The problem certificate's radius of a digital controller's loop as a function of the raw
    parameters: the held reach's proved radius (:func:`wmrjax.certify.held_reach_radius`, with the
    problem's ``[certify] noise_bound``) searched up to the exact map's proved lower bound, as
    ``wmrjax certify`` computes it. It has no gradient (``value_and_grad`` None): a step that
    misses the requirement is halved back, never projected, and initial gains that miss it are
    refused (nothing to climb). One evaluation is one search (about 13 s on ``s_path``, 2 cores,
    after the reach's one compile); the last :data:`CACHED_POINTS` points are kept.

    Args:
      setting: the problem's :class:`wmrjax.problem.Setting`, with a ``control_period``.
      family: the :class:`wmrjax.tune.GainFamily` the raw parameters are of (constant gains).
      req: the :class:`Requirement` (its ``slice`` and ``eps``).
      covers: the plant features the radius holds for (:func:`loop_coverage`).

    Returns:
      A :class:`Radius` with ``value_and_grad`` None, ``kind`` "proved" and ``detail`` giving the
      exact map's proved radius [output-error units], the held reach's, the noise multiple and
      ``bound_by`` "held_reach".
    """
    ctrl, T, base, P = setting.ctrl, setting.t_final, setting.params(), certify.slice_basis(setting.ctrl, req.slice)
    noise = read_section(setting.data)["noise_bound"]

    @_point_cache
    def bounds(raw):
        params = base._replace(gains=family.gains(jnp.asarray(raw)))
        em = float(certify.exact_map_radius(ctrl, params, t_final=T, eps=req.eps, basis=req.slice).lower_bound)
        return em, certify.held_reach_radius(setting, params, P, eps=req.eps, r_max=em, noise_multiple=noise)

    def detail(raw):
        em, hr = bounds(raw)
        return {"exact_map": em, "held_reach": hr.radius, "noise_multiple": hr.noise_multiple, "bound_by": "held_reach"}

    label = f"problem certificate ({req.slice}): the held reach at {noise:g} noise_std, proved"
    return Radius(lambda raw: bounds(raw)[1].radius, None, label, covers, (), str(Kind.PROVED), detail)


def required_radius(setting, req: Requirement, radius: Radius, raw0) -> float:
    """The requirement as a number: ``"initial"`` is the radius at ``raw0``, ``"box"`` the
    half-diagonal of the ``[initial]`` box in the slice. ValueError where ``"initial"`` is zero (the
    initial gains' radius proves nothing: a requirement of zero would keep nothing)."""
    if req.radius == "initial":
        r = radius.value(raw0)
        if not r > 0.0:
            raise ValueError(
                f'[tune.requirement] radius = "initial": the initial gains\' {radius.label} is {r:.4g}, so there '
                "is nothing to keep; lower [certify] noise_bound (a digital controller's loop), or keep the "
                'nominal loop\'s radius with [tune.requirement] loop = "nominal"'
            )
        return r
    if req.radius == "box":
        if Space(setting.data["initial"].get("space", "output")) != Space.OUTPUT:
            raise ValueError(
                '[tune.requirement] radius = "box" needs output-space initial errors ([initial] space '
                '= "output"): the radius is a ball of output errors'
            )
        keys = ("x", "y") if Slice(req.slice) == Slice.POSITION else ("x", "y", "vx", "vy")
        return float(math.sqrt(sum(_half_width(setting.data["initial"].get(k, 0.0)) ** 2 for k in keys)))
    return float(req.radius)


def _half_width(v) -> float:
    """The largest |value| of one ``[initial]`` key (a number, a list or a ``{low, high}`` box)."""
    if isinstance(v, dict):
        return max(abs(float(v.get("low", 0.0))), abs(float(v.get("high", 0.0))))
    return float(np.max(np.abs(np.asarray(v, float)))) if np.size(v) else 0.0


def project(grad, r: float, g_r, required: float):
    """The loss gradient without the part that would shrink the radius, when the radius is within
    :data:`BAND` of ``required`` (a descent step moves by about ``-grad``; it lowers the radius
    where ``grad . g_r > 0``); unchanged where the radius has no gradient (``g_r`` None)."""
    if g_r is None or r > required * (1.0 + BAND):  # None: a radius without a gradient
        return grad
    g, gr = np.asarray(grad, float), np.asarray(g_r, float)
    dot, nn = float(np.sum(g * gr)), float(np.sum(gr * gr))
    if dot <= 0.0 or nn == 0.0:
        return grad
    return jnp.asarray(g - dot / nn * gr, dtype=jnp.asarray(grad).dtype)


def feasible_step(raw, proposal, radius: Radius, required: float):
    """``(accepted point, its radius, halvings)`` for an optimizer's ``proposal`` from ``raw``.

    A proposal below ``required`` is first projected back along the radius's gradient (Newton
    steps on ``radius = required (1 + RESTORE_MARGIN)``, at most :data:`PROJECTION_STEPS`, ending
    at the first iterate that meets ``required``: aiming above it and stopping once inside, each
    evaluation of a costly radius counts, the problem certificate's a few seconds): the
    iterate slides along the boundary instead of stopping at it (a step tangent to it still
    loses radius at second order where the radius is concave). Where that fails the step is halved back toward ``raw``: the furthest of
    ``raw + 2^-k (proposal - raw)`` that meets ``required``, else ``raw`` itself (``halvings``
    is then ``MAX_HALVINGS + 1``, ``HELD_HALVINGS + 1`` for a radius without a gradient; -1
    marks a projected step).
    """
    proposal = jnp.asarray(proposal)
    r = radius.value(proposal)
    if r >= required:
        return proposal, r, 0
    p, target = proposal, required * (1.0 + RESTORE_MARGIN)
    for _ in range(PROJECTION_STEPS if radius.value_and_grad is not None else 0):  # no gradient: halve only
        rv, g = radius.value_and_grad(p)
        gg = float(jnp.sum(g * g))
        if float(rv) >= required or gg == 0.0 or not np.isfinite(gg):
            break
        p = p + (target - float(rv)) / gg * g
    r = radius.value(p)
    if r >= required:
        return p, r, -1
    raw, n = np.asarray(raw), MAX_HALVINGS if radius.value_and_grad is not None else HELD_HALVINGS
    for k in range(1, n + 1):
        cand = jnp.asarray(raw + 0.5**k * (np.asarray(proposal) - raw))
        r = radius.value(cand)
        if r >= required:
            return cand, r, k
    return jnp.asarray(raw), radius.value(jnp.asarray(raw)), n + 1


def restore(raw, radius: Radius, required: float, log=print):
    """Climb the radius from ``raw`` until it meets ``required`` (normalised gradient steps,
    lengthened after an improvement, halved after a failure); ValueError when it cannot."""
    r = radius.value(raw)
    if r >= required:
        return raw, r
    if radius.value_and_grad is None:
        raise ValueError(
            f"the initial gains' {radius.label} is {r:.4g}, below the requirement {required:.4g}, and it has no "
            "gradient to climb: start from gains that meet it, lower the requirement, or (a digital "
            "controller's loop) lower [certify] noise_bound"
        )
    target, step = required * (1.0 + RESTORE_MARGIN), RESTORE_STEP
    for _ in range(RESTORE_STEPS):
        r, g = radius.value_and_grad(raw)
        if float(r) >= target:
            break
        gn = float(jnp.linalg.norm(g))
        if gn == 0.0:
            break
        trial = raw + step * g / gn
        rt = float(radius.value_and_grad(trial)[0])
        if rt > float(r):
            raw, step = trial, step * 1.5
        else:
            step *= 0.5
    r = radius.value(raw)
    if r < required:
        raise ValueError(
            f"the requirement {required:.4g} is beyond what this gain family reaches from the initial gains "
            f"(the radius climbed to {r:.4g} in {RESTORE_STEPS} ascent steps): lower it"
        )
    log(f"requirement {required:.4g}: the initial gains' radius raised to {r:.4g} before tuning")
    return raw, r


# --- every radius of a set of gains, labelled ----------------------------------------------------

K2_LABELS = {
    "paper": "Lemma 2, K2 of eq (64) (the double pole at -1 only)",
    "lyapunov": "Lemma 2, automatic Lyapunov K2",
    "exact_norm": "Lemma 2, K2 = ||e^{At}||",
}
SCHEDULE_K2_LABEL = "Lemma 2, K2 = ||Phi(t, 0)|| (gain schedule)"


def radii(setting, gains, *, eps: float, falsify=False, seed: int = 0, n_starts: int = 16) -> dict:
    """Every radius of ``gains`` on the problem, as the certify module computes it (plain JSON).

    Lemma 2 with each K2 that applies, the exact-map radius of the full error space and of the
    position slice (with the proved lower bound for (1,2)), and with ``falsify`` the falsified
    radius (an upper bound, from rollouts; :func:`wmrjax.certify.falsified_radius` started from
    the largest Lemma 2 radius, as :func:`wmrjax.certify.analyse` does).

    Each exact-map block also has ``worst_error_rollouts`` (:func:`worst_error_rollouts`): the
    map's own worst initial error simulated at 0.99 and 1.01 times its size.

    Args:
      setting: the problem's :class:`wmrjax.problem.Setting`.
      gains: the gains to certify.
      eps: the margin.
      seed: the falsifier's PRNG seed.
      n_starts: its gradient starts.
      falsify: True (both slices), a slice name (that one only) or False.
    """
    ctrl, T = setting.ctrl, setting.t_final
    params = setting.params(gains=gains)
    report = certify.lemma2(ctrl, params, t_final=T, eps=eps)
    out = {"eps": eps, "t_final": T, "lemma2": {}}
    nominal = [str(certify.Feature.NOMINAL)]
    for name, c in report.certificates().items():
        label = SCHEDULE_K2_LABEL if gains.time_varying else K2_LABELS[name]
        out["lemma2"][name] = {
            "radius": float(c.radius),
            "label": label,
            "covers": nominal,
            "kind": str(certify.Kind.PROVED_ON_TIME_GRID),
        }
    certified = max(v["radius"] for v in out["lemma2"].values())
    keys = jax.random.split(jax.random.PRNGKey(seed))
    for basis, key in zip(SLICES, keys):
        em = certify.exact_map_radius(ctrl, params, t_final=T, eps=eps, basis=basis)
        block = {"radius": float(em.radius), "label": f"exact map ({basis})", "covers": nominal}
        block["kind"] = str(certify.Kind.ATTAINED)  # its lower bound (proved) below, where there is one
        if em.lower_bound is not None:
            block["lower_bound"] = float(em.lower_bound)
        block["worst_error_rollouts"] = worst_error_rollouts(setting, params, em, eps)
        if falsify is True or falsify == basis:
            f = certify.falsified_radius(
                ctrl, params, t_final=T, eps=eps, key=key, dt=setting.dt, basis=basis, n_starts=n_starts, r_lo=certified
            )
            block["falsified"] = None if f.radius is None else float(f.radius)
            block["falsified_over_exact"] = None if f.radius is None else float(f.radius) / float(em.radius)
        out[f"exact_map_{basis}"] = block
    return out


def problem_radii(setting, gains, *, eps: float) -> dict:
    """The problem loop's proved radius of ``gains`` per slice, where a proof covers its plant
    (:func:`wmrjax.certify.problem_certificate` without its falsifier, a digital controller's with
    the noise within the problem's ``[certify] noise_bound``): ``loop`` (the plant's
    features) and per slice ``radius`` (None where no proof covers them), ``kind``, ``covers``,
    ``not_covered``, ``bound_by``.

    Args:
      setting: the problem's :class:`wmrjax.problem.Setting` (with a ``[plant]``).
      gains: the gains.
      eps: the margin.
    """
    ctrl, T = setting.ctrl, setting.t_final
    params = setting.params(gains=gains)
    exact = {b: certify.exact_map_radius(ctrl, params, t_final=T, eps=eps, basis=b) for b in SLICES}
    noise = read_section(setting.data)["noise_bound"]  # the problem's, as wmrjax certify reads it
    pc = certify.problem_certificate(setting, params, exact, eps=eps, falsify=False, noise_bound=noise)
    keys = ("radius", "kind", "covers", "not_covered", "bound_by")
    return {"loop": pc["loop"], **{b: {k: pc[b].get(k) for k in keys} for b in SLICES}}


def problem_loop(setting, requirement: Requirement | None = None) -> dict:
    """What the tuner's radii cover against the problem's loop: its plant features
    (:func:`wmrjax.certify.plant_features`), whether the radii cover them (``covered``: only where
    the loop is the nominal one; Lemma 2's and the exact map's radii are the nominal continuous
    loop's) and a ``note`` saying so, with what a ``requirement`` keeps (:func:`loop_coverage`)."""
    features = [str(f) for f in certify.plant_features(setting)]
    if not features:
        return {"features": [], "covered": True, "note": "the problem's loop is the nominal one"}
    note = (
        "the Lemma 2 and exact-map radii here are the nominal continuous loop's; problem_certificate is the loop's own"
    )
    if requirement is not None:
        covers, rest = loop_coverage(setting, requirement)
        note += f"; the requirement keeps a radius of the loop with {', '.join(covers)}"
        if rest:
            note += (
                f"; no proof the tuner keeps covers this problem's {', '.join(rest)} "
                "(wmrjax certify gives the problem loop's falsified radius)"
            )
    return {"features": features, "covered": False, "note": note}


CONFIRM_SCALES = (0.99, 1.01)  # the exact map's worst initial error, simulated this much inside and outside


def worst_error_rollouts(setting, params, em, eps: float) -> dict:
    """The exact map's worst initial error simulated (RK4 at a tenth of the problem's step) at
    :data:`CONFIRM_SCALES` times its size: inside, the run must stay eps away; outside, it must
    come within eps or turn singular. Both holding confirms by rollouts that the radius is
    right to 1 % (an upper bound found where a falsifier's search may miss a brief approach)."""
    x = jnp.asarray(em.worst_error)[None]
    d = certify.min_distance(
        setting.ctrl,
        params,
        initial_errors=jnp.concatenate([x * s for s in CONFIRM_SCALES]),
        t_final=setting.t_final,
        # two runs: the falsifier's confirmation program (its step and blocks), not 256-run blocks
        dt=certify.CONFIRM_DT_FACTOR * setting.dt,
        block=certify.CONFIRM_BLOCK,
        shared=False,
    )
    dist, sing = np.asarray(d.distance), np.asarray(d.singular)
    inside_ok = bool(dist[0] >= eps and not sing[0])
    outside_fails = bool(dist[1] < eps or sing[1])
    return {
        "scales": list(CONFIRM_SCALES),
        "min_distance": dist.tolist(),
        "singular": sing.tolist(),
        "confirmed": inside_ok and outside_fails,
    }
