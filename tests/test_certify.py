"""Lemma 2 certificates: closed forms vs numerics, K2 bounds, and simulation."""

import importlib
import inspect
import logging
import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax import certify as C
from wmrjax import references as R
from wmrjax.gains import monic_coefficients
from wmrjax.linearize import companion


@pytest.fixture(scope="module")
def cert61(paper61):
    ctrl, params, z0 = paper61
    return C.lemma2(ctrl, params, t_final=10.0, eps=1e-2, n_t=1001)


def test_m1_lemma3_equals_eq65_and_numerical(paper61):
    ctrl, params, _ = paper61
    ts = jnp.linspace(0.0, 10.0, 11)
    closed = np.asarray(C.m1_closed_form(ctrl, params, ts))
    np.testing.assert_allclose(closed, 0.04 * (10 - 2 * np.asarray(ts)) ** 2 + 1.0, rtol=1e-12)  # eq (65)
    np.testing.assert_allclose(C.m1_numerical(ctrl, params, ts), closed, rtol=1e-6)  # Remark 16


def test_k2_bounds_hold(rng):
    ts = jnp.linspace(0.0, 20.0, 401)
    A = companion(monic_coefficients(jnp.ones((2, 2))))
    exact = np.asarray(C.k2_exact(A, ts))
    assert np.all(np.asarray(C.k2_paper(ts)) >= exact - 1e-12)  # eq (64) is valid, and conservative
    assert np.all(np.asarray(C.k2_lyapunov(A, ts)) >= exact - 1e-12)
    for _ in range(20):  # random Hurwitz gains, r = 2 or 3
        r = int(rng.integers(2, 4))
        A = companion(monic_coefficients(jnp.asarray(rng.uniform(0.2, 4.0, size=(2, r)))))
        b = C.lyapunov_bound(A)
        assert np.all(np.asarray(b.K1 * np.exp(-b.r1 * np.asarray(ts))) >= np.asarray(C.k2_exact(A, ts)) - 1e-10)
        assert float(b.r1) > 0 and float(b.K1) >= 1.0


def test_lemma2_grid_program_equals_the_public_functions():
    """lemma2 evaluates M1 and every K2 on its grid and on the refinement's points in blocks of
    one compiled program (``_grid_program``): its certificates on the grid equal
    m1_closed_form, k2_paper/k2_lyapunov/k2_exact and certificate() called one by one (to
    rounding), and the grid's 1001 points and the refinement's 1514 went through one program."""
    L2 = importlib.import_module("wmrjax.certify.lemma2")  # the module (wmrjax.certify.lemma2 is the function)
    ctrl = w.dynamic_linearization("(1,1)", "velocity")
    params = ctrl.params(R.figure_eight(), poles=1.0, geometry=ctrl.row.default_geometry)
    before = L2._grid_program._cache_size()
    rep = C.lemma2(ctrl, params, t_final=10.0, eps=1e-2)
    assert L2._grid_program._cache_size() == before + 1
    ts = jnp.linspace(0.0, 10.0, 1001)
    A = ctrl.error_matrix(params.gains)
    m1 = C.m1_closed_form(ctrl, params, ts)
    for got, k2 in ((rep.lyapunov, C.k2_lyapunov(A, ts)), (rep.exact_norm, C.k2_exact(A, ts))):
        want = C.certificate(ts, m1, k2, 1e-2)
        for a, b in zip((got.m1, got.k2, got.F), (want.m1, want.k2, want.F)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13)
        assert float(got.radius) <= float(want.radius)  # the refinement can only lower min F
    assert rep.paper is None  # (64) is for r = 2


def test_section61_condition_52_and_ordering(paper61, cert61):
    ctrl, params, z0 = paper61
    e0 = float(jnp.linalg.norm(ctrl.error(0.0, z0, params)))
    np.testing.assert_allclose(e0, 0.54 * math.sqrt(2), rtol=1e-12)
    paper = cert61.paper
    # the paper: "with our choice (63), condition (52) is satisfied"
    assert e0 <= float(paper.radius) < 1.01 * e0
    np.testing.assert_allclose(paper.F, (paper.m1 - 1e-2) / paper.k2)
    assert float(paper.radius) <= float(cert61.lyapunov.radius) <= float(cert61.exact_norm.radius)


