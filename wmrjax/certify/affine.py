r"""Affine enclosures of a JAX function: a first-order-tight bound over a ball of inputs.

An :class:`Affine` value is :math:`x = c + \sum_i g_i \varepsilon_i + e\,\varepsilon_0` with
symbols :math:`\varepsilon` shared by every value of one evaluation: the first ``n_ball``
symbols lie in the Euclidean unit ball (an initial error ``s = rho * eps`` of a certificate's
ball), the others in [-1, 1] (time in a box), and :math:`\varepsilon_0` is a fresh symbol per
value (:math:`|\varepsilon_0| \le 1`) collecting everything not kept linear. Linear operations are exact in the
symbols; a smooth function is replaced by its tangent at the centre plus its Taylor remainder
over the value's range (:math:`\tfrac12 f''(\xi)\,\delta^2` with :math:`\delta^2 \in [0,
\mathrm{rad}^2]`: signed where :math:`f''` keeps its sign, its midpoint joining the centre),
or, for sqrt and the reciprocal, by the chord's (Chebyshev) form where that is the narrower (a
wide range, over which the curvature's worst point would be charged everywhere); a
product keeps both first-order terms and bounds the second-order one by the product of the radii
(a ball's quadratic form and a box symbol's square :math:`\varepsilon_i^2 \in [0, 1]` are
enclosed by their own ranges).
This is affine arithmetic (Comba & Stolfi 1993; de Figueiredo & Stolfi 2004), here with a ball
of symbols, so dependencies between the many uses of one initial error cancel to first order,
where plain intervals (:mod:`wmrjax.certify.interval`) multiply them.

Rounding: every operation adds :data:`ROUNDING` times the magnitude of its result's terms
(and elementary functions their ulp budget, as in the interval module) to ``e``. Operations
without an affine rule (comparisons, ``floor``, ``rem``, integer arithmetic) go through the
interval rules on the value's range; a ``select_n`` whose predicate is decided keeps the chosen
branch's affine form.
"""

from __future__ import annotations

import itertools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from wmrjax import _math
from wmrjax.certify import interval as iv
from wmrjax.certify.interval import Interval

ROUNDING = 16 * 2.0**-52
"""Relative rounding allowance per affine operation (a few operations of 1 ulp each, with margin)."""


class Affine(NamedTuple):
    """``c + g @ eps + e eps_0`` (every entry of ``c`` its own form; ``g`` has a trailing axis
    of one column per symbol; ``e >= 0``)."""

    c: Any
    g: Any  # (*c.shape, n): one column per symbol
    e: Any


class _Context(NamedTuple):
    balls: tuple  # sizes of the consecutive groups of symbols from the first, each in a unit ball; the rest: [-1, 1]
    n: int
    parts: dict  # id(value) -> (value, its _parts): each value's radii emitted once per trace


def rad(a: Affine, ctx: _Context):
    """Largest ``|x - c|`` over the symbols' set."""
    nb, rest = _parts(a, ctx)
    return jnp.sum(nb, axis=-1) + rest


def to_interval(a, ctx: _Context) -> Interval:
    """The range of an :class:`Affine` value (an :class:`Interval` is its own)."""
    if isinstance(a, Interval):
        return a
    r = rad(a, ctx)
    return Interval(iv._down(a.c - r), iv._up(a.c + r))


def _point(x, ctx: _Context) -> Affine:
    x = jnp.asarray(x)
    z = jnp.zeros_like(x)
    return Affine(x, jnp.zeros(x.shape + (ctx.n,), x.dtype), z)


def _from_interval(b: Interval, ctx: _Context) -> Affine:
    c = b.mid
    # an unbounded box is the whole line: its centre is 0 and its radius inf
    c = jnp.where(jnp.isfinite(c), c, 0.0)
    return Affine(c, jnp.zeros(c.shape + (ctx.n,), c.dtype), iv._up(jnp.maximum(b.hi - c, c - b.lo)))


def _rounding(c, g, e):
    mag = jnp.abs(c) + jnp.sum(jnp.abs(g), axis=-1)
    e = e + ROUNDING * mag + iv._TINY
    return jnp.where(jnp.isnan(e), jnp.inf, e)  # NaN (inf - inf, 0 * inf): nothing is known


def _make(c, g, e) -> Affine:
    return Affine(c, g, _rounding(c, g, e))


