"""Time-varying gains: GainSchedule, the transition matrix Phi(t, 0) against expm and SciPy,
and Lemma 2 / exact-map certificates for scheduled gains checked by simulation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from scipy.integrate import solve_ivp

import wmrjax as w
from wmrjax import certify as C
from wmrjax import linearize

TIMES = np.array([0.0, 2.5, 6.0, 10.0])


def _schedule(m=2, lam=False):
    """omega from 1 to 2.2 and back, zeta from 1 down to 0.6: a strongly varying schedule."""
    om = np.array([1.0, 2.2, 1.4, 1.8])[:, None, None] * np.ones((4, m, 1))
    ze = np.array([1.0, 0.6, 0.8, 0.7])[:, None, None] * np.ones((4, m, 1))
    return w.GainSchedule.from_damping(TIMES, om, ze, np.full((4, m), 1.5) if lam else None)


def _phi_scipy(s, ts):
    """Phi(t, 0) at the times ts by SciPy's DOP853 (rtol = atol = 1e-12): the independent oracle."""
    m, r = s.shape
    n = m * r
    A_of = jax.jit(lambda t: linearize.companion(s.coeffs_at(t)))
    rhs = lambda t, p: (np.asarray(A_of(t)) @ p.reshape(n, n)).reshape(-1)
    sol = solve_ivp(
        rhs, (0.0, float(max(ts))), np.eye(n).reshape(-1), method="DOP853", rtol=1e-12, atol=1e-12, t_eval=ts
    )
    return sol.y.T.reshape(-1, n, n)


def test_schedule_interpolates_its_knots_and_is_hurwitz_everywhere(rng):
    s = _schedule(lam=True)
    assert s.shape == (2, 3)
    for k, t in enumerate(TIMES):  # the knot values are attained
        np.testing.assert_allclose(
            np.asarray(s.parameters_at(t))[0], [s.omega[k, 0, 0], s.zeta[k, 0, 0], 1.5], rtol=1e-12
        )
    np.testing.assert_allclose(s.parameters_at(-1.0), s.parameters_at(0.0), rtol=0)  # held outside
    np.testing.assert_allclose(s.parameters_at(12.0), s.parameters_at(10.0), rtol=0)
    for c in np.asarray(jax.jit(jax.vmap(s.coeffs_at))(jnp.asarray(rng.uniform(0, 10, 25)))):  # Hurwitz at
        for row in c:  # every time
            assert np.all(np.roots(np.concatenate([[1.0], row[::-1]])).real < 0)
    # C^1: one-sided derivatives agree at an interior knot
    d = lambda t: jax.grad(lambda tt: s.parameters_at(tt)[0, 0])(t)
    np.testing.assert_allclose(float(d(2.5 - 1e-9)), float(d(2.5 + 1e-9)), rtol=1e-6)
    const = w.GainSchedule.from_damping(TIMES, np.ones((4, 2, 1)), np.ones((4, 2, 1)))
    np.testing.assert_allclose(const.coeffs_at(3.3), w.Gains.from_poles(1.0, 2, 2).coeffs, rtol=1e-14)


def test_bad_schedules():
    with pytest.raises(ValueError, match="at least 2 knot times"):
        w.GainSchedule.from_damping([0.0], np.ones((1, 2, 1)), np.ones((1, 2, 1)))
    with pytest.raises(ValueError, match="strictly increasing"):
        w.GainSchedule.from_damping([0.0, 0.0], np.ones((2, 2, 1)), np.ones((2, 2, 1)))
    with pytest.raises(ValueError, match="zeta"):
        w.GainSchedule.from_damping([0.0, 1.0], np.ones((2, 2, 1)), -np.ones((2, 2, 1)))
    with pytest.raises(ValueError, match="the controller needs"):
        w.dynamic_linearization("(1,1)").params(
            w.references.circle(), gains=_schedule(), geometry=w.Geometry(L=1.0, e=0.3)
        )
    with pytest.raises(ValueError, match="needs n_steps"):
        linearize.transition_matrix(_schedule(), 1.0)


