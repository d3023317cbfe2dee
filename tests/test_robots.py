"""Models against Table 1, written independently here."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax import robots


def table1(kind, X, u, L):
    """Table 1, typed in from the paper (independent of wmrjax.robots)."""
    x, y, th = X[:3]
    s, c = np.sin(th), np.cos(th)
    if kind == "(3,0)":
        return np.array([c * u[0] - s * u[1], s * u[0] + c * u[1], u[2]])
    if kind == "(2,0)":
        return np.array([-s * u[0], c * u[0], u[1]])
    if kind == "(2,1)":
        b = X[3]
        return np.array([-np.sin(th + b) * u[0], np.cos(th + b) * u[0], u[1], u[2]])
    if kind == "(1,1)":
        b = X[3]
        return np.array([-L * s * np.sin(b) * u[0], L * c * np.sin(b) * u[0], np.cos(b) * u[0], u[1]])
    if kind == "(1,2)":
        b1, b2 = X[3], X[4]
        return np.array(
            [
                (-2 * L * c * np.sin(b1) * np.sin(b2) - L * s * np.sin(b1 + b2)) * u[0],
                (-2 * L * s * np.sin(b1) * np.sin(b2) + L * c * np.sin(b1 + b2)) * u[0],
                np.sin(b2 - b1) * u[0],
                u[1],
                u[2],
            ]
        )
    raise AssertionError(kind)


KINDS = ["(3,0)", "(2,0)", "(2,1)", "(1,1)", "(1,2)"]


@pytest.mark.parametrize("kind", KINDS)
def test_kinematic_equals_table1(kind, rng):
    rt = w.robot_type(kind)
    for _ in range(10):
        X = rng.uniform(-4, 4, size=rt.n_state)
        u = rng.normal(size=rt.n_input)
        L = rng.uniform(0.2, 2.0)
        g = w.Geometry(L=L)
        np.testing.assert_allclose(
            robots.kinematic(rt, jnp.asarray(X), jnp.asarray(u), g), table1(kind, X, u, L), rtol=1e-12, atol=1e-12
        )
        B = robots.input_matrix(rt, jnp.asarray(X), g)
        assert B.shape == (rt.n_state, rt.n_input)
        assert np.linalg.matrix_rank(np.asarray(B)) == rt.n_input  # rank delta_m + delta_s (Remark 6)
        np.testing.assert_allclose(B @ u, table1(kind, X, u, L), rtol=1e-12, atol=1e-12)
        v = rng.normal(size=rt.n_input)
        d = robots.dynamic(rt, jnp.concatenate([X, u]), jnp.asarray(v), g)
        np.testing.assert_allclose(d, np.concatenate([table1(kind, X, u, L), v]), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", KINDS)
def test_the_geometry_the_kinematics_use_is_table1s(kind, rng):
    """kinematics_use_geometry (read from the model's program) against Table 1 typed in above: it
    moves with L for (1,1) and (1,2) only, and with e never. Where it says False, the model
    with any geometry is the model with the default one, bit for bit."""
    rt = w.robot_type(kind)
    moves = False
    for _ in range(5):
        X, u = rng.uniform(-4, 4, size=rt.n_state), rng.normal(size=rt.n_input)
        moves |= not np.allclose(table1(kind, X, u, 0.5), table1(kind, X, u, 1.5), rtol=0, atol=1e-12)
        if not robots.kinematics_use_geometry(rt):
            g = w.Geometry(L=rng.uniform(0.2, 2.0), e=rng.uniform(-1, 1), delta=rng.uniform(-3, 3))
            same = robots.kinematic(rt, jnp.asarray(X), jnp.asarray(u), w.Geometry())
            assert np.array_equal(robots.kinematic(rt, jnp.asarray(X), jnp.asarray(u), g), same)
    assert robots.kinematics_use_geometry(rt) == moves == (kind in ("(1,1)", "(1,2)"))


def test_models_vmap_over_geometry():
    rt = w.robot_type("(1,1)")
    X = jnp.array([0.0, 0.0, 0.3, 0.7])
    u = jnp.array([1.0, 0.0])
    Ls = jnp.array([0.5, 1.0, 2.0])
    out = jax.vmap(lambda L: robots.kinematic(rt, X, u, w.Geometry(L=L)))(Ls)
    np.testing.assert_allclose(out[:, 1], Ls * np.cos(0.3) * np.sin(0.7))


@pytest.mark.parametrize("spec", ["(2,0)", "2,0", "20", (2, 0)])
def test_robot_type_spellings(spec):
    assert w.robot_type(spec).name == "(2,0)"


@pytest.mark.parametrize("bad", ["(4,0)", "(0,1)", "car", (3, 1), 5])
def test_unknown_robot_type_raises(bad):
    with pytest.raises(ValueError, match="unknown robot type"):
        w.robot_type(bad)


def test_model_argument_checks():
    g = w.Geometry()
    with pytest.raises(ValueError, match=r"state must have shape \(3,\)"):
        robots.check_model_args("(2,0)", jnp.zeros(4), jnp.zeros(2), g)
    with pytest.raises(ValueError, match=r"control must have shape \(3,\)"):
        robots.check_model_args("(2,1)", jnp.zeros(4), jnp.zeros(2), g)
    with pytest.raises(ValueError, match="state must be finite"):
        robots.check_model_args("(2,0)", jnp.array([0.0, jnp.nan, 0.0]), jnp.zeros(2), g)
    with pytest.raises(ValueError, match="geometry.e must be finite"):
        robots.check_model_args("(2,0)", jnp.zeros(3), jnp.zeros(2), w.Geometry(e=float("inf")))
    with pytest.raises(ValueError, match=r"state must have shape \(6,\)"):
        robots.check_model_args("(1,1)", jnp.zeros(4), jnp.zeros(2), g, torque=True)
    with pytest.raises(ValueError, match="geometry must be a wmrjax.Geometry"):
        robots.check_geometry((1.0, 0.0, 0.0))


@pytest.mark.parametrize("L_w", [1.0, 2.7])
def test_car_model_conversion_11(L_w, rng):
    """The README's conversion from the car model (rear-axle midpoint, heading psi from the world
    x-axis, speed v, front steering phi, wheelbase L_w) to the (1,1) state and input."""
    for _ in range(20):
        x_r, y_r, psi = rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-np.pi, np.pi)
        v, phi, phi_dot = rng.uniform(-2, 2), rng.uniform(-1.2, 1.2), rng.uniform(-0.5, 0.5)
        X = jnp.array([x_r, y_r, psi + np.pi / 2, phi - np.pi / 2])
        u = jnp.array([v / (L_w * np.cos(phi)), phi_dot])
        Xdot = np.asarray(robots.kinematic(robots.robot_type("(1,1)"), X, u, w.Geometry(L=L_w)))
        car = [v * np.cos(psi), v * np.sin(psi), v * np.tan(phi) / L_w, phi_dot]  # the car model
        np.testing.assert_allclose(Xdot, car, rtol=1e-12, atol=1e-12)
        back_v = -L_w * np.sin(float(X[3])) * float(u[0])  # the inverse map
        back_phi = np.arctan(-np.cos(float(X[3])) / np.sin(float(X[3])))
        np.testing.assert_allclose([back_v, back_phi], [v, phi], rtol=1e-12, atol=1e-12)
