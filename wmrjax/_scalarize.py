r"""Re-emit a function's small-array program as operations on scalars.

The closed loops of this library compute on arrays of a few elements (a state of 3 to 10
components, 2 x 2 decoupling matrices, output jets of shape (r, m)). Under ``vmap`` every
such array becomes a (batch, k) block, and XLA:CPU compiles the closed loop into loop
fusions around the ``concatenate``, ``slice`` and ``transpose`` operations that build and
take apart those blocks. Reverse mode makes it worse: the transpose of taking an array
apart (``unstack``) is assembling one (``concatenate``), and XLA:CPU emits a concatenate
whose operands are long fused expressions as a branchy per-element loop that recomputes
the operands' shared work (on the section 6.1 loss a few such fusions cost more than all the
arithmetic of the step's backward pass).

:func:`scalarize` traces a function once and re-emits its program with every array of at
most :data:`MAX_ELEMENTS` elements held as its elements: elementwise primitives are bound
once per element, structural ones (``reshape``, ``broadcast_in_dim``, ``transpose``,
``slice``, ``concatenate``, ``stack``, ``split``, ``pad``, ``rev``, ``iota``, ...) only
rearrange elements and emit nothing, ``dot_general`` and the reductions become sums of
products. Under ``vmap`` every element is one contiguous batch vector (structure of
arrays), so the whole program is elementwise on batch vectors. Constant subexpressions are
evaluated at trace time. Larger arrays and primitives without a rule (control flow,
gathers, custom derivatives) are bound on whole arrays as before. Values are those of the
original program up to the order of the terms of sums (dot products and reductions are
summed left to right).

Compose with :func:`wmrjax._simplify.simplify`, which then folds the structural zeros and
repeated operations that scalarization exposes (element by element).

``WMRJAX_JAXPR_REWRITES=0`` in the environment turns :func:`scalarize` (and
:func:`wmrjax._simplify.simplify`) into plain calls of the function, read when it is traced: the
plain JAX program, without this module's reliance on JAX's internal jaxpr interfaces (see
:func:`wmrjax._simplify.rewrites_enabled`).
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jex_core

from wmrjax._simplify import rewrites_enabled

# arrays with at most this many elements are held as elements
MAX_ELEMENTS = 64

# primitives applied element by element (operands broadcast to the output's shape)
_ELEMENTWISE = frozenset(
    {
        "abs",
        "acos",
        "acosh",
        "add",
        "add_any",
        "and",
        "asin",
        "asinh",
        "atan",
        "atan2",
        "atanh",
        "cbrt",
        "ceil",
        "clamp",
        "conj",
        "convert_element_type",
        "copy",
        "copy_p",
        "cos",
        "cosh",
        "digamma",
        "div",
        "eq",
        "erf",
        "erf_inv",
        "erfc",
        "exp",
        "exp2",
        "expm1",
        "floor",
        "ge",
        "gt",
        "imag",
        "integer_pow",
        "is_finite",
        "le",
        "lgamma",
        "log",
        "log1p",
        "logistic",
        "lt",
        "max",
        "min",
        "mul",
        "ne",
        "neg",
        "nextafter",
        "not",
        "or",
        "pow",
        "real",
        "reduce_precision",
        "rem",
        "round",
        "rsqrt",
        "select_n",
        "sign",
        "sin",
        "sinh",
        "sqrt",
        "square",
        "stop_gradient",
        "sub",
        "tan",
        "tanh",
        "xor",
        "wmrjax_atan2",
        "wmrjax_sincos",
    }
)
_CALLS = frozenset({"pjit", "jit", "closed_call"})
_REDUCERS = {
    "reduce_sum": lax.add,
    "reduce_prod": lax.mul,
    "reduce_max": lax.max,
    "reduce_min": lax.min,
    "reduce_and": lax.bitwise_and,
    "reduce_or": lax.bitwise_or,
}


def _is_elements(x) -> bool:
    return isinstance(x, np.ndarray) and x.dtype == object


def _concrete(e) -> bool:
    return not isinstance(e, jax.core.Tracer)


def _elements(x):
    """``x`` as an object array of its 0-d elements (NumPy scalars where known at trace time)."""
    if _is_elements(x):
        return x
    shape = np.shape(x)
    out = np.empty(shape, dtype=object)
    if _concrete(x):
        arr = np.asarray(x)
        for idx in np.ndindex(shape):
            out[idx] = arr[idx]
    elif not shape:
        out[()] = x
    elif out.size:
        for idx, e in zip(np.ndindex(shape), jnp.unstack(jnp.reshape(x, (-1,)))):
            out[idx] = e
    return out


def _array(x, aval):
    """``x`` as one array of ``aval``'s shape and dtype (an object array is stacked)."""
    if not _is_elements(x):
        return x
    flat = list(x.reshape(-1))
    if all(_concrete(e) for e in flat):
        return np.asarray([np.asarray(e) for e in flat], aval.dtype).reshape(x.shape)
    if x.shape == ():
        return flat[0]
    return jnp.reshape(jnp.stack([jnp.asarray(e, aval.dtype) for e in flat]), x.shape)


