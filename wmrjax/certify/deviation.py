r"""A proved radius for a plant that is not the law's model: actuator scales and geometry in a
range, with input limits, run continuously or by a digital controller (issue 54, item 3).

The law computes with its nominal model; the plant's inputs are the command scaled by
:math:`s` (each :math:`s_i` anywhere in :math:`[\underline s_i, \overline s_i]`, unknown and
possibly different run to run) and its geometry (L and e) is the law's times
:math:`\sigma \in [\underline\sigma, \overline\sigma]`. The law's output jet
:math:`\zeta = \Psi(z)` (its nominal geometry) of the loop's state then obeys

.. math::

    \dot{\tilde\zeta} = A\tilde\zeta + \Delta(t), \qquad
    \Delta = \frac{\partial\Psi}{\partial X}\bigl[f(X, s\odot u, \sigma g) - f(X, u, g)\bigr],

because the law's own field makes :math:`\dot{\tilde\zeta} = A\tilde\zeta` exactly at every
state and the plant differs from it only in :math:`\dot X` (velocity level; the compensator is
the law's). Hence :math:`\tilde\zeta(t) = e^{At}\tilde\zeta(0) + d(t)` with
:math:`d(t) = \int_0^t e^{A(t-\tau)}\Delta(\tau)\,d\tau`: the deviation from the nominal loop
does not grow with the horizon (A is Hurwitz), unlike a Grönwall bound with the loop's
Lipschitz constant, which multiplies by :math:`e^{LT}`.

**The bound.** Take a radius :math:`\rho`, a tube width R and the tube
:math:`\mathcal T = \{(t, e^{At}Ps + d): t \in [0, T], \|s\| \le \rho, \|d\| \le R\}`. Suppose,
over :math:`\mathcal T` and every scale of the ranges, (i) the applied input
:math:`s \odot u` is within the limits, (ii) :math:`\|\Delta\| \le \bar\delta`, and (iii)
:math:`G_T\bar\delta < R` with :math:`G(t) = \int_0^t \|e^{A\tau}\|\,d\tau`. Then a run from
any initial error :math:`Ps`, :math:`\|s\| \le \rho`, stays in the tube with
:math:`\|d(t)\| \le G(t)\bar\delta` (at a first time it left, :math:`\|d\| = R > G_T\bar\delta`,
while up to then the integral gives :math:`\|d\| \le G_T\bar\delta`), never saturates, and
:math:`\|Cd(t)\| \le G_C\bar\delta` with :math:`G_C = \int_0^T \|Ce^{A\tau}\|\,d\tau`. Its
distance to the singular set is at least the nominal one less :math:`G_C\bar\delta`, so the
exact map's proved radius at the margin :math:`\epsilon + G_C\bar\delta`, capped at
:math:`\rho`, is a proved radius of the real loop. (The tube never meets the singular set:
there the command's enclosure is unbounded and (i) fails; so the run keeps the reference's
branch, on which :func:`wmrjax.controllers.placement.place` inverts :math:`\Psi`.)

**Computed.** (i) and (ii) by the affine enclosure (:mod:`wmrjax.certify.affine`) of the
command and of :math:`\Delta` per time box, as :func:`wmrjax.certify.saturation_free_radius`
does, with the tube's d (a ball of its own), the scales and :math:`\sigma` as further symbols; R by iterating
:math:`R \leftarrow 1.25\,G_T\bar\delta(\rho, R)` until (iii) holds; :math:`\rho` by bisection on
(i)-(iii) and the exact map's attained radius at the inflated margin; then one proved exact
map at that margin. :math:`G_T` and :math:`G_C` are upper Riemann sums of
:math:`\|e^{A\tau_j}\|e^{\|A\|\eta}` on a grid of step :math:`\eta` (the norm of a matrix
exponential evaluated in float64, with a relative allowance, as the exact map's bounds use).

The bound charges the largest :math:`\|\Delta\|` of the horizon to every time; it is a
bound, and the ratio to the real loop's falsified radius says what it costs.

**A digital controller** (``Mismatch.period`` > 0, zero-order hold, measurement noise bounded
by ``Mismatch.noise``). Between samples the plant integrates :math:`s\odot u_k` and the
compensator advances at the held rate :math:`a_k`, both computed at the sample from the measured
state; with the compensator interpolated linearly between samples (it equals the digital
integrator's at every sample), the same identity holds with :math:`\Delta` adding
:func:`hold_rate`, the law's inputs at the sample less those of the state now, written by the
mean value theorem as the law's derivative times the reference's and the error's change since
the sample. Each time box is one period; the error's change is
:math:`(t - t_k)A\tilde\zeta(t)` (kept linear in the tube's symbols) plus a remainder bounded
with an assumed :math:`\|\Delta\| \le a` and the noise's change of the measured error; the
tube's iteration then also requires :math:`\bar\delta < a` (:meth:`_Tube.width`), which closes
the first-exit argument. At the sample, :math:`\det K` over the tube plus the noise must keep
its sign (the measured state is on the reference's branch). This bound is **first order in the
period** but its enclosure loosens fast with the error's size (the law's derivative is enclosed
over the tube): measured on ``s_path`` (position slice, nominal proved 3.59), it proves 0 at
20 Hz, 0.179 at 100 Hz and 0.555 at 500 Hz.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math, robots
from wmrjax.certify import affine
from wmrjax.certify.exact_map import Slice, exact_map_radius, singular_rows, slice_basis, square_basis
from wmrjax.certify.interval import Interval
from wmrjax.certify.lemma2 import check_dynamic, m1_closed_form
from wmrjax.certify.saturation import (
    BOX_BLOCK,
    box_jets,
    placed_command,
    preconditioned_solve,
    reference_heading,
    rotated,
    turned,
)
from wmrjax.controllers import Space, Task, place
from wmrjax.controllers.law import Level
from wmrjax.references import piece_breaks, time_boxes
from wmrjax.robots import Geometry
from wmrjax.simulate import fixed_blocks

NORM_ALLOWANCE = 1e-9
"""Relative allowance on a float64 matrix exponential's norm (its rounding is ~1e-14)."""
GAIN_GRID = 4096
"""Steps of the Riemann sums of :math:`G_T` and :math:`G_C`."""
TUBE_TRIES = 8
"""Iterations of the tube's radius R per initial radius before that radius counts as not certified."""
ENCLOSURE_COMPILE = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}
"""The enclosures' programs are large (nested derivatives of the law, each value an affine form;
the held one two of them) and run a few dozen times: XLA's optimizer would take minutes over
them for little gain (the continuous one on ``steered_21``: 165 s of its 260 s certification),
and XLA:CPU's legacy elemental emitters compile them faster than its MLIR fusion emitters (as
:data:`wmrjax.certify.saturation.SEARCH_COMPILE`)."""
TUBE_FACTOR = 1.25
"""R is set to this factor times the deviation bound it must contain (> 1: (iii) is strict)."""


