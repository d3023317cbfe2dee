r"""A proved radius of a digital controller's loop: its reachable set, one period at a time
(issue 54, item 3).

A problem with a ``control_period`` runs the loop of :func:`wmrjax.controllers.sampled`: at
each sample :math:`t_k = kh` the controller measures the posture with noise
:math:`n_k`, evaluates the law with its nominal geometry and holds the command; between
samples the plant integrates :math:`\operatorname{clip}(s \odot u_k, -\bar u, \bar u)` with its
own geometry (:math:`\sigma` times the law's) and the compensator is held (the digital
integrator advances it by its held rate at the next sample). This module encloses the set of
that loop's states over every initial error of a ball, every noise sequence with
:math:`|n_{k,i}| \le \bar n_i`, every input scale and geometry scale of the plant's ranges,
and every time of the horizon, and certifies a ball when the enclosure stays at least eps from
the singular set. It is the approach of reachability tools for sampled-data systems (the ARCH
competition's unicycle with held controls; JuliaReach, CORA), built on the library's own
affine arithmetic (:mod:`wmrjax.certify.affine`).

**The set.** The loop's state :math:`w = (X, c)` (the plant's posture, and at torque level its
wheel velocities; the compensator) just before a sample is held as an affine form
:math:`w = w_0 + G_b b + G_\kappa \kappa + G_h \eta`: :math:`b` the initial error's symbols (a
unit ball, scaled by the radius: the first-order dependence on the initial error is kept
exactly through the whole run), :math:`\kappa \in [-1, 1]` the plant's scales (kept: they are
the same at every period), :math:`\eta \in [-1, 1]^p` the history (a zonotope's generators).

**One period.** (i) The sample: the law's command, rate and :math:`\det K` at the measured
state :math:`X + n_k` (noise symbols of its own) are enclosed affinely, by the loop's own
:meth:`~wmrjax.controllers.sampled.SampledLoop.sample`, at the reference's jet enclosed before
the reach (:func:`sample_jets`). (ii) The flow: with the input held, the
plant's state is :math:`X(t_k + \tau) = X + \tau F + \tfrac{\tau^2}{2} F' F + R`,
:math:`R \in [0, h^3/6]\,F''(B)` (Taylor's theorem with the Lagrange remainder, componentwise),
where :math:`B` is an a-priori enclosure of the flow over the period: a box with
:math:`X + [0, h] F(B) \subseteq B` (Picard-Lindelöf: the solution cannot leave it). :math:`F`
is the loop's own :meth:`~wmrjax.controllers.sampled.SampledLoop.vector_field`, so the clip is
in it (enclosed exactly where a limit surely does or does not engage, and by the parallel to
its chord across it). (iii) The check: the distance to the singular set of the law's state
:math:`(X(t_k + \tau), c_k)` with :math:`\tau \in [0, h]` a symbol of its own, which must be
at least eps, and the measured :math:`\det K`, which must keep its sign away from the failure
floor. (iv) The next state :math:`(X(t_k + h), c_k + h\,a_k)`; every nonlinear operation's
remainder and the noise's generators join the history, which is reduced back to :math:`p`
generators by boxing the smallest (Girard 2005; an enclosure: every boxed generator's set lies
in the box).

Every step is an enclosure (the affine and interval rules round outward); a period whose
enclosure is unbounded, whose Picard box does not close, or whose check fails fails the ball.
The bound is a proof for every time of :math:`[0, T]`, between samples included. Its cost is
first order in nothing: what it loses is the affine remainders of the law's products over the
ball (second order in its radius) and the boxing of the history; the ratio to the real loop's
falsified radius says how much.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax.certify import affine
from wmrjax.certify import interval as iv
from wmrjax.certify.exact_map import singular_rows, value_digest
from wmrjax.certify.interval import Interval
from wmrjax.certify.saturation import BOX_BLOCK
from wmrjax.controllers import Space, Task, place
from wmrjax.controllers.plant import PlantParams
from wmrjax.controllers.sampled import SampledLoop, SampledParams, SampledState
from wmrjax.references import PIECE_SLACK, enclose_over_pieces, piece_breaks
from wmrjax.robots import Geometry
from wmrjax.simulate import fixed_blocks

HISTORY_PER_STATE = 24
"""The zonotope's history generators per component of the loop's state."""
PICARD_STEPS = 4
"""The a-priori box of a period's flow is tried PICARD_STEPS + 1 times after its first step:
widened until one closes, then narrowed (:func:`_picard_box`)."""
NOISE_BOUND = 3.0
"""The measurement noise a proof covers: each component within this many ``noise_std``."""


class Uncertainty(NamedTuple):
    """The plant a reach covers (every leaf an array: the reach's program does not recompile).

    Attributes:
      limit: (n_input,) input limits (inf: none) [the inputs' units].
      input_scale: (2, n_input) each actuator's scale between row 0 and row 1.
      geometry_scale: (2,) the plant's L and e, between these times the law's.
      noise: (n_X,) the measurement noise's bound per component of X [m, rad].
    """

    limit: Any
    input_scale: Any
    geometry_scale: Any
    noise: Any


class HeldReach(NamedTuple):
    """One ball's reach (arrays; batched over radii where the radius was).

    Attributes:
      ok: whether every period's check passed: the ball is certified.
      distance: a lower bound of the law state's distance to the singular set over [0, T]
        (over the periods reached; -inf where an enclosure was unbounded).
      failed_at: the first period whose check failed (-1: none).
      reason: why it failed (0: it did not; 1: an unbounded enclosure or an open Picard box;
        2: the distance went below eps; 3: the measured det K came within the failure floor or
        changed sign).
      width: the largest radius of the enclosure of the plant's posture over the run [m, rad].
    """

    ok: Any
    distance: Any
    failed_at: Any
    reason: Any
    width: Any


@dataclasses.dataclass(frozen=True)
class SingularDistance:
    """The law state's distance to the singular set in zeta coordinates (static and hashable: the
    loop and the law's nominal geometry as Python floats); ``simulate``'s ``save_fn`` signature."""

    system: Any
    ctrl: Any
    geometry: Any

    def __call__(self, t, z, aux):
        """The distance at the loop's state ``z`` (``t`` and ``aux`` unused)."""
        del t, aux
        zl = self.system.law_state(z)
        jet = self.ctrl.law.jet(zl, self.geometry)[0]
        rows = singular_rows(self.ctrl)
        if rows is None:
            return self.ctrl.row.singular_distance(jet, self.geometry, 1.0)
        flat = jet.reshape(-1)
        # static reads and sqrt(v . v): the same number as a gathered norm, and an enclosure keeps
        # its dependence on the symbols through them (a gather goes through intervals)
        v = jnp.stack([flat[i] for i in rows])
        return jnp.sqrt(jnp.sum(v * v))


class _Layout(NamedTuple):
    """Where each group of symbols sits (columns of the generators)."""

    n_ball: int
    n_kept: int  # the input scales, then the geometry scale
    n_history: int
    n_noise: int

    @property
    def n(self) -> int:
        return self.n_ball + self.n_kept + self.n_history + self.n_noise + 1  # the last: tau

    def cols(self, group: str) -> slice:
        ends = {"ball": 0, "kept": self.n_ball, "history": self.n_ball + self.n_kept}
        ends["noise"] = ends["history"] + self.n_history
        ends["tau"] = ends["noise"] + self.n_noise
        size = dict(ball=self.n_ball, kept=self.n_kept, history=self.n_history, noise=self.n_noise, tau=1)
        return slice(ends[group], ends[group] + size[group])


def _layout(loop: SampledLoop) -> _Layout:
    ctrl = loop.ctrl
    d = loop.n_plant + loop.n_controller
    return _Layout(ctrl.relative_degree * ctrl.m, ctrl.robot.n_input + 1, HISTORY_PER_STATE * d, ctrl.robot.n_state)


def _column_block(values, lay: _Layout, group: str):
    """Generators (len(values), n) with ``values`` on the diagonal of ``group``'s columns."""
    values = jnp.asarray(values, jnp.float64)
    g = jnp.zeros((values.shape[0], lay.n))
    sl = lay.cols(group)
    return g.at[:, sl].set(jnp.diag(values)[:, : sl.stop - sl.start])


def _plant_params(law_params, unc: Uncertainty, s_in, sigma) -> SampledParams:
    g = law_params.geometry
    pg = Geometry(L=sigma * g.L, e=sigma * g.e, delta=g.delta)
    n_x = unc.noise.shape[0]
    return SampledParams(PlantParams(law_params, pg, s_in, unc.limit), jnp.zeros((1, n_x)))


def _scales(unc: Uncertainty, lay: _Layout):
    """The input scales and the geometry scale as affine forms of the kept symbols."""
    lo, hi = jnp.asarray(unc.input_scale[0]), jnp.asarray(unc.input_scale[1])
    glo, ghi = unc.geometry_scale[0], unc.geometry_scale[1]
    kept = jnp.concatenate([0.5 * (hi - lo), jnp.reshape(0.5 * (ghi - glo), (1,))])
    gen = _column_block(kept, lay, "kept")
    s_in = affine.symbols(0.5 * (lo + hi), gen[:-1])
    sigma = affine.symbols(jnp.reshape(0.5 * (glo + ghi), ()), gen[-1])
    return s_in, sigma


def _sampled(loop: SampledLoop, law_params, unc: Uncertainty, t, jet, x, c, noise, s_in, sigma):
    """The loop just after the sample at ``t`` (the reference's jet there: ``jet``) from the true
    plant state ``x``, compensator ``c`` and measurement noise ``noise`` (the loop's own sample,
    fed the measured posture)."""
    sp = _plant_params(law_params, unc, s_in, sigma)
    n_x = loop.robot.n_state
    measured = jnp.concatenate([x[:n_x] + noise, x[n_x:]])
    z = _state(loop, measured, c, t=t)
    return loop.sample(0, t, z, sp, jet)._replace(plant=x), sp


def _state(loop: SampledLoop, plant, controller, command=None, t=0.0) -> SampledState:
    """A loop state with its plant, compensator and held command, the rest zero (a sample
    overwrites them; the held-input field reads only the plant and the command)."""
    nc, ne = loop.n_controller, loop.ctrl.m * loop.ctrl.relative_degree
    command = jnp.zeros(loop.robot.n_input) if command is None else command
    return SampledState(plant, controller, jnp.zeros(nc), t, command, jnp.zeros(()), jnp.zeros(ne))


def _field(loop: SampledLoop, z: SampledState, sp, order: int):
    """The plant's held-input field at ``z`` and its Lie derivatives along itself: d^k X / dt^k,
    k = 1 .. ``order`` (the last one alone)."""
    f = lambda x: loop.vector_field(0.0, z._replace(plant=x), sp)[0].plant
    d = f
    for _ in range(order - 1):
        d = (lambda g: lambda x: jax.jvp(g, (x,), (f(x),))[1])(d)
    return d(z.plant)


def _period_forms(loop, law_params, unc, t, jet, x, c, noise, s_in, sigma):
    """The sample's command, compensator, rate and det K, and the Taylor terms F, F'F at ``x``."""
    z, sp = _sampled(loop, law_params, unc, t, jet, x, c, noise, s_in, sigma)
    return _field(loop, z, sp, 1), _field(loop, z, sp, 2), z.command, z.controller, z.rate, z.regularity


def _held_field(loop, law_params, unc, x, command, s_in, sigma, order: int):
    """d^order X / dt^order of the plant under the held ``command`` (for the interval rules)."""
    sp = _plant_params(law_params, unc, s_in, sigma)
    return _field(loop, _state(loop, x, jnp.zeros(loop.n_controller), command), sp, order)


def _picard_box(loop, law_params, unc, h: float, x0: Interval, held: tuple):
    """A box B with x0 + [0, h] F(B) inside it (the flow of the period stays in B), and whether
    one was found."""
    field = lambda b: iv.enclose(lambda x, *a: _held_field(loop, law_params, unc, x, *a, order=1), b, *held)
    span = Interval(jnp.zeros(()), jnp.asarray(h))
    step = lambda b: iv._add(x0, iv._mul(span, field(b)))
    pick = lambda p, a, b: Interval(jnp.where(p, a.lo, b.lo), jnp.where(p, a.hi, b.hi))

    # one enclosure of the field in a loop (not PICARD_STEPS + 2 copies of it in the program).
    # Pass 0 steps from x0. Until a box closes (step(C) inside C), each pass tries the last step
    # widened by a quarter; after, it tries the last step itself, which is inside the box that
    # closed and, where it closes too, a narrower proof. The box returned is the last one that closed.
    def one(i, carry):
        b, good, found = carry
        r = jnp.maximum(b.hi - b.lo, 1e-12)
        wide = Interval(iv._down(b.lo - 0.25 * r), iv._up(b.hi + 0.25 * r))
        cand = pick(i == 0, x0, pick(found, b, wide))
        nb = step(cand)
        closed = (i > 0) & jnp.all((nb.lo >= cand.lo) & (nb.hi <= cand.hi))
        return nb, pick(closed, cand, good), found | closed

    _, b, found = jax.lax.fori_loop(0, PICARD_STEPS + 2, one, (x0, x0, jnp.asarray(False)))
    return b, found & jnp.all(jnp.isfinite(b.lo) & jnp.isfinite(b.hi))


def _advance(loop: SampledLoop, dist, h: float, x, f1, f2, c, rate, tau, rem):
    """The state at the next sample, and the distance to the singular set at ``t_k + tau``."""
    x_next = x + h * f1 + (0.5 * h * h) * f2 + rem
    x_tau = x + tau * f1 + (0.5 * tau * tau) * f2 + rem
    return x_next, c + h * rate, dist(0.0, _state(loop, x_tau, c), None)


def _reduce(g, e, lay: _Layout):
    """Generators over the layout's symbols with the history, the noise's columns and the
    remainders ``e`` (a box) reduced to ``lay.n_history`` history generators (Girard's order:
    the generators with the smallest ``|g|_1 - |g|_inf`` are boxed)."""
    d = g.shape[0]
    nk = lay.n_ball + lay.n_kept
    rest = jnp.concatenate([g[:, nk:], jnp.diag(e)], axis=1)
    score = jnp.sum(jnp.abs(rest), axis=0) - jnp.max(jnp.abs(rest), axis=0)
    order = jnp.argsort(-score)
    n_top = lay.n_history - d
    boxed = jnp.sum(jnp.abs(rest[:, order[n_top:]]), axis=1)
    # a float sum of q magnitudes is within q ulps of the exact one: rounded up past that
    q = rest.shape[1] - n_top
    boxed = iv._up(boxed * (1 + 2 * (q + 1) * 2.0**-52) + iv._TINY)
    hist = jnp.concatenate([rest[:, order[:n_top]], jnp.diag(boxed)], axis=1)
    out = jnp.zeros((d, lay.n)).at[:, :nk].set(g[:, :nk])
    return out.at[:, lay.cols("history")].set(hist)


class _Carry(NamedTuple):
    k: Any
    centre: Any
    gens: Any
    sign: Any
    ok: Any
    failed_at: Any
    reason: Any
    distance: Any
    width: Any


def _split(centre, gens, n: int):
    zero = jnp.zeros(centre.shape[0])
    a = affine.Affine(centre, gens, zero)
    return affine.Affine(*(v[:n] for v in a)), affine.Affine(*(v[n:] for v in a))


SAMPLE_TIME_ROUNDING = 2.0**-50
"""Relative half-width of the time box around a sample's time :math:`kh` in which the
reference's jet is enclosed: a run computes that time in floats (a product or a short sum, a
few ulps of it, each 2^-53 relative)."""


def sample_jets(ctrl, law_params, h: float, n_periods: int) -> Interval:
    """The reference's jet at each sample time :math:`kh`, ``k < n_periods``, enclosed in interval
    arithmetic over a box of :data:`SAMPLE_TIME_ROUNDING` around it (and a few times
    :data:`wmrjax.references.PIECE_SLACK` of the horizon), pinned to its piece of a sampled path:
    a sample on a knot, where a run may read either piece, is the hull of both.

    Args:
      ctrl: the dynamic law.
      law_params: its parameters (the reference).
      h: the controller period [s].
      n_periods: samples.

    Returns:
      :class:`Interval` of shape (n_periods, r + 1, m), kept by the reference's and geometry's
      values (the jets do not depend on the gains: both slices and a tuner's accepted steps reuse
      them; 1.6 s a call on the S-path).
    """
    ref = law_params.reference
    # the path function itself is in the key (held, so its address is never another's)
    key = (ctrl, float(h), int(n_periods), ref.path, value_digest((ref, law_params.geometry)))
    if key not in _JET_CACHE:
        if len(_JET_CACHE) >= JET_CACHE_SIZE:
            _JET_CACHE.pop(next(iter(_JET_CACHE)))
        _JET_CACHE[key] = _sample_jets(ctrl, law_params, h, n_periods)
    return _JET_CACHE[key]


JET_CACHE_SIZE = 16
"""Sample jets :func:`sample_jets` keeps (the oldest dropped first)."""
_JET_CACHE: dict = {}


def _sample_jets(ctrl, law_params, h: float, n_periods: int) -> Interval:
    """:func:`sample_jets` computed."""
    t = np.arange(n_periods) * h
    # wider than the slack by which a box may pass its piece's ends (PIECE_SLACK: the rounding of
    # boxes that tile the horizon, whose neighbours cover it; these do not tile it)
    half = SAMPLE_TIME_ROUNDING * np.maximum(t, h) + 4.0 * PIECE_SLACK * max(1.0, n_periods * h)
    boxes = lambda rows, j: (t[rows] - half[rows], t[rows] + half[rows]) + (() if j is None else (j,))
    enclose = lambda rows, j: fixed_blocks(lambda *a: _jet_boxes(ctrl, law_params, *a), boxes(rows, j), BOX_BLOCK)
    breaks = piece_breaks(law_params.reference, float(t[-1] + half[-1]))
    if breaks is None:
        lo, hi = enclose(np.arange(n_periods), None)
    else:
        hull = lambda a, b: (np.minimum(a[0], b[0]), np.maximum(a[1], b[1]))
        lo, hi = enclose_over_pieces(enclose, hull, breaks, t, half)
    return Interval(jnp.asarray(lo), jnp.asarray(hi))


def _jet_boxes(ctrl, law_params, lo, hi, piece=None):
    """Per time box [lo, hi]: the reference's jet enclosed (interval arithmetic; ``piece``: each
    box's piece's polynomial). Run eagerly, not compiled, as the exact map's G
    (:func:`wmrjax.certify.exact_map.accel_bound`): compiled, the S-path's took 68 s (2026-12-08)."""

    def one(a, b, j):
        p = law_params if j is None else law_params._replace(reference=law_params.reference.piece(j))
        return tuple(iv.enclose(lambda tt: ctrl.reference_jet(tt, p), Interval(a, b)))

    return jax.vmap(one)(lo, hi, piece)


def _period(loop, law_params, unc, dist, lay: _Layout, h: float, eps, floor, jets: Interval, s: _Carry) -> _Carry:
    """One controller period of the reach (module docstring, (i)-(iv)); ``jets``: :func:`sample_jets`."""
    t = s.k * h
    x, c = _split(s.centre, s.gens, loop.n_plant)
    noise = affine.symbols(jnp.zeros(loop.robot.n_state), _column_block(unc.noise, lay, "noise"))
    s_in, sigma = _scales(unc, lay)
    forms = functools.partial(_period_forms, loop, law_params, unc)
    jet = Interval(jets.lo[s.k], jets.hi[s.k])
    (f1, f2, u, cc, rate, reg), ctx = affine.enclose(forms, t, jet, x, c, noise, s_in, sigma, n_ball=lay.n_ball)
    box = lambda a: affine.to_interval(a, ctx)
    held = (box(u), box(s_in), box(sigma))
    b, closed = _picard_box(loop, law_params, unc, h, box(x), held)
    third = iv.enclose(lambda xx, *a: _held_field(loop, law_params, unc, xx, *a, order=3), b, *held)
    rem = iv._mul(Interval(jnp.zeros(()), jnp.asarray(h**3 / 6)), third)
    tau = affine.symbols(jnp.asarray(h / 2), _column_block(jnp.asarray([h / 2]), lay, "tau")[0])
    adv = functools.partial(_advance, loop, dist, h)
    (xn, cn, d), ctx2 = affine.enclose(adv, x, f1, f2, cc, rate, tau, rem, n_ball=lay.n_ball)
    r = box(reg)
    sign = jnp.where(s.k == 0, jnp.sign(reg.c), s.sign)
    reg_ok = jnp.where(sign > 0, r.lo > floor, r.hi < -floor)
    d_lo = affine.to_interval(d, ctx2).lo
    centre = jnp.concatenate([xn.c, cn.c])
    g, e = jnp.concatenate([xn.g, cn.g]), jnp.concatenate([xn.e, cn.e])
    finite = closed & jnp.all(jnp.isfinite(centre)) & jnp.all(jnp.isfinite(g)) & jnp.all(jnp.isfinite(e))
    reason = jnp.where(~finite, 1, jnp.where(~(d_lo >= eps), 2, jnp.where(~reg_ok, 3, 0)))
    ok = reason == 0
    width = jnp.max(affine.rad(x, ctx)[: loop.robot.n_state])
    return _Carry(
        s.k + 1,
        jnp.where(ok, centre, s.centre),
        jnp.where(ok, _reduce(g, e, lay), s.gens),
        sign,
        ok,
        jnp.where(ok, -1, s.k),
        reason,
        jnp.minimum(s.distance, jnp.where(finite, d_lo, -jnp.inf)),
        jnp.maximum(s.width, width),
    )


def _initial(loop: SampledLoop, law_params, unc, lay: _Layout, branch: float, P, rho):
    """The loop's state at t = 0 over the ball ``rho P b`` of initial output errors (placed on the
    reference's branch, as a run places it): centre and generators (remainders in the history)."""
    ball = affine.symbols(jnp.zeros(lay.n_ball), rho * _column_block(jnp.ones(lay.n_ball), lay, "ball"))
    s_in, sigma = _scales(unc, lay)

    def state(b, s_in, sigma):
        zl = place(loop.ctrl, law_params, P @ b, Space.OUTPUT, Task.POSTURE, branch)
        z = loop.initial_state(zl, _plant_params(law_params, unc, s_in, sigma))
        return jnp.concatenate([z.plant, z.controller])

    w, _ = affine.enclose(state, ball, s_in, sigma, n_ball=lay.n_ball)
    return w.c, _reduce(w.g, w.e, lay)


@functools.partial(jax.jit, static_argnums=(0, 2, 3, 4, 5))
def held_reach(
    loop: SampledLoop, law_params, dist, branch: float, h: float, n_periods: int, P, rho, unc, eps, floor, jets
):
    """The reach of ``loop`` from the initial output errors ``rho P b``, ``|b| <= 1``, over
    ``n_periods`` periods of ``h`` [s], for every plant of ``unc`` (:class:`Uncertainty`).

    Args:
      loop: the sampled loop (:func:`wmrjax.controllers.sampled`).
      law_params: the law's parameters (its nominal geometry, gains, reference).
      dist: the distance to the singular set (:class:`SingularDistance`).
      branch: the reference's branch (+1 or -1), as runs are placed.
      h: the controller period [s].
      n_periods: the horizon in periods.
      P: (r m, r m) the slice's basis (columns beyond the slice's dimension zero).
      rho: () the ball's radius (the initial error's norm in P's coordinates).
      unc: the plant's :class:`Uncertainty`.
      eps: the distance to keep.
      floor: the failure floor of the measured det K.
      jets: the reference's jet at the samples (:func:`sample_jets`).

    Returns:
      :class:`HeldReach`.
    """
    lay = _layout(loop)
    centre, gens = _initial(loop, law_params, unc, lay, branch, P, rho)
    inf = jnp.asarray(jnp.inf)
    s0 = _Carry(
        jnp.asarray(0), centre, gens, jnp.zeros(()), jnp.asarray(True), jnp.asarray(-1), jnp.asarray(0), inf, -inf
    )
    step = functools.partial(_period, loop, law_params, unc, dist, lay, h, eps, floor, jets)
    out = jax.lax.while_loop(lambda s: s.ok & (s.k < n_periods), step, s0)
    return HeldReach(out.ok, out.distance, out.failed_at, out.reason, out.width)


@functools.partial(jax.jit, static_argnums=(0, 2, 3, 4, 5))
def reach_radii(
    loop: SampledLoop, law_params, dist, branch: float, h: float, n_periods: int, P, radii, unc, eps, floor, jets
):
    """:func:`held_reach` at each of ``radii`` ((k,)) side by side (one program per loop and count
    of radii: both slices of a problem share it)."""
    one = lambda r: held_reach(loop, law_params, dist, branch, h, n_periods, P, r, unc, eps, floor, jets)
    return jax.vmap(one)(radii)


class HeldReachRadius(NamedTuple):
    """Result of :func:`held_reach_radius`: a proved radius of a digital controller's loop.

    Attributes:
      radius: the largest radius whose reach passed (0.0: none did): proved for every initial
        error of the slice's ball, every plant of the range, every noise sequence within the bound.
      distance: the reach's lower bound of the distance to the singular set at ``radius`` (None
        when none passed).
      failed_radius: the smallest radius tried whose reach failed (None: every one passed).
      failed_at: the time [s] of the period where it failed.
      reason: why (:class:`HeldReach`'s codes, as words).
      noise_bound: the noise it covers, per component of X [m, rad] (``noise_multiple`` times the
        problem's ``noise_std``).
      noise_multiple: that multiple.
      periods: the horizon in controller periods.
      reaches: balls enclosed.
    """

    radius: float
    distance: float | None
    failed_radius: float | None
    failed_at: float | None
    reason: str | None
    noise_bound: list
    noise_multiple: float
    periods: int
    reaches: int

    def summary(self) -> dict:
        """Plain JSON."""
        return {k: (float(v) if isinstance(v, np.floating) else v) for k, v in self._asdict().items()}


REASONS = {
    1: "an enclosure became unbounded (or a period's Picard box did not close)",
    2: "distance below eps",
    3: "det K at a sample within the failure floor",
}
ROUNDS = 2
"""Refinement rounds of the radius search after its first, geometric, one."""
PER_ROUND = 8
"""Radii enclosed side by side per round (one vmapped program, the same shape every round: one compile)."""


def uncertainties(setting, noise_multiple: float = NOISE_BOUND) -> list:
    """The plant range of ``setting``'s ``[plant]`` as :class:`Uncertainty` values, one per distinct
    listed input limit (the clip is in the enclosed loop, so each limit is its own loop; the
    scales are ranges between their listed values' smallest and largest)."""
    pv = setting.axis("plant").payload
    nu = setting.ctrl.robot.n_input
    limits = np.unique(np.asarray(pv["limit"], float).reshape(-1, nu), axis=0)
    scale = np.asarray(pv["input_scale"], float).reshape(-1, nu)
    geo = np.asarray(pv["geometry_scale"], float).reshape(-1)
    noise = noise_multiple * np.asarray(setting.noise_std or np.zeros(setting.ctrl.robot.n_state), float)
    return [
        Uncertainty(
            jnp.asarray(lim),
            jnp.asarray(np.stack([scale.min(0), scale.max(0)])),
            jnp.asarray([geo.min(), geo.max()]),
            jnp.asarray(noise),
        )
        for lim in limits
    ]


def held_reach_radius(
    setting,
    params,
    P,
    *,
    eps: float,
    r_max: float,
    noise_multiple: float = NOISE_BOUND,
    margin_floor: float = 1e-9,
    log=None,
) -> HeldReachRadius:
    """The largest radius (to the search's resolution) whose :func:`held_reach` passes on every
    distinct limit of ``setting``'s plant (a digital controller's loop: ``control_period`` set).

    Args:
      setting: the problem's :class:`wmrjax.problem.Setting`.
      params: the law's parameters.
      P: (r m, k) the slice's basis (:func:`wmrjax.certify.slice_basis`).
      eps: the distance to the singular set to keep.
      r_max: the largest radius tried (the nominal exact map's: no larger one can hold).
      noise_multiple: the noise covered, in multiples of ``noise_std`` (default 3).
      margin_floor: the runs' failure floor of det K.
      log: a progress callback, or None.

    Returns:
      :class:`HeldReachRadius`.
    """
    loop, ctrl = setting.system(), setting.ctrl
    if not isinstance(loop, SampledLoop):
        raise ValueError("held_reach_radius needs a problem with a control_period (a digital controller's loop)")
    n = ctrl.relative_degree * ctrl.m
    P = np.asarray(P, float)
    Pn = jnp.asarray(np.concatenate([P, np.zeros((n, n - P.shape[1]))], axis=1))
    g = params.geometry
    dist = SingularDistance(loop, ctrl, type(g)(*(float(v) for v in g)))
    h, periods = float(setting.control_period), setting.n_steps // setting.steps_per_sample
    branch = float(ctrl.reference_branch(params))
    uncs = uncertainties(setting, noise_multiple)
    jets = sample_jets(ctrl, params, h, periods)

    def passes(radii):
        args = (loop, params, dist, branch, h, periods, Pn, jnp.asarray(radii))
        outs = [reach_radii(*args, u, eps, margin_floor, jets) for u in uncs]
        ok = np.all([np.asarray(o.ok) for o in outs], axis=0)
        return ok, outs

    lo, hi, best, fail, count = 0.0, None, None, None, 0
    radii = r_max * 0.5 ** np.arange(PER_ROUND - 1, -1, -1.0)
    for rnd in range(ROUNDS + 1):
        ok, outs = passes(radii)
        count += len(radii) * len(uncs)
        for i, r in enumerate(radii):
            if ok[i] and r > lo:
                lo, best = r, min(float(o.distance[i]) for o in outs)
            if not ok[i] and (hi is None or r < hi):
                hi = r
                k = next(j for j, o in enumerate(outs) if not bool(o.ok[i]))
                fail = (float(outs[k].failed_at[i]) * h, REASONS.get(int(outs[k].reason[i]), "?"))
        if log is not None:
            log(f"  held reach: round {rnd}: proved {lo:.4g}, failed {hi}")
        if hi is None:
            break
        radii = lo + (hi - lo) * np.arange(1, PER_ROUND + 1) / (PER_ROUND + 1)
    return HeldReachRadius(
        float(lo),
        best,
        hi,
        None if fail is None else fail[0],
        None if fail is None else fail[1],
        [float(v) for v in np.asarray(uncs[0].noise)],
        float(noise_multiple),
        int(periods),
        count,
    )
