r"""Reference trajectories as functions of time; every derivative comes from autodiff.

A :class:`Reference` describes the posture :math:`\xi_{ref}(t) = (x, y, \theta)` of a
virtual robot (paper §3.1). Its path ``p(t)`` is the trajectory of the virtual robot's
point P; its heading is the path tangent in the paper's convention (the forward axis is
the body x2 axis, so :math:`\theta = \operatorname{atan2}(-\dot p_x, \dot p_y)`), plus an
optional constant offset (non-zero offsets are meaningful for types whose heading is
not tied to the velocity, (2,1) and (1,2)).

Every family is a pure function ``path(t, params)`` of a pytree of arrays, so thousands
of references of one family can be drawn and ``vmap``-ed (``params`` batched), and
differentiated with respect to their parameters.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import warnings
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import jet

from wmrjax import _math, _simplify, io, resources
from wmrjax._validate import check_real, concrete


def taylor(fn: Callable, t, order: int):
    """Derivatives ``fn(t), fn'(t), ..., fn^{(order)}(t)`` by Taylor mode (``jax.experimental.jet``).

    The expansion is re-emitted simplified (:mod:`wmrjax._simplify`): the input series of t
    is (1, 0, 0, ...), and jet would otherwise convolve with its zeros (a circle's (1,1)
    torque-level jet: 807 -> 330 equations).

    Args:
      fn: scalar-time function returning an array of any shape S.
      t: scalar time [s].
      order: highest derivative (static int, >= 0).

    Returns:
      Array of shape ``(order + 1, *S)``.
    """
    if order == 0:
        return fn(t)[None]
    t = jnp.asarray(t, dtype=jnp.result_type(t, float))

    def expand(t):  # the input series (1, 0, 0, ...) is built inside, so its zeros fold away
        return jet.jet(fn, (t,), ([jnp.ones_like(t)] + [jnp.zeros_like(t)] * (order - 1),))

    try:
        y, terms = _simplify.simplify(expand)(t)
    except (KeyError, NotImplementedError):
        # a user's path with a primitive that has no Taylor rule (e.g. a loop): nested forward
        # mode gives the same derivatives with a larger program
        return taylor_nested(fn, t, order)
    return jnp.stack([y] + list(terms))


def taylor_nested(fn: Callable, t, order: int):
    """:func:`taylor` by nested ``jax.jvp`` (any differentiable ``fn``; program grows like 2^order)."""
    derivs = [fn]
    for _ in range(order):
        prev = derivs[-1]
        derivs.append(lambda s, prev=prev: jax.jvp(prev, (s,), (jnp.ones_like(s),))[1])
    return jnp.stack([d(t) for d in derivs])


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Reference:
    """A posture reference of a virtual robot.

    Attributes:
      params: pytree of arrays consumed by ``path`` (batch it to vmap over references).
      heading_offset: constant added to the tangent heading [rad] (scalar array).
      path: static function ``(t, params) -> (2,)`` giving the position of P [m].
      name: static label used in reports.
    """

    params: Any
    heading_offset: Any = 0.0
    path: Callable = dataclasses.field(default=None, metadata=dict(static=True))
    name: str = dataclasses.field(default="custom", metadata=dict(static=True))

    def position(self, t):
        """Position of the virtual robot's point P at time ``t`` [m], shape (2,)."""
        return self.path(t, self.params)

    def velocity(self, t):
        """Velocity of P [m/s], shape (2,)."""
        return jax.jvp(lambda s: self.path(s, self.params), (t,), (jnp.ones_like(t),))[1]

    def posture(self, t):
        r"""Posture :math:`\xi_{ref}(t) = (x, y, \theta)` [m, m, rad], shape (3,)."""
        p = self.position(t)
        v = self.velocity(t)
        theta = _math.atan2(-v[0], v[1]) + self.heading_offset
        return jnp.concatenate([p, theta[None]])

    def speed(self, t):
        """Speed of P, ``|p'(t)|`` [m/s]."""
        return jnp.linalg.norm(self.velocity(t))

    def domain(self):
        """``(start, end)`` [s] of the times on which the path is defined by data (a sampled
        path's first and last sample; arrays, batched like ``params``), or None for a path
        defined at every time. Controllers refuse a horizon outside it (``check_reference``)."""
        f = getattr(self.path, "domain", None)
        return None if f is None else f(self.params)

    def breakpoints(self):
        """Times [s] ((N,) array, increasing) between which the path is one analytic piece (a
        sampled path's sample times: its spline's knots), or None for a path analytic at every
        time. An enclosure over a time box across a breakpoint straddles two pieces; over a box
        inside ``[b_j, b_{j + 1}]`` it can use :meth:`piece` ``(j)`` instead."""
        f = getattr(self.path, "breakpoints", None)
        return None if f is None else f(self.params)

    def piece(self, j) -> "Reference":
        """The path's piece on ``[b_j, b_{j + 1}]`` (:meth:`breakpoints`), continued analytically
        to every time: equal to this reference on that interval (at ``b_{j + 1}`` too: the spline's
        derivatives that a law uses are continuous at its knots), a polynomial in t outside it.

        Args:
          j: the piece's index, 0 <= j <= N - 2 (an integer array: traced and vmapped too).

        Raises:
          ValueError: a path without breakpoints.
        """
        f = getattr(self.path, "piece", None)
        if f is None:
            raise ValueError(f"the path {self.name!r} has no pieces (Reference.breakpoints() is None)")
        return dataclasses.replace(self, params=f(self.params, j), path=_path_polynomial)

    def with_heading_offset(self, offset) -> "Reference":
        """The same path with another constant heading offset [rad] (a crab angle)."""
        return dataclasses.replace(self, heading_offset=_as_array(offset))


# a horizon may pass a sampled path's ends by this much (relative), the rounding of t0 + n dt
DOMAIN_RTOL = 1e-9


def check_domain(ref: "Reference", t0: float, t_final: float) -> None:
    """ValueError if [t0, t_final] leaves the times on which ``ref`` is defined by data
    (:meth:`Reference.domain`); no-op for paths defined at every time and for traced params."""
    dom = ref.domain()
    if dom is None:
        return
    lo, hi = (concrete(x) for x in dom)
    if lo is None or hi is None:
        return
    check_span(ref.name, float(np.max(lo)), float(np.min(hi)), t0, t_final)


