r"""Beyond Lemma 2: the exact error map.

While a run stays regular the linearized error obeys zeta_err(t) = expm(A t) zeta_err(0)
*exactly*, so the set of safe initial errors is known without any K2 bound. For the types
whose singular set in zeta coordinates is the linear subspace {velocity of the output point
= 0} ((2,0), (2,1), (1,1)), the distance to it is ||C zeta|| with C selecting those two rows;
the largest safe ball is then the solution of a semi-infinite problem over t whose inner
problem (fixed t) is a convex QCQP solved in closed form up to a scalar secular equation.

(1,2)'s singular set {sigma(zeta) = 0} is curved, but for a fixed heading phi of the nearest
point its distance condition is again a QCQP in the initial error (two rows, both linear in
it), so the radius is a minimum over (t, phi) of closed-form problems: a branch and bound over
boxes of (t, phi) returns the attained radius (an upper bound: a real initial error that
comes within eps) and a proved lower bound, with their gap."""

from __future__ import annotations

import enum
import functools
import hashlib
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math, linearize
from wmrjax.certify import interval
from wmrjax.certify.interval import Interval
from wmrjax.certify.lemma2 import (
    TRANSITION_STEP,
    check_dynamic,
    check_eager,
    check_lemma2_args,
    m1_closed_form,
    transition_steps,
)
from wmrjax.controllers.dynamic import DynamicLinearization, DynamicParams
from wmrjax.references import PIECE_SLACK, box_pieces, taylor, time_boxes
from wmrjax.simulate import fixed_blocks


def singular_rows(ctrl: DynamicLinearization):
    """Flat indices (into ``ctrl.error(...).reshape(-1)``) of the output point's velocity,
    whose vanishing is the singular set; ``None`` where the singular set is curved ((1,2))."""
    check_dynamic(ctrl)
    return (ctrl.m, ctrl.m + 1) if ctrl.row.singular_set_is_linear else None


class Slice(enum.StrEnum):
    """A slice of initial errors: every output-error component, or the output point's position
    error only (the paper's setting; every other component equal to the reference's)."""

    FULL = "full"
    POSITION = "position"


def slice_basis(ctrl: DynamicLinearization, basis=Slice.FULL):
    """Orthonormal basis (n, k) of a slice of initial errors.

    Args:
      ctrl: a dynamic linearizing law (its r and m).
      basis: a :class:`Slice` (or its name): ``"full"`` (every component, k = r m) or
        ``"position"`` (k = 2); or an explicit (n, k) array with orthonormal columns.
    """
    n = ctrl.relative_degree * ctrl.m
    if isinstance(basis, str):
        if basis not in tuple(Slice):
            raise ValueError(f"unknown slice {basis!r}; expected one of {[str(s) for s in Slice]} or an (n, k) array")
        return jnp.eye(n) if Slice(basis) == Slice.FULL else jnp.eye(n)[:, :2]
    P = jnp.asarray(basis)
    if (
        P.ndim != 2
        or P.shape[0] != n
        or not np.allclose(np.asarray(P).T @ np.asarray(P), np.eye(P.shape[1]), atol=1e-9)
    ):
        raise ValueError(f"a slice basis must be an ({n}, k) array with orthonormal columns, got shape {P.shape}")
    return P


def square_basis(P):
    """The (n, k) slice basis ``P`` padded with zero columns to (n, n).

    Every slice then goes through one compiled program per closed loop (the full one, the
    position slice and any explicit basis alike): its extra coordinates multiply zero columns,
    so they stay zero and add exact zeros to every sum, and the results are those of ``P``.
    """
    return jnp.concatenate([P, jnp.zeros((P.shape[0], P.shape[0] - P.shape[1]), P.dtype)], axis=1)


# singular values below this fraction of the largest count as zero (directions M cannot move)
RANK_TOLERANCE = 1e-14
# the bisection's bracket in log(nu s_max^2) extends this far past where nu s^2 = 1 for the largest and
# the smallest singular value: e^-60 and e^60 leave the residual's terms at 1 and 0 to rounding
BRACKET_MARGIN = 60.0


