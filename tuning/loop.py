"""The tuning loop: optax on the pole parameters through batched sampled-data rollouts,
with a held-out split, early stopping, atomic JSON checkpoints, and baselines (the
paper's gains and a random search given the same rollout budget)."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

import wmrjax as w
from wmrjax import references as R
from wmrjax import io
from tuning.gains import GainSpec
from tuning.losses import LossWeights, certificate_radius, scenario_loss
from tuning.scenarios import RolloutConfig, Scenario, rollout

# the programs that run a few times in a run (scenario draws, validation, figures, reports)
# compile at XLA's backend optimization level 0: 1.5-2.4x faster (section 6.1: the scenario
# sets 1.21 -> 0.51 s, the validation 1.00 -> 0.65 s), with no measurable change in the
# scenario draws' run time (1 ms) and 2 -> 5 ms for a validation; their numbers differ from
# level 2's by rounding (the scenario sets by at most 1.3e-15). The gradient and the baselines'
# evaluator, which run thousands of rollouts, compile at LOOP_COMPILE.
QUICK_COMPILE = {"xla_backend_optimization_level": 0}
# the gradient's and the baselines' evaluator's programs compile at level 1: 5-25 % faster than
# at the default 2, and they run as fast or faster (gradient programs, compile / step: section
# 6.1 1.8 -> 1.6 s / 7.0 -> 6.7 ms, torque_2_1 6.9 -> 5.9 s / 17.6 -> 15.9 ms, car_schedule
# 6.8 -> 6.6 s / 16.3 -> 14.8 ms); the same tuned gains and baseline results on section 6.1
LOOP_COMPILE = {"xla_backend_optimization_level": 1}


REFERENCES = ("paper_62", "circle", "figure_eight", "line", "random")
LEVELS = ("velocity", "torque")
FAILURE_PENALTY = 1.0   # added to the objective per unit fraction of scenarios that failed (singular/non-finite)


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """Everything a tuning run depends on (its JSON form fingerprints checkpoints)."""

    robot: str = "(2,0)"
    task: str = "posture"               # posture: dynamic (restricted) / static (3,0); point: static Table 3
    reference: str = "paper_62"         # paper_62 | circle | figure_eight | line | random
    geometry: tuple = (1.0, 0.0, 0.0)   # nominal (L, e, delta) the controller uses
    n_train: int = 64
    n_heldout: int = 64
    poles_init: float = 1.0             # the paper's gains: every pole at -1
    shared: bool = True
    frozen: tuple = ()
    weights: tuple = tuple(LossWeights())
    steps: int = 40
    learning_rate: float = 0.3
    clip: float = 1.0
    patience: int = 6                   # held-out evaluations without improvement before stopping
    eval_every: int = 5
    seed: int = 0
    mismatch: float = 0.1               # +- relative error on input scales, e and L
    input_limit: tuple = (5.5, 1.0)     # |input_i| <= limit_i in the plant (empty: none)
    noise_std: tuple = (0.01, 0.01, 0.005)
    ic_position: float = 0.5            # +- initial position error [m]
    ic_velocity: float = 0.5            # +- initial velocity error [m/s] (dynamic laws)
    t_final: float = 10.0
    control_dt: float = 0.05
    substeps: int = 5
    search_low: float = 0.2             # random search: omega / real poles log-uniform in [low, high],
    search_high: float = 5.0            # damping log-uniform in [0.3, 3]
    parameterization: str = "damping"   # or "poles" (real poles only)
    problem: str = "section_6_1"        # the preset this configuration came from (tuning.problems)
    level: str = "velocity"             # velocity (kinematic model 5) or torque (Lemma 1, measured velocities)
    heading_offset: float = 0.0         # reference heading offset [rad] (a crab angle where the type needs one)
    knots: int = 0                      # gain schedule: K >= 2 knots uniform on [0, t_final]; 0: constant gains
    knot_times: tuple = ()              # explicit knot times [s] (overrides knots)
    n_validation: int = 32              # scenarios for early stopping and selection (not the held-out ones)
    baseline_seeds: int = 5             # seeds of each baseline (random search, CMA-ES)
    baseline_budget: float = 1.0        # baseline rollouts as a multiple of the gradient's
    cma_population: int = 0             # CMA-ES population (0: 4 + floor(3 ln n))
    cma_sigma: float = 0.5              # CMA-ES initial step in the unconstrained parameters
    min_damping: float = 0.0            # floor of every damping zeta (damping parameterization)
    ref_speed: float = 1.0              # random references: mean speed [m/s]
    ref_min_speed: float = 0.3          # random references: speed floor [m/s]
    resample: bool = False              # fresh training scenarios every gradient step (stochastic gradient)

    def schedule_times(self) -> tuple:
        """The knot times [s] of the gain schedule, () for constant gains."""
        if self.knot_times:
            return tuple(float(t) for t in self.knot_times)
        if self.knots:
            return tuple(float(t) for t in np.linspace(0.0, self.t_final, self.knots))
        return ()

    def check(self) -> "TuneConfig":
        if self.n_train < 1 or self.n_heldout < 1:
            raise ValueError(f"the scenario batch is empty: n_train = {self.n_train}, n_heldout = {self.n_heldout} "
                             "(both must be >= 1)")
        if not (np.isfinite(self.poles_init) and self.poles_init > 0):
            raise ValueError(f"poles_init must be > 0 (poles at -poles_init), got {self.poles_init}")
        LossWeights(*self.weights).check()
        for k in ("learning_rate", "t_final", "control_dt", "clip"):
            if not (np.isfinite(getattr(self, k)) and getattr(self, k) > 0):
                raise ValueError(f"{k} must be finite and > 0, got {getattr(self, k)}")
        if self.steps < 1 or self.substeps < 1 or self.eval_every < 1:
            raise ValueError("steps, substeps and eval_every must be >= 1")
        if not 0 <= self.mismatch < 1:
            raise ValueError(f"mismatch must be in [0, 1), got {self.mismatch}")
        if self.parameterization not in ("damping", "poles"):
            raise ValueError(f"parameterization must be 'damping' or 'poles', got {self.parameterization!r}")
        if not 0 < self.search_low < self.search_high:
            raise ValueError("random search range must satisfy 0 < search_low < search_high")
        if self.reference not in REFERENCES:
            raise ValueError(f"reference must be one of {REFERENCES}, got {self.reference!r}")
        if len(self.geometry) != 3 or not np.all(np.isfinite(np.asarray(self.geometry, float))):
            raise ValueError(f"geometry must be three finite numbers (L [m], e [m], delta [rad]), got {self.geometry}")
        lim = np.asarray(self.input_limit, float)
        if lim.size and not np.all(lim > 0):
            raise ValueError(f"input_limit must be > 0 per input (inf: none), got {self.input_limit}")
        noise = np.asarray(self.noise_std, float)
        if noise.size and not (np.all(np.isfinite(noise)) and np.all(noise >= 0)):
            raise ValueError(f"noise_std must be finite and >= 0 [m, m, rad], got {self.noise_std}")
        for k in ("ic_position", "ic_velocity"):
            if not (np.isfinite(getattr(self, k)) and getattr(self, k) >= 0):
                raise ValueError(f"{k} must be finite and >= 0, got {getattr(self, k)}")
        if self.control_dt > self.t_final:
            raise ValueError(f"control_dt = {self.control_dt} s is longer than the horizon t_final = {self.t_final} s")
        if self.control_dt * self.poles_init > 0.5:
            raise ValueError(f"control_dt = {self.control_dt} s is too long for poles at -{self.poles_init} 1/s: the "
                             f"zero-order-hold loop needs control_dt * pole <= 0.5 (here {self.control_dt * self.poles_init:.3g}); "
                             "shorten control_dt")
        if not 0 <= self.seed < 2**32:
            raise ValueError(f"seed must be an integer in [0, 2**32), got {self.seed}")
        from tuning.problems import PROBLEMS

        if self.problem not in PROBLEMS:
            raise ValueError(f"problem must be one of {sorted(PROBLEMS)}, got {self.problem!r}")
        if self.level not in LEVELS:
            raise ValueError(f"level must be one of {LEVELS}, got {self.level!r}")
        if self.knots == 1 or self.knots < 0 or len(self.knot_times) == 1:
            raise ValueError(f"a gain schedule needs at least 2 knots, got knots = {self.knots}, knot_times = "
                             f"{list(self.knot_times)} (0 knots: constant gains)")
        kt = np.asarray(self.schedule_times(), float)
        if kt.size and (not np.all(np.isfinite(kt)) or np.any(np.diff(kt) <= 0) or kt[0] < 0 or kt[-1] > self.t_final):
            raise ValueError(f"knot_times must be strictly increasing and inside the horizon [0, {self.t_final}] s, "
                             f"got {kt.tolist()}")
        if kt.size and self.parameterization != "damping":
            raise ValueError("a gain schedule needs parameterization 'damping'")
        if self.n_validation < 1:
            raise ValueError(f"n_validation must be >= 1 (early stopping needs scenarios), got {self.n_validation}")
        if self.baseline_seeds < 1:
            raise ValueError(f"baseline_seeds must be >= 1, got {self.baseline_seeds}")
        if not (np.isfinite(self.baseline_budget) and self.baseline_budget > 0):
            raise ValueError(f"baseline_budget must be > 0 (a multiple of the gradient's rollouts), got "
                             f"{self.baseline_budget}")
        if self.cma_population != 0 and self.cma_population < 2:
            raise ValueError(f"cma_population must be >= 2 (CMA-ES ranks its candidates; 0: its default), "
                             f"got {self.cma_population}")
        if not (np.isfinite(self.cma_sigma) and self.cma_sigma > 0):
            raise ValueError(f"cma_sigma must be > 0, got {self.cma_sigma}")
        if not (np.isfinite(self.min_damping) and 0 <= self.min_damping < 1):
            raise ValueError(f"min_damping must be in [0, 1) (the paper's double pole has zeta = 1), got {self.min_damping}")
        if not 0 < self.ref_min_speed < self.ref_speed:
            raise ValueError(f"random references need 0 < ref_min_speed < ref_speed [m/s], got {self.ref_min_speed}, "
                             f"{self.ref_speed}")
        if not np.isfinite(self.heading_offset):
            raise ValueError(f"heading_offset must be finite [rad], got {self.heading_offset}")
        return self

    def baseline_rollouts(self) -> int:
        """Rollout budget of one baseline run: baseline_budget times the gradient's (steps x n_train)."""
        return int(round(self.baseline_budget * self.steps * self.n_train))

    def population(self, n_parameters: int) -> int:
        """CMA-ES population for n tuned parameters (the default of Hansen's CMA-ES)."""
        return self.cma_population or 4 + int(np.floor(3 * np.log(n_parameters)))

    def fingerprint(self) -> str:
        return hashlib.sha256(json.dumps(dataclasses.asdict(self), sort_keys=True).encode()).hexdigest()[:16]


