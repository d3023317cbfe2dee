r"""One generic engine for (static and dynamic) feedback linearization, by autodiff.

Given a control-affine system :math:`\dot z = f(z, U) = F(z) + G(z)U` and outputs
:math:`Y = h(z)` with uniform relative degree r, the engine returns

* the output jet :math:`\zeta = \Psi(z) = (Y, \dot Y, \dots, Y^{(r-1)})` (eq 35), shape (r, m),
  each row a Lie derivative :math:`L_F^j h` (nested ``jax.jvp`` or Taylor mode along the flow);
* the drift :math:`a(z) = L_F^r h` and the decoupling matrix
  :math:`K(z) = L_G L_F^{r-1} h` (eqs 21-23, 33), so that :math:`Y^{(r)} = a(z) + K(z)U`.

Nothing here is specific to a robot type: the paper's closed forms (eqs 39, 43, Tables
3-4) are test oracles in ``tests/test_linearize.py``.
"""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import jet

from wmrjax import _math, _simplify
from wmrjax._rk4 import rk4_step

# relative degree above which the Taylor-mode construction is used (see output_jet)
NESTED_MAX_DEGREE = 2
JET_METHODS = ("auto", "taylor", "nested")


def output_jet(
    field: Callable, h: Callable, z, n_inputs: int, relative_degree: int, method: str = "auto", simplify: bool = True
):
    r"""Output derivatives and the decoupling pair of an affine system.

    With relative degree r, :math:`L_G L_F^j h \equiv 0` for j < r - 1, so along the flow of
    :math:`\dot z = F(z) + G(z)U` with U held constant the output's derivatives are
    :math:`Y^{(j)} = L_F^j h` (j < r) and :math:`Y^{(r)} = a(z) + K(z)U`. Two constructions
    give the same numbers (tested to 1e-11):

    * ``"taylor"``: one Taylor expansion of that flow to order r (``jax.experimental.jet``:
      each order costs one jet of the field), for U = 0 and the m unit inputs at once
      (``vmap``): ``a`` from U = 0, the columns of K from the differences. The program grows
      like r^2 jets of the field.
    * ``"nested"``: Lie derivatives by nested ``jax.jvp`` and one more jvp per input; the
      program grows like 2^r.
    * ``"auto"`` (default): nested for r <= :data:`NESTED_MAX_DEGREE`, Taylor above.
      On XLA:CPU, at r = 2 nested runs faster (jet multiplies by the zero series of
      constants, which IEEE arithmetic cannot fold away) and compiles as fast; at r = 4
      ((1,1), torque level) Taylor mode compiles the closed loop and its gradient several
      times faster (the benchmarks page of the docs has the compile times).

    Args:
      field: ``(z, U) -> zdot``, affine in U.
      h: ``z -> Y``, shape (m,).
      z: state (n,).
      n_inputs: dimension of U (static).
      relative_degree: r (static, >= 1), uniform over the outputs.
      method: ``"auto"``, ``"taylor"`` or ``"nested"`` (static).
      simplify: trace the construction once and re-emit it with structural zeros folded and
        repeated operations emitted once (:mod:`wmrjax._simplify`): same values, a smaller
        program (section 6.1's jet: 911 -> 575 equations, a rollout that compiles faster).

    Returns:
      ``(zeta, a, K)``: ``zeta`` (r, m) with ``zeta[j] = Y^{(j)}``; ``a`` (m,) and
      ``K`` (m, n_inputs) with ``Y^{(r)} = a + K U``.
    """
    if method not in JET_METHODS:
        raise ValueError(f"method must be one of {JET_METHODS}, got {method!r}")
    if method == "nested" or (method == "auto" and relative_degree <= NESTED_MAX_DEGREE):
        build = _nested_output_jet
    else:
        build = _taylor_output_jet
    jet_of = lambda x: build(field, h, x, n_inputs, relative_degree)
    return (_simplify.simplify(jet_of) if simplify else jet_of)(z)