def min_norm_to_ball(M, a, eps, iters: int = 200):
    r"""Smallest :math:`\|x\|` with :math:`\|a + Mx\| \le \epsilon` and the minimiser (inf if unreachable).

    KKT: :math:`x(\nu) = -\nu (I + \nu M^TM)^{-1} M^T a`; in the SVD :math:`M = U S V^T` the
    residual :math:`\|a + Mx(\nu)\|^2 = \sum_i a_i'^2 / (1 + \nu s_i^2)^2` (+ the part of a
    outside range U) decreases in :math:`\nu`; bisection in :math:`\log\nu` finds the root.
    It is solved for :math:`w = \nu s_{max}^2`; the bracket follows the singular values: at its
    low end :math:`\nu s_{max}^2 = e^{-B}`
    (the residual is :math:`\|a\|^2` to rounding), at its high end :math:`\nu s_{min}^2 = e^{B}`
    (every term vanishes), :math:`s_{min}` the smallest singular value counted as nonzero. A
    fixed bracket failed on long horizons, where :math:`s_i(e^{At})` decays like
    :math:`t e^{-pt}` and the root left it: the radius collapsed (2.8e-13 at t = 50 s).
    """
    U, s, Vt = _math.svd_small(M)  # no LAPACK: see wmrjax._math
    ap = U.T @ a
    out2 = jnp.maximum(jnp.sum(a**2) - jnp.sum(ap**2), 0.0)
    kept = s > RANK_TOLERANCE * jnp.max(s)
    limit = out2 + jnp.sum(jnp.where(kept, 0.0, ap**2))
    reachable = (limit < eps**2) & jnp.any(kept)
    # scaled: w = nu s_max^2 and sigma = s / s_max in [0, 1], so that s^2 may underflow (a
    # long horizon's e^{At} is ~1e-217 at t = 1000 s for p = 0.5) and nu overflow, not w
    s_max = jnp.maximum(jnp.max(s), jnp.finfo(s.dtype).tiny)
    sig = s / s_max
    sig_min = jnp.min(jnp.where(kept, sig, 1.0))

    def parts(logw):
        """The residual and x's coordinates times s_max (bounded: w sigma / d <= 1 / (2 sigma))."""
        w = jnp.exp(logw)
        d = 1.0 + w * sig**2
        return jnp.sum((ap / d) ** 2) + out2, w * sig * ap / d

    bracket = (jnp.asarray(-BRACKET_MARGIN, s.dtype), -2.0 * jnp.log(sig_min) + BRACKET_MARGIN)

    def bisect(c, _):
        lo, hi = c
        mid = 0.5 * (lo + hi)
        too_far = parts(mid)[0] > eps**2
        return (jnp.where(too_far, mid, lo), jnp.where(too_far, hi, mid)), None

    (lo, hi), _ = jax.lax.scan(bisect, bracket, None, length=iters)
    c = parts(hi)[1]
    inside = jnp.sum(a**2) <= eps**2
    # ||x|| = ||c|| / s_max (Vt has orthonormal rows): beyond float range it is inf, never NaN
    rho = jnp.where(inside, 0.0, jnp.where(reachable, jnp.linalg.norm(c) / s_max, jnp.inf))
    x = jnp.where(inside | ~jnp.isfinite(rho), 0.0, -(Vt.T @ (c / s_max)))
    return rho, x


class ExactMapRadius(NamedTuple):
    """Largest ball of initial errors (in a slice) keeping dist(zeta(t), singular set) >= eps on [0, T].

    Attributes:
      ts: (T,) time grid [s].
      rho: (T,) smallest initial error reaching the eps-neighbourhood at each t.
      radius: min_t rho(t): attained by ``worst_error`` (refined by golden section; for (1,2)
        the best box centre of the branch and bound), so an upper bound on the safe radius.
      argmin: time of the worst case [s].
      worst_error: (r m,) the initial error achieving it (full coordinates).
      lower_bound: a proved lower bound on the safe radius (every initial error below it stays
        eps away over all of [0, T], between the grid's times too): (1,2)'s branch and bound,
        :func:`linear_lower_bound` for the linear singular sets; None for a gain schedule
        (its transition matrices are RK4's), where ``radius`` is the attained one only.
      gap: ``(radius - lower_bound) / radius`` (None where ``lower_bound`` is).
      boxes: (t, phi) boxes the branch and bound evaluated (0 for the linear sets: their
        ``radius`` is the map's minimum itself, tight against the falsifier).
    """

    ts: jnp.ndarray
    rho: jnp.ndarray
    radius: jnp.ndarray
    argmin: jnp.ndarray
    worst_error: jnp.ndarray
    lower_bound: float | None = None
    gap: float | None = None
    boxes: int = 0


def exact_map_radius(
    ctrl: DynamicLinearization,
    params: DynamicParams,
    *,
    t_final: float,
    eps: float,
    basis=Slice.FULL,
    n_t: int = 2001,
    refine: int = 40,
    lower_bound: bool = True,
) -> ExactMapRadius:
    r"""Exact safe radius from the linear error map (semi-infinite over t; grid then golden section).

    With :math:`\tilde\zeta(t) = e^{At}P s` (P the slice basis) and the singular set
    :math:`\{C\zeta = 0\}`, the run comes within :math:`\epsilon` of it at time t iff
    :math:`\|C\zeta_{ref}(t) + C e^{At} P s\| < \epsilon`. For each t the smallest such
    :math:`\|s\|` is :func:`min_norm_to_ball`; the radius is its minimum over [0, T]. Every
    initial error inside the ball keeps distance :math:`\ge\epsilon` over the horizon, and the
    returned ``worst_error`` (scaled by any factor > 1) does not: the radius is tight.

    For (1,2)'s curved singular set see :func:`curved_exact_map_radius` (called from here).

    Args:
      ctrl: the closed loop (a dynamic linearizing law).
      params: its parameters.
      t_final: horizon T [s].
      eps: Lemma 2's margin.
      basis: slice, see :func:`slice_basis`.
      n_t: grid size.
      refine: golden-section iterations around the grid minimum.
      lower_bound: compute the proved lower bound (constant gains, a linear singular set); False
        returns the attained radius only (``lower_bound`` None), at a fraction of the cost.

    Raises:
      ValueError: bad eps/horizon or a reference within eps of the singular set.
    """
    check_dynamic(ctrl, params)
    check_eager("exact_map_radius", params, "its grid over t and golden-section refinement need values")
    check_lemma2_args(t_final=t_final, eps=eps, reference=params.reference)
    rows = singular_rows(ctrl)
    scheduled = params.gains.time_varying
    if rows is None and scheduled:
        raise ValueError(
            f"the exact-map radius of type {ctrl.robot.name} (a curved singular set, branch and bound "
            "with bounds from ||A||) is implemented for constant gains only, not a GainSchedule; "
            "use lemma2 (K2 = ||Phi(t, 0)||) or the empirical radius"
        )
    if rows is None:
        return curved_exact_map_radius(ctrl, params, t_final=t_final, eps=eps, basis=basis)
    P = square_basis(slice_basis(ctrl, basis))  # one program for every slice
    C = jnp.eye(ctrl.relative_degree * ctrl.m)[jnp.asarray(rows)]
    ts = jnp.linspace(0.0, t_final, n_t)
    m1 = _linear_m1(ctrl, params, C, ts)
    check_lemma2_args(t_final=t_final, eps=eps, m1=m1)
    n_phi = transition_steps(t_final) if scheduled else None
    Phis = linearize.transition_matrices(params.gains, np.asarray(ts), max_step=TRANSITION_STEP) if scheduled else None
    eps_a = jnp.asarray(eps, ts.dtype)
    rho, rad, t_star, worst = _exact_map(ctrl, params, P, C, eps_a, ts, Phis, refine, n_phi)
    if scheduled or not lower_bound:  # Phi(t, 0) of a schedule is RK4's: no bound between its times
        return ExactMapRadius(ts, rho, rad, t_star, worst)
    lower = linear_lower_bound(ctrl, params, P, C, eps_a, float(rad), t_final, min(n_t, LOWER_BOUND_BOXES))
    return ExactMapRadius(ts, rho, rad, t_star, worst, lower, (float(rad) - lower) / float(rad) if rad > 0 else 0.0)