def test_inside_certified_ball_no_violations(paper61, cert61):
    """4 directions x radii up to the exact-norm certificate: (53) holds and no run is singular."""
    ctrl, params, _ = paper61
    A = ctrl.error_matrix(params.gains)
    rad = float(cert61.exact_norm.radius)
    dirs = C.sample_sphere(jax.random.PRNGKey(1), 32, 4)
    errs = dirs * jnp.linspace(0.2, 1.0, 32)[:, None] * rad
    res = C.verify(
        ctrl, params, t_final=10.0, initial_errors=errs, k2=lambda ts: C.k2_exact(A, ts), dt=0.02, save_every=10
    )
    assert not np.any(np.asarray(res.singular))
    assert not np.any(np.asarray(res.violation_53))
    assert float(np.max(res.max_ratio)) <= 1.0 + 1e-6


def test_far_outside_becomes_singular(paper61):
    """A planted unsafe initial error: cancel the reference velocity at t = 0 (chi1(0) ~ 0)."""
    ctrl, params, _ = paper61
    A = ctrl.error_matrix(params.gains)
    href = ctrl.reference_jet(jnp.asarray(0.0), params)
    e0 = jnp.concatenate([jnp.zeros(2), -0.999 * href[1]])[None]
    res = C.verify(
        ctrl, params, t_final=10.0, initial_errors=e0, k2=lambda ts: C.k2_exact(A, ts), dt=0.02, save_every=10
    )
    assert float(res.min_margin[0]) < 0.01 or bool(res.singular[0])


def test_bad_lemma2_arguments(paper61):
    ctrl, params, _ = paper61
    with pytest.raises(ValueError, match="eps must be > 0"):
        C.lemma2(ctrl, params, t_final=10.0, eps=0.0)
    with pytest.raises(ValueError, match="horizon must be > 0"):
        C.lemma2(ctrl, params, t_final=-1.0, eps=1e-2)
    stop = ctrl.params(R.paper_66(), poles=1.0)
    with pytest.raises(ValueError, match="within eps"):
        C.lemma2(ctrl, stop, t_final=10.0, eps=1e-2)
    with pytest.raises(ValueError, match="not Hurwitz"):
        C.lyapunov_bound(jnp.array([[0.0, 1.0], [1.0, -1.0]]))


# --- beyond Lemma 2: exact map, empirical radius, falsifier --------------------------------


@pytest.fixture(scope="module")
def exact61(paper61):
    ctrl, params, _ = paper61
    return {b: C.exact_map_radius(ctrl, params, t_final=10.0, eps=1e-2, basis=b) for b in ("full", "position")}


def testmin_norm_to_ball_matches_boundary_search(rng):
    """Independent oracle: min over the eps-circle y = -a + eps (cos p, sin p) of ||M^+ y||."""
    for _ in range(5):
        M = rng.normal(size=(2, 4))
        a = rng.normal(size=2) * 3.0
        eps = 0.1
        ph = np.linspace(0.0, 2 * np.pi, 20001)
        Y = -a[None] + eps * np.stack([np.cos(ph), np.sin(ph)], 1)
        brute = np.min(np.linalg.norm(Y @ np.linalg.pinv(M).T, axis=1))
        rho, x = C.min_norm_to_ball(jnp.asarray(M), jnp.asarray(a), eps)
        np.testing.assert_allclose(float(rho), brute, rtol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(a + M @ np.asarray(x)), eps, rtol=1e-8)  # on the boundary
    rho, _ = C.min_norm_to_ball(jnp.zeros((2, 2)), jnp.array([1.0, 0.0]), 0.1)  # unreachable
    assert float(rho) == np.inf


@pytest.mark.parametrize("scale", [1.0, 1e-30, 1e-200, 1e-300])
def test_min_norm_to_ball_at_any_scale(scale):
    """M = s diag(1, 2), a = (1, 0.5), eps = 0.01: the closest point of the eps-ball is along a
    after the map's inverse; the oracle is the same boundary search as above, on M / s, times 1/s
    (the smallest ||x|| scales as 1/s). A fixed bisection bracket in log(nu) of [-60, 60] gave
    ||x|| = 1.6e-4 at s = 1e-30 where it is 1.02e30 (measured on e922c0c: the root nu ~ 1/s^2 left
    the bracket), and s^2 underflows below 1e-162."""
    M = np.diag([1.0, 2.0])
    a = np.array([1.0, 0.5])
    ph = np.linspace(0.0, 2 * np.pi, 200001)
    Y = -a[None] + 1e-2 * np.stack([np.cos(ph), np.sin(ph)], 1)
    brute = np.min(np.linalg.norm(Y @ np.linalg.inv(M).T, axis=1))
    rho, x = C.min_norm_to_ball(jnp.asarray(scale * M), jnp.asarray(a), 1e-2)
    np.testing.assert_allclose(float(rho) * scale, brute, rtol=1e-9)
    np.testing.assert_allclose(
        np.asarray(x) * scale, -np.linalg.solve(M, a) * brute / np.linalg.norm(np.linalg.solve(M, a)), rtol=2e-2
    )  # near the unconstrained solution's direction
    np.testing.assert_allclose(np.linalg.norm(a + M @ (np.asarray(x) * scale)), 1e-2, rtol=1e-8)
    rho0, x0 = C.min_norm_to_ball(jnp.asarray(1e-320 * M), jnp.asarray(a), 1e-2)  # beyond float range
    assert float(rho0) == np.inf and np.all(np.asarray(x0) == 0.0)


