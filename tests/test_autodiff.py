"""Gradient modes: forward sensitivities and reverse mode agree, and match central differences,
for every type at both levels, through the tuner's sampled-data loop and the hybrid switch."""

import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax import autodiff
from wmrjax import references as R
from wmrjax.controllers import hybrid as H

GEOM = {
    "(3,0)": w.Geometry(),
    "(2,0)": w.Geometry(e=0.3, delta=0.5),
    "(2,1)": w.Geometry(e=0.3, L=0.8),
    "(1,1)": w.Geometry(L=1.0, e=0.3),
    "(1,2)": w.Geometry(L=0.8, e=0.3, delta=0.4),
}
DYNAMIC = ("(2,0)", "(2,1)", "(1,1)", "(1,2)")
ALL_CASES = [("dynamic", k, lv) for k in DYNAMIC for lv in ("velocity", "torque")] + [
    ("static", k, lv) for k in GEOM for lv in ("velocity", "torque")
]
# make test runs the section 6.1 type at both levels, which covers both engines (nested jvp at
# r = 2, Taylor mode at r = 3); all 18 closed loops take about 9 CPU-minutes of compilation, more
# than the suite's 12-minute budget: WMRJAX_ALL_GRADIENT_CASES=1 pytest tests/test_autodiff.py
SUBSET = [("dynamic", "(2,0)", "velocity"), ("dynamic", "(2,0)", "torque")]
CASES = ALL_CASES if os.environ.get("WMRJAX_ALL_GRADIENT_CASES") == "1" else SUBSET


def _start(family, ctrl, params):
    if family == "dynamic":
        z = ctrl.reference_state(0.0, params)
        return z.at[0].add(0.05).at[1].add(-0.04)
    X = jnp.zeros(ctrl.robot.n_state).at[0].set(0.3).at[1].set(-0.2)
    if ctrl.robot.delta_s:
        X = X.at[3:].set(0.6)
    return ctrl.initial_state_from_physical(X, jnp.full(ctrl.robot.n_input, 0.4), params)


def _check(loss, theta, direction, h=1e-4):
    """Forward vs reverse mode to 1e-10; central differences of the value (second order in h).
    ``loss`` returns ``(value, ok)``: ``ok`` says the run went as intended (alive, switched)."""
    forward = jax.jit(w.value_and_grad(loss, has_aux=True, mode="forward"))
    ((v1, ok), g1), ((v2, _), g2) = forward(theta), jax.jit(w.value_and_grad(loss, has_aux=True, mode="reverse"))(theta)
    assert bool(ok)
    assert float(jnp.max(jnp.abs(g1))) > 1e-6 * abs(float(v1))  # the parameters matter
    np.testing.assert_allclose(v1, v2, rtol=1e-13)
    np.testing.assert_allclose(g1, g2, rtol=1e-10, atol=1e-10 * float(jnp.max(jnp.abs(g2))))
    value = lambda th: forward(th)[0][0]  # the same compiled program (values are mode-independent)
    fd = (value(theta + h * direction) - value(theta - h * direction)) / (2 * h)
    np.testing.assert_allclose(float(jnp.vdot(g1, direction)), float(fd), rtol=2e-6)
    return g1


@pytest.mark.parametrize("family,kind,level", CASES)
def test_forward_and_reverse_modes_agree_and_match_differences(family, kind, level):
    """The closed loop's gains (Hurwitz coefficients, m x r) through a short RK4 rollout."""
    make = w.dynamic_linearization if family == "dynamic" else w.static_linearization
    ctrl = make(kind, level)
    offset = 0.3 if kind in ("(2,1)", "(1,2)") else 0.0  # a steering angle away from the singular one
    params = ctrl.params(R.circle(radius=2.0, omega=0.4, heading_offset=offset), poles=1.5, geometry=GEOM[kind])
    z0 = _start(family, ctrl, params)

    def loss(coeffs):
        p = params._replace(gains=w.Gains(coeffs))
        tr = w.simulate(ctrl, z0, p, dt=0.02, n_steps=12, save_every=3, error_tol=None)
        return jnp.sum(tr.state**2) + jnp.sum(tr.control**2), ~tr.diagnostics.failed

    c = params.gains.coeffs
    direction = jnp.asarray(np.random.default_rng(1).normal(size=c.shape))
    _check(loss, c, direction)