def check_span(name: str, lo: float, hi: float, t0: float, t_final: float) -> None:
    """ValueError if the horizon [t0, t_final] [s] leaves a sampled path's span [lo, hi] [s]
    (beyond :data:`DOMAIN_RTOL`): what :func:`check_domain` checks, on the sample times alone
    (before any spline is built)."""
    tol = DOMAIN_RTOL * (1.0 + max(abs(lo), abs(hi)))
    if t0 < lo - tol or t_final > hi + tol:
        where = "before its first" if t0 < lo - tol else "past its last"
        raise ValueError(
            f"reference {name!r} is defined by its samples on [{lo:g}, {hi:g}] s, and the horizon "
            f"[{t0:g}, {t_final:g}] s goes {where} sample: fit the horizon inside the samples, add "
            "samples, or extend the path explicitly at its end's velocity (from_samples(..., extrapolate=True); "
            "extrapolate = true in a problem file's [reference])"
        )


def _as_array(x):
    return jnp.asarray(x, dtype=jnp.result_type(float))


# --- the paper's references -------------------------------------------------------

_A62 = math.sqrt(2.0) * 1e-2 / 3.0


def _path_62(t, params):
    del params
    u = 10.0 - 2.0 * t
    s = _A62 * u**3 - math.sqrt(2.0) / 2.0 * t + 5.0 * math.sqrt(2.0) / 6.0
    return jnp.stack([s, s])


def paper_62() -> Reference:
    r"""Eq (62): :math:`x_{ref} = y_{ref} = \frac{\sqrt2\,10^{-2}}{3}(10-2t)^3 - \frac{\sqrt2}{2}t + \frac{5\sqrt2}{6}` (§6.1)."""
    return Reference(params=(), path=_path_62, name="paper_62")


def _path_66(t, params):
    del params
    s = 1e-2 * math.sqrt(2.0) / 6.0 * (10.0 - t) ** 3
    return jnp.stack([s, s])


def paper_66() -> Reference:
    r"""Eq (66): :math:`x_{ref} = y_{ref} = 10^{-2}\frac{\sqrt2}{6}(10-t)^3`, at rest at the origin at t = 10 s (§6.2)."""
    return Reference(params=(), path=_path_66, name="paper_66")


# --- simple families -------------------------------------------------------------


def _path_line(t, params):
    return params["start"] + t * params["velocity"]


def line(start=(0.0, 0.0), velocity=(1.0, 0.0), heading_offset=0.0) -> Reference:
    """Straight line at constant velocity: ``p(t) = start + t velocity`` [m, m/s]."""
    return Reference(
        params=dict(start=_as_array(start), velocity=_as_array(velocity)),
        heading_offset=_as_array(heading_offset),
        path=_path_line,
        name="line",
    )


def _path_circle(t, params):
    s, c = _math.sincos(params["omega"] * t + params["phase"])
    return params["center"] + params["radius"] * jnp.stack([c, s])


def circle(center=(0.0, 0.0), radius=2.0, omega=0.5, phase=0.0, heading_offset=0.0) -> Reference:
    """Circle of ``radius`` [m] about ``center`` at angular rate ``omega`` [rad/s] (sign = direction)."""
    return Reference(
        params=dict(center=_as_array(center), radius=_as_array(radius), omega=_as_array(omega), phase=_as_array(phase)),
        heading_offset=_as_array(heading_offset),
        path=_path_circle,
        name="circle",
    )


def _path_eight(t, params):
    s, c = _math.sincos(params["omega"] * t)
    return params["center"] + params["size"] * jnp.stack([s, s * c])


def figure_eight(center=(0.0, 0.0), size=3.0, omega=0.3, heading_offset=0.0) -> Reference:
    """Lemniscate of Gerono ``p = center + size (sin wt, sin wt cos wt)``.

    Its speed never vanishes: ``|p'|^2 = (size omega)^2 (cos^2 wt + cos^2 2wt)`` is smallest
    at ``cos^2 wt = 3/8``, so ``|p'| >= size * omega * sqrt(7) / 4``.
    """
    return Reference(
        params=dict(center=_as_array(center), size=_as_array(size), omega=_as_array(omega)),
        heading_offset=_as_array(heading_offset),
        path=_path_eight,
        name="figure_eight",
    )


def _path_random(t, params):
    s, c = _math.sincos(params["omega"] * t + params["phase"])  # (K,)
    # p(t) = p0 + V t d + sum_k A_k sin(w_k t + phi_k) / w_k  ->  p' = V d + sum_k A_k cos(...)
    return (
        params["start"]
        + t * params["speed"] * params["direction"]
        + (params["amplitude"] * (s / params["omega"])[:, None]).sum(0)
    )