def test_exact_map_radius_holds_on_long_horizons():
    """Section 6.1's loop (position slice) with poles at -0.5 ... -5 over horizons to 1000 s: the
    radius is the same as over 10 s (its worst time is early, 0.21-4.1 s), and above Lemma 2's
    exact-norm radius over the same horizon. Before (e922c0c, measured): poles at -2 gave 5.65 at
    30 s, 6.5e-5 at 40 s and 9.1e-56 at 100 s; poles at -1 6.1e-13 at 100 s; poles at -5 3.1e-56
    at 40 s and 0 at 100 s (s(e^{At}) ~ t e^{-pt} left the fixed bisection bracket)."""
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    for poles in (0.5, 1.0, 2.0, 5.0):
        p = ctrl.params(R.paper_62(), poles=poles, geometry=w.Geometry(e=0.0))
        short = C.exact_map_radius(ctrl, p, t_final=10.0, eps=1e-2, basis="position")
        for T in (40.0, 200.0, 1000.0):
            em = C.exact_map_radius(ctrl, p, t_final=T, eps=1e-2, basis="position")
            np.testing.assert_allclose(float(em.radius), float(short.radius), rtol=1e-9)
            assert np.all(np.isfinite(np.asarray(em.rho)) | (np.asarray(em.rho) == np.inf))
            l2 = C.lemma2(ctrl, p, t_final=T, eps=1e-2, n_t=int(20 * T) + 1)
            assert float(l2.exact_norm.radius) <= float(em.radius)


def test_consistency_alarms():
    """The certifier's alarms: a certified radius above a falsified one, and an exact map of a
    linear singular set more than 1 % from its falsifier's radius (either way), each a message;
    within the tolerance, and for (1,2)'s bounded map, none."""
    from types import SimpleNamespace as NS

    from wmrjax.certify.pipeline import consistency

    exact = {
        "full": NS(radius=4.99, lower_bound=None, boxes=0),
        "position": NS(radius=8.789566, lower_bound=None, boxes=0),
    }
    fals = {"full": NS(radius=4.990007), "position": NS(radius=8.789575)}
    assert consistency({"lyapunov": 1.5}, exact, fals) == (True, [])
    below, msgs = consistency({"lyapunov": 5.2}, exact, fals)  # a Lemma 2 radius above the falsifier's
    assert not below and len(msgs) == 1 and "Lemma 2 (lyapunov) 5.2 > falsified 4.99001" in msgs[0]
    collapsed = {**exact, "full": NS(radius=7.2e-5, lower_bound=None, boxes=0)}  # the old long-horizon collapse
    below, msgs = consistency({"lyapunov": 1e-5}, collapsed, {"full": NS(radius=5.34), "position": None})
    assert below and len(msgs) == 1 and "exact-map radius (full) 7.2e-05 and the falsified radius 5.34" in msgs[0]
    assert consistency({}, {"full": NS(radius=1.0, lower_bound=0.9, boxes=10)}, {"full": NS(radius=1.5)}) == (True, [])
    assert consistency({}, exact, {"full": NS(radius=None), "position": None}) == (True, [])


def _small_analyse(paper61, **kw):
    """The certification pipeline on the section 6.1 loop over 2 s, with few samples and rays."""
    ctrl, params, _ = paper61
    return C.analyse(
        ctrl, params, **({"t_final": 2.0, "dt": 0.02, "n_empirical": 32, "n_directions": 4, "n_starts": 0} | kw)
    )


