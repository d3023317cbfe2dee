r"""A proved radius for a plant that is not the law's model: actuator scales and geometry in a
range, with input limits (issue 54, item 3, the continuous loop).

The law computes with its nominal model; the plant's inputs are the command scaled by
:math:`s` (each :math:`s_i` anywhere in :math:`[\underline s_i, \overline s_i]`, unknown and
possibly different run to run) and its geometry (L and e) is the law's times
:math:`\sigma \in [\underline\sigma, \overline\sigma]`. The law's output jet
:math:`\zeta = \Psi(z)` (its nominal geometry) of the loop's state then obeys

.. math::

    \dot{\tilde\zeta} = A\tilde\zeta + \Delta(t), \qquad
    \Delta = \frac{\partial\Psi}{\partial X}\bigl[f(X, s\odot u, \sigma g) - f(X, u, g)\bigr],

because the law's own field makes :math:`\dot{\tilde\zeta} = A\tilde\zeta` exactly at every
state and the plant differs from it only in :math:`\dot X` (velocity level; the compensator is
the law's). Hence :math:`\tilde\zeta(t) = e^{At}\tilde\zeta(0) + d(t)` with
:math:`d(t) = \int_0^t e^{A(t-\tau)}\Delta(\tau)\,d\tau`: the deviation from the nominal loop
does not grow with the horizon (A is Hurwitz), unlike a Grönwall bound with the loop's
Lipschitz constant, which multiplies by :math:`e^{LT}`.

**The bound.** Take a radius :math:`\rho`, a tube width R and the tube
:math:`\mathcal T = \{(t, e^{At}Ps + d): t \in [0, T], \|s\| \le \rho, \|d\| \le R\}`. Suppose,
over :math:`\mathcal T` and every scale of the ranges, (i) the applied input
:math:`s \odot u` is within the limits, (ii) :math:`\|\Delta\| \le \bar\delta`, and (iii)
:math:`G_T\bar\delta < R` with :math:`G(t) = \int_0^t \|e^{A\tau}\|\,d\tau`. Then a run from
any initial error :math:`Ps`, :math:`\|s\| \le \rho`, stays in the tube with
:math:`\|d(t)\| \le G(t)\bar\delta` (at a first time it left, :math:`\|d\| = R > G_T\bar\delta`,
while up to then the integral gives :math:`\|d\| \le G_T\bar\delta`), never saturates, and
:math:`\|Cd(t)\| \le G_C\bar\delta` with :math:`G_C = \int_0^T \|Ce^{A\tau}\|\,d\tau`. Its
distance to the singular set is at least the nominal one less :math:`G_C\bar\delta`, so the
exact map's proved radius at the margin :math:`\epsilon + G_C\bar\delta`, capped at
:math:`\rho`, is a proved radius of the real loop. (The tube never meets the singular set:
there the command's enclosure is unbounded and (i) fails; so the run keeps the reference's
branch, on which :func:`wmrjax.problem.place` inverts :math:`\Psi`.)

**Computed.** (i) and (ii) by the affine enclosure (:mod:`wmrjax.certify.affine`) of the
command and of :math:`\Delta` per time box, as :func:`wmrjax.certify.saturation_free_radius`
does, with the tube's d (a ball of its own), the scales and :math:`\sigma` as further symbols; R by iterating
:math:`R \leftarrow 1.25\,G_T\bar\delta(\rho, R)` until (iii) holds; :math:`\rho` by bisection on
(i)-(iii) and the exact map's attained radius at the inflated margin; then one proved exact
map at that margin. :math:`G_T` and :math:`G_C` are upper Riemann sums of
:math:`\|e^{A\tau_j}\|e^{\|A\|\eta}` on a grid of step :math:`\eta` (the norm of a matrix
exponential evaluated in float64, with a relative allowance, as the exact map's bounds use).

The bound charges the largest :math:`\|\Delta\|` of the horizon to every time; it is a
bound, and the ratio to the real loop's falsified radius says what it costs.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math, robots
from wmrjax.certify import affine
from wmrjax.certify.exact_map import exact_map_radius, singular_rows, slice_basis, square_basis
from wmrjax.certify.lemma2 import check_dynamic, m1_closed_form
from wmrjax.certify.saturation import BOX_BLOCK, jet_boxes, placed_command, reference_heading, rotated
from wmrjax.controllers.law import Level
from wmrjax.robots import Geometry
from wmrjax.simulate import fixed_blocks

NORM_ALLOWANCE = 1e-9
"""Relative allowance on a float64 matrix exponential's norm (its rounding is ~1e-14)."""
GAIN_GRID = 4096
"""Steps of the Riemann sums of :math:`G_T` and :math:`G_C`."""
TUBE_TRIES = 8
"""Iterations of the tube's radius R per initial radius before that radius counts as not certified."""
TUBE_FACTOR = 1.25
"""R is set to this factor times the deviation bound it must contain (> 1: (iii) is strict)."""


