"""Scalarization of small-array programs: same values and derivatives, no array assembly left."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

import wmrjax as w
from wmrjax import _math, _scalarize, _simplify

STRUCTURAL = {
    "concatenate",
    "stack",
    "unstack",
    "split",
    "slice",
    "transpose",
    "reshape",
    "broadcast_in_dim",
    "dot_general",
    "pad",
    "rev",
    "squeeze",
    "reduce_sum",
    "reduce_max",
    "scatter",
    "iota",
}


def _prims(fun, *args):
    return [e.primitive.name for e in jax.make_jaxpr(fun)(*args).jaxpr.eqns]


def _all_prims(jaxpr):
    """Primitive names of a jaxpr and of every jaxpr nested in it (loop bodies, calls)."""
    out = []
    for e in jaxpr.eqns:
        out.append(e.primitive.name)
        for sub in jax.extend.core.jaxprs_in_params(e.params):
            out += _all_prims(sub)
    return out


def _mixed(x, m, v):
    """Every structural rule: x (3,), m (2, 3), v (2,)."""
    b = jnp.broadcast_to(x, (2, 3)) * m  # broadcast_in_dim
    t = b.T.reshape(6)[::2]  # transpose, reshape, strided slice
    c = jnp.concatenate([t, v, jnp.stack([x[0], m[1, 2]])])  # concatenate, stack, squeeze
    p = lax.pad(c, 0.5, [(-1, 2, 1)])  # negative low, high, interior padding
    r = jnp.flip(p)[1:4] + jnp.arange(3.0)  # rev, iota
    a, rest = jnp.split(m, [1], axis=0)  # split
    rows = jnp.unstack(m, axis=1)  # unstack
    d = m @ x + jnp.einsum("ij,ij->i", m, m) + a[0, :2] @ rest[0, :2]  # dot_general, batch dims
    s = jnp.sum(b, axis=(0, 1)) - jnp.max(m, axis=0).sum() * jnp.prod(v) + jnp.min(m)
    k = jnp.zeros(3).at[1].set(x[2])  # scatter at static indices
    sc, cc = _math.sincos(x)
    e = jnp.where(x > 0.1, jnp.clip(x, -0.2, 0.3) ** 3, _math.atan2(x, 1.0 + x**2))
    return r, d, s + rows[2][1], k + sc * cc, e, jnp.expand_dims(v, 0)


@pytest.fixture(scope="module")
def args():
    rng = np.random.default_rng(3)
    return jnp.asarray(rng.normal(size=3)), jnp.asarray(rng.normal(size=(2, 3))), jnp.asarray(rng.normal(size=2))


def test_values_equal_the_array_program(args):
    want = _mixed(*args)
    got = jax.jit(_scalarize.scalarize(_mixed))(*args)
    for a, b in zip(jax.tree_util.tree_leaves(want), jax.tree_util.tree_leaves(got)):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_allclose(b, a, rtol=1e-14, atol=1e-15)


def test_no_array_operation_is_left(args):
    """Only the inputs' unstack and the outputs' stacks remain: everything else is scalar."""
    prims = _prims(_scalarize.scalarize(_mixed), *args)
    assert set(prims) & STRUCTURAL <= {"unstack", "stack", "reshape"}
    assert prims.count("unstack") == 3  # x, m and v, each taken apart once
    assert "dot_general" not in prims and "concatenate" not in prims and "scatter" not in prims


def test_derivatives_equal_those_of_the_array_program(args):
    def total(f):
        return lambda *a: sum(jnp.sum(jnp.sin(o)) for o in jax.tree_util.tree_leaves(f(*a)))

    want = jax.grad(total(_mixed), argnums=(0, 1, 2))(*args)
    got = jax.jit(jax.grad(total(_scalarize.scalarize(_mixed)), argnums=(0, 1, 2)))(*args)
    for a, b in zip(want, got):
        np.testing.assert_allclose(b, a, rtol=1e-13, atol=1e-14)
    tangents = tuple(jnp.ones_like(a) for a in args)
    _, jw = jax.jvp(_mixed, args, tangents)
    _, jg = jax.jvp(_scalarize.scalarize(_mixed), args, tangents)
    for a, b in zip(jax.tree_util.tree_leaves(jw), jax.tree_util.tree_leaves(jg)):
        np.testing.assert_allclose(b, a, rtol=1e-13, atol=1e-14)


def test_vmap_batches_elements_as_vectors(args):
    xs = jnp.stack([args[0], 2.0 * args[0], -args[0]])
    want = jax.vmap(lambda x: _mixed(x, args[1], args[2]))(xs)
    got = jax.jit(jax.vmap(_scalarize.scalarize(lambda x: _mixed(x, args[1], args[2]))))(xs)
    for a, b in zip(jax.tree_util.tree_leaves(want), jax.tree_util.tree_leaves(got)):
        np.testing.assert_allclose(b, a, rtol=1e-14, atol=1e-15)


def test_constants_are_folded_at_trace_time():
    def f(x):
        c = jnp.exp(lax.lgamma(jnp.asarray([3.0, 4.0])))  # (2, 6)
        return x * c[0] + c[1]

    prims = _prims(_scalarize.scalarize(f), 1.5)
    assert "lgamma" not in prims and "exp" not in prims
    np.testing.assert_allclose(_scalarize.scalarize(f)(1.5), 9.0, rtol=1e-14)


def test_large_arrays_and_primitives_without_rules_stay_whole():
    n = 9  # 81 elements > MAX_ELEMENTS
    assert n * n > _scalarize.MAX_ELEMENTS

    @jax.custom_jvp
    def halved_slope(x):
        return jnp.tanh(x)

    halved_slope.defjvp(lambda p, t: (halved_slope(p[0]), 0.5 * t[0]))

    def f(a, x):
        y = jnp.cumsum(x)  # no rule
        z = lax.cond(x[0] > 0, lambda u: u * 2.0, lambda u: -u, y)  # control flow
        return a @ jnp.tile(z, 3) + halved_slope(x).sum()

    a = jnp.asarray(np.random.default_rng(0).normal(size=(n, n)))
    x = jnp.asarray([0.3, -0.2, 0.1])
    prims = _prims(_scalarize.scalarize(f), a, x)
    assert {"dot_general", "cumsum", "cond", "custom_jvp_call"} <= set(prims)
    np.testing.assert_allclose(_scalarize.scalarize(f)(a, x), f(a, x), rtol=1e-14)
    gx = jax.grad(lambda x: _scalarize.scalarize(f)(a, x).sum())(x)  # the custom rule is kept
    np.testing.assert_allclose(gx, jax.grad(lambda x: f(a, x).sum())(x), rtol=1e-13)


def test_section_6_1_field_is_unchanged_and_smaller(paper61):
    """The section 6.1 field, scalarized and simplified: same values, a smaller program."""
    ctrl, params, z0 = paper61[:3]
    field = lambda t, z: ctrl.vector_field(t, z, params)
    fast = _simplify.simplify(_scalarize.scalarize(_simplify.simplify(field)))
    z = z0 + 0.01
    for a, b in zip(jax.tree_util.tree_leaves(field(0.7, z)), jax.tree_util.tree_leaves(jax.jit(fast)(0.7, z))):
        np.testing.assert_allclose(b, a, rtol=1e-13, atol=1e-15)
    assert len(_prims(fast, 0.7, z)) < len(_prims(_simplify.simplify(field), 0.7, z)) / 2


def test_simulate_loop_body_assembles_no_arrays(paper61):
    """The scan bodies of a rollout's gradient (forward and transposed) assemble no arrays."""
    ctrl, params, z0 = paper61[:3]

    def loss(gains):
        p = params._replace(gains=w.Gains(gains))
        return jnp.sum(w.simulate(ctrl, z0, p, dt=0.01, n_steps=20, save_every=5).state[:, :2] ** 2)

    jaxpr = jax.make_jaxpr(jax.grad(loss))(params.gains.coeffs).jaxpr

    def scans(j):
        for e in j.eqns:
            if e.primitive.name == "scan":
                yield e.params["jaxpr"].jaxpr
            for sub in jax.extend.core.jaxprs_in_params(e.params):
                yield from scans(sub)

    bodies = list(scans(jaxpr))
    assert len(bodies) == 4  # outer and inner loops, forward and backward
    for body in bodies:
        p = _all_prims(body)
        # the forward body assembles the saved sample (state and control), the backward one
        # takes the sample's cotangent apart: nothing else, in particular nothing per RK stage
        assert p.count("stack") <= 2 and p.count("unstack") <= 1, (p.count("stack"), p.count("unstack"))
        assert not {"concatenate", "slice", "split", "transpose", "dot_general"} & set(p)