# time boxes the linear lower bound starts from (they are halved where the bound needs it): one
# block of the boxes' program; the map's own grid (4 points per RK4 step in the pipeline, 14 401
# on the car) is far more than the bound needs
LOWER_BOUND_BOXES = 2048


def linear_lower_bound(
    ctrl, params, P, C, eps_a, rho_up: float, t_final: float, n_t: int, *, rtol: float = 2e-3, max_rounds: int = 16
) -> float:
    r"""A proved lower bound of the exact-map radius of a linear singular set over all of [0, T],
    not only at the grid's times (constant gains).

    Cover [0, T] with time boxes of half-width h centred at :math:`t_c` (``n_t`` of them at
    first). For t in a box and :math:`\|s\| \le \bar\rho` (the attained radius),
    :math:`\|C\zeta(t) - C\zeta(t_c)\| \le \Delta = h\|C\dot\zeta_{ref}(t_c)\| + h^2 G/2
    + \|Ce^{At_c}\|(e^{\|A\|h} - 1)\bar\rho` (C's rows are orthonormal;
    :math:`e^{At} - e^{At_c} = e^{At_c}(e^{A(t - t_c)} - I)`), so an initial error coming
    within eps of the singular set in the box comes within :math:`\epsilon + \Delta` at
    :math:`t_c`, and :func:`min_norm_to_ball` with the inflated margin bounds its norm from
    below. Boxes whose bound is below :math:`(1 - \mathrm{rtol})\bar\rho` are halved, for at
    most ``max_rounds`` rounds (reaching it leaves a wider, still valid, bound). G bounds
    :math:`\|C\ddot\zeta_{ref}\|` over [0, T] (:func:`accel_bound`: proved, by intervals).

    Returns:
      ``min(rho_up, min over boxes)``: every initial error of the slice below it keeps
      :math:`\|C\zeta(t)\| \ge \epsilon` for every t in [0, T].
    """
    if not np.isfinite(rho_up):
        return rho_up
    rho = jnp.asarray(rho_up)
    program = lambda G: lambda tc, hh: _linear_boxes(ctrl, params, P, C, eps_a, rho, G, tc, hh)
    G = jnp.asarray(accel_bound(ctrl, params, t_final, C))
    h = np.full(n_t, 0.5 * t_final / n_t)
    t_c = (np.arange(n_t) + 0.5) * (t_final / n_t)
    closed = rho_up
    for _ in range(max_rounds):
        lb = fixed_blocks(program(G), (t_c, h), BOX_BLOCK)[0]
        done = lb >= (1.0 - rtol) * rho_up
        if done.any():
            closed = min(closed, float(lb[done].min()))
        if done.all():
            return closed
        t_c, h = np.concatenate([t_c[~done] - 0.5 * h[~done], t_c[~done] + 0.5 * h[~done]]), np.tile(0.5 * h[~done], 2)
    return min(closed, float(lb[~done].min()))


@functools.partial(jax.jit, static_argnums=0)
def _linear_boxes(ctrl, params, P, C, eps, rho_up, G, t_c, h):
    r""":func:`linear_lower_bound`'s bound per time box (centre ``t_c``, half-width ``h``), as a
    1-tuple (one Taylor expansion of the reference's outputs gives :math:`\zeta_{ref}` and its
    derivative: no nested autodiff to compile)."""
    A = ctrl.error_matrix(params.gains)
    nA = _math.spectral_norm(A)
    r = ctrl.relative_degree
    ref, g = params.reference, params.geometry
    outputs = lambda s: ctrl.row.extension.outputs(ref.posture(s), g)

    def one(tc, hh):
        jet = taylor(outputs, tc, r)
        z0, z1 = (C @ jet[k : k + r].reshape(-1) for k in range(2))
        CE = C @ _math.expm_small(A * tc)
        move = hh * jnp.linalg.norm(z1) + 0.5 * hh**2 * G + _math.spectral_norm(CE) * jnp.expm1(nA * hh) * rho_up
        return min_norm_to_ball(CE @ P, z0, eps + move)[0]

    return (jax.vmap(one)(t_c, h),)


