"""The worst-case measurement noise within a bound (issue 54, item 4): the projected gradient
search of :func:`wmrjax.certify.worst_noise` and the real loop's falsifier's stage built on it.

Oracles: the noise's own bound (every component within it); a run of the problem's loop with the
returned noise, made here without the search's program (its distance is the one reported);
random noise within the same bound, uniform and at its corners (the search must beat them:
it is what it is for); and the falsifier without the stage (the stage can only lower its
radius).
"""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from circle_loop import circle_problem

import wmrjax.certify as C
from wmrjax.certify.real_loop import WORST_FRACTIONS
from wmrjax.certify.worst_noise import NOISE_STEPS
from wmrjax.controllers import Space, Task, place

EPS = 0.01
STD = [0.02, 0.02, 0.01]
PLANT = {"control_period": 0.1, "noise_std": STD}


@pytest.fixture(scope="module")
def noisy():
    setting = circle_problem(PLANT, t_final=4.0).setting("certification")
    params = setting.params()
    P = np.asarray(C.slice_basis(setting.ctrl, "full"))
    d = np.random.default_rng(1).normal(size=(3, P.shape[1]))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    errs = (np.array([0.0, 0.5, 0.8])[:, None] * d) @ P.T
    return setting, params, errs, C.worst_noise(setting, params, errs, eps=EPS)


def _distances(setting, params, errs, noises):
    """(N,) min distance of runs of the problem's first plant value from ``errs`` with ``noises``."""
    ctrl = setting.ctrl
    g = params.geometry
    dist = C.SingularDistance(setting.system(), ctrl, type(g)(*(float(v) for v in g)))
    branch = float(ctrl.reference_branch(params))

    def one(e0, noise):
        z0 = place(ctrl, params, e0, Space.OUTPUT, Task.POSTURE, branch)
        tr, _ = setting.run(setting.run_inputs(0)._replace(z0=z0), error_tol=math.inf, noise=noise, save_fn=dist)
        return np.where(bool(tr.diagnostics.failed), 0.0, float(np.min(np.where(tr.valid, tr.state, np.inf))))

    return np.array([one(e, n) for e, n in zip(errs, noises)])


def test_the_worst_noise_is_within_its_bound_and_attains_its_distance(noisy):
    setting, params, errs, w = noisy
    bound = 3.0 * np.asarray(STD)
    assert w.noise.shape == (len(errs), setting.n_steps // setting.steps_per_sample + 1, 3)
    assert np.all(np.abs(w.noise) <= bound)
    assert np.allclose(_distances(setting, params, errs, w.noise), w.distance, rtol=0, atol=1e-12)
    assert np.allclose(_distances(setting, params, errs, np.zeros_like(w.noise)), w.zero_noise, rtol=0, atol=1e-12)
    # measured 2026-12-07: the search moves the distance by 0.039-0.057 (the bound is 0.06 m,
    # 0.03 rad); at e = 0 the law's velocity row is the distance, 1 m/s on the reference
    assert w.zero_noise[0] == pytest.approx(1.0, abs=1e-9)
    assert np.all(w.zero_noise - w.distance > 0.03)


def test_the_search_beats_random_noise_within_the_same_bound(noisy):
    setting, params, errs, w = noisy
    bound = 3.0 * np.asarray(STD)
    key = jax.random.PRNGKey(0)
    n = 16
    uniform = np.asarray(jax.random.uniform(key, (n, *w.noise.shape[1:]), minval=-1.0, maxval=1.0)) * bound
    corners = np.sign(np.asarray(jax.random.normal(jax.random.fold_in(key, 1), uniform.shape))) * bound
    for i, e0 in enumerate(errs):
        rand = _distances(setting, params, np.repeat(e0[None], 2 * n, 0), np.concatenate([uniform, corners]))
        assert w.distance[i] < rand.min()


def test_the_falsifiers_worst_noise_stage_can_only_lower_its_radius():
    setting = circle_problem({"input_limit": [1.3, 0.8], **PLANT}, t_final=4.0).setting("certification")
    params = setting.params()
    em = C.exact_map_radius(setting.ctrl, params, t_final=4.0, eps=EPS, basis="position", n_t=401)
    sizes = dict(eps=EPS, r_max=1.1 * float(em.radius), basis="position", n_directions=2, n_grid=4, n_bisect=3)
    sizes["directions"] = [np.asarray(em.worst_error)]
    with_stage = C.real_loop_falsified_radius(setting, params, **sizes)
    without = C.real_loop_falsified_radius(setting, params, noise_steps=0, **sizes)
    assert without.worst_noise is None and without.radius is not None
    stage = with_stage.worst_noise
    assert stage["noise_multiple"] == 3.0 and stage["steps"] == NOISE_STEPS
    assert np.allclose(stage["radii"], without.radius * WORST_FRACTIONS)
    assert all(d <= z for d, z in zip(stage["distance"], stage["zero_noise"]))
    # measured 2026-12-07: 2.332 (0.95 of the Gaussian search's) against 2.454, from 0.99 of which
    # the noise-free run fails too (the Gaussian realisations had kept it off the singular set)
    assert with_stage.radius < without.radius
    assert with_stage.plant["noise_realisation"] == "worst within 3 noise_std"
    assert with_stage.radius == stage["radius"] and with_stage.distance < EPS
    assert with_stage.rollouts > without.rollouts
    assert "the worst case within 3 noise_std" in with_stage.summary()["noise"]


def test_bad_input_is_refused_before_compiling(noisy):
    setting, params, errs, _ = noisy
    continuous = circle_problem({"input_limit": [1.3, 0.8]}, t_final=4.0).setting("certification")
    with pytest.raises(ValueError, match="needs a problem with a control_period and a noise_std"):
        C.worst_noise(continuous, continuous.params(), errs, eps=EPS)
    with pytest.raises(ValueError, match=r"initial_errors must be \(N, 4\)"):
        C.worst_noise(setting, params, errs[:, :2], eps=EPS)
    with pytest.raises(ValueError, match=r"plant must be \(limit \(N, 2\)"):
        C.worst_noise(setting, params, errs, eps=EPS, plant=(np.ones((3, 2)), np.ones((3, 2)), np.ones(2)))
    with pytest.raises(ValueError, match="steps"):
        C.worst_noise(setting, params, errs, eps=EPS, steps=-1)
    with pytest.raises(ValueError, match="noise_steps"):
        C.real_loop_falsified_radius(setting, params, eps=EPS, r_max=1.0, noise_steps=-1)
    p = setting.run_inputs(0)
    with pytest.raises(ValueError, match=r"noise must be \(41, 3\)"):
        setting.run(p, noise=np.zeros((40, 3)))
    with pytest.raises(ValueError, match="this setting has no control_period"):
        continuous.run(continuous.run_inputs(0), noise=np.zeros((41, 3)))
