"""Hybrid parking (§6.2): the time-varying stabilizer, the switch, finiteness and gradients."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax import references as R
from wmrjax.controllers import hybrid as H

DT = 0.02


@pytest.fixture(scope="module")
def paper62_hybrid():
    hy = H.hybrid_parking()
    params = hy.params(R.paper_66())
    z0 = hy.initial_state(jnp.array([[10 * math.sqrt(2) / 6, 2.54], [-0.5, -0.5]]), params)
    return hy, params, z0


@pytest.fixture(scope="module")
def run_hybrid(paper62_hybrid):
    hy, _, _ = paper62_hybrid
    return lambda z0, p: w.simulate(hy, z0, p, dt=DT, n_steps=600)  # simulate is jitted at its entry


def test_stabilizer_alone_decreases_distance(rng):
    sys_ = H.TimeVarying()
    p = sys_.params(lam=40.0)
    sim = jax.jit(jax.vmap(lambda z: w.simulate(sys_, z, p, dt=0.005, n_steps=4000, save_every=10)))
    z0 = jnp.asarray(np.concatenate([rng.uniform(-0.4, 0.4, (6, 2)), rng.uniform(-1.0, 1.0, (6, 1))], 1))
    tr = sim(z0)
    V = 0.5 * np.asarray(tr.state[..., 0] ** 2 + tr.state[..., 1] ** 2)
    assert np.all(np.diff(V, axis=1) <= 1e-9)  # d/dt (x^2 + y^2)/2 = -eta1^2 <= 0
    assert np.all(V[:, -1] < 0.25 * V[:, 0])  # and it does go down (20 s)
    # z = psi(theta) + lambda x cos(tau) decays like exp(-tau)
    zz = np.asarray(tr.state[..., 2] + 40.0 * tr.state[..., 0] * np.cos(np.asarray(tr.t)))
    np.testing.assert_allclose(zz[:, -1], zz[:, 0] * np.exp(-20.0), atol=1e-6)


def test_switch_at_first_step_inside_disk(paper62_hybrid, run_hybrid):
    hy, params, z0 = paper62_hybrid
    tr = run_hybrid(z0, params)
    st, t, mode = np.asarray(tr.state.tracking), np.asarray(tr.t), np.asarray(tr.state.mode)
    assert not bool(tr.diagnostics.failed) and np.all(np.isfinite(st)) and np.all(np.isfinite(tr.control))
    assert isinstance(tr.final_state, H.HybridState) and mode.dtype == np.int32  # named fields, integer mode
    inside = st[:, 0] ** 2 + st[:, 1] ** 2 <= float(params.r_switch) ** 2
    k = int(np.argmax(inside))
    assert 0 < k and not inside[:k].any()
    assert np.all(mode[:k] == H.TRACKING) and np.all(mode[k:] == H.PARKING)
    assert float(tr.final_state.t_switch) == pytest.approx(t[k]) and 5.0 < t[k] < 5.5
    np.testing.assert_allclose(np.asarray(tr.final_state.at_switch), st[k])  # recorded switch state
    assert abs(st[k, 2]) <= math.pi  # theta's representative nearest 0
    # before the switch the robot follows the linearizing law exactly (eta1 = chi1 > 0)
    assert np.all(np.asarray(tr.control)[:k, 0] > 0.2)


def test_hybrid_gradients_finite_and_jit_vmap_consistent(paper62_hybrid, run_hybrid):
    hy, params, z0 = paper62_hybrid

    def final_distance(scale, lam):
        p = params._replace(
            lam=lam, tracking=params.tracking._replace(gains=w.Gains.from_poles(jnp.ones((2, 2)) * scale))
        )
        fs = run_hybrid(z0, p).final_state.tracking
        return jnp.hypot(fs[0], fs[1])

    g = jax.jacfwd(final_distance, argnums=(0, 1))(1.0, params.lam)
    assert all(np.isfinite(float(x)) for x in g)
    shifts = jnp.array([[0.0, 0.0], [0.1, 0.0], [0.0, -0.1]])
    z0s = jax.vmap(lambda d: z0._replace(tracking=z0.tracking.at[:2].add(d)))(shifts)
    batch = jax.vmap(lambda z: run_hybrid(z, params).final_state)(z0s)
    for i in range(3):
        one = run_hybrid(jax.tree_util.tree_map(lambda a: a[i], z0s), params).final_state
        for a, b in zip(jax.tree_util.tree_leaves(batch), jax.tree_util.tree_leaves(one)):
            np.testing.assert_allclose(a[i], b, rtol=1e-10, atol=1e-12)


def test_bad_hybrid_arguments():
    hy = H.hybrid_parking()
    with pytest.raises(ValueError, match="r_s must be > 0"):
        hy.params(R.paper_66(), r_switch=0.0)
    with pytest.raises(ValueError, match="lambda"):
        hy.params(R.paper_66(), lam=-1.0)
    with pytest.raises(ValueError, match="end inside the switching disk"):
        hy.params(R.paper_62())
    with pytest.raises(ValueError, match="lambda"):
        H.TimeVarying().params(lam=0.0)
