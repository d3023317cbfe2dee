"""Gain tuning: gradients, a known optimum, resumption, NaN exclusion, bad input, the command line."""

import copy
import dataclasses
import json
import tomllib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import DEFAULT_OPT_LEVEL
from scipy.optimize import minimize_scalar

import wmrjax.tune
from wmrjax.problem import Problem, ProblemError
from wmrjax.tune import GainFamily, LossWeights, config, loop, mean_loss, mean_loss_and_grad, objective, tune
from wmrjax.tune.losses import scenario_loss

# one small problem shared by several tests, so its compiled functions are reused
TINY_DATA = {
    "title": "tiny",
    "controller": {"law": "dynamic", "robot": "(2,0)", "level": "velocity"},
    "geometry": {"L": 1.0, "e": 0.0, "delta": 0.0},
    "plant": {"input_limit": [5.5, 1.0], "control_period": 0.1, "noise_std": [0.01, 0.01, 0.005]},
    "reference": {"family": "paper_62", "heading_offset": 0.0},
    "initial": {
        "space": "output",
        "random": {"count": 4, "seed": 0},
        "x": {"low": -0.5, "high": 0.5},
        "y": {"low": -0.5, "high": 0.5},
        "vx": {"low": -0.5, "high": 0.5},
        "vy": {"low": -0.5, "high": 0.5},
    },
    "gains": {"poles": 1.0},
    "simulation": {"t_final": 2.0, "dt": 0.05},
    "tune": {
        "steps": 6,
        "scenarios": {"train": 3, "validation": 2, "heldout": 2},
        "stopping": {"eval_every": 2},
        "baselines": {"seeds": 2},
    },
}
TINY = Problem.from_dict(TINY_DATA)
TS = config.read(TINY.section("tune"))


def run_tiny(setting, family=None, out=None, steps=None, **kw):
    family = family or TS.gain_family(setting)
    steps = steps or TS.steps
    return tune(
        setting,
        family,
        TS.optimizer.build(steps),
        steps=steps,
        scenarios=TS.scenarios,
        loss=TS.loss,
        stopping=TS.stopping,
        seed=TS.seed,
        out_dir=out,
        log=lambda *_: None,
        **kw,
    )


@pytest.fixture(scope="module")
def tiny():
    setting = TINY.setting("tuning")
    family = TS.gain_family(setting)
    return setting, family, loop.prepare(setting, family, TS.scenarios, TS.loss, TS.seed)


def test_gain_spec_maps_paper_poles_and_is_hurwitz(rng):
    spec = GainFamily(2, 2)
    np.testing.assert_allclose(spec.coefficients(spec.init(1.0)), [[1.0, 2.0]] * 2, atol=1e-12)  # (s + 1)^2
    spec3 = GainFamily(2, 3, shared=False)
    np.testing.assert_allclose(spec3.coefficients(spec3.init([1.0, 2.0, 3.0]))[0], [6.0, 11.0, 6.0], rtol=1e-12)
    for _ in range(10):  # any raw gives a Hurwitz polynomial
        c = np.asarray(spec3.coefficients(jnp.asarray(rng.normal(size=(2, 3)) * 3)))
        for row in c:
            assert np.all(np.roots(np.concatenate([[1.0], row[::-1]])).real < 0)
    frozen = GainFamily(1, 2, frozen=(1,))
    g = jax.grad(lambda r: jnp.sum(frozen.coefficients(r)))(frozen.init(1.0))
    assert g[1] == 0.0 and g[0] != 0.0


