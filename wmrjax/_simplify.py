r"""Smaller traced programs: fold structural zeros and emit each repeated operation once.

Both constructions of the output jet (:func:`wmrjax.linearize.output_jet`) trace programs
with much redundancy, which the compiler must then remove (slowly) or cannot remove:

* ``jax.experimental.jet`` gives every constant (a robot's geometry, a literal) a zero
  Taylor series, and instantiates it as arrays of zeros before each primitive's rule, so a
  product :math:`c \cdot x` expands into convolutions with zero arrays. IEEE arithmetic
  forbids XLA to fold :math:`0 \cdot x` (NaN for infinite x): the operations stay in the
  compiled program.
* Nested ``jax.jvp`` recomputes each lower-order primal at every level.

:func:`simplify` traces a function once, then re-emits its program while (1) propagating
*structural* zeros -- literals and constants equal to zero, and whatever zero-preserving
operations compute from them: a product with a zero is zero, an added zero is dropped, an
operation on zeros is not emitted -- and (2) emitting an operation that repeats an earlier
one on the same operands only once (common-subexpression elimination), and (3) turning the
slices that pick single elements out of an operand into the pieces of one ``split`` of it
(per operand and axis). (1) is the algebra of Taylor coefficients (a constant's higher
coefficients are exactly zero); (2) and (3) change no value. Section 6.1's output jet goes
from 911 to 575 equations; its rollout compiles faster and runs bit for bit the same. (3) is
for reverse mode: the transpose of n element slices is n zero-padded vectors summed, that of
one split a single ``concatenate``, which makes the reverse-mode gradient of the section 6.1
loss markedly cheaper.

IEEE caveat of (1): a structural zero times anything is folded to zero, and so is a structural
zero divided by anything, so ``0 * x`` with ``x`` infinite and ``0 / x`` with ``x`` zero give 0
where the plain program gives NaN (``tests/test_simplify.py`` shows both). The zeros of a jet
are exact, so the two differ only where an operand is already infinite or a zero is divided by
zero; there the plain program's NaN reaches the outputs (and :func:`wmrjax.simulate` fails the
run as non-finite), while the rewritten one can hide it when the infinity reaches the outputs
no other way. Run with the switch below off to tell the two apart.

Switch: the environment variable ``WMRJAX_JAXPR_REWRITES`` (:data:`REWRITES_ENV`). ``0``
turns :func:`simplify` and :func:`wmrjax._scalarize.scalarize` into plain calls of the
function (the program JAX traces, no rewriting, no reliance on JAX's internal jaxpr
interfaces); unset, empty or ``1`` rewrite (the default). It is read when a function is traced
(:func:`rewrites_enabled`): :func:`wmrjax.simulate` keys its compiled program on it, other
compiled functions keep the choice of their first trace (set it before the process uses
wmrjax, or call ``jax.clear_caches()`` after changing it).
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jex_core

REWRITES_ENV = "WMRJAX_JAXPR_REWRITES"


def rewrites_enabled() -> bool:
    """Whether the jaxpr rewriters (:func:`simplify`, :func:`wmrjax._scalarize.scalarize`) rewrite
    the programs they trace: ``WMRJAX_JAXPR_REWRITES`` unset, empty or ``1`` (yes, the default) or
    ``0`` (no: the plain JAX program); ValueError for another value."""
    value = os.environ.get(REWRITES_ENV, "").strip()
    if value not in ("", "0", "1"):
        raise ValueError(f"{REWRITES_ENV} must be 0 (plain JAX programs) or 1 (rewritten, the default), got {value!r}")
    return value != "0"


class _Zero:
    """An array known to be zero at trace time (only its abstract value is kept)."""

    __slots__ = ("aval",)

    def __init__(self, aval):
        self.aval = aval


def _is_zero_constant(x) -> bool:
    if isinstance(x, jax.core.Tracer):
        return False
    try:
        arr = np.asarray(x)
    except Exception:  # noqa: BLE001 - anything we cannot inspect is not a known zero
        return False
    return arr.dtype.kind in "fcib" and arr.size > 0 and not np.any(arr)


def _is_one(v) -> bool:
    """A literal equal to one (jet's factorial scalings)."""
    return isinstance(v, jex_core.Literal) and np.ndim(v.val) == 0 and v.val == 1


def _materialize(x):
    if isinstance(x, _Zero):
        return jnp.zeros(x.aval.shape, x.aval.dtype)
    return x


# primitives p with p(0, ...) == 0 whenever their first operand is zero (other operands,
# such as indices, are free); the output has the primitive's abstract value
_ZERO_IN_FIRST = {
    "neg",
    "broadcast_in_dim",
    "reshape",
    "convert_element_type",
    "transpose",
    "squeeze",
    "expand_dims",
    "slice",
    "dynamic_slice",
    "gather",
    "reduce_sum",
    "copy",
    "copy_p",
    "rev",
    "sin",
    "tan",
    "sinh",
    "tanh",
    "asin",
    "atan",
    "sqrt",
    "cbrt",
    "cumsum",
    "reduce_precision",
    "real",
    "imag",
    "conj",
    "div",
}
# products: zero if any operand is zero
_ZERO_IN_ANY = {"mul", "dot_general"}
# zero only if every operand is zero
_ZERO_IN_ALL = {"concatenate", "max", "min", "pad", "reduce_max", "reduce_min"}
# calls whose body is inlined (and folded) in place
_CALLS = {"pjit", "jit", "closed_call"}


def _key(x):
    """A hashable identity of an operand: value for scalars, object identity otherwise."""
    if isinstance(x, _Zero):
        return ("zero", x.aval.shape, x.aval.dtype)
    if isinstance(x, (int, float, bool, complex, np.generic)) and np.ndim(x) == 0:
        return ("scalar", type(x), x)
    return ("id", id(x))


_ZERO, _EMIT = "zero", "emit"
_DEAD = object()  # the value of a skipped equation (never bound: the liveness pass proves it unused)


def _action(eqn, zero):
    """What to do with ``eqn`` given which operands are structural zeros.

    Returns ``_ZERO`` (the result is a structural zero), ``(i, negate)`` (the result is
    operand i, negated if ``negate``) or ``_EMIT``.
    """
    name = eqn.primitive.name
    if eqn.primitive.multiple_results or name in _CALLS:
        return _EMIT
    if (
        (name in _ZERO_IN_FIRST and zero and zero[0])
        or (name in _ZERO_IN_ANY and any(zero))
        or (name in _ZERO_IN_ALL and all(zero))
        or (name == "integer_pow" and zero[0] and eqn.params["y"] > 0)
        or (name == "select_n" and all(zero[1:]))
    ):
        return _ZERO
    if name in ("mul", "div") and _is_one(eqn.invars[1]):
        return (0, False)
    if name == "mul" and _is_one(eqn.invars[0]):
        return (1, False)
    if name in ("add", "add_any", "sub") and any(zero):
        if all(zero):
            return _ZERO
        return (0, False) if zero[1] else (1, name == "sub")
    return _EMIT


def _zero_literal(v) -> bool:
    return isinstance(v, jex_core.Literal) and _is_zero_constant(v.val)


def _live(jaxpr, zero_vars):
    """Equations whose results are needed, from the zeros known before evaluation.

    Conservative: a call's results count as non-zero here (its body is simplified when it is
    emitted, which can only find more zeros, so it needs no more operands than counted).
    """
    zero = set(zero_vars)
    actions = []
    for eqn in jaxpr.eqns:
        act = _action(eqn, [_zero_literal(v) if isinstance(v, jex_core.Literal) else v in zero for v in eqn.invars])
        if act == _ZERO:
            zero.update(eqn.outvars)
        actions.append(act)
    needed = {v for v in jaxpr.outvars if not isinstance(v, jex_core.Literal)}
    live = [False] * len(jaxpr.eqns)
    for k in range(len(jaxpr.eqns) - 1, -1, -1):
        eqn, act = jaxpr.eqns[k], actions[k]
        if eqn.effects or any(v in needed for v in eqn.outvars):
            live[k] = True
            used = [] if act == _ZERO else [eqn.invars[act[0]]] if act != _EMIT else eqn.invars
            needed.update(v for v in used if not isinstance(v, jex_core.Literal))
    return live, zero


def _eval(jaxpr, consts, args, memo=None):
    """Evaluate ``jaxpr`` re-emitting its live equations, with zeros folded and repeats reused.

    ``memo`` maps (primitive, parameters, operand identities) to earlier results: the same
    operation on the same operands is emitted once (common-subexpression elimination; nested
    ``jvp`` recomputes each primal several times). It keeps the operands alive, so that
    identities are not recycled.
    """
    memo = {} if memo is None else memo
    env = {}

    def read(v):
        if isinstance(v, jex_core.Literal):
            return _Zero(v.aval) if _is_zero_constant(v.val) else v.val
        if v not in env:  # produced by a skipped equation: its value is not needed
            return _Zero(v.aval) if v in known_zero else _DEAD
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = _Zero(v.aval) if _is_zero_constant(c) else c
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    live, known_zero = _live(jaxpr, [v for v in (*jaxpr.constvars, *jaxpr.invars) if isinstance(env[v], _Zero)])
    for eqn, needed in zip(jaxpr.eqns, live):
        if not needed:
            continue
        invals = [read(v) for v in eqn.invars]
        key = None
        if not eqn.effects and eqn.primitive.name not in _CALLS:
            try:
                key = (eqn.primitive, tuple(sorted(eqn.params.items())), tuple(_key(x) for x in invals))
                hash(key)
            except TypeError:  # unhashable parameters (e.g. functions): emit as is
                key = None
        if key is not None and key in memo:
            outs = memo[key][1]
        else:
            outs = _emit(eqn, invals, memo)
            if key is not None:
                memo[key] = (invals, outs)
        if eqn.primitive.multiple_results:
            for v, o in zip(eqn.outvars, outs):
                env[v] = o
        else:
            env[eqn.outvars[0]] = outs
    return [read(v) for v in jaxpr.outvars]


def _emit(eqn, invals, memo):
    if eqn.primitive.name in _CALLS:
        closed = eqn.params.get("jaxpr", eqn.params.get("call_jaxpr"))
        return _eval(closed.jaxpr, closed.consts, invals, memo)
    act = _action(eqn, [isinstance(x, _Zero) for x in invals])
    if act == _ZERO:
        return _Zero(eqn.outvars[0].aval)
    if act != _EMIT:
        i, negate = act
        x = lax.neg(_materialize(invals[i])) if negate else invals[i]
        return _cast(x, eqn.outvars[0].aval)
    if eqn.primitive is lax.slice_p:
        piece = _unit_slice(invals[0], eqn.params, memo)
        if piece is not None:
            return piece
    params = eqn.primitive.get_bind_params(eqn.params)
    return eqn.primitive.bind(*[_materialize(x) for x in invals], **params)


def _unit_slice(x, params, memo):
    """A slice one element wide along each axis it cuts, as a piece of one ``split`` of the
    operand per axis (shared by every such slice of it), or None for other slices.

    The value is the same; the transpose is not: reverse mode turns n slices of a vector into
    n zero-padded vectors summed (quadratic work, a ``pad`` and an ``add`` each), and one
    split into one ``concatenate``."""
    start, limit, strides = params["start_indices"], params["limit_indices"], params["strides"]
    shape = np.shape(x)
    if (strides is not None and any(s != 1 for s in strides)) or not shape:
        return None
    cut = [a for a, (lo, hi, n) in enumerate(zip(start, limit, shape)) if (lo, hi) != (0, n)]
    if not cut or any(limit[a] - start[a] != 1 for a in cut):
        return None
    piece = x
    for a in cut:
        key = ("split", id(piece), a)
        if key not in memo:
            memo[key] = (piece, lax.split(piece, [1] * shape[a], axis=a))
        piece = memo[key][1][start[a]]
    return piece


def _cast(x, aval):
    """``x`` with the shape and dtype of ``aval`` (a pass-through operand of a binary op)."""
    x = _materialize(x)
    if np.shape(x) != aval.shape:
        x = jnp.broadcast_to(x, aval.shape)
    if jnp.result_type(x) != aval.dtype:
        x = lax.convert_element_type(x, aval.dtype)
    return x


def simplify(fun):
    """``fun`` with structural zeros folded and repeated operations emitted once.

    Works under any outer transformation (``jit``, ``vmap``, ``jvp``, ``grad``): the
    re-emitted operations are bound on the caller's values, so they are transformed as
    usual. Arrays ``fun`` closes over enter as constants (a concrete all-zero one is a
    structural zero; tracers never are).

    Args:
      fun: a function of arrays (pytrees in and out), traceable by JAX.

    Returns:
      A function with ``fun``'s signature and values (but for the IEEE caveat of the module
      docstring: ``0 * inf`` and ``0 / 0`` fold to 0): at each call it traces ``fun`` to a jaxpr
      (with abstract arguments) and evaluates that jaxpr simplified; ``fun`` itself when
      ``WMRJAX_JAXPR_REWRITES=0`` (:func:`rewrites_enabled`).
    """

    @functools.wraps(fun)
    def simplified(*args):
        if not rewrites_enabled():
            return fun(*args)
        closed, shapes = jax.make_jaxpr(fun, return_shape=True)(*args)
        flat = jax.tree_util.tree_leaves(args)
        outs = _eval(closed.jaxpr, closed.consts, flat)
        outs = [_materialize(o) for o in outs]
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(shapes), outs)

    return simplified
