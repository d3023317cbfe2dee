"""The jaxpr simplifier behind output_jet: structural zeros folded, repeats emitted once, same values."""

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import jet

import wmrjax as w
from wmrjax import _simplify, linearize
from wmrjax.controllers import TABLE3, TABLE4


def _prims(fun, *args):
    return [e.primitive.name for e in jax.make_jaxpr(fun)(*args).jaxpr.eqns]


def test_zeros_fold_and_repeats_are_emitted_once():
    def f(x):
        z = jnp.zeros_like(x)
        return jnp.sin(x) * 2.0 + z * jnp.cos(x) + jnp.sin(x), (x - z) * 0.0

    x = jnp.linspace(-1.0, 1.0, 5)
    g = _simplify.simplify(f)
    for a, b in zip(jax.tree_util.tree_leaves(f(x)), jax.tree_util.tree_leaves(g(x))):
        np.testing.assert_array_equal(a, b)
    prims = _prims(g, x)
    assert prims.count("sin") == 1  # sin(x) twice in f
    assert "cos" not in prims  # only ever multiplied by zero
    assert prims.count("mul") == 1  # sin(x) * 2; the products with zeros are gone
    assert prims.count("add") == 1  # the added zero is dropped
    assert "sub" not in prims


def test_jet_of_a_product_with_a_constant_has_no_zero_series_arithmetic():
    L = 0.7

    def taylor(x):
        return jet.jet(lambda y: L * jnp.sin(y) * jnp.cos(y), (x,), ([1.0, 0.0, 0.0],))

    x = jnp.asarray(0.3)
    ref, ours = taylor(x), _simplify.simplify(taylor)(x)
    np.testing.assert_allclose(np.asarray(ours[1]), np.asarray(ref[1]), rtol=1e-15, atol=0)
    assert len(jax.make_jaxpr(_simplify.simplify(taylor))(x).jaxpr.eqns) < len(jax.make_jaxpr(taylor)(x).jaxpr.eqns)


def test_simplified_jet_transforms_like_the_original():
    """jvp / grad through the closed-over geometry, vmap over states: identical to the unsimplified jet."""
    ctrl = w.dynamic_linearization("1,1", "velocity")
    ref = w.references.circle(radius=2.0, omega=0.4, heading_offset=ctrl.row.default_heading_offset)
    params = ctrl.params(ref, poles=1.5, geometry=ctrl.row.default_geometry)
    law = ctrl.law
    z0 = ctrl.reference_state(0.0, params)
    zs = z0 + 0.01 * jnp.asarray(np.random.default_rng(0).normal(size=(3, z0.size)))

    def jet_of(L, z, simplify):
        g = params.geometry._replace(L=L)
        zeta, a, K = linearize.output_jet(
            lambda x, U: law.field(x, U, g),
            lambda x: law.outputs(x, g),
            z,
            law.m,
            law.relative_degree,
            simplify=simplify,
        )
        return jnp.sum(zeta**2) + jnp.sum(a * jnp.sin(a)) + jnp.linalg.det(K)

    L0 = params.geometry.L
    vg = jax.jit(jax.vmap(jax.value_and_grad(jet_of, argnums=(0, 1)), in_axes=(None, 0, None)), static_argnums=2)
    (v0, (dL0, dz0)), (v1, (dL1, dz1)) = (vg(L0, zs, simplify) for simplify in (False, True))
    np.testing.assert_allclose(v1, v0, rtol=1e-13)
    np.testing.assert_allclose(dL1, dL0, rtol=1e-12)
    np.testing.assert_allclose(dz1, dz0, rtol=1e-12, atol=1e-13)


def test_every_rows_jet_program_is_smaller():
    """Every Table 3/4 row at both levels, both engines: simplification removes equations. (The
    simplified values are checked against the closed forms and the independent nested-jvp
    oracle in test_linearize.)"""
    rng = np.random.default_rng(1)
    for make, table in ((w.dynamic_linearization, TABLE4), (w.static_linearization, TABLE3)):
        for kind in table:
            for level in ("velocity", "torque"):
                ctrl = make(kind, level)
                law, g = ctrl.law, ctrl.row.default_geometry
                z = jnp.asarray(rng.uniform(0.2, 0.9, size=law.n_state))
                for method in ("nested", "taylor"):
                    counts = [
                        len(
                            jax.make_jaxpr(
                                lambda x: linearize.output_jet(
                                    lambda y, U: law.field(y, U, g),
                                    lambda y: law.outputs(y, g),
                                    x,
                                    law.m,
                                    law.relative_degree,
                                    method=method,
                                    simplify=s,
                                )
                            )(z).jaxpr.eqns
                        )
                        for s in (False, True)
                    ]
                    assert counts[1] < 0.9 * counts[0], (kind, level, method, counts)


