"""Enclosures and the saturation-free radius (issue 54, item 2).

Oracles: point evaluations of the enclosed functions (every sampled value inside the enclosure);
for the saturation-free radius, the (2,0) law at e = 0 along a circle written here with SciPy's
``expm`` (the nominal command is (chi1, theta') of the state whose output error is
e^{At} s), and a SciPy DOP853 integration of the *saturated* loop from the problem
certificate's worst errors at 0.99 times its radius (:mod:`tests.test_certify_real_loop`'s).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

import wmrjax.certify as C
import wmrjax.references
from tests.test_certify_real_loop import EPS, OMEGA, T_FINAL, _problem, _reference_jet, _saturated_loop
from tests.test_scalarize import _all_prims
from wmrjax.certify import affine, interval, saturation
from wmrjax.certify.interval import Interval
from wmrjax.cli import tune as tune_cli
from wmrjax.tune import certified as tune_certified
from wmrjax.tune import config as tune_config
from wmrjax.tune import loop as tune_loop

LIMIT = np.array([1.3, 0.8])  # binding inside the nominal certificate (test_certify_real_loop)


def _mixed(x, y):
    """Every primitive family the law's programs use: arithmetic, sqrt, sin/cos, atan2, where, dot."""
    r = jnp.sqrt(x * x + y * y + 1.0)
    th = jnp.arctan2(y, x + 3.0)
    s, c = jnp.sin(th), jnp.cos(th)
    m = jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])
    v = m @ jnp.stack([x, y])
    k = jnp.where(r > 1.2, r, 1.2)
    return jnp.stack([v[0] / k, v[1] * jnp.exp(-0.1 * x) + y**3, jnp.abs(x - y)])


def _samples(lo, hi, n, seed=0):
    u = np.random.default_rng(seed).uniform(size=(n, lo.size))
    return lo + u * (hi - lo)


@pytest.mark.parametrize("half", [1e-6, 0.1, 0.6])
def test_interval_enclosure_contains_every_sampled_value(half):
    centre = np.array([0.3, -0.2])
    box = Interval.around(jnp.asarray(centre), half)
    out = jax.jit(lambda lo, hi: interval.enclose(lambda v: _mixed(v[0], v[1]), Interval(lo, hi)))(box.lo, box.hi)
    pts = _samples(np.asarray(box.lo), np.asarray(box.hi), 4000)
    vals = np.asarray(jax.vmap(lambda v: _mixed(v[0], v[1]))(pts))
    assert np.all(vals >= np.asarray(out.lo)) and np.all(vals <= np.asarray(out.hi))
    if half == 1e-6:  # a tiny box: the enclosure is tight to its first order
        assert np.all(np.asarray(out.hi - out.lo) < 1e-4)


@pytest.mark.parametrize("rewrites", ["1", "0"])
def test_an_enclosure_is_of_the_simplified_program(monkeypatch, rewrites):
    """The enclosed program is the simplified one (wmrjax.certify.interval's docstring): a repeated
    sine is enclosed once, and a structural zero divided by a box holding 0 is 0, not the whole
    line; with the rewrites off (WMRJAX_JAXPR_REWRITES=0) the plain program is enclosed."""
    monkeypatch.setenv("WMRJAX_JAXPR_REWRITES", rewrites)
    box, span = Interval(jnp.asarray(0.1), jnp.asarray(0.2)), Interval(jnp.asarray(-1.0), jnp.asarray(1.0))
    size = lambda fn: len(
        _all_prims(jax.make_jaxpr(lambda lo, hi: interval.enclose(fn, Interval(lo, hi)))(box.lo, box.hi).jaxpr)
    )
    once, twice = size(jnp.sin), size(lambda x: jnp.sin(x) + jnp.sin(x))
    out = interval.enclose(lambda x: jnp.sin(x) + jnp.sin(x), box)
    assert float(out.lo) <= 2 * np.sin(0.1) and 2 * np.sin(0.2) <= float(out.hi)
    zero = interval.enclose(lambda y: 0.0 / y, span)
    if rewrites == "1":
        assert twice < 1.5 * once and (float(zero.lo), float(zero.hi)) == (0.0, 0.0)
    else:
        assert twice > 1.9 * once and np.isneginf(float(zero.lo)) and np.isposinf(float(zero.hi))


@pytest.mark.parametrize("rho", [1e-3, 0.2, 0.5])
def test_affine_enclosure_over_a_ball_contains_every_sampled_value(rho):
    centre = jnp.array([0.3, -0.2])
    x = affine.symbols(centre, rho * jnp.eye(2))
    out, ctx = affine.enclose(lambda v: _mixed(v[0], v[1]), x, n_ball=2)
    box = affine.to_interval(out, ctx)
    d = np.random.default_rng(1).normal(size=(4000, 2))
    d *= (rho * np.random.default_rng(2).uniform(size=(4000, 1)) ** 0.5) / np.linalg.norm(d, axis=1, keepdims=True)
    vals = np.asarray(jax.vmap(lambda v: _mixed(v[0], v[1]))(np.asarray(centre) + d))
    assert np.all(vals >= np.asarray(box.lo)) and np.all(vals <= np.asarray(box.hi))