class Mismatch(NamedTuple):
    """The plant's range around the law's model (every value inside it is covered).

    Attributes:
      input_limit: (n_input,) limits on the applied inputs (inf: none).
      input_scale: ``(lo, hi)``, each (n_input,): the applied input is ``s * command``, s_i in [lo_i, hi_i].
      geometry_scale: ``(lo, hi)``: the plant's L and e are the law's times a factor in [lo, hi].
      period: the digital controller's period [s] (zero-order hold; 0: a continuous controller).
      noise: (n_X,) bounds of the measurement noise on X at each sample [m, m, rad, rad...]
        (absolute: e.g. 3 times ``noise_std``; empty or zeros: exact measurements; needs a period).
    """

    input_limit: np.ndarray
    input_scale: tuple
    geometry_scale: tuple
    period: float = 0.0
    noise: tuple = ()


class MismatchRadius(NamedTuple):
    r"""Result of :func:`mismatch_radius` (radii in the slice's output-error units).

    Attributes:
      lower_bound: proved: from every initial error of the slice with norm below it, every run
        of the loop with every plant of the range keeps distance >= eps from the singular set
        over [0, T] and never reaches a limit.
      rate_bound: :math:`\bar\delta`, the bound of :math:`\|\Delta\|` over the tube.
      deviation_bound: :math:`G_T\bar\delta`: ``||zeta_err(t) - e^{At} zeta_err(0)||`` never exceeds it.
      singular_margin: :math:`G_C\bar\delta`, added to eps for the exact map.
      tube: the tube's radius R (a ball around the nominal error).
      gains: ``(G_T, G_C)``.
      tube_radius: the largest radius whose tube passed (i)-(iii) of the module docstring.
      exact_lower_bound: the exact map's proved radius at eps + ``singular_margin``.
      worst_error: (n,) the exact map's worst initial error at that margin (None: none).
      bound_by: ``"exact_map"`` or ``"tube"``: which of the two caps ``lower_bound``.
      boxes: time boxes of the cover.
    """

    lower_bound: float
    rate_bound: float
    deviation_bound: float
    singular_margin: float
    tube: float
    gains: tuple
    tube_radius: float
    exact_lower_bound: float
    worst_error: np.ndarray | None
    bound_by: str
    boxes: int


def deviation_rate(ctrl, params, jet, error, input_scale, geometry_scale, geometry_between=None):
    r"""The rate :math:`\Delta` by which the plant's output error leaves the nominal loop's, and
    the plant's applied input, at the reference jet ``jet`` ((r + 1, m)) and output error
    ``error`` ((r m,)), without limits (velocity level).

    The plant's :math:`\dot X = B(X)u` is linear in u, so the scales' part is exactly
    :math:`B(X, g)((s - 1)\odot u)`; the geometry's part is :math:`(\sigma - 1)\,\partial_\sigma
    B(X, \sigma' g)(s\odot u)` at some :math:`\sigma'` between 1 and :math:`\sigma` (the mean
    value theorem): an enclosure passes ``geometry_between`` as a symbol of that range, so that
    both parts are explicitly proportional to the mismatch; without it the difference is
    evaluated as it is (a point's exact value).

    Returns:
      ``(delta, applied)``: (r m,) :math:`\partial\Psi/\partial X\,[f(X, s\odot u, \sigma g) -
      f(X, u, g)]` and (n_input,) :math:`s \odot u`.
    """
    g, nx, robot = params.geometry, ctrl.robot.n_state, ctrl.robot
    z, u = placed_command(ctrl, params, jet, error)
    X, applied = z[:nx], input_scale * u
    f = lambda uu, sg: robots.kinematic(robot, X, uu, Geometry(L=sg * g.L, e=sg * g.e, delta=g.delta))
    if geometry_between is None:
        d_geometry = f(applied, geometry_scale) - f(applied, 1.0)
    else:
        one = jnp.ones_like(geometry_between)
        d_geometry = (geometry_scale - 1.0) * jax.jvp(lambda sg: f(applied, sg), (geometry_between,), (one,))[1]
    dX = f((input_scale - 1.0) * u, 1.0) + d_geometry
    psi = lambda x: ctrl.law.jet(x, g)[0].reshape(-1)
    delta = jax.jvp(psi, (z,), (jnp.concatenate([dX, jnp.zeros(z.shape[0] - nx, dX.dtype)]),))[1]
    return delta, applied