def _ball_problem(ctrl, params, P, C, t, Phi=None, n_phi=None):
    """``(M, a)`` of the problem at time t: reach ``||a + M s|| <= eps`` with ``M = C Phi(t, 0) P``."""
    a = C @ ctrl.reference_jet(t, params)[: ctrl.relative_degree].reshape(-1)
    if Phi is None:
        Phi = linearize.transition_matrix(params.gains, t, n_steps=n_phi)
    return C @ Phi @ P, a


@functools.partial(jax.jit, static_argnums=(0, 7, 8))
def _exact_map(ctrl, params, P, C, eps, ts, Phis, refine, n_phi):
    """Grid minimum of rho(t), refined by golden section (one compiled program per type and slice shape).
    For a gain schedule ``Phis`` holds Phi(t, 0) on the grid and ``n_phi`` the RK4 steps of one
    Phi(t, 0) off it; for constant gains both are None (expm(A t))."""
    return _exact_map_core(ctrl, params, P, C, eps, ts, Phis, refine, n_phi)


def _exact_map_core(ctrl, params, P, C, eps, ts, Phis, refine, n_phi):
    """:func:`_exact_map`'s body: ``(rho on the grid, radius, its time, its initial error)``."""

    def rho_x(t, Phi=None):
        M, a = _ball_problem(ctrl, params, P, C, t, Phi, n_phi)
        return min_norm_to_ball(M, a, eps)

    if Phis is None:
        rho = jax.vmap(lambda t: rho_x(t)[0])(ts)
    else:
        rho = jax.vmap(lambda t, Phi: rho_x(t, Phi)[0])(ts, Phis)
    i = jnp.argmin(rho)
    lo, hi = ts[jnp.maximum(i - 1, 0)], ts[jnp.minimum(i + 1, ts.shape[0] - 1)]
    lo, hi = _math.golden_section(lambda t: rho_x(t)[0], lo, hi, refine)
    tr = 0.5 * (lo + hi)
    rr, _ = rho_x(tr)
    t_star = jnp.where(rr < rho[i], tr, ts[i])
    rad, xs = rho_x(t_star)
    return rho, rad, t_star, P @ xs


def differentiable_exact_map_radius(
    ctrl: DynamicLinearization,
    params: DynamicParams,
    *,
    t_final: float,
    eps: float,
    basis=Slice.FULL,
    n_t: int = 2001,
    refine: int = 40,
):
    r"""The exact-map radius of a linear singular set as a differentiable function of the gains.

    Its value is :func:`exact_map_radius`'s ``radius`` (the same grid and golden section; no
    rollout). Its gradient is the envelope theorem's, twice: at the minimising time
    :math:`t^*` (the outer minimum over t) and at the minimiser :math:`s^*` of the inner QCQP
    :math:`\min \|s\|^2` s.t. :math:`\|a + M(\theta) s\|^2 \le \epsilon^2`, whose multiplier
    :math:`\nu = -\langle s^*, M^T r\rangle / \|M^T r\|^2` (:math:`r = a + M s^*`) comes from
    stationarity :math:`s^* = -\nu M^T r`. So
    :math:`\partial\rho/\partial\theta = \nu\, r^T (\partial M/\partial\theta)\, s^* / \rho`
    with :math:`M = C\,\Phi(t^*, 0; \theta)\,P` (``expm(A t*)`` for constant gains, RK4 for a
    :class:`wmrjax.GainSchedule`). Where the minimum over t is attained at two times at once
    the radius has a kink and this is one of its one-sided derivatives. Traceable: it runs under
    ``jit``, ``grad`` and ``vmap`` (the eager checks of :func:`exact_map_radius` are left to it).

    Args:
      ctrl: a dynamic closed loop of type (2,0), (2,1) or (1,1) (a linear singular set).
      params: its parameters; the gains in them are what it is differentiated in.
      t_final: horizon T [s].
      eps: the margin.
      basis: slice (:func:`slice_basis`).
      n_t: time grid.
      refine: golden-section iterations.

    Returns:
      A scalar [m, in output-error units]: 0 when the reference itself is within eps, inf when
      no initial error in the slice reaches the singular set (gradient 0 at both).

    Raises:
      ValueError: a static law, or (1,2)'s curved singular set (its radius is a branch and
        bound: :func:`curved_exact_map_radius`).
    """
    rows = singular_rows(ctrl)
    if rows is None:
        raise ValueError(
            f"type {ctrl.robot.name} has a curved singular set: its exact-map radius is a branch and "
            "bound (curved_exact_map_radius, with a proved lower bound), not differentiable"
        )
    P = slice_basis(ctrl, basis)
    C = jnp.eye(ctrl.relative_degree * ctrl.m)[jnp.asarray(rows)]
    ts = np.linspace(0.0, float(t_final), n_t)
    n_phi = transition_steps(t_final) if params.gains.time_varying else None
    frozen = jax.lax.stop_gradient(params)
    Phis = linearize.transition_matrices(frozen.gains, ts, max_step=TRANSITION_STEP) if n_phi is not None else None
    eps = jnp.asarray(eps, jnp.result_type(float))
    _, rad, t_star, worst = _exact_map_core(ctrl, frozen, P, C, eps, jnp.asarray(ts), Phis, refine, n_phi)
    s = P.T @ worst  # s*, in slice coordinates (P orthonormal)
    M0, a0 = _ball_problem(ctrl, frozen, P, C, t_star, None, n_phi)
    g = M0.T @ (a0 + M0 @ s)
    nu = -(s @ g) / jnp.maximum(g @ g, jnp.finfo(g.dtype).tiny)
    M, a = _ball_problem(ctrl, params, P, C, t_star, None, n_phi)  # the live one: gains traced
    lagrange = nu * jnp.sum((a + M @ s) ** 2)
    moving = jnp.isfinite(rad) & (rad > 0)
    step = (lagrange - jax.lax.stop_gradient(lagrange)) / (2.0 * jnp.where(moving, rad, 1.0))
    return rad + jnp.where(moving, step, 0.0)


