r"""C99 from a scalar jaxpr: the exported control step as straight-line code on doubles.

The program a :class:`wmrjax.export.ControlStep` becomes after :func:`wmrjax.scalarized` is,
apart from a few structural operations at its boundaries (stack, unstack, reshape), a list of
scalar arithmetic and elementary functions; a sampled reference adds a lookup in a constant
table of polynomial pieces. :func:`generate` walks it once: every array is held as its
elements (C expressions: a local variable or a literal), structural primitives only rearrange
elements, every arithmetic primitive writes one ``const`` local per element, and a
``dynamic_slice`` of a constant table becomes an indexed read. Sub-programs (``jit``, custom
derivative rules) are inlined. Locals that no output needs are dropped (``-Wall -Werror``
refuses unused variables), and so are tables nothing reads.

Primitives map to what XLA computes on the CPU: ``wmrjax_sincos`` and ``wmrjax_atan2`` to
``sin``/``cos``/``atan2`` of ``math.h`` (the library's polynomial kernels agree with them to
rounding), ``max``/``min`` propagate NaN as XLA does, ``integer_pow`` multiplies as XLA does.
A primitive without a rule is refused with its name (a ``ValueError``), never approximated.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from jax.extend import core as jex_core

# C type of each supported dtype
_CTYPES = {"float64": "double", "int64": "long long", "int32": "int", "bool": "int", "uint32": "unsigned int"}
# constants with more elements than this (the scalarizer's limit, wmrjax._scalarize.MAX_ELEMENTS:
# larger arrays stay arrays in the step) are static const tables; smaller ones are literals
TABLE_MAX_LITERALS = 64

_BINARY = {"add": "({a} + {b})", "add_any": "({a} + {b})", "sub": "({a} - {b})", "mul": "({a} * {b})",
           "div": "({a} / {b})", "lt": "({a} < {b})", "le": "({a} <= {b})", "gt": "({a} > {b})",
           "ge": "({a} >= {b})", "eq": "({a} == {b})", "ne": "({a} != {b})", "atan2": "atan2({a}, {b})",
           "wmrjax_atan2": "atan2({a}, {b})", "pow": "pow({a}, {b})", "nextafter": "nextafter({a}, {b})"}  # fmt: skip
_UNARY_FLOAT = {"neg": "(-{a})", "abs": "fabs({a})", "floor": "floor({a})", "ceil": "ceil({a})",
                "sqrt": "sqrt({a})", "rsqrt": "(1.0 / sqrt({a}))", "exp": "exp({a})", "log": "log({a})",
                "log1p": "log1p({a})", "expm1": "expm1({a})", "sin": "sin({a})", "cos": "cos({a})",
                "tan": "tan({a})", "tanh": "tanh({a})", "atan": "atan({a})", "asin": "asin({a})",
                "acos": "acos({a})", "square": "({a} * {a})", "round": "round({a})",
                "logistic": "(1.0 / (1.0 + exp(-{a})))", "sign": "wmr_sign({a})",
                "cbrt": "cbrt({a})", "sinh": "sinh({a})", "cosh": "cosh({a})"}  # fmt: skip
_IDENTITY = frozenset({"stop_gradient", "copy", "copy_p", "optimization_barrier", "reduce_precision"})
_INLINE = {"jit": "jaxpr", "pjit": "jaxpr", "closed_call": "call_jaxpr", "core_call": "call_jaxpr",
           "custom_jvp_call": "call_jaxpr", "custom_vjp_call": "call_jaxpr", "custom_vjp_call_jaxpr": "fun_jaxpr",
           "remat": "jaxpr", "checkpoint": "jaxpr"}  # fmt: skip

_HELPERS = """static double wmr_max(double a, double b) { return (a != a || b != b) ? a + b : (a > b ? a : b); }
static double wmr_min(double a, double b) { return (a != a || b != b) ? a + b : (a < b ? a : b); }
static double wmr_sign(double a) { return a > 0.0 ? 1.0 : (a < 0.0 ? -1.0 : a); }
static long long wmr_clampi(long long x, long long lo, long long hi) { return x < lo ? lo : (x > hi ? hi : x); }
"""


@dataclasses.dataclass(frozen=True)
class Signature:
    """The C interface of a control step (static sizes and labels)."""

    name: str
    n_measured: int
    n_state: int
    n_command: int
    n_compensator: int
    measured_names: tuple
    command_names: tuple
    compensator_names: tuple
    robot: str
    level: str


@dataclasses.dataclass
class _Table:
    """A constant array emitted as a static table (read by dynamic_slice)."""

    cname: str
    shape: tuple
    ctype: str


@dataclasses.dataclass
class _Val:
    """An array value: its shape, C type and elements (C expressions), or a constant table."""

    shape: tuple
    ctype: str
    elems: list | None = None
    table: _Table | None = None


class _Emitter:
    """Walks a jaxpr, writing one instruction per computed element."""

    def __init__(self):
        self.instrs = []  # (name, ctype, expr, deps)
        self.tables = {}  # cname -> (ctype, flat values)
        self.count = 0

    def fresh(self, prefix="v"):
        self.count += 1
        return f"{prefix}{self.count}"

    def assign(self, ctype, expr, deps):
        name = self.fresh()
        self.instrs.append((name, ctype, expr, frozenset(deps)))
        return name

    # --- values -------------------------------------------------------------------------

    def literal(self, value, dtype) -> str:
        dtype = str(np.dtype(dtype))
        if dtype == "bool":
            return "1" if bool(value) else "0"
        if dtype.startswith("int") or dtype.startswith("uint"):
            v = int(value)
            return f"({v}LL)" if v < 0 else f"{v}LL"
        v = float(value)
        if math.isnan(v):
            return "NAN"
        if math.isinf(v):
            return "INFINITY" if v > 0 else "(-INFINITY)"
        text = repr(v)
        return f"({text})" if v < 0 else text

    def constant(self, value) -> _Val:
        a = np.asarray(value)
        ctype = _ctype(a.dtype)
        if a.size > TABLE_MAX_LITERALS:
            cname = self.fresh("table")
            self.tables[cname] = (ctype, [self.literal(x, a.dtype) for x in a.reshape(-1)])
            return _Val(a.shape, ctype, table=_Table(cname, a.shape, ctype))
        return _Val(a.shape, ctype, [self.literal(x, a.dtype) for x in a.reshape(-1)])

    def elems(self, val: _Val) -> list:
        if val.elems is None:  # a table read whole (a structural use): one read per element
            t = val.table
            return [self.assign(t.ctype, f"{t.cname}[{i}]", {t.cname}) for i in range(int(np.prod(t.shape)))]
        return val.elems


def _ctype(dtype) -> str:
    key = str(np.dtype(dtype))
    if key not in _CTYPES:
        raise ValueError(f"generate_c: dtype {key} has no C counterpart here (float64 programs only)")
    return _CTYPES[key]


def _deps(*exprs) -> set:
    return {e for e in exprs if e and (e[0].isalpha() and e[0] not in "NI")}


def _broadcast(vals, size):
    return [v if len(v) == size else v * size for v in vals]


def _elementwise(em: _Emitter, prim, invals, outaval, params):
    size = int(np.prod(outaval.shape))
    ops = _broadcast([em.elems(v) for v in invals], size)
    ctype = _ctype(outaval.dtype)
    name = prim.name
    is_float = ctype == "double"
    out = []
    for i in range(size):
        args = [o[i] for o in ops]
        a = args[0]
        if name in _BINARY:
            expr = _BINARY[name].format(a=a, b=args[1])
        elif name in ("max", "min"):
            expr = (
                f"wmr_{name}({a}, {args[1]})"
                if is_float
                else f"({a} {'>' if name == 'max' else '<'} {args[1]} ? {a} : {args[1]})"
            )
        elif name == "rem":
            expr = f"fmod({a}, {args[1]})" if is_float else f"({a} % {args[1]})"
        elif name in _UNARY_FLOAT and (is_float or name in ("neg",)):
            expr = _UNARY_FLOAT[name].format(a=a)
        elif name == "abs":
            expr = f"({a} < 0 ? -{a} : {a})"
        elif name == "integer_pow":
            expr = _integer_pow(a, int(params["y"]))
        elif name == "select_n":
            if len(args) != 3:
                raise ValueError("generate_c: select_n with more than two cases is not supported")
            expr = f"({a} ? {args[2]} : {args[1]})"
        elif name == "clamp":
            lo, x, hi = args
            expr = f"wmr_min(wmr_max({x}, {lo}), {hi})" if is_float else f"wmr_clampi({x}, {lo}, {hi})"
        elif name == "convert_element_type":
            expr = f"({a} != 0)" if str(outaval.dtype) == "bool" else f"(({ctype})({a}))"
        elif name in ("and", "or"):
            op = {"and": "&&", "or": "||"}[name] if str(outaval.dtype) == "bool" else {"and": "&", "or": "|"}[name]
            expr = f"({a} {op} {args[1]})"
        elif name == "not":
            expr = f"(!{a})" if str(outaval.dtype) == "bool" else f"(~{a})"
        else:
            raise ValueError(f"generate_c: primitive {name!r} has no C rule")
        out.append(em.assign(ctype, expr, _deps(*args)))
    return [_Val(tuple(outaval.shape), ctype, out)]


def _integer_pow(a, y):
    if y == 0:
        return "1.0"
    if y < 0:
        return f"(1.0 / {_integer_pow(a, -y)})"
    return "(" + " * ".join([a] * y) + ")"


_ELEMENTWISE = (
    set(_BINARY) | set(_UNARY_FLOAT)
    | {"max", "min", "rem", "abs", "integer_pow", "select_n", "clamp", "convert_element_type", "and", "or", "not"}
)  # fmt: skip


def _index_map(prim, in_shapes, params, out_shapes):
    """For a structural primitive: per output, the (operand, flat index) of each element."""
    name = prim.name
    idx = [np.arange(int(np.prod(s))).reshape(s) for s in in_shapes]
    tag = [np.full(s, k) for k, s in enumerate(in_shapes)]

    def both(fn):
        return [list(zip(t.reshape(-1), i.reshape(-1))) for t, i in zip(fn(tag), fn(idx))]

    if name == "reshape":
        return both(lambda a: [a[0].reshape(out_shapes[0])])
    if name == "squeeze":
        return both(lambda a: [a[0].reshape(out_shapes[0])])
    if name == "expand_dims":
        return both(lambda a: [a[0].reshape(out_shapes[0])])
    if name == "broadcast_in_dim":
        dims = params["broadcast_dimensions"]
        shape = [1] * len(params["shape"])
        for d, n in zip(dims, in_shapes[0]):
            shape[d] = n
        return both(lambda a: [np.broadcast_to(a[0].reshape(shape), params["shape"])])
    if name == "transpose":
        return both(lambda a: [np.transpose(a[0], params["permutation"])])
    if name == "rev":
        return both(lambda a: [np.flip(a[0], params["dimensions"])])
    if name == "slice":
        strides = params["strides"] or (1,) * len(in_shapes[0])
        sl = tuple(slice(s, e, k) for s, e, k in zip(params["start_indices"], params["limit_indices"], strides))
        return both(lambda a: [a[0][sl]])
    if name == "concatenate":
        return both(lambda a: [np.concatenate(a, axis=params["dimension"])])
    if name == "stack":
        return both(lambda a: [np.stack(a, axis=params["axis"])])
    if name == "unstack":
        return both(lambda a: [np.moveaxis(a[0], params["axis"], 0)[k] for k in range(len(out_shapes))])
    if name == "split":
        cuts = np.cumsum(params["sizes"])[:-1]
        return both(lambda a: np.split(a[0], cuts, axis=params["axis"]))
    return None


def _dynamic_slice(em: _Emitter, invals, params, outaval):
    operand, starts = invals[0], invals[1:]
    shape, sizes = operand.shape, params["slice_sizes"]
    strides = np.cumprod((1,) + tuple(shape[::-1]))[::-1][1:]
    base_terms, deps = [], set()
    for d, s in enumerate(starts):
        (e,) = em.elems(s)
        clamped = f"wmr_clampi((long long)({e}), 0LL, {shape[d] - sizes[d]}LL)"
        base_terms.append(f"{clamped} * {int(strides[d])}LL")
        deps |= _deps(e)
    base = em.assign("long long", " + ".join(base_terms) or "0LL", deps)
    if operand.table is not None:
        arr, ctype = operand.table.cname, operand.ctype
    else:  # a small array indexed at run time: materialised as a local array
        elems = em.elems(operand)
        arr, ctype = em.fresh("arr"), operand.ctype
        em.instrs.append((arr, f"{ctype}[]", "{" + ", ".join(elems) + "}", frozenset(_deps(*elems))))
    offsets = np.zeros(sizes, dtype=np.int64)
    for d in range(len(sizes)):
        offsets = offsets + np.arange(sizes[d]).reshape([-1 if k == d else 1 for k in range(len(sizes))]) * int(
            strides[d]
        )
    out = [em.assign(ctype, f"{arr}[{base} + {int(o)}]", {arr, base}) for o in offsets.reshape(-1)]
    return [_Val(tuple(outaval.shape), ctype, out)]


def _eval(em: _Emitter, jaxpr, consts, args):
    env = {}

    def read(v):
        if isinstance(v, jex_core.Literal):
            return em.constant(v.val)
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = em.constant(c)
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    for eqn in jaxpr.eqns:
        outs = _eqn(em, eqn, [read(v) for v in eqn.invars])
        for v, o in zip(eqn.outvars, outs):
            env[v] = o
    return [read(v) for v in jaxpr.outvars]


def _eqn(em: _Emitter, eqn, invals):
    prim, params = eqn.primitive, eqn.params
    name = prim.name
    avals = [v.aval for v in eqn.outvars]
    if name in _INLINE and _INLINE[name] in params:
        sub = params[_INLINE[name]]
        closed = sub if hasattr(sub, "jaxpr") else jex_core.ClosedJaxpr(sub, ())
        return _eval(em, closed.jaxpr, closed.consts, invals)
    if name in _IDENTITY:
        return invals
    if name == "wmrjax_sincos":
        (a,) = invals
        s = [em.assign("double", f"sin({e})", _deps(e)) for e in em.elems(a)]
        c = [em.assign("double", f"cos({e})", _deps(e)) for e in em.elems(a)]
        return [_Val(a.shape, "double", s), _Val(a.shape, "double", c)]
    if name in _ELEMENTWISE:
        return _elementwise(em, prim, invals, avals[0], params)
    if name == "dynamic_slice":
        return _dynamic_slice(em, invals, params, avals[0])
    if name == "iota":
        return [em.constant(np.broadcast_to(
            np.arange(params["shape"][params["dimension"]]).reshape(
                [-1 if k == params["dimension"] else 1 for k in range(len(params["shape"]))]), params["shape"]
        ).astype(params["dtype"]))]  # fmt: skip
    maps = _index_map(prim, [v.shape for v in invals], params, [a.shape for a in avals])
    if maps is None:
        raise ValueError(
            f"generate_c: primitive {name!r} has no C rule (the exported step is expected to be scalar "
            "arithmetic after wmrjax.scalarized; a primitive like this one, e.g. a loop or a linear solve, "
            "is not supported)"
        )
    elems = [em.elems(v) for v in invals]
    return [_Val(tuple(a.shape), _ctype(a.dtype), [elems[k][i] for k, i in m]) for a, m in zip(avals, maps)]


def _live(instrs, roots):
    """The instructions the outputs need (backward pass over the straight-line program)."""
    need, keep = set(roots), []
    for name, ctype, expr, deps in reversed(instrs):
        if name in need:
            keep.append((name, ctype, expr))
            need |= deps
    return keep[::-1], need


def _header(sig: Signature, doc: str) -> str:
    n = sig.name.upper()
    lines = [
        f"/* {sig.name}.h -- {doc}",
        " *",
        f" * measured ({sig.n_measured}): {', '.join(sig.measured_names)}",
        f" * command ({sig.n_command}): {', '.join(sig.command_names)}",
        f" * compensator ({sig.n_compensator}): {', '.join(sig.compensator_names) or 'none (a static law)'}",
        " * state: compensator, its held rate, the last sample's time [s] (2 n_compensator + 1; 0 for a static law)",
        " *",
        f" * {sig.name}_init(t0, compensator, state): the state before the first sample at t0 [s]",
        f" * {sig.name}_step(t, measured, state, command, &regularity): one controller period at time t [s]:",
        " *   the command to hold until the next sample, the state updated in place, the signed",
        " *   regularity function (det K; near 0 or changing sign: the singular set).",
        " * Pointers may be NULL where a size is 0. Generated by wmrjax; do not edit. */",
        f"#ifndef {n}_H",
        f"#define {n}_H",
        f"#define {n}_N_MEASURED {sig.n_measured}",
        f"#define {n}_N_STATE {sig.n_state}",
        f"#define {n}_N_COMMAND {sig.n_command}",
        f"#define {n}_N_COMPENSATOR {sig.n_compensator}",
        f"void {sig.name}_init(double t0, const double *compensator, double *state);",
        f"void {sig.name}_step(double t, const double *measured, double *state, double *command, double *regularity);",
        f"#endif /* {n}_H */",
        "",
    ]
    return "\n".join(lines)


def _init_function(sig: Signature) -> list:
    nc = sig.n_compensator
    lines = [f"void {sig.name}_init(double t0, const double *compensator, double *state) {{"]
    if sig.n_state == 0:
        lines += ["    (void)t0;", "    (void)compensator;", "    (void)state;"]
    else:
        lines += [
            "    int i;",
            f"    for (i = 0; i < {nc}; ++i) {{",
            "        state[i] = compensator[i];",
            f"        state[{nc} + i] = 0.0;",
            "    }",
            f"    state[{2 * nc}] = t0;",
        ]
    return lines + ["}", ""]


def generate(closed, sig: Signature, doc: str = "") -> dict:
    """``{"<name>.h": ..., "<name>.c": ...}`` for a closed jaxpr of ``(t, measured, state) ->
    (command, state_next, regularity)`` on float64 (see the module's docstring)."""
    em = _Emitter()
    t = _Val((), "double", ["t"])
    measured = _Val(
        (sig.n_measured,), "double", [em.assign("double", f"measured[{i}]", set()) for i in range(sig.n_measured)]
    )
    state = _Val((sig.n_state,), "double", [em.assign("double", f"state[{i}]", set()) for i in range(sig.n_state)])
    command, state_next, regularity = _eval(em, closed.jaxpr, closed.consts, [t, measured, state])
    outs = [("command", em.elems(command)), ("state", em.elems(state_next)), ("*regularity", em.elems(regularity))]
    roots = {e for _, elems in outs for e in elems}
    keep, need = _live(em.instrs, roots)
    body = []
    for name, ctype, expr in keep:
        if ctype.endswith("[]"):
            body.append(f"    const {ctype[:-2]} {name}[] = {expr};")
        else:
            body.append(f"    const {ctype} {name} = {expr};")
    for target, elems in outs:
        if target == "*regularity":
            body.append(f"    *regularity = {elems[0]};")
        else:
            body += [f"    {target}[{i}] = {e};" for i, e in enumerate(elems)]
    if "t" not in need and not any(e == "t" for _, elems in outs for e in elems):
        body.insert(0, "    (void)t;")
    for arg, n in (("measured", sig.n_measured), ("state", sig.n_state), ("command", sig.n_command)):
        if n == 0:
            body.insert(0, f"    (void){arg};")
    code = "\n".join(body)
    tables = [
        f"static const {ctype} {cname}[{len(vals)}] = {{{', '.join(vals)}}};"
        for cname, (ctype, vals) in em.tables.items()
        if cname in need
    ]
    helpers = [h for h in _HELPERS.splitlines() if h.split("(")[0].split()[-1] in code]
    doc = doc or f"the control step of the {sig.robot} robot's linearizing law at {sig.level} level"
    source = "\n".join(
        [f"/* {sig.name}.c -- {doc}. Generated by wmrjax; do not edit. C99, math.h only. */",
         f'#include "{sig.name}.h"', "#include <math.h>", "", *helpers, "", *tables, "",
         *_init_function(sig),
         f"void {sig.name}_step(double t, const double *measured, double *state, double *command, double *regularity) {{",
         code, "}", ""]
    )  # fmt: skip
    return {f"{sig.name}.h": _header(sig, doc), f"{sig.name}.c": source}