def test_loss_gradient_matches_finite_differences(tiny):
    setting, spec, ctx = tiny
    raw = spec.init(1.3) + jnp.array([0.1, -0.2])
    loss, grad, ok, _ = mean_loss_and_grad(raw, ctx.sets.train, setting, spec, ctx.weights)
    assert bool(jnp.all(ok))
    h = 1e-5
    for i in range(raw.shape[0]):
        d = jnp.zeros_like(raw).at[i].set(h)
        fd = (
            mean_loss(raw + d, ctx.sets.train, setting, spec, ctx.weights)[0]
            - mean_loss(raw - d, ctx.sets.train, setting, spec, ctx.weights)[0]
        ) / (2 * h)
        np.testing.assert_allclose(float(grad[i]), float(fd), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(
        float(loss), float(mean_loss(raw, ctx.sets.train, setting, spec, ctx.weights)[0]), rtol=1e-12
    )


def test_constant_schedule_is_the_constant_gains(tiny):
    """The tuner's rollout with a schedule whose knots all hold the paper's gains equals the
    rollout with constant gains (same metrics to rounding): the law reads coeffs_at(t)."""
    setting, spec, ctx = tiny
    sspec = dataclasses.replace(spec, knots=(0.0, 1.0, 2.0))
    a = mean_loss(spec.init(1.0), ctx.sets.train, setting, spec, ctx.weights)
    b = mean_loss(sspec.init(1.0), ctx.sets.train, setting, sspec, ctx.weights)
    np.testing.assert_allclose(float(b[0]), float(a[0]), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(b[2].tracking), np.asarray(a[2].tracking), rtol=1e-12)


def test_quickly_compiled_programs_match_the_default_ones(tiny):
    """The validation program and the scenario draws compiled at optimization level 0
    (loop.QUICK_COMPILE) give the default programs' numbers to rounding, and the public
    gradient and value functions nest in a user's jit."""
    from wmrjax.tune.scenarios import draw_set

    setting, spec, ctx = tiny
    raw = spec.init(1.3)
    # the default programs at XLA's default level (the test session compiles at level 0: conftest.py)
    default_loss = jax.jit(loop._mean_loss, static_argnums=(2, 3), compiler_options=DEFAULT_OPT_LEVEL)
    v, ok, m = default_loss(raw, ctx.sets.validation, setting, spec, ctx.weights)
    vq, okq, mq = loop.validation_loss(raw, ctx.sets.validation, setting, spec, ctx.weights)
    np.testing.assert_allclose(float(vq), float(v), rtol=1e-13)
    np.testing.assert_array_equal(np.asarray(okq), np.asarray(ok))
    np.testing.assert_allclose(np.asarray(mq.tracking), np.asarray(m.tracking), rtol=1e-12)
    nested = jax.jit(lambda r: mean_loss_and_grad(r, ctx.sets.train, setting, spec, ctx.weights))(raw)
    top = mean_loss_and_grad(raw, ctx.sets.train, setting, spec, ctx.weights)
    np.testing.assert_allclose(np.asarray(nested[1]), np.asarray(top[1]), rtol=1e-13)
    # the sets (one quickly compiled program) against a draw of each set, set by set
    key = jax.random.PRNGKey(TS.seed)
    k_train, k_heldout = jax.random.split(key)
    draw = jax.jit(
        lambda k, n: draw_set(setting, TS.scenarios.mismatch, jax.random.split(k, n)),
        static_argnums=1,
        compiler_options=DEFAULT_OPT_LEVEL,
    )
    for got, k, n in (
        (ctx.sets.train, k_train, 3),
        (ctx.sets.validation, jax.random.fold_in(key, 2), 2),
        (ctx.sets.heldout, k_heldout, 2),
    ):
        for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(draw(k, n))):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-14)


