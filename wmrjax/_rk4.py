"""The one RK4 step: classical fourth-order Runge-Kutta on a state pytree (floating leaves
integrated, integer leaves held). :mod:`wmrjax.simulate` runs it under ``lax.scan``;
:mod:`wmrjax.linearize` uses it for transition matrices. Private: the public name is
:func:`wmrjax.rk4_step`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["axpy", "held", "is_continuous", "rk4_stages", "rk4_step"]


def is_continuous(x) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


def held(k) -> bool:
    """A derivative known to be zero when the step is traced (a held value: it needs no arithmetic)."""
    return not isinstance(k, jax.core.Tracer) and not np.any(np.asarray(k))


def axpy(z, a, k):
    """``z + a k`` on the continuous (floating) leaves of a state pytree; discrete and held leaves kept."""
    return jax.tree_util.tree_map(lambda zi, ki: zi + a * ki if is_continuous(zi) and not held(ki) else zi, z, k)


def rk4_step(field, t, z, dt):
    """One classical RK4 step of ``dz/dt = field(t, z)[0]``; returns ``(z_next, aux_at_t)``.

    ``z`` may be a pytree: its floating leaves are integrated, its integer leaves (discrete
    state such as a mode) are held and change only in a system's ``post_step``.
    """
    z_next, aux, _, _ = rk4_stages(field, t, z, dt)
    return z_next, aux


def rk4_stages(field, t, z, dt, at=None):
    """RK4 step returning ``(z_next, aux_at_t, k1, k4)`` (the stages the error estimate needs).
    ``at``: what ``field`` takes in place of each stage's time (four values, e.g. the rows of a
    table of time-dependent values, :mod:`wmrjax._hoist`); None: the stage times."""
    a1, a2, a3, a4 = (t, t + 0.5 * dt, t + 0.5 * dt, t + dt) if at is None else at
    k1, aux = field(a1, z)
    k2, _ = field(a2, axpy(z, 0.5 * dt, k1))
    k3, _ = field(a3, axpy(z, 0.5 * dt, k2))
    k4, _ = field(a4, axpy(z, dt, k3))
    combine = lambda zi, a, b, c, d: (
        zi + (dt / 6.0) * (a + 2.0 * b + 2.0 * c + d) if is_continuous(zi) and not all(map(held, (a, b, c, d))) else zi
    )
    return jax.tree_util.tree_map(combine, z, k1, k2, k3, k4), aux, k1, k4