def _where(p, a: Affine, b: Affine) -> Affine:
    """``a`` where ``p``, else ``b`` (entrywise, the generators along)."""
    return Affine(jnp.where(p, a.c, b.c), jnp.where(p[..., None], a.g, b.g), jnp.where(p, a.e, b.e))


def _unbounded_where(bad, a: Affine) -> Affine:
    """``a``, with the entries where ``bad`` unbounded (centre 0, no generators, e = inf)."""
    return Affine(jnp.where(bad, 0.0, a.c), jnp.where(bad[..., None], 0.0, a.g), jnp.where(bad, jnp.inf, a.e))


def _add(a, b):
    return _make(a.c + b.c, a.g + b.g, a.e + b.e)


def _sub(a, b):
    return _make(a.c - b.c, a.g - b.g, a.e + b.e)


def _neg(a):
    return Affine(-a.c, -a.g, a.e)


def _scale(a, k, extra=0.0):
    """``k * a`` (k an array of the value's shape) plus ``extra`` in ``e``."""
    return _make(k * a.c, k[..., None] * a.g, jnp.abs(k) * a.e + extra)


def _ball_slices(ctx: _Context) -> list:
    """The column slices of the balls' symbols."""
    ends = [0, *itertools.accumulate(ctx.balls)]
    return [slice(lo, hi) for lo, hi in zip(ends[:-1], ends[1:])]


def _parts(a: Affine, ctx: _Context):
    """``(each ball's generators' norm, stacked on a last axis; box generators' sum of magnitudes + e)``."""
    hit = ctx.parts.get(id(a))
    if hit is not None and hit[0] is a:
        return hit[1]
    norms = [jnp.sqrt(jnp.sum(a.g[..., sl] ** 2, axis=-1)) for sl in _ball_slices(ctx)]
    nb = jnp.stack(norms or [jnp.zeros(a.c.shape)], axis=-1) * (1 + 2.0**-50)
    rest = jnp.sum(jnp.abs(a.g[..., sum(ctx.balls) :]), axis=-1) + a.e
    ctx.parts[id(a)] = (a, (nb, rest))  # the value is kept alive with its entry: ids stay unique
    return nb, rest


def _mul(a, b, ctx):
    r"""Product: a ball's quadratic form x^T (g_a g_b^T) x over its unit ball lies in
    [(g_a.g_b - |g_a||g_b|) / 2, (g_a.g_b + |g_a||g_b|) / 2]: its midpoint joins the centre;
    over the box symbols the diagonal terms :math:`g_i h_i \varepsilon_i^2` lie in
    :math:`[\min(g_i h_i, 0), \max(g_i h_i, 0)]` (their midpoint joins the centre, half their
    magnitude is kept of the bound) and the others by the product of the magnitudes; the
    products across groups, and with the error terms, are bounded by their norms."""
    na, ra = _parts(a, ctx)
    nb, rb = _parts(b, ctx)
    nbs = sum(ctx.balls)
    dot = jnp.sum(a.g[..., :nbs] * b.g[..., :nbs], axis=-1)
    diag = a.g[..., nbs:] * b.g[..., nbs:]
    box_dot, box_same = jnp.sum(diag, axis=-1), jnp.sum(jnp.abs(diag), axis=-1)
    sa, sb = jnp.sum(na, axis=-1), jnp.sum(nb, axis=-1)
    same = jnp.sum(na * nb, axis=-1)
    # (an inf radius times 0 gives NaN: _make turns it into e = inf, "nothing known")
    bound = 0.5 * same + (sa * sb - same) + sa * rb + ra * (sb + rb)
    # ra rb >= the box magnitudes' sum: no cancellation; rounded past the difference's ulps
    quad = iv._up(bound * (1 + 2.0**-49) - 0.5 * box_same * (1 - 2.0**-49))
    g = a.c[..., None] * b.g + b.c[..., None] * a.g
    e = jnp.abs(a.c) * b.e + jnp.abs(b.c) * a.e + quad
    return _make(a.c * b.c + 0.5 * (dot + box_dot), g, e)