def _nested_output_jet(field: Callable, h: Callable, z, n_inputs: int, relative_degree: int):
    """:func:`output_jet` by nested ``jvp`` (Lie derivatives) and one jvp per input for K."""
    zero = jnp.zeros((n_inputs,), dtype=jnp.result_type(z))
    drift = lambda x: field(x, zero)
    fns = [h]
    for _ in range(relative_degree - 1):
        prev = fns[-1]
        fns.append(lambda x, prev=prev: jax.jvp(prev, (x,), (drift(x),))[1])
    zeta = jnp.stack([fn(z) for fn in fns])
    top = fns[-1]
    highest = lambda U: jax.jvp(top, (z,), (field(z, U),))[1]
    a = highest(zero)
    K = _math.jacfwd_small(highest, zero)
    return zeta, a, K


def _taylor_output_jet(field: Callable, h: Callable, z, n_inputs: int, relative_degree: int):
    """:func:`output_jet` in Taylor mode along the flow, for U = 0 and the unit inputs at once."""
    r = relative_degree
    dtype = jnp.result_type(z)
    inputs = jnp.concatenate([jnp.zeros((1, n_inputs), dtype), jnp.eye(n_inputs, dtype=dtype)])

    def along(U):
        f = lambda x: field(x, U)
        series = [f(z)]  # z', z'', ..., z^{(r)} along the flow
        for _ in range(1, r):
            _, terms = jet.jet(f, (z,), (series,))
            series = series + [terms[-1]]
        return jet.jet(h, (z,), (series,))  # (Y, [Y', ..., Y^{(r)}])

    y, terms = jax.vmap(along)(inputs)
    zeta = jnp.stack([y[0]] + [terms[j][0] for j in range(r - 1)])
    top = terms[r - 1]  # (1 + n_inputs, m): a, then a + K e_i
    a = top[0]
    return zeta, a, (top[1:] - a).T


def input_leakage(field: Callable, h: Callable, z, n_inputs: int, relative_degree: int):
    r"""Max over j < r of :math:`\|L_G L_F^{j-1} h\|`: zero iff the relative degree is really r.

    A check used by the tests (and by users defining their own extensions).
    """
    zero = jnp.zeros((n_inputs,), dtype=jnp.result_type(z))
    drift = lambda x: field(x, zero)
    fns = [h]
    worst = jnp.zeros(())
    for _ in range(relative_degree - 1):
        prev = fns[-1]
        leak = _math.jacfwd_small(lambda U, prev=prev: jax.jvp(prev, (z,), (field(z, U),))[1], zero)
        worst = jnp.maximum(worst, jnp.max(jnp.abs(leak)))
        fns.append(lambda x, prev=prev: jax.jvp(prev, (x,), (drift(x),))[1])
    return worst


def companion(coeffs):
    r"""Block error matrix A of the linear error dynamics, for :math:`\dot{\tilde\zeta} = A\tilde\zeta`.

    Args:
      coeffs: (m, r) coefficients per output (:attr:`wmrjax.gains.Gains.coeffs`).

    Returns:
      (r m, r m) matrix acting on ``zeta_err.reshape(-1)`` with ``zeta_err`` ordered (r, m)
      as returned by :func:`output_jet` (Table 4 ordering: h1, h2, h1', h2', ...).
    """
    m, r = coeffs.shape
    n = r * m
    A = jnp.zeros((n, n), coeffs.dtype)
    idx = jnp.arange(m)
    for j in range(r - 1):
        A = A.at[j * m + idx, (j + 1) * m + idx].set(1.0)
    for j in range(r):
        A = A.at[(r - 1) * m + idx, j * m + idx].set(-coeffs[:, j])
    return A


