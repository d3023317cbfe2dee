"""Dynamic linearization of every restricted type at both levels (Table 4, Lemma 1, Prop 8)."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import expm

import wmrjax as w
from wmrjax import references as R
from wmrjax.controllers import dynamic, law

KINDS = ["(2,0)", "(2,1)", "(1,1)", "(1,2)"]
GEOM = w.Geometry(L=0.8, e=0.3, delta=0.4)


def _reference(kind):
    # heading offsets only for types whose heading is free of the velocity direction
    return R.circle(radius=3.0, omega=0.4, heading_offset=0.3 if kind in ("(2,1)", "(1,2)") else 0.0)


def _twin_11(z):
    """(1,1): (beta + pi, -eta1) is the same wheel motion."""
    t = np.array(z, dtype=float)
    t[3] += np.pi
    t[4] = -t[4]
    return t


def _equivalents(kind, z):
    """States describing the same motion: (1,1) (beta + pi, -eta1); (1,2) beta_i + pi pairs."""
    out = [np.array(z)]
    if kind == "(1,1)":
        out.append(_twin_11(z))
    if kind == "(1,2)":
        for f1, f2 in [(1, 0), (0, 1), (1, 1)]:
            t = np.array(z)
            t[3] += np.pi * f1
            t[4] += np.pi * f2
            t[5] *= (-1.0) ** (f1 + f2)
            out.append(t)
    return out


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("level", ["velocity", "torque"])
def test_psi_inverse_round_trip_both_branches(kind, level, rng):
    ctrl = w.dynamic_linearization(kind, level)
    n_angles = 1 + ctrl.robot.delta_s
    zs = rng.uniform(-1.2, 1.2, size=(64, ctrl.n_state))

    P = ctrl.params_unchecked(R.line(), 1.0, GEOM)

    @jax.jit
    def round_trip(z):
        q = ctrl.branch_quantity(z, P)
        branch = jnp.where(q >= 0, 1.0, -1.0)
        back = ctrl.inverse_psi(ctrl.psi(z, P), P, branch)
        return q, ctrl.margin(z, P), back, ctrl.branch_quantity(back, P)

    q, m, back, q_back = (np.asarray(a) for a in jax.vmap(round_trip)(jnp.asarray(zs)))
    keep = (np.abs(q) > 0.05) & (m > 1e-2)
    assert keep.sum() > 20 and set(np.sign(q[keep])) == {1.0, -1.0}  # both branches exercised
    for z, b in zip(zs[keep], back[keep]):
        errs = []
        for c in _equivalents(kind, z):
            d = b - c
            d[2 : 2 + n_angles] = np.angle(np.exp(1j * d[2 : 2 + n_angles]))
            errs.append(np.max(np.abs(d)))
        assert min(errs) < 1e-9, (z, b)
    np.testing.assert_array_equal(np.sign(q_back[keep]), np.sign(q[keep]))


@pytest.fixture(
    scope="module", params=[(k, lv) for k in KINDS for lv in ("velocity", "torque")], ids=lambda p: f"{p[0]}-{p[1]}"
)
def runs(request):
    """Per (type, level): a run from a perturbed start and one from the reference itself."""
    kind, level = request.param
    ctrl = w.dynamic_linearization(kind, level)
    r = ctrl.relative_degree
    poles = jnp.linspace(1.0, 2.0, r)  # distinct poles per derivative, same for every output
    params = ctrl.params(_reference(kind), poles=poles, geometry=GEOM)
    zref = ctrl.reference_state(0.0, params)
    n_post = ctrl.robot.n_state
    pert = jnp.zeros(ctrl.n_state).at[:2].set(jnp.array([0.15, -0.1])).at[2].set(0.05)
    z0s = jnp.stack([zref + pert, zref])
    sim = jax.jit(jax.vmap(lambda z: w.simulate(ctrl, z, params, dt=0.01, n_steps=600, save_every=20)))
    return ctrl, params, z0s, sim(z0s), n_post


def test_error_follows_chosen_linear_dynamics(runs):
    ctrl, params, _, tr, _ = runs
    A = np.asarray(ctrl.error_matrix(params.gains))
    err = np.asarray(jax.vmap(lambda t, z: ctrl.error(t, z, params))(tr.t[0], tr.state[0])).reshape(len(tr.t[0]), -1)
    exact = np.stack([expm(A * t) @ err[0] for t in np.asarray(tr.t[0])])
    assert np.max(np.abs(err[0])) > 0.05
    assert np.max(np.abs(err - exact)) < 1e-6
    assert not bool(tr.diagnostics.failed[0])


def test_posture_converges_and_reference_is_invariant(runs):
    ctrl, params, _, tr, _ = runs
    post_ref = np.asarray(jax.vmap(params.reference.posture)(tr.t[0]))
    perturbed, onref = np.asarray(tr.state[0]), np.asarray(tr.state[1])
    # property 2 of §3.1: posture error -> 0 (6 s with poles in [-2, -1])
    e_end = perturbed[-1, :3] - post_ref[-1]
    e_end[2] = np.angle(np.exp(1j * e_end[2]))
    e_start = perturbed[0, :3] - post_ref[0]
    assert np.max(np.abs(e_end)) < 0.05 * np.max(np.abs(e_start))
    # property 3: started on the reference, stays on it
    dev = onref[:, :3] - post_ref
    dev[:, 2] = np.angle(np.exp(1j * dev[:, 2]))
    assert np.max(np.abs(dev)) < 1e-7


# (2,0): tests/test_autodiff.py; (1,1) alone costs 50 s of compilation; (1,2) 38 s, so it runs with
# WMRJAX_ALL_GRADIENT_CASES=1 (test_autodiff's forward-vs-reverse-vs-differences matrix covers all 18 then)
@pytest.mark.skipif(
    os.environ.get("WMRJAX_ALL_GRADIENT_CASES") != "1",
    reason="the make-test budget: WMRJAX_ALL_GRADIENT_CASES=1 runs it",
)
@pytest.mark.parametrize("kind", ["(1,2)"])
def test_gradients_through_closed_loop(kind, rng):
    """Reverse-mode gradient w.r.t. poles and initial state vs central differences."""
    ctrl = w.dynamic_linearization(kind, "velocity")
    params = ctrl.params(_reference(kind), poles=1.3, geometry=GEOM)
    z0 = ctrl.reference_state(0.0, params) + jnp.zeros(ctrl.n_state).at[0].set(0.1)

    def loss(poles, z0):
        p = params._replace(gains=w.Gains.from_poles(poles))
        tr = w.simulate(ctrl, z0, p, dt=0.1, n_steps=4, save_every=4)
        return jnp.sum(ctrl.error(tr.t[-1], tr.final_state, p) ** 2)

    f = jax.jit(loss)
    poles = jnp.full((ctrl.m, ctrl.relative_degree), 1.3)
    g = jax.jit(jax.grad(loss, argnums=(0, 1)))(poles, z0)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in g)
    for _ in range(2):
        dp = jnp.asarray(rng.normal(size=poles.shape))
        dz = jnp.asarray(rng.normal(size=z0.shape))
        h = 1e-5
        fd = (f(poles + h * dp, z0 + h * dz) - f(poles - h * dp, z0 - h * dz)) / (2 * h)
        ad = jnp.sum(g[0] * dp) + jnp.sum(g[1] * dz)
        np.testing.assert_allclose(ad, fd, rtol=1e-6, atol=1e-9)
        assert abs(float(ad)) > 1e-6


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("level", ["velocity", "torque"])
def test_initial_state_from_physical(kind, level):
    ctrl = w.dynamic_linearization(kind, level)
    params = ctrl.params(_reference(kind), poles=1.0, geometry=GEOM)
    zref = ctrl.reference_state(0.0, params)
    n, ext = ctrl.robot.n_state, ctrl.row.extension
    nv = n + ext.n_comp
    X = np.asarray(zref[:n])
    # the reference's own wheel velocities: its new inputs (zero error) through the plant input map
    U = zref[nv:] if level == "torque" else ctrl.control(0.0, zref, params)[0]
    u = np.asarray(ext.plant_input(zref[:n], zref[n:nv], U, GEOM))
    z = ctrl.initial_state_from_physical(X, u, params)
    np.testing.assert_allclose(z[:n], X)
    if level == "torque":
        u_back = ext.plant_input(z[:n], z[n:nv], z[nv:], GEOM)
        np.testing.assert_allclose(u_back, u, atol=1e-12)
    with pytest.raises(ValueError, match="Remark 17"):  # driving backwards: the other branch
        ctrl.initial_state_from_physical(X, u * np.r_[-1.0, np.ones(len(u) - 1)] if kind != "(2,0)" else -u, params)

    # batched: vmap over 16 measured states (one compiled program), equal to the unbatched calls
    rng = np.random.default_rng(7)
    Xs = X + rng.uniform(-0.05, 0.05, (16, n))
    us = u * (1.0 + rng.uniform(-0.05, 0.05, (16, len(u))))
    batch = jax.vmap(lambda a, b: ctrl.initial_state_from_physical(a, b, params))(jnp.asarray(Xs), jnp.asarray(us))
    assert batch.shape == (16, ctrl.n_state)
    for i in (0, 7, 15):
        np.testing.assert_allclose(batch[i], ctrl.initial_state_from_physical(Xs[i], us[i], params), rtol=0, atol=1e-12)
    # compiled once per controller: new values reuse the compiled programs (map and margin check)
    sizes = (dynamic._physical_jit._cache_size(), law.margin_at._cache_size())
    ctrl.initial_state_from_physical(Xs[3] + 0.01, us[3], params)
    assert (dynamic._physical_jit._cache_size(), law.margin_at._cache_size()) == sizes


def test_singular_initial_conditions_raise():
    for kind in KINDS:
        ctrl = w.dynamic_linearization(kind, "velocity")
        params = ctrl.params(_reference(kind), poles=1.0, geometry=GEOM)
        X = np.zeros(ctrl.robot.n_state)
        X[3:] = 0.7
        with pytest.raises(ValueError, match="singular set"):
            ctrl.initial_state_from_physical(X, np.zeros(ctrl.robot.n_input), params)  # at rest
    ctrl = w.dynamic_linearization("(1,1)", "velocity")
    g = w.Geometry(L=1.0, e=0.0)
    params = ctrl.params(_reference("(1,1)"), poles=1.0, geometry=g)
    with pytest.raises(ValueError, match=r"L sin beta \+ e cos beta"):  # beta = 0: lever vanishes, eta1 != 0
        ctrl.initial_state_from_physical(np.zeros(4), np.array([1.0, 0.0]), params)


def test_reference_reaching_singular_set_raises():
    ctrl = w.dynamic_linearization("(2,0)")
    params = ctrl.params(R.paper_66(), poles=1.0)
    ctrl.check_reference(params, 9.0)  # moving until t = 10 s
    with pytest.raises(ValueError, match="reaches the singular set"):
        ctrl.check_reference(params, 10.0)  # it stops at the origin at t = 10 s
    for kind in ("(2,1)", "(1,2)"):
        c = w.dynamic_linearization(kind)
        with pytest.raises(ValueError, match="is at rest at t = 0"):  # refused when the params are built
            c.params(R.line(velocity=(0.0, 0.0)), poles=1.0, geometry=GEOM)
        p = c.params(R.paper_66(), poles=1.0, geometry=GEOM)
        with pytest.raises(ValueError, match="reaches the singular set"):
            c.check_reference(p, 11.0)


def test_heading_reference_crossing_pi_is_tracked_without_a_turn():
    """theta_ref from atan2 jumps by 2 pi; the law wraps the heading error, so the robot
    keeps turning smoothly (errata: integrate angles unwrapped, wrap only errors)."""
    ctrl = w.dynamic_linearization("(2,1)", "velocity")
    params = ctrl.params(R.circle(radius=2.0, omega=1.0, heading_offset=0.3), poles=1.0, geometry=GEOM)
    z0 = ctrl.reference_state(0.0, params).at[2].add(0.2)
    tr = w.simulate(ctrl, z0, params, dt=0.01, n_steps=800, save_every=10)
    theta = np.asarray(tr.state[:, 2])
    theta_ref = np.unwrap(np.asarray(jax.vmap(params.reference.posture)(tr.t))[:, 2])
    assert theta_ref[-1] - theta_ref[0] > 2 * np.pi  # the reference heading went once around
    err = theta - theta_ref
    assert abs(err[-1]) < 1e-2 and np.max(np.abs(err)) <= 0.2 + 1e-9  # no 2 pi excursion
    assert np.all(np.abs(np.diff(theta)) < 0.2)  # continuous, never wrapped