def test_affine_keeps_dependencies_that_intervals_lose():
    f = lambda v: v[0] * v[1] - v[1] * v[0] + jnp.sin(v[0]) - jnp.sin(v[0])  # identically 0
    iv_box = interval.enclose(f, Interval.around(jnp.array([1.0, 2.0]), 0.1))
    out, ctx = affine.enclose(f, affine.symbols(jnp.array([1.0, 2.0]), 0.1 * jnp.eye(2)), n_ball=2)
    af_box = affine.to_interval(out, ctx)
    assert float(iv_box.hi - iv_box.lo) > 0.5  # x*y - y*x over intervals: the product's width twice
    # affine: the first order cancels exactly; what is left is second order (rho^2 = 0.01 per term)
    assert float(af_box.hi - af_box.lo) < 4 * 0.1**2


_BOX_FUNCTIONS = {  # one per signed second-derivative rule, and a product of one symbol with itself
    "square": lambda v: v[0] * v[0] - 2.0 * v[0] * v[1] + v[1] ** 2,
    "sin": lambda v: jnp.sin(1.5 * v[0] + v[1]),
    "cos": lambda v: jnp.cos(v[0] - 2.0 * v[1]),
    "reciprocal": lambda v: 1.0 / (2.0 + v[0] - v[1]) - 1.0 / (-2.0 + v[1]),
    "sqrt": lambda v: jnp.sqrt(2.5 + v[0] + v[1] * v[2]),
    "exp_log": lambda v: jnp.exp(v[0] - v[2]) + jnp.log(2.0 + v[1]) + jnp.log1p(0.5 * v[2]),
    "atan_tanh": lambda v: jnp.arctan(v[0]) + jnp.tanh(v[1] - v[2]),
}


@pytest.mark.parametrize("name", sorted(_BOX_FUNCTIONS))
def test_affine_enclosure_over_box_symbols_contains_every_sampled_value(name):
    """Two ball symbols and two box symbols in [-1, 1] (a time and a noise), sampled at random and
    at the box's corners: the signed Taylor remainders and the box's squares (eps_i^2 in [0, 1])
    move the centre, and the moved enclosure still holds every value."""
    fn = _BOX_FUNCTIONS[name]
    centre = jnp.array([0.2, -0.1, 0.3])
    gen = np.zeros((3, 4))
    gen[:, :2] = 0.3 * np.array([[1.0, 0.2], [0.0, 1.0], [0.5, -0.5]])  # the ball's columns
    gen[:, 2:] = 0.25 * np.array([[1.0, 0.0], [0.6, -1.0], [0.0, 1.0]])  # the boxes'
    out, ctx = affine.enclose(fn, affine.symbols(centre, jnp.asarray(gen)), n_ball=2)
    box = affine.to_interval(out, ctx)
    rng = np.random.default_rng(3)
    ball = rng.normal(size=(6000, 2))
    ball *= rng.uniform(size=(6000, 1)) ** 0.5 / np.linalg.norm(ball, axis=1, keepdims=True)
    ball[:200] /= np.linalg.norm(ball[:200], axis=1, keepdims=True)  # on the sphere
    boxes = rng.uniform(-1.0, 1.0, size=(6000, 2))
    boxes[: 4 * 200] = np.repeat(np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]]), 200, axis=0)  # corners
    eps = np.concatenate([ball, boxes], axis=1)
    vals = np.asarray(jax.vmap(fn)(np.asarray(centre) + eps @ gen.T))
    assert np.all(vals >= float(box.lo)) and np.all(vals <= float(box.hi))
    # not vacuous: within a few times the sampled range's own width
    assert float(box.hi - box.lo) < 4.0 * (vals.max() - vals.min())


def test_a_box_symbols_square_is_enclosed_by_zero_to_one_and_a_convex_functions_tangent_from_one_side():
    """eps^2 over [-1, 1] is exactly [0, 1] (was [-1, 1]: the product of the radii); exp(eps) is
    enclosed with its remainder in [0, e/2] (was +-e/2)."""
    x = affine.symbols(jnp.array([0.0]), jnp.array([[1.0]]))
    sq, ctx = affine.enclose(lambda v: v[0] * v[0], x, n_ball=0)
    b = affine.to_interval(sq, ctx)
    np.testing.assert_allclose([float(b.lo), float(b.hi)], [0.0, 1.0], atol=1e-12)
    ex, ctx = affine.enclose(lambda v: jnp.exp(v[0]), x, n_ball=0)
    b = affine.to_interval(ex, ctx)
    # tangent 1 + eps on [0, 2] plus [0, e/2]: [0, 2 + e/2], against [e^-1, e] the true range
    np.testing.assert_allclose([float(b.lo), float(b.hi)], [0.0, 2.0 + np.e / 2], atol=1e-12)


