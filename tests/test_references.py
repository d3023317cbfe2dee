import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wmrjax import references as R

S2 = math.sqrt(2.0)


def test_paper_62_jet_matches_hand_derivatives():
    ref = R.paper_62()
    a = S2 * 1e-2 / 3
    for t in [0.0, 1.3, 4.9, 10.0]:
        u = 10 - 2 * t
        jet = R.taylor(ref.position, jnp.asarray(t), 3)
        exp = [a * u**3 - S2 / 2 * t + 5 * S2 / 6, -6 * a * u**2 - S2 / 2, 24 * a * u, -48 * a]
        np.testing.assert_allclose(jet[:, 0], exp, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(jet[:, 1], exp, rtol=1e-13, atol=1e-13)
        # heading: the robot moves along its x2 axis, down-left -> theta = 3 pi / 4
        np.testing.assert_allclose(ref.posture(jnp.asarray(t))[2], 3 * np.pi / 4, rtol=1e-14)
    # eq (65): M1(t) = |chi1_ref| = speed = 0.04 (10 - 2t)^2 + 1
    for t in [0.0, 2.5, 5.0, 8.0]:
        np.testing.assert_allclose(ref.speed(jnp.asarray(t)), 0.04 * (10 - 2 * t) ** 2 + 1.0, rtol=1e-13)


def test_paper_66_stops_at_origin():
    ref = R.paper_66()
    np.testing.assert_allclose(ref.position(jnp.asarray(10.0)), [0, 0], atol=1e-15)
    np.testing.assert_allclose(ref.speed(jnp.asarray(10.0)), 0.0, atol=1e-15)
    np.testing.assert_allclose(ref.position(jnp.asarray(0.0)), [10 * S2 / 6] * 2, rtol=1e-14)


def test_circle_jet_analytic():
    ref = R.circle(center=(1.0, -2.0), radius=3.0, omega=0.7, phase=0.2)
    t = jnp.asarray(1.1)
    jet = R.taylor(ref.position, t, 3)
    ph = 0.7 * 1.1 + 0.2
    for k in range(4):
        # d^k/dt^k (cos, sin)(w t + p) = w^k (cos, sin)(w t + p + k pi/2)
        exp = 3.0 * 0.7**k * np.array([np.cos(ph + k * np.pi / 2), np.sin(ph + k * np.pi / 2)])
        if k == 0:
            exp = exp + np.array([1.0, -2.0])
        np.testing.assert_allclose(jet[k], exp, rtol=1e-13, atol=1e-13)


def test_figure_eight_speed_floor():
    ref = R.figure_eight(size=3.0, omega=0.3)
    ts = jnp.linspace(0, 2 * np.pi / 0.3, 2001)
    speeds = jax.vmap(ref.speed)(ts)
    floor = 3.0 * 0.3 * np.sqrt(7) / 4
    assert float(speeds.min()) >= floor - 1e-12
    assert float(speeds.min()) <= floor * 1.001  # the bound is attained


def test_random_smooth_batch_has_speed_floor():
    keys = jax.random.split(jax.random.PRNGKey(0), 64)
    refs = jax.vmap(lambda k: R.random_smooth(k, speed=1.0, min_speed=0.3))(keys)
    ts = jnp.linspace(0.0, 30.0, 301)
    speeds = jax.vmap(lambda r: jax.vmap(r.speed)(ts))(refs)
    assert speeds.shape == (64, 301)
    assert float(speeds.min()) >= 0.3 - 1e-12
    assert float(speeds.max()) <= 1.7 + 1e-12
    # different keys, different references
    assert float(jnp.std(refs.params["omega"][:, 0])) > 0.05


def test_random_smooth_rejects_bad_floor():
    with pytest.raises(ValueError, match="min_speed"):
        R.random_smooth(jax.random.PRNGKey(0), speed=1.0, min_speed=1.5)


def test_named_reference_errors():
    assert R.named("paper_62").name == "paper_62"
    with pytest.raises(ValueError, match="unknown reference"):
        R.named("spiral")


def test_taylor_mode_jet_equals_nested_jvp_and_falls_back_for_loops():
    """references.taylor (Taylor mode) against nested jvp on a path heading along x at t = 0
    (heading derivatives through atan2 at a zero argument), and on a path written with a
    lax loop, which has no Taylor rule: the nested fallback gives the same numbers."""
    import jax

    def lane(t, params):
        s = t / 8.0
        return jnp.stack([2.0 * t, 3.5 * (10 * s**3 - 15 * s**4 + 6 * s**5)])

    def looped(t, params):
        x = jax.lax.fori_loop(0, 3, lambda i, x: x + jnp.sin(t * (i + 1.0)), 0.0)
        return jnp.stack([t + 0.1 * x, 0.3 * x])

    for path in (lane, looped):
        ref = R.from_function(path)
        for t in (0.0, 1.3):
            t = jnp.asarray(t)
            np.testing.assert_allclose(
                R.taylor(ref.posture, t, 4), R.taylor_nested(ref.posture, t, 4), rtol=1e-12, atol=1e-12
            )
    # heading theta = atan2(-x', y') at t = 0: -pi/2, theta' = 0, theta'' = x' y''' / |p'|^2
    np.testing.assert_allclose(
        R.taylor(R.from_function(lane).posture, jnp.asarray(0.0), 2)[:, 2],
        [-np.pi / 2, 0.0, 2.0 * (3.5 * 60 / 8**3) / 4.0],
        rtol=1e-14,
    )
