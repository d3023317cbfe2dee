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


@pytest.mark.parametrize("shape", [(2, 2), (2, 6), (4, 4), (6, 6), (3, 5), (5, 2), (1, 3), (3, 1)])
def test_svd_small_against_numpy(shape, rng):
    """Singular values to 2e-15 of the largest (NumPy's LAPACK SVD), U diag(s) Vt = M, orthonormal
    factors, at magnitudes from 1e-3 to 1e3 and at 1e-217 (a long horizon's expm(A t))."""
    for scale in (1e-3, 1.0, 1e3, 1e-217):
        M = rng.normal(size=shape) * scale
        U, s, Vt = jax.jit(_math.svd_small)(jnp.asarray(M))
        ref = np.linalg.svd(M, compute_uv=False)
        np.testing.assert_allclose(np.asarray(s), ref, rtol=0, atol=2e-15 * ref[0])
        assert np.all(np.diff(np.asarray(s)) <= 0)
        np.testing.assert_allclose(np.asarray(U) @ np.diag(np.asarray(s)) @ np.asarray(Vt), M, atol=1e-14 * ref[0])
        k = min(shape)
        np.testing.assert_allclose(np.asarray(U).T @ np.asarray(U), np.eye(k), atol=1e-14)
        np.testing.assert_allclose(np.asarray(Vt) @ np.asarray(Vt).T, np.eye(k), atol=1e-14)
        np.testing.assert_allclose(float(_math.spectral_norm(jnp.asarray(M))), ref[0], rtol=2e-15)


def test_svd_small_of_a_rank_deficient_matrix_has_finite_factors():
    """A zero singular value gets a zero row of Vt (not NaN): the exact map multiplies it by zero."""
    M = jnp.asarray([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0]])
    U, s, Vt = _math.svd_small(M)
    np.testing.assert_allclose(np.asarray(s), np.linalg.svd(np.asarray(M), compute_uv=False), atol=1e-15)
    assert np.all(np.isfinite(np.asarray(Vt))) and float(s[1]) < 1e-15


def test_spectral_norm_gradient_matches_lapack(rng):
    """Its gradient is u1 v1^T (the largest singular pair): equal to the LAPACK norm's, both modes."""
    M = jnp.asarray(rng.normal(size=(4, 4)))
    ref = jax.grad(lambda m: jnp.linalg.norm(m, 2))(M)
    np.testing.assert_allclose(np.asarray(jax.grad(_math.spectral_norm)(M)), np.asarray(ref), atol=1e-12)
    np.testing.assert_allclose(np.asarray(jax.jacfwd(_math.spectral_norm)(M)), np.asarray(ref), atol=1e-12)


def _expm_extended(A):
    """exp(A) in NumPy's extended precision (x86's 80-bit long double: 2^-63): scaling until the
    row-sum norm is below 1/16, 40 Taylor terms, then squaring. Its own error (about 2^s of the
    extended unit roundoff, s <= 11 here) is 1e-15 of float64's at most: an oracle for expm_small."""
    A = np.asarray(A, dtype=np.longdouble)
    s = max(0, int(np.ceil(np.log2(max(np.abs(A).sum(axis=1).max(), 1e-300)))) + 4)
    B, term = A / np.longdouble(2.0**s), np.eye(len(A), dtype=np.longdouble)
    E = term.copy()
    for k in range(1, 40):
        term = term @ B / k
        E = E + term
    for _ in range(s):
        E = E @ E
    return E


def test_expm_small_against_an_extended_precision_oracle_and_scipy(rng):
    """Against exp(A) in extended precision (1e-12 of its largest entry; 3.1e-13 was the worst of
    600 random 2x2 (x30), 4x4 and 6x6 (x3) draws) and SciPy's expm (Al-Mohy and Higham, whose own
    error reached 9.7e-12 on those draws and 1.4e-12 on one that failed a 1e-12 bound in CI), from
    ||A|| = 0 to 1e3, companion matrices of the error dynamics included."""
    from scipy.linalg import expm

    from wmrjax import linearize

    A3 = np.asarray(linearize.companion(jnp.asarray([[1.0, 3.0, 3.0], [1.0, 3.0, 3.0]])))  # poles -1 (x3)
    cases = [np.zeros((3, 3)), rng.normal(size=(4, 4)), 30.0 * rng.normal(size=(2, 2))]
    cases += [A3 * t for t in (0.01, 1.0, 5.0, 20.0)]
    extended = np.finfo(np.longdouble).eps < 1e-18  # not on platforms whose long double is a double
    for A in cases:
        got = np.asarray(jax.jit(_math.expm_small)(jnp.asarray(A)))
        scale = np.abs(expm(A)).max()
        np.testing.assert_allclose(got, expm(A), rtol=0, atol=5e-11 * scale)
        if extended:
            err = np.abs(got.astype(np.longdouble) - _expm_extended(A)).max()
            assert float(err) <= 1e-12 * scale


def test_expm_small_derivatives_and_overflow(rng):
    """Its derivatives in both modes against jax.scipy.linalg.expm's; NaN beyond MAX_SQUARINGS."""
    A = jnp.asarray(0.7 * rng.normal(size=(3, 3)))
    f = lambda a: jnp.sum(jnp.sin(_math.expm_small(a)))
    g = lambda a: jnp.sum(jnp.sin(jax.scipy.linalg.expm(a)))
    np.testing.assert_allclose(np.asarray(jax.grad(f)(A)), np.asarray(jax.grad(g)(A)), atol=1e-12)
    np.testing.assert_allclose(np.asarray(jax.jacfwd(f)(A)), np.asarray(jax.grad(g)(A)), atol=1e-12)
    assert np.isnan(np.asarray(_math.expm_small(jnp.asarray([[2.0**41]])))).all()


@pytest.mark.parametrize("n, w, block", [(23, 6, 5), (40, 8, 7), (7, 6, 7), (64, 6, 5)])
def test_banded_solve_is_the_dense_solve_and_its_gradient(n, w, block, rng):
    """banded_solve against numpy's dense solve (a random banded system with rows within ``block``
    columns of the diagonal, sizes that do and do not fill whole blocks), and its gradient in the
    entries and the right-hand side against the dense solve's (jax.grad of both)."""
    half = w // 2
    starts = np.clip(np.arange(n) - half, 0, n - w)
    vals = rng.normal(size=(n, w))
    vals[np.arange(n), np.arange(n) - starts] += 4.0  # the diagonal: a well-posed system
    rhs = rng.normal(size=(n, 2))

    def dense(v):
        A = jnp.zeros((n, n)).at[np.arange(n)[:, None], starts[:, None] + np.arange(w)].set(v)
        return A

    x = np.asarray(_math.banded_solve(jnp.asarray(vals), jnp.asarray(starts), jnp.asarray(rhs), block))
    np.testing.assert_allclose(x, np.linalg.solve(np.asarray(dense(vals)), rhs), rtol=0, atol=1e-12)
    weights = rng.normal(size=(n, 2))
    f_band = lambda v, b: jnp.sum(weights * _math.banded_solve(v, jnp.asarray(starts), b, block))
    f_dense = lambda v, b: jnp.sum(weights * jnp.linalg.solve(dense(v), b))
    for g1, g2 in zip(
        jax.grad(f_band, (0, 1))(jnp.asarray(vals), jnp.asarray(rhs)),
        jax.grad(f_dense, (0, 1))(jnp.asarray(vals), jnp.asarray(rhs)),
    ):
        np.testing.assert_allclose(g1, g2, rtol=1e-10, atol=1e-12)
