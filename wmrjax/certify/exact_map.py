r"""Beyond Lemma 2: the exact error map.

While a run stays regular the linearized error obeys zeta_err(t) = expm(A t) zeta_err(0)
*exactly*, so the set of safe initial errors is known without any K2 bound. For the types
whose singular set in zeta coordinates is the linear subspace {velocity of the output point
= 0} ((2,0), (2,1), (1,1)), the distance to it is ||C zeta|| with C selecting those two rows;
the largest safe ball is then the solution of a semi-infinite problem over t whose inner
problem (fixed t) is a convex QCQP solved in closed form up to a scalar secular equation.
(1,2)'s singular set is curved: use the falsifier (an upper bound) there."""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math
from wmrjax.certify.lemma2 import check_dynamic, check_lemma2_args
from wmrjax.controllers.dynamic import DynamicLinearization, DynamicParams


def singular_rows(ctrl: DynamicLinearization):
    """Flat indices (into ``ctrl.error(...).reshape(-1)``) of the output point's velocity,
    whose vanishing is the singular set; ``None`` where the singular set is curved ((1,2))."""
    check_dynamic(ctrl)
    return (ctrl.m, ctrl.m + 1) if ctrl.row.singular_set_is_linear else None


def slice_basis(ctrl: DynamicLinearization, kind="full"):
    """Orthonormal basis (n, k) of a slice of initial errors.

    Args:
      kind: ``"full"`` (every component, k = r m), ``"position"`` (the paper's setting: the
        output point's position error only, every other component equal to the reference's,
        k = 2), or an explicit (n, k) array with orthonormal columns.
    """
    n = ctrl.relative_degree * ctrl.m
    if isinstance(kind, str):
        if kind == "full":
            return jnp.eye(n)
        if kind == "position":
            return jnp.eye(n)[:, :2]
        raise ValueError(f"unknown slice {kind!r}; expected 'full', 'position' or an (n, k) array")
    P = jnp.asarray(kind)
    if P.ndim != 2 or P.shape[0] != n or not np.allclose(np.asarray(P).T @ np.asarray(P), np.eye(P.shape[1]), atol=1e-9):
        raise ValueError(f"a slice basis must be an ({n}, k) array with orthonormal columns, got shape {P.shape}")
    return P


def min_norm_to_ball(M, a, eps, iters: int = 200):
    r"""Smallest :math:`\|x\|` with :math:`\|a + Mx\| \le \epsilon` and the minimiser (inf if unreachable).

    KKT: :math:`x(\nu) = -\nu (I + \nu M^TM)^{-1} M^T a`; in the SVD :math:`M = U S V^T` the
    residual :math:`\|a + Mx(\nu)\|^2 = \sum_i a_i'^2 / (1 + \nu s_i^2)^2` (+ the part of a
    outside range U) decreases in :math:`\nu`; bisection in :math:`\log\nu` finds the root.
    """
    U, s, Vt = jnp.linalg.svd(M, full_matrices=False)
    ap = U.T @ a
    out2 = jnp.maximum(jnp.sum(a**2) - jnp.sum(ap**2), 0.0)

    def parts(lognu):
        nu = jnp.exp(lognu)
        d = 1.0 + nu * s**2
        return jnp.sum((ap / d) ** 2) + out2, -(Vt.T @ (nu * s * ap / d))

    limit = out2 + jnp.sum(jnp.where(s > 1e-14 * jnp.max(s), 0.0, ap**2))
    reachable = limit < eps**2

    def bisect(c, _):
        lo, hi = c
        mid = 0.5 * (lo + hi)
        too_far = parts(mid)[0] > eps**2
        return (jnp.where(too_far, mid, lo), jnp.where(too_far, hi, mid)), None

    (lo, hi), _ = jax.lax.scan(bisect, (jnp.asarray(-60.0), jnp.asarray(60.0)), None, length=iters)
    x = parts(hi)[1]
    inside = jnp.sum(a**2) <= eps**2
    x = jnp.where(inside, jnp.zeros_like(x), x)
    rho = jnp.where(reachable | inside, jnp.linalg.norm(x), jnp.inf)
    return rho, x