def random_smooth(
    key, n_modes: int = 3, speed: float = 1.0, min_speed: float = 0.3, max_omega: float = 1.0, start_scale: float = 0.0
) -> Reference:
    r"""A keyed random smooth reference with a guaranteed speed floor.

    ``p(t) = p_0 + V t d + \sum_k A_k \sin(\omega_k t + \phi_k)/\omega_k`` with unit ``d``
    and :math:`\sum_k \|A_k\| = V - v_{min}`, so :math:`\|\dot p(t)\| \ge v_{min} > 0` for
    every t: the dynamic linearizing controllers stay regular along it (for e = 0).

    Args:
      key: a ``jax.random`` key. ``jax.vmap(lambda k: random_smooth(k))(keys)`` draws a batch.
      n_modes: number of sinusoids (static).
      speed: mean speed V [m/s].
      min_speed: speed floor [m/s], 0 < min_speed < speed.
      max_omega: sinusoid frequencies are drawn in [0.2, 1] * max_omega [rad/s].
      start_scale: start point drawn in a box of this half-width [m].

    Returns:
      A :class:`Reference` whose ``params`` are arrays (batched when vmapped).
    """
    if not 0.0 < min_speed < speed:
        raise ValueError(f"random_smooth needs 0 < min_speed < speed, got min_speed={min_speed}, speed={speed}")
    if not (
        hasattr(key, "dtype")
        and (jnp.issubdtype(key.dtype, jax.dtypes.prng_key) or (key.dtype == jnp.uint32 and key.shape[-1:] == (2,)))
    ):
        raise ValueError(
            f"random_smooth: key must be a jax.random key (jax.random.key(seed) or "
            f"jax.random.PRNGKey(seed)), got {key!r:.60}"
        )
    k = jax.random.split(key, 6)
    ang = jax.random.uniform(k[0], (), minval=-jnp.pi, maxval=jnp.pi)
    sd, cd = _math.sincos(ang)
    amp_dir = jax.random.uniform(k[1], (n_modes,), minval=-jnp.pi, maxval=jnp.pi)
    sa, ca = _math.sincos(amp_dir)
    w = jax.random.dirichlet(k[2], jnp.ones(n_modes))
    amplitude = ((speed - min_speed) * w)[:, None] * jnp.stack([ca, sa], axis=1)
    omega = max_omega * jax.random.uniform(k[3], (n_modes,), minval=0.2, maxval=1.0)
    phase = jax.random.uniform(k[4], (n_modes,), minval=-jnp.pi, maxval=jnp.pi)
    start = start_scale * jax.random.uniform(k[5], (2,), minval=-1.0, maxval=1.0)
    params = dict(
        start=start,
        speed=jnp.asarray(speed, start.dtype),
        direction=jnp.stack([cd, sd]),
        amplitude=amplitude,
        omega=omega,
        phase=phase,
    )
    return Reference(params=params, heading_offset=jnp.zeros((), start.dtype), path=_path_random, name="random_smooth")


def from_function(path: Callable, params: Any = (), heading_offset=0.0, name: str = "custom") -> Reference:
    """Wrap a user path ``path(t, params) -> (2,)`` (must be hashable: a module-level function)."""
    return Reference(params=params, heading_offset=_as_array(heading_offset), path=path, name=name)


def named(name: str) -> Reference:
    """A reference of a named (deterministic) family with its default parameters."""
    fam = FAMILIES.get(name)
    if fam is None or fam.kind != "named":
        raise ValueError(f"unknown reference {name!r}; expected one of {sorted(REFERENCES)}")
    return fam.make()


# --- references from the user's own samples ---------------------------------------------

SPLINE_DEGREE = 5  # quintic: C^4, enough for every law whose reference jet uses p up to order 4
# the degrees a sampled path may have: odd (an interpolating spline of odd degree has its knots at
# the samples), C^(k-1). Degree 7 is for the torque-level (1,1) dynamic law, whose outputs
# P + e x1(theta) use the path's fifth derivative (through its heading): :func:`spline_degree_for`.
SPLINE_DEGREES = (5, 7)


def spline_degree_for(path_order: int) -> int:
    """The smallest degree of :data:`SPLINE_DEGREES` whose spline has a continuous derivative of
    order ``path_order`` (a law's :attr:`path_order`): a jump there is a jump of the law's
    feed-forward, which a fixed-step integrator follows only to O(dt) (and the certificates'
    empirical checks then measure the integrator, not the loop)."""
    for k in SPLINE_DEGREES:
        if k - 1 >= path_order:
            return k
    raise ValueError(
        f"a law using the path's derivative of order {path_order} needs a spline of degree > "
        f"{SPLINE_DEGREES[-1]}; sampled paths have degree {' or '.join(map(str, SPLINE_DEGREES))}"
    )


def _span(knots, s, n_coef: int, k: int):
    """Index ``l`` with ``knots[l] <= s < knots[l + 1]``, clamped to ``[k, n_coef - 1]`` (end pieces extend)."""
    # the span index is piecewise constant in s: no derivative flows through it (and Taylor
    # mode then evaluates the search once, with no rule needed for its loop)
    l = jnp.searchsorted(knots, jax.lax.stop_gradient(s), side="right").astype(jnp.result_type(int)) - 1
    return jnp.clip(l, k, n_coef - 1)


def _basis(knots, l, s, k: int):
    """The ``k + 1`` B-spline basis functions of degree ``k`` that are non-zero on span ``l``, at ``s``.

    Cox-de Boor recursion (Piegl & Tiller, Algorithm A2.2); polynomial in ``s`` on the span,
    so every derivative with respect to ``s`` (and to the knots) comes from autodiff.
    """
    window = jax.lax.dynamic_slice(knots, (l - k + 1,), (2 * k,))  # knots[l-k+1 .. l+k]
    left = [s - window[k - j] for j in range(1, k + 1)]  # s - knots[l+1-j]
    right = [window[k - 1 + j] - s for j in range(1, k + 1)]  # knots[l+j] - s
    n = [jnp.ones_like(s)]
    for j in range(1, k + 1):
        saved = jnp.zeros_like(s)
        new = []
        for r in range(j):
            denom = right[r] + left[j - r - 1]
            temp = n[r] / jnp.where(denom == 0, 1.0, denom)
            new.append(saved + right[r] * temp)
            saved = left[j - r - 1] * temp
        n = new + [saved]
    return jnp.stack(n)


def _spline_value(knots, coef, s, k: int):
    """Value of the B-spline of degree ``k``, ``sum_j coef[j] B_j(s)``; ``coef``: (n, d)."""
    n = coef.shape[0]
    l = _span(knots, s, n, k)
    b = _basis(knots, l, s, k)
    return b @ jax.lax.dynamic_slice_in_dim(coef, l - k, k + 1, axis=0)


# uneven samples up to this many find their piece by comparing with every sample (no loop)
COMPARE_ALL_SAMPLES = 512