def test_through_the_tuners_sampled_data_loop():
    """Zero-order hold, saturation, sensor noise and mismatch (wmrjax.tune.scenarios.rollout on the
    problem's sampled-data loop, wmrjax.sampled)."""
    from wmrjax.problem import Problem
    from wmrjax.tune import config, loop
    from wmrjax.tune.losses import scenario_loss
    from wmrjax.tune.scenarios import rollout

    box = {"low": -0.5, "high": 0.5}
    problem = Problem.from_dict(
        {
            "controller": {"law": "dynamic", "robot": "(2,0)"},
            "geometry": {"e": 0.0},
            "plant": {"input_limit": [5.5, 1.0], "control_period": 0.1, "noise_std": [0.01, 0.01, 0.005]},
            "reference": {"family": "paper_62"},
            "gains": {"poles": 1.0},
            "initial": {"space": "output", "random": {"count": 3}, "x": box, "y": box, "vx": box, "vy": box},
            "simulation": {"t_final": 1.0, "dt": 0.05},
            "tune": {"scenarios": {"train": 3, "validation": 2, "heldout": 2}},
        }
    )
    setting = problem.setting("test")
    ts = config.read(problem.section("tune"))
    spec = ts.gain_family(setting)
    train = loop.prepare(setting, spec, ts.scenarios, ts.loss, 0).sets.train
    # saturate the first scenario's wheels so the clip is active on part of the run
    train = train._replace(inputs=train.inputs._replace(limit=train.inputs.limit.at[0].set(1.2)))

    def loss(raw):
        ms = jax.vmap(lambda sc: rollout(setting, spec.gains(raw), sc))(train)
        return jnp.sum(jax.vmap(lambda m: scenario_loss(m, ts.loss))(ms)), jnp.all(ms.valid)

    raw = spec.init(1.3) + jnp.array([0.1, -0.2])
    _check(loss, raw, jnp.array([0.6, -0.8]), h=1e-5)


def test_through_the_hybrid_switch():
    """Section 6.2: tracking, the switch into the time-varying stabilizer, its gain lam."""
    hy = H.hybrid_parking()
    params = hy.params(R.paper_66())
    z0 = hy.initial_state(jnp.array([[10 * math.sqrt(2) / 6, 2.54], [-0.5, -0.5]]), params)

    def loss(theta):
        p = params._replace(
            lam=params.lam * theta[0],
            tracking=params.tracking._replace(gains=w.Gains.from_poles(jnp.ones((2, 2)) * theta[1])),
        )
        tr = w.simulate(hy, z0, p, dt=0.05, n_steps=120, save_every=120)
        return jnp.sum(tr.final_state.tracking[:3] ** 2), tr.final_state.mode == 1  # it did switch

    theta = jnp.array([1.1, 0.9])
    _check(loss, theta, jnp.array([0.6, 0.8]), h=1e-6)


def _count(jaxpr, name):
    """Equations of primitive ``name`` in ``jaxpr`` and its sub-jaxprs (loop bodies, calls)."""
    n = 0
    for eqn in jaxpr.eqns:
        n += eqn.primitive.name == name
        for p in eqn.params.values():
            for q in p if isinstance(p, (list, tuple)) else (p,):
                sub = getattr(q, "jaxpr", q)
                if hasattr(sub, "eqns"):
                    n += _count(sub, name)
    return n