def test_batch_reads_shared_inputs_once_and_equals_each_scenario_alone(tiny):
    """The batched loss takes the inputs every scenario shares once (wmrjax.tune.scenarios.shared_axes:
    what depends on them alone is then computed once per batch): it equals each scenario's own
    rollout, run unbatched, to rounding; and what a scenario draws is batched, the rest not."""
    from wmrjax.tune.scenarios import DRAWN, rollout, shared_axes

    setting, spec, ctx = tiny
    raw = spec.init(1.2)
    _, ok, m = mean_loss(raw, ctx.sets.train, setting, spec, ctx.weights)
    one = jax.jit(lambda sc: rollout(setting, spec.gains(raw), sc))
    for i in range(3):
        alone = one(jax.tree_util.tree_map(lambda x: x[i], ctx.sets.train))
        for a, b in zip(jax.tree_util.tree_leaves(alone), jax.tree_util.tree_leaves(m)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b)[i], rtol=1e-12, atol=1e-14)
    _, axes = shared_axes(setting, ctx.sets.train)
    assert {k for k, v in axes.inputs._asdict().items() if v == 0} == set(DRAWN) and axes.key == 0


def test_set_whose_shared_inputs_differ_is_refused(tiny):
    """A set edited by hand so that one scenario has its own actuator limit: the batched losses,
    which read the shared inputs from the first scenario, refuse it (naming the input and the
    scenario) before anything compiles; the same edit inside a transformation is not checkable
    and not checked."""
    setting, spec, ctx = tiny
    train = ctx.sets.train
    bad = train._replace(inputs=train.inputs._replace(limit=train.inputs.limit.at[2].set(1.2)))
    for fn in (mean_loss, mean_loss_and_grad):
        with pytest.raises(ValueError, match=r"inputs\['limit'\] differ between scenarios \(scenarios \[2\]"):
            fn(spec.init(1.0), bad, setting, spec, ctx.weights)
    nan_everywhere = train._replace(inputs=train.inputs._replace(delta=jnp.full_like(train.inputs.delta, jnp.nan)))
    wmrjax.tune.scenarios.check_shared(setting, nan_everywhere)  # the same value (NaN) in every scenario: shared


def test_nan_scenario_is_reported_and_excluded(tiny):
    setting, spec, ctx = tiny
    raw = spec.init(1.0)
    train = ctx.sets.train
    bad = train._replace(inputs=train.inputs._replace(input_scale=train.inputs.input_scale.at[0].set(jnp.nan)))
    loss, grad, ok, _ = mean_loss_and_grad(raw, bad, setting, spec, ctx.weights)
    assert not bool(ok[0]) and bool(jnp.all(ok[1:])) and np.isfinite(float(loss)) and bool(jnp.all(jnp.isfinite(grad)))
    _, ok_all, m = mean_loss(raw, train, setting, spec, ctx.weights)  # the clean batch, scenario by scenario
    assert bool(jnp.all(ok_all))
    per = np.asarray(scenario_loss(m, TS.loss))
    np.testing.assert_allclose(float(loss), per[1:].mean(), rtol=1e-12)  # the mean over the others, exactly


def test_resume_gives_the_same_gains(tmp_path, tiny):
    setting, spec, ctx = tiny
    full = run_tiny(setting)
    assert isinstance(full, wmrjax.tune.TuneResult) and full.finished
    # the loop's gradient program (its own top-level copy, at LOOP_COMPILE) gives the public
    # function's numbers: the first step's training objective
    default_grad = jax.jit(loop._mean_loss_and_grad, static_argnums=(2, 3), compiler_options=DEFAULT_OPT_LEVEL)
    loss, _, ok, _ = default_grad(spec.init(1.0), ctx.sets.train, setting, spec, ctx.weights)
    np.testing.assert_allclose(full.history[0]["train_loss"], float(objective(loss, ok)), rtol=1e-13)
    part = run_tiny(setting, out=tmp_path, stop_after=3)
    assert not part.finished and json.loads((tmp_path / "checkpoint.json").read_text())["step"] == 3
    resumed = run_tiny(setting, out=tmp_path)
    assert resumed.finished
    np.testing.assert_allclose(resumed.raw, full.raw, rtol=0, atol=1e-12)
    np.testing.assert_allclose(resumed.best_raw, full.best_raw, rtol=0, atol=1e-12)
    assert resumed.rollouts == full.rollouts == TS.steps * TS.scenarios.train