@pytest.mark.parametrize(
    "fn, centre, radius, expected",
    [
        # 1/x on [1, 3]: chord slope -1/3, 1/x + x/3 is 4/3 at both ends and 2/sqrt(3) at sqrt(3):
        # -x/3 + [2/sqrt 3, 4/3], i.e. [2/sqrt 3 - 1, 1] (true [1/3, 1]; the tangent's: [1/4, 7/4])
        (lambda v: 1.0 / v, 2.0, 1.0, [2.0 / np.sqrt(3.0) - 1.0, 1.0]),
        # sqrt on [1/4, 4]: slope 0.4, sqrt x - 0.4 x is 0.4 at both ends and 0.625 at 1.5625:
        # [0.5, 2.225] (true [0.5, 2]; the tangent's at 2.125 goes below 0: no bound at all)
        (jnp.sqrt, 2.125, 1.875, [0.5, 2.225]),
        # 1/x on [-3, -1]: the mirror of the first
        (lambda v: 1.0 / v, -2.0, 1.0, [-1.0, 1.0 - 2.0 / np.sqrt(3.0)]),
    ],
)
def test_a_convex_function_over_a_wide_range_takes_its_chord_form(fn, centre, radius, expected):
    """Over a wide range the chord's (Chebyshev) form is narrower than the tangent's and is kept
    (closed forms in the cases); over a narrow one the tangent's is, and both enclose."""
    x = affine.symbols(jnp.array([centre]), jnp.array([[radius]]))
    out, ctx = affine.enclose(lambda v: fn(v[0]), x, n_ball=0)
    b = affine.to_interval(out, ctx)
    np.testing.assert_allclose([float(b.lo), float(b.hi)], expected, rtol=1e-12, atol=1e-12)
    # the form itself encloses f at every point, not just its range
    eps = np.linspace(-1.0, 1.0, 2001)
    vals = np.asarray(fn(jnp.asarray(centre + radius * eps)))
    assert np.all(np.abs(vals - (float(out.c) + eps * float(out.g[0]))) <= float(out.e))
    narrow = affine.symbols(jnp.array([centre]), jnp.array([[1e-3 * radius]]))
    out, ctx = affine.enclose(lambda v: fn(v[0]), narrow, n_ball=0)
    b, f0 = affine.to_interval(out, ctx), float(fn(jnp.asarray(centre)))
    d = abs(float(jax.grad(fn)(jnp.asarray(centre)))) * 1e-3 * radius  # first order: the true half-range
    assert float(b.lo) <= f0 - d * (1 - 1e-3) and float(b.hi) >= f0 + d * (1 - 1e-3)
    assert float(b.hi - b.lo) < 2 * d * (1 + 1e-2)


def test_an_angle_across_the_branch_cut_is_kept_whole_for_sin_and_cos_only():
    box = Interval(jnp.array([-1.0, -0.1]), jnp.array([-0.9, 0.1]))  # x < 0, y across 0: the cut
    used = interval.enclose(lambda v: jnp.cos(jnp.arctan2(v[1], v[0])), box)
    raw = interval.enclose(lambda v: jnp.arctan2(v[1], v[0]), box)
    assert float(used.hi) < -0.98  # cos near pi: one unwrapped interval, not [-1, 1]
    assert float(raw.lo) <= -np.pi + 1e-9 and float(raw.hi) >= np.pi - 1e-9  # the value itself jumps


def test_a_primitive_without_a_rule_is_named():
    with pytest.raises(NotImplementedError, match="'erf'"):
        interval.enclose(jax.scipy.special.erf, Interval.around(jnp.array(0.5), 0.1))


def _commands(setting, params, s, ts):
    """(T, D, 2) nominal commands (chi1, theta') of the (2,0) law at e = 0 along the circle, from
    output errors e^{At} s, in closed form: chi1 = |P'| (branch +1), theta' = -(c, s).v / chi1."""
    A = np.asarray(setting.ctrl.error_matrix(params.gains))
    k = np.asarray(params.gains.coeffs)  # (2, 2): per output, the position and the velocity error's gain
    out = []
    for t in ts:
        err = np.atleast_2d(s) @ scipy.linalg.expm(A * t).T  # (D, 4)
        ref = _reference_jet(t)
        P, V = ref[:2] + err[:, :2], ref[2:] + err[:, 2:]
        chi = np.linalg.norm(V, axis=1)
        th = np.arctan2(-V[:, 0], V[:, 1])
        v = -(OMEGA**2) * ref[:2] - k[:, 1] * err[:, 2:] - k[:, 0] * err[:, :2]
        eta2 = -(np.cos(th) * v[:, 0] + np.sin(th) * v[:, 1]) / chi
        del P
        out.append(np.stack([chi, eta2], axis=1))
    return np.stack(out)