def sampled_inputs(ctrl, params, jet, z):
    r"""What a digital controller computes at a sample: the plant command u and the compensator's
    rate at the law state ``z`` ((n_state,), as measured) and the reference jet ``jet``
    ((r + 1, m)), with the law's nominal geometry (velocity level; eq (49) with its error
    :math:`\Psi(z) - \zeta_{ref}`, the solve as :func:`wmrjax.certify.saturation.preconditioned_solve`).

    The angle errors are not wrapped: the same as the law's while they are below pi (the tube's are).

    Returns:
      ``(u, c_rate)``: (n_input,) and (n_state - n_X,).
    """
    return _sampled(ctrl, params, jet, z)[:2]


def _sampled(ctrl, params, jet, z):
    """:func:`sampled_inputs` and the decoupling matrix K it solved with (one output jet for both)."""
    r, law, g = ctrl.relative_degree, ctrl.law, params.geometry
    zeta, a, K = law.jet(z, g)
    coeffs = params.gains.coeffs_at(0.0)
    err = zeta - jet[:r]
    w = jet[r]
    for j in range(r):
        w = w - coeffs[:, j] * err[j]
    U = preconditioned_solve(K, w - a)
    return law.plant_control(z, U, g), law.field(z, U, g)[ctrl.robot.n_state :], K


def held_inputs(ctrl, params, jet, error):
    """:func:`sampled_inputs` at the state of output error ``error`` ((r m,)) on the reference's
    branch: the sample's command and compensator rate as functions of the reference and the error."""
    z = place(ctrl, params, error, Space.OUTPUT, Task.POSTURE, ctrl.reference_branch(params), jet=jet)
    return sampled_inputs(ctrl, params, jet, z)


def hold_rate(ctrl, params, jet, error, input_scale, geometry_scale, tangents, between):
    r"""The part of :math:`\Delta` that the zero-order hold adds, at the reference jet ``jet`` and
    the output error ``error`` of a time t in the period :math:`[t_k, t_k + h)`.

    The plant receives :math:`s\odot u_k` and the compensator advances at :math:`a_k`, computed at
    the sample from the measured error :math:`\tilde\zeta_k^m` (:func:`held_inputs` at
    :math:`(\zeta_{ref}(t_k), \tilde\zeta_k^m)`), where the law's own field has the inputs
    :math:`(u, a)` of the state now; so :math:`\Delta_{hold} = \partial\Psi/\partial Z\,[f(X,
    s\odot(u_k - u), \sigma g); a_k - a]`, and by the mean value theorem :math:`(u_k, a_k) - (u,
    a) = -\int_0^1 J(p_\lambda)\,d\,d\lambda` with :math:`d = (\zeta_{ref}(t) - \zeta_{ref}(t_k),
    \tilde\zeta(t) - \tilde\zeta_k^m)` and :math:`p_\lambda = (\zeta_{ref}(t), \tilde\zeta(t)) -
    \lambda d` (the chord from the sample). ``tangents`` is d; ``between`` is
    :math:`(\zeta_{ref}(t) - \lambda d_{jet}, -\lambda d_{error})`: an enclosure passes the jet
    as the period's enclosure with a time symbol of its own (the chord's points are in it: it is
    convex and holds both ends) and the error's shift as a box (the set of its values over them
    is convex and holds every :math:`\lambda`, hence the integral).

    Args:
      ctrl: a dynamic linearizing law at velocity level.
      params: its parameters (the law's geometry and gains).
      jet: (r + 1, m) the reference's output jet at t (or an enclosure of it).
      error: (r m,) the output error at t (or an enclosure).
      input_scale: (n_input,) the plant's input scales s.
      geometry_scale: () the plant's geometry scale sigma.
      tangents: ``(d_jet, d_error)``, (r + 1, m) and (r m,).
      between: the chord's points, the same shapes as ``tangents``.

    Returns:
      (r m,) :math:`\Delta_{hold}`.
    """
    g, nx, robot = params.geometry, ctrl.robot.n_state, ctrl.robot
    z = place(ctrl, params, error, Space.OUTPUT, Task.POSTURE, ctrl.reference_branch(params), jet=jet)
    primal = (between[0], error + between[1])
    du, da = jax.jvp(lambda j, e: held_inputs(ctrl, params, j, e), primal, tangents)[1]
    plant = Geometry(L=geometry_scale * g.L, e=geometry_scale * g.e, delta=g.delta)
    dz = jnp.concatenate([robots.kinematic(robot, z[:nx], input_scale * du, plant), da])
    psi = lambda x: ctrl.law.jet(x, g)[0].reshape(-1)
    return -jax.jvp(psi, (z,), (dz,))[1]


def gain_integrals(A, C, t_final: float, n: int = GAIN_GRID) -> tuple[float, float]:
    r"""Upper bounds of :math:`\int_0^T \|e^{A\tau}\|d\tau` and :math:`\int_0^T \|Ce^{A\tau}\|d\tau`:
    on :math:`[\tau_j, \tau_j + \eta]`, :math:`\|e^{A\tau}\| \le \|e^{A\tau_j}\| e^{\|A\|\eta}`."""
    eta = t_final / n
    taus = jnp.arange(n, dtype=jnp.float64) * eta
    E = jax.vmap(lambda t: _math.expm_small(A * t))(taus)
    grow = np.exp(float(_math.spectral_norm(A)) * eta) * eta * (1 + NORM_ALLOWANCE)
    full = float(jnp.sum(jax.vmap(_math.spectral_norm)(E))) * grow
    rows = float(jnp.sum(jax.vmap(lambda e: _math.spectral_norm(C @ e))(E))) * grow
    return full, rows