def test_a_wrong_k2_raises_the_lemma2_alarm(paper61, monkeypatch):
    """The pipeline's first alarm, end to end: a deliberately wrong K2 (a quarter of ||e^{At}||,
    so (53) fails from t = 0 and the certified radius is four times too large) is violated inside
    its own certificate, which analyse warns about and lists in its alarms."""
    import importlib

    L = importlib.import_module("wmrjax.certify.lemma2")  # the module (C.lemma2 is the function)
    values = L._grid_values

    def wrong(*args):
        m1, (paper, lyapunov, exact) = values(*args)
        return m1, (paper, lyapunov, 0.25 * exact)

    # the certificate's K2 (lemma2) and the bound (53) checked on the runs (grid_k2s): one program
    monkeypatch.setattr(L, "_grid_values", wrong)
    with pytest.warns(RuntimeWarning, match="LEMMA 2 VIOLATED inside the exact_norm certificate"):
        report = _small_analyse(paper61)
    assert report.empirical["exact_norm"].violations_53_inside > 0
    assert report.empirical["lyapunov"].violations_53_inside == 0  # the other K2s hold
    assert [a for a in report.alarms if "LEMMA 2" in a] == [a for a in report.alarms if "exact_norm" in a]


def test_a_failure_inside_a_certified_ball_raises_the_falsifier_alarm(paper61, monkeypatch):
    """The pipeline's second alarm, end to end: a falsifier that finds a confirmed failure at
    half the largest certified radius (as it would if a certificate were wrong) makes analyse warn
    that a certified radius exceeds a falsified one and report certified_below_falsified False
    (and, the exact map being tight, that the exact map and the falsifier disagree)."""
    from wmrjax.certify import pipeline
    from wmrjax.certify.falsify import FalsifiedRadius

    def falsifier(ctrl, params, *, r_lo, basis, **kw):
        return FalsifiedRadius(0.5 * r_lo, None, 0.0, 1, (0.0, 0.5 * r_lo), r_lo, None, 1.0)

    monkeypatch.setattr(pipeline, "falsified_radius", falsifier)
    with pytest.warns(RuntimeWarning) as caught:
        report = _small_analyse(paper61, n_empirical=0, n_starts=1)
    assert not report.certified_below_falsified
    warned = [str(m.message) for m in caught]
    exceeded = [m for m in warned if m.startswith("a certified radius exceeds a falsified one")]
    assert any("Lemma 2 (exact_norm)" in m and "full error space" in m for m in exceeded)
    assert set(warned) == set(report.alarms)  # the exact maps disagree with it too: their own alarm
    assert any(m.startswith("the exact-map radius (full)") for m in warned)


def test_exact_map_radius_is_tight_and_above_lemma2(paper61, cert61, exact61):
    ctrl, params, _ = paper61
    full, pos = exact61["full"], exact61["position"]
    # full ball: at t = 0 the worst error cancels the reference velocity, ||h'_ref(0)|| = M1(0) = 5
    np.testing.assert_allclose(float(full.radius), 5.0 - 1e-2, rtol=1e-9)
    assert float(cert61.exact_norm.radius) <= float(full.radius) <= float(pos.radius)
    w = pos.worst_error
    assert np.allclose(np.asarray(w)[2:], 0.0) and abs(float(jnp.linalg.norm(w)) - float(pos.radius)) < 1e-9
    d, s = C.min_distance(ctrl, params, t_final=10.0, initial_errors=jnp.stack([0.99 * w, 1.01 * w]), dt=0.01)
    # the real closed loop agrees: 0.99 w stays eps away, 1.01 w comes within eps (it even crosses
    # the singular set between samples, which the simulator flags)
    assert float(d[0]) > 1e-2 and not bool(s[0]) and (float(d[1]) < 1e-2 or bool(s[1]))


def test_empirical_radius_finds_the_exact_one(paper61, exact61):
    ctrl, params, _ = paper61
    pos = exact61["position"]
    wd = pos.worst_error / jnp.linalg.norm(pos.worst_error)
    er = C.empirical_radius(
        ctrl,
        params,
        t_final=10.0,
        eps=1e-2,
        directions=jnp.stack([wd, -wd]),
        r_max=12.0,
        dt=0.01,
        n_grid=16,
        n_golden=20,
        n_bisect=16,
    )
    np.testing.assert_allclose(er.per_direction[0], float(pos.radius), rtol=1e-3)
    assert er.per_direction[1] == np.inf and er.radius == er.per_direction[0]


