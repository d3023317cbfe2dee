r"""The control step a robot runs, exported: as a ``jax.export`` artifact and as C99 source.

A digital controller runs the paper's law once per period: it measures the robot's posture
and steering angles (and, at torque level, its wheel velocities), evaluates the law with the
tuned gains on the planned reference, and holds the command until the next period. A dynamic
law also carries its compensator: a digital integrator whose rate, computed at one sample, is
held until the next, which first advances the compensator by that rate times the time elapsed.
:func:`control_step` builds that step as one pure function, from the very code the simulator's
sampled-data loop runs (:meth:`wmrjax.SampledLoop.sample`), so what was tuned and certified in
simulation is what is deployed. Its signature::

    command, state_next, regularity = step(t, measured, state)

* ``t``: the sample's time [s] (the reference's clock);
* ``measured``: the measured X = (x, y, theta, beta...) [m, m, rad, rad...], followed at torque
  level by the measured wheel velocities u [m/s, rad/s];
* ``state``: the controller's own state, ``(c, rate, t_last)`` flattened (a dynamic law's
  compensator c -- at torque level with its new inputs --, its held rate, the time of the last
  sample); empty for a static law (size 0);
* ``command``: the plant input to hold until the next sample: u at velocity level, v = du/dt at
  torque level (before the plant's own scaling and saturation);
* ``regularity``: the law's signed regularity function (det K); a sign change between two
  samples or a value near 0 means the robot is at the singular set of its outputs. Along a
  sampled path it is exactly 0 at a time outside the path's samples
  (:func:`reference_span`, also in the export's ``summary.json`` and the C header): there the
  law has no plan to follow, and the robot loop stops on that flag.

:func:`export_artifact` serializes it (``jax.export``: StableHLO, runs with ``jax`` alone, no
``wmrjax``); :func:`generate_c` writes it as dependency-free C99 (``math.h`` only), from the
scalar program the simulator's loop runs (:func:`wmrjax.scalarized`): straight-line code on
doubles, a sampled reference's polynomial pieces as constant tables.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _cgen
from wmrjax._validate import concrete
from wmrjax.controllers.law import Level
from wmrjax.controllers.plant import PlantLoop
from wmrjax.controllers.sampled import SampledLoop, SampledParams, SampledState, sampled
from wmrjax.references import DOMAIN_RTOL
from wmrjax.simulate import scalarized, simulate

__all__ = [
    "ControlStep",
    "Run",
    "control_step",
    "drive",
    "export_artifact",
    "generate_c",
    "program",
    "reference_run",
    "reference_span",
]


@dataclasses.dataclass(frozen=True)
class ControlStep(_cgen.Signature):
    """One period of a digital controller (see the module's docstring for the signature): its
    C interface (:class:`wmrjax._cgen.Signature`: sizes and labels) and the function.

    Attributes:
      name: a C identifier prefixing the generated functions.
      n_measured: X's components, plus the wheel velocities at torque level.
      n_state: the controller's own state, ``2 n_c + 1`` for a dynamic law (0 for a static one).
      n_command: the plant's inputs.
      n_compensator: n_c, the compensator's components (with the new inputs at torque level).
      measured_names: labels of ``measured`` (for generated code and reports).
      command_names: labels of ``command``.
      compensator_names: labels of the compensator.
      robot: the robot type it controls, e.g. ``"(2,0)"``.
      level: ``"velocity"`` or ``"torque"``.
      fn: ``(t, measured, state) -> (command, state_next, regularity)``, pure and jittable;
        shapes ``()``, ``(n_measured,)``, ``(n_state,)`` -> ``(n_command,)``, ``(n_state,)``, ``()``.
      span: ``(t_first, t_last)`` [s] of a sampled path (:func:`reference_span`), None for a
        path defined at every time; outside it the step's regularity is 0.
    """

    fn: Callable = dataclasses.field(repr=False, kw_only=True)
    span: tuple | None = dataclasses.field(default=None, kw_only=True)

    def initial_state(self, t0, compensator=()):
        """The controller's state before its first sample at ``t0`` [s]: the compensator's initial
        value (a dynamic law's; e.g. the reference's speed for (2,0)), a zero rate, last sample at t0."""
        c = jnp.asarray(compensator, jnp.result_type(float)).reshape(-1)
        if c.shape[0] != self.n_compensator:
            raise ValueError(
                f"initial_state: compensator must have {self.n_compensator} values "
                f"({', '.join(self.compensator_names) or 'none: a static law'}), got {c.shape[0]}"
            )
        if self.n_state == 0:
            return jnp.zeros(0, c.dtype)
        return jnp.concatenate([c, jnp.zeros_like(c), jnp.asarray(t0, c.dtype)[None]])


def _labels(ctrl) -> tuple:
    """(measured, command, compensator) names of a linearizing controller."""
    names = tuple(ctrl.state_names)
    nX = ctrl.robot.n_state
    inputs = tuple(f"u{i + 1}" for i in range(ctrl.robot.n_input))
    torque = ctrl.level == Level.TORQUE
    measured = names[:nX] + (inputs if torque else ())
    command = tuple(f"v{i + 1}" for i in range(ctrl.robot.n_input)) if torque else inputs
    # a static law has no state of its own (at torque level its state is the plant's, measured)
    return measured, command, names[nX:] if ctrl.law.extension.n_comp else ()


def control_step(ctrl, params, *, name: str | None = None) -> ControlStep:
    """The control step of a static or dynamic linearizing controller with its parameters.

    The step closes over ``params`` (gains or gain schedule, reference, nominal geometry): they
    are baked into the exported artifact and the generated C, as the robot's controller holds them.

    Args:
      ctrl: a :class:`wmrjax.DynamicLinearization` or :class:`wmrjax.StaticLinearization` (any
        type and level; the hybrid §6.2 controller is not a single law and is refused).
      params: its parameters (``ctrl.params(...)``, e.g. with tuned gains).
      name: a C identifier prefixing the generated functions (default ``wmr_<type>_<level>``).

    Returns:
      :class:`ControlStep`.

    Raises:
      ValueError: not a linearizing controller, parameters of another controller, or a name
        that is not a C identifier.
    """
    if not hasattr(ctrl, "law") or not hasattr(ctrl, "control_and_regularity"):
        raise ValueError(f"control_step exports a static or dynamic linearizing law, got {type(ctrl).__name__}")
    ctrl.check_params(params)
    robot = ctrl.robot.name
    name = name if name is not None else f"wmr_{re.sub(r'[^0-9]', '', robot)}_{ctrl.level}"
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise ValueError(f"control_step: name must be a C identifier (letters, digits, _), got {name!r}")
    measured, command, comp = _labels(ctrl)
    n_c = len(comp)
    fn = _within_span(_static_step(ctrl, params) if n_c == 0 else _dynamic_step(ctrl, params), params.reference)
    return ControlStep(
        name, len(measured), 2 * n_c + 1 if n_c else 0, len(command), n_c, measured, command, comp,
        robot, str(ctrl.level), fn=fn, span=reference_span(params.reference),
    )  # fmt: skip


def reference_span(reference) -> tuple[float, float] | None:
    """``(t_first, t_last)`` [s] of a sampled path (where its data define it), None for a path
    defined at every time (a named family, or one extended with ``extrapolate=True``)."""
    dom = reference.domain()
    if dom is None:
        return None
    lo, hi = (concrete(x) for x in dom)
    return None if lo is None or hi is None else (float(np.max(lo)), float(np.min(hi)))


def _within_span(fn, reference):
    """The step with its regularity output set to 0 -- the flag a robot loop stops on -- at
    times outside a sampled path's span: there the path would be extrapolated silently (the
    reliability probe: 0.2 m off at 8 s and 10.9 m at 12 s for a path sampled on [0, 4] s)."""
    span = reference_span(reference)
    if span is None:
        return fn
    lo, hi = span
    tol = DOMAIN_RTOL * (1.0 + max(abs(lo), abs(hi)))

    def step(t, measured, state):
        command, state, regularity = fn(t, measured, state)
        inside = (t >= lo - tol) & (t <= hi + tol)
        return command, state, jnp.where(inside, regularity, jnp.zeros_like(regularity))

    return step


def _static_step(ctrl, params):
    """A static law: the command from the measured state alone (at torque level the state
    is (X, u), the command v = du/dt)."""
    law = ctrl.law

    def fn(t, measured, state):
        U, regularity = ctrl.control_and_regularity(t, measured, params)
        return law.plant_control(measured, U, params.geometry), state, regularity

    return fn


def _dynamic_step(ctrl, params):
    """A dynamic law: :meth:`SampledLoop.sample` on a state holding the measurement, the
    compensator, its held rate and the last sample's time (no noise: the measurement is given)."""
    loop = SampledLoop(ctrl, 1)
    nX, n_c = ctrl.robot.n_state, ctrl.n_state - ctrl.robot.n_state
    plant = PlantLoop(ctrl).params(params)
    dtype = jnp.result_type(float)
    sp = SampledParams(plant, jnp.zeros((1, nX), dtype))
    n_err = ctrl.m * ctrl.relative_degree

    def fn(t, measured, state):
        z = SampledState(
            measured, state[:n_c], state[n_c : 2 * n_c], state[2 * n_c], jnp.zeros(ctrl.robot.n_input, dtype),
            jnp.zeros((), dtype), jnp.zeros(n_err, dtype),
        )  # fmt: skip
        z = loop.sample(0, t, z, sp)
        return z.command, jnp.concatenate([z.controller, z.rate, z.t_sample[None]]), z.regularity

    return fn