def test_checkpoint_of_another_configuration_is_refused(tmp_path, tiny):
    setting, spec, _ = tiny
    run_tiny(setting, out=tmp_path, stop_after=1)
    with pytest.raises(ValueError, match="another configuration"):
        run_tiny(setting, out=tmp_path, steps=7)


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda d: d.update(step=True), "integer 'step' >= 0"),  # was taken as step 1
        (lambda d: d["state"].update(history=d["state"]["history"][:1]), "state 'history'"),  # a short history
        (lambda d: d["state"].update(stopped_early="no"), "state 'stopped_early' is 'no', expected true or false"),
        (lambda d: d["state"].update(rollouts="6"), "state 'rollouts'"),
        (lambda d: d["state"].update(best_raw=[1.0]), "state 'best_raw'"),
    ],
)
def test_edited_checkpoint_is_refused_by_name(tmp_path, tiny, edit, match):
    """Hand-edited checkpoints that are valid JSON were accepted ("step": true as step 1, a
    short history, stopped_early = "no" as true); each is now refused, naming the field."""
    setting, _, _ = tiny
    run_tiny(setting, out=tmp_path, stop_after=2)
    path = tmp_path / "checkpoint.json"
    d = json.loads(path.read_text())
    edit(d)
    path.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=match):
        run_tiny(setting, out=tmp_path)


def test_checkpoint_that_is_a_directory_is_refused(tmp_path, tiny):
    setting, _, _ = tiny
    (tmp_path / "checkpoint.json").mkdir()
    with pytest.raises(ValueError, match="not a regular file"):
        run_tiny(setting, out=tmp_path)


def test_converges_to_analytic_optimum():
    """(3,0) at velocity level, no noise/mismatch/limits, loss = tracking + w effort on a line
    reference: with a ZOH period dt the error obeys e_{k+1} = (1 - lam dt) e_k, so the loss is
    const + c (1 + w lam^2) / (lam (2 - lam dt)); its minimiser (about 1/sqrt(w)) is the oracle."""
    w_eff, dt = 0.25, 0.01
    problem = Problem.from_dict(
        {
            "controller": {"law": "static", "robot": "(3,0)", "task": "posture"},
            "plant": {"control_period": dt},
            "reference": {"family": "line"},
            "initial": {
                "space": "physical",
                "random": {"count": 4},
                "x": {"low": -2.0, "high": 2.0},
                "y": {"low": -2.0, "high": 2.0},
            },
            "gains": {"poles": 0.7},
            "simulation": {"t_final": 8.0, "dt": dt},
            "tune": {
                "steps": 150,
                "family": {"parameterization": "poles"},
                "loss": {"tracking": 1.0, "effort": w_eff, "saturation": 0.0, "barrier": 0.0},
                "scenarios": {"train": 4, "heldout": 2, "mismatch": 0.0},
                "optimizer": {"learning_rate": 0.3},
                "stopping": {"eval_every": 20, "patience": 1000},
            },
        }
    )
    setting = problem.setting("tuning")
    ts = config.read(problem.section("tune"))
    family = ts.gain_family(setting)
    res = tune(
        setting,
        family,
        ts.optimizer.build(ts.steps),
        steps=ts.steps,
        scenarios=ts.scenarios,
        loss=ts.loss,
        stopping=ts.stopping,
        log=lambda *_: None,
    )
    lam = float(family.coefficients(jnp.asarray(res.raw))[0, 0])
    opt = minimize_scalar(lambda x: (1 + w_eff * x * x) / (x * (2 - x * dt)), bounds=(0.1, 10), method="bounded").x
    assert abs(opt - 2.0) < 0.05 and abs(lam - opt) < 0.005 * opt