def test_falsifier_finds_planted_failure_and_respects_certificates(paper61, cert61, exact61):
    """Just outside the exact radius (position slice) the falsifier, from directions that miss the
    unsafe one, finds a run within eps of the singular set; just inside, nothing it finds is; and
    every certified radius lies below the radius at which it found a failure."""
    ctrl, params, _ = paper61
    rad = float(exact61["position"].radius)
    ang = jnp.linspace(0.0, 2 * np.pi, 16, endpoint=False) + 0.1  # none of them on the unsafe diagonal
    starts = jnp.stack([jnp.cos(ang), jnp.sin(ang)], 1)
    out = C.falsify(
        ctrl, params, t_final=10.0, radius=1.03 * rad, starts=starts, dt=0.02, basis="position", steps=40, n_windows=2
    )
    assert float(jnp.min(out.distance)) < 1e-2
    e = out.initial_errors[int(out.best)]
    assert abs(float(jnp.linalg.norm(e)) - 1.03 * rad) < 1e-9 and np.allclose(np.asarray(e)[2:], 0.0)
    inside = C.falsify(
        ctrl, params, t_final=10.0, radius=0.97 * rad, starts=starts, dt=0.02, basis="position", steps=40, n_windows=2
    )
    assert float(jnp.min(inside.distance)) > 1e-2
    for name in ("paper", "lyapunov", "exact_norm"):
        assert float(getattr(cert61, name).radius) <= 1.03 * rad


def test_bad_exact_map_arguments(paper61):
    ctrl, params, _ = paper61
    with pytest.raises(ValueError, match="orthonormal"):
        C.slice_basis(ctrl, jnp.ones((4, 2)))
    with pytest.raises(ValueError, match=r"unknown slice 'velocity-ish'; expected one of \['full', 'position'\]"):
        C.slice_basis(ctrl, "velocity-ish")
    # the enumeration and its names give the same bases
    for s in C.Slice:
        np.testing.assert_array_equal(C.slice_basis(ctrl, s), C.slice_basis(ctrl, str(s)))
    assert C.slice_basis(ctrl, C.Slice.POSITION).shape == (4, 2) and C.slice_basis(ctrl).shape == (4, 4)
    with pytest.raises(ValueError, match="eps must be > 0"):
        C.exact_map_radius(ctrl, params, t_final=10.0, eps=-1.0)
    with pytest.raises(ValueError, match="linear singular set"):
        C.curved_exact_map_radius(ctrl, params, t_final=10.0, eps=1e-2)


def test_m1_closed_form_12_is_the_distance_to_its_singular_set(rng):
    """(1,2): singular iff the body-frame lateral velocity of P vanishes. Every point of that set is
    at least M1 away, and the minimiser is at exactly M1 with sin(b1) sin(b2) = 0 after Psi^-1."""
    c12 = w.dynamic_linearization("(1,2)")
    g = w.Geometry(L=0.5, e=0.3, delta=0.5)
    params = c12.params(R.figure_eight(size=4.0, omega=0.25, heading_offset=0.5), geometry=g)
    ts = jnp.array([1.0, 3.0, 6.0])
    m1 = np.asarray(C.m1_closed_form(c12, params, ts))
    es = 0.3 * math.sin(0.5)
    for t, m in zip(np.asarray(ts), m1):
        jet = np.asarray(c12.reference_jet(jnp.asarray(t), params)[:2])

        def on_set(dth, vel):  # project a velocity row onto sigma = 0 at heading theta_ref + dth
            th = jet[0, 2] + dth
            n = np.array([np.cos(th), np.sin(th), es])
            return vel - (n @ vel) * n / (n @ n), th

        d = []
        for dth in rng.uniform(-np.pi, np.pi, 2000):
            v, th = on_set(dth, jet[1] + rng.normal(size=3) * 0.3)
            d.append(np.sqrt(dth**2 + np.sum((v - jet[1]) ** 2)))
        assert min(d) >= m - 1e-9
        ths = np.linspace(-np.pi, np.pi, 200001)
        vals = ths**2 + (
            np.cos(jet[0, 2] + ths) * jet[1, 0] + np.sin(jet[0, 2] + ths) * jet[1, 1] + es * jet[1, 2]
        ) ** 2 / (1 + es**2)
        best = ths[np.argmin(vals)]
        np.testing.assert_allclose(np.sqrt(vals.min()), m, rtol=1e-6)
        v, th = on_set(best, jet[1])
        zeta = jnp.asarray(np.stack([jet[0] + np.array([0.0, 0.0, best]), v]))
        X = np.asarray(c12.inverse_psi(zeta, params, 1.0))
        assert abs(np.sin(X[3]) * np.sin(X[4])) < 1e-9


# --- the differentiable exact-map radius (issue 32): value against exact_map_radius, gradient
# against central differences of exact_map_radius itself (an independent computation: no
# envelope theorem, only the grid, the golden section and the bisection)