class ExactMapRadius(NamedTuple):
    """Largest ball of initial errors (in a slice) keeping dist(zeta(t), singular set) >= eps on [0, T]."""

    ts: jnp.ndarray               # (T,) grid [s]
    rho: jnp.ndarray              # (T,) smallest initial error reaching the eps-neighbourhood at t
    radius: jnp.ndarray           # min_t rho(t), refined by golden-section search
    argmin: jnp.ndarray           # time of the worst case [s]
    worst_error: jnp.ndarray      # (r m,) the initial error achieving it (full coordinates)


def exact_map_radius(ctrl: DynamicLinearization, params: DynamicParams, *, t_final: float, eps: float,
                     basis="full", n_t: int = 2001, refine: int = 40) -> ExactMapRadius:
    r"""Exact safe radius from the linear error map (semi-infinite over t; grid then golden section).

    With :math:`\tilde\zeta(t) = e^{At}P s` (P the slice basis) and the singular set
    :math:`\{C\zeta = 0\}`, the run comes within :math:`\epsilon` of it at time t iff
    :math:`\|C\zeta_{ref}(t) + C e^{At} P s\| < \epsilon`. For each t the smallest such
    :math:`\|s\|` is :func:`min_norm_to_ball`; the radius is its minimum over [0, T]. Every
    initial error inside the ball keeps distance :math:`\ge\epsilon` over the horizon, and the
    returned ``worst_error`` (scaled by any factor > 1) does not: the radius is tight.

    Args:
      ctrl, params: the closed loop (types (2,0), (2,1), (1,1)).
      t_final: horizon T [s]; eps: Lemma 2's margin.
      basis: slice, see :func:`slice_basis`.
      n_t: grid size; refine: golden-section iterations around the grid minimum.

    Raises:
      ValueError: bad eps/horizon, a reference within eps of the singular set, or type (1,2).
    """
    check_dynamic(ctrl, params)
    check_lemma2_args(t_final=t_final, eps=eps)
    rows = singular_rows(ctrl)
    if rows is None:
        raise ValueError(f"type {ctrl.robot.name} has a curved singular set: no exact-map radius; "
                         "use falsify/falsified_radius")
    P = slice_basis(ctrl, basis)
    C = jnp.eye(ctrl.relative_degree * ctrl.m)[jnp.asarray(rows)]
    r = ctrl.relative_degree
    ts = jnp.linspace(0.0, t_final, n_t)
    m1 = jax.vmap(lambda t: jnp.linalg.norm(C @ ctrl.reference_jet(t, params)[:r].reshape(-1)))(ts)
    check_lemma2_args(t_final=t_final, eps=eps, m1=m1)
    rho, rad, t_star, worst = _exact_map(ctrl, params, P, C, jnp.asarray(eps, ts.dtype), ts, refine)
    return ExactMapRadius(ts, rho, rad, t_star, worst)


@functools.partial(jax.jit, static_argnums=(0, 6))
def _exact_map(ctrl, params, P, C, eps, ts, refine):
    """Grid minimum of rho(t), refined by golden section (one compiled program per type and slice shape)."""
    A = ctrl.error_matrix(params.gains)
    r = ctrl.relative_degree

    def rho_x(t):
        a = C @ ctrl.reference_jet(t, params)[:r].reshape(-1)
        return min_norm_to_ball(C @ jax.scipy.linalg.expm(A * t) @ P, a, eps)

    rho = jax.vmap(lambda t: rho_x(t)[0])(ts)
    i = jnp.argmin(rho)
    lo, hi = ts[jnp.maximum(i - 1, 0)], ts[jnp.minimum(i + 1, ts.shape[0] - 1)]
    lo, hi = _math.golden_section(lambda t: rho_x(t)[0], lo, hi, refine)
    tr = 0.5 * (lo + hi)
    rr, _ = rho_x(tr)
    t_star = jnp.where(rr < rho[i], tr, ts[i])
    rad, xs = rho_x(t_star)
    return rho, rad, t_star, P @ xs

