r"""Gradients of closed-loop rollouts in the cheaper mode: forward sensitivities or reverse.

:func:`value_and_grad` is a drop-in for ``jax.value_and_grad`` for losses computed through
:func:`wmrjax.simulate`. Both of its modes differentiate the same program exactly (they agree
to rounding, tested); they differ in cost:

* ``"forward"``: forward sensitivities. The P scalar parameters' tangents are pushed through
  the rollout alongside the state (``jax.jvp``, batched over the P unit directions), so the
  time loop stays one primal loop carrying ``(z, dz/dtheta)``: no residual stack, memory of
  a forward pass, and a cost that grows linearly with P.
* ``"reverse"``: ``jax.value_and_grad`` through the rollout's checkpointed scan (one
  recomputation of each step's RK4 stages, then its transpose; the step's two selection
  flags are stored, see :func:`wmrjax.simulate`; two-level checkpointing for long horizons).
  Its cost does not grow with P (the step runs on scalars, see :func:`wmrjax.scalarized`, so
  that its transpose assembles no arrays). It compiles slower than forward mode and stores
  the carry of every step (of every chunk of steps for long horizons) for the whole batch.
* ``"auto"`` (default): forward for at most :data:`FORWARD_MAX_PARAMETERS` scalar
  parameters, reverse above.

:func:`batch_value_and_grad` is for the common case of a loss that is a mean over a batch
of independent rollouts with shared parameters. Its reverse mode differentiates each
example on its own and batches the result (``vmap`` of the per-example ``vjp``), which
XLA:CPU runs faster than the transpose of the batched loop that ``jax.grad`` of the batch
mean builds, and keeps one chunk's checkpoints at a time; its forward mode is
:func:`value_and_grad`'s, used up to :data:`BATCH_FORWARD_MAX_PARAMETERS` parameters.
"""

from __future__ import annotations

from typing import Callable, Sequence

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from wmrjax.simulate import batch_map, batch_mesh, default_chunk

MODES = ("auto", "forward", "reverse")

# forward mode's cost grows with P, reverse mode's through the batched loop does not (the two
# are close at P = 2); reverse compiles slower and stores the batch's carry at every step:
# "auto" keeps forward mode's memory and compile time up to 2 parameters (timings: the docs'
# benchmarks page)
FORWARD_MAX_PARAMETERS = 2

# batch_value_and_grad: forward sensitivities carried through the batched loop cost more with
# every parameter, per-example reverse the same whatever P; forward for one parameter (as fast
# there, with a forward pass's memory and compile time)
BATCH_FORWARD_MAX_PARAMETERS = 1
# per-example reverse mode: examples per batch_map chunk (its forward pass, residuals and
# backward pass run chunk by chunk): the fastest of 128, 256, 512 and 1024 on the section 6.1
# loop
BATCH_REVERSE_CHUNK = 256


