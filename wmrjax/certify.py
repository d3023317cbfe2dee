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

import functools
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

    For (1,2), :math:`\eta_1\sin\beta_1\sin\beta_2 = 0` exactly when the body-frame lateral
    velocity of P vanishes (both wheels' lateral components equal it), i.e. on the curved
    hypersurface :math:`\sigma(\zeta) = \cos\theta\,\dot h_1 + \sin\theta\,\dot h_2 + e\sin\delta\,\dot\theta = 0`.
    For fixed :math:`\theta` it is a hyperplane in :math:`(\dot h_1, \dot h_2, \dot\theta)` with
    normal :math:`(\cos\theta, \sin\theta, e\sin\delta)`, so
    :math:`M_1^2 = \min_\theta (\theta - \theta_{ref})^2 + \sigma_\theta(\zeta_{ref})^2 / (1 + e^2\sin^2\delta)`,
    a one-dimensional minimisation (grid over a full turn, then golden section).

    Args:
      ctrl, params: the closed loop.
      ts: (T,) times [s].

    Returns:
      (T,) array.
    """
    g = params.geometry
    if ctrl.robot.name == "(1,2)":
        es = g.e * jnp.sin(g.delta)
        grid = jnp.linspace(-math.pi, math.pi, 721)
        gr = 0.5 * (math.sqrt(5.0) - 1.0)

        def one(t):
            jet = ctrl.reference_jet(t, params)
            th_r, v = jet[0, 2], jet[1]

            def d2(dth):
                s, c = jnp.sin(th_r + dth), jnp.cos(th_r + dth)
                sig = c * v[0] + s * v[1] + es * v[2]
                return dth**2 + sig**2 / (1.0 + es**2)

            vals = jax.vmap(d2)(grid)
            i = jnp.argmin(vals)
            lo, hi = grid[jnp.maximum(i - 1, 0)], grid[jnp.minimum(i + 1, grid.shape[0] - 1)]

            def golden(c, _):
                lo, hi = c
                x1, x2 = hi - gr * (hi - lo), lo + gr * (hi - lo)
                left = d2(x1) <= d2(x2)
                return (jnp.where(left, lo, x1), jnp.where(left, x2, hi)), None

            (lo, hi), _ = jax.lax.scan(golden, (lo, hi), None, length=60)
            return jnp.sqrt(jnp.minimum(d2(0.5 * (lo + hi)), vals[i]))

        return jax.vmap(one)(jnp.asarray(ts))

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
      m1: "closed" (Lemma 3 and analogues, every type; the default "auto" is the same) or
        "numerical" (Remark 16 by local search: an upper bound, not conservative).

    Returns:
      dict of :class:`Certificate` keyed "paper" (only for double poles at -1, r = 2),
      "lyapunov", "exact_norm", plus "m1_method".
    """
    check_lemma2_args(eps, t_final)
    A = ctrl.error_matrix(params.gains)
    ts = jnp.linspace(0.0, t_final, n_t)
    use_closed = m1 in ("closed", "auto")
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
    branch = jnp.asarray(float(ctrl.reference_branch(params)))
    n_saves = n_steps // save_every
    ts = dt * save_every * jnp.arange(n_saves + 1, dtype=jnp.result_type(float))
    ts = ts.at[-1].set(dt * n_steps)
    k2 = jnp.asarray(k2_fn(ts))   # the bound on the saved grid: one compiled program for every K2
    n0, viol, sing, ratio, mm = _verify(ctrl, params, jnp.asarray(initial_errors), k2, branch, tol, dt, n_steps,
                                        save_every)
    return {"norm0": n0, "violation_53": viol, "singular": sing, "max_ratio": ratio, "min_margin": mm}


@functools.partial(jax.jit, static_argnums=(0, 6, 7, 8))
def _verify(ctrl, params, errs, k2, branch, tol, dt, n_steps, save_every):
    g = params.geometry

    def one(e0):
        tr, z0 = _run_from_error(ctrl, params, e0, branch, dt, n_steps, save_every)
        err = jax.vmap(lambda t, z: ctrl.error(t, z, params).reshape(-1))(tr.t, tr.state)
        nrm = jnp.linalg.norm(err, axis=1)
        n0 = jnp.linalg.norm(e0)
        bound = k2 * n0
        viol = jnp.any(tr.valid & (nrm > bound + tol))
        ratio = jnp.max(jnp.where(tr.valid, nrm / jnp.maximum(bound, 1e-300), 0.0))
        wrong_branch = ctrl.branch_quantity(z0, g) * branch <= 0
        return n0, viol, tr.diagnostics.failed | wrong_branch, ratio, tr.diagnostics.min_margin

    return jax.vmap(one)(errs)


# --- beyond Lemma 2: the exact error map ------------------------------------------------
#
# While a run stays regular the linearized error obeys zeta_err(t) = expm(A t) zeta_err(0)
# *exactly*, so the set of safe initial errors is known without any K2 bound. For the types
# whose singular set in zeta coordinates is the linear subspace {velocity of the output
# point = 0} ((2,0), (2,1), (1,1)), the distance to it is ||C zeta|| with C selecting those
# two rows; the largest safe ball is then the solution of a semi-infinite problem over t whose
# inner problem (fixed t) is a convex QCQP solved here in closed form up to a scalar secular
# equation. (1,2)'s singular set is curved: use the falsifier (an upper bound) there.

def singular_rows(ctrl: DynamicLinearization):
    """Flat indices (into ``ctrl.error(...).reshape(-1)``) of the output point's velocity,
    whose vanishing is the singular set; ``None`` where the singular set is curved ((1,2))."""
    if ctrl.robot.name == "(1,2)":
        return None
    return (ctrl.m, ctrl.m + 1)


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


def _min_norm_to_ball(M, a, eps, iters: int = 200):
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


def exact_map_radius(ctrl: DynamicLinearization, params: DynamicParams, t_final: float, eps: float,
                     basis="full", n_t: int = 2001, refine: int = 40) -> ExactMapRadius:
    r"""Exact safe radius from the linear error map (semi-infinite over t; grid then golden section).

    With :math:`\tilde\zeta(t) = e^{At}P s` (P the slice basis) and the singular set
    :math:`\{C\zeta = 0\}`, the run comes within :math:`\epsilon` of it at time t iff
    :math:`\|C\zeta_{ref}(t) + C e^{At} P s\| < \epsilon`. For each t the smallest such
    :math:`\|s\|` is :func:`_min_norm_to_ball`; the radius is its minimum over [0, T]. Every
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
    check_lemma2_args(eps, t_final)
    rows = singular_rows(ctrl)
    if rows is None:
        raise ValueError("type (1,2) has a curved singular set: no exact-map radius; use falsify/falsified_radius")
    P = slice_basis(ctrl, basis)
    C = jnp.eye(ctrl.relative_degree * ctrl.m)[jnp.asarray(rows)]
    r = ctrl.relative_degree
    ts = jnp.linspace(0.0, t_final, n_t)
    m1 = jax.vmap(lambda t: jnp.linalg.norm(C @ ctrl.reference_jet(t, params)[:r].reshape(-1)))(ts)
    check_lemma2_args(eps, t_final, m1)
    rho, rad, t_star, worst = _exact_map(ctrl, params, P, C, jnp.asarray(eps, ts.dtype), ts, refine)
    return ExactMapRadius(ts, rho, rad, t_star, worst)


@functools.partial(jax.jit, static_argnums=(0, 6))
def _exact_map(ctrl, params, P, C, eps, ts, refine):
    """Grid minimum of rho(t), refined by golden section (one compiled program per type and slice shape)."""
    A = ctrl.error_matrix(params.gains)
    r = ctrl.relative_degree

    def rho_x(t):
        a = C @ ctrl.reference_jet(t, params)[:r].reshape(-1)
        return _min_norm_to_ball(C @ jax.scipy.linalg.expm(A * t) @ P, a, eps)

    rho = jax.vmap(lambda t: rho_x(t)[0])(ts)
    i = jnp.argmin(rho)
    lo, hi = ts[jnp.maximum(i - 1, 0)], ts[jnp.minimum(i + 1, ts.shape[0] - 1)]
    g = 0.5 * (math.sqrt(5.0) - 1.0)

    def golden(c, _):
        lo, hi = c
        x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
        left = rho_x(x1)[0] <= rho_x(x2)[0]
        return (jnp.where(left, lo, x1), jnp.where(left, x2, hi)), None

    (lo, hi), _ = jax.lax.scan(golden, (lo, hi), None, length=refine)
    tr = 0.5 * (lo + hi)
    rr, _ = rho_x(tr)
    t_star = jnp.where(rr < rho[i], tr, ts[i])
    rad, xs = rho_x(t_star)
    return rho, rad, t_star, P @ xs


# --- running the real closed loop from initial errors ---------------------------------------

def _run_from_error(ctrl, params, e0, branch, dt, n_steps, save_every):
    r = ctrl.relative_degree
    zeta0 = ctrl.reference_jet(jnp.asarray(0.0), params)[:r] + e0.reshape(r, ctrl.m)
    z0 = ctrl.inverse_psi(zeta0, params.geometry, branch)
    return simulate(ctrl, z0, params, dt=dt, n_steps=n_steps, save_every=save_every), z0


def _distance_along(ctrl, params, tr, chord=False):
    """Per saved interval, dist(zeta(t), singular set) at its samples (closed-form types; else
    the margin |det K|). Returns ``(distance (N-1,), valid (N-1,))``.

    With ``chord``, minimised over the chord between the two samples instead: the velocity of
    the output point can sweep past zero between samples, and the chord sees that, for the
    falsifier's gradient. The chord cuts inside the curve by O(dt^2), so it may under-estimate;
    failures are therefore always confirmed on samples, which over-estimate."""
    rows = singular_rows(ctrl)
    valid = tr.valid[1:] & tr.valid[:-1]
    if rows is None:
        return jnp.minimum(tr.margin[1:], tr.margin[:-1]), valid
    v = jax.vmap(lambda z: ctrl.psi(z, params.geometry).reshape(-1))(tr.state)[:, jnp.asarray(rows)]
    if not chord:
        return jnp.minimum(jnp.linalg.norm(v[1:], axis=1), jnp.linalg.norm(v[:-1], axis=1)), valid
    a, d = v[:-1], v[1:] - v[:-1]
    s = jnp.clip(-jnp.sum(a * d, axis=1) / jnp.maximum(jnp.sum(d * d, axis=1), 1e-300), 0.0, 1.0)
    return jnp.linalg.norm(a + s[:, None] * d, axis=1), valid


def min_distance(ctrl: DynamicLinearization, params: DynamicParams, initial_errors, *, dt: float, n_steps: int,
                 save_every: int = 1):
    r"""Simulate from :math:`\zeta_{ref}(0) + \tilde\zeta_0` and return, per run,
    :math:`\min_t \mathrm{dist}(\zeta(t), S)` and whether the simulator flagged it singular.

    For (1,2), whose singular set is curved, the measure is :math:`\min_t |\det K|` instead.

    Args:
      initial_errors: (N, r m). Returns: ``(dist (N,), singular (N,) bool)``.
    """
    branch = jnp.asarray(float(ctrl.reference_branch(params)))
    return _min_distance(ctrl, params, jnp.asarray(initial_errors), branch, dt, n_steps, save_every)


@functools.partial(jax.jit, static_argnums=(0, 4, 5, 6))
def _min_distance(ctrl, params, errs, branch, dt, n_steps, save_every):
    def one(e0):
        tr, z0 = _run_from_error(ctrl, params, e0, branch, dt, n_steps, save_every)
        dist, valid = _distance_along(ctrl, params, tr)
        d = jnp.min(jnp.where(valid, dist, jnp.inf))
        wrong = ctrl.branch_quantity(z0, params.geometry) * branch <= 0
        fail = tr.diagnostics.failed | wrong
        return jnp.where(fail, 0.0, d), fail

    return jax.vmap(one)(errs)


def empirical_radius(ctrl: DynamicLinearization, params: DynamicParams, directions, r_max: float, eps: float, *,
                     dt: float, n_steps: int, n_grid: int = 48, n_dips: int = 3, n_golden: int = 30,
                     n_bisect: int = 20) -> dict:
    r"""Empirical safe radius per direction by simulation: the smallest :math:`\rho \le` ``r_max``
    at which the run from :math:`\rho d` comes within ``eps`` of the singular set (or is flagged).

    Along a ray, :math:`m(\rho) = \min_t \mathrm{dist}(\zeta(t), S)` dips below eps only on a
    narrow interval (past it, the velocity of the output point swings around zero instead of
    through it), which a plain grid misses. So: sample m on ``n_grid`` radii, minimise it by
    golden section inside the brackets of the first ``n_dips`` local minima, and bisect for the
    first crossing of eps. All rounds are vmapped over (direction, dip). Rays that never fail
    report ``inf``.

    Args:
      directions: (D, r m) unit vectors.

    Returns:
      dict with ``per_direction`` (D,), ``radius`` (min over directions), ``worst_direction``,
      ``n_runs`` (simulations used).
    """
    dirs = np.asarray(directions)
    D = dirs.shape[0]
    g = np.linspace(0.0, r_max, n_grid + 1)[1:]
    runs = 0

    def m_of(dd, rr):
        nonlocal runs
        runs += rr.size
        e = dd * rr[:, None]
        n = max(64, 1 << (len(e) - 1).bit_length())       # few distinct batch sizes: few compilations
        e = np.concatenate([e, np.repeat(e[:1], n - len(e), axis=0)])
        d, s = min_distance(ctrl, params, jnp.asarray(e), dt=dt, n_steps=n_steps)
        return np.where(np.asarray(s), 0.0, np.asarray(d))[: len(rr)]

    m = m_of(np.repeat(dirs, n_grid, axis=0), np.tile(g, D)).reshape(D, n_grid)
    padded = np.concatenate([np.full((D, 1), np.inf), m, np.full((D, 1), np.inf)], axis=1)
    is_min = (padded[:, 1:-1] <= padded[:, :-2]) & (padded[:, 1:-1] <= padded[:, 2:])
    # brackets [lo, hi] around the n_dips deepest local minima of each ray (padding repeats one)
    lo = np.zeros((D, n_dips))
    hi = np.zeros((D, n_dips))
    for k in range(D):
        idx = np.where(is_min[k])[0]
        idx = list(idx[np.argsort(m[k, idx])][:n_dips])
        idx += [idx[-1]] * (n_dips - len(idx))
        lo[k] = [g[j - 1] if j > 0 else 0.0 for j in idx]
        hi[k] = [g[min(j + 1, n_grid - 1)] for j in idx]
    dd = np.repeat(dirs, n_dips, axis=0)
    a, b = lo.reshape(-1), hi.reshape(-1)
    gr = 0.5 * (math.sqrt(5.0) - 1.0)
    for _ in range(n_golden):
        x1, x2 = b - gr * (b - a), a + gr * (b - a)
        m12 = m_of(np.concatenate([dd, dd]), np.concatenate([x1, x2]))
        left = m12[: len(a)] <= m12[len(a):]
        a, b = np.where(left, a, x1), np.where(left, x2, b)
    r_star = 0.5 * (a + b)
    dips = m_of(dd, r_star) < eps
    # first crossing of eps: below every failing dip, and below the first failing grid radius
    first = np.where((m < eps).any(axis=1), (m < eps).argmax(axis=1), -1)
    g0 = np.concatenate([[0.0], g])
    cand_lo = np.concatenate([lo.reshape(-1), g0[np.maximum(first, 0)]])
    cand_hi = np.concatenate([np.where(dips, r_star, np.inf), np.where(first >= 0, g[np.maximum(first, 0)], np.inf)])
    cand_d = np.concatenate([dd, dirs])
    owner = np.concatenate([np.repeat(np.arange(D), n_dips), np.arange(D)])
    live = np.isfinite(cand_hi)
    cl, ch = cand_lo[live], cand_hi[live]
    for _ in range(n_bisect if live.any() else 0):
        mid = 0.5 * (cl + ch)
        fail = m_of(cand_d[live], mid) < eps
        ch, cl = np.where(fail, mid, ch), np.where(fail, cl, mid)
    per = np.full(D, np.inf)
    np.minimum.at(per, owner[live], ch)
    k = int(np.argmin(per))
    return {"per_direction": per, "radius": float(per[k]), "worst_direction": dirs[k], "n_runs": runs}


# --- falsification ----------------------------------------------------------------------

class Falsification(NamedTuple):
    """Result of :func:`falsify` at one radius."""

    initial_errors: jnp.ndarray   # (S, r m) final iterate of every start
    distance: jnp.ndarray         # (S,) min_t dist(zeta(t), S) (margin for (1,2)) of each
    best: jnp.ndarray             # index of the worst case found


def falsify(ctrl: DynamicLinearization, params: DynamicParams, radius, starts, *, dt: float, n_steps: int,
            basis="full", steps: int = 60, learning_rate: float = 0.1, n_windows: int = 8) -> Falsification:
    r"""Gradient search for the worst initial error on the sphere :math:`\|\tilde\zeta_0\| = \rho`.

    Minimises :math:`\min_t \mathrm{dist}(\zeta(t), S)` over the simulated closed loop (reverse-mode
    through the RK4 scan) with optax Adam on an unconstrained :math:`u`, mapped to the sphere by
    :math:`\tilde\zeta_0 = \rho P u / \|u\|` (projection), from every start at once (vmapped).
    Random sampling misses thin unsafe cones; following the gradient does not need to hit them.

    A single objective :math:`\min_{t\in[0,T]}` has one dominant basin (the time at which most
    directions come closest), and thin cones at other times are missed. So start i minimises
    the distance over its own window of the horizon, window ``i % n_windows`` of
    ``n_windows`` equal ones: every part of the horizon is searched. Adam's step decays
    100-fold over the run, so iterates settle inside eps-thin sets.

    Args:
      radius: sphere radius rho.
      starts: (S, k) initial directions in slice coordinates (need not be normalised).
      basis: slice, see :func:`slice_basis`.
      steps, learning_rate: Adam iterations and initial step size (on the unit sphere).
      n_windows: number of time windows the starts are spread over.
    """
    P = slice_basis(ctrl, basis)
    branch = jnp.asarray(float(ctrl.reference_branch(params)))
    u0 = jnp.asarray(starts)
    edges = jnp.linspace(0.0, dt * n_steps, n_windows + 1)
    win = jnp.arange(u0.shape[0]) % n_windows
    windows = jnp.stack([edges[win] - 0.5 * dt, edges[win + 1] + 0.5 * dt], axis=1)
    us, vals = _falsify(ctrl, params, jnp.asarray(radius, dtype=u0.dtype), u0 / jnp.linalg.norm(u0, axis=1, keepdims=True),
                        windows, P, branch, dt, n_steps, steps, learning_rate)
    errs = radius * (us / jnp.linalg.norm(us, axis=1, keepdims=True)) @ P.T
    return Falsification(errs, vals, jnp.argmin(vals))


@functools.partial(jax.jit, static_argnums=(0, 7, 8, 9, 10))
def _falsify(ctrl, params, radius, us, windows, P, branch, dt, n_steps, steps, learning_rate):
    import optax

    opt = optax.adam(optax.exponential_decay(learning_rate, steps, 0.01))

    def objective(u, window):
        e0 = radius * (P @ (u / jnp.linalg.norm(u)))
        tr, _ = _run_from_error(ctrl, params, e0, branch, dt, n_steps, 1)
        inside = (tr.t[1:] >= window[0]) & (tr.t[:-1] <= window[1])
        dist, valid = _distance_along(ctrl, params, tr, chord=True)
        d = jnp.min(jnp.where(valid & inside, dist, jnp.inf))
        return jnp.where(tr.diagnostics.failed, 0.0, d)

    vg = jax.vmap(jax.value_and_grad(objective))

    def step(c, _):
        us, state, best_u, best_v = c
        v, g = vg(us, windows)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        better = v < best_v
        best_u = jnp.where(better[:, None], us, best_u)
        best_v = jnp.where(better, v, best_v)
        upd, state = opt.update(g, state, us)
        us = optax.apply_updates(us, upd)
        us = us / jnp.linalg.norm(us, axis=1, keepdims=True)
        return (us, state, best_u, best_v), None

    init = (us, opt.init(us), us, jnp.full(us.shape[0], jnp.inf))
    (us, _, best_u, best_v), _ = jax.lax.scan(step, init, None, length=steps)
    v_last = jax.vmap(objective)(us, windows)
    better = v_last < best_v
    return jnp.where(better[:, None], us, best_u), jnp.where(better, v_last, best_v)


def falsified_radius(ctrl: DynamicLinearization, params: DynamicParams, eps: float, r_hi: float, key, *,
                     dt: float, n_steps: int, basis="full", n_starts: int = 16, steps: int = 60,
                     n_bisect: int = 8, learning_rate: float = 0.1, r_lo: float = 0.0, n_windows: int = 4) -> dict:
    """The smallest radius at which the falsifier finds a failure (dist < eps or singular), by bisection.

    Starts at ``r_hi`` (doubled up to 4 times until a failure is found), then bisects between
    ``r_lo`` (typically a certified radius) and the failing radius, warm-starting the directions.
    Any failure found is confirmed by a fresh simulation. An upper bound on the true safe radius:
    every certified radius must be below it.

    Returns:
      dict: ``radius`` (None if nothing failed up to 16 r_hi), ``initial_error`` (r m,),
      ``distance`` at the failure, ``rollouts`` (simulations used, a gradient counts one).
    """
    check_lemma2_args(eps, 1.0)
    P = slice_basis(ctrl, basis)
    if P.shape[1] == 2:     # a plane: evenly spaced angles, randomly rotated
        ang = jnp.linspace(0.0, 2.0 * math.pi, n_starts, endpoint=False) + jax.random.uniform(key, (), maxval=math.pi)
        starts = jnp.stack([jnp.cos(ang), jnp.sin(ang)], axis=1)
    else:
        starts = jax.random.normal(key, (n_starts, P.shape[1]))
    rollouts = 0

    def attempt(rad, st):
        nonlocal rollouts
        f = falsify(ctrl, params, rad, st, dt=dt, n_steps=n_steps, basis=basis, steps=steps,
                    learning_rate=learning_rate, n_windows=n_windows)
        rollouts += n_starts * (steps + 1)
        e = f.initial_errors[int(f.best)]
        # confirm on samples (which over-estimate the distance) of a ten times finer run: the
        # velocity can sweep past zero within one coarse step
        d, s = min_distance(ctrl, params, e[None], dt=0.1 * dt, n_steps=10 * n_steps)
        ok = bool(d[0] < eps) or bool(s[0])
        dirs = jnp.einsum("nk,sn->sk", P, f.initial_errors)
        return ok, e, float(d[0]), dirs

    hi, found = float(r_hi), None
    for _ in range(5):
        ok, e, d, dirs = attempt(hi, starts)
        starts = dirs
        if ok:
            found = (hi, e, d)
            break
        r_lo, hi = hi, 2.0 * hi
    if found is None:
        return {"radius": None, "initial_error": None, "distance": None, "rollouts": rollouts,
                "searched_up_to": hi / 2.0}
    lo = r_lo
    for _ in range(n_bisect):
        mid = 0.5 * (lo + found[0])
        ok, e, d, dirs = attempt(mid, starts)
        if ok:
            found, starts = (mid, e, d), dirs
        else:
            lo = mid
    return {"radius": found[0], "initial_error": np.asarray(found[1]), "distance": found[2], "rollouts": rollouts,
            "bracket": [lo, found[0]]}