# --- (1,2): the curved singular set, by branch and bound over (t, phi) ----------------------


def _turn_of_headings(ctrl, params, P, eps_a, t_c, theta_c, phi_width: float):
    """``(rho, x)`` of shapes (n_t, n_phi) and (n_t, n_phi, n): the attained radius at every time
    centre ``t_c`` and a full turn of headings around the reference's ``theta_c`` (an odd number,
    so that the reference's own heading is one of them)."""
    psi_c = np.linspace(-np.pi, np.pi, 2 * int(np.ceil(np.pi / phi_width)) + 1)
    T, Ps = np.meshgrid(t_c, psi_c, indexing="ij")
    centres = (T.ravel(), (Ps + theta_c[:, None]).ravel())
    _, rho, x, _ = _at_centres(ctrl, params, P, eps_a, 0.0, 0.0, *centres)
    return rho.reshape(T.shape), x.reshape(T.shape + (-1,))


def _heading_boxes(t_c, theta_c, h_t: float, half: float, phi_width: float):
    """``(t_lo, t_hi, p_lo, p_hi)``: per time box of width ``h_t`` centred at ``t_c``, heading
    boxes of width <= ``phi_width`` covering ``theta_c +- half`` [rad]."""
    n_phi = int(np.ceil(2 * half / phi_width))
    edges = np.linspace(-half, half, n_phi + 1)
    t_lo, t_hi = np.repeat(t_c - 0.5 * h_t, n_phi), np.repeat(t_c + 0.5 * h_t, n_phi)
    return t_lo, t_hi, (theta_c[:, None] + edges[None, :-1]).ravel(), (theta_c[:, None] + edges[None, 1:]).ravel()


def _split_in_four(t_lo, t_hi, p_lo, p_hi):
    """Every (t, phi) box split at its centre into four."""
    tm, pm = 0.5 * (t_lo + t_hi), 0.5 * (p_lo + p_hi)
    return (
        np.concatenate([t_lo, t_lo, tm, tm]),
        np.concatenate([tm, tm, t_hi, t_hi]),
        np.concatenate([p_lo, pm, p_lo, pm]),
        np.concatenate([pm, p_hi, pm, p_hi]),
    )


# points of the grid on which the reference's m1 is checked (Lemma 2's arguments)
ACCEL_GRID = 4001
# Boxes are evaluated in blocks of this many, the last one padded: the branch and bound's rounds
# have a different number of boxes each (236 to 16 652 on the figure-eight), and one program per
# count recompiled the box bounds at every round (docs/benchmarks.md: the (1,2) certification).
BOX_BLOCK = 2048


