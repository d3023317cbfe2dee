r"""Fixed-step RK4 under ``lax.scan``, with per-run diagnostics.

:func:`simulate` integrates one unbatched closed loop; batch it with ``jax.vmap`` over
initial states, references, gains or geometry, and differentiate it with ``jax.grad``.
Called with concrete arguments it is jitted at this entry point (the closed-loop object, the
step count and the saving stride are static); called inside an outer ``jit``, ``vmap`` or
``grad`` it traces into the outer program, which is the one compiled.

Six implementation choices matter for speed (``benchmarks/benchmark.py`` times them; its
results are on the benchmarks page of the docs):

* what the vector field computes from the time and the parameters alone (the reference's
  jet, a gain schedule's coefficients) is computed for every stage time of the horizon
  before the loop, vectorised, and fed to the steps as the scan's inputs
  (:mod:`wmrjax._hoist`): the loop holds only what depends on the state, and a sampled path
  costs it what a closed-form reference costs (what depends on parameters batched per run,
  a reference per run say, stays in the loop);

* the scan carry is a tuple of scalars, one per state component, so that under
  ``vmap`` each component is a contiguous batch array (structure of arrays) and the
  whole RK4 step fuses into one vectorised loop;
* the step itself is re-emitted on scalars (:mod:`wmrjax._scalarize`: the law's small
  matrices and jets as their elements) and the parameters enter it as scalars, so that
  neither the step nor its transpose assembles or takes apart an array (which XLA:CPU
  compiles into slow per-element loops, see :mod:`wmrjax._scalarize`): the rollout, and
  its reverse-mode gradient more so, run faster;
* the large laws (:data:`STAGE_LOOP_MIN_EQUATIONS`) run the four RK stages in a loop over
  one copy of the field, checkpointed stage by stage: their programs compile faster;
* the vector fields use :func:`wmrjax._math.sincos`, which XLA vectorises;
* reverse mode recomputes each step (a digital controller's whole period) from its input
  carry but stores the step's two flags that select the next state, so that the
  recomputation is the RK4 stages alone, without the diagnostics and the error estimate.

The rewriting of the step (:mod:`wmrjax._scalarize`, :mod:`wmrjax._simplify`) and the
tabulation (:mod:`wmrjax._hoist`) read JAX's internal jaxpr interfaces.
``WMRJAX_JAXPR_REWRITES=0`` in the environment runs the plain JAX program instead, the whole
field in the loop (same values to rounding, but for the simplifier's IEEE caveat: it folds
``0 * inf`` and ``0 / 0`` to 0); :func:`simulate` reads it at every call and compiles a program
for each setting. Use it to rule the rewriters out when a result looks wrong, or when a new
JAX breaks them.

A run *fails* when its state, its control or a step's error estimate becomes non-finite
(an estimate that overflows leaves the step's accuracy unknown), its singularity margin drops to
``margin_floor`` or below, the sign of its regularity function (det K) changes between two
steps (a crossing of the singular set between samples), or a step's embedded error estimate
exceeds ``error_tol`` (one rule, :func:`_classify`, at every step and at the final state).
From then on its state is frozen at the last good value and
its samples are marked invalid (``Trajectory.valid``), so batch statistics can exclude
it explicitly instead of averaging NaN or a runaway value.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name
from jax.extend import core as jex_core

from wmrjax import _hoist, _rk4, _scalarize, _simplify, resources
from wmrjax._validate import check_finite, check_int, check_number, concrete, is_concrete
from wmrjax.references import DOMAIN_RTOL, Reference
from wmrjax.system import ClosedLoop

# from this many steps on, reverse-mode differentiation checkpoints the saving chunks too
TWO_LEVEL_CHECKPOINT_STEPS = 2000
# the loop body runs on scalars; laws whose scalarized vector field has at least this many
# equations that depend on the state (what is left once the reference's jet is tabulated,
# wmrjax._hoist.state_part_size, counted as if every parameter were shared) run
# the four RK stages in a loop over one copy of it, checkpointed stage by stage: their programs,
# and their gradients', compile faster and run as fast or faster, where the unrolled step of the
# largest is a fused scalar program that XLA:CPU's loop emitter compiles slowly, into slow code.
# Small laws keep the unrolled step, which runs faster for them. On the figure-eight with the
# rows' geometries the stage loop takes (1,2) velocity (196 equations, whose certification is
# slower unrolled) up to (1,1) torque (688); (2,0) torque (175) runs faster unrolled, the section
# 6.1 law has 51 (measurements: docs/benchmarks.md).
STAGE_LOOP_MIN_EQUATIONS = 190
# reverse mode stores these flags of every step (see _simulate)
_SAVED_FLAGS = ("wmrjax_step_ok", "wmrjax_step_finite")


class Diagnostics(NamedTuple):
    """Per-run summary (scalars; batched under vmap).

    Attributes:
      nonfinite: the state, the control, the margin or a step's error estimate became NaN/Inf.
      singular: the margin reached ``margin_floor``, or the signed regularity function
        (``Aux.regularity``, det K for the linearizing laws) changed sign between two
        consecutive steps: the run crossed the singular set between samples.
      failed: ``nonfinite | singular | inaccurate``; samples from the failure on are invalid.
      t_failure: time of the first failure [s] (``inf`` if none).
      min_margin: smallest margin over the valid states at step boundaries.
      t_min_margin: when it occurred [s].
      inaccurate: a step's error estimate exceeded ``error_tol``.
      error_estimate: largest local error estimate of a step before the failure (the
        embedded third-order pair of RK4, see :func:`simulate`), relative to ``1 + max_i |z_i|``.
      internal: what the system's optional ``final_report(t, z, params)`` returns at the
        final state (the static laws: :class:`wmrjax.controllers.static.InternalDynamics`,
        the heading error and ||z3|| of their uncontrolled coordinates); None otherwise.
    """

    nonfinite: jnp.ndarray
    singular: jnp.ndarray
    failed: jnp.ndarray
    t_failure: jnp.ndarray
    min_margin: jnp.ndarray
    t_min_margin: jnp.ndarray
    inaccurate: jnp.ndarray
    error_estimate: jnp.ndarray
    internal: Any = None


class _Running(NamedTuple):
    """The diagnostics carried by the time loop (``Diagnostics.inaccurate`` is derived at the end)."""

    nonfinite: jnp.ndarray
    singular: jnp.ndarray
    failed: jnp.ndarray
    t_failure: jnp.ndarray
    min_margin: jnp.ndarray
    t_min_margin: jnp.ndarray
    error_estimate: jnp.ndarray


class Trajectory(NamedTuple):
    """A simulated run.

    Attributes:
      t: saved times, shape (T,) [s]; T = n_steps // save_every + 1 (t0 included).
      state: (T, n) states at those times (a pytree state: every leaf with a leading T axis).
      control: (T, p) plant input evaluated at those states (at the final time: at the
        last state, for completeness).
      margin: (T,) singularity margin at those states.
      valid: (T,) True where the run is alive and that state's margin and control are
        regular and finite; False from the first failure on.
      final_state: state after the last step (frozen value if the run failed), like ``z0``.
      diagnostics: :class:`Diagnostics`.
    """

    t: Any
    state: Any
    control: Any
    margin: Any
    valid: Any
    final_state: Any
    diagnostics: Diagnostics


def _rk4_stage_loop(field, t, z, dt, parts, rebuild, rows=None):
    """:func:`wmrjax._rk4.rk4_stages` of ``field(t, z, p)``, ``p = rebuild(parts)``, with its four stages run by a
    loop over one copy of the field, on scalars. ``rows``: what ``field`` takes in place of the
    stage times t, t + dt/2 and t + dt (a step's three rows of a table, :mod:`wmrjax._hoist`);
    None: the times.

    For the largest laws: the loop body holds one copy of the field instead of four, so XLA
    compiles the step faster (and its fused scalar program stays small enough for
    XLA:CPU's loop emitter, see :data:`STAGE_LOOP_MIN_EQUATIONS`). The state, the stages and
    the parameters (``parts``, from :func:`scalar_parts`) enter the body as scalars. Each stage
    is checkpointed: reverse mode stores a stage's input (a few scalars), not the residuals of
    the field's linearization, and recomputes them stage by stage. The arithmetic is
    :func:`wmrjax._rk4.rk4_stages`'s in the same order, except that the first stage adds ``0 * dt * 0`` to the
    state (a ``-0.0`` component becomes ``+0.0``) and every stage computes the field's aux (the
    first one's is kept); XLA fuses the two programs differently, so the numbers agree to
    rounding (4e-16 on 300 steps of the section 6.1 loop).
    """
    dtype = jnp.result_type(dt)
    nodes = jnp.asarray([0.0, 0.5, 0.5, 1.0], dtype)  # stage times, in units of dt
    weights = jnp.asarray([1.0, 2.0, 2.0, 1.0], dtype)  # weights x 6
    k_like, aux_like = jax.eval_shape(field, t if rows is None else rows[0], z, rebuild(parts))

    def stage(carry, stage_xs, zs, parts, rows):
        k_prev, acc, k1, aux = carry  # tuples of scalars: the continuous leaves of k; aux
        i, node, weight = stage_xs
        z_i = _rk4.axpy(_from_scalars(zs, z), node * dt, _from_continuous(k_prev, k_like))
        # a row of the table selected on scalars (stage 0: t, 3: t + dt, else t + dt/2): no array
        pick = lambda a, b, c: jnp.where(i == 0, a, jnp.where(i == 3, c, b))
        at = t + node * dt if rows is None else jax.tree_util.tree_map(pick, *rows)
        k, aux_i = field(at, z_i, rebuild(parts))
        k, aux_i = _continuous(k), _to_scalars(aux_i)
        first = i == 0
        acc = tuple(jnp.where(first, ki, s + weight * ki) for s, ki in zip(acc, k))
        keep = lambda new, old: tuple(jnp.where(first, n, o) for n, o in zip(new, old))
        return (k, acc, keep(k, k1), keep(aux_i, aux)), None

    body = jax.checkpoint(scalarized(stage), prevent_cse=False)
    zs = _to_scalars(z)
    zeros = lambda tree: jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), tree)
    zero_k, zero_aux = _continuous(zeros(k_like)), _to_scalars(zeros(aux_like))
    (k4, acc, k1, aux), _ = jax.lax.scan(
        lambda c, xs: body(c, xs, zs, parts, rows), (zero_k, zero_k, zero_k, zero_aux), (jnp.arange(4), nodes, weights)
    )
    acc = _from_continuous(acc, k_like)
    combine = lambda zi, s: zi + (dt / 6.0) * s if _rk4.is_continuous(zi) else zi
    return (
        jax.tree_util.tree_map(combine, z, acc),
        _from_scalars(aux, aux_like),
        _from_continuous(k1, k_like),
        _from_continuous(k4, k_like),
    )


def _continuous(tree):
    """The floating leaves of a pytree, flattened to one tuple of scalars."""
    return tuple(
        x for leaf in jax.tree_util.tree_leaves(tree) if _rk4.is_continuous(leaf) for x in jnp.reshape(leaf, (-1,))
    )


def _from_continuous(scalars, like):
    """Inverse of :func:`_continuous` for the structure of ``like`` (shapes or arrays); its
    discrete leaves come back as zeros."""
    leaves, treedef = jax.tree_util.tree_flatten(like)
    out, i = [], 0
    for leaf in leaves:
        shape = np.shape(leaf)
        if not _rk4.is_continuous(leaf):
            out.append(jnp.zeros(shape, leaf.dtype))
            continue
        n = int(np.prod(shape))
        out.append(jnp.stack(scalars[i : i + n]).reshape(shape) if len(shape) else scalars[i])
        i += n
    return jax.tree_util.tree_unflatten(treedef, out)


def _error_estimate(dt, k4_prev, k1, z):
    r"""Local error estimate of the step that ended at ``z``, relative to ``1 + max_i |z_i|``.

    Classical RK4 (stages at c = 0, 1/2, 1/2, 1) with the first stage of the next step,
    :math:`k_5 = f(t + h, z_{n+1})`, as a fifth stage has the embedded third-order weights
    (1/6, 1/3, 1/3, 0, 1/6) (they satisfy the four order conditions up to order 3); the
    difference of the two solutions is :math:`h (k_4 - k_5) / 6`, at no extra evaluation
    of the vector field (k5 is the next step's k1).
    """
    diff = functools.reduce(jnp.maximum, [jnp.abs(a - b) for a, b in zip(k4_prev, k1)])
    # components that do not move (derivative exactly 0: e.g. a hybrid system's switch records)
    # do not set the scale
    scale = functools.reduce(jnp.maximum, [jnp.where(k == 0, 0.0, jnp.abs(x)) for k, x in zip(k1, z)])
    return (jnp.abs(dt) / 6.0) * diff / (1.0 + scale)


def _sign(regularity, like):
    """+1/-1 from a signed regularity value; 0 where there is none (None or NaN)."""
    if regularity is None:
        return jnp.zeros_like(like)
    r = jnp.asarray(regularity, like.dtype)
    return jnp.where(jnp.isfinite(r), jnp.sign(r), 0.0)


def _all_finite(tree):
    leaves = jax.tree_util.tree_leaves(tree)
    ok = jnp.array(True)
    for leaf in leaves:
        ok = ok & jnp.all(jnp.isfinite(leaf))
    return ok


def _all_equal(a, b):
    ok = jnp.array(True)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        ok = ok & jnp.all(x == y)
    return ok


def _to_scalars(z):
    """A state pytree as a flat tuple of scalars (structure of arrays under vmap).

    One ``unstack`` per leaf, not one slice per component: reverse mode transposes it to one
    ``stack`` instead of a zero-padded vector per component, summed."""
    return tuple(x for leaf in jax.tree_util.tree_leaves(z) for x in jnp.unstack(jnp.reshape(leaf, (-1,))))


def _from_scalars(scalars, like):
    """Inverse of :func:`_to_scalars` for the structure and leaf shapes of ``like``."""
    leaves, treedef = jax.tree_util.tree_flatten(like)
    out, i = [], 0
    for leaf in leaves:
        n = int(np.prod(np.shape(leaf)))
        if n == 0:  # an empty leaf (a static law's controller state)
            out.append(jnp.zeros(np.shape(leaf), jnp.result_type(leaf)))
            continue
        out.append(jnp.stack(scalars[i : i + n]).reshape(np.shape(leaf)) if np.ndim(leaf) else scalars[i])
        i += n
    return jax.tree_util.tree_unflatten(treedef, out)


def scalarized(fun):
    """``fun`` re-emitted as operations on scalars, simplified: for the body of a loop over
    a small state, batched with ``vmap``.

    Every array of at most 64 elements in ``fun``'s traced program is held as its elements
    (:mod:`wmrjax._scalarize`), then structural zeros and repeated operations are removed
    (:mod:`wmrjax._simplify`). Under ``vmap`` each element is one contiguous batch vector, and
    XLA:CPU compiles the body, and its transpose under reverse mode, into elementwise loops
    with no array assembled or taken apart. :func:`simulate` runs its RK4 step this way; use
    it for hand-written loops (the tuner's sampled-data rollout does). Pass the state as
    scalars (a tuple) and close over parameters taken apart into scalars, or the body takes
    them apart (and its transpose assembles them) at every call. ``WMRJAX_JAXPR_REWRITES=0``
    in the environment (read when the body is traced) leaves ``fun`` as it is.

    Args:
      fun: a function of arrays (pytrees in and out), traceable by JAX.

    Returns:
      A function with ``fun``'s signature and values, up to the order of summation in dot
      products and reductions (rounding).
    """
    return _simplify.simplify(_scalarize.scalarize(fun))


def scalar_parts(tree):
    """``(parts, rebuild)``: the small floating leaves of ``tree`` taken apart into tuples of
    scalars (the other leaves as they are), and the function that puts them back together.

    For the parameters of a loop body made with :func:`scalarized`: take them apart once,
    outside the loop, and rebuild them inside the body (free there: scalarization turns the
    rebuilding into a relabelling). The body then closes over scalars, and reverse mode
    accumulates their cotangents as scalars instead of assembling an array at every step.

    Args:
      tree: a pytree of arrays (e.g. a controller's parameters).

    Returns:
      ``parts`` (a list, one entry per leaf) and ``rebuild(parts) -> tree``. ``rebuild`` is
      hashable, and equal for trees of one structure whose leaves have the same shapes and
      the same split (small floating leaves taken apart, the others kept), so a jitted loop
      body can take it as a static argument (and be traced once for all such trees).
    """
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    split = [_rk4.is_continuous(x) and np.ndim(x) > 0 and 0 < np.size(x) <= _scalarize.MAX_ELEMENTS for x in leaves]
    parts = [tuple(jnp.unstack(jnp.reshape(x, (-1,)))) if s else x for x, s in zip(leaves, split)]
    return parts, _Rebuild(treedef, tuple(np.shape(x) for x in leaves), tuple(split))


@dataclasses.dataclass(frozen=True)
class _Rebuild:
    """The inverse of :func:`scalar_parts` for one tree structure and leaf shapes (hashable).

    Attributes:
      treedef: the tree's structure.
      shapes: each leaf's shape.
      split: whether each leaf was taken apart into a tuple of scalars.
    """

    treedef: Any
    shapes: tuple
    split: tuple

    def __call__(self, parts):
        return jax.tree_util.tree_unflatten(
            self.treedef,
            [jnp.reshape(jnp.stack(p), shape) if s else p for p, shape, s in zip(parts, self.shapes, self.split)],
        )


def _scalar_field(system, t, z, params):
    """``(field(t, z, p), closed, out_tree)``: ``system``'s vector field on scalars, traced once
    at the avals of ``(t, z, params)`` (calls with the same avals replay that program), the
    traced program and the structure of its output."""
    scalar = scalarized(_simplify.simplify(lambda t, z, p: system.vector_field(t, z, p)))
    closed, shapes = jax.make_jaxpr(scalar, return_shape=True)(t, z, params)
    out_tree = jax.tree_util.tree_structure(shapes)
    replay = jex_core.jaxpr_as_fun(closed)

    def field(t, z, p):
        return jax.tree_util.tree_unflatten(out_tree, replay(*jax.tree_util.tree_leaves((t, z, p))))

    return field, closed, out_tree


def _sampler(system):
    """``(sample, sample_every)`` of a sampled-data system (``(None, None)`` otherwise): its
    ``sample(k, t, z, params)`` and its steps per sample."""
    every = system.sample_every
    if every is None:
        return None, None
    return system.sample, int(every)  # re-emitted on scalars with the step that calls it


def _period_advance(field_s, t, z, dt, every: int, estimate: bool, parts, rebuild, held_mask):
    """A sampled-data system's period from ``z`` at ``t`` (just sampled): ``every`` RK4 steps
    under the held values; ``(z_next, aux at (t, z), error estimate, (), False)``. The estimate
    is the largest of the steps after the first (the first follows the sample's jump). The
    steps integrate the moving leaves only (``held_mask``: the system's ``held(z)``, True where a
    leaf is held between samples), on scalars like the main loop's body (``field_s(t, z, p)``,
    ``p = rebuild(parts)``): the held ones come out as the same values, with no arithmetic."""
    _, aux = field_s(t, z, rebuild(parts))
    leaves, treedef = jax.tree_util.tree_flatten(z)
    moving = [_rk4.is_continuous(x) and not h for x, h in zip(leaves, jax.tree_util.tree_leaves(held_mask))]
    like = [x for x, m in zip(leaves, moving) if m]

    def merge(mov, hel):
        mov, hel = iter(mov), iter(hel)
        return jax.tree_util.tree_unflatten(treedef, [next(mov) if m else next(hel) for m in moving])

    def sub(c, j, parts, hel):
        zt, k4_prev, est = c

        def f_moving(tt, mov):
            dz, a = field_s(tt, merge(mov, hel), rebuild(parts))
            return [k for k, m in zip(jax.tree_util.tree_leaves(dz), moving) if m], a

        zj = _from_scalars(zt, like)
        z_next, _, k1, k4 = _rk4.rk4_stages(f_moving, t + j.astype(dt.dtype) * dt, zj, dt)
        if estimate:
            e = jax.lax.stop_gradient(_error_estimate(dt, k4_prev, _continuous(k1), _continuous(zj)))
            est = jnp.maximum(est, jnp.where(j == 0, 0.0, e))
        return (_to_scalars(z_next), _continuous(k4) if estimate else (), est), None

    held = tuple(x for x, m in zip(leaves, moving) if not m)
    body = scalarized(sub)
    k0s = tuple(jnp.zeros_like(x) for x in _continuous(like)) if estimate else ()
    (zt, _, est), _ = jax.lax.scan(
        lambda c, j: body(c, j, parts, held), (_to_scalars(like), k0s, jnp.zeros((), dt.dtype)), jnp.arange(every)
    )
    return merge(_from_scalars(zt, like), held), aux, est, (), jnp.array(False)


def _first_float(z):
    leaves = [x for x in jax.tree_util.tree_leaves(z) if _rk4.is_continuous(x)]
    return jnp.reshape(leaves[0], (-1,))[0]


@functools.partial(jax.jit, static_argnames=("system", "n_steps", "save_every", "save_fn", "rewrites"))
def _simulate(system, z0, params, dt, t0, n_steps, save_every, margin_floor, error_tol, save_fn=None, rewrites=True):
    # rewrites (WMRJAX_JAXPR_REWRITES, which the rewriters read as this traces): a key of the compiled program
    dtype = jnp.result_type(*[x for x in jax.tree_util.tree_leaves(z0) if _rk4.is_continuous(x)])
    dt = jnp.asarray(dt, dtype)
    t0 = jnp.asarray(t0, dtype)
    estimate = error_tol is not None  # static: None compiles the loop without the error estimate
    error_tol = jnp.asarray(jnp.inf if error_tol is None else error_tol, dtype)
    # the field on scalars (see wmrjax._scalarize), traced once and replayed by the RK stages, the
    # initial shapes and the final state's evaluation: the same arithmetic at every time, and one
    # trace of the law per run. The loop body takes the parameters apart once, outside the loop;
    # the largest laws run their RK stages in a loop over one copy of it (STAGE_LOOP_MIN_EQUATIONS)
    field_s, closed, out_tree = _scalar_field(system, t0, z0, params)
    field = lambda t, z: field_s(t, z, params)
    post_step = system.post_step
    sample, sample_every = _sampler(system)
    params_parts, rebuild_params = scalar_parts(params)
    # the field's state-independent part (the reference's jet, a schedule) tabulated before the
    # loop (a digital controller's period evaluates its law once: not worth a table, measured)
    n_leaves = len(jax.tree_util.tree_leaves(z0))
    hoisted = _hoisting(closed, out_tree, n_leaves, params, t0, dt, n_steps) if rewrites and sample is None else None
    field_q, q_parts, rebuild_q, table = hoisted or (None, None, None, ())
    # the size of the law's state-dependent part: the same choice whatever a batch varies (a
    # digital controller's period runs its own steps, without a stage loop)
    stage_loop = sample is None and _hoist.state_part_size(closed, n_leaves) >= STAGE_LOOP_MIN_EQUATIONS
    loop = _Loop(system, field_s, dt, estimate, stage_loop, post_step, sample, sample_every, rebuild_params)
    loop = loop._replace(field_q=field_q, rebuild_q=rebuild_q, hoisted=hoisted is not None)
    carry_k4 = estimate and sample is None  # the continuous loops carry the last stage for the next estimate

    def step_on_scalars(carry, ix, parts):
        zt, alive, diag, sign_prev, k4_prev, est_ok = carry  # est_ok is None without discrete transitions
        (i, x), p = ix, rebuild_params(parts[0])
        z = _from_scalars(zt, z0)
        t = t0 + i.astype(dtype) * dt
        z_in = z  # what a failed run keeps: a dead run's sample is discarded by the selection below
        if sample is not None:  # a digital controller samples at its period's start
            z = sample(i // sample_every, t, z, p)
        z_next, aux, est, k4, jumped = _advance(loop, t, z, i, p, parts, k4_prev, est_ok, x)
        margin = jnp.asarray(aux.margin, dtype)
        reg, step_est = getattr(aux, "regularity", None), est if estimate else None
        # classify the state z at time t
        flags = _classify(alive, aux.control, margin, reg, sign_prev, step_est, margin_floor, error_tol)
        finite_next = _all_finite(z_next)
        ok = flags.ok & finite_next  # may we go on from z?
        # reverse mode stores these two flags (the step's checkpoint policy, below), so that
        # its recomputation of the step needs neither the diagnostics nor the error estimate
        ok, finite_next = checkpoint_name(ok, _SAVED_FLAGS[0]), checkpoint_name(finite_next, _SAVED_FLAGS[1])
        diag = _running_update(diag, t, alive, ok, flags, finite_next, margin, est)
        # one selection per leaf, on one flag: nested selections on ok and finite_next (the same
        # values and gradients) let XLA:CPU emit a program a quarter larger for a sampled-data
        # loop, whose held leaves are then selected twice (docs/benchmarks.md)
        z_keep = jax.tree_util.tree_map(lambda a, b: jnp.where(ok & finite_next, a, b), z_next, z_in)
        zt_next = _to_scalars(z_keep)
        sign_next = jnp.where(flags.sign != 0, flags.sign, sign_prev)
        k4_next = _continuous(k4) if carry_k4 else ()
        carry = (zt_next, ok, diag, sign_next, k4_next, None if est_ok is None else ~jumped)
        return carry, (z if save_fn is None else save_fn(t, z, aux), aux.control, margin, flags.ok)

    # One step as operations on scalars: under vmap, elementwise on batch vectors, with no
    # array assembled or taken apart inside the loop, forward or transposed.
    step_on_scalars = scalarized(step_on_scalars)
    # Reverse mode: rematerialise each step instead of storing its intermediates (the
    # jet of the linearizing law has hundreds); the backward pass then stays in cache. It
    # stores the step's two flags that select the next state: the recomputation is then the
    # RK4 stages alone, a faster gradient.
    policy = jax.checkpoint_policies.save_only_these_names(*_SAVED_FLAGS)
    parts = (params_parts, q_parts)
    # A sampled-data period too: storing its residuals (the law's jet at the sample, every plant
    # stage) made the tuner's reverse-mode gradient a third slower than recomputing the period
    # (docs/benchmarks.md).
    step = jax.checkpoint(lambda carry, ix: step_on_scalars(carry, ix, parts), prevent_cse=False, policy=policy)

    outside = _outside_samples(params, t0, t0 + n_steps * dt)
    carry, rec0 = _initial_carry(field, z0, t0, dt, save_fn, carry_k4, post_step is not None and estimate, outside)
    carry, recs = _scan_steps(step, carry, rec0, n_steps, save_every, 1 if sample is None else sample_every, table)
    return _finish(loop, field, carry, recs, z0, params, t0, n_steps, save_every, margin_floor, error_tol, save_fn)


def _hoisting(closed, out_tree, n_state_leaves: int, params, t0, dt, n_steps: int):
    """``(field_q, parts, rebuild, table)`` of a loop whose field's state-independent part is
    computed before it (:mod:`wmrjax._hoist`): the rest of the field ``field_q(row, z, q)``, its
    constants and the batched parameter leaves as scalars with their ``rebuild``, and the table
    of the timed values at every stage time. The parameters an enclosing vmap batches stay in
    the loop with what depends on them. None where the field stays whole in the loop: times
    batched by an enclosing vmap, or a table larger than TABLE_MAX_BYTES."""
    if _hoist.batched(t0) or _hoist.batched(dt):
        return None
    leaves = jax.tree_util.tree_leaves(params)
    varying = [_hoist.batched(x) for x in leaves]
    split = _hoist.split_field(closed, out_tree, n_state_leaves, varying)
    size = sum(int(np.prod(a.shape)) * a.dtype.itemsize for a in split.table.out_avals)
    if size * _hoist.STAGE_TIMES * n_steps > _hoist.TABLE_MAX_BYTES:
        return None
    consts, inputs = _hoist.constants(split, [x for x, v in zip(leaves, varying) if not v])
    table = _hoist.tabulate(split, inputs, _hoist.stage_times(t0, dt, n_steps))
    parts, rebuild = scalar_parts((consts, tuple(x for x, v in zip(leaves, varying) if v)))
    return functools.partial(_hoisted_field, split), parts, rebuild, table


def _hoisted_field(split, row, z, q):
    consts, varying = q
    return _hoist.field_at(split, consts, row, z, varying)


class _Loop(NamedTuple):
    """What one unit of the time loop needs (static pieces and the step; see :func:`_simulate`)."""

    system: object
    field_s: object  # the vector field on scalars, parameters as an argument
    dt: object
    estimate: bool  # compute the error estimate
    stage_loop: bool  # the RK stages in a loop over one copy of the field
    post_step: object  # a hybrid system's discrete transition, or None
    sample: object  # a sampled-data system's sampler, or None
    sample_every: object
    rebuild_params: object
    # where the field's state-independent part is tabulated (``hoisted``), the RK stages run the
    # rest, ``field_q(row, z, q)``, ``q = rebuild_q(parts[1])``, on the table's rows; else
    # ``field_s(t, z, p)`` at the stage times
    field_q: object = None
    rebuild_q: object = None
    hoisted: bool = False


def _stage_rows(x):
    """The table's rows of one step (one per distinct stage time, :data:`_hoist.STAGE_TIMES`) as
    the four RK stages read them: a tuple of four rows."""
    return tuple(x[s] for s in _hoist.STAGE_ROWS)


def _advance(loop: _Loop, t, z, i, p, parts, k4_prev, est_ok, x=()):
    """One unit of the time loop from ``z`` at ``t``: ``(z_next, aux at (t, z), error estimate,
    last stage k4, jumped)``. A unit is one RK4 step (then the system's ``post_step``), or a
    sampled-data system's whole period: its ``sample_every`` steps under the held sample.
    ``parts``: the parameters' and the tabulated field's constants as scalars; ``x``: the step's
    rows of the table (:mod:`wmrjax._hoist`)."""
    dt = loop.dt
    if loop.sample is not None:
        return _period_advance(
            loop.field_s, t, z, dt, loop.sample_every, loop.estimate, parts[0], loop.rebuild_params, loop.system.held(z)
        )
    field, rebuild, q_parts = (
        (loop.field_q, loop.rebuild_q, parts[1]) if loop.hoisted else (loop.field_s, loop.rebuild_params, parts[0])
    )
    if loop.stage_loop:
        z_next, aux, k1, k4 = _rk4_stage_loop(field, t, z, dt, q_parts, rebuild, x if loop.hoisted else None)
    else:
        q = rebuild(q_parts)
        z_next, aux, k1, k4 = _rk4.rk4_stages(
            lambda a, zz: field(a, zz, q), t, z, dt, _stage_rows(x) if loop.hoisted else None
        )
    jumped = jnp.array(False)
    if loop.post_step is not None:  # hybrid systems: discrete transition at the end of the step
        z_post = loop.post_step(t + dt, z_next, p)
        jumped = ~_all_equal(z_post, z_next) if loop.estimate else jumped
        z_next = z_post
    est = jnp.zeros((), dt.dtype)
    if loop.estimate:
        est = jax.lax.stop_gradient(_error_estimate(dt, k4_prev, _continuous(k1), _continuous(z)))
        est = jnp.where(i == 0, 0.0, est)  # no previous step to compare with
        if est_ok is not None:  # no estimate across a discrete jump
            est = jnp.where(est_ok, est, 0.0)
    return z_next, aux, est, k4, jumped


class _Flags(NamedTuple):
    """One sample's classification (see :func:`_classify`)."""

    finite: jnp.ndarray  # its control, margin and error estimate are finite
    regular: jnp.ndarray  # its margin is above the floor and det K kept its sign
    ok: jnp.ndarray  # alive, finite, regular and accurate: a valid sample
    sign: jnp.ndarray  # the sign of its regularity function (0: none)


def _classify(alive, control, margin, regularity, sign_prev, est, margin_floor, error_tol) -> _Flags:
    """The failure rule, for one sample: the state at time t, with the control, margin and signed
    regularity (det K) of the vector field there, and the error estimate of the step that ended
    there. The time loop applies it at every step, :func:`_finish` at the final state.

    * finite: the control, the margin and the error estimate are finite. A non-finite estimate
      (stages whose difference overflows) leaves the step's accuracy unknown: the run is no
      longer trustworthy, and fails as non-finite (not as inaccurate).
    * regular: the margin is above ``margin_floor`` and the sign of the regularity function
      did not change against ``sign_prev``, the last sign seen (0: none yet): a sign change is
      a crossing of the singular set between two samples.
    * ok: ``alive & finite & regular`` and the estimate at most ``error_tol``.

    ``est`` None: no error estimate (the loop compiled without it, or a sampled-data loop's
    final state, whose period estimated its own steps); the sample is then accurate. The time
    loop also needs the next state finite to go on (see :func:`_running_update`).
    """
    sign = _sign(regularity, margin)
    finite = _all_finite((control, margin))
    if est is not None:
        finite = finite & jnp.isfinite(est)
    regular = (margin > margin_floor) & ~(sign_prev * sign < 0)
    ok = alive & finite & regular
    if est is not None:
        ok = ok & ~(est > error_tol)
    return _Flags(finite, regular, ok, sign)


def _running_update(diag, t, alive, ok, flags: _Flags, finite_next, margin, est):
    """The diagnostics after one sample at time ``t`` classified as ``flags`` (the run goes on
    from it if ``ok``; ``finite_next``: the next state is finite): the failure flags (non-finite,
    singular, failed and when), the smallest margin of a valid sample and when, the largest
    error estimate of the live run."""
    newly_failed = alive & ~ok
    better = flags.ok & (margin < diag.min_margin)
    return _Running(
        nonfinite=diag.nonfinite | (alive & ~(flags.finite & finite_next)),
        singular=diag.singular | (alive & flags.finite & ~flags.regular),
        failed=diag.failed | newly_failed,
        t_failure=jnp.where(newly_failed, t, diag.t_failure),
        min_margin=jnp.where(better, margin, diag.min_margin),
        t_min_margin=jnp.where(better, t, diag.t_min_margin),
        error_estimate=jnp.where(alive & flags.finite, jnp.maximum(diag.error_estimate, est), diag.error_estimate),
    )


def _outside_samples(params, t0, t_final):
    """True when [t0, t_final] leaves the samples of a sampled reference in ``params`` (a path
    defined by data, :meth:`wmrjax.references.Reference.domain`, not extrapolated). A horizon known
    when ``simulate`` is called is refused before compiling (the controllers' ``check_run``); one
    traced under jit or vmap is known only here, and fails the run at t0 (False for paths defined
    at every time)."""
    is_ref = lambda x: isinstance(x, Reference)
    outside = jnp.zeros((), bool)
    for ref in (x for x in jax.tree_util.tree_leaves(params, is_leaf=is_ref) if is_ref(x)):
        dom = ref.domain()
        if dom is None:
            continue
        lo, hi = jnp.max(dom[0]), jnp.min(dom[1])
        tol = DOMAIN_RTOL * (1.0 + jnp.maximum(jnp.abs(lo), jnp.abs(hi)))
        outside = outside | (t0 < lo - tol) | (t_final > hi + tol)
    return outside


def _initial_carry(field, z0, t0, dt, save_fn, carry_k4: bool, carry_jumps: bool, outside=False):
    """``(carry, rec0)``: the loop's first carry (scalars of z0, alive, diagnostics, the sign of
    det K, the previous step's last stage when ``carry_k4``, a jump flag when ``carry_jumps``)
    and a record shaped like a step's (zeros), for steps that are not saved."""
    # initial flags derived from z0 so they carry its sharding/varying type (shard_map)
    first = _first_float(z0)
    bad0 = ~jnp.isfinite(first)
    # a traced dt (under jit or vmap) cannot be refused before compiling: one that is not a
    # finite number > 0 fails the run at t0 instead of integrating backwards; so does a traced
    # horizon that leaves a sampled reference's samples (``outside``)
    failed0 = bad0 | ~(jnp.isfinite(dt) & (dt > 0)) | outside
    inf = jnp.where(bad0, jnp.inf, jnp.inf * jnp.ones_like(first))
    zero = 0.0 * jnp.where(bad0, 0.0, first)
    diag0 = _Running(bad0, bad0 & False, failed0, jnp.where(failed0, t0, inf), inf, t0 + zero, zero)
    # shapes only: evaluating the field at t0 would put one more copy of it in the program
    control0 = jax.eval_shape(field, t0, z0)[1].control
    # k4_prev starts at zero; the first step's estimate is set to zero (step index 0)
    carry = (
        _to_scalars(z0),
        ~failed0,
        diag0,
        zero,
        jax.tree_util.tree_map(lambda x: 0.0 * x, _continuous(z0)) if carry_k4 else (),
        bad0 & False if carry_jumps else None,
    )

    saved0 = z0
    if save_fn is not None:  # zeros shaped like what save_fn returns (no evaluation at t0)
        shapes = jax.eval_shape(lambda: save_fn(t0, z0, field(t0, z0)[1]))
        saved0 = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype) + zero.astype(a.dtype), shapes)
    rec0 = (saved0, jnp.zeros(control0.shape, control0.dtype) + zero.astype(control0.dtype), inf, ~failed0)
    return carry, rec0


def _scan_steps(step, carry, rec0, n_steps, save_every, unit, table=()):
    """``(carry, records)``: ``step(carry, (i, x))`` over the horizon by units of ``unit`` steps (a
    sampled-data system runs by whole periods; ``i`` the unit's first step), keeping the record of
    the first step of every ``save_every`` (one copy of the step body in the compiled program,
    whatever save_every is). ``table``: a pytree of arrays with a leading axis of ``n_steps``
    (one step per unit: continuous loops only), whose rows are fed to the steps as ``x``."""
    n_saves = n_steps // save_every
    save_units, n_units = save_every // unit, n_steps // unit
    head = n_saves * save_units

    def inner(c, ijx):
        # one step (or period); keep the record of the first step of each saving chunk (one copy
        # of the step body in the compiled program, whatever save_every is)
        i, j, x = ijx
        state, rec = c
        state, new_rec = step(state, (i, x))
        rec = jax.tree_util.tree_map(lambda a, b: jnp.where(j == 0, a, b), new_rec, rec)
        return (state, rec), None

    idx = unit * jnp.arange(head).reshape(n_saves, save_units)  # first step of each unit
    within = jnp.broadcast_to(jnp.arange(save_units), idx.shape)
    rows = jax.tree_util.tree_map(lambda a: a[:head].reshape(n_saves, save_units, *a.shape[1:]), table)

    def outer(c, ids):
        if save_units == 1:  # one step (or period) per saved sample: no inner loop
            return step(c, (ids[0][0], jax.tree_util.tree_map(lambda a: a[0], ids[2])))
        (state, rec), _ = jax.lax.scan(inner, (c, rec0), ids)
        return state, rec

    if n_steps >= TWO_LEVEL_CHECKPOINT_STEPS and n_saves > 1 and save_every > 1:
        # long horizons: reverse mode keeps one carry per saving chunk and recomputes a chunk's
        # steps when it reaches it (one more forward pass; memory / save_every)
        outer = jax.checkpoint(outer, prevent_cse=False)
    carry, recs = jax.lax.scan(outer, carry, (idx, within, rows))
    rest = unit * jnp.arange(head, n_units)
    if rest.shape[0]:  # steps beyond the last saving chunk run without saving
        tail = jax.tree_util.tree_map(lambda a: a[head:], table)
        (carry, _), _ = jax.lax.scan(inner, (carry, rec0), (rest, jnp.ones_like(rest), tail))
    return carry, recs


def _finish(loop: _Loop, field, carry, recs, z0, params, t0, n_steps, save_every, margin_floor, error_tol, save_fn):
    """The run's end: the failure rule applied at the final state too (its margin, sign, finite
    values and -- the continuous loops -- the last step's error estimate), the
    diagnostics completed (``inaccurate``, the system's ``final_report``) and the
    :class:`Trajectory` assembled from the saved records."""
    system, dt = loop.system, loop.dt
    estimate_last = loop.estimate and loop.sample is None
    dtype = dt.dtype
    zt, alive, diag, sign_prev, k4_prev, est_ok = carry
    z_final = _from_scalars(zt, z0)
    t_final = t0 + n_steps * dt
    k1_f, aux_f = field(t_final, z_final)
    m_f = jnp.asarray(aux_f.margin, dtype)
    est_f = None  # (a sampled period's steps estimated their own error)
    if estimate_last:
        est_f = jax.lax.stop_gradient(_error_estimate(dt, k4_prev, _continuous(k1_f), _continuous(z_final)))
        if est_ok is not None:
            est_f = jnp.where(est_ok, est_f, 0.0)
    flags = _classify(
        alive, aux_f.control, m_f, getattr(aux_f, "regularity", None), sign_prev, est_f, margin_floor, error_tol
    )
    final_ok = flags.ok
    diag = _running_update(
        diag, t_final, alive, final_ok, flags, jnp.array(True), m_f, jnp.zeros_like(m_f) if est_f is None else est_f
    )
    # a step was too inaccurate exactly when the largest estimate of the live run exceeds the
    # tolerance (the estimate stops growing at the failure): derived here, not carried
    diag = Diagnostics(*diag[:6], inaccurate=diag.error_estimate > error_tol, error_estimate=diag.error_estimate)
    final_report = system.final_report
    if final_report is not None:  # e.g. the internal dynamics of a static law
        diag = diag._replace(internal=final_report(t_final, z_final, params))
    states, controls, margins, valids = recs
    n_saves = n_steps // save_every
    # the loop's own times, t0 + i dt (i the step index), to the last bit: a sampled reference or a
    # schedule evaluated at a saved time then sees the time the step saw
    t_saved = t0 + (jnp.arange(n_saves + 1) * save_every).astype(dtype) * dt
    t_saved = t_saved.at[-1].set(t_final)
    traj = Trajectory(
        t=t_saved,
        state=jax.tree_util.tree_map(
            lambda a, b: jnp.concatenate([a, b[None]]),
            states,
            z_final if save_fn is None else save_fn(t_final, z_final, aux_f),
        ),
        control=jnp.concatenate([controls, jnp.asarray(aux_f.control)[None]]),
        margin=jnp.concatenate([margins, jnp.asarray(aux_f.margin, dtype)[None]]),
        valid=jnp.concatenate([valids, final_ok[None]]),
        final_state=z_final,
        diagnostics=diag,
    )
    return traj


def batch_mesh(axis_name: str = "batch", devices=None):
    """A 1-D ``jax.sharding.Mesh`` over all (or the given) devices, for the batch axis."""
    devs = np.asarray(jax.devices() if devices is None else devices)
    return jax.sharding.Mesh(devs, (axis_name,))


def shard_batch(tree, mesh=None):
    """Place a pytree of batched arrays (leading axis = batch) across ``mesh``'s devices.

    ``jax.jit(jax.vmap(...))`` applied to the result runs each device's share of the
    batch in parallel (GSPMD); results are identical to the unsharded run. On a CPU host,
    several devices exist only if ``XLA_FLAGS=--xla_force_host_platform_device_count=N``
    was set before JAX started (the experiments' ``--devices`` option does that).
    The batch size must be divisible by the number of devices.
    """
    mesh = batch_mesh() if mesh is None else mesh
    n = mesh.devices.size
    spec = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(mesh.axis_names[0]))
    for leaf in jax.tree_util.tree_leaves(tree):
        if np.ndim(leaf) == 0 or np.shape(leaf)[0] % n:
            raise ValueError(
                f"shard_batch needs a leading batch axis divisible by {n} devices, got shape {np.shape(leaf)}"
            )
    return jax.device_put(tree, spec)


CPU_CHUNK = 512  # batch_map's chunk on CPU devices: a chunk's working set stays in a core's cache


def default_chunk(mesh, cpu_chunk: int = CPU_CHUNK) -> int | None:
    """``cpu_chunk`` when ``mesh``'s devices are CPUs, None (one chunk: the device's whole share
    of the batch) on accelerators, where a chunk loop only serialises what the device runs in
    parallel (measured on a GPU: the docs' benchmarks page)."""
    return cpu_chunk if all(d.platform == "cpu" for d in np.asarray(mesh.devices).flat) else None


def fixed_blocks(fn, arrays, block: int) -> tuple:
    """``fn`` over blocks of ``block`` rows of ``arrays`` (the last padded with copies of the first
    row), so that a compiled ``fn`` sees one shape whatever the number of rows.

    Args:
      fn: ``fn(*blocks) -> tuple`` of arrays with a leading row axis (a jitted program).
      arrays: sequence of NumPy arrays sharing their leading length N >= 1.
      block: rows per call.

    Returns:
      ``fn``'s outputs for the N rows, as NumPy arrays (the padding cut off).
    """
    n = len(arrays[0])
    pad = -n % block
    padded = [np.concatenate([a, np.repeat(a[:1], pad, axis=0)]) for a in arrays]
    out = [fn(*(jnp.asarray(a[i : i + block]) for a in padded)) for i in range(0, n + pad, block)]
    return tuple(np.concatenate([np.asarray(o[k]) for o in out])[:n] for k in range(len(out[0])))


def batch_map(fn, *args, chunk: int | None = None, mesh=None):
    """Map a per-example function over the leading axis of ``args``, fast on CPUs and GPUs.

    Equivalent to ``jax.vmap(fn)(*args)`` (same results, tested), but the batch is split
    across ``mesh``'s devices with ``jax.shard_map`` (one device per core: run with
    ``--xla_force_host_platform_device_count``) and, on each device, processed in chunks
    of ``chunk`` examples with ``lax.map`` so that a chunk's working set stays in cache
    for the whole time loop. The batch is padded (with copies of its first example) to a
    multiple of ``devices * chunk``; the padding is dropped from the result.

    Call it inside ``jax.jit``. Differentiable like ``vmap``.

    Args:
      fn: function of unbatched arguments returning a pytree.
      *args: pytrees whose leaves share the leading batch size B.
      chunk: examples per chunk (static); None: :data:`CPU_CHUNK` on CPU devices, one chunk
        per device on accelerators (:func:`default_chunk`). Give a chunk on a GPU to bound
        the memory of a very large batch.
      mesh: a 1-D mesh (default: :func:`batch_mesh` over all devices).

    Returns:
      ``fn``'s output pytree with a leading axis of size B.
    """
    if chunk is not None:
        check_int("chunk", chunk, 1)  # a text, a float or a bool was read as int(chunk) before
    mesh = batch_mesh() if mesh is None else mesh
    n_dev = mesh.devices.size
    leaves = jax.tree_util.tree_leaves(args)
    if not leaves:
        raise ValueError("batch_map needs at least one batched argument")
    b = leaves[0].shape[0]
    if any(leaf.shape[:1] != (b,) for leaf in leaves):
        raise ValueError(f"batch_map: every leaf needs the same leading batch size, got {[l.shape for l in leaves]}")
    chunk = default_chunk(mesh) if chunk is None else chunk
    chunk = -(-b // n_dev) if chunk is None else max(1, min(int(chunk), -(-b // n_dev)))
    per = n_dev * chunk
    padded = -(-b // per) * per

    def pad(x):
        if padded == b:
            return x
        return jnp.concatenate([x, jnp.broadcast_to(x[:1], (padded - b,) + x.shape[1:])])

    args = jax.tree_util.tree_map(pad, args)
    axis = mesh.axis_names[0]
    spec = jax.sharding.PartitionSpec(axis)

    def local(*a):
        blocks = jax.tree_util.tree_map(lambda x: x.reshape((-1, chunk) + x.shape[1:]), a)
        out = jax.lax.map(lambda blk: jax.vmap(fn)(*blk), blocks)
        return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), out)

    # check_vma=False: the Taylor-mode jets (jax.experimental.jet) have no rule for the
    # varying-axis casts shard_map would insert; every output here varies along the batch axis
    out = jax.shard_map(local, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)(*args)
    return jax.tree_util.tree_map(lambda x: x[:b], out)


def simulate(
    system,
    z0,
    params,
    *,
    dt,
    n_steps: int,
    t0=0.0,
    save_every: int = 1,
    margin_floor=1e-9,
    error_tol=1e-3,
    save_fn=None,
) -> Trajectory:
    """Simulate one closed loop with fixed-step RK4.

    ``WMRJAX_JAXPR_REWRITES=0`` in the environment (read at each call) runs the plain JAX
    program, without the step's rewriting (module docstring).

    Args:
      system: a closed-loop object (static, hashable) with
        ``vector_field(t, z, params) -> (dz/dt, aux)``, ``aux`` an :class:`wmrjax.Aux`
        (``control``, ``margin``, optional signed ``regularity``), e.g.
        :class:`wmrjax.controllers.DynamicLinearization`; optionally
        ``post_step(t, z, params) -> z``, a discrete transition applied at the end of every
        step (hybrid systems, e.g. :class:`wmrjax.controllers.hybrid.Hybrid`), and
        ``check_run(params, *, t0, dt, n_steps)``, which validates concrete parameters for
        this run before compilation (the controllers: parameters of this controller, a step
        inside RK4's stability region for the error dynamics, the reference over the horizon).
      z0: initial state, unbatched (``vmap`` to batch): an array of shape (n,) or a pytree of
        arrays with n components in all (e.g. :class:`wmrjax.HybridState`). Real; a float32
        state is promoted to the default float type.
      params: pytree of arrays the closed loop depends on (gains, reference, geometry).
      dt: step [s], > 0 (refused eagerly; a traced dt that is not a finite number > 0 fails every
        run at t0: ``diagnostics.failed``, no sample valid).
      n_steps: number of steps (static).
      t0: initial time [s], finite.
      save_every: keep every k-th state (static); the final state is always kept.
        With ``save_every = n_steps`` only the initial and final states are stored.
      margin_floor: a run fails (``singular``) when its margin is ``<= margin_floor`` (>= 0),
        or when the sign of its regularity function changes between two steps.
      error_tol: a run fails (``inaccurate``) when a step's local error estimate (relative
        to ``1 + max_i |z_i|``; :attr:`Diagnostics.error_estimate`) exceeds it (> 0). ``None``
        compiles the loop without the estimate (``error_estimate`` is then 0): a little
        faster, for sweeps whose step is known to be accurate.
      save_fn: what to save at each saved time instead of the state (static, hashable):
        ``save_fn(t, z, aux) -> pytree`` (e.g. a few loss terms); ``Trajectory.state`` then holds
        its outputs (a leading axis of T); ``final_state`` stays the state. None: the state.

    Returns:
      :class:`Trajectory`.

    Raises:
      ValueError: on a non-positive ``dt``, ``n_steps`` or ``save_every``, a non-finite
        ``t0``, a negative or NaN ``margin_floor`` or ``error_tol``, a non-finite, complex or
        wrongly-shaped ``z0``, a run larger than the memory available (:mod:`wmrjax.resources`), or
        what the system's ``check_run`` refuses, or a ``WMRJAX_JAXPR_REWRITES`` other than 0 or 1
        (all checked before compilation).
    """
    if not isinstance(system, ClosedLoop):
        raise ValueError(
            "system must be a wmrjax.ClosedLoop (subclass it: define vector_field and the hooks it needs), "
            f"got {type(system).__name__}"
        )
    n_steps, save_every = _check_steps(system, n_steps, save_every)
    dtv, t0v = _check_scalars(dt, t0, margin_floor, error_tol)
    z0, size = _prepared_state(system, z0)
    # the reference check runs (and takes memory) only with concrete times
    horizon = n_steps * float(dtv) if dtv is not None and t0v is not None else 0.0
    _check_memory(system, n_steps, save_every, size, jnp.result_type(float), horizon)
    _warn_float32(n_steps)
    system.check_run(params, t0=t0, dt=dt, n_steps=n_steps)
    if save_fn is not None and not callable(save_fn):
        raise ValueError(f"save_fn must be a function (t, z, aux) -> pytree, got {type(save_fn).__name__}")
    rewrites = _simplify.rewrites_enabled()
    # inside an outer trace (jit, vmap, grad) the outer program is the one compiled: a jit of our
    # own would only add a call whose traced body the outer transformations process once more
    leaves = jax.tree_util.tree_leaves((z0, params, dt, t0, margin_floor, error_tol))
    run = _simulate if all(is_concrete(x) for x in leaves) else _simulate.__wrapped__
    return run(system, z0, params, dt, t0, n_steps, save_every, margin_floor, error_tol, save_fn, rewrites)


FLOAT32_WARN_STEPS = 1000
"""A float32 run of at least this many steps is warned about (:func:`_warn_float32`)."""


def _warn_float32(n_steps: int) -> None:
    """A RuntimeWarning for a long run in float32 (JAX's default, x64 off): its rounding
    accumulates step by step. Measured on the (2,0) circle loop, poles -1, dt = 0.01 s
    (2026-11-28): the final state is off float64's by 2e-6 m after 1 000 steps and 5e-5 m after
    10 000, where float64's tracking error is 1e-10 m."""
    if n_steps >= FLOAT32_WARN_STEPS and jnp.result_type(float) == jnp.float32:
        warnings.warn(
            f"this run is float32 (jax_enable_x64 is off) over {n_steps} steps: rounding accumulates "
            "(on the circle loop 5e-5 m after 10 000 steps, where float64 tracks to 1e-10 m); for "
            "certificates and tight tracking numbers call jax.config.update('jax_enable_x64', True) "
            "before any computation",
            RuntimeWarning,
            stacklevel=3,
        )


def _check_steps(system, n_steps, save_every):
    """``(n_steps, save_every)`` as ints; ValueError for counts below 1, ``save_every > n_steps``,
    a system both hybrid and sampled, or a sampled-data run that is not whole controller periods."""
    n_steps = check_int("n_steps", n_steps, 1)
    save_every = check_int("save_every", save_every, 1)
    if save_every > n_steps:
        raise ValueError(f"save_every must be <= n_steps ({n_steps}), got {save_every}")
    every = system.sample_every
    if every is not None and system.post_step is not None:
        raise ValueError(
            f"{type(system).__name__} has both post_step and sample_every: a system is hybrid or sampled, not both"
        )
    if every is not None and (n_steps % every or save_every % every):
        raise ValueError(
            f"a sampled-data loop runs whole controller periods of {every} steps: n_steps ({n_steps}) "
            f"and save_every ({save_every}) must be multiples of {every}"
        )
    return n_steps, save_every


def _check_scalars(dt, t0, margin_floor, error_tol):
    """ValueError for a concrete ``dt``, ``t0``, ``margin_floor`` or ``error_tol`` out of range;
    returns the concrete ``(dt, t0)`` (None where traced)."""
    for name, v, what in (
        ("dt", dt, "a finite real scalar > 0 [s]"),
        ("t0", t0, "a finite real scalar [s]"),
        ("margin_floor", margin_floor, "a finite real scalar >= 0"),
        ("error_tol", error_tol, "a real scalar > 0 (or None: no error estimate)"),
    ):
        if v is not None:
            check_number(name, v, what)
    dtv = concrete(dt)
    if dtv is not None and not (np.ndim(dtv) == 0 and np.isrealobj(dtv) and np.isfinite(dtv) and dtv > 0):
        raise ValueError(f"dt must be a finite real scalar > 0 [s], got {dt!r}")
    t0v = concrete(t0)
    if t0v is not None and not (np.ndim(t0v) == 0 and np.isrealobj(t0v) and np.isfinite(t0v)):
        raise ValueError(f"t0 must be a finite real scalar [s], got {t0!r}")
    floor = concrete(margin_floor)
    if floor is not None and not (np.ndim(floor) == 0 and np.isrealobj(floor) and np.isfinite(floor) and floor >= 0):
        raise ValueError(f"margin_floor must be a finite real scalar >= 0, got {margin_floor!r}")
    tol = concrete(error_tol) if error_tol is not None else 1.0
    if tol is not None and not (np.ndim(tol) == 0 and np.isrealobj(tol) and tol > 0):
        raise ValueError(f"error_tol must be a real scalar > 0 (or None: no error estimate), got {error_tol!r}")
    return dtv, t0v


def _prepared_state(system, z0):
    """``(z0, n)``: the initial state as arrays of the default float type (numbers keep their
    dtype, booleans and all-integer vectors become floats) and its number of components;
    ValueError for an empty, wrongly-shaped, complex or non-finite state."""
    leaves = jax.tree_util.tree_leaves(z0)
    if not leaves:
        raise ValueError("z0 must be a state array (or a pytree of arrays), got an empty pytree")
    text = [x for x in leaves if isinstance(x, (str, bytes))]
    if text:
        raise ValueError(f"z0 must be a state array of numbers, got text {text[0]!r:.60}")
    if isinstance(z0, (list, tuple)) and not hasattr(z0, "_fields"):
        z0 = jnp.asarray(z0)  # a plain sequence of numbers is a state vector
    floating = jnp.result_type(float)
    z0 = jax.tree_util.tree_map(  # numbers keep their dtype, booleans become floats
        lambda x: jnp.asarray(x) if jnp.issubdtype(jnp.result_type(x), jnp.number) else jnp.asarray(x, floating), z0
    )
    if not any(_rk4.is_continuous(x) for x in jax.tree_util.tree_leaves(z0)):
        z0 = jax.tree_util.tree_map(lambda x: x.astype(floating), z0)  # an all-integer vector is a state
    n = system.n_state
    size = sum(int(np.size(x)) for x in jax.tree_util.tree_leaves(z0))
    is_array = isinstance(z0, jax.Array)
    if (is_array and z0.ndim != 1) or (n is not None and size != n):
        names = system.state_names
        raise ValueError(
            f"z0 must be an unbatched state of shape ({n},)"
            + (f" = ({', '.join(names)})" if names else "")
            + f"; got shape {np.shape(z0) if is_array else [np.shape(x) for x in jax.tree_util.tree_leaves(z0)]}"
            " (use jax.vmap to batch)"
        )
    for leaf in jax.tree_util.tree_leaves(z0):
        if jnp.issubdtype(jnp.result_type(leaf), jnp.complexfloating):
            raise ValueError(f"z0 must be real, got a complex state of dtype {jnp.result_type(leaf)}")
        check_finite("z0", leaf)
    z0 = jax.tree_util.tree_map(  # float32 with float64 enabled: promote, never mix
        lambda x: x.astype(floating) if _rk4.is_continuous(x) and jnp.result_type(x) != floating else x, z0
    )
    return z0, size


def _check_memory(system, n_steps: int, save_every: int, n_state: int, dtype, horizon: float) -> None:
    """ValueError when one run (its saved samples and its reference check) cannot fit in the
    memory available now (:mod:`wmrjax.resources`)."""
    est = resources.run_estimate(
        system,
        n_steps=n_steps,
        save_every=save_every,
        n_state=n_state,
        itemsize=np.dtype(dtype).itemsize,
        horizon=horizon,
    )
    resources.check_fits(
        est,
        f"n_steps = {n_steps} with save_every = {save_every} (a horizon of {horizon:.6g} s)",
        "raise dt or save_every, or shorten the horizon",
    )