def transition_matrix(gains, t, *, n_steps: int | None = None):
    r"""Transition matrix :math:`\Phi(t, 0)` of the error dynamics :math:`\dot{\tilde\zeta} = A(t)\tilde\zeta`.

    Under the linearizing law :math:`\tilde\zeta(t) = \Phi(t, 0)\,\tilde\zeta(0)` exactly while
    the run is regular; for constant gains :math:`\Phi(t, 0) = e^{At}`. Lemma 2's smallest
    valid :math:`K_2(t)` is :math:`\|\Phi(t, 0)\|_2`.

    Args:
      gains: :class:`wmrjax.Gains` or :class:`wmrjax.GainSchedule` (A(t) = ``companion(gains.coeffs_at(t))``).
      t: scalar time [s], >= 0 (vmap over t for a grid).
      n_steps: RK4 steps of :math:`\dot\Phi = A(t)\Phi` over [0, t] (a static int). None: ``expm(A t)``,
        valid for constant gains only (ValueError for a schedule).

    Returns:
      (r m, r m) matrix acting on ``zeta_err.reshape(-1)`` (:func:`companion`'s ordering).
    """
    if n_steps is None:
        if gains.time_varying:
            raise ValueError(
                "transition_matrix of a gain schedule needs n_steps (RK4 steps over [0, t]); "
                "expm(A t) holds for constant gains only"
            )
        A = companion(gains.coeffs_at(0.0))
        return _math.expm_small(A * t)
    if isinstance(n_steps, bool) or not isinstance(n_steps, int) or n_steps < 1:
        raise ValueError(f"n_steps must be an integer >= 1 (RK4 steps over [0, t]), got {n_steps!r}")
    t = jnp.asarray(t)
    m, r = gains.shape[-2:]
    P0 = jnp.eye(r * m, dtype=jnp.result_type(t, float))
    return _rk4_transition(gains, P0, jnp.zeros((), P0.dtype), t, n_steps)


def _rk4_transition(gains, P, a, b, n_steps: int):
    """P advanced from time a to b by n_steps equal RK4 steps of dP/dt = A(t) P."""
    h = (b - a) / n_steps
    field = lambda s, P: (companion(gains.coeffs_at(s)) @ P, None)

    def step(P, k):
        return rk4_step(field, a + k * h, P, h)[0], None

    P, _ = jax.lax.scan(step, P, jnp.arange(n_steps, dtype=P.dtype))
    return P


def transition_matrices(gains, ts, *, max_step: float):
    r""":math:`\Phi(t, 0)` at every time of a grid, integrated once along it.

    RK4 on :math:`\dot\Phi = A(t)\Phi` from 0 through the sorted times, with the same number
    of equal substeps in every interval, chosen so that none is longer than ``max_step``:
    cost O(T + t_max / max_step) instead of O(T t_max / max_step) for
    :func:`transition_matrix` at each time.

    Args:
      gains: :class:`wmrjax.Gains` or :class:`wmrjax.GainSchedule`.
      ts: (T,) concrete times >= 0 [s], in any order.
      max_step: largest RK4 step [s].

    Returns:
      (T, r m, r m) array, in the order of ``ts``.
    """
    tv = np.asarray(ts, dtype=float)
    if tv.ndim != 1 or not np.all(np.isfinite(tv)) or np.any(tv < 0):
        raise ValueError(f"ts must be a 1-D array of finite times >= 0, got shape {tv.shape}")
    order = np.argsort(tv, kind="stable")
    grid = np.concatenate([[0.0], tv[order]])
    gaps = np.diff(grid)
    n_sub = max(1, int(np.ceil(gaps.max() / max_step - 1e-9))) if gaps.size else 1
    inverse = np.empty_like(order)
    inverse[order] = np.arange(order.size)
    return _transition_grid(gains, jnp.asarray(grid, jnp.result_type(float)), jnp.asarray(inverse), n_sub)


@functools.partial(jax.jit, static_argnums=3)
def _transition_grid(gains, grid, inverse, n_sub: int):
    """Phi(t, 0) at ``grid[1:]`` (sorted, from grid[0] = 0) by n_sub RK4 steps per interval, reordered by ``inverse``."""
    m, r = gains.shape[-2:]
    P0 = jnp.eye(r * m, dtype=grid.dtype)

    def interval(P, ab):
        P = _rk4_transition(gains, P, ab[0], ab[1], n_sub)
        return P, P

    _, Ps = jax.lax.scan(interval, P0, (grid[:-1], grid[1:]))
    return Ps[inverse]