def choose_mode(n_parameters: int, mode: str = "auto", forward_max: int = FORWARD_MAX_PARAMETERS) -> str:
    """``"forward"`` or ``"reverse"`` for ``n_parameters`` scalar parameters under ``mode``
    (``"auto"``: forward for at most ``forward_max`` parameters)."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if mode != "auto":
        return mode
    return "forward" if n_parameters <= forward_max else "reverse"


def value_and_grad(
    fun: Callable, argnums: int | Sequence[int] = 0, *, has_aux: bool = False, mode: str = "auto"
) -> Callable:
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
    choose_mode(0, mode)  # validate now, before anything is traced
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
        value, tangents, aux = jax.vmap(
            lambda v: jax.jvp(along, (flat,), (v,), has_aux=True), out_axes=(None, 0, None)
        )(basis)
        grads = unravel(tangents.astype(flat.dtype))
        grads = grads[0] if single else grads
        return ((value, aux) if has_aux else value), grads

    return wrapped


def _batch_size(args: tuple, nums: tuple) -> int:
    """The leading batch size B of the arguments outside ``nums`` (the first leaf's: batch_map
    checks that every other leaf has it too); ValueError for bad ``argnums`` or no batch."""
    if any(not 0 <= i < len(args) for i in nums):
        raise ValueError(f"argnums {nums} out of range for {len(args)} positional arguments")
    leaves = jax.tree_util.tree_leaves([a for i, a in enumerate(args) if i not in nums])
    if not leaves:
        raise ValueError("batch_value_and_grad needs at least one batched argument (outside argnums)")
    if jnp.ndim(leaves[0]) == 0:
        raise ValueError(
            "batch_value_and_grad: the batched arguments need a leading batch axis (the same "
            f"leading batch size on every leaf), got shapes {[jnp.shape(x) for x in leaves]}"
        )
    return jnp.shape(leaves[0])[0]


def _spread(args, nums, b):
    """``args`` with the shared arguments (``nums``) broadcast along a batch of ``b``: how they
    enter :func:`wmrjax.batch_map`."""
    return [
        jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (b,) + jnp.shape(x)), v) if i in nums else v
        for i, v in enumerate(args)
    ]


def _scalar_checked(fun, has_aux):
    """``fun``, with a ValueError (at trace time) when its per-example loss is not a scalar."""

    def checked(*a):
        out = fun(*a)
        value = out[0] if has_aux else out
        if jnp.ndim(value) != 0:
            raise ValueError(f"batch_value_and_grad needs a scalar per-example loss, got shape {jnp.shape(value)}")
        return out

    return checked


def batch_value_and_grad(
    fun: Callable,
    argnums: int | Sequence[int] = 0,
    *,
    has_aux: bool = False,
    mode: str = "auto",
    chunk: int | None = None,
    mesh=None,
) -> Callable:
    """The mean of a per-example loss over a batch, and its gradient in the cheaper mode.

    ``fun(*args)`` is the scalar loss of ONE example. The arguments in ``argnums`` are the
    parameters shared by the batch (not batched); every other argument is a pytree whose
    leaves carry the batch along their leading axis B. The returned function computes
    ``mean_i fun(..., args_i, ...)`` over the B examples with :func:`wmrjax.batch_map`
    (chunks of ``chunk`` examples, ``mesh``'s devices) and its gradient with respect to the
    shared arguments:

    * ``"forward"``: :func:`value_and_grad`'s forward sensitivities through the batched loop;
    * ``"reverse"``: each example differentiated on its own (``jax.value_and_grad`` of
      ``fun``, batched by ``batch_map``), the gradients averaged: the same numbers as reverse
      mode through the batch mean (to rounding, tested), with a cheaper transposed loop;
    * ``"auto"``: forward for at most :data:`BATCH_FORWARD_MAX_PARAMETERS` scalar parameters.

    Args:
      fun: per-example scalar loss (``(loss, aux)`` with ``has_aux``).
      argnums: the shared argument(s) to differentiate (pytrees of floating arrays).
      has_aux: ``fun`` also returns auxiliary data; it comes back per example, stacked (B, ...).
      mode: ``"auto"``, ``"forward"`` or ``"reverse"``.
      chunk: examples per chunk of :func:`wmrjax.batch_map` (default on CPUs: 512 in forward
        mode, :data:`BATCH_REVERSE_CHUNK` in reverse mode, whose chunks also hold their
        residuals; on accelerators one chunk per device, as :func:`wmrjax.batch_map`'s default:
        give a chunk there to bound the residuals' memory of a very large batch).
      mesh: as in :func:`wmrjax.batch_map`.

    Returns:
      A function with ``fun``'s signature (batched arguments with a leading axis B) returning
      ``(mean_value, grad)`` (``((mean_value, aux), grad)`` with ``has_aux``), ``grad`` shaped
      like the differentiated argument(s).

    Raises:
      ValueError: an unknown ``mode`` or a ``chunk`` that is not a positive integer (at once);
        no batched argument, batched arguments of different leading sizes, or a non-scalar
        per-example loss (when called).
    """
    choose_mode(0, mode)  # validate now, before anything is traced
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1):
        raise ValueError(f"chunk must be a positive integer (examples per chunk) or None, got {chunk!r}")
    single = isinstance(argnums, int)
    nums = (argnums,) if single else tuple(argnums)

    def wrapped(*args):
        b = _batch_size(args, nums)
        checked = _scalar_checked(fun, has_aux)
        spread = lambda a: _spread(a, nums, b)
        n_par = ravel_pytree(tuple(args[i] for i in nums))[0].size

        if choose_mode(n_par, mode, BATCH_FORWARD_MAX_PARAMETERS) == "forward":

            def mean_loss(*a):
                out = batch_map(checked, *spread(a), chunk=chunk, mesh=mesh)
                return (jnp.mean(out[0]), out[1]) if has_aux else jnp.mean(out)

            return value_and_grad(mean_loss, argnums, has_aux=has_aux, mode="forward")(*args)

        per_example = jax.value_and_grad(checked, nums, has_aux=has_aux)
        reverse_chunk = (
            default_chunk(batch_mesh() if mesh is None else mesh, BATCH_REVERSE_CHUNK) if chunk is None else chunk
        )
        out, grads = batch_map(per_example, *spread(args), chunk=reverse_chunk, mesh=mesh)
        grads = jax.tree_util.tree_map(lambda g: jnp.mean(g, axis=0), grads)
        grads = grads[0] if single else grads
        value = (jnp.mean(out[0]), out[1]) if has_aux else jnp.mean(out)
        return value, grads

    return wrapped
