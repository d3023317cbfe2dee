"""The tuning loop: an optax optimizer on the gain parameters, through batched runs of the
problem's closed loop, with a held-out split, early stopping and atomic JSON checkpoints.

:func:`tune` takes a problem's :class:`wmrjax.problem.Setting`, a gain family
(:class:`wmrjax.tune.GainFamily`) and an ``optax.GradientTransformation`` and returns a
:class:`TuneResult`; the configuration comes in small groups (:mod:`wmrjax.tune.config`).
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

import wmrjax as w
from wmrjax import _files as files
from wmrjax import certify, resources
from wmrjax.controllers.dynamic import DynamicLinearization
from wmrjax.references import FAMILIES
from wmrjax.tune import certified
from wmrjax.tune.config import Scenarios, Stopping
from wmrjax.tune.gains import GainFamily
from wmrjax.tune.losses import LossWeights, certificate_radius, scenario_loss
from wmrjax.tune.scenarios import Scenario, check_shared, draw_set, rollout, shared_axes

# the programs that run a few times in a run (scenario draws, validation, figures, reports)
# compile at XLA's backend optimization level 0, the gradient's and the baselines' evaluator's
# (thousands of rollouts) at level 1; the benchmarks page of the docs has the timings
QUICK_COMPILE = {"xla_backend_optimization_level": 0}
LOOP_COMPILE = {"xla_backend_optimization_level": 1}
FAILURE_PENALTY = 1.0  # added to the objective per unit fraction of scenarios that failed (singular/non-finite)
CERTIFICATE_EPS = 1e-2  # Lemma 2's margin eps of the certificate term
CERTIFICATE_TIMES = 501  # grid of M1 over [0, t_final]


class ScenarioSets(NamedTuple):
    """The fixed scenario sets of a run (each a :class:`wmrjax.tune.Scenario` batch)."""

    train: Scenario
    validation: Scenario
    heldout: Scenario


class Certificate(NamedTuple):
    """What the certificate term needs: M1 of the problem's reference on a grid (closed form)."""

    ts: jnp.ndarray
    m1: jnp.ndarray
    eps: float
    weight: float


class Context(NamedTuple):
    """A run's fixed pieces: the problem's setting, the gain family, the scenario sets, the loss
    weights (an array) and the certificate term's data (None without it)."""

    setting: object
    family: GainFamily
    sets: ScenarioSets
    weights: jnp.ndarray
    certificate: Certificate | None
    kept: "Kept | None" = None


class Kept(NamedTuple):
    """A certified-region requirement as the loop keeps it (:mod:`wmrjax.tune.certified`).

    Attributes:
      requirement: :class:`wmrjax.tune.certified.Requirement` as given.
      required: the required radius as a number [output-error units].
      radius: :class:`wmrjax.tune.certified.Radius` (the exact-map radius of raw parameters).
      initial: the initial gains' radius.
    """

    requirement: object
    required: float
    radius: object
    initial: float


class TuneResult(NamedTuple):
    """What :func:`tune` returns.

    Attributes:
      finished: the run reached ``steps`` or stopped early (False after ``stop_after``).
      raw: the last unconstrained parameters; best_raw: those of the best validation objective.
      history: one dict per step (training objective, rollouts, parameters; validation every
        ``eval_every`` steps).
      rollouts, excluded: scenario runs of the gradient steps, and those excluded (failed).
      stopped_early: early stopping ended the run.
      wall_time_s: seconds in the loop (over resumptions).
      context: :class:`Context`.
    """

    finished: bool
    raw: np.ndarray
    best_raw: np.ndarray
    history: list
    rollouts: int
    excluded: int
    stopped_early: bool
    wall_time_s: float
    context: Context


# --- set-up --------------------------------------------------------------------------------------


