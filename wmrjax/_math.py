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
import numpy as np
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
# Its operands broadcast like any elementwise primitive's: a vmap that batches one operand and
# not the other (a path whose x' is a constant, tabulated over time) binds it on a scalar and an array.
atan2_p = jax.extend.core.Primitive("wmrjax_atan2")
atan2_p.def_impl(lambda x, y: jax.jit(jnp.arctan2)(x, y))
atan2_p.def_abstract_eval(lambda x, y: jax.core.ShapedArray(np.broadcast_shapes(x.shape, y.shape), x.dtype))
mlir.register_lowering(atan2_p, mlir.lower_fun(jnp.arctan2, multiple_results=False))
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
      lo: the bracket's lower end.
      hi: its upper end.
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


# --- small dense linear algebra without LAPACK ----------------------------------------
# jaxlib's CPU LAPACK kernels split a large batch of matrices over XLA's intra-op thread pool
# and then block a pool thread until the pieces are done (``ParallelBatchMap``). When two such
# calls run at once -- two independent batched SVDs of one program, which XLA's thunk executor
# starts concurrently -- on a pool of two threads (a 2-core machine), each waits for work that
# only the other's thread could run: the process hangs with every thread parked. The (1,2)
# certification's branch and bound hung so on every run. The certifier's matrices are tiny
# ((r m) x (r m) at most), so these kernels compute them with plain array operations, which
# XLA fuses and vectorises under ``vmap`` and never hands to the pool.

JACOBI_SWEEPS = 8  # cyclic sweeps for three rows or more (quadratic convergence: rounding level for p <= 12)
TAYLOR_DEGREE = 18  # exp(X) for ||X||_1 <= 1: truncation below 1/19! < 1e-17 relative
MAX_SQUARINGS = 40  # ||A||_1 up to 2^40; beyond, expm_small returns NaN (as jax.scipy.linalg.expm does past its limit)


def _power_of_two_scale(x):
    """``2**-e`` with ``max|x|`` in [1/2, 1) after scaling by it (exact; 1 for a zero ``x``)."""
    big = jnp.max(jnp.abs(x))
    _, e = jnp.frexp(jnp.where(big > 0, big, 1.0))
    return jnp.ldexp(jnp.ones((), x.dtype), -e)


def _jacobi_rotate(W, Q, i: int, j: int):
    """Rows i and j of ``W`` (and of the accumulated rotation ``Q``) rotated to be orthogonal."""
    wi, wj = W[i], W[j]
    alpha, beta, gamma = jnp.sum(wi * wi), jnp.sum(wj * wj), jnp.sum(wi * wj)
    rotate = gamma != 0
    zeta = (beta - alpha) / (2.0 * jnp.where(rotate, gamma, 1.0))
    t = jnp.where(zeta >= 0, 1.0, -1.0) / (jnp.abs(zeta) + jnp.hypot(1.0, zeta))
    t = jnp.where(rotate, t, 0.0)
    c = 1.0 / jnp.sqrt(1.0 + t * t)
    s = c * t
    W = W.at[i].set(c * wi - s * wj).at[j].set(s * wi + c * wj)
    qi, qj = Q[i], Q[j]
    return W, Q.at[i].set(c * qi - s * qj).at[j].set(s * qi + c * qj)


def _orthogonal_rows(M):
    """``(Q, W)`` with ``Q`` orthogonal, ``W = Q M`` having mutually orthogonal rows (one-sided Jacobi)."""
    p = M.shape[0]
    pairs = [(i, j) for i in range(p) for j in range(i + 1, p)]

    def sweep(_, c):
        W, Q = c
        for i, j in pairs:
            W, Q = _jacobi_rotate(W, Q, i, j)
        return W, Q

    # two rows are made orthogonal by one rotation, exactly
    sweeps = 1 if p <= 2 else JACOBI_SWEEPS
    W, Q = jax.lax.fori_loop(0, sweeps, sweep, (M, jnp.eye(p, dtype=M.dtype)))
    return Q, W


def svd_small(M):
    r"""Thin SVD ``(U, s, Vt)`` of a small (p, q) matrix, as ``jnp.linalg.svd(M, full_matrices=False)``.

    One-sided Jacobi (Hestenes) on the shorter side, after an exact power-of-two scaling: the
    singular values carry high relative accuracy, the smallest included (a long horizon's
    :math:`e^{At}` reaches 1e-217). ``s`` is descending; the row of ``Vt`` (column of ``U`` for
    a tall ``M``) that belongs to a zero singular value is zero rather than an arbitrary unit
    vector. Differentiable; the singular values' derivatives are exact where they are simple.

    Args:
      M: (p, q) real matrix, p and q small (the work grows as min(p, q)^2 max(p, q)).

    Returns:
      ``U`` (p, k), ``s`` (k,), ``Vt`` (k, q) with k = min(p, q) and ``M = U diag(s) Vt``.
    """
    if M.shape[0] > M.shape[1]:
        V, s, Ut = svd_small(M.T)
        return Ut.T, s, V.T
    scale = _power_of_two_scale(M)
    Q, W = _orthogonal_rows(M * scale)
    s = jnp.sqrt(jnp.sum(W * W, axis=1))
    order = jnp.argsort(-s)
    s, W, U = s[order], W[order], Q[order].T
    Vt = W / jnp.where(s > 0, s, 1.0)[:, None]
    return U, s / scale, Vt