# --- set-up ----------------------------------------------------------------------------

def validate(cfg: TuneConfig):
    """Check everything about a configuration that does not need a compiled rollout; returns the
    controller. ValueError naming the setting otherwise (the robot type, the task, a geometry
    the law excludes, the number of actuator limits and noise levels)."""
    cfg.check()
    ctrl = w.controller(cfg.robot, cfg.level, cfg.task)
    nX, nu = ctrl.robot.n_state, ctrl.robot.n_input
    if cfg.input_limit and len(cfg.input_limit) != nu:
        raise ValueError(f"input_limit needs {nu} entries for type {ctrl.robot.name}, got {cfg.input_limit}")
    if len(cfg.noise_std) not in (0, 3, nX):
        raise ValueError(f"noise_std needs 3 or {nX} entries, got {cfg.noise_std}")
    ref = R.line() if cfg.reference == "random" else R.named(cfg.reference)
    if cfg.heading_offset:
        ref = ref.with_heading_offset(cfg.heading_offset)
    ctrl.params(ref, poles=cfg.poles_init, geometry=w.Geometry(*cfg.geometry))   # geometry and reference rules
    if LossWeights(*cfg.weights).certificate > 0 and (cfg.reference == "random"
                                                      or not isinstance(ctrl, w.DynamicLinearization)):
        raise ValueError("the certificate term needs a dynamic (posture) controller of type (2,0), (2,1) or (1,1) "
                         "and a named reference")
    if cfg.level == "torque" and not isinstance(ctrl, w.DynamicLinearization):
        raise ValueError("torque-level tuning needs a dynamic (posture) controller: its state carries the measured "
                         "wheel velocities (task 'posture' on type (2,0), (2,1), (1,1) or (1,2))")
    n = GainSpec(ctrl.m, ctrl.relative_degree, cfg.shared, tuple(cfg.frozen), cfg.parameterization,
                 cfg.schedule_times(), cfg.min_damping).size
    pop = cfg.population(n)
    if cfg.baseline_rollouts() < pop * cfg.n_train:
        raise ValueError(f"baseline_budget = {cfg.baseline_budget} gives {cfg.baseline_rollouts()} rollouts, less than "
                         f"one CMA-ES generation ({pop} candidates x {cfg.n_train} scenarios = {pop * cfg.n_train}); "
                         "raise baseline_budget or steps, or lower cma_population")
    return ctrl