def check(setting, family: GainFamily, scenarios: Scenarios, loss: LossWeights) -> None:
    """ValueError for what cannot be tuned, before anything compiles: a static law at torque
    level, a certificate term without a dynamic law and a fixed reference, a family of
    another shape, or the problem's initial gains outside the family."""
    ctrl = setting.ctrl
    random_reference = FAMILIES[setting.data["reference"]["family"]].kind == "random"
    # a random family's references are drawn per scenario (its count is a sweep's)
    setting.check_single("tuning", keep=("initial", "plant") + (("reference",) if random_reference else ()))
    limits = np.asarray(setting.axis("plant").payload["limit"])
    if len(np.unique(limits, axis=0)) > 1:  # a listed scale is drawn per scenario; a limit is shared by the batch
        raise ValueError(
            "tuning takes one [plant] input_limit (its scenarios draw a listed input_scale or geometry_scale, "
            f"not a limit), got {len(limits)}; keep one value (sweeps take lists)"
        )
    if (family.m, family.r) != (ctrl.m, ctrl.relative_degree):
        raise ValueError(
            f"the gain family is for (m, r) = ({family.m}, {family.r}), the controller needs "
            f"({ctrl.m}, {ctrl.relative_degree})"
        )
    if loss.certificate > 0 and (not isinstance(ctrl, DynamicLinearization) or random_reference):
        raise ValueError(
            "the certificate term needs a dynamic (posture) controller of type (2,0), (2,1) or (1,1) "
            "and a fixed reference (not a random family)"
        )
    if family.knots and family.knots[-1] > setting.t_final:
        raise ValueError(f"knot times {list(family.knots)} reach beyond the horizon t_final = {setting.t_final} s")
    initial_raw(setting, family)