def _radius_of(ctrl, params, gains, basis, differentiable, t_final=5.0):
    fn = C.differentiable_exact_map_radius if differentiable else lambda *a, **k: C.exact_map_radius(*a, **k).radius
    return fn(ctrl, params._replace(gains=gains), t_final=t_final, eps=0.01, basis=basis)


def _central_differences(f, x, h):
    x = np.asarray(x, float)
    out = np.zeros(x.size)
    for i in range(x.size):
        d = np.zeros(x.size)
        d[i] = h
        out[i] = (float(f(x + d.reshape(x.shape))) - float(f(x - d.reshape(x.shape)))) / (2 * h)
    return out.reshape(x.shape)


@pytest.mark.parametrize("basis", ["full", "position"])
def test_differentiable_exact_map_radius_value_and_gradient(basis):
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    params = ctrl.params(R.paper_62(), poles=1.0, geometry=w.Geometry(e=0.15))
    gains = w.Gains.from_damping([[2.0], [1.6]], [[0.5], [0.6]])  # minimum at t* = 0.84 s (full), 0.79 s
    value, grad = jax.jit(jax.value_and_grad(lambda k: _radius_of(ctrl, params, w.Gains(k), basis, True)))(gains.coeffs)
    exact = float(_radius_of(ctrl, params, gains, basis, False))
    assert abs(float(value) - exact) <= 1e-10 * exact
    fd = _central_differences(
        lambda k: _radius_of(ctrl, params, w.Gains(jnp.asarray(k)), basis, False), gains.coeffs, 1e-6
    )
    assert np.all(np.abs(np.asarray(grad)) > 1e-3)  # every coefficient moves the radius here
    np.testing.assert_allclose(np.asarray(grad), fd, rtol=1e-6, atol=1e-8)


def test_differentiable_exact_map_radius_of_a_gain_schedule():
    """Phi(t*, 0) by RK4 through the schedule: the gradient in the knot values against central
    differences of exact_map_radius (the transition-matrix version)."""
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    params = ctrl.params(R.paper_62(), poles=1.0, geometry=w.Geometry(e=0.15))
    sched = w.GainSchedule.from_damping(
        [0.0, 2.0, 4.0], np.full((3, 2, 1), 1.5) * [[[1.0]], [[1.3]], [[0.8]]], np.full((3, 2, 1), 0.7)
    )
    rad = lambda om: _radius_of(ctrl, params, sched._replace(omega=om), "position", True, t_final=4.0)
    value, grad = jax.value_and_grad(rad)(sched.omega)
    exact = float(_radius_of(ctrl, params, sched, "position", False, t_final=4.0))
    assert abs(float(value) - exact) <= 1e-10 * exact
    # central differences in the middle knot's two omegas (each exact_map_radius of a schedule
    # integrates Phi on the grid: the other four entries would double the test's time)
    for idx in ((1, 0, 0), (1, 1, 0)):
        bump = lambda h: sched._replace(omega=sched.omega.at[idx].add(h))
        fd = (
            float(_radius_of(ctrl, params, bump(1e-6), "position", False, t_final=4.0))
            - float(_radius_of(ctrl, params, bump(-1e-6), "position", False, t_final=4.0))
        ) / 2e-6
        assert abs(fd) > 1e-2
        np.testing.assert_allclose(float(grad[idx]), fd, rtol=1e-5, atol=1e-7)


def test_differentiable_exact_map_radius_refuses_the_curved_set():
    ctrl = w.dynamic_linearization("(1,2)", "velocity")
    params = ctrl.params(R.circle(), poles=1.0)
    with pytest.raises(ValueError, match="curved singular set"):
        C.differentiable_exact_map_radius(ctrl, params, t_final=2.0, eps=0.01)


