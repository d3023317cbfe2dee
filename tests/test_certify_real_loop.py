"""The problem's own loop (issue 54): what each radius covers, the exact map's proved lower bound
between its grid's times, and the falsifier on the plant the problem describes.

Oracles: the closed-form error map with SciPy's ``expm`` on a time grid ten times finer than
the map's (the lower bound is never undercut, the attained radius is); the exact map itself (a
plant whose limits never engage is the nominal loop: its falsified radius must meet the map);
and a SciPy DOP853 integration of the saturated (2,0) loop written here (e = 0: the law's
velocity row is chi1 (-sin theta, cos theta), so the distance to the singular set is |chi1|).
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
from circle_loop import circle_problem

import wmrjax.certify as C
import wmrjax.references

EPS = 0.01
T_FINAL = 6.0
RADIUS, OMEGA = 2.0, 0.5  # the circle reference's defaults: 1 m/s, counter-clockwise


def _problem(plant=None):
    return circle_problem(plant, t_final=T_FINAL)


@pytest.fixture(scope="module")
def nominal():
    setting = _problem().setting("certification")
    params = setting.params()
    exact = {
        b: C.exact_map_radius(setting.ctrl, params, t_final=T_FINAL, eps=EPS, basis=b, n_t=601)
        for b in ("full", "position")
    }
    return setting, params, exact


def _reference_jet(t):
    """(P_ref, P_ref') of the circle, flat (4,)."""
    s, c = np.sin(OMEGA * t), np.cos(OMEGA * t)
    return np.array([RADIUS * c, RADIUS * s, -RADIUS * OMEGA * s, RADIUS * OMEGA * c])


def _min_velocity(setting, params, s, ts):
    """(D,) min over ``ts`` of ||velocity row of zeta_ref(t) + expm(A t) s|| (the closed-form
    distance) for the initial errors ``s`` (D, 4)."""
    A = np.asarray(setting.ctrl.error_matrix(params.gains))
    E = np.stack([scipy.linalg.expm(A * t) for t in ts])  # (T, 4, 4)
    jets = np.stack([_reference_jet(t) for t in ts])  # (T, 4)
    zeta = jets[:, None, :] + np.einsum("tij,dj->tdi", E, np.atleast_2d(s))
    return np.linalg.norm(zeta[..., 2:], axis=-1).min(axis=0)


def test_exact_map_lower_bound_is_never_undercut_and_the_radius_is_attained(nominal):
    setting, params, exact = nominal
    ts = np.linspace(0.0, T_FINAL, 6001)  # ten times the map's 601 points
    rng = np.random.default_rng(0)
    for basis, em in exact.items():
        assert em.lower_bound is not None and em.lower_bound <= float(em.radius)
        assert em.gap < 3e-3  # the time boxes are halved until within rtol = 2e-3
        P = np.asarray(C.slice_basis(setting.ctrl, basis))
        worst = np.asarray(em.worst_error) / np.linalg.norm(em.worst_error)
        dirs = np.concatenate([worst[None], rng.normal(size=(40, P.shape[1])) @ P.T])
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        # inside the proved ball: eps away at every time of the fine grid
        assert np.all(_min_velocity(setting, params, 0.999 * em.lower_bound * dirs, ts) >= EPS)
        # the worst error just outside the attained radius comes within eps (near its time)
        near = np.linspace(max(0.0, float(em.argmin) - 0.05), min(T_FINAL, float(em.argmin) + 0.05), 401)
        assert _min_velocity(setting, params, 1.001 * np.asarray(em.worst_error), near)[0] < EPS


def test_the_reference_acceleration_bound_holds_everywhere_and_is_tight(nominal):
    """The exact map's G (accel_bound) against the circle's closed form: the output point is the
    centre (e = 0), zeta = (p, p'), so ||zeta''|| = R omega^2 sqrt(1 + omega^2) at every t; on the
    spline through the circle sampled every 0.5 s (boxes cut at the knots), against 20001 sampled
    times. Before 2026-12-07 G was twice a 4001-point grid's maximum (an estimate)."""
    setting, params, _ = nominal
    exact = RADIUS * OMEGA**2 * np.sqrt(1.0 + OMEGA**2)
    g = C.exact_map.accel_bound(setting.ctrl, params, T_FINAL)
    assert exact <= g <= 1.01 * exact  # measured 2026-12-07: 0.55943 against 0.55902
    t = -0.25 + 0.5 * np.arange(15)
    ref = wmrjax.references.from_samples(t, np.stack([_reference_jet(tt)[:2] for tt in t]))
    sampled = params._replace(reference=ref)
    r = setting.ctrl.relative_degree
    zeta = lambda tt: setting.ctrl.reference_jet(tt, sampled)[:r].reshape(-1)
    acc = jax.jit(jax.vmap(lambda tt: jnp.linalg.norm(jax.jacfwd(jax.jacfwd(zeta))(tt))))
    top = float(np.max(acc(jnp.linspace(0.0, T_FINAL, 20001))))
    g_s = C.exact_map.accel_bound(setting.ctrl, sampled, T_FINAL)
    assert top <= g_s <= 1.05 * top and top == pytest.approx(exact, rel=1e-3)


def test_without_a_plant_the_problem_certificate_is_the_exact_maps_proved_bound(nominal):
    setting, params, exact = nominal
    assert C.plant_features(setting) == ()
    pc = C.problem_certificate(setting, params, exact, eps=EPS)
    assert pc["loop"] == ["nominal"]
    for basis, em in exact.items():
        b = pc[basis]
        assert b["radius"] == pytest.approx(em.lower_bound, rel=1e-12)
        assert b["covers"] == ["nominal"] and b["kind"] == "proved" and b["not_covered"] == []
        assert np.allclose(b["worst_error"], np.asarray(em.worst_error))


def test_a_geometry_range_alone_on_a_20_robot_is_certified_by_the_exact_map(nominal):
    """(2,0) kinematics have no L and e: a geometry range alone leaves the nominal loop, so the
    problem certificate is the exact map's proved bound, covering the range (its reason in
    ``inert``); beside an input scale (which acts) the geometry range is still the inert one."""
    _, params, exact = nominal
    setting = _problem({"geometry_scale": [0.8, 1.2]}).setting("certification")
    assert set(C.inert_features(setting)) == {C.Feature.GEOMETRY_SCALE}
    pc = C.problem_certificate(setting, params, exact, eps=EPS, falsify=False)
    for basis, em in exact.items():
        b = pc[basis]
        assert b["radius"] == em.lower_bound and b["kind"] == "proved" and b["bound_by"] == "exact_map"
        assert (
            b["covers"] == ["nominal", "geometry_scale"] and b["not_covered"] == [] and "geometry_scale" in b["inert"]
        )
        assert b["saturation_free"] is None and "mismatch" not in b
    acting = _problem({"geometry_scale": [0.8, 1.2], "input_scale": [0.9, 1.1]}).setting("c")
    assert set(C.inert_features(acting)) == {C.Feature.GEOMETRY_SCALE}
    assert C.inert_features(_problem({"input_scale": [0.9, 1.1]}).setting("c")) == {}


def test_plant_features_name_every_section_key():
    assert C.plant_features(_problem({"input_limit": [1.5, 1.0]}).setting("c")) == (C.Feature.INPUT_LIMIT,)
    full = {
        "input_limit": [1.5, 1.0],
        "control_period": 0.1,
        "input_scale": [0.95, 1.05],
        "geometry_scale": [1.0, 1.1],
        "noise_std": [0.01],
    }
    setting = _problem(full).setting("c")
    assert [str(f) for f in C.plant_features(setting)] == [
        "input_limit",
        "control_period",
        "input_scale",
        "geometry_scale",
        "noise",
    ]


def test_a_plant_whose_limits_never_engage_is_falsified_at_the_exact_maps_radius(nominal):
    _, _, exact = nominal
    setting = _problem({"input_limit": [100.0, 100.0]}).setting("certification")
    params = setting.params()
    for basis, em in exact.items():
        f = C.real_loop_falsified_radius(
            setting,
            params,
            eps=EPS,
            r_max=1.1 * float(em.radius),
            basis=basis,
            directions=[np.asarray(em.worst_error)],
            n_directions=4,  # the worst error's ray is the one that fails at the map's radius
        )
        # a confirmed failure can never be inside the proved ball; the map is tight, so it is found near it
        assert em.lower_bound <= f.radius <= 1.02 * float(em.radius)
        assert f.distance < EPS and f.plant["input_limit"] == [100.0, 100.0]


def _saturated_loop(limit):
    """The (2,0) law at e = 0 (P'' = v, chi1' = (-s, c).v, theta' = -(c, s).v / chi1) around a
    plant that clips (eta1, eta2) = (chi1, theta') to +-limit: state (x, y, theta, chi1)."""

    def field(t, z):
        x, y, th, chi = z
        s, c = np.sin(th), np.cos(th)
        ref = _reference_jet(t)
        acc = -(OMEGA**2) * ref[:2]
        v = acc - 2.0 * (chi * np.array([-s, c]) - ref[2:]) - (np.array([x, y]) - ref[:2])  # poles -1, -1
        eta1, eta2 = np.clip([chi, -(c * v[0] + s * v[1]) / chi], -limit, limit)
        return [-eta1 * s, eta1 * c, eta2, -s * v[0] + c * v[1]]

    return field


def test_real_loop_distances_refuses_bad_input_before_running():
    setting = _problem({"input_limit": [1.3, 0.8]}).setting("c")
    params = setting.params()
    with pytest.raises(ValueError, match=r"initial_errors must be \(N, 4\)"):
        C.real_loop_distances(setting, params, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="plant must index the setting's 1 plant values, got 1"):
        C.real_loop_distances(setting, params, np.zeros((1, 4)), plant=1)


def test_the_tuner_says_its_radii_are_the_nominal_loops():
    from wmrjax.tune import certified

    assert certified.problem_loop(_problem().setting("c")) == {
        "features": [],
        "covered": True,
        "note": "the problem's loop is the nominal one",
    }
    setting = _problem({"input_limit": [1.3, 0.8], "control_period": 0.1}).setting("c")
    loop = certified.problem_loop(setting)
    assert loop["features"] == ["input_limit", "control_period"] and not loop["covered"]
    assert "exact-map radii here are the nominal continuous loop's" in loop["note"]
    # the problem's loop of a digital controller is kept by the held reach, which covers it all
    note = certified.problem_loop(setting, certified.Requirement(1.0, "full", EPS, "problem"))["note"]
    assert note.endswith("the requirement keeps a radius of the loop with nominal, input_limit, control_period")
    note = certified.problem_loop(setting, certified.Requirement(1.0, "full", EPS, "nominal"))["note"]
    assert (
        "the requirement keeps a radius of the loop with nominal; no proof the tuner keeps covers this problem's "
        "input_limit, control_period" in note
    )


def test_the_plant_table_runs_each_feature_alone_then_together(tmp_path):
    from wmrjax.certify.plant_table import FACTORS, PlantTableReport, loops, run

    plant = {"input_limit": [2.0, 1.5], "control_period": 0.05, "noise_std": [0.01]}
    assert [label for label, _ in loops(plant)] == [
        "nominal",
        "input_limit",
        "control_period",
        "input_limit + control_period",
        "whole [plant]",
    ]
    assert loops({"input_limit": [2.0, 1.5]}) == [("nominal", None), ("input_limit", {"input_limit": [2.0, 1.5]})]

    # the table of a problem: the nominal row inside the proved ball never comes within eps (the
    # certificate), and every row is the real loop's own distances from the scaled worst error
    problem = _problem({"input_limit": [1.2, 1.2], "control_period": 0.1}).with_values({"certify.eps": EPS})
    r = run(tmp_path, problem, "position", progress=lambda m: None)
    assert isinstance(r, PlantTableReport) and [row["loop"] for row in r.rows] == [
        "nominal",
        "input_limit",
        "control_period",
        "input_limit + control_period",
    ]
    assert min(r.rows[0]["min_distance"]) >= EPS and r.summary()["nominal_radius_kind"] == "proved"
    assert json.loads(json.dumps(r.summary())) == json.loads((tmp_path / "summary.json").read_text())
    s = problem.with_values({"plant": {"control_period": 0.1}}).setting("certification")
    errs = np.array([f * np.asarray(r.worst_error) for f in FACTORS])
    np.testing.assert_array_equal(r.rows[2]["min_distance"], C.real_loop_distances(s, s.params(), errs, plant=0))
    assert r.markdown().count("\n") == 1 + len(r.rows)
