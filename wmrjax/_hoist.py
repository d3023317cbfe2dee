"""The part of a closed loop's vector field that does not depend on the state, computed once
before the time loop instead of at every RK4 stage.

A linearizing law evaluates the reference's jet (and a gain schedule's coefficients) at each
stage time. That work depends on the time and the parameters, never on the state, and the
stage times of a fixed-step run are known before it starts. :func:`split_field` cuts the
traced field (a closed jaxpr of ``(t, z, params)``) by data dependence (JAX's partial
evaluation) into three programs:

* ``consts``: what depends on the parameters alone (a gain, a product of geometry terms),
  evaluated once per run;
* ``table``: what depends on the time (and the parameters), evaluated for all stage times of
  the horizon at once, vectorised, before the loop (:func:`tabulate`);
* ``field``: the rest, which depends on the state, the only part left in the loop; it reads
  the values it needs from the two others (:func:`field_at`).

Every family of references then costs the loop the same: a built-in closed form, a sampled
path (a spline's piece search and Horner's rule), a user's function and a schedule differ
only in the one vectorised evaluation before the loop. The values are those of the whole
field: the same operations on the same numbers, moved.

What it costs: a table of ``3 n_steps`` rows of the time-dependent values per run (three
distinct stage times per RK4 step), and, when a gradient flows into the reference or a
schedule, their cotangents. The table is therefore built only from what the runs of a batch
share: a parameter leaf that an enclosing ``vmap`` batches (a reference, a geometry or gains
per run, :func:`batched`) keeps what depends on it in the loop, as before; and only where the
table is small (:data:`TABLE_MAX_BYTES`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax._src.interpreters import partial_eval as pe
from jax.extend import core as jex_core

# the largest table of one run that is built before the loop [bytes]; a longer horizon runs the
# field whole in the loop (the memory model of wmrjax.resources has no term for the table)
TABLE_MAX_BYTES = 2**24
# stage times per RK4 step: t, t + dt/2 (stages 2 and 3), t + dt
STAGE_TIMES = 3
# which of a step's STAGE_TIMES rows each of the four RK4 stages reads
STAGE_ROWS = (0, 1, 1, 2)


class Split(NamedTuple):
    """A vector field cut by what it depends on (see the module docstring).

    Attributes:
      consts: closed jaxpr ``(*shared_param_leaves) -> (*constant residuals, *table inputs)``.
      table: closed jaxpr ``(*table inputs, t) -> timed residuals``.
      field: closed jaxpr ``(*residuals, *state_leaves, *varying_param_leaves) -> output leaves``
        of the field (``varying``: the parameter leaves batched per run, :func:`split_field`).
      timed: for each residual of ``field``, True where it comes from the table.
      n_consts: how many of ``consts``' outputs are residuals (the rest feed the table).
      out_tree: the structure of the field's output ``(dz/dt, aux)``.
    """

    consts: Any
    table: Any
    field: Any
    timed: tuple
    n_consts: int
    out_tree: Any

    @property
    def n_timed(self) -> int:
        return sum(self.timed)


def split_field(closed, out_tree, n_state_leaves: int, varying) -> Split:
    """Cut ``closed`` (the field traced at ``(t, z, params)``, leaves flattened in that order:
    one time, ``n_state_leaves`` state leaves, then the parameters') into a :class:`Split`.

    ``varying``: for each parameter leaf, True where it differs from run to run of a batch (an
    enclosing vmap batches it, :func:`batched`). What depends on such a leaf stays in the loop
    with the state (a table of it would be batch x steps large); what depends on the time and
    the shared parameters alone is tabulated."""
    varying = [bool(v) for v in varying]
    unknown = [False] + [True] * n_state_leaves + varying
    # instantiate: every output of the field comes out of the part left in the loop
    known, field, _, _ = pe.partial_eval_jaxpr_nounits(closed, unknown, instantiate=True)
    n_shared = len(varying) - sum(varying)
    consts, table, timed, _ = pe.partial_eval_jaxpr_nounits(known, [True] + [False] * n_shared, instantiate=False)
    return Split(consts, table, field, tuple(timed), len(timed) - sum(timed), out_tree)


def state_part_size(closed, n_state_leaves: int) -> int:
    """Equations of ``closed`` (as in :func:`split_field`) that depend on the state: what a loop
    runs when every parameter is shared. A property of the law and its geometry, not of the
    reference's family nor of what a batch varies."""
    n_params = len(closed.in_avals) - 1 - n_state_leaves
    # the same cut as split_field's first with nothing varying (JAX caches it: one partial evaluation)
    unknown = [False] + [True] * n_state_leaves + [False] * n_params
    return len(pe.partial_eval_jaxpr_nounits(closed, unknown, instantiate=True)[1].jaxpr.eqns)


def depends_on(closed, inputs) -> tuple[bool, ...]:
    """Per output of ``closed`` (a closed jaxpr): whether it depends on the inputs flagged True in
    ``inputs`` (one flag per input leaf), by the same partial evaluation as :func:`split_field`:
    an output it reports False is computed from the other inputs alone.

    Args:
      closed: the traced program.
      inputs: one bool per input leaf of ``closed``.
    """
    return tuple(pe.partial_eval_jaxpr_nounits(closed, [bool(x) for x in inputs], instantiate=False)[2])


def batched(x) -> bool:
    """True when ``x`` is batched by an enclosing ``jax.vmap`` traced around this call (looked
    for through the differentiation tracers' primal values). A trace-time question: a ``vmap``
    of an already-traced program (``vmap(jit(f))``) is not seen, and its table is batched."""
    while isinstance(x, jax.core.Tracer):
        if hasattr(x, "batch_dim"):  # a vmap's tracer: batched when it has a batch axis
            if type(x.batch_dim) is int:
                return True
            x = x.val
        elif hasattr(x, "primal"):  # jvp or linearize: the primal value is what is batched
            x = x.primal
        else:  # a jit, checkpoint or shard_map trace: nothing more to see
            return False
    return False


def constants(split: Split, shared_leaves) -> tuple:
    """``(residuals, table inputs)``: the values of the shared parameter leaves alone (those not
    ``varying`` in :func:`split_field`), once per run."""
    out = jex_core.jaxpr_as_fun(split.consts)(*shared_leaves)
    return tuple(out[: split.n_consts]), tuple(out[split.n_consts :])


def stage_times(t0, dt, n_steps: int):
    """The distinct stage times of ``n_steps`` RK4 steps from ``t0``, shape (n_steps, 3): the
    loop's own arithmetic (``t = t0 + i dt``, then ``t + 0.5 dt`` and ``t + dt``), to the bit."""
    t = t0 + jnp.arange(n_steps).astype(jnp.result_type(dt)) * dt
    return jnp.stack([t, t + 0.5 * dt, t + dt], axis=1)


def tabulate(split: Split, inputs, times) -> tuple:
    """The timed residuals at every stage time (vectorised over the times, outside any loop):
    for each column of ``times`` (n, k), a tuple of arrays, one per residual, shaped ``(n,) +
    residual shape``. A step's row is then a tuple of scalars per stage time: the loop body takes
    no array apart to read it."""
    fn = jex_core.jaxpr_as_fun(split.table)
    one = lambda t: tuple(fn(*inputs, t))
    table = jax.vmap(jax.vmap(one))(times)
    return tuple(tuple(r[:, k] for r in table) for k in range(times.shape[1]))


def field_at(split: Split, consts, row, z, varying_leaves=()):
    """The field's ``(dz/dt, aux)`` at state ``z``, from the constant residuals ``consts``,
    ``row``, the timed residuals at the stage's time (one value per timed residual), and the
    varying parameter leaves (in their order among the parameters')."""
    consts, row = iter(consts), iter(row)
    res = [next(row) if timed else next(consts) for timed in split.timed]
    out = jex_core.jaxpr_as_fun(split.field)(*res, *jax.tree_util.tree_leaves(z), *varying_leaves)
    return jax.tree_util.tree_unflatten(split.out_tree, out)
