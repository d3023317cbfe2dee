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
  exactly while the run is regular); for a :class:`wmrjax.GainSchedule` the error obeys
  :math:`\dot{\tilde\zeta} = A(t)\tilde\zeta` and :math:`K_2(t) = \|\Phi(t, 0)\|_2`
  (:func:`k2_transition`) is the only certificate;
* :math:`F(t)`, the certified radius :math:`\min_t F(t)` and condition (52);
* :func:`wmrjax.certify.verify`: batch rollouts from initial errors sampled in and around a radius,
  counting violations of (53) and singularity events.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math, linearize
from wmrjax._validate import concrete
from wmrjax.controllers.dynamic import DynamicLinearization, DynamicParams
from wmrjax.references import check_domain

# --- M1 -------------------------------------------------------------------------------


def check_eager(name: str, params, why: str) -> None:
    """ValueError when ``params`` are traced (inside ``jax.jit`` or ``jax.vmap``): ``name`` runs
    eagerly (``why``); a raw TracerArrayConversionError otherwise."""
    if any(concrete(x) is None for x in jax.tree_util.tree_leaves(params)):
        raise ValueError(
            f"{name} runs eagerly ({why}): call it outside jax.jit / jax.vmap, with concrete params"
            + (
                "; differentiable_exact_map_radius is the version that runs under jit, grad and vmap"
                if name == "exact_map_radius"
                else ""
            )
        )


def check_dynamic(ctrl, params=None) -> None:
    """ValueError unless ``ctrl`` is a dynamic linearizing law (the only one Lemma 2 is about)
    and ``params`` (when given) are its parameters."""
    if not isinstance(ctrl, DynamicLinearization):
        raise ValueError(
            f"certification needs a dynamic linearizing controller (wmrjax.dynamic_linearization), got "
            f"{type(ctrl).__name__}: Lemma 2's M1 is the distance of the reference's output jet to the singular "
            "set of Psi (Remark 16), which a static law does not have"
        )
    if params is not None:
        ctrl.check_params(params)


def m1_closed_form(ctrl: DynamicLinearization, params: DynamicParams, ts):
    r"""M1(t) in closed form: the distance of :math:`\zeta_{ref}(t)` to the singular set (Remark 16).

    The distance is the row's :attr:`~wmrjax.controllers.dynamic.Table4Row.singular_distance`:
    :math:`\|\dot h_{ref}\|` where the singular set is :math:`\{\dot h = 0\}` ((2,0), (1,1):
    :math:`|(\chi_1)_{ref}|`, eq 59; (2,1): :math:`|(\eta_1)_{ref}|`), and for (1,2) a
    one-dimensional minimisation over theta (its singular set is curved).

    Args:
      ctrl: the closed loop (a dynamic linearizing law).
      params: its parameters.
      ts: (T,) times [s].

    Returns:
      (T,) array.
    """
    check_dynamic(ctrl, params)
    return _m1_closed(ctrl, params, jnp.asarray(ts))


@functools.partial(jax.jit, static_argnums=0)
def _m1_closed(ctrl, params, ts):
    return jax.vmap(lambda t: ctrl.singular_distance(ctrl.reference_jet(t, params), params))(ts)


M1_ITERS, M1_DAMPING = 40, 1e-6  # m1_numerical's Levenberg-Marquardt: iterations and relative damping


def m1_numerical(
    ctrl: DynamicLinearization, params: DynamicParams, ts, iters: int = M1_ITERS, damping: float = M1_DAMPING
):
    r"""M1(t) of Remark 16 (eq 58): :math:`\min \|\zeta - \zeta_{ref}(t)\|` over the singular set.

    The singular set is the image under :math:`\Psi` of the states on each singular family
    (``ctrl.row.singular_families``); for each family and time, Levenberg-Marquardt minimises
    :math:`\|\Psi(z) - \zeta_{ref}(t)\|` over the free coordinates from the reference's own
    state and from headings rotated by pi/2, pi, -pi/2. Vmapped over time. A local method:
    it returns an upper bound of the true distance, equal to it when a start lies in the
    right basin (checked against the closed forms in the tests). An upper bound is not
    conservative for Lemma 2, which needs a lower bound on the distance: :func:`lemma2`
    uses the closed form wherever it exists, and :func:`wmrjax.certify.verify` checks any certificate
    against simulation.

    Returns:
      (T,) array.
    """
    check_dynamic(ctrl, params)
    return _m1_numerical(ctrl, params, jnp.asarray(ts), iters, damping)