class Mismatch(NamedTuple):
    """The plant's range around the law's model (every value inside it is covered).

    Attributes:
      input_limit: (n_input,) limits on the applied inputs (inf: none).
      input_scale: ``(lo, hi)``, each (n_input,): the applied input is ``s * command``, s_i in [lo_i, hi_i].
      geometry_scale: ``(lo, hi)``: the plant's L and e are the law's times a factor in [lo, hi].
    """

    input_limit: np.ndarray
    input_scale: tuple
    geometry_scale: tuple


class MismatchRadius(NamedTuple):
    """Result of :func:`mismatch_radius` (radii in the slice's output-error units).

    Attributes:
      lower_bound: proved: from every initial error of the slice with norm below it, every run
        of the loop with every plant of the range keeps distance >= eps from the singular set
        over [0, T] and never reaches a limit.
      rate_bound: :math:`\\bar\\delta`, the bound of :math:`\\|\\Delta\\|` over the tube.
      deviation_bound: :math:`G_T\\bar\\delta`: ``||zeta_err(t) - e^{At} zeta_err(0)||`` never exceeds it.
      singular_margin: :math:`G_C\\bar\\delta`, added to eps for the exact map.
      tube: the tube's radius R (a ball around the nominal error).
      gains: ``(G_T, G_C)``.
      tube_radius: the largest radius whose tube passed (i)-(iii) of the module docstring.
      exact_lower_bound: the exact map's proved radius at eps + ``singular_margin``.
      worst_error: (n,) the exact map's worst initial error at that margin (None: none).
      bound_by: ``"exact_map"`` or ``"tube"``: which of the two caps ``lower_bound``.
      boxes: time boxes of the cover.
    """

    lower_bound: float
    rate_bound: float
    deviation_bound: float
    singular_margin: float
    tube: float
    gains: tuple
    tube_radius: float
    exact_lower_bound: float
    worst_error: np.ndarray | None
    bound_by: str
    boxes: int