def test_optax_shape_any_transformation(tiny):
    """tune takes any optax.GradientTransformation: plain SGD with a tiny rate barely moves the
    gains, Adam moves them; both return a TuneResult of fixed fields, no closures."""
    import optax

    setting, spec, _ = tiny
    slow = tune(setting, spec, optax.sgd(1e-9), steps=2, scenarios=TS.scenarios, log=lambda *_: None)
    np.testing.assert_allclose(slow.raw, np.asarray(spec.init(1.0)), atol=1e-6)
    assert set(wmrjax.tune.TuneResult._fields) == {
        "finished",
        "raw",
        "best_raw",
        "history",
        "rollouts",
        "excluded",
        "stopped_early",
        "wall_time_s",
        "context",
    }
    assert not any(callable(v) for v in slow.context._asdict().values())


def test_bad_tuning_input(tmp_path):
    bad = [
        ({"tune": {"scenarios": {"train": 0}}}, r"\[tune.scenarios\] train: expected an integer >= 1"),
        ({"tune": {"loss": {"effort": -1.0}}}, r"\[tune.loss\] effort: expected a number >= 0"),
        ({"tune": {"loss": {k: 0.0 for k in LossWeights._fields}}}, "at least one loss weight"),
        ({"tune": {"family": {"knots": 1}}}, "at least 2 knots"),
        ({"tune": {"optimizer": {"momentum": 0.9}}}, r"\[tune.optimizer\]: unknown key"),
        ({"tune": {"baselines": {"cma_population": 1}}}, "CMA-ES ranks"),
        ({"tune": {"scenarios": {"mismatch": 1.5}}}, r"mismatch: expected a number in \[0, 1\)"),
    ]
    for change, msg in bad:
        data = copy.deepcopy(TINY_DATA)
        data["tune"] = {**data["tune"], **change["tune"]}
        with pytest.raises(ProblemError, match=msg):
            config.read(Problem.from_dict(data).section("tune"))
    with pytest.raises(ValueError, match="finite and > 0"):
        GainFamily(2, 2).init(-1.0)
    from wmrjax.cli.tune import main

    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--set", "tune.scenarios.train=0"])


def _tiny_file(tmp_path):
    """TINY as a problem file (a TOML writer is not in the standard library: a few lines by hand)."""
    lines = [
        'title = "tiny"',
        "[controller]",
        'law = "dynamic"',
        'robot = "(2,0)"',
        'level = "velocity"',
        "[geometry]",
        "L = 1.0",
        "e = 0.0",
        "delta = 0.0",
        "[plant]",
        "input_limit = [5.5, 1.0]",
        "control_period = 0.1",
        "noise_std = [0.01, 0.01, 0.005]",
        "[reference]",
        'family = "paper_62"',
        "heading_offset = 0.0",
        "[initial]",
        'space = "output"',
        "random = { count = 4, seed = 0 }",
    ]
    lines += [f"{k} = {{ low = -0.5, high = 0.5 }}" for k in ("x", "y", "vx", "vy")]
    lines += [
        "[gains]",
        "poles = 1.0",
        "[simulation]",
        "t_final = 2.0",
        "dt = 0.05",
        "[tune]",
        "steps = 6",
        "[tune.scenarios]",
        "train = 3",
        "validation = 2",
        "heldout = 2",
        "[tune.stopping]",
        "eval_every = 2",
        "[tune.baselines]",
        "seeds = 2",
    ]
    path = tmp_path / "tiny.toml"
    path.write_text("\n".join(lines) + "\n")
    assert tomllib.loads(path.read_text()) == TINY_DATA
    return path


