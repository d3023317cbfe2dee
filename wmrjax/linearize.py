r"""One generic engine for (static and dynamic) feedback linearization, by autodiff.

Given a control-affine system :math:`\dot z = f(z, U) = F(z) + G(z)U` and outputs
:math:`Y = h(z)` with uniform relative degree r, the engine returns

* the output jet :math:`\zeta = \Psi(z) = (Y, \dot Y, \dots, Y^{(r-1)})` (eq 35), shape (r, m),
  each row a Lie derivative :math:`L_F^j h`, computed in Taylor mode along the flow;
* the drift :math:`a(z) = L_F^r h` and the decoupling matrix
  :math:`K(z) = L_G L_F^{r-1} h` (eqs 21-23, 33), so that :math:`Y^{(r)} = a(z) + K(z)U`.

Nothing here is specific to a robot type: the paper's closed forms (eqs 39, 43, Tables
3-4) are test oracles in ``tests/test_linearize.py``.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jax.experimental import jet

from wmrjax import _math


def output_jet(field: Callable, h: Callable, z, n_inputs: int, relative_degree: int):
    r"""Output derivatives and the decoupling pair of an affine system, by Taylor mode.

    With relative degree r, :math:`L_G L_F^j h \equiv 0` for j < r - 1, so along the flow of
    :math:`\dot z = F(z) + G(z)U` with U held constant the output's derivatives are
    :math:`Y^{(j)} = L_F^j h` (j < r) and :math:`Y^{(r)} = a(z) + K(z)U`. One Taylor
    expansion of that flow to order r (``jax.experimental.jet``: each order costs one jet of
    the field) gives them all; it runs for U = 0 and the m unit inputs at once (``vmap``), so
    ``a`` comes from U = 0 and the columns of K from the differences. The program grows
    with r^2 jets of the field, where nested ``jvp`` grows like 2^r: the (1,1) torque-level
    closed loop compiles about 4x faster and runs faster.

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
    r = relative_degree
    dtype = jnp.result_type(z)
    inputs = jnp.concatenate([jnp.zeros((1, n_inputs), dtype), jnp.eye(n_inputs, dtype=dtype)])

    def along(U):
        f = lambda x: field(x, U)
        series = [f(z)]                            # z', z'', ..., z^{(r)} along the flow
        for _ in range(1, r):
            _, terms = jet.jet(f, (z,), (series,))
            series = series + [terms[-1]]
        return jet.jet(h, (z,), (series,))         # (Y, [Y', ..., Y^{(r)}])

    y, terms = jax.vmap(along)(inputs)
    zeta = jnp.stack([y[0]] + [terms[j][0] for j in range(r - 1)])
    top = terms[r - 1]                             # (1 + n_inputs, m): a, then a + K e_i
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