def _n_symbols(ctrl, held: bool = False) -> int:
    """Symbols of one evaluation: the initial errors' ball (n), the tube's ball (n), time, the
    input scales, sigma, sigma'; with a hold, the error's change over a period (n) and a second
    time (of the mean value theorem's point)."""
    n = ctrl.relative_degree * ctrl.m
    return 2 * n + 1 + ctrl.robot.n_input + 2 + (n + 1 if held else 0)


def _scale_symbols(ctrl, scales, n: int, held: bool = False):
    """The input scales', sigma's and sigma''s affine symbols (after the two balls and time);
    ``scales`` is (2, n_input + 1): the input scales' and sigma's lower then upper ends."""
    nu, ns = ctrl.robot.n_input, _n_symbols(ctrl, held)
    centre, half = 0.5 * (scales[0] + scales[1]), 0.5 * (scales[1] - scales[0])
    eye = jnp.eye(ns)
    first = 2 * n + 1
    s_in = affine.symbols(centre[:nu], half[:nu, None] * eye[first : first + nu])
    sigma = affine.symbols(centre[nu], half[nu] * eye[first + nu])
    # sigma' of the mean value theorem: anywhere between 1 and sigma, a symbol of its own
    lo_b, hi_b = jnp.minimum(scales[0, nu], 1.0), jnp.maximum(scales[1, nu], 1.0)
    between = affine.symbols(0.5 * (lo_b + hi_b), 0.5 * (hi_b - lo_b) * eye[first + nu + 1])
    return s_in, sigma, between


def _tube_error(A, P, tc, growth, rho, tube, n_symbols: int):
    r"""The tube's output error over a time box at centre ``tc``: :math:`e^{At_c}P\rho\varepsilon_1
    + R\varepsilon_2`, and :math:`e^{A(t - t_c)}`'s distance from I as an error term."""
    n = P.shape[0]
    E = _math.expm_small(A * tc)
    gen = jnp.concatenate([rho * (E @ P), tube * jnp.eye(n), jnp.zeros((n, n_symbols - 2 * n))], axis=1)
    err = affine.symbols(jnp.zeros(n), gen)
    slack = jnp.linalg.norm(E, axis=1) * growth * rho * (1 + 1e-12) + 1e-15 * rho
    return affine.Affine(err.c, err.g, err.e + slack)


def _widened_jets(jc, jg, je, n: int, n_symbols: int):
    """The jets' affine forms (n ball symbols, then time) with the tube's ball and the scales'
    symbols added: n (the ball's, zero), n (the tube's), time, the scales'."""
    zeros = lambda k: jnp.zeros(jg.shape[:-1] + (k,))
    return affine.Affine(
        jc, jnp.concatenate([jg[..., :n], zeros(n), jg[..., n:], zeros(n_symbols - 2 * n - 1)], axis=-1), je
    )


def _rate_and_fit(delta: Interval, applied: Interval, limit):
    """``(bound of ||delta||, whether applied is finite and within the limits)``."""
    mag = jnp.maximum(jnp.abs(delta.lo), jnp.abs(delta.hi))
    rate = jnp.sqrt(jnp.sum(mag**2)) * (1 + 1e-12)
    fits = jnp.all((applied.lo >= -limit) & (applied.hi <= limit) & jnp.isfinite(applied.lo) & jnp.isfinite(applied.hi))
    return jnp.where(jnp.isfinite(rate), rate, jnp.inf), fits


@functools.partial(jax.jit, static_argnums=(0, 1), compiler_options=ENCLOSURE_COMPILE)
def _box_rates(ctrl, turn: bool, params, P, limit, scales, jc, jg, je, t_c, h, rho, tube):
    r"""Per time box: the bound of :math:`\|\Delta\|` over the tube, and whether the applied
    input's enclosure fits the limits. ``scales`` is (2, n_input + 1): the input scales' and
    sigma's lower then upper ends. Seen from axes along the reference's heading at the box's
    centre with ``turn`` (:func:`wmrjax.certify.saturation.turns_alike`; a norm does not turn)."""
    A = ctrl.error_matrix(params.gains)
    growth = jnp.expm1(_math.spectral_norm(A) * h)
    n, ns = P.shape[0], _n_symbols(ctrl)
    s_in, sigma, between = _scale_symbols(ctrl, scales, n)

    def one(jet, tc, g, rh, tb):
        err = _tube_error(A, P, tc, g, rh, tb, ns)
        phi = reference_heading(ctrl, params, jet.c) if turn else 0.0
        fn = lambda j, e, s, sg, sb: deviation_rate(ctrl, params, *rotated(ctrl, j, e, phi), s, sg, sb)
        (delta, applied), ctx = affine.enclose(fn, jet, err, s_in, sigma, between, n_ball=(n, n))
        return _rate_and_fit(affine.to_interval(delta, ctx), affine.to_interval(applied, ctx), limit)

    return jax.vmap(one, (0, 0, 0, None, None))(_widened_jets(jc, jg, je, n, ns), t_c, growth, rho, tube)


