"""A problem's setting: one controller (one case, robot type and level) with the axes of values a
sweep runs over, the typed inputs of one run (:class:`RunInputs`), and the one run of a problem
(:meth:`Setting.run`), which the sweep, the tuner and the certification's rollouts go through.
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import references as R
from wmrjax.controllers import PlantParams, SampledParams, measurement_noise, sampled, with_plant
from wmrjax.controllers.law import Task
from wmrjax.controllers.placement import Space, place
from wmrjax.problem.schema import GEOMETRY_KEYS, Law, ProblemError
from wmrjax.robots import Geometry
from wmrjax.simulate import simulate


@dataclasses.dataclass
class Axis:
    """One axis of a setting: ``n`` values, their table columns and what the run consumes.

    Attributes:
      name: "geometry" | "plant" | "reference" | "gains" | "initial".
      columns: column name -> (n,) values (float, or str for labels).
      payload: key -> (n, ...) arrays (or a pytree with that leading axis) for the run.
      random: the values are random draws (not a grid): maps do not slice along them.
    """

    name: str
    columns: dict
    payload: dict
    random: bool = False

    @property
    def size(self) -> int:
        """The number of values on the axis."""
        for v in self.columns.values():
            return len(v)
        return 1


class RunInputs(NamedTuple):
    """The inputs of one run of a :class:`Setting` (:meth:`Setting.run`), or with a leading axis
    of many (:meth:`Setting.inputs`): a pytree, batched with ``jax.vmap``.

    Attributes:
      L, e, delta: the law's geometry (:class:`wmrjax.Geometry`) [m, m, rad].
      limit: (n_input,) input limits of the plant (inf: none) [the inputs' units].
      input_scale: (n_input,) the plant's input = scale * command.
      geometry_scale: () or (2,): the plant's L and e = scale * the law's (one factor, or one each).
      reference: the reference's parameters (a pytree of :class:`wmrjax.references.Reference`).
      heading_offset: () the reference's heading offset [rad].
      branch: () +1.0 or -1.0, the reference's branch of Psi^-1 (dynamic laws).
      gains: :class:`wmrjax.Gains` or :class:`wmrjax.GainSchedule`.
      initial: (k,) the initial error in :func:`wmrjax.controllers.initial_keys` order.
      z0: the law's initial state, placed already (None: placed from ``initial``).
    """

    L: Any
    e: Any
    delta: Any
    limit: Any
    input_scale: Any
    geometry_scale: Any
    reference: Any
    heading_offset: Any
    branch: Any
    gains: Any
    initial: Any
    z0: Any = None


INPUT_AXIS = RunInputs(0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 4)
"""The axis (index into :attr:`Setting.axes`: geometry, plant, reference, gains, initial) each
run input varies along."""


@dataclasses.dataclass(eq=False)
class Setting:
    """One controller of a problem (one case, robot type and level) with its axes.

    Attributes:
      case: the case's name (None without ``[[case]]``).
      law, task, space: the law, what it tracks, where initial errors live.
      ctrl: the controller (static, hashable).
      axes: geometry, plant, reference, gains, initial (:class:`Axis`; runs are their product,
        last fastest).
      references: the references of the reference axis (heading offsets applied).
      branch: (n_reference,) branch of each reference (dynamic laws).
      plant: the run closes the law around a plant (limits, scale, mismatch, sampling, noise).
      control_period: the digital controller's period [s] (None: continuous feedback).
      noise_std: measurement noise std of X's components (sampled loops), noise_seed its seed.
      t_final, dt, n_steps: horizon [s], step [s] and step count.
      data: this setting's sections as parsed.
    """

    case: str | None
    law: Law
    task: Task
    space: Space
    ctrl: Any
    axes: list
    references: list
    branch: np.ndarray
    plant: bool
    control_period: float | None
    noise_std: tuple
    noise_seed: int
    t_final: float
    dt: float
    n_steps: int
    data: dict

    @property
    def shape(self) -> tuple:
        """The number of values on each axis (geometry, plant, reference, gains, initial)."""
        return tuple(a.size for a in self.axes)

    def content_digest(self) -> str:
        """A digest of every value this setting runs with, read from files included (a path's
        samples, a gains file's gains): a resumable job's fingerprint, which changes when a file's
        content changes under the same name."""
        h = hashlib.sha256()
        for a in self.axes:
            h.update(a.name.encode())
            for leaf in jax.tree_util.tree_leaves((a.columns, a.payload)):
                arr = np.ascontiguousarray(np.asarray(leaf))
                h.update(f"{arr.dtype}{arr.shape}".encode())
                h.update(arr.tobytes())
        return h.hexdigest()[:16]

    @property
    def size(self) -> int:
        """The number of runs: the product of the axes' sizes."""
        return int(np.prod(self.shape))

    @property
    def reference(self):
        """The first reference of the axis (the only one for a single-valued problem)."""
        return self.references[0]

    @property
    def steps_per_sample(self) -> int | None:
        """RK4 steps per controller period (None: continuous feedback)."""
        return None if self.control_period is None else int(round(self.control_period / self.dt))

    @property
    def noise_shape(self) -> tuple[int, int] | None:
        """(n_samples, n_X): a run's measurement noise, one row per controller sample (None:
        continuous feedback)."""
        if self.control_period is None:
            return None
        return self.n_steps // self.steps_per_sample + 1, self.ctrl.robot.n_state

    def axis(self, name: str) -> Axis:
        """The axis named ``name``."""
        return next(a for a in self.axes if a.name == name)

    def system(self):
        """The closed loop a run simulates: the controller, with a plant, or sampled."""
        if self.control_period is not None:
            return sampled(self.ctrl, self.steps_per_sample)
        return with_plant(self.ctrl) if self.plant else self.ctrl

    def check_single(self, job: str, keep=("initial",)) -> None:
        """ProblemError naming the first axis (other than ``keep``) with more than one value."""
        for a in self.axes:
            if a.name in keep or a.size == 1:
                continue
            swept = [k for k, v in a.columns.items() if len(set(np.asarray(v).tolist())) > 1]
            raise ProblemError(
                f"{job} takes one value of [{a.name}], got {a.size} ({', '.join(swept)} swept); "
                "keep one value (sweeps take lists)"
            )

    def geometry(self, i: int = 0):
        """The ``i``-th geometry of the axis (:class:`wmrjax.Geometry`)."""
        geo = self.axis("geometry").payload
        return Geometry(**{k: float(geo[k][i]) for k in GEOMETRY_KEYS})

    def gains(self, i: int = 0):
        """The i-th gains of the axis: :class:`wmrjax.Gains` or :class:`wmrjax.GainSchedule`."""
        return jax.tree_util.tree_map(lambda x: x[i], self.axis("gains").payload["gains"])

    def params(self, *, gains=None, reference: int = 0, geometry: int = 0):
        """The law's checked parameters (one geometry, one reference; ``gains`` overrides the axis's first)."""
        g = self.geometry(geometry)
        return self.ctrl.params(self.references[reference], geometry=g, gains=self.gains() if gains is None else gains)

    def initial_errors(self) -> np.ndarray:
        """(n, k) initial errors of the initial axis (keys :func:`initial_keys`)."""
        return np.asarray(self.axis("initial").payload["initial"])

    def inputs(self, idx: list | None = None) -> RunInputs:
        """Every run input at its axis's level, or (with ``idx``, per-axis indices of some runs)
        per run: a :class:`RunInputs` whose fields have a leading axis (``z0`` None)."""
        geo, plant, ref, gains, init = (a.payload for a in self.axes)
        src = RunInputs(
            geo["L"],
            geo["e"],
            geo["delta"],
            plant["limit"],
            plant["input_scale"],
            plant["geometry_scale"],
            ref["reference"],
            ref["heading_offset"],
            self.branch.astype(float),
            gains["gains"],
            init["initial"],
        )
        if idx is None:
            return src
        take = lambda v, axis: jax.tree_util.tree_map(lambda x: np.asarray(x)[idx[axis]], v)
        return RunInputs(*(take(v, axis) for v, axis in zip(src[:-1], INPUT_AXIS[:-1])))

    def run_inputs(self, i: int) -> RunInputs:
        """The inputs of run ``i`` (its flat index, last axis fastest), unbatched: for :meth:`run`."""
        if not 0 <= i < self.size:
            raise ProblemError(f"run index {i} outside [0, {self.size}) of this setting")
        idx = list(np.unravel_index(np.array([i]), self.shape))
        return jax.tree_util.tree_map(lambda x: np.asarray(x)[0], self.inputs(idx))

    def run(
        self,
        p: RunInputs,
        *,
        save_every: int | None = None,
        error_tol=1e-3,
        margin_floor=1e-9,
        noise_key=None,
        noise=None,
        t0=0.0,
        save_fn=None,
    ):
        """One run (pure: vmap it) from one run's inputs ``p`` (:meth:`inputs`, unbatched; its
        ``z0``, where given, is the law's initial state, else it is placed from ``p.initial``).

        ``save_every`` (default: every sample of a digital controller, else every step),
        ``error_tol``, ``margin_floor`` and ``save_fn`` are :func:`wmrjax.simulate`'s;
        ``noise_key`` draws the measurement noise of a digital controller, or ``noise`` gives it:
        :attr:`noise_shape`, row k added to the posture measured at sample k
        (a worst case searched within a bound, :func:`wmrjax.certify.worst_noise`; it takes
        precedence over ``noise_key``); ``t0`` [s] starts the run.

        Returns:
          ``(trajectory, params)``: the :class:`wmrjax.Trajectory` of :meth:`system`, and the
          law's parameters (reference, gains, nominal geometry) of this run.
        """
        ctrl = self.ctrl
        g = Geometry(L=p.L, e=p.e, delta=p.delta)
        ref = R.Reference(p.reference, p.heading_offset, self.reference.path, self.reference.name)
        params = ctrl.params_unchecked(ref, 1.0, g)._replace(gains=p.gains)
        t0 = jnp.asarray(t0, jnp.result_type(float))
        # the law's initial state: given (``z0``), or placed from the initial error
        z0 = p.z0 if p.z0 is not None else place(ctrl, params, p.initial, self.space, self.task, p.branch, t0)
        loop = self.system()
        if noise is not None and (not self.plant or self.control_period is None):
            raise ValueError(
                "noise is the measurement noise of a digital controller: this setting has no control_period"
            )
        if noise is not None and jnp.shape(noise) != self.noise_shape:
            raise ValueError(
                f"noise must be {self.noise_shape} (one row per sample, one column per component of X), "
                f"got shape {jnp.shape(noise)}"
            )
        if self.plant:
            scale = jnp.broadcast_to(p.geometry_scale, (2,))  # of L and e (one factor: both)
            pg = Geometry(L=scale[0] * g.L, e=scale[1] * g.e, delta=g.delta)
            plant = PlantParams(params, pg, jnp.broadcast_to(p.input_scale, (ctrl.robot.n_input,)), p.limit)
            if self.control_period is not None:
                if noise is not None:
                    noise = jnp.asarray(noise, t0.dtype)
                elif any(self.noise_std) and noise_key is not None:
                    noise = measurement_noise(noise_key, jnp.asarray(self.noise_std), *self.noise_shape)
                sp = SampledParams(plant, jnp.zeros((1, ctrl.robot.n_state), t0.dtype) if noise is None else noise)
                z0, params_run = loop.initial_state(z0, sp), sp
            else:
                z0, params_run = loop.initial_state(z0, plant), plant
        else:
            params_run = params
        save_every = (self.steps_per_sample or 1) if save_every is None else save_every
        tr = simulate(
            loop,
            z0,
            params_run,
            dt=self.dt,
            n_steps=self.n_steps,
            t0=t0,
            save_every=save_every,
            error_tol=error_tol,
            margin_floor=margin_floor,
            save_fn=save_fn,
        )
        return tr, params


def law_state(system, z):
    """The law's own state ``(X, compensator...)`` of a closed loop's state (batched or not)."""
    return system.law_state(z)


def unravel(setting: Setting, start: int, n: int) -> list:
    """Per-axis value indices of runs ``start .. start + n - 1`` of ``setting`` (last axis fastest)."""
    return list(np.unravel_index(np.arange(start, start + n), setting.shape))


def columns_of(setting: Setting, idx: list) -> dict:
    """The table columns (every axis's) of the runs at per-axis indices ``idx`` (:func:`unravel`)."""
    out = {}
    for a, i in zip(setting.axes, idx):
        for k, v in a.columns.items():
            out[k] = np.asarray(v)[i]
    return out