def _specs(step: ControlStep, dtype):
    return (
        jax.ShapeDtypeStruct((), dtype),
        jax.ShapeDtypeStruct((step.n_measured,), dtype),
        jax.ShapeDtypeStruct((step.n_state,), dtype),
    )


def export_artifact(step: ControlStep) -> bytes:
    """The step as a serialized ``jax.export`` artifact (StableHLO, float64, for the CPU).

    Reload it with ``jax.export.deserialize(data).call(t, measured, state)`` in any process with
    ``jax`` (and ``jax_enable_x64``): no ``wmrjax`` needed.
    """
    dtype = jnp.float64
    if not jax.config.read("jax_enable_x64"):
        raise ValueError("export_artifact needs float64: jax.config.update('jax_enable_x64', True) first")
    exported = jax.export.export(jax.jit(step.fn), platforms=("cpu",))(*_specs(step, dtype))
    return bytes(exported.serialize())


def program(step: ControlStep):
    """The step's scalar program: a closed jaxpr of ``(t, measured, state)`` on float64, re-emitted
    on scalars and simplified as the simulator's loop body is (:func:`wmrjax.scalarized`)."""
    if not jax.config.read("jax_enable_x64"):
        raise ValueError("generate_c needs float64: jax.config.update('jax_enable_x64', True) first")
    return jax.make_jaxpr(scalarized(step.fn))(*_specs(step, jnp.float64))