def test_scalar_parts_take_apart_small_float_leaves_only():
    tree = {
        "k": jnp.arange(4.0).reshape(2, 2),
        "big": jnp.linspace(0.0, 1.0, 100),
        "n": jnp.arange(3),
        "s": jnp.asarray(2.5),
    }
    parts, rebuild = w.scalar_parts(tree)
    by_name = dict(zip(sorted(tree), parts))  # dict leaves flatten in key order
    assert isinstance(by_name["k"], tuple) and len(by_name["k"]) == 4 and by_name["k"][3].shape == ()
    assert by_name["big"] is tree["big"] and by_name["n"] is tree["n"] and by_name["s"] is tree["s"]
    back = rebuild(parts)
    for name in tree:
        np.testing.assert_array_equal(back[name], tree[name])
        assert back[name].shape == tree[name].shape and back[name].dtype == tree[name].dtype


def test_scalarized_loop_body_with_scalar_parts_matches_the_array_loop():
    """A hand-written loop as the tuner writes it: scalar carry, parameters taken apart outside."""
    a = jnp.asarray([[0.0, 1.0], [-2.0, -0.3]])

    def array_loop(a, x0):
        return jax.lax.scan(lambda x, _: (x + 0.01 * (a @ x + jnp.sin(x)), None), x0, None, length=50)[0]

    def scalar_loop(a, x0):
        parts, rebuild = w.scalar_parts(a)
        body = w.scalarized(
            lambda xs: tuple(
                jnp.unstack(jnp.stack(xs) + 0.01 * (rebuild(parts) @ jnp.stack(xs) + jnp.sin(jnp.stack(xs))))
            )
        )
        return jnp.stack(jax.lax.scan(lambda xs, _: (body(xs), None), tuple(jnp.unstack(x0)), None, length=50)[0])

    x0 = jnp.asarray([1.0, -0.5])
    np.testing.assert_allclose(jax.jit(scalar_loop)(a, x0), array_loop(a, x0), rtol=1e-14)
    ga = jax.grad(lambda a: jnp.sum(array_loop(a, x0) ** 2))(a)
    gs = jax.jit(jax.grad(lambda a: jnp.sum(scalar_loop(a, x0) ** 2)))(a)
    np.testing.assert_allclose(gs, ga, rtol=1e-12)
    jaxpr = jax.make_jaxpr(jax.grad(lambda a: jnp.sum(scalar_loop(a, x0) ** 2)))(a).jaxpr
    bodies = [e.params["jaxpr"].jaxpr for e in jaxpr.eqns if e.primitive.name == "scan"]
    assert len(bodies) == 2 and all(
        {"stack", "unstack", "dot_general"}.isdisjoint(q.primitive.name for q in b.eqns) for b in bodies
    )