def build(cfg: TuneConfig):
    """(controller, gain spec, nominal geometry, rollout config, train and held-out scenarios)."""
    ctrl = validate(cfg)
    spec = GainSpec(ctrl.m, ctrl.relative_degree, cfg.shared, tuple(cfg.frozen), cfg.parameterization,
                    cfg.schedule_times(), cfg.min_damping)
    spec.init(cfg.poles_init)
    g = w.Geometry(*cfg.geometry)
    rcfg = RolloutConfig(cfg.t_final, cfg.control_dt, cfg.substeps)
    train, validation, heldout = _scenario_sets(ctrl, cfg, g, jax.random.PRNGKey(cfg.seed))
    return ctrl, spec, g, rcfg, train, validation, heldout


@functools.partial(jax.jit, static_argnums=(0, 1), compiler_options=QUICK_COMPILE)
def _scenario_sets(ctrl, cfg: TuneConfig, g, key):
    """The training, validation and held-out scenarios of ``cfg``, drawn by one vmapped program
    (the same draws as :func:`make_scenarios` of each set's key and size)."""
    k_tr, k_ho = jax.random.split(key)
    sizes = (cfg.n_train, cfg.n_validation, cfg.n_heldout)
    keys = jnp.concatenate([jax.random.split(k, n) for k, n in
                            zip((k_tr, jax.random.fold_in(key, 2), k_ho), sizes)])
    every = scenarios_from_keys(ctrl, cfg, g, keys)
    ends = np.cumsum(sizes)
    return tuple(jax.tree_util.tree_map(lambda x: x[e - n:e], every) for n, e in zip(sizes, ends))