def curved_exact_map_radius(
    ctrl: DynamicLinearization,
    params: DynamicParams,
    *,
    t_final: float,
    eps: float,
    basis=Slice.FULL,
    n_t: int = 400,
    phi_width: float = 0.05,
    rtol: float = 2e-3,
    max_rounds: int = 24,
    max_boxes: int = 1 << 18,
) -> ExactMapRadius:
    r"""Exact-map radius of (1,2) with a proved lower bound (branch and bound over (t, phi)).

    The singular set is :math:`\{\sigma_\theta(\zeta) = 0\}` with
    :math:`\sigma_\phi(\zeta) = \cos\phi\,\dot h_1 + \sin\phi\,\dot h_2 + e\sin\delta\,\dot\theta`,
    and :math:`\mathrm{dist}(\zeta, S) = \min_\phi D_\phi(\zeta)`,
    :math:`D_\phi = \|(\phi - \theta,\ \sigma_\phi / \sqrt{1 + e^2\sin^2\delta})\|` (Remark 16).
    For fixed :math:`(t, \phi)`, with :math:`\zeta(t) = \zeta_{ref}(t) + e^{At} P s`, both
    entries of :math:`D_\phi` are affine in s, so the smallest :math:`\|s\|` with
    :math:`D_\phi \le \epsilon` is :func:`min_norm_to_ball`. The radius is its minimum over
    :math:`t \in [0, T]` and :math:`\phi \in \mathbb R`.

    Branch and bound over boxes of :math:`(t, \phi)`: the centre of a box gives an attained
    initial error (an upper bound). For its lower bound, every :math:`(t, \phi)` in the box and
    every s with :math:`\|s\| \le \bar\rho` (the best upper bound) satisfy
    :math:`D_\phi(\zeta(t)) \ge D_{\phi_c}(\zeta(t_c)) - \Delta_t - h_\phi\sqrt{1 + W^2/c}`:
    :math:`D_\phi` is 1-Lipschitz in :math:`\zeta` (its two rows are orthonormal) and
    :math:`\sqrt{1 + W^2/c}`-Lipschitz in :math:`\phi` (W bounds the output point's speed),
    and :math:`\|\zeta(t) - \zeta(t_c)\| \le \Delta_t = h_t\|\dot\zeta_{ref}(t_c)\| + h_t^2 G/2
    + \|e^{At_c}\|(e^{\|A\|h_t} - 1)\bar\rho`. So the problem at the centre with eps inflated
    by those terms bounds the whole box from below. Boxes whose bound reaches
    :math:`(1 - \mathrm{rtol})\bar\rho` are closed; the others are split in four. G bounds
    :math:`\|\ddot\zeta_{ref}\|` over [0, T] (:func:`accel_bound`: proved, by intervals).

    Args:
      ctrl: a (1,2) closed loop (any level).
      params: its parameters.
      t_final: horizon [s].
      eps: the margin.
      basis: slice (:func:`slice_basis`).
      n_t: initial time boxes.
      phi_width: initial heading box width [rad].
      rtol: relative gap at which the search stops.
      max_rounds: rounds of splitting at most (a work limit: reaching it leaves a wider, still
        valid, gap).
      max_boxes: boxes at most (the same).

    Returns:
      :class:`ExactMapRadius` with ``lower_bound``, ``gap`` and ``boxes``.
    """
    check_dynamic(ctrl, params)
    check_lemma2_args(t_final=t_final, eps=eps, reference=params.reference)
    if singular_rows(ctrl) is not None:
        raise ValueError(f"type {ctrl.robot.name} has a linear singular set: use exact_map_radius")
    P = square_basis(slice_basis(ctrl, basis))  # one program per stage for every slice
    eps_a = jnp.asarray(eps, jnp.result_type(float))
    tg = jnp.linspace(0.0, t_final, ACCEL_GRID)
    m1 = m1_closed_form(ctrl, params, tg)
    check_lemma2_args(t_final=t_final, eps=eps, m1=m1)
    G = accel_bound(ctrl, params, t_final)
    t_c, theta_c, ub0, found = _first_upper_bound(ctrl, params, P, eps_a, t_final, n_t, phi_width)
    if not np.isfinite(found[0]):
        raise ValueError("no initial error in this slice brings zeta within eps of the singular set over the horizon")
    # boxes: per time box, headings within reach of theta(t) for errors up to the first upper bound
    reach = _at_centres(ctrl, params, P, eps_a, found[0], G, t_c, np.zeros_like(t_c), h_t=t_final / (2 * n_t))[3]
    half = float(np.max(reach)) + eps + phi_width
    boxes = _heading_boxes(t_c, theta_c, t_final / n_t, half, phi_width)
    limits = dict(rtol=rtol, max_rounds=max_rounds, max_boxes=max_boxes)
    (rho_up, t_best, x_best), lower, evaluated = _branch_and_bound(ctrl, params, P, eps_a, G, boxes, found, **limits)
    worst = jnp.asarray(np.asarray(P) @ x_best)
    grid = (jnp.asarray(t_c), jnp.asarray(ub0.min(axis=1)))
    gap = (rho_up - lower) / rho_up
    return ExactMapRadius(*grid, jnp.asarray(rho_up), jnp.asarray(t_best), worst, lower, gap, evaluated)


def _first_upper_bound(ctrl, params, P, eps_a, t_final: float, n_t: int, phi_width: float):
    """A first upper bound of :func:`curved_exact_map_radius` from box centres over a full turn of
    headings around theta_ref: ``(t_c, theta_c, rho, best)``, the ``n_t`` time centres, the
    reference's heading at them, the attained radius per (time, heading) centre, and the best
    ``(radius, time, slice coordinates)``."""
    t_c = (np.arange(n_t) + 0.5) * (t_final / n_t)
    theta_c = np.asarray(_reference_heading(ctrl, params, jnp.asarray(t_c)))
    ub0, x0 = _turn_of_headings(ctrl, params, P, eps_a, t_c, theta_c, phi_width)
    best = np.unravel_index(int(np.argmin(ub0)), ub0.shape)
    return t_c, theta_c, ub0, (float(ub0[best]), float(t_c[best[0]]), np.asarray(x0[best]))