@pytest.fixture(scope="module")
def failing_run():
    """Section 6.1 type, 12 steps, with a margin floor that the run crosses at step 7 of 12."""
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    params = ctrl.params(R.circle(radius=2.0, omega=0.4), poles=1.5, geometry=GEOM["(2,0)"])
    z0 = _start("dynamic", ctrl, params).at[3].add(0.4)

    def run(coeffs, floor):
        p = params._replace(gains=w.Gains(coeffs))
        return w.simulate(ctrl, z0, p, dt=0.02, n_steps=12, save_every=1, margin_floor=floor)

    margins = np.asarray(run(params.gains.coeffs, 0.0).margin)
    assert np.all(np.diff(margins) < 0)  # the margin falls along this run
    return run, params.gains.coeffs, 0.5 * (margins[6] + margins[7])


def test_reverse_mode_recomputes_the_stages_only(failing_run):
    """Reverse mode stores each step's two selection flags: its recomputation of the step has
    no finiteness check, sign test or error estimate of its own (the gradient's program has
    exactly the forward pass's)."""
    run, coeffs, _ = failing_run
    loss = lambda c: jnp.sum(run(c, 1e-9).state ** 2)
    forward, gradient = jax.make_jaxpr(loss)(coeffs).jaxpr, jax.make_jaxpr(jax.grad(loss))(coeffs).jaxpr
    for name in ("is_finite", "sign"):
        assert _count(forward, name) > 0
        assert _count(gradient, name) == _count(forward, name), name


def test_gradient_through_a_run_that_fails(failing_run):
    """A run frozen at its failure (margin floor crossed at step 7): the reverse pass selects
    with the stored flags, forward sensitivities with the recomputed ones; they agree."""
    run, coeffs, floor = failing_run
    tr = run(coeffs, floor)
    assert bool(tr.diagnostics.failed) and float(tr.diagnostics.t_failure) == pytest.approx(7 * 0.02, abs=1e-12)

    def loss(c):
        tr = run(c, floor)
        return jnp.sum(tr.state**2), tr.diagnostics.t_failure

    direction = jnp.asarray(np.random.default_rng(2).normal(size=coeffs.shape))
    fwd = jax.jit(w.value_and_grad(loss, has_aux=True, mode="forward"))
    ((v1, t1), g1), ((v2, t2), g2) = fwd(coeffs), jax.jit(w.value_and_grad(loss, has_aux=True, mode="reverse"))(coeffs)
    assert float(t1) == float(t2) == float(tr.diagnostics.t_failure)
    np.testing.assert_allclose(v1, v2, rtol=1e-13)
    np.testing.assert_allclose(g1, g2, rtol=1e-10, atol=1e-10 * float(jnp.max(jnp.abs(g2))))
    h = 1e-5  # small enough that the failure stays at step 7
    fd = (fwd(coeffs + h * direction)[0][0] - fwd(coeffs - h * direction)[0][0]) / (2 * h)
    np.testing.assert_allclose(float(jnp.vdot(g2, direction)), float(fd), rtol=1e-6)
    # from the failure on, the state stays at its last good value
    np.testing.assert_array_equal(
        np.asarray(tr.state[8:]), np.broadcast_to(np.asarray(tr.state[7]), tr.state[8:].shape)
    )


def test_stored_flags_under_two_level_checkpointing(failing_run, monkeypatch):
    """Long horizons checkpoint the saving chunks too (TWO_LEVEL_CHECKPOINT_STEPS, lowered here
    to 10 steps): the flags are stored again when a chunk is recomputed. Reverse mode through a
    24-step run frozen at step 7 equals forward sensitivities (1e-10)."""
    import importlib

    simulate_module = importlib.import_module("wmrjax.simulate")
    _, coeffs, floor = failing_run
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    params = ctrl.params(R.circle(radius=2.0, omega=0.4), poles=1.5, geometry=GEOM["(2,0)"])
    z0 = _start("dynamic", ctrl, params).at[3].add(0.4)

    def loss(c):
        tr = w.simulate(
            ctrl, z0, params._replace(gains=w.Gains(c)), dt=0.02, n_steps=24, save_every=3, margin_floor=floor
        )
        return jnp.sum(tr.state**2), tr.diagnostics.t_failure

    (v1, t1), g1 = jax.jit(w.value_and_grad(loss, has_aux=True, mode="forward"))(coeffs)
    assert float(t1) == pytest.approx(7 * 0.02, abs=1e-12)
    one_level = _count(jax.make_jaxpr(loss)(coeffs).jaxpr, "remat2")  # the step's
    jax.clear_caches()
    monkeypatch.setattr(simulate_module, "TWO_LEVEL_CHECKPOINT_STEPS", 10)
    assert _count(jax.make_jaxpr(loss)(coeffs).jaxpr, "remat2") == one_level + 1  # and the chunks'

    (v2, _), g2 = jax.jit(w.value_and_grad(loss, has_aux=True, mode="reverse"))(coeffs)
    np.testing.assert_allclose(v2, v1, rtol=1e-13)
    np.testing.assert_allclose(g2, g1, rtol=1e-10, atol=1e-10 * float(jnp.max(jnp.abs(g1))))
    jax.clear_caches()