def initial_raw(setting, family: GainFamily):
    """The family's parameters of the problem's ``[gains]`` (poles: real poles; omega and zeta:
    damping factors), from which the tuner starts."""
    gs = setting.data.get("gains", {"poles": 1.0})
    if "poles" in gs or not gs:
        poles = gs.get("poles", 1.0)
        if not isinstance(poles, (int, float)) or isinstance(poles, bool):
            raise ValueError(f"[gains] poles: the tuner starts from one pole magnitude, got {poles!r}")
        return family.init(float(poles))
    if {"omega", "zeta"} <= set(gs) and family.parameterization == "damping":
        om, ze = gs["omega"], gs["zeta"]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (om, ze)):
            raise ValueError(f"[gains] omega, zeta: the tuner starts from one value of each, got {om!r}, {ze!r}")
        one = np.asarray(
            sum(([float(om), float(ze)] for _ in range(family.r // 2)), [])
            + ([float(gs.get("lam", 1.0))] if family.r % 2 else [])
        )
        return family.raw_from_positive(np.broadcast_to(one, family.shape))
    raise ValueError(
        f"[gains]: the tuner starts from poles = p (or omega and zeta with the damping family); got {sorted(gs)}"
    )


@functools.partial(jax.jit, static_argnums=(0, 1), compiler_options=QUICK_COMPILE)
def _draw_sets(setting, scenarios: Scenarios, key) -> ScenarioSets:
    """The training, validation and held-out scenarios, drawn by one program."""
    k_tr, k_ho = jax.random.split(key)
    sizes = (scenarios.train, scenarios.validation, scenarios.heldout)
    keys = jnp.concatenate([jax.random.split(k, n) for k, n in zip((k_tr, jax.random.fold_in(key, 2), k_ho), sizes)])
    every = draw_set(setting, scenarios.mismatch, keys)
    ends = np.cumsum(sizes)
    return ScenarioSets(*(jax.tree_util.tree_map(lambda x: x[e - n : e], every) for n, e in zip(sizes, ends)))


# a fresh training batch (resampling): one program per setting, mismatch and count
_draw_batch = jax.jit(
    lambda setting, mismatch, key, n: draw_set(setting, mismatch, jax.random.split(key, n)), static_argnums=(0, 1, 3)
)


def certificate(setting, weight: float, eps: float = CERTIFICATE_EPS, n_t: int = CERTIFICATE_TIMES):
    """The certificate term's data: M1 of the problem's own reference (heading offset
    included) in closed form over [0, t_final], or None when ``weight`` is 0."""
    if weight <= 0:
        return None
    params = setting.params()
    ts = jnp.linspace(0.0, setting.t_final, n_t)
    return Certificate(ts, certify.m1_closed_form(setting.ctrl, params, ts), eps, float(weight))


def certificate_term(family: GainFamily, raw, cert: Certificate | None):
    """``-weight x`` the Lemma 2 radius of the gains (0 without the term); differentiable in raw."""
    if cert is None:
        return jnp.zeros(())
    return -cert.weight * certificate_radius(family.gains(raw), cert.m1, cert.ts, cert.eps)


def prepare(setting, family: GainFamily, scenarios: Scenarios, loss: LossWeights, seed: int) -> Context:
    """Check, draw the scenario sets and compute the certificate term's data."""
    check(setting, family, scenarios, loss)
    sets = _draw_sets(setting, scenarios, jax.random.PRNGKey(seed))
    return Context(setting, family, sets, jnp.asarray(tuple(loss), float), certificate(setting, loss.certificate))


# --- the objective and its gradient ----------------------------------------------------------------


def _per_scenario(raw, sc, setting, family, w_arr):
    m = rollout(setting, family.gains(raw), sc)
    return scenario_loss(m, LossWeights(*w_arr)), m


def _mean_loss_and_grad(raw, scen, setting, family, w_arr):
    """Mean loss and gradient over the scenarios that stayed valid; a scenario whose value or
    gradient is not finite is dropped from both, never averaged in. :func:`wmrjax.value_and_grad`
    picks the mode: forward sensitivities for a few gain parameters, reverse mode for many."""
    scen, axes = shared_axes(setting, scen)
    vg = jax.vmap(w.value_and_grad(_per_scenario, has_aux=True), in_axes=(None, axes, None, None, None))
    (L, m), G = vg(raw, scen, setting, family, w_arr)
    ok = m.valid & jnp.isfinite(L) & jnp.all(jnp.isfinite(G.reshape(G.shape[0], -1)), axis=1)
    n = jnp.maximum(jnp.sum(ok), 1).astype(L.dtype)
    loss = jnp.sum(jnp.where(ok, L, 0.0)) / n
    grad = jnp.sum(jnp.where(ok.reshape((-1,) + (1,) * (G.ndim - 1)), G, 0.0), axis=0) / n
    return loss, grad, ok, m


_mean_loss_and_grad_program = jax.jit(_mean_loss_and_grad, static_argnums=(2, 3))


def mean_loss_and_grad(raw, scen, setting, family, w_arr):
    """``(mean loss, gradient, valid mask, metrics)`` over a batch of scenarios (not
    :func:`wmrjax.batch_value_and_grad`, which returns per-example gradients).

    Raises:
      ValueError: the scenarios differ in an input they must share (:func:`wmrjax.tune.scenarios.check_shared`).
    """
    check_shared(setting, scen)
    return _mean_loss_and_grad_program(raw, scen, setting, family, w_arr)


# the tuning loop's program: the same function at LOOP_COMPILE (a top-level program: JAX takes
# compiler options on the outermost jit only, so the public function keeps the default)
_gradient_step = jax.jit(_mean_loss_and_grad, static_argnums=(2, 3), compiler_options=LOOP_COMPILE)


def _mean_loss(raw, scen, setting, family, w_arr):
    """Mean loss (valid scenarios only), validity mask and metrics; forward only."""
    scen, axes = shared_axes(setting, scen)
    L, m = jax.vmap(_per_scenario, in_axes=(None, axes, None, None, None))(raw, scen, setting, family, w_arr)
    ok = m.valid & jnp.isfinite(L)
    return jnp.sum(jnp.where(ok, L, 0.0)) / jnp.maximum(jnp.sum(ok), 1).astype(L.dtype), ok, m


_mean_loss_program = jax.jit(_mean_loss, static_argnums=(2, 3))


def mean_loss(raw, scen, setting, family, w_arr):
    """``(mean loss, valid mask, metrics)`` over a batch of scenarios, forward only.

    Raises:
      ValueError: the scenarios differ in an input they must share (:func:`wmrjax.tune.scenarios.check_shared`).
    """
    check_shared(setting, scen)
    return _mean_loss_program(raw, scen, setting, family, w_arr)


# the validation's program: the same function, compiled quickly (it runs every eval_every steps)
validation_loss = jax.jit(_mean_loss, static_argnums=(2, 3), compiler_options=QUICK_COMPILE)


def objective(loss, ok):
    """The training objective every method is compared on: the mean loss over the scenarios that
    stayed valid plus :data:`FAILURE_PENALTY` times the fraction that failed."""
    return loss + FAILURE_PENALTY * (1.0 - jnp.mean(ok.astype(loss.dtype)))


_objective_plus = jax.jit(lambda loss, ok, extra: objective(loss, ok) + extra)
_positive = jax.jit(lambda family, raw: family.positive(raw), static_argnums=0)


# --- checkpoints -----------------------------------------------------------------------------------

STATE_KEYS = ("history", "best", "best_raw", "since_best", "rollouts", "excluded", "wall_time_s", "stopped_early")


def fingerprint(
    setting,
    family: GainFamily,
    scenarios: Scenarios,
    loss: LossWeights,
    stopping: Stopping,
    steps: int,
    seed: int,
    run_id: str = "",
) -> str:
    """A digest of everything a run's checkpoint depends on (``run_id``: what the caller adds,
    e.g. the problem file's fingerprint and the optimizer's settings)."""
    # the setting's values, not only its sections: a path file's name stays when its content changes
    desc = [setting.data, setting.content_digest(), repr(family), scenarios._asdict(), loss._asdict()]
    desc += [stopping._asdict(), steps, seed, run_id]
    return hashlib.sha256(json.dumps(desc, sort_keys=True, default=str).encode()).hexdigest()[:16]


def save_checkpoint(path: Path, fp: str, step, raw, opt_state, state: dict) -> None:
    """Atomic JSON checkpoint of the tuned parameters, the optimizer state and the history."""
    files.write_checkpoint(
        path,
        fingerprint=fp,
        config={"fingerprint": fp},
        step=step,
        trees={"raw": raw, "opt_state": opt_state},
        state=state,
    )


def load_checkpoint(path: Path, fp: str, steps: int, raw_template, opt_state_template):
    """(step, raw, opt_state, state) from a JSON checkpoint; ValueError if it is another run's or
    does not match this run's parameter shapes."""
    ck = files.read_checkpoint(
        path,
        fingerprint=fp,
        config={"fingerprint": fp},
        templates={"raw": raw_template, "opt_state": opt_state_template},
    )
    missing = sorted(set(STATE_KEYS) - set(ck.state))
    if missing:
        raise ValueError(f"checkpoint {path} lacks {missing} in its state (an edited or partial checkpoint)")
    if not 0 <= ck.step <= steps:
        raise ValueError(f"checkpoint {path} is at step {ck.step}, outside [0, {steps}]")
    _check_state(path, ck.step, ck.state, int(np.size(raw_template)))
    return ck.step, ck.trees["raw"], ck.trees["opt_state"], ck.state


def _is_count(v) -> bool:
    return type(v) is int and v >= 0


def _is_real(v) -> bool:
    return type(v) in (int, float)  # not bool; a loss may be inf


def _check_state(path: Path, step: int, state: dict, n_params: int) -> None:
    """ValueError naming the first field of a checkpoint's state that a run could not have
    written: a history of another length than ``step``, a non-boolean ``stopped_early``, ..."""
    hist, best_raw = state["history"], state["best_raw"]
    checks = [
        (
            "history",
            lambda: (
                isinstance(hist, list)
                and len(hist) == step
                and all(isinstance(h, dict) and _is_real(h.get("train_loss")) for h in hist)
            ),
            f"a list of {step} step records (one per step done)",
        ),
        ("best", lambda: state["best"] is None or _is_real(state["best"]), "null or a number"),
        (
            "best_raw",
            lambda: (
                (best_raw is None) == (state["best"] is None)
                and (
                    best_raw is None
                    or (isinstance(best_raw, list) and len(best_raw) == n_params and all(_is_real(v) for v in best_raw))
                )
            ),
            f"{n_params} numbers (null only with 'best' null)",
        ),
        ("since_best", lambda: _is_count(state["since_best"]), "an integer >= 0"),
        ("rollouts", lambda: _is_count(state["rollouts"]), "an integer >= 0"),
        (
            "excluded",
            lambda: _is_count(state["excluded"]) and state["excluded"] <= state["rollouts"],
            "an integer between 0 and rollouts",
        ),
        (
            "wall_time_s",
            lambda: _is_real(state["wall_time_s"]) and np.isfinite(state["wall_time_s"]) and state["wall_time_s"] >= 0,
            "seconds >= 0",
        ),
        ("stopped_early", lambda: type(state["stopped_early"]) is bool, "true or false"),
    ]
    for key, ok, expected in checks:  # in order: a later check may rely on an earlier one
        if not ok():
            raise ValueError(
                f"checkpoint {path}: state '{key}' is {state[key]!r:.80}, expected {expected} "
                "(an edited or corrupt checkpoint); delete it or rerun with --fresh"
            )


# --- the loop --------------------------------------------------------------------------------------


# copies of the scenario sets alive while they are drawn: their keys, the drawn batch, its slices
SCENARIO_COPIES = 3
KEY_BYTES = 8  # a PRNG key per scenario (two uint32)


def check_memory(setting, scenarios: Scenarios) -> None:
    """ValueError before anything compiles when a gradient step over ``scenarios.train`` runs
    (reverse mode through every step) would not fit in memory (:mod:`wmrjax.resources`)."""
    n_state = int(setting.system().n_state or setting.ctrl.n_state)
    est = resources.Estimate(resources.gradient_bytes(scenarios.train, setting.n_steps, n_state), 0.0)
    resources.check_fits(
        est,
        f"a gradient step over {scenarios.train} training scenarios of {setting.n_steps} steps",
        "lower the training scenarios ([tune.scenarios] train) or the horizon, or raise dt",
    )
    # every scenario set is drawn at once and held for the whole tuning (a held-out set of 1e8
    # scenarios ran into the memory limit with no estimate): its arrays, sized from one scenario
    n_all = scenarios.train + scenarios.validation + scenarios.heldout
    one = jax.eval_shape(lambda k: draw_set(setting, scenarios.mismatch, k), jax.random.split(jax.random.PRNGKey(0), 1))
    per = sum(int(np.prod(x.shape[1:])) * np.dtype(x.dtype).itemsize for x in jax.tree_util.tree_leaves(one))
    resources.check_fits(
        resources.Estimate(SCENARIO_COPIES * n_all * (per + KEY_BYTES), 0.0),
        f"drawing {n_all} scenarios (training {scenarios.train}, validation {scenarios.validation}, "
        f"held-out {scenarios.heldout}) of {per} bytes each",
        "lower [tune.scenarios] train, validation or heldout",
    )


def tune(
    setting,
    family: GainFamily,
    optimizer: optax.GradientTransformation,
    *,
    steps: int,
    scenarios: Scenarios = Scenarios(),
    loss: LossWeights = LossWeights(),
    stopping: Stopping = Stopping(),
    seed: int = 0,
    out_dir=None,
    run_id: str = "",
    log: Callable = print,
    stop_after: int | None = None,
    on_built: Callable | None = None,
    requirement=None,
) -> TuneResult:
    """Tune the gains of a problem's controller by gradient descent through its runs.

    The optimizer steps on the mean loss of the valid training scenarios (with
    ``scenarios.resample``, a fresh batch every step; the recorded training objective is then
    that of the fixed training set the baselines use). Every ``stopping.eval_every`` steps the
    validation scenarios decide early stopping and which parameters are returned
    (``best_raw``). The held-out scenarios are not used here.

    Args:
      setting: the problem's :class:`wmrjax.problem.Setting` (one value of every axis).
      family: the tuned gains (:class:`wmrjax.tune.GainFamily`); the run starts from the problem's
        ``[gains]`` (:func:`initial_raw`).
      optimizer: any ``optax.GradientTransformation`` (e.g. :meth:`wmrjax.tune.Optimizer.build`).
      steps: optimizer steps.
      scenarios: the scenario sets' sizes (:class:`wmrjax.tune.Scenarios`).
      loss: the loss's weights (:class:`wmrjax.tune.LossWeights`).
      stopping: when to stop (:class:`wmrjax.tune.Stopping`).
      seed: PRNG seed of the scenario sets and the resampled batches.
      out_dir: where ``checkpoint.json`` lives (None: no checkpointing).
      run_id: mixed into the checkpoint's fingerprint (the optimizer is not inspected: say what
        it is there).
      log: progress messages.
      stop_after: stop after this many steps of *this* call (to test resumption).
      on_built: called with the :class:`Context` once the scenarios are drawn and a checkpoint
        is read, before the first gradient (the command line compiles its later programs then).
      requirement: a :class:`wmrjax.tune.certified.Requirement` (None: none): every accepted point
        keeps the exact-map radius at or above it (:mod:`wmrjax.tune.certified`: the initial gains
        raised to it first when they miss it, the gradient projected near it, a crossing step
        projected or halved back); each history entry then has the point's ``radius`` and the
        step's ``halvings`` (-1: projected back).

    Returns:
      :class:`TuneResult`.
    """
    ctx, cert_vg, raw, opt_state, run_id = _begin(
        setting, family, optimizer, scenarios, loss, seed, run_id, requirement, log
    )

    update = _update_program(optimizer)
    fp = fingerprint(setting, family, scenarios, loss, stopping, steps, seed, run_id)
    ckpt = Path(out_dir) / "checkpoint.json" if out_dir is not None else None
    start = _start(ckpt, fp, steps, raw, opt_state, log)
    if on_built is not None:
        on_built(ctx)
    return _gradient_loop(
        ctx, setting, family, (update, cert_vg), (ckpt, fp), start, steps, scenarios, stopping, seed, log, stop_after
    )


def _begin(setting, family: GainFamily, optimizer, scenarios, loss, seed: int, run_id: str, requirement, log):
    """The scenarios, the certificate's gradient and the starting point: ``(ctx, cert_vg, raw, opt_state, run_id)``."""
    check_memory(setting, scenarios)
    ctx = prepare(setting, family, scenarios, loss, seed)
    cert_vg = (
        jax.jit(jax.value_and_grad(lambda r: certificate_term(family, r, ctx.certificate)))
        if ctx.certificate is not None
        else None
    )
    raw = initial_raw(setting, family)
    if requirement is not None:
        log(f"requirement ({requirement.slice} slice, the {requirement.loop} loop): the initial gains' radius")
        ctx = ctx._replace(kept=keep(setting, family, requirement, raw))
        run_id += repr(tuple(requirement))
        raw, _ = certified.restore(raw, ctx.kept.radius, ctx.kept.required, log)
    opt_state = optimizer.init(raw)
    return ctx, cert_vg, raw, opt_state, run_id


def _gradient_loop(
    ctx, setting, family, programs, checkpoint, start, steps, scenarios, stopping, seed, log, stop_after
) -> TuneResult:
    """The gradient loop from ``start`` (``(step, raw, opt_state, state)`` of :func:`_start`) on;
    ``programs``: ``(update, cert_vg)``, ``checkpoint``: ``(path or None, fingerprint)``."""
    update, cert_vg = programs
    step, raw, opt_state, state = start
    ckpt, fp = checkpoint
    t0 = time.perf_counter() - state["wall_time_s"]
    done_here = 0
    stream = jax.random.fold_in(jax.random.PRNGKey(seed), 3)
    while step < steps and not state["stopped_early"]:
        batch = (
            _draw_batch(setting, scenarios.mismatch, jax.random.fold_in(stream, step), scenarios.train)
            if scenarios.resample
            else ctx.sets.train
        )
        val, grad, ok, _ = _gradient_step(raw, batch, setting, family, ctx.weights)
        c_val, c_grad = cert_vg(raw) if cert_vg is not None else (0.0, None)
        grad = grad if c_grad is None else grad + c_grad
        rec = _record(ctx, step, raw, val, ok, c_val, state, stopping, steps, scenarios.resample)
        state["history"].append(rec)
        if ctx.kept is None:
            raw, opt_state = update(grad, opt_state, raw)
        else:
            raw, opt_state = _kept_step(ctx.kept, update, grad, opt_state, raw, rec)
        step += 1
        done_here += 1
        state["wall_time_s"] = time.perf_counter() - t0
        _log_step(log, family, rec, step, steps, state["wall_time_s"])
        if ckpt is not None:
            save_checkpoint(ckpt, fp, step, raw, opt_state, state)
        if stop_after is not None and done_here >= stop_after:
            break
    finished = step >= steps or state["stopped_early"]
    return TuneResult(
        finished,
        np.asarray(raw),
        np.asarray(state["best_raw"]),
        state["history"],
        state["rollouts"],
        state["excluded"],
        state["stopped_early"],
        state["wall_time_s"],
        ctx,
    )


def _update_program(optimizer):
    """``update(grad, opt_state, raw) -> (raw, opt_state)`` as one program (eager, optax's
    update is ~30 small ones)."""

    @jax.jit
    def update(grad, opt_state, raw):
        with jax.numpy_dtype_promotion("standard"):  # optax mixes its int32 step count with floats
            upd, opt_state = optimizer.update(grad, opt_state, raw)
        return optax.apply_updates(raw, upd), opt_state

    return update


def _start(ckpt, fp: str, steps: int, raw, opt_state, log):
    """``(step, raw, opt_state, state)``: a fresh run's, or those of the checkpoint ``ckpt``."""
    if ckpt is not None and ckpt.exists():
        step, raw, opt_state, state = load_checkpoint(ckpt, fp, steps, raw, opt_state)
        log(f"resumed from {ckpt} at step {step}")
        return step, raw, opt_state, state
    state = {
        "history": [],
        "best": None,
        "best_raw": None,
        "since_best": 0,
        "rollouts": 0,
        "excluded": 0,
        "wall_time_s": 0.0,
        "stopped_early": False,
    }
    return 0, raw, opt_state, state


def keep(setting, family: GainFamily, requirement, raw0) -> Kept:
    """The :class:`Kept` of a requirement, its radius function built and its value resolved
    (``"initial"``: the radius at ``raw0``, the initial gains)."""
    radius = certified.radius_function(setting, family, requirement)
    initial = radius.value(jnp.asarray(raw0))
    return Kept(requirement, certified.required_radius(setting, requirement, radius, raw0), radius, initial)


def _kept_step(kept: Kept, update, grad, opt_state, raw, rec: dict):
    """One optimizer step that keeps the requirement: the gradient projected near it, the step
    halved back to it (:mod:`wmrjax.tune.certified`); records the point's radius and the halvings."""
    rad = kept.radius
    r, g_r = rad.value_and_grad(raw) if rad.value_and_grad is not None else (rad.value(raw), None)
    rec["radius"] = r = float(r)
    if rad.detail is not None:  # which bound of the problem certificate binds at this point
        rec["radius_bound_by"] = rad.detail(raw)["bound_by"]
    proposal, opt_state = update(certified.project(grad, r, g_r, kept.required), opt_state, raw)
    raw, _, rec["halvings"] = certified.feasible_step(raw, proposal, rad, kept.required)
    return raw, opt_state


def _record(
    ctx: Context, step: int, raw, val, ok, c_val, state: dict, stopping: Stopping, steps: int, resampled: bool
) -> dict:
    """One step's history entry; updates the run's counts, best parameters and early stopping."""
    setting, family, n = ctx.setting, ctx.family, int(np.size(ok))
    n_ok = int(np.sum(np.asarray(ok)))
    if n_ok == 0:
        raise RuntimeError(f"step {step}: every training scenario failed (non-finite or singular)")
    if resampled:  # the objective on the fixed training set, as the baselines see it (not counted)
        tr, tr_ok, _ = mean_loss(raw, ctx.sets.train, setting, family, ctx.weights)
        total = float(_objective_plus(tr, tr_ok, c_val))
    else:
        total = float(_objective_plus(val, ok, c_val))
    state["rollouts"] += n
    state["excluded"] += n - n_ok
    rec = {
        "step": step,
        "train_loss": total,
        "rollouts": state["rollouts"],
        "excluded": n - n_ok,
        "params": np.asarray(_positive(family, raw)).tolist(),
    }
    if (step + 1) % stopping.eval_every == 0 or step == 0 or step + 1 == steps:
        va, va_ok, _ = validation_loss(raw, ctx.sets.validation, setting, family, ctx.weights)
        va = float(_objective_plus(va, va_ok, c_val))
        rec["validation_loss"] = va
        if state["best"] is None or va < state["best"]:
            state["best"], state["best_raw"], state["since_best"] = va, np.asarray(raw).tolist(), 0
        else:
            state["since_best"] += 1
            if state["since_best"] >= stopping.patience:
                state["stopped_early"] = True
    return rec


def _log_step(log, family, rec, step, steps, wall) -> None:
    """One line per step: the losses and the parameters they were evaluated at (the record's, not
    the update's result: the line printed the next step's parameters beside this step's loss)."""
    shown = np.round(np.asarray(rec["params"]), 3)
    excluded = rec["excluded"]
    log(
        f"step {step:4d}/{steps}  train {rec['train_loss']:.5g}"
        + (f"  validation {rec['validation_loss']:.5g}" if "validation_loss" in rec else "")
        + (f"  {'/'.join(family.names())} {shown.tolist()}" if shown.size <= 12 else f"  {shown.size} parameters")
        + (f"  excluded {excluded}" if excluded else "")
        + f"  ({wall:.1f} s)"
    )