@pytest.fixture(scope="module")
def certified():
    """The problem certificate of the circle loop with binding limits (one saturation-free
    computation for every test below)."""
    setting = _problem({"input_limit": LIMIT.tolist()}).setting("certification")
    params = setting.params()
    exact = {
        b: C.exact_map_radius(setting.ctrl, params, t_final=T_FINAL, eps=EPS, basis=b, n_t=601)
        for b in ("full", "position")
    }
    return setting, params, exact, C.problem_certificate(setting, params, exact, eps=EPS, n_directions=8)


def test_the_saturation_free_radius_is_never_exceeded_inside_and_is_attained(certified):
    setting, params, _, pc = certified
    ts = np.linspace(0.0, T_FINAL, 3001)
    rng = np.random.default_rng(3)
    for basis in ("full", "position"):
        sat = pc[basis]["saturation_free"]
        assert sat["kind"] == "proved" and sat["covers"] == ["nominal", "input_limit"]
        assert 0.0 < sat["lower_bound"] <= sat["upper_bound"] < np.inf
        P = np.asarray(C.slice_basis(setting.ctrl, basis))
        dirs = rng.normal(size=(200, P.shape[1])) @ P.T
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        inside = _commands(setting, params, sat["lower_bound"] * dirs, ts)  # on the proved sphere
        assert np.all(np.abs(inside) <= LIMIT)
        worst = np.asarray(sat["worst_error"])
        u = _commands(setting, params, worst, [sat["worst_time"]])[0, 0]  # the attained error
        assert np.any(np.abs(u) > LIMIT)
        assert np.linalg.norm(worst) == pytest.approx(sat["upper_bound"], rel=1e-9)


def test_a_limits_only_plant_is_certified_and_its_worst_errors_stay_eps_away_in_scipy(certified):
    _, _, exact, pc = certified
    assert pc["loop"] == ["input_limit"] and C.real_loop.problem_alarms(pc) == []
    for basis in ("full", "position"):
        b = pc[basis]
        assert b["covers"] == ["nominal", "input_limit"] and b["kind"] == "proved" and b["not_covered"] == []
        assert b["radius"] == pytest.approx(
            min(exact[basis].lower_bound, b["saturation_free"]["lower_bound"]), rel=1e-12
        )
        # the proof holds where saturation fails inside the nominal ball
        assert b["radius"] <= b["falsified_radius"] < b["nominal_radius"] or basis == "full"
        e0 = 0.99 * b["radius"] * np.asarray(b["worst_error"]) / np.linalg.norm(b["worst_error"])
        p0 = _reference_jet(0.0) + e0
        z0 = [p0[0], p0[1], np.arctan2(-p0[2], p0[3]), np.linalg.norm(p0[2:])]
        sol = scipy.integrate.solve_ivp(
            _saturated_loop(LIMIT), (0.0, T_FINAL), z0, method="DOP853", rtol=1e-10, atol=1e-12, dense_output=True
        )
        assert np.abs(sol.sol(np.linspace(0.0, T_FINAL, 20001))[3]).min() >= EPS


def test_a_geometry_range_the_kinematics_ignore_keeps_the_limits_certificate(certified):
    """The (2,0) kinematics have no L and e (wmrjax.robots.kinematics_use_geometry): a +-10 %
    geometry range changes no plant, so the problem certificate is the limits-only one to the last
    bit, covers the range (listed as inert, with its reason), and is not contradicted by the real
    loop's falsifier, which searches the range's three plants as the one loop they run."""
    _, _, exact, limits_only = certified  # the law's exact maps: a plant does not change them
    plant = {"input_limit": LIMIT.tolist(), "geometry_scale": [0.9, 1.0, 1.1]}
    setting = _problem(plant).setting("certification")
    pc = C.problem_certificate(setting, setting.params(), exact, eps=EPS, n_directions=8)
    assert pc["loop"] == ["input_limit", "geometry_scale"] and C.real_loop.problem_alarms(pc) == []
    for basis in ("full", "position"):
        b, want = pc[basis], limits_only[basis]
        assert b["radius"] == want["radius"] and b["bound_by"] == want["bound_by"] == "saturation_free"
        assert b["covers"] == ["nominal", "input_limit", "geometry_scale"] and b["kind"] == "proved"
        assert (
            set(b["inert"]) == {"geometry_scale"} and "(2,0) kinematics do not depend" in b["inert"]["geometry_scale"]
        )
        # the three listed geometries run one loop: searched once, the limits-only search's radius exactly
        assert "mismatch" not in b and b["falsified"]["variants"] == 1
        assert b["falsified_radius"] == want["falsified_radius"] and b["radius"] <= b["falsified_radius"]