def test_auto_mode_choice_and_aux():
    assert autodiff.choose_mode(autodiff.FORWARD_MAX_PARAMETERS) == "forward"
    assert autodiff.choose_mode(autodiff.FORWARD_MAX_PARAMETERS + 1) == "reverse"
    assert autodiff.choose_mode(3, "reverse") == "reverse"
    f = lambda a, b: (jnp.sum(jnp.sin(a) * b["x"]), a.shape[0])
    a, b = jnp.arange(3.0), {"x": jnp.array([1.0, 2.0, 3.0])}
    for mode in ("forward", "reverse", "auto"):
        (v, aux), (ga, gb) = w.value_and_grad(f, argnums=(0, 1), has_aux=True, mode=mode)(a, b)
        np.testing.assert_allclose(ga, jnp.cos(a) * b["x"], rtol=1e-15)
        np.testing.assert_allclose(gb["x"], jnp.sin(a), rtol=1e-15)
        assert aux == 3


def test_bad_mode_is_refused_before_tracing():
    with pytest.raises(ValueError, match="mode must be one of"):
        w.value_and_grad(lambda x: x, mode="adjoint")
    with pytest.raises(ValueError, match="scalar value"):
        w.value_and_grad(lambda x: x * 2.0, mode="forward")(jnp.ones(2))


@pytest.fixture(scope="module")
def batch_problem():
    """Section 6.1 type, 6 initial states, 12 steps; per-example loss of shared poles (2, 2) and
    a heading offset, with the example's start and weight as batched data."""
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    params = ctrl.params(R.circle(radius=2.0, omega=0.4), poles=1.5, geometry=GEOM["(2,0)"])
    z_ref = ctrl.reference_state(0.0, params)
    rng = np.random.default_rng(3)
    z0s = z_ref + 0.05 * jnp.asarray(rng.normal(size=(6, z_ref.size)))
    weights = jnp.asarray(rng.uniform(0.5, 1.5, size=6))

    def per_example(poles, shift, z0, weight):
        p = params._replace(gains=w.Gains.from_poles(poles))
        tr = w.simulate(ctrl, z0.at[2].add(shift), p, dt=0.02, n_steps=12, save_every=3, error_tol=None)
        return weight * (jnp.sum(tr.state**2) + jnp.sum(tr.control**2)), tr.final_state

    poles = jnp.array([[1.2, 1.6], [1.4, 1.9]])
    return per_example, poles, jnp.asarray(0.1), z0s, weights