def _bind(prim, args, params):
    """``prim`` on 0-d operands; evaluated now (a NumPy scalar) when they are all known."""
    if all(_concrete(a) for a in args):
        with jax.ensure_compile_time_eval():
            out = prim.bind(*args, **params)
        return [np.asarray(o)[()] for o in out] if prim.multiple_results else np.asarray(out)[()]
    return prim.bind(*args, **params)


def _elementwise(eqn, ins):
    shape = eqn.outvars[0].aval.shape
    ops = [np.broadcast_to(a, shape) for a in ins]
    params = eqn.primitive.get_bind_params(eqn.params)
    outs = [np.empty(shape, dtype=object) for _ in eqn.outvars]
    for idx in np.ndindex(shape):
        r = _bind(eqn.primitive, [a[idx] for a in ops], params)
        for o, ri in zip(outs, r if eqn.primitive.multiple_results else [r]):
            o[idx] = ri
    return outs


def _fold(op, items):
    return functools.reduce(lambda a, b: _bind_fn(op, a, b), list(items))


def _identity(name, dtype):
    """The value of a reduction over no elements."""
    dtype = np.dtype(dtype)
    if name not in ("reduce_max", "reduce_min"):
        value = {"reduce_sum": 0, "reduce_prod": 1, "reduce_and": True, "reduce_or": False}[name]
    elif dtype.kind == "b":
        value = name == "reduce_min"
    elif dtype.kind == "f":
        value = -np.inf if name == "reduce_max" else np.inf
    else:
        value = np.iinfo(dtype).min if name == "reduce_max" else np.iinfo(dtype).max
    return np.asarray(value, dtype)[()]


def _bind_fn(op, a, b):
    if _concrete(a) and _concrete(b):
        with jax.ensure_compile_time_eval():
            return np.asarray(op(a, b))[()]
    return op(a, b)


def _reduce(x, axes, name, aval):
    axes = tuple(sorted(axes))
    keep = [a for a in range(x.ndim) if a not in axes]
    xt = np.transpose(x, keep + list(axes))
    out_shape = xt.shape[: len(keep)]
    xt = xt.reshape(out_shape + (int(np.prod(xt.shape[len(keep) :], dtype=int)),))
    out = np.empty(out_shape, dtype=object)
    for idx in np.ndindex(out_shape):
        out[idx] = _fold(_REDUCERS[name], xt[idx]) if xt.shape[-1] else _identity(name, aval.dtype)
    return out


def _cast(e, dtype):
    if _concrete(e):
        return np.asarray(e, dtype)[()]
    return e if e.dtype == dtype else lax.convert_element_type(e, dtype)


