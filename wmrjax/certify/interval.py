r"""Validated enclosures of a JAX function over boxes: interval arithmetic on its jaxpr.

:func:`enclose` traces ``fn`` once (:func:`jax.make_jaxpr`) and evaluates its equations on
:class:`Interval` values, each primitive by a rule whose result contains every value the
primitive takes on its argument boxes (the natural interval extension, Moore 1966). The
result is an ordinary JAX program in the intervals' end points: ``jit`` and ``vmap`` it like
any other.

What makes it a bound at every step:

* **Rounding.** Every end point of ``+ - * /`` and of a sum is moved one ulp outwards
  (:func:`jax.numpy.nextafter`), which contains the correctly rounded IEEE result of every
  point of the boxes. Elementary functions (``exp``, ``sqrt``, ``sin``/``cos``, ``atan2``)
  are evaluated at the end points (or at their extrema) and widened by :data:`ELEMENTARY_ULPS`
  ulps: it assumes XLA's float64 implementations are within that many ulps of the exact
  function, which their documented accuracy (about 1-2 ulp) gives with margin.
* **Branches.** A comparison of boxes is *certainly true*, *certainly false* or *unknown*;
  ``select_n`` on an unknown predicate takes the hull of both branches.
* **Domains.** Where a box leaves a function's domain (a divisor box containing 0, a square
  root of a box reaching below 0, ``atan2`` of a box containing the origin) the result is
  the whole real line (or the whole angle range): still an enclosure, never a wrong bound.
* **Angles.** ``atan2`` of a box that crosses its branch cut (the negative x axis) is
  ``[-pi, pi]`` except where every use of the angle is ``sin``/``cos``: then the angle is
  kept as one unwrapped interval (``sin``/``cos`` are 2 pi-periodic, so the enclosure of the
  use is still valid).

**The program enclosed.** It is first rewritten by :func:`wmrjax._simplify.simplify`, as the
library's runs are: an operation repeated on the same operands is enclosed once (the same
interval), and a structural zero (a literal or constant 0, such as a constant's Taylor
coefficient) times any real number, or divided by a nonzero one, is 0 (the rule of the
operation would give the whole line where the other operand's box is unbounded or holds 0; the
runs compute the rewritten program too, so a 0 / 0 of the plain one is 0 in both).

A primitive without a rule raises ``NotImplementedError`` naming it (never a silent guess).
Only float64 is enclosed (float32's rounding is not modelled): other float types raise.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend.core import ClosedJaxpr, Literal, Primitive
from jax.interpreters import ad, batching, mlir

from wmrjax import _math, _simplify

ELEMENTARY_ULPS = 8
"""Ulps by which the end points of an elementary function's value are widened (see module)."""

_REL = ELEMENTARY_ULPS * 2.0**-52
_TINY = np.finfo(np.float64).tiny


# --- anchor: one point of a value's range ------------------------------------------------------
# The identity on arrays. An enclosure replaces it by one point of its argument's range (the
# centre): a program may then use an identity that holds for *every* choice of a quantity (a
# preconditioner M in U = M b + (I - M K) U) with the one choice that makes it tight, and stay
# exact at points, where the anchor is the value itself.
anchor_p = Primitive("wmrjax_anchor")
anchor_p.def_impl(lambda x: x)
anchor_p.def_abstract_eval(lambda x: jax.core.ShapedArray(x.shape, x.dtype))
mlir.register_lowering(anchor_p, mlir.lower_fun(lambda x: x, multiple_results=False))
ad.deflinear2(anchor_p, lambda ct, x: [ct])
batching.primitive_batchers[anchor_p] = lambda args, dims: (anchor_p.bind(*args), dims[0])


def anchor(x):
    """``x`` itself; under :func:`enclose` (and :func:`wmrjax.certify.affine.enclose`) one point
    of its range, the centre (see ``anchor_p`` above)."""
    return anchor_p.bind(jnp.asarray(x))


