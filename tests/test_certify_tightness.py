"""Tight certification: one batch for every K2 bound, the falsifier that finds the full-ball
radius on its own, and (1,2)'s exact-map radius with a proved lower bound."""

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax import certify as C
from wmrjax import references as R


def test_verify_all_checks_every_bound_on_one_batch(paper61):
    """verify_all (one simulation, several K2) equals verify called per bound."""
    ctrl, params, _ = paper61
    A = ctrl.error_matrix(params.gains)
    errs = C.sample_sphere(jax.random.PRNGKey(3), 8, 4) * jnp.linspace(0.5, 6.0, 8)[:, None]
    k2s = {"paper": C.k2_paper, "exact_norm": lambda ts: C.k2_exact(A, ts)}
    both = C.verify_all(ctrl, params, t_final=10.0, initial_errors=errs, k2s=k2s, dt=0.02, save_every=10)
    for name, k2 in k2s.items():
        one = C.verify(ctrl, params, t_final=10.0, initial_errors=errs, k2=k2, dt=0.02, save_every=10)
        for a, b in zip(both[name], one):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.asarray(both["paper"].max_ratio).min() < np.asarray(both["exact_norm"].max_ratio).min()


def test_falsifier_finds_the_full_ball_radius_without_the_exact_map(paper61):
    """Section 6.1, full error space: the worst case is at t = 0 (a velocity error cancelling the
    reference's, chi1(0) = eps). From the Lemma 2 radius alone, with each of four PRNG keys, the
    falsifier ends within 1 % of the exact-map radius 4.99 and above it (its failures are
    confirmed), and every certified radius lies below it. Its instantaneous stage descended a
    distance capped at 1, flat beyond the cap: keys 1 to 3 stopped at 7.29, 15.6 and nowhere."""
    ctrl, params, _ = paper61
    cert = C.lemma2(ctrl, params, t_final=3.0, eps=1e-2, n_t=301)
    exact = C.exact_map_radius(ctrl, params, t_final=3.0, eps=1e-2)
    np.testing.assert_allclose(float(exact.radius), 4.99, rtol=1e-9)
    for seed in range(4):
        f = C.falsified_radius(
            ctrl,
            params,
            t_final=3.0,
            eps=1e-2,
            key=jax.random.PRNGKey(seed),
            dt=0.02,
            r_lo=float(cert.exact_norm.radius),
            n_starts=4,
            steps=6,
            n_samples=64,
        )
        assert f.radius is not None and 4.99 - 1e-6 <= f.radius <= 1.01 * 4.99, (seed, f.radius)
        assert f.distance < 1e-2 and abs(float(np.linalg.norm(f.initial_error)) - f.radius) < 1e-9
        assert f.t_failure == 0.0  # found where it happens: at the initial state
        assert set(f.rollouts_by_stage) == {"instantaneous", "sampling", "gradient", "confirmation"}
        assert f.rollouts == sum(v for k, v in f.rollouts_by_stage.items() if k != "instantaneous")
    for c in cert.certificates().values():
        assert float(c.radius) <= f.radius


@pytest.fixture(scope="module")
def curved12():
    c12 = w.dynamic_linearization("(1,2)")
    params = c12.params(R.figure_eight(heading_offset=0.5), geometry=w.Geometry(L=0.5, e=0.3, delta=0.5))
    boxes = importlib.import_module("wmrjax.certify.exact_map")._curved_boxes
    boxes.clear_cache()
    radii = {"full": C.exact_map_radius(c12, params, t_final=3.0, eps=1e-2)}
    # the position slice, on a shorter horizon (fewer boxes, the same block shape)
    assert np.isfinite(float(C.exact_map_radius(c12, params, t_final=0.5, eps=1e-2, basis="position").radius))
    # every round of the branch and bound has its own number of boxes, and its first upper bound and
    # heading reach are boxes of width 0; each slice's basis is padded to square: one program for all
    assert boxes._cache_size() == 1
    return c12, params, radii