def generate_c(step: ControlStep) -> dict[str, str]:
    """Self-contained C99 for the step: ``{"<name>.h": header, "<name>.c": source}``.

    The header documents the API: ``<name>_init(t0, compensator, state)`` fills the controller's
    state before the first sample, ``<name>_step(t, measured, state, command, &regularity)``
    runs one period (``state`` is updated in place), and the sizes as macros. The source needs
    ``math.h`` only (link with ``-lm``).
    """
    doc = (
        ""
        if step.span is None
        else f"valid for t in [{step.span[0]!r}, {step.span[1]!r}] s, the sampled path's span: outside it "
        "regularity is 0 (stop)"
    )
    return _cgen.generate(program(step), step, doc)


class Run(NamedTuple):
    """A sampled-data run of the simulator, as the robot's controller sees it.

    Attributes:
      t: (n,) sample times [s].
      measured: (n, n_measured) what the controller measures at each sample.
      command: (n, n_command) the command the simulator's controller held after each sample.
      initial_state: (n_state,) the controller's state before the first sample.
      state: (n, n_state) the simulator's controller state before each sample (its own, which a
        driven step's state may leave by rounding: a per-sample comparison starts from it).
      complete: the run did not fail (:class:`wmrjax.Diagnostics`); a failed run is cut at its
        last valid sample (its states are frozen from the failure on).
    """

    t: Any
    measured: Any
    command: Any
    initial_state: Any
    state: Any
    complete: bool


