"""Reference paths that a law must refuse, shared by the bad-input tests (module-level, so
hashable as ``Reference.path``)."""

import jax.numpy as jnp
import numpy as np


def kink(t, p):
    """A corner at t = 2 s: the velocity jumps from (1, 1) to (2, 1)."""
    del p
    return jnp.stack([t + jnp.maximum(t - 2.0, 0.0), t])


def accel_kink(t, p):
    """Continuous velocity, a jump of the acceleration at t = 2.5 s."""
    del p
    return jnp.stack([t + 0.5 * jnp.maximum(t - 2.5, 0.0) ** 2, t])


def three(t, p):
    """Returns three numbers (a heading has no place in a path)."""
    del p
    return jnp.stack([t, t, t])


def numpy_path(t, p):
    """Written with NumPy: JAX cannot trace it."""
    del p
    return np.array([float(t), 0.0])


def velocity_kink_midway(t, p):
    """A velocity corner at t = 2.005 s: midway between two points of the 0.01 s grid."""
    del p
    return jnp.stack([t + jnp.maximum(t - 2.005, 0.0), t])


def accel_kink_midway(t, p):
    """An acceleration jump at t = 2.505 s: midway between two points of the 0.01 s grid."""
    del p
    return jnp.stack([t + 0.5 * jnp.maximum(t - 2.505, 0.0) ** 2, t])