def _reference(cfg, key):
    if cfg.reference == "random":
        ref = R.random_smooth(key, n_modes=3, speed=cfg.ref_speed, min_speed=cfg.ref_min_speed, max_omega=0.6,
                              start_scale=2.0)
    else:
        ref = R.named(cfg.reference)
    return ref.with_heading_offset(cfg.heading_offset) if cfg.heading_offset else ref


def _draw(ctrl, cfg, g, key):
    """A fresh training batch (``resample``): n_train scenarios from ``key``."""
    return _scenarios(ctrl, cfg, g, key, cfg.n_train)


def make_scenarios(ctrl, cfg: TuneConfig, g, key, n) -> Scenario:
    """n scenarios: initial errors x references x geometry/input-scale mismatch x noise keys."""
    return scenarios_from_keys(ctrl, cfg, g, jax.random.split(key, n))


def scenarios_from_keys(ctrl, cfg: TuneConfig, g, keys) -> Scenario:
    """One scenario per key of ``keys`` (N keys -> N scenarios, batched along axis 0)."""
    nX, nu = ctrl.robot.n_state, ctrl.robot.n_input
    limit = jnp.full(nu, jnp.inf)
    if cfg.input_limit:                 # lengths checked by validate()
        limit = jnp.asarray(cfg.input_limit, float)
    noise = jnp.zeros(nX).at[: len(cfg.noise_std)].set(jnp.asarray(cfg.noise_std, float))

    def one(k):
        kr, ki, kv, km, kn = jax.random.split(k, 5)
        ref = _reference(cfg, kr)
        params = ctrl.params_unchecked(ref, 1.0, g)
        if isinstance(ctrl, w.DynamicLinearization):       # dynamic law: perturb the output jet, Psi^-1
            r = ctrl.relative_degree
            zeta = ctrl.reference_jet(0.0, params)[:r]
            zeta = zeta.at[0, :2].add(jax.random.uniform(ki, (2,), minval=-1, maxval=1) * cfg.ic_position)
            zeta = zeta.at[1, :2].add(jax.random.uniform(kv, (2,), minval=-1, maxval=1) * cfg.ic_velocity)
            z0 = ctrl.inverse_psi(zeta, params, float(ctrl.reference_branch(params)))
        else:
            post = ref.posture(0.0)
            X = jnp.zeros(nX).at[:3].set(post)
            if params.steering is not None:
                X = X.at[nX - 1].set(params.steering(0.0))
            X = X.at[:2].add(post[:2] - ctrl.outputs(X, params)[:2])
            z0 = X.at[:2].add(jax.random.uniform(ki, (2,), minval=-1, maxval=1) * cfg.ic_position)
        rho = jax.random.uniform(km, (nu + 2,), minval=-cfg.mismatch, maxval=cfg.mismatch)
        pg = w.Geometry(L=g.L * (1 + rho[nu]), e=g.e * (1 + rho[nu + 1]), delta=g.delta)
        return Scenario(z0, ref, pg, 1.0 + rho[:nu], limit, noise, kn)

    return jax.vmap(one)(keys)