def _dot_general(lhs, rhs, params, aval):
    (lc, rc), (lb, rb) = params["dimension_numbers"]
    lf = [a for a in range(lhs.ndim) if a not in lc and a not in lb]
    rf = [a for a in range(rhs.ndim) if a not in rc and a not in rb]
    lt = np.transpose(lhs, list(lb) + lf + list(lc))
    rt = np.transpose(rhs, list(rb) + rf + list(rc))
    nb = len(lb)
    batch, lfree, rfree = lt.shape[:nb], lt.shape[nb : nb + len(lf)], rt.shape[nb : nb + len(rf)]
    lt = lt.reshape(batch + lfree + (-1,))
    rt = rt.reshape(batch + rfree + (-1,))
    out = np.empty(batch + lfree + rfree, dtype=object)
    for b in np.ndindex(batch):
        for i in np.ndindex(lfree):
            for j in np.ndindex(rfree):
                terms = [
                    _bind_fn(lax.mul, _cast(u, aval.dtype), _cast(v, aval.dtype)) for u, v in zip(lt[b + i], rt[b + j])
                ]
                out[b + i + j] = _fold(lax.add, terms) if terms else np.zeros((), aval.dtype)[()]
    return out


def _pad(x, value, config):
    for axis, (lo, hi, interior) in enumerate(config):
        pieces = []
        for k in range(x.shape[axis]):
            if k and interior:
                shape = list(x.shape)
                shape[axis] = interior
                pieces.append(np.full(shape, value, dtype=object))
            pieces.append(np.take(x, [k], axis=axis))
        shape = list(x.shape)
        shape[axis] = 0
        x = np.concatenate(pieces, axis=axis) if pieces else np.empty(shape, dtype=object)
        for n, at_start in ((lo, True), (hi, False)):
            size = x.shape[axis]
            if n < 0:
                x = np.take(x, range(-n, size) if at_start else range(0, size + n), axis=axis)
            elif n > 0:
                shape = list(x.shape)
                shape[axis] = n
                fill = np.full(shape, value, dtype=object)
                x = np.concatenate([fill, x] if at_start else [x, fill], axis=axis)
    return x


def _scatter(eqn, ins):
    """``scatter`` (replace) at indices known at trace time: which element lands where, found by
    scattering the update positions into an array of -1."""
    operand, indices, updates = ins
    if not all(_concrete(e) for e in indices.reshape(-1)):
        return None
    params = eqn.primitive.get_bind_params(eqn.params)
    with jax.ensure_compile_time_eval():
        probe = eqn.primitive.bind(
            jnp.full(operand.shape, -1.0, jnp.float32),
            jnp.asarray(_array(indices, eqn.invars[1].aval)),
            jnp.arange(updates.size, dtype=jnp.float32).reshape(updates.shape),
            **params,
        )
    where = np.asarray(probe).astype(np.int64)
    out = operand.copy()
    flat_updates = updates.reshape(-1)
    for idx in np.ndindex(operand.shape):
        if where[idx] >= 0:
            out[idx] = flat_updates[where[idx]]
    return [out]


def _structural(eqn, ins):
    """Rearrangements of elements (no operation emitted); None for other primitives."""
    name, p = eqn.primitive.name, eqn.params
    x = ins[0] if ins else None
    if name == "broadcast_in_dim":
        shape = list(p["shape"])
        expanded = [1] * len(shape)
        for d, axis in zip(x.shape, p["broadcast_dimensions"]):
            expanded[axis] = d
        return [np.broadcast_to(x.reshape(expanded), shape).copy()]
    if name == "reshape" and p.get("dimensions") is None:
        return [x.reshape(p["new_sizes"])]
    if name == "transpose":
        return [np.transpose(x, p["permutation"]).copy()]
    if name == "squeeze":
        return [x.reshape(eqn.outvars[0].aval.shape)]
    if name == "expand_dims":
        return [np.expand_dims(x, p["dimensions"])]
    if name == "slice":
        strides = p["strides"] or (1,) * x.ndim
        return [x[tuple(slice(a, b, s) for a, b, s in zip(p["start_indices"], p["limit_indices"], strides))].copy()]
    if name == "concatenate":
        return [np.concatenate(ins, axis=p["dimension"])]
    if name == "stack":
        return [np.stack(ins, axis=p["axis"])]
    if name == "unstack":
        return [np.take(x, k, axis=p["axis"]) for k in range(x.shape[p["axis"]])]
    if name == "split":
        return list(np.split(x, list(itertools.accumulate(p["sizes"]))[:-1], axis=p["axis"]))
    if name == "rev":
        return [np.flip(x, axis=tuple(p["dimensions"])).copy()]
    if name == "pad":
        return [_pad(x, ins[1][()], p["padding_config"])]
    if name == "iota":
        aval = eqn.outvars[0].aval
        shape = [1] * len(aval.shape)
        shape[p["dimension"]] = aval.shape[p["dimension"]]
        arange = np.arange(aval.shape[p["dimension"]], dtype=aval.dtype).reshape(shape)
        return [_elements(np.broadcast_to(arange, aval.shape))]
    if name in _REDUCERS:
        return [_reduce(x, p["axes"], name, eqn.outvars[0].aval)]
    if name == "dot_general":
        return [_dot_general(ins[0], ins[1], p, eqn.outvars[0].aval)]
    if name == "scatter":
        return _scatter(eqn, ins)
    return None


