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
import math
from typing import Any, Callable

import jax
import jax.numpy as jnp

from wmrjax import _math


def taylor(fn: Callable, t, order: int):
    """Derivatives ``fn(t), fn'(t), ..., fn^{(order)}(t)`` by nested forward mode.

    Args:
      fn: scalar-time function returning an array of any shape S.
      t: scalar time [s].
      order: highest derivative (static int, >= 0).

    Returns:
      Array of shape ``(order + 1, *S)``.
    """
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
        theta = jnp.arctan2(-v[0], v[1]) + self.heading_offset
        return jnp.concatenate([p, theta[None]])

    def speed(self, t):
        """Speed of P, ``|p'(t)|`` [m/s]."""
        return jnp.linalg.norm(self.velocity(t))

    def with_heading_offset(self, offset) -> "Reference":
        """The same path with another constant heading offset [rad] (a crab angle)."""
        return dataclasses.replace(self, heading_offset=_as_array(offset))


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
    return Reference(params=dict(start=_as_array(start), velocity=_as_array(velocity)),
                     heading_offset=_as_array(heading_offset), path=_path_line, name="line")


def _path_circle(t, params):
    s, c = _math.sincos(params["omega"] * t + params["phase"])
    return params["center"] + params["radius"] * jnp.stack([c, s])


def circle(center=(0.0, 0.0), radius=2.0, omega=0.5, phase=0.0, heading_offset=0.0) -> Reference:
    """Circle of ``radius`` [m] about ``center`` at angular rate ``omega`` [rad/s] (sign = direction)."""
    return Reference(params=dict(center=_as_array(center), radius=_as_array(radius),
                                 omega=_as_array(omega), phase=_as_array(phase)),
                     heading_offset=_as_array(heading_offset), path=_path_circle, name="circle")


def _path_eight(t, params):
    s, c = _math.sincos(params["omega"] * t)
    return params["center"] + params["size"] * jnp.stack([s, s * c])


def figure_eight(center=(0.0, 0.0), size=3.0, omega=0.3, heading_offset=0.0) -> Reference:
    """Lemniscate of Gerono ``p = center + size (sin wt, sin wt cos wt)``.

    Its speed never vanishes: ``|p'|^2 = (size omega)^2 (cos^2 wt + cos^2 2wt)`` is smallest
    at ``cos^2 wt = 3/8``, so ``|p'| >= size * omega * sqrt(7) / 4``.
    """
    return Reference(params=dict(center=_as_array(center), size=_as_array(size), omega=_as_array(omega)),
                     heading_offset=_as_array(heading_offset), path=_path_eight, name="figure_eight")


def _path_random(t, params):
    s, c = _math.sincos(params["omega"] * t + params["phase"])  # (K,)
    # p(t) = p0 + V t d + sum_k A_k sin(w_k t + phi_k) / w_k  ->  p' = V d + sum_k A_k cos(...)
    return params["start"] + t * params["speed"] * params["direction"] + (params["amplitude"] * (s / params["omega"])[:, None]).sum(0)


def random_smooth(key, n_modes: int = 3, speed: float = 1.0, min_speed: float = 0.3,
                  max_omega: float = 1.0, start_scale: float = 0.0) -> Reference:
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
    params = dict(start=start, speed=jnp.asarray(speed, start.dtype), direction=jnp.stack([cd, sd]),
                  amplitude=amplitude, omega=omega, phase=phase)
    return Reference(params=params, heading_offset=jnp.zeros((), start.dtype), path=_path_random, name="random_smooth")


def from_function(path: Callable, params: Any = (), heading_offset=0.0, name: str = "custom") -> Reference:
    """Wrap a user path ``path(t, params) -> (2,)`` (must be hashable: a module-level function)."""
    return Reference(params=params, heading_offset=_as_array(heading_offset), path=path, name=name)


REFERENCES = {"paper_62": paper_62, "paper_66": paper_66, "line": line, "circle": circle, "figure_eight": figure_eight}


def named(name: str) -> Reference:
    """A reference by name with default parameters (used by the CLIs)."""
    if name not in REFERENCES:
        raise ValueError(f"unknown reference {name!r}; expected one of {sorted(REFERENCES)}")
    return REFERENCES[name]()