def deviation_rate(ctrl, params, jet, error, input_scale, geometry_scale, geometry_between=None):
    r"""The rate :math:`\Delta` by which the plant's output error leaves the nominal loop's, and
    the plant's applied input, at the reference jet ``jet`` ((r + 1, m)) and output error
    ``error`` ((r m,)), without limits (velocity level).

    The plant's :math:`\dot X = B(X)u` is linear in u, so the scales' part is exactly
    :math:`B(X, g)((s - 1)\odot u)`; the geometry's part is :math:`(\sigma - 1)\,\partial_\sigma
    B(X, \sigma' g)(s\odot u)` at some :math:`\sigma'` between 1 and :math:`\sigma` (the mean
    value theorem): an enclosure passes ``geometry_between`` as a symbol of that range, so that
    both parts are explicitly proportional to the mismatch; without it the difference is
    evaluated as it is (a point's exact value).

    Returns:
      ``(delta, applied)``: (r m,) :math:`\partial\Psi/\partial X\,[f(X, s\odot u, \sigma g) -
      f(X, u, g)]` and (n_input,) :math:`s \odot u`.
    """
    g, nx, robot = params.geometry, ctrl.robot.n_state, ctrl.robot
    z, u = placed_command(ctrl, params, jet, error)
    X, applied = z[:nx], input_scale * u
    f = lambda uu, sg: robots.kinematic(robot, X, uu, Geometry(L=sg * g.L, e=sg * g.e, delta=g.delta))
    if geometry_between is None:
        d_geometry = f(applied, geometry_scale) - f(applied, 1.0)
    else:
        one = jnp.ones_like(geometry_between)
        d_geometry = (geometry_scale - 1.0) * jax.jvp(lambda sg: f(applied, sg), (geometry_between,), (one,))[1]
    dX = f((input_scale - 1.0) * u, 1.0) + d_geometry
    psi = lambda x: ctrl.law.jet(x, g)[0].reshape(-1)
    delta = jax.jvp(psi, (z,), (jnp.concatenate([dX, jnp.zeros(z.shape[0] - nx, dX.dtype)]),))[1]
    return delta, applied


def gain_integrals(A, C, t_final: float, n: int = GAIN_GRID) -> tuple[float, float]:
    r"""Upper bounds of :math:`\int_0^T \|e^{A\tau}\|d\tau` and :math:`\int_0^T \|Ce^{A\tau}\|d\tau`:
    on :math:`[\tau_j, \tau_j + \eta]`, :math:`\|e^{A\tau}\| \le \|e^{A\tau_j}\| e^{\|A\|\eta}`."""
    eta = t_final / n
    taus = jnp.arange(n, dtype=jnp.float64) * eta
    E = jax.vmap(lambda t: _math.expm_small(A * t))(taus)
    grow = np.exp(float(_math.spectral_norm(A)) * eta) * eta * (1 + NORM_ALLOWANCE)
    full = float(jnp.sum(jax.vmap(_math.spectral_norm)(E))) * grow
    rows = float(jnp.sum(jax.vmap(lambda e: _math.spectral_norm(C @ e))(E))) * grow
    return full, rows


def _n_symbols(ctrl) -> int:
    """Symbols of one evaluation: the initial errors' ball (n), the tube's ball (n), time, the
    input scales, sigma, sigma'."""
    n = ctrl.relative_degree * ctrl.m
    return 2 * n + 1 + ctrl.robot.n_input + 2