def _outward(lo, hi) -> Interval:
    return Interval.around(0.5 * (lo + hi), 0.5 * (hi - lo) * (1 + 1e-12) + 1e-300)


def _sample_ranges(ctrl, params, jet, error, input_scale, noise, noise_between):
    r"""At a sample: the applied input :math:`s\odot u_k` and :math:`\det K` at the measured state
    :math:`Z + \nu`, and the measured error's change :math:`\Psi(Z + \nu) - \Psi(Z) =
    \int_0^1 \partial\Psi(Z + \lambda\nu)\,\nu\,d\lambda` (``noise_between``: :math:`\lambda\nu`)."""
    nx, g = ctrl.robot.n_state, params.geometry
    z = place(ctrl, params, error, Space.OUTPUT, Task.POSTURE, ctrl.reference_branch(params), jet=jet)
    pad = lambda v: jnp.concatenate([v, jnp.zeros(z.shape[0] - nx, z.dtype)])
    u, _, K = _sampled(ctrl, params, jet, z + pad(noise))
    det = _math.adjugate_solve(K, jnp.zeros(ctrl.m))[1]
    psi = lambda x: ctrl.law.jet(x, g)[0].reshape(-1)
    return input_scale * u, det, jax.jvp(psi, (z + pad(noise_between),), (pad(noise),))[1]


@functools.partial(jax.jit, static_argnums=(0, 1), compiler_options=ENCLOSURE_COMPILE)
def _held_box_rates(ctrl, turn: bool, params, P, limit, scales, noise, jc, jg, je, t_c, h, rho, tube, assumed):
    r""":func:`_box_rates` for a digital controller: each box is one period :math:`[t_k, t_k + 2h]`;
    the applied input is the sample's (at the box's tube plus the noise box, ``noise`` (n_X,) its
    bounds seen from turned axes; :math:`\det K` there must keep its sign); :math:`\Delta` adds
    :func:`hold_rate`, the error's change over the period bounded with ``assumed``
    (:math:`\|\Delta\|` on the period) and the noise's."""
    A = ctrl.error_matrix(params.gains)
    growth = jnp.expm1(_math.spectral_norm(A) * h)
    n, ns = P.shape[0], _n_symbols(ctrl, held=True)
    s_in, sigma, between = _scale_symbols(ctrl, scales, n, held=True)
    nz = Interval(-noise, noise)

    def rate(j, e, s, sg, sb, dj, rest, tau, j_between, shift, phi, hh):
        jr, er = rotated(ctrl, j, e, phi)
        # the error's change: (t - t_k) A zeta(t), linear in the tube's symbols, and the rest
        m = ctrl.m
        tangent = hh * (1.0 + tau) * turned((A @ e).reshape(-1, m), phi).reshape(-1) + rest
        between = (rotated(ctrl, j_between, e, phi)[0], shift)
        held = hold_rate(ctrl, params, jr, er, s, sg, (turned(dj, phi), tangent), between)
        return deviation_rate(ctrl, params, jr, er, s, sg, sb)[0] + held

    def one(jet, dj, j_between, tc, hh, g, rh, tb):
        err = _tube_error(A, P, tc, g, rh, tb, ns)
        phi = reference_heading(ctrl, params, jet.c) if turn else 0.0
        fn = lambda j, e, s, a, b: _sample_ranges(ctrl, params, *rotated(ctrl, j, e, phi), s, a, b)
        out, ctx = affine.enclose(fn, jet, err, s_in, nz, nz, n_ball=(n, n))
        applied, det, d_noise = (affine.to_interval(v, ctx) for v in out)
        b = _error_change(A, P, tc, hh, rh, tb, assumed, turn, ctrl.m)
        # the change's own n symbols (before the last): the law's derivative in it stays linear, where a
        # box would lose the place-then-Psi identity that cancels in it
        noise_rad = 0.5 * (d_noise.hi - d_noise.lo) * (1 + 1e-12) + 1e-300
        rest = affine.Affine(-d_noise.mid, b[:, None] * jnp.eye(ns)[ns - n - 1 : ns - 1], noise_rad)
        # -lambda d_error: a box (2h |A zeta| from the tube's bounds, the rest and the noise)
        big = _error_change(A, P, tc, hh, rh, tb, 0.0, turn, ctrl.m, first_order=True)
        shift = _outward(-big - b + d_noise.lo, big + b + d_noise.hi)
        tau = affine.symbols(0.0, jnp.eye(ns)[2 * n])
        f2 = lambda *a: rate(*a, phi, hh)
        args = (jet, err, s_in, sigma, between, dj, rest, tau, j_between, shift)
        delta, ctx = affine.enclose(f2, *args, n_ball=(n, n))
        r, fits = _rate_and_fit(affine.to_interval(delta, ctx), applied, limit)
        return r, fits & ((det.lo > 0) | (det.hi < 0))

    jets = _widened_jets(jc, jg, je, n, ns)
    d_jets = affine.Affine(jets.g[..., 2 * n], jets.g, 2 * je)  # g (tau + 1) + r(tau) - r(-1)
    # the jet at the mean value theorem's time: the period's, in a time symbol of its own (the last)
    g_between = jnp.zeros_like(jets.g).at[..., ns - 1].set(jets.g[..., 2 * n])
    j_between = affine.Affine(jets.c, g_between, je)
    return jax.vmap(one, (0, 0, 0, 0, 0, 0, None, None))(jets, d_jets, j_between, t_c, h, growth, rho, tube)