@functools.partial(jax.jit, static_argnums=(0, 3, 4))
def _m1_numerical(ctrl, params, ts, iters, damping):
    r = ctrl.relative_degree

    def dist_family(t, idx, val, dtheta):
        zref = ctrl.reference_state(t, params).at[2].add(dtheta)
        target = ctrl.reference_jet(t, params)[:r].reshape(-1)
        free = jnp.arange(ctrl.n_state) != idx
        sel = jnp.where(free, size=ctrl.n_state - 1)[0]

        def full(p):
            return zref.at[sel].set(p).at[idx].set(val)

        def resid(p):
            return ctrl.psi(full(p), params).reshape(-1) - target

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

    fams = ctrl.row.singular_families(params.geometry)
    starts = (0.0, 0.5 * math.pi, math.pi, -0.5 * math.pi)

    def one(t):
        # multi-start over the heading: from theta_ref alone LM can sit on a saddle
        return jnp.min(jnp.stack([dist_family(t, i, v, d) for i, v in fams for d in starts]))

    return jax.vmap(one)(ts)


# --- K2 -------------------------------------------------------------------------------


def k2_paper(ts):
    r"""Eq (64): :math:`K_2(t) = 2\sqrt2(1 + 1/\sqrt2)\,e^{-(1 - 1/\sqrt2)t}` (§6.1 gains: double pole -1)."""
    ts = jnp.asarray(ts)
    return 2.0 * math.sqrt(2.0) * (1.0 + 1.0 / math.sqrt(2.0)) * jnp.exp(-(1.0 - 1.0 / math.sqrt(2.0)) * ts)


class LyapunovBound(NamedTuple):
    r""":math:`\|e^{At}\| \le K_1 e^{-r_1 t}` from :math:`A^TP + PA = -I`."""

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
    if Av is not None:
        _check_hurwitz(Av)
    eye = jnp.eye(n, dtype=A.dtype)
    # vec(A^T P + P A) = (I kron A^T + A^T kron I) vec(P)   (column-major vec)
    L = jnp.kron(eye, A.T) + jnp.kron(A.T, eye)
    P = jnp.linalg.solve(L, -eye.reshape(-1, order="F")).reshape(n, n, order="F")
    P = 0.5 * (P + P.T)
    ev = jnp.linalg.eigvalsh(P)
    return LyapunovBound(jnp.sqrt(ev[-1] / ev[0]), 0.5 / ev[-1], P)


def _check_hurwitz(A) -> None:
    """ValueError unless the concrete matrix ``A`` is Hurwitz."""
    ev = np.linalg.eigvals(np.asarray(A))
    if not np.all(ev.real < 0):
        raise ValueError(
            f"error matrix is not Hurwitz (eigenvalues {ev}); the closed-loop poles must be at -poles with poles > 0"
        )


def k2_lyapunov(A, ts):
    """K2(t) = K1 exp(-r1 t) of :func:`lyapunov_bound`."""
    b = lyapunov_bound(A)
    return b.K1 * jnp.exp(-b.r1 * jnp.asarray(ts))


def k2_exact(A, ts):
    r"""The smallest valid K2: :math:`\|e^{At}\|_2` (largest singular value), vmapped over t."""
    return _k2_exact(jnp.asarray(A), jnp.asarray(ts))


@jax.jit
def _k2_exact(A, ts):
    return jax.vmap(lambda t: _math.spectral_norm(_math.expm_small(A * t)))(ts)


TRANSITION_STEP = 1e-2  # [s] largest RK4 step of Phi(t, 0) for scheduled gains (error ~1e-10 at poles ~ -5)