@functools.partial(jax.jit, static_argnums=(0, 1))
def _box_rates(ctrl, turn: bool, params, P, limit, scales, jc, jg, je, t_c, h, rho, tube):
    r"""Per time box: the bound of :math:`\|\Delta\|` over the tube, and whether the applied
    input's enclosure fits the limits. ``scales`` is (2, n_input + 1): the input scales' and
    sigma's lower then upper ends. Seen from axes along the reference's heading at the box's
    centre with ``turn`` (:func:`wmrjax.certify.saturation.turns_alike`; a norm does not turn)."""
    A = ctrl.error_matrix(params.gains)
    growth = jnp.expm1(_math.spectral_norm(A) * h)
    n, nu, ns = P.shape[0], ctrl.robot.n_input, _n_symbols(ctrl)
    centre, half = 0.5 * (scales[0] + scales[1]), 0.5 * (scales[1] - scales[0])
    eye = jnp.eye(ns)
    s_in = affine.symbols(centre[:nu], half[:nu, None] * eye[2 * n + 1 : 2 * n + 1 + nu])
    sigma = affine.symbols(centre[nu], half[nu] * eye[ns - 2])
    # sigma' of the mean value theorem: anywhere between 1 and sigma, a symbol of its own
    lo_b, hi_b = jnp.minimum(scales[0, nu], 1.0), jnp.maximum(scales[1, nu], 1.0)
    between = affine.symbols(0.5 * (lo_b + hi_b), 0.5 * (hi_b - lo_b) * eye[ns - 1])

    def one(jet, tc, g, rh, tb):
        E = _math.expm_small(A * tc)
        gen = jnp.concatenate([rh * (E @ P), tb * jnp.eye(n), jnp.zeros((n, 1 + nu + 2))], axis=1)
        err = affine.symbols(jnp.zeros(n), gen)
        slack = jnp.linalg.norm(E, axis=1) * g * rh * (1 + 1e-12) + 1e-15 * rh
        err = affine.Affine(err.c, err.g, err.e + slack)
        phi = reference_heading(ctrl, params, jet.c) if turn else 0.0
        fn = lambda j, e, s, sg, sb: deviation_rate(ctrl, params, *rotated(ctrl, j, e, phi), s, sg, sb)
        (delta, applied), ctx = affine.enclose(fn, jet, err, s_in, sigma, between, n_ball=(n, n))
        d, a = affine.to_interval(delta, ctx), affine.to_interval(applied, ctx)
        mag = jnp.maximum(jnp.abs(d.lo), jnp.abs(d.hi))
        rate = jnp.sqrt(jnp.sum(mag**2)) * (1 + 1e-12)
        fits = jnp.all((a.lo >= -limit) & (a.hi <= limit) & jnp.isfinite(a.lo) & jnp.isfinite(a.hi))
        return jnp.where(jnp.isfinite(rate), rate, jnp.inf), fits

    # the jets' symbols: n (the ball's, zero) then time; the tube's ball goes between
    zeros = lambda k: jnp.zeros(jg.shape[:-1] + (k,))
    jets = affine.Affine(jc, jnp.concatenate([jg[..., :n], zeros(n), jg[..., n:], zeros(nu + 2)], axis=-1), je)
    return jax.vmap(one, (0, 0, 0, None, None))(jets, t_c, growth, rho, tube)


class _Tube:
    """The time boxes' enclosures at a radius and a tube width: :math:`\\bar\\delta` and the limits' check."""

    def __init__(self, ctrl, turn, params, P, mismatch: Mismatch, t_final: float, n_boxes: int):
        self.t_c = (np.arange(n_boxes) + 0.5) * (t_final / n_boxes)
        self.h = np.full(n_boxes, 0.5 * t_final / n_boxes)
        self.jets = fixed_blocks(lambda tc, hh: jet_boxes(ctrl, params, tc, hh), (self.t_c, self.h), BOX_BLOCK)
        lim = np.asarray(mismatch.input_limit, float)
        lim = jnp.asarray(np.where(np.isfinite(lim), lim, np.finfo(float).max))
        ends = [np.append(np.asarray(mismatch.input_scale[k], float), mismatch.geometry_scale[k]) for k in (0, 1)]
        scales = jnp.asarray(np.stack(ends))
        self.program = lambda rho, tube: lambda *a: _box_rates(ctrl, turn, params, P, lim, scales, *a, rho, tube)

    def rate(self, rho: float, tube: float) -> tuple[float, bool]:
        """``(delta_bar, fits)`` over every box at radius ``rho`` and tube width ``tube``."""
        program = self.program(jnp.asarray(rho), jnp.asarray(tube))
        rates, fits = fixed_blocks(program, (*self.jets, self.t_c, self.h), BOX_BLOCK)
        return float(np.max(rates)), bool(np.all(fits))

    def width(self, rho: float, g_t: float) -> tuple[float, float] | None:
        """A tube width R with (i)-(iii) at ``rho`` and its :math:`\\bar\\delta`, or None."""
        delta, fits = self.rate(rho, 0.0)
        for _ in range(TUBE_TRIES):
            if not (fits and np.isfinite(delta)):
                return None
            tube = max(TUBE_FACTOR * g_t * delta, 1e-12)
            delta, fits = self.rate(rho, tube)
            if fits and g_t * delta < tube:
                return tube, delta
        return None