def test_curved_exact_map_12_is_bracketed_by_a_proved_lower_bound(curved12):
    """(1,2), full error space: branch and bound over (t, phi). Oracle: the exact linear error map with SciPy's expm
    and the global distance to the curved set. Initial errors of norm 0.999 x the lower bound
    (random, and around the worst direction) stay eps away on a fine time grid; the attained
    worst error comes within eps, and so does the real closed loop from 1.001 x it, while 0.999 x
    it stays away (a fine simulation)."""
    from scipy.linalg import expm

    c12, params, radii = curved12
    A = np.asarray(c12.error_matrix(params.gains))
    r = c12.relative_degree
    ts = np.linspace(0.0, 3.0, 301)
    jets = np.asarray(jax.vmap(lambda t: c12.reference_jet(t, params)[:r].reshape(-1))(jnp.asarray(ts)))
    E = np.stack([expm(A * t) for t in ts])
    dist = jax.jit(jax.vmap(jax.vmap(lambda z: c12.singular_distance(z.reshape(r, c12.m), params))))
    rng = np.random.default_rng(0)
    for b, em in radii.items():
        assert em.lower_bound <= float(em.radius) and em.gap <= 0.05 and em.boxes > 0
        P = np.asarray(C.slice_basis(c12, b))
        wd = np.asarray(em.worst_error) / np.linalg.norm(em.worst_error)
        dirs = rng.normal(size=(64, P.shape[1])) @ P.T
        near = wd[None] + 0.02 * rng.normal(size=(64, P.shape[1])) @ P.T
        dirs = np.concatenate([dirs, near, wd[None]])
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        s = 0.999 * em.lower_bound * dirs
        zeta = jets[None] + np.einsum("tij,nj->nti", E, s)
        assert float(np.min(dist(jnp.asarray(zeta)))) >= 1e-2
        t_star = float(em.argmin)
        z_star = np.asarray(c12.reference_jet(t_star, params)[:r]).reshape(-1) + expm(A * t_star) @ np.asarray(
            em.worst_error
        )
        assert float(c12.singular_distance(jnp.asarray(z_star.reshape(r, c12.m)), params)) <= 1e-2 + 1e-9
        d, sing = C.min_distance(
            c12,
            params,
            t_final=3.0,
            initial_errors=jnp.asarray([0.999 * np.asarray(em.worst_error), 1.001 * np.asarray(em.worst_error)]),
            dt=0.002,
        )
        assert float(d[0]) > 1e-2 and not bool(sing[0]) and (float(d[1]) < 1e-2 or bool(sing[1]))


def test_certifier_programs_call_no_lapack(curved12):
    """The certifier's batched programs hold no LAPACK call. jaxlib's CPU LAPACK kernels split a
    large batch over XLA's thread pool and block a pool thread until it is done; two of them at once
    on a 2-thread pool waited for each other forever (the (1,2) figure-eight certification hung in
    every run in its branch and bound, two batched SVDs of one program)."""
    X = importlib.import_module("wmrjax.certify.exact_map")
    L2 = importlib.import_module("wmrjax.certify.lemma2")  # the package exports a function of that name

    c12, params, _ = curved12
    P = C.slice_basis(c12, "full")
    f64 = jnp.result_type(float)
    one, box = jnp.asarray(0.5, f64), jnp.linspace(0.0, 1.0, 64, dtype=f64)
    programs = {
        # the branch and bound's boxes, its first upper bound and its heading reach: one program
        "curved boxes": X._curved_boxes.lower(c12, params, P, one, one, one, box, 0.1 + 0 * box, box, 0.1 + 0 * box),
        "k2 exact": L2._k2_exact.lower(c12.error_matrix(params.gains), box),
        "k2 transition": jax.jit(lambda g: L2.k2_transition(g, np.linspace(0.0, 1.0, 64))).lower(params.gains),
    }
    for name, lowered in programs.items():
        text = lowered.as_text()
        assert "lapack" not in text.lower(), name
        assert "custom_call" not in text, name