class Interval(NamedTuple):
    """A box: every entry x with ``lo <= x <= hi`` (a pytree; ``lo``, ``hi`` one shape).

    Booleans use ``lo`` = certainly true, ``hi`` = possibly true.
    """

    lo: Any
    hi: Any

    @classmethod
    def point(cls, x) -> "Interval":
        """The degenerate interval [x, x]."""
        x = jnp.asarray(x)
        return cls(x, x)

    @classmethod
    def around(cls, centre, radius) -> "Interval":
        """``[centre - radius, centre + radius]`` rounded outwards."""
        c, r = jnp.asarray(centre), jnp.asarray(radius)
        return cls(_down(c - r), _up(c + r))

    @property
    def mid(self):
        """The midpoint (lo + hi) / 2, rounded to nearest."""
        return 0.5 * (self.lo + self.hi)

    @property
    def rad(self):
        """The radius (hi - lo) / 2, rounded up (``mid`` is rounded to nearest: a caller adds its rounding)."""
        return _up(0.5 * (self.hi - self.lo))

    def contains(self, x):
        """True where ``x`` lies in [lo, hi] (elementwise)."""
        return (self.lo <= x) & (x <= self.hi)


def _down(x):
    return jnp.nextafter(x, jnp.asarray(-jnp.inf, x.dtype)) if _is_float(x) else x


def _up(x):
    return jnp.nextafter(x, jnp.asarray(jnp.inf, x.dtype)) if _is_float(x) else x


def _widen(lo, hi, rel: float = _REL) -> Interval:
    """End points moved outwards by ``rel`` relative plus the smallest normal number."""
    return Interval(lo - jnp.abs(lo) * rel - _TINY, hi + jnp.abs(hi) * rel + _TINY)


def _is_float(x) -> bool:
    return jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating)


def _hull(a: Interval, b: Interval) -> Interval:
    return Interval(jnp.minimum(a.lo, b.lo), jnp.maximum(a.hi, b.hi))


def _real_line(like) -> Interval:
    inf = jnp.full(jnp.shape(like), jnp.inf, jnp.asarray(like).dtype)
    return Interval(-inf, inf)


# --- arithmetic ---------------------------------------------------------------------------


def _add(a, b):
    return Interval(_down(a.lo + b.lo), _up(a.hi + b.hi))


def _sub(a, b):
    return Interval(_down(a.lo - b.hi), _up(a.hi - b.lo))


def _neg(a):
    return Interval(-a.hi, -a.lo)


def _mul(a, b):
    if not _is_float(a.lo):
        ps = [a.lo * b.lo, a.lo * b.hi, a.hi * b.lo, a.hi * b.hi]
        return Interval(_reduce(jnp.minimum, ps), _reduce(jnp.maximum, ps))
    # 0 * inf is NaN in IEEE arithmetic and 0 in interval arithmetic (0 times any real)
    ps = [jnp.where((x == 0) | (y == 0), 0.0, x * y) for x in (a.lo, a.hi) for y in (b.lo, b.hi)]
    return Interval(_down(_reduce(jnp.minimum, ps)), _up(_reduce(jnp.maximum, ps)))


def _reduce(op, xs):
    out = xs[0]
    for x in xs[1:]:
        out = op(out, x)
    return out


def _reciprocal(b):
    zero_in = (b.lo <= 0) & (b.hi >= 0)
    lo, hi = _down(1.0 / b.hi), _up(1.0 / b.lo)
    return Interval(jnp.where(zero_in, -jnp.inf, lo), jnp.where(zero_in, jnp.inf, hi))


def _div(a, b):
    if not _is_float(a.lo):
        raise NotImplementedError("interval enclosure of integer division")
    zero_in = (b.lo <= 0) & (b.hi >= 0)
    q = [x / y for x in (a.lo, a.hi) for y in (b.lo, b.hi)]
    lo, hi = _down(_reduce(jnp.minimum, q)), _up(_reduce(jnp.maximum, q))
    return Interval(jnp.where(zero_in, -jnp.inf, lo), jnp.where(zero_in, jnp.inf, hi))