def test_binding_limits_fail_inside_the_nominal_certificate_confirmed_by_scipy(certified):
    """(Moved from test_certify_real_loop: the same plant.) The nominal position radius does not
    hold for the saturated loop; the reported failure, integrated independently (DOP853), dips
    below eps."""
    *_, pc = certified
    b = pc["position"]
    assert b["radius"] <= b["falsified_radius"] < b["nominal_radius"]
    (msg,) = [m for m in C.real_loop.plant_warnings(pc) if "position" in m]
    assert "does not hold for this problem's loop (input_limit)" in msg
    # dense output: the dip lies inside one of DOP853's steps, where an event would not see it
    e0 = np.asarray(b["falsified"]["initial_error"])
    p0 = _reference_jet(0.0) + e0
    z0 = [p0[0], p0[1], np.arctan2(-p0[2], p0[3]), np.linalg.norm(p0[2:])]
    sol = scipy.integrate.solve_ivp(
        _saturated_loop(LIMIT), (0.0, T_FINAL), z0, method="DOP853", rtol=1e-10, atol=1e-12, dense_output=True
    )
    chi = np.abs(sol.sol(np.linspace(0.0, T_FINAL, 60001))[3])
    assert chi.min() < EPS
    assert chi.min() == pytest.approx(b["falsified"]["distance"], abs=2e-4)  # the quarter-step run's, to RK4's error


def test_the_command_is_the_same_seen_from_turned_axes():
    from wmrjax.certify import saturation

    setting = _problem({"input_limit": LIMIT.tolist()}).setting("c")
    params = setting.params()
    assert saturation.turns_alike(setting.ctrl, params, T_FINAL)
    jet = setting.ctrl.reference_jet(1.0, params)[:3]
    err = jnp.array([0.1, -0.2, 0.05, 0.3])
    a = saturation.command(setting.ctrl, params, jet, err)
    b = saturation.command(setting.ctrl, params, *saturation.rotated(setting.ctrl, jet, err, 2.5))
    assert np.allclose(a, b, atol=1e-12)
    # the circle's heading crosses +-pi inside the horizon (pi/2 + 0.5 t): boxes there are certified too
    assert float(saturation.reference_heading(setting.ctrl, params, setting.ctrl.reference_jet(4.0, params))) < 0


def test_the_disc_cover_contains_the_disc_and_reaches_as_far_beyond_it_as_stated():
    cover = saturation.disc_cover(4)
    assert not cover.ball and cover.centres.shape == (121, 4) and np.all(cover.axes[:, 2:] == 0)
    rng = np.random.default_rng(0)
    r = np.concatenate([np.sqrt(rng.uniform(size=20000)), np.ones(4000), np.full(2000, 0.15), np.full(2000, 0.6)])
    phi = rng.uniform(0.0, 2 * np.pi, r.size)
    x = np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)
    inv = np.linalg.inv(cover.axes[:, :2, :2])  # (Q, 2, 2): a point's symbols in each piece
    y = np.einsum("qij,pqj->pqi", inv, x[:, None, :] - cover.centres[None, :, :2])
    assert np.all(np.any(np.all(np.abs(y) <= 1 + 1e-12, axis=2), axis=1))  # every point in some piece
    corners = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], float)
    pts = cover.centres[:, None, :2] + np.einsum("qij,cj->qci", cover.axes[:, :2, :2], corners)
    norms = np.linalg.norm(pts, axis=2)
    assert np.all(norms.max(axis=1) <= cover.sizes)
    assert norms.max() == pytest.approx(np.sqrt(1 + np.sin(np.pi / 32) ** 2), rel=1e-12)  # the outer ring's 32
    with pytest.raises(ValueError, match="increasing rings ending at 1"):
        saturation.disc_cover(4, (0.5, 0.9), (8,))
    with pytest.raises(ValueError, match=">= 3 sectors"):
        saturation.disc_cover(4, (0.5, 1.0), (2,))


