r"""The one placement of an initial state near a reference: :func:`place` (issue 55: with the
controllers, not in the problem file's module).

A run starts from an error to the reference at its first time: in the output jet (dynamic laws:
position and velocity errors of the tracked point, mapped back by :math:`\Psi^{-1}`) or in the
physical posture (and steering angles). Every job (the sweep, the tuner, the certification's
rollouts, the export's check) places its initial states here.
"""

from __future__ import annotations

import enum

import jax.numpy as jnp

from wmrjax.controllers.dynamic import DynamicLinearization
from wmrjax.controllers.law import Level, Task
from wmrjax.controllers.static import controller as static_controller


class Space(enum.StrEnum):
    """Where initial errors live: the output jet (x, y and their rates) or the physical posture."""

    OUTPUT = "output"
    PHYSICAL = "physical"


def initial_keys(ctrl, space) -> tuple:
    """The initial-error keys this controller takes in ``space`` (output: position and velocity
    errors of the output point; physical: posture and steering-angle errors)."""
    if Space(space) == Space.OUTPUT:
        return ("x", "y", "vx", "vy")
    beta = ("beta",) if ctrl.robot.delta_s == 1 else ("beta1", "beta2")[: ctrl.robot.delta_s]
    return ("x", "y", "theta") + beta


def place(ctrl, params, error, space, task, branch, t0=0.0, rest: bool = False, jet=None):
    r"""The initial state of a run whose error from the reference at ``t0`` is ``error`` (pure).

    Output space (dynamic laws): the output jet is the reference's plus ``(x, y)`` in its
    position row and ``(vx, vy)`` in its velocity row (r >= 2) -- or, with r * m entries, plus
    the whole error jet (rows of derivative order, as ``ctrl.error`` flattens it) -- mapped back
    by :math:`\Psi^{-1}` on ``branch``. Physical space: the posture (and steering angles) are
    the reference's plus ``(x, y, theta, beta...)``; a dynamic law's compensator is the
    reference's; a static law tracking a point puts its tracked point at the reference's
    position plus ``(x, y)``, and at torque level starts with the wheel velocities that give the
    reference's output velocity (``rest``: at rest).

    Args:
      ctrl: the controller.
      params: its parameters (reference, geometry, gains).
      error: (k,) errors in the keys of :func:`initial_keys` [m, m, m/s, m/s or m, m, rad, rad...],
        or (r * m,) output-jet errors.
      space: where ``error`` lives (:class:`Space` or its string).
      task: what a static law tracks (:class:`wmrjax.controllers.Task` or its string).
      branch: +1 or -1 (dynamic laws; the reference's branch, ``ctrl.reference_branch``).
      t0: initial time [s].
      rest: static laws at torque level: zero wheel velocities.
      jet: dynamic laws: the reference's output jet ((>= r, m)) to place against instead of
        the reference's at ``t0`` (the saturation-free radius places against a jet seen from
        turned axes, or an enclosure of it).

    Returns:
      The controller's state, shape (ctrl.n_state,).
    """
    t0 = jnp.asarray(t0, jnp.result_type(float))
    d = jnp.asarray(error, t0.dtype)
    if isinstance(ctrl, DynamicLinearization):
        r = ctrl.relative_degree
        zeta = (ctrl.reference_jet(t0, params) if jet is None else jet)[:r]
        if Space(space) == Space.OUTPUT:
            if d.shape[0] == r * ctrl.m:  # the whole error jet
                return ctrl.inverse_psi(zeta + d.reshape(r, ctrl.m), params, branch)
            zeta = zeta.at[0, 0].add(d[0]).at[0, 1].add(d[1])
            if r >= 2:
                zeta = zeta.at[1, 0].add(d[2]).at[1, 1].add(d[3])
            return ctrl.inverse_psi(zeta, params, branch)
        return ctrl.inverse_psi(zeta, params, branch).at[: ctrl.robot.n_state].add(d)
    return _place_static(ctrl, params, d, Task(task), t0, rest)


def _place_static(ctrl, params, d, task, t0, rest):
    ref, g = params.reference, params.geometry
    post = ref.posture(t0)
    steer = _steering(ctrl, params, t0)
    X = jnp.concatenate([jnp.zeros(2, t0.dtype), post[2:3], steer])
    X = X.at[2:].add(d[2:])
    offset = ctrl.law.outputs(X, g)[:2]  # the tracked point relative to (x, y)
    target = ref.position(t0) if task == Task.POINT else post[:2]
    X = X.at[:2].set(target + d[:2] - (offset if task == Task.POINT else 0.0))
    if ctrl.level != Level.TORQUE:
        return X
    if rest:
        return jnp.concatenate([X, jnp.zeros(ctrl.robot.n_input, X.dtype)])
    vl = static_controller(ctrl.robot.name, level=Level.VELOCITY, task=task)
    u = vl.law.solve_top(X, vl.reference_jet(t0, params)[1], g)  # output velocity = the reference's
    return ctrl.physical_state(X, u, params)


def _steering(ctrl, params, t0):
    """The initial steering angles: the steering reference's where the law has one, else 0."""
    n = ctrl.robot.delta_s
    b = (
        jnp.reshape(params.steering(t0), (-1,))
        if getattr(params, "steering", None) is not None
        else jnp.zeros((0,), t0.dtype)
    )
    # (1,2): beta1 free (0), beta2 the steering reference; (2,1): beta the steering reference
    return jnp.concatenate([jnp.zeros(n - b.shape[0], t0.dtype), b]) if b.shape[0] < n else b[:n]
