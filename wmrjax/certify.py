r"""Lemma 2 certificates: from which initial errors the dynamic linearizing law provably
stays away from its singular set (paper §6, Lemma 2, Remark 16, Lemma 3, eqs 50-65).

Lemma 2: if :math:`\|\tilde\zeta(t)\| \le K_2(t)\|\tilde\zeta(0)\|` (53) and
:math:`\|\tilde\zeta(t)\| < M_1(t)` keeps :math:`\zeta(t)` regular (51), then every initial
error with :math:`\|\tilde\zeta(0)\| \le \min_t F(t)`, :math:`F = (M_1 - \epsilon)/K_2` (52),
keeps the closed loop regular. This module computes

* :math:`M_1(t)`: the distance from :math:`\zeta_{ref}(t)` to the singular set (Remark 16,
  eq 58), numerically for any type (:func:`m1_numerical`), in closed form where the
  singular set is :math:`\{\dot h = 0\}` (:func:`m1_closed_form`; Lemma 3 for (2,0));
* :math:`K_2(t)` three ways: the paper's (64), an automatic Lyapunov bound
  :math:`K_1 e^{-r_1 t}` for any Hurwitz gains, and the exact :math:`\|e^{At}\|_2` (valid
  because under the linearizing law the error obeys :math:`\dot{\tilde\zeta} = A\tilde\zeta`
  exactly while the run is regular);
* :math:`F(t)`, the certified radius :math:`\min_t F(t)` and condition (52);
* :func:`verify`: batch rollouts from initial errors sampled in and around a radius,
  counting violations of (53) and singularity events.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math
from wmrjax._validate import concrete
from wmrjax.controllers.dynamic import DynamicLinearization, DynamicParams
from wmrjax.simulate import simulate


# --- M1 -------------------------------------------------------------------------------

def m1_closed_form(ctrl: DynamicLinearization, params: DynamicParams, ts):
    r"""M1(t) in closed form (Lemma 3 and its analogues).

    For (2,0) and (1,1) the singular set in :math:`\zeta` coordinates is
    :math:`\{\dot h = 0\}` (chi1 = 0), so :math:`M_1 = \|\dot h_{ref}\| = |(\chi_1)_{ref}|`
    (eq 59); for (2,1) it is :math:`\{(\dot x, \dot y) = 0\}`, so :math:`M_1 = |(\eta_1)_{ref}|`.
    At torque level the higher rows of :math:`\zeta` can be matched on the singular set
    (for (1,1) on the family L sin(beta) + e cos(beta) = 0), so the same formula holds.

    Args:
      ctrl, params: the closed loop.
      ts: (T,) times [s].

    Returns:
      (T,) array.

    Raises:
      ValueError: for (1,2), whose singular set is curved (use :func:`m1_numerical`).
    """
    if ctrl.robot.name == "(1,2)":
        raise ValueError("no closed-form M1 for type (1,2): use m1_numerical (Remark 16)")
    def one(t):
        jet = ctrl.reference_jet(t, params)
        return jnp.sqrt(jnp.sum(jet[1, :2] ** 2))
    return jax.vmap(one)(jnp.asarray(ts))


def singular_families(ctrl: DynamicLinearization, geometry):
    """Pieces of the singular set as (state index, pinned value): chi1/eta1 = 0, beta_i = 0,
    and for (1,1) the lever L sin(beta) + e cos(beta) = 0."""
    n = ctrl.robot.n_state
    name = ctrl.robot.name
    fams = [(n, 0.0)]                          # first compensator state: chi1 or eta1
    if name == "(1,1)":
        fams.append((3, jnp.arctan2(-geometry.e, geometry.L)))
    if name == "(1,2)":
        fams += [(3, 0.0), (4, 0.0)]
    return fams


def m1_numerical(ctrl: DynamicLinearization, params: DynamicParams, ts, iters: int = 40, damping: float = 1e-6):
    r"""M1(t) of Remark 16 (eq 58): :math:`\min \|\zeta - \zeta_{ref}(t)\|` over the singular set.

    The singular set is the image under :math:`\Psi` of the states on each singular family
    (:func:`singular_families`); for each family and time, Levenberg-Marquardt minimises
    :math:`\|\Psi(z) - \zeta_{ref}(t)\|` over the free coordinates from the reference's own
    state and from headings rotated by pi/2, pi, -pi/2. Vmapped over time. A local method:
    it returns an upper bound of the true distance, equal to it when a start lies in the
    right basin (checked against the closed forms in the tests). An upper bound is not
    conservative for Lemma 2, which needs a lower bound on the distance: :func:`lemma2`
    uses the closed form wherever it exists, and :func:`verify` checks any certificate
    against simulation.

    Returns:
      (T,) array.
    """
    g = params.geometry
    r = ctrl.relative_degree

    def dist_family(t, idx, val, dtheta):
        zref = ctrl.reference_state(t, params).at[2].add(dtheta)
        target = ctrl.reference_jet(t, params)[:r].reshape(-1)
        free = jnp.arange(ctrl.n_state) != idx
        sel = jnp.where(free, size=ctrl.n_state - 1)[0]

        def full(p):
            return zref.at[sel].set(p).at[idx].set(val)

        def resid(p):
            return ctrl.psi(full(p), g).reshape(-1) - target

        def lm(p, _):
            res = resid(p)
            J = jax.jacfwd(resid)(p)
            H = J.T @ J
            step = jnp.linalg.solve(H + damping * (1.0 + jnp.trace(H)) * jnp.eye(p.shape[0]), J.T @ res)
            p_new = p - step
            better = jnp.sum(resid(p_new) ** 2) < jnp.sum(res**2)
            return jnp.where(better, p_new, p), None

        p, _ = jax.lax.scan(lm, zref[sel], None, length=iters)
        return jnp.sqrt(jnp.sum(resid(p) ** 2))

    fams = singular_families(ctrl, g)
    starts = (0.0, 0.5 * math.pi, math.pi, -0.5 * math.pi)

    def one(t):
        # multi-start over the heading: from theta_ref alone LM can sit on a saddle
        return jnp.min(jnp.stack([dist_family(t, i, v, d) for i, v in fams for d in starts]))

    return jax.vmap(one)(jnp.asarray(ts))


# --- K2 -------------------------------------------------------------------------------

def k2_paper(ts):
    r"""Eq (64): :math:`K_2(t) = 2\sqrt2(1 + 1/\sqrt2)\,e^{-(1 - 1/\sqrt2)t}` (§6.1 gains: double pole -1)."""
    ts = jnp.asarray(ts)
    return 2.0 * math.sqrt(2.0) * (1.0 + 1.0 / math.sqrt(2.0)) * jnp.exp(-(1.0 - 1.0 / math.sqrt(2.0)) * ts)


class LyapunovBound(NamedTuple):
    """:math:`\\|e^{At}\\| \\le K_1 e^{-r_1 t}` from :math:`A^TP + PA = -I`."""

    K1: jnp.ndarray
    r1: jnp.ndarray
    P: jnp.ndarray


def lyapunov_bound(A) -> LyapunovBound:
    r"""Automatic K2 from any Hurwitz A: with :math:`V = x^TPx`, :math:`\dot V = -\|x\|^2 \le -V/\lambda_{max}(P)`,
    so :math:`\|x(t)\| \le \sqrt{\lambda_{max}/\lambda_{min}}\, e^{-t/(2\lambda_{max})}\|x(0)\|`.

    Raises:
      ValueError: if A is not Hurwitz (no positive definite solution).
    """
    A = jnp.asarray(A)
    n = A.shape[0]
    Av = concrete(A)
    if Av is not None and not np.all(np.linalg.eigvals(Av).real < 0):
        raise ValueError(f"error matrix is not Hurwitz (eigenvalues {np.linalg.eigvals(Av)}); "
                         "the closed-loop poles must be at -poles with poles > 0")
    eye = jnp.eye(n, dtype=A.dtype)
    # vec(A^T P + P A) = (I kron A^T + A^T kron I) vec(P)   (column-major vec)
    L = jnp.kron(eye, A.T) + jnp.kron(A.T, eye)
    P = jnp.linalg.solve(L, -eye.reshape(-1, order="F")).reshape(n, n, order="F")
    P = 0.5 * (P + P.T)
    ev = jnp.linalg.eigvalsh(P)
    return LyapunovBound(jnp.sqrt(ev[-1] / ev[0]), 0.5 / ev[-1], P)


def k2_lyapunov(A, ts):
    """K2(t) = K1 exp(-r1 t) of :func:`lyapunov_bound`."""
    b = lyapunov_bound(A)
    return b.K1 * jnp.exp(-b.r1 * jnp.asarray(ts))


def k2_exact(A, ts):
    r"""The smallest valid K2: :math:`\|e^{At}\|_2` (largest singular value), vmapped over t."""
    A = jnp.asarray(A)
    return jax.vmap(lambda t: jnp.linalg.norm(jax.scipy.linalg.expm(A * t), ord=2))(jnp.asarray(ts))


# --- F, radii, condition (52) -------------------------------------------------------

class Certificate(NamedTuple):
    """A Lemma 2 certificate on a time grid."""

    ts: jnp.ndarray
    m1: jnp.ndarray
    k2: jnp.ndarray
    F: jnp.ndarray
    radius: jnp.ndarray      # min_t F(t)
    argmin: jnp.ndarray      # where the minimum is attained [s]


def certificate(ts, m1, k2, eps) -> Certificate:
    """F(t) = (M1(t) - eps) / K2(t) and the certified radius min_t F(t) (eq 52)."""
    ts, m1, k2 = jnp.asarray(ts), jnp.asarray(m1), jnp.asarray(k2)
    F = (m1 - eps) / k2
    i = jnp.argmin(F)
    return Certificate(ts, m1, k2, F, F[i], ts[i])


def check_lemma2_args(eps, t_final, m1=None) -> None:
    """ValueError for eps <= 0, horizon <= 0, or a reference reaching the singular set (M1 <= eps)."""
    if not (np.isfinite(eps) and eps > 0):
        raise ValueError(f"eps must be > 0 (Lemma 2's margin), got {eps!r}")
    if not (np.isfinite(t_final) and t_final > 0):
        raise ValueError(f"the horizon must be > 0 [s], got {t_final!r}")
    if m1 is not None:
        m = np.asarray(m1)
        if not np.all(np.isfinite(m)) or np.min(m) <= eps:
            low = np.nanmin(np.where(np.isfinite(m), m, 0.0))
            raise ValueError(f"the reference comes within eps = {eps} of the singular set (min M1 = {low:.3g}; "
                             "non-finite where it stops): "
                             "Lemma 2 certifies nothing (condition 2 fails); shorten the horizon or change the reference")


def lemma2(ctrl: DynamicLinearization, params: DynamicParams, t_final: float, eps: float, n_t: int = 1001,
           m1: str = "auto") -> dict:
    """All certificates of this module for one closed loop over [0, t_final].

    Args:
      m1: "closed" (Lemma 3 analogues), "numerical" (Remark 16), or "auto" (closed form
        where it exists).

    Returns:
      dict of :class:`Certificate` keyed "paper" (only for double poles at -1, r = 2),
      "lyapunov", "exact_norm", plus "m1_method".
    """
    check_lemma2_args(eps, t_final)
    A = ctrl.error_matrix(params.gains)
    ts = jnp.linspace(0.0, t_final, n_t)
    use_closed = m1 == "closed" or (m1 == "auto" and ctrl.robot.name != "(1,2)")
    m1v = m1_closed_form(ctrl, params, ts) if use_closed else m1_numerical(ctrl, params, ts)
    check_lemma2_args(eps, t_final, m1v)
    out = {"m1_method": "closed form (Lemma 3)" if use_closed else "numerical (Remark 16)"}
    poles = np.asarray(params.gains.poles)
    if ctrl.relative_degree == 2 and np.allclose(poles, 1.0):
        out["paper"] = certificate(ts, m1v, k2_paper(ts), eps)
    out["lyapunov"] = certificate(ts, m1v, k2_lyapunov(A, ts), eps)
    out["exact_norm"] = certificate(ts, m1v, k2_exact(A, ts), eps)
    return out


# --- empirical verification ------------------------------------------------------------

def sample_sphere(key, n, dim):
    """n points uniformly on the unit sphere in R^dim."""
    x = jax.random.normal(key, (n, dim))
    return x / jnp.linalg.norm(x, axis=1, keepdims=True)


def verify(ctrl: DynamicLinearization, params: DynamicParams, initial_errors, k2_fn, *, dt: float, n_steps: int,
           save_every: int = 10, tol: float = 1e-6) -> dict:
    r"""Simulate from :math:`\zeta(0) = \zeta_{ref}(0) + \tilde\zeta_0` and check (53) and regularity.

    Args:
      initial_errors: (N, r*m) initial errors (Table 4 ordering, see ``ctrl.error``).
      k2_fn: ``ts -> K2(ts)``, the bound to check.
      dt, n_steps, save_every: integration grid.
      tol: absolute slack for (53), covering integration error.

    Returns:
      dict of per-run arrays: ``norm0`` (N,), ``violation_53`` (N,) bool, ``singular`` (N,)
      bool, ``max_ratio`` (N,) = max_t ||err(t)|| / (K2(t) ||err(0)||), ``min_margin`` (N,).
    """
    r = ctrl.relative_degree
    g = params.geometry
    zeta_ref0 = ctrl.reference_jet(jnp.asarray(0.0), params)[:r]
    branch = float(ctrl.reference_branch(params))

    def one(e0):
        zeta0 = zeta_ref0 + e0.reshape(r, ctrl.m)
        z0 = ctrl.inverse_psi(zeta0, g, branch)
        tr = simulate(ctrl, z0, params, dt=dt, n_steps=n_steps, save_every=save_every)
        err = jax.vmap(lambda t, z: ctrl.error(t, z, params).reshape(-1))(tr.t, tr.state)
        nrm = jnp.linalg.norm(err, axis=1)
        n0 = jnp.linalg.norm(e0)
        bound = k2_fn(tr.t) * n0
        viol = jnp.any(tr.valid & (nrm > bound + tol))
        ratio = jnp.max(jnp.where(tr.valid, nrm / jnp.maximum(bound, 1e-300), 0.0))
        wrong_branch = ctrl.branch_quantity(z0, g) * branch <= 0
        return n0, viol, tr.diagnostics.failed | wrong_branch, ratio, tr.diagnostics.min_margin

    n0, viol, sing, ratio, mm = jax.jit(jax.vmap(one))(jnp.asarray(initial_errors))
    return {"norm0": n0, "violation_53": viol, "singular": sing, "max_ratio": ratio, "min_margin": mm}
