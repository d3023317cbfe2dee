"""Gain tuning: gradients, a known optimum, resumption, NaN exclusion, bad input."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from tuning import GainSpec, LossWeights, TuneConfig, batch_value, batch_value_and_grad, build, objective, tune
from tuning.losses import scenario_loss

# one small configuration shared by several tests, so its compiled functions are reused
TINY = TuneConfig(n_train=3, n_heldout=2, n_validation=2, steps=6, t_final=2.0, control_dt=0.1, substeps=2, eval_every=2,
                  baseline_seeds=2)


@pytest.fixture(scope="module")
def tiny():
    return build(TINY)


def test_gain_spec_maps_paper_poles_and_is_hurwitz(rng):
    spec = GainSpec(2, 2)
    np.testing.assert_allclose(spec.coefficients(spec.init(1.0)), [[1.0, 2.0]] * 2, atol=1e-12)   # (s + 1)^2
    spec3 = GainSpec(2, 3, shared=False)
    np.testing.assert_allclose(spec3.coefficients(spec3.init([1.0, 2.0, 3.0]))[0], [6.0, 11.0, 6.0], rtol=1e-12)
    for _ in range(10):                                                 # any raw gives a Hurwitz polynomial
        c = np.asarray(spec3.coefficients(jnp.asarray(rng.normal(size=(2, 3)) * 3)))
        for row in c:
            assert np.all(np.roots(np.concatenate([[1.0], row[::-1]])).real < 0)
    frozen = GainSpec(1, 2, frozen=(1,))
    g = jax.grad(lambda r: jnp.sum(frozen.coefficients(r)))(frozen.init(1.0))
    assert g[1] == 0.0 and g[0] != 0.0


def test_loss_gradient_matches_finite_differences(tiny):
    ctrl, spec, g, rcfg, train, _, _ = tiny
    w = jnp.asarray(TINY.weights, float)
    raw = spec.init(1.3) + jnp.array([0.1, -0.2])
    loss, grad, ok, _ = batch_value_and_grad(raw, train, ctrl, spec, g, rcfg, w)
    assert bool(jnp.all(ok))
    h = 1e-5
    for i in range(raw.shape[0]):
        d = jnp.zeros_like(raw).at[i].set(h)
        fd = (batch_value(raw + d, train, ctrl, spec, g, rcfg, w)[0] - batch_value(raw - d, train, ctrl, spec, g, rcfg, w)[0]) / (2 * h)
        np.testing.assert_allclose(float(grad[i]), float(fd), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(float(loss), float(batch_value(raw, train, ctrl, spec, g, rcfg, w)[0]), rtol=1e-12)


def test_constant_schedule_is_the_constant_gains(tiny):
    """The tuner's rollout with a schedule whose knots all hold the paper's gains equals the
    rollout with constant gains (same metrics to rounding): the law reads coeffs_at(t)."""
    ctrl, spec, g, rcfg, train, _, _ = tiny
    sspec = dataclasses.replace(spec, knots=(0.0, 1.0, 2.0))
    wts = jnp.asarray(TINY.weights, float)
    a = batch_value(spec.init(1.0), train, ctrl, spec, g, rcfg, wts)
    b = batch_value(sspec.init(1.0), train, ctrl, sspec, g, rcfg, wts)
    np.testing.assert_allclose(float(b[0]), float(a[0]), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(b[2].tracking), np.asarray(a[2].tracking), rtol=1e-12)


def test_quickly_compiled_programs_match_the_default_ones(tiny):
    """The validation program and the scenario draws compiled at optimization level 0
    (loop.QUICK_COMPILE) give the default programs' numbers to rounding, and the public
    gradient and value functions nest in a user's jit."""
    from tuning import loop

    ctrl, spec, g, rcfg, train, validation, heldout = tiny
    wts = jnp.asarray(TINY.weights, float)
    raw = spec.init(1.3)
    v, ok, m = loop.batch_value(raw, validation, ctrl, spec, g, rcfg, wts)
    vq, okq, mq = loop.validation_value(raw, validation, ctrl, spec, g, rcfg, wts)
    np.testing.assert_allclose(float(vq), float(v), rtol=1e-13)
    np.testing.assert_array_equal(np.asarray(okq), np.asarray(ok))
    np.testing.assert_allclose(np.asarray(mq.tracking), np.asarray(m.tracking), rtol=1e-12)
    # the public functions nest in a user's jit (JAX takes compiler options on the outermost
    # jit only: the loop's own programs are separate top-level ones)
    nested = jax.jit(lambda r: batch_value_and_grad(r, train, ctrl, spec, g, rcfg, wts))(raw)
    top = batch_value_and_grad(raw, train, ctrl, spec, g, rcfg, wts)
    np.testing.assert_allclose(np.asarray(nested[1]), np.asarray(top[1]), rtol=1e-13)
    np.testing.assert_allclose(float(jax.jit(lambda r: batch_value(r, validation, ctrl, spec, g, rcfg, wts)[0])(raw)),
                               float(v), rtol=1e-13)
    # build's scenario sets (one quickly compiled program) against make_scenarios, set by set
    key = jax.random.PRNGKey(TINY.seed)
    k_train, k_heldout = jax.random.split(key)
    draw = jax.jit(loop.make_scenarios, static_argnums=(0, 1, 4))
    for got, k, n in ((train, k_train, TINY.n_train), (validation, jax.random.fold_in(key, 2), TINY.n_validation),
                      (heldout, k_heldout, TINY.n_heldout)):
        want = draw(ctrl, TINY, g, k, n)
        for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-14)