def _error_change(A, P, tc, hh, rho, tube, assumed, turn: bool, m: int, first_order: bool = False):
    r"""Bounds b (r m,) of what :math:`\tilde\zeta(t) - \tilde\zeta_k` adds to :math:`(t -
    t_k)A\tilde\zeta(t)` over the period: :math:`\dot{\tilde\zeta} = A\tilde\zeta + \Delta`
    gives :math:`\tilde\zeta(t) - \tilde\zeta_k = (t - t_k)A\tilde\zeta(t) - \int_{t_k}^t\int_\sigma^t
    A\dot{\tilde\zeta}\,d\mu\,d\sigma + \int_{t_k}^t\Delta`, so per row i
    :math:`b_i = 2h^2(\|(A^2E_c)_i\|e^{\|A\|h}\|P\|\rho + \|(A^2)_i\|R + \|A_i\|\bar\delta_a) +
    2h\bar\delta_a`; x and y rows by their pair's norm when seen from turned axes. With
    ``first_order``, bounds of :math:`|(t - t_k)A\tilde\zeta(t)|` instead (A in place of
    :math:`A^2` and h for :math:`h^2`, without the assumed rate)."""
    E = _math.expm_small(A * tc)
    A2 = A if first_order else A @ A
    grow = jnp.exp(_math.spectral_norm(A) * hh)
    rate = (
        jnp.linalg.norm(A2 @ E, axis=1) * grow * _math.spectral_norm(P) * rho
        + jnp.linalg.norm(A2, axis=1) * tube
        + jnp.linalg.norm(A, axis=1) * assumed
    )
    b = (2 * hh * rate if first_order else 2 * hh**2 * rate + 2 * hh * assumed) * (1 + 1e-12)
    if turn:  # x and y of each order mix
        pairs = b.reshape(-1, m)
        xy = jnp.hypot(pairs[:, 0], pairs[:, 1])
        b = jnp.concatenate([xy[:, None], xy[:, None], pairs[:, 2:]], axis=1).reshape(-1)
    return b * (1 + 1e-12)


def _turned_noise(noise, turn: bool):
    """The noise box's bounds seen from turned axes: x and y each within their disc's radius."""
    if not turn:
        return noise
    out = noise.copy()
    out[:2] = np.hypot(noise[0], noise[1]) * (1 + 1e-12)
    return out


class _Tube:
    r"""The time boxes' enclosures at a radius and a tube width: :math:`\bar\delta` and the limits' check."""

    def __init__(self, ctrl, turn, params, P, mismatch: Mismatch, t_final: float, n_boxes: int):
        period = float(mismatch.period)
        if period > 0.0:  # one box per controller period, the last reaching past T
            n_boxes = int(np.ceil(t_final / period - 1e-9))
            self.t_c = (np.arange(n_boxes) + 0.5) * period
            self.h = np.full(n_boxes, 0.5 * period)
            # each period pinned to its piece over the whole period (unpinned, its ends' outward
            # rounding would read the next piece too, and the hull of two pieces' coefficients is
            # unbounded); a period across a knot (a path sampled off the controller's grid) the hull
            # of its pieces' polynomials
            breaks = piece_breaks(params.reference, t_final)
            self.jets = box_jets(ctrl, params, breaks, self.t_c, self.h, across=True)
        else:  # cut at a sampled path's knots, each box's jet its own piece's (wmrjax.references.time_boxes)
            self.t_c, self.h, breaks = time_boxes(params.reference, t_final, n_boxes)
            self.jets = box_jets(ctrl, params, breaks, self.t_c, self.h)
            n_boxes = self.t_c.size
        lim = np.asarray(mismatch.input_limit, float)
        lim = jnp.asarray(np.where(np.isfinite(lim), lim, np.finfo(float).max))
        ends = [np.append(np.asarray(mismatch.input_scale[k], float), mismatch.geometry_scale[k]) for k in (0, 1)]
        scales = jnp.asarray(np.stack(ends))
        if period > 0.0:
            noise = jnp.asarray(_turned_noise(np.asarray(mismatch.noise, float), turn))
            held = lambda *a: _held_box_rates(ctrl, turn, params, P, lim, scales, noise, *a)
            self.program = lambda rho, tube, assumed: lambda *a: held(*a, rho, tube, assumed)
        else:
            box = lambda *a: _box_rates(ctrl, turn, params, P, lim, scales, *a)
            self.program = lambda rho, tube, assumed: lambda *a: box(*a, rho, tube)
        self.boxes = n_boxes

    def rate(self, rho: float, tube: float, assumed: float) -> tuple[float, bool]:
        r"""``(delta_bar, fits)`` over every box at radius ``rho``, tube width ``tube`` and, for a
        digital controller, :math:`\|\Delta\| \le` ``assumed`` on each period."""
        # strongly typed: a Python float's weak type would compile a second program (50 s on steered_21)
        program = self.program(*(jnp.asarray(np.float64(v)) for v in (rho, tube, assumed)))
        rates, fits = fixed_blocks(program, (*self.jets, self.t_c, self.h), BOX_BLOCK)
        return float(np.max(rates)), bool(np.all(fits))

    def width(self, rho: float, g_t: float) -> tuple[float, float] | None:
        r"""A tube width R and :math:`\bar\delta` with (i)-(iii) at ``rho``, or None.

        With an assumed :math:`a = 1.25\bar\delta_{prev}` and :math:`R = G_T a`, an enclosure
        :math:`\bar\delta < a` closes the first-exit argument: while a run is in the tube with
        :math:`\|\Delta\| \le a` (which a digital controller's bound of the error's change over
        a period uses), :math:`\|\Delta\| \le \bar\delta < a` and :math:`\|d\| \le G_T\bar\delta < R`."""
        delta, fits = self.rate(rho, 0.0, 0.0)
        for _ in range(TUBE_TRIES):
            if not (fits and np.isfinite(delta)):
                return None
            assumed = max(TUBE_FACTOR * delta, 1e-12 / max(g_t, 1e-300))
            tube = g_t * assumed
            delta, fits = self.rate(rho, tube, assumed)
            if fits and delta < assumed:
                return tube, delta
        return None