def _piece(ts, s, uniform: bool):
    """Index ``j`` of the sample interval ``[ts[j], ts[j + 1])`` holding ``s``, clamped to
    ``[0, N - 2]`` (the end pieces extend).

    The index is piecewise constant in ``s``: no derivative flows through it. On samples at a
    nearly constant rate (``uniform``: every sample within a quarter step of its place on the
    grid), the grid's index is off by at most one, which two comparisons correct: a few
    operations instead of a binary search, inside a loop that evaluates the reference at every
    stage of every step.
    """
    s = jax.lax.stop_gradient(s)
    ts = jax.lax.stop_gradient(ts)
    n = ts.shape[-1]
    int_type = jnp.result_type(int)
    if uniform:
        guess = jnp.floor((s - ts[0]) * ((n - 1) / (ts[-1] - ts[0]))).astype(int_type)
        j = jnp.clip(guess, 0, n - 2)
        j = j - (s < ts[j]).astype(int_type) + (s >= ts[jnp.minimum(j + 1, n - 1)]).astype(int_type)
    elif n <= COMPARE_ALL_SAMPLES:
        # one comparison per sample, summed: no loop, so the exported C step (scalar code, no
        # loops) can hold it; a binary search is a `scan` there (waypoints, timed by chord length,
        # are not even, and their export failed). The same index.
        j = jnp.sum((ts <= s).astype(int_type)) - 1
    else:
        j = jnp.searchsorted(ts, s, side="right").astype(int_type) - 1
    return jnp.clip(j, 0, n - 2)


def _horner(pp, ts, s, uniform: bool):
    """The piecewise polynomial ``sum_i pp[j, i] (s - ts[j])^i`` on the piece ``j`` holding ``s``."""
    ts, pp = jnp.asarray(ts), jnp.asarray(pp)  # params held as NumPy arrays (a problem's) index by tracers too
    j = _piece(ts, s, uniform)
    c = jax.lax.dynamic_index_in_dim(pp, j, axis=0, keepdims=False)  # (k + 1, 2)
    return _polynomial(c, s - ts[j])


def _polynomial(c, u):
    """``sum_i c[i] u^i`` by Horner's rule (``c``: (k + 1, ...), the degree static from its shape)."""
    v = c[-1]
    for i in range(c.shape[0] - 2, -1, -1):
        v = v * u + c[i]
    return v


def _path_spline(t, params):
    return _horner(params["pp"], params["t"], t, uniform=False)


def _path_spline_uniform(t, params):
    return _horner(params["pp"], params["t"], t, uniform=True)


# [s] the least time scale of an extension past a sampled path's end (else the last k sample
# intervals): the derivatives of its blend scale like 1 / T^j, and over a second or more the
# law's feed-forward stays of the size of the path's own (a blend over one 20 Hz interval put
# a jump into the reference check's finite differences)
EXTENSION_TIME = 1.0


def _extension(c, tau, scale):
    r"""The path past an end, ``tau`` >= 0 [s] away from it, from the end's Taylor coefficients ``c``
    ((k + 1, 2), in ``tau``): :math:`c_0 + c_1\tau + \varphi((k+1)\tau/T)\sum_{i=2}^{k-1} c_i\tau^i` with
    :math:`\varphi(x) = e^{-x}\sum_{j \le k} x^j/j!` (a gentle step: its derivative is
    :math:`-e^{-x}x^k/k!`). :math:`\varphi - 1 = O(x^{k+1})`, so every derivative up
    to order k - 1 is the spline's at the end (the law's feed-forward stays continuous), and the
    path tends to the straight line at the end's velocity within a few ``scale`` [s]: bounded
    speed, where the end polynomial itself ran off (a lane change sampled at 20 Hz on [0, 4] s:
    13 m off and 14.8 m/s at 8 s, 395 m off at 12 s, measured at commit bd57cac)."""
    k = c.shape[-2] - 1
    tau = jnp.maximum(tau, 0.0)  # the side not selected is evaluated too: keep it finite
    v = c[k - 1]  # without c_k: the k-th derivative jumps at every sample already, and a septic
    for i in range(k - 2, 1, -1):  # end piece's c_7 (0.96 on a lane change) ran the blend off at 2.3 m/s
        v = v * tau + c[i]
    x = tau * ((k + 1) / scale)  # the blend's mean time is ``scale``
    blend, term = jnp.ones_like(x), jnp.ones_like(x)
    for j in range(1, k + 1):  # e^-x sum_{j <= k} x^j / j!: 1 - O(x^(k+1)), derivative -e^-x x^k / k!
        term = term * x / j
        blend = blend + term
    return c[0] + c[1] * tau + jnp.exp(-x) * blend * v * tau**2


def _extended(t, params, uniform: bool):
    """The spline inside its samples, :func:`_extension` past either end."""
    ts, ends = jnp.asarray(params["t"]), jnp.asarray(params["ends"])
    # clamped by where, not clip: at an end itself, clip's derivative is split between the sides
    inside = _horner(params["pp"], ts, jnp.where(t > ts[-1], ts[-1], jnp.where(t < ts[0], ts[0], t)), uniform)
    k = ends.shape[-2] - 1
    after = _extension(ends[1], t - ts[-1], jnp.maximum(ts[-1] - ts[-1 - k], EXTENSION_TIME))
    before = _extension(ends[0], ts[0] - t, jnp.maximum(ts[k] - ts[0], EXTENSION_TIME))
    return jnp.where(t > ts[-1], after, jnp.where(t < ts[0], before, inside))


def _end_coefficients(pp, ts):
    """Taylor coefficients (2, k + 1, 2) of the path at its first sample (in the time before it,
    tau = t0 - t) and at its last (tau = t - tN), from the spline's pieces."""
    k = pp.shape[-2] - 1
    i = np.arange(k + 1)
    first = pp[0] * ((-1.0) ** i)[:, None]
    h = ts[-1] - ts[-2]
    binom = np.array([[math.comb(a, b) if a >= b else 0 for a in range(k + 1)] for b in range(k + 1)], float)
    powers = h ** np.clip(i[None, :] - i[:, None], 0, None).astype(float)  # h^(a - b) for a >= b
    last = (binom * powers) @ pp[-1]  # the last piece re-centred at its right end
    return jnp.stack([first, last])


def _path_spline_extrapolated(t, params):
    """:func:`_path_spline`, extended past its samples on request (``extrapolate=True``)."""
    return _extended(t, params, uniform=False)