def test_the_pieces_raise_the_position_slices_proved_radius_to_within_their_gap_of_the_attained(certified, monkeypatch):
    """Over the disc cover the position slice's proved radius is at least the whole disc's (each
    box keeps the larger of two proofs), below both searches' attained bounds (an attained point
    bounds every proof), and the rounds stop within PIECE_GAP of the attained one (the circle's
    whole disc is there already: the limit binds at t = 0). Forced on (no gap, four rounds), the
    cover raises it."""
    setting, params, _, pc = certified
    pieced = pc["position"]["saturation_free"]
    whole = C.saturation_free_radius(setting.ctrl, params, LIMIT, t_final=T_FINAL, basis="position", pieces=False)
    assert whole.lower_bound <= pieced["lower_bound"] <= min(pieced["upper_bound"], whole.upper_bound)
    assert pieced["lower_bound"] >= (1.0 - saturation.PIECE_GAP) * pieced["upper_bound"]
    monkeypatch.setattr(saturation, "PIECE_GAP", 0.0)
    monkeypatch.setattr(saturation, "PIECE_ROUNDS", 4)
    forced = C.saturation_free_radius(setting.ctrl, params, LIMIT, t_final=T_FINAL, basis="position")
    assert whole.lower_bound < forced.lower_bound <= min(forced.upper_bound, whole.upper_bound)
    assert forced.lower_bound == pytest.approx(0.29989, rel=1e-4)  # measured 2026-12-07: 0.2998852 (whole: 0.2990139)


def _sampled_circle(setting):
    """The circle loop's params with its reference replaced by the quintic spline through the
    circle sampled every 0.5 s from -0.25 s (12 knots inside the horizon; the spline is within
    5.4e-6 m of the circle on [0, 6] s, measured on 6001 times)."""
    params = setting.params()
    t = -0.25 + 0.5 * np.arange(15)
    xy = np.stack([_reference_jet(tt)[:2] for tt in t])
    return params._replace(reference=wmrjax.references.from_samples(t, xy))


def test_a_sampled_paths_time_boxes_are_cut_at_its_knots_and_enclose_their_pieces():
    """A box across a spline knot straddles two pieces (the hull of their coefficients: the
    jet's remainder unbounded); the boxes are cut at the knots, each enclosing its own piece's
    polynomial, which holds the reference's jet at every time of the box, the knots included."""
    setting = _problem({"input_limit": LIMIT.tolist()}).setting("c")
    ctrl, params = setting.ctrl, _sampled_circle(setting)
    knots = np.asarray(params.reference.breakpoints())
    t_c, h, breaks = wmrjax.references.time_boxes(params.reference, T_FINAL, 16)
    edges = np.union1d(t_c - h, t_c + h)
    inner = knots[(knots > 0) & (knots < T_FINAL)]
    assert inner.size == 12 and np.all(np.abs(edges[:, None] - inner).min(axis=0) < 1e-12)
    assert t_c.size == 16 + 12 - 4  # the knots at 0.75, 2.25, 3.75, 5.25 s fall on the equal boxes' edges
    j = wmrjax.references.box_pieces(breaks, t_c, h)
    assert np.all(knots[j] <= t_c - h + 1e-12) and np.all(t_c + h <= knots[j + 1] + 1e-12)
    r = ctrl.relative_degree
    c, g, e = (np.asarray(x) for x in saturation.box_jets(ctrl, params, breaks, t_c, h))
    n = g.shape[-1] - 1  # the time symbol is the last
    s = np.linspace(-1.0, 1.0, 41)
    jets = jax.jit(jax.vmap(jax.vmap(lambda t: ctrl.reference_jet(t, params)[: r + 1])))
    pts = np.asarray(jets(jnp.asarray(t_c[:, None] + s[None, :] * h[:, None])))  # (boxes, 41, r + 1, m)
    slack = np.sum(np.abs(g[..., :n]), axis=-1) + e  # the time's own term kept exactly
    lin = c[:, None] + g[:, None, ..., n] * s[None, :, None, None]
    assert np.all(np.isfinite(e)) and np.all(np.abs(pts - lin) <= slack[:, None] + 1e-12)
    with pytest.raises(RuntimeError, match="across a breakpoint"):
        wmrjax.references.box_pieces(breaks, np.array([0.25]), np.array([0.1]))
    # unpinned, a box of 0.2 s across the knot at 0.25 s: its remainder 1.03 (measured 2026-12-07)
    # against at most 0.0044 in the pinned boxes of up to 0.375 s
    across = np.asarray(saturation.jet_boxes(ctrl, params, jnp.array([0.25]), jnp.array([0.1]))[2])
    assert not np.all(np.isfinite(across)) or across.max() > 100 * e.max()


