"""Tuning problems: gain schedules and torque-level gains in the tuner, the sampled-data
torque loop with measured velocities, the baselines (CMA-ES, random search), the presets'
bad input, and the study's aggregation."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from tuning import GainSpec, TuneConfig, baselines, preset
from tuning.loop import load_checkpoint, validate
from tuning.scenarios import RolloutConfig, Scenario, rollout
from tuning.study import aggregate

TINY = TuneConfig(n_train=3, n_heldout=2, n_validation=2, steps=6, t_final=2.0, control_dt=0.1, substeps=2,
                  eval_every=2, baseline_seeds=2)


def test_schedule_spec_gives_a_schedule_and_starts_at_the_paper_gains():
    spec = GainSpec(2, 3, shared=False, knots=(0.0, 5.0, 10.0))
    assert spec.shape == (3, 2, 3) and spec.size == 18
    raw = spec.init(1.0)
    s = spec.gains(raw)
    assert isinstance(s, w.GainSchedule) and s.shape == (2, 3)
    for t in (0.0, 3.7, 10.0):                                       # (s + 1)^3 at every time
        np.testing.assert_allclose(s.coeffs_at(t), [[1.0, 3.0, 3.0]] * 2, rtol=1e-12)
    bumped = raw.at[1, 0, 0].add(0.5)                                # omega of output 1 at the middle knot
    c = np.asarray(spec.gains(bumped).coeffs_at(5.0))
    assert c[0, 0] > 1.0 and np.allclose(c[1], [1.0, 3.0, 3.0])
    np.testing.assert_allclose(spec.gains(bumped).coeffs_at(0.0), [[1.0, 3.0, 3.0]] * 2, rtol=1e-12)
    shared = GainSpec(2, 2, knots=(0.0, 1.0))                         # one schedule for both outputs
    np.testing.assert_allclose(shared.coefficients(shared.init(1.0)), [[[1.0, 2.0]] * 2] * 2, rtol=1e-12)
    assert shared.gains(shared.init(1.0)).shape == (2, 2)
    floor = GainSpec(2, 2, min_damping=0.5)
    np.testing.assert_allclose(floor.positive(floor.init(1.0)), [1.0, 1.0], rtol=1e-12)
    assert float(floor.positive(jnp.array([0.0, -50.0]))[1]) >= 0.5
    with pytest.raises(ValueError, match="knots must be >= 2"):
        GainSpec(2, 2, knots=(0.0,))
    with pytest.raises(ValueError, match="damping parameterization"):
        GainSpec(2, 2, knots=(0.0, 1.0), parameterization="poles")


def test_torque_rollout_with_measured_velocities_tracks_the_continuous_loop():
    """(2,0) at torque level, nominal plant, 100 Hz hold: the sampled loop lifting the measured
    wheel velocities follows the continuous closed loop (w.simulate) to the hold's O(dt) error,
    and its velocities are the plant's."""
    ctrl = w.dynamic_linearization("(2,0)", "torque")
    g = w.Geometry()
    ref = w.references.paper_62()
    p = ctrl.params(ref, poles=1.0, geometry=g)
    z0 = ctrl.reference_state(0.0, p).at[0].add(0.2).at[1].add(-0.1)
    nu = ctrl.robot.n_input
    sc = Scenario(z0, ref, g, jnp.ones(nu), jnp.full(nu, jnp.inf), jnp.zeros(3), jax.random.PRNGKey(0))
    rcfg = RolloutConfig(t_final=2.0, control_dt=0.01, substeps=2)
    m, (zs, cmds) = jax.jit(lambda s: rollout(ctrl, p.gains, g, s, rcfg, trajectory=True))(sc)
    tr = w.simulate(ctrl, z0, p, dt=0.01, n_steps=200)
    assert bool(m.valid)
    err = np.abs(np.asarray(zs[:, :3]) - np.asarray(tr.state[:-1, :3])).max()
    assert 1e-5 < err < 5e-3                          # the zero-order hold's first-order error, no more
    np.testing.assert_allclose(np.asarray(cmds[0]), np.asarray(tr.control[0]), rtol=1e-10)


def test_cma_es_and_random_search_on_a_known_quadratic():
    """A quadratic with its minimum at raw = (0.3, -0.2): CMA-ES gets within 1e-3, random search
    samples inside its box and keeps frozen entries; the accounting is n_train per candidate."""
    spec = GainSpec(1, 2)
    target = np.array([0.3, -0.2])
    evaluate = lambda raws: np.sum((np.asarray(raws).reshape(-1, 2) - target) ** 2, axis=1)
    run = baselines.cma_es(spec, evaluate, np.zeros(2), budget_rollouts=8 * 60 * 4, n_train=4, seed=1,
                           population=8, sigma=0.5)
    assert run.rollouts == 8 * 60 * 4 and len(run.best_so_far) == 480 and run.best_loss < 1e-6
    assert run.rollouts_to_best == 4 * (1 + int(np.argmin(run.best_so_far)))
    np.testing.assert_allclose(run.best_raw, target, atol=1e-3)
    frozen = GainSpec(1, 2, frozen=(1,))
    rs = baselines.random_search(frozen, evaluate, np.array([0.0, 0.7]), budget_rollouts=40, n_train=4, seed=0,
                                 low=0.2, high=5.0)
    assert rs.rollouts == 40 and len(rs.best_so_far) == 10
    assert rs.best_raw[1] == 0.7                                     # the frozen damping stayed
    pos = frozen.positive(jnp.asarray(rs.best_raw))
    assert 0.2 <= float(pos[0]) <= 5.0
    with pytest.raises(ValueError, match="less than one generation"):
        baselines.cma_es(spec, evaluate, np.zeros(2), budget_rollouts=10, n_train=4, seed=0, population=8, sigma=0.5)


