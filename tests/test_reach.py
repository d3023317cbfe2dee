"""The digital controller's loop enclosed period by period (issue 54, item 3:
:func:`wmrjax.certify.held_reach_radius`).

Oracles: a SciPy DOP853 integration of the sampled, held, saturated, noisy (2,0) loop written
here (e = 0, as in ``test_certify_real_loop``: the distance to the singular set is |chi1|, the
compensator held between samples and advanced by its held rate at the next one), from initial
errors on the certified ball's sphere at 0.99 of its radius with noise sequences at the corners
of the bound; the library's own sampled loop from the same starts (the two agree); and, for the
clamp's affine rule, sampled values.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
from circle_loop import circle_problem

import wmrjax.certify as C
from wmrjax.certify import affine
from wmrjax.problem import Problem

EPS = 0.01
T_FINAL, PERIOD = 4.0, 0.1
RADIUS, OMEGA = 2.0, 0.5  # the circle reference's defaults: 1 m/s, counter-clockwise
LIMIT = np.array([1.3, 0.8])
NOISE = np.array([0.01, 0.01, 0.005])  # noise_std of x, y [m] and theta [rad]


def _problem(noise: bool = True):
    plant = {"input_limit": LIMIT.tolist(), "control_period": PERIOD}
    if noise:
        plant["noise_std"] = NOISE.tolist()
    return circle_problem(plant, t_final=T_FINAL)


@pytest.fixture(scope="module")
def reach():
    """The full slice's proved radius with the noise within one noise_std (at three this loop's enclosure
    grows past the singular set: the note of issue 54; one compile serves every test here)."""
    setting = _problem().setting("certification")
    params = setting.params()
    P = C.slice_basis(setting.ctrl, "full")
    hr = C.held_reach_radius(setting, params, P, eps=EPS, r_max=1.0, noise_multiple=1.0)
    return setting, params, hr


def _reference(t):
    s, c = np.sin(OMEGA * t), np.cos(OMEGA * t)
    return np.array([RADIUS * c, RADIUS * s]), np.array([-RADIUS * OMEGA * s, RADIUS * OMEGA * c])


def _sampled_run(e0, noise):
    """min_k |chi1| of the sampled loop from the output error ``e0`` (4,) with the noise (K, 3)
    added to the measured (x, y, theta) at sample k. The law at e = 0: P = (x, y), P' = chi1 (-s,
    c), v = P_ref'' - 2 (P' - P_ref') - (P - P_ref); it commands (eta1, eta2) = (chi1, theta') =
    (chi1, -(c, s).v / chi1), clipped by the plant, and its compensator's rate is (-s, c).v."""
    p0, v0 = _reference(0.0)
    p, v = p0 + e0[:2], v0 + e0[2:]
    chi, th = np.linalg.norm(v), np.arctan2(-v[0], v[1])  # P' = chi (-sin th, cos th), chi > 0
    x = np.array([p[0], p[1], th])
    dists = []
    for k in range(round(T_FINAL / PERIOD)):
        t = k * PERIOD
        dists.append(abs(chi))
        xm = x + noise[k]
        s, c = np.sin(xm[2]), np.cos(xm[2])
        pr, vr = _reference(t)
        acc = -(OMEGA**2) * pr
        w = acc - 2.0 * (chi * np.array([-s, c]) - vr) - (xm[:2] - pr)
        eta = np.clip([chi, -(c * w[0] + s * w[1]) / chi], -LIMIT, LIMIT)
        rate = -s * w[0] + c * w[1]

        def plant(_, z, eta=eta):
            return [-eta[0] * np.sin(z[2]), eta[0] * np.cos(z[2]), eta[1]]

        x = scipy.integrate.solve_ivp(plant, (t, t + PERIOD), x, method="DOP853", rtol=1e-11, atol=1e-12).y[:, -1]
        chi = chi + PERIOD * rate
    return min(dists)


def test_the_held_reach_certifies_a_ball_that_scipy_runs_never_leave(reach):
    """Inside the proved ball (0.99 of it, on its sphere, the worst place for a ball) and with
    noise at the corners of its bound, no run of the sampled loop comes below the reach's
    distance bound, which is above eps."""
    setting, params, hr = reach
    assert hr.radius > 0.05 and hr.distance >= EPS and hr.noise_multiple == 1.0
    assert hr.failed_radius is not None and hr.failed_radius > hr.radius
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(12, 4))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    n_k = round(T_FINAL / PERIOD)
    for i, d in enumerate(dirs):
        noise = NOISE * rng.choice([-1.0, 1.0], size=(n_k, 3)) * (i % 3 != 0)
        assert _sampled_run(0.99 * hr.radius * d, noise) >= hr.distance