def test_a_controller_periods_boxes_are_pinned_where_they_lie_in_a_piece():
    """The held mismatch bound's boxes are the controller's periods, which a sampled path's knots
    need not bound: a period inside a piece encloses that piece over the whole period (its ends,
    the samples, included); one across a knot the hull of both pieces' polynomials over it (the
    reference itself there: unbounded). Every box holds the reference's jet at 41 times across
    it, the ends included."""
    setting = _problem({"input_limit": LIMIT.tolist()}).setting("c")
    ctrl, params = setting.ctrl, _sampled_circle(setting)
    breaks = wmrjax.references.piece_breaks(params.reference, T_FINAL)
    r, s = ctrl.relative_degree, np.linspace(-1.0, 1.0, 41)
    jets = jax.jit(jax.vmap(jax.vmap(lambda t: ctrl.reference_jet(t, params)[: r + 1])))
    worst = {}
    for period in (0.25, 0.2):  # the knots (0.25 + 0.5 k s) on the first grid, inside 12 periods of the second
        n_boxes = int(np.ceil(T_FINAL / period - 1e-9))
        t_c, h = (np.arange(n_boxes) + 0.5) * period, np.full(n_boxes, 0.5 * period)
        lo, hi = wmrjax.references.box_pieces(breaks, t_c, h, across=True)
        ends = np.stack([t_c - h, t_c + h], axis=1)
        inside = (breaks[None, :] > ends[:, :1] + 1e-9) & (breaks[None, :] < ends[:, 1:] - 1e-9)
        assert np.array_equal(hi - lo, inside.sum(axis=1)) and (hi > lo).sum() == (0 if period == 0.25 else 12)
        assert np.all(breaks[lo] <= ends[:, 0] + 1e-12) and np.all(ends[:, 1] <= breaks[hi + 1] + 1e-12)
        c, g, e = (np.asarray(x) for x in saturation.box_jets(ctrl, params, breaks, t_c, h, across=True))
        n = g.shape[-1] - 1
        pts = np.asarray(jets(jnp.asarray(t_c[:, None] + s[None, :] * h[:, None])))
        slack = np.sum(np.abs(g[..., :n]), axis=-1) + e
        lin = c[:, None] + g[:, None, ..., n] * s[None, :, None, None]
        assert np.all(np.abs(pts - lin) <= slack[:, None] + 1e-12)
        worst[period] = (e[hi == lo].max(), e[hi > lo].max(initial=0.0))
        if period == 0.2:  # the reference itself over a period across a knot
            cut = np.flatnonzero(hi > lo)
            whole = np.asarray(saturation.jet_boxes(ctrl, params, jnp.asarray(t_c[cut]), jnp.asarray(h[cut]))[2])
    # measured 2026-12-08: pinned at most 0.0020 (0.25 s) and 0.0013 (0.2 s), the hulls across a
    # knot at most 0.0013; the reference's own enclosure is unbounded on 11 of those 12 periods
    assert max(worst[0.25][0], *worst[0.2]) < 0.005 and not whole.max() < 100 * worst[0.2][1]
    # the held mismatch bound's own boxes are these
    m = C.Mismatch(LIMIT, (np.ones(2), np.ones(2)), (1.0, 1.0), period=0.2)
    tube = C.deviation._Tube(ctrl, False, params, np.eye(4), C.deviation.check_mismatch(ctrl, params, m), T_FINAL, 1)
    assert tube.boxes == 30 and np.asarray(tube.jets[2]).max() == max(worst[0.2])


def test_a_sampled_circle_has_the_circles_saturation_free_radius():
    """On the spline through the sampled circle (its knots on the 48 boxes' edges: the same
    boxes, each pinned to its piece) the proof is about the circle's and below both loops'
    attained bounds."""
    setting = _problem({"input_limit": LIMIT.tolist()}).setting("c")
    kw = dict(t_final=T_FINAL, basis="full", n_boxes=48, rounds=1, iters=14, n_directions=8, pieces=False)
    circle = C.saturation_free_radius(setting.ctrl, setting.params(), LIMIT, **kw)
    sampled = C.saturation_free_radius(setting.ctrl, _sampled_circle(setting), LIMIT, **kw)
    assert 0.0 < circle.lower_bound <= circle.upper_bound
    # measured 2026-12-07: 0.16589 sampled, 0.16405 the circle (the polynomial's enclosure a
    # little narrower than the sine's); unpinned, boxes across knots straddle two pieces
    assert sampled.lower_bound == pytest.approx(circle.lower_bound, rel=0.03)
    assert sampled.lower_bound <= (1 + 1e-3) * min(sampled.upper_bound, circle.upper_bound)


def test_saturation_free_radius_refuses_bad_input():
    setting = _problem({"input_limit": LIMIT.tolist()}).setting("c")
    params = setting.params()
    with pytest.raises(ValueError, match="input_limit must be > 0"):
        C.saturation_free_radius(setting.ctrl, params, [1.0, 0.0], t_final=1.0)
    with pytest.raises(ValueError, match="2 entries"):
        C.saturation_free_radius(setting.ctrl, params, [1.0, 1.0, 1.0], t_final=1.0)