def test_candidate_evaluator_chunks_pads_and_returns_aux():
    """N candidates in padded chunks give each candidate's own objective; with_aux returns the
    objective function's auxiliary data for the N candidates, stacked; non-finite -> +inf."""
    scen = jnp.arange(3.0)

    def objective(raw, s):
        value = jnp.sum((raw[0] - s) ** 2) + raw[1] ** 2
        return jnp.where(raw[0] > 9.0, jnp.nan, value), (raw[0] * s, raw[1] > 0)

    evaluate = baselines.candidate_evaluator(objective, (2,), chunk=4)
    raws = np.array([[0.0, 1.0], [1.0, -1.0], [2.0, 0.5], [3.0, 2.0], [4.0, -2.0], [10.0, 1.0]])
    expected = np.array([np.sum((r[0] - np.arange(3.0)) ** 2) + r[1] ** 2 for r in raws[:5]] + [np.inf])
    np.testing.assert_allclose(evaluate(raws, scen), expected, rtol=1e-15)
    values, (scaled, positive) = evaluate(raws, scen, with_aux=True)
    np.testing.assert_allclose(values, expected, rtol=1e-15)
    assert scaled.shape == (6, 3) and positive.shape == (6,)
    np.testing.assert_allclose(scaled, raws[:, :1] * np.arange(3.0), rtol=1e-15)
    np.testing.assert_array_equal(positive, raws[:, 1] > 0)
    plain = baselines.candidate_evaluator(lambda raw, s: jnp.sum(raw * s[:2]), (2,))
    with pytest.raises(ValueError, match="with_aux=True needs"):
        plain(raws, scen, with_aux=True)


def test_presets_and_bad_tuning_problems(tmp_path):
    car = preset("car_schedule")
    assert validate(car).robot.name == "(1,1)"
    assert GainSpec(2, 3, shared=False, knots=car.schedule_times()).size == 24
    assert preset("torque_2_1").level == "torque" and preset("section_6_1") == TuneConfig()
    with pytest.raises(ValueError, match="problem must be one of"):
        preset("car")
    with pytest.raises(ValueError, match="at least 2 knots"):
        preset("car_schedule", knots=1)
    with pytest.raises(ValueError, match="inside the horizon"):
        preset("car_schedule", knot_times=(0.0, 5.0, 12.0))
    with pytest.raises(ValueError, match="cma_population must be >= 2"):
        preset("section_6_1", cma_population=1)
    with pytest.raises(ValueError, match="less than one CMA-ES generation"):
        validate(preset("section_6_1", baseline_budget=0.01))
    with pytest.raises(ValueError, match="torque-level tuning needs a dynamic"):
        validate(dataclasses.replace(TINY, robot="(3,0)", level="torque", input_limit=()))
    # a checkpoint written by another problem
    ck = tmp_path / "checkpoint.json"
    ck.write_text(json.dumps({"fingerprint": "x", "config": dataclasses.asdict(preset("torque_2_1")), "step": 1}))
    with pytest.raises(ValueError, match="from problem 'torque_2_1', this run is problem 'section_6_1'"):
        load_checkpoint(ck, TuneConfig(), None, None)
    from tuning.cli import main

    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "o"), "--problem", "car_schedule", "--knots", "1"])


def test_study_aggregate_medians_and_targets():
    rows = []
    for seed, (paper, grad, cma, cma_best, match) in enumerate([(0.09, 0.02, 0.05, 6000, 500),
                                                                (0.06, 0.03, 0.04, 4000, None),
                                                                (0.08, 0.02, 0.06, 5000, 400)]):
        rows += [dict(problem="p", method="paper_gains", seed=seed, heldout_loss=paper, best_train_loss=paper,
                      rollouts_to_best=0, gradient_rollouts_to_match=None, singularity_events=0, wall_time_s=0.0),
                 dict(problem="p", method="gradient", seed=seed, heldout_loss=grad, best_train_loss=grad,
                      rollouts_to_best=1000, gradient_rollouts_to_match=None, singularity_events=0, wall_time_s=1.0),
                 dict(problem="p", method="cma_es", seed=seed, heldout_loss=cma, best_train_loss=cma,
                      rollouts_to_best=cma_best, gradient_rollouts_to_match=match, singularity_events=None,
                      wall_time_s=1.0)]
    a = aggregate(rows)["p"]
    assert a["gradient"]["heldout_loss"] == {"median": 0.02, "min": 0.02, "max": 0.03}
    assert a["cma_es"]["gradient_rollouts_to_match"] == {"median": 500.0, "matched_seeds": 2}   # never = inf
    assert a["cma_es"]["rollout_ratio_baseline_over_gradient"]["median"] == 12.0                # 6000/500, 0, 12.5
    t = a["targets"]
    assert t["heldout_ratio_paper_over_gradient"] == 0.08 / 0.02 and t["heldout_3x_below_paper"]
    assert t["10x_fewer_rollouts_than_cma_es"] and t["heldout_at_or_below_cma_es"] and t["no_more_singularity_events"]