def reference_run(step: ControlStep, ctrl, params, z0, *, period: float, n_samples: int, steps_per_sample: int = 5):
    """The simulator's run the exported step must reproduce: the law run by a digital controller
    at ``period`` (:func:`wmrjax.sampled`, no noise, no limits; a static law at torque level, whose
    state is the plant's: its continuous loop sampled at the period), from ``z0``.

    Args:
      step: the exported step (for its sizes).
      ctrl: the law (that of ``step``).
      params: its parameters (those of ``step``).
      z0: (ctrl.n_state,) the law's initial state (X, compensator...).
      period: controller period [s].
      n_samples: samples of the run.
      steps_per_sample: RK4 steps of the plant per period.

    Returns:
      :class:`Run`.
    """
    dt = period / steps_per_sample
    n_steps = n_samples * steps_per_sample
    z0 = jnp.asarray(z0, jnp.result_type(float))
    nX = ctrl.robot.n_state
    if step.n_compensator == 0 and ctrl.level == Level.TORQUE:
        tr = simulate(ctrl, z0, params, dt=dt, n_steps=n_steps, save_every=steps_per_sample)
        n = tr.t.shape[0] - 1
        empty = jnp.zeros((n, 0), tr.t.dtype)
        return _cut(Run(tr.t[:-1], tr.state[:-1], tr.control[:-1], step.initial_state(tr.t[0]), empty, True), tr)
    loop = sampled(ctrl, steps_per_sample)
    sp = loop.params(params)
    zs = loop.initial_state(z0, sp)
    tr = simulate(loop, zs, sp, dt=dt, n_steps=n_steps, save_every=steps_per_sample)
    # a state saved at a sample's time follows that sample, but the first (the initial state)
    # precedes it: the first command is the simulator's sample of the initial state
    first = loop.sample(0, tr.t[0], zs, sp).command
    command = jnp.concatenate([first[None], tr.state.command[1:-1]])
    s0 = step.initial_state(tr.t[0], z0[nX:])
    if step.n_state:
        held = jnp.concatenate([tr.state.controller, tr.state.rate, tr.state.t_sample[:, None]], axis=1)[:-2]
        state = jnp.concatenate([s0[None], held])
    else:  # a static law keeps no state of its own
        state = jnp.zeros((tr.t.shape[0] - 1, 0), tr.t.dtype)
    return _cut(Run(tr.t[:-1], tr.state.plant[:-1], command, s0, state, True), tr)


def _cut(run: Run, tr) -> Run:
    """``run`` up to the trajectory's last valid sample (all of it when the run did not fail)."""
    valid = np.asarray(tr.valid)
    if valid.all():
        return run
    n = int(np.argmin(valid)) - 1  # samples before the first invalid saved state, less the one it follows
    return Run(run.t[:n], run.measured[:n], run.command[:n], run.initial_state, run.state[:n], False)


def drive(step_fn, run: Run):
    """The commands, states and regularity of ``step_fn(t, measured, state)`` driven over ``run``'s
    samples in order (NumPy arrays): ``(command (n, n_command), state (n, n_state), regularity (n,))``.
    ``step_fn`` may be the JAX step, a reloaded artifact's ``call`` or a wrapped C function."""
    state = np.asarray(run.initial_state, np.float64)
    commands, states, regs = [], [], []
    for t, m in zip(np.asarray(run.t), np.asarray(run.measured)):
        c, state, r = (np.asarray(x, np.float64) for x in step_fn(np.float64(t), np.asarray(m, np.float64), state))
        commands.append(c), states.append(state), regs.append(float(r))
    return np.stack(commands), np.stack(states), np.asarray(regs)