def _path_spline_uniform_extrapolated(t, params):
    """:func:`_path_spline_uniform`, extended past its samples on request."""
    return _extended(t, params, uniform=True)


# a sampled path is defined by its data on [first sample, last sample]
_path_spline.domain = _path_spline_uniform.domain = lambda params: (params["t"][..., 0], params["t"][..., -1])


def _path_polynomial(t, params):
    """One piece of a sampled path, ``sum_i c[i] (t - t0)^i``, at every time (:meth:`Reference.piece`)."""
    return _polynomial(jnp.asarray(params["c"]), t - params["t0"])


def _spline_piece(params, j):
    """The params of :func:`_path_polynomial` for piece ``j`` of a sampled path (its Taylor
    coefficients at ``t[j]``: the pieces' own)."""
    ts, pp = jnp.asarray(params["t"]), jnp.asarray(params["pp"])
    return dict(
        c=jax.lax.dynamic_index_in_dim(pp, j, axis=0, keepdims=False),
        t0=jax.lax.dynamic_index_in_dim(ts, j, keepdims=False),
    )


# a sampled path's pieces join at its samples; past its ends (extrapolated) it is the extension,
# which no piece describes (an enclosure there is not pinned)
for _f in (_path_spline, _path_spline_uniform, _path_spline_extrapolated, _path_spline_uniform_extrapolated):
    _f.breakpoints, _f.piece = (lambda params: params["t"]), _spline_piece
del _f

_SPLINE_PATHS = {  # (uniform, extrapolate) -> path
    (False, False): _path_spline,
    (True, False): _path_spline_uniform,
    (False, True): _path_spline_extrapolated,
    (True, True): _path_spline_uniform_extrapolated,
}


def piece_breaks(ref: Reference, t_final: float):
    """The breakpoints of ``ref`` that pin enclosures over ``[0, t_final]`` to its pieces
    (:meth:`Reference.breakpoints`), or None: a reference without them, or a horizon past them
    (an extrapolated path's ends, where no piece's polynomial is the path).

    Args:
      ref: the reference (unbatched).
      t_final: the horizon [s].

    Returns:
      (N,) float breakpoints [s], or None.
    """
    breaks = ref.breakpoints()
    if breaks is None:
        return None
    breaks = np.asarray(breaks, float)
    if breaks.ndim != 1 or breaks[0] > 0.0 or breaks[-1] < t_final:
        return None
    return breaks


def time_boxes(ref: Reference, t_final: float, n_boxes: int):
    """Time boxes of ``[0, t_final]`` for an enclosure of the reference over time: ``n_boxes``
    equal ones, each cut at the reference's breakpoints inside it (:func:`piece_breaks`),
    so that every box lies in one piece (:func:`box_pieces`).

    Args:
      ref: the reference (unbatched).
      t_final: the horizon [s].
      n_boxes: equal boxes before the cut.

    Returns:
      ``(t_c, h, breaks)``: the boxes' centres and half-widths [s] ((B,) each) and the
      breakpoints ((N,), or None: :func:`piece_breaks`, whose boxes are not cut).
    """
    edges = np.linspace(0.0, t_final, n_boxes + 1)
    breaks = piece_breaks(ref, t_final)
    if breaks is not None:
        inner = breaks[(breaks > 0.0) & (breaks < t_final)]
        near = np.abs(edges[:, None] - inner[None, :]).min(axis=1, initial=np.inf) < PIECE_SLACK * t_final
        edges = np.union1d(edges[~near | (edges == 0.0) | (edges == t_final)], inner)  # no sliver boxes
    return 0.5 * (edges[1:] + edges[:-1]), 0.5 * np.diff(edges), breaks


# a box may pass its piece's ends by this much (relative to the horizon): the rounding of its centre
# and half width; the times there are another piece's, each covered by that piece's box too
PIECE_SLACK = 1e-12


def box_pieces(breaks, t_c, h, across: bool = False):
    """Each time box's piece: the index j with the box inside ``[breaks[j], breaks[j + 1]]``, for
    :meth:`Reference.piece`.

    Args:
      breaks: (N,) the reference's breakpoints (:func:`time_boxes`, :func:`piece_breaks`), or None.
      t_c: (B,) the boxes' centres [s].
      h: (B,) their half-widths [s].
      across: return each box's first and last piece instead, ``(lo, hi)`` ((B,) each; equal for
        a box inside one piece; -1 for a box past the breakpoints' ends), for boxes not cut at
        the breakpoints (a controller's periods).

    Returns:
      (B,) integer indices (``(lo, hi)`` with ``across``), or None without ``breaks``.

    Raises:
      RuntimeError: a box across a breakpoint, unless ``across`` (boxes must come from
        :func:`time_boxes`, or from halving its boxes): an internal error.
    """
    if breaks is None:
        return None
    slack = PIECE_SLACK * max(1.0, float(breaks[-1] - breaks[0]))
    piece = lambda t, side: np.clip(np.searchsorted(breaks, t, side=side) - 1, 0, breaks.size - 2)
    # an end within the slack of a breakpoint belongs to the piece on the box's side of it
    lo, hi = piece(t_c - h + slack, "right"), piece(t_c + h - slack, "left")
    hi = np.maximum(lo, hi)
    # past the ends the reference is its extrapolation, no piece's polynomial
    outside = (t_c - h < breaks[0] - slack) | (t_c + h > breaks[-1] + slack)
    if across:
        return np.where(outside, -1, lo), np.where(outside, -1, hi)
    if np.any(hi > lo) or np.any(outside):
        raise RuntimeError("a time box lies across a breakpoint of the reference: its piece is not one")
    return lo


