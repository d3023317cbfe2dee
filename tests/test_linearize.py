"""The generic engine against the paper's closed forms (eqs 39, 43, errata determinants)."""

import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax import linearize
from wmrjax.gains import monic_coefficients


def _rand_state(ctrl, rng):
    z = rng.uniform(-2, 2, size=ctrl.n_state)
    return jnp.asarray(z)


@pytest.mark.parametrize("e", [0.0, 0.35, -0.8])
def test_20_velocity_K_is_eq39(e, rng):
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    g = w.Geometry(e=e)
    for _ in range(10):
        z = _rand_state(ctrl, rng)
        x, y, th, chi1 = np.asarray(z)
        zeta, a, K = ctrl.law.jet(z, g)
        # Psi (eq 38): h = (x + e cos, y + e sin), hdot = chi1 (-sin, cos)
        np.testing.assert_allclose(
            zeta,
            [[x + e * np.cos(th), y + e * np.sin(th)], [-chi1 * np.sin(th), chi1 * np.cos(th)]],
            rtol=1e-12,
            atol=1e-12,
        )
        # eq (39): h1'' = -chi1 cos(th) eta2 - sin(th) U1, h2'' = -chi1 sin(th) eta2 + cos(th) U1; U = (U1, eta2)
        np.testing.assert_allclose(
            K, [[-np.sin(th), -chi1 * np.cos(th)], [np.cos(th), -chi1 * np.sin(th)]], rtol=1e-12, atol=1e-12
        )
        np.testing.assert_allclose(a, [0.0, 0.0], atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(np.asarray(K)), chi1, rtol=1e-12)
        assert (
            float(
                linearize.input_leakage(lambda q, U: ctrl.law.field(q, U, g), lambda q: ctrl.law.outputs(q, g), z, 2, 2)
            )
            < 1e-14
        )


@pytest.mark.parametrize("e", [0.0, 0.4])
def test_20_torque_reproduces_eq43(e, rng):
    """Torque level by the Lemma 1 cascade: h''' = a + K (U2, v2), eq (43); det K = chi1."""
    ctrl = w.dynamic_linearization("(2,0)", "torque")
    g = w.Geometry(e=e)
    assert ctrl.relative_degree == 3 and ctrl.n_state == 6
    for _ in range(6):
        z = _rand_state(ctrl, rng)
        x, y, th, chi1, U1, eta2 = np.asarray(z)  # cascade coordinates: chi2 = U1 = chi1'
        chi2 = U1
        zeta, a, K = ctrl.law.jet(z, g)
        s, c = np.sin(th), np.cos(th)
        # eq (43) with V = (U2, v2): h1''' = -U2 s - v2 c chi1 - 2 eta2 c chi2 + eta2^2 s chi1
        np.testing.assert_allclose(
            a,
            [-2 * eta2 * c * chi2 + eta2**2 * s * chi1, -2 * eta2 * s * chi2 - eta2**2 * c * chi1],
            rtol=1e-11,
            atol=1e-11,
        )
        np.testing.assert_allclose(K, [[-s, -c * chi1], [c, -s * chi1]], rtol=1e-12, atol=1e-12)
        # plant input v = d/dt (eta1, eta2) with eta1 = chi1 - e eta2: v = (U1 - e v2, v2)
        U = jnp.asarray(rng.normal(size=2))
        v = ctrl.law.plant_control(z, U, g)
        np.testing.assert_allclose(v, [U1 - e * U[1], U[1]], rtol=1e-12, atol=1e-12)


# det K_e closed forms of errata.md, as functions of the velocity-level extended state
def _det_closed(kind, z, g):
    if kind == "(2,0)":
        return z[3]
    if kind == "(2,1)":
        return -z[4]
    if kind == "(1,1)":
        return -g.L * z[4] ** 2
    if kind == "(1,2)":
        return 4 * g.L**2 * z[5] ** 2 * np.sin(z[3]) * np.sin(z[4])
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["(2,0)", "(2,1)", "(1,1)", "(1,2)"])
@pytest.mark.parametrize("level", ["velocity", "torque"])
def test_det_K_matches_errata(kind, level, rng):
    ctrl = w.dynamic_linearization(kind, level)
    g = w.Geometry(L=rng.uniform(0.5, 1.5), e=rng.uniform(-1, 1), delta=rng.uniform(-1, 1))
    for _ in range(5):
        z = _rand_state(ctrl, rng)
        _, _, K = ctrl.law.jet(z, g)
        det = np.linalg.det(np.asarray(K))
        # same decoupling matrix at both levels (Lemma 1); the (1,1) K_e is diag(1, -L eta1^2)
        # in body axes, whose rotation has det 1; (1,2): 4 L^2 eta1^2 sin b1 sin b2
        exp = _det_closed(kind, np.asarray(z), g)
        np.testing.assert_allclose(det, exp, rtol=1e-10, atol=1e-12)
        leak = linearize.input_leakage(
            lambda q, U: ctrl.law.field(q, U, g), lambda q: ctrl.law.outputs(q, g), z, ctrl.m, ctrl.relative_degree
        )
        assert float(leak) < 1e-12