def _small(eqn) -> bool:
    return all(np.prod(v.aval.shape, dtype=int) <= MAX_ELEMENTS for v in (*eqn.invars, *eqn.outvars))


def _eval(jaxpr, consts, args):
    env = {}

    def read(v):
        if isinstance(v, jex_core.Literal):
            return np.asarray(v.val, v.aval.dtype)
        return env[v]

    env.update(zip(jaxpr.constvars, consts))
    env.update(zip(jaxpr.invars, args))
    for eqn in jaxpr.eqns:
        ins = [read(v) for v in eqn.invars]
        name = eqn.primitive.name
        outs = None
        if name in _CALLS:
            closed = eqn.params.get("jaxpr", eqn.params.get("call_jaxpr"))
            outs = _eval(closed.jaxpr, closed.consts, ins)
        elif _small(eqn) and not eqn.effects:
            ins_e = [_elements(a) for a in ins]
            outs = _elementwise(eqn, ins_e) if name in _ELEMENTWISE else _structural(eqn, ins_e)
        if outs is None:  # no rule, or large arrays: the primitive on whole arrays
            arrays = [_array(a, v.aval) for a, v in zip(ins, eqn.invars)]
            outs = eqn.primitive.bind(*arrays, **eqn.primitive.get_bind_params(eqn.params))
            outs = outs if eqn.primitive.multiple_results else [outs]
        env.update(zip(eqn.outvars, outs))
    return [read(v) for v in jaxpr.outvars]


def scalarize(fun):
    """``fun`` re-emitted with its arrays of at most :data:`MAX_ELEMENTS` elements as scalars.

    Works under any outer transformation (``jit``, ``vmap``, ``jvp``, ``grad``): the
    re-emitted operations are bound on the caller's values. Inputs are taken apart once
    (scalar inputs cost nothing) and outputs assembled once, so a caller that keeps its
    state as scalars (:func:`wmrjax.simulate`'s carry) sees no array operations at all.

    Args:
      fun: a function of arrays (pytrees in and out), traceable by JAX.

    Returns:
      A function with ``fun``'s signature and values (up to the order of summation in dot
      products and reductions); ``fun`` itself when ``WMRJAX_JAXPR_REWRITES=0``
      (:func:`wmrjax._simplify.rewrites_enabled`).
    """

    @functools.wraps(fun)
    def scalarized(*args):
        if not rewrites_enabled():
            return fun(*args)
        closed, shapes = jax.make_jaxpr(fun, return_shape=True)(*args)
        jaxpr = closed.jaxpr
        flat = jax.tree_util.tree_leaves(args)
        ins = [_elements(x) if np.size(x) <= MAX_ELEMENTS else x for x in flat]
        consts = [_elements(c) if np.size(c) <= MAX_ELEMENTS else c for c in closed.consts]
        outs = _eval(jaxpr, consts, ins)
        outs = [_array(o, v.aval) for o, v in zip(outs, jaxpr.outvars)]
        outs = [jnp.asarray(o, v.aval.dtype) if _concrete(o) else o for o, v in zip(outs, jaxpr.outvars)]
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(shapes), outs)

    return scalarized
