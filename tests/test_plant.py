"""Actuator limits and mismatch in the simulator (:func:`wmrjax.with_plant`): the nominal
plant reproduces the controller's own loop, limits hold, mismatch acts on the plant only."""

import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax import references as R

CASES = [("dynamic", "(2,0)", "torque"), ("static", "(2,0)", "torque"), ("static", "(1,1)", "velocity")]
# (the dynamic velocity-level plant is checked step by step in test_velocity_level_plant_matches_hand_integration)


def _setup(law, robot, level):
    if law == "dynamic":
        ctrl = w.dynamic_linearization(robot, level)
        g = ctrl.row.default_geometry
        p = ctrl.params(R.figure_eight(), poles=1.0, geometry=g)
        z0 = ctrl.reference_state(0.0, p).at[0].add(0.1).at[1].add(-0.05)
    else:
        ctrl = w.controller(robot, level=level, task="point")
        p = ctrl.params(R.circle(), poles=1.0, geometry=ctrl.row.default_geometry)
        X = jnp.zeros(ctrl.robot.n_state).at[0].set(2.2).at[1].set(0.1)
        z0 = ctrl.initial_state_from_physical(X, jnp.zeros(ctrl.robot.n_input), p)
    return ctrl, p, z0


@pytest.mark.parametrize("law, robot, level", CASES)
def test_nominal_plant_is_the_controllers_loop_and_limits_hold(law, robot, level):
    ctrl, p, z0 = _setup(law, robot, level)
    loop = w.with_plant(ctrl)
    lp = loop.params(p)
    a = w.simulate(ctrl, z0, p, dt=0.01, n_steps=300)
    b = w.simulate(loop, loop.initial_state(z0, lp), lp, dt=0.01, n_steps=300)
    np.testing.assert_allclose(np.asarray(loop.law_state(b.state)), np.asarray(a.state), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(b.control), np.asarray(a.control), rtol=0, atol=1e-10)
    # a limit below what the law asks: the plant's input never exceeds it, and it is reached
    peak = np.abs(np.asarray(a.control)).max(axis=0)
    limit = 0.5 * peak
    ls = loop.params(p, input_limit=limit)
    c = w.simulate(loop, loop.initial_state(z0, ls), ls, dt=0.01, n_steps=300)
    u = np.abs(np.asarray(c.control))[np.asarray(c.valid)]
    assert np.all(u <= limit * (1 + 1e-15))
    np.testing.assert_allclose(u.max(axis=0), limit, rtol=1e-12)


def test_velocity_level_plant_matches_hand_integration():
    """(2,0), velocity level: the plant moves with clip(scale * u); the compensator chi1 integrates
    the law's U1 whatever the plant did (one RK4 step against a hand-written one)."""
    ctrl, p, z0 = _setup("dynamic", "(2,0)", "velocity")
    loop = w.with_plant(ctrl)
    plant_geometry = w.Geometry(e=0.05)
    lp = loop.params(p, input_limit=[0.8, 0.4], input_scale=[1.1, 0.9], geometry=plant_geometry)
    dt = 0.01
    got = w.simulate(loop, z0, lp, dt=dt, n_steps=1).final_state

    def field(t, z):
        U, _ = ctrl.control(t, z, p)
        u = ctrl.law.plant_control(z, U, p.geometry)
        u = jnp.clip(jnp.array([1.1, 0.9]) * u, -jnp.array([0.8, 0.4]), jnp.array([0.8, 0.4]))
        xdot = w.robots.kinematic(ctrl.robot, z[:3], u, plant_geometry)
        return jnp.concatenate([xdot, ctrl.law.extension.compensator(z[:3], z[3:], U, p.geometry)])

    k1 = field(0.0, z0)
    k2 = field(dt / 2, z0 + dt / 2 * k1)
    k3 = field(dt / 2, z0 + dt / 2 * k2)
    k4 = field(dt, z0 + dt * k3)
    np.testing.assert_allclose(np.asarray(got), np.asarray(z0 + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)), atol=1e-14)


def test_dynamic_torque_level_plant_velocities_are_a_separate_state():
    """With half the torque the plant lags the law's commands. Integrating its own commands
    ("internal") the law does not see it and ends 1.35 m off the figure eight; feeding back the
    measured wheel velocities (the default) it ends within 0.27 m."""
    ctrl, p, z0 = _setup("dynamic", "(2,0)", "torque")
    final_error = {}
    for feedback in ("internal", "measured"):
        loop = w.with_plant(ctrl, feedback)
        assert loop.n_state == ctrl.n_state + 2 and loop.state_names[-2:] == ("u_plant1", "u_plant2")
        lp = loop.params(p, input_scale=0.5)
        tr = w.simulate(loop, loop.initial_state(z0, lp), lp, dt=0.01, n_steps=1000, save_every=1000)
        z = tr.final_state
        assert bool(tr.valid.all())
        commanded = ctrl.law.extension.plant_input(z[:3], z[3:4], z[4:6], p.geometry)
        if feedback == "internal":
            assert float(jnp.max(jnp.abs(commanded - z[6:]))) > 1e-3
        lifted = ctrl.law.lift_measured(z[:6], z[6:], p.geometry)  # the lift matches the plant exactly
        np.testing.assert_allclose(
            np.asarray(ctrl.law.extension.plant_input(lifted[:3], lifted[3:4], lifted[4:6], p.geometry)),
            np.asarray(z[6:]),
            atol=1e-13,
        )
        final_error[feedback] = float(jnp.linalg.norm(z[:2] - p.reference.position(tr.t[-1])))
    np.testing.assert_allclose([final_error["internal"], final_error["measured"]], [1.3462, 0.2606], atol=2e-3)


def test_bad_plant_params():
    ctrl, p, _ = _setup("dynamic", "(2,0)", "velocity")
    loop = w.with_plant(ctrl)
    with pytest.raises(ValueError, match=r"input_limit must be a scalar or have 2 entries"):
        loop.params(p, input_limit=[1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match=r"input_limit must be > 0 per input \(inf: no limit\)"):
        loop.params(p, input_limit=[1.0, 0.0])
    with pytest.raises(ValueError, match=r"input_scale must be > 0 per input and finite"):
        loop.params(p, input_scale=np.inf)
    with pytest.raises(ValueError, match="PlantParams"):
        w.simulate(loop, jnp.zeros(4), p, dt=0.01, n_steps=10)
    with pytest.raises(ValueError, match="with_plant wraps"):
        w.with_plant(w.hybrid_parking())
    with pytest.raises(ValueError, match="velocity_feedback must be one of"):
        w.with_plant(ctrl, "estimated")