def enclose_over_pieces(enclose, hull, breaks, t_c, h) -> tuple:
    """Per time box not cut at the breakpoints (a controller's periods, its samples), the hull of
    its pieces' enclosures over the whole box: at every time of the box the reference is one of
    its pieces' polynomials (:func:`box_pieces` with ``across``); a box past the breakpoints' ends
    the reference's own enclosure.

    Args:
      enclose: ``enclose(rows, piece)`` -> tuple of NumPy arrays (``len(rows)``, ...): the
        enclosures over the boxes ``rows`` each pinned to ``piece`` ((len(rows),) ints), or with
        ``piece`` None of the reference itself.
      hull: ``hull(a, b)`` -> an enclosure holding both (tuples as ``enclose`` gives).
      breaks: (N,) the reference's breakpoints (:func:`piece_breaks`).
      t_c: (B,) the boxes' centres [s].
      h: (B,) their half-widths [s].

    Returns:
      ``enclose``'s tuple over every box.
    """
    first, last = box_pieces(breaks, t_c, h, across=True)
    out = [np.array(x) for x in enclose(np.arange(t_c.size), np.maximum(first, 0))]
    for k in range(1, int(np.max(last - first)) + 1):  # only the boxes with a k-th further piece
        rows = np.flatnonzero(last - first >= k)
        for x, y in zip(out, hull(tuple(x[rows] for x in out), enclose(rows, first[rows] + k))):
            x[rows] = y
    past = np.flatnonzero(first < 0)
    if past.size:
        for x, y in zip(out, enclose(past, None)):
            x[past] = y
    return tuple(out)


# samples count as uniform when each lies within this fraction of a step of its place on the grid
UNIFORM_TOLERANCE = 0.25


def _is_uniform(t) -> bool:
    """Whether concrete sample times lie within a quarter step of an even grid (False if traced)."""
    tv = concrete(t)
    if tv is None:
        return False
    tv = np.asarray(tv, float)
    grid = np.linspace(tv[0], tv[-1], tv.shape[0])
    return bool(np.max(np.abs(tv - grid)) <= UNIFORM_TOLERANCE * (tv[-1] - tv[0]) / (tv.shape[0] - 1))


def _spline_knots(ts, k: int):
    """Not-a-knot knots of an interpolating spline of odd degree k at ``ts`` (as SciPy's
    ``make_interp_spline``): the end sample repeated k + 1 times, interior knots at the
    interior samples except the (k - 1) / 2 nearest each end."""
    h = (k - 1) // 2
    return jnp.concatenate([jnp.repeat(ts[:1], k + 1), ts[h + 1 : ts.shape[0] - h - 1], jnp.repeat(ts[-1:], k + 1)])


# floats per sample of a spline's construction: its banded system (a block row of 3k^2 entries
# per k samples, twice: the band and its eliminated blocks), the solve's right-hand sides, and the
# pieces' Taylor jets (k + 1 coefficients by 2 coordinates), with a factor 2 for the program's
# temporaries
def _spline_floats_per_sample(k: int) -> float:
    return 2.0 * (2 * 3 * k + 4 + 2 * (k + 1) * (k + 1))


def _check_spline_fits(n: int, k: int) -> None:
    """ValueError, before anything is allocated, when a spline through ``n`` samples does not fit
    in the memory available now (the message says how much it needs)."""
    resources.check_fits(
        resources.Estimate(0.0, 8.0 * n * _spline_floats_per_sample(k)),
        f"a sampled path of {n} samples (its spline of degree {k})",
        "resample the path at fewer points (a spline through a few thousand samples follows any planned path closely)",
    )


def _check_samples(t, xy, k: int):
    """ValueError for samples a spline of degree ``k`` cannot interpolate (concrete inputs only)."""
    for name, v in (("t", t), ("xy", xy)):  # a complex path lost its imaginary part silently
        check_real(f"from_samples: {name}", v)
    tv, xv = concrete(t), concrete(xy)
    if tv is not None:
        tv = np.asarray(tv)
        if tv.ndim != 1:
            raise ValueError(f"from_samples: t must be a 1-D array of times [s], got shape {tv.shape}")
        if tv.shape[0] < k + 1:
            raise ValueError(
                f"from_samples needs at least {k + 1} samples for a spline of degree {k}, got {tv.shape[0]}"
            )
        if not np.all(np.isfinite(tv)):
            raise ValueError("from_samples: t has non-finite values")
        steps = np.diff(tv)
        if not np.all(steps > 0):
            i = int(np.argmin(steps > 0))
            raise ValueError(
                f"from_samples: times must be strictly increasing, got t[{i}] = {tv[i]} then t[{i + 1}] = {tv[i + 1]}"
            )
    if xv is not None:
        xv = np.asarray(xv)
        n = None if tv is None else tv.shape[0]
        if xv.ndim != 2 or xv.shape[1] != 2 or (n is not None and xv.shape[0] != n):
            raise ValueError(
                f"from_samples: xy must have shape ({n if n is not None else 'N'}, 2) (x, y per time) [m], "
                f"got {xv.shape}"
            )
        if not np.all(np.isfinite(xv)):
            raise ValueError("from_samples: xy has non-finite values")


def _natural_knots(ts, k: int):
    """Knots of an interpolating spline of odd degree k with natural ends: the end sample
    repeated k + 1 times, every interior sample a knot."""
    return jnp.concatenate([jnp.repeat(ts[:1], k + 1), ts[1:-1], jnp.repeat(ts[-1:], k + 1)])