def check_mismatch(ctrl, params, mismatch: Mismatch) -> Mismatch:
    """``mismatch`` with arrays of the right shapes, or ValueError naming what is wrong."""
    check_dynamic(ctrl, params)
    if ctrl.level != Level.VELOCITY:
        raise ValueError(
            f"the mismatch radius covers velocity-level laws (the plant differs from the law in dX/dt only); "
            f"got a {ctrl.level}-level law, whose plant's wheel velocities are a state of their own"
        )
    if params.gains.time_varying:
        raise ValueError("the mismatch radius needs constant gains (the error's transition is e^{At})")
    if singular_rows(ctrl) is None:
        raise ValueError(f"the mismatch radius needs a linear singular set ({ctrl.robot.name}'s is curved)")
    nu = ctrl.robot.n_input
    limit = np.broadcast_to(np.asarray(mismatch.input_limit, float), (nu,))
    ends = []
    for name, pair, width in (
        ("input_scale", mismatch.input_scale, nu),
        ("geometry_scale", mismatch.geometry_scale, None),
    ):
        if len(pair) != 2:
            raise ValueError(f"{name} must be a (lo, hi) pair, got {pair!r}")
        lo, hi = (
            np.asarray(v, float) if width is None else np.broadcast_to(np.asarray(v, float), (width,)) for v in pair
        )
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo > 0) and np.all(lo <= hi)):
            raise ValueError(
                f"{name} must be finite ends 0 < lo <= hi, got {np.asarray(lo).tolist()}, {np.asarray(hi).tolist()}"
            )
        ends.append((lo, hi) if width else (float(lo), float(hi)))
    if np.any(~(limit > 0)):
        raise ValueError(f"input_limit must be > 0 per input (inf: none), got {limit.tolist()}")
    period, noise = _checked_hold(ctrl, mismatch)
    return Mismatch(limit, ends[0], ends[1], period, noise)


def _checked_hold(ctrl, mismatch: Mismatch):
    """``(period, (n_X,) noise bounds)`` of ``mismatch``, or ValueError."""
    period = mismatch.period
    if isinstance(period, bool) or not isinstance(period, (int, float, np.floating, np.integer)):
        raise ValueError(f"period must be a number of seconds (0: a continuous controller), got {period!r}")
    if not (np.isfinite(period) and period >= 0):
        raise ValueError(f"period must be finite and >= 0 [s] (0: a continuous controller), got {period}")
    nx = ctrl.robot.n_state
    noise = np.asarray(mismatch.noise if len(mismatch.noise) else np.zeros(0), float).reshape(-1)
    if noise.size > nx or not np.all(np.isfinite(noise)) or np.any(noise < 0):
        raise ValueError(
            f"noise must be at most {nx} finite bounds >= 0 on {ctrl.robot.name}'s X, got {noise.tolist()}"
        )
    if np.any(noise > 0) and period == 0:
        raise ValueError("noise needs a controller period: only a digital controller measures at samples")
    return float(period), np.concatenate([noise, np.zeros(nx - noise.size)])


def _check_alike(ctrl, params, t_final: float, seed: int = 0) -> bool:
    r"""Whether :math:`\|\Delta\|` and the applied input are unchanged when the reference and the
    error are seen from turned axes (then each box is enclosed along its heading), checked at
    random points; and ValueError unless both are unchanged when an angle output of the reference
    turns by 2 pi (the boxes' reference jets are enclosed modulo 2 pi)."""
    rng = np.random.default_rng(seed)
    r, n, nu = ctrl.relative_degree, ctrl.relative_degree * ctrl.m, ctrl.robot.n_input
    angles = tuple(ctrl.law.extension.angle_outputs)
    alike = True
    for t, phi in zip(rng.uniform(0.0, t_final, 4), rng.uniform(-np.pi, np.pi, 4)):
        jet = ctrl.reference_jet(t, params)[: r + 1]
        err, s, sg = (
            jnp.asarray(0.05 * rng.normal(size=n)),
            jnp.asarray(rng.uniform(0.9, 1.1, nu)),
            rng.uniform(0.9, 1.1),
        )
        d, a = (np.asarray(x) for x in deviation_rate(ctrl, params, jet, err, s, sg))
        d2, a2 = (np.asarray(x) for x in deviation_rate(ctrl, params, *rotated(ctrl, jet, err, phi), s, sg))
        alike &= bool(
            np.allclose(a, a2, rtol=1e-8, atol=1e-8)
            and np.isclose(np.linalg.norm(d), np.linalg.norm(d2), rtol=1e-8, atol=1e-10)
        )
        if angles:
            turned = jet.at[0, jnp.asarray(angles)].add(2 * np.pi)
            d3, a3 = (np.asarray(x) for x in deviation_rate(ctrl, params, turned, err, s, sg))
            if not (np.allclose(d, d3, rtol=1e-9, atol=1e-9) and np.allclose(a, a3, rtol=1e-9, atol=1e-9)):
                raise ValueError(
                    f"the {ctrl.robot.name} law's plant rates change when its reference heading turns by 2 pi "
                    f"(at t = {t:g} s): the mismatch radius encloses the reference's angles modulo 2 pi and cannot bound it"
                )
    return alike