def transition_steps(t_final: float, step: float = TRANSITION_STEP) -> int:
    """RK4 steps over [0, t_final] so that none is longer than ``step`` [s]."""
    return max(1, int(math.ceil(float(t_final) / step - 1e-9)))


def k2_transition(gains, ts):
    r"""The smallest valid K2 for any gains, schedules included: :math:`\|\Phi(t, 0)\|_2`.

    :math:`\Phi` is :func:`wmrjax.linearize.transition_matrices`, integrated once along the
    sorted grid by RK4 with steps of at most :data:`TRANSITION_STEP`; for constant gains it
    equals :func:`k2_exact` to that accuracy. Differentiable in the gains.

    Args:
      gains: :class:`wmrjax.Gains` or :class:`wmrjax.GainSchedule`.
      ts: (T,) concrete times >= 0 [s].
    """
    Phi = linearize.transition_matrices(gains, np.asarray(ts), max_step=TRANSITION_STEP)
    return jax.vmap(_math.spectral_norm)(Phi)


# --- F, radii, condition (52) -------------------------------------------------------


class Certificate(NamedTuple):
    """A Lemma 2 certificate on a time grid."""

    ts: jnp.ndarray
    m1: jnp.ndarray
    k2: jnp.ndarray
    F: jnp.ndarray
    radius: jnp.ndarray  # min_t F(t); from lemma2, over the grid and points between them (<= F.min())
    argmin: jnp.ndarray  # where that minimum is attained [s] (from lemma2: possibly between grid points)


def certificate(ts, m1, k2, eps) -> Certificate:
    """F(t) = (M1(t) - eps) / K2(t) and the certified radius min_t F(t) (eq 52)."""
    ts, m1, k2 = jnp.asarray(ts), jnp.asarray(m1), jnp.asarray(k2)
    F = (m1 - eps) / k2
    i = jnp.argmin(F)
    return Certificate(ts, m1, k2, F, F[i], ts[i])


def check_lemma2_args(*, t_final, eps, m1=None, reference=None) -> None:
    """ValueError for eps <= 0, horizon <= 0, a horizon past a sampled ``reference``'s samples,
    or a reference reaching the singular set (M1 <= eps)."""
    if not (np.isfinite(eps) and eps > 0):
        raise ValueError(f"eps must be > 0 (Lemma 2's margin), got {eps!r}")
    if not (np.isfinite(t_final) and t_final > 0):
        raise ValueError(f"the horizon must be > 0 [s], got {t_final!r}")
    if reference is not None:
        check_domain(reference, 0.0, float(t_final))
    if m1 is not None:
        m = np.asarray(m1)
        if not np.all(np.isfinite(m)) or np.min(m) <= eps:
            low = np.nanmin(np.where(np.isfinite(m), m, 0.0))
            raise ValueError(
                f"the reference comes within eps = {eps} of the singular set (min M1 = {low:.3g}; "
                "non-finite where it stops): "
                "Lemma 2 certifies nothing (condition 2 fails); shorten the horizon or change the reference"
            )


class Lemma2Report(NamedTuple):
    """Every Lemma 2 certificate of one closed loop (fixed fields).

    Attributes:
      paper: K2 of eq (64); only for the paper's gains (double pole at -1 per output, r = 2),
        whatever representation gave them; None otherwise.
      lyapunov: the automatic Lyapunov K2; None for a :class:`wmrjax.GainSchedule` (a
        frozen-time Lyapunov function does not bound time-varying error dynamics).
      exact_norm: K2 = ||exp(At)||, or ||Phi(t, 0)|| for a schedule.
      m1_method: how M1 was computed.
    """

    paper: Certificate | None
    lyapunov: Certificate | None
    exact_norm: Certificate
    m1_method: str

    def certificates(self) -> dict:
        """Every certificate by name (name -> :class:`Certificate`), the paper's first when it applies."""
        out = {"paper": self.paper, "lyapunov": self.lyapunov, "exact_norm": self.exact_norm}
        return {k: v for k, v in out.items() if v is not None}


M1_METHODS = ("closed", "numerical")
MIN_GRID = 3  # time samples of min F: at least both ends and a midpoint
GRID_RTOL = 1e-2  # refining the grid may lower min F by at most this fraction