def test_the_tuners_problem_radii_are_the_problem_certificates(certified):
    """The tuner reports the problem loop's proved radius of its gains (issue 54 item 5: reported,
    not yet kept): the same proof as the certification's, here bound by the saturation-free radius."""
    setting, _, _, pc = certified
    got = tune_certified.problem_radii(setting, setting.gains(), eps=EPS)
    assert got["loop"] == ["input_limit"]
    for basis in ("full", "position"):
        assert got[basis]["bound_by"] == pc[basis]["bound_by"] == "saturation_free"
        assert got[basis]["radius"] == pc[basis]["radius"]
        assert got[basis]["kind"] == "proved" and got[basis]["covers"] == ["nominal", "input_limit"]
    radii = {"initial": {}, "tuned": {}, "problem_certificate": {"initial": got, "tuned": got}}
    lines = tune_cli.radius_change_lines(radii)
    assert any("position slice, the problem's loop: nominal, input_limit, proved" in x and "+0 %" in x for x in lines)


TUNE_STEPS = 4
TUNE = {"steps": TUNE_STEPS, "scenarios": {"train": 3, "validation": 2, "heldout": 2}, "stopping": {"eval_every": 2}}


@pytest.fixture(scope="module")
def kept_run():
    """Tuning the circle loop with binding limits, its position slice's problem certificate
    required at the initial gains' value (``[tune.requirement] radius = "initial"``, loop
    "problem": the default)."""
    setting = _problem({"input_limit": LIMIT.tolist()}).setting("tuning")
    ts = tune_config.read(TUNE)
    family = ts.gain_family(setting)
    req = tune_certified.Requirement("initial", "position", EPS)
    kw = dict(scenarios=ts.scenarios, loss=ts.loss, stopping=ts.stopping, seed=ts.seed, log=lambda *_: None)
    res = tune_loop.tune(setting, family, ts.optimizer.build(TUNE_STEPS), steps=TUNE_STEPS, requirement=req, **kw)
    return setting, family, res


def test_the_tuner_keeps_the_problem_certificate_at_every_accepted_step(certified, kept_run):
    """Issue 54 item 5: the requirement is on the problem certificate of the loop with limits (the
    smaller of the exact map's and the saturation-free radius, both proved), the same number as
    the certification's at the initial gains; every accepted point keeps it (the saturation-free
    radius binds throughout here), and the tuned gains'
    saturation-free sphere is checked by SciPy's expm commands (never over a limit)."""
    _, _, _, pc = certified
    setting, family, res = kept_run
    kept = res.context.kept
    assert kept.radius.kind == "proved" and kept.radius.covers == ("nominal", "input_limit")
    assert kept.radius.not_covered == ()
    assert kept.initial == kept.required == pc["position"]["radius"]  # certify's, to the last bit
    hist = res.history
    assert len(hist) == TUNE_STEPS and min(h["radius"] for h in hist) >= kept.required
    assert {h["radius_bound_by"] for h in hist} == {"saturation_free"}
    # the steps moved the certificate: with the attained point at t = 0 (where the limit binds
    # first here) its gradient keeps it up without halvings (measured 2026-12-07: 0.29901 ->
    # 0.29937 in four steps); the projection's halvings are tested in test_tuning_certified
    assert hist[-1]["radius"] > kept.required
    for raw in (res.raw, res.best_raw):
        params = setting.params(gains=family.gains(jnp.asarray(raw)))
        sat = C.saturation_free_radius(setting.ctrl, params, LIMIT, t_final=T_FINAL, basis="position")
        em = C.exact_map_radius(setting.ctrl, params, t_final=T_FINAL, eps=EPS, basis="position")
        assert min(sat.lower_bound, em.lower_bound) >= kept.required
        P = np.asarray(C.slice_basis(setting.ctrl, "position"))
        d = np.random.default_rng(4).normal(size=(100, 2)) @ P.T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        u = _commands(setting, params, sat.lower_bound * d, np.linspace(0.0, T_FINAL, 1501))
        assert np.all(np.abs(u) <= LIMIT)


def test_the_saturation_free_radius_gradient_matches_finite_differences(kept_run):
    """The tuner's direction on the saturation-free radius (the implicit function theorem at the
    attained point, scaled to the proved bound) against central differences of the proved bound."""
    setting, family, res = kept_run
    raw0 = np.asarray(tune_loop.initial_raw(setting, family), float)
    value, grad = res.context.kept.radius.value_and_grad(jnp.asarray(raw0))
    fd = []
    for k in range(raw0.size):
        e = np.zeros_like(raw0)
        e.flat[k] = 1e-4
        lo = [
            C.saturation_free_radius(
                setting.ctrl,
                setting.params(gains=family.gains(jnp.asarray(raw0 + s * e))),
                LIMIT,
                t_final=T_FINAL,
                basis="position",
            ).lower_bound
            for s in (1.0, -1.0)
        ]
        fd.append((lo[0] - lo[1]) / 2e-4)
    fd = np.asarray(fd)
    assert np.linalg.norm(np.asarray(grad).ravel() - fd) <= 0.05 * np.linalg.norm(fd)
