"""Static feedback linearization (§4): Table 3, Prop 3, eqs 12, 14, 27, 28, Remark 11."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax import references as R
from wmrjax.controllers import static as S

GEOM = {
    "(3,0)": w.Geometry(),
    "(2,0)": w.Geometry(e=0.3, delta=0.7),
    "(2,1)": w.Geometry(e=0.3, delta=0.4),
    "(1,1)": w.Geometry(L=1.0, e=0.3),
    "(1,2)": w.Geometry(L=0.5, e=0.3, delta=0.5),
}


def _task(kind):
    return "posture" if kind == "(3,0)" else "point"


def _start(ctrl, p):
    X = jnp.zeros(ctrl.robot.n_state).at[0].set(2.3).at[1].set(0.2)
    if ctrl.robot.delta_s:
        X = X.at[3:].set(0.9)
    return ctrl.initial_state_from_physical(X, jnp.full(ctrl.robot.n_input, 0.1), p)


def _closed_form_K(kind, X, g):
    """Hand-derived K of eq (22) from Table 3's outputs and Table 1's kinematics."""
    x, y, th = X[:3]
    if kind == "(2,0)":
        return np.array([[-np.sin(th), -g.e * np.sin(th + g.delta)], [np.cos(th), g.e * np.cos(th + g.delta)]])
    if kind == "(2,1)":
        b = X[3]
        return np.array(
            [
                [-np.sin(th + b), -g.e * np.sin(th + g.delta), 0.0],
                [np.cos(th + b), g.e * np.cos(th + g.delta), 0.0],
                [0.0, 0.0, 1.0],
            ]
        )
    if kind == "(1,1)":
        b = X[3]
        s, c = np.sin(th + b), np.cos(th + b)
        return np.array([[g.L * c - g.e * s * np.cos(b), -g.e * s], [g.L * s + g.e * c * np.cos(b), g.e * c]])
    if kind == "(1,2)":
        b1, b2 = X[3], X[4]
        vb = np.array([-2 * g.L * np.sin(b1) * np.sin(b2), g.L * np.sin(b1 + b2)])
        om = np.sin(b2 - b1)
        R_T = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        dh_dth = np.array([-g.L * np.sin(th) - g.e * np.cos(th + b1), g.L * np.cos(th) - g.e * np.sin(th + b1)])
        col1 = R_T @ vb + dh_dth * om
        dh_db1 = np.array([-g.e * np.cos(th + b1), -g.e * np.sin(th + b1)])
        return np.array([[col1[0], dh_db1[0], 0.0], [col1[1], dh_db1[1], 0.0], [0.0, 0.0, 1.0]])
    return np.array([[np.cos(th), -np.sin(th), 0.0], [np.sin(th), np.cos(th), 0.0], [0.0, 0.0, 1.0]])  # (3,0)


ERRATA_DET = {
    "(3,0)": lambda X, g: 1.0,
    "(2,0)": lambda X, g: g.e * np.sin(g.delta),
    "(2,1)": lambda X, g: -g.e * np.sin(X[3] - g.delta),
    "(1,1)": lambda X, g: g.e * g.L,
    "(1,2)": lambda X, g: 2 * g.e * g.L * np.sin(X[4]),
}


@pytest.mark.parametrize("kind", list(GEOM))
def test_engine_K_equals_table3_closed_form_and_errata_det(kind, rng):
    for level in ("velocity", "torque"):
        ctrl = S.static_linearization(kind, level)
        g = GEOM[kind]
        for _ in range(5):
            z = jnp.asarray(rng.uniform(-2, 2, ctrl.n_state))
            K = np.asarray(ctrl.law.jet(z, g)[2])
            X = np.asarray(z[: ctrl.robot.n_state])
            np.testing.assert_allclose(K, _closed_form_K(kind, X, g), atol=1e-12)
            np.testing.assert_allclose(np.linalg.det(K), ERRATA_DET[kind](X, g), atol=1e-12)
            if level == "velocity":
                np.testing.assert_allclose(ctrl.law.jet(z, g)[1], 0.0, atol=1e-14)  # no drift: z1' = K u


@pytest.mark.parametrize("kind", list(GEOM))
def test_error_dynamics_exactly_linear(kind):
    """e' + Lambda e = 0 (velocity), e'' + (L1 + L2) e' + L1 L2 e = 0 (torque, eq 28 with tildes)."""
    for level, poles in (("velocity", [[0.8]]), ("torque", [[0.8, 1.7]])):
        ctrl = w.controller(kind, level, _task(kind))
        p = ctrl.params(R.circle(radius=2.0, omega=0.5), poles=jnp.asarray(poles * ctrl.m), geometry=GEOM[kind])
        tr = w.simulate(ctrl, _start(ctrl, p), p, dt=0.02, n_steps=300, save_every=30)
        assert not bool(tr.diagnostics.failed)
        err = jax.vmap(lambda t, z: ctrl.error(t, z, p).reshape(-1))(tr.t, tr.state)
        exact = jax.vmap(lambda t: jax.scipy.linalg.expm(ctrl.error_matrix(p.gains) * t) @ err[0])(tr.t)
        assert float(jnp.max(jnp.abs(err[0]))) > 0.1
        np.testing.assert_allclose(err, exact, rtol=0, atol=1e-5)  # RK4, dt = 0.02: ~1e-6


def test_velocity_and_torque_agree_with_fast_inner_gains():
    kind, g = "(2,0)", GEOM["(2,0)"]
    ref = R.circle(radius=2.0, omega=0.5)
    vel, tor = w.controller(kind, "velocity", "point"), w.controller(kind, "torque", "point")
    pv = vel.params(ref, poles=1.0, geometry=g)
    X0 = jnp.array([2.3, 0.2, 0.0])
    u_vel0 = vel.control(0.0, X0, pv)[0]
    # the step counts of test_error_dynamics_exactly_linear: its compiled rollouts are reused
    tv = w.simulate(vel, X0, pv, dt=0.01, n_steps=300, save_every=30)
    run = lambda z0, p: w.simulate(tor, z0, p, dt=0.01, n_steps=300, save_every=30).state  # noqa: E731
    gap = {}
    for lam2 in (10.0, 40.0):
        pt = tor.params(ref, poles=jnp.array([[1.0, lam2]] * 2), geometry=g)
        # started on the velocity law's input: sigma~(0) = 0, so the two coincide exactly
        same = run(jnp.concatenate([X0, u_vel0]), pt)
        np.testing.assert_allclose(same[:, :3], tv.state, atol=1e-7)
        off = run(jnp.concatenate([X0, u_vel0 + jnp.array([0.3, -0.2])]), pt)
        gap[lam2] = float(jnp.max(jnp.abs(off[3:, :2] - tv.state[3:, :2])))  # t >= 0.9 s
    assert gap[40.0] < 0.3 * gap[10.0] and gap[40.0] < 5e-3  # O(1 / lambda2)


def _decelerating(t, params):  # speed v0 exp(-t / tau): an L1 reference
    return params["p_inf"] - params["v0"] * params["tau"] * jnp.exp(-t / params["tau"]) * params["d"]


def test_z3_bounded_on_L1_speed_reference():
    ctrl = w.controller("(2,0)", "velocity", "point")
    ref = R.from_function(
        _decelerating,
        dict(p_inf=jnp.array([1.0, 2.0]), v0=jnp.asarray(1.0), tau=jnp.asarray(2.0), d=jnp.array([0.6, 0.8])),
    )
    p = ctrl.params(ref, poles=1.0, geometry=GEOM["(2,0)"])
    tr = w.simulate(ctrl, jnp.array([-0.5, 0.3, 1.0]), p, dt=0.02, n_steps=1500, save_every=25)
    th = np.asarray(jax.vmap(ctrl.z3)(tr.state))[:, 0]
    assert np.all(np.isfinite(th)) and np.max(np.abs(th)) < 10.0
    assert abs(th[-1] - th[-11]) < 1e-3  # z3 settles (Prop 5)


def test_sigma_tilde_reference_model_30():
    ctrl = w.controller("(3,0)", "torque", "posture")
    p = ctrl.params(R.circle(heading_offset=0.2), poles=jnp.array([[0.8, 2.0]] * 3))
    z0 = _start(ctrl, p)
    tr = w.simulate(ctrl, z0, p, dt=0.02, n_steps=300, save_every=30)  # compiled in test_error_dynamics_...
    sig = np.asarray(jax.vmap(lambda t, z: ctrl.sigma_tilde(t, z, p))(tr.t, tr.state))
    # eq (14): sigma~ = R^T(theta) (eta - eta_ref), eta_ref = R(theta) [xi_ref' - Lambda1 xi~]
    t0, th, eta = 0.0, float(z0[2]), np.asarray(z0[3:])
    xr = np.asarray(p.reference.posture(jnp.asarray(t0)))
    dxr = np.asarray(ctrl.reference_jet(jnp.asarray(t0), p)[1])
    xi_err = np.asarray(z0[:3]) - xr
    Rm = np.array([[np.cos(th), np.sin(th), 0], [-np.sin(th), np.cos(th), 0], [0, 0, 1]])
    eta_ref = Rm @ (dxr - 0.8 * xi_err)
    np.testing.assert_allclose(sig[0], Rm.T @ (eta - eta_ref), atol=1e-12)
    np.testing.assert_allclose(
        sig, sig[0] * np.exp(-2.0 * np.asarray(tr.t))[:, None], atol=1e-7
    )  # sigma~' = -L2 sigma~


def test_vmap_jit_consistency_12_torque():
    ctrl = w.controller("(1,2)", "torque", "point")
    p = ctrl.params(R.figure_eight(), poles=1.0, geometry=GEOM["(1,2)"])
    z0 = _start(ctrl, p)
    z0s = jnp.stack([z0, z0.at[0].add(0.2), z0.at[1].add(-0.3)])
    batch = jax.jit(jax.vmap(lambda z: w.simulate(ctrl, z, p, dt=0.02, n_steps=200, save_every=200).final_state))(z0s)
    for i in range(3):
        single = w.simulate(ctrl, z0s[i], p, dt=0.02, n_steps=200, save_every=200).final_state
        np.testing.assert_allclose(batch[i], single, rtol=1e-10, atol=1e-12)


def test_bad_static_input():
    ref = R.circle()
    c20 = w.controller("(2,0)", "velocity", "point")
    with pytest.raises(ValueError, match="Table 3, type \\(2,0\\).*e != 0"):
        c20.params(ref, geometry=w.Geometry(e=0.0, delta=0.5))
    with pytest.raises(ValueError, match="delta != k pi"):
        c20.params(ref, geometry=w.Geometry(e=0.3, delta=math.pi))
    with pytest.raises(ValueError, match="poles"):
        c20.params(ref, poles=-1.0, geometry=GEOM["(2,0)"])
    c21 = w.controller("(2,1)", "torque", "point")
    with pytest.raises(ValueError, match="delta != beta mod pi"):
        c21.params(ref, geometry=GEOM["(2,1)"], steering=0.4)
    p21 = c21.params(ref, geometry=GEOM["(2,1)"])
    with pytest.raises(ValueError, match="singular set of the static linearizing law.*Table 3 requires"):
        c21.initial_state_from_physical(jnp.array([0.0, 0.0, 0.0, 0.4]), jnp.zeros(3), p21)
    with pytest.raises(ValueError, match="sin\\(beta2\\) != 0"):
        w.controller("(1,2)", "velocity", "point").params(ref, geometry=GEOM["(1,2)"], steering=0.0)
    with pytest.raises(ValueError, match="L = 0"):
        w.controller("(1,1)", "velocity", "point").params(ref, geometry=w.Geometry(L=0.0, e=0.3))
    with pytest.raises(ValueError, match="task='posture'"):
        w.controller("(3,0)", "velocity", "point")
    with pytest.raises(ValueError, match="task must be one of"):
        w.controller("(2,0)", "velocity", "parking")