def _integer_pow(a, *, y):
    if y == 0:
        return Interval.point(jnp.ones_like(a.lo))
    if y < 0:
        return _reciprocal(_integer_pow(a, y=-y))
    pl, ph = a.lo**y, a.hi**y
    if y % 2:
        return _widen(pl, ph, y * 2.0**-52)
    zero_in = (a.lo <= 0) & (a.hi >= 0)
    lo = jnp.where(zero_in, 0.0, jnp.minimum(pl, ph))
    out = _widen(lo, jnp.maximum(pl, ph), y * 2.0**-52)
    return Interval(jnp.maximum(out.lo, 0.0), out.hi)


def _abs(a):
    lo = jnp.where((a.lo <= 0) & (a.hi >= 0), jnp.zeros_like(a.lo), jnp.minimum(jnp.abs(a.lo), jnp.abs(a.hi)))
    return Interval(lo, jnp.maximum(jnp.abs(a.lo), jnp.abs(a.hi)))


def _monotone(fn):
    """An increasing elementary function: its values at the end points, widened."""
    return lambda a, **_: _widen(fn(a.lo), fn(a.hi))


def _sqrt(a, **_):
    out = _widen(jnp.sqrt(jnp.maximum(a.lo, 0.0)), jnp.sqrt(jnp.maximum(a.hi, 0.0)))
    bad = a.lo < 0  # part of the box is outside the domain: nothing is known
    return Interval(jnp.where(bad, -jnp.inf, jnp.maximum(out.lo, 0.0)), jnp.where(bad, jnp.inf, out.hi))


def _cos(a):
    """The cosine over [lo, hi]: the end points' values, and +-1 where the box holds a maximum/minimum."""
    two_pi = 2.0 * math.pi
    # k pi inside the box, with the box widened by a relative ulp budget so rounding of lo/2pi
    # cannot hide an extremum at an end point
    w = _widen(a.lo, a.hi)
    has_max = jnp.floor(w.hi / two_pi) >= jnp.ceil(w.lo / two_pi)
    has_min = jnp.floor((w.hi - math.pi) / two_pi) >= jnp.ceil((w.lo - math.pi) / two_pi)
    cl, ch = jnp.cos(a.lo), jnp.cos(a.hi)
    e = _widen(jnp.minimum(cl, ch), jnp.maximum(cl, ch))
    wide = (a.hi - a.lo) >= two_pi
    lo = jnp.where(has_min | wide, -1.0, jnp.maximum(e.lo, -1.0))
    hi = jnp.where(has_max | wide, 1.0, jnp.minimum(e.hi, 1.0))
    return Interval(lo, hi)


def _sin(a):
    # sin x = cos(x - pi/2); the shift's rounding is covered by widening the argument first
    return _cos(_widen(a.lo - 0.5 * math.pi, a.hi - 0.5 * math.pi))


def _atan2_box(y, x, unwrapped: bool):
    """atan2(y, x) over a box: extremes at its corners where the box misses the origin and the cut."""
    corners = [jnp.arctan2(yy, xx) for yy in (y.lo, y.hi) for xx in (x.lo, x.hi)]
    lo, hi = _reduce(jnp.minimum, corners), _reduce(jnp.maximum, corners)
    origin = (y.lo <= 0) & (y.hi >= 0) & (x.lo <= 0) & (x.hi >= 0)
    cut = (x.lo < 0) & (y.lo <= 0) & (y.hi >= 0)
    # across the cut the angles are those of the box turned by pi, plus pi (one unwrapped interval)
    turned = [jnp.arctan2(-yy, -xx) for yy in (y.lo, y.hi) for xx in (x.lo, x.hi)]
    tl, th = _reduce(jnp.minimum, turned) + math.pi, _reduce(jnp.maximum, turned) + math.pi
    if unwrapped:
        lo, hi = jnp.where(cut, tl, lo), jnp.where(cut, th, hi)
    else:
        lo, hi = jnp.where(cut, -math.pi, lo), jnp.where(cut, math.pi, hi)
    out = _widen(lo, hi)
    return Interval(jnp.where(origin, -2 * math.pi, out.lo), jnp.where(origin, 2 * math.pi, out.hi))