def _stage_loops(fun, *args):
    """How many RK stage loops (scans of length 4 over a checkpointed body) the program of ``fun`` holds."""

    def count(jaxpr):
        n = 0
        for e in jaxpr.eqns:
            if e.primitive.name == "scan" and e.params["length"] == 4:
                n += "remat2" in [q.primitive.name for q in e.params["jaxpr"].jaxpr.eqns]
            n += sum(count(sub) for sub in jax.extend.core.jaxprs_in_params(e.params))
        return n

    return count(jax.make_jaxpr(fun)(*args).jaxpr)


def test_stage_loop_equals_the_unrolled_step(paper61, monkeypatch):
    """The RK stages run in a loop (the large laws' step) give the unrolled step's rollout,
    diagnostics and gradient (reverse and forward mode) to rounding."""
    import importlib

    simulate_module = importlib.import_module("wmrjax.simulate")  # the module (wmrjax.simulate is also the function)

    ctrl, params, z0 = paper61[:3]

    def run(gains):
        p = params._replace(gains=w.Gains(gains))
        tr = w.simulate(ctrl, z0, p, dt=0.01, n_steps=60, save_every=5)
        return jnp.sum(tr.state[:, :2] ** 2), tr

    def derivatives(forward):
        (value, tr), g = jax.value_and_grad(run, has_aux=True)(params.gains.coeffs)
        return tr, g, jax.jacfwd(lambda c: run(c)[0])(params.gains.coeffs) if forward else None

    # the unrolled step's forward mode against its reverse mode is test_autodiff.py's: the loop's
    # forward mode is compared with the unrolled reverse mode here (one program fewer)
    tr1, g1, _ = derivatives(False)
    assert _stage_loops(lambda g: run(g)[0], params.gains.coeffs) == 0  # 153 equations: unrolled
    jax.clear_caches()
    monkeypatch.setattr(simulate_module, "STAGE_LOOP_MIN_EQUATIONS", 0)
    tr2, g2, f2 = derivatives(True)
    assert _stage_loops(lambda g: run(g)[0], params.gains.coeffs) == 1
    for a, b in ((tr2.state, tr1.state), (tr2.control, tr1.control), (tr2.margin, tr1.margin)):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-14)
    np.testing.assert_array_equal(tr2.valid, tr1.valid)
    for f in ("min_margin", "t_min_margin", "error_estimate"):
        np.testing.assert_allclose(getattr(tr2.diagnostics, f), getattr(tr1.diagnostics, f), rtol=1e-9)
    assert tr1.diagnostics.error_estimate > 1e-12  # the estimate (k1, k4 of the loop) is compared, not zeros
    np.testing.assert_allclose(g2, g1, rtol=1e-11)
    np.testing.assert_allclose(f2, g1, rtol=1e-11)
    jax.clear_caches()