def test_element_slices_become_one_split_and_transpose_to_one_concatenate():
    """x[0], x[1], ... of a vector (and k[i, j] of a matrix) are pieces of one split per axis:
    same values and gradients, and the gradient program has no zero-padded vector per element."""

    def f(x, k):
        return x[0] * x[3] + jnp.sin(x[1]) * x[2] + k[0, 0] * k[1, 1] - k[0, 1] * k[1, 0] + x[1:3].sum()

    x, k = jnp.linspace(0.1, 0.7, 4), jnp.asarray([[1.0, 2.0], [3.0, 5.0]])
    g = _simplify.simplify(f)
    np.testing.assert_array_equal(g(x, k), f(x, k))
    for a, b in zip(jax.grad(f, argnums=(0, 1))(x, k), jax.grad(g, argnums=(0, 1))(x, k)):
        np.testing.assert_allclose(b, a, rtol=1e-15, atol=0)
    prims = _prims(g, x, k)
    assert prims.count("split") == 4  # x along axis 0; k along axis 0, then each of its rows
    assert prims.count("slice") == 1  # x[1:3] is not one element wide: kept
    back = _prims(jax.grad(g, argnums=(0, 1)), x, k)
    assert back.count("pad") == 1 and back.count("concatenate") == 4, back
    assert _prims(jax.grad(f, argnums=(0, 1)), x, k).count("pad") == 9


def test_simulate_program_has_no_per_element_pads_in_reverse_mode(monkeypatch):
    """The closed-loop field is simplified inside simulate: reverse mode through the section 6.1
    rollout has no per-element pads (the transposes of element slices; the backward step was 2x
    slower with them), where the plain JAX program of the same loss has over a hundred."""
    ctrl = w.dynamic_linearization("2,0", "velocity")
    params = ctrl.params(w.references.circle(radius=2.0, omega=0.4), poles=1.5)
    z0 = ctrl.reference_state(0.0, params) + 0.01

    def loss(coeffs):
        tr = w.simulate(ctrl, z0, params._replace(gains=w.Gains(coeffs)), dt=0.01, n_steps=4)
        return jnp.sum(tr.state[-2:] ** 2)

    def eqns(jaxpr):
        for e in jaxpr.eqns:
            yield e
            for v in e.params.values():
                sub = getattr(v, "jaxpr", v)
                if hasattr(sub, "eqns"):
                    yield from eqns(sub)

    def pads():  # (all pads, the per-element ones) of the gradient's program
        prog = list(eqns(jax.make_jaxpr(jax.grad(loss))(params.gains.coeffs).jaxpr))
        found = [e for e in prog if e.primitive.name == "pad"]
        per_element = [
            e
            for e in found
            if any(
                n == 1 and (lo, hi) != (0, 0)
                for n, (lo, hi, _) in zip(e.invars[0].aval.shape, e.params["padding_config"])
            )
        ]
        return found, per_element

    found, per_element = pads()
    assert not per_element, [str(e) for e in per_element[:3]]
    assert len(found) < 60  # the remaining ones: X[:3] of the (4,) state, one per use
    monkeypatch.setenv(_simplify.REWRITES_ENV, "0")  # the check sees them where they are
    assert len(pads()[1]) > 40


def test_zero_folding_ieee_caveat_and_the_switch(monkeypatch):
    """The documented IEEE caveat: a structural zero times an infinity and a structural zero
    divided by zero fold to 0 under the simplifier, where the plain program (the switch
    WMRJAX_JAXPR_REWRITES=0) gives NaN; finite operands give the same values either way."""
    f = lambda x: (0.0 * x, 0.0 / x, jnp.zeros(2) @ jnp.stack([x, x]))
    inf, zero, one = jnp.asarray(jnp.inf), jnp.asarray(0.0), jnp.asarray(1.5)
    monkeypatch.delenv(_simplify.REWRITES_ENV, raising=False)
    g = _simplify.simplify(f)
    assert "mul" not in _prims(g, one) and "div" not in _prims(g, one)  # folded at trace time
    assert [float(v) for v in g(inf)] == [0.0, 0.0, 0.0]  # 0 * inf, 0 * inf summed
    assert float(g(zero)[1]) == 0.0  # 0 / 0
    monkeypatch.setenv(_simplify.REWRITES_ENV, "0")
    g = _simplify.simplify(f)  # a new function: JAX caches the traces of the old one
    assert _prims(g, one) == _prims(f, one)  # the plain program
    assert np.isnan(float(g(inf)[0])) and np.isnan(float(g(inf)[2])) and np.isnan(float(g(zero)[1]))
    for x in (zero, one):
        assert [float(v) for v in g(x)][::2] == [0.0, 0.0]