def _max(a, b):
    return Interval(jnp.maximum(a.lo, b.lo), jnp.maximum(a.hi, b.hi))


def _min(a, b):
    return Interval(jnp.minimum(a.lo, b.lo), jnp.minimum(a.hi, b.hi))


def _rem(a, b):
    """C fmod with a point divisor: exact inside one period, the period's range across one."""
    if not _is_float(a.lo):
        raise NotImplementedError("interval enclosure of integer rem")
    d = b.lo  # a box divisor is refused below
    q_lo, q_hi = jnp.trunc(a.lo / d), jnp.trunc(a.hi / d)
    same = (q_lo == q_hi) & (b.lo == b.hi)
    inside = _widen(lax.rem(a.lo, d), lax.rem(a.hi, d))
    m = jnp.abs(b.hi)
    lo = jnp.where(a.lo >= 0, 0.0, -m)
    hi = jnp.where(a.hi <= 0, 0.0, m)
    return Interval(jnp.where(same, inside.lo, lo), jnp.where(same, inside.hi, hi))


def _point_only(fn):
    """A function without a range rule: its widened value on a point box, the real line elsewhere."""

    def rule(a, **_):
        v = _widen(fn(a.lo), fn(a.lo))
        point = a.lo == a.hi
        return Interval(jnp.where(point, v.lo, -jnp.inf), jnp.where(point, v.hi, jnp.inf))

    return rule


def _floor(a):
    return Interval(jnp.floor(a.lo), jnp.floor(a.hi))


# --- comparisons and selection -------------------------------------------------------------


def _lt(a, b):
    return Interval(a.hi < b.lo, a.lo < b.hi)


def _le(a, b):
    return Interval(a.hi <= b.lo, a.lo <= b.hi)


def _eq(a, b):
    point = (a.lo == a.hi) & (b.lo == b.hi) & (a.lo == b.lo)
    return Interval(point, (a.lo <= b.hi) & (b.lo <= a.hi))


def _ne(a, b):
    e = _eq(a, b)
    return Interval(~e.hi, ~e.lo)


def _not(a):
    if a.lo.dtype != jnp.bool_:
        raise NotImplementedError("interval enclosure of bitwise not on integers")
    return Interval(~a.hi, ~a.lo)


def _and(a, b):
    return Interval(a.lo & b.lo, a.hi & b.hi)


def _or(a, b):
    return Interval(a.lo | b.lo, a.hi | b.hi)


def _select_n(pred, *cases):
    """Case ``pred``; the hull of the cases the predicate's box may choose."""
    if pred.lo.dtype == jnp.bool_:
        lo_i, hi_i = pred.lo.astype(jnp.int32), pred.hi.astype(jnp.int32)
    else:
        lo_i, hi_i = pred.lo, pred.hi
    lo = hi = None
    for i, c in enumerate(cases):
        possible = (lo_i <= i) & (i <= hi_i)
        if c.lo.dtype == jnp.bool_:  # certainly true if every possible case is; possibly if one is
            cl, ch = c.lo | ~possible, c.hi & possible
            lo = cl if lo is None else lo & cl
            hi = ch if hi is None else hi | ch
            continue
        big = jnp.asarray(jnp.inf if _is_float(c.lo) else jnp.iinfo(c.lo.dtype).max, c.lo.dtype)
        cl, ch = jnp.where(possible, c.lo, big), jnp.where(possible, c.hi, -big)
        lo = cl if lo is None else jnp.minimum(lo, cl)
        hi = ch if hi is None else jnp.maximum(hi, ch)
    return Interval(lo, hi)