# --- compiled pieces (module level: repeated runs with one configuration reuse them) ---------

# one program per (controller, configuration, count); eager, the scenario construction
# dispatched a few hundred small operations, each compiled on its first use
_scenarios = jax.jit(make_scenarios, static_argnums=(0, 1, 4))

def _per_scenario(raw, sc, ctrl, spec, g, rcfg, w_arr):
    m = rollout(ctrl, spec.gains(raw), g, sc, rcfg)
    return scenario_loss(m, LossWeights(*w_arr)), m


def _batch_value_and_grad(raw, scen, ctrl, spec, g, rcfg, w_arr):
    """Mean loss and gradient over the scenarios that stayed valid; NaN scenarios are excluded.

    Per-scenario gradients (vmapped) so a scenario whose value or gradient is not finite is
    dropped from both, never averaged in. :func:`wmrjax.value_and_grad` picks the mode: forward
    sensitivities for a few gain parameters (the default families), reverse mode for many.
    """
    vg = jax.vmap(w.value_and_grad(_per_scenario, has_aux=True), in_axes=(None, 0, None, None, None, None, None))
    (L, m), G = vg(raw, scen, ctrl, spec, g, rcfg, w_arr)
    ok = m.valid & jnp.isfinite(L) & jnp.all(jnp.isfinite(G.reshape(G.shape[0], -1)), axis=1)
    n = jnp.maximum(jnp.sum(ok), 1).astype(L.dtype)
    loss = jnp.sum(jnp.where(ok, L, 0.0)) / n
    grad = jnp.sum(jnp.where(ok.reshape((-1,) + (1,) * (G.ndim - 1)), G, 0.0), axis=0) / n
    return loss, grad, ok, m


batch_value_and_grad = jax.jit(_batch_value_and_grad, static_argnums=(2, 3, 5))
# the tuning loop's program: the same function at LOOP_COMPILE (a top-level program: JAX takes
# compiler options on the outermost jit only, so the public functions keep the default)
_gradient_step = jax.jit(_batch_value_and_grad, static_argnums=(2, 3, 5), compiler_options=LOOP_COMPILE)


def _batch_value(raw, scen, ctrl, spec, g, rcfg, w_arr):
    """Mean loss (valid scenarios only), validity mask and metrics; forward only."""
    L, m = jax.vmap(_per_scenario, in_axes=(None, 0, None, None, None, None, None))(raw, scen, ctrl, spec, g, rcfg, w_arr)
    ok = m.valid & jnp.isfinite(L)
    return jnp.sum(jnp.where(ok, L, 0.0)) / jnp.maximum(jnp.sum(ok), 1).astype(L.dtype), ok, m


batch_value = jax.jit(_batch_value, static_argnums=(2, 3, 5))
# the validation's program: the same function, compiled quickly (it runs every eval_every steps)
validation_value = jax.jit(_batch_value, static_argnums=(2, 3, 5), compiler_options=QUICK_COMPILE)


def certificate_setup(ctrl, ref_name, g, t_final, eps=1e-2, n_t=501):
    """M1 on a grid for the certificate term (closed form), or None where not available."""
    from wmrjax import certify

    if ref_name == "random" or not isinstance(ctrl, w.DynamicLinearization):
        return None
    params = ctrl.params_unchecked(R.named(ref_name), 1.0, g)
    ts = jnp.linspace(0.0, t_final, n_t)
    return ts, certify.m1_closed_form(ctrl, params, ts), eps


# --- checkpoints --------------------------------------------------------------------------