def _smooth(a, ctx, f, df, d2, chord=None):
    r"""``f(a)``: the tangent at the centre plus Taylor's remainder :math:`\tfrac12 f''(\xi)\delta^2`,
    :math:`\delta^2 \in [0, \mathrm{rad}^2]`: with ``d2(box)`` an :class:`Interval` holding
    :math:`f''` on the range, the remainder lies in
    :math:`[\tfrac12 \min(m, 0)\,\mathrm{rad}^2, \tfrac12 \max(M, 0)\,\mathrm{rad}^2]`; its
    midpoint joins the centre and its half-width the error (half the symmetric bound's where
    :math:`f''` keeps its sign: the tangent lies on one side of a convex function).

    With ``chord`` (:func:`_chord`'s ``tangent`` and ``side``), where the range is wide the chord's
    form is taken instead where its radius is the smaller: Taylor's remainder charges the
    curvature's worst point (sqrt near its range's low end) to the whole range."""
    r = rad(a, ctx)
    box = to_interval(a, ctx)
    c = f(a.c)
    curv = d2(box)
    half = iv._up(0.5 * r * r * (1 + 2.0**-49))  # with the curvature's own rounding
    lo, hi = half * jnp.minimum(curv.lo, 0.0), half * jnp.maximum(curv.hi, 0.0)
    shift = 0.5 * (lo + hi)
    out = _scale(a, df(a.c), iv._up(0.5 * (hi - lo)))
    e = out.e + iv._REL * jnp.abs(c)  # the elementary function's own ulps at the centre
    e = e + 2.0**-52 * jnp.abs(shift)  # the shift's own rounding (_make's allowance covers the sum)
    bad = ~jnp.isfinite(e) | ~jnp.isfinite(c) | ~jnp.isfinite(shift)
    out = _make(c + shift, out.g, e)
    out = _unbounded_where(bad, out)
    if chord is None:
        return out
    alt = _chord(a, box, f, df, *chord)
    take = rad(alt, ctx) < rad(out, ctx)  # both enclose f(a): either is sound, the narrower is kept
    return _where(take, alt, out)


def _chord(a, box: Interval, f, df, tangent, side):
    r"""``f(a)`` as :math:`\alpha a + [\beta_-, \beta_+]` with :math:`\alpha` the chord's slope over
    the range :math:`[l, u]` (the Chebyshev form of affine arithmetic, de Figueiredo & Stolfi 2004)
    where ``side(box)`` says f is convex (+1) or concave (-1) there (0: not known; the form is then
    unbounded). For convex f, :math:`g = f - \alpha x` is largest at an end, and
    :math:`g \ge g(x^*) - |g'(x^*)|\,(u - l)` for any :math:`x^*` of the range (its tangent
    there lies below it): with :math:`x^* =` ``tangent(alpha)`` clipped to the range (where
    :math:`f' = \alpha`, so the term is the rounding's) the bound is the chord's own. Every
    evaluation of f and f' is charged its ulps, and the slope may be any float: the bounds are
    computed for the slope used."""
    s = side(box)
    # f is evaluated only where the range is in its domain (elsewhere at 1, and the form is
    # discarded): no NaN in either branch of the choice, nor in its gradient
    one = jnp.ones_like(box.lo)
    l, u = jnp.where(s != 0, box.lo, one), jnp.where(s != 0, box.hi, one)
    fl, fu = f(l), f(u)
    width = u - l
    alpha = jnp.where(width > 0, (fu - fl) / jnp.where(width > 0, width, 1.0), df(l))
    xs = jnp.clip(tangent(alpha), l, u)
    fx = f(xs)
    slop = lambda fv, x: iv._REL * jnp.abs(fv) + 2.0**-50 * (jnp.abs(fv) + jnp.abs(alpha * x))
    gl, gu, gx = fl - alpha * l, fu - alpha * u, fx - alpha * xs
    ends_hi = jnp.maximum(gl + slop(fl, l), gu + slop(fu, u))
    ends_lo = jnp.minimum(gl - slop(fl, l), gu - slop(fu, u))
    reach = (jnp.abs(df(xs) - alpha) + iv._REL * jnp.abs(df(xs))) * width * (1 + 2.0**-49) + slop(fx, xs)
    b_lo = jnp.where(s > 0, gx - reach, ends_lo)
    b_hi = jnp.where(s > 0, ends_hi, gx + reach)
    mid = 0.5 * (b_lo + b_hi)
    halfw = iv._up(0.5 * (b_hi - b_lo) + 2.0**-52 * jnp.abs(mid))
    out = _scale(a, alpha, halfw)
    out = _make(out.c + mid, out.g, out.e + 2.0**-52 * jnp.abs(out.c + mid))
    bad = (s == 0) | ~jnp.isfinite(out.e) | ~jnp.isfinite(out.c) | ~(width >= 0)
    return _unbounded_where(bad, out)