def test_the_reach_is_tight_on_a_small_ball_and_agrees_with_the_librarys_loop(reach):
    """On a tiny ball without noise the reach's distance bound is within 1 % of the least distance
    the SciPy loop attains (so the bound is not loose where its remainders vanish); the library's
    sampled loop (the real loop's falsifier's runs) gives SciPy's distances."""
    setting, params, _ = reach
    loop = setting.system()
    g = params.geometry
    dist = C.SingularDistance(loop, setting.ctrl, type(g)(*(float(v) for v in g)))
    unc = C.reach.uncertainties(setting, 0.0)[0]  # no noise
    n_k = round(T_FINAL / PERIOD)
    branch = float(setting.ctrl.reference_branch(params))
    radii = jnp.asarray(np.full(C.reach.PER_ROUND, 1e-3))  # the search's program (its count of radii): compiled once
    out = C.reach.reach_radii(loop, params, dist, branch, PERIOD, n_k, jnp.eye(4), radii, unc, EPS, 1e-9)
    out = jax.tree_util.tree_map(lambda v: v[0], out)
    assert bool(out.ok)
    e0 = np.array([1e-3, 0.0, 0.0, 0.0])
    exact = _sampled_run(e0, np.zeros((n_k, 3)))
    assert float(out.distance) <= exact <= 1.01 * float(out.distance)
    errs = np.array([e0, [0.05, -0.03, 0.02, 0.04]])
    quiet = _problem(noise=False).setting("certification")
    lib = C.real_loop_distances(quiet, params, errs)
    ref = [_sampled_run(e, np.zeros((n_k, 3))) for e in errs]
    np.testing.assert_allclose(lib, ref, rtol=2e-3)


def test_the_problem_certificate_of_a_digital_controller_is_the_held_reach(reach):
    setting, params, hr = reach
    exact = {"full": C.exact_map_radius(setting.ctrl, params, t_final=T_FINAL, eps=EPS, basis="full", n_t=201)}
    pc = C.problem_certificate(setting, params, exact, eps=EPS, falsify=False, noise_bound=1.0)
    b = pc["full"]
    assert b["bound_by"] == "held_reach" and b["kind"] == "proved"
    assert b["covers"] == ["nominal", "input_limit", "control_period", "noise"] and b["not_covered"] == []
    # r_max here is the exact map's proved radius, not the fixture's 1.0: the same search below it
    assert 0 < b["radius"] <= exact["full"].lower_bound
    assert b["held_reach"]["noise_bound"] == pytest.approx(NOISE.tolist())


def test_held_reach_radius_refuses_a_continuous_loop():
    setting = Problem.from_dict(
        {
            "controller": {"law": "dynamic", "robot": "(2,0)", "level": "velocity"},
            "reference": {"family": "circle"},
            "plant": {"input_limit": [1.0, 1.0]},
            "initial": {"space": "output", "x": 0.1},
            "simulation": {"t_final": T_FINAL, "dt": 0.02},
        }
    ).setting("certification")
    with pytest.raises(ValueError, match="needs a problem with a control_period"):
        C.held_reach_radius(setting, setting.params(), np.eye(4), eps=EPS, r_max=1.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_clamps_affine_rule_contains_every_sampled_value(seed):
    """max / min of affine values that may cross (a limit that may engage) keep every value, and
    where one side surely wins its affine form is kept exactly."""
    rng = np.random.default_rng(seed)
    c = jnp.asarray(rng.normal(size=3))
    g = jnp.asarray(rng.normal(size=(3, 2)) * 0.5)
    f = lambda v: (jnp.clip(v, -0.4, 0.4), jnp.maximum(v[0], v[1]), jnp.minimum(v[1], 2.0 * v[2]))
    out, ctx = affine.enclose(f, affine.symbols(c, g), n_ball=2)
    d = rng.normal(size=(4000, 2))
    d *= rng.uniform(size=(4000, 1)) ** 0.5 / np.linalg.norm(d, axis=1, keepdims=True)
    pts = np.asarray(c) + d @ np.asarray(g).T
    vals = jax.vmap(f)(jnp.asarray(pts))
    for o, v in zip(out, vals):
        box = affine.to_interval(o, ctx)
        assert np.all(np.asarray(v) >= np.asarray(box.lo) - 1e-12) and np.all(
            np.asarray(v) <= np.asarray(box.hi) + 1e-12
        )
    far, ctx = affine.enclose(lambda v: jnp.maximum(v, -10.0), affine.symbols(c, g), n_ball=2)
    np.testing.assert_array_equal(np.asarray(far.g), np.asarray(g))  # surely above: the form itself