def check_mismatch(ctrl, params, mismatch: Mismatch) -> Mismatch:
    """``mismatch`` with arrays of the right shapes, or ValueError naming what is wrong."""
    check_dynamic(ctrl, params)
    if ctrl.level != Level.VELOCITY:
        raise ValueError(
            f"the mismatch radius covers velocity-level laws (the plant differs from the law in dX/dt only); "
            f"got a {ctrl.level}-level law, whose plant's wheel velocities are a state of their own"
        )
    if params.gains.time_varying:
        raise ValueError("the mismatch radius needs constant gains (the error's transition is e^{At})")
    if singular_rows(ctrl) is None:
        raise ValueError(f"the mismatch radius needs a linear singular set ({ctrl.robot.name}'s is curved)")
    nu = ctrl.robot.n_input
    limit = np.broadcast_to(np.asarray(mismatch.input_limit, float), (nu,))
    ends = []
    for name, pair, width in (
        ("input_scale", mismatch.input_scale, nu),
        ("geometry_scale", mismatch.geometry_scale, None),
    ):
        if len(pair) != 2:
            raise ValueError(f"{name} must be a (lo, hi) pair, got {pair!r}")
        lo, hi = (
            np.asarray(v, float) if width is None else np.broadcast_to(np.asarray(v, float), (width,)) for v in pair
        )
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo > 0) and np.all(lo <= hi)):
            raise ValueError(
                f"{name} must be finite ends 0 < lo <= hi, got {np.asarray(lo).tolist()}, {np.asarray(hi).tolist()}"
            )
        ends.append((lo, hi) if width else (float(lo), float(hi)))
    if np.any(~(limit > 0)):
        raise ValueError(f"input_limit must be > 0 per input (inf: none), got {limit.tolist()}")
    return Mismatch(limit, ends[0], ends[1])


def _check_alike(ctrl, params, t_final: float, seed: int = 0) -> bool:
    """Whether :math:`\\|\\Delta\\|` and the applied input are unchanged when the reference and the
    error are seen from turned axes (then each box is enclosed along its heading), checked at
    random points; and ValueError unless both are unchanged when an angle output of the reference
    turns by 2 pi (the boxes' reference jets are enclosed modulo 2 pi)."""
    rng = np.random.default_rng(seed)
    r, n, nu = ctrl.relative_degree, ctrl.relative_degree * ctrl.m, ctrl.robot.n_input
    angles = tuple(ctrl.law.extension.angle_outputs)
    alike = True
    for t, phi in zip(rng.uniform(0.0, t_final, 4), rng.uniform(-np.pi, np.pi, 4)):
        jet = ctrl.reference_jet(t, params)[: r + 1]
        err, s, sg = (
            jnp.asarray(0.05 * rng.normal(size=n)),
            jnp.asarray(rng.uniform(0.9, 1.1, nu)),
            rng.uniform(0.9, 1.1),
        )
        d, a = (np.asarray(x) for x in deviation_rate(ctrl, params, jet, err, s, sg))
        d2, a2 = (np.asarray(x) for x in deviation_rate(ctrl, params, *rotated(ctrl, jet, err, phi), s, sg))
        alike &= bool(
            np.allclose(a, a2, rtol=1e-8, atol=1e-8)
            and np.isclose(np.linalg.norm(d), np.linalg.norm(d2), rtol=1e-8, atol=1e-10)
        )
        if angles:
            turned = jet.at[0, jnp.asarray(angles)].add(2 * np.pi)
            d3, a3 = (np.asarray(x) for x in deviation_rate(ctrl, params, turned, err, s, sg))
            if not (np.allclose(d, d3, rtol=1e-9, atol=1e-9) and np.allclose(a, a3, rtol=1e-9, atol=1e-9)):
                raise ValueError(
                    f"the {ctrl.robot.name} law's plant rates change when its reference heading turns by 2 pi "
                    f"(at t = {t:g} s): the mismatch radius encloses the reference's angles modulo 2 pi and cannot bound it"
                )
    return alike