def lemma2(
    ctrl: DynamicLinearization,
    params: DynamicParams,
    *,
    t_final: float,
    eps: float,
    n_t: int = 1001,
    m1: str = "closed",
) -> Lemma2Report:
    """All Lemma 2 certificates of this module for one closed loop over [0, t_final].

    Args:
      ctrl: the closed loop (a dynamic linearizing law).
      params: its parameters.
      t_final: horizon [s].
      eps: Lemma 2's margin.
      n_t: size of the uniform time grid of F (>= 3). min F is taken over the grid, its
        midpoints and 256 points around the grid minimum (so the radius is not the
        over-estimate a grid minimum alone gives); a grid on which this refinement lowers min F
        by more than ``GRID_RTOL`` (1 %) is refused as too coarse.
      m1: "closed" (Remark 16 in closed form, every type) or "numerical" (Remark 16 by local
        search: an upper bound of the distance, so not conservative; for cross-checks).

    Returns:
      :class:`Lemma2Report`.

    Raises:
      ValueError: a static law, an unknown ``m1``, bad eps/horizon, a grid too coarse to bound
        min F, or a reference within eps of the singular set.
    """
    check_dynamic(ctrl, params)
    check_eager("lemma2", params, "its grid search and refinement need values")
    if not isinstance(m1, str) or m1 not in M1_METHODS:
        raise ValueError(f"m1 must be one of {M1_METHODS}, got {m1!r}")
    if isinstance(n_t, bool) or not isinstance(n_t, (int, np.integer)) or n_t < MIN_GRID:
        raise ValueError(f"n_t must be an integer >= {MIN_GRID} (time samples on which min F is taken), got {n_t!r}")
    check_lemma2_args(t_final=t_final, eps=eps, reference=params.reference)
    paper_k2 = _paper_k2_applies(ctrl, params)
    scheduled = params.gains.time_varying
    if not scheduled:
        _check_hurwitz(ctrl.error_matrix(params.gains))

    def certificates(ts):
        ts = np.asarray(ts)
        if scheduled:
            m1v = np.asarray(m1_closed_form(ctrl, params, ts) if m1 == "closed" else m1_numerical(ctrl, params, ts))
            check_lemma2_args(t_final=t_final, eps=eps, m1=m1v)
            return None, None, _certificate_on_host(ts, m1v, np.asarray(k2_transition(params.gains, ts)), eps)
        m1v, k2s = _grid_values(ctrl, params, ts, m1, paper_k2)
        check_lemma2_args(t_final=t_final, eps=eps, m1=m1v)
        return tuple(None if k2 is None else _certificate_on_host(ts, m1v, k2, eps) for k2 in k2s)

    ts = jnp.linspace(0.0, t_final, n_t)
    certs = certificates(ts)
    # min F between the grid's points: at its midpoints and on 256 points across the two intervals
    # next to each certificate's grid minimum. The certified radius is the smallest value seen (a
    # grid minimum alone over-certifies); a grid on which that refinement lowers it by more than
    # GRID_RTOL is too coarse to trust at all (F may dip between points elsewhere) and is refused.
    tg = np.asarray(ts)
    local = [
        np.linspace(tg[max(i - 1, 0)], tg[min(i + 1, n_t - 1)], 257)
        for i in (int(np.argmin(np.asarray(c.F))) for c in certs if c is not None)
    ]
    refined = certificates(jnp.asarray(np.concatenate([0.5 * (tg[1:] + tg[:-1])] + local)))
    certs = _refined(certs, refined, n_t, t_final)
    closed = "closed form (Lemma 3)" if ctrl.row.singular_set_is_linear else "closed form (1-D search over theta)"
    return Lemma2Report(*certs, closed if m1 == "closed" else "numerical (Remark 16)")


GRID_BLOCK = 512  # times per call of the grid program: every grid of every call goes through one program