def _mag(b: Interval):
    return jnp.maximum(jnp.abs(b.lo), jnp.abs(b.hi))


def _mig(b: Interval):
    """Smallest |x| over the box (0 if it holds 0)."""
    return jnp.where((b.lo <= 0) & (b.hi >= 0), 0.0, jnp.minimum(jnp.abs(b.lo), jnp.abs(b.hi)))


def _reciprocal(a, ctx):
    # f'' = 2 / x^3: the sign of x where the range excludes 0 (else _mig = 0: unbounded)
    def d2(b):
        m = 2.0 / _mig(b) ** 3
        pos, neg = b.lo > 0, b.hi < 0
        return Interval(jnp.where(pos, 0.0, -m), jnp.where(neg, 0.0, m))

    # f' = -1 / x^2 = alpha at x = +-1 / sqrt(-alpha): convex for x > 0, concave for x < 0
    sgn = lambda b: jnp.where(b.lo > 0, 1, jnp.where(b.hi < 0, -1, 0))
    tangent = lambda al: jnp.sign(a.c) / jnp.sqrt(jnp.maximum(-al, iv._TINY))
    return _smooth(a, ctx, lambda x: 1.0 / x, lambda x: -1.0 / (x * x), d2, (tangent, sgn))


def _sqrt(a, ctx):
    lo = to_interval(a, ctx).lo
    # f'' = -x^(-3/2) / 4 < 0
    d2 = lambda b: Interval(
        jnp.where(b.lo > 0, -0.25 / jnp.maximum(b.lo, iv._TINY) ** 1.5, -jnp.inf), jnp.zeros_like(b.lo)
    )
    # f' = 1 / (2 sqrt x) = alpha at x = 1 / (4 alpha^2); concave where x > 0
    tangent = lambda al: 0.25 / jnp.maximum(al * al, iv._TINY)
    concave = lambda b: jnp.where(b.lo > 0, -1, 0)
    out = _smooth(a, ctx, jnp.sqrt, lambda x: 0.5 / jnp.sqrt(x), d2, (tangent, concave))
    return Affine(out.c, out.g, jnp.where(lo > 0, out.e, jnp.inf))


def _sin(a, ctx):
    # f'' = -sin: the interval rule's range of sin over the box, negated
    return _smooth(a, ctx, jnp.sin, jnp.cos, lambda b: iv._neg(iv._sin(b)))


def _cos(a, ctx):
    return _smooth(a, ctx, jnp.cos, lambda x: -jnp.sin(x), lambda b: iv._neg(iv._cos(b)))


def _atan2(y, x, ctx, unwrapped: bool):
    """atan2(y, x): tangent plane at the centre, remainder with ||Hessian|| = 1 / r^2 <= 1 / r_min^2."""
    by, bx = to_interval(y, ctx), to_interval(x, ctx)
    r2 = x.c * x.c + y.c * y.c
    ry, rx = rad(y, ctx), rad(x, ctx)
    rmin2 = _mig(bx) ** 2 + _mig(by) ** 2
    rem = 0.5 * (ry * ry + rx * rx) / rmin2
    ky, kx = x.c / r2, -y.c / r2
    g = ky[..., None] * y.g + kx[..., None] * x.g
    c = jnp.arctan2(y.c, x.c)
    e = jnp.abs(ky) * y.e + jnp.abs(kx) * x.e + rem + iv._REL * jnp.abs(c)
    crosses = (bx.lo < 0) & (by.lo <= 0) & (by.hi >= 0)
    out = _make(c, g, e)
    bad = (rmin2 <= 0) | ~jnp.isfinite(out.e)
    if not unwrapped:  # across the branch cut the value jumps by 2 pi: only its range is known
        bad = bad | crosses
    whole = _from_interval(Interval(jnp.full_like(c, -math.pi), jnp.full_like(c, math.pi)), ctx)
    return _where(bad, whole, out)