def test_batch_value_and_grad_modes_equal_the_gradient_of_the_batch_mean(batch_problem):
    """Per-example reverse and batched forward both equal jax.value_and_grad of the mean over a
    vmapped batch (1e-10), aux comes back per example, and the value is the batch mean."""
    per_example, poles, shift, z0s, weights = batch_problem

    def batch_mean(poles, shift, z0s, weights):
        v, zf = jax.vmap(per_example, in_axes=(None, None, 0, 0))(poles, shift, z0s, weights)
        return jnp.mean(v), zf

    (v_ref, zf_ref), g_ref = jax.jit(jax.value_and_grad(batch_mean, (0, 1), has_aux=True))(poles, shift, z0s, weights)
    assert float(jnp.max(jnp.abs(g_ref[0]))) > 1e-3 and abs(float(g_ref[1])) > 1e-3
    for mode in ("forward", "reverse", "auto"):
        f = jax.jit(w.batch_value_and_grad(per_example, (0, 1), has_aux=True, mode=mode, chunk=4))
        (v, zf), (gp, gs) = f(poles, shift, z0s, weights)
        np.testing.assert_allclose(v, v_ref, rtol=1e-13)
        np.testing.assert_allclose(zf, zf_ref, rtol=1e-13)
        np.testing.assert_allclose(gp, g_ref[0], rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(gs, g_ref[1], rtol=1e-10)
    # one shared argument (int argnums): the gradient is that argument's, not a tuple
    f1 = jax.jit(w.batch_value_and_grad(lambda p, z, q: per_example(p, shift, z, q)[0], mode="reverse"))
    v1, g1 = f1(poles, z0s, weights)
    np.testing.assert_allclose(v1, v_ref, rtol=1e-13)
    np.testing.assert_allclose(g1, g_ref[0], rtol=1e-10, atol=1e-12)


def test_batch_value_and_grad_auto_threshold():
    """Forward up to BATCH_FORWARD_MAX_PARAMETERS (1), per-example reverse above; the
    per-rollout rule of value_and_grad differs (forward up to FORWARD_MAX_PARAMETERS, 2)."""
    lim = autodiff.BATCH_FORWARD_MAX_PARAMETERS
    assert lim == 1 and autodiff.FORWARD_MAX_PARAMETERS == 2
    assert autodiff.choose_mode(lim, "auto", lim) == "forward"
    assert autodiff.choose_mode(lim + 1, "auto", lim) == "reverse"
    assert autodiff.choose_mode(lim + 1) == "forward"

    # the dispatch itself: a per-example loss that reverse mode can differentiate and forward
    # mode cannot (a custom_vjp) fails with lim parameters and works with lim + 1
    sq = jax.custom_vjp(lambda u: u * u)
    sq.defvjp(lambda u: (u * u, u), lambda u, ct: (2.0 * u * ct,))
    per_example = lambda th, x: jnp.sum(sq(th * x))
    x = jnp.arange(1.0, 1.0 + 2 * (lim + 1)).reshape(2, lim + 1)
    with pytest.raises(TypeError, match="forward-mode"):
        w.batch_value_and_grad(per_example)(jnp.ones(lim), x[:, :lim])
    v, g = w.batch_value_and_grad(per_example)(jnp.ones(lim + 1), x)
    np.testing.assert_allclose(g, jnp.mean(2.0 * x**2, axis=0), rtol=1e-15)
    np.testing.assert_allclose(v, jnp.mean(jnp.sum(x**2, axis=1)), rtol=1e-15)


def test_batch_value_and_grad_refuses_bad_input():
    f = lambda th, x: jnp.sum(th * x)
    with pytest.raises(ValueError, match="mode must be one of"):
        w.batch_value_and_grad(f, mode="adjoint")
    for chunk in (0, 2.5, True):
        with pytest.raises(ValueError, match="chunk must be a positive integer"):
            w.batch_value_and_grad(f, chunk=chunk)
    with pytest.raises(ValueError, match="at least one batched argument"):
        w.batch_value_and_grad(lambda th: jnp.sum(th))(jnp.ones(2))
    with pytest.raises(ValueError, match="same leading batch size"):
        w.batch_value_and_grad(lambda th, x, y: jnp.sum(th * x) + y)(jnp.ones(2), jnp.ones((4, 2)), jnp.ones(3))
    with pytest.raises(ValueError, match="scalar per-example loss"):
        w.batch_value_and_grad(lambda th, x: th * x, mode="reverse")(jnp.ones(2), jnp.ones((4, 2)))
    with pytest.raises(ValueError, match="out of range"):
        w.batch_value_and_grad(f, argnums=2)(jnp.ones(2), jnp.ones((4, 2)))