def test_rollout_statistics_compile_one_program_for_every_batch_size(paper61):
    """Small and large batches share one compiled block program (a block shrunk to a small batch
    was a second program of the same closed loop, ~5 s of compiling per certification)."""
    import importlib

    E = importlib.import_module("wmrjax.certify.empirical")
    ctrl, params, _ = paper61
    errs = 0.05 * np.asarray(jax.random.normal(jax.random.PRNGKey(0), (300, 4)))
    E._rollout_stats.clear_cache()
    few = E.window_distances(ctrl, params, errs[:3], dt=0.02, n_steps=20)
    many = E.window_distances(ctrl, params, errs, dt=0.02, n_steps=20)
    assert E._rollout_stats._cache_size() == 1
    for a, b in zip(few, many):
        np.testing.assert_array_equal(a, b[:3])  # padding changes nothing
    # without the output error (the falsifier's confirmations): a program of its own, the same values
    lean = E.window_distances(ctrl, params, errs[:3], dt=0.02, n_steps=20, shared=False)
    assert E._rollout_stats._cache_size() == 2
    for a, b in zip(lean, few):
        np.testing.assert_array_equal(a, b)
    # a few runs in the confirmations' blocks (the tuner's worst errors): a third program, the same values
    kw = dict(t_final=0.4, initial_errors=errs[:3], dt=0.02)
    confirm = C.min_distance(ctrl, params, block=C.CONFIRM_BLOCK, shared=False, **kw)
    assert E._rollout_stats._cache_size() == 3
    for a, b in zip(confirm, C.min_distance(ctrl, params, **kw)):
        np.testing.assert_array_equal(a, b)
    E.window_distances(ctrl, params, errs[:3], dt=0.02, n_steps=20, block=C.CONFIRM_BLOCK, shared=False)
    assert E._rollout_stats._cache_size() == 3  # min_distance ran the lean program, not a shared one
    for bad, match in ((dict(block=0), "block"), (dict(shared="no"), "shared must be True or False")):
        with pytest.raises(ValueError, match=match):
            C.min_distance(ctrl, params, **kw, **bad)


def _compiled(records) -> list:
    """Names of the programs XLA compiled, from jax.log_compiles's log records."""
    found = [re.search(r"XLA compilation of jit\((\w+)\)", r.getMessage()) for r in records]
    return sorted(m.group(1) for m in found if m)


def test_programs_compiled_ahead_are_the_ones_the_stages_run(paper61, caplog):
    """The estimate's timed block (step_cost) and compile_search (analyse's thread) compile
    exactly the programs the empirical stages, the gradient stage and the confirmations then
    call: none of those calls compiles its program again. An error on analyse's thread reaches
    its caller."""
    F = importlib.import_module("wmrjax.certify.falsify")
    P = importlib.import_module("wmrjax.certify.pipeline")
    ctrl, params, _ = paper61
    errs = 0.05 * np.asarray(jax.random.normal(jax.random.PRNGKey(1), (5, 4)))
    n = F.gradient_starts(8, 4)
    windows = np.tile([[-0.01, 0.41]], (n, 1))
    fine = C.CONFIRM_DT_FACTOR * 0.02
    jax.clear_caches()
    with caplog.at_level(logging.WARNING), jax.log_compiles(True):
        # analyse's estimate first runs a block at dt (compiling the stages' rollout), then the thread
        C.step_cost(ctrl, params, dt=0.02, n_steps=20)
        P._compile_ahead(ctrl, params, t_final=0.4, dt=0.02, falsifier_dt=0.02, n_starts=8, steps=30)
        ahead = _compiled(caplog.records)
        caplog.clear()
        C.min_distance(ctrl, params, t_final=0.4, initial_errors=errs, dt=0.02)  # the empirical radius's runs
        C.min_distance(ctrl, params, t_final=0.4, initial_errors=errs, dt=fine, block=C.CONFIRM_BLOCK, shared=False)
        for basis, k in (("full", 4), ("position", 2)):  # both slices: one program
            starts = np.asarray(jax.random.normal(jax.random.PRNGKey(2), (n, k)))
            kw = dict(t_final=0.4, radius=0.3, starts=starts, dt=0.02, steps=30, windows=windows)
            C.falsify(ctrl, params, basis=basis, **kw)
        after = _compiled(caplog.records)
    assert ahead.count("_rollout_stats") == 2 and ahead.count("_falsify") == 1, ahead
    assert "_rollout_stats" not in after and "_falsify" not in after, after

    def broken():
        raise ZeroDivisionError("on the thread")

    with pytest.raises(ZeroDivisionError, match="on the thread"):
        P._Ahead(broken).join()