STATE_KEYS = ("history", "best", "best_raw", "since_best", "rollouts", "excluded", "wall_time_s", "stopped_early")

def save_checkpoint(path: Path, cfg: TuneConfig, step, raw, opt_state, state: dict) -> None:
    """Atomic JSON checkpoint of the tuned parameters, the optimizer state and the history."""
    io.write_checkpoint(path, fingerprint=cfg.fingerprint(), config=dataclasses.asdict(cfg), step=step,
                        trees={"raw": raw, "opt_state": opt_state}, state=state)


def load_checkpoint(path: Path, cfg: TuneConfig, raw_template, opt_state_template):
    """(step, raw, opt_state, state) from a JSON checkpoint; ValueError if it is another configuration's
    or does not match the shapes of this configuration's parameters."""
    try:
        stored = json.loads(Path(path).read_text()).get("config", {}).get("problem")
    except (OSError, ValueError, AttributeError):
        stored = None                   # io.read_checkpoint reports what is wrong with the file
    if stored is not None and stored != cfg.problem:
        raise ValueError(f"checkpoint {path} is from problem {stored!r}, this run is problem {cfg.problem!r}: "
                         "use another --out or --fresh")
    ck = io.read_checkpoint(path, fingerprint=cfg.fingerprint(), config=dataclasses.asdict(cfg),
                            templates={"raw": raw_template, "opt_state": opt_state_template})
    missing = sorted(set(STATE_KEYS) - set(ck.state))
    if missing:
        raise ValueError(f"checkpoint {path} lacks {missing} in its state (an edited or partial checkpoint)")
    if not 0 <= ck.step <= cfg.steps:
        raise ValueError(f"checkpoint {path} is at step {ck.step}, outside [0, {cfg.steps}]")
    return ck.step, ck.trees["raw"], ck.trees["opt_state"], ck.state


# --- the loop -----------------------------------------------------------------------------

def objective(loss, ok):
    """The training objective every method is compared on: the mean loss over the scenarios that
    stayed valid plus :data:`FAILURE_PENALTY` times the fraction that failed."""
    return loss + FAILURE_PENALTY * (1.0 - jnp.mean(ok.astype(loss.dtype)))


# the loop's bookkeeping as programs (eager, each of their operations compiled on first use)
_objective_plus = jax.jit(lambda loss, ok, extra: objective(loss, ok) + extra)
_positive = jax.jit(lambda spec, raw: spec.positive(raw), static_argnums=0)