def test_cli_writes_summary_and_gains(tmp_path, returns, capsys):
    from wmrjax.cli import tune as cli

    path = _tiny_file(tmp_path)
    out = tmp_path / "out"
    reports = returns(cli, "run")
    assert cli.main([str(path), "--out", str(out), "--fresh", "--no-compile-cache"]) == 0
    (s,) = reports
    printed = capsys.readouterr().out
    assert f"tuned {s.heldout_loss[1]:.4g}" in printed and "certified radius (position slice" in printed
    on_disk = json.loads((out / "summary.json").read_text())
    hist = json.loads((out / "history.json").read_text())
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
    ho = on_disk["heldout_loss"]
    np.testing.assert_allclose(ho["ratio_paper_over_tuned"], ho["paper_gains"] / ho["tuned"], rtol=1e-15)
    np.testing.assert_allclose(on_disk["initial_gains"]["coefficients_k0_to_kr-1"], [[1.0, 2.0]] * 2, rtol=1e-12)
    for f in ("loss.png", "trajectories.png", "schedule.png", "radii.png"):
        assert (out / f).read_bytes()[:4] == b"\x89PNG"
    # the typed report: its summary is the file; its fields are the numbers in it
    assert json.loads(json.dumps(s.summary())) == on_disk
    assert s.heldout_loss == (ho["paper_gains"], ho["tuned"]) and s.result.rollouts == on_disk["rollouts"]
    np.testing.assert_allclose(s.tuned_gains.coeffs, on_disk["tuned_gains"]["coefficients_k0_to_kr-1"], rtol=1e-15)
    # the lowest held-out loss of every method and seed, and its gains on disk
    best = on_disk["best_heldout"]
    seeds = [p["best_heldout_loss"] for b in on_disk["baselines"].values() for p in b["per_seed"]]
    assert best["heldout_loss"] == min([ho["tuned"], *seeds])
    assert (best["method"] == "gradient") == (best["heldout_loss"] == ho["tuned"])
    kept = json.loads((out / best["file"]).read_text())
    if best["method"] == "gradient":
        assert kept == json.loads((out / "gains.json").read_text())
    # the summary carries the whole problem: it runs again from there alone
    again = Problem.from_dict(on_disk["problem"])
    assert again.resolved() == s.problem.resolved() and on_disk["tune"]["steps"] == 6
    # gains.json is the tuned gains, for this robot and level
    gains = json.loads((out / "gains.json").read_text())
    assert (gains["kind"], gains["robot"], gains["level"]) == ("wmrjax.gains", "(2,0)", "velocity")
    np.testing.assert_allclose(gains["coefficients"], on_disk["tuned_gains"]["coefficients_k0_to_kr-1"], rtol=1e-15)
    assert [on_disk[k] for k in ("robot", "level", "law")] == [gains[k] for k in ("robot", "level", "law")]
    # every reported radius is the certify module's for the same gains, read back from gains.json
    from wmrjax import certify

    radii = on_disk["radii"]
    assert set(radii["tuned"]["lemma2"]) == {"lyapunov", "exact_norm"}  # eq (64) is for the double pole at -1
    assert set(radii["initial"]["lemma2"]) == {"paper", "lyapunov", "exact_norm"}
    for which, gains_table in (("tuned", {"file": str(out / "gains.json")}), ("initial", {"poles": 1.0})):
        st = Problem.from_dict({**on_disk["problem"], "gains": gains_table}).setting("tuning")
        params = st.params()
        for name, c in certify.lemma2(st.ctrl, params, t_final=2.0, eps=0.01).certificates().items():
            np.testing.assert_allclose(radii[which]["lemma2"][name]["radius"], float(c.radius), rtol=1e-12)
        for basis in ("full", "position"):
            em = certify.exact_map_radius(st.ctrl, params, t_final=2.0, eps=0.01, basis=basis)
            np.testing.assert_allclose(radii[which][f"exact_map_{basis}"]["radius"], float(em.radius), rtol=1e-12)


def test_each_log_line_shows_the_parameters_its_loss_was_evaluated_at(tiny):
    """Issue 58: the log printed each step's updated parameters beside the loss of the parameters
    before the update. A large learning rate makes the two differ visibly."""
    import optax

    setting, spec, _ = tiny
    lines = []
    res = tune(setting, spec, optax.sgd(0.5), steps=2, scenarios=TS.scenarios, log=lines.append)
    steps = [ln for ln in lines if ln.startswith("step")]
    assert len(steps) == 2
    for line, rec in zip(steps, res.history):
        assert f"train {rec['train_loss']:.5g}" in line
        assert str(np.round(np.asarray(rec["params"]), 3).tolist()) in line
    assert res.history[0]["params"] != res.history[1]["params"]