def test_compile_ahead_settings_and_bad_arguments(paper61):
    """compile_search compiles falsified_radius's programs only with its defaults: they are the
    same; bad settings are refused before compiling; a block that raises drops the thread's error."""
    F = importlib.import_module("wmrjax.certify.falsify")
    P = importlib.import_module("wmrjax.certify.pipeline")
    ctrl, params, _ = paper61
    ahead, search = inspect.signature(F.compile_search).parameters, inspect.signature(C.falsified_radius).parameters
    for name in ("n_starts", "steps", "learning_rate", "n_windows"):
        assert ahead[name].default == search[name].default, name
    kw = dict(t_final=0.4, dt=0.02)
    for bad, match in (
        (dict(n_starts=0), "n_starts"),
        (dict(steps=1.5), "steps"),
        (dict(learning_rate=-1.0), "learning_rate"),
    ):
        with pytest.raises(ValueError, match=match):
            F.compile_search(ctrl, params, **kw, **bad)
    for bad, match in (
        (dict(block=0, shared=True), "block"),
        (dict(block=16, shared=1), "shared must be True or False"),
    ):
        with pytest.raises(ValueError, match=match):
            importlib.import_module("wmrjax.certify.empirical").compile_window_distances(
                ctrl, params, dt=0.02, n_steps=20, **bad
            )

    def broken():
        raise ZeroDivisionError("on the thread")

    with pytest.raises(KeyError, match="the caller's"):
        with P._Ahead(broken):
            raise KeyError("the caller's")


def test_golden_section_keeps_one_point_per_round():
    """The golden section with one new point per round ends where the two-point version (every
    round both interior points) does, to rounding, with n_golden + 1 evaluations per ray."""
    E = importlib.import_module("wmrjax.certify.empirical")
    rng = np.random.default_rng(3)
    centre = rng.uniform(-1.0, 1.0, 50)
    a, b = centre - rng.uniform(0.1, 2.0, 50), centre + rng.uniform(0.1, 2.0, 50)
    calls = []

    def m_of(rows, r):
        calls.append(len(r))
        x = r - centre[rows.astype(int)]
        return x**2 + 0.1 * x**4 - 0.01 * np.sin(5.0 * x)

    rows = np.arange(50.0)
    got = E._golden_minima(m_of, rows, a, b, 16)
    assert sum(calls) == 50 * 17
    lo, hi = a.copy(), b.copy()
    for _ in range(16):  # the two-point version
        x1, x2 = hi - E.GOLDEN_FRACTION * (hi - lo), lo + E.GOLDEN_FRACTION * (hi - lo)
        left = m_of(rows, x1) <= m_of(rows, x2)
        lo, hi = np.where(left, lo, x1), np.where(left, x2, hi)
    np.testing.assert_allclose(got, 0.5 * (lo + hi), rtol=0, atol=1e-12)
    np.testing.assert_allclose(got, centre, atol=0.05)  # the sine term moves the minimum by ~0.025


def test_exact_map_compiles_one_program_for_every_slice(paper61):
    """The full error space and the position slice go through one compiled exact map (the slice
    basis padded with zero columns), and the padding changes no bit: the position slice's radius,
    time and worst error equal those of the unpadded (n, 2) basis through the same core."""
    X = importlib.import_module("wmrjax.certify.exact_map")
    ctrl, params, _ = paper61
    X._exact_map.clear_cache()
    kw = dict(t_final=1.0, eps=1e-2, n_t=51, refine=8)
    radii = {b: C.exact_map_radius(ctrl, params, basis=b, **kw) for b in ("full", "position")}
    assert X._exact_map._cache_size() == 1
    P = C.slice_basis(ctrl, "position")
    C2 = jnp.eye(4)[jnp.asarray(X.singular_rows(ctrl))]
    ts = jnp.linspace(0.0, 1.0, 51)
    eps = jnp.asarray(1e-2, ts.dtype)
    _, rad, t_star, worst = X._exact_map(ctrl, params, P, C2, eps, ts, None, 8, None)  # compiled unpadded
    pos = radii["position"]
    assert float(pos.radius) == float(rad) and float(pos.argmin) == float(t_star)
    np.testing.assert_array_equal(np.asarray(pos.worst_error), np.asarray(worst))


def test_falsifier_search_traces_its_rollout_once(paper61, monkeypatch):
    """The gradient search's program holds one rollout (the last iterate's value comes from the
    forward-mode program, not from a second trace of the objective)."""
    F = importlib.import_module("wmrjax.certify.falsify")
    ctrl, params, _ = paper61
    traced = []

    def counting(*args):
        traced.append(1)
        return run(*args)

    run = F.run_from_error
    monkeypatch.setattr(F, "run_from_error", counting)
    F._falsify.clear_cache()
    Q = F.square_basis(C.slice_basis(ctrl, "position"))
    us, windows = jnp.eye(4)[:2], jnp.asarray([[0.0, 1.0], [0.0, 1.0]])
    F._falsify.trace(ctrl, params, jnp.asarray(1.0), us, windows, Q, jnp.asarray(1.0), 0.02, 10, 3, 0.1)
    assert len(traced) == 1
    F._falsify.clear_cache()  # the counting trace is not kept for the other tests