# --- sums and products of arrays -------------------------------------------------------------


def _reduce_sum(a, *, axes, **_):
    n = math.prod(a.lo.shape[i] for i in axes)
    lo, hi = jnp.sum(a.lo, axis=axes), jnp.sum(a.hi, axis=axes)
    if not _is_float(lo):
        return Interval(lo, hi)
    # recursive summation's error is at most (n - 1) u sum |x_i| (Higham, Accuracy and Stability, 4.2)
    err = (n * 2.0**-52) * jnp.maximum(jnp.sum(jnp.abs(a.lo), axis=axes), jnp.sum(jnp.abs(a.hi), axis=axes))
    return Interval(lo - err - _TINY, hi + err + _TINY)


def _dot_general(a, b, **params):
    """Midpoint-radius product (Rump 1999), with the rounding of the midpoint product bounded."""
    dot = lambda x, y: lax.dot_general(x, y, **params)
    am, ar, bm, br = a.mid, a.rad, b.mid, b.rad
    (ca, _), _ = params["dimension_numbers"]
    n = math.prod(a.lo.shape[i] for i in ca)
    mid = dot(am, bm)
    rad = dot(jnp.abs(am), br) + dot(ar, jnp.abs(bm)) + dot(ar, br)
    # inner products of length n: error <= (n + 2) u (|A||B| + the radius products)
    err = ((n + 4) * 2.0**-52) * (dot(jnp.abs(am), jnp.abs(bm)) + rad) + _TINY
    return Interval(mid - rad - err, mid + rad + err)


# --- the interpreter -----------------------------------------------------------------------

_BINARY = {
    "add": _add,
    "add_any": _add,
    "sub": _sub,
    "mul": _mul,
    "div": _div,
    "max": _max,
    "min": _min,
    "rem": _rem,
    "lt": _lt,
    "le": _le,
    "gt": lambda a, b: _lt(b, a),
    "ge": lambda a, b: _le(b, a),
    "eq": _eq,
    "ne": _ne,
    "and": _and,
    "or": _or,
}
_UNARY = {
    "neg": lambda a: _neg(a),
    "abs": lambda a: _abs(a),
    "exp": _monotone(jnp.exp),
    "expm1": _monotone(jnp.expm1),
    "log": _monotone(jnp.log),
    "log1p": _monotone(jnp.log1p),
    "tanh": _monotone(jnp.tanh),
    "atan": _monotone(jnp.arctan),
    "sqrt": _sqrt,
    "square": lambda a: _integer_pow(a, y=2),
    "sign": lambda a: Interval(jnp.sign(a.lo), jnp.sign(a.hi)),
    "sin": lambda a: _sin(a),
    "cos": lambda a: _cos(a),
    "floor": lambda a: _floor(a),
    "ceil": lambda a: Interval(jnp.ceil(a.lo), jnp.ceil(a.hi)),
    "not": _not,
    "lgamma": _point_only(jax.lax.lgamma),
    "stop_gradient": lambda a: a,
}
# primitives that only move, copy or reshape entries: applied to each end point alike
_STRUCTURAL = {
    "broadcast_in_dim",
    "reshape",
    "squeeze",
    "expand_dims",
    "slice",
    "concatenate",
    "stack",
    "transpose",
    "rev",
    "split",
    "copy",
    "copy_p",
    "pad",
    "dynamic_slice",
    "gather",
    "select_and_gather_add",
    "reduce_max",
    "reduce_min",
    "cumsum",
}
_SUBJAXPR = {"pjit", "jit", "closed_call", "core_call", "remat", "checkpoint", "custom_jvp_call", "custom_vjp_call"}
_ANGLE_USES = {"sin", "cos", _math.sincos_p.name}