def _branch_and_bound(ctrl, params, P, eps_a, G, boxes, best, *, rtol, max_rounds, max_boxes):
    """The branch and bound of :func:`curved_exact_map_radius` over the (t, phi) ``boxes``
    ``(t_lo, t_hi, p_lo, p_hi)``, from ``best``, the best attained ``(radius, time, slice
    coordinates)`` so far: boxes whose lower bound reaches ``(1 - rtol)`` times the best radius
    are closed, the others split in four, for at most ``max_rounds`` rounds and while the next
    round has at most ``max_boxes`` boxes. Returns ``(best, lower bound, boxes evaluated)``."""
    rho_up, t_best, x_best = best
    t_lo, t_hi, p_lo, p_hi = boxes
    closed_min = np.inf  # smallest lower bound of the closed boxes
    evaluated = 0
    for _ in range(max_rounds):
        lb, ub, xs = _boxes_in_blocks(ctrl, params, P, eps_a, rho_up, G, (t_lo, t_hi, p_lo, p_hi))
        evaluated += len(lb)
        k = int(np.argmin(ub))
        if ub[k] < rho_up:
            rho_up, t_best, x_best = float(ub[k]), float(0.5 * (t_lo[k] + t_hi[k])), np.asarray(xs[k])
        done = lb >= (1.0 - rtol) * rho_up
        if done.any():
            closed_min = min(closed_min, float(lb[done].min()))
        open_ = ~done
        if not open_.any() or 4 * open_.sum() > max_boxes:
            break
        t_lo, t_hi, p_lo, p_hi = _split_in_four(*(x[open_] for x in (t_lo, t_hi, p_lo, p_hi)))
    lower = min(closed_min, float(lb[open_].min()) if open_.any() else np.inf, rho_up)
    return (rho_up, t_best, x_best), lower, evaluated


def _boxes_in_blocks(ctrl, params, P, eps_a, rho_up: float, G: float, boxes):
    """The branch and bound's ``(t_lo, t_hi, p_lo, p_hi)`` boxes through :func:`_centred_boxes`:
    NumPy ``(lower bound, attained radius at the centre, its slice coordinates)``."""
    t_lo, t_hi, p_lo, p_hi = boxes
    tc, ht, pc, hp = 0.5 * (t_lo + t_hi), 0.5 * (t_hi - t_lo), 0.5 * (p_lo + p_hi), 0.5 * (p_hi - p_lo)
    return _centred_boxes(ctrl, params, P, eps_a, rho_up, G, (tc, ht, pc, hp))[:3]


def _at_centres(ctrl, params, P, eps_a, rho_up: float, G: float, ts, phis, h_t: float = 0.0):
    """:func:`_centred_boxes` at the points ``(ts, phis)`` (boxes of heading width 0 and time
    half-width ``h_t``): the first upper bound (``h_t`` 0: the attained radius at each point) and
    the heading reach of the time boxes (``rho_up`` and ``G`` given) come from the branch and
    bound's own program."""
    ts = np.asarray(ts, dtype=float)
    box = (ts, np.full_like(ts, h_t), np.asarray(phis, dtype=float), np.zeros_like(ts))
    return _centred_boxes(ctrl, params, P, eps_a, rho_up, G, box)


def _centred_boxes(ctrl, params, P, eps_a, rho_up: float, G: float, box):
    """:func:`_curved_boxes` over any number of boxes ``(t_c, h_t, p_c, h_p)`` (NumPy arrays)
    through one compiled program: blocks of :data:`BOX_BLOCK` (:func:`wmrjax.simulate.fixed_blocks`).
    NumPy ``(lower bound, attained radius, slice coordinates, heading reach)``."""
    rho, g = jnp.asarray(float(rho_up)), jnp.asarray(float(G))
    return fixed_blocks(lambda *b: _curved_boxes(ctrl, params, P, eps_a, rho, g, *b), box, BOX_BLOCK)


@functools.partial(jax.jit, static_argnums=0)
def _reference_heading(ctrl, params, ts):
    return jax.vmap(lambda t: ctrl.reference_jet(t, params)[0, 2])(ts)


@functools.partial(jax.jit, static_argnums=0)
def _linear_m1(ctrl, params, C, ts):
    """||C zeta_ref(t)|| on a grid: the distance to a linear singular set {C zeta = 0}."""
    r = ctrl.relative_degree
    return jax.vmap(lambda t: jnp.linalg.norm(C @ ctrl.reference_jet(t, params)[:r].reshape(-1)))(ts)


ACCEL_BOXES = 2048
"""Equal time boxes over which :func:`accel_bound` encloses the reference's output acceleration
(before the cut at a sampled path's knots)."""


def accel_bound(ctrl, params, t_final: float, C=None) -> float:
    r"""A proved bound G of :math:`\|C\ddot\zeta_{ref}(t)\|` at every t of [0, T] (the exact map's
    lower bounds use it in the :math:`h^2` term of a time box's move).

    The reference's output jet up to order r + 1 is enclosed in interval arithmetic
    (:func:`wmrjax.certify.interval.enclose`, outward rounding) over :data:`ACCEL_BOXES` time
    boxes cut at a sampled path's knots, each box its own piece's polynomial
    (:func:`wmrjax.references.time_boxes`); G is the largest box's bound of the norm, rounded up.
    Until 2026-12-07 G was twice the maximum on a 4001-point grid: an estimate, not a bound.

    Args:
      ctrl: the dynamic law.
      params: its parameters.
      t_final: the horizon T [s].
      C: (k, r m) rows applied to :math:`\ddot\zeta_{ref}` (flat, rows of derivative order), or
        None (the identity).

    Returns:
      G (inf where an enclosure is unbounded: the lower bound is then 0).
    """
    n = ctrl.relative_degree * ctrl.m
    C = np.eye(n) if C is None else np.asarray(C, float)
    # G depends on the reference and the geometry only: a tuner's steps and both slices reuse it.
    # The path function itself is in the key (held, so its address is never another's)
    ref = params.reference
    key = (ctrl, float(t_final), ref.path, value_digest((ref, params.geometry, C)))
    if key not in _ACCEL_CACHE:
        if len(_ACCEL_CACHE) >= ACCEL_CACHE_SIZE:
            _ACCEL_CACHE.pop(next(iter(_ACCEL_CACHE)))
        _ACCEL_CACHE[key] = _accel_bound(ctrl, params, t_final, jnp.asarray(C))
    return _ACCEL_CACHE[key]