def _d2_bound(name):
    """An :class:`Interval` holding f'' of ``name`` over a box (signed: see :func:`_smooth`)."""
    zero = lambda b: jnp.zeros_like(b.lo)
    sym = lambda m: lambda b: Interval(jnp.full_like(b.lo, -m), jnp.full_like(b.lo, m))
    return {
        "exp": lambda b: Interval(zero(b), jnp.exp(b.hi)),
        "expm1": lambda b: Interval(zero(b), jnp.exp(b.hi)),
        "log": lambda b: Interval(jnp.where(b.lo > 0, -1.0 / jnp.maximum(b.lo, iv._TINY) ** 2, -jnp.inf), zero(b)),
        "log1p": lambda b: Interval(
            jnp.where(b.lo > -1, -1.0 / jnp.maximum(1.0 + b.lo, iv._TINY) ** 2, -jnp.inf), zero(b)
        ),
        "atan": sym(0.65),  # max |d2 atan| = 3 sqrt(3) / 8
        "tanh": sym(0.77),  # max |d2 tanh| = 4 / (3 sqrt(3))
    }[name]


_SMOOTH = {
    "exp": (jnp.exp, jnp.exp),
    "expm1": (jnp.expm1, jnp.exp),
    "log": (jnp.log, lambda x: 1.0 / x),
    "log1p": (jnp.log1p, lambda x: 1.0 / (1.0 + x)),
    "atan": (jnp.arctan, lambda x: 1.0 / (1.0 + x * x)),
    "tanh": (jnp.tanh, lambda x: 1.0 - jnp.tanh(x) ** 2),
}


def _relu(a, ctx):
    r"""``max(a, 0)``: ``a`` where it is surely >= 0, 0 where surely <= 0; across 0 (range
    [l, u]) the parallel to the chord, :math:`\lambda a - \lambda l/2 \pm \lambda l/2` with
    :math:`\lambda = u/(u - l)`, which holds max(x, 0) for every x in [l, u] (the zonotope
    ReLU of Singh et al. 2018): a clamp that may engage keeps its dependence on the symbols."""
    box = to_interval(a, ctx)
    lo, hi = box.lo, box.hi
    pos, neg = lo >= 0, hi <= 0
    finite = jnp.isfinite(lo) & jnp.isfinite(hi)
    lam = jnp.where(pos, 1.0, jnp.where(neg | ~finite, 0.0, hi / jnp.where(pos | neg, 1.0, hi - lo)))
    mu = jnp.where(pos | neg, 0.0, iv._up(-lam * lo * 0.5))
    out = _scale(a, lam, mu)
    out = _make(out.c + mu, out.g, out.e)
    # an unbounded range across 0: its hull, through the interval rule
    hull = _from_interval(iv._max(box, Interval.point(jnp.zeros_like(lo))), ctx)
    keep = pos | neg | finite
    return _where(keep, out, hull)


def _abs(a, ctx):
    """``|a|``: ``a`` or ``-a`` where its sign is sure, else ``2 relu(a) - a``."""
    return _sub(_scale(_relu(a, ctx), jnp.full(a.c.shape, 2.0)), a)


def _decided(a, b, ctx, lower: bool):
    """``max(a, b)`` (``min`` with ``lower``): the argument that surely wins keeps its form, else
    ``b + relu(a - b)`` (``a - relu(a - b)``)."""
    shape = jnp.broadcast_shapes(a.c.shape, b.c.shape)
    a, b = (
        Affine(*(jnp.broadcast_to(x, s) for x, s in zip(v, (shape, shape + v.g.shape[-1:], shape)))) for v in (a, b)
    )
    ia, ib = to_interval(a, ctx), to_interval(b, ctx)
    a_wins = ib.hi <= ia.lo if not lower else ia.hi <= ib.lo
    b_wins = ia.hi <= ib.lo if not lower else ib.hi <= ia.lo
    r = _relu(_sub(a, b), ctx)
    mixed = _sub(a, r) if lower else _add(b, r)
    pick = lambda x, y, z: jnp.where(a_wins, x, jnp.where(b_wins, y, z))
    pick_g = lambda x, y, z: jnp.where(a_wins[..., None], x, jnp.where(b_wins[..., None], y, z))
    return Affine(pick(a.c, b.c, mixed.c), pick_g(a.g, b.g, mixed.g), pick(a.e, b.e, mixed.e))


def _integer_pow(a, y, ctx):
    if y == 0:
        return _point(jnp.ones_like(a.c), ctx)
    if y < 0:
        return _reciprocal(_integer_pow(a, -y, ctx), ctx)
    out = a
    for _ in range(y - 1):
        out = _mul(out, a, ctx)
    return out


