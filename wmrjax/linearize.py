r"""One generic engine for (static and dynamic) feedback linearization, by autodiff.

Given a control-affine system :math:`\dot z = f(z, U) = F(z) + G(z)U` and outputs
:math:`Y = h(z)` with uniform relative degree r, the engine returns

* the output jet :math:`\zeta = \Psi(z) = (Y, \dot Y, \dots, Y^{(r-1)})` (eq 35), shape (r, m),
  each row a Lie derivative :math:`L_F^j h` computed by nested ``jax.jvp``;
* the drift :math:`a(z) = L_F^r h` and the decoupling matrix
  :math:`K(z) = L_G L_F^{r-1} h` (eqs 21-23, 33), so that :math:`Y^{(r)} = a(z) + K(z)U`.

Nothing here is specific to a robot type: the paper's closed forms (eqs 39, 43, Tables
3-4) are test oracles in ``tests/test_linearize.py``.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from wmrjax import _math


def output_jet(field: Callable, h: Callable, z, n_inputs: int, relative_degree: int):
    r"""Output derivatives and the decoupling pair of an affine system.

    Args:
      field: ``(z, U) -> zdot``, affine in U.
      h: ``z -> Y``, shape (m,).
      z: state (n,).
      n_inputs: dimension of U (static).
      relative_degree: r (static, >= 1), uniform over the outputs.

    Returns:
      ``(zeta, a, K)``: ``zeta`` (r, m) with ``zeta[j] = Y^{(j)}``; ``a`` (m,) and
      ``K`` (m, n_inputs) with ``Y^{(r)} = a + K U``.
    """
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
