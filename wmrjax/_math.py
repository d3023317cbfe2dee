"""Small numerical kernels shared by the models and controllers.

``sincos`` exists for speed, not accuracy: XLA:CPU lowers float64 ``sin``/``cos`` to
scalar libm calls, each many times the cost of a fused multiply-add, which made the
batched closed loop trig-bound. The fdlibm
kernels below are plain polynomials, so XLA vectorises them; they agree with
``jnp.sin``/``jnp.cos`` within 2.3e-16 absolute (2 ulp where |value| > 1/2) for
|x| <= 1e4 (see ``tests/test_math.py``). Their
derivatives are defined exactly (d sin = cos, d cos = -sin, and the Taylor recurrence
of ``jax.experimental.jet``) on a primitive, so autodiff sees the mathematical functions.
"""

from __future__ import annotations

import math

import jax
import jax.extend
import jax.numpy as jnp
from jax.experimental import jet as _jet
from jax.interpreters import ad, batching, mlir

# fdlibm __kernel_sin / __kernel_cos minimax coefficients on [-pi/4, pi/4].
_SIN = (
    -1.66666666666666324348e-01,
    8.33333333332248946124e-03,
    -1.98412698298579493134e-04,
    2.75573137070700676789e-06,
    -2.50507602534068634195e-08,
    1.58969099521155010221e-10,
)
_COS = (
    4.16666666666666019037e-02,
    -1.38888888888741095749e-03,
    2.48015872894767294178e-05,
    -2.75573143513906633035e-07,
    2.08757232129817482790e-09,
    -1.13596475577881948265e-11,
)
# pi/2 split in three parts (Cody-Waite): exact products k * _PIO2_1 for |k| < 2**20.
_PIO2_1 = 1.57079632673412561417e00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_3 = 2.02226624871116645580e-21
_TWO_OVER_PI = 0.63661977236758134308


def _horner(z, coeffs):
    acc = coeffs[-1]
    for c in coeffs[-2::-1]:
        acc = acc * z + c
    return acc


def _sincos_kernel(x):
    """The fdlibm polynomials with one Cody-Waite range reduction (traced into the caller's program)."""
    k = jnp.round(x * _TWO_OVER_PI)
    r = ((x - k * _PIO2_1) - k * _PIO2_2) - k * _PIO2_3
    z = r * r
    s = r + r * z * _horner(z, _SIN)
    c = 1.0 - 0.5 * z + z * z * _horner(z, _COS)
    q = jnp.mod(k, 4.0)
    sin_x = jnp.where(q == 0, s, jnp.where(q == 1, c, jnp.where(q == 2, -s, -c)))
    cos_x = jnp.where(q == 0, c, jnp.where(q == 1, -s, jnp.where(q == 2, -c, s)))
    return sin_x, cos_x


# ``sincos`` is a primitive (not a custom_jvp function) so that every transformation the
# library uses sees the mathematical functions: jvp (d sin = cos dx), batching, and the
# Taylor-mode rule of ``jax.experimental.jet`` that the linearization engine runs on.
sincos_p = jax.extend.core.Primitive("wmrjax_sincos")
sincos_p.multiple_results = True
sincos_p.def_impl(lambda x: tuple(jax.jit(_sincos_kernel)(x)))
sincos_p.def_abstract_eval(lambda x: (jax.core.ShapedArray(x.shape, x.dtype),) * 2)
mlir.register_lowering(sincos_p, mlir.lower_fun(_sincos_kernel, multiple_results=True))


def _sincos_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    s, c = sincos_p.bind(x)
    return (s, c), (c * dx, -s * dx)


def _sincos_batch(args, dims):
    return sincos_p.bind(*args), (dims[0], dims[0])


def _sincos_taylor(primals_in, series_in):
    # jet's internal convention: normalised Taylor coefficients u_k (x(t) = sum u_k t^k);
    # the recurrence of jax.experimental.jet's own sin/cos rule, sharing one reduction.
    (x,), (series,) = primals_in, series_in
    u = [x] + list(series)
    s0, c0 = sincos_p.bind(x)
    s, c = [s0] + [None] * len(series), [c0] + [None] * len(series)
    for k in range(1, len(u)):
        s[k] = sum(j * u[j] * c[k - j] for j in range(1, k + 1)) / k
        c[k] = -sum(j * u[j] * s[k - j] for j in range(1, k + 1)) / k
    return (s[0], c[0]), (s[1:], c[1:])


ad.primitive_jvps[sincos_p] = _sincos_jvp
batching.primitive_batchers[sincos_p] = _sincos_batch
_jet.jet_rules[sincos_p] = _sincos_taylor


def sincos(x):
    """Return ``(sin x, cos x)``, elementwise, with one shared range reduction.

    Args:
      x: array of angles [rad], float32 or float64.

    Returns:
      Tuple of two arrays shaped like ``x``.
    """
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    s, c = sincos_p.bind(x)
    return s, c


# ``atan2`` with a Taylor rule that holds where its second argument vanishes (the rule of
# ``jax.experimental.jet`` expands x / y and returns NaN there, e.g. for a path heading
# along x): theta' = (y x' - x y') / (x^2 + y^2), expanded term by term.
atan2_p = jax.extend.core.Primitive("wmrjax_atan2")
atan2_p.def_impl(lambda x, y: jax.jit(jax.lax.atan2)(x, y))
atan2_p.def_abstract_eval(lambda x, y: jax.core.ShapedArray(x.shape, x.dtype))
mlir.register_lowering(atan2_p, mlir.lower_fun(jax.lax.atan2, multiple_results=False))
ad.defjvp(atan2_p, lambda dx, x, y: dx * y / (x * x + y * y), lambda dy, x, y: -dy * x / (x * x + y * y))
batching.defbroadcasting(atan2_p)