def _grid_values(ctrl, params, ts, m1: str, paper_k2: bool):
    """``(M1, (K2 of (64) or None, Lyapunov K2, exact K2))`` on the times ``ts`` (NumPy arrays) for
    constant gains, evaluated in blocks of :data:`GRID_BLOCK` times (the last padded) by one
    compiled program: the grid and its refinement, of other sizes, reuse it."""
    out = []
    for i in range(0, ts.size, GRID_BLOCK):
        tb = ts[i : i + GRID_BLOCK]
        pad = np.concatenate([tb, np.full(GRID_BLOCK - tb.size, tb[-1])])
        out.append(jax.device_get(_grid_program(ctrl, params, jnp.asarray(pad), m1, paper_k2)))
    m1v, *k2s = (np.concatenate([b[k] for b in out])[: ts.size] for k in range(4))
    return m1v, (k2s[0] if paper_k2 else None, k2s[1], k2s[2])


@functools.partial(jax.jit, static_argnums=(0, 3, 4))
def _grid_program(ctrl, params, ts, m1: str, paper_k2: bool):
    """M1, K2 of (64) (zeros where it does not apply), the Lyapunov K2 and the exact K2 on ``ts``."""
    A = ctrl.error_matrix(params.gains)  # Hurwitz: checked by the caller (the Lyapunov bound assumes it)
    m1v = _m1_closed(ctrl, params, ts) if m1 == "closed" else _m1_numerical(ctrl, params, ts, M1_ITERS, M1_DAMPING)
    paper = k2_paper(ts) if paper_k2 else jnp.zeros_like(ts)
    return m1v, paper, k2_lyapunov(A, ts), _k2_exact(A, ts)


def grid_k2s(ctrl, params) -> dict:
    """The K2 bounds by name: name -> ``ts -> K2(ts)`` ((T,) concrete times [s] -> (T,) NumPy array) of the constant-gain
    certificates :func:`lemma2` computes (``"paper"`` where (64) applies, ``"lyapunov"``,
    ``"exact_norm"``), evaluated by the program that computed them: checking the certificates on
    other runs compiles nothing more."""
    paper_k2 = _paper_k2_applies(ctrl, params)

    def k2(i):
        return lambda ts: _grid_values(ctrl, params, np.asarray(ts), "closed", paper_k2)[1][i]

    return ({"paper": k2(0)} if paper_k2 else {}) | {"lyapunov": k2(1), "exact_norm": k2(2)}


def _paper_k2_applies(ctrl, params) -> bool:
    """Whether the paper's K2 (64) bounds this loop: r = 2 and the double pole at -1 per output."""
    return ctrl.relative_degree == 2 and params.gains.is_double_pole(1.0)


def _certificate_on_host(ts, m1, k2, eps) -> Certificate:
    """:func:`certificate` computed with NumPy (no small XLA program per operation and shape)."""
    with np.errstate(divide="ignore", over="ignore"):  # K2 underflowing to 0 on long horizons: F = inf, as jnp gives
        F = (m1 - eps) / k2
    i = int(np.argmin(F))
    return Certificate(*(jnp.asarray(x) for x in (ts, m1, k2, F, F[i], ts[i])))


def _refined(certs, refined, n_t, t_final):
    """The grid's certificates (paper, Lyapunov, exact norm; None where absent) with the radius
    and argmin of ``refined`` (the same certificates between the grid's points) where it is
    smaller; ValueError when it is smaller by more than ``GRID_RTOL``: the grid is too coarse."""
    out = []
    for name, c, c2 in zip(("paper", "lyapunov", "exact_norm"), certs, refined):
        if c is None:
            out.append(None)
            continue
        coarse, fine = float(c.radius), float(c2.radius)
        if fine < coarse - GRID_RTOL * abs(coarse):
            raise ValueError(
                f"n_t = {n_t} is too coarse to bound min F on [0, {t_final}] s: the {name} certificate's "
                f"min F is {coarse:.6g} on the grid but {fine:.6g} between its points (relative drop "
                f"{(coarse - fine) / abs(coarse):.2g} > {GRID_RTOL}); use a finer grid (e.g. n_t = "
                f"{4 * n_t - 3} or more)"
            )
        out.append(c._replace(radius=c2.radius, argmin=c2.argmin) if fine < coarse else c)
    return tuple(out)