def test_stage_loop_with_a_discrete_state_and_a_switch(monkeypatch):
    """Hybrid parking (an integer mode, a post-step switch, no regularity for the stabilizer)
    through the stage loop: the unrolled step's trajectory and switch, and its gradient."""
    import importlib
    import math

    from wmrjax import references as R
    from wmrjax.controllers import hybrid as H

    simulate_module = importlib.import_module("wmrjax.simulate")
    hy = H.hybrid_parking()
    params = hy.params(R.paper_66())
    z0 = hy.initial_state(jnp.array([[10 * math.sqrt(2) / 6, 2.54], [-0.5, -0.5]]), params)

    def final_distance(lam):
        tr = w.simulate(hy, z0, params._replace(lam=lam), dt=0.02, n_steps=300)
        return jnp.hypot(tr.final_state.tracking[0], tr.final_state.tracking[1]), tr

    (d1, tr1), g1 = jax.value_and_grad(final_distance, has_aux=True)(params.lam)
    jax.clear_caches()
    monkeypatch.setattr(simulate_module, "STAGE_LOOP_MIN_EQUATIONS", 0)
    (d2, tr2), g2 = jax.value_and_grad(final_distance, has_aux=True)(params.lam)
    assert _stage_loops(lambda lam: final_distance(lam)[0], params.lam) == 1
    assert np.any(np.asarray(tr1.state.mode) == H.PARKING)  # the run switches
    np.testing.assert_array_equal(tr2.state.mode, tr1.state.mode)
    np.testing.assert_allclose(tr2.state.tracking, tr1.state.tracking, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(tr2.control, tr1.control, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(g2, g1, rtol=1e-10)
    assert abs(float(g1)) > 0
    jax.clear_caches()


def test_stage_loop_rule_picks_the_large_laws():
    """The (2,0) velocity law (153 scalar equations) runs the unrolled step, the dynamic
    (1,2) torque law (821) the stage loop."""
    from wmrjax import references

    out = {}
    for kind, level in (("(2,0)", "velocity"), ("(1,2)", "torque")):
        ctrl = w.dynamic_linearization(kind, level)
        ref = references.circle(radius=2.0, omega=0.4, heading_offset=getattr(ctrl.row, "default_heading_offset", 0.0))
        params = ctrl.params(ref, poles=1.5, geometry=ctrl.row.default_geometry)
        z = ctrl.reference_state(0.0, params)
        out[kind] = _stage_loops(lambda z: w.simulate(ctrl, z, params, dt=0.01, n_steps=3).final_state, z)
    assert out == {"(2,0)": 0, "(1,2)": 1}


def _rollouts(ctrl, params, z0s, gradient=True):
    """A small batch of short rollouts and (``gradient``) the gradient of a loss over them in the gains."""

    def loss(coeffs):
        p = params._replace(gains=w.Gains(coeffs))
        tr = jax.vmap(lambda z: w.simulate(ctrl, z, p, dt=0.01, n_steps=40, save_every=10))(z0s)
        return jnp.sum(tr.state**2) + jnp.sum(tr.control**2), tr

    if gradient:
        (_, tr), grad = jax.value_and_grad(loss, has_aux=True)(params.gains.coeffs)
    else:
        (_, tr), grad = loss(params.gains.coeffs), None

    def scan_prims(j):  # the primitives of the time loop's bodies
        out = []
        for e in j.eqns:
            subs = list(jax.extend.core.jaxprs_in_params(e.params))
            out += [p for sub in subs for p in (_all_prims(sub) if e.primitive.name == "scan" else scan_prims(sub))]
        return out

    return tr, grad, scan_prims(jax.make_jaxpr(lambda c: loss(c)[0])(params.gains.coeffs).jaxpr)


def test_rewrites_can_be_switched_off_with_the_same_values(paper61, monkeypatch):
    """WMRJAX_JAXPR_REWRITES=0: simulate runs the plain JAX program (its loop assembles the law's
    arrays, and is larger) with the rewritten program's values (1e-12 relative), on the section
    6.1 velocity-level loop (and its gradient) and (3,0)'s torque-level static law (values: its
    gradient programs are the make-test budget's); another value is refused."""
    from wmrjax import references

    ctrl, params, z0 = paper61[:3]
    # a torque-level law too: (3,0)'s static law (Prop 3), the smallest torque-level program
    torque = w.controller("(3,0)", "torque", "posture")
    tparams = torque.params(references.circle(radius=2.0, omega=0.4), poles=1.5, geometry=torque.row.default_geometry)
    tz0 = torque.initial_state_from_physical(jnp.array([2.0, 0.0, jnp.pi / 2]), jnp.array([0.8, 0.0, 0.4]), tparams)
    cases = [
        (ctrl, params, z0 + jnp.array([[0.0], [0.05], [-0.05]]) * jnp.ones_like(z0), True),
        (torque, tparams, tz0 + jnp.array([[0.0], [0.02], [-0.02]]) * jnp.ones_like(tz0), False),
    ]
    monkeypatch.delenv(_simplify.REWRITES_ENV, raising=False)
    rewritten = [_rollouts(*case) for case in cases]
    jax.clear_caches()
    monkeypatch.setenv(_simplify.REWRITES_ENV, "0")
    plain = [_rollouts(*case) for case in cases]
    for (tr1, g1, p1), (tr2, g2, p2) in zip(rewritten, plain):
        assert "concatenate" not in p1 and "concatenate" in p2 and len(p2) > len(p1)
        assert not np.asarray(tr1.diagnostics.failed).any()
        for a, b in ((tr1.state, tr2.state), (tr1.control, tr2.control), (tr1.margin, tr2.margin)):
            np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-13)
        np.testing.assert_array_equal(tr2.valid, tr1.valid)
        np.testing.assert_allclose(tr2.diagnostics.error_estimate, tr1.diagnostics.error_estimate, rtol=1e-6)
        if g1 is not None:
            np.testing.assert_allclose(g2, g1, rtol=1e-12)
            assert np.all(np.abs(np.asarray(g1)) > 0)
    monkeypatch.setenv(_simplify.REWRITES_ENV, "no")
    with pytest.raises(ValueError, match="WMRJAX_JAXPR_REWRITES must be 0"):
        w.simulate(ctrl, z0, params, dt=0.01, n_steps=4)
    jax.clear_caches()
