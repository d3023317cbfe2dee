r"""Gradients of closed-loop rollouts in the cheaper mode: forward sensitivities or reverse.

:func:`value_and_grad` is a drop-in for ``jax.value_and_grad`` for losses computed through
:func:`wmrjax.simulate`. Both of its modes differentiate the same program exactly (they agree
to rounding, tested); they differ in cost:

* ``"forward"``: forward sensitivities. The P scalar parameters' tangents are pushed through
  the rollout alongside the state (``jax.jvp``, batched over the P unit directions), so the
  time loop stays one primal loop carrying ``(z, dz/dtheta)``: no residual stack, memory of
  a forward pass, and a cost of roughly ``1 + 2.4 P`` forward passes on XLA:CPU (measured:
  10-11x a forward pass for the 4 gains of the section 6.1 loop).
* ``"reverse"``: ``jax.value_and_grad`` through the rollout's checkpointed scan (one
  recomputation of each step, then its transpose; two-level checkpointing for long
  horizons, see :func:`wmrjax.simulate`). Its cost does not grow with P: about 10x a forward
  pass for the section 6.1 loop (4 or 64 parameters), 3.7-6.2x for the other laws measured
  at B = 256 (the rollout's field is simplified so that its transpose stays small, see
  ``wmrjax._simplify``). It compiles about 1.5x slower than forward mode and stores one
  checkpoint per chunk of steps.
* ``"auto"`` (default): forward for at most :data:`FORWARD_MAX_PARAMETERS` scalar
  parameters, reverse above.
"""

from __future__ import annotations

from typing import Callable, Sequence

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

MODES = ("auto", "forward", "reverse")

# forward costs ~1 + 2.4 P forward passes, reverse ~10 for the section 6.1 loop whatever P
# (experiments/benchmark.py, gradient and gradient_many) and less for heavier laws, but reverse
# compiles ~1.5x slower and keeps checkpoints: "auto" favours compile time and memory up to 8
# parameters (pass mode="reverse" for long runs, see the README's performance notes)
FORWARD_MAX_PARAMETERS = 8


def choose_mode(n_parameters: int, mode: str = "auto") -> str:
    """``"forward"`` or ``"reverse"`` for ``n_parameters`` scalar parameters under ``mode``."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if mode != "auto":
        return mode
    return "forward" if n_parameters <= FORWARD_MAX_PARAMETERS else "reverse"


def value_and_grad(fun: Callable, argnums: int | Sequence[int] = 0, *, has_aux: bool = False,
                   mode: str = "auto") -> Callable:
    """Like ``jax.value_and_grad``, with the differentiation mode chosen by parameter count.

    Args:
      fun: scalar-valued function (returning ``(value, aux)`` when ``has_aux``).
      argnums: which positional argument(s) to differentiate (pytrees of floating arrays).
      has_aux: as in ``jax.value_and_grad``.
      mode: ``"auto"``, ``"forward"`` (forward sensitivities) or ``"reverse"``; see the
        module docstring. The mode is resolved when the function is traced, from the total
        number of scalars in the differentiated arguments.

    Returns:
      A function with ``fun``'s signature returning ``(value, grad)`` (``((value, aux), grad)``
      with ``has_aux``), ``grad`` shaped like the differentiated argument(s).

    Raises:
      ValueError: an unknown ``mode`` (at once), or a non-scalar value (when called).
    """
    choose_mode(0, mode)            # validate now, before anything is traced
    single = isinstance(argnums, int)
    nums = (argnums,) if single else tuple(argnums)

    def wrapped(*args, **kwargs):
        diff = tuple(args[i] for i in nums)
        flat, unravel = ravel_pytree(diff)
        if choose_mode(flat.size, mode) == "reverse":
            return jax.value_and_grad(fun, argnums, has_aux=has_aux)(*args, **kwargs)

        def along(theta):
            new = list(args)
            for i, a in zip(nums, unravel(theta)):
                new[i] = a
            out = fun(*new, **kwargs)
            value, aux = out if has_aux else (out, None)
            if jnp.ndim(value) != 0:
                raise ValueError(f"value_and_grad needs a scalar value, got shape {jnp.shape(value)}")
            return value, aux

        basis = jnp.eye(flat.size, dtype=flat.dtype)
        value, tangents, aux = jax.vmap(lambda v: jax.jvp(along, (flat,), (v,), has_aux=True),
                                        out_axes=(None, 0, None))(basis)
        grads = unravel(tangents.astype(flat.dtype))
        grads = grads[0] if single else grads
        return ((value, aux) if has_aux else value), grads

    return wrapped
