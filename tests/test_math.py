import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from wmrjax import _math
from wmrjax.references import taylor_nested


def test_sincos_matches_libm_to_an_ulp():
    x = np.concatenate(
        [np.linspace(-1e4, 1e4, 400_001), np.linspace(-7, 7, 100_001), [0.0, np.pi / 4, np.pi / 2, -np.pi]]
    )
    s, c = _math.sincos(jnp.asarray(x))
    big = np.abs(np.sin(x)) > 0.5  # relative accuracy where the value is O(1)
    np.testing.assert_array_max_ulp(np.asarray(s)[big], np.sin(x)[big], maxulp=2)
    assert np.max(np.abs(np.asarray(s) - np.sin(x))) <= 2.3e-16
    assert np.max(np.abs(np.asarray(c) - np.cos(x))) <= 2.3e-16


def test_sincos_derivatives_are_exact_functions():
    x = jnp.linspace(-10, 10, 101)
    ds = jax.vmap(jax.grad(lambda t: _math.sincos(t)[0]))(x)
    dc = jax.vmap(jax.grad(lambda t: _math.sincos(t)[1]))(x)
    np.testing.assert_allclose(ds, np.cos(np.asarray(x)), atol=3e-16)
    np.testing.assert_allclose(dc, -np.sin(np.asarray(x)), atol=3e-16)
    check_grads(lambda t: _math.sincos(t)[0] * _math.sincos(2 * t)[1], (jnp.array(0.7),), order=2)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_adjugate_solve_against_numpy(n, rng):
    for _ in range(5):
        k = rng.normal(size=(n, n))
        b = rng.normal(size=n)
        num, det = _math.adjugate_solve(jnp.asarray(k), jnp.asarray(b))
        np.testing.assert_allclose(det, np.linalg.det(k), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(num) / float(det), np.linalg.solve(k, b), rtol=1e-9, atol=1e-12)


def test_small_algebra_matches_jnp(rng):
    a, b = rng.normal(size=(3, 2)), rng.normal(size=(2, 4))
    np.testing.assert_allclose(_math.matmul(jnp.asarray(a), jnp.asarray(b)), a @ b, rtol=1e-14)
    f = lambda x: jnp.stack([jnp.sin(x[0]) * x[1], x[1] ** 3, x[0] * x[1]])
    x = jnp.array([0.3, -1.2])
    np.testing.assert_allclose(_math.jacfwd_small(f, x), jax.jacfwd(f)(x), rtol=1e-14)


def test_safe_divisor_keeps_sign_and_floor():
    d = jnp.array([-1.0, -1e-20, 0.0, 1e-20, 2.0])
    np.testing.assert_array_equal(_math.safe_divisor(d, 1e-12), [-1.0, -1e-12, 1e-12, 1e-12, 2.0])


@pytest.mark.parametrize("t", [0.0, 0.37, -1.2])
def test_taylor_rules_of_sincos_and_atan2_match_nested_jvp(t):
    """The primitives' Taylor-mode rules (jax.experimental.jet) against nested jvp, to order 5,
    including atan2 where its second argument is 0 (jet's own rule returns NaN there)."""
    from jax.experimental import jet

    curve = lambda s: _math.atan2(2.0 + s + s**3, s - 0.5 * s**2) + _math.sincos(3 * s)[0] * _math.sincos(s)[1]
    t = jnp.asarray(t)
    y, terms = jet.jet(curve, (t,), ([jnp.ones_like(t)] + [jnp.zeros_like(t)] * 4,))
    np.testing.assert_allclose(jnp.stack([y] + terms), taylor_nested(curve, t, 5), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        _math.atan2(jnp.asarray([1.0, -2.0, 0.5]), jnp.asarray([0.0, -1.0, 3.0])),
        np.arctan2([1.0, -2.0, 0.5], [0.0, -1.0, 3.0]),
        rtol=0,
        atol=0,
    )
