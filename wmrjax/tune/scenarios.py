r"""Scenarios drawn from a problem, and their rollouts.

A *scenario* is one run of the problem's closed loop (:meth:`wmrjax.problem.Setting.run`:
the law run by its digital controller, with the problem's period, noise and actuator limits)
with its own initial error (uniform in the problem's ``[initial]`` box), reference (a fresh
draw of a random family; the problem's own otherwise), plant (one of the problem's listed
input and geometry scales, each input scale and the plant's L and e within +-``mismatch`` of
it) and noise key. :func:`rollout`
simulates one with given gains and returns the loss terms of its
:class:`wmrjax.Trajectory` (:func:`wmrjax.tune.losses.metrics`). Pure: batch with ``jax.vmap``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import wmrjax as w
from wmrjax import references as R
from wmrjax.controllers import initial_keys, place
from wmrjax.problem import RunInputs, Setting, initial_box, random_options
from wmrjax.tune.losses import MARGIN_FLOOR, MARGIN_SAFE, Metrics, SampleTerms, metrics


class Scenario(NamedTuple):
    """One tuning scenario (a pytree; a set stacks them along a leading axis).

    The scenarios of a set differ only in what :func:`draw` draws (:data:`DRAWN`, the noise key,
    and the reference of a random family); the batched losses read the other inputs from the
    first scenario (:func:`shared_axes`), as every set :func:`draw_set` returns holds them
    (:func:`wmrjax.tune.mean_loss` and :func:`wmrjax.tune.mean_loss_and_grad` refuse a set that does not:
    :func:`check_shared`).

    Attributes:
      inputs: the run's inputs (:class:`wmrjax.problem.RunInputs`, ``gains`` None): nominal
        geometry, plant limits and scales (``geometry_scale``: the plant's L and e over the
        law's, (2,)), reference parameters and heading offset, branch, initial error, and the
        law's initial state ``z0`` placed from it.
      key: the PRNG key of the run's measurement noise.
    """

    inputs: RunInputs
    key: jnp.ndarray


def tuning_box(setting: Setting) -> tuple:
    """``(low, high)`` (k,) arrays of the initial errors the tuner draws from: the ``{ low, high }``
    ranges of a random ``[initial]``, else the extent of its values (a grid's or the points')."""
    ins = setting.data["initial"]
    keys = initial_keys(setting.ctrl, setting.space)
    if "random" in ins:
        box = initial_box(ins, keys)
        return np.array([box[k][0] for k in keys]), np.array([box[k][1] for k in keys])
    e = setting.initial_errors()
    return e.min(axis=0), e.max(axis=0)


def draw(setting: Setting, mismatch: float, key) -> Scenario:
    """One scenario from ``key`` (pure: vmap over keys)."""
    kr, ki, kv, km, kn = jax.random.split(key, 5)
    nu = setting.ctrl.robot.n_input
    base = jax.tree_util.tree_map(lambda x: jnp.asarray(np.asarray(x)[0]), setting.inputs())._replace(gains=None)
    family = R.FAMILIES[setting.data["reference"]["family"]]
    if family.kind == "random":  # a fresh reference per scenario
        base = base._replace(reference=family.make(kr, **random_options(setting.data["reference"])).params)
    lo, hi = (jnp.asarray(v) for v in tuning_box(setting))
    k = lo.shape[0]
    u = jnp.concatenate(
        [jax.random.uniform(ki, (2,), minval=-1, maxval=1), jax.random.uniform(kv, (k - 2,), minval=-1, maxval=1)]
    )
    initial = 0.5 * (lo + hi) + 0.5 * (hi - lo) * u
    # placed once here (the nominal law's state), not in every rollout of the scenario
    params = setting.ctrl.params_unchecked(
        R.Reference(base.reference, base.heading_offset, setting.reference.path, setting.reference.name),
        1.0,
        w.Geometry(base.L, base.e, base.delta),
    )
    z0 = place(setting.ctrl, params, initial, setting.space, setting.task, base.branch)
    rho = jax.random.uniform(km, (nu + 2,), minval=-mismatch, maxval=mismatch)
    input_scale, geometry_scale = _plant_scales(setting, jax.random.fold_in(km, 1))
    base = base._replace(
        initial=initial,
        z0=z0,
        input_scale=input_scale * (1.0 + rho[:nu]),
        geometry_scale=geometry_scale * (1.0 + rho[nu:]),
    )
    return Scenario(base, kn)


def _plant_scales(setting: Setting, key) -> tuple:
    """The problem's own input and geometry scales of one scenario: one of the ``[plant]``
    values the file lists, drawn uniformly (a listed range is tuned over, not refused), around
    which the mismatch is drawn. Both 1 without a ``[plant]``."""
    plant = setting.axis("plant").payload
    inputs, geometry = jnp.asarray(plant["input_scale"]), jnp.asarray(plant["geometry_scale"])  # (n, nu), (n,)
    n = geometry.shape[0]
    j = jax.random.randint(key, (), 0, n) if n > 1 else 0
    return inputs[j], geometry[j]


def draw_set(setting: Setting, mismatch: float, keys) -> Scenario:
    """One scenario per key of ``keys`` (N keys -> N scenarios, batched along axis 0)."""
    return jax.vmap(lambda k: draw(setting, mismatch, k))(keys)


# what a scenario draws; every other input is the problem's own, the same in every scenario
DRAWN = ("initial", "z0", "input_scale", "geometry_scale")


def _drawn(setting: Setting) -> set:
    """The inputs a scenario draws: :data:`DRAWN`, and the reference of a random family."""
    random = R.FAMILIES[setting.data["reference"]["family"]].kind == "random"
    return set(DRAWN) | ({"reference"} if random else set())


def shared_axes(setting: Setting, sc: Scenario) -> tuple:
    """``(sc', axes)``: a scenario batch with the inputs every scenario shares taken once (the
    first scenario's), and the ``in_axes`` of ``jax.vmap`` for it: the shared inputs unbatched, so
    that what depends on them alone is computed once, not once per scenario."""
    drawn = _drawn(setting)
    fields = sc.inputs._asdict()
    inputs = RunInputs(
        **{k: (v if k in drawn else jax.tree_util.tree_map(lambda x: x[0], v)) for k, v in fields.items()}
    )
    axes = RunInputs(**{k: (0 if k in drawn else None) for k in fields})
    return Scenario(inputs, sc.key), Scenario(axes, 0)


def check_shared(setting: Setting, sc: Scenario) -> None:
    """ValueError when the scenarios of a batch differ in an input they must share (one that
    :func:`shared_axes` takes from the first scenario): a set edited or built by hand. Traced
    batches (inside a transformation) are not checked."""
    drawn = _drawn(setting)
    for k, v in sc.inputs._asdict().items():
        if k in drawn:
            continue
        for leaf in jax.tree_util.tree_leaves(v):
            if isinstance(leaf, jax.core.Tracer):
                return
            a = np.asarray(leaf)
            same = (a == a[:1]) | (np.isnan(a) & np.isnan(a[:1])) if a.dtype.kind == "f" else a == a[:1]
            if not np.all(same):
                rows = sorted({int(i) for i in np.nonzero(~same.reshape(a.shape[0], -1).all(axis=1))[0]})
                raise ValueError(
                    f"scenario inputs[{k!r}] differ between scenarios (scenarios {rows[:8]} differ from scenario 0); "
                    f"every scenario of a set shares the problem's {k!r}: only {sorted(drawn)} and the noise key "
                    "vary (draw sets with wmrjax.tune.scenarios.draw_set, or change the problem)"
                )


def rollout(setting: Setting, gains, sc: Scenario, trajectory: bool = False):
    """Simulate one scenario with ``gains`` (:class:`wmrjax.Gains` or a
    :class:`wmrjax.GainSchedule`); returns :class:`wmrjax.tune.Metrics` (with ``trajectory``:
    ``(None, the wmrjax.Trajectory of its states, the law's parameters)``)."""
    every = setting.steps_per_sample or 1
    save = None if trajectory else SampleTerms(setting.ctrl.m, setting.control_period is not None)
    tr, params = setting.run(
        sc.inputs._replace(gains=gains),
        save_every=every,
        error_tol=None,
        margin_floor=MARGIN_FLOOR,
        noise_key=sc.key,
        save_fn=save,
    )
    if trajectory:
        return None, tr, params
    return metrics(setting, tr, params, sc.inputs, MARGIN_SAFE)


__all__ = ["DRAWN", "Metrics", "Scenario", "check_shared", "draw", "draw_set", "rollout", "shared_axes", "tuning_box"]