def _product(a, b, k):
    return sum(a[j] * b[k - j] for j in range(k + 1))


def _atan2_taylor(primals_in, series_in):
    # normalised Taylor coefficients (jet's internal convention)
    (x, y), (xs, ys) = primals_in, series_in
    u, w = [x] + list(xs), [y] + list(ys)
    order = len(xs)
    du = [(k + 1) * u[k + 1] for k in range(order)]  # coefficients of x'(t)
    dw = [(k + 1) * w[k + 1] for k in range(order)]
    num = [_product(w, du, k) - _product(u, dw, k) for k in range(order)]
    den = [_product(u, u, k) + _product(w, w, k) for k in range(order)]
    q = []
    for k in range(order):
        q.append((num[k] - sum(den[j] * q[k - j] for j in range(1, k + 1))) / den[0])
    return atan2_p.bind(x, y), [q[k - 1] / k for k in range(1, order + 1)]


_jet.jet_rules[atan2_p] = _atan2_taylor


def atan2(x, y):
    """``arctan2(x, y)`` [rad], elementwise; exact derivatives of every order (jvp and Taylor mode)."""
    x, y = jnp.asarray(x), jnp.asarray(y)
    dtype = jnp.result_type(x, y, float)
    x, y = jnp.broadcast_arrays(x.astype(dtype), y.astype(dtype))
    return atan2_p.bind(x, y)


def wrap_angle(a):
    """Map angles to [-pi, pi). Use it on errors only; states stay unwrapped."""
    return jnp.mod(a + jnp.pi, 2.0 * jnp.pi) - jnp.pi


def adjugate_solve(k, b):
    """Solve ``k @ x = b`` for a 1x1, 2x2 or 3x3 matrix as ``x = (adj(k) @ b) / det(k)``.

    Batched LAPACK calls are slow on CPU for tiny matrices under ``vmap``; the explicit
    adjugate fuses into the surrounding elementwise code. The division is left to the
    caller, which decides what a (near-)singular matrix means.

    Args:
      k: (n, n) matrix, n in {1, 2, 3}.
      b: (n,) right-hand side.

    Returns:
      ``(adj(k) @ b, det(k))``.
    """
    n = k.shape[0]
    if k.shape != (n, n) or n not in (1, 2, 3):
        raise ValueError(f"adjugate_solve supports square 1x1 to 3x3 matrices, got shape {k.shape}")
    if n == 1:
        return b, k[0, 0]
    if n == 2:
        det = k[0, 0] * k[1, 1] - k[0, 1] * k[1, 0]
        return jnp.stack([k[1, 1] * b[0] - k[0, 1] * b[1], k[0, 0] * b[1] - k[1, 0] * b[0]]), det

    def cross(u, v):
        return jnp.stack([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])

    c0, c1, c2 = cross(k[1], k[2]), cross(k[2], k[0]), cross(k[0], k[1])
    det = k[0, 0] * c0[0] + k[0, 1] * c0[1] + k[0, 2] * c0[2]
    return c0 * b[0] + c1 * b[1] + c2 * b[2], det


def safe_divisor(d, floor):
    """``d`` with its magnitude clamped to at least ``floor`` (sign kept, 0 -> +floor).

    Keeps a singular decoupling matrix from producing Inf/NaN (and NaN gradients): the
    margin ``|d|`` is reported separately so the run is flagged, not silently wrong.
    """
    return jnp.where(jnp.abs(d) >= floor, d, jnp.where(d >= 0, floor, -floor))


# --- small dense algebra, unrolled --------------------------------------------------
# Under vmap, jnp.dot/matmul on (3, 2) matrices becomes a batched `dot` that XLA:CPU
# neither vectorises well nor fuses with the surrounding elementwise code. These
# helpers unroll over the (static, tiny) inner dimension so the whole closed-loop
# vector field compiles to one fused loop, many times faster.


def matvec(a, x):
    """``a @ x`` for a small (p, q) matrix, unrolled over q."""
    out = a[:, 0] * x[0]
    for j in range(1, a.shape[1]):
        out = out + a[:, j] * x[j]
    return out


def matmul(a, b):
    """``a @ b`` for small matrices, unrolled."""
    return jnp.stack([matvec(a, b[:, j]) for j in range(b.shape[1])], axis=1)


def jacfwd_small(fn, x):
    """Jacobian of ``fn`` at ``x`` (1-D) by one ``jvp`` per input, unrolled (shape (out, n))."""
    n = x.shape[0]
    eye = jnp.eye(n, dtype=x.dtype)
    return jnp.stack([jax.jvp(fn, (x,), (eye[j],))[1] for j in range(n)], axis=-1)


_GOLDEN = 0.5 * (math.sqrt(5.0) - 1.0)


def golden_section(f, lo, hi, iters: int):
    """Shrink ``[lo, hi]`` around a minimum of the unimodal scalar ``f`` by golden section.

    Args:
      f: scalar function of a scalar (traceable).
      lo, hi: bracket.
      iters: iterations (static); the bracket shrinks by 0.618 per iteration.

    Returns:
      The final bracket ``(lo, hi)``.
    """

    def step(c, _):
        lo, hi = c
        x1, x2 = hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo)
        left = f(x1) <= f(x2)
        return (jnp.where(left, lo, x1), jnp.where(left, x2, hi)), None

    (lo, hi), _ = jax.lax.scan(step, (lo, hi), None, length=iters)
    return lo, hi