def tune(cfg: TuneConfig, out_dir=None, log=print, stop_after: int | None = None, on_built=None) -> dict:
    """Run (or resume) a tuning job; returns a dict with gains, histories and counts.

    The optimizer steps on the mean loss of the valid training scenarios (with ``resample``, a
    fresh batch of n_train scenarios every step, and the recorded training objective is that of
    the fixed training set the baselines use); every
    ``eval_every`` steps the validation scenarios decide early stopping and which parameters
    are returned (``best_raw``). The held-out scenarios are not used here.

    Args:
      out_dir: where ``checkpoint.json`` lives (None: no checkpointing).
      stop_after: stop after this many steps of *this* call (to test resumption).
      on_built: called with the dict that is returned (without ``finished``, ``raw``,
        ``best_raw`` and ``state``) once the scenarios are drawn and a checkpoint is read, before
        the first gradient: the command line starts compiling its later programs there, on a
        second thread.
    """
    ctrl, spec, g, rcfg, train, validation, heldout = build(cfg)
    w_arr = jnp.asarray(cfg.weights, float)
    wts = LossWeights(*cfg.weights)
    cert = certificate_setup(ctrl, cfg.reference, g, cfg.t_final) if wts.certificate > 0 else None
    if wts.certificate > 0 and cert is None:
        raise ValueError("the certificate term needs a dynamic (posture) controller of type (2,0), (2,1) or (1,1) "
                         "and a named reference")

    def cert_term(raw):
        if cert is None:
            return jnp.asarray(0.0)
        ts, m1, eps = cert
        return -wts.certificate * certificate_radius(spec.gains(raw), m1, ts, eps)

    built = {"spec": spec, "ctrl": ctrl, "geometry": g, "rcfg": rcfg, "train": train, "validation": validation,
             "heldout": heldout, "w_arr": w_arr, "cert_term": cert_term}
    # the certificate term's value and gradient (none without the term: no program to compile)
    cert_vg = jax.jit(jax.value_and_grad(cert_term)) if cert is not None else None
    opt = optax.chain(optax.clip_by_global_norm(cfg.clip),
                      optax.adam(optax.cosine_decay_schedule(cfg.learning_rate, cfg.steps, alpha=0.1)))
    raw = spec.init(cfg.poles_init)
    opt_state = opt.init(raw)

    @jax.jit
    def update(grad, opt_state, raw):       # one program (eager, optax's update is ~30 small ones)
        with jax.numpy_dtype_promotion("standard"):   # optax mixes its int32 step count with floats
            upd, opt_state = opt.update(grad, opt_state, raw)
        return optax.apply_updates(raw, upd), opt_state

    state = {"history": [], "best": None, "best_raw": None, "since_best": 0, "rollouts": 0, "excluded": 0,
             "wall_time_s": 0.0, "stopped_early": False}
    ckpt = Path(out_dir) / "checkpoint.json" if out_dir is not None else None
    start = 0
    if ckpt is not None and ckpt.exists():
        start, raw, opt_state, state = load_checkpoint(ckpt, cfg, raw, opt_state)
        log(f"resumed from {ckpt} at step {start}")
    if on_built is not None:
        on_built(built)
    t0 = time.perf_counter() - state["wall_time_s"]
    done_here = 0
    step = start
    stream = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), 3)
    while step < cfg.steps and not state["stopped_early"]:
        batch = _draw(ctrl, cfg, g, jax.random.fold_in(stream, step)) if cfg.resample else train
        loss, grad, ok, m = _gradient_step(raw, batch, ctrl, spec, g, rcfg, w_arr)
        c_val, c_grad = cert_vg(raw) if cert_vg is not None else (0.0, None)
        n_ok = int(np.sum(np.asarray(ok)))
        if n_ok == 0:
            raise RuntimeError(f"step {step}: every training scenario failed (non-finite or singular)")
        if cfg.resample:        # the objective on the fixed training set, as the baselines see it (not counted)
            tr, tr_ok, _ = batch_value(raw, train, ctrl, spec, g, rcfg, w_arr)
            total = float(_objective_plus(tr, tr_ok, c_val))
        else:
            total = float(_objective_plus(loss, ok, c_val))
        state["rollouts"] += cfg.n_train
        state["excluded"] += cfg.n_train - n_ok
        rec = {"step": step, "train_loss": total, "rollouts": state["rollouts"], "excluded": cfg.n_train - n_ok,
               "params": np.asarray(_positive(spec, raw)).tolist()}
        if (step + 1) % cfg.eval_every == 0 or step == 0 or step + 1 == cfg.steps:
            va, va_ok, _ = validation_value(raw, validation, ctrl, spec, g, rcfg, w_arr)
            va = float(_objective_plus(va, va_ok, c_val))
            rec["validation_loss"] = va
            if state["best"] is None or va < state["best"]:
                state["best"], state["best_raw"], state["since_best"] = va, np.asarray(raw).tolist(), 0
            else:
                state["since_best"] += 1
                if state["since_best"] >= cfg.patience:
                    state["stopped_early"] = True
        state["history"].append(rec)
        raw, opt_state = update(grad if c_grad is None else grad + c_grad, opt_state, raw)
        step += 1
        done_here += 1
        state["wall_time_s"] = time.perf_counter() - t0
        shown = np.round(np.asarray(_positive(spec, raw)), 3)
        log(f"step {step:4d}/{cfg.steps}  train {total:.5g}"
            + (f"  validation {rec['validation_loss']:.5g}" if "validation_loss" in rec else "")
            + (f"  {'/'.join(spec.names())} {shown.tolist()}" if shown.size <= 12 else f"  {shown.size} parameters")
            + (f"  excluded {cfg.n_train - n_ok}" if n_ok < cfg.n_train else "") + f"  ({state['wall_time_s']:.1f} s)")
        if ckpt is not None:
            save_checkpoint(ckpt, cfg, step, raw, opt_state, state)
        if stop_after is not None and done_here >= stop_after:
            break
    finished = step >= cfg.steps or state["stopped_early"]
    return {"finished": finished, "raw": np.asarray(raw), "best_raw": np.asarray(state["best_raw"]),
            "state": state, **built}
