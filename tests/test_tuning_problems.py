"""Tuning problems: gain schedules and torque-level gains in the tuner, the sampled-data loop
against the continuous one, the baselines (CMA-ES, random search), the shipped problem files
and their bad input (the study's tests: test_tuning_study.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax.cli.tune import baseline_budget
from wmrjax.examples import PROBLEMS, problem_file
from wmrjax.problem import Problem, ProblemError
from wmrjax.tune import GainFamily, baselines, config, loop


def test_schedule_spec_gives_a_schedule_and_starts_at_the_paper_gains():
    spec = GainFamily(2, 3, shared=False, knots=(0.0, 5.0, 10.0))
    assert spec.shape == (3, 2, 3) and spec.size == 18
    raw = spec.init(1.0)
    s = spec.gains(raw)
    assert isinstance(s, w.GainSchedule) and s.shape == (2, 3)
    for t in (0.0, 3.7, 10.0):  # (s + 1)^3 at every time
        np.testing.assert_allclose(s.coeffs_at(t), [[1.0, 3.0, 3.0]] * 2, rtol=1e-12)
    bumped = raw.at[1, 0, 0].add(0.5)  # omega of output 1 at the middle knot
    c = np.asarray(spec.gains(bumped).coeffs_at(5.0))
    assert c[0, 0] > 1.0 and np.allclose(c[1], [1.0, 3.0, 3.0])
    np.testing.assert_allclose(spec.gains(bumped).coeffs_at(0.0), [[1.0, 3.0, 3.0]] * 2, rtol=1e-12)
    shared = GainFamily(2, 2, knots=(0.0, 1.0))  # one schedule for both outputs
    np.testing.assert_allclose(shared.coefficients(shared.init(1.0)), [[[1.0, 2.0]] * 2] * 2, rtol=1e-12)
    assert shared.gains(shared.init(1.0)).shape == (2, 2)
    floor = GainFamily(2, 2, min_damping=0.5)
    np.testing.assert_allclose(floor.positive(floor.init(1.0)), [1.0, 1.0], rtol=1e-12)
    assert float(floor.positive(jnp.array([0.0, -50.0]))[1]) >= 0.5
    with pytest.raises(ValueError, match="knots must be >= 2"):
        GainFamily(2, 2, knots=(0.0,))
    with pytest.raises(ValueError, match="damping parameterization"):
        GainFamily(2, 2, knots=(0.0, 1.0), parameterization="poles")


@pytest.mark.parametrize("level", ["velocity", "torque"])
def test_sampled_loop_tracks_the_continuous_loop(level):
    """(2,0), nominal plant, no noise, a 100 Hz hold: the digital controller's loop (at torque level
    lifting the measured wheel velocities) follows the continuous closed loop to the hold's first
    order error, its first sample's command is the continuous law's, and halving the period
    halves the difference (first order)."""
    ctrl = w.dynamic_linearization("(2,0)", level)
    p = ctrl.params(w.references.paper_62(), poles=1.0, geometry=w.Geometry())
    z0 = ctrl.reference_state(0.0, p).at[0].add(0.2).at[1].add(-0.1)
    tr = w.simulate(ctrl, z0, p, dt=0.005, n_steps=400)
    errs = []
    for steps in (2, 1):
        loop_ = w.sampled(ctrl, steps)
        sp = loop_.params(p)
        ts = w.simulate(loop_, loop_.initial_state(z0, sp), sp, dt=0.005, n_steps=400, save_every=steps)
        assert not bool(ts.diagnostics.failed)
        X = np.asarray(ts.state.plant[:, :3])
        errs.append(np.abs(X - np.asarray(tr.state[::steps, :3])).max())
        np.testing.assert_allclose(np.asarray(ts.state.command[0]), np.asarray(tr.control[0]), rtol=1e-10)
    assert 1e-4 < errs[0] < 1e-2  # the hold's first-order error (6.1e-3, 1.5e-3 measured)
    assert 1.9 < errs[0] / errs[1] < 2.1  # first order in the period (2.00 measured)


def test_sampled_loop_refuses_and_checks():
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    p = ctrl.params(w.references.paper_62(), poles=1.0, geometry=w.Geometry())
    loop_ = w.sampled(ctrl, 5)
    sp = loop_.params(p)
    z0 = loop_.initial_state(ctrl.reference_state(0.0, p), sp)
    with pytest.raises(ValueError, match="whole controller periods of 5 steps"):
        w.simulate(loop_, z0, sp, dt=0.01, n_steps=12)
    with pytest.raises(ValueError, match=r"noise must have shape \(n_samples, 3\)"):
        loop_.params(p, noise=np.zeros((4, 2)))
    with pytest.raises(ValueError, match="needs a dynamic law"):
        w.sampled(w.controller("(3,0)", level="torque", task="posture"), 2)
    with pytest.raises(ValueError, match="steps_per_sample"):
        w.sampled(ctrl, 0)


def test_sampled_loop_fails_frozen_at_the_last_good_state():
    """A NaN in the measurement at sample 10 (under jit, where the eager check of the noise
    cannot run) fails the run at t = 10 periods; its final state is the state before that sample:
    the plant at t = 0.25 s and the controller's records of sample 9, all finite (the sample's
    NaN command, rate and regularity used to be frozen into it)."""
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    p = ctrl.params(w.references.paper_62(), poles=1.0, geometry=w.Geometry())
    loop_ = w.sampled(ctrl, 5)
    z0 = loop_.initial_state(ctrl.reference_state(0.0, p).at[0].add(0.2), loop_.params(p))
    noise = np.zeros((80, 3))
    noise[10, 2] = np.nan
    run = jax.jit(lambda nz: w.simulate(loop_, z0, loop_.params(p, noise=nz), dt=0.005, n_steps=400, save_every=5))
    ts = run(noise)
    d = ts.diagnostics
    assert bool(d.failed) and bool(d.nonfinite) and float(d.t_failure) == pytest.approx(0.25, rel=1e-12)
    assert np.asarray(ts.valid).nonzero()[0][-1] == 9
    f = ts.final_state
    assert all(np.all(np.isfinite(x)) for x in jax.tree_util.tree_leaves(f))
    np.testing.assert_array_equal(f.plant, ts.state.plant[10])
    np.testing.assert_array_equal(f.command, ts.state.command[9])
    np.testing.assert_array_equal(f.regularity, ts.state.regularity[9])


def test_cma_es_and_random_search_on_a_known_quadratic():
    """A quadratic with its minimum at raw = (0.3, -0.2): CMA-ES gets within 1e-3, random search
    samples inside its box and keeps frozen entries; the accounting is n_train per candidate."""
    spec = GainFamily(1, 2)
    target = np.array([0.3, -0.2])
    evaluate = lambda raws: np.sum((np.asarray(raws).reshape(-1, 2) - target) ** 2, axis=1)
    run = baselines.cma_es(
        spec, evaluate, np.zeros(2), budget_rollouts=8 * 60 * 4, n_train=4, seed=1, population=8, sigma=0.5
    )
    assert run.rollouts == 8 * 60 * 4 and len(run.best_so_far) == 480 and run.best_loss < 1e-6
    assert run.rollouts_to_best == 4 * (1 + int(np.argmin(run.best_so_far)))
    np.testing.assert_allclose(run.best_raw, target, atol=1e-3)
    frozen = GainFamily(1, 2, frozen=(1,))
    rs = baselines.random_search(
        frozen, evaluate, np.array([0.0, 0.7]), budget_rollouts=40, n_train=4, seed=0, low=0.2, high=5.0
    )
    assert rs.rollouts == 40 and len(rs.best_so_far) == 10
    assert rs.best_raw[1] == 0.7  # the frozen damping stayed
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


def test_shipped_problems_and_bad_tuning_problems(tmp_path):
    assert {"section_6_1", "section_6_1_plant", "s_path", "car_schedule", "torque_2_1"} <= set(PROBLEMS)
    car = Problem.load(problem_file("car_schedule"))
    setting = car.setting("tuning")
    ts = config.read(car.section("tune"))
    assert setting.ctrl.robot.name == "(1,1)" and ts.gain_family(setting).size == 24
    assert Problem.load(problem_file("torque_2_1")).setting("tuning").ctrl.level == "torque"
    with pytest.raises(ValueError, match="problem must be a file or one of"):
        problem_file("car")
    with pytest.raises(ProblemError, match="at least 2 knots"):
        config.read(car.with_values({"tune.family.knots": 1}).section("tune"))
    with pytest.raises(ProblemError, match=r"knot_times: expected >= 2 strictly increasing"):
        config.read(car.with_values({"tune.family.knot_times": [0.0, 5.0, 5.0]}).section("tune"))
    with pytest.raises(ValueError, match="reach beyond the horizon"):
        loop.check(setting, GainFamily(2, 3, knots=(0.0, 5.0, 12.0)), ts.scenarios, ts.loss)
    with pytest.raises(ValueError, match="certificate term needs a dynamic .* fixed reference"):
        loop.check(setting, ts.gain_family(setting), ts.scenarios, ts.loss._replace(certificate=1.0))
    s61 = Problem.load(problem_file("section_6_1_plant"))
    ts61 = config.read(s61.with_values({"tune.baselines.budget": 0.01}).section("tune"))
    with pytest.raises(ValueError, match="less than one CMA-ES generation"):
        baseline_budget(ts61, ts61.gain_family(s61.setting("tuning")))
    with pytest.raises(ValueError, match="takes one value of \\[gains\\]"):
        loop.check(
            s61.with_values({"gains.poles": [1.0, 2.0]}).setting("tuning"), GainFamily(2, 2), ts61.scenarios, ts61.loss
        )
    from wmrjax.cli.tune import main

    with pytest.raises(SystemExit):
        main(["car_schedule", "--out", str(tmp_path / "o"), "--set", "tune.family.knots=1"])
    with pytest.raises(SystemExit):
        main([str(tmp_path / "missing.toml"), "--out", str(tmp_path / "o")])


def test_heading_offset_reaches_the_certificate_term():
    """The certificate term's M1 is that of the problem's own reference, heading offset included
    (the tuner used to rebuild the reference without it): with an output point that depends on
    theta (e != 0) the two differ, and the term's equals wmrjax.certify's for the problem."""
    from wmrjax import certify
    from wmrjax import references as R

    problem = Problem.load(problem_file("section_6_1_plant")).with_values(
        {
            "controller.robot": "(1,1)",
            "geometry.e": 0.3,
            "reference": {"family": "figure_eight", "heading_offset": 0.4},
            "plant.noise_std": [0.01, 0.01, 0.005, 0.005],
            "tune.loss.certificate": 1.0,
        }
    )
    setting = problem.setting("tuning")
    cert = loop.certificate(setting, 1.0)
    params = setting.params()
    assert float(params.reference.heading_offset) == 0.4
    np.testing.assert_allclose(
        np.asarray(cert.m1), np.asarray(certify.m1_closed_form(setting.ctrl, params, cert.ts)), rtol=1e-14
    )
    without = setting.ctrl.params(R.figure_eight(), geometry=params.geometry)  # what the old term used
    other = np.asarray(certify.m1_closed_form(setting.ctrl, without, cert.ts))
    assert np.max(np.abs(other - np.asarray(cert.m1))) > 1e-3