def test_radius_change_is_printed_per_slice():
    """Issue 58: the tuned gains' certified region shrank by 80 % (position slice) and only the
    summary and the figure said so; the console now does, with its kind and loop."""
    from wmrjax.cli.tune import radius_change_lines

    radii = {
        "initial": {"lemma2": {}, "exact_map_full": {"radius": 0.5}, "exact_map_position": {"radius": 2.0}},
        "tuned": {"lemma2": {}, "exact_map_full": {"radius": 0.55}, "exact_map_position": {"radius": 0.4}},
    }
    lines = radius_change_lines(radii)
    assert lines == [
        "certified radius (full slice, exact map, nominal loop, proved): initial 0.5 -> tuned 0.55 (+10 %)",
        "certified radius (position slice, exact map, nominal loop, proved): initial 2 -> tuned 0.4 (-80 %)",
    ]
    assert radius_change_lines({"skipped": "a static law"}) == ["certified radii: a static law"]


def test_listed_plant_scales_are_tuned_over_as_scenarios():
    """Issue 58: a [plant] listing geometry scales (a +-5 % range, to sweep) was refused by the
    tuner; its scenarios now draw a listed value each, around which the mismatch is drawn. A
    single scale is the scenarios' centre (it was ignored: every scenario centred on 1)."""
    from wmrjax.tune.scenarios import draw_set

    keys = jax.random.split(jax.random.PRNGKey(0), 64)
    for scales, mismatch in (([0.9, 1.1], 0.0), (1.05, 0.0), (1.05, 0.02)):
        data = copy.deepcopy(TINY_DATA)
        data["plant"]["geometry_scale"] = scales
        data["plant"]["input_scale"] = scales
        setting = Problem.from_dict(data).setting("tuning")
        loop.check(setting, TS.gain_family(setting), TS.scenarios, TS.loss)
        sc = draw_set(setting, mismatch, keys)
        g = np.asarray(sc.inputs.geometry_scale)
        u = np.asarray(sc.inputs.input_scale)
        assert g.shape == (64, 2) and u.shape == (64, 2)
        if isinstance(scales, list):
            assert set(np.unique(g).tolist()) == set(np.unique(u).tolist()) == {0.9, 1.1}
            assert len({(a, b) for a, b in zip(g[:, 0], u[:, 0])}) == 4  # the plant axis: their product
        else:
            assert np.all(np.abs(g / 1.05 - 1.0) <= mismatch + 1e-12) and np.all(
                np.abs(u / 1.05 - 1.0) <= mismatch + 1e-12
            )
    data = copy.deepcopy(TINY_DATA)
    data["plant"]["input_limit"] = [[5.5, 1.0], [4.0, 1.0]]
    setting = Problem.from_dict(data).setting("tuning")
    with pytest.raises(ValueError, match="tuning takes one \\[plant\\] input_limit"):
        loop.check(setting, TS.gain_family(setting), TS.scenarios, TS.loss)


def test_more_knots_than_steps_are_refused_before_anything_is_built():
    """Issue 57: [tune.family] knots = 1e6 compiled without end and without an estimate."""
    data = copy.deepcopy(TINY_DATA)
    data["tune"]["family"] = {"knots": 1_000_000}
    problem = Problem.from_dict(data)
    settings = config.read(problem.section("tune"))
    with pytest.raises(ProblemError, match=r"1000000 knots on a horizon of 40 steps .* at most one per step \(41\)"):
        settings.gain_family(problem.setting("tuning"))
    data["tune"]["family"] = {"knots": 41}
    problem = Problem.from_dict(data)
    assert len(config.read(problem.section("tune")).gain_family(problem.setting("tuning")).knots) == 41