def spectral_norm(M):
    """Largest singular value of a small (p, q) matrix (``jnp.linalg.norm(M, 2)`` without LAPACK)."""
    if M.shape[0] > M.shape[1]:
        M = M.T
    scale = _power_of_two_scale(M)
    _, W = _orthogonal_rows(M * scale)
    return jnp.sqrt(jnp.max(jnp.sum(W * W, axis=1))) / scale


def expm_small(A):
    r"""Matrix exponential of a small (n, n) matrix without LAPACK: Taylor and squaring.

    :math:`e^{A} = (e^{A / 2^s})^{2^s}` with :math:`s = \lceil \log_2 \|A\|_1 \rceil` (at least 0),
    :math:`e^{X}` by its Taylor polynomial of degree :data:`TAYLOR_DEGREE` (Horner), exact to
    rounding for :math:`\|X\|_1 \le 1`. The squarings run a fixed :data:`MAX_SQUARINGS` masked
    steps so that reverse mode works; NaN beyond that many (:math:`\|A\|_1 > 2^{40}`).
    Agrees with ``jax.scipy.linalg.expm`` to rounding (``tests/test_math.py``).
    """
    n = A.shape[0]
    eye = jnp.eye(n, dtype=A.dtype)
    norm1 = jnp.max(jnp.sum(jnp.abs(A), axis=0))
    _, e = jnp.frexp(jnp.where(norm1 > 0, norm1, 1.0))
    s = jnp.clip(e, 0, None)  # 2^s >= ||A||_1, exactly
    X = A * jnp.ldexp(jnp.ones((), A.dtype), -s)
    E = eye
    for k in range(TAYLOR_DEGREE, 0, -1):
        E = eye + (X @ E) / k

    # static bounds: fori_loop runs as a scan, which reverse mode differentiates
    E = jax.lax.fori_loop(0, MAX_SQUARINGS, lambda i, E: jnp.where(i < s, E @ E, E), E)
    return jnp.where(s <= MAX_SQUARINGS, E, jnp.nan)


def banded_solve(values, starts, rhs, block: int):
    r"""Solve a square system whose row ``r`` is ``values[r]`` at columns ``starts[r] ...
    starts[r] + w - 1`` (every other entry zero), as block-tridiagonal: blocks of ``block`` rows,
    eliminated in order (block Thomas), each block's pivot solved by LU with partial pivoting.

    Memory and work are linear in the size (a dense solve's are quadratic and cubic): a B-spline
    collocation system of 10^5 samples is solved in a second. Without pivoting across blocks it
    is stable for the matrices it is used for: B-spline collocation at samples satisfying
    Schoenberg-Whitney is totally positive, where Gaussian elimination needs no pivoting (de
    Boor, A Practical Guide to Splines, XIII); end-condition rows belong at the top and the bottom,
    where the first and the last block take them whole (the padding goes first for that: a block
    boundary among the last rows made a natural septic spline's pivot block singular).
    Differentiable (two ``lax.scan``).

    Args:
      values: (n, w) each row's non-zero entries.
      starts: (n,) integer column of each row's first entry; every entry of row r must lie within
        ``block`` columns of r (``|c - r| <= block``).
      rhs: (n, d) right-hand sides.
      block: the block size (static).

    Returns:
      (n, d) the solution.
    """
    n, w = values.shape
    b = int(block)
    m = -(-n // b)
    pad = m * b - n
    # padding first (identity rows, unknowns zero), so that the last block ends at the last row:
    # end-condition rows at the bottom then lie in one block, whose pivoting takes them together
    r = jnp.arange(n) + pad
    col = starts[:, None] + pad + jnp.arange(w)[None, :]  # (n, w)
    pos = col - (r[:, None] // b - 1) * b  # within the block row's three blocks, [0, 3b)
    band = jnp.zeros((m * b, 3 * b), values.dtype).at[r[:, None], pos].add(values)
    head = jnp.arange(pad)
    band = band.at[head, head - (head // b - 1) * b].set(1.0)
    band = band.reshape(m, b, 3 * b)
    L, D, U = band[:, :, :b], band[:, :, b : 2 * b], band[:, :, 2 * b :]
    d = jnp.concatenate([jnp.zeros((pad,) + rhs.shape[1:], rhs.dtype), rhs]).reshape(m, b, -1)

    def forward(carry, blk):
        X_prev, y_prev = carry  # the previous block's eliminated coupling and right-hand side
        Li, Di, Ui, di = blk
        A = Di - Li @ X_prev
        X = jnp.linalg.solve(A, Ui)
        y = jnp.linalg.solve(A, di - Li @ y_prev)
        return (X, y), (X, y)

    zero = (jnp.zeros((b, b), values.dtype), jnp.zeros((b, d.shape[-1]), values.dtype))
    _, (X, y) = jax.lax.scan(forward, zero, (L, D, U, d))

    def backward(x_next, blk):
        Xi, yi = blk
        x = yi - Xi @ x_next
        return x, x

    _, x = jax.lax.scan(backward, jnp.zeros_like(y[0]), (X, y), reverse=True)
    return x.reshape(m * b, -1)[pad:]


def quantiles(a) -> dict:
    """Median, 90th and 99th percentiles and the maximum of a 1-D array ({} if empty): the
    summaries' statistics of a batch of runs."""
    a = np.asarray(a)
    if not a.size:
        return {}
    return {f"q{int(p)}": float(np.percentile(a, p)) for p in (50, 90, 99)} | {"max": float(a.max())}