def _subjaxpr(eqn):
    for key in ("jaxpr", "call_jaxpr", "fun_jaxpr"):
        j = eqn.params.get(key)
        if j is not None:
            return j
    raise NotImplementedError(f"interval enclosure: no sub-program found in {eqn.primitive.name}")


def _angle_only_vars(jaxpr) -> set:
    """Variables every use of which is sin/cos (an unwrapped angle interval is valid for them)."""
    uses: dict = {}
    for eqn in jaxpr.eqns:
        for v in eqn.invars:
            if not isinstance(v, Literal):
                uses.setdefault(v, set()).add(eqn.primitive.name)
    outs = {v for v in jaxpr.outvars if not isinstance(v, Literal)}
    return {v for v, names in uses.items() if names <= _ANGLE_USES and v not in outs}


def _structural(prim, args, params):
    if prim.name in _INDEXED:
        return _indexed(prim, args, params)
    los = prim.bind(*[a.lo for a in args], **params)
    his = prim.bind(*[a.hi for a in args], **params)
    if prim.multiple_results:
        return [Interval(lo, hi) for lo, hi in zip(los, his)]
    return Interval(los, his)


_INDEXED = frozenset({"dynamic_slice", "gather"})  # reads at an index: the index must be enclosed too
INDEX_SPAN = 4
"""An indexed read whose one varying index spans at most this many values is the hull of those reads."""


def _indexed(prim, args, params):
    """An indexed read. Exact where the index boxes are points; where one index component may
    take up to :data:`INDEX_SPAN` neighbouring values (a time box across a spline's knots), the
    hull of those reads (every entry it may read is enclosed); the real line otherwise."""
    x, idx = args[0], args[1:]
    lo_v = hi_v = None
    for j in range(INDEX_SPAN):
        at = [jnp.minimum(i.lo + j, i.hi) for i in idx]
        a, b = prim.bind(x.lo, *at, **params), prim.bind(x.hi, *at, **params)
        lo_v = a if lo_v is None else jnp.minimum(lo_v, a)
        hi_v = b if hi_v is None else jnp.maximum(hi_v, b)
    varying = sum(jnp.sum((i.hi != i.lo).astype(jnp.int32)) for i in idx)
    ok = (varying <= 1) & jnp.all(jnp.asarray([jnp.all(i.hi - i.lo < INDEX_SPAN) for i in idx]))
    return Interval(jnp.where(ok, lo_v, -jnp.inf), jnp.where(ok, hi_v, jnp.inf))


def sub_program(eqn):
    """The closed sub-program of a call-like equation (``jit``, ``custom_jvp_call``, ...), or None."""
    if eqn.primitive.name not in _SUBJAXPR:
        return None
    sub = _subjaxpr(eqn)
    return sub if hasattr(sub, "consts") else ClosedJaxpr(sub, ())


def _eval_eqn(eqn, args, angle_vars):
    name, params = eqn.primitive.name, dict(eqn.params)
    sub = sub_program(eqn)
    if sub is not None:
        return run_jaxpr(sub.jaxpr, [Interval.point(c) for c in sub.consts], args, _eval_eqn)
    if name == _math.sincos_p.name:
        return [_sin(args[0]), _cos(args[0])]
    if name == anchor_p.name:  # a point of the range: its midpoint (any point would do)
        b = args[0]
        mid = 0.5 * b.lo + 0.5 * b.hi
        return Interval.point(jnp.where(jnp.isfinite(mid), mid, 0.0))
    if name in ("atan2", _math.atan2_p.name):
        # lax.atan2(y, x) and wmrjax's atan2(y, x) take their arguments in the same order
        return _atan2_box(args[0], args[1], unwrapped=eqn.outvars[0] in angle_vars)
    if name == "integer_pow":
        return _integer_pow(args[0], y=params["y"])
    if name == "select_n":
        return _select_n(*args)
    if name == "convert_element_type":
        return _convert(args[0], params["new_dtype"])
    if name == "reduce_sum":
        return _reduce_sum(args[0], **params)
    if name == "dot_general":
        return _dot_general(*args, **params)
    if name == "iota":
        return Interval.point(eqn.primitive.bind(**params))
    if name in _BINARY:
        a, b = (Interval(*jnp.broadcast_arrays(x.lo, x.hi)) for x in args)
        return _BINARY[name](a, b)
    if name in _UNARY:
        return _UNARY[name](args[0])
    if name in _STRUCTURAL:
        return _structural(eqn.primitive, args, params)
    raise NotImplementedError(f"interval enclosure has no rule for the primitive {name!r}")