@functools.partial(jax.jit, static_argnums=2)
def _interpolant(t, xy, k: int):
    """The interpolating spline of degree ``k`` through ``(t, xy)`` as polynomial pieces: (N - 1, k + 1, 2),
    ``[j, i]`` the i-th Taylor coefficient at ``t[j]`` (from the right) of the spline on
    ``[t[j], t[j + 1]]``.

    Degree 5 has not-a-knot ends (SciPy's ``make_interp_spline(t, xy, k=5)``). Degree 7 has
    natural ends, derivatives 4 to 6 zero at both ends (``bc_type=([(4, 0), (5, 0), (6, 0)],)
    * 2``): a septic not-a-knot end piece spans four intervals and swings far off sparse
    waypoints (1.5 m on a 16-waypoint ellipse of 6 m by 3 m).

    The spline is solved in B-spline form (collocation at the samples, plus the end
    conditions) and its pieces are read off by Taylor mode at each sample: evaluating a piece
    is then a lookup and Horner's rule, where the B-spline form runs the Cox-de Boor
    recursion (15 divisions for degree 5) and its derivatives at every evaluation.
    """
    natural = k > SPLINE_DEGREE
    knots = _natural_knots(t, k) if natural else _spline_knots(t, k)
    n = t.shape[0] + k - 1 if natural else t.shape[0]  # B-spline coefficients

    def row(s):  # the k + 1 basis functions non-zero at s, and the first one's index
        l = _span(knots, s, n, k)
        return _basis(knots, l, s, k), l - k

    def derivative_rows(s):  # the non-zero basis functions' derivatives 0 .. k - 1 at s: (k, k + 1)
        l = _span(knots, s, n, k)
        return taylor(lambda u: _basis(knots, l, u, k), s, k - 1), l - k

    values, starts = jax.vmap(row)(t)
    b = xy
    if natural:  # derivatives (k + 1) / 2 .. k - 1 of the spline zero at both ends: rows first and last
        orders = slice((k + 1) // 2, k)
        (d0, s0), (d1, s1) = derivative_rows(t[0]), derivative_rows(t[-1])
        m = d0[orders].shape[0]
        values = jnp.concatenate([d0[orders], values, d1[orders]])
        starts = jnp.concatenate([jnp.full(m, s0), starts, jnp.full(m, s1)])
        zeros = jnp.zeros((m, 2), b.dtype)
        b = jnp.concatenate([zeros, b, zeros])
    # banded: every row's entries lie within k columns of its diagonal (the knots' layout), so the
    # system is block tridiagonal in blocks of k: solved in linear time and memory
    coef = _math.banded_solve(values, starts, b, k)
    factorials = jnp.asarray([math.factorial(i) for i in range(k + 1)], t.dtype)
    jets = jax.vmap(lambda s: taylor(lambda u: _spline_value(knots, coef, u, k), s, k))(t[:-1])  # (N - 1, k + 1, 2)
    return jets / factorials[:, None]


def _spline_params(t, pp, extrapolate: bool) -> dict:
    """A sampled path's params: times and pieces, and the ends' coefficients if it extends past them."""
    return dict(t=t, pp=pp, ends=_end_coefficients(pp, t)) if extrapolate else dict(t=t, pp=pp)


def from_samples(
    t,
    xy,
    *,
    min_speed: float | None = None,
    heading_offset=0.0,
    name: str = "samples",
    extrapolate: bool = False,
    degree: int = SPLINE_DEGREE,
) -> Reference:
    r"""A reference through sampled positions: the interpolating spline of degree 5 (C^4) or 7 (C^6).

    The spline is the one SciPy's ``make_interp_spline(t, xy, k=degree)`` builds (not-a-knot
    ends for degree 5, natural ends for 7), solved in JAX: the reference is differentiable
    with respect to time (every derivative up to order ``degree - 1`` is continuous) and with
    respect to the samples ``t`` and ``xy`` (call ``from_samples`` inside the differentiated
    function). The path is defined on ``[t[0], t[-1]]`` (:meth:`Reference.domain`): a run
    or a check whose horizon leaves it is refused, unless ``extrapolate=True``, which extends
    it past each end toward the straight line at the end's velocity, every derivative up to
    ``degree - 1`` continuous at the join (:func:`_extension`; the end polynomial itself diverges:
    a quintic through a 4 s lane change was 13 m off 4 s past its end).

    Args:
      t: (N,) strictly increasing sample times [s], N >= 6.
      xy: (N, 2) positions of P at those times [m].
      min_speed: if given, a ValueError when the interpolant's speed drops below it [m/s]
        anywhere in ``[t[0], t[-1]]`` (checked at 8 points per interval): the dynamic laws
        need a moving reference (its heading is the path tangent).
      heading_offset: constant heading offset [rad].
      name: label used in reports.
      extrapolate: allow times outside ``[t[0], t[-1]]`` (the end pieces extended).
      degree: 5 (default) or 7. A law's reference jet uses the path's derivatives up to its
        ``path_order``; the spline must keep that one continuous (:func:`spline_degree_for`):
        degree 7 for the torque-level (1,1) dynamic law, 5 for every other law. Problem files
        choose it from their law.

    Returns:
      A :class:`Reference` whose params are ``{"t": (N,), "pp": (N - 1, degree + 1, 2)}`` (and,
      extrapolated, ``"ends"``: (2, degree + 1, 2), the path's Taylor coefficients at its ends): the sample
      times and the spline's polynomial pieces (``pp[j, i]``: the i-th Taylor coefficient at
      ``t[j]`` of the piece on ``[t[j], t[j + 1]]``).

    Raises:
      ValueError: times not strictly increasing, fewer than ``degree + 1`` samples, wrong
        shapes, non-finite values, a degree other than 5 or 7, or a stop (with ``min_speed``).
    """
    if not isinstance(extrapolate, bool):
        raise ValueError(f"from_samples: extrapolate must be True or False, got {extrapolate!r}")
    if isinstance(degree, bool) or degree not in SPLINE_DEGREES:
        raise ValueError(f"from_samples: degree must be one of {SPLINE_DEGREES}, got {degree!r}")
    _check_samples(t, xy, degree)
    _check_spline_fits(np.shape(t)[0], degree)
    dtype = jnp.result_type(float)
    t = jnp.asarray(t, dtype)
    ref = Reference(
        params=_spline_params(t, _interpolant(t, jnp.asarray(xy, dtype), int(degree)), extrapolate),
        heading_offset=_as_array(heading_offset),
        path=_SPLINE_PATHS[_is_uniform(t), extrapolate],
        name=name,
    )
    if min_speed is not None:
        _check_min_speed(ref, t, float(min_speed))
    return ref


def _check_min_speed(ref: Reference, t, min_speed: float) -> None:
    tv = concrete(t)
    speed = None
    if tv is not None:
        tv = np.asarray(tv)
        frac = np.arange(8) / 8.0
        grid = np.concatenate([(tv[:-1, None] + frac * np.diff(tv)[:, None]).ravel(), tv[-1:]])
        with jax.ensure_compile_time_eval():
            speed = concrete(_speeds(ref, jnp.asarray(grid, jnp.result_type(float))))
    if speed is None:  # traced samples (under jit or vmap): the check needs values
        warnings.warn(
            f"from_samples: min_speed = {min_speed} m/s is not checked on traced samples (under jax.jit "
            "or jax.vmap); build the reference from concrete samples to check it",
            stacklevel=3,
        )
        return
    speed = np.asarray(speed)
    if not np.all(speed >= min_speed):
        i = int(np.nanargmin(speed)) if np.any(np.isfinite(speed)) else 0
        raise ValueError(
            f"reference {ref.name!r} slows to {speed[i]:.3g} m/s at t = {grid[i]:.4g} s, below "
            f"min_speed = {min_speed} m/s: the dynamic laws need a moving reference (its heading "
            "is the path tangent); resample the path or pass min_speed=None"
        )


@jax.jit
def _speeds(ref, ts):
    return jax.vmap(ref.speed)(ts)


def from_waypoints(
    points,
    *,
    speed: float = 1.0,
    t0: float = 0.0,
    min_speed: float | None = None,
    heading_offset=0.0,
    name: str = "waypoints",
    extrapolate: bool = False,
    degree: int = SPLINE_DEGREE,
) -> Reference:
    """A reference through position-only waypoints, timed at constant chord speed.

    Waypoint ``i`` is reached at ``t0 + (chord length from the first waypoint) / speed``;
    the path is the quintic spline of :func:`from_samples` through them, so its speed
    follows the chord speed closely when the waypoints are dense and the turns gentle.

    Args:
      points: (N, 2) waypoints [m], N >= 6, consecutive points distinct.
      speed: chord speed [m/s], > 0.
      t0: time of the first waypoint [s].
      min_speed: as in :func:`from_samples`.
      heading_offset: as in :func:`from_samples`.
      name: as in :func:`from_samples`.
      extrapolate: as in :func:`from_samples` (the path is defined from the first waypoint's
        time to the last's).
      degree: as in :func:`from_samples`.
    """
    check_real("from_waypoints: points", points)
    pv = np.asarray(points, float)
    if pv.ndim != 2 or pv.shape[1] != 2:
        raise ValueError(f"from_waypoints: points must have shape (N, 2) [m], got {pv.shape}")
    if not (np.isfinite(speed) and speed > 0):
        raise ValueError(f"from_waypoints: speed must be a finite number > 0 [m/s], got {speed}")
    chords = np.hypot(*np.diff(pv, axis=0).T)
    if np.any(chords == 0):
        i = int(np.argmin(chords))
        raise ValueError(
            f"from_waypoints: waypoints {i} and {i + 1} coincide ({pv[i].tolist()}); "
            "consecutive waypoints must be distinct"
        )
    t = t0 + np.concatenate([[0.0], np.cumsum(chords)]) / speed
    return from_samples(
        t, pv, min_speed=min_speed, heading_offset=heading_offset, name=name, extrapolate=extrapolate, degree=degree
    )


def load_samples(
    path, *, min_speed: float | None = None, heading_offset=0.0, extrapolate: bool = False, degree: int = SPLINE_DEGREE
) -> Reference:
    """:func:`from_samples` of a CSV file with a header naming columns ``t``, ``x``, ``y``
    (other columns ignored; ``#`` starts a comment; ``extrapolate`` and ``degree`` as there).

    Raises:
      ValueError: what :func:`wmrjax.io.read_csv_columns` refuses (not a regular file, over
        64 MiB, not UTF-8, a column named twice, missing columns, ...), or what
        :func:`from_samples` refuses.
    """
    path = Path(path)
    col = io.read_csv_columns(path, ("t", "x", "y"), "reference samples")
    return from_samples(
        col["t"],
        np.stack([col["x"], col["y"]], axis=1),
        min_speed=min_speed,
        heading_offset=heading_offset,
        name=path.stem,
        extrapolate=extrapolate,
        degree=degree,
    )


# --- the one registry of reference families ------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Family:
    """A family of references, as problem files and command lines name it.

    Attributes:
      name: the family's name (``[reference] family`` of a problem file).
      make: its constructor: ``make(**options)`` for ``"named"`` families, ``make(key, **options)``
        for ``"random"`` ones, :func:`from_samples` / :func:`from_waypoints` for the data families.
      kind: ``"named"`` (deterministic, options from the constructor's keywords), ``"random"``
        (one reference per PRNG key) or ``"data"`` (the user's points, from a CSV file or arrays).
      defaults: the option values a problem file starts from (random families: the keywords
        of ``make`` after the key).
      columns: a data family's columns: ``("t", "x", "y")`` (timed samples) or ``("x", "y")``
        (waypoints, timed at a chord speed).
      paper: the paper's own reference (eq 62 of §6.1, eq 66 of §6.2), tracked with its robot.
    """

    name: str
    make: Callable
    kind: str
    defaults: tuple = ()
    columns: tuple = ()
    paper: bool = False

    def options(self) -> dict:
        """Option name -> default value (named families: the constructor's keyword defaults)."""
        if self.kind == "named":
            sig = inspect.signature(self.make)
            return {k: v.default for k, v in sig.parameters.items() if k != "heading_offset"}
        return dict(self.defaults)


# random_smooth's defaults as problem files use them (a sweep file's options override them)
RANDOM_SMOOTH_DEFAULTS = (("n_modes", 3), ("speed", 1.0), ("min_speed", 0.3), ("max_omega", 1.0), ("start_scale", 0.0))

FAMILIES: dict[str, Family] = {
    f.name: f
    for f in (
        Family("paper_62", paper_62, "named", paper=True),
        Family("paper_66", paper_66, "named", paper=True),
        Family("line", line, "named"),
        Family("circle", circle, "named"),
        Family("figure_eight", figure_eight, "named"),
        Family("random_smooth", random_smooth, "random", RANDOM_SMOOTH_DEFAULTS),
        Family("samples", from_samples, "data", columns=("t", "x", "y")),
        Family("waypoints", from_waypoints, "data", columns=("x", "y")),
    )
}
"""Every reference family, by name: the one registry the problem files, the sweep, the tuner and
the certification read."""

REFERENCES = {name: f.make for name, f in FAMILIES.items() if f.kind == "named"}
"""The named (deterministic) families: name -> constructor with default parameters."""