def test_monic_coefficients_and_companion():
    k = monic_coefficients(jnp.array([[1.0, 1.0], [2.0, 3.0]]))
    np.testing.assert_allclose(k, [[1.0, 2.0], [6.0, 5.0]])  # (s+1)^2, (s+2)(s+3)
    k3 = monic_coefficients(jnp.array([[1.0, 2.0, 4.0]]))
    np.testing.assert_allclose(k3, [[8.0, 14.0, 7.0]])
    A = np.asarray(linearize.companion(jnp.array([[1.0, 2.0], [6.0, 5.0]])))
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(A).real), [-3, -2, -1, -1], atol=1e-6)


@pytest.mark.parametrize("e", [0.0, 0.3])
@pytest.mark.parametrize("branch", [1, -1])
def test_psi_inverse_both_branches(e, branch, rng):
    ctrl = w.dynamic_linearization("(2,0)")
    g = w.Geometry(e=e)
    inv = ctrl.row.psi_inverse
    for _ in range(10):
        z = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-np.pi, np.pi), branch * rng.uniform(0.1, 3)])
        zeta = ctrl.law.jet(jnp.asarray(z), g)[0]
        back = np.asarray(inv(zeta, float(branch), g))
        np.testing.assert_allclose(back[[0, 1, 3]], z[[0, 1, 3]], rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(np.angle(np.exp(1j * (back[2] - z[2]))), 0.0, atol=1e-11)
        # the other branch maps to (theta + pi, -chi1): a different state with the same zeta
        other = np.asarray(inv(zeta, float(-branch), g))
        np.testing.assert_allclose(ctrl.law.jet(jnp.asarray(other), g)[0], zeta, atol=1e-11)
        assert np.sign(other[3]) == -branch


def _nested_output_jet(field, h, z, n_inputs, r):
    """The textbook construction: Lie derivatives by nested jvp, K by one jvp per input."""
    import jax

    zero = jnp.zeros((n_inputs,), z.dtype)
    fns = [h]
    for _ in range(r - 1):
        prev = fns[-1]
        fns.append(lambda x, prev=prev: jax.jvp(prev, (x,), (field(x, zero),))[1])
    top = lambda U: jax.jvp(fns[-1], (z,), (field(z, U),))[1]
    return jnp.stack([fn(z) for fn in fns]), top(zero), jax.jacfwd(top)(zero)


@pytest.mark.parametrize(
    "family,kind,level",
    [("dynamic", "(2,0)", "velocity")]
    + [
        (f, k, "torque")
        for f, k in [
            ("dynamic", "(2,0)"),
            ("dynamic", "(2,1)"),
            ("dynamic", "(1,1)"),
            ("dynamic", "(1,2)"),
            ("static", "(3,0)"),
            ("static", "(1,1)"),
        ]
    ],
)
def test_taylor_mode_engine_equals_nested_jvp(family, kind, level, rng):
    """Taylor mode along the flow = nested jvp Lie derivatives (the engine's two methods)."""
    import jax

    make = w.dynamic_linearization if family == "dynamic" else w.static_linearization
    law = make(kind, level).law
    g = w.Geometry(L=0.9, e=0.3)
    F = lambda x, U: law.field(x, U, g)
    h = lambda x: law.outputs(x, g)
    args = (law.m, law.relative_degree)
    zs = jnp.asarray(rng.uniform(-1.5, 1.5, size=(4, law.n_state)))
    ours = jax.jit(jax.vmap(lambda z: linearize.output_jet(F, h, z, *args, method="taylor")))(zs)
    ref = jax.jit(jax.vmap(lambda z: _nested_output_jet(F, h, z, *args)))(zs)
    for a, b in zip(ours, ref):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-11 * float(jnp.max(jnp.abs(b))))
    if level == "velocity":
        with pytest.raises(ValueError, match="method must be one of"):
            linearize.output_jet(F, h, zs[0], *args, method="lie")