def _convert(a, dtype):
    if jnp.issubdtype(dtype, jnp.floating) and jnp.dtype(dtype) != jnp.float64 and _is_float(a.lo):
        raise NotImplementedError(f"interval enclosure rounds float64 only, got a conversion to {dtype}")
    return Interval(a.lo.astype(dtype), a.hi.astype(dtype))


def run_jaxpr(jaxpr, consts, args, eval_eqn):
    """Evaluate ``jaxpr`` on enclosures with ``eval_eqn(eqn, args, angle_vars)`` per equation."""
    env: dict = {}

    def read(v):
        if isinstance(v, Literal):
            return Interval.point(v.val)
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = c
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    angle_vars = _angle_only_vars(jaxpr)
    for eqn in jaxpr.eqns:
        out = eval_eqn(eqn, [read(v) for v in eqn.invars], angle_vars)
        if eqn.primitive.multiple_results:
            for v, o in zip(eqn.outvars, out):
                env[v] = o
        else:
            env[eqn.outvars[0]] = out
    return [read(v) for v in jaxpr.outvars]


def trace(fn, args, is_box, to_box, eval_eqn):
    """Trace ``fn(*args)`` at the boxes' ``lo`` and run its jaxpr on the boxes (the ``enclose`` core)."""
    leaves, tree = jax.tree_util.tree_flatten(args, is_leaf=is_box)
    boxes = [x if is_box(x) else to_box(x) for x in leaves]
    points = [jnp.asarray(b.lo if isinstance(b, Interval) else b.c) for b in boxes]
    for p in points:
        if _is_float(p) and p.dtype != jnp.float64:
            raise ValueError(f"enclosures need float64 boxes (enable x64), got {p.dtype}")

    def flat(*xs):
        return fn(*jax.tree_util.tree_unflatten(tree, list(xs)))

    # simplified first (module docstring): an enclosure of the same function with fewer equations
    # to enclose, trace and compile (the held reach's program: 45 909 -> 25 314, nested jvp
    # recomputing each primal)
    # (its output's structure from the same trace: eval_shape would trace fn once more)
    closed, shapes = jax.make_jaxpr(_simplify.simplify(flat), return_shape=True)(*points)
    out_tree = jax.tree_util.tree_structure(shapes)
    outs = run_jaxpr(closed.jaxpr, [Interval.point(c) for c in closed.consts], boxes, eval_eqn)
    return jax.tree_util.tree_unflatten(out_tree, outs)


def _is_interval(x) -> bool:
    return isinstance(x, Interval)


def enclose(fn, *args):
    """Enclose ``fn(*args)`` over boxes: every value ``fn`` takes when each :class:`Interval`
    leaf of ``args`` ranges over its box (other leaves are points).

    Args:
      fn: a JAX-traceable function of float64 arrays (its jaxpr's primitives need rules; a
        missing one raises ``NotImplementedError`` naming it).
      *args: pytrees whose leaves are :class:`Interval` (a box, ``lo <= hi`` entrywise) or arrays.

    Returns:
      ``fn``'s output pytree with an :class:`Interval` at every leaf.
    """
    return trace(fn, args, _is_interval, Interval.point, _eval_eqn)