def _select(pred: Interval, cases, ctx):
    """Each entry: the case its predicate certainly picks, else the hull of the possible cases."""
    hull = _from_interval(iv._select_n(pred, *[to_interval(c, ctx) for c in cases]), ctx)
    lo_i, hi_i = (pred.lo.astype(jnp.int32), pred.hi.astype(jnp.int32)) if pred.lo.dtype == jnp.bool_ else pred
    out = hull
    for k, case in enumerate(cases):
        sure = (lo_i == k) & (hi_i == k)
        out = _where(sure, case, out)
    return out


def _reduce_sum(a, axes):
    s = lambda x: jnp.sum(x, axis=axes)
    n = math.prod(a.c.shape[i] for i in axes)
    g = jnp.sum(a.g, axis=tuple(axes))
    mag = s(jnp.abs(a.c)) + jnp.sum(jnp.abs(a.g), axis=tuple(axes) + (-1,))
    return _make(s(a.c), g, s(a.e) + n * 2.0**-52 * mag)


def _dot_general(a, b, ctx, params):
    dot = lambda x, y: jax.lax.dot_general(x, y, **params)
    (ca, _), _ = params["dimension_numbers"]
    n = math.prod(a.c.shape[i] for i in ca)
    ra, rb = rad(a, ctx), rad(b, ctx)
    # one product per symbol (the symbol axis is batched: dot_general's numbering stays valid)
    g = jax.vmap(lambda x, y: dot(a.c, y) + dot(x, b.c), in_axes=-1, out_axes=-1)(a.g, b.g)
    e = dot(jnp.abs(a.c), b.e) + dot(a.e, jnp.abs(b.c)) + dot(ra, rb)
    mag = dot(jnp.abs(a.c), jnp.abs(b.c)) + dot(jnp.abs(a.c), rb) + dot(ra, jnp.abs(b.c))
    return _make(dot(a.c, b.c), g, e + (n + 4) * 2.0**-52 * mag)


def _structural(prim, args, params, ctx):
    bind = lambda *xs: prim.bind(*xs, **params)
    c, e = bind(*[a.c for a in args]), bind(*[a.e for a in args])
    # the generators' symbol axis is a batch axis of the same primitive
    g = jax.vmap(bind, in_axes=-1, out_axes=-1)(*[a.g for a in args])
    if prim.multiple_results:
        return [Affine(ci, gi, ei) for ci, gi, ei in zip(c, g, e)]
    return Affine(c, g, e)


_AFFINE_STRUCTURAL = iv._STRUCTURAL - {"dynamic_slice", "gather", "reduce_max", "reduce_min", "cumsum"}


class _Evaluator:
    """One evaluation's equation rules (the symbols' context is fixed for it)."""

    def __init__(self, ctx: _Context, angles_mod_2pi: bool):
        self.ctx = ctx
        self.angles_mod_2pi = angles_mod_2pi

    def as_affine(self, x):
        if isinstance(x, Affine):
            return x
        return _from_interval(x, self.ctx) if iv._is_float(x.lo) else None

    def __call__(self, eqn, args, angle_vars):
        name, params, ctx = eqn.primitive.name, dict(eqn.params), self.ctx
        sub = iv.sub_program(eqn)
        if sub is not None:
            return iv.run_jaxpr(sub.jaxpr, [Interval.point(c) for c in sub.consts], args, self)
        if not any(isinstance(a, Affine) for a in args):
            return iv._eval_eqn(eqn, args, angle_vars)
        rule = self._rule(eqn, name, params, angle_vars)
        if rule is not None:
            return rule([self.as_affine(a) if iv._is_float(_lo(a)) else a for a in args])
        # no affine rule: through the intervals of the arguments' ranges
        boxes = [to_interval(a, ctx) if isinstance(a, Affine) else a for a in args]
        # kept as intervals (floor, comparisons, clamps are exact there); converted where they
        # meet an affine value
        return iv._eval_eqn(eqn, boxes, angle_vars)

    def _rule(self, eqn, name, params, angle_vars):
        ctx = self.ctx
        if name in ("add", "add_any"):
            return lambda a: _add(a[0], a[1])
        if name == "sub":
            return lambda a: _sub(a[0], a[1])
        if name == "neg":
            return lambda a: _neg(a[0])
        if name == "mul":
            return lambda a: _mul(a[0], a[1], ctx)
        if name == "div":
            return lambda a: _mul(a[0], _reciprocal(a[1], ctx), ctx)
        if name == "integer_pow":
            return lambda a: _integer_pow(a[0], params["y"], ctx)
        if name == "square":
            return lambda a: _mul(a[0], a[0], ctx)
        if name == "sqrt":
            return lambda a: _sqrt(a[0], ctx)
        if name == "sin":
            return lambda a: _sin(a[0], ctx)
        if name == "cos":
            return lambda a: _cos(a[0], ctx)
        if name == _math.sincos_p.name:
            return lambda a: [_sin(a[0], ctx), _cos(a[0], ctx)]
        if name in ("atan2", _math.atan2_p.name):
            return lambda a: _atan2(a[0], a[1], ctx, self.angles_mod_2pi or eqn.outvars[0] in angle_vars)
        if name in _SMOOTH:
            f, df = _SMOOTH[name]
            return lambda a: _smooth(a[0], ctx, f, df, _d2_bound(name))
        if name == "select_n":
            return lambda a: _select(a[0], a[1:], ctx)
        if name == "abs":
            return lambda a: _abs(a[0], ctx)
        if name in ("max", "min"):
            return lambda a: _decided(a[0], a[1], ctx, lower=name == "min")
        if name == "reduce_sum":
            return lambda a: _reduce_sum(a[0], params["axes"])
        if name == "dot_general":
            return lambda a: _dot_general(a[0], a[1], ctx, params)
        if name == "stop_gradient":
            return lambda a: a[0]
        if name == iv.anchor_p.name:  # one point of the range: the centre
            return lambda a: _point(a[0].c, ctx)
        if name == "convert_element_type" and jnp.dtype(params["new_dtype"]) == jnp.float64:
            return lambda a: a[0]
        if name in _AFFINE_STRUCTURAL:
            return lambda a: _structural(eqn.primitive, [self._full(x) for x in a], params, ctx)
        return None

    def _full(self, x):
        return x if isinstance(x, Affine) else _from_interval(x, self.ctx)