ACCEL_CACHE_SIZE = 64
"""Bounds :func:`accel_bound` keeps (the oldest dropped first)."""
_ACCEL_CACHE: dict = {}


def value_digest(tree) -> str:
    """A cache key of a pytree of concrete arrays: its structure and every leaf's dtype, shape and
    bytes (the certificates' caches of what depends on the reference only)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    h = hashlib.sha256(str(treedef).encode())
    for x in leaves:
        a = np.asarray(x)
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _accel_bound(ctrl, params, t_final: float, C) -> float:
    """:func:`accel_bound` computed."""
    t_c, h, breaks = time_boxes(params.reference, t_final, ACCEL_BOXES)
    j = box_pieces(breaks, t_c, h)
    # boxes widened by the rounding of their ends: adjacent ones overlap, so their union holds [0, T]
    slack = PIECE_SLACK * max(1.0, t_final)
    lo, hi = t_c - h - slack, t_c + h + slack
    args = (lo, hi) if j is None else (lo, hi, j)
    out = fixed_blocks(lambda *a: _accel_boxes(ctrl, params, C, *a), args, BOX_BLOCK)
    g = float(np.max(out[0]))
    return g * (1.0 + 1e-12) if np.isfinite(g) else np.inf


def _accel_boxes(ctrl, params, C, lo, hi, piece=None):
    """Per time box [lo, hi]: an upper bound of ||C zeta_ref''|| over it (interval enclosure), as a
    1-tuple. Run eagerly, not compiled: the enclosure of the car's order-4 jet did not compile in
    20 minutes (2026-12-07), and op by op over a block of boxes it takes seconds."""
    r = ctrl.relative_degree

    def one(a, b, j):
        p = params if j is None else params._replace(reference=params.reference.piece(j))
        outputs = lambda s: ctrl.row.extension.outputs(p.reference.posture(s), p.geometry)  # reference_jet's
        accel = lambda t: C @ taylor(outputs, t, r + 1)[2 : r + 2].reshape(-1)
        box = interval.enclose(accel, Interval(a, b))
        mag = jnp.maximum(jnp.abs(box.lo), jnp.abs(box.hi))
        return jnp.sqrt(jnp.sum(mag * mag))

    return (jax.vmap(one)(lo, hi, piece),)


def _curved_rows(ctrl, params, t, phi):
    """(zeta_ref(t), zeta_ref'(t), the two unit rows (theta, n_phi) of D_phi), flat (r m,) vectors."""
    r, m = ctrl.relative_degree, ctrl.m
    g = params.geometry
    jet = ctrl.reference_jet(t, params)
    es = g.e * jnp.sin(g.delta)
    n = r * m
    e_th = jnp.zeros(n).at[2].set(1.0)
    n_phi = jnp.zeros(n).at[m].set(jnp.cos(phi)).at[m + 1].set(jnp.sin(phi)).at[m + 2].set(es) / jnp.sqrt(1.0 + es**2)
    return jet[:r].reshape(-1), jet[1 : r + 1].reshape(-1), e_th, n_phi


def _centre_problem(ctrl, params, P, t, phi):
    """(M, a, zeta_ref, zeta_ref', expm(A t)) of the QCQP at (t, phi)."""
    A = ctrl.error_matrix(params.gains)
    zr, zd, e_th, n_phi = _curved_rows(ctrl, params, t, phi)
    E = _math.expm_small(A * t)
    Phi = E @ P
    M = jnp.stack([e_th @ Phi, n_phi @ Phi])
    a = jnp.stack([e_th @ zr - phi, n_phi @ zr])
    return M, a, zr, zd, E


@functools.partial(jax.jit, static_argnums=(0,))
def _curved_boxes(ctrl, params, P, eps, rho_up, G, t_c, h_t, p_c, h_p):
    """Per box (centre ``(t_c, p_c)``, half-widths ``(h_t, h_p)``): the lower bound, the attained
    radius at the centre, its slice coordinates, and how far the heading can move from the
    reference's over the time box for errors up to ``rho_up`` (``|M_0| rho_up + Delta_t``)."""
    A = ctrl.error_matrix(params.gains)
    nA = _math.spectral_norm(A)
    g = params.geometry
    c2 = 1.0 + (g.e * jnp.sin(g.delta)) ** 2
    m = ctrl.m

    def one(tc, ht, pc, hp):
        M, a, zr, zd, E = _centre_problem(ctrl, params, P, tc, pc)
        ub, x = min_norm_to_ball(M, a, eps)
        move = ht * jnp.linalg.norm(zd) + 0.5 * ht**2 * G + _math.spectral_norm(E) * jnp.expm1(nA * ht) * rho_up
        speed = jnp.linalg.norm(zr[m : m + 2]) + _math.spectral_norm((E @ P)[m : m + 2]) * rho_up + move
        lb, _ = min_norm_to_ball(M, a, eps + move + hp * jnp.sqrt(1.0 + speed**2 / c2))
        return jnp.minimum(lb, rho_up), ub, x, jnp.linalg.norm(M[0]) * rho_up + move

    return jax.vmap(one)(t_c, h_t, p_c, h_p)