def test_transition_matrix_equals_expm_and_scipy():
    gains = w.Gains.from_damping([1.3], [0.4], lam=2.0, m=2)
    A = np.asarray(linearize.companion(gains.coeffs))
    for t in (0.7, 4.0, 10.0):  # constant gains: RK4 and expm agree with scipy's expm
        want = scipy.linalg.expm(A * t)
        np.testing.assert_allclose(np.asarray(linearize.transition_matrix(gains, t, n_steps=1000)), want, atol=1e-10)
        np.testing.assert_allclose(np.asarray(linearize.transition_matrix(gains, t)), want, atol=1e-12)
    s = _schedule(lam=True)  # a schedule: against DOP853 on dPhi/dt = A(t) Phi
    want = _phi_scipy(s, [3.0, 10.0])
    for i, t in enumerate((3.0, 10.0)):
        got = linearize.transition_matrix(s, t, n_steps=C.transition_steps(t))
        np.testing.assert_allclose(np.asarray(got), want[i], atol=2e-9)
    np.testing.assert_allclose(
        C.k2_transition(gains, jnp.array([1.0, 5.0])),
        C.k2_exact(jnp.asarray(A), jnp.array([1.0, 5.0])),
        rtol=0,
        atol=1e-9,
    )


@pytest.fixture(scope="module")
def scheduled61(paper61):
    ctrl, params, _ = paper61
    p = params._replace(gains=_schedule())
    return ctrl, p, C.lemma2(ctrl, p, t_final=10.0, eps=1e-2, n_t=201)


def test_scheduled_certificate_holds_in_simulation(scheduled61):
    """K2(t) = ||Phi(t, 0)||: runs from inside the certified ball never violate (53) nor become
    singular, and the error really follows Phi (max ratio ||err(t)|| / (K2 ||err(0)||) <= 1)."""
    ctrl, p, rep = scheduled61
    assert rep.paper is None and rep.lyapunov is None and list(rep.certificates()) == ["exact_norm"]
    rad = float(rep.exact_norm.radius)
    ts = np.linspace(0.0, 10.0, 4001)  # oracle: min_t (M1 - eps) / ||Phi||, M1 of eq (65), SciPy's Phi
    k2 = np.linalg.norm(_phi_scipy(p.gains, ts), ord=2, axis=(1, 2))
    np.testing.assert_allclose(rad, np.min((0.04 * (10 - 2 * ts) ** 2 + 1.0 - 1e-2) / k2), rtol=1e-5)
    dirs = C.sample_sphere(jax.random.PRNGKey(3), 16, 4)
    errs = dirs * jnp.linspace(0.3, 1.0, 16)[:, None] * rad
    res = C.verify(
        ctrl, p, t_final=10.0, initial_errors=errs, k2=lambda ts: C.k2_transition(p.gains, ts), dt=0.02, save_every=10
    )
    assert not np.any(np.asarray(res.singular)) and not np.any(np.asarray(res.violation_53))
    assert 0.9 < float(np.max(res.max_ratio)) <= 1.0 + 1e-6  # the bound is attained, not just valid


def test_scheduled_exact_map_is_tight(scheduled61):
    ctrl, p, rep = scheduled61
    pos = C.exact_map_radius(ctrl, p, t_final=10.0, eps=1e-2, basis="position", n_t=201)
    assert float(rep.exact_norm.radius) <= float(pos.radius)
    wst = pos.worst_error
    d, s = C.min_distance(ctrl, p, t_final=10.0, initial_errors=jnp.stack([0.99 * wst, 1.01 * wst]), dt=0.01)
    assert float(d[0]) > 1e-2 and not bool(s[0]) and (float(d[1]) < 1e-2 or bool(s[1]))