def _angle_reach(ctrl, params, mismatch: Mismatch, t_final: float) -> tuple[float, float]:
    r"""``(sup ||e^{At}|| over [0, T], the noise's largest bound)`` for a held law with angle
    outputs (its errors at the samples are not wrapped), ``(0, -inf)`` otherwise (no constraint)."""
    if not (mismatch.period > 0 and ctrl.law.extension.angle_outputs):
        return 0.0, -np.inf
    A = ctrl.error_matrix(params.gains)
    eta = t_final / GAIN_GRID
    norms = jax.vmap(lambda t: _math.spectral_norm(_math.expm_small(A * t)))(jnp.arange(GAIN_GRID + 1) * eta)
    grow = np.exp(float(_math.spectral_norm(A)) * eta) * (1 + NORM_ALLOWANCE)
    return float(jnp.max(norms)) * grow, float(np.max(mismatch.noise, initial=0.0))


def _largest_passing(passes, rho_max: float):
    """Bisection on [0, rho_max] for the largest radius ``passes`` accepts: ``(rho, its tube)``
    (``passes(rho)`` is ``(ok, (R, delta_bar) or None)``; 0 and None where none passes)."""
    ok, w = passes(rho_max)
    if ok:
        return rho_max, w
    lo, hi, w = 0.0, rho_max, None
    for _ in range(BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        ok_mid, w_mid = passes(mid)
        lo, hi = (mid, hi) if ok_mid else (lo, mid)
        if ok_mid:
            w = w_mid
    return lo, w


BISECTION_STEPS = 14
"""Bisection steps of the tube's radius (its relative resolution: 2**-14 of the nominal radius)."""


def mismatch_radius(
    ctrl,
    params,
    mismatch: Mismatch,
    *,
    t_final: float,
    eps: float,
    basis=Slice.FULL,
    n_t: int = 2001,
    n_boxes: int = 512,
    nominal=None,
) -> MismatchRadius:
    """The proved radius of the loop with every plant of ``mismatch`` (module docstring).

    Args:
      ctrl: a dynamic linearizing law at velocity level with constant gains and a linear singular
        set ((2,0), (2,1), (1,1)).
      params: its parameters.
      mismatch: the plant's range (:class:`Mismatch`); with a ``period``, the digital
        controller's loop (one time box per period: ``n_boxes`` is not used; its program takes
        minutes to compile).
      t_final: horizon T [s].
      eps: the margin to the singular set [zeta units].
      basis: the slice (``"full"``, ``"position"`` or an (n, k) basis).
      n_t: the exact map's time grid.
      n_boxes: the tube's time boxes.
      nominal: the slice's :class:`wmrjax.certify.ExactMapRadius` at ``eps`` on ``n_t`` times
        when the caller has it (the certification does), else computed here.

    Raises:
      ValueError: a law or a range this bound does not cover, or bad values.
    """
    mismatch = check_mismatch(ctrl, params, mismatch)
    P = slice_basis(ctrl, basis)
    turn = _check_alike(ctrl, params, t_final)
    n = ctrl.relative_degree * ctrl.m
    C = jnp.eye(n)[jnp.asarray(singular_rows(ctrl))]
    g_t, g_c = gain_integrals(ctrl.error_matrix(params.gains), C, t_final)
    if nominal is None or nominal.lower_bound is None:
        nominal = exact_map_radius(ctrl, params, t_final=t_final, eps=eps, basis=basis, n_t=n_t)
    tube = _Tube(ctrl, turn, params, square_basis(P), mismatch, t_final, n_boxes)
    m1 = float(np.min(np.asarray(m1_closed_form(ctrl, params, jnp.linspace(0.0, t_final, n_t)))))

    def exact_at(eps_x, prove: bool):
        """The exact map at margin eps_x (None where the reference itself comes within it)."""
        if eps_x >= m1:
            return None
        return exact_map_radius(ctrl, params, t_final=t_final, eps=eps_x, basis=basis, n_t=n_t, lower_bound=prove)

    # the held law's angle errors are not wrapped (sampled_inputs): the tube's must stay below pi
    angle_reach = _angle_reach(ctrl, params, mismatch, t_final)

    def passes(rho):
        w = tube.width(rho, g_t)
        if w is not None and rho * angle_reach[0] + w[0] + angle_reach[1] >= np.pi:
            return False, w
        em = None if w is None else exact_at(eps + g_c * w[1], prove=False)  # attained only: cheap
        return em is not None and rho <= float(em.radius), w

    hi, w = _largest_passing(passes, float(nominal.lower_bound))
    if hi <= 0.0 or w is None:
        return MismatchRadius(0.0, np.inf, np.inf, np.inf, np.nan, (g_t, g_c), 0.0, 0.0, None, "tube", tube.boxes)
    R, delta = w
    proved = exact_at(eps + g_c * delta, prove=True)
    # (proved None: the bisection's attained radius said otherwise, rounding at the edge)
    pl = 0.0 if proved is None else float(proved.lower_bound)
    worst = None if proved is None else np.asarray(proved.worst_error)
    by = "tube" if hi < pl else "exact_map"
    bounds = (delta, g_t * delta, g_c * delta, R, (g_t, g_c))
    return MismatchRadius(0.0 if proved is None else min(hi, pl), *bounds, hi, pl, worst, by, tube.boxes)