def test_nan_scenario_is_reported_and_excluded(tiny):
    ctrl, spec, g, rcfg, train, _, _ = tiny
    w = jnp.asarray(TINY.weights, float)
    raw = spec.init(1.0)
    bad = train._replace(input_scale=train.input_scale.at[0].set(jnp.nan))
    loss, grad, ok, _ = batch_value_and_grad(raw, bad, ctrl, spec, g, rcfg, w)
    assert not bool(ok[0]) and bool(jnp.all(ok[1:])) and np.isfinite(float(loss)) and bool(jnp.all(jnp.isfinite(grad)))
    _, ok_all, m = batch_value(raw, train, ctrl, spec, g, rcfg, w)      # the clean batch, scenario by scenario
    assert bool(jnp.all(ok_all))
    per = np.asarray(scenario_loss(m, LossWeights(*TINY.weights)))
    np.testing.assert_allclose(float(loss), per[1:].mean(), rtol=1e-12)   # the mean over the others, exactly


def test_resume_gives_the_same_gains(tmp_path, tiny):
    full = tune(TINY, None, log=lambda *_: None)
    # the loop's gradient program (its own top-level copy, at LOOP_COMPILE) gives the public
    # function's numbers: the first step's training objective
    ctrl, spec, g, rcfg, train, _, _ = tiny
    loss, _, ok, _ = batch_value_and_grad(spec.init(TINY.poles_init), train, ctrl, spec, g, rcfg,
                                          jnp.asarray(TINY.weights, float))
    np.testing.assert_allclose(full["state"]["history"][0]["train_loss"], float(objective(loss, ok)), rtol=1e-13)
    part = tune(TINY, tmp_path, log=lambda *_: None, stop_after=3)
    assert not part["finished"] and json.loads((tmp_path / "checkpoint.json").read_text())["step"] == 3
    resumed = tune(TINY, tmp_path, log=lambda *_: None)
    assert resumed["finished"]
    np.testing.assert_allclose(resumed["raw"], full["raw"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(resumed["best_raw"], full["best_raw"], rtol=0, atol=1e-12)
    assert resumed["state"]["rollouts"] == full["state"]["rollouts"] == TINY.steps * TINY.n_train


def test_checkpoint_of_another_configuration_is_refused(tmp_path):
    tune(TINY, tmp_path, log=lambda *_: None, stop_after=1)
    with pytest.raises(ValueError, match="another configuration.*learning_rate"):
        tune(dataclasses.replace(TINY, learning_rate=0.01), tmp_path, log=lambda *_: None)


def test_converges_to_analytic_optimum():
    """(3,0) at velocity level, no noise/mismatch/limits, loss = tracking + w effort on a line
    reference: with a ZOH period dt the error obeys e_{k+1} = (1 - lam dt) e_k, so the loss is
    const + c (1 + w lam^2) / (lam (2 - lam dt)); its minimiser (about 1/sqrt(w)) is the oracle."""
    w_eff, dt = 0.25, 0.01
    cfg = TuneConfig(robot="(3,0)", task="posture", reference="line", n_train=4, n_heldout=2, poles_init=0.7,
                     weights=(1.0, w_eff, 0.0, 0.0, 0.0), steps=150, learning_rate=0.3, patience=1000, ic_position=2.0,
                     mismatch=0.0, input_limit=(), noise_std=(), t_final=8.0, control_dt=dt, substeps=1,
                     eval_every=20)
    res = tune(cfg, None, log=lambda *_: None)
    lam = float(res["spec"].coefficients(jnp.asarray(res["raw"]))[0, 0])
    opt = minimize_scalar(lambda x: (1 + w_eff * x * x) / (x * (2 - x * dt)), bounds=(0.1, 10), method="bounded").x
    assert abs(opt - 2.0) < 0.05 and abs(lam - opt) < 0.005 * opt


def test_bad_tuning_input(tmp_path):
    with pytest.raises(ValueError, match="poles_init must be > 0"):
        TuneConfig(poles_init=0.0).check()
    with pytest.raises(ValueError, match="scenario batch is empty"):
        TuneConfig(n_train=0).check()
    with pytest.raises(ValueError, match="finite and >= 0"):
        TuneConfig(weights=(1.0, -1.0, 0.0, 0.0, 0.0)).check()
    with pytest.raises(ValueError, match="at least one loss weight"):
        TuneConfig(weights=(0.0,) * 5).check()
    with pytest.raises(ValueError, match="finite and > 0"):
        GainSpec(2, 2).init(-1.0)
    from tuning.cli import main

    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--n-train", "0"])


def test_cli_writes_summary(tmp_path):
    args = ["--out", str(tmp_path), "--n-train", "3", "--n-heldout", "2", "--n-validation", "2", "--steps", "6",
            "--t-final", "2", "--control-dt", "0.1", "--baseline-seeds", "2"]
    # substeps and eval_every are not CLI options: set them as in TINY to reuse its compilations
    from tuning import cli

    cfg = dataclasses.replace(cli.config_from_args(cli.parser().parse_args(args)), substeps=2, eval_every=2)
    assert cfg == TINY
    s = cli.run(cfg, tmp_path, fresh=True, log=lambda *_: None)
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    hist = json.loads((tmp_path / "history.json").read_text())
    assert on_disk["rollouts"] == 6 * 3 and len(hist["gradient"]) == 6 and on_disk["n_parameters"] == 2
    # same budget (18 rollouts): random search 6 candidates of 3 scenarios; CMA-ES one generation of 4 + floor(3 ln 2) = 6
    for name in ("random_search", "cma_es"):
        runs = hist[name]
        b = on_disk["baselines"][name]
        assert len(runs) == 2 and all(len(r["best_so_far"]) == 6 for r in runs)
        for r, per in zip(runs, b["per_seed"]):
            assert per["best_loss"] == r["best_so_far"][-1]
            assert per["rollouts_to_best"] == 3 * (1 + int(np.argmin(r["best_so_far"])))
            want = next((h["rollouts"] for h in hist["gradient"] if h["train_loss"] <= per["best_loss"]), None)
            assert per["gradient_rollouts_to_match"] == want
        assert b["best_loss"] == float(np.median([p["best_loss"] for p in b["per_seed"]]))
    assert on_disk["baselines"]["cma_es"]["population"] == 6
    assert on_disk["train_loss"]["initial"] == hist["gradient"][0]["train_loss"]
    assert on_disk["train_loss"]["final"] == hist["gradient"][-1]["train_loss"]
    ho = on_disk["heldout_loss"]
    np.testing.assert_allclose(ho["ratio_paper_over_tuned"], ho["paper_gains"] / ho["tuned"], rtol=1e-15)
    np.testing.assert_allclose(on_disk["initial_gains"]["coefficients_k0_to_kr-1"], [[1.0, 2.0]] * 2, rtol=1e-12)
    for f in ("loss.png", "trajectories.png", "schedule.png"):
        assert (tmp_path / f).read_bytes()[:4] == b"\x89PNG"
    assert s["heldout_loss"] == on_disk["heldout_loss"]
    assert set(on_disk["singularity_events"]) == {"paper_gains", "tuned"} and on_disk["wall_time_s"] > 0