def _largest_passing(passes, rho_max: float):
    """Bisection on [0, rho_max] for the largest radius ``passes`` accepts: ``(rho, its tube)``
    (``passes(rho)`` is ``(ok, (R, delta_bar) or None)``; 0 and None where none passes)."""
    ok, w = passes(rho_max)
    if ok:
        return rho_max, w
    lo, hi, w = 0.0, rho_max, None
    for _ in range(BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        ok_mid, w_mid = passes(mid)
        lo, hi = (mid, hi) if ok_mid else (lo, mid)
        if ok_mid:
            w = w_mid
    return lo, w


BISECTION_STEPS = 14
"""Bisection steps of the tube's radius (its relative resolution: 2**-14 of the nominal radius)."""


def mismatch_radius(
    ctrl,
    params,
    mismatch: Mismatch,
    *,
    t_final: float,
    eps: float,
    basis="full",
    n_t: int = 2001,
    n_boxes: int = 512,
    nominal=None,
) -> MismatchRadius:
    """The proved radius of the continuous loop with every plant of ``mismatch`` (module docstring).

    Args:
      ctrl: a dynamic linearizing law at velocity level with constant gains and a linear singular
        set ((2,0), (2,1), (1,1)); params: its parameters.
      mismatch: the plant's range (:class:`Mismatch`).
      t_final: horizon T [s]; eps: the margin to the singular set [zeta units].
      basis: the slice (``"full"``, ``"position"`` or an (n, k) basis).
      n_t: the exact map's time grid; n_boxes: the tube's time boxes.
      nominal: the slice's :class:`wmrjax.certify.ExactMapRadius` at ``eps`` on ``n_t`` times
        when the caller has it (the certification does), else computed here.

    Raises:
      ValueError: a law or a range this bound does not cover, or bad values.
    """
    mismatch = check_mismatch(ctrl, params, mismatch)
    P = slice_basis(ctrl, basis)
    turn = _check_alike(ctrl, params, t_final)
    n = ctrl.relative_degree * ctrl.m
    C = jnp.eye(n)[jnp.asarray(singular_rows(ctrl))]
    g_t, g_c = gain_integrals(ctrl.error_matrix(params.gains), C, t_final)
    if nominal is None or nominal.lower_bound is None:
        nominal = exact_map_radius(ctrl, params, t_final=t_final, eps=eps, basis=basis, n_t=n_t)
    tube = _Tube(ctrl, turn, params, square_basis(P), mismatch, t_final, n_boxes)
    m1 = float(np.min(np.asarray(m1_closed_form(ctrl, params, jnp.linspace(0.0, t_final, n_t)))))

    def exact_at(eps_x, prove: bool):
        """The exact map at margin eps_x (None where the reference itself comes within it)."""
        if eps_x >= m1:
            return None
        return exact_map_radius(ctrl, params, t_final=t_final, eps=eps_x, basis=basis, n_t=n_t, lower_bound=prove)

    def passes(rho):
        w = tube.width(rho, g_t)
        em = None if w is None else exact_at(eps + g_c * w[1], prove=False)  # attained only: cheap
        return em is not None and rho <= float(em.radius), w

    hi, w = _largest_passing(passes, float(nominal.lower_bound))
    if hi <= 0.0 or w is None:
        return MismatchRadius(0.0, np.inf, np.inf, np.inf, np.nan, (g_t, g_c), 0.0, 0.0, None, "tube", n_boxes)
    R, delta = w
    proved = exact_at(eps + g_c * delta, prove=True)
    if proved is None:  # (the bisection's attained radius said otherwise: rounding at the edge)
        return MismatchRadius(0.0, delta, g_t * delta, g_c * delta, R, (g_t, g_c), hi, 0.0, None, "exact_map", n_boxes)
    lower = min(hi, float(proved.lower_bound))
    return MismatchRadius(
        lower,
        delta,
        g_t * delta,
        g_c * delta,
        R,
        (g_t, g_c),
        hi,
        float(proved.lower_bound),
        np.asarray(proved.worst_error),
        "tube" if hi < float(proved.lower_bound) else "exact_map",
        n_boxes,
    )