def _lo(a):
    return a.c if isinstance(a, Affine) else a.lo


def symbols(centre, generators):
    """An :class:`Affine` input ``centre + generators @ eps`` (``generators``: (..., n), one
    column per symbol, the balls' first: see :func:`enclose`), with no error term."""
    centre = jnp.asarray(centre, jnp.float64)
    gen = jnp.broadcast_to(jnp.asarray(generators, jnp.float64), centre.shape + (jnp.shape(generators)[-1],))
    return Affine(centre, gen, jnp.zeros_like(centre))


def enclose(fn, *args, n_ball, angles_mod_2pi: bool = False):
    """Affine enclosure of ``fn(*args)`` where the :class:`Affine` leaves of ``args`` share their
    symbols (the first ``n_ball`` in the unit ball, the rest in [-1, 1]); other leaves are points.
    ``n_ball`` may be a tuple of sizes: consecutive groups of symbols from the first, each in a
    unit ball of its own (an initial error's ball and a tube's ball: their joint set is the
    product of the two balls, not one ball around both).

    With ``angles_mod_2pi`` every ``atan2`` is enclosed on its continuous branch through the
    box (its values are then correct modulo 2 pi only): for a caller whose use of the result is
    2 pi-periodic in those angles (a reference's heading fed to a law that uses it through
    sin/cos and wrapped errors), checked by that caller.

    Returns:
      ``fn``'s output pytree with an :class:`Affine` at every float leaf (an :class:`Interval`
      at integer and boolean ones); :func:`to_interval` gives each leaf's range.
    """
    leaves = jax.tree_util.tree_leaves(args, is_leaf=lambda x: isinstance(x, Affine))
    n = {x.g.shape[-1] for x in leaves if isinstance(x, Affine)}
    if len(n) != 1:
        raise ValueError(f"every Affine argument needs the same number of symbols, got {sorted(n)}")
    balls = (n_ball,) if isinstance(n_ball, int) else tuple(n_ball)
    ctx = _Context(tuple(b for b in balls if b), n.pop(), {})
    if any(not isinstance(b, int) or b < 0 for b in balls) or sum(balls) > ctx.n:
        raise ValueError(f"n_ball must be sizes >= 0 of at most {ctx.n} symbols in all, got {n_ball}")
    ev = _Evaluator(ctx, angles_mod_2pi)

    def to_box(x):
        x = jnp.asarray(x)
        return _point(x, ctx) if iv._is_float(x) else Interval.point(x)

    return iv.trace(fn, args, lambda x: isinstance(x, (Affine, Interval)), to_box, ev), ctx
